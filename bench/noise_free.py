"""Logs without noise: do the tests keep quiet where the model is right?

A simulation without measurement noise or unmeasured disturbance (the first thing many users try)
leaves, in every row whose model elements are right, a prediction error of 0 or rounding (a few
ulps of the output, depending on how the BLAS rounds).  The row and element fits of such a row are
exact; an F ratio of their residuals divides rounding by rounding, so the tests must decide those
rows outright (no mismatch), not on the rounding (``EXACT_FIT`` in :mod:`mpm_monitor.core.statistics`).

For every run ``k`` of family ``seed`` this draws the random closed loop of :mod:`bench.structures_mc`
(every element structure, 0 to 2 mismatched elements), simulates it with the unmeasured disturbance
and the measurement noise off (the measured disturbances still move), and runs the detection
(``detect``: the row and element tests, no repair) on

* the model as drawn, and
* the plant itself as the model (no mismatch at all).

Recorded, against the truth:

* rows whose model is right (every element of the row matches the plant): flagged, by their S_Delta
  test or through a located element (false alarms);
* elements located in a row whose model is right (false alarms), and in a mismatched row though the
  element itself is right (there the prediction error is the mismatch's, and what the row's ARX
  cannot reproduce of it exactly is no noise either: see the README's limits);
* the mismatched elements located (power).

Run: ``python -m bench.noise_free [--runs 100] [--seed 0] [--jobs 2] [--out bench/results/noise_free.json]``
"""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.errors import DataFileError
from mpm_monitor.sim.plant import DisturbanceOptions

from . import map_runs, run_mc_main
from . import structures_mc

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "noise_free.json"
#: No unmeasured disturbance and no measurement noise.
QUIET = DisturbanceOptions(disturbance_std=0.0, noise_std=0.0)


def _decisions(model, data, alpha: float) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = detect(model, data, AnalysisOptions(alpha=alpha))
    oi = {name: k for k, name in enumerate(model.outputs)}
    ci = {name: k for k, name in enumerate(model.columns)}
    return {"rows": [oi[r.output] for r in rep.rows if r.mismatch],
            "located": [[oi[e.output], ci[e.input]] for e in rep.elements if e.mismatch]}


def one(seed: int, index: int, samples: int, alpha: float) -> dict:
    """One random loop without noise, with the model as drawn and with the plant as its model."""
    sc = structures_mc.make_structures_scenario(seed, index)

    def log(model):
        s = dataclasses.replace(sc, model=model)
        return structures_mc.simulate(s, samples, disturbance=QUIET).as_logged_data(source=f"run {index}")

    truth = sorted({(int(m["output"]), int(m["column"])) for m in sc.mismatches})
    rec = {"index": index, "shape": [sc.plant.n_outputs, sc.plant.n_inputs, sc.plant.n_disturbances],
           "mismatched": [list(t) for t in truth]}
    try:
        rec["drawn"] = _decisions(sc.model, log(sc.model), alpha)
        rec["clean"] = _decisions(sc.plant, log(sc.plant), alpha)
    except DataFileError as exc:      # a loop that diverged is refused in one line (the scale check): recorded
        rec["error"] = str(exc)
    return rec


def _one_star(args):
    return one(*args)


def summarise(records: Sequence[dict]) -> dict:
    """False alarms in the rows whose model is right, and the power, over the runs."""
    right_rows = flagged = right_located = beside = 0
    hits = total = 0
    clean_runs_alarm = clean_rows = clean_flagged = 0
    errors = [r for r in records if "error" in r]
    records = [r for r in records if "error" not in r]
    for r in records:
        truth = {tuple(t) for t in r["mismatched"]}
        bad_rows = {i for i, _ in truth}
        ny = r["shape"][0]
        d = r["drawn"]
        located = {tuple(t) for t in d["located"]}
        rows = set(d["rows"])
        right_rows += ny - len(bad_rows)
        flagged += len(rows - bad_rows)
        right_located += sum(1 for i, _ in located if i not in bad_rows)
        beside += sum(1 for t in located if t[0] in bad_rows and t not in truth)
        hits += len(located & truth)
        total += len(truth)
        c = r["clean"]
        clean_rows += ny
        clean_flagged += len(set(c["rows"]))
        clean_runs_alarm += bool(c["rows"] or c["located"])
    n = len(records)
    return {"runs": n, "errors": [{"index": r["index"], "error": r["error"]} for r in errors],
            "model_as_drawn": {"rows_whose_model_is_right": right_rows, "of_them_flagged": flagged,
                               "elements_located_in_them": right_located,
                               "right_elements_located_beside_a_mismatch": beside,
                               "mismatched_elements": total, "mismatched_elements_located": hits},
            "plant_as_model": {"runs": n, "runs_with_any_alarm": clean_runs_alarm, "rows": clean_rows,
                               "rows_flagged": clean_flagged}}


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01,
        progress=None) -> dict:
    tasks = [(seed, k, samples, alpha) for k in range(runs)]
    t0 = time.perf_counter()
    records = map_runs(_one_star, tasks, jobs, progress)
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha,
                       "disturbance": dataclasses.asdict(QUIET)},
            "summary": summarise(records), "seconds": time.perf_counter() - t0, "records": records}


def format_table(result: dict) -> str:
    s, cfg = result["summary"], result["config"]
    a, c = s["model_as_drawn"], s["plant_as_model"]
    return "\n".join([
        f"logs without noise: {s['runs']} random loops (bench.structures_mc draws, seed {cfg['seed']}), "
        f"{cfg['samples']} samples, alpha {cfg['alpha']}",
        f"model as drawn: {a['of_them_flagged']} of {a['rows_whose_model_is_right']} rows whose model is right "
        f"flagged, {a['elements_located_in_them']} elements located in them; "
        f"{a['right_elements_located_beside_a_mismatch']} right elements located beside a mismatch; "
        f"{a['mismatched_elements_located']} of {a['mismatched_elements']} mismatched elements located",
        f"plant as its model: {c['runs_with_any_alarm']} of {c['runs']} runs with any alarm, "
        f"{c['rows_flagged']} of {c['rows']} rows flagged",
        *(f"not analysed: run {e['index']}: {e['error']}" for e in s.get("errors", [])),
        f"({result['seconds']:.0f} s)"])


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_mc_main(argv, "python -m bench.noise_free", __doc__, 100, DEFAULT_OUT, run, format_table)


if __name__ == "__main__":
    sys.exit(main())
