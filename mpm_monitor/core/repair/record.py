"""The record a repair reads: the data and the model as every step of :func:`~.model_repair.repair_model`
takes them, the split into the fit and the held-out part, and the prediction error about its level over
the held-out part."""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import numpy as np

from ..discretize import model_columns
from ..errors import InputError
from ..logged_data import LoggedData, check_loop_data, diverging_outputs, moving_columns
from ..model import PlantModel
from ..segments import GapSegments, centred_fill
from ..signals import (LoopSignals, compute_signals, scored_segments, segment_signals, segments_mask,
                       unknown_starts)
from .holdout import ar_one_step_errors
from .options import RepairOptions, _TestSettings, is_int


def _project_out(x: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``x`` minus its least-squares fit on the columns ``cols``."""
    coef, *_ = np.linalg.lstsq(cols, x, rcond=None)
    return x - cols @ coef


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def _holdout_residual(d, n_fit: int, extra: Optional[np.ndarray] = None) -> np.ndarray:
    """The prediction error ``d`` (shape (n_samples,)) over the held-out part, about its level, shape
    (n_samples - n_fit,).

    The level of a prediction error is a nuisance the fit of the repair estimates (an offset; on an
    integrating output the arbitrary level of the output): like any parameter of the fit, it is
    taken from the fit part (samples ``0 .. n_fit - 1``, its mean there) and carried over to the
    held-out part.  With ``extra`` (shape (n_samples, n_extra): the unexplained step or ramp of the
    row) an offset and those regressors are projected out over the held-out part instead.
    """
    d = np.asarray(d, float)
    hold = d[n_fit:]
    if hold.size == 0:
        return hold
    if extra is not None:
        return _project_out(hold, np.column_stack([np.ones(hold.shape[0]), extra[n_fit:]]))
    return hold - np.mean(d[:n_fit])


def _about_level(d, n_fit: int, keep: Optional[np.ndarray], extra: Optional[np.ndarray]) -> np.ndarray:
    """``d`` (shape (n_samples,)) about its level as the held-out check takes it, over the whole record: the
    mean of the fit part's samples ``keep`` (all when None) removed, or with ``extra`` an offset and those
    regressors projected out over the fit part and over the held-out part, each on its own."""
    d = np.asarray(d, float)
    mask = np.ones(d.shape[0], bool) if keep is None else np.asarray(keep, bool)
    fit = mask & (np.arange(d.shape[0]) < n_fit)
    if extra is None:
        return d - np.mean(d[fit])
    out = d.copy()
    for part in (fit, mask & ~fit):
        if part.any():
            out[part] = _project_out(d[part], np.column_stack([np.ones(np.count_nonzero(part)), extra[part]]))
    return out

def _check_inputs(model: PlantModel, data: LoggedData, located, signals):
    """The located pairs, sorted and unique, once the data (:func:`~mpm_monitor.core.logged_data.check_loop_data`),
    the pairs and the signals fit the model; else :class:`InputError` naming what does not."""
    check_loop_data(model, data)
    n = data.n_samples
    out = []
    for item in located:
        try:
            i, j = (int(v) for v in item)
        except (TypeError, ValueError):
            raise InputError(f"repair: located element {item!r}: expected a pair (output index, column index)") from None
        if not (0 <= i < model.n_outputs and 0 <= j < model.n_columns):
            raise InputError(f"repair: located element ({i}, {j}): expected 0 <= output < {model.n_outputs} "
                             f"and 0 <= column < {model.n_columns} (inputs, then measured disturbances)")
        if (i, j) not in out:
            out.append((i, j))
    if signals is not None:
        for key in ("yhat", "d"):
            if np.shape(getattr(signals, key)) != (n, model.n_outputs):
                raise InputError(f"repair: signals.{key}: expected shape ({n}, {model.n_outputs}), "
                                 f"got {np.shape(getattr(signals, key))}")
    return sorted(out)


def _check_delays(delays, located) -> dict:
    """``{(output, column): lag}`` of the located elements from ``delays`` (the element test's estimates of
    the lag of each element's mismatch, samples; None: none), once every value is an integer >= 0; else
    :class:`InputError`.  Estimates of elements not located are dropped."""
    if delays is None:
        return {}
    try:
        items = list(delays.items())
    except AttributeError:
        raise InputError(f"repair: delays: expected a mapping (output index, column index) -> lag in samples, "
                         f"got {type(delays).__name__}") from None
    out = {}
    for key, lag in items:
        if not (is_int(lag) and lag >= 0):
            raise InputError(f"repair: delays[{key!r}]: expected an integer number of samples >= 0, got {lag!r}")
        try:
            pair = tuple(int(v) for v in key)
        except (TypeError, ValueError):
            raise InputError(f"repair: delays key {key!r}: expected a pair (output index, column index)") from None
        if pair in located:
            out[pair] = int(lag)
    return out


@dataclasses.dataclass(frozen=True)
class _Record:
    """The record and the model as every step of :func:`~.model_repair.repair_model` reads them.

    Attributes
    ----------
    model : PlantModel
        The model as given.
    data : LoggedData
    u, y : ndarray, shape (n_samples, n_columns) and (n_samples, n_outputs)
        The model's columns (``data.u``, then ``data.dv``) and ``data.y`` as float arrays.
    signals : LoopSignals
        Of the model as given on the data.
    d0 : ndarray, shape (n_samples, n_outputs)
        ``signals.d`` as a float array.
    settings : _TestSettings
    n_fit : int
        Samples ``0 .. n_fit - 1`` are the fit part, the rest is held out.
    holdout_before : dict
        ``{output name: RMS of d0 over the held-out part about its level}`` (empty without a
        held-out part; see :meth:`holdout`).
    segments : tuple of (int, int) or None
        Data with gaps (``data.t`` skips samples): its contiguous runs of samples, each simulated and
        fitted as a record of its own (from rest, with its own offset and free responses); the
        split into the fit and the held-out part is at sample ``n_fit`` of the samples as they are.
        None: one record.
    tests : dict
        ``{output index: (d, segments, test)}``: the last :func:`~.disturbance.unexplained_disturbance` of each
        output, on its prediction error ``d`` and the scored ``segments`` (see :func:`~.model_repair._evaluate`),
        reused while they stay the same.
    delays : dict
        ``{(output index, column index): lag}``: the element test's estimates of the lag (samples) of the
        located elements' mismatches, where given (see :meth:`row_delays`).
    """

    model: PlantModel
    data: LoggedData
    u: np.ndarray
    y: np.ndarray
    signals: LoopSignals
    d0: np.ndarray
    settings: _TestSettings
    n_fit: int
    holdout_before: dict
    segments: Optional[tuple] = None
    tests: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)
    delays: dict = dataclasses.field(default_factory=dict)

    @property
    def options(self) -> RepairOptions:
        return self.settings.options

    def row_delays(self, i: int) -> dict:
        """``{column index: lag}`` of :attr:`delays` in row ``i`` (what :class:`~.row._RowData` takes)."""
        return {j: lag for (ii, j), lag in self.delays.items() if ii == i}

    @functools.cached_property
    def spread(self) -> np.ndarray:
        """The outputs' standard deviations over the record, shape (n_outputs,): the scales of the disturbance
        tests (:func:`~.model_repair._evaluate`), computed once."""
        return np.std(np.asarray(self.y, float), axis=0)

    @functools.cached_property
    def moving(self) -> np.ndarray:
        """Whether each output moves over the record (:func:`~mpm_monitor.core.logged_data.moving_columns`),
        shape (n_outputs,): one that never moves (a stuck sensor) is not tested for a disturbance."""
        return moving_columns(np.asarray(self.y, float))

    @functools.cached_property
    def diverged(self) -> bool:
        """Some output grows without bound over the record (:func:`~mpm_monitor.core.logged_data.diverging_outputs`):
        a loop that diverged, where the held-out check's tests mean nothing (:func:`~.validation._compare_on_holdout`)."""
        return bool(diverging_outputs(self.model.outputs, np.asarray(self.y, float)))

    @property
    def n(self) -> int:
        return self.data.n_samples

    @property
    def n_hold(self) -> int:
        return self.n - self.n_fit

    def scored(self, *models: PlantModel) -> Optional[np.ndarray]:
        """The samples the held-out check is taken over: with gaps, all but the first samples of every
        segment after a gap that still depend on the state the gap leaves (:meth:`scored_segments` as a
        mask); None without gaps (every sample)."""
        if self.segments is None:
            return None
        return segments_mask(self.scored_segments(*models), self.n)

    def scored_segments(self, *models: PlantModel, settled: bool = False) -> Optional[list]:
        """:func:`~mpm_monitor.core.signals.scored_segments` of the record's segments (None without gaps)."""
        if self.segments is None:
            return None
        return scored_segments(self.segments, *models, settled=settled, restarts=self.restarts)

    @functools.cached_property
    def bridge(self) -> Optional[GapSegments]:
        """With gaps and the option ``max_gap``, the record's segments as :class:`~mpm_monitor.core.segments.GapSegments`
        (the runs the model is simulated through, the known columns inside their gaps filled, ``[u | dv]``, NaN where
        not known): what a fit of a step-response row runs its held elements through (:func:`~.row._held_row`);
        None without gaps or ``max_gap``."""
        if self.segments is None or self.options.max_gap is None:
            return None
        fill = self.data.fill_on_grid()
        bridge = GapSegments(self.segments, self.data.grid_index, self.options.max_gap,
                             None if fill is None else fill[0], None if fill is None else fill[1])
        return centred_fill(bridge, np.zeros(self.u.shape[1]))

    @property
    def restarts(self) -> Optional[list]:
        """With gaps, the segments whose start still carries an unknown (after a gap longer than the
        option ``max_gap``, or with a sample of unknown columns whose response is not fitted; every segment
        after the first when ``max_gap`` is None): :func:`~mpm_monitor.core.signals.unknown_starts` of the
        model as given."""
        if self.segments is None or self.options.max_gap is None:
            return None
        return unknown_starts(self.segments, self.data.grid_index, self.options.max_gap, self.data.fill_on_grid(),
                              self.model)

    @property
    def levels(self) -> Optional[list]:
        """With gaps, the level of every segment: segments that no restart (:attr:`restarts`) separates
        share one (the model runs through the gaps between them, and the response to their unknown
        columns is fitted), ``[0, 0, 1, ...]``; None without gaps."""
        if self.segments is None:
            return None
        restarts = self.restarts
        restarts = set(range(1, len(self.segments))) if restarts is None else set(restarts)
        return [int(x) for x in np.cumsum([k in restarts for k in range(len(self.segments))])]

    def holdout(self, d: np.ndarray, keep: Optional[np.ndarray], extra: Optional[np.ndarray] = None,
                row: Optional[int] = None) -> float:
        """RMS of :meth:`holdout_residual` of ``d`` (shape (n_samples,)) over the samples ``keep`` (:meth:`scored`;
        nan without a held-out part)."""
        return _rms(self.holdout_residual(d, keep, extra, row))

    def holdout_residual(self, d: np.ndarray, keep: Optional[np.ndarray],
                         extra: Optional[np.ndarray] = None, row: Optional[int] = None) -> np.ndarray:
        """:func:`_holdout_residual` of ``d`` (shape (n_samples,)) over the samples ``keep`` (:meth:`scored`):
        shape (held-out samples kept,).

        On data with gaps, the prediction error of an integrating output (``row``, its index) is taken about each
        segment's own level in the held-out part: the model's columns are held through a gap while the plant
        received others, and on an integrating output (whose response to them is not fitted,
        :mod:`~mpm_monitor.core.gap_inputs`) that moves the level of the error after every gap, by as much as the
        element's gain.  About one level carried over from the fit part, a repaired integrator of the plant's
        gain (twice the model's) lost to the model as given (RMS 0.191 vs 0.142) on every record with 1 % of its
        samples dropped, while it predicted one step ahead significantly better (an outside check).  The repair's
        fit already has an offset per segment on such a row."""
        if self.segments is not None and row is not None and bool(self.model.integrating_outputs[row]) \
                and extra is None:
            return self._holdout_by_segment(np.asarray(d, float), keep)
        if keep is None:
            return _holdout_residual(d, self.n_fit, extra)
        return _holdout_residual(d[keep], int(np.count_nonzero(keep[:self.n_fit])),
                                 None if extra is None else extra[keep])

    def _holdout_by_segment(self, d: np.ndarray, keep: Optional[np.ndarray]) -> np.ndarray:
        """The held-out samples ``keep`` of ``d`` (shape (n_samples,)), each segment's about its own mean there
        (the segments cover the samples in order, so the pieces stacked are the held-out samples in order)."""
        pieces = []
        for a, b in self.segments:
            part = d[max(a, self.n_fit):b]
            if keep is not None:
                part = part[np.asarray(keep[max(a, self.n_fit):b], bool)]
            if part.size:
                pieces.append(part - np.mean(part))
        return np.concatenate(pieces) if pieces else d[:0]

    def one_step_holdout(self, d: np.ndarray, keep: Optional[np.ndarray], segments: Optional[list],
                         extra: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """The one-step errors of ``d`` (shape (n_samples,)) over the held-out part under an AR noise model of
        the option ``noise_order`` fitted on the fit part (:func:`~.holdout.ar_one_step_errors`), ``d``
        taken about its level as :meth:`holdout_residual` takes it; with gaps over the scored ``segments``
        (:meth:`scored_segments`) and the samples ``keep``.  None when too few samples."""
        return ar_one_step_errors(_about_level(d, self.n_fit, keep, extra), self.n_fit, self.options.noise_order,
                                  segments)

    def signals_of(self, model: PlantModel) -> LoopSignals:
        """:func:`compute_signals` of ``model`` on the record (the rows where it equals the model as
        given taken from :attr:`signals`); with gaps each segment from its own start."""
        if self.segments is not None:
            return segment_signals(model, self.data.r, self.data.u, self.y, self.segments,
                                   initial_state=self.options.initial_state, dv=self.data.dv,
                                   grid=self.data.grid_index, max_gap=self.options.max_gap,
                                   fill=self.data.fill_on_grid())
        return compute_signals(model, self.data.r, self.data.u, self.y, initial_state=self.options.initial_state,
                               dv=self.data.dv, like=(self.model, self.signals))


def _set_up(model: PlantModel, data: LoggedData, options: RepairOptions,
            signals: Optional[LoopSignals], delays: Optional[dict] = None) -> _Record:
    """The record of checked inputs: float arrays, the signals of the model, the split, the levels
    (``delays``: checked by :func:`_check_delays`)."""
    u, y = model_columns(np.asarray(data.u, float), np.asarray(data.dv, float)), np.asarray(data.y, float)
    n = data.n_samples
    segments = data.segments
    segments = tuple(segments) if len(segments) > 1 else None
    if signals is None and segments is not None:
        signals = segment_signals(model, data.r, data.u, y, segments, initial_state=options.initial_state, dv=data.dv,
                                  grid=data.grid_index, max_gap=options.max_gap, fill=data.fill_on_grid())
    elif signals is None:
        signals = compute_signals(model, data.r, data.u, y, initial_state=options.initial_state, dv=data.dv)
    d0 = np.asarray(signals.d, float)
    n_hold = _holdout_samples(n, options)
    n_fit = n - n_hold
    rec = _Record(model=model, data=data, u=u, y=y, signals=signals, d0=d0, settings=_TestSettings.of(options),
                  n_fit=n_fit, holdout_before={}, segments=segments, delays=dict(delays or {}))
    if n_hold > 0:
        keep = rec.scored(model)
        rec.holdout_before.update({model.outputs[i]: rec.holdout(d0[:, i], keep, row=i) for i in range(model.n_outputs)})
    return rec


def _min_fit(model: PlantModel, options: RepairOptions) -> int:
    """The fewest samples of the fit part with which located elements are re-estimated."""
    return max(200, 20 * (2 * model.n_columns + options.noise_order + 5))


def _holdout_samples(n: int, options: RepairOptions) -> int:
    """The samples at the end of a record of ``n`` held out of the fit to validate the repair (:func:`_set_up`)."""
    return int(round(options.holdout_fraction * n))


def samples_for_repair(model: PlantModel, options: RepairOptions) -> int:
    """The fewest samples of a record on which the repair re-estimates located elements: a fit part of
    :func:`_min_fit` samples once the held-out last ``holdout_fraction`` is set apart (:func:`_holdout_samples`)."""
    min_fit = _min_fit(model, options)
    n = min_fit
    while n - _holdout_samples(n, options) < min_fit:
        n += 1
    return n


def _located_in_row(located: list, i: int) -> list:
    return [j for (ii, j) in located if ii == i]
