"""ARX estimation, significance tests and delay estimation (multi-input, single-output).

The ARX structure (Ljung, *System Identification: Theory for the User*, 2nd ed., 1999, eq. 4.7;
the paper's eq. 10 to 12) is::

    A(q) y(t) = sum_j B_j(q) u_j(t) + e(t)
    A(q) = 1 + a_1 q^-1 + ... + a_na q^-na
    B_j(q) = q^-nk_j (b_j,0 + b_j,1 q^-1 + ... + b_j,nb-1 q^-(nb-1))      (MATLAB ``arx`` convention)

It is linear in the parameters, so it is fitted by least squares through a QR factorisation of the
regressor matrix (never the normal equations).  The parameter covariance is
``sigma^2 (R'R)^-1``; a linear restriction (some ``B_j`` zero) is tested with the F statistic of
nested least squares (Ljung 1999, section 16.4), whose false-alarm rate is exact for Gaussian white
equation errors and asymptotically valid otherwise.

When several single-output regressions share the same exogenous block of regressors (every row of
S_Delta regresses on the same lagged setpoints, every row of Delta on the same lagged inputs), the
block is factored once (:class:`SharedBlockRegression`) and each row only adds its own few
autoregressive columns.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional, Sequence

import numpy as np

from .statistics import exact_fit_statistic, exact_sigma2, f_tail, f_test

#: Relative threshold on the diagonal of R below which a column is treated as linearly dependent.
RANK_TOLERANCE = 1e-9


def lag_matrix(x: np.ndarray, lags: Sequence[int], start: int) -> np.ndarray:
    """Lagged copies of the columns of ``x``.

    Parameters
    ----------
    x : ndarray, shape (n_samples, n_channels)
    lags : sequence of int
        Lags (samples, >= 0), the same for every channel.
    start : int
        First sample index used (>= max(lags)).

    Returns
    -------
    ndarray, shape (n_samples - start, n_channels * len(lags))
        Column ``c * len(lags) + l`` holds ``x[t - lags[l], c]`` for ``t = start .. n_samples - 1``.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n, m = x.shape
    lags = [int(lag) for lag in lags]
    out = np.empty((n - start, m * len(lags)))
    if lags and n > start and 0 <= lags[0] and lags[-1] <= start and all(b - a == 1 for a, b in zip(lags, lags[1:])):
        # Consecutive lags: out[t, c, l] = x[start - lags[0] + t - l, c] is a strided view of x (rows back by
        # one per lag), copied row after row of out at once, instead of one strided column at a time.
        back = np.lib.stride_tricks.as_strided(x[start - lags[0]:], shape=(n - start, m, len(lags)),
                                               strides=(x.strides[0], x.strides[1], -x.strides[0]), writeable=False)
        out.reshape(n - start, m, len(lags))[...] = back
        return out
    for c in range(m):
        for li, lag in enumerate(lags):
            out[:, c * len(lags) + li] = x[start - lag:n - lag, c]
    return out


def segment_lag_matrix(x: np.ndarray, lags: Sequence[int], start: int, segments=None) -> np.ndarray:
    """:func:`lag_matrix` of every segment of ``x``, stacked: no row's lags reach across a gap.

    Parameters
    ----------
    x : ndarray, shape (n_samples, n_channels) or (n_samples,)
    lags : sequence of int
    start : int
        First sample used in every segment (>= max(lags)).
    segments : sequence of (int, int) or None
        Contiguous runs of rows ``(first, end)`` of ``x`` (data with gaps stacked segment after
        segment); None: ``x`` is one contiguous run (:func:`lag_matrix` itself).

    Returns
    -------
    ndarray, shape (sum of (end - first - start), n_channels * len(lags))
    """
    if segments is None:
        return lag_matrix(x, lags, start)
    return np.vstack([lag_matrix(x[a:b], lags, start) for a, b in segments])


def segment_rows(x: np.ndarray, start: int, segments=None) -> np.ndarray:
    """The regression rows ``x[start:]`` of every segment, stacked (``x[start:]`` when ``segments`` is None)."""
    if segments is None:
        return x[start:]
    return np.concatenate([x[a + start:b] for a, b in segments])


def least_squares_ar(x: np.ndarray, order: int, start: Optional[int] = None) -> np.ndarray:
    """Least-squares AR coefficients of one signal: ``x(k) = a_1 x(k-1) + ... + a_p x(k-p) + e(k)``.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        The signal (centred by the caller if it should be).
    order : int
        ``p`` (>= 0).
    start : int, optional
        First sample ``k`` of the fit (>= ``order``); default ``order`` (every sample with all its
        lags in ``x``).

    Returns
    -------
    ndarray, shape (order,)
        ``a_1 .. a_p`` (``numpy.linalg.lstsq``, so a rank-deficient fit gives the minimum-norm
        solution).
    """
    start = order if start is None else start
    coef, *_ = np.linalg.lstsq(lag_matrix(x, range(1, order + 1), start), x[start:], rcond=None)
    return coef


@dataclasses.dataclass
class ArxFit:
    """An ARX model fitted by least squares.

    Attributes
    ----------
    a : ndarray, shape (na,)
        ``a_1 .. a_na``.
    b : list of ndarray, each shape (nb,)
        ``b_j,0 .. b_j,nb-1`` per input.
    nk : ndarray of int, shape (n_inputs,)
        Delay (samples) of each input.
    theta : ndarray, shape (na + n_inputs * nb,)
        All parameters: ``a`` then each ``b_j``.
    covariance : ndarray, shape (n_params, n_params)
        ``sigma^2 (R'R)^-1``.
    residuals : ndarray, shape (n_used,)
        Equation errors ``e(t)``.
    sigma2 : float
        Residual variance (RSS / degrees of freedom).
    fit_percent : float
        ``100 (1 - ||e|| / ||y - mean(y)||)``, MATLAB's one-step fit.
    condition_number : float
        Of the column-scaled regressor matrix.
    dof : int
        Residual degrees of freedom.
    rank : int
        Numerical rank of the regressor matrix.
    """

    a: np.ndarray
    b: list
    nk: np.ndarray
    theta: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    sigma2: float
    fit_percent: float
    condition_number: float
    dof: int
    rank: int

    def b_block(self, j: int) -> slice:
        """Slice of ``theta`` holding ``b_j``."""
        na = self.a.shape[0]
        nb = self.b[0].shape[0] if self.b else 0
        return slice(na + j * nb, na + (j + 1) * nb)

    def frequency_response(self, omega: np.ndarray) -> np.ndarray:
        """``B_j(e^{jw}) / A(e^{jw})`` for every input, shape (n_freq, n_inputs); omega in rad/sample."""
        omega = np.asarray(omega, dtype=float)
        z1 = np.exp(-1j * omega)
        a_poly = 1.0 + sum(self.a[k] * z1 ** (k + 1) for k in range(self.a.shape[0]))
        out = np.empty((omega.shape[0], len(self.b)), dtype=complex)
        for j, bj in enumerate(self.b):
            bpoly = sum(bj[l] * z1 ** (self.nk[j] + l) for l in range(bj.shape[0]))
            out[:, j] = bpoly / a_poly
        return out


#: A scaled copy of at least this many bytes is factored in place (:func:`_scaled_qr`).
QR_IN_PLACE_BYTES = 32 * 2 ** 20


def _scaled_qr(X: np.ndarray):
    """Economic QR of the column-scaled ``X``; returns (Q, R, scale, rank, condition number).

    ``numpy.linalg.qr`` takes about five copies of ``X`` besides it (1 GB for the 200 MB regressors of a
    long window's confirmation, :data:`~mpm_monitor.core.confirmation.TAIL_FIT_BYTES`).  From
    :data:`QR_IN_PLACE_BYTES` on, the scaled copy is factored in place and becomes ``Q`` (LAPACK's ``geqrf``
    and ``orgqr`` through ``scipy.linalg.qr`` with ``overwrite_a``): one copy.  The two are the same
    Householder QR from two builds of the LAPACK, equal to rounding; below the bound numpy's is kept, so
    the numbers of every window of ordinary length stay as they were.
    """
    scale = np.sqrt(np.sum(X * X, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    if X.nbytes >= QR_IN_PLACE_BYTES and X.shape[0] >= X.shape[1]:
        import scipy.linalg as sla

        Xs = np.empty(X.shape, order="F")
        np.divide(X, scale, out=Xs)
        Q, R = sla.qr(Xs, overwrite_a=True, mode="economic", check_finite=False)
    else:
        Q, R = np.linalg.qr(X / scale, mode="reduced")
    d = np.abs(np.diag(R))
    dmax = d.max(initial=0.0)
    rank = int(np.sum(d > RANK_TOLERANCE * max(dmax, 1e-300)))
    sv = np.linalg.svd(R, compute_uv=False) if R.size else np.array([1.0])
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    return Q, R, scale, rank, cond


def _scaled_r(X: np.ndarray, target: np.ndarray):
    """Like :func:`_scaled_qr` but without forming Q: returns (R, Q' target, scale, rank, condition number).

    The triangular factor of ``[X / scale | target]`` holds ``R`` and ``Q' target`` in its first
    columns (Golub and Van Loan, *Matrix Computations*, 4th ed., section 5.3.3), at half the cost of
    the explicit ``Q``.
    """
    n, p = X.shape
    if n < p + 1:
        Q, R, scale, rank, cond = _scaled_qr(X)
        return R, Q.T @ target, scale, rank, cond
    scale = np.sqrt(np.sum(X * X, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    r_aug = np.linalg.qr(np.column_stack([X / scale, target]), mode="r")
    R, qty = r_aug[:p, :p], r_aug[:p, p]
    d = np.abs(np.diag(R))
    rank = int(np.sum(d > RANK_TOLERANCE * max(d.max(initial=0.0), 1e-300)))
    sv = np.linalg.svd(R, compute_uv=False) if R.size else np.array([1.0])
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    return R, qty, scale, rank, cond


def fit_arx(y: np.ndarray, u: np.ndarray, na: int, nb: int, nk: Sequence[int] | int = 1, segments=None) -> ArxFit:
    """Least-squares ARX fit of one output on several inputs.

    Parameters
    ----------
    y : ndarray, shape (n_samples,)
        Output.
    u : ndarray, shape (n_samples, n_inputs)
        Inputs.
    na, nb : int
        Orders of ``A`` and of every ``B_j`` (na >= 0, nb >= 1).
    nk : int or sequence of int
        Delay of each input in samples (>= 0).
    segments : sequence of (int, int), optional
        Contiguous runs of rows (data with gaps): the rows of every run are stacked, none reaching
        across a gap (:func:`segment_lag_matrix`); default one run.

    Returns
    -------
    ArxFit
    """
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    nu = u.shape[1]
    nk = np.full(nu, int(nk)) if np.isscalar(nk) else np.asarray(nk, dtype=int)
    start = max(na, int(np.max(nk + nb - 1)) if nu else 0)
    cols = [-segment_lag_matrix(y, range(1, na + 1), start, segments)] if na else []
    for j in range(nu):
        cols.append(segment_lag_matrix(u[:, j], range(nk[j], nk[j] + nb), start, segments))
    target = segment_rows(y, start, segments)
    X = np.hstack(cols) if cols else np.zeros((target.shape[0], 0))
    R, qty, scale, rank, cond = _scaled_r(X, target)
    p = X.shape[1]
    # scipy.linalg here, as in the functions below: importing the package does not need it.
    import scipy.linalg as sla

    if rank < p:
        theta_s, *_ = np.linalg.lstsq(R, qty, rcond=None)
        rinv = np.linalg.pinv(R)
    else:
        theta_s = sla.solve_triangular(R, qty)
        rinv = sla.solve_triangular(R, np.eye(p))
    theta = theta_s / scale
    resid = target - X @ theta
    dof = max(target.shape[0] - rank, 1)
    sigma2 = float(resid @ resid) / dof
    cov = sigma2 * (rinv @ rinv.T) / np.outer(scale, scale)
    ynorm = np.linalg.norm(target - target.mean())
    fit = 100.0 * (1.0 - np.linalg.norm(resid) / ynorm) if ynorm > 0 else 0.0
    a = theta[:na]
    b = [theta[na + j * nb: na + (j + 1) * nb] for j in range(nu)]
    return ArxFit(a=a, b=b, nk=nk, theta=theta, covariance=cov, residuals=resid, sigma2=sigma2,
                  fit_percent=float(fit), condition_number=cond, dof=int(dof), rank=rank)


@dataclasses.dataclass
class BlockTest:
    """Result of a Wald/F test that one block of coefficients is zero."""

    statistic: float
    p_value: float
    df_num: int
    df_den: int


class SharedBlockRegression:
    """Least squares of several targets on ``[X_common | X_own(target)]``, factoring ``X_common`` once.

    Parameters
    ----------
    common : ndarray, shape (n_rows, p_common)
        The regressors shared by every target (e.g. lagged setpoints or lagged inputs).
    block_sizes : sequence of int
        Sizes of consecutive column blocks of ``common`` (one per input), for block tests.

    Notes
    -----
    With ``common = Q1 R1`` the fit of a target ``y`` on ``[common | X_own]`` is obtained from the
    projections ``X_own - Q1 Q1' X_own`` and ``y - Q1 Q1' y`` (Frisch-Waugh-Lovell), and the
    triangular factor of the full regressor matrix is
    ``[[R1, Q1' X_own], [0, R2]]`` with ``R2`` from the QR of the projected own columns.
    """

    def __init__(self, common: np.ndarray, block_sizes: Sequence[int]):
        self.common = np.asarray(common, dtype=float)
        self.block_sizes = list(block_sizes)
        if sum(self.block_sizes) != self.common.shape[1]:
            raise ValueError("block sizes must add up to the number of common columns")
        self.Q, self.R, self.scale, self.rank, self.condition_number = _scaled_qr(self.common)
        self.full_rank = self.rank == self.common.shape[1]
        self._rinv = None

    @property
    def n_common(self) -> int:
        """Number of common columns."""
        return self.R.shape[1]

    @functools.cached_property
    def block_starts(self) -> np.ndarray:
        """First column of every block, then the number of common columns; shape (n_blocks + 1,)."""
        return np.cumsum([0] + self.block_sizes)

    def rinv(self) -> np.ndarray:
        """``R^-1`` of the common block (computed once, shared by every target's fit)."""
        if self._rinv is None:
            import scipy.linalg as sla

            p = self.R.shape[1]
            self._rinv = sla.solve_triangular(self.R, np.eye(p)) if self.full_rank else np.linalg.pinv(self.R)
        return self._rinv

    def fit(self, target: np.ndarray, own: np.ndarray | None):
        """Fit one target; returns a :class:`SharedFit`."""
        return SharedFit(self, np.asarray(target, dtype=float), None if own is None else np.asarray(own, dtype=float))


def block_triangular_solution(reg: SharedBlockRegression, qo: np.ndarray, R2: np.ndarray, qy: np.ndarray):
    """Triangular factor, rank and inverse of ``[[R1, qo], [0, R2]]`` and the scaled solution.

    Parameters
    ----------
    reg : SharedBlockRegression
        Holds ``R1`` (the common block's factor) and its inverse.
    qo : ndarray, shape (p_common, p_own)
        ``Q1' X_own`` (scaled own columns).
    R2 : ndarray, shape (p_own, p_own)
        Triangular factor of the own columns after projection off the common block.
    qy : ndarray, shape (p_common + p_own,)
        ``[Q1' y; Q2' y]``.

    Returns
    -------
    rank : int
    rinv : ndarray, shape (p, p)
        ``R^-1`` (pseudo-inverse when rank-deficient); with a full-rank ``R`` it is assembled from
        the shared ``R1^-1`` as ``[[R1^-1, -R1^-1 qo R2^-1], [0, R2^-1]]``.
    theta_s : ndarray, shape (p,)
        Coefficients of the scaled columns, ``R^-1 qy``.
    """
    pc, po = qo.shape
    p = pc + po
    d = np.abs(np.concatenate([np.diag(reg.R), np.diag(R2)]))
    rank = int(np.sum(d > RANK_TOLERANCE * max(d.max(initial=0.0), 1e-300)))
    if rank < p:
        R = np.zeros((p, p))
        R[:pc, :pc] = reg.R
        R[:pc, pc:] = qo
        R[pc:, pc:] = R2
        rinv = np.linalg.pinv(R)
    else:
        import scipy.linalg as sla

        r1i = reg.rinv()
        r2i = sla.solve_triangular(R2, np.eye(po)) if po else np.zeros((0, 0))
        rinv = np.zeros((p, p))
        rinv[:pc, :pc] = r1i
        rinv[pc:, pc:] = r2i
        if po:
            rinv[:pc, pc:] = -(r1i @ qo) @ r2i
    return rank, rinv, rinv @ qy


class SharedFit:
    """The fit of one target in a :class:`SharedBlockRegression` (see there).

    Its tests decide outright when the fit is exact (a log without noise): set the spread of the
    target's output with :meth:`set_output_spread` (:func:`~mpm_monitor.core.statistics.exact_fit_statistic`).
    """

    #: Residual variance at or below which the fit is exact, target units squared (:meth:`set_output_spread`;
    #: 0: only a residual of exactly 0).
    exact_sigma2 = 0.0

    def set_output_spread(self, spread: float) -> None:
        """Count the fit as exact when its residual's standard deviation is at most
        :data:`~mpm_monitor.core.statistics.EXACT_FIT` times ``spread`` (the output's standard deviation,
        output units): the rounding of an exact fit, not noise."""
        self.exact_sigma2 = exact_sigma2(spread)

    @property
    def exact_floor(self) -> float:
        """Residual sum of squares at or below which the fit is exact: ``dof * exact_sigma2``."""
        return self.dof * self.exact_sigma2

    @property
    def exact(self) -> bool:
        """Whether the fit is exact (its residual is rounding, not noise)."""
        return self.rss <= self.exact_floor

    def __init__(self, reg: SharedBlockRegression, y: np.ndarray, own: np.ndarray | None):
        self.reg = reg
        n = y.shape[0]
        Q = reg.Q
        pc = reg.common.shape[1]
        if own is None or own.shape[1] == 0:
            own = np.zeros((n, 0))
        po = own.shape[1]
        own_scale = np.sqrt(np.sum(own * own, axis=0))
        own_scale = np.where(own_scale > 0, own_scale, 1.0)
        own_s = own / own_scale
        qo = Q.T @ own_s                      # (pc, po)
        own_perp = own_s - Q @ qo
        if po:
            Q2, R2 = np.linalg.qr(own_perp, mode="reduced")
        else:
            Q2, R2 = np.zeros((n, 0)), np.zeros((0, 0))
        qy = np.concatenate([Q.T @ y, Q2.T @ y])
        self.rank, self.rinv, theta_s = block_triangular_solution(reg, qo, R2, qy)
        scale = np.concatenate([reg.scale, own_scale])
        self.theta = theta_s / scale
        self.scale = scale
        resid = y - reg.common @ self.theta[:pc] - own @ self.theta[pc:]
        self.residuals = resid
        self.rss = float(resid @ resid)
        self.dof = max(n - self.rank, 1)
        self.sigma2 = self.rss / self.dof
        self.n_common = pc
        # RSS of the target on its own columns only (every common coefficient zero).
        if po:
            th_own, *_ = np.linalg.lstsq(own_s, y, rcond=None)
            r0 = y - own_s @ th_own
            self.rss_own_only = float(r0 @ r0)
            self.rank_own = int(np.linalg.matrix_rank(own_s))
            self._own_only = th_own / own_scale
        else:
            self.rss_own_only = float(y @ y)
            self.rank_own = 0
            self._own_only = np.zeros(0)
        ynorm = np.linalg.norm(y - y.mean())
        self.fit_percent = 100.0 * (1.0 - np.sqrt(self.rss) / ynorm) if ynorm > 0 else 0.0

    def covariance_scaled(self) -> np.ndarray:
        """``(R'R)^-1`` in the scaled parameters (multiply by sigma2 and 1/scale for theta)."""
        return self.rinv @ self.rinv.T

    def covariance_block(self, idx: np.ndarray) -> np.ndarray:
        """Rows and columns ``idx`` of :meth:`covariance_scaled`, without forming the whole matrix."""
        return self.covariance_blocks(np.asarray(idx, dtype=int)[None, :])[0]

    def covariance_blocks(self, idx: np.ndarray) -> np.ndarray:
        """:meth:`covariance_block` of every row of ``idx`` (shape (g, k)); shape (g, k, k)."""
        ri = self.rinv[idx]
        return ri @ np.swapaxes(ri, 1, 2)

    def common_variances(self) -> np.ndarray:
        """Diagonal of :meth:`covariance_scaled` over the common columns, shape (p_common,)."""
        ri = self.rinv[:self.n_common]
        return np.einsum("ij,ij->i", ri, ri)

    def block_index(self, block: int, n_first: Optional[int] = None) -> np.ndarray:
        """Indices in the fit's parameters of block ``block``'s coefficients (its first ``n_first`` only, if given)."""
        starts = self.reg.block_starts
        end = starts[block + 1] if n_first is None else min(starts[block] + n_first, starts[block + 1])
        return np.arange(starts[block], end)

    def test_all_common_zero(self) -> BlockTest:
        """F test that every common coefficient is zero (e.g. the S_Delta row equals the identity)."""
        df_num = self.rank - self.rank_own
        f, p = f_test(self.rss_own_only, self.rss, df_num, self.dof, self.exact_floor)
        return BlockTest(f, p, int(df_num), int(self.dof))

    def test_blocks_zero(self, blocks: Sequence[int], n_first: Optional[int] = None) -> BlockTest:
        """Wald F test that the common coefficients of the given blocks are all zero.

        For least squares the Wald statistic ``theta_S' [cov_SS]^-1 theta_S / |S|`` equals the F
        statistic of the nested fit without those columns.  With ``n_first`` only the first
        ``n_first`` coefficients of each block are tested (the others stay free in the fit).
        """
        idx = np.concatenate([self.block_index(b, n_first) for b in blocks]) if blocks else np.array([], int)
        if idx.size == 0:
            return BlockTest(float("nan"), 1.0, 0, int(self.dof))
        return self._wald_tests(idx[None, :])[0]

    def test_each_block_zero(self, n_first: Sequence[Optional[int]]) -> list:
        """``[test_blocks_zero([b], n_first=n_first[b]) for every block b]``, computed together.

        Blocks whose tested coefficients are equally many share one stacked eigen-decomposition.
        """
        idx = [self.block_index(b, k) for b, k in enumerate(n_first)]
        out = [BlockTest(float("nan"), 1.0, 0, int(self.dof))] * len(idx)
        for k in sorted({i.size for i in idx} - {0}):
            blocks = [b for b, i in enumerate(idx) if i.size == k]
            for b, t in zip(blocks, self._wald_tests(np.stack([idx[b] for b in blocks]))):
                out[b] = t
        return out

    def _wald_tests(self, idx: np.ndarray) -> list:
        """Rank-aware Wald F tests that the coefficients of every row of ``idx`` (shape (g, k)) are zero.

        A block inside a collinear group has a near-singular covariance: its quadratic form keeps
        only the eigen-directions above ``1e-10`` of the largest.
        """
        th = (self.theta * self.scale)[idx]           # scaled parameters, (g, k)
        cov = self.covariance_blocks(idx)
        w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
        keep = w > 1e-10 * np.maximum(w.max(axis=1, initial=0.0), 1e-300)[:, None]
        df_num = keep.sum(axis=1)
        proj = np.einsum("gkm,gk->gm", v, th)
        quad = np.sum(np.where(keep, proj ** 2 / np.where(keep, w, 1.0), 0.0), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):    # a row fitted exactly (no noise): sigma2 0
            f = quad / np.maximum(df_num, 1) / self.sigma2
        f = np.where(np.isnan(f), 0.0, f)           # 0 / 0: nothing to explain, F 0 (p 1); q / 0: F inf (p 0)
        f = exact_fit_statistic(f, self.rss + quad, self.rss, self.exact_floor)     # the same for rounding
        p = f_tail(f, np.maximum(df_num, 1), self.dof)
        dof = int(self.dof)
        return [BlockTest(float(f[g]), float(p[g]), int(df_num[g]), dof) if df_num[g] else
                BlockTest(float("nan"), 1.0, 0, dof) for g in range(idx.shape[0])]

    def block_theta(self, block: int) -> np.ndarray:
        """Common coefficients of one block."""
        starts = self.reg.block_starts
        return self.theta[starts[block]:starts[block + 1]]

    def block_std(self, block: int) -> np.ndarray:
        """Standard errors of the coefficients of one block."""
        idx = self.block_index(block)
        cov = self.covariance_block(idx) * self.sigma2
        return np.sqrt(np.maximum(np.diag(cov), 0.0)) / self.scale[idx]

    def block_stds(self) -> list:
        """``[block_std(b) for every block b]``, from the diagonal of the covariance alone."""
        std = np.sqrt(np.maximum(self.common_variances() * self.sigma2, 0.0)) / self.scale[:self.n_common]
        starts = self.reg.block_starts
        return [std[starts[b]:starts[b + 1]] for b in range(len(starts) - 1)]

    def own_theta(self) -> np.ndarray:
        """Coefficients of the target's own columns."""
        return self.theta[self.n_common:]

    def own_only_theta(self) -> np.ndarray:
        """Coefficients of the target on its own columns alone (every common coefficient zero), shape (p_own,)."""
        return self._own_only

    def own_covariance_scaled(self) -> np.ndarray:
        """The own columns' block of :meth:`covariance_scaled`, shape (p_own, p_own)."""
        ri = self.rinv[self.n_common:]
        return ri @ ri.T

    def own_standard_errors(self) -> np.ndarray:
        """Standard errors of :meth:`own_theta`, shape (p_own,) (NaN where the fit left no residual to
        measure them against)."""
        var = np.diag(self.own_covariance_scaled()) * self.sigma2
        return np.sqrt(np.maximum(var, 0.0)) / self.scale[self.n_common:]


def estimate_delay_from_lags(coef: np.ndarray, std: np.ndarray, nb: int, first_lag: int) -> int:
    """Delay (samples) of one input from a long-lag fit, as MATLAB's ``delayest`` intends.

    Picks the start of the window of ``nb`` consecutive lags with the largest sum of squared
    t-statistics, i.e. the delay whose short B polynomial explains most of the output.

    Parameters
    ----------
    coef, std : ndarray, shape (n_lags,)
        Coefficients of lags ``first_lag .. first_lag + n_lags - 1`` and their standard errors.
    nb : int
        Window length.
    first_lag : int
        Lag of ``coef[0]``.
    """
    t2 = np.where(std > 0, (coef / np.where(std > 0, std, 1.0)) ** 2, 0.0)
    n = t2.shape[0]
    if n <= nb:
        return int(first_lag)
    window = np.convolve(t2, np.ones(nb), mode="valid")
    return int(first_lag + int(np.argmax(window)))


def estimate_delays(y: np.ndarray, u: np.ndarray, na: int, nb: int, max_delay: int, min_delay: int = 0) -> np.ndarray:
    """Delay of every input (``delayest`` for a multi-input ARX).

    Fits one ARX with B polynomials covering lags ``min_delay .. max_delay + nb - 1`` and, for each
    input, picks the window of ``nb`` lags that explains most (:func:`estimate_delay_from_lags`).

    Parameters
    ----------
    y : ndarray, shape (n_samples,)
    u : ndarray, shape (n_samples, n_inputs)
    na, nb : int
    max_delay : int
        Largest delay searched (samples).
    min_delay : int
        Smallest delay searched (samples).

    Returns
    -------
    ndarray of int, shape (n_inputs,)
    """
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    n_lags = max_delay - min_delay + nb
    fit = fit_arx(y, u, na, n_lags, nk=min_delay)
    out = []
    for j in range(u.shape[1]):
        sl = fit.b_block(j)
        std = np.sqrt(np.maximum(np.diag(fit.covariance)[sl], 0.0))
        out.append(estimate_delay_from_lags(fit.theta[sl], std, nb, min_delay))
    return np.array(out, dtype=int)
