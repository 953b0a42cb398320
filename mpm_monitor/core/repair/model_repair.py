"""repair_model: set up the record, repair each row, redo rows with an unexplained step or drift,
and assemble the result.

Each output row with located elements is classified (:mod:`.classify`), its repair fitted on the
first part of the record (:mod:`.refit`), validated on the held-out last part, and refitted on
the whole record.  The residual of the repaired model is then tested for an unexplained step or
drift on every output (:mod:`.disturbance`); a repaired row where one shows is processed again
with the step (ramp) as a nuisance regressor, so that it does not bias the elements.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional, Sequence

import numpy as np

from ..discretize import model_columns
from ..errors import ConfigurationError, InputError
from ..logged_data import LoggedData, check_loop_data, in_deviations, moving_columns, t_text
from ..model import PlantModel
from ..parallel import split_map
from ..signals import (LoopSignals, compute_signals, error_rms, packed, scored_segments, segment_signals,
                       segments_mask, unknown_starts)
from ..statistics import holm_adjust
from .classify import _classify_row
from .disturbance import not_tested, unexplained_disturbance
from .fit import _TooShort
from .forms import unsettled_warning
from .holdout import ar_one_step_errors, loss_rise_p_value
from .options import RepairOptions, _TestSettings
from .refit import _fit_repair, _refit_on_all
from .result import ElementVerdict, RepairResult, _unchanged_entry
from .row import _RowData


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


def _holdout_rms(d, n_fit: int, extra: Optional[np.ndarray] = None) -> float:
    """RMS of :func:`_holdout_residual` (nan without a held-out part)."""
    return _rms(_holdout_residual(d, n_fit, extra))


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


def _fit_percent(y, yhat, about_level: bool = False) -> float:
    """``100 (1 - ||y - yhat|| / ||y - mean y||)``; with ``about_level`` (an integrating output, whose
    level is arbitrary) the error taken about its mean."""
    if not moving_columns(y):              # an output that never moves: no variance to explain (its mean's
        return float("nan")                # rounding gave a "fit" of -1e18 % for one held at 0.1)
    den = np.linalg.norm(y - np.mean(y))
    err = y - yhat
    if about_level:
        err = err - np.mean(err)
    return float(100.0 * (1.0 - np.linalg.norm(err) / den))


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


@dataclasses.dataclass(frozen=True)
class _Record:
    """The record and the model as every step of :func:`repair_model` reads them.

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
        held-out part; see :func:`_holdout_rms`).
    segments : tuple of (int, int) or None
        Data with gaps (``data.t`` skips samples): its contiguous runs of samples, each simulated and
        fitted as a record of its own (from rest, with its own offset and free responses); the
        split into the fit and the held-out part is at sample ``n_fit`` of the samples as they are.
        None: one record.
    tests : dict
        ``{output index: (d, segments, test)}``: the last :func:`unexplained_disturbance` of each
        output, on its prediction error ``d`` and the scored ``segments`` (see :func:`_evaluate`),
        reused while they stay the same.
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

    @property
    def options(self) -> RepairOptions:
        return self.settings.options

    @functools.cached_property
    def spread(self) -> np.ndarray:
        """The outputs' standard deviations over the record, shape (n_outputs,): the scales of the disturbance
        tests (:func:`_evaluate`), computed once."""
        return np.std(np.asarray(self.y, float), axis=0)

    @functools.cached_property
    def moving(self) -> np.ndarray:
        """Whether each output moves over the record (:func:`~mpm_monitor.core.logged_data.moving_columns`),
        shape (n_outputs,): one that never moves (a stuck sensor) is not tested for a disturbance."""
        return moving_columns(np.asarray(self.y, float))

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

    @property
    def restarts(self) -> Optional[list]:
        """With gaps, the segments whose start still carries an unknown (after a gap longer than the
        option ``max_gap``, or with a sample of unknown columns; every segment after the first when
        ``max_gap`` is None): :func:`~mpm_monitor.core.signals.unknown_starts`."""
        if self.segments is None or self.options.max_gap is None:
            return None
        return unknown_starts(self.segments, self.data.grid_index, self.options.max_gap, self.data.fill_on_grid())

    def holdout(self, d: np.ndarray, keep: Optional[np.ndarray], extra: Optional[np.ndarray] = None) -> float:
        """:func:`_holdout_rms` of ``d`` (shape (n_samples,)) over the samples ``keep`` (:meth:`scored`)."""
        return _rms(self.holdout_residual(d, keep, extra))

    def holdout_residual(self, d: np.ndarray, keep: Optional[np.ndarray],
                         extra: Optional[np.ndarray] = None) -> np.ndarray:
        """:func:`_holdout_residual` of ``d`` (shape (n_samples,)) over the samples ``keep`` (:meth:`scored`):
        shape (held-out samples kept,)."""
        if keep is None:
            return _holdout_residual(d, self.n_fit, extra)
        return _holdout_residual(d[keep], int(np.count_nonzero(keep[:self.n_fit])),
                                 None if extra is None else extra[keep])

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


@dataclasses.dataclass
class _RowOutcome:
    """What the processing of one row gave.

    Attributes
    ----------
    elements : dict
        ``{j: ElementVerdict}`` of the row's located elements.
    warnings : list of str
    check : _HoldoutCheck or None
        The row's held-out check (None when no repair was validated).
    """

    elements: dict
    warnings: list
    check: Optional["_HoldoutCheck"] = None

    @property
    def holdout_after(self) -> Optional[float]:
        """RMS of the row's held-out prediction error with the candidate (None when not validated)."""
        return None if self.check is None else self.check.after

    @property
    def holdout_before(self) -> Optional[float]:
        """RMS of the row's held-out prediction error with the model as given (None when not validated)."""
        return None if self.check is None else self.check.before


@dataclasses.dataclass
class _Findings:
    """What the result lists, filled in as the repair goes.

    Attributes
    ----------
    changes : list of dict
        The ``changes`` entries (see :class:`RepairResult`).
    kinds : dict
        ``{(i, j): kind}``.
    warnings : list of str
    """

    changes: list = dataclasses.field(default_factory=list)
    kinds: dict = dataclasses.field(default_factory=dict)
    warnings: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class _Evaluation:
    """The model with the accepted repairs, its signals, and the disturbance test of every output."""

    model: PlantModel
    signals: LoopSignals
    tests: dict


def _set_up(model: PlantModel, data: LoggedData, options: RepairOptions,
            signals: Optional[LoopSignals]) -> _Record:
    """The record of checked inputs: float arrays, the signals of the model, the split, the levels."""
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
    n_hold = int(round(options.holdout_fraction * n))
    n_fit = n - n_hold
    rec = _Record(model=model, data=data, u=u, y=y, signals=signals, d0=d0, settings=_TestSettings.of(options),
                  n_fit=n_fit, holdout_before={}, segments=segments)
    if n_hold > 0:
        keep = rec.scored(model)
        rec.holdout_before.update({model.outputs[i]: rec.holdout(d0[:, i], keep) for i in range(model.n_outputs)})
    return rec


def _min_fit(model: PlantModel, options: RepairOptions) -> int:
    """The fewest samples of the fit part with which located elements are re-estimated."""
    return max(200, 20 * (2 * model.n_columns + options.noise_order + 5))


def _rows_to_repair(rec: _Record, located: list, found: _Findings) -> list:
    """The rows with located elements, or none when the fit part is too short (then every located
    element gets an unchanged entry in ``found``); warnings about the set-up."""
    options, model, n_fit = rec.options, rec.model, rec.n_fit
    warnings = found.warnings
    rows = sorted({i for i, _ in located})
    min_fit = _min_fit(model, options)
    if located and n_fit < min_fit:
        warnings.append(f"Only {n_fit} samples are available for re-estimating the located elements "
                        f"(at least {min_fit} needed); no element was changed.")
        for (i, j) in located:
            found.kinds[(i, j)] = "unknown"
            found.changes.append(_unchanged_entry(model, i, j, "too few samples"))
        rows = []
    if located and options.holdout_fraction == 0:
        warnings.append("No held-out data (holdout_fraction = 0): the repair was not validated on data "
                        "outside the fit.")
    return rows


def _repair_row(row: _RowData, js, n_fit: int, settings: _TestSettings, classified: Optional[tuple] = None):
    """Classify the located elements ``js`` of the row on the whole record (or take ``classified``,
    what :func:`_classify_row` gave for them), then fit their repair on samples ``0 .. n_fit - 1``.

    Returns
    -------
    verdicts : dict
        ``{j: ElementVerdict}``; the intervals of the parameters the repair fit frees are still those
        of the classification.
    warnings : list of str
    repair_fit : _RepairFit or None
        The repair fit (:func:`_fit_repair`), whose intervals replace those of its free parameters
        unless the refit on the whole record does.
    """
    free, verdicts, warnings = classified if classified is not None else _classify_row(row, js, settings)
    return verdicts, warnings, _fit_repair(free, verdicts, n_fit, settings)


#: The output-error alternative of a row's repair is tried when a repaired element's gain or time
#: constant moved by more than this factor (or the gain changed sign) ...
OUTPUT_ERROR_FACTOR = 3.0
#: ... and the repaired row's simulation error over the fit part is above this fraction of the model's
#: (the prediction-error fit's AR noise model may have taken what an element of the wrong structure
#: cannot: a second lag repaired as one lag, its gain driven towards 0) ...
OUTPUT_ERROR_TRY = 0.5
#: ... and taken when its simulation error over the fit part is below the other's by this factor.
OUTPUT_ERROR_MARGIN = 1.25


def _far_moved(model: PlantModel, i: int, j: int, after: dict) -> bool:
    """Whether the repaired element's gain or time constant is more than :data:`OUTPUT_ERROR_FACTOR`
    times off the model's (or its gain changed sign); an element the model lacks is not."""
    before = model.element(i, j)
    g0, g1 = float(before.get("gain", 0.0)), float(after.get("gain", 0.0))
    if g0 == 0.0:
        return False
    if g1 == 0.0 or (g0 > 0) != (g1 > 0) or not 1 / OUTPUT_ERROR_FACTOR <= g1 / g0 <= OUTPUT_ERROR_FACTOR:
        return True
    t0, t1 = float(before.get("time_constant", 0.0)), float(after.get("time_constant", 0.0))
    return t0 > 0 and t1 > 0 and not 1 / OUTPUT_ERROR_FACTOR <= t1 / t0 <= OUTPUT_ERROR_FACTOR


def _fit_part_rms(rec: _Record, i: int, elements: dict) -> tuple:
    """RMS of the simulation error of row ``i`` over the fit part (about its level), with the applied
    elements of ``elements`` and with the model as given: ``(after, before)``."""
    candidate = rec.model
    for j, el in elements.items():
        if el.apply:
            candidate = el.applied_to(candidate, i, j)
    keep = rec.scored(rec.model, candidate)
    fit = np.arange(rec.n) < rec.n_fit
    if keep is not None:
        fit &= keep

    def rms(d):
        x = np.asarray(d, float)[fit]
        return _rms(x - np.mean(x)) if x.size else float("nan")

    return rms(rec.signals_of(candidate).d[:, i]), rms(rec.d0[:, i])


@dataclasses.dataclass(frozen=True)
class _HoldoutCheck:
    """What the held-out check of one row found (:func:`_compare_on_holdout`).

    Attributes
    ----------
    accepted : bool
    after, before : float or None
        RMS of the held-out simulation error (about its level) with the candidate and with the model as
        given; None when the held-out part holds no scored sample.
    one_step_after, one_step_before : float or None
        RMS of the held-out one-step errors under each model's own AR noise model (:meth:`_Record.one_step_holdout`);
        None when not computed.
    p_rise : float or None
        One-sided p-value of a rise of the simulation error (:func:`~.holdout.loss_rise_p_value`), when the
        one-step errors were consulted (the simulation error did not fall, the one-step error did).
    p_one_step : float or None
        One-sided p-value of "the candidate's one-step error is not smaller", then.
    one_step : bool
        Accepted on the one-step errors (the simulation error did not fall).
    """

    accepted: bool
    after: Optional[float] = None
    before: Optional[float] = None
    one_step_after: Optional[float] = None
    one_step_before: Optional[float] = None
    p_rise: Optional[float] = None
    p_one_step: Optional[float] = None
    one_step: bool = False


def _compare_on_holdout(rec: _Record, i: int, candidate: PlantModel,
                        extra: Optional[np.ndarray] = None) -> _HoldoutCheck:
    """The held-out check of row ``i`` of ``candidate`` against the model as given (no side effect).

    Both errors are taken about their level (:func:`_holdout_residual`: the level of the fit part, or on
    a row with nuisance regressors ``extra`` those regressors and an offset projected out over the
    held-out part).  The candidate is accepted when its RMS simulation error there is smaller by
    ``min_holdout_improvement``, or (option ``holdout_one_step``, off by default) when its RMS one-step
    error under its own AR noise model of order ``noise_order`` (:meth:`_Record.one_step_holdout`) is
    smaller by as much and significantly so while its simulation error is not significantly larger
    (each by :func:`~.holdout.loss_rise_p_value` at ``holdout_alpha``).  In a closed loop the simulation
    errors carry the disturbance the controller answered through the same inputs, which can make the
    right element's simulation error slightly larger than a wrong one's; the one-step errors do not,
    but they weigh an element's slow misfit little (the noise model predicts much of it), and the
    test on the simulation errors has little power over a few hundred autocorrelated samples.  The
    simulation error is what an internal-model controller runs the model for, so it decides by
    default (``bench.holdout_mc`` scores both rules against the plant).  The two p-values are computed
    whenever the one-step error is the smaller, for the warning.

    A record with gaps whose held-out part holds no scored sample (:meth:`_Record.scored`) cannot be
    checked: accepted, with ``after`` None.
    """
    model, options = rec.model, rec.options
    keep = rec.scored(model, candidate)
    if keep is not None and not keep[rec.n_fit:].any():
        return _HoldoutCheck(True)
    d_c = rec.signals_of(candidate).d[:, i]
    # The unexplained disturbance is no model's job either: compare without it (the step or ramp
    # fitted over the held-out part), since a wrong element can partly cancel it.
    e_after = rec.holdout_residual(d_c, keep, extra)
    e_before = rec.holdout_residual(rec.d0[:, i], keep, extra)
    h_after = _rms(e_after)
    h_before = _rms(e_before)
    segments = rec.scored_segments(model, candidate)
    o_after = rec.one_step_holdout(d_c, keep, segments, extra)
    o_before = rec.one_step_holdout(rec.d0[:, i], keep, segments, extra)
    os_after, os_before = (None, None) if o_after is None or o_before is None else (_rms(o_after), _rms(o_before))
    done = functools.partial(_HoldoutCheck, after=h_after, before=h_before, one_step_after=os_after,
                             one_step_before=os_before)
    factor = 1.0 - options.min_holdout_improvement
    if h_after < h_before * factor:
        return done(True)
    if options.noise_order > 0 and os_after is not None and os_after < os_before * factor:
        p_fall = loss_rise_p_value(o_before, o_after)       # small: the candidate's one-step error significantly smaller
        p_rise = loss_rise_p_value(e_after, e_before)       # small: its simulation error significantly larger
        ok = options.holdout_one_step and p_fall < options.holdout_alpha <= p_rise
        return done(ok, p_rise=p_rise, p_one_step=p_fall, one_step=ok)
    return done(False)


def _validate_on_holdout(rec: _Record, row: _RowData, js, elements: dict, warnings: list) -> _HoldoutCheck:
    """:func:`_compare_on_holdout` of the row's candidate (its applied verdicts of ``elements``), with its
    warning: when the candidate is refused, the applied verdicts are rejected; when it was accepted one
    step ahead, a note says so; without a scored held-out sample (gaps), a warning says it stands
    unvalidated."""
    model, i, options = rec.model, row.i, rec.options
    name = model.outputs[i]
    cols = ', '.join(model.columns[j] for j in js)
    held = f"the held-out last {100 * options.holdout_fraction:.0f}% of the record"
    candidate = model
    for j, el in elements.items():
        if el.apply:
            candidate = el.applied_to(candidate, i, j)
    check = _compare_on_holdout(rec, i, candidate, row.extra)
    if check.after is None:
        # Every held-out sample still depends on columns held through a gap: as with no held-out part, the repair
        # stands unvalidated.
        warnings.append(f"{name}: {held} holds no sample that does not depend on the columns held through a gap; "
                        f"the re-estimated element(s) {cols} were not validated on data outside the fit.")
        return check
    h_after, h_before, os_after, os_before = check.after, check.before, check.one_step_after, check.one_step_before
    ar = f"AR({options.noise_order})"
    if check.one_step:
        warnings.append(
            f"{name}: the re-estimated element(s) {cols} predict {held} significantly better one step ahead (RMS "
            f"error {os_after:.4g} vs {os_before:.4g} with the model as given, each under its own {ar} noise model; "
            f"one-sided p = {check.p_one_step:.2g}) and their simulation error there is not significantly larger "
            f"({h_after:.4g} vs {h_before:.4g}; p = {check.p_rise:.2g}): the repair is accepted.")
    if check.accepted:
        return check
    why = ""
    if os_after is not None:
        why = f"; one step ahead {os_after:.4g} vs {os_before:.4g}, each under its own {ar} noise model"
    alpha = options.holdout_alpha
    undecided = ""
    if check.p_rise is not None and check.p_one_step >= alpha:
        why += f", not significantly smaller (one-sided p = {check.p_one_step:.2g}, at least {alpha:g})"
    elif check.p_rise is not None and check.p_rise < alpha:
        why += f", but the rise in simulation error is significant (one-sided p = {check.p_rise:.2g} < {alpha:g})"
    elif check.p_rise is not None:
        why += (f", significantly smaller (one-sided p = {check.p_one_step:.2g}), and the rise in simulation error "
                f"is not significant (p = {check.p_rise:.2g})")
        undecided = (" The held-out data do not tell which is better: the simulation error decides (an "
                     "experiment, or RepairOptions(holdout_one_step=True), which accepts such a repair, may).")
    warnings.append(
        f"{name}: the re-estimated element(s) {cols} did not predict {held} better in simulation (RMS error "
        f"{h_after:.4g} vs {h_before:.4g} with the model as given{why}); the elements are kept as they were."
        f"{undecided}")
    for el in elements.values():
        if el.apply:
            el.reject("rejected by held-out validation")
    return check


def _process_row(rec: _Record, i: int, js, extra: Optional[np.ndarray],
                 classified: Optional[tuple] = None) -> _RowOutcome:
    """Classify, fit, validate and (optionally) refit the located elements ``js`` of row ``i``.

    ``extra`` (shape (n_samples, n_extra)) holds nuisance regressors for an unexplained step or
    drift on the row, or None.  ``classified``: the classification of ``js`` without ``extra``
    already made (:func:`explained_elements`), or None.

    The fits are prediction-error fits with the AR noise model of ``noise_order``.  When a repaired
    element moved far (:func:`_far_moved`) and the row's repair leaves more than
    :data:`OUTPUT_ERROR_TRY` of the model's simulation error over the fit part, the row is processed
    again with an output-error fit (no noise model), and that repair is taken when its simulation
    error over the fit part is :data:`OUTPUT_ERROR_MARGIN` times lower, with a warning: in a closed
    loop the noise model can take what an element of the wrong structure cannot fit (a second lag
    repaired as one lag, its gain driven towards 0).
    """
    outcome, tried = _process_row_with(rec, rec.settings, i, js, extra, classified)
    if not tried or rec.options.noise_order == 0 or rec.n_hold == 0:
        return outcome
    if not any(el.apply and _far_moved(rec.model, i, j, el.after) for j, el in tried.items()):
        return outcome
    after, before = _fit_part_rms(rec, i, tried)
    if not after > OUTPUT_ERROR_TRY * before:
        return outcome
    oe_settings = _TestSettings.of(dataclasses.replace(rec.options, noise_order=0))
    oe_outcome, oe_tried = _process_row_with(rec, oe_settings, i, js, extra, None)
    if not oe_tried:
        return outcome
    oe_after, _ = _fit_part_rms(rec, i, oe_tried)
    if not oe_after * OUTPUT_ERROR_MARGIN < after:
        return outcome
    oe_outcome.warnings.append(
        f"{rec.model.outputs[i]}: the repair fitted with the AR noise model left {after:.4g} of simulation error "
        f"over the fit part (the model as given {before:.4g}); fitted without a noise model (output error) it "
        f"leaves {oe_after:.4g}, and that repair is the one taken: the element's structure may not be the "
        f"plant's (for example a second lag)")
    return oe_outcome


def _process_row_with(rec: _Record, settings: _TestSettings, i: int, js, extra: Optional[np.ndarray],
                      classified: Optional[tuple]) -> tuple:
    """:func:`_process_row` with the fits of ``settings``; also the verdicts as validated on the held-out
    part (before the refit on the whole record), or None when none was accepted."""
    model = rec.model
    row = _RowData(model=model, u=rec.u, y=rec.y, i=i, extra=extra, segments=rec.segments)
    try:
        elements, row_warnings, repair_fit = _repair_row(row, js, rec.n_fit, settings, classified)
    except _TooShort as exc:
        elements = {j: ElementVerdict(kind="unknown", changed=[], after=model.element(i, j), interval=None,
                                      evidence={}, confidence=0.0, apply=False, reason=str(exc)) for j in js}
        return _RowOutcome(elements, [f"{model.outputs[i]}: {exc}; its elements were not re-estimated."]), None
    row_warnings = list(row_warnings)
    check = None
    validated = None
    accepted = any(el.apply for el in elements.values())
    if accepted and rec.n_hold > 0:
        check = _validate_on_holdout(rec, row, js, elements, row_warnings)
        accepted = check.accepted
        if accepted:
            validated = {j: dataclasses.replace(el) for j, el in elements.items()}
    if accepted and rec.options.refit_on_all and rec.n_hold > 0:
        _refit_on_all(row, {j: el for j, el in elements.items() if el.apply}, settings)
    elif repair_fit is not None:
        repair_fit.put_intervals(elements, settings)
    if not accepted:
        for el in elements.values():
            el.apply = False
    return _RowOutcome(elements, row_warnings, check), validated


def _evaluate(rec: _Record, results: dict) -> _Evaluation:
    """The model with every accepted repair of ``results``, its signals, and the disturbance tests
    (of the outputs whose prediction error an earlier evaluation tested as it is, taken from
    :attr:`_Record.tests`)."""
    repaired = rec.model
    for i, res in results.items():
        for j, el in res.elements.items():
            if el.apply:
                repaired = el.applied_to(repaired, i, j)
    sig = rec.signals if repaired == rec.model else rec.signals_of(repaired)
    d = np.asarray(sig.d, float)
    segments = rec.scored_segments(rec.model, repaired, settled=True)
    tests = {}
    for i in range(rec.model.n_outputs):
        # An output whose prediction error did not change (its row not repaired) keeps its test.
        done = rec.tests.get(i)
        if done is None or done[1] != segments or not np.array_equal(done[0], d[:, i]):
            done = rec.tests[i] = (d[:, i].copy(), segments,
                                   _disturbance_test(d[:, i], segments, float(rec.spread[i]), rec.model, rec.options,
                                                     bool(rec.moving[i])))
        tests[i] = dict(done[2])
    _one_family(tests, rec.options.disturbance_alpha)
    if rec.segments is not None:      # the step's time since the first sample, the missing samples counted
        t = np.asarray(rec.data.t, float)
        for test in tests.values():
            if test["index"] is not None:
                test["time"] = float(t[test["index"]] - t[0])
    return _Evaluation(model=repaired, signals=sig, tests=tests)


def _one_family(tests: dict, alpha: float) -> None:
    """The unexplained-disturbance tests of every output as one family, in place: Holm's adjusted p-value
    (:func:`~mpm_monitor.core.statistics.holm_adjust`) over the outputs tested becomes each test's
    ``p_value`` (its own in ``p_value_raw``), and a test whose adjusted value is not below ``alpha`` no longer
    reports a disturbance.  So a loop without one reports one with probability at most ``alpha`` however
    many outputs it has (each output alone at ``alpha`` reported one on 63 % of 100-output loops).

    Parameters
    ----------
    tests : dict
        ``{output index: test}``, each :func:`unexplained_disturbance`'s result (``detected`` exactly when
        its ``p_value`` is below ``alpha``); an output not tested keeps its test and is not counted.
    alpha : float
        The family-wise level (:attr:`RepairOptions.disturbance_alpha`).
    """
    tested = [i for i, test in tests.items() if test.get("tested")]
    if not tested:
        return
    for i, adjusted in zip(tested, holm_adjust([tests[i]["p_value"] for i in tested])):
        test, adjusted = tests[i], float(adjusted)
        if test["detected"] and not adjusted < alpha:
            tests[i] = test = dict(not_tested(), p_step=test["p_step"], p_drift=test["p_drift"],
                                   p_value=test["p_value"], tested=True)
        test["p_value_raw"], test["p_value"] = test["p_value"], adjusted


def _disturbance_test(d: np.ndarray, segments, scale: float, model: PlantModel, options: RepairOptions,
                      moves: bool) -> dict:
    """:func:`unexplained_disturbance` of one output's prediction error ``d`` (shape (n_samples,)), as the
    repair tests every output: at ``options``' level, trim and noise order, over the scored ``segments``
    (None: every sample), ``scale`` the output's standard deviation.  An output that never moves
    (``moves`` false: a stuck sensor) is not tested: its prediction error is the model's own response."""
    if not moves:
        return not_tested()
    return unexplained_disturbance(d, model.sample_time, options.disturbance_alpha, options.disturbance_trim,
                                   options.noise_order, segments=segments, scale=scale)


def _test_settings_key(model: PlantModel, options: RepairOptions) -> tuple:
    """What a disturbance test depends on besides its prediction error, segments and scale."""
    return (float(model.sample_time), float(options.disturbance_alpha), float(options.disturbance_trim),
            int(options.noise_order))


@dataclasses.dataclass
class DisturbanceTests:
    """The unexplained-disturbance tests of every output of a model as given, on a record without gaps,
    computed ahead of :func:`repair_model` (:func:`disturbance_tests`), which takes each output's test
    whose prediction error it finds unchanged instead of testing it again.

    Attributes
    ----------
    key : tuple
        The sample time, the level, trim and noise order of the tests (:class:`RepairOptions`).
    spread : ndarray, shape (n_outputs,)
        The outputs' standard deviations, the tests' scales (output units).
    d : ndarray, shape (n_samples, n_outputs)
        The prediction errors tested (output units).
    tests : list of dict
        Per output, :func:`~mpm_monitor.core.repair.disturbance.unexplained_disturbance`'s result.
    """

    key: tuple
    spread: np.ndarray
    d: np.ndarray
    tests: list


def disturbance_tests(model: PlantModel, data: LoggedData, d: np.ndarray,
                      options: RepairOptions = RepairOptions()) -> DisturbanceTests:
    """The tests :func:`repair_model` runs on every output of ``model`` as given, computed ahead.

    The repair tests the prediction error of every output of the repaired model for an unexplained
    step or drift; an output whose row it does not repair keeps the prediction error of the model as
    given.  :func:`~mpm_monitor.core.pipeline.analyze` computes these tests in its second process
    while the detection's first stages run in one (the second core is idle then), and gives them to
    :func:`repair_model` (its ``disturbance_tests``): the same numbers.

    Parameters
    ----------
    model : PlantModel
        The model as given.
    data : LoggedData
        The record the repair fits, without gaps (the scales are the standard deviations of its ``y``).
    d : ndarray, shape (n_samples, n_outputs)
        ``model``'s prediction error on ``data`` (output units).
    options : RepairOptions
        The repair's options.

    Returns
    -------
    DisturbanceTests
    """
    d = np.asarray(d, float)
    y = np.asarray(in_deviations(model, data).y, float)
    spread, moving = np.std(y, axis=0), moving_columns(y)
    return DisturbanceTests(key=_test_settings_key(model, options), spread=spread, d=d,
                            tests=[_disturbance_test(d[:, i], None, float(spread[i]), model, options, bool(moving[i]))
                                   for i in range(model.n_outputs)])


def _seed_tests(rec: _Record, given: Optional[DisturbanceTests]) -> None:
    """Put the tests ``given`` (:func:`disturbance_tests`) into :attr:`_Record.tests` when they were taken with
    the record's settings and scales (without gaps); :func:`_evaluate` uses each one whose prediction error it
    finds unchanged."""
    if given is None or rec.segments is not None or given.key != _test_settings_key(rec.model, rec.options):
        return
    if given.d.shape != rec.d0.shape or not np.array_equal(given.spread, rec.spread):
        return
    for i, test in enumerate(given.tests):
        rec.tests[i] = (given.d[:, i], None, test)


def _redo_disturbed_rows(rec: _Record, located: list, rows: list, results: dict, tests: dict,
                         jobs: int = 1) -> bool:
    """Process again, with the step or ramp as a nuisance regressor, every repaired row whose
    residual shows an unexplained disturbance (it stays in the residual: the model has no place
    for it, but it would bias the elements), ``jobs`` processes taking the rows (:func:`repair_model`).
    Returns whether a row was redone."""
    n = rec.n
    redo = [i for i in rows if tests[i]["detected"]]

    def one_row(i: int) -> _RowOutcome:
        t = tests[i]
        k = np.arange(n, dtype=float)
        col = (k >= t["index"]).astype(float) if t["kind"] == "step" else k / n
        return _process_row(rec, i, _located_in_row(located, i), col[:, None])
    for i, outcome in zip(redo, split_map(one_row, redo, jobs)):
        t = tests[i]
        results[i] = outcome
        results[i].warnings.append(
            f"{rec.model.outputs[i]}: the re-estimation of its elements allowed for the unexplained "
            f"{'step' if t['kind'] == 'step' else 'drift'} in the prediction error.")
    return bool(redo)


def _located_in_row(located: list, i: int) -> list:
    return [j for (ii, j) in located if ii == i]


def _disturbance_findings(rec: _Record, tests: dict):
    """The ``disturbances`` entries and their warnings, in output order."""
    disturbances, warnings = [], []
    for i, name in enumerate(rec.model.outputs):
        test = tests[i]
        if not test["detected"]:
            continue
        disturbances.append({"output": name, "kind": test["kind"], "size": test["size"],
                             "time": test["time"], "rate": test["rate"], "p_value": test["p_value"],
                             "p_value_raw": test["p_value_raw"], "statistic": test["statistic"]})
        if test["kind"] == "step":
            # At the log's own time (the stamp of the sample the step is at): ``time`` counts from the first sample,
            # which read as 1164 s beside the gap warnings' 1700001664 s in a live window.
            k, t = test.get("index"), np.asarray(rec.data.t)
            when = t_text(float(t[k])) if k is not None and 0 <= k < t.shape[0] else f"{test['time']:.0f}"
            warnings.append(
                f"{name}: the prediction error shifts by {test['size']:+.3g} at about t = {when} s "
                f"(p = {test['p_value']:.2g}) and no input explains it: an unmeasured disturbance or a change "
                f"in the process, not an error of one model element; no element was changed for it.")
        else:
            warnings.append(
                f"{name}: the prediction error drifts by {test['size']:+.3g} over the record "
                f"({test['rate']:+.3g} per second, p = {test['p_value']:.2g}) and no input explains it: an "
                f"unmeasured disturbance or a slow process change; no element was changed for it.")
    return disturbances, warnings


def _assemble(rec: _Record, results: dict, found: _Findings, ev: _Evaluation) -> RepairResult:
    """The :class:`RepairResult`: the row outcomes (``results``, ``{i: _RowOutcome}`` in row
    order) after ``found``, the errors, the disturbances."""
    model, y = rec.model, rec.y
    names_y = model.outputs
    ny = model.n_outputs
    changes, kinds, warnings = found.changes, found.kinds, found.warnings
    holdout_before, holdout_after = dict(rec.holdout_before), {}
    one_step_before, one_step_after = {}, {}
    for i, res in results.items():
        warnings.extend(res.warnings)
        if res.holdout_after is not None:
            holdout_after[names_y[i]] = res.holdout_after
            holdout_before[names_y[i]] = res.holdout_before
        if res.check is not None and res.check.one_step_after is not None:
            one_step_after[names_y[i]] = res.check.one_step_after
            one_step_before[names_y[i]] = res.check.one_step_before
        for j, el in res.elements.items():
            kinds[(i, j)] = el.kind
            changes.append(el.change_entry(model, i, j))
            if el.apply and model.is_step_response:     # the coefficients written: the entry's estimate
                unsettled = unsettled_warning(model, i, j, el.after, changes[-1]["estimate"]["step_response"])
                if unsettled:
                    warnings.append(unsettled)
    d1 = np.asarray(ev.signals.d, float)
    keep = rec.scored(model, ev.model)
    for i in range(ny):
        if rec.n_hold > 0 and names_y[i] not in holdout_after:
            holdout_after[names_y[i]] = rec.holdout(d1[:, i], keep)
            if keep is not None:
                holdout_before[names_y[i]] = rec.holdout(rec.d0[:, i], keep)
    yhat0, yhat1, d0 = np.asarray(rec.signals.yhat, float), np.asarray(ev.signals.yhat, float), rec.d0
    scored = rec.scored_segments(model, ev.model, settled=True)
    runs = None
    if scored is not None:        # with gaps: the samples settled from the state each gap leaves
        settled = segments_mask(scored, rec.n)
        y, yhat0, yhat1, d0, d1 = (x[settled] for x in (y, yhat0, yhat1, d0, d1))
        runs = packed(scored)
    level = model.integrating_outputs
    error_before, error_after = error_rms(model, d0, runs), error_rms(model, d1, runs)
    fit_before = {names_y[i]: _fit_percent(y[:, i], yhat0[:, i], level[i]) for i in range(ny)}
    fit_after = {names_y[i]: _fit_percent(y[:, i], yhat1[:, i], level[i]) for i in range(ny)}
    disturbances, disturbance_warnings = _disturbance_findings(rec, ev.tests)
    warnings.extend(disturbance_warnings)
    return RepairResult(model=ev.model, changes=changes, kinds=kinds, error_before=error_before,
                        error_after=error_after, fit_before=fit_before, fit_after=fit_after,
                        holdout_error_before=holdout_before, holdout_error_after=holdout_after,
                        holdout_one_step_error_before=one_step_before, holdout_one_step_error_after=one_step_after,
                        disturbances=disturbances, warnings=warnings, n_samples=rec.n, n_fit=rec.n_fit,
                        options=rec.options, signals=ev.signals)


def repair_model(model: PlantModel, data: LoggedData, located: Sequence[tuple],
                 options: RepairOptions = RepairOptions(), signals: Optional[LoopSignals] = None,
                 classified: Optional["JointClassification"] = None,
                 disturbance_tests: Optional[DisturbanceTests] = None, jobs: int = 1) -> RepairResult:
    """Re-estimate the located elements, classify their mismatch, and validate the repair.

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat`` as given.
    data : LoggedData
        Closed-loop record (``r``, ``u``, ``dv``, ``y``), shapes (n_samples, n_outputs/n_inputs/n_disturbances).
    located : sequence of (int, int)
        (output index, column index) of the elements located as mismatched (the columns are the
        inputs, then the measured disturbances).  No other element is ever changed; a located element
        keeps its structure (a parametric element its keys, a step-response element the length of
        its response).
    options : RepairOptions
    signals : LoopSignals, optional
        :func:`~mpm_monitor.core.signals.compute_signals` of ``model`` on ``data`` (computed when absent).
    classified : JointClassification, optional
        What :func:`explained_elements` found on the same model, data and options: a row whose
        located elements are those it classified is not classified again.
    disturbance_tests : DisturbanceTests, optional
        The unexplained-disturbance tests of ``model``'s outputs on ``data``, computed ahead
        (:func:`disturbance_tests`): an output whose prediction error the repair leaves as it is keeps
        its test instead of being tested again.  Ignored unless taken with these options and scales on a
        record without gaps; each test is used only where its prediction error is the one the repair
        would test.
    jobs : int
        Processes: with 2, a forked second process takes part of the rows to repair, each row's
        classification, fits and held-out check whole (:func:`~mpm_monitor.core.parallel.split_map`: the same
        code on the same numbers, so the same result as in one process).

    Returns
    -------
    RepairResult
    """
    if not isinstance(options, RepairOptions):
        raise ConfigurationError(f"options: expected RepairOptions, got {type(options).__name__}")
    data = in_deviations(model, data)
    located = _check_inputs(model, data, located, signals)
    rec = _set_up(model, data, options, signals)
    _seed_tests(rec, disturbance_tests)
    found = _Findings()
    rows = _rows_to_repair(rec, located, found)

    def one_row(i: int) -> _RowOutcome:
        js = _located_in_row(located, i)
        return _process_row(rec, i, js, None, classified.of_row(i, js) if classified is not None else None)
    results = dict(zip(rows, split_map(one_row, rows, jobs)))
    ev = _evaluate(rec, results)
    if _redo_disturbed_rows(rec, located, rows, results, ev.tests, jobs):
        ev = _evaluate(rec, results)
    return _assemble(rec, results, found, ev)


@dataclasses.dataclass
class JointClassification:
    """What :func:`explained_elements` found.

    Attributes
    ----------
    released : dict
        ``{(i, j): [k, ...]}``: the located element ``(i, j)`` (output index, column index) whose
        mismatch the located elements ``k`` of its row explain (those the row keeps).
    rows : dict
        ``{i: (js, (free, verdicts, warnings)))}``: the last classification of row ``i``'s located
        elements ``js`` (a tuple: those kept after the releases when the last one released nothing),
        which :func:`repair_model` takes instead of classifying again when they are the row's
        located elements.
    """

    released: dict
    rows: dict

    def of_row(self, i: int, js) -> Optional[tuple]:
        """``(free, verdicts, warnings)`` of row ``i`` when its last classification was of the
        elements ``js``, else None."""
        done = self.rows.get(i)
        return done[1] if done is not None and done[0] == tuple(js) else None


def explained_elements(model: PlantModel, data: LoggedData, located: Sequence[tuple],
                       options: RepairOptions = RepairOptions(),
                       signals: Optional[LoopSignals] = None) -> JointClassification:
    """The located elements whose mismatch another located element of their row explains.

    The element test locates each element on its own statistic, with the row's other columns free
    as lag windows.  In closed loop a mismatch that a lag window does not hold whole (a slow or
    shifted response) leaves a remainder that the other columns, correlated with the mismatched
    one through the controller, can pick up: a second element of the row is then located for the
    first one's mismatch.  The classification of the repair settles it.  It fits the row's located
    elements jointly, each in its structure, and tests every parameter of each against the model
    (likelihood-ratio tests at ``1 - options.confidence_level``, a change counted only above
    ``options.min_relative_change``, and the joint hold of every parameter found unchanged;
    :mod:`.classify`).  An element none of whose parameters differs from the model there (its kind
    "unknown"), in a row where another located element's do, adds nothing to the row
    once those are re-estimated: it is released, with the elements that explain it.  The row's
    remaining elements are then classified again, and released in turn, until none is: the
    result is the rule applied to its own outcome, and the classification of the elements kept is
    the one the repair takes over.  An element alone in its row is never released, nor are the
    elements of a row where none changed.

    Parameters
    ----------
    model : PlantModel
        The controller's model as given.
    data : LoggedData
        The record the repair fits (:func:`repair_model`).
    located : sequence of (int, int)
        (output index, column index) of the located elements.
    options : RepairOptions
    signals : LoopSignals, optional
        :func:`~mpm_monitor.core.signals.compute_signals` of ``model`` on ``data``.

    Returns
    -------
    JointClassification
        Empty when no row has two located elements (nothing is fitted then) or the record is too
        short for the repair.
    """
    if not isinstance(options, RepairOptions):
        raise ConfigurationError(f"options: expected RepairOptions, got {type(options).__name__}")
    data = in_deviations(model, data)
    located = _check_inputs(model, data, located, signals)
    result = JointClassification(released={}, rows={})
    rows = {i: tuple(_located_in_row(located, i)) for i in sorted({i for i, _ in located})}
    rows = {i: js for i, js in rows.items() if len(js) > 1}
    if not rows:
        return result
    rec = _set_up(model, data, options, signals)
    if rec.n_fit < _min_fit(model, options):
        return result
    for i, js in rows.items():
        row = _RowData(model=model, u=rec.u, y=rec.y, i=i, extra=None, segments=rec.segments)
        gone = []
        while len(js) > 1:          # until the row's classification releases nothing more
            try:
                free, verdicts, warnings = _classify_row(row, js, rec.settings)
            except _TooShort:
                break
            result.rows[i] = (js, (free, verdicts, list(warnings)))
            known = tuple(j for j in js if verdicts[j].kind != "unknown")
            if not known or len(known) == len(js):
                break
            gone += [j for j in js if j not in known]
            js = known
        # The elements the row keeps in the end explain every element released from it.
        result.released.update({(i, j): list(js) for j in gone})
    return result
