"""Outputs logged with a coarse resolution: false alarms, located elements and the warning.

For every run ``k`` of family ``seed`` of :mod:`bench.monte_carlo`'s loops (2x2 to 8x8, 0 to 3
mismatched elements), the log is analysed (``repair=False``) as simulated and with its outputs
rounded to a grid of step ``r`` times each output's noise standard deviation, for every ``r`` of
``--ratios``.  The noise's standard deviation is the prediction error's with the plant as its model
(what the output does that no input explains), so ``r = 1`` rounds each output to its own noise.
Recorded per resolution: clean runs with a located element, located elements on and off the
mismatches, and the runs the analysis warns about (:mod:`mpm_monitor.core.resolution`: an output on a
grid coarser than ``RESOLUTION_RATIO`` times the standard deviation of its prediction error, or an input
whose grid is through an element's gain), and among the runs with a false positive, those it warned about.
``--inputs`` rounds the logged inputs instead (the plant had them exact): input ``j`` to ``r`` times
``min_i noise_i / |gain_ij|``, the step that moves some output by its noise.

Run: ``python -m bench.quantized [--runs 200] [--seed 0] [--jobs 2] [--ratios 0.5,1,2,3,5,10]
[--out bench/results/quantized.json]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.signals import compute_signals

from . import map_runs, write_json
from .monte_carlo import simulate
from .scenarios import make_scenario

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "quantized.json"
RATIOS = (0.5, 1.0, 2.0, 3.0, 5.0, 10.0)
#: The words of the analysis's warnings about a coarse resolution, of outputs and of inputs
#: (mpm_monitor.core.resolution).
WARNING = "logged with a coarse resolution: "


def rounded(y: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """``y`` (shape (n_samples, n_outputs)) rounded to a grid of step ``steps[i]`` in column ``i``."""
    return np.round(np.asarray(y, dtype=float) / steps) * steps


def input_steps(gain: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Per input ``j``, the step that moves some output by its noise's standard deviation through the
    element's gain: ``min_i noise_i / |gain_ij|`` over the present elements (shape (n_inputs,); input units).

    Parameters
    ----------
    gain : ndarray, shape (n_outputs, n_inputs)
    noise : ndarray, shape (n_outputs,)
    """
    g = np.abs(np.asarray(gain, dtype=float))
    with np.errstate(divide="ignore"):
        per = np.where(g > 0, np.asarray(noise, dtype=float)[:, None] / np.where(g > 0, g, 1.0), np.inf)
    return per.min(axis=0)


def one(seed: int, index: int, samples: int, alpha: float, ratios: Sequence[float], inputs: bool = False) -> dict:
    """One loop: its analysis as simulated and at every resolution (of the outputs, or with ``inputs`` of
    the logged inputs, the plant having had them exact: :func:`input_steps` times the ratio)."""
    sc = make_scenario(seed, index)
    data = simulate(sc, samples)
    noise = np.std(compute_signals(sc.plant, data.r, data.u, data.y, "estimate").d, axis=0)
    model = sc.model
    rec = {"index": index, "shape": [model.n_outputs, model.n_inputs],
           "truth": sorted([m.output, m.input] for m in sc.mismatches), "noise_std": noise.tolist()}
    unit = input_steps(sc.plant.gain, noise) if inputs else None
    for ratio in (0.0, *ratios):
        if ratio == 0:
            logged = data
        elif inputs:
            logged = dataclasses.replace(data, u=rounded(data.u, ratio * unit))
        else:
            logged = dataclasses.replace(data, y=rounded(data.y, ratio * noise))
        rep = analyze(model, logged, AnalysisOptions(alpha=alpha, repair=False))
        rec[f"{ratio:g}"] = {
            "located": sorted([model.outputs.index(e.output), model.inputs.index(e.input)]
                              for e in rep.elements if e.mismatch),
            "warned": any(WARNING in w for w in rep.warnings)}
    return rec


def _one_star(args):
    return one(*args)


def summarise(records: Sequence[dict], ratios: Sequence[float]) -> dict:
    """Per resolution: false alarms, hits and false positives, runs warned and the same as unrounded."""
    out = {}
    for ratio in (0.0, *ratios):
        key = f"{ratio:g}"
        clean = [r for r in records if not r["truth"]]
        fa = sum(1 for r in clean if r[key]["located"])
        tp = fp = 0
        fp_runs = warned_fp = same = 0
        for r in records:
            truth = {tuple(t) for t in r["truth"]}
            loc = {tuple(t) for t in r[key]["located"]}
            tp += len(loc & truth)
            fp += len(loc - truth)
            if loc - truth:
                fp_runs += 1
                warned_fp += r[key]["warned"]
            same += loc == {tuple(t) for t in r["0"]["located"]}
        out[key] = {"clean_runs": len(clean), "false_alarms": fa, "hits": tp, "false_positives": fp,
                    "runs_with_a_false_positive": fp_runs, "of_them_warned": warned_fp,
                    "runs_warned": sum(r[key]["warned"] for r in records), "same_as_unrounded": same}
    return out


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01,
        ratios: Sequence[float] = RATIOS, progress=None, inputs: bool = False) -> dict:
    """The benchmark: ``runs`` loops of family ``seed`` (:func:`one`), their records and :func:`summarise`."""
    tasks = [(seed, k, samples, alpha, tuple(ratios), inputs) for k in range(runs)]
    t0 = time.perf_counter()
    records = map_runs(_one_star, tasks, jobs, progress)
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha, "ratios": list(ratios),
                       "rounded": "inputs" if inputs else "outputs"},
            "summary": summarise(records, ratios), "seconds": time.perf_counter() - t0, "records": records}


def format_table(result: dict) -> str:
    """The summary as plain text, one line per resolution (what ``main`` prints)."""
    cfg = result["config"]
    what = ("inputs rounded to r x the step that moves an output by its noise" if cfg.get("rounded") == "inputs"
            else "outputs rounded to r x their noise standard deviation")
    lines = [f"{what}: {cfg['runs']} loops of bench.monte_carlo "
             f"(seed {cfg['seed']}), {cfg['samples']} samples, alpha {cfg['alpha']} ({result['seconds']:.0f} s)",
             f"{'r':>6} {'false alarms':>13} {'hits':>5} {'false pos.':>10} {'runs warned':>12} "
             f"{'FP runs warned':>15} {'same as r=0':>12}"]
    for key, s in result["summary"].items():
        lines.append(f"{key:>6} {s['false_alarms']:>6}/{s['clean_runs']:<6} {s['hits']:>5} {s['false_positives']:>10} "
                     f"{s['runs_warned']:>12} {s['of_them_warned']:>7}/{s['runs_with_a_false_positive']:<7} "
                     f"{s['same_as_unrounded']:>12}")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m bench.quantized``; returns the exit code."""
    p = argparse.ArgumentParser(prog="python -m bench.quantized", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--alpha", type=float, default=0.01)
    p.add_argument("--ratios", default=",".join(f"{r:g}" for r in RATIOS),
                   help="resolutions, in noise standard deviations (comma-separated, each > 0)")
    p.add_argument("--inputs", action="store_true",
                   help="round the logged inputs instead (the plant had them exact), input j to r x min_i "
                        "noise_i / |gain_ij|")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    try:
        ratios = tuple(float(x) for x in args.ratios.split(","))
    except ValueError:
        p.error(f"--ratios: expected numbers separated by commas, got {args.ratios!r}")
    if not ratios or min(ratios) <= 0 or args.runs < 1 or args.jobs < 1:
        p.error("--ratios must be > 0, --runs and --jobs >= 1")

    def progress(done, total, rec):
        if done % 20 == 0 or done == total:
            print(f"  {done}/{total}", file=sys.stderr, flush=True)

    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha, ratios, progress, inputs=args.inputs)
    print(format_table(result))
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
