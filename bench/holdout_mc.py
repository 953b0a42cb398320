"""The repair's held-out check against the truth, over the Monte-Carlo loops of ``bench.repair_mc``.

Every held-out check the repair makes (one per output row with a re-estimated element) is recorded:
the candidate's and the given model's held-out simulation errors and one-step errors (each model
under its own AR noise model), the one-sided p-value of a rise of the simulation error, and the
decision.  The truth is the plant: a candidate is *better* when its row's simulated response to the
logged inputs is closer to the plant's over the held-out part than the given model's is (RMS of
``yhat_plant - yhat_model`` about its level).  Scored, for the check as it is (simulation error, or
one-step error without a significant rise in simulation) and for the simulation error alone:

- accepted but worse (a wrong repair let through: the check's false acceptances);
- refused but better (a right repair held back).

Checks on rows re-estimated with an unexplained step or drift, or on data with gaps, are counted but
not scored (none in these loops).

Run: ``python -m bench.holdout_mc [--runs 200] [--seed 0] [--samples 3000] [--setpoint-steps]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import model_repair
from mpm_monitor.core.repair.holdout import loss_rise_p_value
from mpm_monitor.sim.closed_loop import run_closed_loop

from . import write_json
from .scenarios import SETPOINT_STEPS, ScenarioOptions, make_scenario


def _recorder(plant, checks: list):
    """A wrapper of the repair's held-out check that records what it compared (and leaves its decision)."""
    validate = model_repair._validate_on_holdout

    def record(rec, row, js, elements, warnings):
        check = validate(rec, row, js, elements, warnings)
        model, i = rec.model, row.i
        entry = {"output": model.outputs[i], "inputs": [model.columns[j] for j in js], "accepted": check.accepted}
        if check.after is None or row.extra is not None or rec.segments is not None:
            checks.append(dict(entry, scored=False))
            return check
        candidate = model
        for j, el in elements.items():
            if el.apply or el.reason == "rejected by held-out validation":
                candidate = el.applied_to(candidate, i, j)
        d_c = np.asarray(rec.signals_of(candidate).d[:, i], float)
        d_0 = np.asarray(rec.d0[:, i], float)
        d_p = np.asarray(rec.signals_of(plant).d[:, i], float)
        p = loss_rise_p_value(rec.holdout_residual(d_c, None), rec.holdout_residual(d_0, None))
        # yhat_plant - yhat = d - d_plant: the candidate's and the model's distance to the plant's response
        truth_after = float(np.sqrt(np.mean(rec.holdout_residual(d_c - d_p, None) ** 2)))
        truth_before = float(np.sqrt(np.mean(rec.holdout_residual(d_0 - d_p, None) ** 2)))
        checks.append(dict(entry, scored=True, simulation_after=check.after, simulation_before=check.before,
                           one_step_after=check.one_step_after, one_step_before=check.one_step_before,
                           p_rise=p, truth_after=truth_after, truth_before=truth_before,
                           better=truth_after < truth_before, simulation_alone=check.after < check.before))
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


def summarize(checks: list) -> dict:
    scored = [c for c in checks if c["scored"]]

    def tally(decide):
        return {"accepted": sum(decide(c) for c in scored),
                "accepted_but_worse": sum(decide(c) and not c["better"] for c in scored),
                "refused_but_better": sum(not decide(c) and c["better"] for c in scored)}

    return {"checks": len(checks), "scored": len(scored), "better": sum(c["better"] for c in scored),
            "worse": sum(not c["better"] for c in scored),
            "check_as_it_is": tally(lambda c: c["accepted"]),
            "simulation_alone": tally(lambda c: c["simulation_alone"]),
            "accepted_one_step_ahead": [{k: c[k] for k in ("run", "output", "inputs", "simulation_after",
                                                          "simulation_before", "one_step_after", "one_step_before",
                                                          "p_rise", "better")}
                                        for c in scored if c["accepted"] and not c["simulation_alone"]],
            "refused": [{k: c[k] for k in ("run", "output", "inputs", "simulation_after", "simulation_before",
                                           "one_step_after", "one_step_before", "p_rise", "better")}
                        for c in scored if not c["accepted"]]}


def format_table(res: dict) -> str:
    lines = [f"held-out checks: {res['checks']} ({res['scored']} scored); candidates better than the model as given "
             f"(closer to the plant's response over the held-out part): {res['better']}, worse: {res['worse']}"]
    for name in ("check_as_it_is", "simulation_alone"):
        t = res[name]
        lines.append(f"  {name.replace('_', ' '):<18} accepted {t['accepted']:4d}   accepted but worse "
                     f"{t['accepted_but_worse']:3d}   refused but better {t['refused_but_better']:3d}")
    for title, key in (("accepted one step ahead (simulation error higher)", "accepted_one_step_ahead"),
                       ("refused", "refused")):
        lines.append(f"{title}: {len(res[key])}")
        for c in res[key]:
            lines.append(f"  run {c['run']:3d} {c['output']} ({', '.join(c['inputs'])}): simulation "
                         f"{c['simulation_after']:.4g} vs {c['simulation_before']:.4g}, one step "
                         f"{c['one_step_after']:.4g} vs {c['one_step_before']:.4g}, p(rise) {c['p_rise']:.2g}, "
                         f"{'better' if c['better'] else 'WORSE'}")
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
