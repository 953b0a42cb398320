"""What the analysis found: :class:`AnalysisReport`, its JSON and its summary text.

:func:`json_ready` turns the report into plain JSON values (:meth:`AnalysisReport.to_dict`), the
summary names the detectable gain changes (:func:`detectable_text`), and :func:`settle_report` puts
into a report the detectable gain changes and the experiment a forked child computed.  Callers
import :class:`AnalysisReport` from :mod:`mpm_monitor.core.analysis`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from .model import PlantModel
from .signals import LoopSignals
from .wording import repair_summary_lines

def json_ready(x):
    """``x`` as plain JSON-ready values, in one pass (what :meth:`AnalysisReport.to_dict` writes).

    A dataclass instance becomes the dict of its fields (as :func:`dataclasses.asdict`), a dict a dict
    (same keys), a list, tuple or ndarray a list, a numpy number a Python one; a float that is NaN or
    infinite becomes None; anything else is kept.
    """
    if isinstance(x, float):
        return float(x) if math.isfinite(x) else None
    if x is None or isinstance(x, (str, int)):
        return x
    if isinstance(x, (list, tuple)):
        return [json_ready(v) for v in x]
    if isinstance(x, dict):
        return {k: json_ready(v) for k, v in x.items()}
    if isinstance(x, np.floating):
        return json_ready(float(x))
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return json_ready(x.tolist())
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: json_ready(getattr(x, f.name)) for f in dataclasses.fields(x)}
    return x


@dataclasses.dataclass
class AnalysisReport:
    """Everything the analysis found; :meth:`to_dict` gives the JSON report.

    The report and its JSON are described in docs/interfaces.md ("analyze and its JSON report").

    Attributes
    ----------
    sample_time : float
        Seconds per sample.
    samples : int
        Samples analysed.
    method : str
        The element test (:attr:`~mpm_monitor.core.analysis_options.AnalysisOptions.method`).
    alpha : float
        False-alarm rate of the whole analysis.
    rows : list of RowResult
        The S_Delta row test of every output (:mod:`mpm_monitor.core.row_test`).
    elements : list of ElementResult
        The Delta element test of every pair of the rows tested (:mod:`mpm_monitor.core.element_test`).
    overall_rsi : float
        Largest singular value of the identified S_Delta over the band.
    warnings : list of str
    frequencies : ndarray, shape (n_freq,)
        The band's grid, rad/sample.
    row_gains : ndarray, shape (n_outputs, n_freq)
    sigma_max : ndarray, shape (n_freq,)
    sdelta_response : ndarray of complex, shape (n_freq, n_outputs, n_outputs)
        The identified S_Delta.
    arx_tables : list of RowArxTable
        The paper's ARX table of every row tested (ARX method only).
    repair : dict
        The repair (JSON values): the model, its changes, the prediction error before and after.
    repaired_model : PlantModel
        The model with the repairs applied (the model itself when nothing was repaired).
    collinear_groups : list of tuple of str
        Columns (inputs, measured disturbances) that cannot be told apart.
    max_variance_inflation : float
        Largest variance-inflation factor of an input's lag block.
    signals : LoopSignals or None
        ``yhat``, ``d`` and ``eps`` the tests used (of the samples used, segment after segment, on
        data with gaps).
    repair_result : RepairResult or None
        The repair's full result (None without repair).
    gaps : dict or None
        Data with gaps: :meth:`mpm_monitor.core.gaps.GapPlan.to_dict` (the JSON ``gaps`` object);
        None without a gap.
    regressions : object or None
        The row test's part of the tests' least-squares problems, when
        :func:`~mpm_monitor.core.analysis.detect` built them
        (:meth:`~mpm_monitor.core.regressions.GramRegressions.row_test_part`), for a detection of another
        model on the same data (``detect(..., previous=report)``); None in what
        :func:`~mpm_monitor.core.pipeline.analyze` returns.
    experiment : Experiment or None
        The dither experiment that would resolve what this window cannot decide (ambiguous elements,
        or no element decidable at 20 %), :mod:`mpm_monitor.core.experiment`; None when not needed.
    candidates : CandidateReport or None
        The candidate channels tried (:mod:`mpm_monitor.core.candidates`); None when none were asked for.
    noise_order : dict or None
        The ARX element test only: ``na`` (the order of the tests reported), ``requested`` (the option's
        ``na``), ``max_na``, ``coloured`` (the outputs whose element-test residual is coloured at this
        ``na``, :func:`~mpm_monitor.core.noise_order.coloured_rows`) and ``p_values`` (output -> the
        Ljung-Box p-value of its residual).  :func:`~mpm_monitor.core.pipeline.analyze` raises ``na``
        while ``coloured`` is not empty.
    pending : object or None
        The detectable gain changes and the experiment while a second process still computes them
        (:func:`~mpm_monitor.core.analysis.detect` with ``settle`` False); None once :func:`settle_report` has
        put them in.
    still_outputs : list of str
        Outputs that never move in the window (every value the same: a stuck sensor or a held value).
        Their rows' elements are not tested (listed with no p-value), no candidate is tested on them and
        the repair leaves them as they are; the JSON key ``still_outputs`` is written only when there is
        one.
    """

    sample_time: float
    samples: int
    method: str
    alpha: float
    rows: list
    elements: list
    overall_rsi: float
    warnings: list
    frequencies: np.ndarray
    row_gains: np.ndarray
    sigma_max: np.ndarray
    sdelta_response: np.ndarray
    arx_tables: list
    repair: dict
    repaired_model: PlantModel
    collinear_groups: list
    max_variance_inflation: float
    signals: Optional[LoopSignals] = None
    repair_result: object = None
    gaps: Optional[dict] = None
    experiment: object = None
    regressions: object = dataclasses.field(default=None, compare=False, repr=False)
    candidates: object = None
    noise_order: Optional[dict] = None
    pending: object = dataclasses.field(default=None, compare=False, repr=False)
    still_outputs: list = dataclasses.field(default_factory=list)

    @property
    def flagged_rows(self) -> list:
        """Outputs whose row is flagged."""
        return [r.output for r in self.rows if r.mismatch]

    @property
    def located_elements(self) -> list:
        """(output, column) pairs located as mismatched (the column an input or a measured disturbance)."""
        return [(e.output, e.input) for e in self.elements if e.mismatch]

    @property
    def ambiguous_elements(self) -> list:
        """(output, column) pairs that could not be told apart."""
        return [(e.output, e.input) for e in self.elements if e.ambiguous]

    def to_dict(self) -> dict:
        """The report as JSON-ready data (NaN and infinity become null; see :func:`json_ready`)."""
        doc = {
            "sample_time": self.sample_time,
            "samples": self.samples,
            "method": self.method,
            "alpha": self.alpha,
            "overall_rsi": self.overall_rsi,
            "rows": self.rows,
            "elements": self.elements,
            "located": [{"output": o, "input": i} for o, i in self.located_elements],
            "collinearity": {"max_variance_inflation": self.max_variance_inflation,
                             "groups": [list(g) for g in self.collinear_groups]},
            "arx_tables": self.arx_tables,
            "repair": self.repair,
            "experiment": self.experiment.to_dict() if self.experiment is not None else None,
            "warnings": list(self.warnings),
        }
        if self.gaps is not None:
            doc["gaps"] = self.gaps
        if self.candidates is not None:
            doc["candidates"] = self.candidates.to_dict()
        if self.noise_order is not None:
            doc["noise_order"] = self.noise_order
        if self.still_outputs:
            doc["still_outputs"] = list(self.still_outputs)
        return json_ready(doc)

    def summary_text(self) -> str:
        """A short human-readable summary (rows, located elements, errors, warnings)."""
        lines = [f"{self.samples} samples at {self.sample_time:g} s, method {self.method}, "
                 f"false-alarm rate alpha {self.alpha:g}; overall RSI {self.overall_rsi:.3f}"]
        width = max([10] + [len(r.output) for r in self.rows])      # a longer name widens the column
        lines.append(f"{'row':<{width}} {'RSI':>8} {'p-value':>10}  mismatch")
        for r in self.rows:
            lines.append(f"{r.output:<{width}} {r.rsi:8.3f} {r.p_value:10.2e}  {'YES' if r.mismatch else 'no'}")
        loc = [e for e in self.elements if e.mismatch]
        if loc:
            lines.append("located elements:")
            for e in loc:
                delay = "" if e.delay is None else f"  delay={e.delay}"    # None: a method that estimates none
                lines.append(f"  ({e.output}, {_column_label(e)})  p={e.p_value:.2e}  kind={e.kind}{delay}")
        else:
            lines.append("located elements: none")
        released = [e for e in self.elements if e.explained_by]
        if released:
            lines.append("flagged, but explained by the row's located elements (not located): "
                         + ", ".join(f"({e.output}, {_column_label(e)}) by {', '.join(e.explained_by)}"
                                     for e in released))
        unlocated = [e for e in self.elements if e.unlocated_at_na is not None]
        if unlocated:
            na = sorted({e.unlocated_at_na for e in unlocated})
            lines.append(f"flagged in rows the S_Delta row test does not flag, but not confirmed with na = "
                         f"{', '.join(map(str, na))} own lags (not located): "
                         + ", ".join(f"({e.output}, {_column_label(e)})" for e in unlocated))
        amb = [e for e in self.elements if e.ambiguous and not _never_moves(e)]
        if amb:
            moving = "inputs and measured disturbances" if any(e.role == "disturbance" for e in amb) else "inputs"
            lines.append(f"ambiguous ({moving} move together): "
                         + ", ".join(f"({e.output}, {_column_label(e)})" for e in amb))
        still = [e for e in self.elements if e.ambiguous and _never_moves(e)]
        if still:
            lines.append("not testable (their column never moves): "
                         + ", ".join(f"({e.output}, {_column_label(e)})" for e in still))
        if self.still_outputs:
            lines.append("not tested (the output never moves: a stuck sensor or a held value?): every element of "
                         + ", ".join(self.still_outputs))
        lines += detectability_summary_lines(self.elements, self.experiment)
        if self.candidates is not None:
            lines += self.candidates.summary_lines()
        lines += repair_summary_lines(self.repair)
        for w in self.warnings:
            lines.append(f"warning: {w}")
        return "\n".join(lines)


def _never_moves(e) -> bool:
    """Whether an element was not tested because its column never moves in the window (reported ``ambiguous``,
    with no partner and no test at all)."""
    return e.ambiguous and e.p_value_raw is None and e.statistic is None


def detectable_text(x) -> str:
    """A detectable gain change as a percentage (``35%``), ``n/a`` where it cannot be computed.

    Above 1 it reads ``>100%``: the value comes from the test's noncentrality to first order in the gain
    error, which an error larger than the element itself leaves behind (it changes the loop the window
    recorded).  ``python -m bench.detectability --still --first-order`` (loops whose setpoints never move, no
    dither) detected an error of the first-order size in 61 of 65 runs whose value was at most 1, and in 160
    of 235 above.  So the text says only what holds: this window does not reliably detect an error of 100 %
    of the element.  The JSON keeps the number.
    """
    if x is None or not math.isfinite(x):
        return "n/a"
    if x > 1:
        return ">100%"
    pct = f"{100 * x:.0f}"
    return "<1%" if pct == "0" else f"{pct}%"       # "0%" read as an error of none detected for sure


def detectability_summary_lines(elements: list, experiment) -> list:
    """The summary's lines on the detectable gain change of every tested element, and the experiment.

    One line per tested row, ``y1: u1 12%, u2 35%, u3 n/a (ambiguous)``: the smallest relative gain
    error of each element this window detects with probability 0.9 (``n/a`` where it cannot be
    computed); then the recommended experiment, if any, with its ``why``.
    """
    tested = [e for e in elements if getattr(e, "detectable_gain_change", None) is not None or e.ambiguous]
    lines = []
    if tested:
        lines.append("detectable gain change (smallest relative gain error detected with probability 0.9):")
        for out in dict.fromkeys(e.output for e in tested):
            lines.append(f"  {out}: " + ", ".join(
                f"{_column_label(e)} {detectable_text(e.detectable_gain_change)}"
                + ((" (never moves)" if _never_moves(e) else " (ambiguous)") if e.ambiguous and not e.mismatch
                   else "") for e in tested if e.output == out))
    if experiment is not None:
        dither = ", ".join(f"{k} {v:g}" for k, v in experiment.dither.items())
        lines.append(f"experiment recommended: PRBS dither on {dither} (input units) for {experiment.samples} samples; "
                     f"expected detectable gain change "
                     f"{detectable_text(experiment.expected_detectable_gain_change)}")
        lines.append(f"  why: {experiment.why}")
    return lines


def _column_label(e) -> str:
    """``u2``, ``dv1 (measured disturbance)`` for an element of a measured disturbance, ``tf (candidate)``
    for the effect of a candidate channel."""
    if e.role in ("disturbance", "candidate"):
        return f"{e.input} ({'measured disturbance' if e.role == 'disturbance' else e.role})"
    return e.input


class _Valuation:
    """The detectable gain changes and the experiment of a report, being computed
    (:class:`~mpm_monitor.core.parallel.Forked`), and where they go: the report's elements, and its warnings
    at a placeholder left where they belong."""

    def __init__(self, handle, elements: list, warnings: list):
        self.handle, self.elements = handle, elements
        self.marker = object()
        warnings.append(self.marker)


def settle_report(report: AnalysisReport) -> AnalysisReport:
    """Wait for the detectable gain changes and the experiment of ``report``
    (:func:`~mpm_monitor.core.analysis.detect` with ``settle`` False) and put them into it: each element's
    ``detectable_gain_change``, the ``experiment`` and the warnings they give, at their place among the
    others.  A report without any pending is returned as it is.  An error of their computation is raised here.

    Returns
    -------
    AnalysisReport
        ``report`` itself.
    """
    pending = report.pending
    if pending is None:
        return report
    report.pending = None
    try:
        values, why, experiment = pending.handle.result()
    finally:
        at = next(k for k, w in enumerate(report.warnings) if w is pending.marker)
        del report.warnings[at]
    report.warnings[at:at] = why
    for e, v in zip(pending.elements, values):
        e.detectable_gain_change = v
    report.experiment = experiment
    return report
