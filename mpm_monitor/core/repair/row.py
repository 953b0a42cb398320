"""A row of the model and its fit: from the model's elements to the row problem and back.

:func:`_estimate_row` turns the located elements of one output row into a :class:`_RowProblem`
(output minus the response of the row's other elements, held at the model's values) and searches
it; :func:`_element_summary` turns a fitted element back into its parameters in seconds (gain,
time constants, lead, delay) with their intervals (:func:`_element_after`: the parameters alone).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..discretize import discretize, simulate_elements
from ..model import PlantModel
from ..segments import GapSegments, through
from .fit import _lag_interval, _RowEstimate, _RowProblem, _search_row
from .forms import _fitted_params, _lag_seconds, _match_lags
from .options import RepairOptions, _TestSettings


@dataclasses.dataclass(frozen=True)
class _RowData:
    """One output row of the record, as every fit of the row reads it.

    Attributes
    ----------
    model : PlantModel
        The model as given: the row's elements that are not fitted are held at its values.
    u : ndarray, shape (n_samples, n_columns)
        The model's columns in the record: inputs, then measured disturbances.
    y : ndarray, shape (n_samples, n_outputs)
        Outputs of the record.
    i : int
        Output index of the row.
    extra : ndarray, shape (n_samples, n_extra), optional
        Nuisance regressors for an unexplained step or drift on the row (see :class:`_RowProblem`).
    shared : dict
        What every fit of the row computes alike, computed once: the row with its located elements
        removed (:func:`_held_row`) and the free responses of the poles (see :class:`_RowProblem`).
    segments : tuple of (int, int), optional
        Data with gaps: the contiguous runs ``(first, end)`` of the samples, each a record of its own
        (simulated from rest at its first sample; see :class:`_RowProblem`).  None: one record.
    delays : dict
        ``{column index: lag}``: the element test's estimate of the lag (samples) at which each located
        element's mismatch acts, where it was given (the lag search reaches it,
        :func:`~.classify._free_spec`).
    """

    model: PlantModel
    u: np.ndarray
    y: np.ndarray
    i: int
    extra: Optional[np.ndarray] = None
    shared: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)
    segments: Optional[tuple] = None
    delays: dict = dataclasses.field(default_factory=dict)
    bridge: Optional[GapSegments] = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def bridged(self) -> bool:
        """Whether the row's held elements run through the short gaps (:func:`_held_row`): a row of a step-response
        model on data with gaps whose segments some short gap joins."""
        return self.bridge is not None and self.model.is_step_response and self.bridge.joined

    @property
    def n_samples(self) -> int:
        return self.u.shape[0]

    def name(self, j: Optional[int] = None) -> str:
        """``output`` of the row, or ``output/column`` of its element ``j`` (for the warnings)."""
        out = self.model.outputs[self.i]
        return out if j is None else f"{out}/{self.model.columns[j]}"


def _row_response(model: PlantModel, u: np.ndarray, i: int, segments=None) -> np.ndarray:
    """Response of row ``i`` of ``model`` to ``u`` from rest (:func:`mpm_monitor.core.discretize.simulate_elements`)
    as :func:`~mpm_monitor.core.segments.through` runs it: with plain ``segments`` from rest at the start of each;
    with a :class:`GapSegments` from rest at the start of each of its runs, through their short gaps with the
    columns held (or filled where known)."""
    return through(u, lambda x: simulate_elements(model, x, rows=[i])[:, 0], segments, column=slice(None))


def _without(model: PlantModel, i: int, js) -> PlantModel:
    """``model`` with the elements ``(i, j), j in js`` removed (no effect)."""
    for j in js:
        if model.is_step_response:
            model = model.with_element(i, j, step_response=np.zeros(model.step_length))
        else:
            model = model.with_element(i, j, gain=0.0)
    return model


#: Fraction of a step-response element's impulse response left when its memory is taken as over.
_TAIL_FRACTION = 1e-3


def _held_memory(model: PlantModel, i: int, j: int) -> int:
    """Samples over which the columns before the record act on row ``i`` through the held element
    ``(i, j)`` other than through the free responses of its lags: its input lag; for an element of a
    step-response model, the samples until its impulse response (its numerator) has run out to
    :data:`_TAIL_FRACTION` of its sum."""
    el = model.discrete_element(i, j)
    if not model.is_step_response:
        return el.input_lag
    h = np.abs(el.num)
    tail = np.cumsum(h[::-1])[::-1]                 # tail[k] = sum of |h_l| for l >= k
    return el.delay + int(np.flatnonzero(tail > _TAIL_FRACTION * tail[0])[-1]) + 1


@dataclasses.dataclass(frozen=True)
class _HeldRow:
    """Row ``i`` with its located elements removed, the same for every fit of these elements.

    Attributes
    ----------
    z : ndarray, shape (n_samples,)
        The output minus the response of the row's other elements (held at the model's values), from rest
        (at each segment's start; on a :attr:`~_RowData.bridged` row at each run's, through its short gaps).
    lag_poles : dict
        ``{pole: multiplicity}`` of the other elements' lags (:meth:`DiscreteElements.lag_poles`).
    memories : list of int
        :func:`_held_memory` of each other element.
    """

    z: np.ndarray
    lag_poles: dict
    memories: list


def _held_row(row: _RowData, js: tuple) -> _HeldRow:
    """:class:`_HeldRow` of ``row`` without the elements ``js``, computed once per row and ``js``."""
    key = ("held", tuple(int(j) for j in js))
    if key not in row.shared:
        model, i = row.model, row.i
        held = _without(model, i, js)
        row.shared[key] = _HeldRow(
            z=row.y[:, i] - _row_response(held, row.u, i, row.bridge if row.bridged else row.segments),
            lag_poles=discretize(held).lag_poles(i),
            memories=[_held_memory(held, i, j) for j in range(model.n_columns) if held.present[i, j]])
    return row.shared[key]


def _default_skip(row: _RowData, specs: dict) -> int:
    """Samples left out at the start of a fit of the located elements ``specs``: the largest input lag
    searched, or the longest memory of the row's held elements (:func:`_held_memory`), at least 1; on a
    :attr:`~_RowData.bridged` row the held elements' memory is left out at the start of each run only
    (:func:`_fit_segments`)."""
    memories = [] if row.bridged else _held_row(row, tuple(sorted(specs))).memories
    return max([specs[j].window[1] for j in specs] + memories + [1])


def _fit_segments(row: _RowData, js, skip: int):
    """The segments a fit of the located elements ``js`` with ``skip`` takes (:class:`_RowProblem`): the row's; on a
    :attr:`~_RowData.bridged` row none starts before its run's first row plus what the held elements' memory
    (:func:`_held_memory`) exceeds ``skip`` (the columns before the run are unknown; rows, not samples: a gap only
    adds to the distance), and the later segments of a run keep their samples: the held elements run through the
    short gap before them."""
    if not row.bridged:
        return row.segments
    memory = max(_held_row(row, tuple(sorted(js))).memories + [0])
    late = max(0, memory - int(skip))
    starts = [row.bridge.runs[r][0] for r in row.bridge.run_of]
    return tuple((max(a, first + late), b) for (a, b), first in zip(row.segments, starts))


def _estimate_row(row: _RowData, specs: dict, lags0: dict, n_use: int, options: RepairOptions, max_sweeps: int = 1,
                  skip: Optional[int] = None, ar0=None):
    """Fit the located elements ``specs`` (``{column index: _ElementSpec}``) of a row.

    The row's other elements are held at the model's values (their free responses from all their
    lags' poles, repeated poles included); samples ``0 .. n_use - 1`` are used, starting from the
    input lags ``lags0`` (``{column index: lag}``).  ``skip`` (samples left out at the start) defaults
    to the largest lag searched or held memory of the row (:func:`_held_memory`); fits whose costs
    are compared must share it.  ``ar0``, when given, starts the noise model there (one
    re-estimation instead of three).

    Returns
    -------
    problem : _RowProblem
    est : _RowEstimate
    """
    js = sorted(specs)
    held = _held_row(row, tuple(js))
    if skip is None:
        skip = _default_skip(row, specs)
    problem = _RowProblem(held.z, row.u[:, js], [specs[j] for j in js], n_use, skip, held.lag_poles,
                          options.initial_state == "estimate", options.noise_order, row.extra,
                          sample_time=row.model.sample_time, shared=row.shared, segments=_fit_segments(row, js, skip),
                          segment_levels=bool(row.model.integrating_outputs[row.i]))
    if ar0 is not None:
        problem.set_ar(ar0)
    est = _search_row(problem, [lags0[j] for j in js], max_sweeps, ar_iterations=3 if ar0 is None else 1)
    return problem, est


def _pole_interval(a: float, se: float, zcrit: float, ts: float) -> list:
    """Interval (s) of the time constant of pole ``a`` with standard error ``se``."""
    a_lo = min(max(a - zcrit * se, 1e-12), a)
    a_hi = max(min(a + zcrit * se, 1.0 - 1e-12), a)
    return [-ts / math.log(a_lo), -ts / math.log(a_hi)]


def _element_after(problem: _RowProblem, est: _RowEstimate, m: int, ts: float,
                   reference: Optional[dict] = None) -> dict:
    """The ``after`` of :func:`_element_summary` alone: the fitted parameters of element ``m``, without
    their intervals (no covariance, no lag profile)."""
    fit, form = est.fit, problem.specs[m].form
    after = _fitted_params(form, float(fit.gains[m]), [float(a) for a in fit.poles[problem.slices[m]]],
                           float(fit.leads[m]), int(fit.lags[m]), ts)
    if form.n_lags == 2:
        _match_lags(after, {}, reference)
    return after


def _element_summary(problem: _RowProblem, est: _RowEstimate, m: int, ts: float, settings: _TestSettings,
                     reference: Optional[dict] = None, no_lag: bool = False):
    """Fitted parameters (seconds) and their intervals of element ``m`` of an estimate.

    The two lags of a second-order element are named after those of ``reference``
    (:func:`~mpm_monitor.core.repair.forms._match_lags`).  ``no_lag``: a first-order element is read as
    the pure gain its fit shows (:meth:`~mpm_monitor.core.repair.classify._FreeFit.lost_lag`), whatever
    its pole.

    Returns
    -------
    after : dict
        Every parametric key (:func:`~mpm_monitor.core.repair.forms._fitted_params`).
    interval : dict
        ``[lo, hi]`` of the gain, the time constant and the delay, and of ``time_constant2`` and
        ``lead`` where the element's form has them, at the settings' level: from the covariance of
        the estimate, the delay from the lag profile.
    """
    zcrit, chi_crit = settings.zcrit, settings.chi_crit
    fit, spec = est.fit, problem.specs[m]
    form = spec.form
    k_hat, lag_hat = float(fit.gains[m]), int(fit.lags[m])
    poles = [float(a) for a in fit.poles[problem.slices[m]]]
    var_gain, var_lead, var_poles = problem.variances(est.cov, fit, m)
    after = _fitted_params(form, k_hat, poles, float(fit.leads[m]), lag_hat, ts, no_lag=no_lag)
    lo_lag, hi_lag = _lag_interval(est, m, spec.window, chi_crit)
    se_k = math.sqrt(var_gain)
    if form.first_order:
        lagged = after["time_constant"] > 0
        tau_iv = _pole_interval(poles[0], math.sqrt(var_poles[0]), zcrit, ts) if lagged else [0.0, 0.0]
        shift = 1 if lagged else 0
    else:
        taus = [_pole_interval(a, math.sqrt(v), zcrit, ts) for a, v in zip(poles, var_poles)]
        tau_iv = taus[0] if taus else [0.0, 0.0]
        shift = form.offset
    interval = {"gain": [k_hat - zcrit * se_k, k_hat + zcrit * se_k], "time_constant": tau_iv,
                "delay": [_lag_seconds(max(lo_lag - shift, 0), ts), _lag_seconds(max(hi_lag - shift, 0), ts)]}
    if form.n_lags == 2:
        interval["time_constant2"] = taus[1]
    if form.lead:
        se_l = math.sqrt(var_lead)
        interval["lead"] = [after["lead"] - zcrit * se_l, after["lead"] + zcrit * se_l]
    if form.n_lags == 2:
        _match_lags(after, interval, reference)
    return after, interval
