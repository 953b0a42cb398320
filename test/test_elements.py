"""Every element structure's sampled form against an independent reference.

Reference: python-control 0.10 (``control.c2d(..., 'zoh')``, which samples through scipy's
``cont2discrete``, and ``control.step_response``), with the dead time appended as ``z^-n_d``.
Tolerance 1e-9 relative (the largest difference seen is about 2e-11, near the integrator's pole).
"""

import control
import numpy as np
import pytest

from mpm_monitor.core.elements import (
    DiscreteElement,
    continuous_frequency_response,
    dead_time_samples,
    from_step_response,
    sample_parametric,
)

STRUCTURES = [
    pytest.param(dict(gain=2.0, time_constant=10.0), id="first-order"),
    pytest.param(dict(gain=-1.3, time_constant=0.0), id="static"),
    pytest.param(dict(gain=2.0, time_constant=10.0, time_constant2=4.0), id="second-order"),
    pytest.param(dict(gain=3.0, time_constant=7.0, time_constant2=7.0), id="repeated-lag"),
    pytest.param(dict(gain=1.5, time_constant=8.0, lead=3.0), id="lead-lag"),
    pytest.param(dict(gain=1.0, time_constant=10.0, time_constant2=5.0, lead=-3.0), id="inverse-response"),
    pytest.param(dict(gain=0.1, integrating=True), id="integrator"),
    pytest.param(dict(gain=0.1, time_constant=6.0, integrating=True), id="integrator-lag"),
    pytest.param(dict(gain=0.1, time_constant=6.0, integrating=True, lead=2.0), id="integrator-lead-lag"),
    pytest.param(dict(gain=0.3, integrating=True, lead=4.0), id="integrator-lead"),
    pytest.param(dict(gain=0.2, time_constant=5.0, time_constant2=3.0, integrating=True, lead=-1.0),
                 id="integrator-two-lags-inverse"),
]


def reference(params: dict, delay: int, ts: float):
    """The element as a discrete python-control transfer function, dead time included."""
    k = params["gain"]
    lead = params.get("lead", 0.0)
    num = [k * lead, k] if lead else [k]
    den = np.array([1.0])
    for tau in (params.get("time_constant", 0.0), params.get("time_constant2", 0.0)):
        if tau > 0:
            den = np.convolve(den, [tau, 1.0])
    if params.get("integrating"):
        den = np.convolve(den, [1.0, 0.0])
    if den.size == 1:
        sysd = control.tf(num, [1.0], ts)
    else:
        sysd = control.c2d(control.tf(num, den), ts, "zoh")
    return sysd * control.tf([1.0], [1.0] + [0.0] * delay, ts)


@pytest.mark.parametrize("params", STRUCTURES)
@pytest.mark.parametrize("ts, delay", [(1.0, 0), (1.0, 3), (0.3, 5)])
def test_step_and_frequency_response_match_python_control(params, ts, delay):
    el = sample_parametric(delay_samples=delay, sample_time=ts, time_constant=params.get("time_constant", 0.0),
                           **{k: v for k, v in params.items() if k != "time_constant"})
    ref = reference(params, delay, ts)
    n = 300
    _, y_ref = control.step_response(ref, T=np.arange(n) * ts)
    y = el.step_response(n)
    assert np.max(np.abs(y - y_ref)) <= 1e-9 * max(1.0, np.max(np.abs(y_ref)))
    omega = np.linspace(0.005, np.pi, 64)
    f_ref = np.array([complex(np.squeeze(ref(np.exp(1j * w)))) for w in omega])
    f = el.frequency_response(omega)
    assert np.max(np.abs(f - f_ref) / np.abs(f_ref)) <= 1e-9


@pytest.mark.parametrize("params", STRUCTURES)
def test_zero_order_hold_is_step_invariant(params):
    """Invariant: the sampled step response equals the continuous one at the sampling instants."""
    ts, delay = 0.5, 2
    el = sample_parametric(delay_samples=delay, sample_time=ts, time_constant=params.get("time_constant", 0.0),
                           **{k: v for k, v in params.items() if k != "time_constant"})
    ref = control.tf(*_continuous(params))
    t = np.arange(200) * ts
    _, yc = control.step_response(ref, T=t)
    shifted = np.concatenate([np.zeros(delay), yc[:t.size - delay]])
    if params.get("time_constant", 0.0) == 0 and not params.get("integrating"):
        shifted = np.concatenate([np.zeros(delay), np.full(t.size - delay, params["gain"])])
    assert np.allclose(el.step_response(t.size), shifted, rtol=1e-8, atol=1e-10 * max(1.0, np.abs(yc).max()))


def _continuous(params):
    k, lead = params["gain"], params.get("lead", 0.0)
    num = [k * lead, k] if lead else [k]
    den = np.array([1.0])
    for tau in (params.get("time_constant", 0.0), params.get("time_constant2", 0.0)):
        if tau > 0:
            den = np.convolve(den, [tau, 1.0])
    if params.get("integrating"):
        den = np.convolve(den, [1.0, 0.0])
    return num, den


def test_continuous_frequency_response_matches_python_control():
    omega = np.logspace(-3, 0, 40)
    for p in STRUCTURES:
        params = p.values[0]
        ref = control.tf(*_continuous(params))
        f = continuous_frequency_response(omega, params["gain"], params.get("time_constant", 0.0), 4.0,
                                          lead=params.get("lead", 0.0),
                                          time_constant2=params.get("time_constant2", 0.0),
                                          integrating=params.get("integrating", False))
        f_ref = np.array([complex(np.squeeze(ref(1j * w))) for w in omega]) * np.exp(-4.0j * omega)
        assert np.allclose(f, f_ref, rtol=1e-12)


def test_first_order_closed_form():
    el = sample_parametric(2.0, 10.0, 4, 1.0)
    a = np.exp(-0.1)
    assert np.array_equal(el.num, [0.0, 2.0 * (1 - a)]) and np.array_equal(el.den, [1.0, -a]) and el.delay == 4
    assert el.input_lag == 5 and el.strictly_proper and not el.integrating


def test_step_response_element_reproduces_its_coefficients():
    s = np.array([0.0, 0.0, 0.4, 1.1, 1.6, 1.9, 2.0])
    el = from_step_response(s)
    y = el.step_response(20)
    assert np.allclose(y[1:8], s, atol=1e-15) and np.allclose(y[8:], 2.0, atol=1e-15) and y[0] == 0.0
    assert dead_time_samples(s) == 2 and el.input_lag == 3


def test_ramp_step_response_keeps_its_last_slope():
    s = np.array([0.0, 0.1, 0.3, 0.6, 1.0, 1.5])
    el = from_step_response(s, ramp=True)
    y = el.step_response(30)
    assert np.allclose(y[1:7], s, atol=1e-14)
    assert np.allclose(np.diff(y[6:]), 0.5, atol=1e-12)
    assert el.integrating


def test_step_response_of_a_sampled_element_round_trips():
    """A parametric element written as N step-response coefficients gives the same response over N samples."""
    el = sample_parametric(1.2, 9.0, 3, 1.0, lead=-2.0, time_constant2=4.0)
    s = el.step_response(121)[1:]
    fir = from_step_response(s)
    assert np.allclose(fir.step_response(121), el.step_response(121), atol=1e-14)


def test_a_lead_without_a_lag_is_refused():
    with pytest.raises(ValueError, match="lead needs a lag"):
        sample_parametric(1.0, 0.0, 0, 1.0, lead=2.0)


def test_discrete_element_checks_its_denominator():
    with pytest.raises(ValueError, match="den"):
        DiscreteElement(num=[1.0], den=[2.0, 1.0], delay=0)


@pytest.mark.parametrize("params", [
    pytest.param(dict(gain=2.0, time_constant=10.0, time_constant2=1e-40), id="second-lag"),
    pytest.param(dict(gain=0.1, time_constant=1e-40, integrating=True), id="integrator-lag"),
    pytest.param(dict(gain=1.5, time_constant=8.0, time_constant2=1e-40, lead=3.0), id="lead-two-lags"),
])
def test_a_lag_far_below_the_sample_time_is_left_out(params):
    """A lag of 1e-40 s sampled every second (whose continuous coefficients gave NaN) changes the response by
    about 1e-40: it is left out, and the step response is python-control's of the element without it."""
    el = sample_parametric(delay_samples=2, sample_time=1.0, time_constant=params["time_constant"],
                           **{k: v for k, v in params.items() if k != "time_constant"})
    without = {k: (0.0 if v == 1e-40 else v) for k, v in params.items()}
    _, ref = control.step_response(reference(without, 2, 1.0), T=np.arange(200.0))
    np.testing.assert_allclose(el.step_response(200), np.ravel(ref), rtol=1e-9, atol=1e-12)
    assert np.all(np.isfinite(el.num)) and np.all(np.isfinite(el.den))
