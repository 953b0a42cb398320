"""Plant simulator, internal-model MPC and the batch closed loop (plant.py, mpc.py, closed_loop.py).

Invariants tested:
- with the controller's model equal to the plant, the prediction error ``d = y - yhat`` is exactly
  the injected disturbance plus measurement noise, whatever the controller does (IMC structure,
  paper Fig. 1);
- offset-free tracking of setpoint steps (DMC constant-disturbance model, Maciejowski 2002, 2.3);
- bounds on ``u`` and ``du`` are never violated;
- the QP equals the closed form when no bound is active, and the closed form equals an
  independent least-squares solution of the stated cost (built here by simulating the model).
"""

import dataclasses

import numpy as np
import pytest
from scipy.optimize import lsq_linear
from structure_models import MODELS

from mpm_monitor.core.discretize import simulate, state_space
from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.sim.cases import level_plant, paper_case, shell_plant
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop, seeded_generators
from mpm_monitor.sim.excitation import PrbsGenerator, PrbsOptions
from mpm_monitor.sim.mpc import InternalModelMpc, MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions, PlantSimulator


NOISE_FREE = DisturbanceOptions(0.0, 0.95, 0.0)
SMALL_MPC = dict(prediction_horizon=40, control_horizon=10)  # keeps the bounded runs fast


def _random_plant(seed=5):
    """A random 2x3 strictly proper plant with a static delayed element and a zero element."""
    rng = np.random.default_rng(seed)
    gain = rng.uniform(-3, 3, (2, 3))
    tau = rng.uniform(2, 30, (2, 3))
    delay = rng.integers(0, 6, (2, 3)).astype(float)
    tau[0, 1], delay[0, 1] = 0.0, 2.0   # static element with delay: allowed
    gain[1, 2] = 0.0                    # "no such effect"
    return PlantModel(sample_time=1.0, inputs=("a", "b", "c"), outputs=("p", "q"), gain=gain,
                      time_constant=tau, delay=delay, name="random 2x3")


# --------------------------------------------------------------------------- plant simulator


def _run_plant(model, options, seed, u):
    sim = PlantSimulator(model, options, np.random.default_rng(seed))
    ys = []
    for uk in u:
        ys.append(sim.measure())
        sim.apply(uk)
    return np.array(ys)


def test_plant_simulator_deterministic_for_a_seed():
    plant = shell_plant()
    u = np.random.default_rng(0).standard_normal((200, 3))
    opts = DisturbanceOptions()
    y1 = _run_plant(plant, opts, 42, u)
    y2 = _run_plant(plant, opts, 42, u)
    np.testing.assert_array_equal(y1, y2)  # bit-identical
    y3 = _run_plant(plant, opts, 43, u)
    assert np.max(np.abs(y1 - y3)) > 1e-3  # another seed gives other noise


def test_plant_simulator_noise_free_equals_discrete_model():
    # Noise-free, y(k) is measured before u(k) is applied: y = simulate(model, u) (strictly proper).
    # Reference: discretize.simulate (itself tested against python-control); tolerance 1e-12.
    plant = _random_plant()
    u = np.random.default_rng(1).standard_normal((150, 3))
    y = _run_plant(plant, NOISE_FREE, 0, u)
    np.testing.assert_allclose(y, simulate(plant, u), rtol=0, atol=1e-12)
    assert np.std(y) > 0.1


def test_plant_simulator_noise_statistics():
    # n white with std sigma_n; v = z/(z-p) w: AR(1) with lag-1 autocorrelation p and std
    # sigma_w / sqrt(1 - p^2).  n = 20000 samples: the std estimates are within ~1 % (1 sigma)
    # for n and ~5 % for v; bounds 6 % and 25 % (autocorrelation within 0.02).
    opts = DisturbanceOptions(disturbance_std=0.02, disturbance_pole=0.9, noise_std=0.01)
    plant = _random_plant()
    sim = PlantSimulator(plant, opts, np.random.default_rng(9))
    n = 20000
    v, e = np.zeros((n, 2)), np.zeros((n, 2))
    for k in range(n):
        y = sim.measure()
        v[k], e[k] = sim.last_disturbance, sim.last_noise
        np.testing.assert_allclose(y, v[k] + e[k], atol=1e-15)  # plant at rest: y = v + n
    np.testing.assert_allclose(e.std(axis=0), 0.01, rtol=0.06)
    np.testing.assert_allclose(v.std(axis=0), 0.02 / np.sqrt(1 - 0.81), rtol=0.25)
    rho = [np.corrcoef(v[1:, i], v[:-1, i])[0, 1] for i in range(2)]
    np.testing.assert_allclose(rho, 0.9, atol=0.02)
    assert abs(np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1]) < 0.05


@pytest.mark.parametrize("bad", [dict(disturbance_std=-1.0), dict(noise_std=np.nan),
                                 dict(disturbance_pole=1.0), dict(disturbance_pole=-0.1)])
def test_disturbance_options_refused(bad):
    with pytest.raises(ConfigurationError, match=next(iter(bad))):
        DisturbanceOptions(**bad)


# --------------------------------------------------------------------------- d = v + n


CLOSED_LOOPS = [
    pytest.param("3.1", {}, None, id="case3.1-paper-tuning"),
    pytest.param("3.1", dict(SMALL_MPC, u_min=-0.4, u_max=0.4, du_max=0.1),
                 PrbsOptions(amplitude=0.2), id="case3.1-bounds-dither"),
    pytest.param("random", dict(SMALL_MPC, input_weight=0.0, input_rate_weight=0.01), None,
                 id="random-aggressive"),
    pytest.param("random", dict(SMALL_MPC, u_min=[-0.5, -0.3, -1.0], u_max=[0.2, 0.6, 1.0], du_max=0.05),
                 PrbsOptions(amplitude=0.3, switch_probability=0.2), id="random-bounds-dither"),
]


@pytest.mark.parametrize("which,mpc_kw,dither", CLOSED_LOOPS)
def test_prediction_error_is_disturbance_plus_noise_when_model_equals_plant(which, mpc_kw, dither):
    # IMC identity: with Phat = P, d = y - Phat u = v + n exactly (the loop's inputs, bounds and
    # dither do not matter).  Tolerance 1e-9 absolute, against the injected signals.
    if which == "3.1":
        case = paper_case("3.1")
        plant, model = case.plant, case.model
        mpc = MpcOptions(**{**dict(prediction_horizon=100, control_horizon=30, output_weight=1.0,
                                   input_weight=1.0, input_rate_weight=0.1), **mpc_kw})
        dist = case.disturbance
    else:
        plant = model = _random_plant()
        mpc = MpcOptions(**mpc_kw)
        dist = DisturbanceOptions(0.05, 0.95, 0.02)
    log = run_closed_loop(plant, model, 300, seed=3, mpc=mpc, disturbance=dist,
                          excitation=ExcitationOptions(setpoint=PrbsOptions(amplitude=1.0), dither=dither))
    np.testing.assert_allclose(log.d, log.disturbance + log.noise, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.eps, log.r - log.d, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.y - log.yhat, log.d, rtol=0, atol=1e-12)
    # The identity is not vacuous: the inputs moved, the disturbance is not zero.
    assert np.std(log.u) > 0.05 and np.std(log.d) > 1e-3
    if dither is not None:
        assert set(np.unique(log.dither)) == {-dither.amplitude, dither.amplitude}


def test_prediction_error_differs_from_disturbance_under_mismatch():
    # Counter-check: the same identity fails for the mismatched model of case 3.2 (row y3 is exact).
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 300, seed=3, mpc=MpcOptions(**SMALL_MPC),
                          disturbance=case.disturbance)
    err = np.abs(log.d - log.disturbance - log.noise).max(axis=0)
    assert err[0] > 0.1 and err[1] > 0.05
    assert err[2] < 1e-9


def test_closed_loop_deterministic_for_a_seed():
    case = paper_case("3.2")
    kw = dict(seed=11, mpc=MpcOptions(**SMALL_MPC), disturbance=case.disturbance)
    a = run_closed_loop(case.plant, case.model, 150, **kw)
    b = run_closed_loop(case.plant, case.model, 150, **kw)
    for key in ("r", "u", "y", "yhat", "d", "disturbance", "noise"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    c = run_closed_loop(case.plant, case.model, 150, **{**kw, "seed": 12})
    assert np.max(np.abs(a.y - c.y)) > 1e-3
    np.testing.assert_array_equal(a.t, np.arange(150) * 1.0)


# --------------------------------------------------------------------------- offset-free tracking


@pytest.mark.parametrize("model_case", ["3.1", "3.2"], ids=["model=plant", "model=case3.2-mismatch"])
def test_unconstrained_mpc_tracks_setpoint_steps_without_offset(model_case):
    # input_weight = 0: no penalty on u, so the constant-disturbance (DMC) model gives zero
    # steady-state error, even under the 3.2 mismatch.  Noise-free; two setpoint steps, then an
    # unmeasured output step disturbance, each held 1200 samples (the slowest closed-loop mode of
    # the Shell plant, tau = 60 s, settles below 1e-6 after ~620 samples, the mismatched loop after
    # ~1060).  Tolerance: |y - r| < 1e-6 at the end of each segment.
    case = paper_case(model_case)
    hold = 1200
    r = np.empty((3 * hold, 3))
    r[:hold] = [1.0, -1.0, 0.5]
    r[hold:] = [-0.5, 0.5, 1.0]
    step = np.zeros((3 * hold, 3))
    step[2 * hold:, 1] = 0.3
    log = run_closed_loop(case.plant, case.model, 3 * hold, mpc=MpcOptions(input_weight=0.0),
                          disturbance=NOISE_FREE, setpoints=r, output_disturbance=step)
    err = np.abs(log.y - log.r)
    for end in (hold - 1, 2 * hold - 1, 3 * hold - 1):
        assert err[end].max() < 1e-6, (end, err[end])
    # Not trivially zero: the loop had to move after each step.
    assert err[hold + 5].max() > 0.1 and err[2 * hold + 1].max() > 0.1


def test_input_weight_leaves_offset():
    # Counter-check: penalising u away from 0 (input_weight = 1, the paper's tuning) trades offset
    # for input effort, so the same test must NOT reach 1e-6.
    r = np.tile([1.0, -1.0, 0.5], (1200, 1))
    log = run_closed_loop(shell_plant(), shell_plant(), 1200, mpc=MpcOptions(input_weight=1.0),
                          disturbance=NOISE_FREE, setpoints=r)
    assert np.abs(log.y[-1] - r[-1]).max() > 1e-3


# --------------------------------------------------------------------------- bounds


@pytest.mark.parametrize("bounds", [
    dict(u_min=-0.3, u_max=0.3, du_max=0.05),
    dict(u_min=[-0.2, -0.5, -0.1], u_max=[0.4, 0.1, 0.25]),
    dict(du_max=[0.02, 0.05, 0.03]),
], ids=["u-and-du", "u-asymmetric", "du-only"])
def test_bounds_never_violated_and_active(bounds):
    # Own loop (same objects as run_closed_loop) to also see that the QP was used.
    plant = shell_plant()
    opts = MpcOptions(**SMALL_MPC, **bounds)
    ctrl = InternalModelMpc(plant, opts)
    rngs = seeded_generators(2)
    sim = PlantSimulator(plant, DisturbanceOptions(), rngs["plant"])
    r = PrbsGenerator(3, PrbsOptions(amplitude=1.0, switch_probability=0.1), rngs["setpoint"]).generate(300)
    u = np.zeros((300, 3))
    for k in range(300):
        u[k] = ctrl.step(r[k], sim.measure())
        sim.apply(u[k])
    assert ctrl.qp_solves > 0
    tol = 1e-9
    du = np.diff(np.vstack([np.zeros(3), u]), axis=0)  # u(-1) = u_nom = 0
    lo = np.broadcast_to(np.asarray(bounds.get("u_min", -np.inf), float), (3,))
    hi = np.broadcast_to(np.asarray(bounds.get("u_max", np.inf), float), (3,))
    dmax = np.broadcast_to(np.asarray(bounds.get("du_max", np.inf), float), (3,))
    assert np.all(u >= lo - tol) and np.all(u <= hi + tol)
    assert np.all(np.abs(du) <= dmax + tol)
    # Active: the trajectory touches the bounds (each given bound kind, on some input, many times).
    if "u_max" in bounds:
        touching = (np.abs(u - hi) < 1e-7) | (np.abs(u - lo) < 1e-7)
        assert touching.sum() >= 10
    if "du_max" in bounds:
        assert (np.abs(np.abs(du) - dmax) < 1e-7).sum() >= 10


def test_bounds_hold_with_dither_in_run_closed_loop():
    plant = shell_plant()
    mpc = MpcOptions(**SMALL_MPC, u_min=-0.25, u_max=0.25)
    log = run_closed_loop(plant, plant, 300, seed=4, mpc=mpc,
                          excitation=ExcitationOptions(dither=PrbsOptions(amplitude=0.1)))
    assert log.u.min() >= -0.25 - 1e-9 and log.u.max() <= 0.25 + 1e-9
    assert (np.abs(np.abs(log.u) - 0.25) < 1e-7).sum() >= 10


# --------------------------------------------------------------------------- QP vs closed form


def _cost_as_least_squares(ctrl, eps, x, u_prev, dv=None):
    """Cost J(U) = ||F U - g||^2 over the input path U = (u(k), ..., u(k+Hc-1)) (Hc * nu,), built by
    simulating the controller's model forward (module docstring of mpc.py), independent of its
    matrices; a model with measured disturbances holds ``dv`` (n_disturbances,) over the horizon."""
    ss = state_space(ctrl.model)
    hp, hc = ctrl.options.prediction_horizon, ctrl.options.control_horizon
    nu = ctrl.model.n_inputs
    q, r, s = np.sqrt(ctrl.q), np.sqrt(ctrl.r), np.sqrt(ctrl.s)
    dv = np.zeros(ctrl.model.n_disturbances) if dv is None else np.asarray(dv, float)

    def residual(U):
        U = U.reshape(hc, nu)
        res, xk = [], np.array(x, float)
        for i in range(hp):
            uk = U[min(i, hc - 1)]
            res.append(r * (uk - ctrl.u_nom))
            xk = ss.A @ xk + ss.B @ np.concatenate([uk, dv])
            res.append(q * (eps - ss.C @ xk - ss.D_disturbances @ dv))          # yhat(k+i+1)
        prev = u_prev
        for t in range(hc):
            res.append(s * (U[t] - prev))
            prev = U[t]
        return np.concatenate(res)

    r0 = residual(np.zeros(hc * nu))
    F = np.column_stack([residual(e) - r0 for e in np.eye(hc * nu)])
    return F, -r0


def _moves_to_path(du, u_prev, nu):
    return u_prev + np.cumsum(du.reshape(-1, nu), axis=0)


def _path_to_moves(U, u_prev, nu):
    U = U.reshape(-1, nu)
    return np.diff(np.vstack([u_prev, U]), axis=0).reshape(-1)


def _state_after(plant, n, seed):
    """A non-trivial internal-model state: the model driven by random inputs."""
    ss = state_space(plant)
    x = np.zeros(ss.n_states)
    rng = np.random.default_rng(seed)
    for _ in range(n):
        x = ss.A @ x + ss.B @ (0.1 * rng.standard_normal(plant.n_inputs))
    return x


@pytest.mark.parametrize("hp,hc", [(40, 10), (100, 30)])
def test_closed_form_moves_minimise_the_stated_cost(hp, hc):
    # Reference: numpy lstsq of the cost built by simulation; tolerance 1e-6 on the moves.
    plant = shell_plant()
    ctrl = InternalModelMpc(plant, MpcOptions(prediction_horizon=hp, control_horizon=hc, input_weight=0.5,
                                              input_rate_weight=0.2, input_nominal=[0.1, 0.0, -0.1]))
    x = _state_after(plant, 60, 1)
    eps, u_prev = np.array([0.3, -0.2, 0.1]), np.array([0.05, -0.02, 0.01])
    F, g = _cost_as_least_squares(ctrl, eps, x, u_prev)
    U_ref = np.linalg.lstsq(F, g, rcond=None)[0]
    du = ctrl.unconstrained_moves(eps, x, u_prev)
    np.testing.assert_allclose(du, _path_to_moves(U_ref, u_prev, 3), rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", ["rich", "step", "level"])
def test_closed_form_moves_with_dv_minimise_the_stated_cost_and_the_qp_agrees(name):
    # A model of every structure with a measured disturbance held at dv over the horizon: the moves
    # against the least-squares reference (1e-6), the QP with far bounds against them (1e-5).
    plant = level_plant() if name == "level" else MODELS[name]()
    nu, nd = plant.n_inputs, plant.n_disturbances
    opts = dict(prediction_horizon=30, control_horizon=6, input_weight=0.3, input_rate_weight=0.2)
    ctrl = InternalModelMpc(plant, MpcOptions(**opts))
    ss = state_space(plant)
    rng = np.random.default_rng(2)
    x = np.zeros(ss.n_states)
    for _ in range(40):
        x = ss.A @ x + ss.B @ (0.2 * rng.standard_normal(plant.n_columns))
    eps, u_prev, dv = rng.standard_normal(plant.n_outputs) * 0.3, rng.standard_normal(nu) * 0.1, np.full(nd, 0.7)
    F, g = _cost_as_least_squares(ctrl, eps, x, u_prev, dv)
    U_ref = np.linalg.lstsq(F, g, rcond=None)[0]
    du = ctrl.unconstrained_moves(eps, x, u_prev, dv)
    np.testing.assert_allclose(du, _path_to_moves(U_ref, u_prev, nu), rtol=0, atol=1e-6)
    # the disturbance term is not vacuous
    assert np.abs(du - ctrl.unconstrained_moves(eps, x, u_prev, np.zeros(nd))).max() > 1e-3
    wide = InternalModelMpc(plant, MpcOptions(**opts, u_min=-1e3, u_max=1e3))
    np.testing.assert_allclose(wide.solve_qp(eps, x, u_prev, dv), du, rtol=0, atol=1e-5)
    with pytest.raises(ConfigurationError, match=r"controller model: it has measured disturbances"):
        ctrl.step(np.zeros(plant.n_outputs), np.zeros(plant.n_outputs))


def test_qp_equals_closed_form_when_no_bound_is_active():
    # Bounds far away: the exact active-set solver returns the closed form to rounding.
    plant = shell_plant()
    ctrl = InternalModelMpc(plant, MpcOptions(**SMALL_MPC, u_min=-50.0, u_max=50.0, du_max=20.0))
    rng = np.random.default_rng(8)
    for trial in range(3):
        x = _state_after(plant, 40, trial)
        eps, u_prev = rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3)
        du_cf = ctrl.unconstrained_moves(eps, x, u_prev)
        path = _moves_to_path(du_cf, u_prev, 3)
        assert np.abs(path).max() < 50 and np.abs(du_cf).max() < 20  # really inactive
        np.testing.assert_allclose(ctrl.solve_qp(eps, x, u_prev), du_cf, rtol=0, atol=1e-10)


def test_qp_with_active_input_bounds_equals_bounded_least_squares():
    # u bounds only are box bounds on the path U: reference scipy.optimize.lsq_linear of the same
    # cost (built by simulation); tolerance 1e-8 on the moves, 1e-12 relative on the cost.
    plant = shell_plant()
    lo, hi = np.array([-0.2, -0.3, -0.1]), np.array([0.2, 0.3, 0.1])
    ctrl = InternalModelMpc(plant, MpcOptions(**SMALL_MPC, u_min=lo, u_max=hi))
    x = _state_after(plant, 40, 5)
    eps, u_prev = np.array([1.0, -1.0, 0.5]), np.array([0.1, 0.0, -0.05])
    du_cf = ctrl.unconstrained_moves(eps, x, u_prev)
    path_cf = _moves_to_path(du_cf, u_prev, 3)
    assert np.any(path_cf > hi) or np.any(path_cf < lo)  # the bounds matter here
    du_qp = ctrl.solve_qp(eps, x, u_prev)
    path_qp = _moves_to_path(du_qp, u_prev, 3)
    assert np.all(path_qp >= lo - 1e-7) and np.all(path_qp <= hi + 1e-7)
    F, g = _cost_as_least_squares(ctrl, eps, x, u_prev)
    ref = lsq_linear(F, g, bounds=(np.tile(lo, 10), np.tile(hi, 10)), tol=1e-14, lsmr_tol="auto",
                     max_iter=5000, method="bvls")
    np.testing.assert_allclose(du_qp, _path_to_moves(ref.x, u_prev, 3), rtol=0, atol=1e-8)
    cost = lambda U: np.sum((F @ U - g) ** 2)  # noqa: E731
    np.testing.assert_allclose(cost(path_qp.reshape(-1)), cost(ref.x), rtol=1e-12)


@pytest.mark.parametrize("u_prev", [[0.1, 0.0, -0.05], [0.5, -0.45, 0.0], [2.0, 0.0, 0.0]],
                         ids=["inside", "outside-reachable", "outside-unreachable"])
def test_qp_with_input_and_move_bounds_equals_osqp(u_prev):
    # u and du bounds together (not a box on either): reference OSQP at tolerance 1e-12, polished.
    # An input outside its bounds is brought in within du_max when it can be; when it cannot, there
    # is no feasible move path and the unconstrained moves are returned (step() clips them).
    plant = shell_plant()
    ctrl = InternalModelMpc(plant, MpcOptions(**SMALL_MPC, u_min=-0.3, u_max=0.3, du_max=0.2,
                                              qp_tolerance=1e-12))
    x = _state_after(plant, 40, 6)
    eps, u_prev = np.array([1.0, -1.0, 0.5]), np.array(u_prev)
    du = ctrl.solve_qp(eps, x, u_prev)
    du_unc = ctrl.unconstrained_moves(eps, x, u_prev)
    if u_prev[0] > 0.3 + 0.2:
        np.testing.assert_array_equal(du, du_unc)
        assert ctrl.qp_fallbacks == 1
        return
    assert ctrl.qp_fallbacks == 0
    path = _moves_to_path(du, u_prev, 3)
    assert np.all(np.abs(path) <= 0.3 + 1e-12) and np.all(np.abs(du) <= 0.2 + 1e-12)
    assert np.sum(np.isclose(np.abs(path), 0.3)) + np.sum(np.isclose(np.abs(du), 0.2)) >= 3
    ref = _osqp_moves(ctrl, *ctrl.qp_problem(eps, x, u_prev)[:3])
    np.testing.assert_allclose(du, ref, rtol=0, atol=1e-7)


def _osqp_moves(ctrl, q, lo, hi):
    """The bounded QP of ``ctrl`` solved by OSQP (an independent solver, tests only) at 1e-12, polished."""
    import osqp
    import scipy.sparse as sp

    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.triu(ctrl._H)), q, sp.csc_matrix(ctrl.qp_rows), lo, hi, verbose=False,
                 eps_abs=1e-12, eps_rel=1e-12, polishing=True, max_iter=200000)
    res = solver.solve(raise_error=True)
    assert res.info.status == "solved"
    return res.x


def test_a_guessed_start_that_reaches_the_iteration_limit_starts_again_from_the_free_minimum(monkeypatch):
    # The warm start's guess changes the work, not the answer: a guessed solve made to fail at its
    # iteration limit is solved again without the guess, to the same moves, and is not a fallback.
    from mpm_monitor.sim.qp import ActiveSetQp

    plant = shell_plant()
    opts = MpcOptions(**SMALL_MPC, u_min=-0.3, u_max=0.3, du_max=0.05)
    r = PrbsGenerator(3, PrbsOptions(amplitude=1.0, switch_probability=0.1),
                      np.random.default_rng(4)).generate(120)
    y = np.zeros(3)

    def moves(ctrl):
        return np.array([ctrl.step(r[k], y) for k in range(120)])

    reference = InternalModelMpc(plant, opts)
    u_ref = moves(reference)
    assert reference.qp_solves > 20 and reference.qp_fallbacks == 0
    solve = ActiveSetQp.solve
    guessed = []

    def failing_guess(self, q, lo, hi, guess=None, guess_upper=None, max_iter=None, tolerance=1e-9):
        if guess is not None:
            guessed.append(True)
            return solve(self, q, lo, hi, guess, guess_upper, max_iter=0, tolerance=tolerance)
        return solve(self, q, lo, hi, max_iter=max_iter, tolerance=tolerance)

    monkeypatch.setattr(ActiveSetQp, "solve", failing_guess)
    ctrl = InternalModelMpc(plant, opts)
    np.testing.assert_allclose(moves(ctrl), u_ref, rtol=0, atol=1e-12)
    assert len(guessed) > 10 and ctrl.qp_fallbacks == 0


# --------------------------------------------------------------------------- refusals


def _feedthrough_plant():
    return shell_plant().with_element(2, 2, time_constant=0.0, delay=0.0)


def test_direct_feedthrough_refused():
    ft = _feedthrough_plant()
    with pytest.raises(ConfigurationError, match=r"plant: element \(y3, u3\) has time_constant 0 and delay 0"):
        PlantSimulator(ft, DisturbanceOptions(), np.random.default_rng(0))
    with pytest.raises(ConfigurationError, match=r"controller model: element \(y3, u3\) .*feed-through"):
        InternalModelMpc(ft, MpcOptions(**SMALL_MPC))
    with pytest.raises(ConfigurationError, match=r"feed-through"):
        run_closed_loop(ft, shell_plant(), 10, mpc=MpcOptions(**SMALL_MPC))
    # A static element with one sample of delay is fine; so is a zero-gain static element.
    InternalModelMpc(shell_plant().with_element(2, 2, time_constant=0.0, delay=1.0), MpcOptions(**SMALL_MPC))
    InternalModelMpc(shell_plant().with_element(2, 2, gain=0.0, time_constant=0.0, delay=0.0),
                     MpcOptions(**SMALL_MPC))


@pytest.mark.parametrize("kw,pattern", [
    (dict(prediction_horizon=0), "prediction_horizon"),
    (dict(prediction_horizon=10, control_horizon=11), "control_horizon"),
    (dict(control_horizon=2.5), "control_horizon"),
    (dict(qp_tolerance=0.0), "qp_tolerance"),
])
def test_mpc_options_refused(kw, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        MpcOptions(**kw)


@pytest.mark.parametrize("kw,pattern", [
    (dict(u_min=1.0, u_max=0.0), "u_min <= u_max"),
    (dict(du_max=0.0), "du_max"),
    (dict(input_weight=-1.0), "input_weight"),
    (dict(output_weight=[1.0, 1.0]), r"output_weight: expected a number or a list of 3 numbers"),
    (dict(input_weight=0.0, input_rate_weight=0.0, output_weight=0.0), "singular"),
])
def test_mpc_configuration_refused(kw, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        InternalModelMpc(shell_plant(), MpcOptions(**SMALL_MPC, **kw))


def test_bounds_need_no_qp_package(monkeypatch):
    """The bounded MPC solves its QP with numpy and scipy alone: with osqp impossible to import it is
    built, meets its bounds and moves exactly as it does otherwise."""
    import sys

    plant = shell_plant()
    opts = MpcOptions(**SMALL_MPC, u_min=-0.3, u_max=0.3, du_max=0.05)
    r = PrbsGenerator(3, PrbsOptions(amplitude=1.0, switch_probability=0.1),
                      np.random.default_rng(2)).generate(100)
    reference = InternalModelMpc(plant, opts)
    u_ref = np.array([reference.step(r[k], np.zeros(3)) for k in range(100)])
    monkeypatch.setitem(sys.modules, "osqp", None)  # import osqp fails
    ctrl = InternalModelMpc(plant, opts)
    u = np.array([ctrl.step(r[k], np.zeros(3)) for k in range(100)])
    assert ctrl.qp_solves > 10 and ctrl.qp_fallbacks == 0
    np.testing.assert_array_equal(u, u_ref)
    assert np.all(np.abs(u) <= 0.3) and np.all(np.abs(np.diff(u, axis=0)) <= 0.05 + 1e-12)


# --------------------------------------------------------------------------- large models


def _wide_plant(ny=6, nu=4, seed=3):
    rng = np.random.default_rng(seed)
    return PlantModel(sample_time=1.0, inputs=[f"u{j}" for j in range(nu)], outputs=[f"y{i}" for i in range(ny)],
                      gain=rng.uniform(-3, 3, (ny, nu)), time_constant=rng.uniform(2, 40, (ny, nu)),
                      delay=rng.integers(0, 8, (ny, nu)).astype(float))


@pytest.mark.parametrize("kw", [{}, dict(prediction_horizon=40, control_horizon=5, input_weight=[0.5, 1, 2, 1],
                                         output_weight=[1, 2, 1, 3, 1, 1], input_rate_weight=0.3)])
def test_structured_set_up_gives_the_dense_control_law(kw):
    # The set-up for large models (sparse state space, H from the step-response blocks, the free
    # response run forward) computes the same gains and moves as the dense one, to rounding.
    model = _wide_plant()
    dense = InternalModelMpc(model, MpcOptions(**kw))
    structured = InternalModelMpc(model, MpcOptions(**kw), structured=True)
    assert not dense.structured and structured.structured
    np.testing.assert_allclose(structured._H, dense._H, rtol=1e-12, atol=1e-12 * np.abs(dense._H).max())
    nu = model.n_inputs
    for key in ("_K_eps", "_K_u", "_K_nom"):
        ref = getattr(dense, key)
        np.testing.assert_allclose(getattr(structured, key), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    np.testing.assert_allclose(structured._K_x1, dense._K_x[:nu], rtol=0, atol=1e-10 * np.abs(dense._K_x).max())
    rng = np.random.default_rng(0)
    x = rng.normal(size=dense._ss.n_states)
    ref = dense._K_x @ x
    np.testing.assert_allclose(structured._free_moves(x), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    u_dense, u_structured = [], []
    for _ in range(150):
        r, y = np.sign(rng.normal(size=6)), 0.1 * rng.normal(size=6)
        u_dense.append(dense.step(r, y))
        u_structured.append(structured.step(r, y))
    np.testing.assert_allclose(u_structured, u_dense, rtol=0, atol=1e-9 * np.abs(u_dense).max())


def test_structured_set_up_keeps_the_bounds():
    model = _wide_plant()
    opts = MpcOptions(prediction_horizon=40, control_horizon=10, u_min=-0.3, u_max=0.3, du_max=0.05)
    ctrl = InternalModelMpc(model, opts, structured=True)
    rng = np.random.default_rng(1)
    prev = np.zeros(model.n_inputs)
    for _ in range(120):
        u = ctrl.step(2.0 * np.sign(rng.normal(size=6)), 0.1 * rng.normal(size=6))
        assert np.all(u <= 0.3 + 1e-9) and np.all(u >= -0.3 - 1e-9)
        assert np.all(np.abs(u - prev) <= 0.05 + 1e-9)
        prev = u
    assert ctrl.qp_solves > 0


def test_large_models_take_the_structured_set_up_and_the_sparse_plant():
    # 30 x 36 first-order elements and their delay lines: more states than DENSE_STATE_LIMIT.
    from mpm_monitor.sim.plant import DENSE_STATE_LIMIT

    model = _wide_plant(30, 36, seed=4)
    ss = state_space(model)
    assert ss.n_states > DENSE_STATE_LIMIT
    ctrl = InternalModelMpc(model, MpcOptions(prediction_horizon=30, control_horizon=5))
    assert ctrl.structured and ctrl._K_x is None
    plant = PlantSimulator(model, NOISE_FREE, np.random.default_rng(0))
    u = np.random.default_rng(2).normal(size=(50, 36))
    y = []
    for k in range(50):
        y.append(plant.measure())
        plant.apply(u[k])
    np.testing.assert_allclose(y, simulate(model, u), rtol=0, atol=1e-12 * np.abs(y).max())


@pytest.mark.parametrize("structured", [False, True])
@pytest.mark.parametrize("weights, said", [
    ({"input_weight": 1e308}, "give a control problem that cannot be solved"),
    ({"output_weight": 1e308}, "overflow floating point"),
])
def test_weights_too_far_apart_in_scale_are_refused_naming_them(weights, said, structured):
    """``input_weight`` 1e308 made the gains' solve fail ('Singular matrix', a LinAlgError), ``output_weight`` 1e308
    gave gains that are not finite (the first input NaN): both refused at set-up, every weight named; a moderate
    scale (1e6 against 1) is kept."""
    model = paper_case("3.2").model
    if structured:      # the structured set-up's solve does not fail on the first: its gains overflow
        said = "(give a control problem that cannot be solved|overflow floating point)"
    with pytest.raises(ConfigurationError, match=rf"^MPC weights output_weight \[[^]]*\], input_weight \[[^]]*\], "
                                                 rf"input_rate_weight \[[^]]*\] {said}") as refused:
        InternalModelMpc(model, MpcOptions(**weights), structured=structured)
    assert "1e+308" in str(refused.value)
    ctrl = InternalModelMpc(model, MpcOptions(output_weight=1e6), structured=structured)
    assert np.all(np.isfinite(ctrl.unconstrained_moves(np.ones(3), np.ones(ctrl._ss.n_states), np.ones(3))))


@pytest.mark.parametrize("bad, said", [
    (dict(u_min=1e308), "u_min: 1e+308 for input 'u1' (expected a bound, or -inf for none, within 1e+40"),
    (dict(u_min=[-np.inf, 1e41, 0.0]), "u_min: 1e+41 for input 'u2'"),
    (dict(u_min=np.inf), "u_min: inf for input 'u1'"),
    (dict(u_max=-np.inf), "u_max: -inf for input 'u1' (expected a bound, or inf for none"),
    (dict(u_max=-1e308), "u_max: -1e+308 for input 'u1'"),
    (dict(input_nominal=[0.0, 0.0, 1e300]), "input_nominal: 1e+300 for input 'u3' (expected a nominal, within 1e+40"),
    (dict(input_nominal=[0.0, np.inf, 0.0]), "input_nominal: inf for input 'u2'"),
])
def test_an_input_bound_or_nominal_beyond_what_the_loop_can_run_is_refused_naming_it(bad, said):
    # u_min: [1e308] was taken: the controller held every input at 1e308 and the loop ran to "diverged".
    case = paper_case("3.1")
    with pytest.raises(ConfigurationError) as refused:
        InternalModelMpc(case.model, dataclasses.replace(case.mpc, **bad))
    assert str(refused.value).startswith(said) and "\n" not in str(refused.value), str(refused.value)


def test_bounds_at_the_scale_limit_and_infinite_bounds_for_none_are_taken():
    case = paper_case("3.1")
    for bounds in (dict(u_min=-1e40, u_max=1e40), dict(u_min=-np.inf, u_max=np.inf), dict(u_min=[-np.inf, -1.0, -2.0])):
        ctrl = InternalModelMpc(case.model, dataclasses.replace(case.mpc, **bounds))
        assert np.all(np.isfinite(ctrl.step(np.ones(3), np.zeros(3))))
