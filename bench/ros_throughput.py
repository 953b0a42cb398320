"""Throughput of the lock-step node suite: samples per second with zero dropped samples (issue 4).

Run::

    python -m bench.ros_throughput [--samples 5000] [--sizes 3,10] [--executor events|single]
                                   [--repeats 3] [--with-analysis] [--json bench/results/ros_throughput.json]

Each measurement builds the four nodes (plant, setpoint, MPC, monitor) on a private context
(``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``) in one process and one executor
(:class:`mpm_monitor.apps.demo.Suite`, the demo's suite), waits for discovery, then times the lock-step loop from the
plant's first sample until the plant has applied its last input and the monitor holds every sample
in its window.  Per sample the loop carries ``/clock``, ``setpoint``, ``output`` and ``input``
through real rclpy publishers and subscriptions (Fast DDS, intra-process), and the MPC solves its
control law.  ``dropped`` is the number of samples the monitor did not complete (samples run minus
samples completed, which includes any gap); it must be 0.

* size 3: paper case 3.2 (Shell 3x3, Hp = 100, Hc = 30);
* size 10: a 10x10 FOPDT model (:func:`bench.plants.square_model`), same tuning.

By default the monitor only windows the data during the timed loop (its analysis is switched
off), which isolates the transport; ``--with-analysis`` lets it analyse every 1000 samples in its
worker thread while the loop runs (the analysis then competes for the interpreter).

This is a measurement, not a unit test: it prints figures and optionally writes them as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Callable, Optional, Sequence

from mpm_monitor.apps.demo import Suite, case_parameters, private_context
from mpm_monitor.io.model_file import save_model

from .plants import square_model


@dataclasses.dataclass(frozen=True)
class Throughput:
    """Result of :func:`measure_throughput`."""

    n_outputs: int
    n_inputs: int
    samples: int
    seconds: float
    dropped: int
    executor: str

    @property
    def samples_per_second(self) -> float:
        return self.samples / self.seconds


def measure_throughput(size: int = 3, samples: int = 3000, executor: str = "events",
                       analyze: Optional[Callable] = None, analysis_period: int = 0) -> Throughput:
    """Samples per second the lock-step suite sustains, with the monitor receiving every sample.

    Parameters
    ----------
    size : int
        3 = paper case 3.2 (Shell 3x3); otherwise an ``size x size`` model from :func:`square_model`.
    samples : int
        Samples to run.
    executor : {"events", "single"}
    analyze : callable, optional
        The monitor's analysis (default: a no-op, to time the loop alone).
    analysis_period : int
        Samples between analyses during the run (0 = none during the run).

    Returns
    -------
    Throughput
        ``dropped`` = samples the monitor did not complete (must be 0).
    """
    ctx = private_context()
    suite = None
    try:
        with tempfile.TemporaryDirectory(prefix="mpm_bench_") as tmp:
            if size == 3:
                params = case_parameters("3.2", seed=1)
            else:
                path = str(Path(tmp) / "model.yaml")
                save_model(square_model(size), path)
                params = {"plant": {"model_file": path, "seed": 1},
                          "mpc": {"model_file": path}, "setpoint": {"model_file": path},
                          "monitor": {"model_file": path}}
            params["plant"]["max_samples"] = samples
            if analysis_period:
                params["monitor"].update(window_samples=samples, min_samples=min(samples, analysis_period),
                                         analysis_period=analysis_period)
            else:
                params["monitor"].update(window_samples=samples, min_samples=samples, analysis_period=samples)
            if analyze is None and not analysis_period:
                analyze = _no_analysis
            suite = Suite(ctx, params, analyze=analyze, executor=executor)
            suite.start()
            if not suite.run(timeout=max(60.0, samples / 50.0), final_analysis=False):
                raise RuntimeError(f"the loop stalled at sample {suite.plant.k} of {samples}")
            done = suite.monitor.core.window.n_completed
            return Throughput(size, size, samples, suite.loop_seconds, samples - done, executor)
    finally:
        if suite is not None:
            suite.close()
        ctx.try_shutdown()


def _no_analysis(model, data, options):
    raise RuntimeError("analysis disabled for the throughput measurement")


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
