"""The repair under a slow drift: do its intervals hold the plant, are its kinds right, does it report steps?

The loops of :mod:`bench.drift_mc` (Wood-Berry and the paper's cases 3.1, 3.2 and 3.3, each plant's MPC or an
offset-free one, 4,000 samples, white measurement noise of 0.02 plus a drift ``v(k) = 0.98 v(k-1) + a e(k)`` or
another unmeasured disturbance), analysed with the repair (:func:`~mpm_monitor.core.pipeline.analyze`, defaults).
A drift under white noise is an ARMA(1, 1) that an AR noise model of 4 lags leaves coloured: the repair's
prediction-error fit then has intervals too narrow, likelihood-ratio tests too liberal (a right parameter "moved":
``mixed``), and its disturbance tests report steps no input explains on clean loops.

Scored per disturbance variant (none, the two drifts of :data:`bench.drift_mc.DRIFTS`, the other disturbances
pooled), over the repair's entries of the plant's mismatched elements (the truth: the parameters that differ
between plant and model):

* ``intervals``: each reported interval (``gain``, ``time_constant``, ``delay``) that holds the plant's value,
  over those reported, per parameter; the confidence level is 99.9 %, so a miss in more than a few per thousand
  says the intervals are too narrow;
* ``kinds``: the repair's kind equal to the truth's (a single parameter changed: its name; several: ``mixed``);
* ``disturbances_clean``: clean loops (case 3.1 counts as clean: its plant has no mismatched element) on which
  the repair reported an unexplained step or drift, also per variant: under white noise and the stationary
  drifts a report is a false alarm (the family's level is 1 %); a random walk (``walk``) is a drift no input
  explains and the ``steps`` variant's steps are steps no input explains, so a report there is right;
* the repair's noise order used (histogram) and the median analysis time.

``--code DIR`` is not offered: to compare with an earlier commit, run this file from a ``git worktree`` of it (the
package is imported from the working directory).

Run: ``python -m bench.drift_intervals [--seeds 6] [--jobs 2] [--out bench/results/drift_intervals.json]``
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze

from . import write_json
from .drift_mc import DRIFT_POLE, DRIFTS, NOISE, REGIMES, loop, loop_keys, run_loops
from .quiet_loops import PLANTS, SAMPLES, plant_of

DEFAULT_OUT = "bench/results/drift_intervals.json"
#: The parameters whose intervals are scored.
PARAMS = ("gain", "time_constant", "delay")
#: The groups of variants summarized: ``drift`` pools the two drifts, ``other`` the other disturbances.
GROUPS = ("none", "drift", "other")


def group_of(variant: str) -> str:
    """``none``, ``drift`` (a variant of :data:`bench.drift_mc.DRIFTS` with a drift) or ``other``."""
    if variant == "none":
        return "none"
    return "drift" if variant in DRIFTS else "other"


def true_kind(model, plant, i: int, j: int) -> Optional[str]:
    """The kind the repair should report for element ``(i, j)``: the one parameter of :data:`PARAMS` that
    differs between ``plant`` and ``model``, ``mixed`` when several do, None when none does."""
    a, b = model.element(i, j), plant.element(i, j)
    moved = [p for p in PARAMS if not np.isclose(a[p], b[p], rtol=1e-9, atol=1e-12)]
    if not moved:
        return None
    return moved[0] if len(moved) == 1 else "mixed"


def scored_changes(model, plant, changes: list) -> list:
    """Per entry of the repair's ``changes``: its element, whether the element is mismatched, the true and the
    reported kind, whether it was applied, and per parameter of :data:`PARAMS` with an interval whether that
    interval holds the plant's value."""
    out = []
    for c in changes:
        i, j = model.outputs.index(c["output"]), model.columns.index(c["input"])
        truth = plant.element(i, j)
        held = {p: bool(lo - 1e-9 <= truth[p] <= hi + 1e-9) for p, (lo, hi) in (c.get("interval") or {}).items()
                if p in PARAMS}
        kind = true_kind(model, plant, i, j)
        out.append({"element": [c["output"], c["input"]], "mismatched": kind is not None, "true_kind": kind,
                    "kind": c["kind"], "applied": bool(c.get("applied")), "held": held})
    return out


def run_one(plant_name: str, mismatched: bool, seed: int, variant: str, regime: str) -> dict:
    """One loop of :func:`bench.drift_mc.loop`, analysed with the repair; a JSON-ready record."""
    model, _, data, truth, v = loop(plant_name, mismatched, seed, variant, regime)
    plant = plant_of(plant_name, mismatched)[1]
    rec = {"plant": plant_name, "mismatched": mismatched, "seed": seed, "variant": variant, "regime": regime,
           "truth": truth, "drift_std": None if v is None else float(np.std(v))}
    t0 = time.perf_counter()
    try:
        rep = analyze(model, data, AnalysisOptions())
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {**rec, "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    repair = rep.repair
    return {**rec, "seconds": seconds, "na": (rep.noise_order or {}).get("na"),
            "noise_order": repair.get("noise_order", 4),
            "located": sorted([list(x) for x in rep.located_elements]),
            "changes": scored_changes(model, plant, repair.get("changes", [])),
            "disturbances": [[d["output"], d["kind"], float(d["size"])] for d in repair.get("disturbances", [])]}


def _star(args):
    return run_one(*args)


def summarize(records: list) -> dict:
    """Per group of variants (:data:`GROUPS`): intervals holding the plant's value per parameter (mismatched
    elements, and elements located that are not), kinds right, clean loops with a disturbance reported, the
    repair's noise orders and the median time."""
    out = {}
    for group in GROUPS:
        recs = [r for r in records if group_of(r["variant"]) == group]
        if not recs:
            continue
        ok = [r for r in recs if "error" not in r]
        entries = [c for r in ok for c in r["changes"]]
        v = {"runs": len(recs), "errors": len(recs) - len(ok)}
        for who, keep in (("mismatched", True), ("not_mismatched", False)):
            cs = [c for c in entries if c["mismatched"] is keep]
            v[f"intervals_{who}"] = {p: [sum(c["held"][p] for c in cs if p in c["held"]),
                                         sum(p in c["held"] for c in cs)] for p in PARAMS}
        true = [c for c in entries if c["mismatched"]]
        v["kinds_right"] = [sum(c["kind"] == c["true_kind"] for c in true), len(true)]
        v["kinds"] = dict(Counter(f"{c['true_kind']} -> {c['kind']}" for c in true))
        clean = [r for r in ok if not r["truth"]]
        v["disturbances_clean"] = [sum(bool(r["disturbances"]) for r in clean), len(clean)]
        v["disturbances_clean_by_variant"] = {
            name: [sum(bool(r["disturbances"]) for r in clean if r["variant"] == name),
                   sum(r["variant"] == name for r in clean)] for name in dict.fromkeys(r["variant"] for r in clean)}
        v["located_clean"] = [sum(bool(r["located"]) for r in clean), len(clean)]
        v["noise_order"] = {str(k): c for k, c in sorted(Counter(int(r["noise_order"]) for r in ok).items())}
        v["seconds_median"] = float(np.median([r["seconds"] for r in recs]))
        out[group] = v
    return out


def format_table(result: dict) -> str:
    s, cfg = result["summary"], result["config"]
    lines = [f"the repair under a drift: the loops of bench.drift_mc, {cfg['seeds']} seeds x {len(cfg['plants'])} "
             f"plants, "
             f"clean and mismatched, {cfg['samples']} samples, white noise {NOISE} + a drift (pole {DRIFT_POLE}) or "
             f"another disturbance; intervals at 99.9 %",
             "group  runs  intervals holding the plant (mismatched elements): gain  time constant  delay  | "
             "kinds right | clean: disturbance reported, located | repair's noise order | median s"]
    for group, v in s.items():
        iv = v["intervals_mismatched"]
        held = "  ".join(f"{iv[p][0]}/{iv[p][1]}" for p in PARAMS)
        order = " ".join(f"{k}:{c}" for k, c in v["noise_order"].items())
        lines.append(f"{group:6s} {v['runs']:4d}  {held}  | {v['kinds_right'][0]}/{v['kinds_right'][1]} | "
                     f"{v['disturbances_clean'][0]}/{v['disturbances_clean'][1]}, "
                     f"{v['located_clean'][0]}/{v['located_clean'][1]} | {order} | {v['seconds_median']:.2f}"
                     + (f"  ({v['errors']} errors)" if v["errors"] else ""))
    for group, v in s.items():
        wrong = {k: c for k, c in v["kinds"].items() if k.split(" -> ")[0] != k.split(" -> ")[1]}
        iv = v["intervals_not_mismatched"]
        by = v["disturbances_clean_by_variant"]
        lines.append(f"{group}: kinds not right {wrong or 'none'}; intervals of elements located that are not "
                     f"mismatched: " + ", ".join(f"{p} {iv[p][0]}/{iv[p][1]}" for p in PARAMS)
                     + "; clean loops with a disturbance reported: "
                     + ", ".join(f"{k} {c[0]}/{c[1]}" for k, c in by.items()))
    return "\n".join(lines)


def run(seeds: int, jobs: int = 1) -> dict:
    records, seconds = run_loops(_star, loop_keys(seeds), jobs, 24)
    return {"config": {"seeds": seeds, "samples": SAMPLES, "drifts": DRIFTS, "drift_pole": DRIFT_POLE, "noise": NOISE,
                       "regimes": list(REGIMES), "plants": list(PLANTS)},
            "seconds": seconds, "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.drift_intervals", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=6, help="seeds per plant, clean and mismatched (default 6)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    if args.seeds < 1 or args.jobs < 1:
        p.error(f"--seeds and --jobs: expected integers >= 1, got {args.seeds} and {args.jobs}")
    res = run(args.seeds, args.jobs)
    print(format_table(res))
    print(f"{res['seconds']:.0f} s")
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
