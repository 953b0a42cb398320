"""Monte-Carlo of quiet closed loops: setpoint steps held for minutes, no dither, with and without gaps.

Real MPC logs are mostly quiet: the setpoints step now and then and the inputs move after each step,
then only follow the disturbances.  The other Monte-Carlo benches excite their loops with setpoint
PRBS switching every few samples, so their inputs move at every sample.  Here every setpoint takes
steps of +-1 held at least 150 samples (switching with probability 0.005 a sample after that), on:

* ``wood-berry``: the Wood and Berry distillation column (R. K. Wood and M. W. Berry, "Terminal
  composition control of a binary distillation column", Chemical Engineering Science 28, 1973), 2x2,
  its minutes read as seconds (sample time 1 s), under this package's MPC (horizons 90 / 10, input
  rate weight 20); the mismatch: the gain of (xb, steam) 30 % high in the plant;
* the paper's cases 3.1, 3.2 and 3.3 with their MPC and noise; the mismatch: the case's own.

Each plant runs ``--seeds`` seeds clean (plant = model) and mismatched, 4,000 samples, and every log
is analysed (``analyze``, repair off) as simulated (``full``) and with each sample dropped with
probability 1/500 and 1/300 (rows removed, as in a CSV with missing rows).  Scored: false alarms
(clean runs with a located element); in the mismatched runs, the true elements located and the same
located elements as the full log's; and the full logs in which samples were called spikes (there are
none: every one is a good sample left out).  Case 3.1's plant differs from its model in no element
(its mismatch is in the noise), so its runs count as clean both ways.

Run: ``python -m bench.quiet_loops [--seeds 10] [--jobs 2] [--out bench/results/quiet_loops.json]``
"""

from __future__ import annotations

import argparse
import time
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.spikes import find_spikes
from mpm_monitor.sim.cases import CASE_NAMES, simulation_case
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop
from mpm_monitor.sim.excitation import PrbsOptions
from mpm_monitor.sim.mpc import MpcOptions

from . import map_runs, write_json
from .gaps_mc import drop_rows

DEFAULT_OUT = "bench/results/quiet_loops.json"
SAMPLES = 4000
DROPS = {"drop500": 1.0 / 500, "drop300": 1.0 / 300}
STEPS = ExcitationOptions(setpoint=PrbsOptions(amplitude=1.0, switch_probability=0.005, min_hold=150))
PLANTS = ("wood-berry",) + tuple(CASE_NAMES)
WOOD_BERRY = PlantModel(sample_time=1.0, inputs=("reflux", "steam"), outputs=("xd", "xb"),
                        gain=np.array([[12.8, -18.9], [6.6, -19.4]]),
                        time_constant=np.array([[16.7, 21.0], [10.9, 14.4]]),
                        delay=np.array([[1.0, 3.0], [7.0, 3.0]]))


#: Wood-Berry's MPC: horizons 90 / 10, input rate weight 20.
WOOD_BERRY_MPC = MpcOptions(prediction_horizon=90, control_horizon=10, input_rate_weight=20.0)


def plant_of(plant_name: str, mismatched: bool):
    """``(model, plant, mpc, disturbance, truth)`` of one of :data:`PLANTS`: the controller's model, the
    plant (the model when not ``mismatched``), the MPC options, the disturbance options (None: the
    default) and the mismatched elements as ``[output, column]`` names (empty when not mismatched)."""
    if plant_name == "wood-berry":
        plant = WOOD_BERRY.with_element(1, 1, gain=1.3 * WOOD_BERRY.gain[1, 1]) if mismatched else WOOD_BERRY
        return WOOD_BERRY, plant, WOOD_BERRY_MPC, None, [["xb", "steam"]] if mismatched else []
    case = simulation_case(plant_name)
    truth = sorted([list(x) for x in case.mismatched_elements]) if mismatched else []
    return case.model, case.plant if mismatched else case.model, case.mpc, case.disturbance, truth


def loop(plant_name: str, mismatched: bool, seed: int):
    """``(model, plant, data, truth)`` of one quiet loop; ``truth`` the mismatched elements (names)."""
    model, plant, mpc, dist, truth = plant_of(plant_name, mismatched)
    kw = {} if dist is None else {"disturbance": dist}
    data = run_closed_loop(plant, model, SAMPLES, seed=seed, mpc=mpc, excitation=STEPS, **kw).as_logged_data(
        f"{plant_name} seed {seed}")
    return model, plant, data, truth


def _located(model, data) -> dict:
    try:
        rep = analyze(model, data, AnalysisOptions(repair=False))
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"located": sorted([list(x) for x in rep.located_elements]), "rows": sorted(rep.flagged_rows)}


def run_one(plant_name: str, mismatched: bool, seed: int) -> dict:
    """One loop analysed full and with drops; a JSON-ready record."""
    model, _, data, truth = loop(plant_name, mismatched, seed)
    rec = {"plant": plant_name, "mismatched": mismatched, "seed": seed, "truth": truth,
           "spike_samples": int(sum(int(m.sum()) for m in find_spikes(data).values())), "full": _located(model, data)}
    for key, p in DROPS.items():
        rng = np.random.default_rng([seed, PLANTS.index(plant_name), int(mismatched), int(round(1 / p))])
        rec[key] = _located(model, data.take(drop_rows(data.n_samples, p, rng)))
    return rec


def _star(args):
    return run_one(*args)


def summarize(records: list) -> dict:
    """Per variant: false alarms among the clean runs, recall and sameness among the mismatched ones."""
    clean = [r for r in records if not r["truth"]]      # case 3.1's plant differs from its model in no element
    bad = [r for r in records if r["truth"]]
    out = {"runs": len(records), "clean": len(clean), "mismatched": len(bad),
           "full_logs_with_spikes": sum(r["spike_samples"] > 0 for r in records)}
    for key in ("full",) + tuple(DROPS):
        ok = [r for r in records if "error" not in r[key]]
        out[key] = {
            "errors": len(records) - len(ok),
            "false_alarms": sum(bool(r[key]["located"]) for r in ok if not r["truth"]),
            "clean_rows_flagged": sum(bool(r[key]["rows"]) for r in ok if not r["truth"]),
            "true_located": sum(all(t in r[key]["located"] for t in r["truth"]) for r in ok if r["truth"]),
            "extra_located": sum(any(x not in r["truth"] for x in r[key]["located"]) for r in ok if r["truth"]),
            "same_as_full": None if key == "full" else sum(
                "error" not in r["full"] and r[key]["located"] == r["full"]["located"] for r in ok),
        }
    return out


def format_table(s: dict) -> str:
    lines = [f"quiet loops: {s['runs']} runs ({s['clean']} clean, {s['mismatched']} mismatched), setpoint steps held "
             f">= 150 samples, no dither; full logs with samples called spikes: {s['full_logs_with_spikes']}",
             "log       false alarms  clean rows flagged  true located  with extra elements  same as full",
             ]
    for key in ("full",) + tuple(DROPS):
        v = s[key]
        same = "-" if v["same_as_full"] is None else f"{v['same_as_full']}/{s['runs']}"
        lines.append(f"{key:9s} {v['false_alarms']:>5d}/{s['clean']:<6d} {v['clean_rows_flagged']:>8d}/{s['clean']:<9d} "
                     f"{v['true_located']:>6d}/{s['mismatched']:<6d} {v['extra_located']:>10d}/{s['mismatched']:<8d} "
                     f"{same:>10s}" + (f"  ({v['errors']} errors)" if v["errors"] else ""))
    return "\n".join(lines)


def run(seeds: int, jobs: int = 1) -> dict:
    tasks = [(p, m, s) for p in PLANTS for m in (False, True) for s in range(seeds)]
    t0 = time.perf_counter()
    records = map_runs(_star, tasks, jobs)
    return {"config": {"seeds": seeds, "samples": SAMPLES, "drops": DROPS, "plants": list(PLANTS)},
            "seconds": time.perf_counter() - t0, "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.quiet_loops", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=10, help="seeds per plant, clean and mismatched (default 10)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    res = run(args.seeds, args.jobs)
    print(format_table(res["summary"]))
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
