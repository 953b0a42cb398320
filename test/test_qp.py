"""The MPC's dense QP solver (mpm_monitor.sim.qp): exact minimum of a convex QP with two-sided bounds.

References, independent of the solver:
- small problems: every combination of rows held at their lower or upper bound enumerated, the one
  feasible KKT point kept (it is unique: H positive definite);
- MPC-sized problems: OSQP, polished, at tolerance 1e-12; and the KKT conditions checked directly.
"""

import itertools

import numpy as np
import osqp
import pytest
import scipy.sparse as sp

from mpm_monitor.sim.qp import ActiveSetQp

pytestmark = pytest.mark.filterwarnings("ignore:The default value of raise_error:PendingDeprecationWarning")


def _random_problem(rng, n, m, infinite=0.2):
    """A random strictly convex QP: H (n, n), q (n,), A (m, n), lo <= hi (m,) with some infinite."""
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    A = rng.normal(size=(m, n))
    q = rng.normal(size=n) * 3
    centre = rng.normal(size=m) * 0.3
    width = rng.uniform(0.1, 1.0, m)
    lo, hi = centre - width, centre + width
    lo[rng.random(m) < infinite] = -np.inf
    hi[rng.random(m) < infinite] = np.inf
    return H, q, A, lo, hi


def _enumerated(H, q, A, lo, hi):
    """The minimum by trying every set of held rows (None: no set gives a feasible KKT point)."""
    n, m = H.shape[0], A.shape[0]
    found = []
    for held in itertools.product((0, -1, 1), repeat=m):
        rows = [i for i in range(m) if held[i]]
        b = np.array([hi[i] if held[i] > 0 else lo[i] for i in rows])
        if not np.all(np.isfinite(b)) or len(rows) > n:
            continue
        Aw = A[rows]
        K = np.block([[H, Aw.T], [Aw, np.zeros((len(rows), len(rows)))]])
        try:
            sol = np.linalg.solve(K, np.concatenate([-q, b]))
        except np.linalg.LinAlgError:
            continue
        x, lam = sol[:n], sol[n:]
        c = A @ x
        signed = np.array([lam[k] if held[i] > 0 else -lam[k] for k, i in enumerate(rows)])
        if np.all(c >= lo - 1e-9) and np.all(c <= hi + 1e-9) and np.all(signed >= -1e-9):
            found.append(x)
    return found


@pytest.mark.parametrize("seed", range(40))
def test_small_problems_equal_the_enumerated_kkt_point(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 5))
    m = int(rng.integers(1, 7))
    H, q, A, lo, hi = _random_problem(rng, n, m)
    ref = _enumerated(H, q, A, lo, hi)
    sol = ActiveSetQp(H, A).solve(q, lo, hi)
    if not ref:
        assert sol is None
        return
    assert sol is not None
    for x in ref:                                      # all the same point, up to rounding
        np.testing.assert_allclose(sol.x, x, rtol=0, atol=1e-9)


def _mpc_like(rng, nu=3, hc=10):
    """A problem shaped like the MPC's: moves dU (hc nu,), rows u(k+t) = u_prev + sum du, then du."""
    n = nu * hc
    M = rng.normal(size=(3 * n, n))
    H = M.T @ M + 0.1 * np.eye(n)
    Mc = np.kron(np.tril(np.ones((hc, hc))), np.eye(nu))
    A = np.vstack([Mc, np.eye(n)])
    q = rng.normal(size=n) * 20
    u_prev = rng.uniform(-0.3, 0.3, nu)
    umax, dmax = rng.uniform(0.4, 1.0, nu), rng.uniform(0.05, 0.3, nu)
    lo = np.concatenate([np.tile(-umax - u_prev, hc), -np.tile(dmax, hc)])
    hi = np.concatenate([np.tile(umax - u_prev, hc), np.tile(dmax, hc)])
    return H, q, A, lo, hi


def _osqp(H, q, A, lo, hi):
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.triu(H)), q, sp.csc_matrix(A), lo, hi, verbose=False, eps_abs=1e-12,
                 eps_rel=1e-12, polishing=True, max_iter=200000)
    res = solver.solve()
    assert res.info.status == "solved"
    return res.x


@pytest.mark.parametrize("seed", range(10))
def test_mpc_shaped_problems_meet_kkt_and_equal_osqp(seed):
    rng = np.random.default_rng(100 + seed)
    H, q, A, lo, hi = _mpc_like(rng)
    sol = ActiveSetQp(H, A).solve(q, lo, hi)
    assert sol is not None and sol.active.size >= 5          # many bounds held
    x = sol.x
    c = A @ x
    assert np.all(c >= lo - 1e-10) and np.all(c <= hi + 1e-10)
    held = np.where(sol.upper, hi[sol.active], lo[sol.active])
    np.testing.assert_allclose(c[sol.active], held, rtol=0, atol=1e-12)
    assert np.all(sol.multipliers >= -1e-12)
    lam = np.where(sol.upper, sol.multipliers, -sol.multipliers)
    np.testing.assert_allclose(H @ x + q + A[sol.active].T @ lam, 0.0, rtol=0, atol=1e-9 * np.abs(q).max())
    np.testing.assert_allclose(x, _osqp(H, q, A, lo, hi), rtol=0, atol=1e-7)


@pytest.mark.parametrize("seed", range(5))
def test_a_guess_changes_the_work_not_the_answer(seed):
    rng = np.random.default_rng(200 + seed)
    H, q, A, lo, hi = _mpc_like(rng)
    qp = ActiveSetQp(H, A)
    cold = qp.solve(q, lo, hi)
    warm = qp.solve(q, lo, hi, cold.active, cold.upper)
    assert warm.iterations <= 1 < cold.iterations
    np.testing.assert_allclose(warm.x, cold.x, rtol=0, atol=1e-12)
    m = A.shape[0]
    for _ in range(5):                                  # wrong guesses, dependent rows among them
        rows = rng.choice(m, size=int(rng.integers(1, 40)), replace=True)
        other = qp.solve(q, lo, hi, rows, rng.random(rows.size) < 0.5)
        np.testing.assert_allclose(other.x, cold.x, rtol=0, atol=1e-10)


def test_bounds_that_cannot_be_met_give_none():
    H = np.eye(2)
    A = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    lo = np.array([-np.inf, 1.0, -1.0])
    hi = np.array([0.0, np.inf, 1.0])                   # x1 <= 0 and x1 >= 1
    qp = ActiveSetQp(H, A)
    assert qp.solve(np.zeros(2), lo, hi) is None
    assert qp.last_failure == "infeasible"


def test_the_iteration_limit_gives_none_and_says_so():
    rng = np.random.default_rng(7)
    H, q, A, lo, hi = _mpc_like(rng)
    qp = ActiveSetQp(H, A)
    full = qp.solve(q, lo, hi)
    assert full.iterations >= 5 and qp.last_failure is None
    assert qp.solve(q, lo, hi, max_iter=full.iterations - 1) is None
    assert qp.last_failure == "iteration_limit"
    again = qp.solve(q, lo, hi, max_iter=full.iterations)     # a solve after a failure starts afresh
    assert qp.last_failure is None
    np.testing.assert_array_equal(again.x, full.x)


def test_the_tolerance_is_how_far_a_bound_may_be_exceeded():
    # The free minimum x = 1 exceeds the bound x <= 1 - 1e-7 by 1e-7 (relative to 1 + |x|: 5e-8).
    H, A = np.eye(1), np.eye(1)
    q, lo, hi = np.array([-1.0]), np.array([-np.inf]), np.array([1.0 - 1e-7])
    qp = ActiveSetQp(H, A)
    loose = qp.solve(q, lo, hi, tolerance=1e-7)
    assert loose.active.size == 0 and loose.x[0] == 1.0
    tight = qp.solve(q, lo, hi, tolerance=1e-9)
    assert tight.active.tolist() == [0] and tight.x[0] == 1.0 - 1e-7


def test_an_equality_row_may_hold_either_sign():
    H = np.eye(2)
    A = np.array([[1.0, 1.0]])
    for target in (-2.0, 2.0):                          # the free minimum 0 is above, then below
        sol = ActiveSetQp(H, A).solve(np.zeros(2), np.array([target]), np.array([target]))
        np.testing.assert_allclose(sol.x, [target / 2, target / 2], atol=1e-14)
