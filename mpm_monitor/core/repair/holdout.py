"""Statistics of the repair's held-out check: one-step errors under an AR noise model, and a test of
whether one model's held-out simulation error is significantly larger than another's.

The held-out check (:func:`mpm_monitor.core.repair.validation._validate_on_holdout`) compares the
candidate's and the given model's prediction errors over the held-out last part of the record.  The
simulation errors (``d = y - yhat``) are what the model is used for, but in a closed loop they carry
the disturbance the controller answered through the same inputs: a right element can show a
slightly larger simulation error than a wrong one.  The one-step errors under each model's own AR
noise model (what the repair's fit minimises) do not carry that bias but can hide a gross
simulation error in a slow noise model.  So the check accepts a candidate whose simulation error
falls, or whose one-step error falls while its simulation error does not rise significantly:
:func:`ar_one_step_errors` and :func:`loss_rise_p_value` give the two.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from ..statistics import normal_sf


def ar_one_step_errors(e: np.ndarray, n_fit: int, order: int,
                       segments: Optional[Sequence[tuple]] = None) -> Optional[np.ndarray]:
    """One-step errors over the held-out part of ``e`` under an AR(``order``) model fitted on the fit part.

    Parameters
    ----------
    e : ndarray, shape (n_samples,)
        A prediction error about its level (output units).
    n_fit : int
        Samples ``0 .. n_fit - 1`` are the fit part (the AR coefficients are fitted by least squares
        on the errors at those samples), the rest the held-out part.
    order : int
        AR order ``p`` (>= 0); 0 gives ``e`` over the held-out part as it is.
    segments : sequence of (int, int), optional
        The runs ``(first, end)`` of samples to use (data with gaps): a lag never reaches outside its
        run, and the first ``order`` samples of each run are not predicted.  None: one run.

    Returns
    -------
    ndarray, shape (n_predicted,) or None
        ``e[t] - sum_k a_k e[t - k]`` at the held-out samples predicted, in time order; None when the
        fit part holds fewer than ``2 order + 1`` predicted samples or the held-out part none.
    """
    e = np.asarray(e, float)
    runs = [(0, e.shape[0])] if segments is None else [(int(a), int(b)) for a, b in segments]
    rows, target, held = [], [], []
    for a, b in runs:
        t = np.arange(a + order, b)
        if t.size == 0:
            continue
        rows.append(np.column_stack([e[t - k] for k in range(1, order + 1)]) if order else np.empty((t.size, 0)))
        target.append(e[t])
        held.append(t >= n_fit)
    if not rows:
        return None
    x, y, h = np.concatenate(rows), np.concatenate(target), np.concatenate(held)
    if not h.any() or np.count_nonzero(~h) < 2 * order + 1:
        return None
    if order == 0:
        return y[h]
    coef, *_ = np.linalg.lstsq(x[~h], y[~h], rcond=None)
    return y[h] - x[h] @ coef


def bartlett_bandwidth(x: np.ndarray) -> int:
    """Andrews' (1991) bandwidth of the Bartlett kernel for the long-run variance of ``x``, AR(1) plug-in.

    ``ceil(1.1447 (alpha n)^(1/3))`` with ``alpha = 4 rho^2 / ((1 - rho)^2 (1 + rho)^2)`` and ``rho``
    the lag-one autocorrelation of ``x`` (shape (n,)), bounded to [-0.99, 0.99]; at most ``n - 1``.
    """
    x = np.asarray(x, float)
    n = x.shape[0]
    if n < 3:
        return 0
    c = x - x.mean()
    den = float(c[:-1] @ c[:-1])
    rho = float(c[1:] @ c[:-1]) / den if den > 0 else 0.0
    rho = min(max(rho, -0.99), 0.99)
    alpha = 4.0 * rho ** 2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return int(min(n - 1, math.ceil(1.1447 * (alpha * n) ** (1.0 / 3.0))))


def mean_t_statistic(x: np.ndarray, bandwidth: Optional[int] = None) -> float:
    """``mean(x) / sqrt(V / n)`` with ``V`` the Newey–West (Bartlett) long-run variance of ``x`` (shape (n,)).

    ``V = g_0 + 2 sum_{k=1}^{L} (1 - k / (L + 1)) g_k`` with ``g_k`` the lag-``k`` autocovariance
    (divided by ``n``) and ``L`` the bandwidth (:func:`bartlett_bandwidth` when None).  0 when ``x``
    is constant at 0; +-inf when it is constant elsewhere.
    """
    x = np.asarray(x, float)
    n = x.shape[0]
    m = float(x.mean())
    c = x - m
    lags = bartlett_bandwidth(x) if bandwidth is None else int(bandwidth)
    v = float(c @ c) / n
    for k in range(1, min(lags, n - 1) + 1):
        v += 2.0 * (1.0 - k / (lags + 1.0)) * float(c[k:] @ c[:-k]) / n
    if v <= 0.0:
        return 0.0 if m == 0.0 else math.copysign(math.inf, m)
    return m / math.sqrt(v / n)


def loss_rise_p_value(after: np.ndarray, before: np.ndarray) -> float:
    """One-sided p-value of "the squared error ``after`` is not larger on average than ``before``".

    The Diebold–Mariano test on the loss differential ``after**2 - before**2`` (shapes (n,), the same
    samples), with its Newey–West variance at Andrews' bandwidth (:func:`mean_t_statistic`): small
    when ``after`` is significantly larger.
    """
    loss = np.asarray(after, float) ** 2 - np.asarray(before, float) ** 2
    return float(normal_sf(mean_t_statistic(loss)))
