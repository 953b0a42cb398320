"""The final refit of accepted elements on the whole record."""

from __future__ import annotations

from .fit import _element_lag, _ElementSpec, _pole_of
from .row import _element_summary, _estimate_row


def _refit_row(model, u, y, i, verdicts: dict, n, options, zcrit, chi_crit, extra=None):
    """Refit accepted elements on the whole record with the validated structure (lags +-3 samples)."""
    ts = model.sample_time
    specs, lags0 = {}, {}
    for j, v in verdicts.items():
        changed = set(v["changed"]) | ({"gain", "time_constant", "delay"} if v["kind"] == "missing" else set())
        a = v["after"]
        lag = _element_lag(a["time_constant"], int(round(a["delay"] / ts)))
        window = (max(1, lag - 3), lag + 3) if "delay" in changed else (lag, lag)
        specs[j] = _ElementSpec("gain" in changed, "time_constant" in changed, a["gain"],
                                _pole_of(a["time_constant"], ts), window)
        lags0[j] = lag
    problem, est = _estimate_row(model, u, y, i, specs, n, options, lags0, 1, extra=extra)
    out = {}
    for m, j in enumerate(sorted(specs)):
        after, interval, _ = _element_summary(problem, est, m, ts, zcrit, chi_crit)
        sp = specs[j]
        old = verdicts[j]["after"]
        new = {"gain": after["gain"] if sp.gain_free else old["gain"],
               "time_constant": after["time_constant"] if sp.pole_free else old["time_constant"],
               "delay": after["delay"] if (sp.lag_free or after["time_constant"] == 0.0) else old["delay"]}
        iv = dict(verdicts[j]["interval"])
        for key, free in (("gain", sp.gain_free), ("time_constant", sp.pole_free), ("delay", sp.lag_free)):
            if free:
                iv[key] = interval[key]
        out[j] = {"after": new, "interval": iv, "edge": est.edge[m]}
    return out
