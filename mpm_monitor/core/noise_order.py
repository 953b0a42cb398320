"""Is the ARX order ``na`` high enough to whiten the prediction error?  The check behind ``max_na``.

The Delta element test fits every row's prediction error ``d_i`` by an ARX: its own lags ``1 .. na``
and every column's lags.  Its F tests hold their false-alarm rate only when that fit leaves white
noise.  In closed loop this matters more than in open loop: the inputs follow the past prediction
errors through the controller, so a residual that is still correlated in time correlates with the
input lags, and a model that matches the plant gets elements "located".  The common case is an
ordinary slow drift under white measurement noise: ``d = v + w`` with ``v(k) = 0.98 v(k-1) + e(k)``
is an ARMA(1, 1) whose inverse noise model ``(1 - 0.98 q^-1) / (1 - c q^-1)`` (``c`` near 0.8 for a
drift small against the noise) needs 15 or more own lags; the paper's ``na = 4`` leaves it coloured.

:func:`residual_whiteness` takes each row's residual of the element test's unrestricted fit (every
testable column's lags and the row's own lags; the fit's coefficients applied to the logged signals)
and its Ljung-Box statistic over :data:`WHITENESS_LAGS` lags beyond ``na`` (G. M. Ljung and G. E. P.
Box, "On a measure of lack of fit in time series models", Biometrika 65(2), 1978), within each segment
of data with gaps.  :func:`~mpm_monitor.core.pipeline.analyze` raises ``na`` (doubling, up to
``max_na``) while some row's residual is coloured at :data:`WHITENESS_ALPHA` (Bonferroni over the rows)
and runs the detection again: a window whose residuals are white keeps ``na`` and its results.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .arx import segment_rows
from .statistics import chi2_tail

#: Autocorrelation lags of the Ljung-Box statistic beyond the fitted own lags: the statistic sums
#: ``na + WHITENESS_LAGS`` lags and has ``WHITENESS_LAGS`` degrees of freedom.
WHITENESS_LAGS = 20
#: Family-wise level of the whiteness check: a row's residual is coloured when its Ljung-Box p-value
#: times the number of rows checked is below it.  Under a white residual in every row the detection is
#: run again with a larger ``na`` with probability at most this.
WHITENESS_ALPHA = 0.01


def ljung_box(e: np.ndarray, lengths, lags: int, fitted: int = 0) -> tuple:
    """Ljung-Box statistic of a residual made of contiguous segments, and its chi-square p-value.

    Parameters
    ----------
    e : ndarray, shape (n,)
        The residual, segment after segment (target units); centred here.
    lengths : sequence of int
        Samples of each segment (sum ``n``); the autocorrelations pair samples of one segment only.
    lags : int
        Autocorrelation lags summed, ``1 .. lags``.
    fitted : int
        Parameters of the fit counted against the lags (its own AR lags): the statistic has ``lags -
        fitted`` degrees of freedom (at least 1).

    Returns
    -------
    (float, int, float)
        ``Q = n (n + 2) sum_k r_k^2 / (n - k)``, its degrees of freedom and ``P(chi2(dof) > Q)``; ``(0,
        dof, 1)`` for a residual without spread.
    """
    e = np.asarray(e, dtype=float)
    e = e - e.mean()
    n = e.size
    denom = float(e @ e)
    dof = max(int(lags) - int(fitted), 1)
    if not denom > 0 or n <= lags + 1:
        return 0.0, dof, 1.0
    bounds = np.concatenate([[0], np.cumsum(np.asarray(lengths, dtype=int))])
    acf = np.zeros(lags)
    for a, b in zip(bounds[:-1], bounds[1:]):
        seg = e[a:b]
        for k in range(1, min(lags, seg.size - 1) + 1):
            acf[k - 1] += float(seg[k:] @ seg[:-k])
    r = acf / denom
    q = float(n * (n + 2) * np.sum(r * r / (n - np.arange(1, lags + 1))))
    return q, dof, float(chi2_tail(q, dof))


def row_residuals(u: np.ndarray, d: np.ndarray, rows: list, testable: list, n_lag: int, start: int,
                  blocks: dict, own: dict, segments: Optional[list] = None) -> dict:
    """The element test's unrestricted residual of every row of ``rows``, from its coefficients.

    ``e_i(t) = d_i(t) + sum_k a_ik d_i(t - k) - sum_j sum_l b_ijl u_j(t - l)`` over the regression rows
    (``t >= start`` in every segment), less its mean (the fits are of centred signals).

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_columns)
        The columns the regressions were built from (column units).
    d : ndarray, shape (n_samples, n_outputs)
        The prediction errors they fitted (output units).
    rows : list of int
    testable : list of int
        The columns whose lag blocks the fits hold, in block order.
    n_lag : int
        Lags ``1 .. n_lag`` of each block.
    start : int
        First regression row of each segment (>= ``n_lag`` and >= every own lag).
    blocks : dict
        Row -> ndarray, shape (len(testable), n_lag): the block coefficients ``b_ijl``.
    own : dict
        Row -> ndarray, shape (na_i,): the own-lag coefficients ``a_ik`` (of the regressors ``-d_i(t - k)``).
    segments : list of (int, int), optional
        Data with gaps: the segments, stacked.

    Returns
    -------
    dict
        Row -> residual, shape (n_regression_rows,).
    """
    t = segment_rows(np.arange(u.shape[0]), start, segments)
    out = {}
    if not rows:
        return out
    fitted = np.zeros((t.size, len(rows)))
    if testable:
        theta = np.stack([blocks[i] for i in rows], axis=-1)          # (n_testable, n_lag, n_rows)
        ut = u[:, testable]
        for lag in range(1, n_lag + 1):
            fitted += ut[t - lag] @ theta[:, lag - 1, :]
    for c, i in enumerate(rows):
        e = d[t, i] - fitted[:, c]
        for k, a in enumerate(own[i], start=1):
            e += a * d[t - k, i]
        out[i] = e - e.mean()
    return out


def segment_lengths(n_samples: int, start: int, segments: Optional[list] = None) -> list:
    """Regression rows of each segment (``b - a - start``, the segments with rows), in order."""
    if segments is None:
        return [max(n_samples - start, 0)]
    return [b - a - start for a, b in segments if b - a > start]


def coloured_rows(p_values: dict, alpha: float = WHITENESS_ALPHA) -> list:
    """The rows whose residual is coloured: Ljung-Box ``p * len(p_values) < alpha`` (Bonferroni)."""
    m = max(len(p_values), 1)
    return [i for i, p in p_values.items() if p * m < alpha]


def next_order(na: int, max_na: int) -> Optional[int]:
    """The next ARX order tried: ``2 na`` (4 -> 8 -> 16; 1 from 0), at most ``max_na``; None at ``max_na``."""
    if na >= max_na:
        return None
    return min(max(2 * na, 1), max_na)


def residual_whiteness(regressions, testable: list, n_lag: int, blocks: dict, own: dict) -> dict:
    """Ljung-Box p-value of every row's unrestricted element-test residual (:func:`row_residuals`).

    Parameters
    ----------
    regressions : QrRegressions or GramRegressions
        The window's regressions (their ``u``, ``d``, ``layout.start`` and ``segments``).
    testable, n_lag, blocks, own
        As :func:`row_residuals`; the rows are ``blocks``' keys.

    Returns
    -------
    dict
        Row -> p-value of :func:`ljung_box` over ``len(own[i]) + WHITENESS_LAGS`` lags with ``len(own[i])``
        fitted.
    """
    rows = list(blocks)
    if not rows:
        return {}
    u = np.asarray(regressions.u, dtype=float)
    d = np.asarray(regressions.d, dtype=float)
    start, segments = regressions.layout.start, getattr(regressions, "segments", None)
    resid = row_residuals(u, d, rows, testable, n_lag, start, blocks, own, segments)
    lengths = segment_lengths(u.shape[0], start, segments)
    return {i: ljung_box(e, lengths, len(own[i]) + WHITENESS_LAGS, len(own[i]))[2] for i, e in resid.items()}
