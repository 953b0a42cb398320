"""The repair fit: only what changed is re-estimated, first for validation, then on the whole record.

:func:`_fit_repair` (stage 2) refits, on the first ``n_fit`` samples so that the rest validates
it, only the parameters the classification found changed (everything for a missing element),
with the rest held at the model's values; elements without a change are held entirely.  Fewer
free parameters give tighter, less biased estimates when inputs move together.
:func:`_refit_on_all` refits the accepted elements on the whole record with the validated
structure; the intervals of the first fit are taken only for elements not refitted
(:meth:`_RepairFit.put_intervals`).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

from .classify import _FreeFit
from .fit import _ElementSpec, _RowEstimate, _RowProblem
from .forms import _POLE_MIN, _input_lag, _poles_of, _reads_no_lag
from .options import _TestSettings
from .result import ElementVerdict
from .row import _element_after, _element_summary, _estimate_row, _RowData

#: The parameters of an element the repair may free, with the keys of ``after`` each one sets.
_SHAPE_KEYS = ("time_constant", "time_constant2", "lead")


def _update_free_intervals(interval: dict, new: dict, spec: _ElementSpec) -> None:
    """Replace in ``interval`` the intervals of the parameters ``spec`` leaves free by those of ``new``."""
    for key, free in (("gain", spec.gain_free), ("time_constant", spec.pole_free), ("delay", spec.lag_free),
                      ("time_constant2", spec.pole_free), ("lead", spec.pole_free)):
        if free and key in new:
            interval[key] = new[key]


def _compose(fitted: dict, held: dict, spec: _ElementSpec, held_lag_too: bool = False,
             fewer_lags: bool = False) -> dict:
    """The element after a fit of ``spec``: the free parameters from ``fitted``, the others from ``held``.

    A first-order element held without a lag (its pole at the bound) is a pure gain.  One whose pole was
    fitted with its delay held takes the fitted delay, read from the lag and the pole together: where the
    lag vanished (time constant 0) the sample of the lag moves into the delay (``held_lag_too``: also
    when the pole was held, where the fitted delay is the held one).  So does an element fitted with one lag
    fewer than ``held`` has (``fewer_lags``, :func:`~mpm_monitor.core.repair.classify._reduce_vanished_lags`):
    its fitted dead time is measured in its own form.
    """
    out = dict(held)
    out["integrating"] = fitted["integrating"]
    if spec.gain_free:
        out["gain"] = float(fitted["gain"])
    if spec.pole_free:
        for key in _SHAPE_KEYS:
            out[key] = float(fitted[key])
    elif spec.form.first_order and spec.poles and _reads_no_lag(spec.poles[0]):
        # Held as a pure gain (an element that lost its lag, or a reference whose lag is too short to show,
        # a hair above 0): a pure gain acts at the lag of its dead time, so the delay is the fit's reading of
        # its lag (the held one where the lag vanished; a sample longer than a held lag of 0.001 s at 10 s,
        # which kept as it was acted a sample early).
        out["time_constant"] = 0.0
        out["delay"] = float(fitted["delay"])
    # A first-order element's dead time is read from its lag and pole together (a pole at the bound reads as no
    # lag, the dead time one sample longer): with the pole fitted, the delay is the fit's reading.
    vanished = spec.form.first_order and (spec.pole_free or held_lag_too)
    if spec.lag_free or vanished or fewer_lags:
        out["delay"] = float(fitted["delay"])
    return out


def _repair_specs(free: _FreeFit, verdicts: dict):
    """Specs of the repair fit: the changed parameters free from the free fit's values, the rest held.

    Elements of kind "unknown" are left out (held at the model's values).  Returns the specs
    ``{j: _ElementSpec}`` and the start lags ``{j: lag}``: the free fit's lag where the delay
    changed, the reference's dead time elsewhere (:meth:`_Located.held_lag`: in the first-order form
    an element with a lag acts one sample after a pure gain of the same dead time).
    """
    est = free.est
    specs, lags0 = {}, {}
    for m, j in enumerate(free.js):
        v = verdicts[j]
        if v.kind == "unknown":
            continue
        loc = free.located[j]
        missing = v.kind == "missing"
        free_k = missing or "gain" in v.changed
        free_t = (missing or "time_constant" in v.changed) and loc.form.n_shape > 0
        free_d = missing or "delay" in v.changed
        fitted_poles = est.fit.poles[free.problem.slices[m]]
        poles = tuple(float(a) for a in fitted_poles) if free_t else loc.poles
        lost = free_t and free.lost_lag(m)
        held = loc.held_lag(free_t, lost)                   # the reference's dead time
        if lost:
            free_t, poles = False, (_POLE_MIN,)             # a pure gain now: fitted as one, at that dead time
        form, window, lag = loc.form, free.specs[j].window if free_d else (held, held), \
            est.fit.lags[m] if free_d else held
        if not free_t and loc.declared is not None:     # the reference's shape held: its form, the same dead time
            shift = loc.declared.offset - loc.form.offset
            form, window, lag = loc.declared, (window[0] + shift, window[1] + shift), lag + shift
        specs[j] = _ElementSpec(free_k, free_t, est.fit.gains[m] if free_k else loc.reference["gain"], poles,
                                window, form=form, lead=float(est.fit.leads[m]) if free_t else loc.reference["lead"])
        lags0[j] = lag
    return specs, lags0


@dataclasses.dataclass
class _RepairFit:
    """The stage-2 fit of a row (:func:`_fit_repair`), whose intervals are taken only when reported.

    Attributes
    ----------
    problem : _RowProblem
    est : _RowEstimate
    specs : dict
        ``{j: _ElementSpec}`` of the fit (element ``m`` is ``sorted(specs)[m]``).
    references : dict
        ``{j: reference}`` (the lags of a second-order element are named after its reference's).
    """

    problem: _RowProblem
    est: _RowEstimate
    specs: dict
    references: dict

    def put_intervals(self, verdicts: dict, settings: _TestSettings) -> None:
        """Replace the intervals of the fit's free parameters in the verdicts' ``interval`` (in place).

        Not needed when :func:`_refit_on_all` refits the elements: it replaces the same intervals
        (the same parameters are free in both fits).
        """
        ts = self.problem.ts
        for m, j in enumerate(sorted(self.specs)):
            _, interval = _element_summary(self.problem, self.est, m, ts, settings, self.references[j])
            _update_free_intervals(verdicts[j].interval, interval, self.specs[j])


def _fit_repair(free: _FreeFit, verdicts: dict, n_fit: int, settings: _TestSettings) -> Optional[_RepairFit]:
    """Stage 2: fit what changed on samples ``0 .. n_fit - 1``; the verdicts' ``after`` and
    ``evidence["condition_number_repair"]`` are updated in place.

    Returns the fit, whose :meth:`_RepairFit.put_intervals` puts its free intervals into the
    verdicts, or None when no element changed (nothing fitted).
    """
    row = free.row
    ts = row.model.sample_time
    specs, lags0 = _repair_specs(free, verdicts)
    if not specs:
        return None
    problem, est = _estimate_row(row, specs, lags0, n_fit, settings.options)
    references = {j: free.located[j].reference for j in specs}
    for m, j in enumerate(sorted(specs)):
        v = verdicts[j]
        fewer = specs[j].form != v.form           # one lag fewer where a lag vanished (_reduce_vanished_lags)
        v.after = _compose(_element_after(problem, est, m, ts, references[j]), references[j], specs[j],
                           fewer_lags=fewer)
        v.form = specs[j].form
        v.evidence["condition_number_repair"] = est.cond
    return _RepairFit(problem=problem, est=est, specs=specs, references=references)


def _refit_on_all(row: _RowData, verdicts: dict, settings: _TestSettings) -> None:
    """Refit accepted elements on the whole record with the validated structure (lags +-3 samples).

    ``verdicts`` (``{j: ElementVerdict}``, the accepted ones) get the new ``after`` and a new
    ``interval`` dict with the free parameters' intervals replaced.  A first-order element whose lag
    was lost (its reference has one, its repair none) is refitted as the pure gain it was repaired as:
    its pole freed again would come back a hair above its bound, a lag of ``T / 8`` read a sample
    earlier.
    """
    ts = row.model.sample_time
    specs, lags0 = {}, {}
    for j, v in verdicts.items():
        changed = set(v.changed) | ({"gain", "time_constant", "delay"} if v.kind == "missing" else set())
        a, form = v.after, v.form
        lag = _input_lag(form, a, ts)
        window = (max(1, lag - 3), lag + 3) if "delay" in changed else (lag, lag)
        lost_lag = (form.first_order and not form.integrating and a["time_constant"] == 0
                    and (v.reference or {}).get("time_constant", 0.0) > 0)
        pole_free = "time_constant" in changed and form.n_shape > 0 and not lost_lag
        specs[j] = _ElementSpec("gain" in changed, pole_free, a["gain"], _poles_of(form, a, ts), window, form=form,
                                lead=a["lead"])
        lags0[j] = lag
    problem, est = _estimate_row(row, specs, lags0, row.n_samples, settings.options)
    for m, j in enumerate(sorted(specs)):
        fitted, interval = _element_summary(problem, est, m, ts, settings, verdicts[j].after)
        sp = specs[j]
        v: ElementVerdict = verdicts[j]
        iv = dict(v.interval)
        _update_free_intervals(iv, interval, sp)
        v.after, v.interval = _compose(fitted, v.after, sp, held_lag_too=True), iv
