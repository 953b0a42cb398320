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

Ctrl-C (SIGINT) or SIGTERM stops every process: the launcher sends each node still running a SIGINT,
waits up to 10 s for it (then kills it, with one line ``suite: <node> did not stop within 10 s; killed``)
and ends.  With ``--samples`` the plant stops after that many samples; the other nodes keep running (the
monitor still publishes its last result) until ``--linger`` seconds later, or until stopped.

Exit codes (:func:`exit_code`):

- 0: the plant ended with 0 and ``--linger`` seconds passed;
- 130 after a SIGINT (Ctrl-C), 143 after a SIGTERM (the shell's 128 + the signal's number), whatever
  code each node then ends with (a Ctrl-C to the process group reaches the nodes too, and each ends
  as it can: 0, 130 while it starts, or killed);
- the code of the first node that ended on its own, as one line ``suite: <node> exited with <code>``
  says: any node but the plant stops the suite when it ends (its 0 gives 1: it should not end), the plant
  counts when its code is not 0 (it diverged: 1); a node a signal ended gives 128 + its number.  This
  holds when a Ctrl-C comes after it too.
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


#: Seconds the launcher waits for each node after it sent the node a SIGINT, before it kills it.
STOP_TIMEOUT = 10.0


def exit_code(failed, signum=None) -> int:
    """The launcher's exit code from the nodes that ended on their own and the signal that stopped it.

    Parameters
    ----------
    failed : sequence of (str, int)
        The nodes that ended on their own while the suite ran, before any signal reached the launcher, as
        ``(name, returncode)`` in the order the launcher saw them (:class:`subprocess.Popen`'s code: -N when
        signal N ended the node).  A node the launcher stopped is not among them.
    signum : int, optional
        The first SIGINT or SIGTERM the launcher received while the suite ran; None when none did.

    Returns
    -------
    int
        The first failed node's code (1 for its 0, 128 + N for its -N), else 128 + ``signum`` (130 after
        SIGINT, 143 after SIGTERM), else 0.
    """
    if failed:
        code = failed[0][1]
        return 128 - code if code < 0 else code or 1
    if signum is not None:
        return 128 + int(signum)
    return 0


def main(argv=None) -> int:
    """Console script ``suite_processes``.

    Parameters
    ----------
    argv : list of str, optional
        The command-line options (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit code, :func:`exit_code` (0, 130 after SIGINT, 143 after SIGTERM, or a failed node's code).
    """
    received = []

    def stop(signum, frame=None):
        received.append(signum)

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return run_suite(argv, received)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_suite(argv, received: list) -> int:
    """Start the four node processes, wait until a signal arrives in ``received`` (the launcher's SIGINT and
    SIGTERM handlers append to it), a node fails or the plant's ``--linger`` is over, stop them and return the
    exit code (:func:`exit_code`)."""
    limit_blas_threads()
    args = build_parser().parse_args(argv)
    params = suite_params(args)
    env = ros_env(args.domain_id, args.localhost)
    procs = []
    failed = []
    with tempfile.TemporaryDirectory(prefix="mpm_suite_") as tmp:
        import yaml

        for node in NODES:
            if received:
                break
            f = Path(tmp) / f"{node}.yaml"
            f.write_text(yaml.safe_dump({f"/**/{node}": {"ros__parameters": params.get(node, {})}}), encoding="utf-8")
            procs.append((node, subprocess.Popen(node_command(node, f, args.namespace), env=env)))
        plant_done_at = None
        while procs and not received and not any(name != "plant" for name, _ in failed):
            time.sleep(0.1)
            ended = [(name, p.returncode) for name, p in procs
                     if p.poll() is not None and not (name == "plant" and plant_done_at is not None)]
            if received:     # checked after the polls: what ended now may have ended by the same Ctrl-C
                break
            for name, code in ended:
                if name == "plant":
                    plant_done_at = time.monotonic()
                if name != "plant" or code != 0:
                    print(f"suite: {name} exited with {code}", file=sys.stderr)
                    failed.append((name, code))
            if plant_done_at is not None and args.linger is not None and time.monotonic() - plant_done_at > args.linger:
                break
        signum = received[0] if received else None
        for _, p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for name, p in procs:
            try:
                p.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                print(f"suite: {name} did not stop within {STOP_TIMEOUT:g} s; killed", file=sys.stderr)
                p.kill()
                p.wait()
    return exit_code(failed, signum)


if __name__ == "__main__":
    raise SystemExit(main())
