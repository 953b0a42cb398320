"""A row of the model and its fit."""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from ..discretize import discretize
from ..model import FopdtModel
from .fit import _element_lag, _element_params, _lag_interval, _RowProblem, _search_row


def _row_response(model: FopdtModel, u: np.ndarray, i: int) -> np.ndarray:
    """Response of row ``i`` of ``model`` to ``u`` from rest, element by element (as
    :func:`mpm_monitor.core.discretize.simulate`).

    ``s(k+1) = a s(k) + b u_j(k - m)`` contributes ``s(k)``, i.e. ``b q^-(m+1) / (1 - a q^-1)``;
    a static element without delay is a feed-through (see :mod:`mpm_monitor.core.discretize`).
    """
    disc = discretize(model)
    out = np.zeros(u.shape[0])
    for j in range(model.n_inputs):
        if disc.active[i, j]:
            m = int(disc.input_lag[i, j]) + 1
            if m < u.shape[0]:
                a = disc.pole[i, j]
                out[m:] += signal.lfilter([disc.numerator[i, j]], [1.0, -a], u[:-m, j])
        if disc.feedthrough[i, j] != 0:
            out += disc.feedthrough[i, j] * u[:, j]
    return out


def _estimate_row(model, u, y, i, specs: dict, n_fit, options, lags0: dict, max_sweeps, skip=None, extra=None,
                  ar0=None, need_cov=True):
    """Fit the located elements ``specs`` (``{input index: _ElementSpec}``) of row ``i``.

    The row's other elements are held at the model's values.  ``skip`` (samples left out at the
    start) defaults to the largest lag searched; fits whose costs are compared must share it.
    Returns the problem and estimate.
    """
    js = sorted(specs)
    held = model
    for j in js:
        held = held.with_element(i, j, gain=0.0)
    z = y[:, i] - _row_response(held, u, i)
    disc = discretize(held)
    fixed_poles = [disc.pole[i, j] for j in range(model.n_inputs) if disc.active[i, j]]
    row_lags = [_element_lag(model.time_constant[i, j], model.delay_samples[i, j])
                for j in range(model.n_inputs) if held.gain[i, j] != 0]
    if skip is None:
        skip = max([specs[j].window[1] for j in js] + row_lags + [1])
    problem = _RowProblem(z, u[:, js], [specs[j] for j in js], n_fit, skip, fixed_poles,
                          options.initial_state == "estimate", options.noise_order, extra)
    if ar0 is not None:
        problem.set_ar(ar0)
    est = _search_row(problem, [lags0[j] for j in js], max_sweeps, ar_iterations=3 if ar0 is None else 1,
                      need_cov=need_cov)
    return problem, est


def _element_summary(problem, est, m, ts, zcrit, chi_crit):
    """Fitted parameters (seconds) and their intervals of element ``m`` of an estimate."""
    fit = est.fit
    k_hat, a_hat, lag_hat = float(fit.gains[m]), float(fit.poles[m]), int(fit.lags[m])
    se_k, se_a = math.sqrt(est.var_gain[m]), math.sqrt(est.var_pole[m])
    after = dict(zip(("gain", "time_constant", "delay"), _element_params(k_hat, a_hat, lag_hat, ts)))
    lo_lag, hi_lag = _lag_interval(est, m, problem.specs[m].window, chi_crit)
    a_lo = min(max(a_hat - zcrit * se_a, 1e-12), a_hat)
    a_hi = max(min(a_hat + zcrit * se_a, 1.0 - 1e-12), a_hat)
    lagged = after["time_constant"] > 0
    tau_iv = [-ts / math.log(a_lo), -ts / math.log(a_hi)] if lagged else [0.0, 0.0]
    shift = 1 if lagged else 0
    interval = {"gain": [k_hat - zcrit * se_k, k_hat + zcrit * se_k], "time_constant": tau_iv,
                "delay": [max(lo_lag - shift, 0) * ts, max(hi_lag - shift, 0) * ts]}
    return after, interval, (k_hat, se_k, a_hat, se_a)
