"""Which parameters of a located element changed: likelihood-ratio tests and kinds."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .fit import _element_lag, _ElementSpec, _lag_lr, _pole_of
from .row import _element_summary, _estimate_row


def _p_from_z(zv):
    return float(2.0 * stats.norm.sf(abs(zv)))


def _margin(p, alpha):
    """How clearly a p-value lies on its side of ``alpha``: 0 at the threshold, 1 far from it."""
    if p <= 0:
        return 1.0
    return float(1.0 - min(p / alpha, alpha / p))


def _lr_hold(model, u, y, i, specs, est, holds: dict, lag_orig: dict, n_use, options, skip, extra=None):
    """Likelihood-ratio statistic of holding parameters of located elements at the model's values.

    The row is refitted with, for each element index ``m`` in ``holds``, the parameters named in
    ``holds[m]`` ("gain", "pole", "lag", or "absent": no effect at all) held at the model's values,
    the other lags at their optimum and everything else free; the statistic is
    ``n ln(SSR_held / SSR_free)``, chi-square with as many degrees of freedom as parameters held
    when they did not change (Ljung 1999, section 16.5).  Unlike a Wald test on the Jacobian it
    does not depend on the parametrization, which matters along the ridge where gain and time
    constant trade off.
    """
    js = sorted(specs)
    held, lags = {}, {}
    for m, j in enumerate(js):
        sp = specs[j]
        lag = est.fit.lags[m]
        what = holds.get(m, set())
        if "lag" in what:
            lag = lag_orig[j]
        sp_new = _ElementSpec(sp.gain_free, sp.pole_free, float(est.fit.gains[m]), float(est.fit.poles[m]),
                              (lag, lag))
        if "gain" in what:
            sp_new.gain_free, sp_new.gain = False, float(model.gain[i, j])
        if "pole" in what:
            sp_new.pole_free, sp_new.pole = False, _pole_of(model.time_constant[i, j], model.sample_time)
        if "absent" in what:
            sp_new.gain_free, sp_new.gain, sp_new.pole_free = False, 0.0, False
        held[j] = sp_new
        lags[j] = lag
    _, est_h = _estimate_row(model, u, y, i, held, n_use, options, lags, 1, skip=skip, extra=extra, ar0=est.ar,
                             need_cov=False)
    return max(est_h.fit.n_resid * math.log(max(est_h.fit.ssr, 1e-300) / max(est.fit.ssr, 1e-300)), 0.0)


_PARAM_OF_TEST = {"gain": "gain", "time_constant": "pole", "delay": "lag", "missing": "absent"}


def _repair_row(model, u, y, i, js, n_fit, options, zcrit, chi_crit, alpha, extra=None):
    """Classify the located elements ``js`` of row ``i`` and fit their repair on samples ``0 .. n_fit-1``.

    Stage 1 (whole record, the most evidence) frees gain, time constant and delay of every located
    element and tests each against the model's value by a likelihood-ratio test.  Parameters
    judged unchanged are then held *together* and that joint hypothesis tested as well: gain and
    time constant (or two elements on inputs that move together) can each stand in for the other,
    so that each alone looks unchanged while holding both does not fit; while the joint test
    rejects, the held parameter with the strongest evidence of change is freed.  Stage 2 (first
    ``n_fit`` samples, so that the rest validates it) refits only what changed (everything for a
    missing element) with the rest held at the model's values; elements without a change are held
    entirely.  Fewer free parameters give tighter, less biased estimates when inputs move together.

    Returns
    -------
    dict
        ``elements``: ``{j: verdict}``, ``warnings``: list of str.
    """
    ts = model.sample_time
    n_all = u.shape[0]
    names_y, names_u = model.outputs, model.inputs
    gain, tau, nd = model.gain, model.time_constant, model.delay_samples
    row_nonzero = gain[i] != 0
    row_taus = tau[i][row_nonzero & (tau[i] > 0)]
    base_tau = float(np.median(row_taus)) if row_taus.size else 10.0 * ts
    max_row_lag = max([_element_lag(tau[i, j], nd[i, j]) for j in range(model.n_inputs) if row_nonzero[j]],
                      default=1)
    s = options.max_delay_shift
    warnings = []
    specs, lags0, lag_orig = {}, {}, {}
    for j in js:
        if gain[i, j] != 0:
            lag = max(1, _element_lag(tau[i, j], nd[i, j]))
            pole = _pole_of(tau[i, j], ts) if tau[i, j] > 0 else _pole_of(base_tau, ts)
            specs[j] = _ElementSpec(True, True, gain[i, j], pole, (max(1, lag - s), lag + s))
        else:
            lag = max_row_lag
            specs[j] = _ElementSpec(True, True, 0.0, _pole_of(base_tau, ts), (1, max_row_lag + s))
        lags0[j] = lag
        lag_orig[j] = _element_lag(tau[i, j], nd[i, j])
    problem, est = _estimate_row(model, u, y, i, specs, n_all, options, lags0, options.max_sweeps, extra=extra)
    skip1 = problem.start - problem.p

    def lr(holds):
        return _lr_hold(model, u, y, i, specs, est, holds, lag_orig, n_all, options, skip1, extra)

    # Individual tests.
    summaries, tests = {}, {}
    for m, j in enumerate(js):
        after, interval, _ = _element_summary(problem, est, m, ts, zcrit, chi_crit)
        summaries[j] = (after, interval)
        before = model.element(i, j)
        t = {}
        if before["gain"] == 0:
            t["missing"] = [float(stats.chi2.sf(lr({m: {"absent"}}), 1)), True]
        else:
            t["gain"] = [float(stats.chi2.sf(lr({m: {"gain"}}), 1)),
                         abs(after["gain"] - before["gain"]) > options.min_relative_change * abs(before["gain"])]
            tau0 = before["time_constant"]
            t["time_constant"] = [float(stats.chi2.sf(lr({m: {"pole"}}), 1)),
                                  abs(after["time_constant"] - tau0) > options.min_relative_change * max(tau0, ts)]
            w = specs[j].window
            p_d = float(stats.chi2.sf(_lag_lr(est, m, lag_orig[j]), 1)) \
                if w[0] <= lag_orig[j] <= w[1] else 0.0
            t["delay"] = [p_d, after["delay"] != before["delay"]]
        tests[j] = t
    changed = {j: {k for k, (p, big) in tests[j].items() if p < alpha and big} for j in js}
    margins = {j: {k: _margin(p, alpha) for k, (p, _) in tests[j].items()} for j in js}
    # Joint test of everything held.
    joint_p = None
    while True:
        holds = {m: {_PARAM_OF_TEST[k] for k in tests[j] if k not in changed[j]} for m, j in enumerate(js)}
        n_held = sum(len(h) for h in holds.values())
        if n_held == 0:
            break
        joint_p = float(stats.chi2.sf(lr(holds), n_held))
        if joint_p >= alpha:
            break
        j_free, k_free = min(((j, k) for j in js for k in tests[j] if k not in changed[j]),
                             key=lambda jk: tests[jk[0]][jk[1]][0])
        changed[j_free].add(k_free)
        margins[j_free][k_free] = _margin(joint_p, alpha)
        warnings.append(f"{names_y[i]}/{names_u[j_free]}: its {k_free.replace('_', ' ')} alone does not show a "
                        f"significant change, but holding it together with the other unchanged parameters of the "
                        f"row does not fit the data (p = {joint_p:.2g}); it is re-estimated too.")
    verdicts = {}
    for m, j in enumerate(js):
        after, interval = summaries[j]
        hits = sorted(changed[j], key=["missing", "gain", "time_constant", "delay"].index)
        if "missing" in hits:
            kind = "missing"
        elif not hits:
            kind = "unknown"
        else:
            kind = hits[0] if len(hits) == 1 else "mixed"
        confidence = min(margins[j].values())
        if joint_p is not None and any(k not in changed[j] for k in tests[j]):
            confidence = min(confidence, _margin(joint_p, alpha))
        evidence = {"p_gain": tests[j].get("gain", tests[j].get("missing"))[0],
                    "p_time_constant": tests[j]["time_constant"][0] if "time_constant" in tests[j] else None,
                    "p_delay": tests[j]["delay"][0] if "delay" in tests[j] else None,
                    "p_unchanged_jointly": joint_p, "condition_number": est.cond, "samples": est.fit.n_resid,
                    "noise_model": [float(v) for v in est.ar]}
        verdicts[j] = {"kind": kind, "changed": hits, "after": after, "interval": interval,
                       "evidence": evidence, "confidence": confidence, "apply": kind != "unknown"}
        if est.edge[m]:
            warnings.append(f"{names_y[i]}/{names_u[j]}: the best delay lies at the edge of the searched range; "
                            f"the true delay may lie outside it (raise max_delay_shift).")
        if kind == "unknown":
            warnings.append(
                f"{names_y[i]}/{names_u[j]}: located as mismatched, but no parameter of the element differs "
                f"significantly from the model (at {100 * (1 - alpha):.4g}% confidence); the element is kept. "
                f"The mismatch may be too small for these data or not of first-order-plus-dead-time form.")
    if est.cond > 1e3 and len(js) > 1:
        warnings.append(
            f"{names_y[i]}: the inputs {', '.join(names_u[j] for j in js)} move together in these data "
            f"(condition number {est.cond:.3g}); their elements are hard to tell apart. More independent "
            f"excitation of these inputs (dither) would help.")
    # Stage 2: only what changed is free; fitted on the first n_fit samples.
    specs2, lags2 = {}, {}
    for m, j in enumerate(js):
        v = verdicts[j]
        if v["kind"] == "unknown":
            continue
        missing = v["kind"] == "missing"
        free_k = missing or "gain" in v["changed"]
        free_t = missing or "time_constant" in v["changed"]
        free_d = missing or "delay" in v["changed"]
        specs2[j] = _ElementSpec(free_k, free_t, est.fit.gains[m] if free_k else gain[i, j],
                                 est.fit.poles[m] if free_t else _pole_of(tau[i, j], ts),
                                 specs[j].window if free_d else (lag_orig[j], lag_orig[j]))
        lags2[j] = est.fit.lags[m] if free_d else lag_orig[j]
    if specs2:
        problem2, est2 = _estimate_row(model, u, y, i, specs2, n_fit, options, lags2, 1, extra=extra)
        for m, j in enumerate(sorted(specs2)):
            after2, interval2, _ = _element_summary(problem2, est2, m, ts, zcrit, chi_crit)
            sp = specs2[j]
            v = verdicts[j]
            after = {"gain": float(after2["gain"] if sp.gain_free else gain[i, j]),
                     "time_constant": float(after2["time_constant"] if sp.pole_free else tau[i, j]),
                     "delay": float(after2["delay"] if sp.lag_free else model.delay[i, j])}
            if not sp.lag_free and sp.pole_free and after2["time_constant"] == 0.0:
                after["delay"] = after2["delay"]  # a vanished lag moves the sample into the delay
            for key, free in (("gain", sp.gain_free), ("time_constant", sp.pole_free), ("delay", sp.lag_free)):
                if free:
                    v["interval"][key] = interval2[key]
            v["after"] = after
            v["evidence"]["condition_number_repair"] = est2.cond
    return {"elements": verdicts, "warnings": warnings}
