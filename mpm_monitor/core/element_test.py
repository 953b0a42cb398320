"""The Delta element test: which elements of the model ``Phat`` no longer match the plant.

With ``d = y - Phat u`` the prediction error and ``Delta = P - Phat`` ("A Novel Algorithm for
Model-Plant Mismatch Detection for Model Predictive Controllers")::

    d = Delta u + v                                                (paper eq. 9)

Here ``u`` holds the model's columns: the manipulated inputs, then the measured disturbances (the
feedforward variables), whose elements are tested exactly like the inputs' and reported with the
role ``"disturbance"``.  For every row (the paper: every row the S_Delta test flags,
:mod:`mpm_monitor.core.row_test`), the ARX ``A(q) d_i = sum_j B_ij(q) u_j + e`` (paper eq. 10) with
B polynomials covering every lag from 1 to ``max_delay + nb`` (so no delay needs to be known in
advance); element ``(i, j)`` is located when its first B coefficients (where a mismatch of an element
the model has must start and its response sets in, :func:`element_window`; all of them for an
element the model lacks and for a measured disturbance's) are rejected as zero by their F (Wald) test, or, for an
element the model has, its whole modelled response (with, for an integrating element, its time-constant sensitivity) explains part of ``d_i``
(:mod:`mpm_monitor.core.response_test`; the two p-values combined by Bonferroni), with Holm's procedure across
every element tested at level ``alpha / N_FAMILIES`` (:mod:`mpm_monitor.core.statistics`); in a
row with two or more located elements each is confirmed with the others' whole tails
(:func:`_confirm_with_tails`).

An integrating output keeps the test valid: under "no mismatch" ``d`` stays stationary (the model
integrates like the plant, and the centring of every signal removes the arbitrary level); an error
of an integrator's gain makes ``d`` drift, and the root ``q = 1`` it needs is carried by ``A(q)``
(see :mod:`mpm_monitor.core.signals`, "Integrating outputs").

Columns that move together (the closed loop drives them collinearly, a feedforward makes an input
follow a disturbance) cannot be told apart: the lag blocks of the columns are checked for
collinearity once per window (:class:`InputDesign`), and the elements of columns that cannot be
separated are reported as ambiguous with their group
(:func:`~mpm_monitor.core.input_design.group_inputs`), never guessed.

The baselines of :mod:`mpm_monitor.core.baselines` (cross-correlation, partial correlation) give
their element decisions in the same form (:func:`baseline_element_test`).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .arx import BlockTest, estimate_delay_from_lags, segment_lag_matrix, segment_rows
from .baselines import ELEMENT_TESTS
from .confirmation import _confirm_given_responses, _confirm_with_tails
from .element_windows import element_window
from .input_design import InputDesign, _columns_word
from .model import PlantModel
from .noise_order import residual_whiteness
from .noise_polynomial import RowNoise, row_noise, undetermined_noise_warnings
from .parallel import split_map
from .response_test import combined_p_value, given_other_responses, row_response_regressors
from .segments import centred_fill
from .statistics import N_FAMILIES, holm_adjust


@dataclasses.dataclass
class ElementResult:
    """Delta element test of one (output, column) pair.

    Attributes
    ----------
    output : str
    input : str
        The column: an input, or a measured disturbance (see ``role``).
    mismatch : bool
        Located as mismatched.
    p_value : float or None
        Holm-adjusted p-value of ``B_ij = 0`` (None when not testable).
    p_value_raw : float or None
        Unadjusted p-value of the element: ``2 min(p_value_window, p_value_response)`` when both
        tests ran (:func:`~mpm_monitor.core.response_test.combined_p_value`), else the window's.
    statistic : float or None
        F statistic of the lag-window test.
    kind : str or None
        ``gain``, ``time_constant``, ``delay``, ``missing``, ``mixed``, ``unknown`` (located
        elements) or None.
    ambiguous : bool
        The input cannot be told apart from others in ``ambiguous_with``.
    ambiguous_with : tuple of str
    delay : int or None
        Estimated dead time of ``Delta_ij`` in samples.
    b : list of float
        ARX ``B_ij`` coefficients at that delay (``nb`` values).
    role : str
        ``"input"`` (a manipulated input) or ``"disturbance"`` (a measured disturbance).
    detectable_gain_change : float or None
        Smallest relative gain error of the element this window detects with probability 0.9
        (:mod:`mpm_monitor.core.detectability`); None where it cannot be computed.
    p_value_window : float or None
        Unadjusted p-value of the lag-window test (the F test of the block's first lags).
    p_value_response : float or None
        Unadjusted p-value of the whole-response test (:mod:`mpm_monitor.core.response_test`); None
        for an element the model does not have, or with ``element_response`` off.
    explained_by : tuple of str
        The element test flagged this element, but re-estimated jointly with the located elements
        of its row named here it does not differ from the model: they explain the row's mismatch
        and it is not located (``mismatch`` false; option ``release_explained``,
        :func:`mpm_monitor.core.repair.explained_elements`).  Empty otherwise.
    unlocated_at_na : int or None
        The element test located this element in a row the S_Delta row test does not flag, and with this
        many own lags (the analysis's ``max_na``) it does not confirm it (neither located there nor below
        ``alpha`` under Holm's procedure over the elements so checked): a disturbance's colour that the
        inputs' lags took up, and it is not located (``mismatch`` false; option ``release_quiet_rows``,
        :func:`mpm_monitor.core.pipeline.analyze`).  None otherwise.
    """

    output: str
    input: str
    mismatch: bool
    p_value: Optional[float]
    p_value_raw: Optional[float]
    statistic: Optional[float]
    kind: Optional[str] = None
    ambiguous: bool = False
    ambiguous_with: tuple = ()
    delay: Optional[int] = None
    b: list = dataclasses.field(default_factory=list)
    role: str = "input"
    detectable_gain_change: Optional[float] = None
    p_value_window: Optional[float] = None
    p_value_response: Optional[float] = None
    explained_by: tuple = ()
    unlocated_at_na: Optional[int] = None


@dataclasses.dataclass
class RowArxTable:
    """The paper's ARX table of a flagged row (Tables 1 to 5): A, each B with its delay, fit."""

    output: str
    a: list
    b: dict
    delay: dict
    fit_percent: float


@dataclasses.dataclass(frozen=True)
class GroupHit:
    """Inputs that cannot be told apart but jointly explain part of a row's prediction error.

    Attributes
    ----------
    output : str
    inputs : tuple of str
        The group (:attr:`InputDesign.groups`).
    p_value : float
        Unadjusted p-value of the joint test that every lag of the group is zero.
    """

    output: str
    inputs: tuple
    p_value: float


@dataclasses.dataclass
class ElementTest:
    """The element decisions of one analysis.

    Attributes
    ----------
    elements : list of ElementResult
        Row by row (the rows tested), input by input.
    arx_tables : list of RowArxTable
        The ARX test only: one per row tested.
    group_hits : list of GroupHit
        The ARX test only.
    warnings : list of str
        What limits the conclusions (the groups that explain a row; the baselines' warnings).
    noise : dict
        The ARX test only: output index -> :class:`RowNoise` of its fit (for the detectability,
        :mod:`mpm_monitor.core.detectability`).
    responses : dict
        The ARX test with ``element_response`` only: ``(i, j)`` ->
        :class:`~mpm_monitor.core.response_test.ResponseTest` of every element whose whole response
        was tested (for the detectability).
    whiteness : dict
        The ARX test only: output index -> Ljung-Box p-value of the residual of its unrestricted fit
        (:func:`~mpm_monitor.core.noise_order.residual_whiteness`; a row whose fit is exact has none).
    """

    elements: list
    arx_tables: list = dataclasses.field(default_factory=list)
    group_hits: list = dataclasses.field(default_factory=list)
    warnings: list = dataclasses.field(default_factory=list)
    noise: dict = dataclasses.field(default_factory=dict)
    responses: dict = dataclasses.field(default_factory=dict)
    whiteness: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class _Estimate:
    """One element's tests and its ``B_ij`` at the estimated delay."""

    test: BlockTest
    delay: int
    b: list
    response: Optional[BlockTest] = None
    #: Its unadjusted p-value with the row's other elements' whole responses free
    #: (:func:`~mpm_monitor.core.response_test.given_other_responses`); None where not computed.
    given_responses: Optional[float] = None

    @property
    def p_value(self) -> float:
        """The element's unadjusted p-value (:func:`~mpm_monitor.core.response_test.combined_p_value`)."""
        return combined_p_value(self.test.p_value, None if self.response is None else self.response.p_value)


@dataclasses.dataclass
class _RowPart:
    """What :func:`arx_element_test` keeps of one row: its noise, element estimates, group hits and
    table; the fit's blocks and own coefficients for the residual's whiteness (None when exact); the
    row's moments the whole-response test computed (None when it computed none)."""

    i: int
    noise: RowNoise
    estimates: dict
    group_hits: list
    table: RowArxTable
    blocks: Optional[np.ndarray]
    own: Optional[np.ndarray]
    moments: object


def arx_element_test(model: PlantModel, rows: list, design: InputDesign, regressions, options,
                     moments=None, output_spread: Optional[np.ndarray] = None, fits: Optional[dict] = None,
                     whiteness: Optional[dict] = None, meanwhile=None) -> ElementTest:
    """The Delta element test on the rows ``rows`` (see the module docstring).

    Parameters
    ----------
    model : PlantModel
    rows : list of int
        Outputs tested.
    design : InputDesign
        The window's input lag blocks.
    regressions : QrRegressions or GramRegressions
        The window's least-squares problems (``element_fit``, ``short_arx``).
    options : AnalysisOptions
        Its ``nb``, ``alpha``, ``element_window`` and ``jobs`` (with 2, a forked child process tests
        part of the rows: :func:`~mpm_monitor.core.parallel.split_map`, the same numbers).
    moments : ResponseMoments, optional
        The window's element responses and their moments with the input lags
        (:class:`~mpm_monitor.core.response_moments.ResponseMoments`, of the same columns, prediction
        errors and segments as ``regressions``), shared with the detectability: the whole-response
        tests take their regressors and products from them.
    output_spread : ndarray, shape (n_outputs,), optional
        Standard deviation of every output over the window, output units: a row's fit that leaves at
        most :data:`~mpm_monitor.core.statistics.EXACT_FIT` of it is exact (a log without noise), and
        its tests are decided outright (:meth:`~mpm_monitor.core.arx.SharedFit.set_output_spread`).
        Default: only a residual of exactly 0.
    fits, whiteness : dict, optional
        The unrestricted fits of ``rows`` and their residuals' whiteness, already taken by
        :func:`unrestricted_fits` with the same arguments (default: taken here); each fit is taken out
        of ``fits`` as its row is tested.
    meanwhile : callable, optional
        Other work of the caller (the row test) done in this process while a child process with
        ``options.jobs`` > 1 starts on the rows (:func:`~mpm_monitor.core.parallel.split_map`); with one
        process, done first.

    Returns
    -------
    ElementTest
        With the paper's ARX table of every row tested and the groups that explain a row.
    """
    nb, alpha = options.nb, options.alpha
    nu = model.n_columns
    names = model.columns
    testable, group_of = design.testable, design.group_of
    estimates, tables, group_hits, noise = {}, [], [], {}
    row_blocks, own = {}, {}
    whole = _WholeResponses(model, design, regressions, options, moments) if options.element_response else None
    confirm = getattr(options, "confirm_responses", False)

    def one_row(i: int) -> _RowPart:
        """Row ``i``'s fit, tests and table: everything the rows' loop keeps of it (a child process
        computes part of the rows with ``options.jobs`` > 1, :func:`~mpm_monitor.core.parallel.split_map`)."""
        blocks_i, own_i = {}, {}      # the caller's dicts are filled in the order of the rows, below
        fit = fits.pop(i) if fits is not None else _unrestricted_fit(design, regressions, i, output_spread,
                                                                     blocks_i, own_i)
        windows = [element_window(model, i, j, nb, options.element_window) for j in testable]
        tests = fit.test_each_block_zero(windows)
        noise_i = row_noise(fit)
        responses, reg = whole.tests(i, fit, noise_i.a) if whole is not None else ({}, None)
        stds = fit.block_stds()
        row_estimates, hits = {}, []
        for bj, j in enumerate(testable):
            coef = fit.block_theta(bj)
            lag0 = estimate_delay_from_lags(coef, stds[bj], nb, first_lag=1)
            est = _Estimate(tests[bj], lag0, coef[lag0 - 1:lag0 - 1 + nb].tolist(), responses.get(j))
            if confirm and reg is not None and names[j] not in group_of and N_FAMILIES * est.p_value < alpha:
                # Only an element that can be located (Holm's factor is at least 1) needs it.
                est = dataclasses.replace(est, given_responses=given_other_responses(
                    fit, reg, j, fit.block_index(bj, windows[bj]), fit.block_index(bj)))
            row_estimates[(i, j)] = est
        for g in design.groups:
            blocks = [testable.index(names.index(x)) for x in g]
            jt = fit.test_blocks_zero(blocks)
            if np.isfinite(jt.p_value) and \
                    N_FAMILIES * jt.p_value * max(len(rows) * len(design.groups), 1) < alpha:
                hits.append(GroupHit(model.outputs[i], g, jt.p_value))
        # The paper's table (Tables 1 to 5): a short ARX at the estimated delays, for reporting.
        nk = np.array([row_estimates[(i, j)].delay if (i, j) in row_estimates else 1 for j in range(nu)])
        short = regressions.short_arx(i, nk)
        table = RowArxTable(output=model.outputs[i], a=short.a.tolist(),
                            b={names[j]: short.b[j].tolist() for j in range(nu)},
                            delay={names[j]: int(nk[j]) for j in range(nu)}, fit_percent=short.fit_percent)
        return _RowPart(i, noise_i, row_estimates, hits, table, blocks_i.get(i), own_i.get(i),
                        None if whole is None or whole.moments is None else whole.moments.kept(i))

    for part in split_map(one_row, rows, getattr(options, "jobs", 1), meanwhile=meanwhile):
        i = part.i
        noise[i] = part.noise
        estimates.update(part.estimates)
        group_hits.extend(part.group_hits)
        tables.append(part.table)
        if part.blocks is not None:         # what the row's fit left for the residual's whiteness
            row_blocks[i], own[i] = part.blocks, part.own
        if part.moments is not None:
            whole.moments.keep(part.moments)
        if fits is not None:
            fits.pop(i, None)
    keys = [k for k in estimates if names[k[1]] not in group_of]
    adj = dict(zip(keys, holm_adjust(np.array([estimates[k].p_value for k in keys])))) if keys else {}
    elements = []
    for i in rows:
        for j in range(nu):
            name, out, role = names[j], model.outputs[i], model.role(j)
            if (i, j) not in estimates:   # the column never moves
                elements.append(ElementResult(output=out, input=name, mismatch=False, p_value=None,
                                              p_value_raw=None, statistic=None, ambiguous=True, role=role))
                continue
            est = estimates[(i, j)]
            t = est.test
            p_resp = None if est.response is None else est.response.p_value
            if name in group_of:
                elements.append(ElementResult(
                    output=out, input=name, mismatch=False, p_value=None, p_value_raw=est.p_value,
                    statistic=t.statistic, ambiguous=True,
                    ambiguous_with=tuple(x for x in group_of[name] if x != name), delay=int(est.delay), b=est.b,
                    role=role, p_value_window=t.p_value, p_value_response=p_resp))
                continue
            p = min(1.0, N_FAMILIES * adj[(i, j)])
            elements.append(ElementResult(
                output=out, input=name, mismatch=bool(np.isfinite(p) and p < alpha),
                p_value=float(p) if np.isfinite(p) else 1.0, p_value_raw=est.p_value, statistic=t.statistic,
                delay=int(est.delay), b=est.b, role=role, p_value_window=t.p_value, p_value_response=p_resp))
    explained = _confirm_given_responses(model, estimates, keys, elements, alpha) if confirm else []
    kept = _confirm_with_tails(model, rows, design, regressions, options, estimates, keys, elements, output_spread)
    warnings = explained \
        + [_group_hit_warning(model, h) for h in group_hits] \
        + kept + undetermined_noise_warnings(model, noise)
    responses = {k: e.response for k, e in estimates.items() if e.response is not None}
    if whiteness is None:
        whiteness = residual_whiteness(regressions, testable, design.n_lag, row_blocks, own)
    return ElementTest(elements=elements, arx_tables=tables, group_hits=group_hits, warnings=warnings, noise=noise,
                       responses=responses, whiteness=whiteness)


def _unrestricted_fit(design: InputDesign, regressions, i: int, output_spread, row_blocks: dict, own: dict):
    """Row ``i``'s fit on every testable column's lags and its own lags; a fit that is not exact puts
    its column blocks (shape (n_testable, n_lag)) in ``row_blocks[i]`` and its own coefficients in
    ``own[i]``, for :func:`~mpm_monitor.core.noise_order.residual_whiteness`."""
    fit = regressions.element_fit(design.regression, i)
    if output_spread is not None:
        fit.set_output_spread(output_spread[i])
    if not fit.exact:
        row_blocks[i] = np.array([fit.block_theta(bj) for bj in range(len(design.testable))]).reshape(
            len(design.testable), design.n_lag)
        own[i] = np.asarray(fit.theta[fit.n_common:], dtype=float)
    return fit


def unrestricted_fits(rows: list, design: InputDesign, regressions, output_spread: Optional[np.ndarray] = None) -> tuple:
    """The unrestricted fits of :func:`arx_element_test` on ``rows`` and their residuals' whiteness, without
    the tests (arguments as there).

    Returns
    -------
    (dict, dict)
        Row -> its fit, and row -> the Ljung-Box p-value of its residual
        (:func:`~mpm_monitor.core.noise_order.residual_whiteness`; none for a row whose fit is exact):
        the ``fits`` and ``whiteness`` :func:`arx_element_test` takes to run its tests on them.  A fit
        is small until its tests assemble its inverse factor (about 8 MB for 40 inputs of 23 lags):
        :func:`arx_element_test` takes each out of ``fits`` as it tests its row, so only one is whole
        at a time.
    """
    fits, row_blocks, own = {}, {}, {}
    for i in rows:
        fits[i] = _unrestricted_fit(design, regressions, i, output_spread, row_blocks, own)
    return fits, residual_whiteness(regressions, design.testable, design.n_lag, row_blocks, own)


class _WholeResponses:
    """The whole-response tests of the rows of one element test (:mod:`mpm_monitor.core.response_test`).

    Holds the window's centred columns and prediction errors and the input lag blocks, built once; or
    the window's shared :class:`~mpm_monitor.core.response_moments.ResponseMoments`, when they are of
    the same columns, segments and lags, from which the tests take their regressors and products.
    """

    def __init__(self, model: PlantModel, design: InputDesign, regressions, options, moments=None):
        self.model, self.design = model, design
        self.na = options.na
        self.start = regressions.layout.start
        self.segments = getattr(regressions, "segments", None)
        u = np.asarray(regressions.u, dtype=float)
        usable = moments is not None and moments.of(u, self.segments) and moments.n_lag == design.n_lag \
            and moments.start == self.start and moments.na == self.na
        self.moments = moments if usable else None
        d = np.asarray(regressions.d, dtype=float)
        self.u_c = u - u.mean(axis=0)
        self.d_c = d - d.mean(axis=0)
        # The columns of the samples inside the gaps that are known (a segment left out, a spike), centred alike:
        # an element's response runs on them, as the model does.
        self.segments = centred_fill(self.segments, u.mean(axis=0))
        self._common = getattr(design.regression, "common", None)

    @property
    def common(self) -> np.ndarray:
        """The lag blocks of the testable columns, shape (n_rows, n_lag * n_testable)."""
        if self._common is None:
            testable, n_lag = self.design.testable, self.design.n_lag
            self._common = segment_lag_matrix(self.u_c[:, testable], range(1, n_lag + 1), self.start, self.segments) \
                if testable else np.zeros((segment_rows(self.d_c, self.start, self.segments).shape[0], 0))
        return self._common

    def tests(self, i: int, fit, a: np.ndarray) -> tuple:
        """Column -> whole-response :class:`~mpm_monitor.core.arx.BlockTest` of row ``i`` (element fit ``fit``,
        noise polynomial ``a``: :func:`~mpm_monitor.core.noise_polynomial.noise_filter`), and the row's
        :class:`~mpm_monitor.core.response_test.RowRegressors` (None when no element has a response)."""
        testable = self.design.testable
        if not any(self.model.present[i, j] for j in testable):
            return {}, None
        sizes = [self.design.n_lag] * len(testable)
        if self.moments is None:
            reg = row_response_regressors(self.model, i, fit, testable, self.common, sizes, self.u_c, self.d_c,
                                          self.start, self.na, self.segments, a=a)
        else:
            try:
                reg = row_response_regressors(self.model, i, fit, testable, None, sizes, self.u_c, self.d_c,
                                              self.start, self.na, self.segments, a=a, moments=self.moments)
            finally:
                self.moments.release(i)
        return ({}, None) if reg is None else (reg.tests(fit), reg)


def baseline_element_test(model: PlantModel, u: np.ndarray, d: np.ndarray, options) -> ElementTest:
    """Element decisions of a baseline method (``options.method``: ``xcorr`` or ``pcorr``) on every row.

    The baseline runs at level ``alpha / N_FAMILIES``, as the ARX element test; its adjusted
    p-values are reported times ``N_FAMILIES``.  The measured disturbances are columns like the
    inputs.

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
        The model's columns: inputs, then measured disturbances.
    d : ndarray, shape (n_samples, n_outputs)
        Prediction error ``y - Phat u``.
    options : AnalysisOptions
        Its ``method`` and ``alpha``.

    Returns
    -------
    ElementTest
        ``elements`` for every (output, column) pair and the baseline's ``warnings``.
    """
    res = ELEMENT_TESTS[options.method](d, u, alpha=options.alpha / N_FAMILIES)
    adjusted = N_FAMILIES * (res.adjusted_p_values if res.adjusted_p_values is not None else res.p_values)
    elements = []
    for i in range(model.n_outputs):
        for j in range(model.n_columns):
            amb = bool(res.ambiguous[i, j]) if res.ambiguous is not None else False
            p_raw, p_adj = float(res.p_values[i, j]), float(adjusted[i, j])
            elements.append(ElementResult(output=model.outputs[i], input=model.columns[j], role=model.role(j),
                                          mismatch=bool(res.mismatch[i, j]) and not amb,
                                          p_value=None if amb or not np.isfinite(p_adj) else p_adj,
                                          p_value_raw=p_raw if np.isfinite(p_raw) else None,
                                          statistic=float(res.statistic[i, j]), ambiguous=amb))
    return ElementTest(elements=elements, warnings=list(res.warnings or []))


def _group_hit_warning(model: PlantModel, h: "GroupHit") -> str:
    """The warning of a group of columns that explains part of a row's prediction error (:class:`GroupHit`); a group
    of one column (it moves with a combination of the other columns' lags) is said as such."""
    if len(h.inputs) == 1:
        return (f"row {h.output}: {_columns_word(model, h.inputs)[:-1]} {h.inputs[0]} explains part of its prediction "
                f"error (p={h.p_value:.2g}) but moves with a combination of the other columns: it cannot be told apart "
                f"from them in these data")
    return (f"row {h.output}: {_columns_word(model, h.inputs)} {', '.join(h.inputs)} jointly explain part of its "
            f"prediction error (p={h.p_value:.2g}) but cannot be told apart from these data")
