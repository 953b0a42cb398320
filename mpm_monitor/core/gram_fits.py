"""Least-squares fits solved from Gram matrices, each with a check of its condition number.

The Gram path of the tests' regressions (:class:`mpm_monitor.core.regressions.GramRegressions`) solves
its shared blocks (:class:`GramBlockRegression`), the rows' fits that extend them (:class:`GramFit`) and
the short ARX tables (:func:`gram_arx`) here, and raises :class:`IllConditioned` for a regression it
must refit by QR.

Columns are scaled to unit norm as in the QR path; the Cholesky factor of the scaled Gram matrix
is the triangular factor of the QR factorisation of the scaled regressors (up to the signs of its
rows, which no result depends on).  Normal equations square the condition number: relative errors
are of the order ``kappa^2 * 1e-16``.  Each regression's 2-norm condition number ``kappa`` is checked
-- first against the cheap bound ``||R||_F ||R^-1||_F >= kappa``, then, if that bound is too large,
for a fit that extends a shared block by its own lags, against the bound from the shared block's
2-norms (estimated once per regression) and the own columns' Frobenius norms, and last by a
power-iteration estimate of the whole factor (:func:`checked_condition`) -- and above ``max_condition`` (default
1e3, errors below about 1e-10) the regression is refitted by QR from the window's signals.  A fit
that explains nearly all of its target (noise-free data) is refitted too: its residual sum of
squares ``y'y - |Q'y|^2`` would lose digits (:data:`MIN_RESIDUAL_PER_CONDITION`).  Closed-loop data
with PRBS setpoints give ``kappa`` of 2 to 60 (measured on the paper cases and on random 2x2 to
20x20 plants); collinear inputs (no dither, more inputs than outputs) fall back.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import scipy.linalg as sla
from scipy.linalg import blas

from .arx import RANK_TOLERANCE, ArxFit, SharedBlockRegression, SharedFit

#: Largest condition number of the scaled regressors for which a regression is solved from its Gram
#: matrix: the normal equations then lose at most about 1e6 * 1e-16 = 1e-10 (relative).
DEFAULT_MAX_CONDITION = 1e3


class IllConditioned(ArithmeticError):
    """A regression too ill-conditioned to be solved from its Gram matrix (the caller refits by QR)."""


def _frobenius(a: np.ndarray) -> float:
    return float(np.sqrt(np.sum(a * a)))


def _trmv(t: np.ndarray, x: np.ndarray, trans: bool) -> np.ndarray:
    """``t x`` (``t' x`` with ``trans``) of an upper triangular ``t`` (BLAS ``dtrmv``: half the reads of a product)."""
    if t.shape[0] == 0:                           # BLAS refuses an empty vector
        return np.zeros(0)
    if t.flags.f_contiguous:
        return blas.dtrmv(t, x, lower=0, trans=int(trans))
    if t.flags.c_contiguous:                      # t' is a Fortran-ordered lower triangle
        return blas.dtrmv(t.T, x, lower=1, trans=int(not trans))
    return blas.dtrmv(np.asfortranarray(t), x, lower=0, trans=int(trans))


def _norm2_estimate(a, iterations: int = 12) -> float:
    """Largest singular value of an upper triangular matrix by power iteration (a lower estimate,
    usually within a few %).

    Parameters
    ----------
    a : ndarray, shape (p, p), or tuple (A, B, C)
        The upper triangular matrix, or its blocks ``[[A, B], [0, C]]`` with ``A`` (k, k) and ``C``
        (p - k, p - k) upper triangular and ``B`` (k, p - k) dense (so that a factor partitioned as
        :class:`GramFit` keeps it need not be assembled).
    iterations : int
    """
    A, B, C = (a, None, None) if isinstance(a, np.ndarray) else a
    k = A.shape[0]
    split = B is not None and B.shape[1] > 0

    def apply(x):
        if not split:
            return _trmv(A, x, False)
        return np.concatenate([_trmv(A, x[:k], False) + B @ x[k:], _trmv(C, x[k:], False)])

    def apply_t(y):
        if not split:
            return _trmv(A, y, True)
        return np.concatenate([_trmv(A, y[:k], True), B.T @ y[:k] + _trmv(C, y[k:], True)])

    p = k + (B.shape[1] if split else 0)
    x = np.linspace(1.0, 2.0, p)
    x /= np.linalg.norm(x)
    for _ in range(iterations):
        x = apply_t(apply(x))
        nx = np.linalg.norm(x)
        if not nx > 0:
            return 0.0
        x /= nx
    return float(np.linalg.norm(apply(x)))


def checked_condition(R, rinv, max_condition: float, frobenius_R: Optional[float] = None,
                      frobenius_rinv: Optional[float] = None, block_bound=None, norms=None) -> float:
    """Condition number of the triangular factor ``R``, or :class:`IllConditioned` above ``max_condition``.

    Returns the Frobenius bound ``||R||_F ||R^-1||_F`` when it is within the limit (it is never below
    the 2-norm condition number); else ``block_bound()`` when given and within the limit; else a
    power-iteration estimate of the 2-norm condition number.
    ``R`` and ``rinv`` may be callables that build them (only needed for the estimate) when their
    Frobenius norms are given; either may be given as the blocks of :func:`_norm2_estimate`.

    Parameters
    ----------
    block_bound : callable, optional
        ``() -> float``: a bound of the 2-norm condition number cheaper than the estimate (a
        :class:`GramFit`'s from its shared block, :meth:`GramBlockRegression.norm2_estimates`).
    norms : callable, optional
        ``() -> (||R||_2, ||R^-1||_2)`` estimates already at hand (cached), used instead of estimating
        them here.
    """
    if frobenius_rinv is None:
        rinv = rinv() if callable(rinv) else rinv
        if rinv.size == 0:
            return 1.0
        frobenius_rinv = _frobenius(rinv)
    bound = (_frobenius(R) if frobenius_R is None else frobenius_R) * frobenius_rinv
    if bound <= max_condition:
        return bound
    if block_bound is not None:
        bound = block_bound()
        if bound <= max_condition:
            return bound
    if norms is not None:
        norm_R, norm_rinv = norms()
        estimate = norm_R * norm_rinv
    else:
        R = R() if callable(R) else R
        rinv = rinv() if callable(rinv) else rinv
        estimate = _norm2_estimate(R) * _norm2_estimate(rinv)
    if estimate <= max_condition:
        return estimate
    raise IllConditioned(f"condition number {estimate:.3g} > {max_condition:.3g}")


def _cholesky_upper(g: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.cholesky(g).T
    except np.linalg.LinAlgError:
        raise IllConditioned("Gram matrix not positive definite") from None


def _stacked_gram(a: np.ndarray) -> np.ndarray:
    """``a a'`` of every matrix of the stack ``a`` (shape (g, k, m)); shape (g, k, k)."""
    return a @ np.swapaxes(a, 1, 2)


class GramBlockRegression(SharedBlockRegression):
    """A :class:`~mpm_monitor.core.arx.SharedBlockRegression` built from the Gram matrix of its columns.

    Parameters
    ----------
    gram : ndarray, shape (p, p)
        ``X' X`` of the common columns (centred as the batch path centres them).
    block_sizes : sequence of int
    max_condition : float
        Largest accepted condition number of the scaled columns (:func:`checked_condition`).

    Raises
    ------
    IllConditioned
        When the bound is exceeded or the matrix is not positive definite.

    Notes
    -----
    ``Q`` and ``common`` are not available (None); targets are fitted by :class:`GramFit`.  The
    common block's share of every fit's covariance (``R1^-1 R1^-T``, its diagonal and its diagonal
    blocks) is computed once here and shared by the fits.
    """

    def __init__(self, gram: np.ndarray, block_sizes, max_condition: float = DEFAULT_MAX_CONDITION):
        self.common = None
        self.Q = None
        self.block_sizes = list(block_sizes)
        p = gram.shape[0]
        if sum(self.block_sizes) != p:
            raise ValueError("block sizes must add up to the number of common columns")
        scale = np.sqrt(np.maximum(np.diag(gram), 0.0))
        self.scale = np.where(scale > 0, scale, 1.0)
        self.R = _cholesky_upper(gram / np.outer(self.scale, self.scale)) if p else np.zeros((0, 0))
        d = np.abs(np.diag(self.R))
        self.rank = int(np.sum(d > RANK_TOLERANCE * max(d.max(initial=0.0), 1e-300)))
        self.full_rank = self.rank == p
        if not self.full_rank:
            raise IllConditioned("rank-deficient common block")
        self._rinv = sla.solve_triangular(self.R, np.eye(p), check_finite=False) if p else np.zeros((0, 0))
        self.frobenius_R = _frobenius(self.R)
        self.variances = np.einsum("ij,ij->i", self._rinv, self._rinv)       # diagonal of R1^-1 R1^-T
        self.frobenius_rinv = math.sqrt(float(self.variances.sum()))
        self._norms = None
        self.condition_bound = checked_condition(self.R, self._rinv, max_condition, self.frobenius_R,
                                                 self.frobenius_rinv, norms=lambda: self.norm2_estimates) if p else 1.0
        self._cond = None
        self._blocks = {}

    @property
    def norm2_estimates(self) -> tuple:
        """``(||R1||_2, ||R1^-1||_2)`` by power iteration (:func:`_norm2_estimate`), computed once and
        shared by the fits (their block bound, :class:`GramFit`)."""
        if self._norms is None:
            self._norms = (_norm2_estimate(self.R), _norm2_estimate(self._rinv))
        return self._norms

    @property
    def condition_number(self) -> float:
        """2-norm condition number of the scaled common columns (as the batch path reports it)."""
        if self._cond is None:
            sv = np.linalg.svd(self.R, compute_uv=False) if self.R.size else np.array([1.0])
            self._cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
        return self._cond

    def covariance_blocks(self, idx: np.ndarray) -> np.ndarray:
        """Rows and columns ``idx[g]`` of ``R1^-1 R1^-T`` for every ``g``; shape (g, k, k) (cached)."""
        key = (idx.shape, idx.tobytes())
        if key not in self._blocks:
            self._blocks[key] = _stacked_gram(self._rinv[idx])
        return self._blocks[key]

    def projections(self, rhs: np.ndarray) -> tuple:
        """``R1^-T rhs`` and ``R1^-1 R1^-T rhs``: the products of fits with the shared block (:class:`GramFit`),
        for the right-hand sides of any number of fits at once.

        Two triangular solves, each one pass over ``R1`` for all the columns (instead of three passes
        over ``R1`` and ``R1^-1`` for each fit); every column's result is the one it has when solved
        alone, whichever columns are solved with it (a product with ``R1^-1`` would round the last
        columns of a block differently).

        Parameters
        ----------
        rhs : ndarray, shape (p_common, k)
            Cross products of the scaled common columns with ``k`` scaled columns
            (:meth:`GramFit.common_rhs`, side by side).

        Returns
        -------
        q, w : ndarray, shape (p_common, k)
            ``R1^-T rhs`` and ``R1^-1 q``.
        """
        if not rhs.size:
            return np.zeros(rhs.shape), np.zeros(rhs.shape)
        q = sla.solve_triangular(self.R, rhs, trans="T", check_finite=False)
        return q, sla.solve_triangular(self.R, q, check_finite=False)

    def fit(self, target, own):
        raise TypeError("a GramBlockRegression has no regressor matrix: fit targets with GramFit")


#: A fit solved from cross products computes its residual sum of squares as ``y'y - |Q'y|^2``, which
#: loses up to about ``1e-16 * kappa * y'y / RSS`` (relative) when the regressors explain nearly all of
#: ``y`` (noise-free data); the fit is refitted by QR when that bound exceeds 1e-8, i.e. when
#: ``RSS < MIN_RESIDUAL_PER_CONDITION * kappa * y'y`` (``kappa``: the condition bound).
MIN_RESIDUAL_PER_CONDITION = 1e-8


class GramFit(SharedFit):
    """The fit of one target in a :class:`GramBlockRegression`, from cross products only.

    Parameters
    ----------
    reg : GramBlockRegression
    g_co : ndarray, shape (p_common, p_own)
        Cross products of the common and the own columns.
    g_oo : ndarray, shape (p_own, p_own)
    g_cy : ndarray, shape (p_common,)
    g_oy : ndarray, shape (p_own,)
    g_yy : float
        Cross products with the target ``y``.
    sum_y : float
        Sum of the target over the regression rows.
    n : int
        Number of regression rows.
    max_condition : float
    common : tuple of ndarray, optional
        ``reg.projections(GramFit.common_rhs(reg, g_co, g_oo, g_cy))``, both of shape (p_common, p_own + 1),
        when solved together with other fits'
        (:meth:`~mpm_monitor.core.regressions.GramRegressions.row_fits`); default: solved here, with
        products by ``R1^-1``.

    Raises
    ------
    IllConditioned
        When the condition bound exceeds ``max_condition``, or the target is explained so closely
        that its residual sum of squares cannot be taken from the cross products
        (:data:`MIN_RESIDUAL_PER_CONDITION`).

    Notes
    -----
    The quantities of :class:`~mpm_monitor.core.arx.SharedFit` follow from the partitioned factor
    ``[[R1, Q1' X_own], [0, R2]]``: ``Q1' X_own = R1^-T X_c' X_own``, ``R2' R2 = X_own' X_own -
    (Q1' X_own)' (Q1' X_own)``, ``Q1' y = R1^-T X_c' y``, ``Q2' y = R2^-T (X_own' y - (Q1' X_own)' Q1' y)``
    and ``RSS = y'y - ||[Q1' y; Q2' y]||^2``.  ``residuals`` is None.  The inverse factor
    ``[[R1^-1, W], [0, R2^-1]]`` with ``W = -R1^-1 (Q1' X_own) R2^-1`` is kept in these pieces; the
    covariance of common coefficients is the regression's shared ``R1^-1 R1^-T`` plus ``W W'``.
    """

    @staticmethod
    def own_scale(g_oo: np.ndarray) -> np.ndarray:
        """Norms of the own columns (1 for a zero column), shape (p_own,)."""
        scale = np.sqrt(np.maximum(np.diag(g_oo), 0.0))
        return np.where(scale > 0, scale, 1.0)

    @staticmethod
    def common_rhs(reg: GramBlockRegression, g_co: np.ndarray, g_oo: np.ndarray, g_cy: np.ndarray) -> np.ndarray:
        """``[X_c' X_own | X_c' y]`` of the scaled columns, shape (p_common, p_own + 1): the right-hand sides
        of the fit's solves with the shared block (:meth:`GramBlockRegression.projections`)."""
        return np.column_stack([g_co / np.outer(reg.scale, GramFit.own_scale(g_oo)), g_cy / reg.scale])

    def __init__(self, reg: GramBlockRegression, g_co, g_oo, g_cy, g_oy, g_yy: float, sum_y: float, n: int,
                 max_condition: float = DEFAULT_MAX_CONDITION, common: Optional[tuple] = None):
        self.reg = reg
        pc, po = g_co.shape
        p = pc + po
        own_scale = self.own_scale(g_oo)
        g_oo_s = g_oo / np.outer(own_scale, own_scale)
        g_oy_s = g_oy / own_scale
        if common is None:
            q = sla.solve_triangular(reg.R, self.common_rhs(reg, g_co, g_oo, g_cy), trans="T",
                                     check_finite=False) if pc else np.zeros((0, po + 1))
            w = None
        else:
            q, w = common
        qo, q1y = q[:, :po], q[:, po]                                 # Q1' X_own, Q1' y
        if po:
            R2 = _cholesky_upper(g_oo_s - qo.T @ qo)
            q2y = sla.solve_triangular(R2, g_oy_s - qo.T @ q1y, trans="T", check_finite=False)
            r2i = sla.solve_triangular(R2, np.eye(po), check_finite=False)
        else:
            R2, q2y, r2i = np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0))
        d = np.abs(np.concatenate([np.diag(reg.R), np.diag(R2)]))
        self.rank = int(np.sum(d > RANK_TOLERANCE * max(d.max(initial=0.0), 1e-300)))
        if self.rank < p:
            raise IllConditioned("rank-deficient regression")
        r1i = reg.rinv()
        w_o, w_y = (r1i @ qo, r1i @ q1y) if w is None else (w[:, :po], w[:, po])    # R1^-1 Q1'X_own, R1^-1 Q1'y
        self._qo, self._R2, self._r2i = qo, R2, r2i
        self._w = -w_o @ r2i                                          # block (common, own) of R^-1
        self._rinv = None
        theta_own = r2i @ q2y
        theta_s = np.concatenate([w_y + self._w @ q2y, theta_own])
        own_R = float(np.sum(qo * qo)) + float(np.sum(R2 * R2))            # ||[Q1'X_own; R2]||_F^2
        own_rinv = float(np.sum(self._w * self._w)) + float(np.sum(r2i * r2i))    # ||[W; R2^-1]||_F^2
        frobenius_R = math.sqrt(reg.frobenius_R ** 2 + own_R)
        frobenius_rinv = math.sqrt(reg.frobenius_rinv ** 2 + own_rinv)

        def block_bound():
            # ||[A B]||_2^2 <= ||A||_2^2 + ||B||_F^2 for R = [[R1, Q1'X_own], [0, R2]] split into its common
            # and own columns, and the same for R^-1: the shared block's estimates (once per regression)
            # with the own columns' exact Frobenius norms.
            norm_R1, norm_r1i = reg.norm2_estimates if pc else (0.0, 0.0)
            return math.sqrt(norm_R1 ** 2 + own_R) * math.sqrt(norm_r1i ** 2 + own_rinv)

        self.condition_bound = checked_condition((reg.R, qo, R2), lambda: (r1i, self._w, r2i), max_condition,
                                                 frobenius_R, frobenius_rinv, block_bound) if p else 1.0
        scale = np.concatenate([reg.scale, own_scale])
        self.theta = theta_s / scale
        self.scale = scale
        self.residuals = None
        qy = np.concatenate([q1y, q2y])
        self.rss = max(float(g_yy - qy @ qy), 0.0)
        if self.rss < MIN_RESIDUAL_PER_CONDITION * self.condition_bound * g_yy:
            raise IllConditioned(f"residual sum of squares {self.rss:.3g} too small against y'y = {g_yy:.3g}")
        self.dof = max(n - self.rank, 1)
        self.sigma2 = self.rss / self.dof
        self.n_common = pc
        if po:
            Ro = _cholesky_upper(g_oo_s)
            qoy = sla.solve_triangular(Ro, g_oy_s, trans="T", check_finite=False)
            self.rss_own_only = max(float(g_yy - qoy @ qoy), 0.0)
            self.rank_own = po
            self._own_only_factor = (Ro, qoy, own_scale)
        else:
            self.rss_own_only = float(g_yy)
            self.rank_own = 0
            self._own_only_factor = None
        ynorm2 = float(g_yy - sum_y * sum_y / n) if n else 0.0
        self.fit_percent = 100.0 * (1.0 - math.sqrt(self.rss / ynorm2)) if ynorm2 > 0 else 0.0

    @property
    def rinv(self) -> np.ndarray:
        """``R^-1`` of the whole regression, shape (p, p) (assembled on first use)."""
        if self._rinv is None:
            pc, po = self._w.shape
            rinv = np.zeros((pc + po, pc + po))
            rinv[:pc, :pc], rinv[:pc, pc:], rinv[pc:, pc:] = self.reg.rinv(), self._w, self._r2i
            self._rinv = rinv
        return self._rinv

    def own_only_theta(self) -> np.ndarray:
        if self._own_only_factor is None:
            return np.zeros(0)
        Ro, qoy, own_scale = self._own_only_factor
        return sla.solve_triangular(Ro, qoy, check_finite=False) / own_scale

    def own_covariance_scaled(self) -> np.ndarray:
        return self._r2i @ self._r2i.T

    def covariance_blocks(self, idx: np.ndarray) -> np.ndarray:
        if idx.size and idx.max() < self.n_common:
            return self.reg.covariance_blocks(idx) + _stacked_gram(self._w[idx])
        return super().covariance_blocks(idx)

    def common_variances(self) -> np.ndarray:
        return self.reg.variances + np.einsum("ij,ij->i", self._w, self._w)


def gram_arx(gram: np.ndarray, sum_y: float, n: int, na: int, nb: int, nk: np.ndarray,
             max_condition: float = DEFAULT_MAX_CONDITION, condition: bool = True) -> ArxFit:
    """:func:`mpm_monitor.core.arx.fit_arx` from the cross products of its columns.

    Parameters
    ----------
    gram : ndarray, shape (p + 1, p + 1)
        Cross products of ``[-y(t-1) .. -y(t-na), u_1(t-nk_1) .. u_1(t-nk_1-nb+1), ..., y(t)]`` over
        the fit's rows (the regressors of :func:`~mpm_monitor.core.arx.fit_arx`, then the target).
    sum_y : float
        Sum of the target over the rows.
    n : int
        Number of rows.
    na, nb : int
    nk : ndarray of int, shape (n_columns,)
    max_condition : float
    condition : bool
        False: ``condition_number`` is not computed (NaN; it takes an SVD of the factor).

    Returns
    -------
    ArxFit
        With ``residuals`` None.

    Raises
    ------
    IllConditioned
    """
    p = gram.shape[0] - 1
    g, gy, g_yy = gram[:p, :p], gram[:p, p], float(gram[p, p])
    scale = np.sqrt(np.maximum(np.diag(g), 0.0))
    scale = np.where(scale > 0, scale, 1.0)
    R = _cholesky_upper(g / np.outer(scale, scale))
    d = np.abs(np.diag(R))
    rank = int(np.sum(d > RANK_TOLERANCE * max(d.max(initial=0.0), 1e-300)))
    if rank < p:
        raise IllConditioned("rank-deficient ARX regression")
    rinv = sla.solve_triangular(R, np.eye(p), check_finite=False)
    checked_condition(R, rinv, max_condition)
    qy = sla.solve_triangular(R, gy / scale, trans="T", check_finite=False)
    theta = (rinv @ qy) / scale
    rss = max(g_yy - float(qy @ qy), 0.0)
    dof = max(n - rank, 1)
    sigma2 = rss / dof
    cov = sigma2 * (rinv @ rinv.T) / np.outer(scale, scale)
    ynorm2 = g_yy - sum_y * sum_y / n
    fit = 100.0 * (1.0 - math.sqrt(rss / ynorm2)) if ynorm2 > 0 else 0.0
    cond = float("nan")
    if condition:
        sv = np.linalg.svd(R, compute_uv=False)
        cond = float(sv[0] / sv[-1])
    nu = nk.shape[0]
    return ArxFit(a=theta[:na], b=[theta[na + j * nb: na + (j + 1) * nb] for j in range(nu)], nk=nk, theta=theta,
                  covariance=cov, residuals=None, sigma2=float(sigma2), fit_percent=float(fit),
                  condition_number=cond, dof=int(dof), rank=rank)
