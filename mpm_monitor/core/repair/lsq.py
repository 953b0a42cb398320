"""A small bounded nonlinear least-squares solver: the repair's pole fits, without ``scipy.optimize``.

:func:`least_squares_bounded` minimizes ``0.5 ||f(x)||^2`` over a box ``lb <= x <= ub`` for a few
parameters (the repair fits one to four discrete poles, :mod:`.fit` and :mod:`.forms`) and a residual
``f`` of many samples, with a forward-difference Jacobian.  Importing ``scipy.optimize`` for its
``least_squares`` would cost about 0.13 s of the command (linprog, shgo, sparse, spatial...); this is
numpy only.

Algorithm
---------
A trust-region Levenberg-Marquardt method (Marquardt 1963; Moré 1978, with his scaling and his
update of the radius) whose step is the minimizer of the damped Gauss-Newton model *within the
box*.  At an iterate ``x`` (always feasible) with residual ``f`` and Jacobian ``J = Q R``::

    d(mu) = argmin ||R d + Q'f||^2 + mu ||D d||^2   subject to   lb - x <= d <= ub - x

``D`` holds the largest norm each column of ``J`` has had so far.  The step is the Gauss-Newton step
``d(0)`` when ``||D d(0)||`` is within the trust radius, else ``d(mu)`` with the ``mu`` that brings
the unconstrained step to the radius (:func:`_mu_for_radius`, Newton's method on the secular
equation, closed form from the SVD of the ``n x n`` matrix ``R D^-1``).  With few parameters the
box-constrained subproblem is solved exactly (:func:`_damped_step`: the unconstrained step when it
stays in the box, else an active-set method, :func:`_box_lstsq`; the ``m`` residuals enter once per
Jacobian, through ``Q'f``).  This is the projected Levenberg-Marquardt idea of Kanzow, Yamashita
and Fukushima (2004) with the projection replaced by the exact constrained step: a variable on its
bound whose gradient pushes outward stays there, the others take the step of the reduced problem.
A trial step is accepted when it lowers the cost; the gain ratio ``rho`` (actual over predicted
reduction) sets the radius: a quarter of the step's length when ``rho < 0.25``, at least twice it
when ``rho > 0.75``.  The first radius is a tenth of ``||D max(1, |x0|)||``: a first Gauss-Newton
step that jumped across the box (as it does near a saddle, where ``J`` is nearly singular) could
land on a bound far from the valley the descent from ``x0`` leads to.

A Gauss-Newton method cannot leave a saddle where ``J`` is rank-deficient: a response symmetric in
two poles started at equal poles has two equal columns, and every step keeps the poles equal.  When
the iteration stops with a scaled ``J`` whose smallest singular value is below ``1e-8`` of its
largest, the cost is probed once each way along the null direction (a step of ``1e-3 max(1, |x|)``);
a probe that lowers the cost by more than ``1e-8`` of it is taken and the iteration goes on (at most
twice; the probes count in ``nfev``).

Stopping rules (``S = ||f||^2``; ``d_GN = d(0)``, the undamped step, used so that a step cut short by
the damping never passes for convergence):

* ``gtol``: ``max_i |v_i g_i| <= gtol`` at the current Jacobian, ``g = J'f`` and ``v_i`` the distance
  to the bound that ``-g_i`` points to (1 when that bound is infinite), the first-order measure of
  Coleman and Li (1996): zero at an interior stationary point and where every nonzero gradient
  component pushes a variable against its bound;
* ``ftol``: an accepted step with ``rho > 0.25`` reduced ``S`` by at most ``ftol S`` *and* the
  Gauss-Newton model promised at most ``ftol S`` (or a rejected step where it promised that);
* ``xtol``: an accepted step whose undamped step ``d_GN`` was at most ``xtol (xtol + ||x||)``, or a
  rejected step itself that short (nothing is gained at that resolution);
* ``max_nfev``: the evaluations of the iteration (the start and every trial point) reached
  ``max_nfev``.  As in ``scipy.optimize.least_squares`` (methods ``trf``, ``dogbox``), the ``n``
  evaluations of each finite-difference Jacobian are counted apart (:attr:`LsqResult.njev`).

The returned ``x`` is always a point at which ``fun`` was called (the very array values, so that a
caller can look up what it computed there), and ``fun`` at it is returned too.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import numpy as np

_EPS = float(np.finfo(float).eps)
_TINY = float(np.finfo(float).tiny)
#: Default relative step of the forward differences: ``sqrt(eps)`` (then times ``max(1, |x|)``).
_DEFAULT_STEP = float(np.sqrt(_EPS))
#: The first trust radius, in ``||D d||``, relative to ``||D max(1, |x0|)||``.
_RADIUS0 = 0.1
#: A scaled Jacobian whose smallest singular value is below this fraction of its largest is rank-deficient.
_RANK_TOL = 1e-8
#: Length of a probe along the null direction of a rank-deficient Jacobian, relative to ``max(1, |x|)``.
_PROBE = 1e-3
#: Relative reduction of the cost that a probe must achieve to be taken.
_PROBE_GAIN = 1e-8
#: Probes per solve, at most.
_MAX_ESCAPES = 2

STATUS_MESSAGES = {0: "the number of function evaluations reached max_nfev",
                   1: "gtol: the scaled gradient is at most gtol",
                   2: "ftol: the reduction of the cost, and the model's, are at most ftol",
                   3: "xtol: the step is at most xtol (xtol + ||x||)"}


@dataclasses.dataclass
class LsqResult:
    """The solution of :func:`least_squares_bounded`.

    Attributes
    ----------
    x : ndarray, shape (n,)
        The solution (a point at which ``fun`` was evaluated), within the bounds.
    fun : ndarray, shape (m,)
        The residual at ``x``.
    cost : float
        ``0.5 fun @ fun``.
    optimality : float
        The scaled gradient ``max_i |v_i g_i|`` at the last Jacobian (see the module's notes).
    nfev : int
        Evaluations of the iteration: the start and the trial points (what ``max_nfev`` limits).
    njev : int
        Finite-difference Jacobians, each of ``n`` more evaluations (fewer on a fixed variable).
    n_calls : int
        Every call of ``fun``.
    status : int
        0 ``max_nfev``, 1 ``gtol``, 2 ``ftol``, 3 ``xtol`` (the codes of ``scipy.optimize.least_squares``).
    """

    x: np.ndarray
    fun: np.ndarray
    cost: float
    optimality: float
    nfev: int
    njev: int
    n_calls: int
    status: int

    @property
    def success(self) -> bool:
        """Whether a tolerance stopped the iteration (not ``max_nfev``)."""
        return self.status > 0

    @property
    def message(self) -> str:
        return STATUS_MESSAGES[self.status]


#: Spread (standard deviation) of a fit's target below which its search sees the residual scaled by a power
#: of two (:func:`solver_scale`).
SOLVER_SCALE_BELOW = 2.0 ** -7


def solver_scale(x: np.ndarray) -> float:
    """The factor a least-squares search multiplies its residual by: 1 for a target ``x`` whose standard
    deviation is at least :data:`SOLVER_SCALE_BELOW`, else the power of two that brings it to about 1.

    The search's gradient tolerance (``gtol`` of :func:`least_squares_bounded`)
    is absolute, in squared residual units: with an output in small units (case 3.2 with every output
    in units of 1e-8) it is met at the start, and the repair kept a wrong pole and called a time-constant
    error a gain error.  A power of two scales every number exactly, so the search then takes the steps
    it takes on the same data in units of about 1; the ftol and xtol tests are relative and unchanged.
    Above the bound the factor is 1: the search's path is the one it always took (the benchmarks' figures
    are unchanged).  Used by the pole search of a row (:class:`~mpm_monitor.core.repair.fit._RowProblem`)
    and by the fit of a form to a step-response model's coefficients (:mod:`~mpm_monitor.core.repair.forms`).
    """
    spread = float(np.std(x)) if x.size else 0.0
    if not (spread > 0.0 and math.isfinite(spread)) or spread >= SOLVER_SCALE_BELOW:
        return 1.0
    return 2.0 ** round(-math.log2(spread))


def symmetric_pinv(a: np.ndarray, rcond: float) -> np.ndarray:
    """``numpy.linalg.pinv(a, rcond=rcond, hermitian=True)`` of a real symmetric matrix, the very same numbers.

    The same operations in the same order as numpy 2's (the eigendecomposition, the eigenvalues'
    magnitudes sorted in decreasing order with their signs moved into ``V'``, the small ones dropped below
    ``rcond`` times the largest, then ``V' ' diag(1/s) U'``), without the stacked-matrix generality
    (``take_along_axis``, the wrappers) that cost about 35 microseconds of its 85 on a 10 x 10 matrix.  The
    repair's pole searches call it tens of thousands of times on a step-response model's row.
    ``test_lsq.py`` checks it against ``numpy.linalg.pinv`` bit for bit.

    Parameters
    ----------
    a : ndarray, shape (n, n)
        Real symmetric.
    rcond : float
        Singular values at most ``rcond`` times the largest count as zero.

    Returns
    -------
    ndarray, shape (n, n)
    """
    if a.shape[0] == 0:
        return np.empty((0, 0))
    s, u = np.linalg.eigh(a)
    sgn = np.copysign(1.0, s)
    s = np.abs(s)
    order = np.argsort(s)[::-1]
    sgn, s, u = sgn[order], s[order], u[:, order]
    vt = (u * sgn).T.conjugate()
    large = s > rcond * np.max(s)
    s = np.divide(1, s, where=large, out=s)
    s[~large] = 0
    return vt.T @ (s[:, None] * u.T)


def least_squares_bounded(fun: Callable[[np.ndarray], np.ndarray], x0, bounds=(-np.inf, np.inf), *,
                          xtol: float = 1e-8, ftol: float = 1e-8, gtol: float = 1e-8, max_nfev: Optional[int] = None,
                          diff_step: Optional[float] = None) -> LsqResult:
    """Minimize ``0.5 ||fun(x)||^2`` subject to ``lb <= x <= ub`` (Levenberg-Marquardt, box-constrained step).

    Meant for a few parameters (the active-set step is exact, its cost grows like ``n^4``) and many
    residuals; see the module's notes for the algorithm and the stopping rules.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> f``, ``x`` of shape (n,), ``f`` of shape (m,), the same ``m`` at every call.
        ``x`` is a fresh array each call (the caller may keep it).  A residual that is not finite at
        a trial point rejects that point.
    x0 : array_like, shape (n,)
        The start, within the bounds (on a bound is allowed).
    bounds : (lb, ub)
        Lower and upper bounds, scalars or shape (n,); ``-inf`` / ``inf`` for none, ``lb == ub``
        holds a variable.
    xtol, ftol, gtol : float
        Tolerances of the stopping rules (relative step, relative reduction of the cost, scaled
        gradient in the units of ``J'f``).  Zero disables a rule.
    max_nfev : int, optional
        Most evaluations of the iteration, the start and the trial points; the Jacobians'
        ``n`` evaluations each are not counted.  Default ``100 n``.
    diff_step : float, optional
        Relative step of the forward differences: ``h_j = diff_step |x_j|`` (the default step where
        that is zero).  Default: ``h_j = sqrt(eps) max(1, |x_j|)``.  A step that would leave the box
        is taken backwards (or to the farther bound when the box is narrower than ``h_j``).

    Returns
    -------
    LsqResult

    Raises
    ------
    ValueError
        ``x0`` outside the bounds, ``lb > ub``, a residual that is not one-dimensional, or not finite
        at ``x0``.
    """
    x = np.array(x0, dtype=float).ravel()
    n = x.size
    lb, ub = (np.broadcast_to(np.asarray(b, dtype=float), (n,)).copy() for b in bounds)
    if np.any(lb > ub):
        raise ValueError("least_squares_bounded: a lower bound exceeds its upper bound")
    if np.any(x < lb) or np.any(x > ub) or not np.all(np.isfinite(x)):
        raise ValueError("least_squares_bounded: x0 is not within the bounds")
    max_nfev = 100 * max(n, 1) if max_nfev is None else int(max_nfev)
    if max_nfev < 1:
        raise ValueError("least_squares_bounded: max_nfev must be at least 1")

    f = _evaluate(fun, x)
    if f.ndim != 1:
        raise ValueError("least_squares_bounded: fun must return a one-dimensional residual")
    if not np.all(np.isfinite(f)):
        raise ValueError("least_squares_bounded: the residual is not finite at x0")
    m = f.shape[0]
    s = float(f @ f)
    nfev, njev, n_calls = 1, 0, 1
    if n == 0 or m == 0:
        return LsqResult(x=x, fun=f, cost=0.5 * s, optimality=0.0, nfev=nfev, njev=njev, n_calls=n_calls,
                         status=1)

    scale = np.zeros(n)                 # D: the largest norm of each Jacobian column so far
    radius = None                       # the trust radius, in ||D d||
    status = None
    optimality = np.inf
    svd = None
    escapes = 0
    while True:
        while status is None:
            jac, used = _forward_jacobian(fun, x, f, lb, ub, diff_step)
            njev += 1
            n_calls += used
            # The triangle of [J, f] = Q [[R, c], [0, .]]: J = Q R and c = Q'f, without forming Q.
            aug = np.column_stack([jac, f])
            if m < n:                                           # (zero rows change nothing)
                aug = np.vstack([aug, np.zeros((n - m, n + 1))])
            rc = np.linalg.qr(aug, mode="r")
            r, c = np.triu(rc[:n, :n]), rc[:n, n].copy()
            g = r.T @ c                                         # J'f
            optimality = float(np.max(np.abs(_distance_against(x, g, lb, ub) * g)))
            if optimality <= gtol:
                status = 1
                break
            scale = np.maximum(scale, np.sqrt(np.sum(r * r, axis=0)))   # the columns' norms of J
            dscale = np.where(scale > 0, scale, 1.0)
            lo, hi = lb - x, ub - x
            svd = np.linalg.svd(r / dscale)                     # of the scaled R, n x n
            d_gn, at_gn = _damped_step(r, c, dscale, svd, 0.0, lo, hi)
            pred_gn = _predicted(r, c, d_gn)
            if radius is None:
                radius = _RADIUS0 * float(np.linalg.norm(dscale * np.maximum(np.abs(x), 1.0)))
            tiny_step = xtol * (xtol + float(np.linalg.norm(x)))
            gn_converged_x = float(np.linalg.norm(d_gn)) <= tiny_step
            gn_converged_f = pred_gn <= ftol * s
            while True:                                         # trial steps until one is accepted
                if nfev >= max_nfev:
                    status = 0
                    break
                if float(np.linalg.norm(dscale * d_gn)) <= radius:
                    d, at = d_gn, at_gn
                else:
                    d, at = _damped_step(r, c, dscale, svd, _mu_for_radius(svd, c, radius), lo, hi)
                x_new = np.clip(np.where(at < 0, lb, np.where(at > 0, ub, x + d)), lb, ub)
                d = x_new - x
                pred = _predicted(r, c, d)
                step_norm = float(np.linalg.norm(d))
                if step_norm == 0.0 or pred <= 0.0:             # no step reduces the model: stationary
                    status = 3
                    break
                f_new = _evaluate(fun, x_new)
                nfev += 1
                n_calls += 1
                s_new = float(f_new @ f_new) if f_new.shape == f.shape and np.all(np.isfinite(f_new)) else np.inf
                actual = s - s_new
                rho = actual / pred
                scaled_step = float(np.linalg.norm(dscale * d))
                if rho < 0.25:
                    radius = 0.25 * scaled_step
                elif rho > 0.75:
                    radius = max(radius, 2.0 * scaled_step)
                if actual > 0.0:                                # accepted
                    reduced_little = rho > 0.25 and actual <= ftol * s and gn_converged_f
                    x, f, s = x_new, f_new, s_new
                    if reduced_little:
                        status = 2
                    elif gn_converged_x:
                        status = 3
                    break
                if gn_converged_f:
                    status = 2
                    break
                if step_norm <= tiny_step:
                    status = 3
                    break
        # A stop where the Jacobian is rank-deficient may be a saddle that the Gauss-Newton model cannot
        # see (a response symmetric in two poles, at equal poles: their columns coincide).  Probe along
        # the null direction, both ways; go on from a point that lowers the cost clearly.
        if status == 0 or svd is None or escapes >= _MAX_ESCAPES or svd[1][-1] > _RANK_TOL * svd[1][0]:
            break
        escapes += 1
        p = svd[2][-1] / dscale
        p *= _PROBE * max(float(np.max(np.abs(x))), 1.0) / float(np.max(np.abs(p)))
        escaped = False
        for sign in (1.0, -1.0):
            x_probe = np.clip(x + sign * p, lb, ub)
            if nfev >= max_nfev or np.array_equal(x_probe, x):
                continue
            f_probe = _evaluate(fun, x_probe)
            nfev += 1
            n_calls += 1
            if f_probe.shape == f.shape and np.all(np.isfinite(f_probe)):
                s_probe = float(f_probe @ f_probe)
                if s - s_probe > _PROBE_GAIN * s:
                    radius = max(radius, 2.0 * float(np.linalg.norm(dscale * (x_probe - x))))
                    x, f, s, escaped = x_probe, f_probe, s_probe, True
                    break
        if not escaped:
            break
        status = None
    return LsqResult(x=x, fun=f, cost=0.5 * s, optimality=optimality, nfev=nfev, njev=njev, n_calls=n_calls,
                     status=status)


def _evaluate(fun, x: np.ndarray) -> np.ndarray:
    """``fun`` at a copy of ``x``, as a float array."""
    return np.asarray(fun(x.copy()), dtype=float)


def _predicted(r: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """Reduction of ``||f + J d||^2`` from ``||f||^2`` that the linear model predicts (``J = Q R``, ``c = Q'f``)."""
    lin = r @ d + c
    return float(c @ c - lin @ lin)


def _damped_step(r, c, dscale, svd, mu: float, lo, hi):
    """``d(mu) = argmin ||R d + c||^2 + mu ||D d||^2`` subject to ``lo <= d <= hi``.

    Unconstrained first, from the SVD ``U S V'`` of ``R D^-1`` (``d = -D^-1 V S (S^2 + mu)^-1 U'c``;
    for ``mu = 0`` the pseudo-inverse, singular values below ``n eps`` of the largest dropped); when that
    leaves the box, by the active-set method (:func:`_box_lstsq`).

    Parameters
    ----------
    r : ndarray, shape (n, n)
    c : ndarray, shape (n,)
    dscale : ndarray, shape (n,)
        ``D``, positive.
    svd : tuple
        ``np.linalg.svd(r / dscale)``.
    mu : float
        Damping, >= 0.
    lo, hi : ndarray, shape (n,)

    Returns
    -------
    d : ndarray, shape (n,)
    at : ndarray of int, shape (n,)
        -1 / +1 where ``d`` is held at ``lo`` / ``hi``, 0 elsewhere.
    """
    u, sv, vt = svd
    n = sv.size
    if mu > 0.0:
        w = sv / (sv * sv + mu)
    else:
        keep = sv > n * _EPS * sv[0]
        w = np.divide(1.0, sv, out=np.zeros(n), where=keep)
    d = -(vt.T @ (w * (u.T @ c))) / dscale
    if np.all(d >= lo) and np.all(d <= hi):
        return d, np.zeros(n, dtype=int)
    if mu > 0.0:
        return _box_lstsq(np.vstack([r, np.diag(np.sqrt(mu) * dscale)]), np.concatenate([-c, np.zeros(n)]), lo, hi)
    return _box_lstsq(r, -c, lo, hi)


def _mu_for_radius(svd, c, radius: float) -> float:
    """The damping ``mu`` whose step, without the bounds, has ``||D d(mu)|| = radius`` (to 10 %).

    With ``R D^-1 = U S V'`` and ``h = U'c``, ``||D d(mu)|| = ||S h / (S^2 + mu)||`` decreases in ``mu``;
    ``1 / ||D d(mu)||`` is increasing and concave (nearly linear), so Newton's method on
    ``1 / ||D d(mu)|| - 1 / radius`` from ``mu = 0``, where the step is longer than ``radius``, rises to
    the root without passing it (Moré 1978; Moré and Sorensen 1983).

    Parameters
    ----------
    svd : tuple
        ``np.linalg.svd(R / D)``.
    c : ndarray, shape (n,)
    radius : float
        > 0, less than the length of the undamped step.

    Returns
    -------
    mu : float
    """
    u, sv, _ = svd
    sh = sv * (u.T @ c)
    sv2 = sv * sv
    keep = sh != 0
    sh, sv2 = sh[keep], sv2[keep]
    mu = 0.0
    for _ in range(30):
        y = sh / (sv2 + mu)
        q = float(np.linalg.norm(y))
        if q <= 1.1 * radius:
            break
        dq = float(np.sum(y * y / (sv2 + mu)))                  # -d||y||/dmu times ||y||
        mu += (q / radius - 1.0) * q * q / dq                 # Newton on 1/||y|| - 1/radius
    return mu


def _distance_against(x, g, lb, ub) -> np.ndarray:
    """Coleman-Li scaling: the distance from ``x`` to the bound that ``-g`` points to (1 where infinite), shape (n,)."""
    v = np.ones_like(x)
    down = (g > 0) & np.isfinite(lb)                            # a descent would lower x_i
    up = (g < 0) & np.isfinite(ub)
    v[down] = (x - lb)[down]
    v[up] = (ub - x)[up]
    return v


def _forward_jacobian(fun, x, f, lb, ub, diff_step):
    """Forward-difference Jacobian of ``fun`` at ``x`` (``f = fun(x)``), steps kept within the box.

    Returns
    -------
    jac : ndarray, shape (m, n)
    used : int
        Evaluations of ``fun`` (a variable held by ``lb == ub`` takes none: its column is zero; one
        whose forward step gives a residual that is not finite takes a second, backwards).
    """
    n = x.size
    default = _DEFAULT_STEP * np.maximum(1.0, np.abs(x))
    h = default if diff_step is None else np.where(x != 0, diff_step * np.abs(x), default)
    jac = np.zeros((f.shape[0], n))
    used = 0
    for j in range(n):
        room_up, room_down = ub[j] - x[j], x[j] - lb[j]
        step = h[j]
        if step > room_up:                                      # forward would leave the box
            step = -step if step <= room_down else (room_up if room_up >= room_down else -room_down)
        xj = x.copy()
        xj[j] = x[j] + step
        step = xj[j] - x[j]                                     # the step the floats hold
        if step == 0.0:
            continue
        fj = _evaluate(fun, xj)
        used += 1
        if not np.all(np.isfinite(fj)) and x[j] - h[j] >= lb[j]:  # not finite ahead: the other side
            xj[j] = x[j] - h[j]
            step = xj[j] - x[j]
            fj = _evaluate(fun, xj)
            used += 1
        if not np.all(np.isfinite(fj)):
            raise ValueError("least_squares_bounded: the residual is not finite on either side of x for "
                             "the finite differences")
        jac[:, j] = (fj - f) / step
    return jac, used


def _box_lstsq(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """``argmin ||a d - b||`` subject to ``lo <= d <= hi`` (``lo <= 0 <= hi``), by an active-set method.

    A primal active-set method from the feasible ``d = 0``: on the free variables, move towards the
    least-squares solution with the others held at their bounds (the smallest correction where that
    is not unique), stopping at the first bound met, which is then held; when the free solution is
    feasible, free the held variable whose multiplier has the wrong sign (the one that most lowers
    the cost), until none has.  Few variables: each step is a small ``lstsq``.

    Parameters
    ----------
    a : ndarray, shape (k, n)
    b : ndarray, shape (k,)
    lo, hi : ndarray, shape (n,)
        Bounds of ``d``, ``lo <= 0 <= hi`` (``-inf`` / ``inf`` allowed).

    Returns
    -------
    d : ndarray, shape (n,)
    at : ndarray of int, shape (n,)
        -1 where ``d`` is held at ``lo``, +1 at ``hi``, 0 free.
    """
    n = a.shape[1]
    d = np.zeros(n)
    at = np.zeros(n, dtype=int)
    pinned = lo == hi                                           # no room: held for good
    at[pinned] = -1
    tol = 1e3 * _EPS * (float(np.linalg.norm(a)) * float(np.linalg.norm(b)) + _TINY)
    for _ in range(4 * n + 8):
        for _ in range(n + 1):                                  # to the minimum on the free variables
            free = np.flatnonzero(at == 0)
            if free.size == 0:
                break
            delta = np.linalg.lstsq(a[:, free], b - a @ d, rcond=None)[0]
            target = d[free] + delta
            below, above = target < lo[free], target > hi[free]
            if not (below.any() or above.any()):
                d[free] = target
                break
            # The longest feasible fraction of the move, and the variable that blocks it.
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(below, (lo[free] - d[free]) / delta, np.where(above, (hi[free] - d[free]) / delta, np.inf))
            k = int(np.argmin(t))
            d[free] += max(float(t[k]), 0.0) * delta
            j = free[k]
            if below[k]:
                d[j], at[j] = lo[j], -1
            else:
                d[j], at[j] = hi[j], 1
            d[free] = np.clip(d[free], lo[free], hi[free])
        w = a.T @ (b - a @ d)                                   # minus the gradient of 0.5 ||a d - b||^2
        wrong = np.where((at < 0) & ~pinned, w, 0.0) - np.where(at > 0, w, 0.0)  # > 0: would move inward
        k = int(np.argmax(wrong))
        if wrong[k] <= tol:
            break
        at[k] = 0
    return d, at
