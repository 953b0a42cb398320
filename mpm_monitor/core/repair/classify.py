"""Which parameters of the located elements of a row changed: likelihood-ratio tests and kinds.

On the whole record (the most evidence) the located elements of a row are fitted with gain, time
constant and delay free (:func:`_fit_free`), and every parameter is tested against the model's
value by refitting the row with that parameter held (:meth:`_FreeFit.hold_statistic`;
``n ln(SSR_held / SSR_free)`` against chi-square, Ljung, *System Identification*, 2nd ed., 1999,
section 16.5; the delay by its profile over the lag grid).  The parameters judged unchanged are
then held together (:func:`_joint_hold`): gain and time constant, or two elements on inputs that
move together, can each stand in for the other, so that each alone looks unchanged while holding
both does not fit.  The kind of each element follows from what changed (:func:`_verdict`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..statistics import chi2_tail
from .fit import _element_lag, _ElementSpec, _lag_lr, _pole_of, _RowEstimate, _RowProblem
from .options import RepairOptions, _TestSettings
from .result import ElementVerdict
from .row import _element_summary, _estimate_row, _RowData

#: The parameter a test holds at the model's value ("absent": the whole element at gain 0).
_PARAM_OF_TEST = {"gain": "gain", "time_constant": "pole", "delay": "lag", "missing": "absent"}

#: The order in which changed parameters are listed; the first names the kind of a single change.
_TEST_ORDER = ["missing", "gain", "time_constant", "delay"]


def _margin(p, alpha):
    """How clearly a p-value lies on its side of ``alpha``: 0 at the threshold, 1 far from it."""
    if p <= 0:
        return 1.0
    return float(1.0 - min(p / alpha, alpha / p))


@dataclasses.dataclass
class _ElementTests:
    """The tests of one located element.

    Attributes
    ----------
    results : dict
        ``{test: [p-value of "unchanged", change large enough]}``; the tests are "missing" for an
        element the model does not have, else "gain", "time_constant" and "delay".
    changed : set of str
        The tests that found a change (significant and large enough, or freed by the joint test).
    margins : dict
        ``{test: margin}`` (see :func:`_margin`).
    """

    results: dict
    changed: set
    margins: dict

    @classmethod
    def of(cls, results: dict, alpha: float) -> "_ElementTests":
        return cls(results=results, changed={k for k, (p, big) in results.items() if p < alpha and big},
                   margins={k: _margin(p, alpha) for k, (p, _) in results.items()})

    def unchanged(self) -> list:
        """The tests that found no change, in test order."""
        return [k for k in self.results if k not in self.changed]


@dataclasses.dataclass
class _FreeFit:
    """The whole-record fit of a row's located elements with gain, time constant and delay free.

    Attributes
    ----------
    row : _RowData
    js : list of int
        Input indices of the located elements, sorted (element ``m`` of the fit is ``js[m]``).
    specs : dict
        ``{j: _ElementSpec}`` of the fit: everything free, lags searched around the model's.
    lag_orig : dict
        ``{j: input lag of the model's element}`` (samples).
    problem : _RowProblem
    est : _RowEstimate
    """

    row: _RowData
    js: list
    specs: dict
    lag_orig: dict
    problem: _RowProblem
    est: _RowEstimate

    def hold_statistic(self, holds: dict, options: RepairOptions) -> float:
        """Likelihood-ratio statistic of holding parameters of located elements at the model's values.

        The row is refitted with, for each element index ``m`` in ``holds``, the parameters named
        in ``holds[m]`` ("gain", "pole", "lag", or "absent": no effect at all) held at the model's
        values, the other lags at their optimum and everything else free; the statistic is
        ``n ln(SSR_held / SSR_free)``, chi-square with as many degrees of freedom as parameters
        held when they did not change (Ljung 1999, section 16.5).  Unlike a Wald test on the
        Jacobian it does not depend on the parametrization, which matters along the ridge where
        gain and time constant trade off.
        """
        model, i, est = self.row.model, self.row.i, self.est
        held, lags = {}, {}
        for m, j in enumerate(self.js):
            sp = self.specs[j]
            lag = est.fit.lags[m]
            what = holds.get(m, set())
            if "lag" in what:
                lag = self.lag_orig[j]
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
        skip = self.problem.start - self.problem.p
        _, est_h = _estimate_row(self.row, held, lags, self.row.n_samples, options, 1, skip=skip, ar0=est.ar,
                                 need_cov=False)
        return max(est_h.fit.n_resid * math.log(max(est_h.fit.ssr, 1e-300) / max(est.fit.ssr, 1e-300)), 0.0)


def _free_specs(row: _RowData, js, options: RepairOptions):
    """Specs of the free fit: everything free, lags within ``max_delay_shift`` of the model's.

    An element the model does not have (gain 0) starts at the row's median time constant and the
    row's largest input lag, searched from 1 to that lag plus ``max_delay_shift``.

    Returns
    -------
    specs : dict
        ``{j: _ElementSpec}``.
    lags0 : dict
        ``{j: start lag}``.
    lag_orig : dict
        ``{j: input lag of the model's element}``.
    """
    model, i = row.model, row.i
    ts = model.sample_time
    gain, tau, nd = model.gain, model.time_constant, model.delay_samples
    row_nonzero = gain[i] != 0
    row_taus = tau[i][row_nonzero & (tau[i] > 0)]
    base_tau = float(np.median(row_taus)) if row_taus.size else 10.0 * ts
    max_row_lag = max([_element_lag(tau[i, j], nd[i, j]) for j in range(model.n_columns) if row_nonzero[j]],
                      default=1)
    s = options.max_delay_shift
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
    return specs, lags0, lag_orig


def _fit_free(row: _RowData, js, options: RepairOptions) -> _FreeFit:
    """Fit the located elements ``js`` of the row on the whole record with everything free."""
    specs, lags0, lag_orig = _free_specs(row, js, options)
    problem, est = _estimate_row(row, specs, lags0, row.n_samples, options, options.max_sweeps)
    return _FreeFit(row=row, js=list(js), specs=specs, lag_orig=lag_orig, problem=problem, est=est)


def _single_tests(free: _FreeFit, settings: _TestSettings):
    """The fitted parameters of each element and the test of each of its parameters alone.

    Returns
    -------
    summaries : dict
        ``{j: (after, interval)}`` (see :func:`_element_summary`).
    tests : dict
        ``{j: _ElementTests}``.
    """
    model, i = free.row.model, free.row.i
    ts = model.sample_time
    options = settings.options
    summaries, tests = {}, {}
    for m, j in enumerate(free.js):
        after, interval = _element_summary(free.problem, free.est, m, ts, settings)
        summaries[j] = (after, interval)
        before = model.element(i, j)
        t = {}
        if before["gain"] == 0:
            t["missing"] = [float(chi2_tail(free.hold_statistic({m: {"absent"}}, options), 1)), True]
        else:
            t["gain"] = [float(chi2_tail(free.hold_statistic({m: {"gain"}}, options), 1)),
                         abs(after["gain"] - before["gain"]) > options.min_relative_change * abs(before["gain"])]
            tau0 = before["time_constant"]
            t["time_constant"] = [float(chi2_tail(free.hold_statistic({m: {"pole"}}, options), 1)),
                                  abs(after["time_constant"] - tau0) > options.min_relative_change * max(tau0, ts)]
            w = free.specs[j].window
            lag0 = free.lag_orig[j]
            p_d = float(chi2_tail(_lag_lr(free.est, m, lag0), 1)) if w[0] <= lag0 <= w[1] else 0.0
            t["delay"] = [p_d, after["delay"] != before["delay"]]
        tests[j] = _ElementTests.of(t, settings.alpha)
    return summaries, tests


def _joint_hold(free: _FreeFit, tests: dict, settings: _TestSettings, warnings: list):
    """Test the parameters judged unchanged held together; free the likeliest changed while it rejects.

    While the joint likelihood-ratio test of every held parameter rejects at ``alpha``, the held
    parameter with the smallest single p-value is added to its element's ``changed`` (its margin
    becomes that of the joint test) and a warning says so; ``tests`` (``{j: _ElementTests}``) and
    ``warnings`` are updated in place.

    Returns
    -------
    float or None
        The p-value of the last joint test (None when nothing was held).
    """
    alpha, js = settings.alpha, free.js
    joint_p = None
    while True:
        holds = {m: {_PARAM_OF_TEST[k] for k in tests[j].unchanged()} for m, j in enumerate(js)}
        n_held = sum(len(h) for h in holds.values())
        if n_held == 0:
            break
        joint_p = float(chi2_tail(free.hold_statistic(holds, settings.options), n_held))
        if joint_p >= alpha:
            break
        j_free, k_free = min(((j, k) for j in js for k in tests[j].unchanged()),
                             key=lambda jk: tests[jk[0]].results[jk[1]][0])
        tests[j_free].changed.add(k_free)
        tests[j_free].margins[k_free] = _margin(joint_p, alpha)
        warnings.append(f"{free.row.name(j_free)}: its {k_free.replace('_', ' ')} alone does not show a "
                        f"significant change, but holding it together with the other unchanged parameters of the "
                        f"row does not fit the data (p = {joint_p:.2g}); it is re-estimated too.")
    return joint_p


def _verdict(est: _RowEstimate, summary: tuple, tests: _ElementTests, joint_p, alpha: float) -> ElementVerdict:
    """The kind, the confidence and the evidence of an element from its tests.

    One changed parameter names the kind (gain, time_constant or delay), several give "mixed", a
    significant element the model does not have "missing", nothing "unknown".  The confidence is
    the smallest margin of the tests, including the joint test when the element has a parameter
    held in it.
    """
    after, interval = summary
    results = tests.results
    hits = sorted(tests.changed, key=_TEST_ORDER.index)
    if "missing" in hits:
        kind = "missing"
    elif not hits:
        kind = "unknown"
    else:
        kind = hits[0] if len(hits) == 1 else "mixed"
    confidence = min(tests.margins.values())
    if joint_p is not None and tests.unchanged():
        confidence = min(confidence, _margin(joint_p, alpha))
    evidence = {"p_gain": results.get("gain", results.get("missing"))[0],
                "p_time_constant": results["time_constant"][0] if "time_constant" in results else None,
                "p_delay": results["delay"][0] if "delay" in results else None,
                "p_unchanged_jointly": joint_p, "condition_number": est.cond, "samples": est.fit.n_resid,
                "noise_model": [float(v) for v in est.ar]}
    return ElementVerdict(kind=kind, changed=hits, after=after, interval=interval, evidence=evidence,
                          confidence=confidence, apply=kind != "unknown")


def _verdict_warnings(free: _FreeFit, m: int, verdict: ElementVerdict, alpha: float) -> list:
    """What limits the verdict on element ``m``: a best delay at the edge of its range, no change found."""
    name = free.row.name(free.js[m])
    out = []
    if free.est.edge[m]:
        out.append(f"{name}: the best delay lies at the edge of the searched range; "
                   f"the true delay may lie outside it (raise max_delay_shift).")
    if verdict.kind == "unknown":
        out.append(
            f"{name}: located as mismatched, but no parameter of the element differs "
            f"significantly from the model (at {100 * (1 - alpha):.4g}% confidence); the element is kept. "
            f"The mismatch may be too small for these data or not of first-order-plus-dead-time form.")
    return out


def _classify_row(row: _RowData, js, settings: _TestSettings):
    """Classify the located elements ``js`` of the row on the whole record.

    Returns
    -------
    free : _FreeFit
        The fit with everything free (the start of the repair fit).
    verdicts : dict
        ``{j: ElementVerdict}``, ``after`` and ``interval`` from the free fit.
    warnings : list of str
    """
    alpha = settings.alpha
    free = _fit_free(row, js, settings.options)
    warnings = []
    summaries, tests = _single_tests(free, settings)
    joint_p = _joint_hold(free, tests, settings, warnings)
    verdicts = {}
    for m, j in enumerate(free.js):
        verdicts[j] = _verdict(free.est, summaries[j], tests[j], joint_p, alpha)
        warnings.extend(_verdict_warnings(free, m, verdicts[j], alpha))
    if free.est.cond > 1e3 and len(free.js) > 1:
        names_u = row.model.columns
        warnings.append(
            f"{row.name()}: the inputs {', '.join(names_u[j] for j in free.js)} move together in these data "
            f"(condition number {free.est.cond:.3g}); their elements are hard to tell apart. More independent "
            f"excitation of these inputs (dither) would help.")
    return free, verdicts, warnings
