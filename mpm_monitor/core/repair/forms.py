"""The structure of a re-estimated element: its lags, lead and integrator, sampled for the fit.

A located element is fitted in a *form* (:class:`_Form`): ``n_lags`` lags (each as its discrete pole
``a = exp(-T / tau)``), with or without a lead, with or without an integrator::

    G(s) = K (lead s + 1) e^{-theta s} / ((tau s + 1)(tau2 s + 1))        (over s when integrating)

For given poles the sampled (zero-order-hold) element is linear in ``K`` and ``K lead``::

    G(q) = K G_a(q) + (K lead) G_b(q),   G_a = ZOH{1 / den(s)},  G_b = ZOH{s / den(s)}

so the fit eliminates both by variable projection and searches only the poles (and the delay on the
sample grid).  The first-order form without lead or integrator is sampled in closed form,
``G_a = (1 - a) q^-1 / (1 - a q^-1)``, the same numbers as before the other structures existed;
every other form through :func:`~mpm_monitor.core.elements.sample_parametric`, the one exact sampled
form of the model.

An element the model has keeps its declared form.  An element the model lacks, and every element
of a step-response model, is fitted in the form the data call for (:data:`_LADDER_MISSING`,
:data:`_LADDER_STEP`); a step-response element is compared with the parametric form of its old
response (:func:`_step_reference`) and written back as the sampled step response of the same
length (:func:`_step_coefficients`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..discretize import REPEATED_POLE_TOLERANCE
from ..elements import dead_time_samples, pulse_response, sample_parametric
from ..filters import lfilter
from ..model import PlantModel
from .lsq import least_squares_bounded, solver_scale

#: Bounds of a lag element's discrete pole ``a = exp(-T / tau)`` during the fit.
_POLE_MIN, _POLE_MAX = 1e-4, 0.9995
#: Input lags searched on either side of a step response's dead time for its parametric form.
_LAG_SHIFT = 3


@dataclasses.dataclass(frozen=True)
class _Form:
    """The structure of a fitted element.

    Attributes
    ----------
    n_lags : int
        Lags fitted as poles (0, 1 or 2; 0 only with an integrator).
    lead : bool
        A lead ``(lead s + 1)`` (its coefficient ``K lead`` enters linearly).
    integrating : bool
        A pole at ``s = 0`` (``K`` per second).
    """

    n_lags: int = 1
    lead: bool = False
    integrating: bool = False

    @property
    def first_order(self) -> bool:
        """The first-order form (one lag, no lead, no integrator), sampled in closed form."""
        return self.n_lags == 1 and not self.lead and not self.integrating

    @property
    def offset(self) -> int:
        """Samples between the dead time and the first sample the input acts: 1 for a strictly proper
        element, 0 when the lead makes it biproper (a lead with one lag and no integrator)."""
        return 1 if self.n_lags + int(self.integrating) - int(self.lead) >= 1 else 0

    @property
    def n_shape(self) -> int:
        """Parameters of the shape: the lags and the lead (the ``time_constant`` test holds them)."""
        return self.n_lags + int(self.lead)

    def describe(self) -> str:
        """``first-order``, ``second-order with a lead``, ``integrating with one lag``, ... (for messages)."""
        if self.integrating:
            text = "integrating" + {0: "", 1: " with one lag", 2: " with two lags"}[self.n_lags]
            return text + (" and a lead" if self.lead else "")
        return ("first-order" if self.n_lags == 1 else "second-order") + (" with a lead" if self.lead else "")


FIRST_ORDER = _Form()

#: Forms tried, in order, for an element the model lacks: a first-order fit, a second lag where the
#: data call for it.
_LADDER_MISSING = (FIRST_ORDER, _Form(n_lags=2))
#: The same on an integrating output (a level; a step-response model's ``ramp`` row): every effect on
#: it integrates, as its own elements do (a flow the model lacks, a candidate channel).
_LADDER_MISSING_INTEGRATING = (_Form(integrating=True), _Form(n_lags=2, integrating=True))


def _missing_ladder(model: PlantModel, i: int) -> tuple:
    """The forms tried for an element the model lacks in row ``i``."""
    if model.integrating_outputs[i]:
        return _LADDER_MISSING_INTEGRATING
    return _LADDER_MISSING
#: Forms tried, in order, for an element of a step-response model (self-regulating).
_LADDER_STEP = (FIRST_ORDER, _Form(n_lags=2), _Form(n_lags=2, lead=True))
#: The same on a ``ramp`` output whose element keeps a slope (integrating), from a pure integrator: read with a
#: lag, the dead time of a pure integrator's response became one sample shorter and a lag of a sample, and a
#: change of its dead time alone was classified ``mixed``.
_LADDER_STEP_RAMP = (_Form(n_lags=0, integrating=True), _Form(integrating=True), _Form(n_lags=2, integrating=True),
                     _Form(n_lags=2, lead=True, integrating=True))


def _pole_of(tau: float, ts: float) -> float:
    """Discrete pole ``exp(-T / tau)`` (the lower pole bound for ``tau = 0``)."""
    return min(max(math.exp(-ts / tau), _POLE_MIN), _POLE_MAX) if tau > 0 else _POLE_MIN


def _tau_of(pole: float, ts: float) -> float:
    """Time constant (s) of a discrete pole in (0, 1)."""
    return float(-ts / math.log(min(max(pole, _POLE_MIN), _POLE_MAX)))


def _form_of(model: PlantModel, i: int, j: int) -> _Form:
    """The declared form of a present parametric element (a pure gain is fitted first order)."""
    lags = int(model.time_constant[i, j] > 0) + int(model.time_constant2[i, j] > 0)
    integrating = bool(model.integrating[i, j])
    if not integrating and lags == 0:
        return FIRST_ORDER
    return _Form(n_lags=lags, lead=bool(model.lead[i, j] != 0), integrating=integrating)


def _step_samples(form: _Form, poles, k: np.ndarray):
    """Unit-step responses at ``t = k T`` of ``1 / den(s)`` and of ``s / den(s)`` of a form.

    ``den(s) = (tau s + 1)(tau2 s + 1)`` (times ``s`` when integrating) with ``exp(-T / tau)`` the
    given poles, in closed form (sums of exponentials, ``t e^{-t/tau}`` for a repeated lag).  The
    second is the time derivative of the first (the step response of ``s G`` is the impulse
    response of ``G``).  Time is counted in samples (``T = 1``); the caller scales.

    Returns
    -------
    s_a, s_b : ndarray, shape (len(k),)
    """
    t = np.asarray(k, float)
    taus = [-1.0 / math.log(a) for a in poles]
    es = [np.asarray(a, float) ** t for a in poles]
    if form.n_lags == 0:
        s_a, ds = t.copy(), np.ones_like(t)
    elif form.n_lags == 1:
        (tau,), (e,) = taus, es
        s_a, ds = 1.0 - e, e / tau
    elif abs(poles[0] - poles[1]) < REPEATED_POLE_TOLERANCE:
        tau = 0.5 * (taus[0] + taus[1])
        e = np.exp(-t / tau)
        s_a, ds = 1.0 - (1.0 + t / tau) * e, t * e / tau ** 2
    else:
        (t1, t2), (e1, e2) = taus, es
        s_a, ds = 1.0 - (t1 * e1 - t2 * e2) / (t1 - t2), (e1 - e2) / (t1 - t2)
    if not form.integrating or form.n_lags == 0:
        return s_a, ds
    # Integrating: the integral of the self-regulating step response.
    if form.n_lags == 1:
        (tau,), (e,) = taus, es
        return t - tau * (1.0 - e), s_a
    if abs(poles[0] - poles[1]) < REPEATED_POLE_TOLERANCE:
        tau = 0.5 * (taus[0] + taus[1])
        e = np.exp(-t / tau)
        return t - 2.0 * tau + (2.0 * tau + t) * e, s_a
    (t1, t2), (e1, e2) = taus, es
    return t - (t1 ** 2 * (1.0 - e1) - t2 ** 2 * (1.0 - e2)) / (t1 - t2), s_a


def _basis(form: _Form, poles, ts: float):
    """The sampled unit responses of a form for given poles, from the element's input lag on.

    The zero-order-hold equivalent is step invariant: ``G(z) = den(z) (1 - z^-1) S(z)`` truncated to
    the order, ``S`` the samples of the continuous step response (:func:`_step_samples`), with
    ``den(z) = prod (1 - a z^-1)`` (and ``1 - z^-1`` for the integrator) -- the numbers of
    :func:`~mpm_monitor.core.elements.sample_parametric`, without its matrix exponential.

    Returns
    -------
    num_a : ndarray
        Numerator of ``G_a`` (``z^0, z^-1, ...`` after the input lag).
    num_b : ndarray or None
        Numerator of ``G_b`` (with a lead), over the same denominator.
    den : ndarray
        Denominator, ``den[0] = 1``.
    """
    if form.first_order:
        a = poles[0]
        return np.array([1.0 - a]), None, np.array([1.0, -a])
    den = np.ones(1)
    for a in poles:
        den = np.convolve(den, [1.0, -a])
    if form.integrating:
        den = np.convolve(den, [1.0, -1.0])
    order = den.size - 1
    s_a, s_b = _step_samples(form, poles, np.arange(order + 1))
    # Time in samples: an integrator's K is per second (times T), a lead's s is per second (over T).
    scale_a = ts if form.integrating else 1.0
    num_a = np.convolve(den, pulse_response(s_a))[:order + 1] * scale_a
    if not form.lead:
        return num_a[form.offset:], None, den
    num_b = np.convolve(den, pulse_response(s_b))[:order + 1] * (scale_a / ts)
    return num_a[form.offset:], num_b[form.offset:], den


def _reads_no_lag(pole: float) -> bool:
    """Whether a first-order element's discrete pole reads as no lag (at most ``2 _POLE_MIN``, a lag under
    ``T / 8.5``): the element is then a pure gain, its dead time its input lag, one sample longer than
    an element with a lag at the same input lag."""
    return pole <= 2 * _POLE_MIN


def _lag_seconds(samples: int, ts: float) -> float:
    """``samples`` sample times in seconds, to 15 significant digits: 6 x 0.1 s is 0.6 s, as a model file writes
    it, not 0.6000000000000001 (an unchanged delay written anew, a change found where there is none)."""
    return float(f"{float(samples) * ts:.15g}")


def _element_params(gain: float, pole: float, lag: int, ts: float, no_lag: bool = False):
    """(gain, time constant in s, delay in s) of a fitted first-order element; a vanishing pole means no lag
    (:func:`_reads_no_lag`), as does ``no_lag``."""
    if no_lag or _reads_no_lag(pole):
        return float(gain), 0.0, _lag_seconds(lag, ts)
    return float(gain), float(-ts / math.log(pole)), _lag_seconds(max(lag - 1, 0), ts)


def _fitted_params(form: _Form, gain: float, poles, lead: float, lag: int, ts: float, no_lag: bool = False) -> dict:
    """The element of a fit in seconds, every parametric key given (``lead``, ``time_constant2``,
    ``integrating`` explicit, so that :meth:`PlantModel.with_element` sets all of them); ``no_lag``: a
    first-order element read as a pure gain (:func:`_element_params`)."""
    if form.first_order:
        out = dict(zip(("gain", "time_constant", "delay"), _element_params(gain, poles[0], lag, ts, no_lag)))
    else:
        taus = [_tau_of(a, ts) for a in poles] + [0.0, 0.0]
        out = {"gain": float(gain), "time_constant": taus[0], "delay": _lag_seconds(max(lag - form.offset, 0), ts),
               "time_constant2": taus[1]}
    out.setdefault("time_constant2", 0.0)
    out["lead"] = float(lead) if form.lead else 0.0
    out["integrating"] = form.integrating
    return out


def _match_lags(params: dict, interval: dict, reference: Optional[dict]) -> None:
    """Name the two fitted lags of a second-order element after the reference's (in place).

    The element is symmetric in its lags, so the fit may return them in either order: each is given
    the name of the reference's lag it is nearer to (in ratio), or, against an element the model
    lacks, the larger is ``time_constant``.  ``interval`` follows.
    """
    t1, t2 = params["time_constant"], params["time_constant2"]
    if t1 <= 0 or t2 <= 0:
        return
    r1, r2 = (reference or {}).get("time_constant", 0.0), (reference or {}).get("time_constant2", 0.0)
    if r1 > 0 and r2 > 0:
        swap = abs(math.log(t2 / r1)) + abs(math.log(t1 / r2)) < abs(math.log(t1 / r1)) + abs(math.log(t2 / r2))
    else:
        swap = t2 > t1
    if swap:
        params["time_constant"], params["time_constant2"] = t2, t1
        if "time_constant2" in interval:
            interval["time_constant"], interval["time_constant2"] = interval["time_constant2"], interval["time_constant"]


def _public_params(params: dict) -> dict:
    """A parametric element with the keys :meth:`PlantModel.element` gives: ``gain``, ``time_constant``,
    ``delay``, and ``lead``, ``time_constant2``, ``integrating`` where set."""
    out = {k: float(params[k]) for k in ("gain", "time_constant", "delay")}
    if params.get("lead", 0.0) != 0:
        out["lead"] = float(params["lead"])
    if params.get("time_constant2", 0.0) != 0:
        out["time_constant2"] = float(params["time_constant2"])
    if params.get("integrating", False):
        out["integrating"] = True
    return out


def _params_of(model: PlantModel, i: int, j: int) -> dict:
    """The parametric element (i, j) of a parametric model, every key given (see :func:`_fitted_params`)."""
    return {"gain": float(model.gain[i, j]), "time_constant": float(model.time_constant[i, j]),
            "delay": float(model.delay[i, j]), "time_constant2": float(model.time_constant2[i, j]),
            "lead": float(model.lead[i, j]), "integrating": bool(model.integrating[i, j])}


def _poles_of(form: _Form, params: dict, ts: float) -> tuple:
    """The poles of a parametric element in a form (its first ``n_lags`` time constants)."""
    taus = (params["time_constant"], params.get("time_constant2", 0.0))
    return tuple(_pole_of(taus[k], ts) for k in range(form.n_lags))


def _input_lag(form: _Form, params: dict, ts: float) -> int:
    """The input lag (samples) of a parametric element fitted in ``form``."""
    nd = int(round(params["delay"] / ts))
    if form.first_order:
        return nd + 1 if params["time_constant"] > 0 else nd
    return nd + form.offset


# ----------------------------------------------------------------------------------------------------
# Step-response elements


def _ramps(model: PlantModel, i: int, j: int) -> bool:
    """Whether step-response element (i, j) keeps a slope beyond its ``N`` samples (integrating)."""
    s = model.step_response[i, j]
    if not model.ramp[i] or s.size < 2:
        return False
    return abs(s[-1] - s[-2]) * s.size > 1e-6 * max(float(np.max(np.abs(s))), 1e-300)


def _step_ladder(model: PlantModel, i: int, j: int) -> tuple:
    """The forms tried for step-response element (i, j)."""
    return _LADDER_STEP_RAMP if _ramps(model, i, j) else _LADDER_STEP


def _unit_steps(form: _Form, poles, lag: int, n: int, ts: float):
    """Unit-step responses ``y(1) .. y(n)`` of ``G_a`` (and ``G_b``) with input lag ``lag``, shape (n, 1 or 2)."""
    num_a, num_b, den = _basis(form, poles, ts)
    u = np.zeros(n + 1)
    u[lag:] = 1.0
    cols = [lfilter(num_a, den, u)[1:]]
    if num_b is not None:
        cols.append(lfilter(num_b, den, u)[1:])
    return np.column_stack(cols)


#: A step-response element's old response is read in the first form of its ladder whose step response lies within
#: this fraction of the coefficients' largest magnitude at every sample (:func:`_step_start_form`).
STEP_READ_TOLERANCE = 0.01
#: A larger form of the ladder reads the old response better only when it at least halves the smaller one's error
#: (:func:`_step_start_form`): coefficients identified with noise that no form of the ladder reads within
#: :data:`STEP_READ_TOLERANCE` are not read in a larger form for its fit to their noise.
STEP_READ_GAIN = 0.5
#: A reading off by at most this fraction of the coefficients' largest magnitude is exact: the solver's own precision
#: (:func:`_step_reference` stops at relative steps of 1e-12), where comparing two readings compares rounding.
STEP_READ_EXACT = 1e-8


def _step_start_form(reading_error, ladder: tuple) -> _Form:
    """The form of ``ladder`` a step-response element's old response is read in, and its fit starts from.

    The first form whose reading error (``reading_error(form)``, the fourth value of :func:`_step_reference`) is
    at most :data:`STEP_READ_TOLERANCE`; while the current form's error exceeds that, the next larger form whose
    error is at most :data:`STEP_READ_GAIN` of it is taken (past a larger form that reads no better: a lag and a
    lead read in two lags no better than in one).  A first-order model element written as step responses starts
    first order, as before; a two-lag element (one whose one-lag reading is off by more than 1 %, as 5.8 s and
    7.9 s read as one lag of 11.3 s and three more samples of dead time) starts with two lags, as its parametric
    form does.  Read in one lag, a pure gain change of such an element was classified ``mixed``: the data fitted
    in one lag moved that reading's dead time by a sample.  The data may still call for a larger form
    (:func:`~mpm_monitor.core.repair.classify._choose_forms`).
    """
    k, error = 0, reading_error(ladder[0])
    while error > STEP_READ_TOLERANCE:
        better = next((m for m in range(k + 1, len(ladder)) if reading_error(ladder[m]) <= STEP_READ_GAIN * error),
                      None)
        if better is None:
            break
        k, error = better, reading_error(ladder[better])
    return ladder[k]


def _step_reference(coefficients, form: _Form, ts: float, lag_shift: int = _LAG_SHIFT) -> tuple:
    """The element of ``form`` whose step response is closest to ``coefficients`` (least squares).

    The old response of a step-response element, in the parametric form its new one is fitted in,
    so that the tests of which parameter changed compare like with like.

    Parameters
    ----------
    coefficients : ndarray, shape (N,)
        ``s_1 .. s_N``.
    form : _Form
    ts : float
    lag_shift : int
        Input lags searched on either side of the one the response's dead time gives.

    Returns
    -------
    params : dict
        The element (see :func:`_fitted_params`).
    lag : int
        Its input lag.
    poles : tuple
    error : float
        The reading's largest difference from ``coefficients``, a fraction of their largest magnitude (0 when
        they are all zero); of an integrating form, of the pulse responses (:func:`_reading_error`).
    """
    s = np.asarray(coefficients, float)
    n = s.size
    dead = dead_time_samples(s)
    first = dead + 1                                            # the first sample that moves
    # Where the response (of an integrating form: its pulse response, which settles where the ramp does not) has
    # covered 63 % of its largest move: the first time constant tried.
    shape = np.diff(s, prepend=0.0) if form.integrating else s
    moved = np.abs(shape - (shape[first - 1] if first > 1 else 0.0))
    reach = np.flatnonzero(moved >= 0.63 * moved.max()) if moved.max() > 0 else np.array([first])
    tau0 = max(float(reach[0] - dead) if reach.size else 1.0, 1.0) * ts
    starts = {1: [(tau0,)], 2: [(0.7 * tau0, 0.3 * tau0), (tau0, tau0)], 0: [()]}[form.n_lags]
    best = None
    scale = solver_scale(s)                 # a power of two: coefficients in small units (solver_scale)
    for lag in range(max(first - lag_shift, 1), first + lag_shift + 1):
        if lag > n:
            break

        def resid(x, lag=lag):
            cols = _unit_steps(form, x, lag, n, ts)
            beta, *_ = np.linalg.lstsq(cols, s, rcond=None)
            r = cols @ beta - s
            return r if scale == 1.0 else r * scale

        for taus in starts:
            x0 = np.array([_pole_of(t, ts) for t in taus])
            if x0.size:
                sol = least_squares_bounded(resid, x0, (_POLE_MIN, _POLE_MAX), xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                            max_nfev=200)
                x, r = sol.x, sol.fun
            else:
                x = x0
                r = resid(x)
            ssr = float(r @ r)
            if best is None or ssr < best[0]:
                best = (ssr, lag, tuple(float(v) for v in x))
    _, lag, poles = best
    # Two lags are symmetric: the solver may end on either order.  The larger first (``time_constant``), as
    # :func:`_match_lags` names them against an element the model lacks.
    poles = tuple(sorted(poles, reverse=True))
    cols = _unit_steps(form, poles, lag, n, ts)
    beta, *_ = np.linalg.lstsq(cols, s, rcond=None)
    gain = float(beta[0])
    lead = float(beta[1] / beta[0]) if form.lead and beta[0] != 0 else 0.0
    return _fitted_params(form, gain, poles, lead, lag, ts), lag, poles, _reading_error(cols @ beta, s, form.integrating)


def _reading_error(fitted: np.ndarray, s: np.ndarray, integrating: bool) -> float:
    """The largest difference of a form's step response ``fitted`` from the coefficients ``s`` (both shape (N,)),
    a fraction of the coefficients' largest magnitude; of an integrating form, of their pulse responses (the
    first differences, which settle: a ramp's own magnitude grows with ``N`` and would hide any shape)."""
    if integrating:
        fitted, s = np.diff(fitted, prepend=0.0), np.diff(s, prepend=0.0)
    top = float(np.max(np.abs(s))) if s.size else 0.0
    return float(np.max(np.abs(fitted - s))) / top if top > 0 else 0.0


def _sampled(params: dict, ts: float):
    """The :class:`~mpm_monitor.core.elements.DiscreteElement` of a parametric element (seconds)."""
    return sample_parametric(params["gain"], params["time_constant"], int(round(params["delay"] / ts)), ts,
                             lead=params.get("lead", 0.0), time_constant2=params.get("time_constant2", 0.0),
                             integrating=bool(params.get("integrating", False)))


def _shifted(s: np.ndarray, shift: int, ramp: bool) -> np.ndarray:
    """``s_1 .. s_N`` delayed by ``shift`` samples (advanced when negative); the end continued as the
    model file continues it (held, or its last slope on a ramp output)."""
    n = s.size
    if shift == 0:
        return s.copy()
    full = np.concatenate([np.zeros(max(shift, 0)), s])
    if shift < 0:
        full = full[-shift:]
    if full.size < n:
        slope = (s[-1] - s[-2]) if ramp and n >= 2 else 0.0
        extra = full[-1] + slope * np.arange(1, n - full.size + 1)
        full = np.concatenate([full, extra])
    return full[:n]


def _step_coefficients(old, ramp: bool, reference: dict, after: dict, changed, ts: float) -> np.ndarray:
    """The new ``s_1 .. s_N`` of a re-estimated step-response element.

    Where only the gain and/or the delay changed, the old response is scaled by the ratio of the
    fitted gains and shifted by the change of delay, so that its shape stays exactly as it was;
    where the shape changed (or the element is new), the sampled step response of the fitted
    parametric element.
    """
    old = np.asarray(old, float)
    n = old.size
    if set(changed) <= {"gain", "delay"} and np.any(old != 0) and reference["gain"] != 0:
        out = old * (after["gain"] / reference["gain"]) if "gain" in changed else old.copy()
        if "delay" in changed:
            out = _shifted(out, int(round((after["delay"] - reference["delay"]) / ts)), ramp)
        return out
    return _sampled(after, ts).step_response(n + 1)[1:]


#: A re-estimated element written into a step-response model that reaches less than this share of its
#: final value within the model's N samples is named (:func:`unsettled_warning`).
SETTLED_SHARE = 0.97


def unsettled_warning(model: PlantModel, i: int, j: int, after: dict, written: np.ndarray) -> Optional[str]:
    """A warning when the fitted element ``after`` does not settle within a step-response model's N samples.

    A step-response model holds each element's last coefficient beyond ``N`` (its last slope on a ramp
    row): a re-estimated element whose shape was fitted (``written``, the coefficients put into the
    model, are its sampled step response) and that is still moving at ``N`` is written with the value
    it reaches there, not its final value (the gain the parametric fit found).  None for a parametric
    model, a ramp row, an element given as a step response, one whose old coefficients were only
    scaled or shifted, or one that reaches :data:`SETTLED_SHARE` of its final value within ``N``.
    """
    if not model.is_step_response or model.ramp[i] or "step_response" in after or after.get("integrating"):
        return None
    gain = float(after.get("gain", 0.0))
    if gain == 0 or not np.isfinite(gain):
        return None
    n, ts = model.step_length, model.sample_time
    element = _sampled(after, ts)
    sampled = element.step_response(n + 1)[1:]
    if not np.array_equal(np.asarray(written, float), sampled):
        return None
    reached = float(sampled[-1]) / gain
    if abs(reached) >= SETTLED_SHARE:
        return None
    long = element.step_response(50 * n + 1)
    inside = np.flatnonzero(np.abs(long / gain - 1.0) > 1.0 - SETTLED_SHARE)
    needed = int(inside[-1]) + 1 if inside.size else n
    needed_text = f"{needed}" if inside.size < 50 * n else f"more than {50 * n}"
    return (f"{model.outputs[i]}: the re-estimated element of {model.columns[j]} (gain {gain:.4g}, its parametric fit "
            f"in the change's evidence) reaches only {100 * reached:.0f}% of its final value within the model's "
            f"{n} samples; a step-response model holds its last coefficient beyond them, so the written "
            f"element's final value is {100 * reached:.0f}% of the fitted gain: a model of {needed_text} samples "
            f"would hold it")


def _element_keys(model: PlantModel, i: int, j: int, after: dict, reference: Optional[dict] = None,
                  changed=()) -> dict:
    """The keyword arguments of :meth:`PlantModel.with_element` that put a fitted element into the model.

    A parametric model takes every parametric key; a step-response model the step response of the
    same length (:func:`_step_coefficients`).  ``after`` may also be an element as
    :meth:`PlantModel.element` gives it (then taken as it is).
    """
    if "step_response" in after:
        return {"step_response": after["step_response"]}
    if model.is_step_response:
        ref = reference if reference is not None else after
        return {"step_response": _step_coefficients(model.step_response[i, j], bool(model.ramp[i]), ref, after,
                                                    changed, model.sample_time)}
    return {"gain": after["gain"], "time_constant": after["time_constant"], "delay": after["delay"],
            "lead": after.get("lead", 0.0), "time_constant2": after.get("time_constant2", 0.0),
            "integrating": bool(after.get("integrating", False))}
