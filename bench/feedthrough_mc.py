"""Model elements with a direct feed-through: located, classified and repaired in the model's own structure?

``analyze`` accepts a model element that acts on ``y(k)`` through ``u(k)`` (a lead over one lag, or a pure gain, with
no dead time), though a closed loop cannot run it; so these loops are open: every input a PRBS held 6 samples, every
output with the Monte-Carlo's coloured disturbance (a random walk through a pole of 0.95, step 0.0075) and white
measurement noise (0.005).  Each run ``k`` of family ``seed`` draws a plant of 2 outputs x 3 inputs whose elements
are first order plus dead time (gains 0.5 to 2 of either sign, time constants 5 to 20 s, dead times 1 to 4 samples,
sample time 1 s) but for ``(y1, u1)``, which has a feed-through in the model: a lead over one lag (the lead 0.2 to
0.6 of the lag, either sign: an inverse response when negative) or, with probability 1/2, a pure gain, each with no
dead time.  The plant is the model but for one change of ``(y1, u1)``, each with probability 1/4: none (a clean
run); its gain (x or / 1.3 to 1.8; ``gain``); its shape (the lead x 1.3 to 1.8, or a lag of 3 to 8 s the pure gain
gained; ``time_constant``); its dead time (2 to 4 samples; ``delay``).  ``analyze`` runs with its defaults and the
repair.

Recorded per run: the located elements, their kinds, and for a located mismatched element the repaired model's
unit-step response against the plant's over 300 samples (:func:`bench.structures_mc.step_response_error`; "within
10 %" as there).  Summarised: clean runs with a location (the false alarms), mismatched elements located, false
locations, the kind right (the one the change calls for), repairs within 10 %.

Run: ``python -m bench.feedthrough_mc [--runs 200] [--seed 0] [--jobs 2] [--out bench/results/feedthrough_mc.json]``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.discretize import simulate_elements
from mpm_monitor.core.filters import lfilter
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel

from . import map_runs, run_mc_main
from .step_models import analyse_located, located_after_counts

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "feedthrough_mc.json"
#: The change of (y1, u1) and the kind it calls for.
EXPECTED_KIND = {"none": None, "gain": "gain", "shape": "time_constant", "delay": "delay"}
#: Samples simulated before the record starts (the plant's start-up transient dropped).
BURN_IN = 300


def draw(seed: int, index: int) -> tuple:
    """``(plant, model, structure, change)`` of run ``index`` of family ``seed`` (module docstring)."""
    rng = np.random.default_rng([seed, index, 75])
    ny, nu = 2, 3
    gain = rng.uniform(0.5, 2.0, (ny, nu)) * rng.choice([-1.0, 1.0], (ny, nu))
    tau = rng.uniform(5.0, 20.0, (ny, nu))
    delay = rng.integers(1, 5, (ny, nu)).astype(float)
    lead = np.zeros((ny, nu))
    structure = "pure_gain" if rng.random() < 0.5 else "lead_lag"
    delay[0, 0] = 0.0
    if structure == "pure_gain":
        tau[0, 0] = 0.0
    else:
        lead[0, 0] = rng.uniform(0.2, 0.6) * tau[0, 0] * rng.choice([-1.0, 1.0])
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3"), outputs=("y1", "y2"), gain=gain,
                       time_constant=tau, delay=delay, lead=lead, name=f"feed-through {seed}/{index}")
    change = str(rng.choice(list(EXPECTED_KIND)))
    factor = rng.uniform(1.3, 1.8)
    if change == "gain":
        plant = model.with_element(0, 0, gain=gain[0, 0] * (factor if rng.random() < 0.5 else 1.0 / factor))
    elif change == "shape" and structure == "lead_lag":
        plant = model.with_element(0, 0, lead=lead[0, 0] * factor)
    elif change == "shape":
        plant = model.with_element(0, 0, time_constant=float(rng.uniform(3.0, 8.0)))
    elif change == "delay":
        plant = model.with_element(0, 0, delay=float(rng.integers(2, 5)))
    else:
        plant = model
    return plant, model, structure, change


def simulate(plant: PlantModel, samples: int, seed: int, index: int) -> LoggedData:
    """The open-loop record of ``plant`` (module docstring), ``samples`` long after :data:`BURN_IN`."""
    rng = np.random.default_rng([seed, index, 76])
    total = samples + BURN_IN
    u = np.repeat(rng.choice([-1.0, 1.0], size=(total // 6 + 1, plant.n_inputs)), 6, axis=0)[:total]
    v = lfilter([1.0], [1.0, -0.95], 0.0075 * rng.standard_normal((total, plant.n_outputs)), axis=0)
    y = simulate_elements(plant, u) + v + 0.005 * rng.standard_normal((total, plant.n_outputs))
    r = rng.choice([-1.0, 1.0], size=(total, plant.n_outputs))
    cut = slice(BURN_IN, total)
    return LoggedData(t=np.arange(samples) * plant.sample_time, r=r[cut], u=u[cut], y=y[cut], inputs=plant.inputs,
                      outputs=plant.outputs, sample_time=plant.sample_time, source=f"feed-through run {index}")


def one(seed: int, index: int, samples: int, alpha: float) -> dict:
    """One run: drawn, simulated, analysed with the repair."""
    plant, model, structure, change = draw(seed, index)
    data = simulate(plant, samples, seed, index)
    mismatched = [] if change == "none" else [[0, 0]]
    located, seconds, errors, kinds, after = analyse_located(model, plant, mismatched, data, alpha)
    rec = {"index": index, "structure": structure, "change": change, "located": located, "kinds": kinds,
           "analyze_s": seconds, "mismatched": mismatched, "located_after": after}
    if "0,0" in errors:
        rec["repair_error"] = errors["0,0"]
    return rec


def _one_star(args):
    return one(*args)


def summarise(records: Sequence[dict]) -> dict:
    """The counts of the module docstring, overall and per structure."""
    def counts(recs):
        clean = [r for r in recs if r["change"] == "none"]
        mismatched = [r for r in recs if r["change"] != "none"]
        hits = [r for r in mismatched if [0, 0] in r["located"]]
        errors = [r["repair_error"] for r in hits if "repair_error" in r]
        return {"runs": len(recs), "clean_runs": len(clean),
                "clean_runs_with_a_location": sum(bool(r["located"]) for r in clean),
                "mismatched": len(mismatched), "located": len(hits),
                "false_locations": sum(len([e for e in r["located"] if e != [0, 0]]) for r in recs),
                "kind_right": sum(r["kinds"].get("0,0") == EXPECTED_KIND[r["change"]] for r in hits),
                "repaired_within_10_percent": int(sum(e <= 0.1 for e in errors)),
                "median_repair_error": float(np.median(errors)) if errors else None,
                "said": {k: sum(r["kinds"].get("0,0") == k for r in hits) for k in
                         sorted({r["kinds"].get("0,0", "none") for r in hits})}}
    out = counts(records)
    out.update(located_after_counts(records, "located", "located_after"))
    out["by_structure"] = {s: counts([r for r in records if r["structure"] == s]) for s in ("lead_lag", "pure_gain")}
    out["by_change"] = {c: counts([r for r in records if r["change"] == c]) for c in EXPECTED_KIND if c != "none"}
    times = [r["analyze_s"] for r in records]
    out["median_analyze_s"] = float(np.median(times)) if times else None
    return out


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01, progress=None) -> dict:
    tasks = [(seed, k, samples, alpha) for k in range(runs)]
    t0 = time.perf_counter()
    records = map_runs(_one_star, tasks, jobs, progress)
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha},
            "summary": summarise(records), "seconds": time.perf_counter() - t0, "records": records}


def _line(name: str, x: dict) -> str:
    med = "-" if x["median_repair_error"] is None else f"{100 * x['median_repair_error']:.2g} %"
    return (f"{name:<11} located {x['located']} of {x['mismatched']}, kind right {x['kind_right']} "
            f"({', '.join(f'{k} {v}' for k, v in x['said'].items())}), within 10 % {x['repaired_within_10_percent']} "
            f"(median {med}); clean runs with a location {x['clean_runs_with_a_location']} of {x['clean_runs']}; "
            f"false locations {x['false_locations']}")


def format_table(result: dict) -> str:
    s, cfg = result["summary"], result["config"]
    lines = [f"feed-through model elements: {s['runs']} open-loop runs (seed {cfg['seed']}), {cfg['samples']} samples, "
             f"alpha {cfg['alpha']}, analyze with the repair", _line("all", s)]
    lines += [_line(name, x) for name, x in s["by_structure"].items()]
    lines += [_line(name, x) for name, x in s["by_change"].items()]
    if "located_after_new" in s:
        lines.append(f"the repaired model's detection locates {s['located_after_new']} element(s) not located before "
                     f"(drawn {s['located_after_new_drawn']}) and {s['located_after_again']} repaired element(s) "
                     f"again (drawn {s['located_after_again_drawn']})")
    lines.append(f"median analyze {s['median_analyze_s']:.2f} s ({result['seconds']:.0f} s)")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    return run_mc_main(argv, "python -m bench.feedthrough_mc", __doc__, 200, DEFAULT_OUT, run, format_table)


if __name__ == "__main__":
    raise SystemExit(main())
