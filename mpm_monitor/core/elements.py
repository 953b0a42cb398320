"""One element of the transfer matrix: its exact sampled form, whatever its structure.

A model element (output ``i``, input or measured disturbance ``j``) is either parametric,

    G(s) = K (lead s + 1) e^{-theta s} / ((tau s + 1)(tau2 s + 1))                (self-regulating)
    G(s) = K (lead s + 1) e^{-theta s} / (s (tau s + 1)(tau2 s + 1))              (integrating)

with ``theta`` a whole number of samples (``K`` in output units per input unit, per second for an
integrating element; ``tau``, ``tau2``, ``lead`` in seconds, 0 = absent; a negative ``lead`` is an
inverse response), or a step response ``s_1 .. s_N``: the change of the output ``1 .. N`` samples
after a unit step of the input at sample 0, held at ``s_N`` beyond (or, for a ``ramp`` output,
continued with the last slope ``s_N - s_(N-1)``), the form of DMC-type controllers.

Every structure becomes the same discrete object, :class:`DiscreteElement`::

    G(z) = z^{-delay} num(z^-1) / den(z^-1),    den[0] = 1

the exact zero-order-hold (step-invariant) equivalent of the parametric element (Franklin, Powell &
Workman, *Digital Control of Dynamic Systems*, 3rd ed., section 4.3), or the finite impulse response
of the step-response element (with the integrator ``1 / (1 - z^-1)`` for a ramp).  The simulation,
the frequency response and the state-space realisation of the model only ever see this form.

Sampling a rational element: its controllable canonical realisation ``(A, B, C, D)`` is sampled with
the matrix exponential of ``[[A, B], [0, 0]] T`` (Van Loan, 1978); the denominator is
``prod_k (1 - exp(p_k T) z^-1)`` over the continuous poles ``p_k`` (``-1/tau``, ``-1/tau2``, 0), and
the numerator follows from the first Markov parameters ``h_0 = D``, ``h_k = C Ad^(k-1) Bd``:
``num = (den * h)`` truncated to the order.  A first-order element uses the closed form
``K (1 - a) z^-1 / (1 - a z^-1)``, ``a = exp(-T / tau)``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

#: Coefficients below this fraction of the largest are treated as zero when trimming a step response.
STEP_RESPONSE_ZERO = 0.0


@dataclasses.dataclass(frozen=True)
class DiscreteElement:
    """``G(z) = z^-delay num(z^-1) / den(z^-1)``: one element in discrete time.

    Attributes
    ----------
    num : ndarray, shape (n_num,)
        Numerator coefficients of ``z^0, z^-1, ...`` (output units per input unit).
    den : ndarray, shape (n_den,)
        Denominator coefficients of ``z^0, z^-1, ...``, ``den[0] == 1``.
    delay : int
        Whole samples of dead time, >= 0.
    """

    num: np.ndarray
    den: np.ndarray
    delay: int

    def __post_init__(self):
        num = np.atleast_1d(np.asarray(self.num, dtype=float)).copy()
        den = np.atleast_1d(np.asarray(self.den, dtype=float)).copy()
        if den.size == 0 or den[0] != 1.0:
            raise ValueError(f"den[0] must be 1, got {den[:1]}")
        if num.size == 0:
            num = np.zeros(1)
        num.setflags(write=False)
        den.setflags(write=False)
        object.__setattr__(self, "num", num)
        object.__setattr__(self, "den", den)
        object.__setattr__(self, "delay", int(self.delay))
        object.__setattr__(self, "_is_zero", not np.any(num != 0))

    @property
    def is_zero(self) -> bool:
        """True when the element has no effect (every numerator coefficient 0; computed once)."""
        return self._is_zero

    @property
    def order(self) -> int:
        """Order of the denominator (number of poles)."""
        return self.den.size - 1

    @property
    def feedthrough(self) -> float:
        """``G(z)`` at ``z^-1 = 0``: the direct feed-through (0 unless ``delay == 0``)."""
        return float(self.num[0]) if self.delay == 0 else 0.0

    @property
    def strictly_proper(self) -> bool:
        """True when ``u(k)`` does not act on ``y(k)`` (no feed-through)."""
        return self.is_zero or self.feedthrough == 0.0

    @property
    def poles(self) -> np.ndarray:
        """Poles in the z-plane, shape (order,)."""
        return np.roots(self.den) if self.order else np.zeros(0)

    @property
    def integrating(self) -> bool:
        """True when a pole lies at ``z = 1`` (the step response grows without bound)."""
        return bool(np.any(np.abs(self.poles - 1.0) < 1e-9))

    @property
    def input_lag(self) -> int:
        """Samples before ``u`` first acts: ``delay`` plus the leading zeros of ``num``."""
        if self.is_zero:
            return 0
        return self.delay + int(np.flatnonzero(self.num != 0)[0])

    def impulse_response(self, n: int) -> np.ndarray:
        """``g(0) .. g(n-1)``, the response to a unit pulse at sample 0, shape (n,)."""
        x = np.zeros(n)
        if n > self.delay:
            x[self.delay] = 1.0
        return _filter(self.num, self.den, x)

    def step_response(self, n: int) -> np.ndarray:
        """``y(0) .. y(n-1)`` after a unit step at sample 0, shape (n,) (output units)."""
        return np.cumsum(self.impulse_response(n))

    def frequency_response(self, omega: np.ndarray) -> np.ndarray:
        """``G(e^{j omega})`` for ``omega`` in rad/sample, shape (n_freq,); infinite at 0 for an integrator."""
        z1 = np.exp(-1j * np.asarray(omega, dtype=float))
        num = np.polynomial.polynomial.polyval(z1, self.num)
        den = np.polynomial.polynomial.polyval(z1, self.den)
        with np.errstate(divide="ignore", invalid="ignore"):
            return z1 ** self.delay * num / den

    def respond(self, u: np.ndarray) -> np.ndarray:
        """Response from rest to ``u`` of shape (n_samples,) (held over each sample), shape (n_samples,)."""
        u = np.asarray(u, dtype=float)
        n = u.shape[0]
        out = np.zeros(n)
        if self.is_zero or self.delay >= n:
            return out
        out[self.delay:] = _filter(self.num, self.den, u[:n - self.delay])
        return out


def _filter(num, den, x):
    """``lfilter(num, den, x)`` (one home for the recursive filters: :mod:`mpm_monitor.core.filters`)."""
    from .filters import lfilter

    return lfilter(num, den, x)


ZERO_ELEMENT = DiscreteElement(num=np.zeros(1), den=np.ones(1), delay=0)


#: A lag whose sample time is more than this many times its time constant changes the sampled response by
#: about ``tau / ts``, below rounding: it is left out (:func:`sample_parametric`).
NEGLIGIBLE_LAG = 1e13


def sample_parametric(gain: float, time_constant: float, delay_samples: int, sample_time: float,
                      lead: float = 0.0, time_constant2: float = 0.0, integrating: bool = False) -> DiscreteElement:
    """Exact zero-order-hold equivalent of a parametric element (see the module docstring).

    Parameters
    ----------
    gain : float
        ``K``: output units per input unit (per second when ``integrating``); 0 = no effect.
    time_constant, time_constant2 : float
        ``tau``, ``tau2`` in seconds, >= 0 (0 = absent; ``tau2`` only with ``tau``).
    delay_samples : int
        Dead time in whole samples, >= 0.
    sample_time : float
        Seconds per sample.
    lead : float
        ``lead`` in seconds (numerator ``lead s + 1``); needs a lag or an integrator to be proper.
    integrating : bool
        Add the pole at ``s = 0``.

    Returns
    -------
    DiscreteElement
    """
    k, tau, tau2, ts = float(gain), float(time_constant), float(time_constant2), float(sample_time)
    nd = int(delay_samples)
    if k == 0.0:
        return DiscreteElement(num=np.zeros(1), den=np.ones(1), delay=0)
    lags = [t for t in (tau, tau2) if t > 0]
    # A lag under 1/NEGLIGIBLE_LAG of the sample time changes the sampled response below rounding, and the
    # continuous form's coefficients (a tau of 1e-40 s) break the exact hold (NaN).
    # It is left out when what remains is still proper (another lag, an integrator, or no lead).
    quick = [t for t in lags if ts / t > NEGLIGIBLE_LAG]
    if quick and (len(quick) < len(lags) or integrating or lead == 0.0):
        lags = [t for t in lags if ts / t <= NEGLIGIBLE_LAG]
    if not lags and not integrating:
        if lead != 0.0:
            raise ValueError("a lead needs a lag or an integrator (the element would not be proper)")
        return DiscreteElement(num=np.array([k]), den=np.ones(1), delay=nd)
    if len(lags) == 1 and not integrating and lead == 0.0:
        a = math.exp(-ts / lags[0])
        return DiscreteElement(num=np.array([0.0, k * (1.0 - a)]), den=np.array([1.0, -a]), delay=nd)
    num_s = k * np.array([lead, 1.0]) if lead != 0.0 else np.array([k])
    den_s = np.ones(1)
    poles = []
    for t in lags:
        den_s = np.convolve(den_s, [t, 1.0])
        poles.append(-1.0 / t)
    if integrating:
        den_s = np.convolve(den_s, [1.0, 0.0])
        poles.append(0.0)
    A, B, C, D = _controllable_canonical(num_s, den_s)
    Ad, Bd = _zoh(A, B, ts)
    n = A.shape[0]
    h = np.empty(n + 1)
    h[0] = D
    ca = C.copy()
    for m in range(1, n + 1):
        h[m] = float(ca @ Bd)
        ca = ca @ Ad
    den_z = np.real(np.poly(np.exp(np.array(poles) * ts)))
    num_z = np.convolve(den_z, h)[:n + 1]
    return DiscreteElement(num=num_z, den=den_z, delay=nd)


def _controllable_canonical(num_s: np.ndarray, den_s: np.ndarray):
    """``(A, B, C, D)`` of ``num_s(s) / den_s(s)`` (coefficients highest power first, proper)."""
    den = np.asarray(den_s, float)
    num = np.asarray(num_s, float)
    lead_coef = den[0]
    den = den / lead_coef
    num = num / lead_coef
    n = den.size - 1
    num = np.concatenate([np.zeros(n + 1 - num.size), num])
    D = num[0]
    num_strict = num[1:] - D * den[1:]             # strictly proper part, highest power first
    A = np.zeros((n, n))
    A[0, :] = -den[1:]
    if n > 1:
        A[1:, :-1] = np.eye(n - 1)
    B = np.zeros(n)
    B[0] = 1.0
    C = num_strict.copy()
    return A, B, C, float(D)


def _zoh(A: np.ndarray, B: np.ndarray, ts: float):
    """``(Ad, Bd)`` of the zero-order hold: ``expm([[A, B], [0, 0]] T)`` (Van Loan, 1978)."""
    import scipy.linalg as sla

    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A * ts
    M[:n, n] = B * ts
    E = sla.expm(M)
    return E[:n, :n], E[:n, n]


def pulse_response(coefficients) -> np.ndarray:
    """``h_l = s_l - s_(l-1)`` of step-response samples ``s`` (the sample before the first taken as 0).

    Parameters
    ----------
    coefficients : array_like, shape (N,)
        Consecutive samples of a unit-step response (output units per input unit).

    Returns
    -------
    ndarray, shape (N,)
        The response to a unit pulse at the same samples.
    """
    s = np.asarray(coefficients, dtype=float).ravel()
    return np.diff(np.concatenate([[0.0], s]))


def from_step_response(coefficients, ramp: bool = False) -> DiscreteElement:
    """The element of a step-response model (see the module docstring).

    Parameters
    ----------
    coefficients : array_like, shape (N,)
        ``s_1 .. s_N``: output change 1 .. N samples after a unit step at sample 0.
    ramp : bool
        Beyond ``N`` the output keeps the last slope ``s_N - s_(N-1)`` instead of holding ``s_N``.

    Returns
    -------
    DiscreteElement
        ``num = [0, h_1 .. h_N]`` with ``h_l = s_l - s_(l-1)`` (``s_0 = 0``), ``den = 1``; with ``ramp``
        ``num (1 - z^-1) + h_N z^-(N+1)`` over ``1 - z^-1``.  Leading zeros become ``delay``.
    """
    s = np.asarray(coefficients, dtype=float).ravel()
    h = pulse_response(s)
    num = np.concatenate([[0.0], h])
    den = np.ones(1)
    if ramp and s.size:
        num = np.concatenate([np.convolve(num, [1.0, -1.0]), [0.0]])
        num[s.size + 1] += h[-1]
        den = np.array([1.0, -1.0])
    if not np.any(num != 0):
        return DiscreteElement(num=np.zeros(1), den=np.ones(1), delay=0)
    first = int(np.flatnonzero(num != 0)[0])
    return DiscreteElement(num=num[first:], den=den, delay=first)


def continuous_frequency_response(omega: np.ndarray, gain: float, time_constant: float, delay: float,
                                  lead: float = 0.0, time_constant2: float = 0.0,
                                  integrating: bool = False) -> np.ndarray:
    """``G(j omega)`` of a parametric element, omega in rad/s, shape (n_freq,) (delay in seconds)."""
    s = 1j * np.asarray(omega, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = gain * (lead * s + 1.0) * np.exp(-s * delay) / ((time_constant * s + 1.0) * (time_constant2 * s + 1.0))
        return g / s if integrating else g


def dead_time_samples(coefficients, tolerance: Optional[float] = None) -> int:
    """Samples before a step response first moves: the dead time of a step-response element.

    Parameters
    ----------
    coefficients : array_like, shape (N,)
        ``s_1 .. s_N``.
    tolerance : float, optional
        A coefficient counts as moved when ``|s_k| > tolerance``; default ``1e-9 max |s|``.
    """
    s = np.abs(np.asarray(coefficients, dtype=float).ravel())
    if s.size == 0 or not np.any(s > 0):
        return 0
    tol = 1e-9 * s.max() if tolerance is None else tolerance
    moved = np.flatnonzero(s > tol)
    return int(moved[0]) if moved.size else 0
