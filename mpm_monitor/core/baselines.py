"""Baseline element tests for model-plant mismatch: cross-correlation and partial correlation.

Both tests decide, for every element ``(i, j)`` of the model, whether the prediction error
``d_i = y_i - yhat_i`` carries a contribution of the plant input ``u_j``, i.e. whether
``Delta_ij(q) != 0`` in ``d(t) = Delta(q) u(t) + v(t)`` (paper eq. 9).  They are the alternatives
the paper compares its ARX method with (section 1 and 2.2):

* :func:`cross_correlation_test` -- sample cross-correlation of ``d_i`` with ``u_j`` over lags
  (Webber and Gupta, 2008), one pair at a time;
* :func:`partial_correlation_test` -- partial correlation of ``d_i`` with ``u_j`` after removing
  the linear effect of the other inputs (Badwe, Gudi, Patwardhan, Shah and Narasimhan, 2009).

Making the p-values honest in closed loop
-----------------------------------------
In an MPC loop the input reacts to the disturbance: ``u(k)`` is computed from ``y(k)``, so
``u(k - m)`` depends on ``v(k - m)`` and, through the colour of ``v``, on ``d(k)`` even when
``Delta = 0`` (Carlsson, 2010, gives such counter-examples).  A textbook correlation test on raw
signals therefore raises false alarms on a perfect model.  Both tests here

1. prewhiten every input ``u_j`` with its own autoregressive (AR) model and every prediction error
   ``d_i`` with its own AR model ("double prewhitening", Haugh, 1976; the Box-Jenkins single
   prewhitening of the input alone is only valid when the input does not react to the noise);
2. use lags ``1 .. L`` only.  Lag 0 is excluded: ``u(k)`` is computed after ``y(k)`` is measured
   (docs/DESIGN.md, time convention), so ``d(k)`` and ``u(k)`` are correlated by the feedback
   whatever the model, while ``Delta`` is strictly proper (plant and model are) and has no lag-0
   term.

Under "no contribution of ``u_j`` to ``d_i``" the whitened ``d_i(k)`` is (approximately) the
innovation of ``d_i``, uncorrelated with everything measured before ``k``; its sample
correlations with the past of the whitened inputs are then asymptotically independent
``N(0, 1/N)`` (Haugh, 1976), which gives the chi-square and F reference distributions below.
False alarms are controlled family-wise over the whole ``(n_outputs, n_inputs)`` matrix with
Holm's step-down procedure (Holm, 1979).

References
----------
- Webber, J. R. and Gupta, Y. P. (2008). A closed-loop cross-correlation method for detecting
  model mismatch in MIMO model-based controllers. *ISA Transactions* 47(4), 395-400.
- Badwe, A. S., Gudi, R. D., Patwardhan, R. S., Shah, S. L. and Patwardhan, S. C. (2009).
  Detection of model-plant mismatch in MPC applications. *Journal of Process Control* 19(8),
  1305-1313.
- Haugh, L. D. (1976). Checking the independence of two covariance-stationary time series: a
  univariate residual cross-correlation approach. *JASA* 71(354), 378-385.
- Box, G. E. P., Jenkins, G. M. and Reinsel, G. C. (2008). *Time Series Analysis*, 4th ed.,
  section 12.2 (prewhitening and the cross-correlation function).
- Holm, S. (1979). A simple sequentially rejective multiple test procedure. *Scandinavian
  Journal of Statistics* 6(2), 65-70.
- Carlsson, R. (2010). *A practical approach to detection of plant model mismatch for MPC*.
  Master's thesis, Linkoping University.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
from scipy import linalg

from .arx import lag_matrix, least_squares_ar
from .errors import ConfigurationError, InputError, TooFewSamples
from .filters import lfilter
from .statistics import chi2_tail, f_tail, holm_adjust

#: Default number of lags tested when ``max_lag`` is None (samples).  Covers the delays of the
#: FOPDT elements the project targets (up to about 16 samples of dead time after a delay
#: mismatch) plus a few samples of dynamics.
DEFAULT_MAX_LAG = 20

#: Smallest number of lags the default ``max_lag`` is reduced to on short data.
MIN_AUTO_LAG = 5

#: Largest AR order tried when prewhitening a signal; the order is chosen by BIC.
DEFAULT_MAX_AR_ORDER = 12

#: Lags of the whitened prediction error added to the conditioning set of the partial correlation
#: test (absorbs what the AR prewhitening leaves of the noise colour in mismatched rows).
DEFAULT_OWN_LAGS = 4

#: Separability (:func:`input_separability`, ``1 - rho_max^2``) below which the partial correlation
#: test declares an input's elements ambiguous instead of testing them (a variance-inflation
#: factor above 100).
DEFAULT_SEPARABILITY_THRESHOLD = 1e-2

#: Relative variance below which a signal is treated as constant (no information).
_CONSTANT_TOL = 1e-12


@dataclasses.dataclass(frozen=True)
class ElementTestResult:
    """Result of an element-wise mismatch test over the whole model matrix.

    Attributes
    ----------
    p_values : ndarray, shape (n_outputs, n_inputs)
        Unadjusted p-value of "``u_j`` does not enter ``d_i``" for every element.
    mismatch : ndarray of bool, shape (n_outputs, n_inputs)
        Elements declared mismatched, with Holm's family-wise error rate <= ``alpha`` over all
        ``n_outputs * n_inputs`` elements.
    statistic : ndarray, shape (n_outputs, n_inputs)
        Test statistic: the portmanteau ``Q`` (chi-square with ``max_lag`` degrees of freedom) for
        ``"xcorr"``, the partial F statistic (``F(max_lag, dof)``) for ``"pcorr"``.
    method : str
        ``"xcorr"`` or ``"pcorr"``.
    max_lag : int
        Lags ``1 .. max_lag`` (samples) that were tested jointly.
    alpha : float
        Family-wise significance level used.
    adjusted_p_values : ndarray, shape (n_outputs, n_inputs)
        Holm-adjusted p-values (``mismatch == adjusted_p_values <= alpha``).
    n_used : int
        Samples left after prewhitening and lagging (the ``N`` of the test).
    warnings : tuple of str
        What limits the conclusions (a constant input, inputs that move together, ...).
    ambiguous : ndarray of bool, shape (n_outputs, n_inputs), optional
        Elements that could not be tested because their input is (nearly) collinear with the
        others (``"pcorr"`` only; p-value 1, never ``mismatch``, left out of the Holm family).
        None means no element was ambiguous.
    separability : ndarray, shape (n_inputs,), optional
        ``"pcorr"``: :func:`input_separability` of each input, ``1 - rho_max^2`` of its lag block
        against the other inputs' (1 = independent, 0 = collinear).
    """

    p_values: np.ndarray
    mismatch: np.ndarray
    statistic: np.ndarray
    method: str
    max_lag: int = 0
    alpha: float = 0.01
    adjusted_p_values: Optional[np.ndarray] = None
    n_used: int = 0
    warnings: tuple = ()
    ambiguous: Optional[np.ndarray] = None
    separability: Optional[np.ndarray] = None


# --------------------------------------------------------------------------- checks
def _check_inputs(d, u, alpha, max_lag):
    """Validate and convert the arguments; return ``(d, u, alpha, max_lag)``."""
    try:
        alpha_f = float(alpha)
    except (TypeError, ValueError):
        raise ConfigurationError(f"alpha: expected a number in (0, 1), got {alpha!r}") from None
    if not (0.0 < alpha_f < 1.0):
        raise ConfigurationError(f"alpha: expected a number in (0, 1), got {alpha!r}")
    arrays = []
    for name, arr, cols in (("d", d, "n_outputs"), ("u", u, "n_inputs")):
        try:
            a = np.asarray(arr, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{name}: expected a numeric array of shape (n_samples, {cols})") from None
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[1] == 0:
            raise InputError(f"{name}: expected shape (n_samples, {cols}), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            k, c = np.argwhere(~np.isfinite(a))[0]
            raise InputError(f"{name}: expected finite numbers, got {a[k, c]} at sample {k}, column {c}")
        arrays.append(a)
    d_arr, u_arr = arrays
    if d_arr.shape[0] != u_arr.shape[0]:
        raise InputError(f"d and u: expected the same number of samples, got d shape {d_arr.shape} and "
                         f"u shape {u_arr.shape}")
    n = d_arr.shape[0]
    if max_lag is None:
        lag = None
    else:
        if isinstance(max_lag, bool) or int(max_lag) != max_lag or max_lag < 1:
            raise ConfigurationError(f"max_lag: expected an integer >= 1 (samples), got {max_lag!r}")
        lag = int(max_lag)
    return d_arr, u_arr, alpha_f, lag, n


def _auto_lag(lag, n, largest_fitting, warnings):
    """``lag`` if given; else :data:`DEFAULT_MAX_LAG`, reduced (>= ``MIN_AUTO_LAG``) to fit ``n`` samples."""
    if lag is not None:
        return lag
    fit = int(largest_fitting)
    if fit >= DEFAULT_MAX_LAG:
        return DEFAULT_MAX_LAG
    lag = max(MIN_AUTO_LAG, fit)
    warnings.append(f"only {n} samples: lags 1..{lag} tested instead of 1..{DEFAULT_MAX_LAG}; a mismatch with a "
                    f"longer dead time may go unseen")
    return lag


def _require_samples(n, needed, what):
    if n < needed:
        raise TooFewSamples(f"d and u: {what} needs at least {needed} samples, got {n}")


# --------------------------------------------------------------------------- building blocks
def fit_ar(x: np.ndarray, max_order: int = DEFAULT_MAX_AR_ORDER) -> np.ndarray:
    """Least-squares AR model of a signal, order chosen by BIC.

    Fits ``x(k) = a_1 x(k-1) + ... + a_p x(k-p) + e(k)`` for ``p = 0 .. max_order`` on the same
    samples (``k >= max_order``) from one QR factorisation of ``[X_lags, x]``: the residual sum of
    squares of order ``p`` is the sum of squares of the last column of ``R`` below row ``p``.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        Signal, mean already removed.
    max_order : int
        Largest order tried (>= 0).

    Returns
    -------
    ndarray, shape (p,)
        AR coefficients ``a_1 .. a_p`` of the chosen order (possibly empty).
    """
    n = x.shape[0]
    pmax = int(min(max_order, max(0, n // 10)))
    if pmax == 0:
        return np.zeros(0)
    X = lag_matrix(x, range(1, pmax + 1), pmax)
    y = x[pmax:]
    r = np.linalg.qr(np.column_stack([X, y]), mode="r")
    tail = r[:, -1] ** 2
    # rss[p] = sum_{k >= p} R[k, -1]^2 over rows k = p .. pmax (row pmax holds the final residual).
    rss = np.cumsum(tail[::-1])[::-1][: pmax + 1]
    m = y.shape[0]
    with np.errstate(divide="ignore"):
        bic = m * np.log(np.maximum(rss, np.finfo(float).tiny) / m) + np.arange(pmax + 1) * np.log(m)
    p = int(np.argmin(bic))
    if p == 0:
        return np.zeros(0)
    return least_squares_ar(x, p, start=pmax)


def prewhiten(x: np.ndarray, max_order: int = DEFAULT_MAX_AR_ORDER):
    """Filter a signal with its own AR model, ``e(k) = x(k) - sum_l a_l x(k - l)``.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
    max_order : int
        Largest AR order tried (BIC selection, :func:`fit_ar`).

    Returns
    -------
    e : ndarray, shape (n_samples,)
        Whitened signal; the first ``len(a)`` samples are transients and must be discarded.
    a : ndarray, shape (p,)
        The AR coefficients used.
    """
    xc = x - x.mean()
    a = fit_ar(xc, max_order)
    e = lfilter(np.concatenate([[1.0], -a]), [1.0], xc)
    return e, a


def _is_constant(x: np.ndarray) -> bool:
    scale = max(1.0, float(np.max(np.abs(x)))) if x.size else 1.0
    return x.size == 0 or float(np.var(x)) <= _CONSTANT_TOL * scale * scale


def _whiten_all(d, u, max_order):
    """Prewhiten every column; return whitened arrays, the common start and flags of constant columns."""
    ny, nu = d.shape[1], u.shape[1]
    dw, uw = np.zeros_like(d), np.zeros_like(u)
    d_const = np.array([_is_constant(d[:, i]) for i in range(ny)])
    u_const = np.array([_is_constant(u[:, j]) for j in range(nu)])
    start = 0
    for arr, out, const in ((d, dw, d_const), (u, uw, u_const)):
        for c in range(arr.shape[1]):
            if const[c]:
                continue
            out[:, c], a = prewhiten(arr[:, c], max_order)
            start = max(start, a.size)
    return dw, uw, start, d_const, u_const


def _constant_warnings(d_const, u_const, outputs_label="output", inputs_label="input"):
    msgs = []
    for j in np.flatnonzero(u_const):
        msgs.append(f"{inputs_label} column {j} is constant: its elements cannot be tested (p-value 1)")
    for i in np.flatnonzero(d_const):
        msgs.append(f"prediction error column {i} is constant: its row cannot be tested (p-value 1)")
    return msgs


# --------------------------------------------------------------------------- the tests
def cross_correlation_test(d, u, alpha: float = 0.01, max_lag: Optional[int] = None, *,
                           max_ar_order: int = DEFAULT_MAX_AR_ORDER) -> ElementTestResult:
    """Cross-correlation test of every prediction error against every input (Webber and Gupta, 2008).

    For each element ``(i, j)`` the prewhitened prediction error ``e_i`` is correlated with the
    past of the prewhitened input ``w_j`` at lags ``1 .. L``::

        r_ij(l) = sum_k e_i(k) w_j(k - l) / sqrt(sum_k e_i(k)^2 sum_k w_j(k)^2)
        Q_ij    = N sum_{l=1..L} r_ij(l)^2   ~ chi2(L)  when u_j does not enter d_i

    (a Haugh (1976) / Box-Pierce portmanteau statistic).  Elements are declared mismatched by
    Holm's procedure over the whole matrix at family-wise level ``alpha``.

    Parameters
    ----------
    d : array_like, shape (n_samples, n_outputs)
        Prediction error ``y - yhat`` (output units), one column per output.
    u : array_like, shape (n_samples, n_inputs)
        Plant inputs, one column per input, aligned with ``d`` (sample ``k`` holds ``u(k)`` computed
        after ``y(k)`` was measured).
    alpha : float
        Family-wise false-alarm level over all ``n_outputs * n_inputs`` elements, in (0, 1).
    max_lag : int, optional
        ``L``, the largest lag tested (samples, >= 1); default :data:`DEFAULT_MAX_LAG`, reduced
        (with a warning, not below :data:`MIN_AUTO_LAG`) when there are fewer than ``10 L``
        samples.  It must cover the dead time of the mismatch plus some of its dynamics.
    max_ar_order : int
        Largest AR order of the prewhitening filters (BIC selection).

    Returns
    -------
    ElementTestResult
        ``method == "xcorr"``, ``statistic`` = ``Q``.

    Raises
    ------
    InputError
        ``d`` or ``u`` not 2-D numeric finite arrays with the same number of samples, or fewer
        than ``10 * max_lag`` samples (``10 * MIN_AUTO_LAG`` with the default).
    ConfigurationError
        ``alpha`` outside (0, 1) or ``max_lag`` not a positive integer.

    Notes
    -----
    Assumptions: linear time-invariant loop; ``v`` stationary (non-drifting); ``Delta`` strictly
    proper.  The test looks at one pair at a time, so when inputs are correlated with each other
    (as a multivariable controller makes them) a mismatch in ``Delta_ik`` also shows up as
    correlation with ``u_j``: the row is right, the element may not be (Badwe et al., 2009).  The
    p-value is valid for a row without mismatch; in a mismatched row the other elements' p-values
    are not protected against this leakage.
    """
    d, u, alpha, lag, n = _check_inputs(d, u, alpha, max_lag)
    notes = []
    lag = _auto_lag(lag, n, n // 10, notes)
    _require_samples(n, 10 * lag, f"the cross-correlation test with max_lag={lag}")
    ny, nu = d.shape[1], u.shape[1]
    dw, uw, start, d_const, u_const = _whiten_all(d, u, max_ar_order)
    start = max(start, lag)
    e = dw[start:]  # (N, ny), e(k) for k = start .. n-1
    m = e.shape[0]
    e_norm = np.sqrt(np.sum(e * e, axis=0))
    stat = np.zeros((ny, nu))
    for j in range(nu):
        if u_const[j]:
            continue
        w = uw[:, j]
        w_norm = np.sqrt(np.sum(w[start:] ** 2))
        lags = lag_matrix(w, range(1, lag + 1), start)  # (N, L): w_j(k - l)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = (e.T @ lags) / (e_norm[:, None] * w_norm)  # (ny, L)
        r = np.where(np.isfinite(r), r, 0.0)
        stat[:, j] = m * np.sum(r * r, axis=1)
    stat[d_const, :] = 0.0
    p = chi2_tail(stat, lag)
    p[:, u_const] = 1.0
    p[d_const, :] = 1.0
    adj = holm_adjust(p)
    return ElementTestResult(p_values=p, mismatch=adj <= alpha, statistic=stat, method="xcorr", max_lag=lag,
                             alpha=alpha, adjusted_p_values=adj, n_used=m,
                             warnings=tuple(notes + _constant_warnings(d_const, u_const)))


def input_separability(u: np.ndarray, max_lag: int) -> np.ndarray:
    """How much of each input's lag block is *not* explained by the other inputs' lag blocks.

    With ``X_j`` the columns ``u_j(k - 1) .. u_j(k - L)`` and ``X_o`` those of every other input,
    the value for input ``j`` is ``1 - rho_max^2``, ``rho_max`` the largest canonical correlation
    between ``X_j`` and ``X_o`` (Hotelling, 1936): the smallest generalised eigenvalue of
    ``(S_j, X_j' X_j)`` with ``S_j = X_j' X_j - X_j' X_o (X_o' X_o)^+ X_o' X_j`` the Schur complement.
    It is 1 for an input moving independently of the others and 0 when some combination of its
    lags is a combination of the other inputs' lags -- as when the closed loop drives more inputs
    than it has independent excitations (more inputs than setpoints, no dither).  ``1 / value`` is
    the largest generalised variance-inflation factor of the block.

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_inputs)
        Inputs (means are removed here).
    max_lag : int
        ``L``, samples.

    Returns
    -------
    ndarray, shape (n_inputs,)
        Values in [0, 1].
    """
    u = np.asarray(u, dtype=float)
    n, nu = u.shape
    lag = int(max_lag)
    out = np.ones(nu)
    if nu == 1:
        return out
    uc = u - u.mean(axis=0)
    X = np.column_stack([lag_matrix(uc[:, j], range(1, lag + 1), lag) for j in range(nu)])
    norms = np.sqrt(np.sum(X * X, axis=0))
    X = X / np.where(norms > 0, norms, 1.0)
    G = X.T @ X
    for j in range(nu):
        blk = np.arange(j * lag, (j + 1) * lag)
        oth = np.setdiff1d(np.arange(nu * lag), blk)
        g_jj = G[np.ix_(blk, blk)]
        g_jo = G[np.ix_(blk, oth)]
        schur = g_jj - g_jo @ np.linalg.pinv(G[np.ix_(oth, oth)], rcond=1e-13, hermitian=True) @ g_jo.T
        try:
            ev = linalg.eigh(0.5 * (schur + schur.T), g_jj, eigvals_only=True)
            out[j] = float(np.clip(ev.min(), 0.0, 1.0))
        except (linalg.LinAlgError, ValueError):
            out[j] = 0.0  # the block's own Gram matrix is singular: no usable variation
    return out


def partial_correlation_test(d, u, alpha: float = 0.01, max_lag: Optional[int] = None, *,
                             max_ar_order: int = DEFAULT_MAX_AR_ORDER,
                             own_lags: int = DEFAULT_OWN_LAGS,
                             separability_threshold: float = DEFAULT_SEPARABILITY_THRESHOLD) -> ElementTestResult:
    """Partial-correlation test of every prediction error against every input (Badwe et al., 2009).

    For each row ``i`` the prediction error is prewhitened with its own AR filter ``A_i(q)``
    (BIC order) and, as in Box-Jenkins prewhitening, the *same* filter is applied to every input,
    which leaves ``Delta`` unchanged: ``A_i d_i = sum_j Delta_ij (A_i u_j) + A_i v_i``.  The
    correlation of ``e_i = A_i d_i`` with the lags ``1 .. L`` of ``A_i u_j`` is then measured
    *after removing the linear effect of the other inputs*: both are regressed on the lags
    ``1 .. L`` of every other filtered input (and on ``own_lags`` lags of ``e_i``, which absorb the
    noise colour the AR filter leaves in a mismatched row), and the residuals are correlated.  By
    the Frisch-Waugh theorem the joint test of the ``L`` partial correlations is the partial F test
    of the block of ``u_j`` in the regression of ``e_i`` on everything::

        F_ij = ((RSS_without_j - RSS_all) / L) / (RSS_all / dof)   ~ F(L, dof)

    with ``dof = N - n_inputs * L - own_lags``; the squared multiple partial correlation is
    ``L F / (L F + dof)``.  Elements are declared mismatched by Holm's procedure over the tested
    elements at family-wise level ``alpha``.

    An input with a direction of its lags almost entirely explained by the other inputs' lags
    (:func:`input_separability` below ``separability_threshold``) leaves (almost) nothing to
    correlate after the other inputs are removed: its elements are reported ``ambiguous``
    (p-value 1, not tested) with a warning, rather than decided on the tiny, bias-dominated
    remainder (any lag-truncation error of a mismatch on one input of the group is then
    attributed to the others).

    Parameters
    ----------
    d : array_like, shape (n_samples, n_outputs)
        Prediction error ``y - yhat`` (output units).
    u : array_like, shape (n_samples, n_inputs)
        Plant inputs aligned with ``d``.
    alpha : float
        Family-wise false-alarm level over all elements, in (0, 1).
    max_lag : int, optional
        ``L``, the largest lag (samples, >= 1); default :data:`DEFAULT_MAX_LAG`, reduced (with a
        warning, not below :data:`MIN_AUTO_LAG`) when the samples do not allow five per
        regressor.
    max_ar_order : int
        Largest AR order of the prewhitening filters (BIC selection).
    own_lags : int
        Lags of the whitened prediction error in the conditioning set (>= 0).
    separability_threshold : float
        In [0, 1); inputs below it are not tested (0 tests every input).

    Returns
    -------
    ElementTestResult
        ``method == "pcorr"``, ``statistic`` = ``F``, ``ambiguous`` and ``separability`` set.

    Raises
    ------
    InputError
        Bad shapes or values of ``d``/``u``, or fewer samples than ``5 * (n_inputs * L + own_lags)``
        (the regression needs several samples per regressor).
    ConfigurationError
        ``alpha``, ``max_lag``, ``own_lags`` or ``separability_threshold`` out of range.

    Notes
    -----
    Assumptions: linear time-invariant loop, stationary ``v``, strictly proper ``Delta`` whose
    effect is captured by ``L`` lags (with the ``own_lags`` autoregressive terms for the tail).
    """
    d, u, alpha, lag, n = _check_inputs(d, u, alpha, max_lag)
    if isinstance(own_lags, bool) or int(own_lags) != own_lags or own_lags < 0:
        raise ConfigurationError(f"own_lags: expected an integer >= 0 (samples), got {own_lags!r}")
    if not (0.0 <= float(separability_threshold) < 1.0):
        raise ConfigurationError(
            f"separability_threshold: expected a number in [0, 1), got {separability_threshold!r}")
    own_lags = int(own_lags)
    ny, nu = d.shape[1], u.shape[1]
    notes = []
    lag = _auto_lag(lag, n, (n - 5 * own_lags - max_ar_order) // (5 * nu + 2), notes)
    n_reg = nu * lag + own_lags
    _require_samples(n, 5 * n_reg + 2 * lag + max_ar_order,
                     f"the partial correlation test with {nu} inputs and max_lag={lag}")
    d_const = np.array([_is_constant(d[:, i]) for i in range(ny)])
    u_const = np.array([_is_constant(u[:, j]) for j in range(nu)])
    warnings = notes + _constant_warnings(d_const, u_const)
    active = np.flatnonzero(~u_const)
    uc = u[:, active] - u[:, active].mean(axis=0)
    separability = np.zeros(nu)
    if active.size:
        separability[active] = input_separability(uc, lag)
    weak = active[separability[active] < separability_threshold]
    tested = np.array([j for j in active if j not in set(weak.tolist())], dtype=int)
    if weak.size:
        warnings.append(
            "inputs " + ", ".join(str(j) for j in weak) + " move (almost) collinearly with the other inputs "
            f"(separability {', '.join(f'{separability[j]:.2g}' for j in weak)}): their elements cannot be told "
            "apart and are reported ambiguous; an input dither would separate them")
    start = max(lag, own_lags) + max_ar_order
    m = n - start
    dof = m - active.size * lag - own_lags
    stat = np.zeros((ny, nu))
    p = np.ones((ny, nu))
    for i in range(ny):
        if d_const[i] or tested.size == 0:
            continue
        e, a = prewhiten(d[:, i], max_ar_order)
        filt = np.concatenate([[1.0], -a])
        uf = lfilter(filt, [1.0], uc, axis=0)
        cols = [lag_matrix(uf[:, c], range(1, lag + 1), start) for c in range(active.size)]
        cols.append(lag_matrix(e, range(1, own_lags + 1), start))
        X = np.column_stack(cols)
        X = X / np.maximum(np.sqrt(np.sum(X * X, axis=0)), np.finfo(float).tiny)
        r_aug = np.linalg.qr(np.column_stack([X, e[start:]]), mode="r")
        r = r_aug[:-1, :-1]
        qe = r_aug[:-1, -1]
        rss = float(r_aug[-1, -1] ** 2)
        s2 = rss / dof
        if not s2 > 0:
            continue
        # R^{-1} by a pseudo-inverse: exact collinearity among the untested inputs must not break it.
        r_inv = np.linalg.pinv(r, rcond=1e-12)
        beta = r_inv @ qe
        for j in tested:
            b = int(np.flatnonzero(active == j)[0])
            blk = slice(b * lag, (b + 1) * lag)
            # Covariance of beta_j up to s2: (X'X)^{-1}_jj = R^{-1}[j, :] R^{-1}[j, :]'.
            rj = r_inv[blk, :]
            bj = beta[blk]
            wald = float(bj @ np.linalg.pinv(rj @ rj.T, rcond=1e-12, hermitian=True) @ bj)
            stat[i, j] = wald / (lag * s2)
        p[i, tested] = f_tail(stat[i, tested], lag, dof)
    ambiguous = np.zeros((ny, nu), dtype=bool)
    ambiguous[:, weak] = True
    ambiguous[d_const, :] = False
    p_family = np.where(ambiguous, np.nan, p)
    adj = holm_adjust(p_family)
    adj = np.where(np.isnan(adj), 1.0, adj)
    return ElementTestResult(p_values=p, mismatch=adj <= alpha, statistic=stat, method="pcorr", max_lag=lag,
                             alpha=alpha, adjusted_p_values=adj, n_used=m, warnings=tuple(warnings),
                             ambiguous=ambiguous, separability=separability)


#: Element tests by method name, as :func:`mpm_monitor.core.element_test.baseline_element_test` selects them.
ELEMENT_TESTS = {"xcorr": cross_correlation_test, "pcorr": partial_correlation_test}
