"""The recursive (IIR) and moving-average (FIR) filters of the package, in one place.

``lfilter(b, a, x, axis=-1, zi=None)`` computes ``a(q) y = b(q) x`` (the difference equation and
the initial state of ``scipy.signal.lfilter``): the model simulation, the prediction-error fit and
the prewhitening all filter through here.

It needs neither ``scipy.signal`` (whose import takes about 1.5 s) nor a Python loop per sample:

* the moving-average part ``v = b(q) x`` is a convolution (``numpy.convolve``, as
  ``scipy.signal.lfilter`` computes a filter without ``a``: the same numbers);
* the recursive part ``a(q) y = v`` is a lower-triangular banded Toeplitz system of bandwidth
  ``len(a) - 1``, solved by LAPACK's forward substitution ``?tbtrs`` for every column at once
  (for a first-order ``a`` the same operations, in the same order, as ``scipy.signal.lfilter``: the
  same numbers where the BLAS does not fuse a multiply and an add, to rounding where it does, as
  OpenBLAS's kernels for AVX-512 processors);
* an initial state ``zi`` of the direct-form II transposed realisation is the part of ``y(k)``,
  ``k < len(zi)``, that the samples before ``x`` contribute: it is added to ``v`` there, and the
  final state ``zf`` is the same sum taken at the end of the record.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack


def lfilter(b, a, x, axis: int = -1, zi=None):
    """``a(q) y = b(q) x`` along ``axis`` (as ``scipy.signal.lfilter``; returns ``(y, zf)`` with ``zi``).

    Parameters
    ----------
    b : array_like, shape (n_b,)
        Numerator coefficients of ``q^0, q^-1, ...``.
    a : array_like, shape (n_a,)
        Denominator coefficients, ``a[0] != 0`` (both are divided by ``a[0]``).
    x : array_like
        The signal, any shape; real or complex.
    axis : int
        Axis of time.
    zi : array_like, optional
        Initial state of the direct-form II transposed realisation: the shape of ``x`` with the
        time axis of length ``max(n_a, n_b) - 1`` (a length-``max(n_a, n_b) - 1`` vector for a
        one-dimensional ``x``).

    Returns
    -------
    y : ndarray, the shape of ``x``
    zf : ndarray, the shape of ``zi``
        Only when ``zi`` is given: the final state.
    """
    b = np.atleast_1d(np.asarray(b))
    a = np.atleast_1d(np.asarray(a))
    if b.ndim != 1 or a.ndim != 1 or b.size == 0 or a.size == 0:
        raise ValueError("lfilter: b and a must be non-empty one-dimensional coefficient vectors")
    if a[0] == 0:
        raise ValueError("lfilter: a[0] must not be zero")
    if a[0] != 1:
        b, a = b / a[0], a / a[0]
    x = np.asarray(x)
    if zi is None and x.ndim == 1 and x.dtype == np.float64 and b.dtype.kind in "fiu" and a.dtype.kind in "fiu":
        # The common case, with the least overhead: a real signal from rest.
        n = x.shape[0]
        if n == 0:
            return np.zeros(0)
        v = np.convolve(b, x)[:n] if b.size > 1 else float(b[0]) * x
        if a.size == 1:
            return v
        return _recursive(np.asarray(a, dtype=float), v[:, None])[:, 0]
    dtype = np.result_type(b, a, x, 1.0)
    b, a = b.astype(dtype, copy=False), a.astype(dtype, copy=False)
    order = max(a.size, b.size) - 1
    axis = axis % max(x.ndim, 1) if x.ndim else 0
    xt = np.moveaxis(np.atleast_1d(x).astype(dtype, copy=False), axis, 0)
    n, shape = xt.shape[0], xt.shape[1:]
    x2 = xt.reshape(n, int(np.prod(shape, dtype=int)))
    y = _moving_average(b, x2) if n else np.zeros(x2.shape, dtype=dtype)
    state = None
    if zi is not None:
        state = np.moveaxis(np.asarray(zi, dtype=dtype).reshape(_state_shape(x, axis, order)), axis, 0)
        state = state.reshape(order, x2.shape[1])
        k = min(order, n)
        y[:k] += state[:k]
    if a.size > 1 and y.size:          # LAPACK is never handed an empty right-hand side (it corrupts the heap)
        y = _recursive(a, y)
    out = np.moveaxis(y.reshape((n,) + shape), 0, axis)
    if x.ndim == 0:
        out = out.reshape(())
    if zi is None:
        return out
    zf = _final_state(b, a, x2, y, state, order)
    zf_shape = _state_shape(x, axis, order)
    zf = np.moveaxis(zf.reshape((order,) + shape), 0, axis).reshape(zf_shape)
    return out, zf


def _state_shape(x, axis: int, order: int) -> tuple:
    shape = list(np.shape(x)) or [1]
    shape[axis] = order
    return tuple(shape)


def _moving_average(b, x2):
    """``v(k) = sum_m b_m x(k - m)`` of every column of ``x2`` (shape (n, n_columns)), a new array."""
    n, cols = x2.shape
    if b.size == 1:
        return b[0] * x2
    out = np.empty((n, cols), dtype=np.result_type(b, x2))
    for c in range(cols):
        out[:, c] = np.convolve(b, x2[:, c])[:n]
    return out


def _recursive(a, v):
    """Solve ``a(q) y = v`` column by column: forward substitution in the banded Toeplitz matrix.

    ``v`` without columns or rows is returned as it is: SciPy's ``?tbtrs`` wrapper corrupts the heap
    when handed a right-hand side with no columns (a later garbage collection aborts the process).
    """
    if v.size == 0:
        return v
    band = np.tile(a, (v.shape[0], 1)).T         # (len(a), n), column-major: LAPACK's band storage
    tbtrs = lapack.ztbtrs if np.iscomplexobj(v) or np.iscomplexobj(a) else lapack.dtbtrs
    y, info = tbtrs(band, np.asfortranarray(v), uplo="L", trans="N", diag="U", overwrite_b=1)
    if info != 0:
        raise ValueError(f"lfilter: LAPACK ?tbtrs failed (info {info})")
    return y


def _final_state(b, a, x2, y, state, order: int):
    """``zf[k] = sum_{m > k} (b_m x(n + k - m) - a_m y(n + k - m))`` plus what is left of ``zi``."""
    n = x2.shape[0]
    bp = np.zeros(order + 1, dtype=b.dtype)
    ap = np.zeros(order + 1, dtype=a.dtype)
    bp[:b.size], ap[:a.size] = b, a
    zf = np.zeros((order, x2.shape[1]), dtype=y.dtype)
    for k in range(order):
        for m in range(k + 1, order + 1):
            t = n + k - m
            if 0 <= t < n:
                zf[k] += bp[m] * x2[t] - ap[m] * y[t]
        if n + k < order:
            zf[k] += state[n + k]
    return zf
