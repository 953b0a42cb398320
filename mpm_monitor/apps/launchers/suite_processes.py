"""Start the plant, setpoint, MPC and monitor nodes as four separate processes.

Examples (in a colcon workspace; from the repository, ``python launch_scripts/suite_processes.py``
instead of ``ros2 run mpm_monitor suite_processes``)::

    ros2 run mpm_monitor suite_processes --case 3.2
    ros2 run mpm_monitor suite_processes --case 3.2 --samples 3000 --domain-id 42 --localhost \\
        --namespace /unit1 -p monitor.alpha:=0.05
    ros2 run mpm_monitor suite_processes --params my_suite.yaml --wall-clock

Each node reads the params file (default ``config/case_<case>.yaml``) plus the ``-p node.param:=value``
overrides.  In simulated time (default) the plant owns the clock and runs lock-step; it starts once
the MPC and the monitor listen on ``output`` (``min_subscribers: 2``) and a settling delay passed.
A plant leaving after ``--samples`` waits until its readers acknowledged every vector
(``exit_ack_timeout``): the monitor, which may run behind, gets the last ones too.
With ``--wall-clock`` the plant advances every sample time of the wall clock, the setpoint node runs
on a timer and the MPC and monitor hold the latest setpoint.

Ctrl-C (SIGINT) or SIGTERM stops every process.  With ``--samples`` the plant stops after that many
samples; the other nodes keep running (the monitor still publishes its last result) until
``--linger`` seconds later, or until stopped.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ... import limit_blas_threads
from ..cli import DEMO_CASES
from .common import NODES, case_params_file, load_params_file, merge, node_command, parse_overrides, ros_env


def build_parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", choices=DEMO_CASES, default="3.2")
    p.add_argument("--params", default=None,
                   help="params file for the four nodes "
                        "(default config/case_<case>.yaml; installed, in share/mpm_monitor/config)")
    p.add_argument("--samples", type=int, default=None, help="plant.max_samples (0 = run until stopped)")
    p.add_argument("--namespace", default="", help="namespace of the four nodes and their relative topics")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID of the processes")
    p.add_argument("--localhost", action="store_true", help="ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")
    p.add_argument("--wall-clock", action="store_true", help="run in wall-clock time instead of lock-step")
    p.add_argument("--linger", type=float, default=None,
                   help="seconds to keep the other nodes after the plant's last sample (default: until stopped)")
    p.add_argument("-p", dest="overrides", action="append", default=[], metavar="NODE.PARAM:=VALUE")
    return p


def suite_params(args) -> dict:
    """The parameters of each node after the params file and the overrides."""
    params = load_params_file(args.params or case_params_file(args.case))
    extra = {}
    if args.samples is not None:
        extra["plant"] = {"max_samples": args.samples, "exit_when_done": args.samples > 0}
    if args.wall_clock:
        extra = merge(extra, {"plant": {"lock_step": False, "publish_clock": False},
                              "setpoint": {"trigger": "timer"}, "mpc": {"hold_setpoint": True},
                              "monitor": {"hold_setpoint": True}})
    else:
        extra = merge(extra, {"plant": {"min_subscribers": 2, "start_delay": 1.0}})
    if args.namespace:
        # keep the clock and the diagnostics inside the namespace: one suite per namespace
        extra = merge(extra, {"plant": {"clock_topic": "clock"}, "setpoint": {"clock_topic": "clock"},
                              "monitor": {"diagnostics_topic": "diagnostics"}})
    return merge(merge(params, extra), parse_overrides(args.overrides))


def main(argv=None) -> int:
    """Console script ``suite_processes``."""
    limit_blas_threads()
    args = build_parser().parse_args(argv)
    params = suite_params(args)
    env = ros_env(args.domain_id, args.localhost)
    procs = []
    stopping = False

    def stop(signum=None, frame=None):
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    with tempfile.TemporaryDirectory(prefix="mpm_suite_") as tmp:
        import yaml

        for node in NODES:
            f = Path(tmp) / f"{node}.yaml"
            f.write_text(yaml.safe_dump({f"/**/{node}": {"ros__parameters": params.get(node, {})}}), encoding="utf-8")
            procs.append((node, subprocess.Popen(node_command(node, f, args.namespace), env=env)))
        plant = procs[0][1]
        plant_done_at = None
        rc = 0
        while not stopping:
            time.sleep(0.1)
            if plant.poll() is not None and plant_done_at is None:
                plant_done_at = time.monotonic()
            for name, p in procs[1:]:
                if p.poll() is not None:
                    print(f"suite: {name} exited with {p.returncode}", file=sys.stderr)
                    rc = rc or p.returncode or 1
                    stopping = True
            if plant_done_at is not None and args.linger is not None and time.monotonic() - plant_done_at > args.linger:
                break
        for _, p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for _, p in procs:
            try:
                p.wait(10.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if plant.returncode not in (0, None, -signal.SIGINT):
            rc = rc or plant.returncode
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
