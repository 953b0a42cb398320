"""mpm_monitor: model-plant mismatch detection, location and repair for MPC loops.

The core (this package minus :mod:`mpm_monitor.nodes`) is plain numpy/scipy and never imports
rclpy; the ROS 2 nodes in :mod:`mpm_monitor.nodes` are thin adapters around it.
"""

__version__ = "0.1.0"
