"""Monte-Carlo of data with gaps: one sample in 500 dropped at random, offline and live (issue item 4).

Run::

    python -m bench.gaps_mc [--paper-seeds 20] [--runs 150] [--seed 0] [--samples 3000] [--drop 0.002]
                            [--burst 1] [--split-gap 0] [--jobs 1] [--repair] [--structures 0] [--step-form] [--cut]
                            [--out bench/results/gaps_mc.json]

Every run simulates one closed loop -- the paper's three cases (:mod:`bench.paper_cases`, seeds
``1000 ..``), the random scenarios of :mod:`bench.monte_carlo` (family ``--seed``, indices ``0 ..``) and,
with ``--structures N``, the random loops of :mod:`bench.structures_mc` (every element structure,
integrating outputs, measured disturbances; family ``--seed``) -- and analyses it three times with
:func:`mpm_monitor.core.pipeline.analyze` (``repair=False``):

* ``full``: the log as simulated;
* ``offline``: the same log with each sample dropped with probability ``--drop`` (rows removed; the
  data's ``t`` skips them, as in a CSV with missing rows);
* ``live``: the same drops, the log fed sample by sample into a
  :class:`~mpm_monitor.monitor.window.SampleWindow` (the live monitor's window, ``max_gap`` 10, a
  window as long as the log; a dropped sample's three vectors never arrive) and the window's data
  analysed.

Figures: the fraction of runs whose located elements (and flagged rows) are the same with drops as
without (acceptance: at least 99 %), and the false-alarm rate (runs with any located element among
the runs without a mismatch) of the three analyses.  With ``--cut``, a fourth analysis for reference:
the log without drops, cut short by as many samples as the drops cost regression rows (``offline``'s
``rows_lost``) -- the same loss of rows in one piece at the end, where no gap's level or state is
unknown; its agreement with ``full`` is what losing that many rows alone moves.  ``--step-form`` analyses the same loops with the
controller's model in step-response form (:func:`bench.step_models.step_form`, about twelve time
constants of every element), written to ``bench/results/gaps_mc_step.json``.  The drops of run ``k``
are a pure function of the run, so ``--jobs`` only changes the speed.

``--burst L`` (``L > 1``) drops the samples in bursts instead, as a lossy link does (a Wi-Fi link to a
robot loses several messages in a row): a burst starts at each sample with probability ``--drop / L``
and its length is geometric with mean ``L`` (:func:`drop_bursts`), so that about the same fraction of
the samples is lost.  A burst longer than the analysis's ``max_gap`` splits the log (offline: the
regression's lag reach; live: the window's 10 samples, after which the window restarts, unless
``--split-gap N`` sets the window's ``split_gap``: then the window keeps its samples across a gap of
up to ``N`` samples).

``--repair`` adds the repair on the same drops.  In every run with a mismatch, the true mismatched
elements that the analysis of the full log locates are repaired
(:func:`mpm_monitor.core.repair.repair_model`) three ways:

* ``full``: on the log as simulated;
* ``spans``: on the log with the drops, every span between the gaps a record of its own, the model run
  through the short gaps (what :func:`mpm_monitor.core.pipeline.analyze` does,
  :func:`mpm_monitor.core.pipeline.repair_data` and ``RepairOptions.max_gap``; before stop 95 the bench
  left ``max_gap`` unset, every gap a restart);
* ``longest``: on the longest span without a gap only (what ``analyze`` did before).

Each repaired element's unit-step response is compared with the plant's over 300 samples
(:func:`bench.structures_mc.step_response_error`): the figures are the fraction within 10 % of the
plant's and the median error, per way.
"""

from __future__ import annotations

import argparse
import time
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.pipeline import analyze, repair_data
from mpm_monitor.core.gaps import plan_gaps
from mpm_monitor.core.regressions import regression_layout
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.monitor.window import SampleWindow, WindowOptions
from mpm_monitor.sim.cases import CASE_NAMES

from . import map_runs, write_json
from .monte_carlo import family_log
from .structures_mc import REPAIR_TOLERANCE, step_response_error

DEFAULT_OUT = "bench/results/gaps_mc.json"
STEP_OUT = "bench/results/gaps_mc_step.json"
DROP = 1.0 / 500
NS = 1_000_000_000
OPTIONS = AnalysisOptions(repair=False)


def drop_rows(n: int, probability: float, rng: np.random.Generator) -> np.ndarray:
    """Rows kept when each of ``n`` samples is dropped with ``probability`` (the first and last kept)."""
    keep = rng.random(n) >= probability
    keep[0] = keep[-1] = True
    return np.flatnonzero(keep)


def drop_bursts(n: int, probability: float, mean: float, rng: np.random.Generator) -> np.ndarray:
    """Rows kept when the ``n`` samples are dropped in bursts (the first and last kept).

    A burst starts at each sample with probability ``probability / mean``; its length is geometric with
    mean ``mean`` (at least one sample).  Bursts may overlap, so slightly fewer than ``probability * n``
    samples are dropped on average.

    Parameters
    ----------
    n : int
        Samples.
    probability : float
        Fraction of the samples to drop, in [0, 1).
    mean : float
        Mean burst length in samples, > 1.
    rng : numpy.random.Generator

    Returns
    -------
    ndarray of int, shape (n_kept,)
        The kept rows, increasing.
    """
    starts = np.flatnonzero(rng.random(n) < probability / mean)
    lengths = rng.geometric(1.0 / mean, size=starts.size)
    keep = np.ones(n, dtype=bool)
    for k, m in zip(starts, lengths):
        keep[k:k + m] = False
    keep[0] = keep[-1] = True
    return np.flatnonzero(keep)


def run_drops(kind: str, name: str, seed: int, n: int, drop: float, burst: float = 1.0) -> np.ndarray:
    """The rows kept of run ``(kind, name, seed)``'s ``n`` samples: each dropped with probability ``drop``
    (:func:`drop_rows`), or in bursts of mean length ``burst`` > 1 (:func:`drop_bursts`), a pure function of the
    run (the benches that drop samples from these runs drop the same ones)."""
    rng_seed = (seed, CASE_NAMES.index(name)) if kind == "paper" else (seed, int(name), 7 if kind == "mc" else 8)
    rng = np.random.default_rng(list(rng_seed))
    return drop_rows(n, drop, rng) if burst <= 1 else drop_bursts(n, drop, burst, rng)


def live_window_data(data: LoggedData, kept: np.ndarray, max_gap: int = 10, split_gap: int = 0) -> LoggedData:
    """The samples ``kept`` of ``data`` fed one by one into a SampleWindow; the window's data at the end."""
    ts = data.sample_time
    window = SampleWindow(data.outputs, data.inputs, ts,
                          WindowOptions(window_samples=data.n_samples, reorder_samples=2, max_gap=max_gap,
                                        split_gap=split_gap),
                          disturbances=data.disturbances)
    period = int(round(ts * NS))
    for k in kept:
        stamp = int(round(data.t[k] / ts)) * period
        window.add("setpoint", stamp, data.r[k])
        window.add("input", stamp, data.u[k])
        window.add("output", stamp, data.y[k])
        if data.disturbances:
            window.add("disturbance", stamp, data.dv[k])
    return window.data(source=f"{data.source} (live)")


def _located(model, data: LoggedData) -> dict:
    try:
        rep = analyze(model, data, OPTIONS)
    except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}
    return {"located": sorted([list(x) for x in rep.located_elements]), "rows": sorted(rep.flagged_rows),
            "samples": rep.samples, "rows_lost": (rep.gaps or {}).get("rows_lost", 0)}


def _repairs(model, plant, data: LoggedData, offline: LoggedData, pairs: list) -> dict:
    """Step-response errors of the elements ``pairs`` (names) repaired on ``data`` and on ``offline``
    (every span, and the longest span only); see the module docstring."""
    located = [(model.outputs.index(o), model.columns.index(c)) for o, c in pairs]
    spans, _ = repair_data(offline, len(offline.segments) > 1, OPTIONS, model)
    # The model run through the short gaps, as analyze runs it (RepairOptions.max_gap: the gaps' plan's).
    plan = plan_gaps(offline, regression_layout(model, OPTIONS).start, OPTIONS.max_gap)
    through = RepairOptions(max_gap=None if plan is None else int(plan.max_gap))
    a, b = max(offline.segments, key=lambda s: s[1] - s[0])
    out = {}
    for key, d in (("full", data), ("spans", spans), ("longest", offline.slice(a, b))):
        try:
            res = repair_model(model, d, located, through if key == "spans" else RepairOptions())
        except Exception as exc:  # noqa: BLE001 - a benchmark records the failure and goes on
            out[key] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        out[key] = {"step_error": [step_response_error(plant, res.model, i, j) for i, j in located],
                    "samples": int(d.n_samples)}
    return out


def run_one(kind: str, name: str, seed: int, samples: int, drop: float, repair: bool = False,
            step: bool = False, cut: bool = False, burst: float = 1.0, split_gap: int = 0) -> dict:
    """Simulate one run, drop samples and analyse it full, offline and live (with ``step``, the controller's
    model in step-response form; with ``cut``, also cut short by the rows the drops lose; with ``burst`` > 1,
    the samples dropped in bursts of that mean length; ``split_gap``: the live window's); a JSON-ready record."""
    model, plant, data, truth = family_log(kind, name, seed, samples)
    if step:
        from .step_models import step_form

        model = step_form(model)
    kept = run_drops(kind, name, seed, data.n_samples, drop, burst)
    offline = data.take(kept)
    live = live_window_data(data, kept, split_gap=split_gap)
    rec = {"kind": kind, "name": name, "seed": seed, "truth": truth, "dropped": int(data.n_samples - kept.size),
           "live_samples": int(live.n_samples)}
    if burst > 1:
        rec["gaps"] = int(np.sum(np.diff(kept) > 1))
        rec["longest_gap"] = int(np.max(np.diff(kept), initial=1)) - 1
    for key, d in (("full", data), ("offline", offline), ("live", live)):
        rec[key] = _located(model, d)
    if cut:
        lost = rec["offline"].get("rows_lost", 0)
        rec["cut"] = _located(model, data.slice(0, data.n_samples - lost))
    for key in ("offline", "live") + (("cut",) if cut else ()):
        a, b = rec["full"], rec[key]
        rec[f"same_{key}"] = "error" not in a and "error" not in b and a["located"] == b["located"] \
            and a["rows"] == b["rows"]
    pairs = [x for x in rec["full"].get("located", []) if x in truth]
    if repair and pairs:
        rec["repair"] = _repairs(model, plant, data, offline, pairs)
    return rec


def _run_star(args):
    return run_one(*args)


def tasks(paper_seeds: int, runs: int, seed: int, samples: int, drop: float, repair: bool = False,
          step: bool = False, structures: int = 0, cut: bool = False, burst: float = 1.0, split_gap: int = 0) -> list:
    rest = (repair, step, cut, burst, split_gap)
    out = [("paper", name, s, samples, drop) + rest for name in CASE_NAMES for s in range(1000, 1000 + paper_seeds)]
    return out + [("mc", str(k), seed, samples, drop) + rest for k in range(runs)] \
        + [("structures", str(k), seed, samples, drop) + rest for k in range(structures)]


def summarize(records: Sequence[dict]) -> dict:
    """Agreement with the full log and false-alarm rates, per family and overall."""
    out = {}
    for fam in ("paper", "mc", "structures", "all"):
        recs = [r for r in records if fam == "all" or r["kind"] == fam]
        if not recs:
            continue
        clean = [r for r in recs if not r["truth"]]
        fa = {key: (sum(1 for r in clean if r[key].get("located")) / len(clean) if clean else None)
              for key in ("full", "offline", "live")}
        out[fam] = {"runs": len(recs), "dropped_per_run": float(np.mean([r["dropped"] for r in recs])),
                    "gaps_per_run": float(np.mean([r["gaps"] for r in recs])) if all("gaps" in r for r in recs)
                    else None,
                    "live_samples": float(np.median([r["live_samples"] for r in recs])),
                    "same_offline": sum(r["same_offline"] for r in recs) / len(recs),
                    "same_live": sum(r["same_live"] for r in recs) / len(recs),
                    "same_cut": (sum(r["same_cut"] for r in recs) / len(recs)) if all("same_cut" in r for r in recs)
                    else None,
                    "clean_runs": len(clean), "false_alarm": fa,
                    "errors": sum(1 for r in recs for k in ("full", "offline", "live") if "error" in r[k]),
                    "differ": [{k: r[k] for k in ("kind", "name", "seed", "truth")}
                               | {"full": r["full"].get("located"), "offline": r["offline"].get("located"),
                                  "live": r["live"].get("located")}
                               for r in recs if not (r["same_offline"] and r["same_live"])]}
        repaired = [r["repair"] for r in recs if "repair" in r]
        if repaired:
            out[fam]["repair"] = {}
            for key in ("full", "spans", "longest"):
                errs = [e for rp in repaired for e in rp[key].get("step_error", [])]
                out[fam]["repair"][key] = {
                    "elements": len(errs), "errors": sum(1 for rp in repaired if "error" in rp[key]),
                    "within": sum(e <= REPAIR_TOLERANCE for e in errs) / len(errs) if errs else None,
                    "median_step_error": float(np.median(errs)) if errs else None,
                    "p90_step_error": float(np.percentile(errs, 90)) if errs else None}
    return out


def format_table(summary: dict, drop: float, burst: float = 1.0) -> str:
    w = max([7] + [len(fam) + 1 for fam in summary])          # the first column's width
    how = f"each sample dropped with probability {drop:g}" if burst <= 1 else \
        f"samples dropped in bursts of mean length {burst:g}, {drop:g} of them"
    lines = [f"gaps Monte-Carlo: {how}, analyze (repair off), alpha 0.01",
             f"{'runs':<{w}}{'n':>5}{'dropped/run':>13}{'same offline':>14}{'same live':>11}"
             f"{'clean':>7}{'false alarms full / offline / live':>37}"]
    for fam, s in summary.items():
        fa = s["false_alarm"]
        fa_text = " / ".join("-" if fa[k] is None else f"{100 * fa[k]:.1f}%" for k in ("full", "offline", "live"))
        lines.append(f"{fam:<{w}}{s['runs']:>5}{s['dropped_per_run']:>13.1f}{100 * s['same_offline']:>13.1f}%"
                     f"{100 * s['same_live']:>10.1f}%{s['clean_runs']:>7}{fa_text:>37}")
    if burst > 1:
        lines += ["", f"{'runs':<{w}}{'gaps/run':>9}{'live window (median samples)':>30}"]
        lines += [f"{fam:<{w}}{s['gaps_per_run']:>9.1f}{s['live_samples']:>30.0f}" for fam, s in summary.items()]
    if any(s.get("same_cut") is not None for s in summary.values()):
        lines += ["", "reference: the log without drops cut short by the rows the drops lose (no gap)",
                  f"{'runs':<{w}}{'same as full':>14}"]
        lines += [f"{fam:<{w}}{100 * s['same_cut']:>13.1f}%" for fam, s in summary.items() if s.get("same_cut") is not None]
    if any("repair" in s for s in summary.values()):
        lines += ["", "repair of the true mismatched elements the full log's analysis locates (step response vs the "
                  "plant's over 300 samples)",
                  f"{'runs':<{w}}{'way':<9}{'elements':>9}{'within 10%':>12}{'median error':>14}{'90th pct':>10}"]
        for fam, s in summary.items():
            for key, c in s.get("repair", {}).items():
                if c["within"] is None:
                    continue
                lines.append(f"{fam:<{w}}{key:<9}{c['elements']:>9}{100 * c['within']:>11.1f}%"
                             f"{100 * c['median_step_error']:>13.2f}%{100 * c['p90_step_error']:>9.2f}%")
    return "\n".join(lines)


def run(paper_seeds: int, runs: int, seed: int = 0, samples: int = 3000, drop: float = DROP, jobs: int = 1,
        progress: bool = False, repair: bool = False, step: bool = False, structures: int = 0,
        cut: bool = False, burst: float = 1.0, split_gap: int = 0) -> dict:
    todo = tasks(paper_seeds, runs, seed, samples, drop, repair, step, structures, cut, burst, split_gap)
    t0 = time.perf_counter()
    records = map_runs(_run_star, todo, jobs,
                       progress=(lambda done, total, _: print(f"{done}/{total}", flush=True)) if progress else None)
    return {"config": {"paper_seeds": paper_seeds, "runs": runs, "seed": seed, "samples": samples, "drop": drop,
                       "jobs": jobs, "repair": repair, "step_form": step, "burst": burst,
                       "split_gap": split_gap,
                       "structures": structures, "cut": cut, "wall_time_s": time.perf_counter() - t0},
            "summary": summarize(records), "records": records}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.gaps_mc", description=__doc__.split("\n\n")[0])
    p.add_argument("--paper-seeds", type=int, default=20, help="seeds per paper case (default 20)")
    p.add_argument("--runs", type=int, default=150, help="random scenarios of bench.monte_carlo (default 150)")
    p.add_argument("--seed", type=int, default=0, help="scenario family (default 0)")
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--drop", type=float, default=DROP, help="probability that a sample is dropped (default 1/500)")
    p.add_argument("--burst", type=float, default=1.0, help="mean length of a burst of dropped samples (default 1: "
                   "each sample dropped on its own; module docstring)")
    p.add_argument("--split-gap", type=int, default=0, help="the live window's split_gap: it keeps its samples across "
                   "a gap longer than its max_gap (10) of up to this many samples (default 0: it restarts)")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--progress", action="store_true")
    p.add_argument("--repair", action="store_true", help="also repair the located mismatches: full log, every span, "
                   "longest span (module docstring)")
    p.add_argument("--structures", type=int, default=0, help="random loops of bench.structures_mc (every element "
                   "structure, measured disturbances; family --seed), default 0")
    p.add_argument("--step-form", action="store_true", help="the controllers' models in step-response form "
                   "(bench.step_models.step_form), the same loops")
    p.add_argument("--cut", action="store_true", help="also analyse each log without drops cut short by the rows "
                   "the drops lose (the agreement that losing as many rows alone gives)")
    p.add_argument("--out", default=None, help=f"JSON output (default {DEFAULT_OUT}, with --step-form {STEP_OUT})")
    args = p.parse_args(argv)
    res = run(args.paper_seeds, args.runs, args.seed, args.samples, args.drop, args.jobs, args.progress, args.repair,
              args.step_form, args.structures, args.cut, args.burst, args.split_gap)
    if args.step_form:
        print("the controllers' models in step-response form")
    if args.split_gap:
        print(f"the live window keeps its samples across gaps of up to split_gap = {args.split_gap} samples")
    print(format_table(res["summary"], args.drop, args.burst))
    for fam, s in res["summary"].items():
        for d in s["differ"] if fam != "all" else []:
            print(f"  differs: {d}")
    write_json(args.out or (STEP_OUT if args.step_form else DEFAULT_OUT), res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
