"""The recommended experiment on the Monte-Carlo: does it resolve what the data could not?

For every run of :mod:`bench.monte_carlo` (same scenarios, seeds and default design: dither in 30 %
of the runs, never forced on fat plants):

1. simulate the closed loop (3,000 samples) and analyse it as the Monte-Carlo does (``arx``,
   ``repair=False``); record the report's ``experiment``;
2. for every run with an experiment, simulate the *same* loop again (same plant, model, setpoints
   and noise seeds) with the recommended PRBS dither -- the recommended amplitude on each
   recommended input, switching with probability 1/2 every sample, nothing on the other inputs --
   for the recommended number of samples, and analyse that log.

Scored with :func:`bench.monte_carlo.score` (a located element on a true mismatch is a hit,
elsewhere a false positive; ``recall_all`` counts an ambiguous true mismatch as a miss):

* ``before``: every run's first analysis (the Monte-Carlo's figures);
* ``after``: the runs with an experiment replaced by their re-run;
* the runs with ambiguity and how many got an experiment (all should);
* the experiments: dithered inputs per run, the amplitude relative to the input's standard deviation
  in the first window, the samples (medians and quartiles); the predicted detectable gain change
  against the largest one the re-run's analysis reports for the same elements, and whether the
  re-run still has ambiguous elements.

With ``--goal-check K`` (the check of the prediction itself): for every experiment predicted to
reach its goal (a gain error of 20 % of every target element detected with probability 0.9), the
target the re-run finds hardest (the largest ``detectable_gain_change`` among the targets the model
has and that are not mismatched) is given a gain error of exactly 20 % (the plant's element
``(1 +- 0.2)`` times the model's, the sign drawn), and the experiment's loop is run ``K`` more times
with it, each with other noise seeds; a run counts when that element is located.  The prediction
promises at least 0.9 where the re-run's own value is at most 0.2.

``--still``: the loops with every setpoint held at 0 and no dither (the inputs move only with the
controller's feedback of the noise; ``bench/results/experiment_mc_still.json``).  There the inputs move
little, so half their spread, the largest amplitude allowed, rarely reaches the goal; the experiment's
``why`` then names the smallest multiple of it predicted to (``Experiment.beyond``).  With ``--beyond``
the re-run (and the goal check) of such an experiment uses that larger dither for its samples, so that
its prediction is checked too; the others are re-run as recommended.

``--small``: loops of 1 to 3 outputs and 1 to 3 inputs (:data:`bench.scenarios.SMALL`; the fat ones are 1x2, 1x3
and 2x3, where one or two outputs tie all the inputs together; ``bench/results/experiment_mc_small.json``).  The
default design's plants have 2 to 8 outputs and inputs.

Run: ``python -m bench.experiment_mc [--runs 200] [--seed 0] [--jobs 2] [--goal-check 0] [--still | --small]
[--beyond] [--out bench/results/experiment_mc.json]``
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.experiment import GOAL
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.excitation import PrbsOptions

from . import mc_parser, write_json
from .monte_carlo import ALPHA, SEPARABILITY_COLLINEAR, score, simulate
from .scenarios import SMALL, STILL, ScenarioOptions, input_separability, make_scenario

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "experiment_mc.json"


def _decisions(model, data, alpha: float):
    t0 = time.perf_counter()
    rep = analyze(model, data, AnalysisOptions(method="arx", alpha=alpha, repair=False))
    dt = time.perf_counter() - t0
    oi = {name: k for k, name in enumerate(model.outputs)}
    ii = {name: k for k, name in enumerate(model.inputs)}
    res = {"located": sorted((oi[e.output], ii[e.input]) for e in rep.elements if e.mismatch),
           "ambiguous": sorted((oi[e.output], ii[e.input]) for e in rep.elements if e.ambiguous and not e.mismatch),
           "rows": sorted(oi[r.output] for r in rep.rows if r.mismatch), "time_s": dt,
           "warnings": list(rep.warnings)}
    return rep, res


def dithered_log(scenario, dither: dict, samples: int):
    """The scenario's loop again (same seeds) with a PRBS dither of these amplitudes (input name -> amplitude)."""
    amplitudes = tuple(float(dither.get(name, 0.0)) for name in scenario.plant.inputs)
    excitation = dataclasses.replace(scenario.excitation, dither=PrbsOptions(amplitude=1.0, switch_probability=0.5),
                                     dither_amplitudes=amplitudes)
    log = run_closed_loop(scenario.plant, scenario.model, samples, seed=scenario.loop_seed, mpc=scenario.mpc,
                          excitation=excitation, disturbance=scenario.disturbance)
    return log.as_logged_data(f"scenario {scenario.seed}/{scenario.index} with the recommended dither")


def goal_check(sc, exp, rep2, targets: set, repeats: int, alpha: float) -> Optional[dict]:
    """The experiment's loop with a gain error of :data:`~mpm_monitor.core.experiment.GOAL` on its
    hardest target, ``repeats`` times with other noise seeds (module docstring); None when no target
    qualifies."""
    model = sc.model
    truth = {(m.output, m.input) for m in sc.mismatches}
    hardest = None
    for e in rep2.elements:
        i, j = model.outputs.index(e.output), model.columns.index(e.input)
        if (i, j) in truth or not model.present[i, j] or model.role(j) != "input" or e.mismatch \
                or e.detectable_gain_change is None or (e.output, e.input) not in targets:
            continue
        if hardest is None or e.detectable_gain_change > hardest[2]:
            hardest = (i, j, float(e.detectable_gain_change))
    if hardest is None:
        return None
    i, j, value = hardest
    rng = np.random.default_rng([sc.seed, sc.index, 11])
    sign = float(rng.choice([-1.0, 1.0]))
    plant = sc.plant.with_element(i, j, gain=float(model.gain[i, j]) * (1.0 + sign * GOAL))
    located = []
    for r in range(repeats):
        sc2 = dataclasses.replace(sc, plant=plant, loop_seed=int(sc.loop_seed) + 7919 * (r + 1))
        rep3, _ = _decisions(model, dithered_log(sc2, exp.dither, exp.samples), alpha)
        located.append(any(e.mismatch and (e.output, e.input) == (model.outputs[i], model.columns[j])
                           for e in rep3.elements))
    return {"target": [model.outputs[i], model.columns[j]], "detectable_rerun": value, "sign": sign,
            "located": located}


def one(seed: int, index: int, samples: int, alpha: float = ALPHA,
        options: ScenarioOptions = ScenarioOptions(), goal_repeats: int = 0, beyond: bool = False) -> dict:
    """Run ``index`` of family ``seed``: the first analysis and, with an experiment, the re-run (and the
    goal check, ``goal_repeats`` > 0); with ``beyond``, an experiment out of reach is re-run with the larger
    dither its ``why`` names (``Experiment.beyond``), when it names one."""
    sc = make_scenario(seed, index, options)
    data = simulate(sc, samples)
    sep = input_separability(data.u)
    rec = sc.describe()
    rec["separability"] = [float(x) for x in sep]
    rec["collinear_inputs"] = [int(j) for j in np.flatnonzero(sep < SEPARABILITY_COLLINEAR)]
    rep, res = _decisions(sc.model, data, alpha)
    rec["results"] = {"arx": res}
    exp = rep.experiment
    rec["experiment"] = exp.to_dict() if exp is not None else None
    if exp is not None:
        rec["experiment"]["beyond"] = exp.beyond          # the larger dither the why names (not in the report's JSON)
    if exp is None:
        return rec
    std = data.u.std(axis=0)
    rec["experiment_relative_amplitude"] = {k: float(v / std[sc.model.inputs.index(k)]) if std[
        sc.model.inputs.index(k)] > 0 else None for k, v in exp.dither.items()}
    larger = beyond and exp.beyond is not None
    plan = SimpleNamespace(dither=exp.beyond["dither"], samples=exp.beyond["samples"]) if larger else exp
    rec["rerun_dither"] = "beyond" if larger else "recommended"
    t0 = time.perf_counter()
    data2 = dithered_log(sc, plan.dither, plan.samples)
    sim_time = time.perf_counter() - t0
    rep2, res2 = _decisions(sc.model, data2, alpha)
    sep2 = input_separability(data2.u)
    rerun = dict(rec)
    rerun["separability"] = [float(x) for x in sep2]
    rerun["collinear_inputs"] = [int(j) for j in np.flatnonzero(sep2 < SEPARABILITY_COLLINEAR)]
    rerun["results"] = {"arx": res2}
    # The elements the experiment is for: the ambiguous ones (all of them when nothing was decidable).
    targets = {(e.output, e.input) for e in rep.elements if e.ambiguous} or \
        {(e.output, e.input) for e in rep.elements if not e.mismatch}
    achieved = [e.detectable_gain_change for e in rep2.elements if (e.output, e.input) in targets]
    rec["rerun"] = {"results": res2, "separability": rerun["separability"],
                    "collinear_inputs": rerun["collinear_inputs"], "simulation_time_s": sim_time,
                    "ambiguous_after": len(res2["ambiguous"]),
                    "largest_detectable_after": max((a for a in achieved if a is not None), default=None),
                    "experiment_after": rep2.experiment.to_dict() if rep2.experiment is not None else None}
    if goal_repeats > 0 and (larger or (exp.expected_detectable_gain_change is not None
                                        and exp.expected_detectable_gain_change <= GOAL + 1e-9)):
        rec["goal_check"] = goal_check(sc, plan, rep2, targets, goal_repeats, alpha)
    return rec


def _one_star(args):
    return one(*args)


def _quartiles(xs) -> Optional[list]:
    xs = [x for x in xs if x is not None]
    return [float(q) for q in np.quantile(xs, [0.25, 0.5, 0.75])] if xs else None


def summarise(records: Sequence[dict]) -> dict:
    """Scores before and after the experiments, and the experiments themselves."""
    after = []
    for r in records:
        if r.get("rerun"):
            a = dict(r)
            a["results"] = {"arx": r["rerun"]["results"]}     # as the first analysis's (score reads results["arx"])
            a["collinear_inputs"] = r["rerun"]["collinear_inputs"]
            after.append(a)
        else:
            after.append(r)
    before_s, after_s = score(records, "arx"), score(after, "arx")
    amb = [r for r in records if r["results"]["arx"]["ambiguous"]]
    exps = [r for r in records if r["experiment"]]
    # An input that did not move in the first log has no amplitude / std (None): counted apart.
    rel_all = [v for r in exps for v in r["experiment_relative_amplitude"].values()]
    rel = [v for v in rel_all if v is not None]
    samples = [r["experiment"]["samples"] for r in exps]
    predicted = [r["experiment"]["expected_detectable_gain_change"] for r in exps]
    achieved = [r["rerun"]["largest_detectable_after"] for r in exps]

    def brief(s):
        e = s["element"]
        return {"precision": e["precision"], "recall": e["recall"], "recall_all": e["recall_all"],
                "tp": e["tp"], "fp": e["fp"], "fn": e["fn"], "ambiguous_true": e["amb_true"],
                "false_alarm_runs": s["false_alarms"]["runs_with_located_element"],
                "clean_runs": s["false_alarms"]["clean_runs"], "row_precision": s["row"]["precision"],
                "row_recall": s["row"]["recall"]}

    return {
        "before": brief(before_s), "after": brief(after_s),
        "runs": len(records), "runs_with_ambiguity": len(amb),
        "runs_with_ambiguity_and_experiment": sum(1 for r in amb if r["experiment"]),
        "runs_with_experiment": len(exps),
        "runs_with_experiment_without_ambiguity": sum(1 for r in exps if not r["results"]["arx"]["ambiguous"]),
        "dithered_inputs_per_experiment": _quartiles([len(r["experiment"]["dither"]) for r in exps]),
        "inputs_per_experiment_run": _quartiles([r["shape"][1] for r in exps]),
        "relative_amplitude_quartiles": _quartiles(rel),
        "median_relative_amplitude": statistics.median(rel) if rel else None,
        "dithered_inputs_that_did_not_move": len(rel_all) - len(rel),
        "samples_quartiles": _quartiles(samples),
        "median_samples": statistics.median(samples) if samples else None,
        "experiments_reaching_goal": sum(1 for p in predicted if p is not None and p <= 0.2 + 1e-9),
        "experiments_with_a_larger_dither": sum(1 for r in exps if r["experiment"].get("beyond") is not None),
        "reruns_with_the_larger_dither": sum(1 for r in exps if r.get("rerun_dither") == "beyond"),
        "predicted_detectable_quartiles": _quartiles(predicted),
        "achieved_detectable_quartiles": _quartiles(achieved),
        "reruns_still_ambiguous": sum(1 for r in exps if r["rerun"]["ambiguous_after"]),
        "reruns_with_another_experiment": sum(1 for r in exps if r["rerun"]["experiment_after"]),
        "misses_after": after_s["misses"], "false_positives_after": after_s["false_positives"],
        **_goal_summary([r["goal_check"] for r in exps if r.get("goal_check")]),
    }


def _goal_summary(checks: list) -> dict:
    """Detection rate of the goal check, overall and by the re-run's own value (at most 0.2 or above)."""
    if not checks:
        return {}
    out = {}
    for name, sel in (("all", checks), ("rerun_at_most_goal", [c for c in checks if c["detectable_rerun"] <= GOAL]),
                      ("rerun_above_goal", [c for c in checks if c["detectable_rerun"] > GOAL])):
        hits = [x for c in sel for x in c["located"]]
        out[name] = {"experiments": len(sel), "runs": len(hits), "located": sum(hits),
                     "rate": sum(hits) / len(hits) if hits else None}
    return {"goal_check": out}


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = ALPHA,
        progress=None, goal_repeats: int = 0, still: bool = False, beyond: bool = False, small: bool = False) -> dict:
    options = STILL if still else SMALL if small else ScenarioOptions()
    tasks = [(seed, k, samples, alpha, options, goal_repeats, beyond) for k in range(runs)]
    t0 = time.perf_counter()
    records = []
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(jobs) as pool:
            for rec in pool.imap_unordered(_one_star, tasks):
                records.append(rec)
                if progress:
                    progress(len(records), runs, rec)
    else:
        for t in tasks:
            records.append(one(*t))
            if progress:
                progress(len(records), runs, records[-1])
    records.sort(key=lambda r: r["index"])
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha, "goal_repeats": goal_repeats,
                       "scenario_options": "still: every setpoint held at 0, no dither" if still else
                       "bench.scenarios.SMALL (1 to 3 outputs and inputs)" if small else
                       "bench.scenarios.ScenarioOptions() (default design)", "beyond": beyond,
                       "wall_time_s": time.perf_counter() - t0},
            "summary": summarise(records), "runs": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = mc_parser("python -m bench.experiment_mc", __doc__, 200, DEFAULT_OUT)
    parser.set_defaults(alpha=ALPHA)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--goal-check", type=int, default=0, metavar="K",
                        help="re-run every experiment predicted to reach its goal K times with a 20%% gain error on its "
                             "hardest target (module docstring; default 0: not run)")
    parser.add_argument("--still", action="store_true", help="every setpoint held at 0, no dither (module docstring)")
    parser.add_argument("--beyond", action="store_true",
                        help="re-run an experiment out of reach with the larger dither its why names")
    parser.add_argument("--small", action="store_true",
                        help="loops of 1 to 3 outputs and inputs (bench.scenarios.SMALL; module docstring)")
    args = parser.parse_args(argv)
    if args.still and args.small:
        parser.error("--still and --small: choose one")
    if args.still and args.out == DEFAULT_OUT:
        args.out = DEFAULT_OUT.with_name("experiment_mc_still.json")
    if args.small and args.out == DEFAULT_OUT:
        args.out = DEFAULT_OUT.with_name("experiment_mc_small.json")

    def progress(done, total, rec):
        if args.quiet:
            return
        e = rec["experiment"]
        tail = "no experiment" if e is None else (
            f"dither {', '.join(f'{k} {v:g}' for k, v in e['dither'].items())}, {e['samples']} samples"
            f"{' (re-run with the larger dither)' if rec.get('rerun_dither') == 'beyond' else ''}; after: "
            f"located {len(rec['rerun']['results']['located'])}, ambiguous {rec['rerun']['ambiguous_after']}")
        print(f"[{done}/{total}] run {rec['index']} {rec['shape'][0]}x{rec['shape'][1]} "
              f"{len(rec['mismatches'])} mism: {tail}", flush=True)

    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha, progress, args.goal_check, args.still,
                 args.beyond, args.small)
    s = result["summary"]
    b, a = s["before"], s["after"]
    def f3(x):
        return "-" if x is None else f"{x:.3f}"

    print(f"element recall (ambiguous = miss): {f3(b['recall_all'])} -> {f3(a['recall_all'])}; precision "
          f"{f3(b['precision'])} -> {f3(a['precision'])}")
    print(f"runs with ambiguity {s['runs_with_ambiguity']}, with an experiment "
          f"{s['runs_with_ambiguity_and_experiment']}; experiments {s['runs_with_experiment']} "
          f"(reaching the goal {s['experiments_reaching_goal']})")
    print(f"median amplitude / input std {s['median_relative_amplitude']} (dithered inputs that did not move "
          f"{s['dithered_inputs_that_did_not_move']}), median samples {s['median_samples']}; "
          f"re-runs still ambiguous {s['reruns_still_ambiguous']}")
    if s["experiments_with_a_larger_dither"]:
        print(f"experiments out of reach naming a larger dither {s['experiments_with_a_larger_dither']}, re-run with it "
              f"{s['reruns_with_the_larger_dither']}")
    for name, g in s.get("goal_check", {}).items():
        rate = "-" if g["rate"] is None else f"{g['rate']:.3f}"
        print(f"goal check ({name.replace('_', ' ')}): {g['located']} of {g['runs']} runs located the 20% gain error "
              f"({g['experiments']} experiments): {rate}")
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
