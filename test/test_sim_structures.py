"""The simulation with every element structure and with measured disturbances (sim/plant, mpc, excitation, closed_loop).

References, independent of the code under test:
- the plant's response to ``u`` and ``dv``: the element-wise simulation of the core
  (:func:`mpm_monitor.core.discretize.simulate_elements`) and python-control's ``forced_response``
  of every element built from its parameters (test/structure_models.py), 1e-9;
- the MPC's moves with a measured disturbance: in test_plant_mpc.py, against a least-squares
  solution of the stated cost built by simulating the model forward with ``dv(k)`` held;
- the IMC identity ``d = v + n`` when the controller's model equals the plant, for every structure
  with measured disturbances, 1e-9 (the internal model is driven by ``u`` and ``dv`` exactly as the
  plant);
- the measured-disturbance generator against the statistics it is defined by.
"""

import numpy as np
import pytest
from structure_models import MODELS, reference_response, step_model

from mpm_monitor.core.discretize import simulate_elements
from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.sim.cases import DEMO_CASES, level_case, level_plant, simulation_case
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop, seeded_generators
from mpm_monitor.sim.excitation import MeasuredDisturbanceGenerator, MeasuredDisturbanceOptions, PrbsOptions
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions, PlantSimulator


NOISE_FREE = DisturbanceOptions(0.0, 0.95, 0.0)
SMALL_MPC = dict(prediction_horizon=40, control_horizon=10)
MODEL_IDS = sorted(MODELS)


def without_disturbances(model: PlantModel) -> PlantModel:
    """The model of the inputs only: the controller's model of a loop without feedforward."""
    nu = model.n_inputs
    if model.is_step_response:
        return PlantModel.from_step_response(model.sample_time, model.inputs, model.outputs,
                                             model.step_response[:, :nu], ramp=model.ramp)
    return PlantModel(sample_time=model.sample_time, inputs=model.inputs, outputs=model.outputs,
                      gain=model.gain[:, :nu], time_constant=model.time_constant[:, :nu], delay=model.delay[:, :nu],
                      lead=model.lead[:, :nu], time_constant2=model.time_constant2[:, :nu],
                      integrating=model.integrating[:, :nu], name=model.name + " (no feedforward)")


# ------------------------------------------------------------------------------- plant


@pytest.mark.parametrize("name", MODEL_IDS + ["level"])
def test_plant_response_to_u_and_dv_equals_the_elementwise_simulation_and_python_control(name):
    # Noise-free, y(k) is measured before u(k) is applied and with dv(k): y is the model's response
    # to the columns [u | dv] from rest.  1e-9 against both references.
    model = level_plant() if name == "level" else MODELS[name]()
    n = 250
    cols = np.random.default_rng(7).standard_normal((n, model.n_columns))
    nu = model.n_inputs
    sim = PlantSimulator(model, NOISE_FREE, np.random.default_rng(0))
    y = np.zeros((n, model.n_outputs))
    for k in range(n):
        y[k] = sim.measure(dv=cols[k, nu:])
        np.testing.assert_array_equal(sim.last_dv, cols[k, nu:])
        sim.apply(cols[k, :nu])
    np.testing.assert_allclose(y, simulate_elements(model, cols), rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, reference_response(model, cols), rtol=0, atol=1e-9)
    # the disturbance columns matter: the response without them differs
    no_dv = cols.copy()
    no_dv[:, nu:] = 0.0
    assert np.abs(y - simulate_elements(model, no_dv)).max() > 0.1


def test_plant_with_disturbances_wants_dv():
    sim = PlantSimulator(level_plant(), NOISE_FREE, np.random.default_rng(0))
    with pytest.raises(ConfigurationError, match=r"plant: the plant has measured disturbances \(inflow\): give dv"):
        sim.measure()
    with pytest.raises(ConfigurationError, match=r"plant: dv: expected 1 finite value\(s\) \(inflow\)"):
        sim.measure(dv=[np.nan])
    with pytest.raises(ConfigurationError, match=r"expected 1 finite value"):
        sim.measure(dv=[1.0, 2.0])


# --------------------------------------------------------------------------- closed loop, IMC identity


@pytest.mark.parametrize("name", MODEL_IDS + ["level"])
@pytest.mark.parametrize("bounded", [False, True], ids=["closed-form", "bounded"])
def test_prediction_error_is_disturbance_plus_noise_for_every_structure_with_dv(name, bounded):
    # Phat = P with measured disturbances: the internal model, driven by u and dv, follows the plant
    # exactly, so d = y - yhat = v + n (1e-9) whatever the loop does; bounds hold.
    plant = level_plant() if name == "level" else MODELS[name]()
    mpc = MpcOptions(**SMALL_MPC, input_weight=0.1, **(dict(u_min=-0.8, u_max=0.8, du_max=0.2) if bounded else {}))
    log = run_closed_loop(plant, plant, 400, seed=5, mpc=mpc, disturbance=DisturbanceOptions(0.02, 0.9, 0.01),
                          excitation=ExcitationOptions(setpoint=PrbsOptions(amplitude=0.5, switch_probability=0.1)),
                          measured_disturbance=MeasuredDisturbanceOptions(step_amplitude=1.0, switch_probability=0.05,
                                                                          min_hold=10, noise_std=0.1))
    np.testing.assert_allclose(log.d, log.disturbance + log.noise, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.y - log.yhat, log.d, rtol=0, atol=1e-12)
    assert log.dv.shape == (400, plant.n_disturbances) and np.std(log.dv) > 0.2
    assert np.std(log.u) > 0.05
    if bounded:
        du = np.diff(np.vstack([np.zeros(plant.n_inputs), log.u]), axis=0)
        assert log.u.min() >= -0.8 - 1e-9 and log.u.max() <= 0.8 + 1e-9
        assert np.abs(du).max() <= 0.2 + 1e-9
        assert (np.abs(np.abs(log.u) - 0.8) < 1e-7).sum() + (np.abs(np.abs(du) - 0.2) < 1e-7).sum() >= 5
    data = log.as_logged_data("test")
    assert data.disturbances == plant.disturbances
    np.testing.assert_array_equal(data.dv, log.dv)


def test_controller_model_without_the_plant_disturbances_runs_and_one_with_others_is_refused():
    plant = level_plant()
    log = run_closed_loop(plant, without_disturbances(plant), 50, seed=1, mpc=MpcOptions(**SMALL_MPC))
    assert log.disturbances == ("inflow",) and log.dv.shape == (50, 1)
    other = PlantModel(sample_time=1.0, inputs=plant.inputs, outputs=plant.outputs, disturbances=("feed",),
                       gain=plant.gain, time_constant=plant.time_constant, delay=plant.delay,
                       integrating=plant.integrating)
    with pytest.raises(ConfigurationError, match=r"measured disturbance\(s\) feed not among the plant's \(inflow\)"):
        run_closed_loop(plant, other, 10)


def test_runs_without_disturbances_keep_their_random_streams():
    # The fourth generator (measured disturbances) leaves the three of the runs before it unchanged.
    old = np.random.SeedSequence(3).spawn(3)
    new = seeded_generators(3)
    for key, ss in zip(("plant", "setpoint", "dither"), old):
        np.testing.assert_array_equal(new[key].random(5), np.random.default_rng(ss).random(5))
    log = run_closed_loop(simulation_case("3.2").plant, simulation_case("3.2").model, 20, seed=3)
    assert log.dv.shape == (20, 0) and log.disturbances == ()
    assert log.as_logged_data().dv.shape == (20, 0)


# --------------------------------------------------------------------------- MPC with feedforward


def _step_disturbance_run(controller_model, n=600, bounds=None):
    plant = level_plant()
    dv = np.zeros((n, 1))
    dv[100:] = 1.0                     # the inflow steps up
    mpc = MpcOptions(prediction_horizon=100, control_horizon=30, input_weight=0.0, input_rate_weight=0.1,
                     **(bounds or {}))
    r = np.zeros((n, 2))
    return run_closed_loop(plant, controller_model, n, mpc=mpc, disturbance=NOISE_FREE, setpoints=r, dv=dv)


@pytest.mark.parametrize("bounds", [None, dict(u_min=-3.0, u_max=3.0, du_max=0.5)], ids=["closed-form", "bounded"])
def test_feedforward_rejects_a_measured_step_better_than_feedback_alone(bounds):
    # The inflow steps by 1 at sample 100.  With its column in the controller's model (feedforward)
    # the outflow and the steam move as soon as the step is measured; without it (the same model
    # without the disturbance column) only once the outputs have moved.  The level integrates the
    # inflow: without feedforward the constant-d controller leaves it off the setpoint.
    ff = _step_disturbance_run(level_plant(), bounds=bounds)
    fb = _step_disturbance_run(without_disturbances(level_plant()), bounds=bounds)
    err_ff = np.sum((ff.y - ff.r) ** 2, axis=0)
    err_fb = np.sum((fb.y - fb.r) ** 2, axis=0)
    assert np.all(err_ff < 0.05 * err_fb), (err_ff, err_fb)
    peak_ff, peak_fb = np.abs(ff.y).max(axis=0), np.abs(fb.y).max(axis=0)
    assert np.all(peak_ff < 0.5 * peak_fb), (peak_ff, peak_fb)
    # feedforward with the exact model: back on the setpoints (1e-6), and the outflow moved at once
    assert np.abs(ff.y[-1] - ff.r[-1]).max() < 1e-6
    assert abs(ff.u[100, 1]) > 0.05 and np.all(ff.u[:100] == 0.0)
    assert np.abs(fb.u[100]).max() < 1e-12
    if bounds is not None:
        for log in (ff, fb):
            assert log.u.min() >= -3.0 - 1e-9 and log.u.max() <= 3.0 + 1e-9
            assert np.abs(np.diff(log.u, axis=0)).max() <= 0.5 + 1e-9


def test_integrating_output_tracks_setpoint_steps_without_offset():
    # The level integrates the outflow; input_weight 0: offset-free tracking of setpoint steps on
    # both outputs (within 1e-6 at the end of each 500-sample hold) with the exact model under a
    # constant measured inflow, and with the level case's wrong integrator and inflow gains without
    # a load (dv = 0).
    case = level_case()
    hold = 500
    r = np.empty((3 * hold, 2))
    r[:hold] = [1.0, -1.0]
    r[hold:2 * hold] = [-0.5, 2.0]
    r[2 * hold:] = [0.3, 0.5]
    for model, load in ((case.plant, 0.4), (case.model, 0.0)):
        log = run_closed_loop(case.plant, model, 3 * hold, mpc=MpcOptions(input_weight=0.0), disturbance=NOISE_FREE,
                              setpoints=r, dv=np.full((3 * hold, 1), load))
        err = np.abs(log.y - log.r)
        for end in (hold - 1, 2 * hold - 1, 3 * hold - 1):
            assert err[end].max() < 1e-6, (model.name, end, err[end])
        assert err[hold + 5].max() > 0.1
        # the level needs the outflow that balances the inflow: -0.05 u2 + 0.05 * load = 0
        np.testing.assert_allclose(log.u[-1, 1], load, atol=1e-6)


def test_mismatched_integrator_under_a_load_leaves_an_offset():
    # Counter-check (mpc.py docstring): with the wrong outflow integrator gain the model does not
    # balance the inflow at the plant's outflow, d ramps, and the constant-d controller settles off
    # the level setpoint.
    case = level_case()
    r = np.tile([0.0, 1.0], (1500, 1))
    log = run_closed_loop(case.plant, case.model, 1500, mpc=MpcOptions(input_weight=0.0), disturbance=NOISE_FREE,
                          setpoints=r, dv=np.full((1500, 1), 0.4))
    assert abs(log.y[-1, 1] - 1.0) > 1e-2
    assert abs(log.y[-1, 1] - log.y[-2, 1]) < 1e-9         # settled, off the setpoint


def test_step_response_plant_with_a_ramp_output_is_controlled_without_offset():
    plant = step_model()
    r = np.tile([0.5, -0.5], (600, 1))
    log = run_closed_loop(plant, plant, 600, mpc=MpcOptions(input_weight=0.0), disturbance=NOISE_FREE,
                          setpoints=r, dv=np.zeros((600, 1)))
    assert np.abs(log.y[-1] - r[-1]).max() < 1e-6


# --------------------------------------------------------------------------- generator


def test_measured_disturbance_generator_is_seeded_and_next_equals_generate():
    opts = MeasuredDisturbanceOptions(step_amplitude=2.0, switch_probability=0.05, min_hold=5, noise_std=0.3)
    a = MeasuredDisturbanceGenerator(2, opts, np.random.default_rng(4)).generate(500)
    gen = MeasuredDisturbanceGenerator(2, opts, np.random.default_rng(4))
    b = np.array([gen.next() for _ in range(500)])
    np.testing.assert_array_equal(a, b)
    c = MeasuredDisturbanceGenerator(2, opts, np.random.default_rng(5)).generate(500)
    assert np.abs(a - c).max() > 0.1
    assert a.shape == (500, 2)


def test_measured_disturbance_steps_hold_and_stay_within_the_amplitude():
    opts = MeasuredDisturbanceOptions(step_amplitude=1.5, switch_probability=0.1, min_hold=20, noise_std=0.0,
                                      offset=3.0)
    x = MeasuredDisturbanceGenerator(3, opts, np.random.default_rng(1)).generate(20000)
    assert np.all(np.abs(x - 3.0) <= 1.5)
    for j in range(3):
        steps = np.flatnonzero(np.diff(x[:, j]) != 0) + 1
        holds = np.diff(np.concatenate([[0], steps]))
        assert holds.min() >= 20
        # mean hold min_hold - 1 + 1/p = 29 samples; 20000 samples give ~690 holds: 3 % (> 5 sigma)
        assert abs(holds.mean() - 29.0) < 0.03 * 29.0
        # levels uniform in [-1.5, 1.5]: std 1.5 / sqrt(3)
        levels = x[np.concatenate([[0], steps]), j] - 3.0
        assert abs(levels.std() - 1.5 / np.sqrt(3)) < 0.1


def test_measured_disturbance_noise_has_its_std_and_pole():
    # steps off: e(k) = p e(k-1) + sqrt(1 - p^2) sigma w(k), stationary from the start.
    opts = MeasuredDisturbanceOptions(step_amplitude=0.0, noise_std=0.4, noise_pole=0.8)
    x = MeasuredDisturbanceGenerator(1, opts, np.random.default_rng(2)).generate(100000)[:, 0]
    # 100000 samples of an AR(1) with p = 0.8: std within 2 %, lag-1 correlation within 0.01 (> 4 sigma)
    assert abs(x.std() - 0.4) < 0.02 * 0.4
    assert abs(np.corrcoef(x[1:], x[:-1])[0, 1] - 0.8) < 0.01
    assert abs(x[:5000].std() - 0.4) < 0.05 * 0.4 * 4        # stationary from the first samples


@pytest.mark.parametrize("kw,pattern", [
    (dict(step_amplitude=-1.0), "step_amplitude: expected a finite number >= 0"),
    (dict(noise_std=np.inf), "noise_std: expected a finite number >= 0"),
    (dict(switch_probability=0.0), r"switch_probability: expected a number in \(0, 1\]"),
    (dict(min_hold=0), "min_hold: expected an integer >= 1"),
    (dict(noise_pole=1.0), r"noise_pole: expected a number in \[0, 1\)"),
    (dict(offset=np.nan), "offset: expected a finite number"),
])
def test_measured_disturbance_options_refused(kw, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        MeasuredDisturbanceOptions(**kw)


# --------------------------------------------------------------------------- cases


def test_cases_and_the_level_case():
    assert DEMO_CASES == ("3.1", "3.2", "3.3", "level")
    case = simulation_case("level")
    assert case.plant.disturbances == ("inflow",) and case.plant.integrating_outputs == (False, True)
    assert set(case.mismatched_elements) == {("temperature", "inflow"), ("level", "outflow")}
    differ = np.argwhere(case.plant.gain != case.model.gain)
    assert sorted(map(tuple, differ)) == [(0, 2), (1, 1)]
    assert case.measured_disturbance is not None
    assert simulation_case("3.2").measured_disturbance is None
    with pytest.raises(ValueError, match="unknown case 'x': expected one of 3.1, 3.2, 3.3, level"):
        simulation_case("x")
