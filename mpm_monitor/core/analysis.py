"""Model-plant mismatch detection: the options, the report and the run of the paper's two tests.

"A Novel Algorithm for Model-Plant Mismatch Detection for Model Predictive Controllers" decides in
two steps which elements of the controller's model ``Phat`` no longer match the plant:

1. the S_Delta row test (:mod:`mpm_monitor.core.row_test`): which rows of the sensitivity
   ``S_Delta = (I + Delta C)^-1`` differ from the identity, with each row's relative sensitivity
   index (RSI);
2. the Delta element test (:mod:`mpm_monitor.core.element_test`): which elements of
   ``Delta = P - Phat`` are non-zero, from the ARX of the prediction error on the model's columns
   -- the inputs and the measured disturbances -- (or a baseline method,
   :mod:`mpm_monitor.core.baselines`).

Every element structure goes through the same code: the model is only ever seen through its
sampled elements (:mod:`mpm_monitor.core.discretize`), and an element test needs only each
element's dead time.  An integrating output keeps both tests valid (see
:mod:`mpm_monitor.core.signals`, "Integrating outputs").

:func:`detect` runs both on one window of logged data (:class:`AnalysisOptions`) and gathers what
they found in an :class:`AnalysisReport`; the whole analysis -- detection, repair of the located
elements, and the detection run again on the repaired model -- is
:func:`mpm_monitor.core.pipeline.analyze`.  The false-alarm rate ``alpha`` is shared by the two
families of tests (:data:`mpm_monitor.core.statistics.N_FAMILIES`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import numpy as np

from .errors import ConfigurationError, DataFileError, TooFewSamples
from .logged_data import (
    NUMERICAL_ERRORS,
    LoggedData,
    check_loop_data,
    check_scale,
    divergence,
    in_deviations,
    moving_columns,
    numerical_breakdown,
    t_text,
)
from .model import PlantModel
from .options import check_options, option, option_specs
from .parallel import Forked
from .signals import INITIAL_STATE_CHOICES, LoopSignals
from .wording import repair_summary_lines

METHODS = ("arx", "xcorr", "pcorr")
ELEMENT_WINDOWS = ("model", "full")


@dataclasses.dataclass(frozen=True)
class AnalysisOptions:
    """Options of the analysis (:func:`detect`, :func:`mpm_monitor.core.pipeline.analyze`).

    Each field is declared with its default, description and range once
    (:func:`mpm_monitor.core.options.option`); :data:`ANALYSIS_PARAMS` holds them as
    :class:`~mpm_monitor.core.options.ParamSpec` and every value is checked by them on creation
    (:func:`check_analysis_options`), a number converted to the field's type.

    Attributes
    ----------
    na : int
        Order of the ARX ``A`` polynomials (paper: 4): the first order tried, see ``max_na``.
    max_na : int
        Largest ARX order :func:`~mpm_monitor.core.pipeline.analyze` raises ``na`` to when the element
        test's residuals are not white (:mod:`mpm_monitor.core.noise_order`: a slow drift under the
        measurement noise needs more own lags than the paper's 4, and a coloured residual in closed loop
        gives false alarms): ``na`` doubles (4, 8, 16) while some row's residual is coloured, at most to
        ``max_na`` (default 16; at most ``na`` keeps ``na`` whatever the residuals).
    nb : int
        Length of the ARX ``B`` polynomials once the delay is known (paper: 4); the tests use
        ``max_delay + nb`` lags so that the delay need not be known.
    alpha : float
        False-alarm rate of the whole analysis, in (0, 0.5): when the model matches the plant, the
        probability that any row or any element is reported mismatched is at most ``alpha``.  It
        is split equally (Bonferroni) between the row tests and the element tests, each family
        controlled by Holm's procedure; the reported ``p_value`` of a row or element is adjusted
        for both, so a finding is reported exactly when ``p_value < alpha``.
    band : tuple of float
        Band ``Omega`` of the RSI in rad/sample, ``0 <= low < high <= pi``.
    n_freq : int
        Frequencies evaluated in the band.
    max_delay : int or None
        Largest dead time (samples) searched, in [0, 1000]; None (default): the model's largest
        delay + 5, at least 10.
    initial_state : {"estimate", "zero"}
        How the model output is started (:func:`mpm_monitor.core.signals.compute_signals`).
    method : {"arx", "xcorr", "pcorr"}
        Element test: the ARX Delta test (default), or a baseline: cross-correlation (Webber and
        Gupta 2008) or partial correlation (Badwe et al. 2009).
    repair : bool
        Trace each located element to its kind and re-estimate it (:mod:`mpm_monitor.core.repair`).
    collinearity_threshold : float
        An input is not separable from the others (its elements are reported as ambiguous) when
        the variance-inflation factor of its lag block exceeds ``1 / collinearity_threshold``.
    element_window : {"model", "full"}
        Lags the element test examines: "model" (default) the first ``delay + nb`` lags of an
        element the model has (where any mismatch of that element starts), later up to the
        element's onset for slow structures (:func:`mpm_monitor.core.element_test.element_window`),
        all lags for an element the model lacks and for a measured disturbance's; "full" all lags
        ``1 .. max_delay + nb`` for every element.
    element_response : bool
        Also test every element the model has against its whole modelled response, one regressor
        ``A(q) Phat_ij u_j`` in place of the column's lag block
        (:mod:`mpm_monitor.core.response_test`), combined with the lag-window test by Bonferroni
        (default True).  It sees a mismatch of a slow element that the window's lags miss.
    test_all_rows : bool
        Run the element test on every row (default), not only on the rows the S_Delta test flags
        (the paper's order).  The family-wise false-alarm rate stays ``alpha`` (Holm's procedure
        over every element tested); a row in which an element is located counts as mismatched even
        when its S_Delta test, which has less power for a small mismatch, did not reject.
    confirm_responses : bool
        Re-test every located element with the whole modelled responses (and an integrating element's
        time-constant sensitivity) of its row's other elements as free regressors, at its Holm step, and
        keep it located only if it still rejects (default False; needs ``element_response``;
        :func:`mpm_monitor.core.response_test.given_other_responses`).  A slow or integrating element's
        mismatch outlives its column's lags and, through the controller, reaches another column's test;
        but in closed loop the other columns' responses also carry part of the element's own mismatch
        (the controller moves them against it), so the test loses true elements too: on
        ``bench.structures_mc`` (seed 0) it removed 3 false locations and 6 true ones.
    release_explained : bool
        When two or more elements of a row are located, re-estimate them jointly, each in its
        structure, and release (no longer report as located) an element none of whose parameters
        differs significantly from the model while another located element's do: its finding was
        that element's mismatch leaking into its test (default True;
        :func:`mpm_monitor.core.repair.explained_elements`).  This runs the repair's
        classification of those rows also when ``repair`` is off, so the located elements do not
        depend on ``repair``.
    drop_spikes : bool
        :func:`~mpm_monitor.core.pipeline.analyze` leaves out the samples of the log's spikes (one to
        three samples that leave a channel by more than 10 robust standard deviations of its
        sample-to-sample changes and come back; :mod:`mpm_monitor.core.spikes`) as missing samples,
        and its report's warnings name them (default True).  One such sample dominates every
        least-squares fit of the tests.  :func:`detect` alone does not screen.
    max_gap : int or None
        Data with gaps (docs/interfaces.md, "Gaps") are analysed segment by segment, stacked, however
        long the gaps; a gap longer than ``max_gap`` samples (default None: the longest lag of the
        tests, ``max_delay + nb``) splits the data the same way and is only named louder in the
        warning (:mod:`mpm_monitor.core.gaps`).
    jobs : int
        Processes the analysis uses (default 1).  With 2 or more, a forked second process
        (:mod:`mpm_monitor.core.parallel`) shares the element test's rows and the detectable gain
        changes' chunks with this one, each taking the next as it is free (this process runs the row
        test first when every row is element-tested, after a child has factored a large setpoint block,
        :data:`ROW_FORK_MIN_COLUMNS`), and on large windows takes one of two halves of the model run's
        rows, of the Gram matrices' products, of S_Delta's singular values and of the channels searched
        for spikes (:data:`SPLIT_MIN_WORK`, :data:`LIGHT_SPLIT_MIN_WORK`); in
        :func:`~mpm_monitor.core.pipeline.analyze` it computes the detectable gain changes and the
        experiment while the model is repaired and the repaired model detected, and on a window of at least
        :data:`SPLIT_MIN_WORK` takes rows to repair, each whole (:func:`row_jobs`).  The results are the
        same bit for bit, since each part is computed by the same code on the same numbers.  A process that runs other threads (a ROS node)
        never forks: it computes everything itself.  At most 2 are used.
    """

    na: int = option(4, "ARX order of A (the first tried; see max_na).", low=0, high=50)
    max_na: int = option(16, "Largest ARX order of A: while a row's element-test residual is not white "
                             "(Ljung-Box), na doubles up to this and the detection runs again (at most na: "
                             "never raised).", low=0, high=50)
    nb: int = option(4, "ARX order of each B.", low=1, high=50)
    alpha: float = option(0.01, "False-alarm rate of a whole analysis (split between the row tests and the element "
                                "tests, each with Holm's procedure).", low=0.0, high=0.5, open_low=True, open_high=True)
    band: tuple = option((0.0, math.pi), "RSI band, rad/sample.", low=0.0, high=math.pi, length=2)
    n_freq: int = option(256, "Frequencies evaluated in the band.", low=8, high=100000)
    max_delay: Optional[int] = option(None, "Largest dead time searched, samples.", low=0, high=1000)
    initial_state: str = option("estimate", "Model state at the first sample analysed: estimated by least squares or zero.",
                                choices=INITIAL_STATE_CHOICES)
    method: str = option("arx", "Element test: arx (paper), xcorr or pcorr (baselines).", choices=METHODS)
    repair: bool = option(True, "Also trace each located element to its kind and re-estimate it, for a suggested "
                                "repaired model (about 0.15 s more per analysis of a 3x3 or 5x5 window of 3,000 "
                                "samples with two to five located elements).")
    collinearity_threshold: float = option(1e-2, "Inputs are not separable when the variance inflation of a lag "
                                                 "block exceeds 1 / this.", low=0.0, high=1.0, open_low=True,
                                           open_high=True)
    test_all_rows: bool = option(True, "Run the element test on every row, not only on the rows the S_Delta test "
                                       "flags.")
    element_response: bool = option(True, "Also test each element the model has against its whole modelled "
                                          "response (one regressor), combined with the lag-window test.")
    element_window: str = option("model", "Lags the element test examines: model (an element the model has: "
                                          "delay + nb, wider for a slow onset; a measured disturbance's and an "
                                          "absent element's: all) or full (all).", choices=ELEMENT_WINDOWS)
    confirm_responses: bool = option(False, "Stricter: keep a located element only if it still rejects with the whole "
                                            "modelled responses of its row's other elements free (fewer elements "
                                            "located through another's mismatch, and fewer true ones).")
    release_explained: bool = option(True, "Where a row has several located elements, re-estimate them jointly and "
                                           "release one that does not differ from the model while another does "
                                           "(its finding was the other's mismatch).")
    drop_spikes: bool = option(True, "Leave out as missing samples the spikes of the log (one to three samples that "
                                     "leave a channel by more than 10 robust standard deviations of its changes and "
                                     "come back), with a warning naming them.")
    max_gap: Optional[int] = option(None, "Longest gap in the data (missing samples) called short, samples; longer "
                                          "gaps are named louder in the warning (None: the longest lag of the "
                                          "tests).", low=0, high=10**9)
    jobs: int = option(1, "Processes the analysis uses: with 2, a forked second process takes part of the rows' "
                          "work, row by row as each is free (the same results, bit for bit).", low=1, high=64)

    def __post_init__(self):
        for name, value in check_analysis_options(self).items():
            object.__setattr__(self, name, value)


def check_analysis_options(o: AnalysisOptions) -> dict:
    """Check every option against its :class:`~mpm_monitor.core.options.ParamSpec` (:data:`ANALYSIS_PARAMS`).

    Returns
    -------
    dict
        Option name -> value converted to the option's type.

    Raises
    ------
    ConfigurationError
        Naming the option outside its range (or a band whose low edge is not below its high edge).
    """
    values = check_options(o)
    lo, hi = values["band"]
    if not lo < hi:
        raise ConfigurationError(f"parameter band: expected 0 <= low < high <= pi rad/sample, got {o.band!r}")
    return values


#: The :class:`~mpm_monitor.core.options.ParamSpec` of every analysis option, by name: the one source
#: of the command line's analysis flags and the monitor node's analysis parameters.
ANALYSIS_PARAMS = {spec.name: spec for spec in option_specs(AnalysisOptions)}


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
        The element test (:attr:`AnalysisOptions.method`).
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
        The row test's part of the tests' least-squares problems, when :func:`detect` built them
        (:meth:`~mpm_monitor.core.regressions.GramRegressions.row_test_part`), for a detection of
        another model on the same data (``detect(..., previous=report)``); None in what
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
        (:func:`detect` with ``settle`` False); None once :func:`settle_report` has put them in.
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
        lines.append(f"{'row':<10} {'RSI':>8} {'p-value':>10}  mismatch")
        for r in self.rows:
            lines.append(f"{r.output:<10} {r.rsi:8.3f} {r.p_value:10.2e}  {'YES' if r.mismatch else 'no'}")
        loc = [e for e in self.elements if e.mismatch]
        if loc:
            lines.append("located elements:")
            for e in loc:
                lines.append(f"  ({e.output}, {_column_label(e)})  p={e.p_value:.2e}  kind={e.kind}  delay={e.delay}")
        else:
            lines.append("located elements: none")
        released = [e for e in self.elements if e.explained_by]
        if released:
            lines.append("flagged, but explained by the row's located elements (not located): "
                         + ", ".join(f"({e.output}, {_column_label(e)}) by {', '.join(e.explained_by)}"
                                     for e in released))
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


#: Samples x outputs x columns of a window below which the stages of a detection are not split over two
#: processes (``AnalysisOptions.jobs``): a fork makes every page of the process copy-on-write, and the
#: page faults after it, with the pickling of the results, cost more than half of a small window's
#: stages.  Measured in one process, medians of 5, split against not: case 3.2 (3x3, 3,000 samples,
#: 27,000) 0.638 against 0.576 s; case 3.3 (5x5, 10,000 samples, 250,000) 3.43 against 3.18 s; the
#: command on a 20x20 window of 10,000 samples (4e6) 1.18 against 1.28 s (one process: 1.36 s).
SPLIT_MIN_WORK = 1_000_000
#: ... and below which the lighter stages (the model run, the Gram matrices' products, the singular
#: values of S_Delta) are not split either: at 20x20 each takes a few hundredths of a second, about what
#: the page faults after a fork cost (the command at 20x20 split everywhere and with these three in one
#: process: the same time, median ratio 1.00 over 15 pairs; three forks fewer).
LIGHT_SPLIT_MIN_WORK = 10_000_000


def row_jobs(jobs: int, n_samples: int, model: PlantModel) -> int:
    """The processes the stages split row by row use on a window of ``n_samples`` (the element test, the
    repair): ``jobs`` from :data:`SPLIT_MIN_WORK` samples x outputs x columns, else 1."""
    return jobs if n_samples * model.n_outputs * model.n_columns >= SPLIT_MIN_WORK else 1


def light_jobs(jobs: int, n_samples: int, model: PlantModel) -> int:
    """The processes the lighter stages use on a window of ``n_samples``: ``jobs`` from
    :data:`LIGHT_SPLIT_MIN_WORK` samples x outputs x columns, else 1."""
    return jobs if n_samples * model.n_outputs * model.n_columns >= LIGHT_SPLIT_MIN_WORK else 1


#: Columns of the row test's setpoint block (moving setpoints x setpoint lags) from which, with two
#: processes, a forked child factors it while this process computes the colour of the element fits and
#: the input design (:func:`_detect`).  Its Gram factorisation takes about 0.27 s at 1,800 columns (100
#: outputs x 18 lags), 0.11 s at 1,260 and 0.04 s at 900, one BLAS thread; the child sends back two
#: matrices of that size (52 MB at 1,800), and below about 1,000 columns the fork and the transfer are
#: not repaid.
ROW_FORK_MIN_COLUMNS = 1000


def detect(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
           signals: Optional[LoopSignals] = None, regressions=None,
           previous: Optional["AnalysisReport"] = None, candidates=None, detectability: bool = True,
           rows_only: bool = False, settle: bool = True,
           beside: Optional[Callable[[LoopSignals], None]] = None) -> AnalysisReport:
    """Run the S_Delta row test and the Delta element test on logged closed-loop data (no repair).

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat``.
    data : LoggedData
        Setpoints, inputs, measured disturbances (those of the model) and outputs, on the grid of
        ``model.sample_time``; ``t`` may skip samples (the analysis then runs on the segments between
        the gaps, :mod:`mpm_monitor.core.gaps`).
    options : AnalysisOptions
        ``options.repair`` is not used here (:func:`mpm_monitor.core.pipeline.analyze`).
    signals : LoopSignals, optional
        ``yhat``, ``d`` and ``eps`` of these samples, e.g. from a model run continuously since
        before the window (:mod:`mpm_monitor.core.sliding`); default: recomputed from the data with
        ``options.initial_state`` (segment by segment on data with gaps).
    regressions : object, optional
        Provider of the tests' least-squares fits with the methods of
        :class:`~mpm_monitor.core.regressions.QrRegressions`.  Default:
        :func:`mpm_monitor.core.regressions.window_regressions`, the fits solved from the Gram
        matrices of the window's lagged signals, each regression whose condition bound exceeds
        1e3 (or whose residual is too small a part of its target) refitted by QR; the results equal
        those of :class:`~mpm_monitor.core.regressions.QrRegressions` to about 1e-10.
    previous : AnalysisReport, optional
        The detection of another model on the same data (before a repair): with the default
        regressions, the S_Delta row test takes from it the setpoint block and the fits of the rows
        whose prediction error is the same (the same numbers,
        :meth:`~mpm_monitor.core.regressions.GramRegressions.reuse_rows_of`).
    candidates : str, sequence of str or CandidateChannels, optional
        Logged channels the model does not use (``data.extra``), tested as causes of each output's
        prediction error jointly with the model's columns (:mod:`mpm_monitor.core.candidates`):
        ``"all"``, names, or channels already selected.  Their tests join the element tests' family.
        Default: none (the analysis is then exactly that without candidates).
    detectability : bool
        False: no ``detectable_gain_change`` (None) and no ``experiment`` (e.g. for the detection of a
        repaired model, of which only the rows are reported); the tests are the same.
    rows_only : bool
        True: a detection of which only the rows are read (the repaired model's): the identified
        ``S_Delta``'s largest singular values are not computed (``sigma_max`` and ``overall_rsi`` NaN),
        and when no row is to be element-tested (``test_all_rows`` false and no row flagged) the
        element test does not run (no elements, ARX tables or collinearity: ``max_variance_inflation``
        NaN), nor are the input lags' cross products taken.  Every row's test and RSI are the same.
    settle : bool
        False, with ``options.jobs`` 2 and no ``candidates``: the detectable gain changes and the
        experiment are computed in a forked second process, and the report is returned while they are
        (its ``pending``); :func:`settle_report` waits for them and puts them in (the analysis repairs the
        model meanwhile, :func:`~mpm_monitor.core.pipeline.analyze`).  The same numbers either way.
    beside : callable, optional
        Called once with the model's signals on data without gaps, when they were computed here and the
        stages that follow run in this process while the analysis has a second one (``options.jobs`` 2, a
        window that splits row by row but not its lighter stages, :func:`light_jobs`): work for the idle
        second process (:func:`~mpm_monitor.core.pipeline.analyze` forks the repair's disturbance tests
        there).  It must not change what it is given.

    Returns
    -------
    AnalysisReport
        ``samples`` counts the samples used and ``gaps`` says what the gaps cost (data with gaps).
        Its ``repair`` holds the model unchanged (no changes; the prediction error's RMS before and
        after) and every located element has the kind ``unknown``.

    Raises
    ------
    DataFileError
        When the data do not fit the model, are too short for the tests or too large for them
        (:func:`~mpm_monitor.core.logged_data.check_scale`), or when the tests break down numerically
        on them (:func:`~mpm_monitor.core.logged_data.numerical_breakdown`: a loop that diverged),
        the numpy error as its ``__cause__``.
    """
    return _guarded(model, data, options, signals, regressions, previous, candidates, detectability,
                    rows_only=rows_only, settle=settle, beside=beside)


def load_tests(model: Optional[PlantModel] = None) -> None:
    """Import now what a detection imports when it first runs (the tests and ``scipy.special``; the options
    and the report are described without them), and sample ``model``'s elements (kept on it, as its first
    simulation would): the command line does it while a child process parses the CSV, instead of after
    (at 100x40 the 4,000 elements take about 0.08 s)."""
    from . import detectability, element_test, experiment, gaps, regressions, response_moments, row_test  # noqa: F401
    from . import resolution, signals, spikes  # noqa: F401
    from .discretize import discretize
    from .statistics import _special

    _special()
    if model is not None:
        discretize(model)


def longest_delay_note(model: PlantModel, options, layout, enough: Callable) -> str:
    """``; max_delay is the model's longest delay + 5 samples: (y1, u1) 500 s, 500 samples`` when that delay is
    why the data are too short: ``options.max_delay`` not given, and ``enough(least)`` for the layout of the
    tests at their least lags (``max_delay`` 10, a :class:`~mpm_monitor.core.regressions.RegressionLayout`).
    A delay in the wrong unit (500 s for 5 s) otherwise reads as a short log.  '' otherwise."""
    if options.max_delay is not None or model.n_outputs == 0 or layout.max_delay <= 10:
        return ""
    from .regressions import regression_layout

    if not enough(regression_layout(model, dataclasses.replace(options, max_delay=10))):
        return ""
    d = model.delay_samples
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    return (f"; max_delay is the model's longest delay + 5 samples: ({model.outputs[i]}, {model.columns[j]}) "
            f"{int(d[i, j]) * model.sample_time:g} s, {int(d[i, j])} samples")


def _guarded(model: PlantModel, data: LoggedData, *args, **how):
    """:func:`_detect` on ``data`` in deviations, its numerical errors turned into a ``DataFileError``
    (:func:`~mpm_monitor.core.logged_data.numerical_breakdown`)."""
    data = in_deviations(model, data)
    try:
        return _detect(model, data, *args, **how)
    except NUMERICAL_ERRORS as err:
        raise numerical_breakdown(model, data, err) from err


def _detect(model: PlantModel, data: LoggedData, options: AnalysisOptions, signals: Optional[LoopSignals],
            regressions, previous: Optional["AnalysisReport"], candidates, detectability: bool,
            unless_coloured: bool = False, rows_only: bool = False, settle: bool = True, beside=None):
    """:func:`detect` (same arguments), its numerical errors not yet turned into a ``DataFileError``; with
    ``unless_coloured``, :func:`detect_unless_coloured`."""
    # The tests are imported here: the options and the report above are described (the command line's
    # flags, the monitor's parameters) without the scipy they need.
    from .detectability import element_detectability
    from .discretize import model_columns
    from .element_test import ElementTest, InputDesign, arx_element_test, baseline_element_test
    from .experiment import design_experiment
    from .gaps import plan_gaps
    from .regressions import regression_layout, window_regressions
    from .resolution import column_resolution_warnings, resolution_warnings
    from .response_moments import ResponseMoments
    from .row_test import moving_setpoints, sdelta_row_test
    from .segments import GapSegments
    from .signals import (compute_signals, error_rms, packed, scored_segments, segment_signals, segments_mask,
                          unknown_starts)

    ny = model.n_outputs
    src = data.source or "data"
    r, u, y = check_loop_data(model, data)
    found = divergence(model.outputs, y)
    diverging, diverged = [warning for _, warning in found], [name for name, _ in found]
    check_scale(model, data)
    dv = np.asarray(data.dv, dtype=float)
    layout = regression_layout(model, options)
    plan = plan_gaps(data, layout.start, options.max_gap)
    restarts = None
    if plan is not None:          # data with gaps: the segments long enough for a regression row, stacked
        check_gap_rows(plan, layout, options, src, model, notes=data.notes)
        r, u, y, dv = (plan.take(x) for x in (r, u, y, dv))
        grid = plan.take(data.grid_index)     # the model runs through a short gap (segment_signals)
        restarts = unknown_starts(plan.local_segments, grid, plan.max_gap, data.fill_on_grid())
        # The regressions' segments, and the runs the element responses are simulated through (as the model).
        segments = GapSegments(plan.local_segments, grid, plan.max_gap)
    columns = model_columns(u, dv)            # the inputs, then the measured disturbances
    n = r.shape[0]
    # Two processes: the detectable gain changes beside the repair (settle) whenever asked for; the stages split
    # row by row only for a window large enough that half of their work outweighs what a fork costs.
    two = options.jobs > 1
    if two and row_jobs(options.jobs, n, model) == 1:
        options = dataclasses.replace(options, jobs=1)
    split_light = light_jobs(options.jobs, n, model)     # the model run, Gram products, SVD
    if n < layout.min_samples and plan is None:
        raise TooFewSamples(f"{src}: {n} samples; the tests with na={options.na}, nb={options.nb}, "
                            f"max_delay={layout.max_delay} need at least {layout.min_samples} samples"
                            f"{longest_delay_note(model, options, layout, lambda least: n >= least.min_samples)}")
    if signals is None:
        sig = compute_signals(model, r, u, y, options.initial_state, dv=dv, jobs=split_light) if plan is None else \
            segment_signals(model, r, u, y, plan.local_segments, options.initial_state, dv=dv, grid=grid,
                            max_gap=plan.max_gap, fill=data.fill_on_grid())
        if beside is not None and plan is None and options.jobs > 1 and split_light == 1:
            beside(sig)
    else:
        sig = signals
        n_given = data.n_samples
        if sig.d.shape != (n_given, ny) or sig.eps.shape != (n_given, ny):
            raise DataFileError(f"{src}: signals of shape {sig.d.shape} / {sig.eps.shape}, expected ({n_given}, {ny})")
        if plan is not None:
            sig = LoopSignals(*(plan.take(x) for x in (sig.yhat, sig.d, sig.eps, sig.transient)))
    if regressions is None and plan is None:
        z = sig.eps - r   # = -d: zero-mean noise under "no mismatch"
        regressions = window_regressions(r, columns, z, sig.d, layout, options.na, options.nb, jobs=split_light,
                                         previous=None if previous is None else previous.regressions)
    elif regressions is None:
        # Each segment's d centred on its own (its level restarts with its model output, and moves across
        # a short gap the model runs through with its columns held).
        d = np.vstack([sig.d[a:b] - sig.d[a:b].mean(axis=0) for a, b in plan.local_segments])
        regressions = window_regressions(r, columns, -d, d, layout, options.na, options.nb,
                                         segments=segments, jobs=split_light)

    # A fit that leaves at most EXACT_FIT of its output's spread is exact (a log without noise): its tests
    # decide outright instead of on the rounding of its residual.  The spread is the larger of the
    # output's and of its prediction error's (the signal the tests fit): an output that never moves
    # (a flat, noise-free log) still leaves the rounding of a moving model output.  A diverging
    # output's spread (its last samples') is no scale for that rounding: there only a residual of
    # exactly 0 is exact.
    error_std = np.std(sig.d, axis=0)
    spread = np.maximum(np.std(y, axis=0), error_std)
    spread[[model.outputs.index(name) for name in diverged]] = 0.0
    probe = unless_coloured and options.method == "arx"
    # With two processes, when the rows to element-test do not depend on the row test (every row, arx), the
    # row test runs in this process after the element test's child has started on the rows (its
    # ``meanwhile``), and this process then takes its share of the rows: the same numbers.
    overlap = options.jobs > 1 and options.method == "arx" and options.test_all_rows and not rows_only
    # Then a large setpoint block (ROW_FORK_MIN_COLUMNS) is factored in a forked child while this process
    # computes the colour, the input design and the element responses' set-up below, and the element test's
    # child starts on its rows; the row test reads the factor (the same numbers).
    factoring = None
    if overlap and hasattr(regressions, "factored_row_regression"):
        r_moving = moving_setpoints(r)
        if len(r_moving) * layout.n_lag_r >= ROW_FORK_MIN_COLUMNS and regressions.row_regression_pending(r_moving):
            factoring = Forked(lambda: regressions.factored_row_regression(r_moving))
    # An output that never moves (a stuck sensor or a held value) has a prediction error that is the model's own
    # response: its row's elements are not tested (the element test would locate every one of them, and the
    # repair would take the row's gains to zero for a fault of the measurement).
    still = np.flatnonzero(~moving_columns(y)).tolist()
    colour = None
    if probe and options.test_all_rows:       # the rows tested do not depend on the row test: before it
        colour = _ElementColour(model, _moving_rows(range(ny), still), columns, layout, regressions, options, spread)
        if colour.noise_order["coloured"]:
            return Coloured(colour.noise_order, sig, None if plan is None else plan.to_dict())
    row_tests = []

    def run_row_test(jobs: int) -> None:
        nonlocal factoring
        if factoring is not None:        # the child's factor of the setpoint block, read once the row test needs it
            factored, factoring = factoring.result(), None
            if factored is not None:
                regressions.keep_row_regression(r_moving, factored)
        row_tests.append(sdelta_row_test(model, r, sig.eps, regressions, layout, options, output_spread=spread,
                                         singular_values=not rows_only, jobs=jobs))
    if not overlap:
        run_row_test(split_light)
    test_rows = list(range(ny)) if (options.test_all_rows or options.method != "arx") else \
        [i for i in range(ny) if row_tests[0].rows[i].mismatch]
    element_rows = _moving_rows(test_rows, still)
    if probe and colour is None:
        colour = _ElementColour(model, element_rows, columns, layout, regressions, options, spread)
        if colour.noise_order["coloured"]:
            return Coloured(colour.noise_order, sig, None if plan is None else plan.to_dict())
    untested = rows_only and not test_rows and options.method == "arx"
    if untested:                  # nothing to element-test, and only the rows are read: no design either
        design = None
    else:
        design = colour.design if colour is not None else \
            InputDesign(model, columns, layout.n_lag_u, layout.start, options.collinearity_threshold,
                        regressions.input_regression)
    # On a loop that diverged every moment is of signals that grow without bound: no detectable change
    # and no experiment means anything there (the warnings already say the tests' results do not).
    valued = options.method == "arx" and detectability and not diverging and not untested
    moments = None
    if valued:
        # The element responses and their products with the input lags, taken once for the
        # whole-response tests and the detectability.
        moments = ResponseMoments(model, columns, sig.d, design.testable, layout.n_lag_u, layout.start, options.na,
                                  None if plan is None else segments)
    later_warnings = []
    if untested:
        element_test = ElementTest(elements=[])
    elif options.method == "arx":
        element_test = arx_element_test(model, element_rows, design, regressions, options, moments,
                                        output_spread=spread, fits=None if colour is None else colour.fits,
                                        whiteness=None if colour is None else colour.whiteness,
                                        meanwhile=(lambda: run_row_test(1)) if overlap else None)
    elif plan is None:
        element_test = baseline_element_test(model, columns, sig.d, options)
    else:                         # the baselines' correlations need one contiguous span: the longest
        a, b = max(plan.local_segments, key=lambda s: s[1] - s[0])
        element_test = baseline_element_test(model, columns[a:b], sig.d[a:b], options)
        later_warnings.append(f"the {options.method} element test ran on the longest span without a gap "
                              f"({b - a} samples)")
    row_test = row_tests[0]
    rows = row_test.rows
    t_used = data.t if plan is None else plan.take(data.t)
    warnings = still_output_warnings(model, still) + held_tail_warnings(model, y, t_used, still) \
        + unsettled_warnings(model) + diverging + list(row_test.warnings) \
        + offset_warnings(model, sig.d, y, diverged, t_used) + resolution_warnings(model.outputs, y, error_std, still) \
        + column_resolution_warnings(model.columns, model.outputs, columns, model.gain,
                                     np.asarray(model.integrating_outputs, dtype=bool)[:, None] | model.integrating,
                                     error_std, still) \
        + ([] if design is None else design.warnings()) + later_warnings
    warnings += element_test.warnings
    # (The baselines test every row: their results on a still output's row are set aside as well.)
    still_names = [model.outputs[i] for i in still]
    elements = with_untested_rows(model, [e for e in element_test.elements if e.output not in still_names],
                                  [i for i in test_rows if i not in element_rows])
    valuation = None
    if valued:
        # The detectable gain changes and the experiment: with settle False and two processes, computed in a
        # forked child while the caller goes on (the repair and the repaired model's detection), and put into
        # the report by settle_report.
        later = not settle and candidates is None and two
        value_options = dataclasses.replace(options, jobs=1) if later else options

        def values_and_experiment():
            info, detectable, why = element_detectability(model, columns, sig.d, design, element_test.noise, layout,
                                                          value_options, None if plan is None else segments,
                                                          responses=element_test.responses, moments=moments)
            values = [detectable.get((model.outputs.index(e.output), model.columns.index(e.input))) for e in elements]
            for e, v in zip(elements, values):
                e.detectable_gain_change = v
            return values, why, design_experiment(model, info, elements, options, layout)
        handle = Forked(values_and_experiment, inline=not later)
        if handle.forked:
            moments.forget()      # only the child reads them now (this process again only if the child dies)
        valuation = _Valuation(handle, elements, warnings)
    elif options.method == "arx" and detectability:
        warnings.append(f"the loop diverged ({', '.join(diverged)}): the smallest gain "
                        "change this window detects is not computed (detectable_gain_change null) and no experiment "
                        "is designed; the model needs repairing before the loop can be probed")
    elif detectability:
        warnings.append(f"method {options.method}: the smallest gain change this window detects is computed for the "
                        f"arx element test only (detectable_gain_change null)")
    experiment = design_experiment(model, None, elements, options, layout) if detectability and not valued else None
    candidate_report = None
    if candidates is not None:
        from .candidates import CandidateChannels, run_candidate_tests, select_candidates

        if options.method != "arx":
            raise ConfigurationError(f"candidates: tested by the arx element test only, not by method {options.method}")
        cdata = data
        if plan is not None:      # the rows of the segments used, as the other tests
            cdata = data.take(np.concatenate([np.arange(a, b) for a, b in plan.used]))
        if isinstance(candidates, CandidateChannels):
            chosen = candidates if plan is None else dataclasses.replace(candidates, values=plan.take(candidates.values))
        else:
            chosen = select_candidates(cdata, candidates, model)
        tested = run_candidate_tests(model, cdata, chosen, columns, sig.d, elements, layout, options,
                                     output_spread=spread, still_outputs=still)
        elements = tested.elements + tested.candidate_elements
        candidate_report = tested.report
        warnings += candidate_report.warnings()
        if tested.candidate_elements and detectability:
            warnings.append("candidate channels: the smallest gain change this window detects is computed for the "
                            "model's own columns only (detectable_gain_change null for the candidates' elements)")

    # A row in which an element is located is mismatched, even when its S_Delta test did not reject.
    for i in range(ny):
        if not rows[i].mismatch and any(e.mismatch for e in elements if e.output == model.outputs[i]):
            rows[i] = dataclasses.replace(rows[i], mismatch=True)
    for i in element_rows:
        out = model.outputs[i]
        row_el = [e for e in elements if e.output == out]
        if rows[i].mismatch and not any(e.mismatch or e.ambiguous for e in row_el):
            what = "no input or measured disturbance" if model.n_disturbances else "no input"
            warnings.append(f"row {out} differs from the identity but {what} explains its prediction error: an "
                            f"unmeasured disturbance, a nonlinearity or too little input excitation")
    for e in elements:
        if e.mismatch:
            e.kind = "missing" if e.role == "candidate" else "unknown"
    # With gaps: over the samples settled from the state each gap leaves, as the repair takes its errors.
    if plan is None:
        rms = error_rms(model, sig.d)
    else:
        scored = scored_segments(plan.local_segments, model, settled=True, restarts=restarts)
        rms = error_rms(model, sig.d[segments_mask(scored, n)], segments=packed(scored))
    unrepaired = {"model": model.to_dict(), "changes": [], "error_before": rms, "error_after": dict(rms)}
    if plan is not None:
        warnings.insert(0, plan.warning())
    warnings[:0] = data.notes
    noise_order = _noise_order(model, options, element_test.whiteness) if options.method == "arx" else None
    report = AnalysisReport(
        sample_time=model.sample_time, samples=n, method=options.method, alpha=options.alpha, rows=rows,
        elements=elements, overall_rsi=float("nan") if rows_only else float(row_test.sigma_max.max()),
        warnings=warnings,
        frequencies=row_test.frequencies, row_gains=row_test.row_gains, sigma_max=row_test.sigma_max,
        sdelta_response=row_test.response, arx_tables=element_test.arx_tables, repair=unrepaired,
        repaired_model=model, collinear_groups=[] if untested else design.groups,
        max_variance_inflation=float("nan") if untested else design.max_vif, signals=sig,
        gaps=None if plan is None else plan.to_dict(), experiment=experiment, candidates=candidate_report,
        regressions=regressions.row_test_part() if getattr(regressions, "batch", False) else None,
        noise_order=noise_order, pending=valuation,
        still_outputs=still_names)
    if settle:
        settle_report(report)
    return report


class _Valuation:
    """The detectable gain changes and the experiment of a report, being computed (:class:`Forked`), and
    where they go: the report's elements, and its warnings at a placeholder left where they belong."""

    def __init__(self, handle, elements: list, warnings: list):
        self.handle, self.elements = handle, elements
        self.marker = object()
        warnings.append(self.marker)


def settle_report(report: AnalysisReport) -> AnalysisReport:
    """Wait for the detectable gain changes and the experiment of ``report`` (:func:`detect` with ``settle``
    False) and put them into it: each element's ``detectable_gain_change``, the ``experiment`` and the
    warnings they give, at their place among the others.  A report without any pending is returned as
    it is.  An error of their computation is raised here.

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


#: A row whose prediction error's mean exceeds this many times its standard deviation is named as
#: offset (:func:`offset_warnings`).
OFFSET_RATIO = 10.0


#: A step-response element that still changes by more than this fraction of its largest |value| over the last
#: tenth of its ``N`` samples (on a row without ``ramp``) has not settled within ``N`` (:func:`unsettled_warnings`).
UNSETTLED_FRACTION = 0.03


def unsettled_warnings(model: PlantModel) -> list:
    """One warning naming the step-response elements that have not settled within the model's ``N`` samples.

    The model holds each response at its last coefficient beyond ``N``: a plant whose response goes on
    rising differs from the model there, every such element can be located, and a repair that keeps the
    element's ``N`` cannot follow it.  A ``ramp`` row's elements end on a slope by design and are left out.
    "Still changing" is measured over the last tenth of the samples (the last step below 20 samples).
    """
    if not model.is_step_response or model.step_length < 2:     # (below 10 samples it was never checked)
        return []
    sr, n = model.step_response, model.step_length              # (n_outputs, n_columns, N)
    tail = np.abs(sr[..., -1] - sr[..., n - 1 - max(1, n // 10)])
    scale = np.max(np.abs(sr), axis=-1)
    cut = (tail > UNSETTLED_FRACTION * scale) & (scale > 0) & ~np.array(model.ramp, dtype=bool)[:, None]
    if not np.any(cut):
        return []
    pairs = [f"({model.outputs[i]}, {model.columns[j]})" for i, j in zip(*np.nonzero(cut))]
    shown = ", ".join(pairs[:6]) + (f" and {len(pairs) - 6} more" if len(pairs) > 6 else "")
    return [f"the step responses of {shown} have not settled within the model's {n} samples (they still change by "
            f"more than {UNSETTLED_FRACTION:.0%} of their size over its last tenth): the model holds each at its last "
            f"value beyond that, so a plant whose response goes on differs from it there, and a repair in "
            f"{n} samples cannot follow it; a longer step_response (more samples) is needed"]


def still_output_warnings(model: PlantModel, still) -> list:
    """One warning naming the outputs ``still`` (indices) that never move in the window
    (:func:`~mpm_monitor.core.logged_data.moving_columns` of the outputs): a stuck sensor or a held value,
    whose rows' elements the element test leaves untested and the repair leaves as they are."""
    still = [model.outputs[i] for i in still]
    if not still:
        return []
    rows = "their rows" if len(still) > 1 else "its row"
    return [f"output{'s' if len(still) > 1 else ''} {', '.join(still)} never move{'' if len(still) > 1 else 's'} in "
            f"this window (every value the same: a stuck sensor or a held value?): a fault of the measurement, not "
            f"of the model; the elements of {rows} are not tested (no p-value, detectable_gain_change null) and the "
            f"repair leaves them as they are (the row test reads a constant: check the measurement first)"]


#: An output whose last samples hold one value, at least this many of them and this fraction of the window, while
#: it changed at almost every sample before (:func:`held_tail_warnings`), is named as a sensor stuck there.
HELD_TAIL_SAMPLES, HELD_TAIL_FRACTION = 50, 0.05
#: ... "almost every sample": at most this fraction of its changes before the held value are zero (a quantized
#: measurement repeats its value often, and is not named).
HELD_TAIL_REPEATS = 0.01


def held_tail_warnings(model: PlantModel, y: np.ndarray, t: np.ndarray, still) -> list:
    """One warning per output (not in ``still``) whose last samples hold one value while it moved before.

    A sensor that sticks during the window (a transmitter gone, a historian holding its last value) leaves its
    output constant from there on: the tests then read the process before and the model's own response
    after, and may locate its row's elements.  Named, not left out: a held value cannot be told from a
    process at rest when the noise is below the measurement's resolution.

    Parameters
    ----------
    y : ndarray, shape (n_samples, n_outputs)
        The outputs of the window.
    t : ndarray, shape (n_samples,)
        Their times (s).
    still : sequence of int
        Outputs that never move (named by :func:`still_output_warnings`).
    """
    n = y.shape[0]
    least = max(HELD_TAIL_SAMPLES, int(HELD_TAIL_FRACTION * n))
    out = []
    for i in range(y.shape[1]):
        if i in still or n <= least:
            continue
        changes = y[1:, i] != y[:-1, i]
        moved = np.flatnonzero(changes)
        if moved.size == 0:
            continue
        held = n - 1 - int(moved[-1])           # samples after the last change, the last value's included
        before = changes[:moved[-1] + 1]
        if held >= least and np.count_nonzero(~before) <= HELD_TAIL_REPEATS * before.size:
            out.append(f"output {model.outputs[i]} holds one value over its last {held} samples (from t = "
                       f"{t_text(t[n - held])} s) while it changed at almost every sample before: a sensor stuck "
                       f"there or a held value? What the tests and the repair say of row {model.outputs[i]} mixes "
                       f"the process before with a constant after")
    return out


def _moving_rows(rows, still) -> list:
    """The rows of ``rows`` (output indices) whose output moves (not in ``still``)."""
    return [i for i in rows if i not in still]


def with_untested_rows(model: PlantModel, elements: list, rows: list) -> list:
    """``elements`` with an untested entry for every column of each row of ``rows`` (output indices, of
    outputs that never move), in the order of the rows (then of the columns) as the element test lists them.

    An untested entry has ``mismatch`` false, no p-value and no statistic, and is not ambiguous."""
    if not rows:
        return elements
    from .element_test import ElementResult

    added = [ElementResult(output=model.outputs[i], input=name, mismatch=False, p_value=None, p_value_raw=None,
                           statistic=None, role=model.role(j))
             for i in rows for j, name in enumerate(model.columns)]
    order = {name: i for i, name in enumerate(model.outputs)}
    return sorted(elements + added, key=lambda e: order.get(e.output, len(order)))


def offset_warnings(model: PlantModel, d: np.ndarray, y: np.ndarray, skip=(), t: Optional[np.ndarray] = None) -> list:
    """The warnings naming the rows whose prediction error sits far from zero, or ramps on an integrating
    output: an undeclared operating point?

    The model's elements act on deviations from the model file's ``input_nominal``, ``output_nominal``
    and ``disturbance_nominal``.  A log whose columns sit at an operating point the file does not
    declare (a feed temperature logged at 350) leaves the model's output offset from the outputs by a
    constant: the tests remove each signal's mean and do not see it, but the prediction-error figures
    (``error_before``, ``error_after``) do, and a step-response model, simulated from rest, starts
    with its response to the offset.  A row is named when the mean of its prediction error exceeds
    :data:`OFFSET_RATIO` times its standard deviation (and is not the rounding of a log without noise).

    An integrating output (a level) has no fixed level: its prediction error's offset is the level the log
    starts at, not a sign of anything, and is not named.  There an undeclared operating point of a column
    that feeds the level makes the model integrate it: the prediction error ramps, which the tests'
    centring does not remove (they may then locate an element of that row that is right).  Such a row is
    named when the change of its prediction error's straight-line fit over the window exceeds
    :data:`OFFSET_RATIO` times the standard deviation about that line.

    Parameters
    ----------
    model : PlantModel
    d : ndarray, shape (n_samples, n_outputs)
        Prediction errors ``y - yhat``, output units.
    y : ndarray, shape (n_samples, n_outputs)
        Outputs (deviations), output units: the scale below which an offset is rounding.
    skip : sequence of str
        Outputs not named (a diverged loop's).
    t : ndarray, shape (n_samples,), optional
        The samples' times, seconds (the ramp's abscissa; default the sample numbers).

    Returns
    -------
    list of str
        At most two warnings.
    """
    mean, std = d.mean(axis=0), d.std(axis=0)
    floor = 1e-6 * np.maximum(y.std(axis=0), np.abs(y).mean(axis=0))
    integrating = model.integrating_outputs
    named = [i for i in range(model.n_outputs) if model.outputs[i] not in skip and abs(mean[i]) > floor[i]
             and abs(mean[i]) > OFFSET_RATIO * std[i] and not integrating[i]]
    out = []
    if named:
        what = ", ".join(f"{model.outputs[i]} by {mean[i]:.4g} (" + ("no spread)" if std[i] <= 1e-12 * abs(mean[i])
                                                                       else f"{abs(mean[i]) / std[i]:.3g} times its "
                                                                       f"spread)") for i in named)
        out.append(f"the model's output is offset from the logged output: {what}; an operating point of the inputs, "
                   f"outputs or measured disturbances that the model file does not declare (input_nominal, "
                   f"output_nominal, disturbance_nominal)? The tests remove the mean, the prediction-error figures do "
                   f"not, and a step-response model starts from rest, with its response to the offset")
    levels = [i for i in range(model.n_outputs) if integrating[i] and model.outputs[i] not in skip]
    if levels and d.shape[0] > 2:
        x = np.arange(d.shape[0], dtype=float) if t is None else np.asarray(t, dtype=float)
        x = x - x.mean()
        sxx = float(x @ x)
        ramps = []
        for i in levels:
            di = d[:, i] - mean[i]
            slope = float(x @ di) / sxx if sxx > 0 else 0.0
            rest = float(np.std(di - slope * x))
            change = abs(slope) * float(x.max() - x.min())
            if change > floor[i] and change > OFFSET_RATIO * rest:
                ramps.append(f"{model.outputs[i]} by {slope:.4g} per {'second' if t is not None else 'sample'} "
                             f"({change:.4g} over the window, " + ("no spread about it)" if rest <= 1e-12 * change
                                                                   else f"{change / rest:.3g} times the spread about "
                                                                        f"it)"))
        if ramps:
            out.append(f"the prediction error of an integrating output ramps: {', '.join(ramps)}; an operating point "
                       f"of the inputs or measured disturbances that feed it that the model file does not declare "
                       f"(input_nominal, disturbance_nominal), which the model integrates, or a gain error of its "
                       f"integrating elements? The tests remove the mean, not a ramp: an element of that row may be "
                       f"located because of it")
    return out


def _noise_order(model: PlantModel, options: AnalysisOptions, white: dict) -> dict:
    """The report's ``noise_order`` from the element test's whiteness (row -> Ljung-Box p-value)."""
    from .noise_order import coloured_rows

    return {"na": options.na, "requested": options.na, "max_na": options.max_na,
            "coloured": [model.outputs[i] for i in coloured_rows(white)],
            "p_values": {model.outputs[i]: float(p) for i, p in white.items()}}


class _ElementColour:
    """The unrestricted element fits of ``rows``, their residuals' whiteness and the report's ``noise_order``
    (:func:`detect_unless_coloured`); the fits and the design go on to the element test when white."""

    def __init__(self, model: PlantModel, rows: list, columns: np.ndarray, layout, regressions,
                 options: AnalysisOptions, spread: np.ndarray):
        from .element_test import InputDesign, unrestricted_fits

        self.design = InputDesign(model, columns, layout.n_lag_u, layout.start, options.collinearity_threshold,
                                  regressions.input_regression)
        self.fits, self.whiteness = unrestricted_fits(rows, self.design, regressions, spread)
        self.noise_order = _noise_order(model, options, self.whiteness)


@dataclasses.dataclass
class Coloured:
    """What :func:`detect_unless_coloured` returns instead of a report: a row's residual is coloured.

    Attributes
    ----------
    noise_order : dict
        As :attr:`AnalysisReport.noise_order` (``coloured`` not empty).
    signals : LoopSignals
        The model run of the data (on the samples used, as :attr:`AnalysisReport.signals`).
    gaps : dict or None
        As :attr:`AnalysisReport.gaps`.
    """

    noise_order: dict
    signals: LoopSignals
    gaps: Optional[dict]


def detect_unless_coloured(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
                           signals: Optional[LoopSignals] = None, regressions=None,
                           previous: Optional["AnalysisReport"] = None, candidates=None, detectability: bool = True,
                           settle: bool = True, beside: Optional[Callable[[LoopSignals], None]] = None):
    """:func:`detect`, or only the noise order when a row's element-test residual is coloured.

    The element test's unrestricted fits of every row it tests come first (for ``test_all_rows``, before
    the row test); when a row's residual is coloured (:mod:`mpm_monitor.core.noise_order`) the tests
    are not run and a :class:`Coloured` is returned: :func:`~mpm_monitor.core.pipeline.analyze` would
    discard that detection for one with a larger ``na``.  Otherwise the detection goes on with those
    fits: the report is :func:`detect`'s, the same numbers.  Arguments as :func:`detect`; a method
    other than ``arx`` (no noise order) always detects.

    Returns
    -------
    AnalysisReport or Coloured
    """
    return _guarded(model, data, options, signals, regressions, previous, candidates, detectability,
                    unless_coloured=True, settle=settle, beside=beside)


def check_gap_rows(plan, layout, options, src: str, model: PlantModel, notes=()) -> None:
    """Refuse data with gaps whose segments give fewer regression rows than the tests need.

    The tests need ``layout.min_samples`` samples of one contiguous span, that is
    ``min_samples - start`` regression rows; data with gaps must give as many rows from its segments.
    ``model`` names the delay that sets ``max_delay`` (:func:`longest_delay_note`); ``notes`` (the data's: rows
    the reader left out for bad values or spikes, which made gaps too) end the refusal.

    Raises
    ------
    DataFileError
        Naming the rows kept, the segments and the gaps.
    """
    need = layout.min_samples - layout.start
    if plan.rows_kept >= need:
        return
    n_seg, n_gaps = len(plan.segments), plan.gap_lengths.size

    def enough(least) -> bool:     # whether the rows would do for the tests at their least lags
        return plan.rows_kept >= least.min_samples - least.start
    raise TooFewSamples(f"{src}: {plan.rows_kept} regression rows from {len(plan.used)} of {n_seg} spans between "
                        f"{n_gaps} gap{'s' if n_gaps != 1 else ''} ({plan.samples_missing} samples missing; a span "
                        f"gives rows after its first {layout.start} samples); the tests with na={options.na}, "
                        f"nb={options.nb}, max_delay={layout.max_delay} need at least {need} rows (is the sample "
                        f"time right?)" + time_unit_note(plan, model.sample_time)
                        + longest_delay_note(model, options, layout, enough) + "".join(f"; {x}" for x in notes))


#: Units a log's time column is often written in, and their seconds (:func:`time_unit_note`).
TIME_UNITS = (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9))


def time_unit_note(plan, sample_time: float) -> str:
    """``"; t advances by ..."`` when most rows of the data are followed by a gap: the time column is then
    likely in other units than seconds (a ROS stamp in nanoseconds: every row 1e9 sample times after the
    last), or the model's sample time is wrong; the unit is named when the step is 1e3, 1e6 or 1e9 sample
    times to 1 %.  ``""`` otherwise."""
    n_rows = sum(b - a for a, b in plan.segments)
    if plan.gap_lengths.size < max(10, n_rows // 2):
        return ""
    step = float(np.median(plan.gap_lengths)) + 1.0          # sample times from one row to the next
    unit = next((name for name, seconds in TIME_UNITS if abs(step * seconds - 1.0) < 0.01), None)
    return (f"; t advances by a median of {step * sample_time:.6g} from one row to the next, {step:.6g} times the "
            f"model's sample_time of {sample_time:g} s" + (f": t in {unit}?" if unit else ""))
