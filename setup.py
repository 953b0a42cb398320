"""Installs mpm_monitor under colcon (ament_python) and under ``pip install -e .``.

Under colcon, ``setup.cfg`` puts the console scripts (the nodes, the launchers, ``mpm_analyze``) in
``lib/mpm_monitor/``, where ``ros2 run`` finds them; ``share/mpm_monitor/`` gets ``package.xml`` and the
params files ``config/*.yaml`` (the launchers' defaults).  The nodes' console scripts start in
:mod:`mpm_monitor.nodes.entry`, which imports the node (rclpy, numpy) only once it can end a Ctrl-C
quietly.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "mpm_monitor"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
    ],
    install_requires=["setuptools", "numpy", "scipy", "PyYAML"],
    zip_safe=True,
    maintainer="mpm_monitor developers",
    maintainer_email="mpm-monitor@example.com",
    description="Model-plant mismatch monitor for MPC loops (ROS 2 Jazzy, Python).",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "mpm_analyze = mpm_monitor.apps.cli:main_analyze",
            "plant_node = mpm_monitor.nodes.entry:plant_node",
            "mpc_node = mpm_monitor.nodes.entry:mpc_node",
            "setpoint_node = mpm_monitor.nodes.entry:setpoint_node",
            "monitor_node = mpm_monitor.nodes.entry:monitor_node",
            "recorder_node = mpm_monitor.nodes.entry:recorder_node",
            "replay_node = mpm_monitor.nodes.entry:replay_node",
            "suite_inprocess = mpm_monitor.apps.launchers.suite_inprocess:main",
            "suite_processes = mpm_monitor.apps.launchers.suite_processes:main",
            "monitor_only = mpm_monitor.apps.launchers.monitor_only:main",
        ],
    },
)
