"""Gaps on busy loops: what the model's run through a gap leaves in the prediction error, and what the tests make of it.

Run::

    python -m bench.gap_transients [--paper-seeds 10] [--runs 100] [--seed 0] [--samples 3000]
                                   [--drop 0.01] [--jobs 1] [--out bench/results/gap_transients.json]

The model runs through a short gap with its columns held; the plant received the columns the
controller really sent, so the prediction error after the gap carries the model's response to their
difference.  On loops whose inputs move at every sample (the paper's cases and the random scenarios
of :mod:`bench.monte_carlo`: PRBS setpoints and an input dither) that transient is as large as the
response to one move.  The analysis fits it and subtracts it
(:func:`mpm_monitor.core.gap_inputs.gap_response`).

Every run simulates one closed loop (the runs of :mod:`bench.gaps_mc`: the same logs and the same
drops for the same seeds), drops each sample with probability ``--drop`` and runs
:func:`mpm_monitor.core.pipeline.analyze` with its defaults (the repair included, as ``analyze`` on
the command line) on the whole log and on the log with the drops.  Figures, per family:

* ``same located``: runs whose located elements are the same with the drops as without;
* ``na raised``: runs whose element test raised ``na`` above 4 (its residual not white);
* ``disturbance``: runs where the repair reports an unexplained step or drift on some output (no
  scenario has one);
* ``false alarm``: runs without a mismatch with a located element.
"""

from __future__ import annotations

import argparse
import time
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.cases import CASE_NAMES

from . import map_runs, write_json
from .gaps_mc import run_drops
from .monte_carlo import family_log

DEFAULT_OUT = "bench/results/gap_transients.json"
OPTIONS = AnalysisOptions(jobs=1)


def _findings(model, data) -> dict:
    try:
        rep = analyze(model, data, OPTIONS)
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"located": sorted([list(x) for x in rep.located_elements]),
            "na": int((rep.noise_order or {}).get("na", OPTIONS.na)),
            "disturbances": sorted(f"{x['output']}:{x['kind']}" for x in (rep.repair or {}).get("disturbances", []))}


def run_one(kind: str, name: str, seed: int, samples: int, drop: float) -> dict:
    """One run: the whole log and the log with the drops analysed; a JSON-ready record."""
    model, _, data, truth = family_log(kind, name, seed, samples)
    kept = run_drops(kind, name, seed, data.n_samples, drop)
    rec = {"kind": kind, "name": name, "seed": seed, "truth": truth, "dropped": int(data.n_samples - kept.size),
           "full": _findings(model, data), "offline": _findings(model, data.take(kept))}
    rec["same"] = "error" not in rec["full"] and "error" not in rec["offline"] \
        and rec["full"]["located"] == rec["offline"]["located"]
    return rec


def _run_star(args):
    return run_one(*args)


def summarize(records: Sequence[dict]) -> dict:
    """Per family and overall: agreement, ``na`` raised, disturbances reported and false alarms, whole and dropped."""
    out = {}
    for fam in ("paper", "mc", "all"):
        recs = [r for r in records if fam == "all" or r["kind"] == fam]
        if not recs:
            continue
        clean = [r for r in recs if not r["truth"]]
        row = {"runs": len(recs), "clean_runs": len(clean),
               "dropped_per_run": float(np.mean([r["dropped"] for r in recs])),
               "same_located": sum(r["same"] for r in recs) / len(recs),
               "errors": sum(1 for r in recs for k in ("full", "offline") if "error" in r[k])}
        for key in ("full", "offline"):
            ok = [r[key] for r in recs if "error" not in r[key]]
            row[key] = {"na_raised": sum(1 for x in ok if x["na"] > OPTIONS.na),
                        "disturbance": sum(1 for x in ok if x["disturbances"]),
                        "false_alarm": sum(1 for r in clean if r[key].get("located"))}
        out[fam] = row
    return out


def format_table(summary: dict, drop: float) -> str:
    lines = [f"gaps on busy loops: each sample dropped with probability {drop:g}; analyze with its defaults (repair "
             f"on); counts of runs, whole log / with the drops",
             f"{'runs':<7}{'n':>5}{'dropped/run':>13}{'same located':>14}{'na raised':>12}{'disturbance':>13}"
             f"{'clean':>7}{'false alarm':>13}"]
    for fam, s in summary.items():
        f, o = s["full"], s["offline"]
        lines.append(f"{fam:<7}{s['runs']:>5}{s['dropped_per_run']:>13.1f}{100 * s['same_located']:>13.1f}%"
                     f"{f['na_raised']:>6} / {o['na_raised']:<3}{f['disturbance']:>7} / {o['disturbance']:<3}"
                     f"{s['clean_runs']:>7}{f['false_alarm']:>7} / {o['false_alarm']:<3}")
    return "\n".join(lines)


def run(paper_seeds: int, runs: int, seed: int = 0, samples: int = 3000, drop: float = 0.01, jobs: int = 1,
        progress: bool = False) -> dict:
    todo = [("paper", name, s, samples, drop) for name in CASE_NAMES for s in range(1000, 1000 + paper_seeds)] \
        + [("mc", str(k), seed, samples, drop) for k in range(runs)]
    t0 = time.perf_counter()
    records = map_runs(_run_star, todo, jobs,
                       progress=(lambda done, total, _: print(f"{done}/{total}", flush=True)) if progress else None)
    return {"config": {"paper_seeds": paper_seeds, "runs": runs, "seed": seed, "samples": samples, "drop": drop,
                       "jobs": jobs, "wall_time_s": time.perf_counter() - t0},
            "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.gap_transients", description=__doc__.split("\n\n")[0])
    p.add_argument("--paper-seeds", type=int, default=10, help="seeds per paper case (default 10)")
    p.add_argument("--runs", type=int, default=100, help="random scenarios of bench.monte_carlo (default 100)")
    p.add_argument("--seed", type=int, default=0, help="scenario family (default 0)")
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--drop", type=float, default=0.01, help="probability that a sample is dropped (default 1/100)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--progress", action="store_true")
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if not 0.0 <= args.drop < 1.0:
        p.error(f"--drop: expected a probability in [0, 1), got {args.drop}")
    for flag, value in (("--paper-seeds", args.paper_seeds), ("--runs", args.runs), ("--jobs", args.jobs)):
        if value < (1 if flag == "--jobs" else 0):
            p.error(f"{flag}: expected a non-negative integer{' >= 1' if flag == '--jobs' else ''}, got {value}")
    result = run(args.paper_seeds, args.runs, args.seed, args.samples, args.drop, args.jobs, args.progress)
    print(format_table(result["summary"], args.drop))
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
