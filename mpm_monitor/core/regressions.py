"""The least-squares problems of the two tests, by QR or from the Gram matrices of lagged signals.

Both tests are single-output ARX regressions over the same window (:class:`RegressionLayout`):

* S_Delta row test (:mod:`mpm_monitor.core.row_test`): for every output ``i``, ``z_i = eps_i - r_i``
  on the setpoints ``r_c(t - l)``, ``l = 0 .. n_lag_r - 1``, and its own lags ``z_i(t - l)``,
  ``l = 1 .. na``;
* Delta element test (:mod:`mpm_monitor.core.element_test`): for every output ``i``, the prediction
  error ``d_i`` on the model's columns ``u_j(t - l)``, ``l = 1 .. n_lag_u`` (the inputs, then the
  measured disturbances: every signal called ``u`` below has one column per model column), and its
  own lags.

Every row's regression shares its large block (lagged setpoints or lagged inputs) with the other
rows, so that block is factored once per window and each row adds its own columns by the
Frisch-Waugh-Lovell partition of :class:`~mpm_monitor.core.arx.SharedBlockRegression`.  Two
providers of these fits have the same methods (``row_regression``, ``row_fit``, ``row_fits``,
``input_regression``, ``element_fit``, ``short_arx``):

* :class:`QrRegressions` builds the lagged regressor matrices and factors them by QR: the
  reference path;
* :class:`GramRegressions` solves them from cross-product (Gram) matrices of the lagged signals
  (:class:`LaggedGram`), ``O(p^3)`` per analysis whatever the number of samples, and refits by QR
  every regression too ill-conditioned for the normal equations.  The batch analysis builds them
  for its window at once (:func:`window_regressions`); the sliding-window analyzer
  (:mod:`mpm_monitor.core.sliding`) keeps them up to date sample by sample.

Gram matrices
-------------
A Gram matrix built from scratch uses the shift structure of lagged columns
(:func:`lagged_cross_products`): ``O(W n_channels^2 n_lags)`` instead of ``O(W p^2)`` for ``W`` rows
and ``p`` columns.  The tests centre each signal by its mean over the window.  With ``X`` the raw
lagged columns, ``s = X' 1`` their sums over the ``N`` regression rows and ``m`` the window means,
the centred cross products are ``X'X - s m' - m s' + N m m'`` (:meth:`LaggedGram.centred`).  To keep
that subtraction harmless the raw columns are stored relative to a reference ``ref`` (the window
means when the matrix was last built), so ``m - ref`` stays of the order of the signals' spread.

Solving and accuracy
--------------------
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

import dataclasses
import math
from typing import Optional

import numpy as np
import scipy.linalg as sla
from scipy.linalg import blas

from .arx import RANK_TOLERANCE, ArxFit, SharedBlockRegression, SharedFit, fit_arx, segment_lag_matrix, segment_rows
from .logged_data import moving_columns
from .model import PlantModel
from .parallel import split_map
from .segments import as_segments

#: Largest condition number of the scaled regressors for which a regression is solved from its Gram
#: matrix: the normal equations then lose at most about 1e6 * 1e-16 = 1e-10 (relative).
DEFAULT_MAX_CONDITION = 1e3
#: Rows of a Gram matrix mirrored at once by :func:`lagged_cross_products` (its entries below the lag
#: diagonal from those above; bounds the temporaries to a few MB at any size).
MIRROR_ROWS = 64


class IllConditioned(ArithmeticError):
    """A regression too ill-conditioned to be solved from its Gram matrix (the caller refits by QR)."""


# ----------------------------------------------------------------------------------------- layout
def _minimum_samples(n_params: int) -> int:
    return 3 * n_params + 50


@dataclasses.dataclass(frozen=True)
class RegressionLayout:
    """Lags and first usable sample of the tests, fixed by the model and the options.

    Attributes
    ----------
    max_delay : int
        Largest dead time searched (samples).
    n_lag_r : int
        Setpoint lags ``0 .. n_lag_r - 1`` of the row test.
    n_lag_u : int
        Column lags ``1 .. n_lag_u`` of the element test (inputs and measured disturbances).
    start : int
        First sample of the window used as a regression row (every lag is inside the window).
    min_samples : int
        Fewest samples the tests accept.
    """

    max_delay: int
    n_lag_r: int
    n_lag_u: int
    start: int
    min_samples: int


def regression_layout(model: PlantModel, options) -> RegressionLayout:
    """The :class:`RegressionLayout` of the tests for this model and these options.

    Parameters
    ----------
    model : PlantModel
    options : AnalysisOptions
        Its ``na``, ``nb`` and ``max_delay`` (:class:`mpm_monitor.core.analysis.AnalysisOptions`).

    Returns
    -------
    RegressionLayout
        ``max_delay`` defaults to the model's largest delay + 5 samples, at least 10.
    """
    ny, nu, na, nb = model.n_outputs, model.n_columns, options.na, options.nb
    dmax_model = int(model.delay_samples.max(initial=0))
    max_delay = options.max_delay if options.max_delay is not None else max(10, dmax_model + 5)
    n_lag_r = max_delay + nb + 1            # setpoint lags 0 .. max_delay + nb
    n_lag_u = max_delay + nb                # input lags 1 .. max_delay + nb
    n_params = max(ny * n_lag_r, nu * n_lag_u) + na
    return RegressionLayout(max_delay=max_delay, n_lag_r=n_lag_r, n_lag_u=n_lag_u,
                            start=max(n_lag_r - 1, n_lag_u, na), min_samples=_minimum_samples(n_params))


# ----------------------------------------------------------------------------------------- QR
class QrRegressions:
    """The least-squares problems of the tests, built from the window's signals and factored by QR.

    This is the reference path, and the fallback of the default one: the analysis solves the tests
    from the Gram matrices of the window (:func:`window_regressions`) and refits by this class every
    regression too ill-conditioned for the normal equations.  Pass an instance as
    ``analyze(..., regressions=...)`` (:func:`mpm_monitor.core.pipeline.analyze`) to factor every
    regression by QR.

    Parameters
    ----------
    r, z, d : ndarray, shape (n_samples, n_outputs)
        Setpoints, ``z = eps - r`` and prediction errors of the window.
    u : ndarray, shape (n_samples, n_columns)
        The model's columns: plant inputs, then measured disturbances.
    layout : RegressionLayout
    na, nb : int
        ARX orders.
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows ``(first, end)`` of the signals, stacked one after
        the other; every run gives its own regression rows ``first + start .. end - 1``, so that no
        row's lags reach across a gap (docs/interfaces.md, "Gaps").  Default: one run.
    """

    def __init__(self, r, u, z, d, layout: RegressionLayout, na: int, nb: int, segments=None):
        self.r, self.u, self.z, self.d = r, u, z, d
        self.layout, self.na, self.nb = layout, na, nb
        self.segments = as_segments(segments)
        self._u_c = u - u.mean(axis=0)

    def _lags(self, x, lags) -> np.ndarray:
        return segment_lag_matrix(x, lags, self.layout.start, self.segments)

    @property
    def n_rows(self) -> int:
        """Regression rows (of every segment)."""
        start, n = self.layout.start, self.r.shape[0]
        return n - start if self.segments is None else sum(b - a - start for a, b in self.segments)

    def row_regression(self, r_moving: list) -> SharedBlockRegression:
        """Setpoint lags ``0 .. n_lag_r - 1`` of the moving setpoints (S_Delta row test)."""
        r, lay = self.r, self.layout
        r_c = r - r.mean(axis=0)
        Xr = self._lags(r_c[:, r_moving], range(0, lay.n_lag_r)) if r_moving else np.zeros((self.n_rows, 0))
        return SharedBlockRegression(Xr, [lay.n_lag_r] * len(r_moving))

    def row_fit(self, reg: SharedBlockRegression, i: int):
        """ARX of ``z_i`` on the setpoints (``reg``) and its own lags 1..na."""
        start = self.layout.start
        zi = self.z[:, i] - self.z[:, i].mean()
        own = -self._lags(zi, range(1, self.na + 1)) if self.na else None
        return reg.fit(segment_rows(zi, start, self.segments), own)

    def row_fits(self, reg: SharedBlockRegression, outputs) -> list:
        """:meth:`row_fit` of every output of ``outputs``."""
        return [self.row_fit(reg, i) for i in outputs]

    def input_regression(self, testable: list) -> SharedBlockRegression:
        """Input lags ``1 .. n_lag_u`` of the inputs ``testable`` (Delta element test)."""
        lay = self.layout
        X = self._lags(self._u_c[:, testable], range(1, lay.n_lag_u + 1)) if testable else \
            np.zeros((self.n_rows, 0))
        return SharedBlockRegression(X, [lay.n_lag_u] * len(testable))

    def element_fit(self, reg: SharedBlockRegression, i: int):
        """ARX of ``d_i`` on the input lags (``reg``) and its own lags 1..na."""
        start = self.layout.start
        di = self.d[:, i] - self.d[:, i].mean()
        own = -self._lags(di, range(1, self.na + 1)) if self.na else None
        return reg.fit(segment_rows(di, start, self.segments), own)

    def short_arx(self, i: int, nk: np.ndarray):
        """The short ARX of ``d_i`` at the delays ``nk`` (the paper's tables); an :class:`ArxFit`."""
        di = self.d[:, i] - self.d[:, i].mean()
        return fit_arx(di, self._u_c, self.na, self.nb, nk, segments=self.segments)


# ----------------------------------------------------------------------------------------- buffer
class SampleBuffer:
    """The last ``window`` samples of some signals side by side, with their absolute sample indices.

    The sliding-window analyzer keeps ``[r | u | y | yhat]`` in one; :func:`window_regressions`
    wraps a window's ``[r | u | z | d]``.  :class:`LaggedGram` reads its rows by absolute index.

    Parameters
    ----------
    n_channels : int
        Columns of a sample.
    window : int
        Samples kept by :meth:`compact`.
    slack : int
        Extra rows, so that samples are appended without moving the others every time.
    fill : bool
        False: the rows are not set to 0 first (the caller writes every one before reading it).
    """

    def __init__(self, n_channels: int, window: int, slack: int, fill: bool = True):
        self.window = window
        self.data = (np.zeros if fill else np.empty)((window + slack, n_channels))
        self.first = 0          # absolute index of data[0]
        self.count = 0          # rows in use

    @property
    def end(self) -> int:
        """Absolute index one past the newest sample."""
        return self.first + self.count

    def free(self) -> int:
        return self.data.shape[0] - self.count

    def append(self, rows: np.ndarray) -> None:
        k = rows.shape[0]
        self.data[self.count:self.count + k] = rows
        self.count += k

    def compact(self) -> None:
        """Keep only the last ``window`` samples, moved to the front."""
        drop = max(self.count - self.window, 0)
        if drop:
            self.data[:self.count - drop] = self.data[drop:self.count]
            self.first += drop
            self.count -= drop

    def rows(self, a: int, b: int) -> np.ndarray:
        """Samples with absolute indices ``a .. b - 1`` (a view)."""
        if a < self.first or b > self.end:
            raise IndexError(f"samples {a}..{b - 1} are not in the buffer ({self.first}..{self.end - 1})")
        return self.data[a - self.first:b - self.first]


# ----------------------------------------------------------------------------------------- Gram
def _column_runs(col_channel: np.ndarray, col_lag: np.ndarray) -> list:
    """The columns of :func:`lagged_cross_products` as runs of consecutive channels sharing one lag sequence.

    Parameters
    ----------
    col_channel, col_lag : ndarray of int, shape (p,)

    Returns
    -------
    list of (int, int, int, ndarray of int)
        ``(offset, first, n, lags)``: column ``offset + c * len(lags) + k`` holds channel ``first + c``
        at lag ``lags[k]``, for ``c < n``.  Every column is in exactly one run (at worst a run of one
        channel, of its consecutive columns).
    """
    starts = np.flatnonzero(np.diff(col_channel, prepend=-1))           # where the channel changes
    runs = []
    for a, b in zip(starts, np.append(starts[1:], col_channel.size)):
        channel, lags = int(col_channel[a]), col_lag[a:b]
        if runs:
            offset, first, n, run_lags = runs[-1]
            if channel == first + n and np.array_equal(lags, run_lags):
                runs[-1] = (offset, first, n + 1, run_lags)
                continue
        runs.append((int(a), channel, 1, lags))
    return runs


def lagged_cross_products(values: np.ndarray, col_channel: np.ndarray, col_lag: np.ndarray, max_lag: int,
                          jobs: int = 1):
    """Cross products and sums of lagged columns, from ``max_lag + 1`` products of the unlagged signals.

    Column ``c`` holds ``x_{ch(c)}(t - lag(c))`` over the rows ``t = max_lag .. n - 1`` of ``values``.
    Two columns whose lags differ by ``delta >= 0`` have, with ``m`` the smaller lag and the rows
    ``[s, e)``::

        sum_{t=s}^{e-1} x_a(t - m) x_b(t - m - delta)
            = sum_{t=s}^{e-1} x_a(t) x_b(t - delta)                          (one matrix product per delta)
            + sum_{k=1}^{m} x_a(s - k) x_b(s - k - delta)                     (rows entering at the head)
            - sum_{k=1}^{m} x_a(e - k) x_b(e - k - delta)                     (rows leaving at the tail)

    so the ``p x p`` Gram matrix costs ``O(n n_channels^2 max_lag)`` instead of ``O(n p^2)`` with
    ``p = n_channels n_lags``; every entry is still a plain sum over the rows plus at most ``2 max_lag``
    corrections, so its rounding error is that of the direct product.

    The corrections are accumulated lag by lag (``m = 0, 1, ...``) for every ``delta`` at once, and each
    ``n_channels x n_channels`` matrix of one ``(m, delta)`` is written straight into the Gram matrix,
    one strided block per pair of column runs sharing a lag sequence (:func:`_column_runs`) with the
    lags ``m`` and ``m + delta``; the entries whose row has the larger lag are then mirrored from
    those above them.

    Parameters
    ----------
    values : ndarray, shape (max_lag + n_rows, n_channels)
        The signals; row ``max_lag + t`` is regression row ``t``.
    col_channel, col_lag : ndarray of int, shape (p,)
        Channel and lag (``0 .. max_lag``) of every column.
    max_lag : int
    jobs : int
        With 2, a forked child process takes the products of part of the lag differences
        (:func:`~mpm_monitor.core.parallel.split_map`; each is the same product, the same numbers).

    Returns
    -------
    gram : ndarray, shape (p, p)
        ``Phi' Phi`` (symmetric).
    sums : ndarray, shape (p,)
        ``Phi' 1``.
    """
    x = np.asfortranarray(values, dtype=float)      # column slices are contiguous for the products
    L = int(max_lag)
    n = x.shape[0] - L
    n_ch = x.shape[1]
    col_channel, col_lag = np.asarray(col_channel, dtype=int), np.asarray(col_lag, dtype=int)
    p = col_lag.size
    if n <= 0:
        return np.zeros((p, p)), np.zeros(p)
    lag_lo = np.full(n_ch, L + 1)
    lag_hi = np.full(n_ch, -1)
    np.minimum.at(lag_lo, col_channel, col_lag)
    np.maximum.at(lag_hi, col_channel, col_lag)
    used = lag_hi >= 0
    lowest = int(lag_lo[used].min()) if used.any() else 0
    n_delta = int(lag_hi.max()) - lowest + 1 if used.any() else 1
    cur = x[L:L + n]
    head = x[L - 1::-1] if L else x[:0]                    # x(s - 1), x(s - 2), ..., x(s - L)
    tail = x[L + n - 1:n - 1:-1] if L else x[:0]            # x(e - 1), ..., x(e - L)
    # base[delta][a, k] = sum_{t=s}^{e-1} x_a(t) x_b(t - delta) for b = b_need[delta][k], the channels
    # that appear lagged by delta more than some a (others are never needed).
    b_need, b_cols = [], []
    for delta in range(n_delta):
        need = np.flatnonzero(used & (lag_hi - lowest >= delta))
        contiguous = need.size and need[-1] - need[0] + 1 == need.size
        b_cols.append(slice(need[0], need[-1] + 1) if contiguous else need)     # a view, not a copy
        b_need.append(need)
    base = split_map(lambda delta: cur.T @ x[L - delta:L - delta + n, b_cols[delta]], range(n_delta), jobs)
    # corr[delta]: the head and tail corrections of the smaller lag m, summed over k < min(m, L - delta)
    # (n_corr[delta] terms so far).
    corr = [np.zeros_like(g) for g in base]
    n_corr = [0] * n_delta
    runs = _column_runs(col_channel, col_lag)
    at_lag = {}                                             # lag -> (run, position in its lags)
    for r, (_, _, _, lags) in enumerate(runs):
        for k, lag in enumerate(lags):
            at_lag.setdefault(int(lag), []).append((r, k))
    gram = np.empty((p, p))
    for m in sorted(at_lag):
        for delta in range(n_delta):
            if m + delta not in at_lag:
                continue
            need = b_need[delta]
            while n_corr[delta] < min(m, L - delta):
                k = n_corr[delta]
                corr[delta] += (head[k][:, None] * head[k + delta][None, need]
                                - tail[k][:, None] * tail[k + delta][None, need])
                n_corr[delta] += 1
            for r1, k1 in at_lag[m]:
                off1, a1, n1, lags1 = runs[r1]
                rows = slice(off1 + k1, off1 + n1 * lags1.size, lags1.size)
                for r2, k2 in at_lag[m + delta]:
                    off2, a2, n2, lags2 = runs[r2]
                    q = int(np.searchsorted(need, a2))
                    np.add(base[delta][a1:a1 + n1, q:q + n2], corr[delta][a1:a1 + n1, q:q + n2],
                           out=gram[rows, off2 + k2:off2 + n2 * lags2.size:lags2.size])
    for a in range(0, p, MIRROR_ROWS):
        rows = slice(a, a + MIRROR_ROWS)
        np.copyto(gram[rows], gram[:, rows].T, where=col_lag[rows, None] > col_lag[None, :])
    # Sums: sum_{t=s}^{e-1} x_c(t - l) = sum over [s, e) + the l rows before s - the last l rows.
    cum_head = np.vstack([np.zeros((1, n_ch)), np.cumsum(head, axis=0)])
    cum_tail = np.vstack([np.zeros((1, n_ch)), np.cumsum(tail, axis=0)])
    sums = cur.sum(axis=0)[col_channel] + cum_head[col_lag, col_channel] - cum_tail[col_lag, col_channel]
    return gram, sums


class LaggedGram:
    """Cross products ``Phi' Phi`` and sums ``Phi' 1`` of lagged signal columns over a range of rows.

    Parameters
    ----------
    groups : list of (str, int, sequence of int)
        ``(signal name, n_channels, lags)``; the columns are ordered group by group, channel by
        channel, lag by lag (the order of :func:`mpm_monitor.core.arx.lag_matrix`).
    signals : callable
        ``signals(block)`` maps buffer rows ``[r | u | y | yhat]`` to a dict of the named signals.

    Notes
    -----
    Row ``t`` holds ``x_c(t - l) - ref_c`` for every column; ``ref`` is set at each rebuild.  A rebuild
    fills both triangles (:func:`lagged_cross_products`); the updates are symmetric rank-k updates (BLAS
    ``dsyrk``, or ``dsyr2k`` when as many rows leave as enter) of the lower triangle, in place;
    :meth:`symmetric` returns the full matrix.
    """

    def __init__(self, groups, signals):
        self.groups = [(name, int(nch), np.asarray(list(lags), dtype=int)) for name, nch, lags in groups]
        self.signals = signals
        self.max_lag = int(max(lags.max(initial=0) for _, _, lags in self.groups))
        offsets, col_channel, ch = [], [], 0
        col = 0
        for name, nch, lags in self.groups:
            offsets.append(col)
            for c in range(nch):
                col_channel.extend([ch + c] * len(lags))
            col += nch * len(lags)
            ch += nch
        self.offsets = offsets
        self._column = {(g, c, int(lag)): offsets[g] + c * len(lags) + k
                        for g, (_, nch, lags) in enumerate(self.groups) for c in range(nch)
                        for k, lag in enumerate(lags)}
        self.n_columns = col
        self.n_channels = ch
        self.col_channel = np.asarray(col_channel, dtype=int)
        self.col_lag = np.concatenate([np.tile(lags, nch) for _, nch, lags in self.groups]).astype(int)
        self._full = None
        self.ref = np.zeros(ch)
        self.gram = np.zeros((col, col))
        self.sums = np.zeros(col)
        self.lo = self.hi = 0        # rows lo .. hi - 1 are accumulated

    @property
    def n_rows(self) -> int:
        return self.hi - self.lo

    def column(self, group: int, channel: int, lag: int) -> int:
        """Index of the column of ``channel`` of ``group`` at ``lag``."""
        return self._column[(group, channel, int(lag))]

    def channel_values(self, block: np.ndarray) -> np.ndarray:
        """The signals of the groups side by side, shape (n_rows, n_channels)."""
        sig = self.signals(block)
        return np.hstack([sig[name] for name, _, _ in self.groups])

    def centred_values(self, block: np.ndarray, order: str = "C") -> np.ndarray:
        """:meth:`channel_values` minus the reference :attr:`ref`, written at once into one array of memory
        ``order`` (shape (n_rows, n_channels))."""
        sig = self.signals(block)
        values = np.empty((block.shape[0], self.n_channels), order=order)
        at = 0
        for name, nch, _ in self.groups:
            np.subtract(sig[name], self.ref[at:at + nch], out=values[:, at:at + nch])
            at += nch
        return values

    def rows(self, buf: SampleBuffer, a: int, b: int) -> np.ndarray:
        """``Phi`` for the rows ``a .. b - 1`` (absolute sample indices), shape (b - a, n_columns)."""
        values = self.centred_values(buf.rows(a - self.max_lag, b))
        t = np.arange(self.max_lag, self.max_lag + b - a)[:, None]
        return values[t - self.col_lag, self.col_channel]

    def _accumulate(self, phi: np.ndarray, sign: float) -> None:
        # gram's lower triangle += sign * phi' phi, in place (gram.T is Fortran-ordered).
        blas.dsyrk(sign, phi.T, beta=1.0, c=self.gram.T, trans=0, lower=0, overwrite_c=1)
        self.sums += sign * phi.sum(axis=0)
        self._full = None

    def rebuild(self, buf: SampleBuffer, a: int, b: int, ref: np.ndarray, jobs: int = 1) -> None:
        """Recompute from scratch over rows ``a .. b - 1`` with a new reference ``ref`` (n_channels,).

        Uses the shift structure of the lagged columns (:func:`lagged_cross_products`, with ``jobs``),
        which fills both triangles: the matrix is its own :meth:`symmetric` until an update.
        """
        self.ref = np.asarray(ref, dtype=float).copy()
        if b > a:
            # In the column order the products read.
            values = self.centred_values(buf.rows(a - self.max_lag, b), order="F")
            self.gram, self.sums = lagged_cross_products(values, self.col_channel, self.col_lag, self.max_lag, jobs)
        else:
            self.gram = np.zeros((self.n_columns, self.n_columns))
            self.sums = np.zeros(self.n_columns)
        self.lo, self.hi = a, b
        self._full = self.gram

    def update(self, buf: SampleBuffer, add: tuple, remove: tuple) -> None:
        """Add the rows ``add = (a, b)`` and remove the rows ``remove = (a, b)``."""
        n_add, n_remove = max(add[1] - add[0], 0), max(remove[1] - remove[0], 0)
        if not (n_add or n_remove):
            return
        self._writable()
        lag = self.max_lag
        slabs, index, base = [], [], 0
        for (a, b), k in ((remove, n_remove), (add, n_add)):
            if k:
                slabs.append(buf.rows(a - lag, b))
                index.append(np.arange(base + lag, base + lag + k))
                base += k + lag
        values = self.centred_values(slabs[0] if len(slabs) == 1 else np.vstack(slabs))
        t = np.concatenate(index)[:, None] if len(index) > 1 else index[0][:, None]
        phi = values[t - self.col_lag, self.col_channel]
        if n_add == n_remove:
            # A'A - B'B = ((A + B)'(A - B) + (A - B)'(A + B)) / 2: one pass over the matrix (dsyr2k).
            a, b = phi[n_remove:], phi[:n_remove]
            blas.dsyr2k(0.5, (a + b).T, (a - b).T, beta=1.0, c=self.gram.T, trans=0, lower=0, overwrite_c=1)
            self.sums += a.sum(axis=0) - b.sum(axis=0)
            self._full = None
        else:
            if n_remove:
                self._accumulate(phi[:n_remove], -1.0)
            if n_add:
                self._accumulate(phi[n_remove:], 1.0)
        if n_remove:
            self.lo = remove[1]
        if n_add:
            self.hi = add[1]

    def _writable(self) -> None:
        """Before the matrix is changed in place: a matrix that :meth:`symmetric` handed out as itself
        (after a rebuild) is copied first, so what a caller holds does not change under it."""
        if self._full is self.gram:
            self.gram = self.gram.copy()
        self._full = None

    def symmetric(self) -> np.ndarray:
        """The full cross-product matrix (the kept lower triangle mirrored; after a rebuild, the matrix
        itself: do not write to it)."""
        if self._full is None:
            low = np.tril(self.gram)
            self._full = low + np.tril(low, -1).T
        return self._full

    def clear(self) -> None:
        """No rows."""
        self._writable()
        self.gram[:] = 0.0
        self.sums[:] = 0.0
        self.lo = self.hi = 0
        self._full = None

    def centred(self, cols_a, signs_a, cols_b, signs_b, means: np.ndarray):
        """Block of the centred cross products and the centred sums of the columns ``cols_b``.

        Column ``c`` centred is ``sign_c (x_c - mean_c)`` with ``mean`` the window mean of its
        channel (``means`` has shape (n_channels,)).

        Returns
        -------
        gram : ndarray, shape (len(cols_a), len(cols_b))
        sums_b : ndarray, shape (len(cols_b),)
        """
        cols_a, cols_b = np.asarray(cols_a, dtype=int), np.asarray(cols_b, dtype=int)
        shift = np.asarray(means, dtype=float) - self.ref
        ma, mb = shift[self.col_channel[cols_a]], shift[self.col_channel[cols_b]]
        sa, sb = self.sums[cols_a], self.sums[cols_b]
        n = self.n_rows
        g = self.symmetric()[np.ix_(cols_a, cols_b)] - np.outer(sa, mb) - np.outer(ma, sb) + n * np.outer(ma, mb)
        sign_a, sign_b = np.asarray(signs_a, dtype=float), np.asarray(signs_b, dtype=float)
        return g * np.outer(sign_a, sign_b), (sb - n * mb) * sign_b


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
        when solved together with other fits' (:meth:`GramRegressions.row_fits`); default: solved here,
        with products by ``R1^-1``.

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


class GramRegressions:
    """The tests' least-squares problems solved from the Gram matrices of a window.

    Has the methods of :class:`QrRegressions`, for ``analyze(..., regressions=...)``.  A regression
    whose condition bound exceeds ``max_condition`` is refitted by that class from the window's
    signals.

    Parameters
    ----------
    row_gram, input_gram : LaggedGram
        Up to date over the window's regression rows.
    r, u, z, d : ndarray
        The window's signals (for the window means, the few rows of the short ARX outside the Gram
        rows, and the QR fallback).
    layout : RegressionLayout
    na, nb : int
    max_condition : float
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows of the signals, as for :class:`QrRegressions`
        (the Gram matrices then sum the runs' regression rows).
    """

    def __init__(self, row_gram: LaggedGram, input_gram: LaggedGram, r, u, z, d, layout: RegressionLayout,
                 na: int, nb: int, max_condition: float = DEFAULT_MAX_CONDITION, segments=None):
        self.segments = as_segments(segments)
        self.row_gram, self._input_gram = row_gram, input_gram
        self._take_input_gram = None      # window_regressions: how to take the input Gram when first read
        self.r, self.u, self.z, self.d = r, u, z, d
        self.layout, self.na, self.nb = layout, na, nb
        self.max_condition = max_condition
        self.row_means = np.concatenate([r.mean(axis=0), z.mean(axis=0)])
        self.row_z = None             # the outputs whose z the row Gram holds (None: all; window_regressions)
        self._widen_row_gram = None   # window_regressions: the row Gram of every z, when a reduced one lacks a row
        self.input_means = np.concatenate([u.mean(axis=0), d.mean(axis=0)])
        self._inputs_move = bool(np.all(moving_columns(u)))     # as InputDesign.testable
        self._qr = None
        self._qr_regs = {}
        self.fallbacks = []          # names of the regressions refitted by QR
        self.batch = False           # built at once from the window's signals (window_regressions)
        self._row_regs = {}          # channels -> the row test's regression
        self._row_fits = {}          # (id of the regression, output) -> its row fit
        self._previous, self._same_rows = None, frozenset()

    @property
    def input_gram(self) -> LaggedGram:
        """The Gram of the input lags and the own lags (:func:`window_regressions` takes it when first read:
        a detection that tests no element needs none)."""
        if self._take_input_gram is not None:
            take, self._take_input_gram = self._take_input_gram, None
            take()
        return self._input_gram

    def row_test_part(self) -> "GramRegressions":
        """A copy with only what :meth:`reuse_rows_of` reads from it (the setpoints, ``z``, the row
        test's regressions and fits): kept for the detection after a repair without the Gram matrices."""
        out = object.__new__(GramRegressions)
        out.__dict__.update(batch=self.batch, layout=self.layout, na=self.na, nb=self.nb,
                            max_condition=self.max_condition, r=self.r, z=self.z, fallbacks=list(self.fallbacks),
                            _row_regs=dict(self._row_regs), _row_fits=dict(self._row_fits),
                            _previous=self._previous, _same_rows=self._same_rows, row_z=None, _widen_row_gram=None)
        return out

    def reuse_rows_of(self, other: "GramRegressions") -> None:
        """Take the S_Delta row test's regression and fits from ``other`` where they are the same numbers.

        ``other``: the regressions of the same window with another model (the detection before a
        repair).  Both must be built by :func:`window_regressions` with the same layout and orders
        from the same setpoints; then the setpoint block is the same, and so is the row fit of every
        output whose ``z`` column is the same.  Otherwise nothing is taken.
        """
        if not (isinstance(other, GramRegressions) and self.batch and other.batch
                and (self.layout, self.na, self.nb, self.max_condition)
                == (other.layout, other.na, other.nb, other.max_condition)
                and self.r.shape == other.r.shape and self.z.shape == other.z.shape
                and np.array_equal(self.r, other.r)):
            return
        self._previous = other
        self._same_rows = frozenset(i for i in range(self.z.shape[1]) if np.array_equal(self.z[:, i], other.z[:, i]))

    def rows_to_fit(self) -> Optional[list]:
        """The outputs whose row fit this window needs although it reuses another's (:meth:`reuse_rows_of`):
        those whose ``z`` differs, or that the other did not fit; None when nothing is reused."""
        if self._previous is None:
            return None
        fitted = {i for _, i in self._previous._row_fits}
        return [i for i in range(self.z.shape[1]) if i not in self._same_rows or i not in fitted]

    @property
    def row_gram_means(self) -> np.ndarray:
        """The window means of the row Gram's channels: the setpoints, then the ``z`` of :attr:`row_z`."""
        if self.row_z is None:
            return self.row_means
        ny = self.r.shape[1]
        return self.row_means[np.concatenate([np.arange(ny), ny + np.asarray(self.row_z, dtype=int)])]

    # -------------------------------------------------------------- helpers
    @property
    def qr(self) -> QrRegressions:
        if self._qr is None:
            self._qr = QrRegressions(self.r, self.u, self.z, self.d, self.layout, self.na, self.nb, self.segments)
        return self._qr

    def _qr_regression(self, kind: str, channels: tuple) -> SharedBlockRegression:
        key = (kind, channels)
        if key not in self._qr_regs:
            build = self.qr.row_regression if kind == "row" else self.qr.input_regression
            self._qr_regs[key] = build(list(channels))
        return self._qr_regs[key]

    def _own_columns(self, gram: LaggedGram, i: int):
        """Own columns ``-x_i(t-1) .. -x_i(t-na)`` and the target ``x_i(t)`` of output ``i``."""
        c = i if (gram is not self.row_gram or self.row_z is None) else self.row_z.index(i)
        own = [gram.column(1, c, lag) for lag in range(1, self.na + 1)]
        return own, [-1.0] * len(own), gram.column(1, c, 0)

    def _common(self, kind, channels):
        gram = self.row_gram if kind == "row" else self.input_gram
        lags = range(0, self.layout.n_lag_r) if kind == "row" else range(1, self.layout.n_lag_u + 1)
        return gram, [gram.column(0, c, lag) for c in channels for lag in lags]

    def _regression(self, kind: str, channels: list):
        gram, cols = self._common(kind, channels)
        means = self.row_gram_means if kind == "row" else self.input_means
        g, _ = gram.centred(cols, np.ones(len(cols)), cols, np.ones(len(cols)), means)
        n_lag = self.layout.n_lag_r if kind == "row" else self.layout.n_lag_u
        try:
            reg = GramBlockRegression(g, [n_lag] * len(channels), self.max_condition)
        except IllConditioned:
            self.fallbacks.append(f"{kind} regression")
            return self._qr_regression(kind, tuple(channels))
        reg.kind, reg.channels, reg.columns = kind, tuple(channels), cols
        return reg

    def _fit_arguments(self, kind: str, reg: GramBlockRegression, i: int) -> tuple:
        """The cross products of output ``i``'s fit in ``reg``: :class:`GramFit`'s arguments
        ``(g_co, g_oo, g_cy, g_oy, g_yy, sum_y, n)``."""
        gram = self.row_gram if kind == "row" else self.input_gram
        means = self.row_gram_means if kind == "row" else self.input_means
        own, own_signs, target = self._own_columns(gram, i)
        cols_b = own + [target]
        signs_b = np.array(own_signs + [1.0])
        g_cb, _ = gram.centred(reg.columns, np.ones(len(reg.columns)), cols_b, signs_b, means)
        g_bb, sums_b = gram.centred(cols_b, signs_b, cols_b, signs_b, means)
        po = len(own)
        return (g_cb[:, :po], g_bb[:po, :po], g_cb[:, po], g_bb[:po, po], float(g_bb[po, po]), float(sums_b[po]),
                gram.n_rows)

    def _fits(self, kind: str, reg, outputs: list, together: bool = False) -> list:
        """The fits of the outputs in ``reg``; an ill-conditioned one refitted by QR.

        ``together``: their products with the shared block are solved at once
        (:meth:`GramBlockRegression.projections`: a fit's numbers do not depend on the others solved
        with it); else by each :class:`GramFit` (the element test's fits).
        """
        def qr_fit(qr_reg, i):
            return (self.qr.row_fit if kind == "row" else self.qr.element_fit)(qr_reg, i)
        if not isinstance(reg, GramBlockRegression):
            return [qr_fit(reg, i) for i in outputs]
        args = [self._fit_arguments(kind, reg, i) for i in outputs]
        common = [None] * len(outputs)
        if together and outputs:
            rhs = [GramFit.common_rhs(reg, g_co, g_oo, g_cy) for g_co, g_oo, g_cy, *_ in args]
            q, w = reg.projections(np.hstack(rhs))
            ends = np.cumsum([b.shape[1] for b in rhs])
            common = [(q[:, e - b.shape[1]:e], w[:, e - b.shape[1]:e]) for e, b in zip(ends, rhs)]
        fits = []
        for i, arg, solved in zip(outputs, args, common):
            try:
                fits.append(GramFit(reg, *arg, self.max_condition, common=solved))
            except IllConditioned:
                self.fallbacks.append(f"{kind} fit of output {i}")
                fits.append(qr_fit(self._qr_regression(kind, reg.channels), i))
        return fits

    # -------------------------------------------------------------- the QrRegressions interface
    @staticmethod
    def _row_key(r_moving) -> tuple:
        """The key of the row test's regression on the setpoints ``r_moving``."""
        return tuple(int(c) for c in r_moving)

    def row_regression(self, r_moving: list) -> SharedBlockRegression:
        """Setpoint lags of the moving setpoints (S_Delta row test)."""
        key = self._row_key(r_moving)
        if key not in self._row_regs:
            prev = self._previous
            if prev is not None and key in prev._row_regs:
                self._row_regs[key] = prev._row_regs[key]
                self.fallbacks += [f for f in prev.fallbacks if f == "row regression"]
            else:
                self._row_regs[key] = self._regression("row", list(key))
        return self._row_regs[key]

    def row_regression_pending(self, r_moving: list) -> bool:
        """Whether :meth:`row_regression` of these setpoints would factor its block now (not kept here, nor
        in the regressions it reuses)."""
        key = self._row_key(r_moving)
        prev = self._previous
        return key not in self._row_regs and not (prev is not None and key in prev._row_regs)

    def factored_row_regression(self, r_moving: list) -> Optional["GramBlockRegression"]:
        """:meth:`row_regression` of these setpoints when its block is well conditioned (its Gram
        factorisation), else None; for :meth:`keep_row_regression` in another process (a forked child
        computes it while this one goes on, :func:`~mpm_monitor.core.analysis.detect`)."""
        reg = self.row_regression(r_moving)
        return reg if isinstance(reg, GramBlockRegression) else None

    def keep_row_regression(self, r_moving: list, reg: "GramBlockRegression") -> None:
        """Keep ``reg``, :meth:`factored_row_regression` of these setpoints computed in another process (the
        same numbers), as their :meth:`row_regression`."""
        self._row_regs.setdefault(self._row_key(r_moving), reg)

    def row_fit(self, reg, i: int):
        """ARX of ``z_i`` on the setpoints and its own lags."""
        return self.row_fits(reg, [i])[0]

    def row_fits(self, reg, outputs) -> list:
        """:meth:`row_fit` of every output of ``outputs``; those not fitted yet are solved together
        (two triangular solves with the setpoint block for all, :meth:`_fits`)."""
        prev = self._previous
        fits = {}
        for i in outputs:
            key = (id(reg), int(i))
            if key in self._row_fits:
                fits[i] = self._row_fits[key][1]
            elif prev is not None and i in self._same_rows and key in prev._row_fits:
                fits[i] = prev._row_fits[key][1]
        new = [i for i in dict.fromkeys(outputs) if i not in fits]
        if self.row_z is not None and any(i not in self.row_z for i in new):
            self._widen_row_gram()        # a row whose z the reduced row Gram lacks: the Gram of every z
        for i, fit in zip(new, self._fits("row", reg, new, together=True)):
            if isinstance(fit, GramFit):
                # Kept for a detection of another model on this window (reuse_rows_of), without its
                # assembled inverse factor (p x p; the row test does not read it, rinv assembles it again).
                fit._rinv = None
                self._row_fits[(id(reg), int(i))] = (reg, fit)
            fits[i] = fit
        return [fits[i] for i in outputs]

    def input_regression(self, testable: list) -> SharedBlockRegression:
        """Input lags of the inputs ``testable`` (Delta element test)."""
        return self._regression("input", list(testable))

    def element_fit(self, reg, i: int):
        """ARX of ``d_i`` on the input lags and its own lags."""
        return self._fits("input", reg, [i])[0]

    def short_arx(self, i: int, nk: np.ndarray) -> ArxFit:
        """The short ARX of ``d_i`` at the delays ``nk`` (the paper's tables, which read its ``a``, ``b`` and
        fit: its ``condition_number`` is NaN, not computed, unless refitted by QR)."""
        na, nb = self.na, self.nb
        nk = np.asarray(nk, dtype=int)
        nu = self.u.shape[1]
        if (not self._inputs_move or np.any(nk < 1) or np.any(nk + nb - 1 > self.layout.n_lag_u)):
            self.fallbacks.append(f"short ARX of output {i}")
            return self.qr.short_arx(i, nk)
        gram = self.input_gram
        own, own_signs, target = self._own_columns(gram, i)
        cols = own + [gram.column(0, j, lag) for j in range(nu) for lag in range(nk[j], nk[j] + nb)] + [target]
        signs = np.array(own_signs + [1.0] * (nu * nb) + [1.0])
        g, sums = gram.centred(cols, signs, cols, signs, self.input_means)
        n = gram.n_rows
        # fit_arx starts at max(na, max(nk) + nb - 1) <= layout.start: add the rows before the Gram's.
        first = max(na, int(np.max(nk + nb - 1)) if nu else 0)
        start = self.layout.start
        if first < start:
            t = np.arange(first, start)[:, None] if self.segments is None else \
                np.concatenate([np.arange(a + first, a + start) for a, _ in self.segments])[:, None]
            d_mean = self.input_means[nu + i]
            lags = (nk[:, None] + np.arange(nb)).ravel()
            channels = np.repeat(np.arange(nu), nb)
            x = np.hstack([-(self.d[t - np.arange(1, na + 1), i] - d_mean),
                           self.u[t - lags, channels] - self.input_means[channels],
                           self.d[t, i] - d_mean])
            g = g + x.T @ x
            sums = sums + x.sum(axis=0)
            n += t.shape[0]
        try:
            return gram_arx(g, float(sums[-1]), n, na, nb, nk, self.max_condition, condition=False)
        except IllConditioned:
            self.fallbacks.append(f"short ARX of output {i}")
            return self.qr.short_arx(i, nk)


def window_regressions(r, u, z, d, layout: RegressionLayout, na: int, nb: int,
                       max_condition: float = DEFAULT_MAX_CONDITION, segments=None, jobs: int = 1,
                       previous: Optional[GramRegressions] = None) -> GramRegressions:
    """The tests' regressions on one window, from Gram matrices built at once (the batch analysis).

    Both Gram matrices are computed from the window's signals by :func:`lagged_cross_products`,
    centred by the window means as :class:`QrRegressions` centres its columns; every regression
    whose condition bound exceeds ``max_condition`` is refitted by QR (see the module docstring),
    so the results equal the QR path's to about ``max_condition^2 * 1e-16``.

    Parameters
    ----------
    r, z, d : ndarray, shape (n_samples, n_outputs)
        Setpoints, ``z = eps - r`` and prediction errors of the window.
    u : ndarray, shape (n_samples, n_columns)
        The model's columns (inputs, then measured disturbances).
    layout : RegressionLayout
    na, nb : int
    max_condition : float
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows ``(first, end)`` of the signals; each gives the
        regression rows ``first + start .. end - 1`` and the Gram matrices are their sums, so that no
        row's lags reach across a gap.  Default: one run.
    jobs : int
        Processes the Gram matrices' products are split over (:func:`lagged_cross_products`; one run
        only: with segments each is computed here).
    previous : GramRegressions, optional
        The regressions of the same window with another model (the detection before a repair): their
        row test's regression and fits are reused where they are the same numbers
        (:meth:`GramRegressions.reuse_rows_of`), and the row Gram then holds, besides the setpoints, only
        the ``z`` of the outputs still to fit (:meth:`GramRegressions.rows_to_fit`; after a repair
        of one row, 1 of 100 at 100x40: about a quarter of the products).  Each entry is the one the
        Gram of every ``z`` has.  Without segments only.

    Returns
    -------
    GramRegressions
    """
    n, ny = r.shape
    nu = u.shape[1]
    buf = SampleBuffer(3 * ny + nu, n, 0, fill=False)
    at = 0
    for part in (r, u, z, d):            # [r | u | z | d], each copied in once
        buf.data[:, at:at + part.shape[1]] = part
        at += part.shape[1]
    buf.count = n

    def signals(block):
        return {"r": block[:, :ny], "u": block[:, ny:ny + nu], "z": block[:, ny + nu:2 * ny + nu],
                "d": block[:, 2 * ny + nu:]}
    row_gram = LaggedGram([("r", ny, range(0, layout.n_lag_r)), ("z", ny, range(0, na + 1))], signals)
    input_gram = LaggedGram([("u", nu, range(1, layout.n_lag_u + 1)), ("d", ny, range(0, na + 1))], signals)
    regs = GramRegressions(row_gram, input_gram, r, u, z, d, layout, na, nb, max_condition, segments)
    if segments is None:
        regs.batch = True
        start = min(layout.start, n)
        if previous is not None:
            regs.reuse_rows_of(previous)
        to_fit = regs.rows_to_fit()
        if to_fit is not None and len(to_fit) < ny:
            z_at = ny + nu + np.asarray(to_fit, dtype=int)

            def some_z(block):
                return {"r": block[:, :ny], "z": block[:, z_at]}
            regs.row_z = tuple(to_fit)
            regs.row_gram = LaggedGram([("r", ny, range(0, layout.n_lag_r)), ("z", len(to_fit), range(0, na + 1))],
                                       some_z)

            def widen():
                regs.row_z, regs.row_gram = None, row_gram
                row_gram.rebuild(buf, start, n, regs.row_means, jobs)
            regs._widen_row_gram = widen
        regs.row_gram.rebuild(buf, start, n, regs.row_gram_means, jobs)
        regs._take_input_gram = lambda: input_gram.rebuild(buf, start, n, regs.input_means, jobs)
        return regs
    for gram, means in ((row_gram, regs.row_means), (input_gram, regs.input_means)):
        total, sums, rows = 0.0, 0.0, 0
        for a, b in regs.segments:
            gram.rebuild(buf, a + layout.start, b, means)
            total, sums, rows = total + gram.gram, sums + gram.sums, rows + gram.n_rows
        gram.gram, gram.sums, gram.lo, gram.hi, gram._full = total, sums, 0, rows, None
    return regs
