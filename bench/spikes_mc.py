"""Monte-Carlo of logs with spikes: a few bad samples (1 to 3 in a row) in random channels.

For the paper's cases (``--paper-seeds`` seeds each) and ``--runs`` random closed loops of
:mod:`bench.monte_carlo` (3,000 samples), each log is analysed (``analyze``, repair off):

* ``clean``: as simulated; the spikes found in it (there should be none: each would be a sample left
  out of a good log);
* ``spiked``: with ``--spikes`` (default 4) bursts written over it, each in a channel drawn among
  the setpoints, the inputs and the outputs, at a sample drawn at least 20 samples from either end,
  1, 2 or 3 samples long, each sample ``sign x U(20, 200)`` times the channel's standard deviation
  off its logged value (the sign drawn once per burst), analysed with the spikes left out (the
  default, ``drop_spikes``) and, in the first ``--kept`` runs of each family only (default 10: such
  an analysis can take minutes, its tests locating dozens of elements), kept (``drop_spikes``
  false).

Scored: the located elements and flagged rows the same as the clean log's; false alarms in the runs
without a mismatch; the written samples found, and samples found that were not written.

Run: ``python -m bench.spikes_mc [--paper-seeds 10] [--runs 150] [--spikes 4] [--kept 10] [--jobs 2] [--out bench/results/spikes_mc.json]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.spikes import find_spikes
from mpm_monitor.sim.cases import CASE_NAMES

from . import map_runs, write_json
from .monte_carlo import family_log

DEFAULT_OUT = "bench/results/spikes_mc.json"
OPTIONS = AnalysisOptions(repair=False)
EDGE = 20


def add_spikes(data: LoggedData, count: int, rng: np.random.Generator) -> tuple:
    """``data`` with ``count`` bursts written over it (module docstring), and the mask of the written samples."""
    channels = [("r", i) for i in range(data.r.shape[1])] + [("u", j) for j in range(data.u.shape[1])] + \
        [("y", i) for i in range(data.y.shape[1])]
    arrays = {"r": data.r.copy(), "u": data.u.copy(), "y": data.y.copy()}
    written = np.zeros(data.n_samples, dtype=bool)
    for _ in range(count):
        kind, c = channels[int(rng.integers(len(channels)))]
        x = arrays[kind]
        m = int(rng.integers(1, 4))
        k = int(rng.integers(EDGE, data.n_samples - EDGE - m))
        std = float(np.std(x[:, c])) or 1.0
        sign = float(rng.choice([-1.0, 1.0]))
        x[k:k + m, c] += sign * rng.uniform(20.0, 200.0, size=m) * std
        written[k:k + m] = True
    return dataclasses.replace(data, r=arrays["r"], u=arrays["u"], y=arrays["y"]), written


def _decisions(model, data: LoggedData, options: AnalysisOptions) -> dict:
    try:
        rep = analyze(model, data, options)
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"located": sorted([list(x) for x in rep.located_elements]), "rows": sorted(rep.flagged_rows),
            "samples": rep.samples}


def run_one(kind: str, name: str, seed: int, samples: int, spikes: int, kept: bool = True) -> dict:
    """One log, clean and spiked, analysed as the module docstring says; a JSON-ready record."""
    model, _, data, truth = family_log(kind, name, seed, samples)
    rng_seed = [seed, CASE_NAMES.index(name) if kind == "paper" else int(name), 31]
    found_clean = find_spikes(data)
    spiked, written = add_spikes(data, spikes, np.random.default_rng(rng_seed))
    found = np.zeros(data.n_samples, dtype=bool)
    for mask in find_spikes(spiked).values():
        found |= mask
    rec = {"kind": kind, "name": name, "seed": seed, "truth": truth,
           "clean_spikes": int(sum(int(m.sum()) for m in found_clean.values())),
           "written": int(written.sum()), "found_written": int((found & written).sum()),
           "found_not_written": int((found & ~written).sum()),
           "clean": _decisions(model, data, OPTIONS),
           "dropped": _decisions(model, spiked, OPTIONS)}
    if kept:
        rec["kept"] = _decisions(model, spiked, dataclasses.replace(OPTIONS, drop_spikes=False))
    for key in ("dropped", "kept") if kept else ("dropped",):
        a, b = rec["clean"], rec[key]
        rec[f"same_{key}"] = "error" not in a and "error" not in b and a["located"] == b["located"] \
            and a["rows"] == b["rows"]
    return rec


def _run_star(args):
    return run_one(*args)


def tasks(paper_seeds: int, runs: int, seed: int, samples: int, spikes: int, kept: int = 10) -> list:
    paper = [("paper", name, s, samples, spikes) for name in CASE_NAMES for s in range(paper_seeds)]
    return [t + (i < kept,) for i, t in enumerate(paper)] + \
        [("mc", str(k), seed, samples, spikes, k < kept) for k in range(runs)]


def summarize(records: Sequence[dict]) -> dict:
    out = {}
    for fam in ("paper", "mc", "all"):
        rs = [r for r in records if fam == "all" or r["kind"] == fam]
        if not rs:
            continue
        clean = [r for r in rs if not r["truth"]]
        with_kept = [r for r in rs if "kept" in r]
        clean_kept = [r for r in clean if "kept" in r]
        written = sum(r["written"] for r in rs)
        out[fam] = {
            "runs": len(rs), "clean_runs": len(clean),
            "runs_with_spikes_found_in_the_clean_log": sum(1 for r in rs if r["clean_spikes"]),
            "same_dropped": sum(r["same_dropped"] for r in rs) / len(rs),
            "kept_runs": len(with_kept),
            "same_kept": sum(r["same_kept"] for r in with_kept) / len(with_kept) if with_kept else None,
            "false_alarm": {key: (sum(1 for r in clean if r[key].get("located")) / len(clean) if clean else None)
                            for key in ("clean", "dropped")},
            "false_alarm_kept": (sum(1 for r in clean_kept if r["kept"].get("located")) / len(clean_kept)
                                 if clean_kept else None),
            "clean_kept_runs": len(clean_kept),
            "written_found": sum(r["found_written"] for r in rs) / written if written else None,
            "found_not_written": sum(r["found_not_written"] for r in rs),
            "errors": sum(1 for r in rs for key in ("clean", "dropped", "kept") if "error" in r.get(key, {})),
            "differ": [{k: r[k] for k in ("kind", "name", "seed", "truth", "clean", "dropped")}
                       for r in rs if not r["same_dropped"]] if fam != "all" else [],
        }
    return out


def format_table(summary: dict, spikes: int) -> str:
    lines = [f"spikes Monte-Carlo: {spikes} bursts of 1-3 samples (20-200 standard deviations) per log, analyze "
             f"(repair off), alpha 0.01",
             f"{'runs':<7}{'n':>5}{'same as clean':>15}{'clean':>7}{'false alarms clean / spiked':>29}"
             f"{'written found':>15}{'extra found':>13}{'clean logs with spikes':>24}"]
    for fam, s in summary.items():
        fa = s["false_alarm"]
        fas = " / ".join("-" if fa[k] is None else f"{100 * fa[k]:.1f}%" for k in ("clean", "dropped"))
        wf = "-" if s["written_found"] is None else f"{100 * s['written_found']:.1f}%"
        lines.append(f"{fam:<7}{s['runs']:>5}{100 * s['same_dropped']:>14.1f}%{s['clean_runs']:>7}{fas:>29}{wf:>15}"
                     f"{s['found_not_written']:>13}{s['runs_with_spikes_found_in_the_clean_log']:>24}")
    lines.append("with the spikes kept (drop_spikes false), the first runs of each family only:")
    for fam, s in summary.items():
        if s["kept_runs"]:
            fa = "-" if s["false_alarm_kept"] is None else f"{100 * s['false_alarm_kept']:.1f}%"
            lines.append(f"  {fam:<7}{s['kept_runs']:>4} runs: same as clean {100 * s['same_kept']:.1f}%; false alarms "
                         f"{fa} of {s['clean_kept_runs']} clean runs")
    return "\n".join(lines)


def run(paper_seeds: int, runs: int, seed: int = 0, samples: int = 3000, spikes: int = 4, jobs: int = 1,
        progress: bool = False, kept: int = 10) -> dict:
    todo = tasks(paper_seeds, runs, seed, samples, spikes, kept)
    t0 = time.perf_counter()
    records = map_runs(_run_star, todo, jobs,
                       progress=(lambda done, total, _: print(f"{done}/{total}", flush=True)) if progress else None)
    records.sort(key=lambda r: (r["kind"], r["name"], r["seed"]))
    return {"config": {"paper_seeds": paper_seeds, "runs": runs, "seed": seed, "samples": samples, "spikes": spikes,
                       "kept": kept, "jobs": jobs, "wall_time_s": time.perf_counter() - t0},
            "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.spikes_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--paper-seeds", type=int, default=10, help="seeds per paper case (default 10)")
    p.add_argument("--runs", type=int, default=150, help="random scenarios of bench.monte_carlo (default 150)")
    p.add_argument("--seed", type=int, default=0, help="scenario family (default 0)")
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--spikes", type=int, default=4, help="bursts written over each log (default 4)")
    p.add_argument("--kept", type=int, default=10, help="runs of each family also analysed with the spikes kept "
                   "(default 10; slow)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--progress", action="store_true")
    p.add_argument("--out", default=DEFAULT_OUT)
    args = p.parse_args(argv)
    res = run(args.paper_seeds, args.runs, args.seed, args.samples, args.spikes, args.jobs, args.progress, args.kept)
    print(format_table(res["summary"], args.spikes))
    for fam, s in res["summary"].items():
        for d in s["differ"]:
            print(f"  differs: {d}")
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
