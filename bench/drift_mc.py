"""Monte-Carlo of quiet closed loops whose outputs drift under white measurement noise: false alarms and recall.

The unmeasured disturbance of a real output is often a slow drift (feed quality, ambient temperature,
fouling) under the measurement's white noise: ``d = v + w`` with ``v(k) = 0.98 v(k-1) + a e(k)``.  That
is an ARMA(1, 1) whose inverse noise model needs far more own lags than the paper's ``na = 4`` when
the drift is small against the noise; the element test's residual stays coloured, and in closed loop
it correlates with the input lags: false alarms.  ``analyze`` checks every row's residual for
whiteness and raises ``na`` (4, 8, 16, up to ``max_na``) while one is coloured
(:mod:`mpm_monitor.core.noise_order`).  This bench measures both, on the same logs: every log is
analysed with the order fixed (``max_na`` = ``na``: the analysis before the check) and raised (the
defaults).

Two regimes of loops, each on Wood-Berry (the gain of (xb, steam) 30 % high in the mismatched plant) and
the paper's cases 3.1, 3.2 and 3.3 (the case's own mismatch), 4,000 samples, no dither:

* ``steps``: the loops of :mod:`bench.quiet_loops` (each plant's MPC, setpoint steps of +-1 held at
  least 150 samples);
* ``levels``: an offset-free MPC (the weight on the inputs themselves set to 0, only their moves
  weighted: integral action; Wood-Berry horizons 60 / 8 and move weight 50; the fat case 3.3 keeps
  its own MPC, which needs the input weight) with setpoint levels drawn uniform in [-1, 1], each held
  150 to 399 samples (:func:`setpoint_levels`).  An outside check's loops were of this kind.

Their disturbance is replaced by white measurement noise of standard deviation :data:`NOISE` on every
output, plus an independent drift per output of innovation ``a`` (``e`` standard normal from
``numpy.random.default_rng([seed, plant index, int(mismatched), 7])``, through
``run_closed_loop(..., output_disturbance=v)``): the variants ``none`` (``a = 0``), ``a0.005`` and
``a0.01``; and in the ``levels`` regime also other disturbances no benchmark covered before
(:data:`OTHER_DISTURBANCES`): an oscillating AR(2), a random walk, a sinusoid, occasional steps, and a
slower drift (pole 0.995).  Case 3.1's plant differs from its model in no element (its mismatch is in
the noise, replaced here), so its runs count as clean both ways.

Scored per regime, variant and analysis: false alarms (clean runs with a located element), clean runs
with a flagged row, mismatched runs with every true element located and with an element located
that is not mismatched, the ARX order used (histogram) and the analysis time.  ``--set key=value``
(repeatable) sets an option of both analyses, e.g. ``--set na=10``.

Run: ``python -m bench.drift_mc [--seeds 6] [--jobs 2] [--set key=value ...] [--out bench/results/drift_mc.json]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections import Counter
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions

from . import map_runs, write_json
from .quiet_loops import PLANTS, SAMPLES, STEPS, plant_of

DEFAULT_OUT = "bench/results/drift_mc.json"
#: Drift variants: name -> ``a``, the standard deviation of the drift's innovation (output units).
DRIFTS = {"none": 0.0, "a0.005": 0.005, "a0.01": 0.01}
#: Other unmeasured disturbances, run in the ``levels`` regime only (:func:`disturbance`): ``ar2``, an
#: oscillating AR(2) ``v(k) = 1.6 v(k-1) - 0.8 v(k-2) + 0.005 e(k)``; ``walk``, a random walk of step
#: 0.001; ``sine``, a sinusoid of period 200 samples and amplitude 0.05 (a random phase per output);
#: ``steps``, a step of +-0.1 on a random output every 300 to 799 samples; ``drift995``, the drift with
#: pole 0.995 and innovation 0.003.
OTHER_DISTURBANCES = ("ar2", "walk", "sine", "steps", "drift995")
DRIFT_POLE = 0.98
#: Standard deviation of the white measurement noise of every output (output units); no other disturbance.
NOISE = 0.02
#: The two analyses of every log: the ARX order fixed at ``na`` (``max_na = na``), and raised (default).
ANALYSES = ("fixed", "raised")
#: The loops: ``steps``, the quiet loops' (each plant's MPC, setpoint steps of +-1); ``levels``, an
#: offset-free MPC (no weight on the inputs themselves, only on their moves; Wood-Berry's horizons 60 / 8,
#: move weight 50) and setpoint levels drawn uniform in [-1, 1], each held 150 to 400 samples.
REGIMES = ("steps", "levels")
WOOD_BERRY_OFFSET_FREE = MpcOptions(prediction_horizon=60, control_horizon=8, input_rate_weight=50.0,
                                    input_weight=0.0)


def parse_set(items: Sequence[str]) -> dict:
    """``["na=10", "drop_spikes=false"]`` -> ``{"na": 10, "drop_spikes": False}``: each value an int,
    a float, true / false (any case), else the string."""
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise argparse.ArgumentTypeError(f"--set: expected key=value, got {item!r}")
        text = text.strip()
        if text.lower() in ("true", "false"):
            value = text.lower() == "true"
        else:
            for kind in (int, float):
                try:
                    value = kind(text)
                    break
                except ValueError:
                    continue
            else:
                value = text
        out[key.strip()] = value
    return out


def drift(plant_name: str, mismatched: bool, seed: int, a: float, n_outputs: int) -> np.ndarray:
    """The output drift, shape (SAMPLES, n_outputs): per output ``v(k) = 0.98 v(k-1) + a e(k)`` from ``v(-1) = 0``."""
    rng = np.random.default_rng([seed, PLANTS.index(plant_name), int(mismatched), 7])
    e = rng.standard_normal((SAMPLES, n_outputs)) * a
    v = np.zeros_like(e)
    prev = np.zeros(n_outputs)
    for k in range(SAMPLES):
        prev = DRIFT_POLE * prev + e[k]
        v[k] = prev
    return v


def disturbance(variant: str, plant_name: str, mismatched: bool, seed: int, n_outputs: int):
    """The unmeasured output disturbance of a variant, shape (SAMPLES, n_outputs), or None for ``none``:
    the drifts of :data:`DRIFTS` (:func:`drift`) and the :data:`OTHER_DISTURBANCES`, these from
    ``numpy.random.default_rng([seed, plant index, int(mismatched), 13])``."""
    if variant in DRIFTS:
        a = DRIFTS[variant]
        return drift(plant_name, mismatched, seed, a, n_outputs) if a > 0 else None
    rng = np.random.default_rng([seed, PLANTS.index(plant_name), int(mismatched), 13])
    n = SAMPLES
    if variant == "sine":
        phase = rng.uniform(0.0, 2 * np.pi, n_outputs)
        return 0.05 * np.sin(2 * np.pi * np.arange(n)[:, None] / 200.0 + phase)
    if variant == "steps":
        v = np.zeros((n, n_outputs))
        k = int(rng.integers(300, 800))
        while k < n:
            v[k:, int(rng.integers(n_outputs))] += rng.choice((-0.1, 0.1))
            k += int(rng.integers(300, 800))
        return v
    e = rng.standard_normal((n, n_outputs))
    v = np.zeros((n, n_outputs))
    for k in range(n):
        prev1 = v[k - 1] if k >= 1 else 0.0
        prev2 = v[k - 2] if k >= 2 else 0.0
        if variant == "ar2":
            v[k] = 1.6 * prev1 - 0.8 * prev2 + 0.005 * e[k]
        elif variant == "walk":
            v[k] = prev1 + 0.001 * e[k]
        elif variant == "drift995":
            v[k] = 0.995 * prev1 + 0.003 * e[k]
        else:
            raise ValueError(f"unknown disturbance variant {variant!r}")
    return v


def variants(regime: str) -> tuple:
    """The disturbance variants run in ``regime``: the drifts in both, the others in ``levels`` only."""
    return tuple(DRIFTS) + (OTHER_DISTURBANCES if regime == "levels" else ())


def setpoint_levels(rng: np.random.Generator, n: int, ny: int) -> np.ndarray:
    """Setpoints of the ``levels`` regime, shape (n, ny): 0 until a first step in samples 20 to 99, then
    levels uniform in [-1, 1] each held 150 to 399 samples, every output on its own."""
    r = np.zeros((n, ny))
    for i in range(ny):
        k = int(rng.integers(20, 100))
        while k < n:
            end = k + int(rng.integers(150, 400))
            r[k:end, i] = rng.uniform(-1.0, 1.0)
            k = end
    return r


def loop(plant_name: str, mismatched: bool, seed: int, variant: str, regime: str = "steps"):
    """``(model, log, data, truth, v)`` of one quiet loop under white noise :data:`NOISE` and the unmeasured
    disturbance of ``variant`` on every output (:func:`disturbance`; ``v`` None for ``none``); ``truth`` the
    mismatched elements (names).

    ``regime`` (:data:`REGIMES`): ``steps``, :func:`bench.quiet_loops.loop`'s plant, MPC and setpoint steps;
    ``levels``, the offset-free MPC (the case's with no input weight; a fat plant, case 3.3, keeps its
    own, which needs the input weight) and :func:`setpoint_levels`."""
    model, plant, mpc, _, truth = plant_of(plant_name, mismatched)      # its disturbance replaced below
    if regime == "levels":
        if plant_name == "wood-berry":
            mpc = WOOD_BERRY_OFFSET_FREE
        elif model.n_inputs <= model.n_outputs:
            mpc = dataclasses.replace(mpc, input_weight=0.0)
    v = disturbance(variant, plant_name, mismatched, seed, model.n_outputs)
    kw = {"excitation": STEPS} if regime == "steps" else {"setpoints": setpoint_levels(
        np.random.default_rng([seed, PLANTS.index(plant_name), int(mismatched), 11]), SAMPLES, model.n_outputs)}
    log = run_closed_loop(plant, model, SAMPLES, seed=seed, mpc=mpc, output_disturbance=v,
                          disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=NOISE), **kw)
    return model, log, log.as_logged_data(f"{plant_name} seed {seed}"), truth, v


def _analysed(model, data, overrides: dict) -> dict:
    t0 = time.perf_counter()
    try:
        rep = analyze(model, data, AnalysisOptions(repair=False, **overrides))
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t0}
    order = rep.noise_order or {}
    return {"located": sorted([list(x) for x in rep.located_elements]), "rows": sorted(rep.flagged_rows),
            "na_used": order.get("na"), "seconds": time.perf_counter() - t0}


def run_one(plant_name: str, mismatched: bool, seed: int, variant: str, overrides: dict,
            regime: str = "steps") -> dict:
    """One loop of one drift variant and regime, simulated and analysed both ways; a JSON-ready record."""
    model, log, data, truth, v = loop(plant_name, mismatched, seed, variant, regime)
    na = AnalysisOptions(**overrides).na
    return {"plant": plant_name, "mismatched": mismatched, "seed": seed, "variant": variant, "regime": regime,
            "truth": truth, "y_max_abs": float(np.max(np.abs(log.y))),
            "drift_std": None if v is None else float(np.std(v)),
            "fixed": _analysed(model, data, {**overrides, "max_na": na}),
            "raised": _analysed(model, data, overrides)}


def _star(args):
    return run_one(*args)


def summarize(records: list) -> dict:
    """Per regime and drift variant (key ``"steps a0.005"``), per analysis: false alarms among the clean
    runs, recall and extra elements among the mismatched ones, the histogram of the ARX order used, the
    median analysis time."""
    out = {}
    for regime in REGIMES:
        for variant in variants(regime):
            recs = [r for r in records if r.get("regime", "steps") == regime and r["variant"] == variant]
            if not recs:
                continue
            clean = [r for r in recs if not r["truth"]]      # case 3.1's plant differs from its model in no element
            bad = [r for r in recs if r["truth"]]
            drifts = [r["drift_std"] for r in recs if r["drift_std"] is not None]
            v = {"regime": regime, "variant": variant, "a": DRIFTS.get(variant), "runs": len(recs), "clean": len(clean),
                 "mismatched": len(bad), "y_max_abs": max(r["y_max_abs"] for r in recs),
                 "drift_std_mean": float(np.mean(drifts)) if drifts else None}
            for key in ANALYSES:
                ok = [r for r in recs if "error" not in r[key]]
                na = Counter(int(r[key]["na_used"]) for r in ok if r[key]["na_used"] is not None)
                v[key] = {
                    "errors": len(recs) - len(ok),
                    "false_alarms": sum(bool(r[key]["located"]) for r in ok if not r["truth"]),
                    "clean_rows_flagged": sum(bool(r[key]["rows"]) for r in ok if not r["truth"]),
                    "true_located": sum(all(t in r[key]["located"] for t in r["truth"]) for r in ok if r["truth"]),
                    "extra_located": sum(any(x not in r["truth"] for x in r[key]["located"])
                                         for r in ok if r["truth"]),
                    "na_used": {str(k): c for k, c in sorted(na.items())},
                    "seconds_median": float(np.median([r[key]["seconds"] for r in recs])),
                    "false_alarms_by_plant": {p: sum(bool(r[key]["located"]) for r in ok
                                                     if not r["truth"] and r["plant"] == p) for p in PLANTS},
                }
            out[f"{regime} {variant}"] = v
    return out


def format_table(result: dict) -> str:
    s, cfg = result["summary"], result["config"]
    sets = " ".join(f"{k}={v}" for k, v in cfg["overrides"].items()) or "defaults"
    lines = [f"drifting quiet loops: {cfg['seeds']} seeds x {len(cfg['plants'])} plants, clean and mismatched, "
             f"{cfg['samples']} samples, white noise {NOISE} + a drift (pole {DRIFT_POLE}) or another disturbance; "
             f"options: {sets}",
             "regime disturb. na      false alarms  clean rows flagged  true located  with extra elements  median s  "
             "na used",
             ]
    for key, n in s.items():
        for how in ANALYSES:
            v = n[how]
            na = " ".join(f"{k}:{c}" for k, c in v["na_used"].items()) or "-"
            lines.append(f"{n['regime']:6s} {n['variant']:8s} {how:6s} {v['false_alarms']:>5d}/{n['clean']:<6d} "
                         f"{v['clean_rows_flagged']:>8d}/{n['clean']:<9d} "
                         f"{v['true_located']:>6d}/{n['mismatched']:<6d} {v['extra_located']:>10d}/{n['mismatched']:<8d} "
                         f"{v['seconds_median']:>8.2f}  {na}" + (f"  ({v['errors']} errors)" if v["errors"] else ""))
    for how in ANALYSES:
        lines.append(f"false alarms by plant, {how}: " + "; ".join(
            f"{key}: " + ", ".join(f"{p} {c}" for p, c in n[how]["false_alarms_by_plant"].items() if c)
            for key, n in s.items() if n[how]["false_alarms"]))
    return "\n".join(lines)


def loop_keys(seeds: int) -> list:
    """``(plant, mismatched, seed, variant, regime)`` of every loop of ``seeds`` seeds, in the records' order."""
    return [(p, m, s, d, g) for g in REGIMES for p in PLANTS for m in (False, True) for s in range(seeds)
            for d in variants(g)]


def run_loops(star, tasks: list, jobs: int, every: int) -> tuple:
    """``(records, seconds)``: :func:`bench.map_runs` of ``star`` over ``tasks``, its progress every ``every`` runs
    on stderr."""
    def progress(done, total, rec):
        if done % every == 0 or done == total:
            print(f"  {done}/{total}", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    records = map_runs(star, tasks, jobs, progress)
    return records, time.perf_counter() - t0


def run(seeds: int, jobs: int = 1, overrides: Optional[dict] = None) -> dict:
    overrides = dict(overrides or {})
    AnalysisOptions(repair=False, **overrides)  # a wrong key or value fails here, not in every run
    tasks = [(p, m, s, d, overrides, g) for p, m, s, d, g in loop_keys(seeds)]
    records, seconds = run_loops(_star, tasks, jobs, 12)
    return {"config": {"seeds": seeds, "samples": SAMPLES, "drifts": DRIFTS, "other_disturbances": list(OTHER_DISTURBANCES), "drift_pole": DRIFT_POLE,
                       "noise": NOISE, "regimes": list(REGIMES), "plants": list(PLANTS), "overrides": overrides},
            "seconds": seconds, "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.drift_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=6, help="seeds per plant, clean and mismatched (default 6)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="an AnalysisOptions field for every analysis, e.g. na=10 (repeatable)")
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    try:
        overrides = parse_set(args.sets)
    except argparse.ArgumentTypeError as exc:
        p.error(str(exc))
    res = run(args.seeds, args.jobs, overrides)
    print(format_table(res))
    print(f"{res['seconds']:.0f} s")
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
