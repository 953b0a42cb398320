"""The paper's three cases over many seeds: how often the located rows and elements are exactly
those the paper gives (:mod:`mpm_monitor.sim.cases`; issue 3 acceptance: at least 20 seeds each).

Run: ``python -m bench.paper_cases [--seeds 20] [--samples 3000] [--out bench/results/paper_cases.json]``
"""

from __future__ import annotations

import argparse
import time

from mpm_monitor.apps.reproduce import simulate_case
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.cases import CASE_NAMES

from . import write_json


def run(seeds: int, samples: int, first_seed: int = 1000) -> dict:
    """Exact-match counts per case; every run's located rows/elements in ``runs``."""
    out = {"seeds": seeds, "samples": samples, "first_seed": first_seed, "cases": {}}
    for name in CASE_NAMES:
        exact, runs, times = 0, [], []
        for s in range(first_seed, first_seed + seeds):
            case, data, _ = simulate_case(name, samples, s)
            t0 = time.perf_counter()
            rep = analyze(case.model, data, AnalysisOptions(repair=False))
            times.append(time.perf_counter() - t0)
            ok = (set(rep.flagged_rows) == set(case.mismatched_rows)
                  and set(rep.located_elements) == set(case.mismatched_elements))
            exact += ok
            runs.append({"seed": s, "exact": ok, "rows": rep.flagged_rows,
                         "located": [list(x) for x in rep.located_elements],
                         "ambiguous": [list(x) for x in rep.ambiguous_elements],
                         "rsi": {r.output: round(r.rsi, 4) for r in rep.rows}})
        times.sort()
        out["cases"][name] = {"exact": exact, "runs": len(runs), "median_analyze_s": times[len(times) // 2],
                              "expected_rows": list(case.mismatched_rows),
                              "expected_elements": [list(x) for x in case.mismatched_elements], "detail": runs}
    return out


def format_table(res: dict) -> str:
    lines = [f"paper cases, {res['seeds']} seeds each, {res['samples']} samples, alpha 0.01",
             f"{'case':<6}{'exact rows and elements':>26}{'median analyze (s)':>21}"]
    for name, c in res["cases"].items():
        lines.append(f"{name:<6}{c['exact']:>18} / {c['runs']:<5}{c['median_analyze_s']:>21.3f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.paper_cases", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--out", default="bench/results/paper_cases.json")
    args = p.parse_args(argv)
    res = run(args.seeds, args.samples)
    print(format_table(res))
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
