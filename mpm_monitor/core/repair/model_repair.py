"""repair_model: set up the record, repair each row, redo rows with an unexplained step or drift,
and assemble the result.

Each output row with located elements is classified (:mod:`.classify`), its repair fitted on the
first part of the record (:mod:`.refit`), validated on the held-out last part (:mod:`.validation`),
and refitted on the whole record.  The residual of the repaired model is then tested for an
unexplained step or drift on every output (:mod:`.residual_tests`); a repaired row where one shows
is processed again with the step (ramp) as a nuisance regressor, so that it does not bias the
elements.  The record every step reads is :mod:`.record`.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional, Sequence

import numpy as np

from ..errors import ConfigurationError
from ..logged_data import LoggedData, in_deviations, moving_columns
from ..model import PlantModel
from ..parallel import split_map
from ..signals import LoopSignals, error_rms, packed, segments_mask
from .classify import _classify_row
from .explained import JointClassification
from .fit import _TooShort
from .forms import unsettled_warning
from .options import RepairOptions, _TestSettings
from .record import _check_delays, _check_inputs, _located_in_row, _min_fit, _Record, _rms, _set_up
from .refit import _fit_repair, _refit_on_all
from .residual_tests import DisturbanceTests, _disturbance_findings, _disturbance_test, _one_family, _seed_tests
from .result import ElementVerdict, RepairResult, _unchanged_entry
from .row import _RowData
from .validation import _HoldoutCheck, _validate_on_holdout


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

def _process_row(rec: _Record, i: int, js, extra: Optional[np.ndarray],
                 classified: Optional[tuple] = None) -> _RowOutcome:
    """Classify, fit, validate and (optionally) refit the located elements ``js`` of row ``i``.

    ``extra`` (shape (n_samples, n_extra)) holds nuisance regressors for an unexplained step or
    drift on the row, or None.  ``classified``: the classification of ``js`` without ``extra``
    already made (:func:`~.explained.explained_elements`), or None.

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
    row = _RowData(model=model, u=rec.u, y=rec.y, i=i, extra=extra, segments=rec.segments, delays=rec.row_delays(i),
                   bridge=rec.bridge)
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


def _evaluate(rec: _Record, results: dict, jobs: int = 1, store: Optional[dict] = None) -> _Evaluation:
    """The model with every accepted repair of ``results``, its signals, and the disturbance tests
    (of the outputs whose prediction error an earlier evaluation tested as it is, taken from
    ``store``, default :attr:`_Record.tests`, and kept there); ``jobs`` processes confirm the disturbances the
    family reports, each output's confirmation whole (:func:`~mpm_monitor.core.parallel.split_map`: the same
    numbers)."""
    store = rec.tests if store is None else store
    repaired = rec.model
    for i, res in results.items():
        for j, el in res.elements.items():
            if el.apply:
                repaired = el.applied_to(repaired, i, j)
    sig = rec.signals if repaired == rec.model else rec.signals_of(repaired)
    d = np.asarray(sig.d, float)
    segments = rec.scored_segments(rec.model, repaired, settled=True)
    levels = rec.levels
    tests = {}
    for i in range(rec.model.n_outputs):
        # An output whose prediction error did not change (its row not repaired) keeps its test.
        done = store.get(i)
        if done is None or done[1] != segments or not np.array_equal(done[0], d[:, i]):
            done = store[i] = (d[:, i].copy(), segments,
                               _disturbance_test(d[:, i], segments, float(rec.spread[i]), rec.model, rec.options,
                                                 bool(rec.moving[i]), levels))
        tests[i] = dict(done[2])
    _one_family(tests, rec.options.disturbance_alpha)
    # A disturbance the family reports is confirmed on simulated records of its output's own noise (the asymptotic
    # tails are too light with slow noise); Holm's procedure is monotone, so no other output can join.
    confirm = [i for i, test in tests.items() if test["detected"] and not store[i][2].get("calibrated")]
    if confirm and rec.options.disturbance_draws > 0:
        def confirmed(i: int) -> dict:
            done = store[i]
            return _disturbance_test(done[0], done[1], float(rec.spread[i]), rec.model, rec.options,
                                     bool(rec.moving[i]), levels, calibrate=True)
        for i, test in zip(confirm, split_map(confirmed, confirm, jobs)):
            store[i] = (store[i][0], store[i][1], test)
        tests = {i: dict(store[i][2]) for i in tests}
        _one_family(tests, rec.options.disturbance_alpha)
    if rec.segments is not None:      # the step's time since the first sample, the missing samples counted
        t = np.asarray(rec.data.t, float)
        for test in tests.values():
            if test["index"] is not None:
                test["time"] = float(t[test["index"]] - t[0])
    return _Evaluation(model=repaired, signals=sig, tests=tests)


def _taken_up(rec: _Record, quiet: list, jobs: int = 1) -> dict:
    """``{i: test}``: the disturbances of the model as given (:func:`_evaluate` of no repair: the outputs' family,
    each reported one confirmed) on the repaired rows ``quiet``, whose repaired prediction error shows none.

    A first repair can take up a disturbance: against a drift on many outputs the controller ramps its inputs,
    and a located element fitted alone became a slow element of a large gain that ramps with them (on
    ``bench.perf``'s 20x20 loop with a drift on every output, a gain of -10.9 against the plant's -0.577).  Its
    residual then shows no drift to allow for; the model as given's does, and the row is processed again with it
    as a nuisance (:func:`_redo_disturbed_rows`).  Only a row whose error as given shows one on its own test (the
    family and the confirmation only take reports away) runs the family; the evaluation's tests of the repaired
    rows stay as they were.  Integrating outputs are left out: there an element's error (an integrator's gain)
    makes a ramp of the error as given itself.
    """
    # On an integrating output an element's error is itself a ramp or a step in the error as given (a gain error
    # of an integrator): there it is no evidence of a disturbance the repair took up.
    integrating = np.asarray(rec.model.integrating_outputs, dtype=bool)
    quiet = [i for i in quiet if not integrating[i]]
    if not quiet:
        return {}
    segments = rec.scored_segments(rec.model, rec.model, settled=True)      # as _evaluate scores the model as given
    own = {i: _disturbance_test(rec.d0[:, i], segments, float(rec.spread[i]), rec.model, rec.options,
                                bool(rec.moving[i]), rec.levels) for i in quiet}
    if not any(test["detected"] for test in own.values()):
        return {}
    # A store of its own: the record's keeps the repaired rows' tests (the others are the same), and the rows'
    # own tests above are not taken again.
    store = {**rec.tests, **{i: (rec.d0[:, i].copy(), segments, test) for i, test in own.items()}}
    given = _evaluate(rec, {}, jobs, store).tests
    return {i: given[i] for i in quiet if given[i]["detected"]}


def _redo_disturbed_rows(rec: _Record, located: list, rows: list, results: dict, tests: dict,
                         jobs: int = 1) -> bool:
    """Process again, with the step or ramp as a nuisance regressor, every repaired row whose ``tests[i]`` shows
    an unexplained disturbance: its repaired residual's (it stays in the residual: the model has no place for it,
    but it would bias the elements), or the model as given's where the repair took it up (:func:`repair_model`),
    ``jobs`` processes taking the rows.  Returns the rows redone (their warnings: :func:`_redo_warnings`)."""
    n = rec.n
    redo = [i for i in rows if tests[i]["detected"]]

    def one_row(i: int) -> _RowOutcome:
        t = tests[i]
        k = np.arange(n, dtype=float)
        col = (k >= t["index"]).astype(float) if t["kind"] == "step" else k / n
        return _process_row(rec, i, _located_in_row(located, i), col[:, None])
    for i, outcome in zip(redo, split_map(one_row, redo, jobs)):
        results[i] = outcome
    return redo


def _redo_warnings(rec: _Record, redo: list, first: dict, final: dict, results: dict, taken: dict) -> None:
    """The warning of each row ``redo`` processed again with a step or ramp as a nuisance regressor
    (:func:`_redo_disturbed_rows`, on the test ``first[i]`` that called for it: the first repair's prediction
    error's, or the model as given's where the first repair took it up, ``taken``), after the evaluation of the
    repaired model (``final[i]``).  Where the disturbance stays in the repaired prediction error it is reported
    (the repair's disturbances) and the warning says that the elements allowed for it; where it does not, the
    warning says where it was seen and that none is reported (a report that names a step nowhere else read as a
    contradiction: 33 of 41 such reports of a gain error without any step, in an outside check)."""
    for i in redo:
        t = first[i]
        kind = "step" if t["kind"] == "step" else "drift"
        name = rec.model.outputs[i]
        if final[i]["detected"]:
            text = f"{name}: the re-estimation of its elements allowed for the unexplained {kind} in the prediction error."
        else:
            seen = "the model as given" if i in taken else "its first re-estimated elements"
            text = (f"{name}: the prediction error of {seen} showed an unexplained {kind} (p = {t['p_value']:.2g}), "
                    f"so its elements were re-estimated allowing for one; the repaired model's prediction error "
                    f"shows none at the disturbance tests' level, and none is reported.")
        results[i].warnings.append(text)

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
            holdout_after[names_y[i]] = rec.holdout(d1[:, i], keep, row=i)
            if keep is not None:
                holdout_before[names_y[i]] = rec.holdout(rec.d0[:, i], keep, row=i)
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
                 disturbance_tests: Optional[DisturbanceTests] = None, jobs: int = 1,
                 delays: Optional[Mapping] = None) -> RepairResult:
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
        What :func:`~.explained.explained_elements` found on the same model, data and options: a row whose
        located elements are those it classified is not classified again.
    disturbance_tests : DisturbanceTests, optional
        The unexplained-disturbance tests of ``model``'s outputs on ``data``, computed ahead
        (:func:`~.residual_tests.disturbance_tests`): an output whose prediction error the repair leaves as it is keeps
        its test instead of being tested again.  Ignored unless taken with these options and scales on a
        record without gaps; each test is used only where its prediction error is the one the repair
        would test.
    jobs : int
        Processes: with 2, a forked second process takes part of the rows to repair, each row's
        classification, fits and held-out check whole (:func:`~mpm_monitor.core.parallel.split_map`: the same
        code on the same numbers, so the same result as in one process).
    delays : mapping, optional
        ``{(output index, column index): lag}``: the element test's estimate of the lag (samples) at which
        each located element's mismatch ``Delta`` acts (``ElementResult.delay``).  Where one lies more
        than ``options.max_delay_shift`` samples from the model's delay, the element's delay is searched
        as far as that many samples beyond it (a plant's dead time far from the model's).  Estimates of
        elements not located are ignored.

    Returns
    -------
    RepairResult
    """
    if not isinstance(options, RepairOptions):
        raise ConfigurationError(f"options: expected RepairOptions, got {type(options).__name__}")
    data = in_deviations(model, data)
    located = _check_inputs(model, data, located, signals)
    rec = _set_up(model, data, options, signals, _check_delays(delays, located))
    _seed_tests(rec, disturbance_tests)
    found = _Findings()
    rows = _rows_to_repair(rec, located, found)

    def one_row(i: int) -> _RowOutcome:
        js = _located_in_row(located, i)
        return _process_row(rec, i, js, None, classified.of_row(i, js) if classified is not None else None)
    results = dict(zip(rows, split_map(one_row, rows, jobs)))
    ev = _evaluate(rec, results, jobs)
    tests = dict(ev.tests)
    taken = _taken_up(rec, [i for i in results if not tests[i]["detected"]], jobs)
    tests.update(taken)
    redo = _redo_disturbed_rows(rec, located, rows, results, tests, jobs)
    if redo:
        ev = _evaluate(rec, results, jobs)
        _redo_warnings(rec, redo, tests, ev.tests, results, taken)
    return _assemble(rec, results, found, ev)
