"""A small dense convex QP with two-sided linear bounds, solved exactly by a dual active-set method.

The problem, with ``H`` symmetric positive definite and ``H`` and ``A`` fixed between solves (an
MPC's horizon: only the linear term and the bounds change from one sample to the next)::

    minimise  1/2 x' H x + q' x    subject to    lo <= A x <= hi

is solved by the dual method of Goldfarb and Idnani ("A numerically stable dual method for solving
strictly convex quadratic programs", *Mathematical Programming* 27, 1983): from the unconstrained
minimum, or from a guessed working set whose multipliers have their sign, it adds the most violated
row at each step, releasing any held row whose multiplier reaches zero on the way, and stops when no
row is violated.  Every iterate is the minimum on its working set with multipliers >= 0, so the last
one meets the KKT conditions: the problem's unique minimum, to rounding (a first-order method such
as OSQP stops at a tolerance instead).

The work is done in the constraints' space: with ``G = A H^-1 A'`` formed once, the working set
``W`` enters through the Cholesky factor of ``G_WW`` (grown by one row when a row is added, formed
again when one is released), so an iteration costs ``O(|W|^2 + m |W|)`` (``O(|W|^3)`` when it
releases a row) and ``H`` is factorised once.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import scipy.linalg as sla
from scipy.linalg.lapack import dtrtrs


@dataclasses.dataclass(frozen=True)
class QpSolution:
    """The minimum found by :meth:`ActiveSetQp.solve`.

    Attributes
    ----------
    x : ndarray, shape (n,)
        The minimiser.
    active : ndarray of int, shape (k,)
        The rows of ``A`` held at a bound at the end (the final working set).
    upper : ndarray of bool, shape (k,)
        For each of ``active``: held at ``hi`` (True) or at ``lo`` (False).
    multipliers : ndarray, shape (k,)
        Their Lagrange multipliers, signed so that all are >= 0 at the minimum.
    iterations : int
        Active-set iterations taken.
    """

    x: np.ndarray
    active: np.ndarray
    upper: np.ndarray
    multipliers: np.ndarray
    iterations: int


class ActiveSetQp:
    """``min 1/2 x'Hx + q'x`` s.t. ``lo <= A x <= hi`` for a fixed ``H`` and ``A``.

    Parameters
    ----------
    H : ndarray, shape (n, n)
        Symmetric positive definite Hessian.
    A : ndarray, shape (m, n)
        Constraint rows (any ``m``; a row whose bounds are both infinite is never held).
    """

    def __init__(self, H: np.ndarray, A: np.ndarray):
        H = np.asarray(H, dtype=float)
        A = np.asarray(A, dtype=float)
        if H.ndim != 2 or H.shape[0] != H.shape[1] or A.ndim != 2 or A.shape[1] != H.shape[0]:
            raise ValueError(f"expected H (n, n) and A (m, n), got {H.shape} and {A.shape}")
        self.A = A
        self._chol = (np.linalg.cholesky(H), True)                            # H = L L'
        self._hinv_at = sla.cho_solve(self._chol, A.T, check_finite=False)   # H^-1 A', (n, m)
        g = A @ self._hinv_at
        self._G = 0.5 * (g + g.T)                                             # A H^-1 A', (m, m)
        norm = np.sqrt(np.maximum(np.diag(self._G), 0.0))                   # ||a_i|| in H^-1
        self._row_scale = np.where(norm > 0, norm, 1.0)
        #: Why the last :meth:`solve` returned None: ``"infeasible"`` (the bounds cannot all be met) or
        #: ``"iteration_limit"``; None after a solve that found the minimum.
        self.last_failure: Optional[str] = None

    @property
    def n(self) -> int:
        return self.A.shape[1]

    @property
    def m(self) -> int:
        return self.A.shape[0]

    def solve(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, guess: Optional[np.ndarray] = None,
              guess_upper: Optional[np.ndarray] = None, max_iter: Optional[int] = None,
              tolerance: float = 1e-9) -> Optional[QpSolution]:
        """The minimum, by the dual active-set method.

        Parameters
        ----------
        q : ndarray, shape (n,)
            Linear term.
        lo, hi : ndarray, shape (m,)
            Bounds on ``A x`` (``-inf``/``inf`` for none), ``lo <= hi``.
        guess, guess_upper : ndarray of int and of bool, shape (k,), optional
            Rows expected to be held at the minimum, and whether at ``hi`` (an MPC: the last sample's
            held rows, shifted by one move).  They start the working set when their multipliers come
            out with their sign (after at most three rounds of dropping those that do not); the
            answer does not depend on them, only the work.
        max_iter : int, optional
            Iteration limit (default ``5 (n + m)``).
        tolerance : float, optional
            A row counts as violated when ``A x`` lies beyond a bound by more than ``tolerance (1 +
            |A x|)`` (default 1e-9; relative, no unit).

        Returns
        -------
        QpSolution or None
            None when the bounds cannot all be met, or when the limit is reached; :attr:`last_failure`
            says which.
        """
        G, n, m = self._G, self.n, self.m
        self.last_failure = None
        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        max_iter = 5 * (n + m) if max_iter is None else int(max_iter)
        x_unc = -sla.cho_solve(self._chol, np.asarray(q, dtype=float), check_finite=False)
        c_unc = self.A @ x_unc

        work, upper, lam, chol = self._dual_feasible_start(guess, guess_upper, c_unc, lo, hi)
        k = work.size
        W = np.empty(n, dtype=int)                 # the working set, rows of A
        S = np.empty(n)                            # +1 held at hi, -1 at lo
        mu = np.empty(n)                           # multipliers (>= 0)
        L = np.zeros((n, n), order="F")            # Cholesky factor of G[W, W]
        in_work = np.zeros(m, dtype=bool)
        W[:k], S[:k], mu[:k] = work, np.where(upper, 1.0, -1.0), np.where(upper, lam, -lam)
        in_work[work] = True
        c = c_unc.copy()                           # A x
        if k:
            L[:k, :k] = chol
            c -= G[:, work] @ lam
        it = 0
        while True:
            over = np.maximum(c - hi, lo - c)
            over -= tolerance * (1.0 + np.abs(c))
            over /= self._row_scale
            over[in_work] = -np.inf
            p = int(np.argmax(over))
            if not over[p] > 0:
                break
            sp = 1.0 if c[p] > hi[p] else -1.0
            bp = hi[p] if sp > 0 else lo[p]
            mu_p = 0.0
            while True:
                it += 1
                if it > max_iter:
                    self.last_failure = "iteration_limit"
                    return None
                if k:
                    Lk = L[:k, :k]
                    low, _ = dtrtrs(Lk, G[W[:k], p], lower=1)
                    coef, _ = dtrtrs(Lk, low, lower=1, trans=1)     # G_WW^-1 G_Wp
                    curv = G[p, p] - low @ low                      # a_p' z, z its part off the set
                    r = sp * S[:k] * coef                           # the held multipliers' rate
                else:
                    curv, r = G[p, p], np.zeros(0)
                t2 = sp * (c[p] - bp) / curv if curv > 1e-12 * G[p, p] else np.inf
                t1, drop = np.inf, -1
                pos = np.flatnonzero(r > 1e-12 * (1.0 + np.max(np.abs(r), initial=0.0)))
                if pos.size:
                    ratios = mu[pos] / r[pos]
                    j = int(np.argmin(ratios))
                    t1, drop = ratios[j], int(pos[j])
                t = min(t1, t2)
                if not np.isfinite(t):
                    self.last_failure = "infeasible"                # the bounds cannot all be met
                    return None
                if np.isfinite(t2):                                 # x -= t sp H^-1 (a_p - A_W' coef)
                    dz = G[:, p] - G[:, W[:k]] @ coef if k else G[:, p]
                    c -= (t * sp) * dz
                if k:
                    mu[:k] = np.maximum(mu[:k] - t * r, 0.0)
                mu_p += t
                if t2 <= t1:                                        # p is met: hold it
                    if k:
                        L[k, :k] = low
                    L[k, k] = np.sqrt(curv)
                    W[k], S[k], mu[k] = p, sp, mu_p
                    in_work[p] = True
                    k += 1
                    break
                # A held row's multiplier reached 0 first: release it and go on towards p.
                in_work[W[drop]] = False
                W[drop:k - 1], S[drop:k - 1], mu[drop:k - 1] = W[drop + 1:k], S[drop + 1:k], mu[drop + 1:k]
                k -= 1
                L[:, :] = 0.0
                if k:
                    L[:k, :k] = np.linalg.cholesky(G[np.ix_(W[:k], W[:k])])
        # The minimum: x again from the working set's equations (the steps' rounding left out).
        work, up = W[:k].copy(), S[:k] > 0
        lam = np.zeros(0)
        x = x_unc
        if k:
            low, _ = dtrtrs(L[:k, :k], c_unc[work] - np.where(up, hi[work], lo[work]), lower=1)
            lam, _ = dtrtrs(L[:k, :k], low, lower=1, trans=1)
            x = x_unc - self._hinv_at[:, work] @ lam
        return QpSolution(x=x, active=work, upper=up, multipliers=np.where(up, lam, -lam), iterations=it)

    def _dual_feasible_start(self, guess, guess_upper, c_unc, lo, hi):
        """The guessed rows that start the working set: (rows, at hi, multipliers ``lambda``, the Cholesky
        factor of ``G`` on them)."""
        none = (np.zeros(0, dtype=int), np.zeros(0, dtype=bool), np.zeros(0), None)
        if guess is None or not len(guess):
            return none
        work = np.asarray(guess, dtype=int)
        upper = np.asarray(guess_upper, dtype=bool)
        keep = np.isfinite(np.where(upper, hi[work], lo[work]))
        work, upper = work[keep], upper[keep]
        for _ in range(3):
            if not work.size:
                return none
            gw = self._G[np.ix_(work, work)]
            try:
                chol = np.linalg.cholesky(gw)
            except np.linalg.LinAlgError:
                return none                        # dependent rows
            if np.min(np.diag(chol)) ** 2 <= 1e-9 * np.max(np.diag(gw)):
                return none
            lam = sla.cho_solve((chol, True), c_unc[work] - np.where(upper, hi[work], lo[work]),
                                check_finite=False)
            signed = np.where(upper, lam, -lam)
            if np.all(signed >= 0):
                return work, upper, lam, chol
            work, upper = work[signed >= 0], upper[signed >= 0]
        return none
