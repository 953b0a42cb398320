"""The repair's held-out check against the truth, over the Monte-Carlo loops of ``bench.repair_mc``.

Every held-out check the repair makes (one per output row with a re-estimated element) is recorded:
the candidate's and the given model's held-out simulation errors and one-step errors (each model
under its own AR noise model), the one-sided p-value of a rise of the simulation error, and the
decision.  The truth is the plant: a candidate is *better* when its row's simulated response to the
logged inputs is closer to the plant's over the held-out part than the given model's is (RMS of
``yhat_plant - yhat_model`` about its level).  Scored for three rules: the simulation error alone
(``RepairOptions(holdout_one_step=False)``, the default before stop 77); the default (also accepted when the
one-step error is significantly smaller and the simulation error not significantly larger, each at
``holdout_alpha``, nor larger by more than ``holdout_tolerance``, 5 %); and that route unbounded
(``holdout_tolerance=None``):

- accepted but worse (a wrong repair let through: the check's false acceptances);
- refused but better (a right repair held back).

Checks on rows re-estimated with an unexplained step or drift, or on data with gaps, are counted but
not scored.

Wrong candidates are rare among the fitted ones, so each scored check is also made on deliberately
wrong candidates (:data:`PERTURBATIONS`: the fitted candidate with every re-estimated element's gain
halved or raised by half, or its time constant doubled; each model again under its own AR noise
model): of those that are worse than the model as given, how many each rule accepts.

Run: ``python -m bench.holdout_mc [--runs 200] [--seed 0] [--samples 3000] [--setpoint-steps]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import RepairOptions, model_repair, validation
from mpm_monitor.core.repair.holdout import loss_rise_p_value
from mpm_monitor.sim.closed_loop import run_closed_loop

from . import write_json
from .scenarios import SETPOINT_STEPS, ScenarioOptions, make_scenario


#: The wrong candidates made of each fitted one: (name, gain factor, time-constant factor).
PERTURBATIONS = (("gain x0.5", 0.5, 1.0), ("gain x1.5", 1.5, 1.0), ("time constant x2", 1.0, 2.0))


def _truth(rec, d, d_p) -> float:
    """RMS over the held-out part (about the fit part's level) of ``d - d_p`` = ``yhat_plant - yhat``."""
    return float(np.sqrt(np.mean(rec.holdout_residual(d - d_p, None) ** 2)))


def _one_step_rule(check, alpha: float) -> bool:
    """The decision of ``RepairOptions(holdout_tolerance=None)`` (the one-step route unbounded) on a check made with
    the default options (its p-values are computed either way)."""
    return bool(check.after < check.before or (check.p_one_step is not None
                                               and check.p_one_step < alpha <= check.p_rise))


def _perturbed(rec, i, candidate, js, d_p, truth_before) -> list:
    """The held-out check of each :data:`PERTURBATIONS` of ``candidate``'s elements ``js`` in row ``i``."""
    out = []
    for name, gain, tau in PERTURBATIONS:
        wrong = candidate
        for j in js:
            el = candidate.element(i, j)
            if tau != 1.0 and el["time_constant"] <= 0:
                break
            wrong = wrong.with_element(i, j, gain=el["gain"] * gain, time_constant=el["time_constant"] * tau)
        else:
            check = validation._compare_on_holdout(rec, i, wrong)
            truth = _truth(rec, np.asarray(rec.signals_of(wrong).d[:, i], float), d_p)
            out.append({"perturbation": name, "accepted": check.accepted,
                        "simulation_alone": check.after < check.before, "worse": truth >= truth_before,
                        "one_step_rule": _one_step_rule(check, rec.options.holdout_alpha),
                        "simulation_after": check.after, "simulation_before": check.before,
                        "one_step_after": check.one_step_after, "one_step_before": check.one_step_before,
                        "p_rise": check.p_rise, "p_one_step": check.p_one_step, "truth": truth,
                        "truth_before": truth_before})
    return out


def _recorder(plant, checks: list):
    """A wrapper of the repair's held-out check that records what it compared (and leaves its decision)."""
    validate = model_repair._validate_on_holdout

    def record(rec, row, js, elements, warnings):
        check = validate(rec, row, js, elements, warnings)
        model, i = rec.model, row.i
        entry = {"output": model.outputs[i], "inputs": [model.columns[j] for j in js], "accepted": check.accepted}
        if check.after is None or row.extra is not None or rec.segments is not None or model.is_step_response:
            checks.append(dict(entry, scored=False))
            return check
        candidate, fitted = model, []
        for j, el in elements.items():
            if el.apply or el.reason == "rejected by held-out validation":
                candidate = el.applied_to(candidate, i, j)
                fitted.append(j)
        d_c = np.asarray(rec.signals_of(candidate).d[:, i], float)
        d_0 = np.asarray(rec.d0[:, i], float)
        d_p = np.asarray(rec.signals_of(plant).d[:, i], float)
        p = loss_rise_p_value(rec.holdout_residual(d_c, None), rec.holdout_residual(d_0, None))
        alpha = rec.options.holdout_alpha
        # yhat_plant - yhat = d - d_plant: the candidate's and the model's distance to the plant's response
        truth_after, truth_before = _truth(rec, d_c, d_p), _truth(rec, d_0, d_p)
        checks.append(dict(entry, scored=True, simulation_after=check.after, simulation_before=check.before,
                           one_step_after=check.one_step_after, one_step_before=check.one_step_before,
                           p_rise=p, truth_after=truth_after, truth_before=truth_before,
                           better=truth_after < truth_before, simulation_alone=check.after < check.before,
                           p_one_step=check.p_one_step, one_step_rule=_one_step_rule(check, alpha),
                           perturbed=_perturbed(rec, i, candidate, fitted, d_p, truth_before)))
        return check

    return record


def one(seed: int, index: int, samples: int, options: ScenarioOptions) -> list:
    sc = make_scenario(seed, index, options)
    log = run_closed_loop(sc.plant, sc.model, samples, seed=sc.loop_seed, mpc=sc.mpc, excitation=sc.excitation,
                          disturbance=sc.disturbance)
    checks = []
    validate = model_repair._validate_on_holdout
    model_repair._validate_on_holdout = _recorder(sc.plant, checks)
    try:
        analyze(sc.model, log.as_logged_data(), AnalysisOptions())
    finally:
        model_repair._validate_on_holdout = validate
    return [dict(c, run=index) for c in checks]


RULES = (("simulation error alone", "simulation_alone"),
         (f"one step, within {100 * RepairOptions().holdout_tolerance:g} % (default)", "accepted"),
         ("one step, unbounded", "one_step_rule"))


def summarize(checks: list) -> dict:
    scored = [c for c in checks if c["scored"]]
    wrong = [w for c in scored for w in c.get("perturbed", []) if w["worse"]]

    def tally(key):
        return {"accepted": sum(c[key] for c in scored),
                "accepted_but_worse": sum(c[key] and not c["better"] for c in scored),
                "refused_but_better": sum(not c[key] and c["better"] for c in scored),
                "wrong_made_accepted": sum(w[key] for w in wrong)}

    def row(c):
        return {k: c[k] for k in ("run", "output", "inputs", "simulation_after", "simulation_before", "one_step_after",
                                  "one_step_before", "p_one_step", "p_rise", "better")}

    return {"checks": len(checks), "scored": len(scored), "better": sum(c["better"] for c in scored),
            "worse": sum(not c["better"] for c in scored),
            "wrong_made": sum(len(c.get("perturbed", [])) for c in scored), "wrong_made_worse": len(wrong),
            "rules": {key: tally(key) for _, key in RULES},
            "differ": [row(c) for c in scored if c["accepted"] != c["simulation_alone"]],
            "unbounded_only": [row(c) for c in scored if c["one_step_rule"] and not c["accepted"]],
            "refused": [row(c) for c in scored if not c["accepted"]]}


def format_table(res: dict) -> str:
    lines = [f"held-out checks: {res['checks']} ({res['scored']} scored); candidates better than the model as given "
             f"(closer to the plant's response over the held-out part): {res['better']}, worse: {res['worse']}",
             f"wrong candidates made ({', '.join(p[0] for p in PERTURBATIONS)} of each scored one): "
             f"{res['wrong_made']}, worse than the model as given: {res['wrong_made_worse']}"]
    for title, key in RULES:
        t = res["rules"][key]
        lines.append(f"  {title:<31} accepted {t['accepted']:4d}   accepted but worse {t['accepted_but_worse']:3d}   "
                     f"refused but better {t['refused_but_better']:3d}   wrong made accepted "
                     f"{t['wrong_made_accepted']:3d} of {res['wrong_made_worse']}")

    def fmt(c):
        p1 = "-" if c["p_one_step"] is None else f"{c['p_one_step']:.2g}"
        return (f"  run {c['run']:3d} {c['output']} ({', '.join(c['inputs'])}): simulation "
                f"{c['simulation_after']:.4g} vs {c['simulation_before']:.4g}, one step {c['one_step_after']:.4g} vs "
                f"{c['one_step_before']:.4g}, p(one step smaller) {p1}, p(simulation larger) {c['p_rise']:.2g}, "
                f"{'better' if c['better'] else 'WORSE'}")
    lines.append(f"refused by the default rule: {len(res['refused'])}")
    lines.extend(fmt(c) for c in res["refused"])
    lines.append(f"accepted by the default rule, not by the simulation error alone: {len(res['differ'])}")
    lines.extend(fmt(c) for c in res["differ"])
    lines.append(f"accepted only by the unbounded one-step route: {len(res['unbounded_only'])}")
    lines.extend(fmt(c) for c in res["unbounded_only"])
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.holdout_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--setpoint-steps", action="store_true",
                   help="setpoints in steps (bench.scenarios.SETPOINT_STEPS) instead of the paper's PRBS")
    p.add_argument("--out", default=None, help="JSON output (default bench/results/holdout_mc[_setpoint_steps].json)")
    args = p.parse_args(argv)
    options = dataclasses.replace(SETPOINT_STEPS if args.setpoint_steps else ScenarioOptions(), dither_fat=True)
    t0 = time.perf_counter()
    checks = [c for k in range(args.runs) for c in one(args.seed, k, args.samples, options)]
    res = {"runs": args.runs, "seed": args.seed, "samples": args.samples, "dither_fat": True,
           "setpoints": "steps" if args.setpoint_steps else "paper PRBS", **summarize(checks),
           "seconds": time.perf_counter() - t0, "records": checks}
    print(format_table(res))
    out = args.out or f"bench/results/holdout_mc{'_setpoint_steps' if args.setpoint_steps else ''}.json"
    write_json(out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
