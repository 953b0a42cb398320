"""Unexplained disturbance test of a residual: a level shift (sup-Wald) or a linear drift (Wald).

Both run in a regression with AR(p) terms that absorb the coloured noise; see
:func:`unexplained_disturbance`.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..arx import lag_matrix
from ..statistics import EXACT_FIT, chi2_tail


def sup_wald_p_value(statistic: float, trim: float) -> float:
    """Approximate p-value of the sup-Wald statistic of one break in the mean.

    Parameters
    ----------
    statistic : float
        ``sup_pi W(pi)`` over break fractions ``pi`` in ``[trim, 1 - trim]``.
    trim : float
        Trimming fraction.

    Notes
    -----
    Asymptotically ``W(pi) -> B(pi)^2 / (pi (1 - pi))`` with ``B`` a Brownian bridge (Andrews,
    *Econometrica* 61, 1993).  The tail ``P(sup > c)`` is approximated by
    ``sqrt(c) e^{-c/2} / sqrt(2 pi) [(1 - 1/c) ln(lambda) + 4/c]`` with
    ``lambda = (1 - trim)^2 / trim^2`` (Estrella, *Econometric Theory* 19, 2003).  The
    approximation is slightly conservative: 0.054 at Andrews' 5 % value 8.68, 0.011 at the 1 %
    value 12.16 for ``trim = 0.15``.
    """
    c = float(statistic)
    if not math.isfinite(c):
        return 0.0
    if c <= 1.0:
        return 1.0
    lam = (1.0 - trim) ** 2 / trim ** 2
    p = math.sqrt(c) * math.exp(-c / 2.0) / math.sqrt(2.0 * math.pi) * ((1.0 - 1.0 / c) * math.log(lam) + 4.0 / c)
    return float(min(1.0, max(0.0, p)))



def _row_quadratic_forms(q: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``q[i] @ a @ q[i]`` of every row ``i`` of ``q`` (shape (n, k); ``a`` shape (k, k)).

    The sum of ``(q[i, j] a[j, l]) q[i, l]`` over ``j``, then ``l``, from 0: the terms and their order
    of ``np.einsum("ij,jk,ik->i", q, a, q)`` (the same numbers), a column pair at a time over
    contiguous columns (about 3 times faster for ``k = 5``).
    """
    qt = np.ascontiguousarray(q.T)
    out = np.zeros(q.shape[0])
    for j in range(q.shape[1]):
        for col, a_jl in zip(qt, a[j]):
            out += qt[j] * a_jl * col
    return out


def _break_rows(lo: int, hi: int, n: int, trim: float, windowed: bool) -> Optional[np.ndarray]:
    """The rows ``k`` of the breaks searched in the rows ``lo .. hi - 1`` of a regression of ``n`` rows (shape
    (n_breaks,), maybe empty), trimmed by ``trim`` at both ends; ``windowed`` (one of several levels), also never
    in the record's first or last ``trim``, and None when that leaves no break.  The caller drops the breaks whose
    step column the other regressors explain (:func:`_step_wald`)."""
    m = hi - lo
    k_lo, k_hi = lo + int(math.ceil(trim * m)), lo + int(math.floor((1 - trim) * m))
    if windowed:           # and never at the record's ends (its initial transient, the last rows)
        k_lo, k_hi = max(k_lo, int(math.ceil(trim * n))), min(k_hi, int(math.floor((1 - trim) * n)))
        if k_hi <= k_lo:
            return None
    ks = np.arange(max(k_lo, 1), max(k_hi, k_lo + 1))
    return ks[ks < n]


def _step_wald(X: np.ndarray, yv: np.ndarray, trim: float, windows=None):
    """The largest Wald statistic of a level shift in ``yv = X b + c 1(row >= k) + e`` over ``k``.

    Breaks are searched from ``trim`` to ``1 - trim`` of the rows (with ``windows``, of the rows of each
    window and of all the rows); the statistic of every break is computed at once by Frisch-Waugh with
    cumulative sums.

    Parameters
    ----------
    X : ndarray, shape (n_rows, n_regressors)
        The offset and AR columns.
    yv : ndarray, shape (n_rows,)
    trim : float
    windows : sequence of (int, int), optional
        Row ranges ``(first, end)`` searched each on its own (the rows of one level, whose offset is a column
        of ``X``); default all the rows as one.

    Returns
    -------
    (statistic, break row, SSR with the step) or None when no break can be estimated; with ``windows``, a
    list of them, one per window (None for a window without a break to estimate).
    """
    n = yv.shape[0]
    xtx_inv = np.linalg.pinv(X.T @ X)
    beta = xtx_inv @ (X.T @ yv)
    e = yv - X @ beta
    ssr0 = float(e @ e)
    # For every break k, regressor s_k = 1(row >= k).
    q = np.cumsum(X[::-1], axis=0)[::-1]            # q[k] = sum_{t>=k} X[t]
    se = np.cumsum(e[::-1])[::-1]                    # sum_{t>=k} e[t]
    cnt = n - np.arange(n, dtype=float)
    denom = cnt - _row_quadratic_forms(q, xtx_inv)
    dof = n - X.shape[1] - 1

    def best(lo: int, hi: int):
        ks = _break_rows(lo, hi, n, trim, windows is not None)
        if ks is None:
            return None
        ks = ks[denom[ks] > 1e-9 * cnt[ks]]
        if ks.size == 0:
            return None
        num = se[ks] ** 2 / denom[ks]
        s2 = (ssr0 - num) / dof
        wald = num / np.maximum(s2, 1e-300)
        top = int(np.argmax(wald))
        return float(wald[top]), int(ks[top]), ssr0 - float(num[top])

    if windows is None:
        return best(0, n)
    return [best(int(a), int(b)) for a, b in windows]


def _drift_wald(X: np.ndarray, yv: np.ndarray):
    """Wald statistic of a linear trend added to the regressors ``X`` of ``yv``, and the SSR with it."""
    n = yv.shape[0]
    tcol = np.arange(n, dtype=float) / n
    X2 = np.column_stack([X, tcol])
    beta2, *_ = np.linalg.lstsq(X2, yv, rcond=None)
    e2 = yv - X2 @ beta2
    ssr_drift = float(e2 @ e2)
    cov2 = np.linalg.pinv(X2.T @ X2) * ssr_drift / (n - X2.shape[1])
    w_drift = float(beta2[-1] ** 2 / cov2[-1, -1]) if cov2[-1, -1] > 0 else 0.0
    return w_drift, ssr_drift


#: Simulated records of the calibration of the disturbance tests (:meth:`_Design.null_scale`).
NULL_DRAWS = 200

#: AR order of the calibration's noise model (:meth:`_Design.null_scale`), at most: the tests' own AR(p) (4 by
#: default) leaves a slow drift under white measurement noise coloured (``d = v + w``, ``v`` an AR(1) of pole
#: 0.95 whose spread is below ``w``'s: an ARMA(1, 1) of zero near 0.77, whose AR inverse needs 15 or more lags),
#: and a step test on such a residual reported a step in 15 % of 200 records at alpha 0.01 when its calibration
#: simulated the AR(4) it fitted.  It also simulates an AR of this order (of ``rows / 50`` lags on a shorter
#: record; none when that is not above ``p``), so that the scale holds what ``p`` lags leave, and takes the larger
#: of the two scales: near a unit root the longer AR, fitted on the same record, is the less persistent (the
#: paper's noise at pole 0.99: 7 of 400 records reported with its scale alone, 5 with the AR(p)'s).
NULL_NOISE_ORDER = 32

#: The calibration's AR noise model is kept inside this spectral radius (a fitted unit or explosive root
#: is moved in, radially).
MAX_NOISE_RADIUS = 0.999
#: The simulated records of :meth:`_Design.null_scale` are drawn, filtered and tested this many bytes of
#: innovations at a time (whole batches of records): 200 records of 100,000 samples held at once took three arrays
#: of 153 MiB.  The same numbers as drawing them all at once (the generator's stream is the same).
NULL_RECORD_BYTES = 32 * 2 ** 20


def _p_values(w_step: float, w_drift: float, searched: int, trim: float) -> tuple:
    """The step and drift tests' p-values, each Bonferroni-adjusted for the two tests (and the step's for the
    ``searched`` levels)."""
    return (min(1.0, 2.0 * searched * sup_wald_p_value(w_step, trim)),
            min(1.0, 2.0 * float(chi2_tail(w_drift, 1))))


class _Design:
    """The rows of the disturbance tests' regressions on a standardised residual: where they are and how
    they are grouped (one record, or segments sharing levels), so that a simulated record of the same
    length is tested exactly as the residual is.

    Attributes
    ----------
    p : int
        AR order.
    index : ndarray of int or None
        With segments, the sample of the residual of every row (None: rows ``p .. n - 1``).
    kept : list of (int, int, int) or None
        With segments, ``(first, end, level)`` of the segments long enough for a row.
    """

    def __init__(self, p: int, index, kept):
        self.p, self.index, self.kept = p, index, kept

    @classmethod
    def of(cls, dz: np.ndarray, p: int, segments, levels) -> Optional["_Design"]:
        """The design of ``dz`` (shape (n,)); None when no segment is long enough for a row."""
        if segments is None:
            return cls(p, None, None)
        level_of = list(range(len(segments))) if levels is None else [int(x) for x in levels]
        kept = [(int(a), int(b), lev) for (a, b), lev in zip(segments, level_of) if b - a > p + 1]
        if not kept:
            return None
        return cls(p, np.concatenate([np.arange(a + p, b) for a, b, _ in kept]), kept)

    def rows(self, n: int) -> int:
        """The number of regression rows of a record of ``n`` samples."""
        return n - self.p if self.index is None else int(self.index.shape[0])

    def row_samples(self, n: int) -> np.ndarray:
        """The sample of a record of ``n`` samples that every regression row explains (shape (n_rows,))."""
        return np.arange(self.p, n) if self.index is None else self.index

    def with_order(self, q: int) -> Optional["_Design"]:
        """The design of the same record and segments (and levels) with ``q`` AR terms; None when no segment is
        long enough for a row."""
        if self.index is None:
            return _Design(q, None, None)
        return _Design.of(None, q, [(a, b) for a, b, _ in self.kept], [lev for _, _, lev in self.kept])

    def regression(self, dz: np.ndarray) -> tuple:
        """``(yv, X, windows)``: the rows (shape (n_rows,)), the offset and AR columns (shape (n_rows, levels +
        p)), and the row ranges of the levels searched each on its own (None: one record)."""
        p = self.p
        if self.index is None:
            yv, lags = dz[p:], lag_matrix(dz, range(1, p + 1), p)
            return yv, np.column_stack([np.ones(yv.shape[0]), lags]), None
        yv = dz[self.index]
        lags = np.vstack([lag_matrix(dz[a:b], range(1, p + 1), p) for a, b, _ in self.kept])
        offsets, windows = self._levels()
        return yv, np.column_stack([offsets, lags]), windows

    def _levels(self) -> tuple:
        """``(offsets, windows)`` of a design with segments: the offset columns of the rows (shape (n_rows,
        levels)) and the row ranges of the levels (:meth:`regression`)."""
        p = self.p
        names = list(dict.fromkeys(lev for _, _, lev in self.kept))
        offsets = np.zeros((self.index.shape[0], len(names)))
        at = 0
        for a, b, lev in self.kept:
            offsets[at:at + b - a - p, names.index(lev)] = 1.0
            at += b - a - p
        edges = np.cumsum([0] + [int(np.sum(offsets[:, k])) for k in range(len(names))])
        return offsets, list(zip(edges[:-1], edges[1:]))

    def batch_statistics(self, Z: np.ndarray, trim: float, kind: str) -> np.ndarray:
        """The ``kind`` ("step" or "drift") statistic of every record of ``Z``, each tested as :meth:`statistics`
        tests one residual: the step's largest Wald statistic over its breaks (0 where no break can be
        estimated), or the drift's Wald statistic.

        The records' regressions are stacked and solved together (their normal equations, the step's breaks by
        the cumulative sums of :func:`_step_wald`): the statistics of :meth:`statistics` up to rounding, without
        a Python loop over the records.

        Parameters
        ----------
        Z : ndarray, shape (n_records, n)
            Standardised records of the residual's length.
        trim : float
        kind : {"step", "drift"}

        Returns
        -------
        ndarray, shape (n_records,)
        """
        p, (m, n) = self.p, Z.shape
        rows = np.arange(p, n) if self.index is None else self.index
        offsets, windows = (np.ones((rows.shape[0], 1)), None) if self.index is None else self._levels()
        n_rows, n_off = offsets.shape
        k = n_off + p + (1 if kind == "drift" else 0)
        Xt = np.empty((m, k, n_rows))                                  # the regressors, a record's in rows
        Xt[:, :n_off] = offsets.T
        for lag in range(1, p + 1):
            Xt[:, n_off + lag - 1] = Z[:, p - lag:n - lag] if self.index is None else Z[:, rows - lag]
        if kind == "drift":
            Xt[:, -1] = np.arange(n_rows, dtype=float) / n_rows
        yv = Z[:, p:] if self.index is None else Z[:, rows]
        # G+ = T T' (the pseudo-inverse of the normal matrix G, its eigenvalues below 1e-15 of the largest dropped, as
        # numpy.linalg.pinv drops them); W = T' X' are the regressors whitened: the fit is W' (W y).
        w, V = np.linalg.eigh(Xt @ Xt.transpose(0, 2, 1))
        keep = w > 1e-15 * w[:, -1:]
        T = V * np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)[:, None, :]
        Wt = T.transpose(0, 2, 1) @ Xt
        c = Wt @ yv[:, :, None]
        e = yv - (Wt.transpose(0, 2, 1) @ c)[:, :, 0]
        ssr = np.einsum("ij,ij->i", e, e)
        if kind == "drift":
            var = np.einsum("ij,ij->i", T[:, -1], T[:, -1]) * ssr / (n_rows - k)     # G+[-1, -1] times sigma^2
            slope = (T[:, -1:] @ c)[:, 0, 0]
            out = np.zeros(m)
            ok = var > 0
            out[ok] = slope[ok] ** 2 / var[ok]
            return out
        # The step 1(row >= j): its part the regressors explain has norm^2 |sum_{t>=j} W_t|^2 (of every break j).
        qw = np.cumsum(Wt[:, :, ::-1], axis=2)[:, :, ::-1]
        cnt = n_rows - np.arange(n_rows, dtype=float)
        denom = cnt - np.einsum("ikj,ikj->ij", qw, qw)
        se = np.cumsum(e[:, ::-1], axis=1)[:, ::-1]
        dof = n_rows - k - 1
        out = np.full(m, -np.inf)
        for lo, hi in ([(0, n_rows)] if windows is None else windows):
            ks = _break_rows(int(lo), int(hi), n_rows, trim, windows is not None)
            if ks is None or ks.size == 0:
                continue
            den = denom[:, ks]
            ok = den > 1e-9 * cnt[ks]
            num = np.where(ok, se[:, ks] ** 2 / np.where(ok, den, 1.0), 0.0)
            wald = num / np.maximum((ssr[:, None] - num) / dof, 1e-300)
            out = np.maximum(out, np.where(ok, wald, -np.inf).max(axis=1))
        return np.where(np.isfinite(out), out, 0.0)

    @staticmethod
    def _step(X: np.ndarray, yv: np.ndarray, windows, trim: float) -> Optional[tuple]:
        """``(step Wald, break row, SSR with the step, levels searched)`` of the regression ``(yv, X, windows)``
        (:meth:`regression`), or None when no break can be estimated."""
        if windows is None:
            step, searched = _step_wald(X, yv, trim), 1
        else:
            # Each level is searched on its own, trimmed at both of its ends (its first samples follow a restart
            # of the model, whose settled start still carries what the initial-state estimate missed), and the
            # smallest p-value is Bonferroni-adjusted over the levels searched.
            found = [w for w in _step_wald(X, yv, trim, windows) if w is not None]
            step, searched = (max(found, key=lambda w: w[0]) if found else None), len(found)
        return None if step is None else step + (searched,)

    def statistics(self, dz: np.ndarray, trim: float) -> Optional[tuple]:
        """``((step Wald, break row, SSR with the step, levels searched), (drift Wald, SSR with the drift))`` of
        ``dz``, or None when no break can be estimated."""
        yv, X, windows = self.regression(dz)
        step = self._step(X, yv, windows, trim)
        return None if step is None else (step, _drift_wald(X, yv))

    def null_scale(self, dz: np.ndarray, trim: float, draws: int, rng: np.random.Generator,
                   alternative: Optional[np.ndarray] = None, kind: str = "step", order: Optional[int] = None) -> float:
        """How much larger the ``kind`` ("step" or "drift") statistic reads on the residual's own noise than on
        white noise, for records of this design: its scale, at least 1.

        The noise is an AR(q) (``q = order``, at least the tests' own ``p``; default ``p``) fitted as the tests'
        regression with ``q`` lags and the ``alternative`` column added (the step found, for the step test's
        scale; the trend, for the drift test's): without it a real step or drift passes for persistence and the
        scale takes the power away (on the paper's noise at pole 0.99, 38 of 200 steps of two standard
        deviations reported against 75 with it; with both columns at once the level doubled).  Its spectral
        radius is kept within :data:`MAX_NOISE_RADIUS`.  ``draws`` records of the residual's length are
        simulated from it (from its stationary state: a burn-in of 5 / (1 - radius) samples) and, with the same
        innovations, as white noise; both are tested as the residual is, with ``p`` lags.  A scale is the ratio
        of the mean statistics (common random numbers: the ratio is far less noisy than either mean).  With
        ``q > p`` the scale also holds what ``p`` lags leave coloured (a slow drift under white measurement
        noise, an ARMA whose AR inverse is long: :data:`NULL_NOISE_ORDER`).

        Parameters
        ----------
        dz : ndarray, shape (n,)
            The standardised residual.
        trim : float
        draws : int
        rng : numpy.random.Generator
        alternative : ndarray, shape (n_rows,), optional
            A column of the regression's rows fitted with the AR terms (and then dropped); with ``q > p`` its
            values on the rows of the ``q``-lag regression (the same samples).
        kind : {"step", "drift"}
            The statistic scaled (only it is computed on the simulated records).
        order : int, optional
            ``q``, the AR order of the simulated noise (default and at least ``p``).  Where no segment is long
            enough for ``q`` lags, ``p``.

        Returns
        -------
        float

        Notes
        -----
        Near a unit root the tests' statistics grow by a factor that is the same across their quantiles (on
        AR(1) noise plus white noise, 3,000 samples: about 1.08 at pole 0.95, 1.3 at 0.99, 1.5 at 0.995, from
        the median to the 99.5 % point), so dividing by the factor restores the asymptotic tail.
        """
        from ..filters import lfilter

        p = self.p
        n = dz.shape[0]
        fit = self
        if order is not None and int(order) > p:
            fit = self.with_order(int(order))
            if fit is None or fit.rows(n) <= fit.p + 3:
                fit = self
        q = fit.p
        yv, X, _ = fit.regression(dz)
        if alternative is not None and fit is not self:      # the same samples' values, on the q-lag rows
            alternative = np.asarray(alternative)[np.searchsorted(self.row_samples(n), fit.row_samples(n))]
        Xa = X if alternative is None else np.column_stack([X, alternative])
        beta, *_ = np.linalg.lstsq(Xa, yv, rcond=None)
        a = np.asarray(beta[X.shape[1] - q:X.shape[1]], dtype=float)
        radius = 0.0
        if q:
            companion = np.zeros((q, q))
            companion[0] = a
            companion[1:, :-1] = np.eye(q - 1)
            radius = float(np.max(np.abs(np.linalg.eigvals(companion))))
            if radius > MAX_NOISE_RADIUS:
                a = a * (MAX_NOISE_RADIUS / radius) ** np.arange(1, q + 1)
                radius = MAX_NOISE_RADIUS
        burn = int(math.ceil(5.0 / (1.0 - radius))) if q else 0
        draws = int(draws)
        sums = np.zeros(2)
        # Records a batch: their stacked regressions' largest array about 8 MB.
        batch = max(1, int(1_000_000 // (self.rows(n) * (p + 3 + (0 if self.kept is None else len(self.kept))))))
        # Records drawn at a time: whole batches, NULL_RECORD_BYTES of innovations (all of them when they fit).
        chunk = batch * max(1, NULL_RECORD_BYTES // (8 * batch * (burn + n)))
        for done in range(0, draws, chunk):
            e = rng.standard_normal((min(chunk, draws - done), burn + n))
            coloured = lfilter([1.0], np.concatenate([[1.0], -a]), e, axis=1)[:, burn:] if q else e[:, burn:]
            white = e[:, burn:]
            for row, Z in enumerate((coloured, white)):
                mean, std = Z.mean(axis=1, keepdims=True), Z.std(axis=1, keepdims=True)
                if row == 0 and not q:            # the white records are the same memory, still to be read
                    Z = Z - mean
                else:                             # standardised in place: read no more as they were
                    Z -= mean
                Z /= std
                for first in range(0, Z.shape[0], batch):      # each sum in the order of the records
                    for value in self.batch_statistics(Z[first:first + batch], trim, kind):
                        sums[row] += value
            del e, coloured, white, Z
        if not sums[1] > 0:
            return 1.0
        return max(1.0, float(sums[0] / sums[1]))


def null_noise_order(p: int, rows: int) -> int:
    """The AR order of the calibration's noise model: :data:`NULL_NOISE_ORDER`, or ``rows / 50`` on a shorter
    record, at least the tests' own ``p``."""
    return max(int(p), min(NULL_NOISE_ORDER, int(rows) // 50))


def not_tested() -> dict:
    """What :func:`unexplained_disturbance` returns for a signal it does not test (too short, not finite, fitted
    exactly; ``tested`` false) or, with ``tested`` true and its p-values, one in which it finds nothing: no
    disturbance detected."""
    return {"detected": False, "kind": None, "size": 0.0, "time": None, "index": None, "rate": None, "p_value": 1.0,
            "p_step": 1.0, "p_drift": 1.0, "statistic": 0.0, "tested": False, "null_scale_step": 1.0,
            "null_scale_drift": 1.0, "calibrated": False}


def unexplained_disturbance(d: np.ndarray, sample_time: float = 1.0, alpha: float = 0.01, trim: float = 0.15,
                            noise_order: int = 4, segments=None, scale: Optional[float] = None,
                            levels=None, calibrate: bool = False, draws: int = NULL_DRAWS,
                            rng: Optional[np.random.Generator] = None) -> dict:
    """Test one residual for a step or a linear drift on top of AR(p)-coloured noise.

    Parameters
    ----------
    d : ndarray, shape (n_samples,)
        The prediction error of one output (output units).
    sample_time : float
        Seconds per sample, for the reported time and rate.
    alpha : float
        False-alarm probability of the combined test; each of the two tests runs at ``alpha / 2``.
    trim : float
        Fraction of the record at each end where no step is searched.
    noise_order : int
        Order ``p`` of the AR terms.
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs ``(first, end)`` of the samples of ``d``.  The AR terms
        then never reach across a gap and every segment has its own offset (a step is searched
        inside the segments; ``time`` counts the samples of ``d``, not the missing ones).
    levels : sequence of int, optional
        With ``segments``, the level of each segment (non-decreasing): segments of one level share
        their offset (the model runs through the short gaps between them,
        :attr:`~mpm_monitor.core.repair.record._Record.levels`).  A step is searched inside each level,
        trimmed at both of its ends by ``trim`` (and never in the record's first or last ``trim``, as
        without gaps), and the smallest of the levels' p-values is Bonferroni-adjusted over the levels
        searched.  Default: every segment a level of its own.
    scale : float, optional
        The spread of the signal ``d`` is the error of (the output's standard deviation, output
        units): a ``d`` whose standard deviation is below :data:`EXACT_FIT` times it is not tested.
    calibrate : bool
        When either test would report at ``alpha`` on its asymptotic p-value, scale both statistics by
        what they read on ``draws`` simulated records of the fitted AR(p) noise (:meth:`_Design.null_scale`)
        before taking their p-values: with slow noise the asymptotic tails are too light (on the paper's
        noise, pole 0.95, each test at 0.5 % fires on about 0.75 % of records; at pole 0.99 the step test
        on 2.2 %).  For a test those scales still leave reporting, the records of a longer fitted AR
        (:func:`null_noise_order`, :data:`NULL_NOISE_ORDER`) are tested too and the larger scale taken: what the
        AR(p) terms leave coloured (a drift under white measurement noise) is scaled out as well.  Default
        False: the asymptotic p-values, as before.
    draws : int
        Simulated records of the calibration (``calibrate``).
    rng : numpy.random.Generator, optional
        The calibration's random numbers; default a generator seeded with 0 (the same ``d`` gives the
        same result).

    Returns
    -------
    dict
        ``detected`` (bool), ``kind`` ("step", "drift" or None), ``size`` (output units: the step
        height, or the drift over the whole record), ``time`` (s, the step instant or None),
        ``index`` (the sample of ``d`` where the step starts, or None),
        ``rate`` (output units per second, drift only), ``p_value`` (the smaller of the two tests,
        Bonferroni-adjusted), ``p_step``, ``p_drift``, ``statistic`` (of the reported kind), ``tested``
        (False: the signal was not tested, see :func:`not_tested`), ``null_scale_step`` and
        ``null_scale_drift`` (the calibration's scales of the two statistics, 1 without it), ``calibrated``
        (``calibrate`` was asked for: the p-values are confirmed ones wherever the asymptotic ones would report).

    Notes
    -----
    Step: in ``d(k) = c0 + c1 1(k >= k_b) + sum_l a_l d(k-l) + e(k)`` the Wald statistic of
    ``c1 = 0`` is computed for every break ``k_b`` at once (Frisch-Waugh with cumulative sums)
    and its supremum tested with :func:`sup_wald_p_value`.  Drift: the Wald statistic of ``c1`` in
    ``d(k) = c0 + c1 k + sum_l a_l d(k-l) + e(k)`` against chi-square(1).  The AR terms absorb the
    coloured disturbance, so a slowly wandering but stationary disturbance is not reported.

    With slow noise both statistics are larger than their asymptotic laws say, by a factor that hardly
    depends on the quantile; ``calibrate`` measures it on records of the fitted noise
    (:meth:`_Design.null_scale`) and divides it out, which brings the tests back to their level.

    The regressions run on ``d`` centred and scaled to unit spread (the statistics do not change; a
    residual far from zero, or in very large or small units, would leave ``[1, lags of d]``
    numerically singular).  The reported sizes are in the units of ``d``.
    """
    d = np.asarray(d, float).ravel()
    p = int(noise_order)
    n_all = d.shape[0]
    out = not_tested()
    if n_all < max(50, 10 * (p + 3)) or not np.all(np.isfinite(d)):
        return out
    spread = float(np.std(d))
    if not spread > 0 or (scale is not None and spread <= EXACT_FIT * float(scale)):
        return out
    dz = (d - float(np.mean(d))) / spread
    design = _Design.of(dz, p, segments, levels)
    if design is None:
        return out
    index, kept = design.index, design.kept
    found = design.statistics(dz, trim)
    if found is None:
        return out
    (w_step, k_step, ssr_step, searched), (w_drift, ssr_drift) = found
    scale_step = scale_drift = 1.0
    p_step, p_drift = _p_values(w_step, w_drift, searched, trim)
    if calibrate and min(p_step, p_drift) < alpha and draws > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        rows = np.arange(design.rows(dz.shape[0]), dtype=float)
        step_column, trend = (rows >= k_step).astype(float), rows / rows.shape[0]
        scale_step = design.null_scale(dz, trim, draws, rng, step_column, "step")
        scale_drift = design.null_scale(dz, trim, draws, rng, trend, "drift")
        order = null_noise_order(p, rows.shape[0])
        # And on the longer AR's records (NULL_NOISE_ORDER), the larger scale of the two: only for a test that the
        # AR(p)'s scale still leaves reporting, since a larger scale can only take a report away (the decisions
        # are the same; a test that does not report keeps the p-value of the AR(p)'s scale).
        if order > p:
            still = [x < alpha for x in _p_values(w_step / scale_step, w_drift / scale_drift, searched, trim)]
            if still[0]:
                scale_step = max(scale_step, design.null_scale(dz, trim, draws, rng, step_column, "step", order))
            if still[1]:
                scale_drift = max(scale_drift, design.null_scale(dz, trim, draws, rng, trend, "drift", order))
        p_step, p_drift = _p_values(w_step / scale_step, w_drift / scale_drift, searched, trim)
    out.update(p_step=p_step, p_drift=p_drift, p_value=min(p_step, p_drift), tested=True,
               null_scale_step=scale_step, null_scale_drift=scale_drift, calibrated=bool(calibrate))
    step_hit, drift_hit = p_step < alpha, p_drift < alpha
    if not (step_hit or drift_hit):
        return out
    kb = k_step + p if index is None else int(index[k_step])  # index into d
    if step_hit and (not drift_hit or ssr_step <= ssr_drift):
        if index is None:
            size = float(np.mean(d[kb:]) - np.mean(d[:kb]))
        else:                     # within the step's level (the segments sharing its offset)
            lev = next(lev for a, b, lev in kept if a + p <= kb < b)
            same = [(a, b) for a, b, other in kept if other == lev]
            before = np.concatenate([d[a:min(b, kb)] for a, b in same if a < kb])
            after = np.concatenate([d[max(a, kb):b] for a, b in same if b > kb])
            size = float(np.mean(after) - np.mean(before))
        out.update(detected=True, kind="step", size=size, time=kb * sample_time, index=kb, p_value=p_step,
                   statistic=w_step)
    else:
        # Size from an ordinary straight line through d: what an engineer would draw.
        slope = float(np.polyfit(np.arange(n_all, dtype=float), d, 1)[0])
        out.update(detected=True, kind="drift", size=slope * n_all, rate=slope / sample_time,
                   p_value=p_drift, statistic=w_drift)
    return out
