"""A row of the model and its fit: from the model's elements to the row problem and back.

:func:`_estimate_row` turns the located elements of one output row into a :class:`_RowProblem`
(output minus the response of the row's other elements, held at the model's values) and searches
it; :func:`_element_summary` turns a fitted element back into gain, time constant and delay in
seconds with their intervals.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..discretize import discretize, simulate_elements
from ..model import PlantModel
from .fit import _element_lag, _element_params, _lag_interval, _RowEstimate, _RowProblem, _search_row
from .options import RepairOptions, _TestSettings


@dataclasses.dataclass(frozen=True)
class _RowData:
    """One output row of the record, as every fit of the row reads it.

    Attributes
    ----------
    model : PlantModel
        The model as given: the row's elements that are not fitted are held at its values.
    u : ndarray, shape (n_samples, n_inputs)
        Inputs of the record.
    y : ndarray, shape (n_samples, n_outputs)
        Outputs of the record.
    i : int
        Output index of the row.
    extra : ndarray, shape (n_samples, n_extra), optional
        Nuisance regressors for an unexplained step or drift on the row (see :class:`_RowProblem`).
    shared : dict
        What every fit of the row computes alike, computed once: the row with its located elements
        removed (:func:`_held_row`) and the free responses of the poles (see :class:`_RowProblem`).
    """

    model: PlantModel
    u: np.ndarray
    y: np.ndarray
    i: int
    extra: Optional[np.ndarray] = None
    shared: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

    @property
    def n_samples(self) -> int:
        return self.u.shape[0]

    def name(self, j: Optional[int] = None) -> str:
        """``output`` of the row, or ``output/input`` of its element ``j`` (for the warnings)."""
        out = self.model.outputs[self.i]
        return out if j is None else f"{out}/{self.model.inputs[j]}"


def _row_response(model: PlantModel, u: np.ndarray, i: int) -> np.ndarray:
    """Response of row ``i`` of ``model`` to ``u`` from rest (:func:`mpm_monitor.core.discretize.simulate_elements`)."""
    return simulate_elements(model, u, rows=[i])[:, 0]


def _held_row(row: _RowData, js: tuple):
    """The row without its located elements ``js``: ``z`` (the output minus the response of the
    other elements, from rest), the poles of the other lag elements and their input lags.

    The same for every fit of the row with these elements located, so computed once per row.
    """
    key = ("held", js)
    if key not in row.shared:
        model, u, i = row.model, row.u, row.i
        held = model
        for j in js:
            held = held.with_element(i, j, gain=0.0)
        z = row.y[:, i] - _row_response(held, u, i)
        disc = discretize(held)
        fixed_poles = [disc.pole[i, j] for j in range(model.n_inputs) if disc.active[i, j]]
        row_lags = [_element_lag(model.time_constant[i, j], model.delay_samples[i, j])
                    for j in range(model.n_inputs) if held.gain[i, j] != 0]
        row.shared[key] = (z, fixed_poles, row_lags)
    return row.shared[key]


def _estimate_row(row: _RowData, specs: dict, lags0: dict, n_use: int, options: RepairOptions, max_sweeps: int = 1,
                  skip: Optional[int] = None, ar0=None, need_cov: bool = True):
    """Fit the located elements ``specs`` (``{input index: _ElementSpec}``) of a row.

    The row's other elements are held at the model's values; samples ``0 .. n_use - 1`` are used,
    starting from the input lags ``lags0`` (``{input index: lag}``).  ``skip`` (samples left out at
    the start) defaults to the largest lag searched; fits whose costs are compared must share it.
    ``ar0``, when given, starts the noise model there (one re-estimation instead of three).

    Returns
    -------
    problem : _RowProblem
    est : _RowEstimate
    """
    u = row.u
    js = sorted(specs)
    z, fixed_poles, row_lags = _held_row(row, tuple(js))
    if skip is None:
        skip = max([specs[j].window[1] for j in js] + row_lags + [1])
    problem = _RowProblem(z, u[:, js], [specs[j] for j in js], n_use, skip, fixed_poles,
                          options.initial_state == "estimate", options.noise_order, row.extra, shared=row.shared)
    if ar0 is not None:
        problem.set_ar(ar0)
    est = _search_row(problem, [lags0[j] for j in js], max_sweeps, ar_iterations=3 if ar0 is None else 1,
                      need_cov=need_cov)
    return problem, est


def _element_summary(problem: _RowProblem, est: _RowEstimate, m: int, ts: float, settings: _TestSettings):
    """Fitted parameters (seconds) and their intervals of element ``m`` of an estimate.

    Returns
    -------
    after : dict
        ``gain``, ``time_constant`` (s), ``delay`` (s).
    interval : dict
        ``[lo, hi]`` of each at the settings' level: gain and time constant from the variances of
        the estimate, the delay from the lag profile.
    """
    zcrit, chi_crit = settings.zcrit, settings.chi_crit
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
    return after, interval
