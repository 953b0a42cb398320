"""``make bench``: every benchmark in one command; each prints its table and writes JSON to
``bench/results/``.  Figures in the README and docs/benchmarks.md come from runs of this.

Run: ``python -m bench.run_all [--quick]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

#: (module, arguments, arguments with --quick)
BENCHMARKS = [
    ("bench.paper_cases", [], ["--seeds", "5"]),
    ("bench.monte_carlo", ["--runs", "200"], ["--runs", "30"]),
    ("bench.monte_carlo", ["--runs", "200", "--bounds", "0.8", "--jobs", "2", "--out",
                           "bench/results/monte_carlo_bounded.json"],
     ["--runs", "20", "--bounds", "0.8", "--jobs", "2", "--no-timing", "--out", "bench/results/monte_carlo_bounded_quick.json"]),
    ("bench.monte_carlo", ["--runs", "200", "--setpoint-steps", "--jobs", "2", "--out",
                           "bench/results/monte_carlo_setpoint_steps.json"],
     ["--runs", "20", "--setpoint-steps", "--jobs", "2", "--no-timing", "--out",
      "bench/results/monte_carlo_setpoint_steps_quick.json"]),
    ("bench.detection_power", [], ["--runs", "10", "--lengths", "300,800,2000"]),
    ("bench.repair_validation", ["--seeds", *map(str, range(1, 13)), "--json", "bench/results/repair_validation.json"],
     ["--seeds", "1"]),
    ("bench.repair_mc", ["--dither-fat"], ["--runs", "20", "--dither-fat"]),
    ("bench.repair_mc", ["--dither-fat", "--setpoint-steps", "--out", "bench/results/repair_mc_setpoint_steps.json"],
     ["--runs", "20", "--dither-fat", "--setpoint-steps", "--out", "bench/results/repair_mc_setpoint_steps_quick.json"]),
    ("bench.holdout_mc", [], ["--runs", "20", "--out", "bench/results/holdout_mc_quick.json"]),
    ("bench.holdout_mc", ["--setpoint-steps"],
     ["--runs", "20", "--setpoint-steps", "--out", "bench/results/holdout_mc_setpoint_steps_quick.json"]),
    ("bench.candidates_mc", [], ["--runs", "20", "--detection-runs", "5"]),
    ("bench.candidates_mc", ["--setpoint-steps", "--jobs", "2"],
     ["--runs", "20", "--detection-runs", "5", "--setpoint-steps", "--jobs", "2", "--out",
      "bench/results/candidates_mc_setpoint_steps_quick.json"]),
    ("bench.structures_mc", ["--jobs", "2"], ["--runs", "30", "--clean-integrating", "30"]),
    ("bench.gaps_mc", ["--paper-seeds", "20", "--runs", "150", "--repair", "--jobs", "2"],
     ["--paper-seeds", "2", "--runs", "10", "--jobs", "2"]),
    ("bench.spikes_mc", ["--paper-seeds", "10", "--runs", "150", "--kept", "3", "--jobs", "2"],
     ["--paper-seeds", "2", "--runs", "10", "--kept", "1", "--jobs", "2"]),
    ("bench.quiet_loops", ["--seeds", "8", "--jobs", "2"], ["--seeds", "1", "--jobs", "2"]),
    ("bench.drift_mc", ["--seeds", "6", "--jobs", "2"], ["--seeds", "1", "--jobs", "2"]),
    ("bench.drift_intervals", ["--seeds", "10", "--jobs", "2"],
     ["--seeds", "1", "--jobs", "2", "--out", "bench/results/drift_intervals_quick.json"]),
    ("bench.quiet_rows", ["--runs", "150", "--jobs", "2"],
     ["--runs", "10", "--jobs", "2", "--out", "bench/results/quiet_rows_quick.json"]),
    ("bench.noise_free", ["--runs", "300", "--jobs", "2"], ["--runs", "20"]),
    ("bench.quantized", ["--runs", "200", "--jobs", "2"], ["--runs", "20", "--jobs", "2", "--out",
                                                          "bench/results/quantized_quick.json"]),
    ("bench.quantized", ["--runs", "200", "--jobs", "2", "--inputs", "--out", "bench/results/quantized_inputs.json"],
     ["--runs", "20", "--jobs", "2", "--inputs", "--out", "bench/results/quantized_inputs_quick.json"]),
    ("bench.step_models", ["--runs", "100", "--jobs", "2"], ["--runs", "10"]),
    ("bench.feedthrough_mc", ["--runs", "200", "--jobs", "2"],
     ["--runs", "20", "--out", "bench/results/feedthrough_mc_quick.json"]),
    ("bench.mpc_qp", [], ["--samples", "300", "--out", "bench/results/mpc_qp_quick.json"]),
    ("bench.model_load", ["--analyze", "100x40", "--out", "bench/results/model_load.json"],
     ["--sizes", "40x40", "--lengths", "120", "--repeats", "1"]),
    ("bench.model_load", ["--block", "--lengths", "120", "--out", "bench/results/model_load_block.json"],
     ["--block", "--sizes", "40x40", "--lengths", "120", "--repeats", "1"]),
    ("bench.perf", [], ["--quick"]),
    ("bench.stages", ["--out", "bench/results/stages.json"], ["--sizes", "20x20", "--repeats", "1"]),
    ("bench.timeline", ["--out", "bench/results/timeline.json"], ["--sizes", "20x20", "--repeats", "1"]),
    ("bench.memory", [], ["--quick"]),
    ("bench.ros_throughput", ["--json", "bench/results/ros_throughput.json"], ["--samples", "2000", "--repeats", "1"]),
    ("bench.monitor_load", ["--json", "bench/results/monitor_load.json"], ["--quick"]),
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.run_all", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smaller runs (a few minutes in all)")
    p.add_argument("--only", default=None, help="comma-separated module names (e.g. bench.perf)")
    args = p.parse_args(argv)
    failed = []
    for module, full, quick in BENCHMARKS:
        if args.only and module not in args.only.split(","):
            continue
        cmd = [sys.executable, "-m", module] + (quick if args.quick else full)
        print(f"\n=== {' '.join(cmd[1:])}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd)
        print(f"=== {module}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(module)
    if failed:
        print(f"failed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
