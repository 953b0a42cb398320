"""The statistics the tests share: F and chi-square tail probabilities, nested F tests, Holm's procedure.

Every test of the package ends in one of these: the S_Delta row test and the Delta element test
(:mod:`mpm_monitor.core.row_test`, :mod:`mpm_monitor.core.element_test`) in F tests of nested
least squares, the cross-correlation baseline in a chi-square portmanteau statistic, and all of
them in Holm's step-down adjustment of the p-values of a family of tests.

References
----------
- Ljung, L. (1999). *System Identification: Theory for the User*, 2nd ed., section 16.4 (F tests
  of nested least-squares models).
- Holm, S. (1979). A simple sequentially rejective multiple test procedure. *Scandinavian Journal
  of Statistics* 6(2), 65-70.
"""

from __future__ import annotations

import numpy as np

#: The families of tests that share the false-alarm rate ``alpha`` of one analysis: the S_Delta row
#: tests and the Delta element tests.  Each family is controlled at ``alpha / N_FAMILIES``
#: (Bonferroni) with Holm's procedure inside it; a reported p-value is the Holm-adjusted one times
#: ``N_FAMILIES``, so a finding is reported exactly when its p-value is below ``alpha``.
N_FAMILIES = 2

#: A residual whose spread is at most this fraction of its signal's (an output's standard deviation) is
#: the rounding error of an exact fit (a log without noise), not noise: the repair's disturbance test does
#: not test it and the detectability does not measure a detectable change against it.  A fit that is
#: exact in real numbers leaves 0 or a few ulps, depending on how the BLAS rounds (fused multiply-adds).
EXACT_FIT = 1e-10


def _special():
    """``scipy.special``, imported on first use: describing the analysis options needs none of it."""
    from scipy import special

    return special


def f_tail(statistic, df_num, df_den):
    """``P(F(df_num, df_den) > statistic)``, elementwise (``scipy.special.fdtrc``)."""
    return _special().fdtrc(df_num, df_den, statistic)


def detection_noncentrality(df_num, df_den, level: float, power: float) -> float:
    """Noncentrality ``lambda`` at which the F test at ``level`` rejects with probability ``power``.

    ``P(F'(df_num, df_den, lambda) > F_crit) = power`` with ``F_crit`` the ``1 - level`` quantile of
    ``F(df_num, df_den)`` (``scipy.special.fdtri``, ``scipy.special.ncfdtrinc``).
    """
    special = _special()
    f_crit = special.fdtri(df_num, df_den, 1.0 - level)
    return float(special.ncfdtrinc(df_num, df_den, 1.0 - power, f_crit))


def chi2_tail(statistic, df):
    """``P(chi2(df) > statistic)``, elementwise (``scipy.special.chdtrc``)."""
    return _special().chdtrc(df, statistic)


def normal_sf(z):
    """``P(N(0, 1) > z)``, elementwise (``scipy.special.ndtr(-z)``)."""
    return _special().ndtr(-np.asarray(z, float))


def normal_isf(q):
    """Upper quantile ``z`` of the standard normal, ``P(N(0, 1) > z) = q`` (``-scipy.special.ndtri(q)``)."""
    return -_special().ndtri(q)


def chi2_isf(q, df):
    """Upper quantile ``x`` of the chi-square, ``P(chi2(df) > x) = q`` (``scipy.special.chdtri``)."""
    return _special().chdtri(df, q)


def exact_sigma2(spread) -> float:
    """Residual variance at or below which a fit of a signal of standard deviation ``spread`` is exact.

    ``(EXACT_FIT * spread)^2`` (:data:`EXACT_FIT`), output units squared; a fit of ``dof`` residual
    degrees of freedom is exact when its residual sum of squares is at most ``dof`` times it.
    """
    return (EXACT_FIT * float(spread)) ** 2


def exact_fit_statistic(f, rss_restricted, rss_full, floor):
    """The F statistic ``f`` of a nested test, decided outright where the full fit is exact.

    Where ``rss_full <= floor`` (the full model fits exactly: its residual is rounding, not noise,
    :func:`exact_sigma2`), the F ratio divides rounding by rounding and means nothing.  The restriction
    is then rejected outright (F ``inf``, p 0) when the restricted fit leaves more than the floor, and
    there is nothing to test (F 0, p 1) when it does not.  Elsewhere ``f`` is returned.  With ``floor``
    0 this is the exact arithmetic's ``q / 0 = inf`` and ``0 / 0 = 0``.  Elementwise.
    """
    return np.where(rss_full <= floor, np.where(rss_restricted > floor, np.inf, 0.0), f)


def f_test(rss_restricted: float, rss_full: float, df_num: int, df_den: int, floor: float = 0.0):
    """F statistic and p-value of a nested least-squares restriction.

    ``F = ((RSS_r - RSS_f) / df_num) / (RSS_f / df_den)``, ``p = P(F(df_num, df_den) > F)``
    (Ljung 1999, section 16.4).  Returns (nan, 1.0) when ``df_num < 1`` or ``df_den < 1``.  When the
    full model fits exactly (``RSS_f <= floor``, residual sums of squares in the target's units squared),
    the restriction is decided outright (:func:`exact_fit_statistic`): (inf, 0.0) when ``RSS_r > floor``,
    (0.0, 1.0) otherwise.
    """
    if df_num < 1 or df_den < 1:
        return float("nan"), 1.0
    if rss_full <= floor:
        return (float("inf"), 0.0) if rss_restricted > floor else (0.0, 1.0)
    f = max(rss_restricted - rss_full, 0.0) / df_num / (rss_full / df_den)
    return float(f), float(f_tail(f, df_num, df_den))


def holm_adjust(p_values) -> np.ndarray:
    """Holm's step-down adjusted p-values (Holm 1979).

    With the ``m`` p-values of the family sorted, ``p_(1) <= ... <= p_(m)``, the adjusted value of
    ``p_(k)`` is ``min(1, max_{l <= k} (m - l + 1) p_(l))``; rejecting ``p_adj <= alpha`` controls the
    family-wise error rate at ``alpha`` under any dependence between the tests.

    Parameters
    ----------
    p_values : array_like
        Unadjusted p-values in [0, 1], any shape.  A non-finite entry (NaN; an infinity is no
        p-value and is treated alike) marks a hypothesis that was not tested: it is left out of
        the family (not counted in ``m``) and its adjusted value is NaN.

    Returns
    -------
    ndarray, same shape
        The adjusted p-values.
    """
    p = np.asarray(p_values, dtype=float)
    flat = p.ravel()
    ok = np.flatnonzero(np.isfinite(flat))
    out = np.full(flat.shape, np.nan)
    m = ok.size
    if m:
        order = ok[np.argsort(flat[ok], kind="stable")]
        scaled = (m - np.arange(m)) * flat[order]
        out[order] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return out.reshape(p.shape)


def holm_reject(p_values, alpha: float) -> np.ndarray:
    """Boolean array of the hypotheses Holm's procedure rejects at family-wise level ``alpha``."""
    adj = holm_adjust(p_values)
    return np.where(np.isnan(adj), False, adj <= alpha)
