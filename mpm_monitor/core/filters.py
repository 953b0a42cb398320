"""The recursive (IIR) and moving-average (FIR) filters of the package, in one place.

``lfilter(b, a, x, axis=-1, zi=None)`` computes ``a(q) y = b(q) x`` with ``a[0] = 1`` (the
difference equation of ``scipy.signal.lfilter``): the model simulation, the prediction-error fit
and the prewhitening all filter through here.
"""

from __future__ import annotations



def lfilter(b, a, x, axis: int = -1, zi=None):
    """``a(q) y = b(q) x`` along ``axis`` (as ``scipy.signal.lfilter``; returns ``(y, zf)`` with ``zi``).

    Parameters
    ----------
    b : array_like, shape (n_b,)
        Numerator coefficients of ``q^0, q^-1, ...``.
    a : array_like, shape (n_a,)
        Denominator coefficients, ``a[0] != 0``.
    x : ndarray
        The signal.
    axis : int
        Axis of time.
    zi : ndarray, optional
        Initial state of the direct-form II transposed realisation.
    """
    from scipy import signal

    if zi is None:
        return signal.lfilter(b, a, x, axis=axis)
    return signal.lfilter(b, a, x, axis=axis, zi=zi)
