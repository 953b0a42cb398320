"""The repair under a drift on every output: does the located element's repair take the drift up?

Usage::

    .venv/bin/python -m bench.drift_repair [--size 20] [--runs 12] [--samples 10000] [--amplitude 1.0] [--out F]

Outputs of a plant drift (feed quality, fouling, ambient temperature), and the controller ramps its inputs
against the drifts.  A located element fitted on its own can then become a slow element of a large gain
that ramps with those inputs and explains its output's drift: the repaired model is far from the plant
though it predicts the log well.  Each run is the industrial case of :mod:`bench.perf` (``--size`` outputs
and inputs, the gain of ``(y1, u2)`` 30 % off in the model, ``seed`` = the run) simulated again with a drift
on every output (a straight line from 0 to ``--amplitude`` standard deviations of the output's clean log over
the record, the sign drawn), analysed by :func:`~mpm_monitor.core.pipeline.analyze` with its defaults.  Per
run: the located elements, the repair's kind and the relative error of the repaired gain of ``(y1, u2)``
against the plant's, and whether the repair allowed for the drift.  Summary: runs that locate ``(y1, u2)``,
other elements located (false locations), and the repaired gains within 2 %, 10 % and beyond.

``--code DIR`` imports ``mpm_monitor`` from another checkout (a ``git worktree`` of an earlier commit): the
figures before and after a change on the same loops.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def one_run(size: int, seed: int, samples: int, amplitude: float) -> dict:
    """The figures of one run (see the module's docstring)."""
    from bench.perf import industrial_case
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.sim.closed_loop import run_closed_loop

    plant, model, clean = industrial_case(size, size, samples, seed, mismatches=1)
    spread = np.std(np.asarray(clean.y, float), axis=0)
    signs = np.random.default_rng(100 + seed).choice([-1.0, 1.0], size)
    drifts = np.outer(np.arange(samples) / samples, amplitude * spread * signs)
    data = run_closed_loop(plant, model, samples, seed=seed + 7, output_disturbance=drifts).as_logged_data()
    t0 = time.perf_counter()
    report = analyze(model, data, AnalysisOptions(jobs=1))
    seconds = time.perf_counter() - t0
    located = [f"{o}:{i}" for o, i in report.located_elements]
    change = next((c for c in report.repair.get("changes", []) if (c["output"], c["input"]) == ("y1", "u2")), None)
    error = None
    if change is not None and change.get("applied"):
        error = abs(change["after"]["gain"] / float(plant.gain[0, 1]) - 1.0)
    return {"seed": seed, "located": located, "kind": None if change is None else change["kind"],
            "gain_error": error, "allowed_for": any(w.startswith("y1: the re-estimation of its elements allowed for")
                                                    for w in report.repair.get("warnings", [])),
            "analyze_s": seconds}


def summary(records: list) -> dict:
    """Counts over the runs."""
    errors = [r["gain_error"] for r in records if r["gain_error"] is not None]
    return {"runs": len(records), "located_y1_u2": sum("y1:u2" in r["located"] for r in records),
            "false_locations": sum(len([x for x in r["located"] if x != "y1:u2"]) for r in records),
            "repaired": len(errors), "within_2pct": sum(e <= 0.02 for e in errors),
            "within_10pct": sum(e <= 0.10 for e in errors), "beyond_10pct": sum(e > 0.10 for e in errors),
            "largest_error": max(errors) if errors else None,
            "allowed_for": sum(r["allowed_for"] for r in records)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.drift_repair", description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=20, help="outputs and inputs (default 20)")
    parser.add_argument("--runs", type=int, default=12)
    parser.add_argument("--samples", type=int, default=10000)
    parser.add_argument("--amplitude", type=float, default=1.0, help="drift over the record, output standard deviations")
    parser.add_argument("--code", default=None, help="the checkout whose mpm_monitor runs (default: this one)")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    for flag, value in (("--size", args.size), ("--runs", args.runs), ("--samples", args.samples)):
        if value < 1:
            parser.error(f"{flag}: expected an integer >= 1, got {value}")
    if args.child is not None:                        # one run, in the interpreter of the checkout asked for
        print(json.dumps(one_run(args.size, args.child, args.samples, args.amplitude)))
        return 0
    code = Path(args.code).resolve() if args.code else Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(code), str(Path(__file__).resolve().parents[1])]))
    records = []
    for seed in range(args.runs):
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(seed), "--size",
                               str(args.size), "--samples", str(args.samples), "--amplitude", str(args.amplitude)],
                              cwd=code, env=env, capture_output=True, text=True, check=True)
        records.append(json.loads(done.stdout.strip().splitlines()[-1]))
        r = records[-1]
        error = "-" if r["gain_error"] is None else f"{100 * r['gain_error']:.2f} %"
        print(f"  run {seed}: located {', '.join(r['located']) or 'none'}; (y1, u2) {r['kind']}, gain error {error}"
              f"{', the drift allowed for' if r['allowed_for'] else ''}", flush=True)
    s = summary(records)
    largest = "-" if s["largest_error"] is None else f"{100 * s['largest_error']:.2f} %"
    print(f"{args.size}x{args.size}, {args.samples} samples, a drift of {args.amplitude:g} standard deviations on every "
          f"output: (y1, u2) located in {s['located_y1_u2']} of {s['runs']}, other elements located {s['false_locations']}; "
          f"repaired gains within 2 % {s['within_2pct']} of {s['repaired']}, within 10 % {s['within_10pct']}, "
          f"beyond {s['beyond_10pct']} (largest error {largest}); "
          f"the drift allowed for in {s['allowed_for']}")
    if args.out:
        from bench import write_json
        write_json(args.out, {"size": args.size, "samples": args.samples, "amplitude": args.amplitude,
                              "code": str(code), "summary": s, "records": records})
    return 0


if __name__ == "__main__":
    sys.exit(main())
