"""Throughput of the lock-step node suite: samples per second with zero dropped samples (issue 4).

Run::

    python -m bench.ros_throughput [--samples 5000] [--sizes 3,10] [--executor events|single]
                                   [--repeats 3] [--with-analysis] [--json bench/results/ros_throughput.json]

Each measurement builds the four nodes (plant, setpoint, MPC, monitor) on a private context
(``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``) in one process and one executor
(:class:`mpm_monitor.apps.demo.Suite`), waits for discovery, then times the lock-step loop from the
plant's first sample until the plant has applied its last input and the monitor holds every sample
in its window.  Per sample the loop carries ``/clock``, ``setpoint``, ``output`` and ``input``
through real rclpy publishers and subscriptions (Fast DDS, intra-process), and the MPC solves its
control law.  ``dropped`` is the number of samples the monitor did not complete (samples run minus
samples completed, which includes any gap); it must be 0.

* size 3: paper case 3.2 (Shell 3x3, Hp = 100, Hc = 30);
* size 10: a 10x10 FOPDT model (:func:`mpm_monitor.apps.demo.square_model`), same tuning.

By default the monitor only windows the data during the timed loop (its analysis is switched
off), which isolates the transport; ``--with-analysis`` lets it analyse every 1000 samples in its
worker thread while the loop runs (the analysis then competes for the interpreter).

This is a measurement, not a unit test: it prints figures and optionally writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
from typing import Optional, Sequence

from mpm_monitor.apps.demo import measure_throughput


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.ros_throughput", description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=5000)
    p.add_argument("--sizes", default="3,10", help="comma-separated: 3 = paper case 3.2, n = n x n model")
    p.add_argument("--executor", choices=("events", "single"), default="events")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--with-analysis", action="store_true", help="analyse every 1000 samples during the loop")
    p.add_argument("--json", default=None, help="write the figures to this file")
    args = p.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    results = []
    print(f"lock-step suite, {args.samples} samples per run, executor {args.executor}, "
          f"{'analysis every 1000 samples' if args.with_analysis else 'analysis off during the loop'}, "
          f"{os.cpu_count()} CPU(s), Python {platform.python_version()}")
    print(f"{'size':>6} {'run':>4} {'seconds':>8} {'samples/s':>10} {'dropped':>8}")
    for size in sizes:
        rates = []
        for rep in range(args.repeats):
            t = measure_throughput(size=size, samples=args.samples, executor=args.executor,
                                   analysis_period=1000 if args.with_analysis else 0)
            rates.append(t.samples_per_second)
            results.append({"size": size, "run": rep, "samples": t.samples, "seconds": t.seconds,
                            "samples_per_second": t.samples_per_second, "dropped": t.dropped,
                            "executor": t.executor, "with_analysis": args.with_analysis})
            print(f"{size}x{size:<4} {rep:>4} {t.seconds:8.2f} {t.samples_per_second:10.0f} {t.dropped:8d}")
            sys.stdout.flush()
        print(f"{size}x{size:<4} median {statistics.median(rates):.0f} samples/s "
              f"(min {min(rates):.0f}, max {max(rates):.0f})")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"cpu_count": os.cpu_count(), "python": platform.python_version(), "runs": results}, fh,
                      indent=2)
            fh.write("\n")
    return 0 if all(r["dropped"] == 0 for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
