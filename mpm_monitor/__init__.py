"""mpm_monitor: model-plant mismatch detection, location and repair for MPC loops.

Layers, from the bottom up (``docs/architecture.md``):

- :mod:`mpm_monitor.core`: the mathematics in numpy/scipy (model, simulation, signals, the S_Delta
  row test, the Delta element test, the repair); it imports nothing else of the package;
- :mod:`mpm_monitor.sim`: plant, MPC, excitation, closed loop and the paper's cases;
- :mod:`mpm_monitor.io`: the model file, the CSV log, bags, reports and plots;
- :mod:`mpm_monitor.monitor`: the live monitor's window, schedule and statuses, without rclpy;
- :mod:`mpm_monitor.nodes`: the ROS 2 nodes;
- :mod:`mpm_monitor.apps`: the command line, the demo and the paper reproduction.

Importing the package has no side effects.  The entry points call :func:`limit_blas_threads`.
"""

import os as _os

__version__ = "0.1.0"

#: Environment variables that set the BLAS thread count when numpy loads.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads() -> None:
    """Ask for one BLAS thread, unless the user chose otherwise.

    The least-squares problems here are tall and thin (thousands of rows, tens to hundreds of
    columns), where a multi-threaded BLAS spends more time synchronising than computing: on the
    2-core machines this was measured on, case 3.3 took 71 s with the default OpenBLAS threads and
    2 s with one.  This takes effect for numpy loaded after the call, in this process or in a child
    process started after it (the monitor's analysis process); the command line and the nodes call it
    first thing.
    """
    for var in BLAS_THREAD_VARIABLES:
        _os.environ.setdefault(var, "1")
