"""Monte-Carlo benchmark of mismatch location: our ARX method against the two baselines (issue 3).

Run::

    python -m bench.monte_carlo [--runs 200] [--seed 0] [--samples 3000] [--jobs 1]
                                [--methods arx,xcorr,pcorr] [--dither-fat | --still | --setpoint-steps]
                                [--bounds Q]
                                [--out bench/results/monte_carlo.json]

``--still``: every setpoint held at 0 and no dither, so the inputs move only with the controller's
feedback of the noise (``bench/results/monte_carlo_still.json``; the false-alarm rate there, and what a
square loop's element test can still locate).

``--setpoint-steps``: every setpoint moved in steps, as operators move them, instead of the paper's
PRBS (each held at least 60 samples, then switched with probability 1 % a sample: about 30 steps in
3000 samples; :data:`bench.scenarios.SETPOINT_STEPS`); the inputs move sharply at a step and little
between (``bench/results/monte_carlo_setpoint_steps.json``).

``--bounds Q``: every loop is run a second time with its MPC's inputs bounded at the ``Q`` quantile of
their magnitude in the first run, and their moves at the ``(1 + Q) / 2`` quantile of theirs
(:func:`bounded_scenario`; the MPC solves its QP with the bounds, so the loop is no longer linear), and
the methods analyse that log (``bench/results/monte_carlo_bounded.json``); the ``arx`` result of the
same loop without bounds is kept beside it, with how often the bounds were active.

Every run draws a random scenario (:mod:`bench.scenarios`: plant 2x2 to 8x8, 0 to 3 mismatched
elements of random kind and size, the paper's noise and MPC tuning, PRBS setpoints, input dither
in 30 % of the runs), simulates the closed loop once, and gives the *same* logged ``r, u, y`` to
every method:

* ``arx``: :func:`mpm_monitor.core.pipeline.analyze` with ``method="arx"`` (S_Delta row test, then the
  Delta element test on the flagged rows), ``repair=False`` (the repair does not change which
  elements are located and is timed separately);
* ``xcorr`` / ``pcorr``: the baselines of :mod:`mpm_monitor.core.baselines`, called exactly as
  ``analyze`` calls them (on ``d`` recomputed from the log by
  :func:`mpm_monitor.core.signals.compute_signals` with the same initial-state estimate, and ``u``), at
  the same ``alpha``.  They are called directly so that the bench also sees the ``ambiguous``
  elements of the partial correlation test.

Scoring (per method, pooled over runs):

* elements: a located element on a true mismatch is a hit (TP), elsewhere a false positive (FP);
  a true mismatch not located is a miss (FN).  Elements reported **ambiguous** (inputs the closed
  loop drives collinearly) are neither: they are counted separately, split into "justified"
  (the input's measured separability, :func:`bench.scenarios.input_separability`, is below
  ``SEPARABILITY_COLLINEAR``) and "unjustified".  ``precision = TP / (TP + FP)``,
  ``recall = TP / (TP + FN)`` (ambiguous excluded) and ``recall_all`` (ambiguous true mismatches
  counted as misses);
* rows: ``arx`` uses its S_Delta row decision; a baseline flags a row when it locates an element
  in it;
* false alarms: among the runs without any mismatch, the fraction with at least one located
  element (and with at least one flagged row);
* breakdowns of recall by mismatch kind, by size, by plant shape and by dither, and the list of
  every miss and false positive (for failure analysis) in the JSON;
* timing: the median wall time of ``analyze`` (every method, ``repair=False`` and the default
  ``repair=True`` for ``arx``) on 3,000 samples of a 5x5 scenario.

Scenario ``k`` of seed ``s`` is a pure function of ``(s, k)``: ``--jobs`` only changes the speed.
"""

from __future__ import annotations

# One BLAS thread per process is set by the bench package (bench/__init__.py), imported before this module:
# the machine is shared and --jobs gives the parallelism.
import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.baselines import ELEMENT_TESTS
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.signals import compute_signals
from mpm_monitor.sim.closed_loop import run_closed_loop

from . import map_runs
from .scenarios import KINDS, SETPOINT_STEPS, STILL, Scenario, ScenarioOptions, input_separability, make_scenario

METHODS = ("arx", "xcorr", "pcorr")
ALPHA = 0.01
#: An input whose separability is below this is "collinear" in the ground truth of ambiguity.
SEPARABILITY_COLLINEAR = 1e-2
SIZE_BINS = ((0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.0001))
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "monte_carlo.json"


# --------------------------------------------------------------------------- one run
def simulate(scenario: Scenario, samples: int) -> LoggedData:
    """Closed-loop log of a scenario as :class:`LoggedData` (what a user would hand to ``analyze``)."""
    return _closed_loop(scenario, samples).as_logged_data(f"scenario {scenario.seed}/{scenario.index}")


def _closed_loop(scenario: Scenario, samples: int):
    """The scenario's :class:`~mpm_monitor.sim.closed_loop.ClosedLoopLog` (its dither apart)."""
    return run_closed_loop(scenario.plant, scenario.model, samples, seed=scenario.loop_seed, mpc=scenario.mpc,
                           excitation=scenario.excitation, disturbance=scenario.disturbance)


def family_log(kind: str, name: str, seed: int, samples: int) -> tuple:
    """One log of a bench run over the paper's cases and the Monte-Carlo scenarios.

    Parameters
    ----------
    kind : str
        ``"paper"`` (``name`` one of the cases, ``seed`` its noise seed), ``"mc"`` (``name`` the
        scenario index of family ``seed``) or ``"structures"`` (``name`` the run of
        :func:`bench.structures_mc.make_structures_scenario`'s family ``seed``: every element structure,
        integrating outputs, measured disturbances).
    seed : int
    samples : int

    Returns
    -------
    (PlantModel, PlantModel, LoggedData, list)
        The controller's model, the plant, the closed-loop log and the mismatched elements as sorted
        ``[output, input]`` name pairs (a measured disturbance by its name).
    """
    if kind == "structures":
        from . import structures_mc

        sc = structures_mc.make_structures_scenario(seed, int(name))
        data = structures_mc.simulate(sc, samples).as_logged_data(source=f"structures run {name}")
        model = sc.model
        return model, sc.plant, data, \
            sorted([model.outputs[int(m["output"])], model.columns[int(m["column"])]] for m in sc.mismatches)
    if kind == "paper":
        from mpm_monitor.apps.reproduce import simulate_case

        case, data, _ = simulate_case(name, samples, seed)
        return case.model, case.plant, data, sorted(list(x) for x in case.mismatched_elements)
    sc = make_scenario(seed, int(name))
    model = sc.model
    return model, sc.plant, simulate(sc, samples), \
        sorted([model.outputs[m.output], model.inputs[m.input]] for m in sc.mismatches)


def _analysis():
    """The analysis (:mod:`mpm_monitor.core.pipeline`), or None while it does not exist."""
    try:
        from mpm_monitor.core import pipeline
    except ImportError:
        return None
    return pipeline


def _run_arx(model, data: LoggedData, alpha: float) -> dict:
    analysis = _analysis()
    if analysis is None:
        raise RuntimeError("mpm_monitor.core.analysis is not available: method 'arx' cannot run")
    t0 = time.perf_counter()
    report = analysis.analyze(model, data, AnalysisOptions(method="arx", alpha=alpha, repair=False))
    dt = time.perf_counter() - t0
    oi = {name: k for k, name in enumerate(model.outputs)}
    ii = {name: k for k, name in enumerate(model.inputs)}
    located = sorted((oi[e.output], ii[e.input]) for e in report.elements if e.mismatch)
    ambiguous = sorted((oi[e.output], ii[e.input]) for e in report.elements if e.ambiguous and not e.mismatch)
    rows = sorted(oi[r.output] for r in report.rows if r.mismatch)
    return {"located": located, "ambiguous": ambiguous, "rows": rows, "time_s": dt,
            "warnings": list(report.warnings)}


def _run_baseline(method: str, model, data: LoggedData, alpha: float) -> dict:
    t0 = time.perf_counter()
    sig = compute_signals(model, data.r, data.u, data.y, "estimate")
    res = ELEMENT_TESTS[method](sig.d, data.u, alpha=alpha)
    dt = time.perf_counter() - t0
    located = sorted((int(i), int(j)) for i, j in np.argwhere(res.mismatch))
    amb = res.ambiguous if res.ambiguous is not None else np.zeros_like(res.mismatch)
    ambiguous = sorted((int(i), int(j)) for i, j in np.argwhere(amb & ~res.mismatch))
    rows = sorted({i for i, _ in located})
    return {"located": located, "ambiguous": ambiguous, "rows": rows, "time_s": dt, "warnings": list(res.warnings)}


def run_method(method: str, model, data: LoggedData, alpha: float = ALPHA) -> dict:
    """Located elements, ambiguous elements, flagged rows and wall time of one method on one log.

    Returns
    -------
    dict
        ``located``, ``ambiguous`` (lists of ``(output, input)`` index pairs), ``rows`` (output
        indices), ``time_s``, ``warnings``; or ``error`` (a message) when the method raised.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    try:
        if method == "arx":
            return _run_arx(model, data, alpha)
        return _run_baseline(method, model, data, alpha)
    except Exception as exc:  # noqa: BLE001 - a benchmark records a method's failure and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}


def bounded_scenario(sc: Scenario, moves: np.ndarray, quantile: float) -> tuple:
    """The scenario with bounds on its MPC's inputs and moves, placed from its run without bounds.

    Each input ``j`` is bounded to ``|u_j| <= U_j`` and ``|du_j| <= D_j``, ``U_j`` the ``quantile`` of
    ``|u_j|`` and ``D_j`` the ``(1 + quantile) / 2`` quantile of ``|u_j(k) - u_j(k - 1)|`` over the run
    without bounds (in deviations: the scenarios' operating point is 0), so that the bounded loop
    spends a share of its samples against them.  The bounds hold the MPC's inputs; a dither is added
    after them (:func:`~mpm_monitor.sim.closed_loop.run_closed_loop`).

    Parameters
    ----------
    sc : Scenario
    moves : ndarray, shape (n_samples, n_inputs)
        The MPC's inputs in the run without bounds (the plant's inputs less the dither).
    quantile : float
        In (0, 1).

    Returns
    -------
    (Scenario, dict)
        The bounded scenario, and its bounds (``u_max``, ``du_max``: lists, input units).
    """
    u = np.asarray(moves, dtype=float)
    hi = np.quantile(np.abs(u), quantile, axis=0)
    dmax = np.quantile(np.abs(np.diff(u, axis=0)), (1.0 + quantile) / 2.0, axis=0)
    hi = np.maximum(hi, 1e-9)
    dmax = np.maximum(dmax, 1e-9)
    mpc = dataclasses.replace(sc.mpc, u_min=[-float(x) for x in hi], u_max=[float(x) for x in hi],
                              du_max=[float(x) for x in dmax])
    return dataclasses.replace(sc, mpc=mpc), {"u_max": hi.tolist(), "du_max": dmax.tolist()}


def bound_activity(u: np.ndarray, bounds: dict) -> dict:
    """Shares of a bounded run's samples with an input at a bound (:func:`bounded_scenario`'s).

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_inputs)
        The MPC's inputs (the plant's less the dither).
    bounds : dict
        ``u_max`` and ``du_max`` (each one per input).

    Returns
    -------
    dict
        ``u``: share of (sample, input) pairs at ``+-u_max``; ``du``: of moves at ``+-du_max``;
        ``any``: of samples with some input at either bound.
    """
    u = np.asarray(u, dtype=float)
    hi, dmax = np.asarray(bounds["u_max"]), np.asarray(bounds["du_max"])
    at_u = np.abs(u) >= hi * (1 - 1e-9)
    moves = np.abs(np.diff(u, axis=0, prepend=u[:1]))
    at_du = moves >= dmax * (1 - 1e-9)
    return {"u": float(at_u.mean()), "du": float(at_du[1:].mean()), "any": float((at_u | at_du).any(axis=1).mean())}


def run_one(seed: int, index: int, samples: int, methods: Sequence[str],
            scenario_options: ScenarioOptions = ScenarioOptions(), alpha: float = ALPHA,
            bounds: Optional[float] = None) -> dict:
    """Draw, simulate and analyse scenario ``(seed, index)``; return its JSON-ready record.

    ``bounds``: a quantile in (0, 1): the loop is run with its MPC's inputs and moves bounded
    (:func:`bounded_scenario`, from a first run without bounds) and the methods analyse the bounded
    log; the record also holds the bounds, their activity (:func:`bound_activity`), the inputs'
    separability without them, and the ``arx`` result on the log without bounds (``results_unbounded``)."""
    sc = make_scenario(seed, index, scenario_options)
    t0 = time.perf_counter()
    log = _closed_loop(sc, samples)
    data = log.as_logged_data(f"scenario {sc.seed}/{sc.index}")
    sim_time = time.perf_counter() - t0
    bounded = free_results = None
    if bounds is not None:
        free = data
        sc_b, limits = bounded_scenario(sc, log.u - log.dither, bounds)
        t0 = time.perf_counter()
        log = _closed_loop(sc_b, samples)
        data = log.as_logged_data(f"scenario {sc.seed}/{sc.index}, bounded")
        sim_time += time.perf_counter() - t0
        free_sep = input_separability(free.u)
        bounded = {"quantile": float(bounds), **limits, "active": bound_activity(log.u - log.dither, limits),
                   "free_separability": [float(x) for x in free_sep],
                   "free_collinear_inputs": [int(j) for j in np.flatnonzero(free_sep < SEPARABILITY_COLLINEAR)]}
        free_results = {"arx": run_method("arx", sc.model, free, alpha)} if "arx" in methods else {}
    sep = input_separability(data.u)
    rec = sc.describe()
    rec["simulation_time_s"] = sim_time
    rec["separability"] = [float(x) for x in sep]
    rec["collinear_inputs"] = [int(j) for j in np.flatnonzero(sep < SEPARABILITY_COLLINEAR)]
    rec["results"] = {m: run_method(m, sc.model, data, alpha) for m in methods}
    if bounded is not None:
        rec["results_unbounded"] = free_results
        rec["bounds"] = bounded
    return rec


def _run_one_star(args):
    return run_one(*args)


# --------------------------------------------------------------------------- scoring
def _ratio(num: float, den: float) -> Optional[float]:
    return float(num) / float(den) if den else None


def _size_bin(size: float) -> str:
    for lo, hi in SIZE_BINS:
        if lo <= size < hi:
            return f"{lo:.1f}-{min(hi, 1.0):.1f}"
    return "other"


def score(records: Sequence[dict], method: str) -> dict:
    """Pooled element, row and false-alarm scores of one method over run records (see module docstring)."""
    el = dict(tp=0, fp=0, fn=0, tn=0, amb_true=0, amb_clean=0, amb_justified=0, amb_unjustified=0)
    row = dict(tp=0, fp=0, fn=0, tn=0)
    clean_runs = clean_alarm_el = clean_alarm_row = 0
    errors = []
    times = []
    by = {"kind": {}, "size": {}, "shape": {}, "dither": {}}
    fp_by_shape = {}
    misses, false_pos = [], []
    for rec in records:
        res = rec["results"].get(method)
        if res is None:
            continue
        if "error" in res:
            errors.append({"index": rec["index"], "error": res["error"]})
            continue
        times.append(res["time_s"])
        ny, nu = rec["shape"]
        truth = {(m["output"], m["input"]): m for m in rec["mismatches"]}
        located = {tuple(x) for x in res["located"]}
        ambiguous = {tuple(x) for x in res["ambiguous"]} - located
        collinear = set(rec["collinear_inputs"])
        for i in range(ny):
            for j in range(nu):
                key = (i, j)
                is_true = key in truth
                if key in ambiguous:
                    el["amb_true" if is_true else "amb_clean"] += 1
                    el["amb_justified" if j in collinear else "amb_unjustified"] += 1
                    outcome = "ambiguous"
                elif key in located:
                    el["tp" if is_true else "fp"] += 1
                    outcome = "hit" if is_true else "fp"
                else:
                    el["fn" if is_true else "tn"] += 1
                    outcome = "miss" if is_true else "tn"
                if outcome == "fp":
                    false_pos.append({"index": rec["index"], "output": i, "input": j, "shape": rec["shape"],
                                      "dither": rec["dither"], "row_mismatched": any(o == i for o, _ in truth),
                                      "input_collinear": j in collinear})
                    fp_by_shape[rec["shape_class"]] = fp_by_shape.get(rec["shape_class"], 0) + 1
                if is_true:
                    m = truth[key]
                    for cat, val in (("kind", m["kind"]), ("size", _size_bin(m["size"])),
                                     ("shape", rec["shape_class"]), ("dither", "dither" if rec["dither"] else "none")):
                        cell = by[cat].setdefault(val, {"hit": 0, "miss": 0, "ambiguous": 0})
                        cell[{"hit": "hit", "miss": "miss", "ambiguous": "ambiguous"}[outcome]] += 1
                    if outcome != "hit":
                        misses.append({"index": rec["index"], "output": i, "input": j, "kind": m["kind"],
                                       "size": m["size"], "plant": m["plant"], "model": m["model"],
                                       "shape": rec["shape"], "dither": rec["dither"], "outcome": outcome,
                                       "input_collinear": j in collinear,
                                       "row_flagged": i in set(res["rows"])})
        true_rows = {i for i, _ in truth}
        flagged = set(res["rows"])
        for i in range(ny):
            if i in true_rows:
                row["tp" if i in flagged else "fn"] += 1
            else:
                row["fp" if i in flagged else "tn"] += 1
        if not truth:
            clean_runs += 1
            clean_alarm_el += bool(located)
            clean_alarm_row += bool(flagged)
    for cat in by.values():
        for cell in cat.values():
            cell["recall"] = _ratio(cell["hit"], cell["hit"] + cell["miss"])
    return {
        "runs": len(records) - len(errors),
        "errors": errors,
        "element": {**el, "precision": _ratio(el["tp"], el["tp"] + el["fp"]),
                    "recall": _ratio(el["tp"], el["tp"] + el["fn"]),
                    "recall_all": _ratio(el["tp"], el["tp"] + el["fn"] + el["amb_true"]),
                    "false_positive_rate": _ratio(el["fp"], el["fp"] + el["tn"])},
        "row": {**row, "precision": _ratio(row["tp"], row["tp"] + row["fp"]),
                "recall": _ratio(row["tp"], row["tp"] + row["fn"])},
        "false_alarms": {"clean_runs": clean_runs, "runs_with_located_element": clean_alarm_el,
                         "runs_with_flagged_row": clean_alarm_row,
                         "rate_element": _ratio(clean_alarm_el, clean_runs),
                         "rate_row": _ratio(clean_alarm_row, clean_runs)},
        "recall_by": by,
        "false_positives_by_shape": fp_by_shape,
        "median_time_s": statistics.median(times) if times else None,
        "misses": misses,
        "false_positives": false_pos,
    }


# --------------------------------------------------------------------------- timing
def time_analyze(methods: Sequence[str] = METHODS, samples: int = 3000, repeats: int = 5, seed: int = 0,
                 include_repair: bool = True) -> dict:
    """Median wall time (s) of ``analyze`` on ``samples`` samples of a 5x5 scenario, per method.

    The scenario is the first of family ``seed`` drawn as 5x5 with two mismatched elements and
    dither (so the element test has rows to work on).  With ``include_repair`` the default
    ``repair=True`` of ``arx`` is timed too (once: it can be slow).
    """
    analysis = _analysis()
    if analysis is None:
        return {"error": "mpm_monitor.core.analysis is not available"}
    opts = ScenarioOptions(min_size=5, max_size=5, dither_fraction=1.0)
    sc = make_scenario(seed, 0, opts, n_mismatches=2)
    data = simulate(sc, samples)
    out = {"samples": samples, "shape": [5, 5], "repeats": repeats}
    for m in methods:
        analysis.analyze(sc.model, data, AnalysisOptions(method=m, repair=False))  # warm-up
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            analysis.analyze(sc.model, data, AnalysisOptions(method=m, repair=False))
            ts.append(time.perf_counter() - t0)
        out[m] = statistics.median(ts)
    if include_repair and "arx" in methods:
        t0 = time.perf_counter()
        analysis.analyze(sc.model, data, AnalysisOptions(method="arx", repair=True))
        out["arx_with_repair"] = time.perf_counter() - t0
    return out


# --------------------------------------------------------------------------- driver
def run_monte_carlo(n_runs: int, seed: int = 0, samples: int = 3000, methods: Sequence[str] = METHODS, *,
                    jobs: int = 1, scenario_options: ScenarioOptions = ScenarioOptions(), alpha: float = ALPHA,
                    timing: bool = False, progress: Optional[Callable[[int, int, dict], None]] = None,
                    bounds: Optional[float] = None) -> dict:
    """Run the benchmark and score it.

    Parameters
    ----------
    n_runs : int
        Number of random scenarios (indices ``0 .. n_runs - 1`` of family ``seed``).
    seed : int
        Family seed.
    samples : int
        Samples per closed-loop run.
    methods : sequence of str
        Subset of ``("arx", "xcorr", "pcorr")``.
    jobs : int
        Worker processes (1 = in this process).
    scenario_options : ScenarioOptions
        The scenario distribution.
    alpha : float
        Family-wise false-alarm level given to every method.
    timing : bool
        Also time ``analyze`` on 3,000 samples of 5x5 (:func:`time_analyze`).
    progress : callable, optional
        Called as ``progress(done, total, record)`` after each run.
    bounds : float, optional
        Run every loop with its MPC's inputs and moves bounded at this quantile (:func:`run_one`).

    Returns
    -------
    dict
        ``config``, ``summary`` (method -> :func:`score`), ``timing`` and ``runs`` (every record); with
        ``bounds`` also ``unbounded`` (the ``arx`` score of the same loops without bounds, the runs
        whose located elements are the same with and without bounds, and the bounds' activity).
    """
    methods = tuple(methods)
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ValueError(f"methods: expected a subset of {', '.join(METHODS)}, got {', '.join(bad)}")
    if int(n_runs) != n_runs or n_runs < 1:
        raise ValueError(f"n_runs: expected an integer >= 1, got {n_runs!r}")
    if bounds is not None and not 0.0 < bounds < 1.0:
        raise ValueError(f"bounds: expected a quantile in (0, 1), got {bounds!r}")
    tasks = [(seed, k, samples, methods, scenario_options, alpha, bounds) for k in range(int(n_runs))]
    t0 = time.perf_counter()
    records = map_runs(_run_one_star, tasks, jobs, progress)
    records.sort(key=lambda r: r["index"])
    wall = time.perf_counter() - t0
    result = {
        "config": {"runs": int(n_runs), "seed": int(seed), "samples": int(samples), "methods": list(methods),
                   "alpha": alpha, "jobs": int(jobs), "scenario_options": _plain(scenario_options),
                   "separability_collinear": SEPARABILITY_COLLINEAR, "wall_time_s": wall,
                   "machine": {"python": platform.python_version(), "platform": platform.platform(),
                               "processor": platform.processor() or platform.machine(),
                               "cpu_count": os.cpu_count()}},
        "summary": {m: score(records, m) for m in methods},
        "timing": time_analyze(methods, samples=3000, seed=seed) if timing else None,
        "runs": records,
    }
    if bounds is not None:
        result["config"]["bounds_quantile"] = float(bounds)
        if "arx" in methods:
            result["unbounded"] = compare_unbounded(records)
    return result


def compare_unbounded(records: Sequence[dict]) -> dict:
    """``arx`` on the loops with bounds against the same loops without (:func:`run_one` with ``bounds``).

    Returns
    -------
    dict
        ``score``: :func:`score` of the logs without bounds; ``same_located``: runs whose located elements
        are the same in both; ``runs``: runs compared; ``differ``: the indices of the others;
        ``active``: medians and ranges over the runs of the bounds' activity (:func:`bound_activity`).
    """
    # Each run's ambiguity judged on its own inputs: the free run's separability for the free run's results.
    free = [dict(rec, results=rec["results_unbounded"], separability=rec["bounds"]["free_separability"],
                 collinear_inputs=rec["bounds"]["free_collinear_inputs"]) for rec in records]
    pairs = [(rec["index"], rec["results"]["arx"], rec["results_unbounded"]["arx"]) for rec in records]
    ok = [(k, a, b) for k, a, b in pairs if "error" not in a and "error" not in b]
    differ = [k for k, a, b in ok if sorted(map(tuple, a["located"])) != sorted(map(tuple, b["located"]))]
    active = {}
    for key in ("u", "du", "any"):
        vals = [rec["bounds"]["active"][key] for rec in records]
        active[key] = {"median": float(statistics.median(vals)), "min": float(min(vals)), "max": float(max(vals))}
    return {"score": score(free, "arx"), "runs": len(ok), "same_located": len(ok) - len(differ), "differ": differ,
            "active": active}


def _plain(opts) -> dict:
    import dataclasses

    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(opts).items()}


def _fmt(x, pct=False) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.1f}%" if pct else f"{x:.3f}"


def format_table(result: dict) -> str:
    """The summary as a plain-text table (what ``main`` prints)."""
    cfg = result["config"]
    methods = cfg["methods"]
    lines = [f"Monte-Carlo: {cfg['runs']} runs, seed {cfg['seed']}, {cfg['samples']} samples, alpha {cfg['alpha']}, "
             f"wall {cfg['wall_time_s']:.0f} s"]
    head = f"{'':34}" + "".join(f"{m:>15}" for m in methods)
    lines.append(head)

    def line(label, get):
        lines.append(f"{label:34}" + "".join(f"{get(result['summary'][m]):>15}" for m in methods))

    line("element precision", lambda s: _fmt(s["element"]["precision"]))
    line("element recall (excl. ambiguous)", lambda s: _fmt(s["element"]["recall"]))
    line("element recall (ambiguous=miss)", lambda s: _fmt(s["element"]["recall_all"]))
    line("elements TP / FP / FN", lambda s: f"{s['element']['tp']}/{s['element']['fp']}/{s['element']['fn']}")
    line("ambiguous: mismatched / clean", lambda s: f"{s['element']['amb_true']}/{s['element']['amb_clean']}")
    line("ambiguous: justified / not", lambda s: f"{s['element']['amb_justified']}/{s['element']['amb_unjustified']}")
    line("row precision", lambda s: _fmt(s["row"]["precision"]))
    line("row recall", lambda s: _fmt(s["row"]["recall"]))
    line("false alarms (clean runs, elem.)", lambda s: f"{s['false_alarms']['runs_with_located_element']}/"
                                                      f"{s['false_alarms']['clean_runs']}")
    line("false-alarm rate (element)", lambda s: _fmt(s["false_alarms"]["rate_element"], pct=True))
    line("false-alarm rate (row)", lambda s: _fmt(s["false_alarms"]["rate_row"], pct=True))
    line("median time per run (s)", lambda s: _fmt(s["median_time_s"]))
    line("errors", lambda s: str(len(s["errors"])))
    lines.append("recall by kind / size / shape / dither (hits/(hits+misses); ambiguous excluded):")
    cats = []
    for cat, keys in (("kind", KINDS), ("size", [f"{lo:.1f}-{min(hi, 1.0):.1f}" for lo, hi in SIZE_BINS]),
                      ("shape", ("square", "tall", "fat")), ("dither", ("dither", "none"))):
        for key in keys:
            cats.append((cat, key))
    for cat, key in cats:
        def get(s, cat=cat, key=key):
            cell = s["recall_by"][cat].get(key)
            if not cell:
                return "-"
            return f"{_fmt(cell['recall'])} ({cell['hit']}/{cell['hit'] + cell['miss']})"
        line(f"  {cat} {key}", get)
    free = result.get("unbounded")
    if free is not None:
        sc, act = free["score"], free["active"]
        lines.append(f"bounds at the {result['config']['bounds_quantile']:g} quantile: an input at a bound in a median "
                     f"{100 * act['u']['median']:.0f} % of (sample, input) pairs ({100 * act['u']['min']:.0f}-"
                     f"{100 * act['u']['max']:.0f} %), a move at its bound in {100 * act['du']['median']:.0f} %, some "
                     f"bound active in {100 * act['any']['median']:.0f} % of samples")
        lines.append(f"arx without bounds on the same loops: precision {_fmt(sc['element']['precision'])}, recall "
                     f"{_fmt(sc['element']['recall'])}, false alarms {sc['false_alarms']['runs_with_located_element']}/"
                     f"{sc['false_alarms']['clean_runs']}; the same located elements with and without bounds in "
                     f"{free['same_located']} of {free['runs']} runs")
    timing = result.get("timing")
    if timing and "error" not in timing:
        lines.append(f"analyze on {timing['samples']} samples of 5x5, median of {timing['repeats']} (s): "
                     + ", ".join(f"{m} {timing[m]:.3f}" for m in methods if m in timing)
                     + (f"; arx with repair {timing['arx_with_repair']:.2f}" if "arx_with_repair" in timing else ""))
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.monte_carlo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=200, help="number of random closed-loop runs (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="family seed of the scenarios (default 0)")
    parser.add_argument("--samples", type=int, default=3000, help="samples per run (default 3000)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of arx,xcorr,pcorr")
    parser.add_argument("--alpha", type=float, default=ALPHA, help="family-wise false-alarm level (default 0.01)")
    parser.add_argument("--dither-fat", action="store_true",
                        help="always dither plants with more inputs than outputs (identifiable design)")
    parser.add_argument("--still", action="store_true",
                        help="still loops: every setpoint held at 0, no dither (the inputs move only with the "
                             "controller's feedback of the noise)")
    parser.add_argument("--setpoint-steps", action="store_true",
                        help="setpoints moved in steps (held at least 60 samples, then 1 %% a sample) instead of "
                             "the paper's PRBS")
    parser.add_argument("--bounds", type=float, default=None, metavar="QUANTILE",
                        help="bound every MPC's inputs and moves at this quantile of their run without bounds "
                             "(e.g. 0.8) and analyse the bounded loop; the arx result without bounds is kept beside")
    parser.add_argument("--no-timing", action="store_true", help="skip the analyze timing on 5x5")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output (default bench/results/monte_carlo.json)")
    parser.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    args = parser.parse_args(argv)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if args.runs < 1 or args.samples < 100 or args.jobs < 1:
        parser.error("--runs and --jobs must be >= 1 and --samples >= 100")
    if args.still and args.setpoint_steps:
        parser.error("--still and --setpoint-steps exclude each other (still loops hold every setpoint)")

    def progress(done, total, rec):
        if args.quiet:
            return
        parts = []
        truth = {(m["output"], m["input"]) for m in rec["mismatches"]}
        for m, res in rec["results"].items():
            if "error" in res:
                parts.append(f"{m}: ERROR")
                continue
            loc = {tuple(x) for x in res["located"]}
            parts.append(f"{m}: +{len(loc & truth)} fp{len(loc - truth)} miss{len(truth - loc)}"
                         + (f" amb{len(res['ambiguous'])}" if res["ambiguous"] else ""))
        print(f"[{done}/{total}] run {rec['index']} {rec['shape'][0]}x{rec['shape'][1]} "
              f"{len(truth)} mism{' dither' if rec['dither'] else ''} | " + " | ".join(parts), flush=True)

    try:
        result = run_monte_carlo(args.runs, args.seed, args.samples, methods, jobs=args.jobs, alpha=args.alpha,
                                 timing=not args.no_timing, progress=progress, bounds=args.bounds,
                                 scenario_options=dataclasses.replace(
                                     STILL if args.still else SETPOINT_STEPS if args.setpoint_steps
                                     else ScenarioOptions(), dither_fat=args.dither_fat))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table(result))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=_json_default) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


def _json_default(x):
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


if __name__ == "__main__":
    sys.exit(main())
