"""The held-out check of a row's repair: the candidate against the model as given over the held-out
last part of the record (the statistics it uses are in :mod:`.holdout`)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import numpy as np

from ..model import PlantModel
from .holdout import loss_rise_p_value
from .record import _Record, _rms
from .row import _RowData


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
    within : bool
        The simulation error rose by no more than the option ``holdout_tolerance`` (True when it fell, or when
        the one-step errors were not consulted).
    """

    accepted: bool
    after: Optional[float] = None
    before: Optional[float] = None
    one_step_after: Optional[float] = None
    one_step_before: Optional[float] = None
    p_rise: Optional[float] = None
    p_one_step: Optional[float] = None
    one_step: bool = False
    within: bool = True


def _compare_on_holdout(rec: _Record, i: int, candidate: PlantModel,
                        extra: Optional[np.ndarray] = None) -> _HoldoutCheck:
    """The held-out check of row ``i`` of ``candidate`` against the model as given (no side effect).

    Both errors are taken about their level (:func:`~.record._holdout_residual`: the level of the fit part, or on
    a row with nuisance regressors ``extra`` those regressors and an offset projected out over the
    held-out part).  The candidate is accepted when its RMS simulation error there is smaller by
    ``min_holdout_improvement``, or (option ``holdout_one_step``, on by default) when its RMS one-step
    error under its own AR noise model of order ``noise_order`` (:meth:`_Record.one_step_holdout`) is
    smaller by as much and significantly so while its simulation error is not significantly larger
    (each by :func:`~.holdout.loss_rise_p_value` at ``holdout_alpha``) and has risen by no more than
    ``holdout_tolerance`` of the model's.  In a closed loop the simulation errors carry the disturbance
    the controller answered through the same inputs, which can make the right element's simulation error
    slightly larger than a wrong one's; the one-step errors do not, but they weigh an element's slow misfit
    little (the noise model predicts much of it), and the test on the simulation errors has little power
    over a few hundred autocorrelated samples.  The simulation error is what an internal-model controller
    runs the model for: the tolerance bounds what the one-step route may cost there (``bench.holdout_mc``
    scores the rules against the plant).  On a loop that diverged (:attr:`_Record.diverged`) the tests'
    p-values mean nothing (the errors grow without bound): the simulation error alone decides there.  The two
    p-values are computed whenever the one-step error is the smaller, for the warning.

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
    e_after = rec.holdout_residual(d_c, keep, extra, row=i)
    e_before = rec.holdout_residual(rec.d0[:, i], keep, extra, row=i)
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
        tol = options.holdout_tolerance
        within = tol is None or h_after <= h_before * (1.0 + tol)
        ok = options.holdout_one_step and not rec.diverged and p_fall < options.holdout_alpha <= p_rise and within
        return done(ok, p_rise=p_rise, p_one_step=p_fall, one_step=ok, within=within)
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
    tol = options.holdout_tolerance
    rise = f"{100.0 * (h_after / h_before - 1.0):.2g}% above" if h_before > 0 else "above"
    tolerance = "" if tol is None else f" the tolerance of {100.0 * tol:g}%"
    if check.one_step:
        warnings.append(
            f"{name}: the re-estimated element(s) {cols} predict {held} significantly better one step ahead (RMS "
            f"error {os_after:.4g} vs {os_before:.4g} with the model as given, each under its own {ar} noise model; "
            f"one-sided p = {check.p_one_step:.2g}) and their simulation error there is not significantly larger "
            f"({h_after:.4g} vs {h_before:.4g}; p = {check.p_rise:.2g}"
            + (f"; {rise}, within{tolerance}" if tol is not None else "") + "): the repair is accepted.")
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
    elif check.p_rise is not None and options.holdout_one_step and rec.diverged:
        why += (f", significantly smaller (one-sided p = {check.p_one_step:.2g}), but the loop diverged, where the "
                f"held-out tests mean nothing: the simulation error alone decides")
    elif check.p_rise is not None and options.holdout_one_step and not check.within:
        why += (f", significantly smaller (one-sided p = {check.p_one_step:.2g}), and the rise in simulation error "
                f"is not significant (p = {check.p_rise:.2g}) but is {rise} the model's, beyond{tolerance}")
        undecided = (" The held-out data do not tell which is better: beyond the tolerance the simulation error "
                     "decides (an experiment, or RepairOptions(holdout_tolerance=None), which accepts such a repair, "
                     "may).")
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
