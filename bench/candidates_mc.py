"""Candidate channels: the false-alarm level on unrelated channels, and the detection of an undeclared effect.

Two Monte-Carlo studies on the Shell loop of :mod:`mpm_monitor.sim.undeclared` (3000 samples, the
paper's setpoint PRBS, disturbance and noise, the model matching the plant):

1. **Level.**  The log holds only channels the plant ignores: two Gaussian random walks (step std
   0.05 and 0.5), two first-order filtered noises (poles 0.9 and 0.98) and the undeclared channel's
   signal with a gain of 0 (steps plus filtered noise).  The analysis (``alpha`` 0.01, no repair)
   tries all of them; a run in which any candidate is located is a false alarm, which must happen
   in at most ``alpha`` of the runs.  Also counted: runs with an element located (the model matches
   the plant), and channels called "not exogenous" (they are exogenous: Holm's level over the
   candidates bounds that too).
2. **Detection.**  The undeclared channel drives ``y1`` (gain 0.8, time constant 30 s, dead time
   4 s); the log also holds a random walk, a filtered noise and ``u2_flow``, a response of an
   intermediate flow to ``u2``.  The full analysis with the repair: how often the channel is
   located and added, the fitted element against the truth, ``y1``'s error after the repair
   against the noise floor, and that no decoy is ever added and ``u2_flow`` is reported as not
   exogenous.

``--setpoint-steps``: both studies on the loop with its setpoints moved in rare steps (at least 60
samples apart, then 1 % a sample: about 30 steps in 3000 samples), as operators move them,
instead of the paper's PRBS.  The inputs then move sharply at each step and little between them.
The level study adds two channels changed by hand in six steps without noise (a feed set by an
operator): one at random times, one with a step 1 to 5 samples after a setpoint step, by chance.
Such a channel's own-lag residual is six spikes; the lags of the inputs can fit one that follows
their sharp move, and the exogeneity test's F test alone then called it "not exogenous" far beyond
its level.  Each run records, per channel, whether the F test alone (Holm's procedure over the
run's candidates) would have called it so, beside the test's decision.

Run: ``python -m bench.candidates_mc [--runs 200] [--detection-runs 50] [--seed 0] [--jobs 1] [--setpoint-steps]``
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import time

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.statistics import holm_adjust
from mpm_monitor.sim.closed_loop import ExcitationOptions
from mpm_monitor.sim.excitation import PrbsOptions
from mpm_monitor.sim.undeclared import (
    EFFECT_CHANNEL,
    LOOP_CHANNEL,
    UndeclaredEffect,
    filtered_noise,
    random_walk,
    undeclared_effect_run,
)

from . import write_json

ALPHA = 0.01
#: The unrelated channels of the level study: name -> (kind, generator of n samples from an rng).
NULL_CHANNELS = {
    "walk_small": ("random walk", lambda n, rng: random_walk(n, 0.05, rng)),
    "walk_large": ("random walk", lambda n, rng: random_walk(n, 0.5, rng)),
    "noise_fast": ("filtered noise", lambda n, rng: filtered_noise(n, 1.0, 0.9, rng)),
    "noise_slow": ("filtered noise", lambda n, rng: filtered_noise(n, 1.0, 0.98, rng)),
}
#: ``--setpoint-steps``: the setpoints move in steps, at least 60 samples apart (about 30 in 3000 samples).
SETPOINT_STEPS = ExcitationOptions(setpoint=PrbsOptions(amplitude=1.0, switch_probability=0.01, min_hold=60))
#: Steps of a channel changed by hand.
HAND_STEPS = 6
#: The channels changed by hand of the level study with ``--setpoint-steps``.
HAND_CHANNELS = {"hand_steps": "steps by hand", "hand_steps_after_setpoint": "steps by hand, one after a setpoint step"}


def hand_steps(n: int, rng: np.random.Generator, setpoint_steps=None) -> np.ndarray:
    """A channel changed by hand: ``HAND_STEPS`` steps to uniform levels in [-1, 1] at random times (at
    least 50 samples from either end), no noise, shape (n,).  Given ``setpoint_steps`` (sample indices),
    one of the steps falls 1 to 5 samples after one of them, drawn at random."""
    times = rng.choice(np.arange(50, n - 50), HAND_STEPS, replace=False)
    if setpoint_steps is not None and len(setpoint_steps):
        times[0] = min(int(rng.choice(setpoint_steps)) + int(rng.integers(1, 6)), n - 1)
    x = np.full(n, rng.uniform(-1.0, 1.0))
    for t in np.sort(times):
        x[t:] = rng.uniform(-1.0, 1.0)
    return x


def null_run(seed: int, index: int, samples: int, alpha: float = ALPHA, setpoint_steps: bool = False) -> dict:
    """One run of the level study."""
    run = undeclared_effect_run(samples, seed=1000 * seed + index, effect=UndeclaredEffect(gain=0.0),
                                loop_channel=False, excitation=SETPOINT_STEPS if setpoint_steps else None)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, index, 7]).spawn(len(NULL_CHANNELS))]
    extra = {EFFECT_CHANNEL: run.data.extra[EFFECT_CHANNEL]}
    extra.update({name: make(samples, rng) for (name, (_, make)), rng in zip(NULL_CHANNELS.items(), rngs)})
    if setpoint_steps:
        rng = np.random.default_rng([seed, index, 11])
        moves = np.flatnonzero(np.any(np.diff(run.data.r, axis=0) != 0, axis=1)) + 1
        extra["hand_steps"] = hand_steps(samples, rng)
        extra["hand_steps_after_setpoint"] = hand_steps(samples, rng, moves)
    run.data.extra = extra
    rep = analyze(run.model, run.data, AnalysisOptions(alpha=alpha, repair=False), candidates="all")
    cands = rep.candidates
    return {"index": index,
            "located": sorted({c for _, c in cands.located}),
            "not_exogenous": sorted(cands.not_exogenous),
            "not_exogenous_by_f_alone": _f_alone(cands, alpha),
            "elements_located": [list(k) for k in rep.located_elements if k[1] not in extra],
            "min_p": min((p for ps in cands.p_values.values() for p in ps.values()), default=1.0),
            "raw_p": {name: {e.output: e.p_value_raw for e in rep.elements if e.role == "candidate" and e.input == name}
                      for name in cands.p_values}}


def _f_alone(cands, alpha: float) -> list:
    """The candidates the exogeneity test's F test alone would have called not exogenous (Holm's
    procedure over the run's candidates at ``alpha``, as the analysis adjusts its own p-values)."""
    names = sorted(cands.exogeneity_tests)
    p = [cands.exogeneity_tests[n].p_value_f for n in names]
    p = [1.0 if not np.isfinite(v) else v for v in p]
    return [n for n, a in zip(names, holm_adjust(p) if names else []) if a < alpha]


def detection_run(seed: int, index: int, samples: int, alpha: float = ALPHA, setpoint_steps: bool = False,
                  effect_delay: float = UndeclaredEffect.delay) -> dict:
    """One run of the detection study (the undeclared effect's dead time ``effect_delay``, seconds)."""
    effect = UndeclaredEffect(delay=effect_delay)
    run = undeclared_effect_run(samples, seed=5000 + 1000 * seed + index, effect=effect,
                                excitation=SETPOINT_STEPS if setpoint_steps else None)
    t0 = time.perf_counter()
    rep = analyze(run.model, run.data, AnalysisOptions(alpha=alpha), candidates="all")
    dt = time.perf_counter() - t0
    cands = rep.candidates
    el = None
    if EFFECT_CHANNEL in cands.added:
        m = rep.repaired_model
        el = m.element(m.outputs.index(effect.output), m.columns.index(EFFECT_CHANNEL))
    out = effect.output
    return {"index": index, "time_s": dt,
            "located": [list(k) for k in cands.located], "added": list(cands.added),
            "loop_not_exogenous": LOOP_CHANNEL in cands.not_exogenous,
            "not_exogenous": sorted(cands.not_exogenous),
            "not_exogenous_by_f_alone": _f_alone(cands, alpha),
            "element": el, "truth": {"gain": effect.gain, "time_constant": effect.time_constant,
                                     "delay": effect.delay},
            "error_before": rep.repair["error_before"][out], "error_after": rep.repair["error_after"][out],
            "floor": run.noise_floor[out]}


def _star(args):
    kind, seed, index, samples, alpha, setpoint_steps, effect_delay = args
    if kind == "null":
        return null_run(seed, index, samples, alpha, setpoint_steps)
    return detection_run(seed, index, samples, alpha, setpoint_steps, effect_delay)


def _map(jobs: int, tasks: list) -> list:
    if jobs > 1:
        with mp.get_context("spawn").Pool(int(jobs)) as pool:
            return pool.map(_star, tasks, chunksize=1)
    return [_star(t) for t in tasks]


def run(runs: int, detection_runs: int, seed: int, samples: int, jobs: int = 1, alpha: float = ALPHA,
        setpoint_steps: bool = False, effect_delay: float = UndeclaredEffect.delay) -> dict:
    """Both studies; the result as JSON-ready data (see the module docstring)."""
    nulls = _map(jobs, [("null", seed, k, samples, alpha, setpoint_steps, effect_delay) for k in range(runs)])
    dets = _map(jobs, [("det", seed, k, samples, alpha, setpoint_steps, effect_delay) for k in range(detection_runs)])
    kinds = {name: kind for name, (kind, _) in NULL_CHANNELS.items()}
    kinds[EFFECT_CHANNEL] = "steps plus filtered noise"
    if setpoint_steps:
        kinds.update(HAND_CHANNELS)
    by_kind = {}
    for kind in sorted(set(kinds.values())):
        names = [n for n, k in kinds.items() if k == kind]
        by_kind[kind] = {"channels": len(names) * runs,
                         "located": sum(len(set(r["located"]) & set(names)) for r in nulls),
                         "runs_with_one_located": sum(bool(set(r["located"]) & set(names)) for r in nulls),
                         "not_exogenous": sum(len(set(r["not_exogenous"]) & set(names)) for r in nulls),
                         "not_exogenous_by_f_alone": sum(len(set(r["not_exogenous_by_f_alone"]) & set(names))
                                                         for r in nulls),
                         "raw_tests": sum(len(r["raw_p"].get(n, {})) for r in nulls for n in names),
                         "raw_below_5pct": sum(p < 0.05 for r in nulls for n in names
                                               for p in r["raw_p"].get(n, {}).values())}
        k = by_kind[kind]
        k["raw_rejection_at_5pct"] = k["raw_below_5pct"] / max(k["raw_tests"], 1)
    level = {"runs": runs, "alpha": alpha,
             "false_alarm_rate": sum(bool(r["located"]) for r in nulls) / runs,
             "runs_with_not_exogenous": sum(bool(r["not_exogenous"]) for r in nulls) / runs,
             "runs_with_not_exogenous_by_f_alone": sum(bool(r["not_exogenous_by_f_alone"]) for r in nulls) / runs,
             "runs_with_element_located": sum(bool(r["elements_located"]) for r in nulls) / runs,
             "by_kind": by_kind}
    fitted = [d for d in dets if d["element"] is not None]

    def rel(key):
        return [abs(d["element"][key] - d["truth"][key]) / abs(d["truth"][key]) for d in fitted]

    detection = {"runs": detection_runs,
                 "located_rate": sum(any(c == EFFECT_CHANNEL for _, c in d["located"]) for d in dets) / detection_runs,
                 "added_rate": len(fitted) / detection_runs,
                 "decoys_added": sum(len([a for a in d["added"] if a != EFFECT_CHANNEL]) for d in dets),
                 "loop_channel_not_exogenous_rate": sum(d["loop_not_exogenous"] for d in dets) / detection_runs,
                 "effect_channel_not_exogenous": sum(EFFECT_CHANNEL in d["not_exogenous"] for d in dets),
                 "effect_channel_not_exogenous_by_f_alone": sum(EFFECT_CHANNEL in d["not_exogenous_by_f_alone"]
                                                                for d in dets),
                 "gain_within_10pct": sum(e <= 0.1 for e in rel("gain")) / max(len(fitted), 1),
                 "time_constant_within_10pct": sum(e <= 0.1 for e in rel("time_constant")) / max(len(fitted), 1),
                 "delay_within_1_sample": sum(abs(d["element"]["delay"] - d["truth"]["delay"]) <= 1.0
                                              for d in fitted) / max(len(fitted), 1),
                 "gain_error_median": statistics.median(rel("gain")) if fitted else None,
                 "time_constant_error_median": statistics.median(rel("time_constant")) if fitted else None,
                 "after_over_floor_median": statistics.median(d["error_after"] / d["floor"] for d in dets),
                 "after_over_floor_max": max(d["error_after"] / d["floor"] for d in dets),
                 "after_within_10pct_of_floor": sum(d["error_after"] <= 1.1 * d["floor"] for d in dets)
                 / detection_runs,
                 "before_over_floor_median": statistics.median(d["error_before"] / d["floor"] for d in dets),
                 "median_analyze_s": statistics.median(d["time_s"] for d in dets)}
    return {"seed": seed, "samples": samples, "setpoints": "steps" if setpoint_steps else "paper PRBS",
            "effect_delay": effect_delay,
            "level": level, "detection": detection, "null_runs": nulls, "detection_runs": dets}


def format_table(res: dict) -> str:
    lv, dt = res["level"], res["detection"]
    steps = res.get("setpoints") == "steps"
    n_channels = len(NULL_CHANNELS) + 1 + (len(HAND_CHANNELS) if steps else 0)
    lines = [f"candidate channels, Shell loop{', setpoints in steps' if steps else ''}, {res['samples']} samples, "
             f"alpha {lv['alpha']:g} (seed {res['seed']})",
             f"level: {lv['runs']} runs with {n_channels} unrelated candidates each",
             f"  runs with any candidate located: {lv['false_alarm_rate']:.3f} (alpha {lv['alpha']:g})"]
    width = max(len(kind) for kind in lv["by_kind"])
    for kind, k in lv["by_kind"].items():
        lines.append(f"  {kind:<{width}} located {k['located']} of {k['channels']} channels "
                     f"(in {k['runs_with_one_located']} runs); called not exogenous {k['not_exogenous']} "
                     f"(F test alone {k['not_exogenous_by_f_alone']}); "
                     f"unadjusted p < 0.05 in {k['raw_rejection_at_5pct']:.3f} of {k['raw_tests']} tests")
    lines.append(f"  runs with a candidate called not exogenous: {lv['runs_with_not_exogenous']:.3f} "
                 f"(F test alone {lv['runs_with_not_exogenous_by_f_alone']:.3f}); "
                 f"runs with a model element located: {lv['runs_with_element_located']:.3f}")
    lines.append(f"detection: {dt['runs']} runs, {EFFECT_CHANNEL} on y1 (gain 0.8, 30 s, "
                 f"{res.get('effect_delay', UndeclaredEffect.delay):g} s)")
    lines.append(f"  located {dt['located_rate']:.3f}, added {dt['added_rate']:.3f}; decoys added: "
                 f"{dt['decoys_added']}; {LOOP_CHANNEL} reported not exogenous "
                 f"{dt['loop_channel_not_exogenous_rate']:.3f}; {EFFECT_CHANNEL} reported not exogenous in "
                 f"{dt['effect_channel_not_exogenous']} runs (F test alone "
                 f"{dt['effect_channel_not_exogenous_by_f_alone']})")
    if dt["gain_error_median"] is not None:
        lines.append(f"  gain within 10%: {dt['gain_within_10pct']:.3f} (median error {dt['gain_error_median']:.3f}); "
                     f"time constant within 10%: {dt['time_constant_within_10pct']:.3f} (median error "
                     f"{dt['time_constant_error_median']:.3f}); delay within 1 sample: "
                     f"{dt['delay_within_1_sample']:.3f}")
    lines.append(f"  y1 error / noise floor: before {dt['before_over_floor_median']:.2f} (median), after "
                 f"{dt['after_over_floor_median']:.3f} (median), {dt['after_over_floor_max']:.3f} (max); within 10% "
                 f"of the floor {dt['after_within_10pct_of_floor']:.3f}")
    lines.append(f"  median analyze time with the repair: {dt['median_analyze_s']:.2f} s")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.candidates_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200, help="runs of the level study (default 200)")
    p.add_argument("--detection-runs", type=int, default=50, help="runs of the detection study (default 50)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--alpha", type=float, default=ALPHA, help=f"false-alarm rate of the analysis (default {ALPHA})")
    p.add_argument("--setpoint-steps", action="store_true",
                   help="setpoints in rare steps instead of the paper's PRBS, and two channels changed by hand")
    p.add_argument("--effect-delay", type=float, default=UndeclaredEffect.delay,
                   help=f"dead time of the undeclared effect in the detection study, seconds (default "
                        f"{UndeclaredEffect.delay:g}; the model's longest is 7 samples of 1 s)")
    p.add_argument("--out", default=None, help="JSON results (default bench/results/candidates_mc.json, "
                                               "with --setpoint-steps candidates_mc_setpoint_steps.json)")
    args = p.parse_args(argv)
    if args.runs < 1 or args.detection_runs < 1 or args.jobs < 1 or args.samples < 500 or not 0 < args.alpha < 0.5:
        p.error("--runs, --detection-runs and --jobs must be >= 1, --samples >= 500 and --alpha in (0, 0.5)")
    if args.out is None:
        args.out = ("bench/results/candidates_mc_setpoint_steps.json" if args.setpoint_steps
                    else "bench/results/candidates_mc.json")
    res = run(args.runs, args.detection_runs, args.seed, args.samples, args.jobs, args.alpha, args.setpoint_steps,
              args.effect_delay)
    print(format_table(res))
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
