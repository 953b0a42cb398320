"""mpm_monitor: model-plant mismatch detection, location and repair for MPC loops.

The core (this package minus :mod:`mpm_monitor.nodes`) is plain numpy/scipy and never imports
rclpy; the ROS 2 nodes in :mod:`mpm_monitor.nodes` are thin adapters around it.

The least-squares problems here are tall and thin (thousands of rows, tens to hundreds of
columns), where a multi-threaded BLAS spends more time synchronising than computing: on the 2-core
machines this was measured on, case 3.3 took 71 s with the default OpenBLAS threads and 2 s with
one.  Unless the user has chosen otherwise, BLAS is therefore limited to one thread; this takes
effect when ``mpm_monitor`` is imported before numpy (the CLI, the nodes and the tests do).
"""

import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
