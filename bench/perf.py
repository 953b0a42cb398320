"""Compute benchmark of the detection (issue 8): time per analysis, per sample, and the simulator.

Run from the repository root::

    .venv/bin/python -m bench.perf [--quick] [--threads 1] [--out bench/results/perf.json]

Prints one table and writes every number to the JSON file.  All times are wall-clock medians over
repeats (``time.perf_counter``); each cell is repeated up to ``--repeats`` times within a time
budget, and the count is recorded.  Ratios are taken between numbers measured in the same run.

What is measured, for random n x n plants (gains log-uniform in [0.5, 5] with random sign, time
constants 10..80 s, delays 0..8 samples, sample time 1 s: :func:`bench.plants.random_plant`) under the paper's MPC and PRBS setpoints,
with the controller model's (y1, u2) gain 30 % off, over windows of W samples:

``batch``
    The batch analysis as the CLI and the live monitor run it on a window:
    :func:`mpm_monitor.core.pipeline.analyze` from the :class:`~mpm_monitor.core.logged_data.LoggedData` alone,
    i.e. including :func:`mpm_monitor.core.signals.compute_signals` (element-wise model run,
    ``initial_state="estimate"``) and the tests solved from the window's Gram matrices with the QR
    fallback (:func:`mpm_monitor.core.regressions.window_regressions`); every row's element test
    (``test_all_rows=True``), no repair.  The regressions it refitted by QR are listed per cell.
``qr``
    The reference it replaced: the same tests with every regression factored by QR
    (:class:`mpm_monitor.core.regressions.QrRegressions`), the signals ``d, eps`` given.
``dense``
    The signals as they were computed before: the dense state-space simulation
    (:func:`mpm_monitor.core.discretize.simulate_state_space`, ``scipy.signal.dlsim``) and the same
    initial-transient estimate.  ``before = qr + dense`` is the previous batch analysis, measured in
    its two parts in the same run.
``scratch``
    :class:`mpm_monitor.core.sliding.SlidingWindowAnalyzer` built from nothing on the W samples:
    model run, Gram matrices from scratch, solve -- the sufficient-statistics path's full analysis.
``periodic``
    The periodic analysis of a live monitor: 100 new samples pushed into a full window, then
    ``analyze()`` (folding in the pending samples and solving; ``--quick``: 50).
``per_sample``
    ``push()`` of one sample into a full window: model step, buffer, and the Gram updates, with the
    default ``update_block`` (16) and strictly per sample (``update_block=1``); averaged over W pushes
    (one turnover of the window, so including its one scheduled rebuild of the Gram matrices).
``xcorr``
    The cross-correlation baseline :func:`mpm_monitor.core.baselines.cross_correlation_test` on ``d, u``
    of the window (skipped with a note when the module is absent).
``floor``
    One dense least-squares solve (``numpy.linalg.lstsq``) of the largest regression of the analysis
    (the setpoint or input lag block plus ``na`` own columns, over the window's regression rows).

and the batch closed-loop simulation speed (:func:`mpm_monitor.sim.closed_loop.run_closed_loop`, model =
plant, no mismatch) for 3x3, 5x5, 10x10 and 20x20, steady samples per second (set-up of the MPC
timed apart), plus the memory of the sliding window (:mod:`bench.memory`).

Industrial size (``industrial``): a square 20x20 and 50x50 and a tall 100x40 plant
(:func:`bench.plants.random_plant`), the controller model with three elements off (a gain 30 %,
a delay 3 samples, a time constant 60 %), 10,000 samples of the closed loop.  Per size: the set-up
and the step of the MPC and the plant and their memory, the closed loop's speed, the detection
(:func:`mpm_monitor.core.analysis.detect`, no repair) and the whole analysis with the repair
(:func:`mpm_monitor.core.pipeline.analyze`) with their time and peak memory (tracemalloc: numpy
reports its buffers to it), what was located and repaired, and the live monitor's part: one
sample into its window (:class:`mpm_monitor.monitor.monitor_core.MonitorCore`) and one analysis of
its default window (3,000 samples, with the repair).

The command as a user runs it (``command_line``): ``python -m mpm_monitor analyze --model M --data
CSV`` on a 20x20 and a 100x40 log of 10,000 samples with one element off (a gain 30 %), which
it locates and repairs, against the floor (a fresh interpreter that imports numpy and scipy.linalg
and reads the same CSV with ``numpy.loadtxt``), run in turn, three times each after a warm-up; and
``python -m mpm_monitor analyze --help`` against a bare ``python -c "import numpy"``, five times
each.  Medians of the wall time and of the ratio pair by pair, and the largest resident memory of
each process (``/usr/bin/time``).

BLAS threads: ``--threads`` (default 1) sets ``OPENBLAS_NUM_THREADS`` / ``OMP_NUM_THREADS`` /
``MKL_NUM_THREADS`` before numpy is imported, unless they are already set; a multi-threaded BLAS on
2 shared cores slowed small factorisations 100-fold under load in our measurements.
"""

from __future__ import annotations

import os
import sys


def _threads_from_argv(argv):
    for k, a in enumerate(argv):
        if a == "--threads" and k + 1 < len(argv):
            return argv[k + 1]
        if a.startswith("--threads="):
            return a.split("=", 1)[1]
    return None


if __name__ == "__main__":     # before numpy is imported anywhere (the bench package asked for 1 thread)
    _threads = _threads_from_argv(sys.argv[1:])
    if _threads is not None:
        for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[_var] = _threads

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Optional  # noqa: E402

import numpy as np  # noqa: E402

from mpm_monitor.core.analysis import AnalysisOptions  # noqa: E402
from mpm_monitor.core.arx import lag_matrix  # noqa: E402
from mpm_monitor.core.discretize import simulate_state_space, state_space  # noqa: E402
from mpm_monitor.core.pipeline import analyze  # noqa: E402
from mpm_monitor.core.regressions import QrRegressions, regression_layout, window_regressions  # noqa: E402
from mpm_monitor.core.signals import LoopSignals, compute_signals, initial_transient  # noqa: E402
from mpm_monitor.core.sliding import SlidingWindowAnalyzer  # noqa: E402
from mpm_monitor.sim.closed_loop import run_closed_loop  # noqa: E402

from .plants import random_plant  # noqa: E402

#: Targets of issue 8 (this machine, 2 cores).
TARGET_FULL_20X20_10K_S = 0.5
TARGET_UPDATE_10X10_S = 1e-3
TARGET_SIM_5X5_PER_S = 20_000
#: Targets of the industrial-size issue: the command against its floor, --help against import numpy,
#: the 100x40 command's time and memory.
TARGET_COMMAND_OVER_FLOOR = 2.0
TARGET_HELP_OVER_NUMPY = 2.0
TARGET_100X40_S = 3.0
TARGET_100X40_MIB = 1024.0

OPTIONS = AnalysisOptions(repair=False, test_all_rows=True)


@dataclasses.dataclass(frozen=True)
class Grid:
    """Plant sizes and windows of a run, and its time budget per cell."""

    sizes: tuple = (2, 5, 10, 20)
    windows: tuple = (1000, 2000, 5000, 10000, 20000)
    repeats: int = 5
    budget_s: float = 3.0
    periodic_step: int = 100
    sim_sizes: tuple = (3, 5, 10, 20)
    sim_samples: int = 3000


QUICK = Grid(sizes=(2, 5, 10), windows=(1000, 2000), repeats=3, budget_s=1.0, periodic_step=50,
             sim_sizes=(3, 5, 10), sim_samples=1000)


# ----------------------------------------------------------------------------------------- set-up
def machine_info() -> dict:
    """CPU model, cores, load, library versions, BLAS threads."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import scipy
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        blas = f"{blas.get('name')} {blas.get('version')}"
    except Exception:                                  # noqa: BLE001 - informative only
        blas = "unknown"
    return {"cpu": cpu, "logical_cores": os.cpu_count(),
            "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "load_average_start": list(os.getloadavg()), "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "blas": blas,
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "platform": platform.platform(),
            "stale_bytecode_modules": stale_bytecode()}


def stale_bytecode(package: Optional[Path] = None) -> int:
    """How many of the package's modules have no current compiled bytecode (``make`` compiles it).

    Each such module is compiled on every start of the command (about 4 ms each here).  ``package``: the
    folder of another copy of the package (default: the one imported here).
    """
    import importlib.util

    if package is None:
        import mpm_monitor

        package = Path(mpm_monitor.__file__).parent
    stale = 0
    for src in Path(package).rglob("*.py"):
        pyc = Path(importlib.util.cache_from_source(str(src)))
        if not pyc.exists() or pyc.stat().st_mtime < src.stat().st_mtime:
            stale += 1
    return stale


def timed(fn, repeats: int, budget_s: float) -> tuple:
    """Median wall time of ``fn()`` over 1..repeats calls (stops when the budget is spent); (median, n)."""
    times = []
    start = time.perf_counter()
    while len(times) < repeats:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if time.perf_counter() - start > budget_s:
            break
    return statistics.median(times), len(times)


def _largest_regression(model, data, sig, options) -> np.ndarray:
    """The larger of ``[setpoint lags | own]`` and ``[input lags | own]`` of the first row, centred."""
    lay = regression_layout(model, options)
    na, start = options.na, lay.start
    d = sig.d[:, 0] - sig.d[:, 0].mean()
    own = lag_matrix(d, range(1, na + 1), start)
    r_c = data.r - data.r.mean(axis=0)
    u_c = data.u - data.u.mean(axis=0)
    xr = lag_matrix(r_c, range(0, lay.n_lag_r), start)
    xu = lag_matrix(u_c, range(1, lay.n_lag_u + 1), start)
    x = xr if xr.shape[1] >= xu.shape[1] else xu
    return np.hstack([x, own]), d[start:]


def _dense_signals(model, r, u, y) -> LoopSignals:
    """``compute_signals(..., "estimate")`` as it was: dense state-space simulation, then the transient."""
    yhat = simulate_state_space(state_space(model), u)
    transient = initial_transient(model, y - yhat)
    yhat = yhat + transient
    d = y - yhat
    return LoopSignals(yhat=yhat, d=d, eps=r - d, transient=transient)


def _qr_regressions(model, data, sig, options) -> QrRegressions:
    return QrRegressions(data.r, data.u, sig.eps - data.r, sig.d, regression_layout(model, options),
                         options.na, options.nb)


def _xcorr():
    try:
        from mpm_monitor.core.baselines import cross_correlation_test
    except ImportError as exc:
        return None, f"mpm_monitor.core.baselines.cross_correlation_test not available ({exc})"
    return cross_correlation_test, ""


# ----------------------------------------------------------------------------------------- analysis
def bench_analysis(grid: Grid, seed: int = 0, log=print) -> list:
    """Every (size, window) cell of the grid; a list of dicts."""
    xcorr, xcorr_note = _xcorr()
    cells = []
    for n in grid.sizes:
        rng = np.random.default_rng(seed + n)
        plant = random_plant(n, n, rng)
        model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.3)
        lay = regression_layout(model, OPTIONS)
        total = max(grid.windows) + grid.periodic_step * (grid.repeats + 1) + 10
        t0 = time.perf_counter()
        cl = run_closed_loop(plant, model, total, seed=seed + 100 + n)
        log(f"  {n}x{n}: closed loop of {total} samples in {time.perf_counter() - t0:.1f} s")
        sig_all = compute_signals(model, cl.r, cl.u, cl.y, "zero")
        for w in grid.windows:
            cell = {"size": f"{n}x{n}", "n": n, "window": w, "min_samples": lay.min_samples}
            if w < lay.min_samples:
                cell["skipped"] = f"the tests need at least {lay.min_samples} samples"
                cells.append(cell)
                log(f"  {n}x{n} W={w}: skipped ({cell['skipped']})")
                continue
            a, b = 0, w
            data = cl.as_logged_data().slice(a, b)
            sig = LoopSignals(sig_all.yhat[a:b], sig_all.d[a:b], sig_all.eps[a:b], sig_all.transient[a:b])
            X, y = _largest_regression(model, data, sig, OPTIONS)
            cell["largest_regression"] = list(X.shape)
            reps, budget = grid.repeats, grid.budget_s
            cell["batch_s"], cell["batch_n"] = timed(lambda: analyze(model, data, OPTIONS), reps, budget)
            cell["signals_s"], cell["signals_n"] = timed(
                lambda: compute_signals(model, data.r, data.u, data.y, OPTIONS.initial_state), reps, budget)
            batch_sig = compute_signals(model, data.r, data.u, data.y, OPTIONS.initial_state)
            regs = window_regressions(data.r, data.u, batch_sig.eps - data.r, batch_sig.d, lay, OPTIONS.na,
                                      OPTIONS.nb)
            analyze(model, data, OPTIONS, signals=batch_sig, regressions=regs)
            cell["batch_fallbacks"] = list(regs.fallbacks)
            def qr_analysis():
                qr_regs = _qr_regressions(model, data, sig, OPTIONS)
                return analyze(model, data, OPTIONS, signals=sig, regressions=qr_regs)
            cell["qr_s"], cell["qr_n"] = timed(qr_analysis, reps, budget)
            cell["dense_s"], cell["dense_n"] = timed(lambda: _dense_signals(model, data.r, data.u, data.y), reps,
                                                     budget)
            cell["before_s"] = cell["qr_s"] + cell["dense_s"]

            def scratch():
                an = SlidingWindowAnalyzer(model, OPTIONS, w)
                an.push_many(cl.r[a:b], cl.u[a:b], cl.y[a:b])
                return an.analyze()
            cell["scratch_s"], cell["scratch_n"] = timed(scratch, reps, budget)
            cell["floor_s"], cell["floor_n"] = timed(lambda: np.linalg.lstsq(X, y, rcond=None), reps, budget)
            if xcorr is not None:
                cell["xcorr_s"], cell["xcorr_n"] = timed(lambda: xcorr(sig.d, data.u, alpha=OPTIONS.alpha),
                                                         reps, budget)
            # Live monitor: a full window, then periodic analyses and per-sample pushes.
            an = SlidingWindowAnalyzer(model, OPTIONS, w)
            an.push_many(cl.r[:b], cl.u[:b], cl.y[:b])
            an.analyze()
            k = b
            periodic = []
            for _ in range(grid.repeats):
                an.push_many(cl.r[k:k + grid.periodic_step], cl.u[k:k + grid.periodic_step],
                             cl.y[k:k + grid.periodic_step])
                k += grid.periodic_step
                t0 = time.perf_counter()
                an.analyze()
                periodic.append(time.perf_counter() - t0)
            cell["periodic_s"], cell["periodic_n"] = statistics.median(periodic), len(periodic)
            cell["fallbacks"] = list(an.last_fallbacks)
            for block, key in ((16, "per_sample_s"), (1, "per_sample_block1_s")):
                live = SlidingWindowAnalyzer(model, OPTIONS, w, update_block=block)
                live.push_many(cl.r[:k], cl.u[:k], cl.y[:k])
                live.flush()
                rows = [(cl.r[j % total], cl.u[j % total], cl.y[j % total]) for j in range(k, k + w)]
                t0 = time.perf_counter()
                for r_k, u_k, y_k in rows:      # the log is reused cyclically: the cost does not depend on it
                    live.push(r_k, u_k, y_k)
                live.flush()                    # the last partial block is part of the cost
                cell[key] = (time.perf_counter() - t0) / w
                cell[key.replace("_s", "_rebuilds")] = live.rebuilds
            cell["ratio_before_to_batch"] = cell["before_s"] / cell["batch_s"]
            cell["ratio_qr_to_batch"] = cell["qr_s"] / cell["batch_s"]
            cell["ratio_batch_to_periodic"] = cell["batch_s"] / cell["periodic_s"]
            cell["ratio_batch_to_scratch"] = cell["batch_s"] / cell["scratch_s"]
            cell["ratio_batch_to_floor"] = cell["batch_s"] / cell["floor_s"]
            cell["ratio_scratch_to_floor"] = cell["scratch_s"] / cell["floor_s"]
            cell["ratio_periodic_to_floor"] = cell["periodic_s"] / cell["floor_s"]
            if "xcorr_s" in cell:
                cell["ratio_batch_to_xcorr"] = cell["batch_s"] / cell["xcorr_s"]
                cell["ratio_periodic_to_xcorr"] = cell["periodic_s"] / cell["xcorr_s"]
            cells.append(cell)
            log(f"  {n}x{n} W={w}: batch {cell['batch_s']:.3f} s (before {cell['before_s']:.3f} s), "
                f"scratch {cell['scratch_s']:.3f} s, periodic {cell['periodic_s']:.4f} s, "
                f"push {cell['per_sample_s'] * 1e6:.0f} us")
    if xcorr is None:
        cells.append({"note": xcorr_note})
    return cells


# ----------------------------------------------------------------------------------------- simulation
def bench_simulation(grid: Grid, seed: int = 0, log=print) -> list:
    """Closed-loop simulation speed, model = plant."""
    out = []
    for n in grid.sim_sizes:
        plant = random_plant(n, n, np.random.default_rng(seed + 1000 + n))
        setup, _ = timed(lambda: run_closed_loop(plant, plant, 1, seed=1), 3, 2.0)
        total, reps = timed(lambda: run_closed_loop(plant, plant, grid.sim_samples, seed=1), 3, 10.0)
        steady = max(total - setup, 1e-9)
        row = {"size": f"{n}x{n}", "n": n, "samples": grid.sim_samples, "total_s": total, "setup_s": setup,
               "repeats": reps, "samples_per_s": grid.sim_samples / steady,
               "samples_per_s_with_setup": grid.sim_samples / total}
        out.append(row)
        log(f"  closed loop {n}x{n}: {row['samples_per_s']:.0f} samples/s (set-up {setup:.3f} s)")
    return out


# ----------------------------------------------------------------------------------------- report
def targets(cells, sims, command_line=None, industrial=None) -> list:
    """The issues' targets, each with the measured value and met / not met / not measured."""
    def cell(n, w):
        return next((c for c in cells if c.get("n") == n and c.get("window") == w and "batch_s" in c), None)
    out = []
    c = cell(20, 10000)
    out.append({"target": "full analysis 20x20, W=10,000 < 0.5 s",
                "measured": None if c is None else {"batch_s": c["batch_s"], "before_s": c["before_s"],
                                                    "scratch_s": c["scratch_s"], "periodic_s": c["periodic_s"]},
                "met": None if c is None else c["batch_s"] < TARGET_FULL_20X20_10K_S,
                "note": "batch_s: analyze() from the LoggedData, compute_signals included (what the CLI and the "
                        "monitor run); before_s: the dense simulation plus the QR path it replaced"})
    c10 = [c for c in cells if c.get("n") == 10 and "per_sample_block1_s" in c]
    worst = max((c["per_sample_block1_s"] for c in c10), default=None)
    out.append({"target": "incremental update per sample, 10x10 < 1 ms",
                "measured": None if worst is None else {"worst_per_sample_block1_s": worst,
                                                        "per_sample_default_s": max(c["per_sample_s"] for c in c10)},
                "met": None if worst is None else worst < TARGET_UPDATE_10X10_S,
                "note": "update_block=1 (one Gram update per sample), worst over the windows measured"})
    s5 = next((s for s in sims if s["n"] == 5), None)
    out.append({"target": "batch closed-loop simulation 5x5 >= 20,000 samples/s",
                "measured": None if s5 is None else {"samples_per_s": s5["samples_per_s"]},
                "met": None if s5 is None else s5["samples_per_s"] >= TARGET_SIM_5X5_PER_S,
                "note": "steady rate, MPC set-up excluded"})
    if command_line is not None:
        c = command_line.get("20x20")
        out.append({"target": "analyze end to end (20x20 x 10,000, with the repair) <= 2 x the floor",
                    "measured": None if c is None else {"analyze_s": c["a_wall_s"], "floor_s": c["b_wall_s"],
                                                        "ratio": c["ratio_median"]},
                    "met": None if c is None else c["ratio_median"] <= TARGET_COMMAND_OVER_FLOOR,
                    "note": "floor: a fresh interpreter importing numpy and scipy.linalg and reading the CSV with "
                            "numpy.loadtxt; medians of 3 in turn"})
        h = command_line["help"]
        out.append({"target": "analyze --help <= 2 x python -c 'import numpy'",
                    "measured": {"help_s": h["a_wall_s"], "import_numpy_s": h["b_wall_s"], "ratio": h["ratio_median"]},
                    "met": h["ratio_median"] <= TARGET_HELP_OVER_NUMPY, "note": "medians of 5 in turn"})
        c = command_line.get("100x40")
        out.append({"target": "analyze 100x40 x 10,000 (with the repair) <= 3 s and <= 1 GB",
                    "measured": None if c is None else {"analyze_s": c["a_wall_s"], "max_rss_mib": c["a_max_rss_mib"]},
                    "met": None if c is None else (c["a_wall_s"] <= TARGET_100X40_S
                                                   and c["a_max_rss_mib"] <= TARGET_100X40_MIB),
                    "note": "whole process, median of 3; memory: largest resident set"})
    return out


def format_table(result: dict) -> str:
    """The run as plain-text tables."""
    m = result["machine"]
    lines = [f"machine: {m['cpu']}, {m['usable_cores']} usable cores ({m['logical_cores']} logical), "
             f"load {m['load_average_start'][0]:.2f} at start / {m.get('load_average_end', [float('nan')])[0]:.2f} at "
             f"end, Python {m['python']}, numpy {m['numpy']}, {m['blas']}, BLAS threads {m['blas_threads']}",
             "", "analysis per window (medians; times in seconds unless noted)", ""]
    head = (f"{'plant':>6} {'W':>6} {'X (rows x cols)':>16} {'batch':>8} {'before':>8} {'speedup':>8} "
            f"{'signals':>8} {'qr':>8} {'scratch':>8} {'periodic':>9} {'push us':>8} {'push1 us':>8} "
            f"{'xcorr':>8} {'floor':>8} {'bat/floor':>9} {'per/floor':>9} {'per/xcorr':>9}")
    lines += [head, "-" * len(head)]

    def f(x, fmt="{:8.3f}"):
        return fmt.format(x) if x is not None else f"{'-':>8}"
    fallbacks = []
    for c in result["analysis"]:
        if "note" in c:
            lines.append(f"note: {c['note']}")
            continue
        if "skipped" in c:
            lines.append(f"{c['size']:>6} {c['window']:>6} skipped: {c['skipped']}")
            continue
        if c.get("batch_fallbacks"):
            fallbacks.append(f"{c['size']} W={c['window']}: {', '.join(c['batch_fallbacks'])}")
        shape = "x".join(str(v) for v in c["largest_regression"])
        lines.append(
            f"{c['size']:>6} {c['window']:>6} {shape:>16} {f(c['batch_s'])} {f(c['before_s'])} "
            f"{f(c['ratio_before_to_batch'], '{:8.1f}')} {f(c['signals_s'])} {f(c['qr_s'])} "
            f"{f(c['scratch_s'])} {f(c['periodic_s'], '{:9.4f}')} {f(c['per_sample_s'] * 1e6, '{:8.0f}')} "
            f"{f(c['per_sample_block1_s'] * 1e6, '{:8.0f}')} {f(c.get('xcorr_s'))} {f(c['floor_s'], '{:8.4f}')} "
            f"{f(c['ratio_batch_to_floor'], '{:9.1f}')} {f(c['ratio_periodic_to_floor'], '{:9.1f}')} "
            f"{f(c.get('ratio_periodic_to_xcorr'), '{:9.2f}')}")
    lines += ["", "columns: batch = analyze() from the LoggedData (compute_signals(\"estimate\") + tests from the "
              "window's Gram matrices, QR fallback); before = the previous batch path (dense dlsim signals + QR "
              "regressions), measured as dense + qr; speedup = before / batch; signals = compute_signals alone; "
              "qr = the tests with QR regressions, signals given; scratch = SlidingWindowAnalyzer from nothing "
              "(model run + Gram + solve); periodic = analyze() of a live window after new samples; push = push() "
              "per sample (update_block 16), push1 = update_block 1; floor = one numpy lstsq of the largest "
              "regression X",
              "batch regressions refitted by QR: " + ("; ".join(fallbacks) if fallbacks else "none"), ""]
    lines.append("closed-loop batch simulation (model = plant, unconstrained MPC Hp 100 Hc 30)")
    for s in result["simulation"]:
        lines.append(f"  {s['size']:>6}: {s['samples_per_s']:10.0f} samples/s steady "
                     f"({s['samples_per_s_with_setup']:.0f} incl. {s['setup_s']:.3f} s MPC set-up)")
    if result.get("memory"):
        mem = result["memory"]
        lines += ["", f"memory of the sliding window: {mem['summary']}"]
    lines += ["", "targets:"]
    for t in result["targets"]:
        state = {True: "MET", False: "NOT MET", None: "not measured"}[t["met"]]
        lines.append(f"  {t['target']}: {state}  {json.dumps(t['measured'])}  ({t['note']})")
    if result.get("command_line"):
        cl = result["command_line"]
        lines += ["", "the command as a user runs it (wall-clock medians, largest resident memory)"]
        h = cl["help"]
        lines.append(f"  analyze --help {h['a_wall_s']:.3f} s vs python -c 'import numpy' {h['b_wall_s']:.3f} s: "
                     f"x{h['ratio_median']:.2f}")
        for key, c in cl.items():
            if key == "help":
                continue
            lines.append(f"  analyze {key} x 10,000, one element off and repaired ({c['csv_bytes'] / 1e6:.1f} MB CSV): "
                         f"{c['a_wall_s']:.2f} s, "
                         f"{c['a_max_rss_mib']:.0f} MiB; floor {c['b_wall_s']:.2f} s ({c['b_max_rss_mib']:.0f} MiB): "
                         f"x{c['ratio_median']:.2f}"
                         + (f"; --jobs 1 {c['c_wall_s']:.2f} s, {c['c_max_rss_mib']:.0f} MiB: x{c['c_ratio_median']:.2f}"
                            if "c_wall_s" in c else ""))
    if result.get("industrial"):
        lines += ["", "industrial size (10,000 samples; times in seconds, memory: tracemalloc peak in MiB)", ""]
        head = (f"{'plant':>7} {'states':>6} {'MPC set-up':>10} {'MiB':>5} {'step ms':>8} {'loop':>6} {'detect':>7} "
                f"{'MiB':>5} {'analyze':>8} {'MiB':>5} {'mon. us':>8} {'mon. ana':>8} {'MiB':>5}  located / repaired")
        lines += [head, "-" * len(head)]
        for r in result["industrial"]:
            mib = 2.0 ** 20
            lines.append(f"{r['size']:>7} {r['n_states']:>6} {r['mpc_setup_s']:>10.2f} {r['mpc_setup_peak_bytes'] / mib:>5.0f} "
                         f"{r['loop_step_s'] * 1e3:>8.2f} {r['closed_loop_s']:>6.1f} {r['detect_s']:>7.2f} "
                         f"{r['detect_peak_bytes'] / mib:>5.0f} {r['analyze_s']:>8.2f} {r['analyze_peak_bytes'] / mib:>5.0f} "
                         f"{r['monitor_sample_s'] * 1e6:>8.0f} {r['monitor_analysis_s']:>8.2f} "
                         f"{r['monitor_analysis_peak_bytes'] / mib:>5.0f}  {', '.join(r['repairs']) or 'none'}")
        lines.append("columns: states = the controller model's state-space order; step = one MPC step and one plant "
                     "step; loop = the closed loop of 10,000 samples (set-up included); detect = the tests without "
                     "the repair; analyze = detect, repair, detect; mon. us = one sample (three vectors) into the "
                     f"monitor's window; mon. ana = one analysis of the monitor's window: its default "
                     f"{MONITOR_WINDOW} samples, or 10% above the tests' minimum when that is longer (window "
                     + ", ".join(f"{r['size']}: {r['monitor_window']}" for r in result["industrial"]) + ")")
    lines.append(f"\nwall time of the run: {result['wall_s']:.0f} s")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- industrial size
#: Plant sizes (outputs, inputs) of the industrial section, and its window.
INDUSTRIAL_SIZES = ((20, 20), (50, 50), (100, 40))
INDUSTRIAL_SAMPLES = 10_000
#: The live monitor's default window (the monitor node's ``window_samples``).
MONITOR_WINDOW = 3000


def industrial_case(ny: int, nu: int, samples: int, seed: int = 0, mismatches: int = 3):
    """``(plant, model, log)``: a random plant, the controller model with ``mismatches`` (1 to 3)
    elements off (a gain 30 %, a delay 3 samples, a time constant 60 %), and ``samples`` samples of
    the closed loop."""
    plant = random_plant(ny, nu, np.random.default_rng(seed + 3000 + 100 * ny + nu))
    model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.3)
    if mismatches >= 2:
        model = model.with_element(3 % ny, 2 % nu, delay=model.delay[3 % ny, 2 % nu] + 3.0)
    if mismatches >= 3:
        model = model.with_element(5 % ny, 4 % nu, time_constant=model.time_constant[5 % ny, 4 % nu] * 1.6)
    log = run_closed_loop(plant, model, samples, seed=seed + 7)
    return plant, model, log


def traced(fn):
    """``(result, seconds, peak bytes)`` of ``fn()`` under tracemalloc (the peak above the start)."""
    import tracemalloc

    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        t0 = time.perf_counter()
        out = fn()
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    return out, seconds, peak


def bench_industrial(sizes=INDUSTRIAL_SIZES, samples: int = INDUSTRIAL_SAMPLES, seed: int = 0, log=print) -> list:
    """Controller, plant, analysis and monitor at industrial sizes; a list of dicts."""
    from mpm_monitor.core.analysis import detect
    from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
    from mpm_monitor.monitor.window import WindowOptions
    from mpm_monitor.sim.mpc import InternalModelMpc
    from mpm_monitor.sim.plant import DisturbanceOptions, PlantSimulator

    rows = []
    for ny, nu in sizes:
        row = {"size": f"{ny}x{nu}", "n_outputs": ny, "n_inputs": nu, "samples": samples}
        plant, model, cl = None, None, None
        t0 = time.perf_counter()
        plant, model, cl = industrial_case(ny, nu, samples, seed)
        row["closed_loop_s"] = time.perf_counter() - t0
        ctrl, row["mpc_setup_s"], row["mpc_setup_peak_bytes"] = traced(lambda: InternalModelMpc(model))
        row["mpc_structured"] = bool(ctrl.structured)
        row["n_states"] = int(ctrl._ss.n_states)
        sim, row["plant_setup_s"], row["plant_setup_peak_bytes"] = traced(
            lambda: PlantSimulator(plant, DisturbanceOptions(), np.random.default_rng(0)))
        r0 = np.zeros(ny)
        t0 = time.perf_counter()
        for _ in range(200):
            y = sim.measure()
            sim.apply(ctrl.step(r0, y))
        row["loop_step_s"] = (time.perf_counter() - t0) / 200
        del ctrl, sim
        data = cl.as_logged_data(source=f"{ny}x{nu} closed loop")
        det, row["detect_s"], row["detect_peak_bytes"] = traced(lambda: detect(model, data, AnalysisOptions(repair=False)))
        row["detect_located"] = [f"{o}:{i}" for o, i in det.located_elements]
        del det
        rep, row["analyze_s"], row["analyze_peak_bytes"] = traced(lambda: analyze(model, data, AnalysisOptions()))
        row["located"] = [f"{o}:{i}" for o, i in rep.located_elements]
        row["repairs"] = [f"{c['output']}:{c['input']} {c['kind']}{'' if c.get('applied') else ' (not applied)'}"
                          for c in rep.repair.get("changes", [])]
        del rep
        # The live monitor: samples into its window, and the analysis of its default window (or of the
        # shortest the tests take, 10 % above their minimum, when that is longer).
        need = regression_layout(model, AnalysisOptions()).min_samples
        window_n = max(MONITOR_WINDOW, int(np.ceil(1.1 * need)))
        row["monitor_window"] = window_n
        core = MonitorCore(model, MonitorOptions(window=WindowOptions(window_samples=window_n),
                                                 analysis_period=500, min_samples=min(1000, window_n)))
        core.start(0.0)
        ns = int(round(model.sample_time * 1e9))
        n_push = min(samples, window_n + 1000)
        t0 = time.perf_counter()
        for k in range(n_push):
            core.add("setpoint", k * ns, cl.r[k], 0.0)
            core.add("input", k * ns, cl.u[k], 0.0)
            core.add("output", k * ns, cl.y[k], 0.0)
        row["monitor_sample_s"] = (time.perf_counter() - t0) / n_push
        window = core.window.data(source="window")
        del core
        _, row["monitor_analysis_s"], row["monitor_analysis_peak_bytes"] = traced(
            lambda: analyze(model, window, AnalysisOptions()))
        rows.append(row)
        log(f"  {row['size']}: closed loop {row['closed_loop_s']:.1f} s ({row['n_states']} states, MPC set-up "
            f"{row['mpc_setup_s']:.2f} s, step {row['loop_step_s'] * 1e3:.2f} ms); detect {row['detect_s']:.2f} s "
            f"({row['detect_peak_bytes'] / 2**20:.0f} MiB); analyze with repair {row['analyze_s']:.2f} s "
            f"({row['analyze_peak_bytes'] / 2**20:.0f} MiB), located {', '.join(row['located']) or 'none'}; monitor "
            f"{row['monitor_sample_s'] * 1e6:.0f} us/sample, analysis of {window_n} samples "
            f"{row['monitor_analysis_s']:.2f} s")
    return rows


# ----------------------------------------------------------------------------------------- command line
TIME = "/usr/bin/time"


def _run_process(cmd, cwd=None, env=None) -> tuple:
    """``(wall seconds, max resident MiB, exit code)`` of one process (run in ``cwd`` with ``env``: by default
    this process's).

    The largest resident set comes from ``/usr/bin/time`` (``%M``): a child forked from this
    process would report this process's memory as its own (Linux counts the image replaced at
    ``exec``).  Without ``/usr/bin/time`` it is NaN.
    """
    import tempfile

    have_time = os.access(TIME, os.X_OK)
    with tempfile.NamedTemporaryFile("r", suffix=".time") as fh:
        full = [TIME, "-f", "%M", "-o", fh.name] + list(cmd) if have_time else list(cmd)
        t0 = time.perf_counter()
        rc = subprocess.call(full, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=cwd, env=env)
        wall = time.perf_counter() - t0
        rss = float("nan")
        if have_time:
            lines = [ln for ln in fh.read().split() if ln.strip().isdigit()]
            rss = int(lines[-1]) / 1024.0 if lines else float("nan")
    return wall, rss, rc


def _paired(cmd_a, cmd_b, repeats: int, cmd_c=None) -> dict:
    """``cmd_a`` and ``cmd_b`` (and ``cmd_c``) in turn, ``repeats`` times each, after one warm-up of each;
    medians, and the ratios to ``cmd_b`` pair by pair (``c_``: the third command's)."""
    cmds = [cmd_a, cmd_b] + ([cmd_c] if cmd_c is not None else [])
    for cmd in cmds:
        _run_process(cmd)
    runs = [[] for _ in cmds]
    for _ in range(repeats):
        for cmd, got in zip(cmds, runs):
            got.append(_run_process(cmd))
    med = statistics.median
    a, b = runs[0], runs[1]
    out = {"a_wall_s": med(x[0] for x in a), "b_wall_s": med(x[0] for x in b),
           "a_max_rss_mib": max(x[1] for x in a), "b_max_rss_mib": max(x[1] for x in b),
           "ratio_median": med(x[0] / y[0] for x, y in zip(a, b)), "a_exit": [x[2] for x in a],
           "a_walls": [x[0] for x in a], "b_walls": [x[0] for x in b]}
    out["ratio_of_medians"] = out["a_wall_s"] / out["b_wall_s"]
    if cmd_c is not None:
        c = runs[2]
        out.update(c_wall_s=med(x[0] for x in c), c_max_rss_mib=max(x[1] for x in c), c_exit=[x[2] for x in c],
                   c_walls=[x[0] for x in c], c_ratio_median=med(x[0] / y[0] for x, y in zip(c, b)))
    return out


def write_industrial_case(folder: Path, ny: int, nu: int, samples: int = INDUSTRIAL_SAMPLES, seed: int = 0) -> tuple:
    """``(model file, CSV)`` of :func:`industrial_case` with one element off, written in ``folder``."""
    from mpm_monitor.io.csv_log import write_log_csv
    from mpm_monitor.io.model_file import save_model

    _, model, cl = industrial_case(ny, nu, samples, seed, mismatches=1)
    csv, yml = folder / f"log_{ny}x{nu}.csv", folder / f"model_{ny}x{nu}.yaml"
    write_log_csv(csv, cl)
    save_model(model, yml)
    return yml, csv


def floor_command(csv: Path) -> list:
    """The floor of the command on ``csv``: a fresh interpreter that imports numpy and scipy.linalg and
    reads the CSV with ``numpy.loadtxt`` (argv of a process)."""
    return [sys.executable, "-c",
            "import sys, numpy, scipy.linalg; numpy.loadtxt(sys.argv[1], delimiter=',', skiprows=1)", str(csv)]


def bench_command_line(sizes=((20, 20), (100, 40)), samples: int = INDUSTRIAL_SAMPLES, seed: int = 0,
                       log=print) -> dict:
    """``python -m mpm_monitor analyze`` end to end against the floor, and ``--help`` against ``import numpy``."""
    import tempfile

    py = sys.executable
    out = {"help": _paired([py, "-m", "mpm_monitor", "analyze", "--help"], [py, "-c", "import numpy"], 5)}
    log(f"  analyze --help {out['help']['a_wall_s']:.3f} s, import numpy {out['help']['b_wall_s']:.3f} s: "
        f"x{out['help']['ratio_median']:.2f}")
    tmp = Path(tempfile.mkdtemp(prefix="mpm_perf_"))
    for ny, nu in sizes:
        yml, csv = write_industrial_case(tmp, ny, nu, samples, seed)
        floor = floor_command(csv)
        command = [py, "-m", "mpm_monitor", "analyze", "--model", str(yml), "--data", str(csv)]
        # The command as it runs (--jobs: 2 on two cores), the floor, and the command in one process.
        res = _paired(command, floor, 3, cmd_c=command + ["--jobs", "1"])
        res["csv_bytes"] = csv.stat().st_size
        out[f"{ny}x{nu}"] = res
        log(f"  analyze {ny}x{nu} x {samples}, repairing one element: {res['a_wall_s']:.2f} s, {res['a_max_rss_mib']:.0f} MiB; "
            f"floor {res['b_wall_s']:.2f} s: x{res['ratio_median']:.2f} (exit {res['a_exit']}); --jobs 1: "
            f"{res['c_wall_s']:.2f} s, x{res['c_ratio_median']:.2f}")
    return out


def run(grid: Grid, seed: int = 0, log=print, industrial: bool = True, only_industrial: bool = False,
        sizes=INDUSTRIAL_SIZES, command_line: bool = True) -> dict:
    """The whole benchmark; returns the JSON-ready result."""
    t0 = time.perf_counter()
    machine = machine_info()
    cells, sims, memory = [], [], {}
    if not only_industrial:
        log("analysis:")
        cells = bench_analysis(grid, seed, log)
        log("closed-loop simulation:")
        sims = bench_simulation(grid, seed, log)
        log("memory:")
        from bench.memory import measure_memory
        memory = measure_memory(quick=grid.sizes == QUICK.sizes, log=log)
    out = {"machine": machine, "grid": dataclasses.asdict(grid), "options": dataclasses.asdict(OPTIONS),
           "analysis": cells, "simulation": sims, "memory": memory}
    if industrial and command_line:
        log("command line:")
        out["command_line"] = bench_command_line(seed=seed, log=log)
    if industrial:
        log("industrial size:")
        out["industrial"] = bench_industrial(sizes, seed=seed, log=log)
    machine["load_average_end"] = list(os.getloadavg())
    out["targets"] = targets(cells, sims, out.get("command_line"), out.get("industrial"))
    out["wall_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.perf", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small grid (about a minute)")
    parser.add_argument("--threads", default="1", help="BLAS threads (set before numpy is imported)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench/results/perf.json", help="JSON output path")
    parser.add_argument("--no-industrial", action="store_true", help="skip the industrial sizes and the command line")
    parser.add_argument("--industrial-only", action="store_true", help="only the industrial sizes and the command line")
    parser.add_argument("--sizes", default=None, help="industrial sizes, e.g. 50x50,100x40 (default 20x20,50x50,100x40)")
    parser.add_argument("--no-command-line", action="store_true", help="skip the command-line measurements")
    args = parser.parse_args(argv)
    grid = QUICK if args.quick else Grid()
    sizes = INDUSTRIAL_SIZES if not args.sizes else tuple(tuple(int(v) for v in s.split("x"))
                                                         for s in args.sizes.split(","))
    result = run(grid, args.seed, industrial=not (args.no_industrial or args.quick),
                 only_industrial=args.industrial_only, sizes=sizes, command_line=not args.no_command_line)
    text = format_table(result)
    print()
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result["table"] = text
    out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
