"""Fat plants: does a row next to a mismatched one keep the false-alarm level?

On a plant with more inputs than outputs, without dither, the MPC moves its inputs together.  With
one mismatched element ``(m, j)``, ``Delta`` has only row ``m``, so every other row of
``S_Delta = (I + Delta C)^-1`` is a row of the identity: its S_Delta test and its element tests are
tests of true hypotheses, and the family-wise false-alarm rate of the analysis (``alpha``, split
between the row tests and the element tests) bounds how often any of them rejects.

For every run ``k`` of family ``seed`` this draws the scenario of :mod:`bench.scenarios` restricted to
fat plants (``n_inputs > n_outputs``), without dither, with exactly one mismatched element, and runs
the analysis (``repair=False``); the same plant with a correct model is the reference (no mismatch
at all).  Recorded:

* runs in which a row without mismatch is flagged (by its S_Delta test, or through a located
  element);
* runs in which an element of a row without mismatch is located;
* the unadjusted p-values of the S_Delta tests of the rows without mismatch (uniform on [0, 1]
  when the test keeps its level: Kolmogorov-Smirnov distance and p-value, and the fraction below
  0.01 and 0.001);
* the power: runs whose mismatched row is flagged.

Run: ``python -m bench.fat_rows [--runs 300] [--seed 0] [--jobs 2] [--out bench/results/fat_rows.json]``
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from scipy import stats

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze

from . import mc_parser, write_json
from .monte_carlo import simulate
from .scenarios import ScenarioOptions, make_scenario

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "fat_rows.json"
#: Fat plants without dither: inputs 3..8, outputs 2..7 (redrawn until n_inputs > n_outputs).
FAT = ScenarioOptions(dither_fraction=0.0)


def fat_scenario(seed: int, index: int, n_mismatches: int):
    """Scenario ``index`` of family ``seed`` among the fat ones (sub-draws ``index * 100 + k``)."""
    for k in range(100):
        sc = make_scenario(seed, index * 100 + k, FAT, n_mismatches=n_mismatches)
        if sc.shape[1] > sc.shape[0]:
            return sc
    raise RuntimeError(f"no fat plant among the draws of run {index}")   # pragma: no cover - 100 draws


def _decisions(sc, model, data, alpha: float) -> dict:
    rep = analyze(model, data, AnalysisOptions(alpha=alpha, repair=False))
    oi = {name: k for k, name in enumerate(model.outputs)}
    return {"rows": [oi[r.output] for r in rep.rows if r.mismatch],
            "row_p_raw": [r.p_value_raw for r in rep.rows],
            "located": [[oi[e.output], model.inputs.index(e.input)] for e in rep.elements if e.mismatch],
            "ambiguous": sum(e.ambiguous for e in rep.elements)}


def one(seed: int, index: int, samples: int, alpha: float) -> dict:
    """One fat plant with one mismatched element, and the same loop with a correct model."""
    sc = fat_scenario(seed, index, 1)
    m = sc.mismatches[0]
    mismatched = _decisions(sc, sc.model, simulate(sc, samples), alpha)
    clean_sc = dataclasses.replace(sc, model=sc.plant)
    clean = _decisions(clean_sc, sc.plant, simulate(clean_sc, samples), alpha)
    return {"index": index, "shape": list(sc.shape), "mismatch": {"output": m.output, "input": m.input,
                                                                  "kind": m.kind, "size": m.size},
            "mismatched": mismatched, "clean": clean}


def _one_star(args):
    return one(*args)


def summarise(records: Sequence[dict], alpha: float) -> dict:
    """False alarms next to the mismatched row, against the correct model's; the power."""
    def block(key):
        runs = len(records)
        other_row = other_el = 0
        p_clean = []
        for r in records:
            res = r[key]
            m = r["mismatch"]["output"] if key == "mismatched" else -1
            other_row += any(i != m for i in res["rows"])
            other_el += any(i != m for i, _ in res["located"])
            p_clean += [p for i, p in enumerate(res["row_p_raw"]) if i != m and p is not None]
        p = np.array(p_clean)
        ks = stats.kstest(p, "uniform") if p.size else None
        return {"runs": runs, "runs_with_other_row_flagged": other_row,
                "rate_other_row_flagged": other_row / runs if runs else None,
                "runs_with_other_element_located": other_el,
                "clean_rows": int(p.size), "fraction_raw_p_below_0.01": float(np.mean(p < 0.01)) if p.size else None,
                "fraction_raw_p_below_0.001": float(np.mean(p < 0.001)) if p.size else None,
                "ks_statistic": float(ks.statistic) if ks else None, "ks_p_value": float(ks.pvalue) if ks else None}

    power = sum(r["mismatch"]["output"] in r["mismatched"]["rows"] for r in records)
    return {"alpha": alpha, "row_family_level": alpha / 2, "next_to_mismatch": block("mismatched"),
            "no_mismatch": block("clean"),
            "power_mismatched_row_flagged": power / len(records) if records else None}


def run(runs: int, seed: int = 0, samples: int = 3000, jobs: int = 1, alpha: float = 0.01) -> dict:
    tasks = [(seed, k, samples, alpha) for k in range(runs)]
    t0 = time.perf_counter()
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(jobs) as pool:
            records = list(pool.imap(_one_star, tasks))
    else:
        records = [one(*t) for t in tasks]
    return {"config": {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha,
                       "wall_time_s": time.perf_counter() - t0},
            "summary": summarise(records, alpha), "runs": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = mc_parser("python -m bench.fat_rows", __doc__, 300, DEFAULT_OUT)
    args = parser.parse_args(argv)
    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha)
    s = result["summary"]
    for key in ("next_to_mismatch", "no_mismatch"):
        b = s[key]
        print(f"{key}: {b['runs_with_other_row_flagged']}/{b['runs']} runs with a row without mismatch flagged, "
              f"{b['runs_with_other_element_located']} with an element located there; raw row p-values of "
              f"{b['clean_rows']} rows: below 0.01 {b['fraction_raw_p_below_0.01']:.3f}, below 0.001 "
              f"{b['fraction_raw_p_below_0.001']:.4f}, KS p {b['ks_p_value']:.3f}")
    print(f"power (mismatched row flagged): {s['power_mismatched_row_flagged']:.3f}")
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
