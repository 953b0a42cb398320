"""The repair fit: only what changed is re-estimated, first for validation, then on the whole record.

:func:`_fit_repair` (stage 2) refits, on the first ``n_fit`` samples so that the rest validates
it, only the parameters the classification found changed (everything for a missing element),
with the rest held at the model's values; elements without a change are held entirely.  Fewer
free parameters give tighter, less biased estimates when inputs move together.
:func:`_refit_on_all` refits the accepted elements on the whole record with the validated
structure.
"""

from __future__ import annotations

from .classify import _FreeFit
from .fit import _element_lag, _ElementSpec, _pole_of
from .options import _TestSettings
from .result import ElementVerdict
from .row import _element_summary, _estimate_row, _RowData


def _update_free_intervals(interval: dict, new: dict, spec: _ElementSpec) -> None:
    """Replace in ``interval`` the intervals of the parameters ``spec`` leaves free by those of ``new``."""
    for key, free in (("gain", spec.gain_free), ("time_constant", spec.pole_free), ("delay", spec.lag_free)):
        if free:
            interval[key] = new[key]


def _repair_specs(free: _FreeFit, verdicts: dict):
    """Specs of the repair fit: the changed parameters free from the free fit's values, the rest held.

    Elements of kind "unknown" are left out (held at the model's values).  Returns the specs
    ``{j: _ElementSpec}`` and the start lags ``{j: lag}``: the free fit's lag where the delay
    changed, the model's elsewhere.
    """
    model, i, est = free.row.model, free.row.i, free.est
    ts = model.sample_time
    specs, lags0 = {}, {}
    for m, j in enumerate(free.js):
        v = verdicts[j]
        if v.kind == "unknown":
            continue
        missing = v.kind == "missing"
        free_k = missing or "gain" in v.changed
        free_t = missing or "time_constant" in v.changed
        free_d = missing or "delay" in v.changed
        lag_orig = free.lag_orig[j]
        specs[j] = _ElementSpec(free_k, free_t, est.fit.gains[m] if free_k else model.gain[i, j],
                                est.fit.poles[m] if free_t else _pole_of(model.time_constant[i, j], ts),
                                free.specs[j].window if free_d else (lag_orig, lag_orig))
        lags0[j] = est.fit.lags[m] if free_d else lag_orig
    return specs, lags0


def _fit_repair(free: _FreeFit, verdicts: dict, n_fit: int, settings: _TestSettings) -> None:
    """Stage 2: fit what changed on samples ``0 .. n_fit - 1``; the verdicts' ``after``, free
    intervals and ``evidence["condition_number_repair"]`` are updated in place."""
    row = free.row
    model, i = row.model, row.i
    ts = model.sample_time
    specs, lags0 = _repair_specs(free, verdicts)
    if not specs:
        return
    problem, est = _estimate_row(row, specs, lags0, n_fit, settings.options)
    for m, j in enumerate(sorted(specs)):
        fitted, interval = _element_summary(problem, est, m, ts, settings)
        sp = specs[j]
        v = verdicts[j]
        after = {"gain": float(fitted["gain"] if sp.gain_free else model.gain[i, j]),
                 "time_constant": float(fitted["time_constant"] if sp.pole_free else model.time_constant[i, j]),
                 "delay": float(fitted["delay"] if sp.lag_free else model.delay[i, j])}
        if not sp.lag_free and sp.pole_free and fitted["time_constant"] == 0.0:
            after["delay"] = fitted["delay"]  # a vanished lag moves the sample into the delay
        _update_free_intervals(v.interval, interval, sp)
        v.after = after
        v.evidence["condition_number_repair"] = est.cond


def _refit_on_all(row: _RowData, verdicts: dict, settings: _TestSettings) -> None:
    """Refit accepted elements on the whole record with the validated structure (lags +-3 samples).

    ``verdicts`` (``{j: ElementVerdict}``, the accepted ones) get the new ``after`` and a new
    ``interval`` dict with the free parameters' intervals replaced.
    """
    ts = row.model.sample_time
    specs, lags0 = {}, {}
    for j, v in verdicts.items():
        changed = set(v.changed) | ({"gain", "time_constant", "delay"} if v.kind == "missing" else set())
        a = v.after
        lag = _element_lag(a["time_constant"], int(round(a["delay"] / ts)))
        window = (max(1, lag - 3), lag + 3) if "delay" in changed else (lag, lag)
        specs[j] = _ElementSpec("gain" in changed, "time_constant" in changed, a["gain"],
                                _pole_of(a["time_constant"], ts), window)
        lags0[j] = lag
    problem, est = _estimate_row(row, specs, lags0, row.n_samples, settings.options)
    for m, j in enumerate(sorted(specs)):
        fitted, interval = _element_summary(problem, est, m, ts, settings)
        sp = specs[j]
        v: ElementVerdict = verdicts[j]
        old = v.after
        new = {"gain": fitted["gain"] if sp.gain_free else old["gain"],
               "time_constant": fitted["time_constant"] if sp.pole_free else old["time_constant"],
               "delay": fitted["delay"] if (sp.lag_free or fitted["time_constant"] == 0.0) else old["delay"]}
        iv = dict(v.interval)
        _update_free_intervals(iv, interval, sp)
        v.after, v.interval = new, iv
