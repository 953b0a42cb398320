"""The element tests' level in closed loop: their p-values where the model is right.

Run::

    python -m bench.element_level [--runs 800] [--seed 3] [--samples 3000] [--jobs 1] [--step-form]
                                  [--noise-order] [--drop 0.002 [--cut]] [--family main]
                                  [--paired BASE.json] [--out bench/results/element_level.json]

The scenarios are those of :mod:`bench.structures_mc` (the same family, a pure function of
``(seed, index)``; seeds 0 and 1 are its scored runs, so this check defaults to seed 3).  Each run is
simulated and detected with the default options (no repair, no detectable change), and every element
of every row **without a mismatch** contributes its two unadjusted p-values, the lag window's
(``p_value_window``) and the whole response's (``p_value_response``, where the element has one).
Under "no mismatch" a valid test's p-value is uniform: the fraction below ``t`` is ``t``.  The table
counts the p-values below 0.05, 0.01 and 0.001 against that expectation, for all elements and split
by the element's structure (integrating or not) and role (input or measured disturbance), with the
one-sided Poisson tail of each count (a small tail says the test rejects too often there).

With ``--step-form`` every run's model is analysed in its step-response (DMC) form instead
(:func:`bench.step_models.step_form`: the same plant and log, the model's elements as step responses
of ``N`` coefficients, ramps on the integrating rows), so the level of the tests on a model that
states no poles is measured apart (default output ``element_level_step.json``).  An element is
grouped by the structure of the parametric model it was drawn from.

With ``--noise-order`` the p-values are those of ``analyze`` (no repair, no release of explained
elements, no spike screening: the detection alone), which raises the ARX order ``na`` while a row's
element-test residual is coloured (:mod:`mpm_monitor.core.noise_order`); without it, the first
detection's at ``na`` = 4.  Either way the S_Delta row test's unadjusted p-value of every row without a
mismatch is counted too (the group ``rows (S_Delta test)``).

With ``--family F`` the loops are those of another ``bench.structures_mc`` family (``lost-lag``,
``gained-lag``, ``pure-gains``, ``two-lag-leads``, ``lost-pair``: its variant flag); the default ``main`` is
the family above.

With ``--drop P`` every sample of each run is dropped with probability ``P`` before the analysis (the
rows removed, as :mod:`bench.gaps_mc` does; the drops a pure function of the seed and the run), and the
p-values are ``analyze``'s as with ``--noise-order``: the gaps' regression rows are left out and the
statistics use the rows kept, so the level must not move.  Compare with a ``--noise-order`` run of the
same seed (default output ``element_level_drop.json``).

With ``--cut`` (and ``--drop``) each run is analysed a second time without the drops, its log cut short
by as many rows as the drops lost (no gap; the record's ``cut``): what losing as many rows alone does.
``--paired BASE.json`` then compares every p-value, element by element, with a run of the same seed
without drops (``--noise-order``, the same ``analyze``): per test and group, the mean of ``z^2`` (``z``
the normal quantile of ``p / 2``: 1 under a valid test) in both runs, and the spread of ``z``'s change
(:func:`paired`).  A change no larger than the cut's is what losing the rows costs; a larger one is the
gaps' own (the model run through them, a level per segment).

These rows are not clean in every sense: their columns are moved by a controller that also reacts to
the other rows' mismatches.  That is where the tests must hold their level.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from scipy.special import ndtri, pdtrc

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.pipeline import analyze

from . import map_runs, write_json
from .step_models import step_form
from .structures_mc import StructuresOptions, make_structures_scenario, simulate

THRESHOLDS = (0.05, 0.01, 0.001)
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "element_level.json"
DEFAULT_OUT_STEP = Path(__file__).resolve().parent / "results" / "element_level_step.json"
DEFAULT_OUT_DROP = Path(__file__).resolve().parent / "results" / "element_level_drop.json"


#: The families of :mod:`bench.structures_mc` (its variant flags; ``main`` none).
FAMILIES = ("main", "lost-lag", "gained-lag", "pure-gains", "two-lag-leads", "lost-pair")


def family_options(family: str) -> StructuresOptions:
    """:class:`~bench.structures_mc.StructuresOptions` of one of :data:`FAMILIES`."""
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")
    return StructuresOptions(**({} if family == "main" else {family.replace("-", "_"): True}))


def run_one(seed: int, index: int, samples: int, step_response: bool = False, noise_order: bool = False,
            drop: float = 0.0, family: str = "main", cut: bool = False) -> dict:
    """The p-values of the elements and rows without a mismatch of one scenario (its model analysed in
    its step-response form with ``step_response``).

    The p-values are the first detection's (``detect``, ``na`` = 4); with ``noise_order`` those of
    ``analyze`` (without the repair, the release of explained elements and the spike screening), which
    raises ``na`` while a row's residual is coloured (:mod:`mpm_monitor.core.noise_order`).  With
    ``drop`` > 0 each sample is dropped with that probability first (:func:`bench.gaps_mc.drop_rows`),
    and the p-values are ``analyze``'s.  ``family``: one of :data:`FAMILIES` (the loops of that
    ``bench.structures_mc`` family).  With ``cut`` (and ``drop`` > 0) the record's ``cut`` holds the same
    p-values of the log without drops cut short by the rows the drops lost (:func:`_p_values`)."""
    from .gaps_mc import drop_rows

    opts = family_options(family)
    sc = make_structures_scenario(seed, index, opts)
    data = simulate(sc, samples, opts).as_logged_data(f"structures scenario {seed}/{index}")
    rec = {"index": int(index), "elements": [], "rows": []}
    if not (np.all(np.isfinite(data.y)) and np.max(np.abs(data.y)) < 1e6):
        rec["error"] = "the closed loop diverged"
        return rec
    full = data
    if drop > 0:
        kept = drop_rows(data.n_samples, drop, np.random.default_rng([seed, index, 11]))
        rec["dropped"] = int(data.n_samples - kept.size)
        data = data.take(kept)
    model = step_form(sc.model) if step_response else sc.model
    try:
        rec.update(_p_values(sc, model, data, noise_order or drop > 0))
    except Exception as exc:  # noqa: BLE001 - a benchmark records a failure and goes on
        rec["error"] = f"{type(exc).__name__}: {exc}"
        return rec
    if cut and drop > 0:
        try:
            rec["cut"] = _p_values(sc, model, full.slice(0, full.n_samples - rec.get("rows_lost", 0)), True)
        except Exception as exc:  # noqa: BLE001
            rec["cut"] = {"error": f"{type(exc).__name__}: {exc}", "elements": [], "rows": []}
    return rec


def _p_values(sc, model, data, use_analyze: bool) -> dict:
    """The unadjusted p-values of scenario ``sc``'s elements and rows without a mismatch on ``data``:
    ``{"elements": [...], "rows": [...]}``, and ``rows_lost`` on data with gaps (:func:`run_one`)."""
    if use_analyze:
        report = analyze(model, data, AnalysisOptions(repair=False, release_explained=False, drop_spikes=False))
    else:
        report = detect(model, data, AnalysisOptions(repair=False), detectability=False)
    rows = {m["output"] for m in sc.mismatches}
    out = {"rows": [{"output": i, "mismatch_run": bool(sc.mismatches), "row": float(r.p_value_raw)}
                    for i, r in enumerate(report.rows) if i not in rows], "elements": []}
    if report.gaps:
        out["rows_lost"] = int(report.gaps.get("rows_lost", 0))
    for e in report.elements:
        i, j = sc.model.outputs.index(e.output), sc.model.columns.index(e.input)
        if i in rows or e.p_value_window is None:
            continue
        out["elements"].append({"output": i, "column": j, "role": e.role,
                                "integrating": bool(sc.model.present[i, j]
                                                    and sc.model.discrete_element(i, j).integrating),
                                "present": bool(sc.model.present[i, j]),
                                "mismatch_run": bool(sc.mismatches),
                                "window": float(e.p_value_window),
                                "response": None if e.p_value_response is None else float(e.p_value_response)})
    return out


def _run_one_star(args):
    return run_one(*args)


def poisson_upper_tail(k: int, mean: float) -> float:
    """``P(N >= k)`` for ``N`` Poisson with ``mean`` (``scipy.special.pdtrc``, no cancellation in the tail)."""
    return 1.0 if k <= 0 else float(pdtrc(k - 1, mean))


def count(ps: Sequence[float]) -> dict:
    """Counts below each threshold, their expectation under a uniform p-value and the Poisson tail."""
    ps = np.asarray([p for p in ps if p is not None and np.isfinite(p)], dtype=float)
    out = {"n": int(ps.size), "below": {}, "expected": {}, "tail": {}}
    for t in THRESHOLDS:
        k, m = int(np.sum(ps < t)), ps.size * t
        out["below"][str(t)], out["expected"][str(t)] = k, m
        out["tail"][str(t)] = poisson_upper_tail(k, m)
    return out


GROUPS = (("all", lambda e: True),
          ("integrating elements", lambda e: e["integrating"]),
          ("stable elements the model has", lambda e: e["present"] and not e["integrating"]),
          ("elements the model lacks", lambda e: not e["present"]),
          ("inputs", lambda e: e["role"] == "input"),
          ("measured disturbances", lambda e: e["role"] != "input"),
          ("rows of runs with a mismatch", lambda e: e["mismatch_run"]),
          ("runs without a mismatch", lambda e: not e["mismatch_run"]))


def score(records: Sequence[dict]) -> dict:
    """Per group and test, the counts of :func:`count` (the rows' S_Delta test as one more group)."""
    elements = [e for r in records for e in r["elements"]]
    out = {name: {test: count([e[test] for e in elements if keep(e)]) for test in ("window", "response")}
           for name, keep in GROUPS}
    out["rows (S_Delta test)"] = {"row": count([w["row"] for r in records for w in r.get("rows", [])])}
    return out


def _z(p: float) -> float:
    """The normal quantile of ``p / 2`` (``|z|`` of a two-sided test with p-value ``p``; ``z^2`` is the
    chi-square(1) quantile of ``p``); ``p`` below 1e-300 (a p-value of 0) is taken as 1e-300 (``z`` 37.1)."""
    return float(-ndtri(max(p, 1e-300) / 2.0))


def paired(base: Sequence[dict], records: Sequence[dict], key: Optional[str] = None) -> dict:
    """Element by element, this run's p-values (``key``: a record's part, e.g. ``"cut"``) against ``base``'s.

    Parameters
    ----------
    base, records : sequence of dict
        :func:`run_one`'s records of the same seed and runs (``base`` without drops).
    key : str, optional
        Read each record's ``record[key]`` (its ``elements``) instead of the record itself.

    Returns
    -------
    dict
        Per group of :data:`GROUPS` and test: ``n`` elements tested in both, ``z2_base`` and ``z2`` the mean
        ``z^2`` in each (1 under a valid test), ``dz_mean`` and ``dz_sd`` the mean and standard deviation of
        ``z``'s change (:func:`_z`).
    """
    ref = {(r["index"], e["output"], e["column"]): e for r in base if "error" not in r for e in r["elements"]}
    pairs = []
    for r in records:
        part = r.get(key) if key else r
        if "error" in r or part is None or "error" in part:
            continue
        pairs += [(ref[(r["index"], e["output"], e["column"])], e) for e in part["elements"]
                  if (r["index"], e["output"], e["column"]) in ref]
    out = {}
    for name, keep in GROUPS:
        out[name] = {}
        for test in ("window", "response"):
            z = np.array([(_z(a[test]), _z(b[test])) for a, b in pairs
                          if keep(b) and a[test] is not None and b[test] is not None]).reshape(-1, 2)
            if not z.shape[0]:
                continue
            dz = z[:, 1] - z[:, 0]
            out[name][test] = {"n": int(z.shape[0]), "z2_base": float(np.mean(z[:, 0] ** 2)),
                               "z2": float(np.mean(z[:, 1] ** 2)), "dz_mean": float(np.mean(dz)),
                               "dz_sd": float(np.std(dz))}
    return out


def format_paired(comparisons: dict) -> str:
    """The :func:`paired` comparisons ``{label: paired(...)}`` as a table."""
    lines = ["paired with the run without drops: mean z^2 (1 under a valid test) and the change of z, element by element",
             f"{'group':<32} {'test':<9} {'against':<7} {'n':>6} {'z^2 base':>9} {'z^2':>7} {'mean dz':>8} {'sd dz':>7}"]
    labels = list(comparisons)
    for name, _ in GROUPS:
        for test in ("window", "response"):
            for label in labels:
                c = comparisons[label].get(name, {}).get(test)
                if c:
                    lines.append(f"{name:<32} {test:<9} {label:<7} {c['n']:>6} {c['z2_base']:>9.3f} {c['z2']:>7.3f} "
                                 f"{c['dz_mean']:>8.3f} {c['dz_sd']:>7.3f}")
    return "\n".join(lines)


def format_table(result: dict) -> str:
    form = " (models in step-response form)" if result["config"].get("step_form") else ""
    if result["config"].get("drop"):
        form += f" (each sample dropped with probability {result['config']['drop']:g})"
    if result["config"].get("family", "main") != "main":
        form += f" (bench.structures_mc family --{result['config']['family']})"
    lines = [f"element tests' level{form}: seed {result['config']['seed']}, {result['config']['runs']} runs, "
             f"{result['config']['errors']} not analysed; p-values of the elements of rows without a mismatch",
             f"{'group':<32} {'test':<9} {'n':>6}   " + "   ".join(f"below {t:<5} (exp, tail)" for t in THRESHOLDS)]
    for name, tests in result["summary"].items():
        for test, c in tests.items():
            if not c["n"]:
                continue
            cells = "   ".join(f"{c['below'][str(t)]:>5} ({c['expected'][str(t)]:6.1f}, {c['tail'][str(t)]:.3f})"
                               for t in THRESHOLDS)
            lines.append(f"{name:<32} {test:<9} {c['n']:>6}   {cells}")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.element_level", description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=800, help="random closed loops (default 800)")
    parser.add_argument("--seed", type=int, default=3, help="family seed (default 3; 0 and 1 are bench.structures_mc's)")
    parser.add_argument("--samples", type=int, default=3000, help="samples per run (default 3000)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--step-form", action="store_true",
                        help="analyse each run's model in its step-response form (bench.step_models.step_form)")
    parser.add_argument("--noise-order", action="store_true",
                        help="the p-values of analyze, which raises na while a row's residual is coloured, instead "
                             "of the first detection's")
    parser.add_argument("--drop", type=float, default=0.0,
                        help="drop each sample with this probability before analyze (default 0: none)")
    parser.add_argument("--family", choices=FAMILIES, default="main",
                        help="the loops of this bench.structures_mc family (default main: no variant flag)")
    parser.add_argument("--cut", action="store_true",
                        help="with --drop: also analyse each log without drops, cut short by the rows the drops lost")
    parser.add_argument("--paired", type=Path, default=None, metavar="BASE.json",
                        help="compare every p-value with this run's of the same seed without drops (--noise-order)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON output (default bench/results/element_level.json, element_level_step.json "
                             "with --step-form, element_level_drop.json with --drop)")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.samples < 100 or args.jobs < 1:
        parser.error("--runs and --jobs must be >= 1 and --samples >= 100")
    if not 0.0 <= args.drop < 0.5:
        parser.error(f"--drop must be a probability in [0, 0.5), got {args.drop}")
    if args.cut and not args.drop:
        parser.error("--cut needs --drop")
    base = None
    if args.paired is not None:
        import json

        base = json.loads(args.paired.read_text())
        if base["config"]["seed"] != args.seed or base["config"].get("drop"):
            parser.error(f"--paired {args.paired}: expected a run of seed {args.seed} without drops")
    t0 = time.perf_counter()
    records = sorted(map_runs(_run_one_star, [(args.seed, k, args.samples, args.step_form, args.noise_order,
                                                 args.drop, args.family, args.cut) for k in range(args.runs)],
                              args.jobs), key=lambda r: r["index"])
    result = {"config": {"runs": args.runs, "seed": args.seed, "samples": args.samples, "step_form": args.step_form,
                         "noise_order": args.noise_order, "drop": args.drop, "family": args.family, "cut": args.cut,
                         "errors": sum("error" in r for r in records), "wall_time_s": time.perf_counter() - t0},
              "summary": score(records), "runs": records}
    print(format_table(result))
    if base is not None:
        result["paired"] = {"drops": paired(base["runs"], records)}
        if args.cut:
            result["paired"]["cut"] = paired(base["runs"], records, "cut")
        result["config"]["paired_with"] = args.paired.name
        print()
        print(format_paired(result["paired"]))
    default = DEFAULT_OUT_DROP if args.drop > 0 else DEFAULT_OUT_STEP if args.step_form else DEFAULT_OUT
    write_json(args.out or default, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
