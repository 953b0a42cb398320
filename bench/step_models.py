"""Step-response (DMC-style) models: the same decisions as the parametric model they sample?

A DMC controller holds its model as step responses.  For every run ``k`` of family ``seed`` this
draws the random closed loop of :mod:`bench.structures_mc` (every element structure, integrating
outputs, measured disturbances, 0 to 2 mismatched elements), simulates it with the paper's noise,
and runs ``analyze`` (with the repair) twice on the same log:

* with the controller's model as drawn (parametric), and
* with its step-response form: ``s_1 .. s_N`` of every element, ``N`` the largest dead time plus 12
  time constants (the responses settled to ``exp(-12)``), a ramp on every integrating output.

Recorded: the located elements of both against the truth (hits, false locations, clean runs with an
alarm), the runs in which the two differ, both analysis times, and for every located mismatched
element the repaired model's unit-step response against the plant's
(:func:`bench.structures_mc.step_response_error`: the largest difference over
``REPAIR_HORIZON`` samples, a fraction of the plant's largest value; "within 10 %" as there), and each
located element's kind on both forms: where it differs between them, and for a mismatched element whether it is
the kind its change calls for (``bench.structures_mc.REPORTED_KIND``, "kind right").

Run: ``python -m bench.step_models [--runs 100] [--seed 0] [--jobs 2] [--lost-lag] [--out bench/results/step_models.json]``
(``--lost-lag``: the loops of ``bench.structures_mc --lost-lag``, every mismatch a second lag the model has and the
plant lacks; default ``--out`` ``bench/results/step_models_lost_lag.json``).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze

from . import map_runs, run_mc_main, structures_mc

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "step_models.json"
LOST_LAG_OUT = DEFAULT_OUT.with_name("step_models_lost_lag.json")
#: The step responses run this many time constants (both lags) past the largest dead time.
SETTLED_TIME_CONSTANTS = 12


def step_form(model: PlantModel) -> PlantModel:
    """The step-response form of a parametric model (module docstring)."""
    tau = (model.time_constant + model.time_constant2) / model.sample_time
    n = int(np.max(model.delay_samples + SETTLED_TIME_CONSTANTS * tau)) + 5
    coefs = [[model.discrete_element(i, j).step_response(n + 1)[1:] for j in range(model.n_columns)]
             for i in range(model.n_outputs)]
    return PlantModel.from_step_response(model.sample_time, model.inputs, model.outputs, coefs,
                                         ramp=list(model.integrating_outputs), disturbances=model.disturbances,
                                         name=f"{model.name} (step responses, N = {n})")


def analyse_located(model, plant, mismatched, data, alpha: float):
    """The located elements ``[[i, j], ...]``, the seconds of ``analyze``, ``{"i,j": error}`` of the
    repaired model's step response of every located mismatched element, ``{"i,j": kind}`` of every
    located element (the repair's kind), and ``[[i, j], ...]`` the repaired model's detection locates in the
    rows it still flags (the report's ``repair.located_after``)."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = analyze(model, data, AnalysisOptions(alpha=alpha))
    seconds = time.perf_counter() - t0
    ci = {name: k for k, name in enumerate(model.columns)}
    oi = {name: k for k, name in enumerate(model.outputs)}
    located = sorted([oi[o], ci[c]] for o, c in rep.located_elements)
    errors = {f"{i},{j}": structures_mc.step_response_error(plant, rep.repaired_model, i, j)
              for i, j in located if [i, j] in mismatched and rep.repaired_model is not None}
    kinds = {f"{i},{j}": kind for (i, j), kind in (rep.repair_result.kinds.items() if rep.repair_result else ())}
    after = sorted([oi[x["output"]], ci[x["input"]]] for x in (rep.repair or {}).get("located_after", []))
    return located, seconds, errors, kinds, after


def one(seed: int, index: int, samples: int, alpha: float, lost_lag: bool = False) -> dict:
    """One random loop analysed with its model and with the model's step-response form (``lost_lag``: the
    loops of ``bench.structures_mc --lost-lag``)."""
    sc = structures_mc.make_structures_scenario(seed, index, structures_mc.StructuresOptions(lost_lag=lost_lag))
    data = structures_mc.simulate(sc, samples).as_logged_data(source=f"run {index}")
    step = step_form(sc.model)
    rec = {"index": index, "shape": [sc.plant.n_outputs, sc.plant.n_inputs, sc.plant.n_disturbances],
           "step_length": int(step.step_length), "ramp_rows": int(sum(step.ramp)),
           "mismatched": sorted([int(m["output"]), int(m["column"])] for m in sc.mismatches),
           "expected_kinds": {f"{m['output']},{m['column']}": structures_mc.REPORTED_KIND[m["kind"]]
                              for m in sc.mismatches}}
    try:
        for key, model in (("parametric", sc.model), ("step", step)):
            (rec[key], rec[f"{key}_s"], rec[f"{key}_repair_error"], rec[f"{key}_kinds"],
             rec[f"{key}_located_after"]) = analyse_located(model, sc.plant, rec["mismatched"], data, alpha)
    except Exception as exc:                    # a diverged loop refused by both: recorded, not scored
        rec["error"] = f"{type(exc).__name__}: {exc}"
    return rec


def _one_star(args):
    return one(*args)


def summarise(records: Sequence[dict]) -> dict:
    scored = [r for r in records if "error" not in r]
    out = {"runs": len(records), "scored": len(scored), "errors": len(records) - len(scored),
           "runs_where_the_two_differ": [r["index"] for r in scored if r["parametric"] != r["step"]],
           # Elements both forms locate whose repair's kind differs (records without kinds: none).
           "kinds_that_differ": [[r["index"], k, r["parametric_kinds"][k], r["step_kinds"][k]] for r in scored
                                 for k in sorted(set(r.get("parametric_kinds", {})) & set(r.get("step_kinds", {})))
                                 if r["parametric_kinds"][k] != r["step_kinds"][k]]}
    for key in ("parametric", "step"):
        hits = false = total = clean = clean_alarm = 0
        for r in scored:
            truth = {tuple(t) for t in r["mismatched"]}
            got = {tuple(t) for t in r[key]}
            hits += len(got & truth)
            false += len(got - truth)
            total += len(truth)
            if not truth:
                clean += 1
                clean_alarm += bool(got)
        # Located mismatched elements whose kind is the one the change calls for (records without it: none).
        judged = [(r[f"{key}_kinds"][k], want) for r in scored for k, want in r.get("expected_kinds", {}).items()
                  if k in r.get(f"{key}_kinds", {})]
        times = [r[f"{key}_s"] for r in scored]
        errors = [e for r in scored for e in r[f"{key}_repair_error"].values()]
        out[key] = {"mismatched_elements": total, "located": hits, "false_locations": false,
                    "clean_runs": clean, "clean_runs_with_a_location": clean_alarm,
                    "kinds_judged": len(judged), "kind_right": sum(said == want for said, want in judged),
                    "repaired_within_10_percent": int(sum(e <= 0.1 for e in errors)),
                    "median_repair_error": float(np.median(errors)) if errors else None,
                    "median_analyze_s": float(np.median(times)) if times else None,
                    "total_analyze_s": float(np.sum(times)), "max_analyze_s": float(np.max(times, initial=0.0))}
        out[key].update(located_after_counts(scored, key, f"{key}_located_after"))
    return out


def located_after_counts(records: Sequence[dict], located_key: str, after_key: str) -> dict:
    """What the repaired model's detection locates in the rows it still flags, over ``records`` (those without
    ``after_key``: none): elements the first detection did not locate ("new") and located elements it locates
    again, each with how many are drawn mismatches."""
    new = again = new_drawn = again_drawn = 0
    for r in records:
        truth = {tuple(t) for t in r["mismatched"]}
        located = {tuple(t) for t in r[located_key]}
        for e in map(tuple, r.get(after_key, [])):
            if e in located:
                again, again_drawn = again + 1, again_drawn + (e in truth)
            else:
                new, new_drawn = new + 1, new_drawn + (e in truth)
    return {"located_after_new": new, "located_after_new_drawn": new_drawn,
            "located_after_again": again, "located_after_again_drawn": again_drawn}


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01, progress=None,
        lost_lag: bool = False) -> dict:
    tasks = [(seed, k, samples, alpha, lost_lag) for k in range(runs)]
    t0 = time.perf_counter()
    records = map_runs(_one_star, tasks, jobs, progress)
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha,
                       "settled_time_constants": SETTLED_TIME_CONSTANTS, "lost_lag": lost_lag},
            "summary": summarise(records), "seconds": time.perf_counter() - t0, "records": records}


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.2g} %"


def format_table(result: dict) -> str:
    s, cfg = result["summary"], result["config"]
    family = ", every mismatch a lost second lag" if cfg.get("lost_lag") else ""
    lines = [f"step-response models: {s['scored']} of {s['runs']} random loops (bench.structures_mc draws, seed "
             f"{cfg['seed']}{family}), {cfg['samples']} samples, alpha {cfg['alpha']}, analyze with the repair"]
    for key in ("parametric", "step"):
        x = s[key]
        lines.append(f"{key}: {x['located']} of {x['mismatched_elements']} mismatched elements located, "
                     f"{x['false_locations']} false locations, {x['clean_runs_with_a_location']} of {x['clean_runs']} "
                     f"clean runs with one; kind right on {x.get('kind_right', '-')} of {x.get('kinds_judged', '-')}; "
                     f"repaired within 10 %: {x['repaired_within_10_percent']} (median "
                     f"error {_pct(x['median_repair_error'])}); analyze median {x['median_analyze_s']:.2f} s, total "
                     f"{x['total_analyze_s']:.0f} s, longest {x['max_analyze_s']:.1f} s")
        if "located_after_new" in x:
            lines.append(f"{key}: the repaired model's detection locates {x['located_after_new']} element(s) not "
                         f"located before (drawn {x['located_after_new_drawn']}) and {x['located_after_again']} "
                         f"repaired element(s) again (drawn {x['located_after_again_drawn']})")
    lines.append(f"runs where the two differ: {len(s['runs_where_the_two_differ'])} {s['runs_where_the_two_differ']}")
    differ = s.get("kinds_that_differ", [])
    lines.append(f"elements located by both whose kind differs: {len(differ)}"
                 + "".join(f"; run {r} ({k}) {a} / {b}" for r, k, a, b in differ))
    lines.append(f"({result['seconds']:.0f} s)")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    lost_lag = ("lost-lag", "the loops of bench.structures_mc --lost-lag: every mismatch a second lag the model has "
                            "and the plant lacks", LOST_LAG_OUT)
    return run_mc_main(argv, "python -m bench.step_models", __doc__, 100, DEFAULT_OUT, run, format_table, (lost_lag,))


if __name__ == "__main__":
    sys.exit(main())
