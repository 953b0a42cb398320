"""Every element structure and the measured-disturbance columns through core/discretize.py.

References (test/structure_models.py): python-control 0.10 -- ``control.c2d(..., 'zoh')`` of the
continuous element built from its parameters, times ``z^-n_d``, and ``forced_response`` /
``frequency_response`` of those transfer functions; for a step-response element its definition in
the model file (the coefficients, held, or continued with the last slope for a ramp output).
Tolerances: 1e-9 absolute on responses of order 1 (the largest difference seen is about 3e-11, in
the frequency response near an integrator's pole); the element-wise simulation and the dense state
space agree to 1e-12 (rounding).
"""

import control
import numpy as np
import pytest
from structure_models import (
    MODELS,
    element_reference,
    first_order_model,
    frequency_reference,
    reference_response,
    rich_model,
    step_model,
    step_reference,
)

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
from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.sim.plant import require_strictly_proper

MODEL_IDS = sorted(MODELS)
OMEGA = np.linspace(1e-3, np.pi, 97)     # rad/sample


def _columns(model, n, seed=0):
    return np.random.default_rng(seed).standard_normal((n, model.n_columns))


@pytest.mark.parametrize("name", MODEL_IDS)
def test_element_simulation_and_state_space_equal_python_control(name):
    # Random inputs and disturbances: the element-wise simulation and the dense state space are the
    # python-control response of the element references, summed (1e-9), and each other (1e-12).
    model = MODELS[name]()
    u = _columns(model, 300)
    ref = reference_response(model, u)
    el = simulate_elements(model, u)
    dense = simulate(model, u)
    np.testing.assert_allclose(el, ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dense, ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(el, dense, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.all(np.std(ref, axis=0) > 0.05)       # every output moves: the comparison can fail


@pytest.mark.parametrize("name", MODEL_IDS)
def test_unit_steps_of_every_column_equal_the_references(name):
    # The whole model's step response, column by column: state space and element-wise simulation
    # against python-control's step response of each element (parametric) or the coefficients as
    # defined (step response, with the ramp continued beyond N); 1e-9.
    model = MODELS[name]()
    n = 120
    t = np.arange(n) * model.sample_time
    for j in range(model.n_columns):
        u = np.zeros((n, model.n_columns))
        u[:, j] = 1.0
        for y in (simulate(model, u), simulate_elements(model, u)):
            for i in range(model.n_outputs):
                if model.is_step_response:
                    ref = step_reference(model, i, j, n)
                else:
                    ref = np.asarray(control.step_response(element_reference(model, i, j), T=t).outputs).reshape(n)
                np.testing.assert_allclose(y[:, i], ref, rtol=0, atol=1e-9, err_msg=f"column {j}, row {i}")


@pytest.mark.parametrize("name", MODEL_IDS)
def test_frequency_response_of_the_model_and_its_state_space_equal_python_control(name):
    model = MODELS[name]()
    ref = frequency_reference(model, OMEGA)
    np.testing.assert_allclose(frequency_response(model, OMEGA), ref, rtol=0, atol=1e-9)
    ss = state_space(model)
    fr = control.ss(ss.A, ss.B, ss.C, ss.D, model.sample_time).frequency_response(OMEGA / model.sample_time)
    h_ss = np.moveaxis(np.asarray(fr.magnitude) * np.exp(1j * np.asarray(fr.phase)), -1, 0)
    np.testing.assert_allclose(h_ss, ref, rtol=0, atol=1e-9)


def test_continuous_frequency_response_and_integrators_at_zero():
    model = rich_model()
    w = np.array([0.0, 1e-3, 0.05, 0.7])           # rad/s
    h = frequency_response(model, w, discrete=False)
    for i in range(2):
        for j in range(3):
            k, lead = model.gain[i, j], model.lead[i, j]
            den = np.convolve([model.time_constant[i, j], 1.0], [model.time_constant2[i, j], 1.0])
            if model.integrating[i, j]:
                den = np.convolve(den, [1.0, 0.0])
            sys = control.tf([k * lead, k], den)
            ref = np.array([control.evalfr(sys, 1j * wk) for wk in w[1:]]) * np.exp(-1j * w[1:] * model.delay[i, j])
            np.testing.assert_allclose(h[1:, i, j], ref, rtol=1e-12, atol=1e-12)
            if model.integrating[i, j]:
                assert np.isinf(h[0, i, j]) and np.isinf(frequency_response(model, [0.0])[0, i, j])
            else:
                np.testing.assert_allclose(h[0, i, j], k, rtol=1e-12)
                np.testing.assert_allclose(frequency_response(model, [0.0])[0, i, j], k, rtol=1e-9)
    with pytest.raises(ValueError, match="step-response model has only a discrete form"):
        frequency_response(step_model(), w, discrete=False)


@pytest.mark.parametrize("name", MODEL_IDS)
def test_predictor_by_samples_and_blocks_and_split_runs_equal_the_simulation(name):
    # The element states carry a run across blocks exactly, with inputs and disturbances (1e-12).
    model = MODELS[name]()
    nu = model.n_inputs
    x = _columns(model, 260, seed=4)
    whole = simulate_elements(model, x)
    pred = ModelPredictor(model)
    stepped = np.array([pred.step(x[k, :nu], x[k, nu:]) for k in range(5)])
    blocks = [stepped, pred.run(x[5:6, :nu], x[5:6, nu:]), pred.run(x[6:6, :nu], x[6:6, nu:])]
    blocks.append(np.array([pred.step(x[k, :nu], x[k, nu:]) for k in range(6, 90)]))
    blocks.append(pred.run(x[90:, :nu], x[90:, nu:]))
    np.testing.assert_allclose(np.vstack(blocks), whole, rtol=0, atol=1e-12 * np.abs(whole).max())
    disc = discretize(model)
    state = np.zeros((model.n_outputs, model.n_columns, max(int(disc.state_order.max()), 1)))
    h = int(disc.input_lag.max())
    first = element_response(disc, x[:100], state=state)
    second = element_response(disc, x[100:], state=state, past=x[100 - h:100])
    np.testing.assert_allclose(np.vstack([first, second]), whole, rtol=0, atol=1e-12 * np.abs(whole).max())
    with pytest.raises(ValueError, match="measured disturbances: give dv"):
        ModelPredictor(model).step(x[0, :nu])


def test_state_space_shares_one_register_per_column_and_splits_its_columns():
    # Rich model: element states max(n, 1) each: second lag 2, lead-lag 1, first order 1 | integrator
    # with a lag 2, integrator with a lead 1, second lag with a lead 2 = 9, then one register per column.
    model = rich_model()
    ss = state_space(model)
    disc = discretize(model)
    n_el = sum(max(disc.denominators[i][j].size - 1, 1) for i in range(2) for j in range(3) if disc.active[i, j])
    assert n_el == 9
    assert ss.n_states == n_el + int(disc.register_length.sum())
    assert disc.register_length is disc.register_length and not disc.register_length.flags.writeable
    assert ss.B.shape == (ss.n_states, 3) and ss.B_inputs.shape == (ss.n_states, 2)
    assert ss.B_disturbances.shape == (ss.n_states, 1) and ss.D_disturbances.shape == (2, 1)
    np.testing.assert_array_equal(np.hstack([ss.B_inputs, ss.B_disturbances]), ss.B)
    # Superposition over the split: inputs through B_inputs, disturbances through B_disturbances.
    x = _columns(model, 200, seed=2)
    from mpm_monitor.core.discretize import StateSpace
    only_u = StateSpace(ss.A, ss.B_inputs, ss.C, ss.D_inputs, ss.sample_time)
    only_dv = StateSpace(ss.A, ss.B_disturbances, ss.C, ss.D_disturbances, ss.sample_time)
    np.testing.assert_allclose(simulate_state_space(only_u, x[:, :2]) + simulate_state_space(only_dv, x[:, 2:]),
                               simulate(model, x), rtol=0, atol=1e-12)
    # A step-response model: one state per element, the taps read from the register (N + dead time).
    sm = step_model(40)
    ss = state_space(sm)
    assert ss.n_states == int(sm.present.sum()) + int(discretize(sm).register_length.sum())
    assert discretize(sm).register_length.max() <= 40 + 5


def test_first_order_models_keep_their_realisation():
    # A model of first-order elements: one lag state per element (A = a, B = K (1 - a)) and
    # registers as long as the column's largest delay -- the realisation of earlier versions.
    model = first_order_model()
    ss = state_space(model)
    assert ss.n_states == 6 + (2 + 3 + 2)
    disc = discretize(model)
    assert np.all(disc.first_order == disc.active)
    a = np.exp(-1.0 / model.time_constant)
    np.testing.assert_allclose(np.diag(ss.A)[:6], a.ravel(), rtol=1e-15)
    np.testing.assert_allclose(disc.pole, a, rtol=1e-15)
    np.testing.assert_allclose(disc.numerator, model.gain * (1 - a), rtol=1e-15)
    np.testing.assert_array_equal(disc.input_lag, model.delay_samples)
    assert np.all(np.isnan(discretize(rich_model()).pole[[0, 1], [0, 2]]))     # second lags: no single pole


def test_settling_samples_of_every_structure():
    # Parametric: delay + (tau + tau2) ln(1/f) / T, lags only (integrators never settle); the
    # self-regulating step responses are within f of their final value by then.
    model = rich_model()
    n = settling_samples(model, 1e-3)
    assert n == 4 + int(np.ceil(15.0 * np.log(1000))) + 1          # (y2, dv1): delay 4, tau 12 + tau2 3
    steps = simulate_elements(model, np.ones((n + 1, 3)) * np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(steps[n, 0], model.gain[0, 0], rtol=1e-3)
    # The integrating element's lag part has settled: its slope is K T (1e-3 relative).
    u1 = np.zeros((n + 2, 3))
    u1[:, 0] = 1.0
    y = simulate_elements(model, u1)[:, 1]
    np.testing.assert_allclose(y[-1] - y[-2], model.gain[1, 0] * model.sample_time, rtol=1e-3)
    # A step-response model: no free response beyond its N coefficients and dead time.
    sm = step_model(40)
    assert 40 < settling_samples(sm) <= 40 + 3         # the ramp's FIR part ends at N + 1


def test_strictly_proper_uses_the_sampled_elements():
    lead_no_delay = PlantModel(1.0, ("u",), ("y",), gain=[[1.0]], time_constant=[[5.0]], delay=[[0.0]], lead=[[2.0]])
    assert not discretize(lead_no_delay).strictly_proper
    with pytest.raises(ConfigurationError, match=r"plant: element \(y, u\) has a lead and delay 0, a direct feed-through"):
        require_strictly_proper(lead_no_delay)
    require_strictly_proper(rich_model())          # every element of the rich model is strictly proper
    require_strictly_proper(step_model())
    # A measured-disturbance column is checked too.
    static_dv = first_order_model().with_element(1, 2, time_constant=0.0, delay=0.0)
    with pytest.raises(ConfigurationError, match=r"element \(y2, dv1\) has time_constant 0 and delay 0"):
        require_strictly_proper(static_dv)
