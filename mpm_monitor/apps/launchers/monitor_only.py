"""Run the monitor alone against an existing control stack (any publisher of the contract topics).

Examples (in a colcon workspace; from the repository, ``python launch_scripts/monitor_only.py`` instead
of ``ros2 run mpm_monitor monitor_only``)::

    ros2 run mpm_monitor monitor_only --model unit1_model.yaml
    ros2 run mpm_monitor monitor_only --model unit1_model.yaml --namespace /unit1 \\
        --setpoint-topic /unit1/mpc/setpoints --input-topic /unit1/mpc/mv --output-topic /unit1/plant/cv \\
        --hold-setpoint -p window_samples:=5000 -p analysis_period:=250

The stack must publish ``sensor_msgs/JointState`` vectors (``name`` = the model's channel names,
``header.stamp`` = the sample time) for the setpoints, the plant inputs and the measured outputs (and,
for a model with measured disturbances, those on ``--disturbance-topic``).
Use ``--hold-setpoint`` when the setpoints are published only when they change.  Parameters come
from ``config/monitor.yaml`` (or ``--params``) and ``-p name:=value``; if the stack runs in simulated
time, add ``-p use_sim_time:=true`` so that the diagnostics are stamped with it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ... import limit_blas_threads
from .common import config_dir


def ros_args(args) -> list:
    """The ``--ros-args`` of the monitor node for the command-line options."""
    out = ["--ros-args", "-r", "__node:=monitor", "--params-file", str(args.params or config_dir() / "monitor.yaml"),
           "-p", f"model_file:={Path(args.model).resolve()}"]
    if args.namespace:
        out += ["-r", f"__ns:={args.namespace if args.namespace.startswith('/') else '/' + args.namespace}"]
    for opt, param in (("setpoint_topic", "setpoint_topic"), ("input_topic", "input_topic"),
                       ("output_topic", "output_topic"), ("disturbance_topic", "disturbance_topic"),
                       ("diagnostics_topic", "diagnostics_topic")):
        value = getattr(args, opt)
        if value:
            out += ["-p", f"{param}:={value}"]
    if args.hold_setpoint:
        out += ["-p", "hold_setpoint:=true"]
    for item in args.overrides:
        out += ["-p", item]
    return out


def main(argv=None) -> int:
    """Console script ``monitor_only``."""
    limit_blas_threads()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True, help="the controller's model file (docs/interfaces.md, Model file)")
    p.add_argument("--params", default=None,
                   help="params file (default config/monitor.yaml; installed, share/mpm_monitor/config/monitor.yaml)")
    p.add_argument("--namespace", default="", help="namespace of the monitor (relative topics follow it)")
    p.add_argument("--setpoint-topic", dest="setpoint_topic", default=None)
    p.add_argument("--input-topic", dest="input_topic", default=None)
    p.add_argument("--output-topic", dest="output_topic", default=None)
    p.add_argument("--disturbance-topic", dest="disturbance_topic", default=None,
                   help="the measured disturbances' topic (a model with measured disturbances; default disturbance)")
    p.add_argument("--diagnostics-topic", dest="diagnostics_topic", default=None)
    p.add_argument("--hold-setpoint", action="store_true", help="setpoints are published only when they change")
    p.add_argument("-p", dest="overrides", action="append", default=[], metavar="NAME:=VALUE")
    args = p.parse_args(argv)
    from ...nodes.monitor_node import main as monitor_main

    return monitor_main(ros_args(args))


if __name__ == "__main__":
    raise SystemExit(main())
