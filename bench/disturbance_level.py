"""The unexplained-disturbance tests on slow noise: their false-alarm rate and power, asymptotic and confirmed.

Run::

    python -m bench.disturbance_level [--level-draws 2000] [--power-draws 200] [--loops 200] [--samples 3000]
                                      [--seed 0] [--jobs 1] [--out bench/results/disturbance_level.json]

Each draw is one output's prediction error under a right model: the paper's noise (white noise of 7.5e-3
through ``1 / (1 - p q^-1)`` plus white measurement noise of 5e-3), at the poles ``p`` below, ``--samples``
long.  :func:`mpm_monitor.core.repair.unexplained_disturbance` tests it at its defaults (alpha 0.01: the step
and the drift test at 0.005 each, AR(4) terms), once with the asymptotic p-values (the rule before stop 86) and
once confirmed on 200 records of the fitted noise (``calibrate=True``, what the repair does).

* **level**: no disturbance; a valid test reports on 1 % of the draws (0.5 % each kind).
* **power**: a step of ``size`` times the record's standard deviation at a break drawn in [0.3, 0.7] of the
  record, or a linear drift of ``size`` standard deviations over the record.
* **the drift under measurement noise** (stop 96, appended conditions): white noise of 5e-3 through
  ``1 / (1 - p q^-1)`` plus white measurement noise of 2e-2, the drift's spread below the noise's (an ARMA(1, 1)
  whose zero is near 0.77 at pole 0.95: the tests' AR(4) leaves it coloured; an outside check's loop, a
  decentralised PI on a 2x2 plant, reported a step on 19 % of its clean runs); level at poles 0.95, 0.98 and
  0.99, power of steps and a drift at 0.95.
* **loops**: the whole repair on closed loops, where the level counts: the paper's Shell plant (3x3) under its
  MPC, the model right, the paper's disturbance at poles 0.99 and 0.998, 4,000 samples;
  :func:`~mpm_monitor.core.repair.repair_model` with nothing located, asymptotic
  (``disturbance_draws=0``) and confirmed (the default): loops whose report names a disturbance (1 % is the
  family's level).

Every draw's noise comes from its own seeded generator (``--seed``, the condition and the draw), the
confirmation from the test's default seed: the same command gives the same records.
"""

from __future__ import annotations

import argparse
import time
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.filters import lfilter
from mpm_monitor.core.repair import unexplained_disturbance

from . import map_runs, write_json

DEFAULT_OUT = "bench/results/disturbance_level.json"
LEVEL_POLES = (0.9, 0.95, 0.98, 0.99, 0.995)
POWER = tuple((kind, pole, size) for kind in ("step", "drift") for pole in (0.95, 0.99) for size in (0.5, 1.0, 2.0))
LOOP_POLES = (0.99, 0.998)
#: The drift under measurement noise (``noise = "drift"``): its level poles and its power conditions.
DRIFT_NOISE_LEVEL_POLES = (0.95, 0.98, 0.99)
DRIFT_NOISE_POWER = tuple((kind, 0.95, size) for kind, size in (("step", 0.5), ("step", 1.0), ("step", 2.0),
                                                                   ("drift", 1.0)))
LOOP_SAMPLES = 4000


def _ar1_under_white(rng: np.random.Generator, n: int, pole: float, innovation: float, white: float) -> np.ndarray:
    """Shape (n,): white noise of ``innovation`` through ``1 / (1 - pole q^-1)`` from its stationary state (a burn-in
    of ``5 / (1 - pole)`` samples), plus white noise of ``white`` (drawn in that order)."""
    burn = int(np.ceil(5.0 / (1.0 - pole)))
    w = rng.normal(0.0, innovation, n + burn)
    return lfilter([1.0], [1.0, -pole], w)[burn:] + rng.normal(0.0, white, n)


def paper_noise(rng: np.random.Generator, n: int, pole: float) -> np.ndarray:
    """The paper's output disturbance and measurement noise, shape (n,): innovation 7.5e-3, measurement 5e-3."""
    return _ar1_under_white(rng, n, pole, 7.5e-3, 5e-3)


def drift_noise(rng: np.random.Generator, n: int, pole: float) -> np.ndarray:
    """A slow drift under white measurement noise, shape (n,): innovation 5e-3, measurement 2e-2."""
    return _ar1_under_white(rng, n, pole, 5e-3, 2e-2)


def run_one(seed: int, condition: int, draw: int, kind: str, pole: float, size: float, samples: int,
            noise: str = "paper") -> dict:
    """One draw: its noise (``"paper"`` or ``"drift"``), the disturbance added, and both tests' results; a
    JSON-ready record."""
    rng = np.random.default_rng([seed, condition, draw])
    d = (paper_noise if noise == "paper" else drift_noise)(rng, samples, pole)
    at = None
    if kind == "step" and size:
        at = int(rng.uniform(0.3, 0.7) * samples)
        d[at:] += size * d.std()
    elif kind == "drift" and size:
        d += size * d.std() * np.arange(samples) / samples
    rec = {"condition": condition, "draw": draw, "kind": kind, "pole": pole, "size": size, "at": at}
    if noise != "paper":
        rec["noise"] = noise
    for key, calibrate in (("plain", False), ("confirmed", True)):
        out = unexplained_disturbance(d, calibrate=calibrate)
        rec[key] = {"reported": out["kind"] if out["detected"] else None, "p_step": out["p_step"],
                    "p_drift": out["p_drift"], "scale_step": out["null_scale_step"],
                    "scale_drift": out["null_scale_drift"]}
    return rec


def run_loop(seed: int, condition: int, draw: int, pole: float) -> dict:
    """One closed loop of the Shell plant, its model right, under the paper's disturbance at ``pole``; the repair's
    disturbance reports without and with the confirmation; a JSON-ready record."""
    from mpm_monitor.core.repair import RepairOptions, repair_model
    from mpm_monitor.sim.cases import shell_plant
    from mpm_monitor.sim.closed_loop import run_closed_loop
    from mpm_monitor.sim.plant import DisturbanceOptions

    plant = shell_plant()
    data = run_closed_loop(plant, plant, LOOP_SAMPLES, seed=int(np.random.default_rng([seed, condition, draw])
                                                                 .integers(2 ** 31)),
                           disturbance=DisturbanceOptions(disturbance_pole=pole)).as_logged_data()
    rec = {"condition": condition, "draw": draw, "kind": "loop", "pole": pole, "size": 0.0, "at": None}
    for key, options in (("plain", RepairOptions(disturbance_draws=0)), ("confirmed", RepairOptions())):
        found = repair_model(plant, data, [], options).disturbances
        rec[key] = {"reported": found[0]["kind"] if found else None, "outputs": [x["output"] for x in found],
                    "p_step": None, "p_drift": None, "scale_step": 1.0, "scale_drift": 1.0}
    return rec


def _run_star(args):
    if args[3] == "loop":
        return run_loop(args[0], args[1], args[2], args[4])
    return run_one(*args)


def summarize(records: Sequence[dict]) -> list:
    """Per condition: draws, and for each rule the reports (any kind, steps, drifts) and the median scales."""
    out = []
    for key in sorted({(r["condition"], r["kind"], r["pole"], r["size"]) for r in records}):
        recs = [r for r in records if (r["condition"], r["kind"], r["pole"], r["size"]) == key]
        row = {"condition": key[0], "kind": key[1], "pole": key[2], "size": key[3], "draws": len(recs)}
        if recs[0].get("noise", "paper") != "paper":
            row["noise"] = recs[0]["noise"]
        for rule in ("plain", "confirmed"):
            rep = [r[rule]["reported"] for r in recs]
            row[rule] = {"reported": sum(x is not None for x in rep), "steps": rep.count("step"),
                         "drifts": rep.count("drift")}
        scaled = [r["confirmed"]["scale_step"] for r in recs if r["kind"] != "loop" and
                  (r["confirmed"]["scale_step"] != 1.0 or r["plain"]["reported"])]
        row["median_scale_step_confirmed"] = float(np.median(scaled)) if scaled else None
        out.append(row)
    return out


def format_table(summary: Sequence[dict]) -> str:
    lines = ["unexplained-disturbance tests on the paper's noise (alpha 0.01: 0.5 % each kind); reports of "
             "draws, asymptotic -> confirmed (*: the drift under measurement noise)",
             f"{'what':<8}{'pole':>6}{'size':>6}{'draws':>7}{'reported':>20}{'steps':>14}{'drifts':>14}"
             f"{'rate':>18}"]
    for s in summary:
        what = s["kind"] if s["kind"] == "loop" or s["size"] else "level"
        what = f"{what}*" if s.get("noise") == "drift" else what
        p, c, n = s["plain"], s["confirmed"], s["draws"]
        lines.append(f"{what:<8}{s['pole']:>6g}{s['size']:>6g}{n:>7}{p['reported']:>10} -> {c['reported']:<6}"
                     f"{p['steps']:>6} -> {c['steps']:<5}{p['drifts']:>6} -> {c['drifts']:<5}"
                     f"{100 * p['reported'] / n:>8.2f} -> {100 * c['reported'] / n:.2f} %")
    return "\n".join(lines)


def run(level_draws: int = 2000, power_draws: int = 200, samples: int = 3000, seed: int = 0, jobs: int = 1,
        progress: bool = False, loops: int = 0) -> dict:
    # The drift-noise conditions come last, so that the other conditions keep their numbers (and draws).
    conditions = ([("level", pole, 0.0, "paper") for pole in LEVEL_POLES] + [c + ("paper",) for c in POWER]
                  + [("loop", p, 0.0, "paper") for p in LOOP_POLES]
                  + [("level", pole, 0.0, "drift") for pole in DRIFT_NOISE_LEVEL_POLES]
                  + [c + ("drift",) for c in DRIFT_NOISE_POWER])
    count = {"level": level_draws, "loop": loops}
    todo = [(seed, c, k, kind, pole, size, samples, noise)
            for c, (kind, pole, size, noise) in enumerate(conditions)
            for k in range(count.get(kind, power_draws))]
    t0 = time.perf_counter()
    records = map_runs(_run_star, todo, jobs,
                       progress=(lambda done, total, _: print(f"{done}/{total}", flush=True)) if progress else None)
    return {"config": {"level_draws": level_draws, "power_draws": power_draws, "loops": loops,
                       "loop_samples": LOOP_SAMPLES, "samples": samples, "seed": seed, "jobs": jobs,
                       "wall_time_s": time.perf_counter() - t0},
            "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.disturbance_level", description=__doc__.split("\n\n")[0])
    p.add_argument("--level-draws", type=int, default=2000, help="draws per pole without a disturbance (default 2000)")
    p.add_argument("--power-draws", type=int, default=200, help="draws per step or drift condition (default 200)")
    p.add_argument("--loops", type=int, default=200, help="closed loops per pole (default 200)")
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--progress", action="store_true")
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    for flag, value, least in (("--level-draws", args.level_draws, 0), ("--power-draws", args.power_draws, 0),
                               ("--loops", args.loops, 0),
                               ("--samples", args.samples, 100), ("--jobs", args.jobs, 1)):
        if value < least:
            p.error(f"{flag}: expected an integer >= {least}, got {value}")
    result = run(args.level_draws, args.power_draws, args.samples, args.seed, args.jobs, args.progress, args.loops)
    print(format_table(result["summary"]))
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
