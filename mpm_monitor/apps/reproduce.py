"""``python -m mpm_monitor reproduce --case 3.1|3.2|3.3|level``: the paper's experiments, paper-style.

Simulates the case (:mod:`mpm_monitor.sim.cases`; 3.3 with the input dither of the paper's second
experiment; the level case with its measured inflow), runs the analysis and prints the row RSI
table, the flagged rows, the ARX tables of the flagged rows (the paper's Tables 1 to 5) and the
located elements; saves the singular-value plots of S_Delta per row (the paper's Figures 3 to 5) as
PNG.
"""

from __future__ import annotations

from pathlib import Path

from ..core.analysis import AnalysisOptions
from ..core.pipeline import analyze
from ..core.wording import repair_summary_lines
from ..sim.cases import CASE_NAMES, simulation_case
from ..sim.closed_loop import run_closed_loop


def simulate_case(case_name: str, samples: int, seed: int) -> tuple:
    """Simulate a case (the paper's, or "level"); returns (case, LoggedData, ClosedLoopLog)."""
    case = simulation_case(case_name)
    dv = {} if case.measured_disturbance is None else {"measured_disturbance": case.measured_disturbance}
    log = run_closed_loop(case.plant, case.model, samples, seed=seed, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance, **dv)
    return case, log.as_logged_data(f"{_title(case_name).lower()} (seed {seed})"), log


def _title(case_name: str) -> str:
    return f"{'Paper case' if case_name in CASE_NAMES else 'Case'} {case_name}"


def format_arx_table(table) -> str:
    """One flagged row's ARX table in the layout of the paper's Tables 1 to 5."""
    nb = len(next(iter(table.b.values()))) if table.b else 0
    na = len(table.a)
    ncol = max(na, nb)
    head = f"{'Polynomial':<12}" + "".join(f"{'q^-' + str(k + 1):>12}" for k in range(ncol)) + f"{'Delay':>7}{'Fit(%)':>9}"
    lines = [f"ARX model between d_{table.output} and u", head]
    lines.append(f"{'A(q)':<12}" + "".join(f"{v:12.3e}" for v in table.a) + " " * 12 * (ncol - na)
                 + f"{0:>7}{table.fit_percent:9.2f}")
    for name, b in table.b.items():
        lines.append(f"{'B_' + name + '(q)':<12}" + "".join(f"{v:12.3e}" for v in b) + " " * 12 * (ncol - nb)
                     + f"{table.delay[name]:>7}")
    return "\n".join(lines)


def save_sdelta_plots(report, directory, case_name: str) -> list:
    """Overall and per-row singular values of S_Delta with the identity line (paper Figs. 3-5)."""
    from ..io.plots import plot_sdelta

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"sdelta_case_{case_name.replace('.', '_')}.png"
    return [plot_sdelta(report, path, title=f"{_title(case_name)}: S_Delta singular values")]


def reproduce(case_name: str, samples: int = 3000, seed: int = 1, options: AnalysisOptions = AnalysisOptions(),
              plot_dir=None) -> str:
    """Run one case and return the paper-style text (and save the plots to ``plot_dir``)."""
    case, data, _ = simulate_case(case_name, samples, seed)
    report = analyze(case.model, data, options)
    lines = [f"{_title(case.name)}: {case.description}; {samples} samples, seed {seed}", "",
             f"{'row':<6}{'RSI':>8}{'p-value':>11}  flagged"]
    for r in report.rows:
        lines.append(f"{r.output:<6}{r.rsi:8.3f}{r.p_value:11.2e}  {'YES' if r.mismatch else 'no'}")
    lines.append(f"overall RSI (largest singular value of S_Delta): {report.overall_rsi:.3f}")
    lines.append(f"flagged rows: {', '.join(report.flagged_rows) or 'none'}"
                 f"   (expected: {', '.join(case.mismatched_rows) or 'none'})")
    for table in report.arx_tables:
        if table.output in report.flagged_rows:
            lines += ["", format_arx_table(table)]
    lines.append("")
    located = report.located_elements
    lines.append("located elements: " + (", ".join(f"({o}, {i})" for o, i in located) or "none"))
    lines.append("expected:         " + (", ".join(f"({o}, {i})" for o, i in case.mismatched_elements) or "none"))
    for e in report.elements:
        if e.mismatch:
            delay = "" if e.delay is None else f", delay {e.delay} samples"    # None: a method that estimates none
            lines.append(f"  ({e.output}, {e.input}): p = {e.p_value:.2e}, kind {e.kind}{delay}")
    if report.repair.get("changes"):
        lines += [""] + repair_summary_lines(report.repair)
    ok = set(located) == set(case.mismatched_elements) and set(report.flagged_rows) == set(case.mismatched_rows)
    lines.append(f"result matches the {'paper' if case.name in CASE_NAMES else 'case'}: {'yes' if ok else 'NO'}")
    for w in report.warnings:
        lines.append(f"warning: {w}")
    if plot_dir:
        for p in save_sdelta_plots(report, plot_dir, case.name):
            lines.append(f"saved {p}")
    return "\n".join(lines)
