"""Run the plant, setpoint, MPC and monitor nodes in one process with one executor (lock-step).

Examples (in a colcon workspace; from the repository, ``python launch_scripts/suite_inprocess.py``
instead of ``ros2 run mpm_monitor suite_inprocess``)::

    ros2 run mpm_monitor suite_inprocess --case 3.2
    ros2 run mpm_monitor suite_inprocess --params my_suite.yaml --samples 10000 --namespace /unit1
    ros2 run mpm_monitor suite_inprocess --case 3.1 --private      # talk to no other process

The nodes take their parameters from the params file (default ``config/case_<case>.yaml``) and the
``-p node.param:=value`` overrides; they are ordinary nodes on the ROS graph (``ros2 topic echo
/diagnostics`` sees them) unless ``--private``.  The diagnostics are printed as they arrive; the run
ends after ``plant.max_samples`` samples (with the monitor's analysis of the last window), or on
Ctrl-C when ``max_samples`` is 0.
"""

from __future__ import annotations

import argparse
import sys

from ... import limit_blas_threads
from ..cli import DEMO_CASES
from .common import case_params_file, load_params_file, merge, parse_overrides


def main(argv=None) -> int:
    """Console script ``suite_inprocess``."""
    limit_blas_threads()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", choices=DEMO_CASES, default="3.2")
    p.add_argument("--params", default=None,
                   help="params file for the four nodes "
                        "(default config/case_<case>.yaml; installed, in share/mpm_monitor/config)")
    p.add_argument("--samples", type=int, default=None, help="plant.max_samples (0 = until Ctrl-C)")
    p.add_argument("--namespace", default="", help="namespace of the four nodes")
    p.add_argument("--private", action="store_true", help="ROS_AUTOMATIC_DISCOVERY_RANGE=OFF for this process")
    p.add_argument("--executor", choices=("events", "single"), default="events")
    p.add_argument("-p", dest="overrides", action="append", default=[], metavar="NODE.PARAM:=VALUE")
    args = p.parse_args(argv)

    import rclpy
    from rclpy.context import Context

    from ...core.errors import InputError
    from ..demo import DiagnosticsPrinter, Suite, private_context

    params = load_params_file(args.params or case_params_file(args.case))
    if args.samples is not None:
        params = merge(params, {"plant": {"max_samples": args.samples}})
    if args.namespace:
        params = merge(params, {"plant": {"clock_topic": "clock"}, "setpoint": {"clock_topic": "clock"},
                                "monitor": {"diagnostics_topic": "diagnostics"}})
    params = merge(params, parse_overrides(args.overrides))
    if args.private:
        ctx = private_context()
    else:
        ctx = Context()
        rclpy.init(args=[], context=ctx)
    suite = None
    try:
        suite = Suite(ctx, params, namespace=args.namespace, executor=args.executor)
        diag_topic = params.get("monitor", {}).get("diagnostics_topic", "/diagnostics")
        printer = DiagnosticsPrinter(ctx, topic=diag_topic, namespace=args.namespace)
        suite.add_node(printer.node)
        suite.start(diagnostics_listeners=1)
        if suite.samples:
            ok = suite.run(timeout=1e9)
            printer.wait_for(suite, 5.0)
            report = suite.monitor.core.latest_report
            if ok and report is not None:
                rows = [r.output for r in report.rows if r.mismatch]
                els = [f"({e.output}, {e.input})" for e in report.elements if e.mismatch]
                print(f"located rows: {', '.join(rows) or 'none'}; elements: {', '.join(els) or 'none'}")
        else:
            suite.spin_until(lambda: False, timeout=None)
        return 0
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    finally:
        if suite is not None:
            suite.close()
        ctx.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
