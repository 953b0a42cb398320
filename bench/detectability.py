"""Calibration of ``detectable_gain_change``: is an error of the reported size detected 90 % of the time?

For every run ``k`` of family ``seed``:

1. draw the scenario of :mod:`bench.scenarios` (same distribution as :mod:`bench.monte_carlo`:
   plants 2x2 to 8x8, dither in 30 % of the runs) with a model equal to the plant; in a quarter of
   the runs one element, drawn at random, is taken out of both (gain 0: an element the model
   lacks);
2. simulate the closed loop and analyse it (:func:`mpm_monitor.core.analysis.detect`, default
   options); draw one element ``(i, j)`` that is not ambiguous and read its reported
   ``detectable_gain_change`` ``delta``;
3. give the plant exactly that error -- its gain ``K (1 + delta)`` or ``K (1 - delta)`` (sign at
   random), or, for an element the model lacks, the row's typical element
   (:func:`mpm_monitor.core.detectability.typical_element`) with gain ``+- delta |K_typical|`` --
   simulate the same loop again (same seeds) and analyse it;
4. record whether ``(i, j)`` is located, and whether any other element is.

A run whose changed loop diverges (possible only for a large reported change: ``--still``) is counted
apart (``diverged``), not in the rates.

A scenario in which no element can be calibrated (every element ambiguous: a fat plant without
dither) is skipped and counted; scenarios are drawn until ``--runs`` runs are calibrated.

The detection rate over the runs should be 0.9 (between 0.85 and 0.95 with 200 or more runs: the
binomial standard error at 0.9 is 0.021 for 200 runs).

With ``--still`` the loops are still: every setpoint held at 0 and no dither, so the inputs move only
with the controller's feedback of the noise (``bench/results/detectability_still.json``).  There the
element fit's noise polynomial is often undetermined (:data:`mpm_monitor.core.noise_polynomial.MAX_NOISE_FILTER_SE`),
the reported changes are large (often above 100 %, beyond the first-order picture the calibration rests
on), and the rates are also given by the sign of the error and for the runs whose reported change is
at most 1 (a gain of ``K (1 - delta)`` with ``delta`` above 1 reverses the element's sign).  The rows
whose inputs move only with the controller's feedback get no value (null); ``--first-order`` values them
too, to the first order the product would use, and gives their rate apart
(``detectability_still_first_order.json``).

Run: ``python -m bench.detectability [--runs 300] [--seed 0] [--samples 3000] [--jobs 2] [--still]
[--out bench/results/detectability.json]``
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.detectability import POWER, typical_element
from mpm_monitor.core.errors import DataFileError

from . import mc_parser, write_json
from .monte_carlo import simulate
from .scenarios import STILL, ScenarioOptions, make_scenario

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "detectability.json"
STILL_OUT = DEFAULT_OUT.with_name("detectability_still.json")
#: Fraction of the runs whose calibrated element is one the model lacks.
ABSENT_FRACTION = 0.25


def _index(model, e) -> tuple:
    return model.outputs.index(e.output), model.inputs.index(e.input)


def one(seed: int, index: int, samples: int, options: ScenarioOptions = ScenarioOptions(),
        alpha: float = 0.01, first_order: bool = False) -> dict:
    """One calibration run (see the module docstring); a JSON-ready record.

    ``first_order``: value the rows whose inputs move only with the controller's feedback too (the product
    reports null there), and record whether the calibrated element's row is one (``feedback_row``).
    """
    if not first_order:
        return _one(seed, index, samples, options, alpha, None)
    import mpm_monitor.core.detectability as det

    real, seen = det.undetermined_rows, []
    det.undetermined_rows = lambda noise: seen.append(set(real(noise))) or []
    try:
        return _one(seed, index, samples, options, alpha, seen)
    finally:
        det.undetermined_rows = real


def _one(seed: int, index: int, samples: int, options: ScenarioOptions, alpha: float, seen) -> dict:
    sc = make_scenario(seed, index, options, n_mismatches=0)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 7]))
    plant = sc.plant
    ny, nu = sc.shape
    absent = None
    if rng.random() < ABSENT_FRACTION:
        absent = divmod(int(rng.integers(ny * nu)), nu)
        gain = plant.gain.copy()
        gain[absent] = 0.0
        plant = plant.replace(gain=gain)
    model = plant
    opts = AnalysisOptions(alpha=alpha)
    clean = detect(model, simulate(_with(sc, plant, model), samples), opts)
    candidates = [e for e in clean.elements if not e.ambiguous and e.detectable_gain_change is not None
                  and math.isfinite(e.detectable_gain_change)]
    if absent is not None:
        candidates = [e for e in candidates if _index(model, e) == absent] or candidates
    rec = {"index": index, "shape": [ny, nu], "dither": sc.dither, "clean_located": len(clean.located_elements)}
    if not candidates:
        rec["skipped"] = "no element with a finite detectable gain change"
        return rec
    e = candidates[int(rng.integers(len(candidates)))]
    i, j = _index(model, e)
    delta = float(e.detectable_gain_change)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if model.present[i, j]:
        gain = plant.gain.copy()
        gain[i, j] *= 1.0 + sign * delta
        changed = plant.replace(gain=gain)
        kind = "present"
    else:
        a, b = typical_element(model, i)
        changed = plant.with_element(i, j, gain=sign * delta * abs(float(model.gain[a, b])),
                                     time_constant=float(model.time_constant[a, b]),
                                     delay=float(model.delay[a, b]))
        kind = "absent"
    rec.update({"element": [i, j], "kind": kind, "delta": delta, "sign": sign})
    if seen is not None:                    # the clean analysis's rows (the first call)
        rec["feedback_row"] = bool(seen and i in seen[0])
    try:
        rep = detect(model, simulate(_with(sc, changed, model), samples), opts)
    except DataFileError as err:          # the changed loop diverged (a still loop's large reported change)
        rec["diverged"] = str(err)
        return rec
    located = {_index(model, x) for x in rep.elements if x.mismatch}
    rec.update({
                "detected": (i, j) in located, "others_located": len(located - {(i, j)})})
    return rec


def _with(sc, plant, model):
    import dataclasses

    return dataclasses.replace(sc, plant=plant, model=model)


def _one_star(args):
    return one(*args)


def wilson(k: int, n: int, z: float = 1.96) -> tuple:
    """Wilson 95 % interval of a binomial proportion ``k / n``."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (mid - half, mid + half)


def summarise(records: Sequence[dict]) -> dict:
    """Detection rate overall and by kind, shape class and size of the reported change."""
    done = [r for r in records if "detected" in r]

    def rate(rs):
        k = sum(r["detected"] for r in rs)
        lo, hi = wilson(k, len(rs))
        return {"runs": len(rs), "detected": k, "rate": k / len(rs) if rs else None, "wilson95": [lo, hi]}

    def shape_class(r):
        ny, nu = r["shape"]
        return "square" if ny == nu else ("tall" if ny > nu else "fat")

    deltas = [r["delta"] for r in done]
    q = np.quantile(deltas, [1 / 3, 2 / 3]) if deltas else [0, 0]
    bins = {"small": lambda d: d <= q[0], "middle": lambda d: q[0] < d <= q[1], "large": lambda d: d > q[1]}
    return {
        "target_power": POWER,
        "overall": rate(done),
        "by_kind": {k: rate([r for r in done if r["kind"] == k]) for k in ("present", "absent")},
        "by_shape": {s: rate([r for r in done if shape_class(r) == s]) for s in ("square", "tall", "fat")},
        "by_dither": {d: rate([r for r in done if r["dither"] == (d == "dither")]) for d in ("dither", "none")},
        "by_reported_size": {k: rate([r for r in done if f(r["delta"])]) for k, f in bins.items()},
        "by_sign": {k: rate([r for r in done if (r["sign"] > 0) == (k == "plus")]) for k in ("plus", "minus")},
        "reported_at_most_1": rate([r for r in done if r["delta"] <= 1.0]),
        "by_feedback_row": {k: rate([r for r in done if r.get("feedback_row") == (k == "feedback")])
                            for k in ("feedback", "other")},
        "size_tertiles": [float(x) for x in q],
        "median_delta": statistics.median(deltas) if deltas else None,
        "skipped": sum(1 for r in records if "skipped" in r),
        "diverged": sum(1 for r in records if "diverged" in r),
        "runs_with_other_located": sum(1 for r in done if r["others_located"]),
        "clean_runs_with_located": sum(1 for r in records if r["clean_located"]),
    }


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01,
        progress: Optional[callable] = None, options: ScenarioOptions = ScenarioOptions(),
        first_order: bool = False) -> dict:
    """Run the calibration until ``runs`` runs are calibrated; ``{"config", "summary", "runs"}``.

    A scenario without an element to calibrate (every element ambiguous: a fat plant without dither)
    is skipped and the next scenario index drawn, so the rate is over ``runs`` calibrated runs.
    """
    t0 = time.perf_counter()
    records = []
    pool = None
    if jobs > 1:
        import multiprocessing as mp

        pool = mp.get_context("spawn").Pool(jobs)
    try:
        start = 0
        while sum("detected" in r for r in records) < runs:
            done = sum("detected" in r for r in records)
            rate = done / len(records) if records else 1.0
            batch = max(int(math.ceil((runs - done) / max(rate, 0.2))), 1)
            tasks = [(seed, k, samples, options, alpha, first_order) for k in range(start, start + batch)]
            start += batch
            results = pool.imap(_one_star, tasks) if pool is not None else map(_one_star, tasks)
            for rec in results:
                records.append(rec)
                if progress:
                    progress(len(records), start, rec)
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    records.sort(key=lambda r: r["index"])
    calibrated = [r for r in records if "detected" in r]
    keep = {r["index"] for r in calibrated[:runs]}      # exactly ``runs`` calibrated runs (the first ones)
    last = max(keep) if keep else -1
    records = [r for r in records if r["index"] <= last]
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha,
                       "still": options == STILL, "first_order": first_order,
                       "absent_fraction": ABSENT_FRACTION, "scenarios_drawn": len(records),
                       "wall_time_s": time.perf_counter() - t0},
            "summary": summarise(records), "runs": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = mc_parser("python -m bench.detectability", __doc__, 300, DEFAULT_OUT)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--still", action="store_true", help="every setpoint held at 0 and no dither (module docstring)")
    parser.add_argument("--first-order", action="store_true",
                        help="also value the rows whose inputs move only with the controller's feedback (null in "
                             "the product) and give the rates of those rows apart")
    args = parser.parse_args(argv)
    if args.still and args.out == DEFAULT_OUT:
        args.out = STILL_OUT.with_name("detectability_still_first_order.json") if args.first_order else STILL_OUT

    def progress(done, total, rec):
        if not args.quiet:
            tail = rec.get("skipped") or (f"{rec['kind']} delta {rec['delta']:.3f} " + (
                "diverged" if "diverged" in rec else "detected" if rec["detected"] else "MISSED"))
            print(f"[{done}/{total}] run {rec['index']} {rec['shape'][0]}x{rec['shape'][1]}: {tail}", flush=True)

    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha, progress,
                 STILL if args.still else ScenarioOptions(), args.first_order)
    s = result["summary"]
    o = s["overall"]
    print(f"detection rate at the reported detectable_gain_change: {o['rate']:.3f} ({o['detected']}/{o['runs']}, "
          f"95% interval {o['wilson95'][0]:.3f}-{o['wilson95'][1]:.3f}); target {POWER}")
    for cat in ("by_kind", "by_shape", "by_dither", "by_reported_size", "by_sign") + (
            ("by_feedback_row",) if args.first_order else ()):
        print(f"  {cat}: " + ", ".join(f"{k} {v['rate']:.3f} ({v['detected']}/{v['runs']})"
                                      for k, v in s[cat].items() if v["runs"]))
    small = s["reported_at_most_1"]
    if small["runs"]:
        print(f"  reported change at most 1: {small['rate']:.3f} ({small['detected']}/{small['runs']})")
    if s["diverged"]:
        print(f"  runs whose changed loop diverged (not in the rates): {s['diverged']}")
    print(f"  clean runs with a located element: {s['clean_runs_with_located']} of {result['config']['scenarios_drawn']}")
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
