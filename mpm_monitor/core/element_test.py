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
separated are reported as ambiguous with their group (:func:`group_inputs`), never guessed.

The baselines of :mod:`mpm_monitor.core.baselines` (cross-correlation, partial correlation) give
their element decisions in the same form (:func:`baseline_element_test`).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .arx import BlockTest, SharedBlockRegression, estimate_delay_from_lags, lag_matrix, segment_lag_matrix, segment_rows
from .baselines import ELEMENT_TESTS
from .elements import pulse_response
from .logged_data import moving_columns
from .model import PlantModel
from .noise_order import residual_whiteness
from .parallel import split_map
from .response_test import (combined_p_value, element_responses, given_other_responses, integrating_element,
                            row_response_regressors, row_response_tests)
from .segments import run_lag_matrix, run_positions, segment_labels
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


@dataclasses.dataclass(frozen=True)
class RowNoise:
    """What the element test of one row estimated about its noise.

    Attributes
    ----------
    sigma2 : float
        Residual (equation-error) variance of the row's ARX, output units squared.
    dof : int
        Its residual degrees of freedom.
    a : ndarray, shape (na,)
        ``a_1 .. a_na`` of the row's noise polynomial ``A(q) = 1 + a_1 q^-1 + ... + a_na q^-na``
        (:func:`noise_filter`): the ARX's own coefficients, or, where the window leaves them
        undetermined, those of the prediction error's own lags alone.
    exact : bool
        The fit is exact (:attr:`~mpm_monitor.core.arx.SharedFit.exact`): its residual is rounding, not
        noise (a log without noise).
    undetermined : float or None
        The largest standard error of the ARX's own coefficients where it exceeds
        :data:`MAX_NOISE_FILTER_SE` (``a`` then comes from the own lags alone); None otherwise.
    """

    sigma2: float
    dof: int
    a: np.ndarray
    exact: bool = False
    undetermined: Optional[float] = None


#: Largest standard error of the element fit's own coefficients ``a_k`` (dimensionless filter taps) for
#: which they are the row's noise polynomial.  In a loop whose inputs move only with the controller's
#: feedback (no setpoint move, no dither) the input lags and the own lags can be nearly collinear (the
#: controller's law ties them; in a square loop always): the fit then splits the prediction error between
#: them arbitrarily, and its ``a_k`` come out as 1e4 to 1e11 with standard errors as large, where 0.02 to
#: 0.1 is usual.  Such an ``A(q)`` is no noise model: filtering an element's response by it made the
#: whole-response test's regressor meaningless and the detectable gain changes
#: (:mod:`mpm_monitor.core.detectability`) 1e-5 where 30 % went unseen.  Over the 194 rows of 40 such
#: loops of the Monte-Carlo's plants (``bench.scenarios``, setpoints held, no dither) the largest standard
#: error was either below 3.4 or above 2.8e4; over 118 rows of excited loops with noise, below 0.03.  A mismatched
#: row of a log without noise exceeds it too: its prediction error is then an exact function of the inputs.
MAX_NOISE_FILTER_SE = 1.0


def noise_filter(fit, na: Optional[int] = None) -> tuple:
    """The row's noise polynomial from an element-test fit.

    Parameters
    ----------
    fit : SharedFit or GramFit
        The row's element fit: ``d_i`` on the lag blocks and ``-d_i`` at lags ``1 .. na`` (then any
        further free columns).
    na : int, optional
        Own lags of the polynomial (default: every own column of ``fit``).

    Returns
    -------
    a : ndarray, shape (na,)
        ``a_1 .. a_na`` (dimensionless): the fit's first ``na`` own coefficients, unless their largest
        standard error exceeds :data:`MAX_NOISE_FILTER_SE`; then the first ``na`` coefficients of the fit
        of the prediction error on its own columns alone (under "no mismatch" the prediction error is
        the disturbance, so these whiten it).
    undetermined : float or None
        That largest standard error where it exceeds the bound; None otherwise.
    """
    own = np.array(fit.own_theta(), dtype=float)
    na = own.size if na is None else int(na)
    if not na:
        return own[:0], None
    with np.errstate(invalid="ignore"):
        se = float(np.max(fit.own_standard_errors()[:na]))
    if np.isfinite(se) and se > MAX_NOISE_FILTER_SE:
        return np.array(fit.own_only_theta(), dtype=float)[:na], se
    return own[:na], None


def undetermined_rows(noise: dict) -> list:
    """The rows of ``noise`` (output index -> :class:`RowNoise`), in order, whose noise polynomial came from the
    own lags alone (:func:`noise_filter`): inputs that move only with the controller's feedback, or a
    prediction error without noise."""
    return [i for i in sorted(noise) if getattr(noise[i], "undetermined", None) is not None]


def undetermined_noise_warnings(model: PlantModel, noise: dict) -> list:
    """One warning naming the rows whose noise polynomial came from the own lags alone (:func:`undetermined_rows`)."""
    rows = undetermined_rows(noise)
    if not rows:
        return []
    worst = max(noise[i].undetermined for i in rows)
    return [f"row{'s' if len(rows) > 1 else ''} {', '.join(model.outputs[i] for i in rows)}: the input lags and the "
            f"prediction error's own lags are nearly collinear here (the element fit's noise polynomial has standard "
            f"errors up to {worst:.2g}: inputs that move only with the controller's feedback, or a prediction error "
            f"without noise), so these data give no noise model of {'these rows' if len(rows) > 1 else 'the row'}: no "
            f"detectable gain change is computed for {'their' if len(rows) > 1 else 'its'} elements "
            "(detectable_gain_change null), and the whole-response test filters by the noise polynomial of the "
            "prediction error alone"]


def row_noise(fit) -> RowNoise:
    """The :class:`RowNoise` of an element-test fit (``sigma2``, ``dof``, its noise polynomial
    :func:`noise_filter`, ``exact``)."""
    a, undetermined = noise_filter(fit)
    return RowNoise(sigma2=float(fit.sigma2), dof=int(fit.dof), a=a, exact=bool(fit.exact), undetermined=undetermined)


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


class InputDesign:
    """The lagged-column regressors of the Delta test, factored once and checked for collinearity.

    The columns are the model's inputs, then its measured disturbances; "input" below means any of
    them (:attr:`~mpm_monitor.core.model.PlantModel.columns`).

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
    n_lag : int
        Lags ``1 .. n_lag`` of every column.
    start : int
        First sample used.
    threshold : float
        An input is not separable when the largest generalised variance-inflation factor of its
        lag block, ``1 / (1 - rho_max^2)`` with ``rho_max`` its largest canonical correlation with
        the lag blocks of the other inputs, exceeds ``1 / threshold``.
    regression : callable, optional
        ``regression(testable)`` returns the :class:`~mpm_monitor.core.arx.SharedBlockRegression` of
        the lags of the inputs ``testable`` (default: built here as
        :meth:`~mpm_monitor.core.regressions.QrRegressions.input_regression` builds it).

    Attributes
    ----------
    testable : list of int
        Inputs that move.
    constant : list of str
        Inputs that never move.
    vif : dict
        Input name -> largest variance-inflation factor of its lag block.
    max_vif : float
        The largest of them (1 when no input moves).
    groups : list of tuple of str
        Inputs that cannot be told apart, grouped (:func:`group_inputs`).
    group_of : dict
        Input name -> its group, for the inputs in a group.
    regression : SharedBlockRegression
        The factored lag blocks of the inputs ``testable``.
    """

    def __init__(self, model, u, n_lag, start, threshold, regression=None):
        self.n_lag = n_lag
        moves = moving_columns(u)        # a column that moves relative to its own size, in any units
        names = model.columns
        self._disturbances = set(model.disturbances)
        self.testable = [j for j in range(model.n_columns) if moves[j]]
        self.constant = [names[j] for j in range(model.n_columns) if j not in self.testable]
        if regression is None:
            u_c = u - u.mean(axis=0)
            X = lag_matrix(u_c[:, self.testable], range(1, n_lag + 1), start) if self.testable else \
                np.zeros((u.shape[0] - start, 0))
            self.regression = SharedBlockRegression(X, [n_lag] * len(self.testable))
        else:
            self.regression = regression(self.testable)
        self.vif = {}
        R = self.regression.R
        p = R.shape[1]
        if p:
            rinv = self.regression.rinv()             # pseudo-inverse when rank-deficient
            blocks = np.arange(p).reshape(len(self.testable), n_lag)
            r_blocks = np.swapaxes(R.T[blocks], 1, 2)                     # R[:, sl] of every block
            gram = np.swapaxes(r_blocks, 1, 2) @ r_blocks                 # X_j' X_j, scaled columns
            ri = rinv[blocks]
            inv = ri @ np.swapaxes(ri, 1, 2)                              # blocks of (X'X)^-1
            eigenvalues = np.linalg.eigvals(gram @ inv).real
            for b, j in enumerate(self.testable):
                sl = slice(b * n_lag, (b + 1) * n_lag)
                ev = eigenvalues[b]
                vif = float(ev.max()) if np.all(np.isfinite(ev)) else float("inf")
                if not self.regression.full_rank:
                    # A dependent lag block makes (X'X) singular: the pseudo-inverse hides it.
                    sub = R[:, [c for c in range(p) if c < sl.start or c >= sl.stop]]
                    if np.linalg.matrix_rank(np.hstack([sub, R[:, sl]])) < np.linalg.matrix_rank(sub) + n_lag:
                        vif = float("inf")
                self.vif[names[j]] = vif
        bad = [name for name, v in self.vif.items() if not v < 1.0 / threshold]
        self.max_vif = max(self.vif.values(), default=1.0)
        self.groups = group_inputs(u, bad, names, threshold)
        self.group_of = {name: g for g in self.groups for name in g}

    def warnings(self) -> list:
        """What the design limits: inputs that never move, inputs that move together."""
        out = []
        still_u = [c for c in self.constant if c not in self._disturbances]
        still_dv = [c for c in self.constant if c in self._disturbances]
        if still_u:
            out.append(f"inputs {', '.join(still_u)} never move: their elements cannot be tested")
        if still_dv:
            out.append(f"measured disturbances {', '.join(still_dv)} never move: their elements cannot be tested")
        if self.groups:
            grouped = {c for g in self.groups for c in g}
            what = ("measured disturbances " if grouped <= self._disturbances else
                    "inputs and measured disturbances " if grouped & self._disturbances else "inputs ")
            if all(len(g) == 1 for g in self.groups):     # each moves with a combination of the others
                if len(self.groups) == 1:
                    name = self.groups[0][0]
                    kind = "measured disturbance" if name in self._disturbances else "input"
                    head = f"{kind} {name} moves with the other columns "
                else:
                    head = what + ", ".join(g[0] for g in self.groups) + " each move with the other columns "
            else:
                head = what + "; ".join("{" + ", ".join(g) + "}" for g in self.groups) + " move together "
            if grouped <= self._disturbances:      # measured disturbances alone: no dither of the inputs helps
                why = ("the controller does not move them, so their elements cannot be told apart from these data "
                       "and no dither of the inputs separates them: data where they move apart would")
            else:
                why = ("the closed loop drives them collinearly, so their elements cannot be told apart from these "
                       "data; add a small dither on the inputs to separate them")
            out.append(head + f"(largest variance inflation {self.max_vif:.3g}, condition number of the "
                       f"input regressors {self.regression.condition_number:.3g}): " + why)
        return out


def _columns_word(model: PlantModel, names) -> str:
    """``inputs``, ``measured disturbances`` or ``inputs and measured disturbances``: what the columns ``names`` are."""
    index = {c: j for j, c in enumerate(model.columns)}
    roles = {model.role(index[n]) if n in index else "input" for n in names}
    return {frozenset({"input"}): "inputs", frozenset({"disturbance"}): "measured disturbances"}.get(
        frozenset(roles), "inputs and measured disturbances")


def group_inputs(u: np.ndarray, bad: list, names, threshold: float) -> list:
    """Group the non-separable inputs by the near-null directions of their correlation matrix.

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_columns)
    bad : list of str
        The inputs whose lag block is not separable from the others'.
    names : sequence of str
        Every input's name, in the columns' order.
    threshold : float
        The collinearity threshold of :class:`InputDesign`.

    Returns
    -------
    list of tuple of str
        Inputs joined when they share a direction of small variance of their correlation matrix;
        all of ``bad`` in one group when none is small (the collinearity is only dynamic).
    """
    if not bad:
        return []
    idx = [list(names).index(b) for b in bad]
    z = u[:, idx] - u[:, idx].mean(axis=0)
    z = z / np.maximum(z.std(axis=0), 1e-300)
    w, v = np.linalg.eigh(z.T @ z / z.shape[0])
    parent = list(range(len(idx)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    small = [k for k in range(len(w)) if w[k] < 10 * threshold * max(w.mean(), 1e-300)]
    for k in small:
        members = [m for m in range(len(idx)) if abs(v[m, k]) > 0.1]
        for m in members[1:]:
            parent[find(m)] = find(members[0])
    if not small:  # dynamic collinearity only: the inputs cannot be separated from each other
        for m in range(1, len(idx)):
            parent[find(m)] = find(0)
    groups = {}
    for m in range(len(idx)):
        groups.setdefault(find(m), []).append(bad[m])
    return [tuple(g) for g in groups.values()]


#: An element's response has set in at the first lag where its impulse response reaches this fraction of
#: its largest absolute value (:func:`element_window`).
ONSET_FRACTION = 0.5
#: Samples of an element's impulse response searched for its onset.
ONSET_HORIZON = 1000


def element_window(model: PlantModel, i: int, j: int, nb: int, window: str = "model") -> Optional[int]:
    """Leading column lags the element test of (i, j) tests (None: all of them).

    ``Delta_ij = P_ij - Phat_ij`` is non-zero from lag ``min(theta_plant, theta_model) + 1`` on,
    and a mismatch shows where the element's own response has set in: for an element the model has
    (:attr:`~mpm_monitor.core.model.PlantModel.present`) the test covers its lags up to the onset
    ``k_on`` (the first lag at which the model element's impulse response reaches
    :data:`ONSET_FRACTION` of its largest absolute value) plus ``nb - 1`` more, and at least the first
    ``theta_model + nb``.  For a first-order element with dead time ``theta`` the impulse response
    is largest at lag ``theta + 1``, so the window is the first ``theta + nb`` lags; a second lag, an
    integrator or a lead that builds up slowly moves the onset later (a short window would see
    almost nothing of such an element, and its later lags, left free, would absorb the mismatch).
    The later lags stay in the fit as nuisance (under "no mismatch" every lag is zero, so the test
    keeps its level); fewer tested lags means more power.  Elements the model does not have have no
    known delay, and a measured disturbance's column is typically slow and step-like (its later
    lags would absorb a wrong gain): all lags are tested for them, as with ``window="full"``.
    """
    if window == "full" or not model.present[i, j] or model.role(j) == "disturbance":
        return None
    return max(int(model.delay_samples[i, j]) + nb, element_onset(model, i, j) + nb - 1)


def element_onset(model: PlantModel, i: int, j: int) -> int:
    """The first lag at which element (i, j)'s impulse response reaches :data:`ONSET_FRACTION` of its peak.

    Kept with the model's sampled elements (:meth:`~mpm_monitor.core.model.PlantModel.discrete_element`),
    so that it is computed once per model and element: every row's element test, its confirmation and
    the detectability ask for it (at 100 outputs x 40 inputs, 8,000 impulse responses of 1,000 samples
    per analysis otherwise).  A copy of the model with the element changed
    (:meth:`~mpm_monitor.core.model.PlantModel.with_element`) computes it again.

    A first-order element ``b z^-(delay+1) / (1 - a z^-1)`` with ``|a| <= 1`` needs no simulation: its
    impulse response is 0 up to lag ``delay``, ``b`` at ``delay + 1`` and then ``a`` times the previous
    value, rounded, which is never larger in magnitude; so its onset is ``delay + 1`` (the value the
    simulation gives, when ``delay + 1`` is inside :data:`ONSET_HORIZON` and the threshold is not 0).
    """
    key = ("onset", i, j)
    cache = model._elements
    if key not in cache:
        el = model.discrete_element(i, j)
        num, den = el.num, el.den
        if num.size == 2 and num[0] == 0 and den.size == 2 and abs(den[1]) <= 1 \
                and el.delay + 1 < ONSET_HORIZON and ONSET_FRACTION * abs(num[1]) > 0:
            cache[key] = el.delay + 1
        else:
            h = np.abs(el.impulse_response(ONSET_HORIZON))
            cache[key] = int(np.flatnonzero(h >= ONSET_FRACTION * h.max())[0]) if h.max() > 0 else 0
    return cache[key]


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
        + [f"row {h.output}: {_columns_word(model, h.inputs)} {', '.join(h.inputs)} jointly explain part of its "
           f"prediction error (p={h.p_value:.2g}) but cannot be told apart from these data" for h in group_hits] \
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
        noise polynomial ``a``: :func:`noise_filter`), and the row's
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


#: The tail regressors of a located column cover this many time constants of the row's slowest pole.
TAIL_TIME_CONSTANTS = 6.0
#: ... and at most this fraction of the regression rows.
TAIL_MAX_FRACTION = 0.1
#: The tails of all the other located columns of a row together: at most this fraction of the rows
#: (binds from four located elements in a row on; :func:`_confirm_with_tails`).
TAIL_TOTAL_FRACTION = 0.25
#: Bytes of the regressors of one confirmation fit (rows x columns x 8) at most: a longer window's fit takes
#: its last rows only.  Its QR holds a few copies of them: about 1 GB at most.
TAIL_FIT_BYTES = 200 * 2 ** 20


def tail_lags(model: PlantModel, i: int, n_lag: int, n_rows: int) -> int:
    """Lags of a located column's block in the confirmation of row ``i`` (:func:`_confirm_with_tails`).

    The row's largest dead time plus :data:`TAIL_TIME_CONSTANTS` time constants of its slowest decaying
    pole (the model's elements), at least ``n_lag`` and at most :data:`TAIL_MAX_FRACTION` of the
    ``n_rows`` regression rows.  A step-response model has no poles: there the row's longest
    :func:`step_response_tail` stands for them.
    """
    from .discretize import discretize

    if model.is_step_response:
        want = max((step_response_tail(model, i, j) for j in np.flatnonzero(model.present[i])), default=0)
        return int(max(n_lag, min(want, int(TAIL_MAX_FRACTION * n_rows))))
    poles = discretize(model).lag_poles(i)
    if not poles:
        return n_lag
    tau = -1.0 / np.log(max(poles))
    want = int(model.delay_samples[i].max(initial=0)) + int(np.ceil(TAIL_TIME_CONSTANTS * tau))
    return int(max(n_lag, min(want, int(TAIL_MAX_FRACTION * n_rows))))


def step_response_tail(model: PlantModel, i: int, j: int) -> int:
    """Samples after which a step-response element's response to a pulse has all but died out.

    The impulse response ``h_l = s_l - s_(l-1)`` of element (``i``, ``j``) (on a ramp row, less its
    final slope ``h_N``: the part that dies out); the first ``l`` after which the remaining
    ``sum |h_k|`` is at most ``exp(-TAIL_TIME_CONSTANTS)`` of the whole, the step-response analogue
    of :data:`TAIL_TIME_CONSTANTS` time constants after the dead time (a first-order element's
    remaining mass after ``delay + m tau`` is ``exp(-m)``).  In samples; 0 for an absent element.
    """
    h = pulse_response(model.step_response[i, j])
    if model.ramp[i] and h.size:
        h = h - h[-1]
    mass = np.abs(h)[::-1].cumsum()[::-1]                  # mass[l]: sum of |h_k| for k >= l (0-based)
    total = float(mass[0]) if mass.size else 0.0
    if not total > 0:
        return 0
    above = np.flatnonzero(mass > np.exp(-TAIL_TIME_CONSTANTS) * total)
    return int(above[-1]) + 1 if above.size else 0


def _holm_factors(estimates: dict, keys: list) -> dict:
    """Element key -> its Holm factor ``m - l + 1`` (``l`` its rank among the unadjusted p-values of ``keys``)."""
    order = np.argsort(np.array([estimates[k].p_value for k in keys]), kind="stable")
    return {keys[o]: len(keys) - rank for rank, o in enumerate(order)}


def _confirm_given_responses(model: PlantModel, estimates: dict, keys: list, elements: list, alpha: float) -> list:
    """Re-test every located element with the whole modelled responses of its row's other elements free.

    Each located element's p-value given those responses
    (:func:`~mpm_monitor.core.response_test.given_other_responses`, computed with its row's tests) is
    adjusted at its Holm step; an element that no longer rejects is not located.  Its ``p_value`` is
    the larger of the two.  ``elements`` is updated in place.

    A slow or integrating element's mismatch outlives its column's lag block, and in closed loop its
    remainder correlates with another column's lags and modelled response: a well-modelled element of
    the same row was located through it, sometimes alone (an integrator's gain error made the row's
    well-modelled integrating disturbance element the only one located in 4 of 8 probe runs).  Most of
    that remainder is the mismatched element's own modelled response, which this test leaves free.
    But the controller also moves the other columns against the element's own mismatch, so their
    responses carry part of it, and true elements are dropped too: the option
    (``AnalysisOptions.confirm_responses``) is off by default.

    Returns
    -------
    list of str
        A warning for each element no longer located.
    """
    names = model.columns
    by_key = {(model.outputs.index(e.output), names.index(e.input)): e for e in elements}
    factor = _holm_factors(estimates, keys)
    warnings = []
    for k in keys:
        e, given = by_key[k], estimates[k].given_responses
        if not e.mismatch or given is None:
            continue
        p = min(1.0, N_FAMILIES * factor[k] * given) if np.isfinite(given) else 1.0
        e.p_value = max(e.p_value, p)
        if not p < alpha:
            e.mismatch = False
            warnings.append(f"row {e.output}: element ({e.output}, {e.input}) is not located: its test rejects "
                            f"(p={N_FAMILIES * factor[k] * estimates[k].p_value:.2g}) but not with the modelled "
                            f"responses of the row's other elements free (p={p:.2g}): another element's mismatch may "
                            f"reach it")
    return warnings


def _confirm_with_tails(model, rows, design, regressions, options, estimates, keys, elements,
                        output_spread=None) -> list:
    """Re-test the located elements of every row with two or more, each given the others' whole tails.

    The ARX of a row holds ``n_lag`` lags of every column.  A located element's ``Delta_ij`` of a slow
    element lasts far longer; in closed loop the part beyond ``n_lag`` correlates with the other
    columns' lags and can make one of them look mismatched too (a time-constant error of a slow
    element made a well-modelled element of the same row "located" at ``p`` ~ 1e-7).  So each located
    element of such a row is tested again with the blocks of the row's other located columns extended
    to :func:`tail_lags` lags (nuisance: under "no mismatch" of the element tested they are free, so
    the test keeps its level), at its Holm step's level; an element that no longer rejects is not
    located (its ``p_value`` is the larger of the two).  ``elements`` is updated in place.  No tail
    carries an integrating element's gain error (its response never dies out), so the responses of
    the other located integrating elements (lags 0 .. na, for any ``A(q)``) are free beside the test too.

    When that drops every located element of the row, the free tails (hundreds of lags each) stand in
    for one another: the row holds a mismatch among these columns, which each column's own test
    showed, but the tails cannot attribute it.  Then the row is confirmed step by step instead: the
    element with the smallest unadjusted p-value is kept, and each next one (in the order of their
    p-values) is tested with the tails of the elements kept so far only, and kept when it rejects.
    Such rows are named in a warning.  Only removes locations of the Holm-adjusted test.

    A window so long that a fit's regressors would exceed :data:`TAIL_FIT_BYTES` is confirmed on its last
    rows only, and a warning says how many.

    Data with gaps: the fit takes the regression rows whose tails stay inside their run of segments
    (:class:`~mpm_monitor.core.segments.GapSegments`: the model runs through a short gap with its columns
    held, and a tail reads them so, :func:`~mpm_monitor.core.segments.run_lag_matrix`), with a free level
    per segment (the prediction error is centred over each segment).  No row's own lags or tested lags
    reach across a gap.

    Returns
    -------
    list of str
        The warnings of the rows confirmed step by step or on their last rows.
    """
    from .arx import SharedBlockRegression

    segments = getattr(regressions, "segments", None)
    nb, alpha, na = options.nb, options.alpha, options.na
    names = model.columns
    by_key = {(model.outputs.index(e.output), names.index(e.input)): e for e in elements}
    factor = _holm_factors(estimates, keys)
    u = np.asarray(regressions.u, dtype=float)
    d = np.asarray(regressions.d, dtype=float)
    n_lag, testable = design.n_lag, design.testable
    start0 = regressions.layout.start
    u_c = u - u.mean(axis=0)
    d_c = d - d.mean(axis=0)
    # With gaps: the regression rows of every segment, and each one's place on its run's sample grid (a tail
    # reads the columns held through the short gaps, as the model runs, segments.run_lag_matrix).
    place = None if segments is None else run_positions(start0, segments)
    n_rows = u.shape[0] - start0 if segments is None else place.size
    stepwise = []
    for i in rows:
        located = [j for j in testable if by_key[(i, j)].mismatch]
        if len(located) < 2:
            continue
        tail = tail_lags(model, i, n_lag, n_rows)
        # Many located columns (a row whose model is wrong throughout): their tails together at most
        # TAIL_TOTAL_FRACTION of the rows, or the fits become as wide as the record (and take minutes).
        budget = int(TAIL_TOTAL_FRACTION * n_rows)
        if (len(located) - 1) * tail > budget:
            tail = max(n_lag, budget // (len(located) - 1))
        if tail <= n_lag:
            continue
        start = max(start0, tail)
        # The rows of the fit: without gaps from sample ``start`` on; with gaps, the regression rows whose tails
        # stay inside their run.
        keep = None if segments is None else place >= tail
        n_fit = u.shape[0] - start if segments is None else int(keep.sum())
        # A long window (days of samples) would make the fit's regressors as long as the record and hundreds of
        # columns wide: gigabytes.  Its last rows stand for it then, as many as TAIL_FIT_BYTES holds.
        width = (len(located) - 1) * tail + (len(testable) - len(located) + 1) * n_lag + na + (na + 1) * len(located)
        most = max(TAIL_FIT_BYTES // (8 * width), 1)
        if n_fit > most:
            stepwise.append(f"row {model.outputs[i]}: the confirmation of its located elements with the others' slow "
                            f"tails used the last {most} of its {n_fit} regression rows (its regressors "
                            f"{width} columns wide held within {TAIL_FIT_BYTES // 2 ** 20} MB)")
            if segments is None:
                start = u.shape[0] - most
            else:
                keep[:np.flatnonzero(keep)[-most]] = False
        if keep is not None and not keep.any():
            continue
        di = d[:, i] - d[:, i].mean()
        # An integrating element's gain error never dies out: no tail carries it, its response does.
        responses = element_responses(model, i, [k for k in located if integrating_element(model, i, k)], u_c,
                                      segments)
        levels = None
        if segments is None:
            def lagged(x, lags):
                return lag_matrix(x, lags, start)
            target = di[start:]
        else:
            def lagged(x, lags):
                return run_lag_matrix(x, lags, start0, segments)[keep]
            target = segment_rows(di, start0, segments)[keep]
            # d is centred over each segment (its level moves across a gap): a free level per segment here too,
            # or the tails' own levels, which d no longer has, would stay in the fit's residual.
            labels = segment_labels(start0, segments)[keep]
            levels = (labels[:, None] == np.unique(labels)[None, :]).astype(float)
        own = -lagged(di, range(1, na + 1)) if na else None
        response_lags = {k: lagged(x, range(na + 1)) for k, x in responses.items()}

        def confirmed(j, given):
            """Holm-adjusted p-value of element (i, j) with the tails of the columns ``given``."""
            sizes = [tail if (k in given and k != j) else n_lag for k in testable]
            X = np.hstack([lagged(u_c[:, k], range(1, size + 1)) for k, size in zip(testable, sizes)])
            free = [response_lags[k] for k in given if k != j and k in response_lags] \
                + ([] if levels is None else [levels])
            extra = np.hstack(free) if free else None
            nuisance = [m for m in (own, extra) if m is not None]
            fit = SharedBlockRegression(X, sizes).fit(target, np.hstack(nuisance) if nuisance else None)
            if output_spread is not None:
                fit.set_output_spread(output_spread[i])
            test = fit.test_blocks_zero([testable.index(j)], element_window(model, i, j, nb, options.element_window))
            response = None
            if estimates[(i, j)].response is not None:
                a = noise_filter(fit, na)[0]
                # With gaps the fit's rows are those ``keep`` picks among the segments' regression rows.
                response = row_response_tests(model, i, fit, testable, X, sizes, u_c, d_c,
                                              start if segments is None else start0, na, segments, columns=[j],
                                              a=a, extra=extra, rows=keep).get(j)
            p_raw = combined_p_value(test.p_value, None if response is None else response.p_value)
            return min(1.0, N_FAMILIES * factor[(i, j)] * p_raw) if np.isfinite(p_raw) else 1.0

        decided = {j: confirmed(j, located) for j in located}
        if not any(p < alpha for p in decided.values()):
            by_strength = sorted(located, key=lambda j: estimates[(i, j)].p_value)
            kept = [by_strength[0]]
            decided = {by_strength[0]: by_key[(i, by_strength[0])].p_value}
            for j in by_strength[1:]:
                decided[j] = confirmed(j, kept)
                if decided[j] < alpha:
                    kept.append(j)
            stepwise.append(f"row {model.outputs[i]}: its located elements "
                            f"{', '.join(names[j] for j in by_strength)} cannot each be confirmed given the others' slow "
                            f"tails; confirmed step by step from the strongest: {', '.join(names[j] for j in kept)}")
        for j, p in decided.items():
            e = by_key[(i, j)]
            e.p_value = max(e.p_value, p)
            if not p < alpha:
                e.mismatch = False
    return stepwise


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
