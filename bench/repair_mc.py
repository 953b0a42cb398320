"""Trace and repair over the Monte-Carlo scenarios (issue 5 on data never seen in tuning).

For each random closed loop of ``bench.scenarios`` (the same draws as ``bench.monte_carlo``) the
full analysis runs with the repair.  Scored, for every mismatched element that was located:

- the kind reported against the kind drawn (``gain``, ``time_constant``, ``delay``, ``missing``,
  ``mixed``);
- on every output with a located element, the RMS prediction error after the repair divided by
  the error before, and divided by the noise floor (the RMS of the injected disturbance plus
  measurement noise on the same data: what a perfect model would leave);
- on outputs without a located element, that the error is unchanged.

``--setpoint-steps``: the setpoints moved in steps instead of the paper's PRBS
(:data:`bench.scenarios.SETPOINT_STEPS`, as ``bench.monte_carlo --setpoint-steps``).

``--kinds missing --max-delay 40``: elements the model lacks, on plants with dead times up to 40 samples
(every run at least one mismatch; the repaired delay of a located missing element is scored as above).

``--far-delays``: one or two delay mismatches a run, each 11 to 30 samples from the plant's
(:data:`bench.scenarios.FAR_DELAYS`), more than the repair's own search range (``max_delay_shift``, 10
samples); the repaired delay of every located element whose delay was drawn is scored against the plant's
(within one sample, and applied).  Every run also records the elements located that were not drawn (false
alarms) and the drawn ones missed.

Run: ``python -m bench.repair_mc [--runs 200] [--seed 0] [--samples 3000] [--dither-fat] [--setpoint-steps]
[--far-delays] [--kinds K,...] [--max-delay N]``
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import statistics
import time
from typing import Optional

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.closed_loop import run_closed_loop

from . import write_json
from .scenarios import FAR_DELAYS, SETPOINT_STEPS, ScenarioOptions, make_scenario


def one(seed: int, index: int, samples: int, options: ScenarioOptions) -> dict:
    sc = make_scenario(seed, index, options)
    log = run_closed_loop(sc.plant, sc.model, samples, seed=sc.loop_seed, mpc=sc.mpc, excitation=sc.excitation,
                          disturbance=sc.disturbance)
    data = log.as_logged_data()
    t0 = time.perf_counter()
    rep = analyze(sc.model, data, AnalysisOptions())
    dt = time.perf_counter() - t0
    floor = np.sqrt(np.mean((log.disturbance + log.noise) ** 2, axis=0))
    truth = {(sc.model.outputs[m.output], sc.model.inputs[m.input]): m.kind for m in sc.mismatches}
    drawn = {(sc.model.outputs[m.output], sc.model.inputs[m.input]): m for m in sc.mismatches}
    kinds = {(e.output, e.input): e.kind for e in rep.elements if e.mismatch}
    eb, ea = rep.repair["error_before"], rep.repair["error_after"]
    rows = {o for o, _ in kinds}
    changes = {(c["output"], c["input"]): c for c in rep.repair["changes"]}
    delays = []
    for k, m in drawn.items():
        if k in kinds and (m.plant["delay"] != m.model["delay"] or m.kind == "missing") and k in changes:
            c = changes[k]
            delays.append({"element": list(k), "plant": m.plant["delay"], "model": m.model["delay"],
                           "repaired": c["after"]["delay"], "applied": bool(c["applied"])})
    # What the detection of the repaired model locates in the rows it still flags (the report's located_after).
    after = [(x["output"], x["input"]) for x in rep.repair.get("located_after", [])]
    return {
        "index": index, "shape": [sc.plant.n_outputs, sc.plant.n_inputs], "time_s": dt, "drawn": len(truth),
        "located_after_new": [{"element": list(k), "drawn": k in truth} for k in after if k not in kinds],
        "located_after_again": [{"element": list(k), "drawn": k in truth} for k in after if k in kinds],
        "false_elements": [list(k) for k in kinds if k not in truth],
        "missed_elements": [list(k) for k in truth if k not in kinds],
        "delays": delays,
        "kinds": [{"element": list(k), "truth": truth[k], "reported": kinds[k]} for k in kinds if k in truth],
        "located_rows": [{"output": o, "before": eb[o], "after": ea[o],
                          "floor": float(floor[sc.model.outputs.index(o)])} for o in sorted(rows)],
        "other_rows": [{"output": o, "ratio": ea[o] / eb[o]} for o in sc.model.outputs if o not in rows],
    }


def run(runs: int, seed: int, samples: int, dither_fat: bool, setpoint_steps: bool = False,
        far_delays: bool = False, kinds: Optional[tuple] = None, max_delay: Optional[int] = None) -> dict:
    base = FAR_DELAYS if far_delays else ScenarioOptions()
    if kinds is not None:
        base = dataclasses.replace(base, kinds=tuple(kinds), min_mismatches=max(base.min_mismatches, 1))
    if max_delay is not None:
        base = dataclasses.replace(base, max_delay=int(max_delay))
    if setpoint_steps:
        base = dataclasses.replace(base, setpoint_switch_probability=SETPOINT_STEPS.setpoint_switch_probability,
                                   setpoint_min_hold=SETPOINT_STEPS.setpoint_min_hold)
    options = dataclasses.replace(base, dither_fat=dither_fat)
    recs = [one(seed, k, samples, options) for k in range(runs)]
    delays = [x for r in recs for x in r["delays"]]
    within = [x for x in delays if x["applied"] and abs(x["repaired"] - x["plant"]) <= options.sample_time]
    confusion = collections.Counter((k["truth"], k["reported"]) for r in recs for k in r["kinds"])
    n_kinds = sum(confusion.values())
    exact = sum(v for (t, p), v in confusion.items() if t == p)
    rows = [x for r in recs for x in r["located_rows"]]
    after_floor = [x["after"] / x["floor"] for x in rows]
    after_before = [x["after"] / x["before"] for x in rows]
    others = [x["ratio"] for r in recs for x in r["other_rows"]]
    return {"runs": runs, "seed": seed, "samples": samples, "dither_fat": dither_fat,
            "setpoints": "steps" if setpoint_steps else "paper PRBS", "far_delays": far_delays,
            "kinds": list(options.kinds), "max_delay": options.max_delay,
            "drawn_elements": sum(r["drawn"] for r in recs),
            "missed_elements": sum(len(r["missed_elements"]) for r in recs),
            "false_elements": sum(len(r["false_elements"]) for r in recs),
            "runs_with_a_false_element": sum(bool(r["false_elements"]) for r in recs),
            "located_after_new": sum(len(r["located_after_new"]) for r in recs),
            "located_after_new_drawn": sum(x["drawn"] for r in recs for x in r["located_after_new"]),
            "located_after_new_runs": sum(bool(r["located_after_new"]) for r in recs),
            "located_after_again": sum(len(r["located_after_again"]) for r in recs),
            "located_after_again_drawn": sum(x["drawn"] for r in recs for x in r["located_after_again"]),
            "delays_scored": len(delays), "delays_within_one_sample": len(within),
            "delays_far_scored": sum(abs(x["plant"] - x["model"]) > 10 * options.sample_time for x in delays),
            "delays_far_within_one_sample": sum(abs(x["plant"] - x["model"]) > 10 * options.sample_time
                                                for x in within),
            "kind_accuracy": exact / n_kinds if n_kinds else None, "kinds_scored": n_kinds,
            "confusion": {f"{t} -> {p}": v for (t, p), v in sorted(confusion.items())},
            "located_rows": len(rows),
            "after_over_floor": {"median": statistics.median(after_floor) if rows else None,
                                 "p90": float(np.percentile(after_floor, 90)) if rows else None,
                                 "max": max(after_floor) if rows else None,
                                 "within_5pct": sum(v <= 1.05 for v in after_floor) / len(rows) if rows else None},
            "after_over_before": {"median": statistics.median(after_before) if rows else None,
                                  "at_most_half": sum(v <= 0.5 for v in after_before) / len(rows) if rows else None},
            "unlocated_rows_changed": sum(abs(v - 1.0) > 1e-12 for v in others), "unlocated_rows": len(others),
            "median_analyze_with_repair_s": statistics.median(r["time_s"] for r in recs),
            "records": recs}


def format_table(res: dict) -> str:
    a, b = res["after_over_floor"], res["after_over_before"]
    lines = [f"trace and repair over {res['runs']} Monte-Carlo scenarios (seed {res['seed']}, {res['samples']} samples"
             f"{', dither on fat plants' if res['dither_fat'] else ''}"
             f"{', setpoints in steps' if res.get('setpoints') == 'steps' else ''}"
             f"{', delays 11 to 30 samples off' if res.get('far_delays') else ''}"
             f"{', kinds ' + ' '.join(res['kinds']) if res.get('kinds') and len(res['kinds']) < 5 and not res.get('far_delays') else ''}"
             f"{', plant delays up to ' + str(res['max_delay']) if res.get('max_delay', 8) != 8 and not res.get('far_delays') else ''})",
             f"kind of located mismatched elements: {res['kind_accuracy']:.3f} exact ({res['kinds_scored']} elements)",
             "confusion (drawn -> reported):"]
    width = max(len(k) for k in res["confusion"]) if res["confusion"] else 10
    for k, v in res["confusion"].items():
        lines.append(f"  {k:<{width}}  {v}")
    lines.append(f"outputs with a located element: {res['located_rows']}; error after / noise floor: median "
                 f"{a['median']:.3f}, 90th percentile {a['p90']:.3f}, max {a['max']:.3f}, within 5% of the floor "
                 f"{a['within_5pct']:.3f}")
    lines.append(f"error after / before: median {b['median']:.3f}; at most half on {b['at_most_half']:.3f} of them")
    lines.append(f"outputs without a located element changed: {res['unlocated_rows_changed']} of "
                 f"{res['unlocated_rows']}")
    if "delays_scored" in res:
        lines.append(f"drawn elements missed: {res['missed_elements']} of {res['drawn_elements']}; elements located "
                     f"that were not drawn: {res['false_elements']} (in {res['runs_with_a_false_element']} runs)")
        if "located_after_new" in res:
            lines.append(f"elements the repaired model's detection locates that the first did not: "
                         f"{res['located_after_new']} (in {res['located_after_new_runs']} runs), drawn "
                         f"{res['located_after_new_drawn']}; repaired elements it locates again: "
                         f"{res['located_after_again']} (drawn {res['located_after_again_drawn']})")
        lines.append(f"located elements with a drawn delay change or missing: repaired within one sample of the plant's and "
                     f"applied {res['delays_within_one_sample']} of {res['delays_scored']}; of those more than 10 "
                     f"samples off {res['delays_far_within_one_sample']} of {res['delays_far_scored']}")
    lines.append(f"median analyze time with the repair: {res['median_analyze_with_repair_s']:.2f} s")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.repair_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--dither-fat", action="store_true")
    p.add_argument("--setpoint-steps", action="store_true",
                   help="setpoints moved in steps (bench.scenarios.SETPOINT_STEPS) instead of the paper's PRBS")
    p.add_argument("--far-delays", action="store_true",
                   help="delay mismatches 11 to 30 samples off (bench.scenarios.FAR_DELAYS)")
    p.add_argument("--kinds", default=None, metavar="KIND[,KIND...]",
                   help="mismatch kinds drawn (bench.scenarios.KINDS; at least one mismatch a run)")
    p.add_argument("--max-delay", type=int, default=None, help="largest plant delay, samples (default 8)")
    p.add_argument("--out", default="bench/results/repair_mc.json")
    args = p.parse_args(argv)
    kinds = tuple(args.kinds.split(",")) if args.kinds else None
    res = run(args.runs, args.seed, args.samples, args.dither_fat, args.setpoint_steps, args.far_delays, kinds,
              args.max_delay)
    print(format_table(res))
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
