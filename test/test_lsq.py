"""core.repair.lsq.least_squares_bounded against scipy.optimize.least_squares (the solver it replaces).

The reference is ``scipy.optimize.least_squares(method="trf")`` with the same bounds and tolerances
(here the tight ones of the step-response form fit, 1e-12, so that both runs stop at the minimum and
not at their different stopping rules).  Problems: exponential fits by variable projection (one and two
poles, noisy and exact, as the repair's pole fits), Rosenbrock, a bound active at the solution, a start
on a bound, per-variable and one-sided bounds.

Tolerances.  At a minimum ``x*`` of a smooth problem the two solutions differ by what stops each
solver short of ``x*`` and by the error of its forward-difference Jacobian: a relative step ``h`` of
``sqrt(eps) = 1.5e-8`` makes ``J`` wrong by about ``h``, and so the gradient ``J'f``; for a zero
residual that moves nothing, for a noisy one it moves the stationary point by about ``h`` times the
ratio of the residual to the curvature, about ``1e-7`` relative on these well-conditioned problems.
``x`` is required to agree to ``2e-6`` relative (absolute on a zero solution): an order of magnitude
of margin, and far below any difference of minimum (the minima of these problems are apart by
``1e-2`` or more).  The costs, to ``1e-10`` relative (``1e-22`` absolute for the exact fits whose
minimum is zero): the cost is flat at the minimum, so a ``2e-6`` error in ``x`` changes it by about
``4e-12`` relative.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from scipy import optimize

from mpm_monitor.core.repair.lsq import _box_lstsq, least_squares_bounded, symmetric_pinv

TIGHT = dict(xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
# The settings of the repair's row fit (fit.py): looser tolerances, relative step 1e-6.
ROW_FIT = dict(xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=60, diff_step=1e-6)
POLE_BOUNDS = (1e-4, 0.9995)


def _exponentials(poles, noise, seed, n=300):
    """Residual of a variable-projection fit of ``sum_i c_i a_i^k`` (the amplitudes eliminated) to data."""
    rng = np.random.default_rng(seed)
    k = np.arange(n, dtype=float)
    y = sum((i + 1.0) * a ** k for i, a in enumerate(poles)) + noise * rng.standard_normal(n)

    def fun(x):
        cols = np.column_stack([a ** k for a in x])
        beta = np.linalg.lstsq(cols, y, rcond=None)[0]
        return cols @ beta - y
    return fun


def _rosenbrock(x):
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def _box3d(x):
    """Box's three-dimensional function (Moré, Garbow and Hillstrom 1981, problem 12), zero at (1, 10, 1)."""
    t = 0.1 * np.arange(1, 11)
    return (np.exp(-t * x[0]) - np.exp(-t * x[1])) - x[2] * (np.exp(-t) - np.exp(-10.0 * t))


# name: (fun, x0, bounds, options); the minimum is the reference's
PROBLEMS = {
    "one pole, noisy": (_exponentials([0.9], 0.05, 1), [0.5], POLE_BOUNDS, TIGHT),
    "one pole, noisy, row-fit settings": (_exponentials([0.9], 0.05, 2), [0.5], POLE_BOUNDS, ROW_FIT),
    "two poles, noisy": (_exponentials([0.95, 0.6], 0.05, 3), [0.8, 0.3], POLE_BOUNDS, TIGHT),
    "two poles, noisy, row-fit settings": (_exponentials([0.95, 0.6], 0.02, 4), [0.8, 0.3], POLE_BOUNDS, ROW_FIT),
    "two poles, exact": (_exponentials([0.95, 0.7], 0.0, 5), [0.8, 0.3], POLE_BOUNDS, TIGHT),
    "three poles, slightly noisy": (_exponentials([0.97, 0.8, 0.4], 1e-3, 6), [0.9, 0.6, 0.2], POLE_BOUNDS, TIGHT),
    "pole beyond the upper bound (bound active)": (_exponentials([0.9999], 0.01, 7), [0.9], POLE_BOUNDS, TIGHT),
    "start on the upper bound": (_exponentials([0.99], 0.01, 8), [0.9995], POLE_BOUNDS, TIGHT),
    "start on the lower bound": (_exponentials([0.5], 0.01, 9), [1e-4], POLE_BOUNDS, TIGHT),
    "rosenbrock": (_rosenbrock, [-1.2, 1.0], (-np.inf, np.inf), TIGHT),
    "rosenbrock, bound active": (_rosenbrock, [-1.2, 1.0], ([-2.0, -2.0], [0.5, 2.0]), TIGHT),
    "rosenbrock, one-sided bound active": (_rosenbrock, [-1.2, 2.0], ([-np.inf, 1.5], [np.inf, np.inf]), TIGHT),
    "box 3d": (_box3d, [0.0, 10.0, 20.0], (-np.inf, np.inf), TIGHT),
    "box 3d, bounded": (_box3d, [0.5, 5.0, 1.5], ([0.0, 0.0, 0.0], [2.0, 9.5, 2.0]), TIGHT),
}


def _reference(fun, x0, bounds, options):
    return optimize.least_squares(fun, x0, bounds=bounds, method="trf", **options)


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_same_minimum_as_scipy(name):
    fun, x0, bounds, options = PROBLEMS[name]
    ref = _reference(fun, x0, bounds, options)
    ours = least_squares_bounded(fun, x0, bounds, **options)
    assert ours.success, ours.message
    scale = np.maximum(np.abs(ref.x), 1.0 if ref.cost < 1e-20 else 1e-300)
    assert np.max(np.abs(ours.x - ref.x) / scale) <= 2e-6, (ours.x, ref.x)
    assert abs(ours.cost - ref.cost) <= 1e-10 * ref.cost + 1e-22, (ours.cost, ref.cost)
    np.testing.assert_array_equal(ours.fun, fun(ours.x))        # the residual returned is that at x
    assert ours.cost == 0.5 * float(ours.fun @ ours.fun)


def test_bound_active_at_the_solution_is_met_exactly():
    fun, x0, bounds, options = PROBLEMS["pole beyond the upper bound (bound active)"]
    ours = least_squares_bounded(fun, x0, bounds, **options)
    assert ours.x[0] == POLE_BOUNDS[1]
    sol = least_squares_bounded(_rosenbrock, [-1.2, 1.0], ([-2.0, -2.0], [0.5, 2.0]), **TIGHT)
    assert sol.x[0] == 0.5 and abs(sol.x[1] - 0.25) < 1e-8


def test_noise_many_seeds_same_minimum_as_scipy():
    """The repair's settings on noisy one- and two-pole fits: the same minimum, at most as many evaluations."""
    total_ours = total_ref = 0
    for seed in range(12):
        fun = _exponentials([0.93, 0.7][: 1 + seed % 2], 0.1, 100 + seed, n=2000)
        x0 = [0.85, 0.5][: 1 + seed % 2]
        ref = _reference(fun, x0, POLE_BOUNDS, ROW_FIT)
        ours = least_squares_bounded(fun, x0, POLE_BOUNDS, **ROW_FIT)
        # ftol 1e-9 on the cost: either solver may stop that far above the minimum, and x move by the
        # square root of that relative to the parameters' standard error.
        assert abs(ours.cost - ref.cost) <= 2e-9 * ref.cost
        assert np.max(np.abs(ours.x - ref.x) / ref.x) <= 1e-4
        total_ours += ours.n_calls
        total_ref += ref.nfev + ref.njev * len(x0)
    assert total_ours <= 1.2 * total_ref, (total_ours, total_ref)


def _recording(fun):
    seen = []

    def wrapped(x):
        seen.append(np.array(x, copy=True))
        return fun(x)
    return wrapped, seen


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_every_evaluation_within_the_bounds(name):
    fun, x0, bounds, options = PROBLEMS[name]
    rec, seen = _recording(fun)
    ours = least_squares_bounded(rec, x0, bounds, **options)
    lb, ub = (np.broadcast_to(np.asarray(b, float), (len(x0),)) for b in bounds)
    points = np.array(seen)
    assert np.all(points >= lb) and np.all(points <= ub)
    assert any(p.tobytes() == ours.x.tobytes() for p in seen)    # the solution is a point evaluated
    assert len(seen) == ours.n_calls


def test_finite_differences_are_relative_steps_and_step_back_at_the_upper_bound():
    rec, seen = _recording(_exponentials([0.9], 0.01, 11))
    least_squares_bounded(rec, [0.5], POLE_BOUNDS, xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=2, diff_step=1e-6)
    assert seen[1][0] - seen[0][0] == pytest.approx(0.5e-6, rel=1e-9)       # h = diff_step |x|
    rec, seen = _recording(_exponentials([0.99], 0.01, 12))
    least_squares_bounded(rec, [POLE_BOUNDS[1]], POLE_BOUNDS, max_nfev=2, diff_step=1e-6)
    assert seen[1][0] == pytest.approx(POLE_BOUNDS[1] * (1 - 1e-6), rel=1e-12)  # backwards from the bound
    rec, seen = _recording(_rosenbrock)
    least_squares_bounded(rec, [-1.2, 1.0], max_nfev=2)                     # default: sqrt(eps) max(1, |x|)
    assert seen[1][0] - seen[0][0] == pytest.approx(np.sqrt(np.finfo(float).eps) * 1.2, rel=1e-6)


@pytest.mark.parametrize("max_nfev", [1, 2, 5, 9])
def test_max_nfev_is_respected(max_nfev):
    rec, seen = _recording(_rosenbrock)
    sol = least_squares_bounded(rec, [-1.2, 1.0], (-np.inf, np.inf), xtol=0, ftol=0, gtol=0, max_nfev=max_nfev)
    assert sol.status == 0 and not sol.success
    assert sol.nfev == max_nfev
    # The Jacobians' evaluations are counted apart (as scipy's trf does): two each here.
    assert len(seen) == sol.nfev + 2 * sol.njev == sol.n_calls
    assert sol.njev <= sol.nfev
    assert sol.cost <= 0.5 * float(_rosenbrock(np.array([-1.2, 1.0])) @ _rosenbrock(np.array([-1.2, 1.0])))


def test_cost_never_rises_and_fixed_variable_stays():
    fun = _exponentials([0.95, 0.6], 0.05, 13)
    sol = least_squares_bounded(fun, [0.8, 0.3], ([1e-4, 0.3], [0.9995, 0.3]), **TIGHT)
    assert sol.x[1] == 0.3
    ref = _reference(lambda a: fun(np.array([a[0], 0.3])), [0.8], POLE_BOUNDS, TIGHT)
    assert sol.x[0] == pytest.approx(ref.x[0], rel=2e-6)
    assert sol.cost <= 0.5 * float(fun(np.array([0.8, 0.3])) @ fun(np.array([0.8, 0.3])))


def test_bad_input_raises():
    with pytest.raises(ValueError, match="within the bounds"):
        least_squares_bounded(_rosenbrock, [1.0, 3.0], ([0.0, 0.0], [2.0, 2.0]))
    with pytest.raises(ValueError, match="lower bound"):
        least_squares_bounded(_rosenbrock, [1.0, 1.0], ([0.0, 2.0], [2.0, 1.0]))
    with pytest.raises(ValueError, match="not finite"):
        least_squares_bounded(lambda x: np.array([np.nan, x[0]]), [1.0])


def test_non_finite_trial_is_rejected():
    """A residual that is not finite beyond 2 stops no fit: the trial is rejected, the step shortened,
    and a forward difference that would cross 2 is taken backwards."""
    def fun(x):
        return np.array([x[0] - 3.0, 0.1 * x[0]]) if x[0] < 2.0 else np.array([np.inf, 0.0])
    rec, seen = _recording(fun)
    sol = least_squares_bounded(rec, [0.0], **TIGHT)
    assert sol.success and sol.x[0] < 2.0
    assert sol.x[0] == pytest.approx(2.0, abs=1e-6)
    assert sum(p[0] >= 2.0 for p in seen) >= 1                  # the first Gauss-Newton step (to 2.97) was tried


def test_box_lstsq_against_scipy_lsq_linear():
    rng = np.random.default_rng(0)
    for trial in range(300):
        n = 1 + trial % 4
        a = rng.standard_normal((n + 3, n))
        if trial % 5 == 0:
            a[:, -1] = a[:, 0]                                      # rank deficient
            a = np.vstack([a, 1e-3 * np.eye(n)])                    # (the damped subproblem is not)
        b = rng.standard_normal(a.shape[0])
        lo = -rng.uniform(0, 1, n) * (rng.uniform(size=n) < 0.8)
        hi = rng.uniform(0, 1, n) * (rng.uniform(size=n) < 0.8)
        lo[rng.uniform(size=n) < 0.2] = -np.inf
        hi[(lo == 0) & (hi == 0)] = 0.5
        d, at = _box_lstsq(a, b, lo, hi)
        assert np.all(d >= lo) and np.all(d <= hi)
        np.testing.assert_array_equal(d[at < 0], lo[at < 0])
        np.testing.assert_array_equal(d[at > 0], hi[at > 0])
        ref = optimize.lsq_linear(a, b, bounds=(lo, hi), method="bvls", tol=1e-14)
        r_ours, r_ref = a @ d - b, a @ ref.x - b
        assert r_ours @ r_ours <= r_ref @ r_ref * (1 + 1e-10) + 1e-14
        np.testing.assert_allclose(d, ref.x, atol=1e-7)


def test_the_repair_runs_without_scipy_optimize():
    """A child that cannot import scipy.optimize analyses and repairs paper case 3.2, and fits the
    parametric form of a step response."""
    child = textwrap.dedent('''
        import importlib.abc, sys

        class Blocker(importlib.abc.MetaPathFinder):
            def find_spec(self, fullname, path=None, target=None):
                if fullname == "scipy.optimize" or fullname.startswith("scipy.optimize."):
                    raise ImportError(f"{fullname} is blocked")
                return None

        sys.meta_path.insert(0, Blocker())
        import numpy as np
        import mpm_monitor
        mpm_monitor.limit_blas_threads()
        from mpm_monitor.core.analysis import AnalysisOptions
        from mpm_monitor.core.pipeline import analyze
        from mpm_monitor.core.repair.forms import FIRST_ORDER, _step_reference
        from mpm_monitor.sim.cases import paper_case
        from mpm_monitor.sim.closed_loop import run_closed_loop

        case = paper_case("3.2")
        log = run_closed_loop(case.plant, case.model, 3000, seed=1, mpc=case.mpc, excitation=case.excitation,
                              disturbance=case.disturbance)
        report = analyze(case.model, log.as_logged_data("paper case 3.2"), AnalysisOptions())
        assert report.repair is not None and report.repaired_model is not None
        params, lag, poles, _ = _step_reference(2.0 * (1 - 0.9 ** np.arange(1, 61)), FIRST_ORDER, 1.0)
        assert abs(params["gain"] - 2.0) < 1e-6 and abs(poles[0] - 0.9) < 1e-8, (params, poles)
        assert "scipy.optimize" not in sys.modules
        print("ok")
    ''')
    proc = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().endswith("ok")


def test_fewer_residuals_than_parameters():
    """One residual, two parameters: any point of the line ``x0 + x1 = 1`` is a minimum."""
    sol = least_squares_bounded(lambda x: np.array([x[0] + x[1] - 1.0]), [3.0, 2.0], ([0.0, 0.0], [5.0, 5.0]), **TIGHT)
    assert sol.success and abs(sol.x.sum() - 1.0) < 1e-10 and np.all(sol.x >= 0)


@pytest.mark.parametrize("noise", [0.0, 0.01])
@pytest.mark.parametrize("start", [0.5, 0.8, 0.97])
def test_equal_starting_poles_leave_the_symmetric_saddle(noise, start):
    """Two poles started equal (the step-response form fit starts one of its tries at a double pole):
    the residual is symmetric in them and its two Jacobian columns coincide, so no Gauss-Newton step
    makes them differ; the probe along the null direction must.  Reference: scipy from a split start
    (the minimum up to the order of the poles)."""
    fun = _exponentials([0.95, 0.6], noise, 21)
    ref = _reference(fun, [start * 1.01, start * 0.99], POLE_BOUNDS, TIGHT)
    ours = least_squares_bounded(fun, [start, start], POLE_BOUNDS, **TIGHT)
    np.testing.assert_allclose(np.sort(ours.x), np.sort(ref.x), rtol=2e-6)
    assert abs(ours.cost - ref.cost) <= 1e-10 * ref.cost + 1e-22


def test_step_response_form_from_a_double_pole():
    """The repair's own case: a second-order step response fitted from the start ``(tau, tau)``."""
    from mpm_monitor.core.repair.forms import _Form, _unit_steps

    form, n = _Form(n_lags=2), 60
    s = 1.5 * _unit_steps(form, [np.exp(-1 / 2.0), np.exp(-1 / 5.0)], 2, n, 1.0)[:, 0]

    def resid(x):
        cols = _unit_steps(form, x, 2, n, 1.0)
        return cols @ np.linalg.lstsq(cols, s, rcond=None)[0] - s
    for start in (0.8, 0.9, 0.95):
        ours = least_squares_bounded(resid, [start, start], POLE_BOUNDS, **TIGHT)
        np.testing.assert_allclose(np.sort(ours.x), np.exp(-1 / np.array([2.0, 5.0])), rtol=1e-9)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 12, 30])
def test_symmetric_pinv_is_numpys_bit_for_bit(n):
    """symmetric_pinv gives numpy.linalg.pinv(hermitian=True)'s very numbers: full-rank, rank-deficient (a
    repeated column, a zero column), indefinite and scaled Gram matrices, at the repair's two cut-offs."""
    rng = np.random.default_rng(n)
    cases = []
    for _ in range(20):
        x = rng.standard_normal((3 * n + 5, n)) * np.exp(rng.uniform(-8, 8, n))
        cases.append(x.T @ x)
        if n > 1:
            x[:, -1] = 2.0 * x[:, 0]
            cases.append(x.T @ x)
            x[:, 0] = 0.0
            cases.append(x.T @ x)
        s = rng.standard_normal((n, n))
        cases.append(s + s.T)                               # indefinite: signs moved into V'
    cases.append(np.zeros((n, n)))
    for g in cases:
        for rcond in (1e-12, 1e-13):
            assert np.array_equal(symmetric_pinv(g, rcond), np.linalg.pinv(g, rcond=rcond, hermitian=True))


def test_symmetric_pinv_of_an_empty_matrix():
    assert symmetric_pinv(np.zeros((0, 0)), 1e-12).shape == (0, 0)
