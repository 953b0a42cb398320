"""Gram matrices of lagged signals: built from scratch by the shift structure, kept up to date sample by sample.

The tests' regressions (:mod:`mpm_monitor.core.regressions`) read the cross products of lagged signal
columns from here: :class:`LaggedGram` holds them over a range of rows, :class:`SampleBuffer` the
samples they are built from.

A Gram matrix built from scratch uses the shift structure of lagged columns
(:func:`lagged_cross_products`): ``O(W n_channels^2 n_lags)`` instead of ``O(W p^2)`` for ``W`` rows
and ``p`` columns.  The tests centre each signal by its mean over the window.  With ``X`` the raw
lagged columns, ``s = X' 1`` their sums over the ``N`` regression rows and ``m`` the window means,
the centred cross products are ``X'X - s m' - m s' + N m m'`` (:meth:`LaggedGram.centred`).  To keep
that subtraction harmless the raw columns are stored relative to a reference ``ref`` (the window
means when the matrix was last built), so ``m - ref`` stays of the order of the signals' spread.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from .parallel import split_map

#: Rows of a Gram matrix mirrored at once by :func:`lagged_cross_products` (its entries below the lag
#: diagonal from those above; bounds the temporaries to a few MB at any size).
MIRROR_ROWS = 64


# ----------------------------------------------------------------------------------------- buffer
class SampleBuffer:
    """The last ``window`` samples of some signals side by side, with their absolute sample indices.

    The sliding-window analyzer keeps ``[r | u | y | yhat]`` in one;
    :func:`~mpm_monitor.core.regressions.window_regressions` wraps a window's ``[r | u | z | d]``.
    :class:`LaggedGram` reads its rows by absolute index.

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
