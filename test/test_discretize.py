"""Exact ZOH discretization (discretize.py) against independent references.

References:
- the analytic continuous step response ``K (1 - exp(-(t - theta)/tau))`` for ``t >= theta``;
- python-control: ``control.step_response`` of ``tf([K], [tau, 1])`` (shifted by the delay ourselves,
  python-control has no delays), ``control.sample_system(..., 'zoh')``, and the MIMO
  ``control.ss(A, B, C, D, Ts)`` evaluated with ``evalfr`` / ``frequency_response``;
- ``scipy.signal.freqz`` and ``scipy.signal.lfilter`` of ``b z^-(m+1) / (1 - a z^-1)`` with
  ``a``, ``b``, ``m`` computed here from the element parameters (Franklin, Powell & Workman,
  *Digital Control of Dynamic Systems*, 3rd ed., section 4.3).
"""

import control
import numpy as np
import pytest
from scipy import signal

from mpm_monitor.core.discretize import (
    ModelPredictor,
    discretize,
    element_response,
    frequency_response,
    settling_samples,
    simulate,
    simulate_elements,
    simulate_state_space,
    state_space,
)
from mpm_monitor.core.model import PlantModel
from mpm_monitor.sim.cases import shell_plant

N_STEP = 400  # samples of every step response (8 time constants of the slowest Shell element)


def _siso(gain, tau, delay, ts=1.0):
    return PlantModel(sample_time=ts, inputs=("u",), outputs=("y",), gain=[[gain]], time_constant=[[tau]],
                      delay=[[delay]])


def _shell_elements():
    plant = shell_plant()
    return [pytest.param(float(plant.gain[i, j]), float(plant.time_constant[i, j]), float(plant.delay[i, j]), 1.0,
                         id=f"shell-y{i + 1}-u{j + 1}")
            for i in range(3) for j in range(3)]


EXTRA_ELEMENTS = [
    pytest.param(2.5, 0.0, 3.0, 1.0, id="tau0-delay3"),
    pytest.param(-1.5, 0.0, 0.0, 1.0, id="tau0-nodelay"),
    pytest.param(0.0, 20.0, 4.0, 1.0, id="gain0"),
    pytest.param(0.0, 0.0, 0.0, 1.0, id="gain0-static"),
    pytest.param(-3.0, 7.0, 0.0, 1.0, id="negative-gain-nodelay"),
    pytest.param(1.2, 0.35, 0.0, 1.0, id="tau-below-sample"),
    pytest.param(0.8, 4.0, 1.5, 0.5, id="ts0.5-delay3"),
    pytest.param(2.0, 0.0, 0.6, 0.2, id="ts0.2-tau0-delay3"),
]
ELEMENTS = _shell_elements() + EXTRA_ELEMENTS


def _analytic_step(gain, tau, delay, t):
    """Continuous unit-step response of K e^{-theta s} / (tau s + 1) at times t (seconds)."""
    after = t >= delay - 1e-12
    if tau == 0:
        return np.where(after, gain, 0.0)
    return np.where(after, gain * (1.0 - np.exp(-np.clip(t - delay, 0.0, None) / tau)), 0.0)


def _control_step(gain, tau, delay, ts, n):
    """python-control step response of K / (tau s + 1), shifted by the delay (an integer of samples)."""
    nd = int(round(delay / ts))
    t = np.arange(n) * ts
    sys = control.tf([gain], [tau, 1.0]) if tau > 0 else control.tf([gain], [1.0])
    y = np.asarray(control.step_response(sys, T=t).outputs).reshape(-1)
    return np.concatenate([np.zeros(nd), y[:n - nd]])


@pytest.mark.parametrize("gain,tau,delay,ts", ELEMENTS)
def test_element_step_equals_continuous_step_at_sample_instants(gain, tau, delay, ts):
    # ZOH is step invariant: the discrete step response equals the continuous one at t = k T.
    # Tolerance 1e-9 absolute (gains are O(10); exact arithmetic up to rounding).
    model = _siso(gain, tau, delay, ts)
    t = np.arange(N_STEP) * ts
    y = simulate(model, np.ones((N_STEP, 1)))[:, 0]
    np.testing.assert_allclose(y, _analytic_step(gain, tau, delay, t), rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, _control_step(gain, tau, delay, ts, N_STEP), rtol=0, atol=1e-9)


@pytest.mark.parametrize("gain,tau,delay,ts", [p for p in ELEMENTS if p.values[0] != 0])
def test_delay_exact_to_the_sample(gain, tau, delay, ts):
    # A lag element's step first moves one sample after the dead time (y(t) = 0 at t = theta);
    # a static element moves at the dead time itself.
    nd = int(round(delay / ts))
    y = simulate(_siso(gain, tau, delay, ts), np.ones((N_STEP, 1)))[:, 0]
    first = int(np.flatnonzero(y != 0)[0])
    assert np.all(y[:first] == 0.0)  # exactly zero before, not merely small
    assert first == (nd + 1 if tau > 0 else nd)


@pytest.mark.parametrize("gain,tau,delay,ts", [p for p in ELEMENTS if p.values[1] > 0 and p.values[0] != 0])
def test_discrete_coefficients_equal_python_control_zoh(gain, tau, delay, ts):
    # python-control's ZOH of K / (tau s + 1) is K (1 - a) / (z - a), a = exp(-T / tau); rel. tol 1e-12.
    disc = discretize(_siso(gain, tau, delay, ts))
    dsys = control.sample_system(control.tf([gain], [tau, 1.0]), ts, method="zoh")
    num = np.trim_zeros(np.asarray(dsys.num[0][0], dtype=float), "f")
    den = np.asarray(dsys.den[0][0], dtype=float)
    num, den = num / den[0], den / den[0]
    np.testing.assert_allclose(disc.pole[0, 0], -den[1], rtol=1e-12)
    np.testing.assert_allclose(disc.numerator[0, 0], num[-1], rtol=1e-12)
    assert disc.input_lag[0, 0] == int(round(delay / ts))


# --------------------------------------------------------------------------- frequency response

OMEGA = np.linspace(1e-3, np.pi, 97)  # rad/sample, up to Nyquist


def _reference_tf(gain, tau, delay, ts):
    """Numerator and denominator (in z^-1) of the ZOH equivalent, from the formula of FPW 4.3."""
    nd = int(round(delay / ts))
    if gain == 0:
        return np.array([0.0]), np.array([1.0])
    if tau == 0:
        return np.r_[np.zeros(nd), gain], np.array([1.0])
    a = np.exp(-ts / tau)
    return np.r_[np.zeros(nd + 1), gain * (1.0 - a)], np.array([1.0, -a])


@pytest.mark.parametrize("gain,tau,delay,ts", ELEMENTS)
def test_element_frequency_response_equals_freqz(gain, tau, delay, ts):
    # Reference: scipy.signal.freqz of b z^-(m+1) / (1 - a z^-1); tolerance 1e-9 absolute.
    b, a = _reference_tf(gain, tau, delay, ts)
    _, h_ref = signal.freqz(b, a, worN=OMEGA)
    h = frequency_response(_siso(gain, tau, delay, ts), OMEGA)
    assert h.shape == (OMEGA.size, 1, 1)
    np.testing.assert_allclose(h[:, 0, 0], h_ref, rtol=0, atol=1e-9)


def test_frequency_response_dc_gain_and_continuous_form():
    plant = shell_plant()
    # At omega -> 0 the discrete response is the steady-state gain (tolerance 1e-9).
    h0 = frequency_response(plant, np.array([0.0]))[0]
    np.testing.assert_allclose(h0, plant.gain, rtol=0, atol=1e-9)
    # Continuous form against python-control's tf evaluated at j omega times e^{-j omega theta}.
    w = np.array([1e-3, 0.02, 0.3, 1.0])  # rad/s
    hc = frequency_response(plant, w, discrete=False)
    for i in range(3):
        for j in range(3):
            sys = control.tf([plant.gain[i, j]], [plant.time_constant[i, j], 1.0])
            ref = np.array([control.evalfr(sys, 1j * wk) for wk in w]) * np.exp(-1j * w * plant.delay[i, j])
            np.testing.assert_allclose(hc[:, i, j], ref, rtol=1e-12, atol=1e-12)


def _mixed_model():
    """2x3 model with every kind of element: lag with/without delay, static with delay, feed-through, zero."""
    return PlantModel(sample_time=0.5, inputs=("a", "b", "c"), outputs=("p", "q"),
                      gain=[[1.5, 0.0, -2.0], [0.7, 3.0, 1.1]],
                      time_constant=[[4.0, 9.0, 0.0], [0.0, 2.5, 0.0]],
                      delay=[[1.0, 0.5, 2.0], [0.0, 0.0, 1.5]])


@pytest.mark.parametrize("model_fn", [shell_plant, _mixed_model], ids=["shell", "mixed"])
def test_mimo_state_space_frequency_response_equals_python_control(model_fn):
    # Reference: python-control ss(A, B, C, D, Ts) evaluated at z = e^{j omega} with evalfr and
    # frequency_response (omega in rad/s = rad/sample / Ts); tolerance 1e-9 absolute.  This ties the
    # dense state_space() realization to the element-wise frequency_response().
    model = model_fn()
    ss = state_space(model)
    ts = model.sample_time
    sys = control.ss(ss.A, ss.B, ss.C, ss.D, ts)
    h = frequency_response(model, OMEGA)
    fr = sys.frequency_response(OMEGA / ts)
    h_ctrl = np.asarray(fr.magnitude) * np.exp(1j * np.asarray(fr.phase))  # (ny, nu, n_freq)
    np.testing.assert_allclose(np.moveaxis(h_ctrl, -1, 0), h, rtol=0, atol=1e-9)
    for k in (0, 30, 96):
        np.testing.assert_allclose(control.evalfr(sys, np.exp(1j * OMEGA[k])), h[k], rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- MIMO structure


@pytest.mark.parametrize("model_fn", [shell_plant, _mixed_model], ids=["shell", "mixed"])
def test_state_space_response_is_sum_of_element_responses(model_fn):
    # Superposition: y_i = sum_j G_ij u_j for random inputs.  References: (1) simulate() of each
    # element as a 1x1 model; (2) scipy.signal.lfilter of the FPW 4.3 formula.  Tolerance 1e-9.
    model = model_fn()
    rng = np.random.default_rng(3)
    n = 300
    u = rng.standard_normal((n, model.n_inputs))
    y = simulate(model, u)
    assert y.shape == (n, model.n_outputs)
    y_sum = np.zeros_like(y)
    y_lfilter = np.zeros_like(y)
    for i in range(model.n_outputs):
        for j in range(model.n_inputs):
            g, tau, dly = model.gain[i, j], model.time_constant[i, j], model.delay[i, j]
            y_sum[:, i] += simulate(_siso(g, tau, dly, model.sample_time), u[:, [j]])[:, 0]
            b, a = _reference_tf(g, tau, dly, model.sample_time)
            y_lfilter[:, i] += signal.lfilter(b, a, u[:, j])
    np.testing.assert_allclose(y, y_sum, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, y_lfilter, rtol=0, atol=1e-9)
    # Non-trivial: every output moved.
    assert np.all(np.std(y, axis=0) > 0.1)


@pytest.mark.parametrize("model_fn", [shell_plant, _mixed_model], ids=["shell", "mixed"])
def test_element_response_continues_from_its_state_and_past_inputs(model_fn):
    # Invariants of the one element-wise simulation: (1) from rest it is the dense simulate() to
    # 1e-9; (2) selected rows are those columns exactly; (3) a run split in two blocks, the second
    # started from the first's element states and inputs, is the whole run to rounding (bit for bit
    # where the BLAS does not fuse multiply-adds: where it does, as OpenBLAS on AVX-512, the state's
    # carry-over rounds apart from the recursion's, about 1 ulp); (4) the model
    # run sample by sample (ModelPredictor.step) and in blocks (run) agrees with it to 1e-12.
    model = model_fn()
    disc = discretize(model)
    u = np.random.default_rng(5).standard_normal((200, model.n_inputs))
    whole = simulate_elements(model, u)
    np.testing.assert_allclose(whole, simulate(model, u), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(simulate_elements(model, u, rows=[1]), whole[:, [1]])
    state = np.zeros((model.n_outputs, model.n_inputs))
    h = int(disc.input_lag.max())
    first = element_response(disc, u[:70], state=state)
    second = element_response(disc, u[70:], state=state, past=u[70 - h:70])
    np.testing.assert_allclose(np.vstack([first, second]), whole, rtol=0, atol=1e-13)
    pred = ModelPredictor(model)
    stepped = [pred.step(u[k]) for k in range(3)]
    blocks = np.vstack([np.array(stepped), pred.run(u[3:4]), pred.run(u[4:4]), pred.run(u[4:])])
    np.testing.assert_allclose(blocks, whole, rtol=0, atol=1e-12)
    assert np.max(np.abs(whole)) > 0.1


def test_state_space_dimensions_share_shift_registers():
    # Shell: 9 lag states + per-input registers of the longest column lag: 6, 7, 6 -> 9 + 19 = 28.
    ss = state_space(shell_plant())
    assert ss.A.shape == (28, 28) and ss.B.shape == (28, 3) and ss.C.shape == (3, 28)
    np.testing.assert_array_equal(ss.D, np.zeros((3, 3)))
    # Stable: all poles inside the unit circle (lags exp(-1/tau), shift registers at 0).
    assert np.max(np.abs(np.linalg.eigvals(ss.A))) < 1.0
    assert discretize(shell_plant()).strictly_proper
    assert not discretize(_mixed_model()).strictly_proper


def test_simulate_from_initial_state_is_free_plus_forced_response():
    # Linearity in (x0, u): response(x0, u) = response(x0, 0) + response(0, u); tolerance 1e-9.
    model = _mixed_model()
    ss = state_space(model)
    rng = np.random.default_rng(11)
    x0 = rng.standard_normal(ss.n_states)
    u = rng.standard_normal((50, model.n_inputs))
    both = simulate(model, u, x0)
    free = simulate(model, np.zeros_like(u), x0)
    forced = simulate(model, u)
    np.testing.assert_allclose(both, free + forced, rtol=0, atol=1e-9)
    assert np.max(np.abs(free)) > 0.1
    # Short inputs are handled (n = 0 and n = 1).
    assert simulate(model, np.zeros((0, 3))).shape == (0, 2)
    np.testing.assert_allclose(simulate(model, u[:1], x0)[0], ss.C @ x0 + ss.D @ u[0], atol=1e-12)


def test_static_model_without_states():
    # Every element a feed-through: no states, y = D u exactly.
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y",), gain=[[2.0, -1.0]],
                       time_constant=[[0.0, 0.0]], delay=[[0.0, 0.0]])
    ss = state_space(model)
    assert ss.n_states == 0
    u = np.random.default_rng(0).standard_normal((20, 2))
    np.testing.assert_allclose(simulate_state_space(ss, u)[:, 0], 2.0 * u[:, 0] - u[:, 1], atol=1e-12)


def test_settling_samples_bounds_the_step_response():
    # After settling_samples(fraction) the step response is within fraction * |K| of K (analytic).
    model = shell_plant()
    n = settling_samples(model, 1e-3)
    # max over elements of delay + ceil(tau ln 1000), + 1: element (y1, u2) gives 7 + 415 + 1 = 423.
    assert n == 7 + int(np.ceil(60 * np.log(1000))) + 1
    y = simulate(model, np.ones((n + 1, 3)))
    np.testing.assert_array_less(np.abs(y[n] - model.gain.sum(axis=1)), 1e-3 * np.abs(model.gain).sum(axis=1))
