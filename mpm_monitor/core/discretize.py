"""Exact zero-order-hold discretization of a first-order-plus-dead-time transfer matrix.

For an element ``K e^{-theta s} / (tau s + 1)`` with ``theta = n_d T`` (an integer number of
samples), the zero-order-hold (step-invariant) equivalent is (Franklin, Powell & Workman, *Digital
Control of Dynamic Systems*, 3rd ed., section 4.3)::

    G(z) = K (1 - a) z^{-(n_d + 1)} / (1 - a z^{-1}),   a = exp(-T / tau)     (tau > 0)
    G(z) = K z^{-n_d}                                                          (tau = 0)

In state-space form every element with a non-zero gain has one lag state ``s`` with
``s(k+1) = a s(k) + b u_j(k - m)`` and contributes ``s(k)`` to its output, where for ``tau > 0``
``b = K (1 - a)`` and ``m = n_d``; for ``tau = 0`` ``a = 0``, ``b = K`` and ``m = n_d - 1``; a static
element without delay (``tau = 0, n_d = 0``) is a direct feed-through ``D``.  The delayed inputs
``u_j(k - m)`` come from one shift register per input, shared by the elements of its column.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from .model import PlantModel


@dataclasses.dataclass(frozen=True)
class DiscreteFopdt:
    """Element-wise discrete form of a :class:`PlantModel`.

    Attributes
    ----------
    pole : ndarray, shape (n_outputs, n_inputs)
        ``a`` of each element (0 for static elements).
    numerator : ndarray, shape (n_outputs, n_inputs)
        ``b`` of each element (0 where the gain is 0 or the element is a feed-through).
    input_lag : ndarray of int, shape (n_outputs, n_inputs)
        ``m``: the state update uses ``u_j(k - m)``.
    feedthrough : ndarray, shape (n_outputs, n_inputs)
        ``D``: direct feed-through of static elements without delay.
    active : ndarray of bool, shape (n_outputs, n_inputs)
        Elements with a lag state (non-zero gain and not a pure feed-through).
    """

    pole: np.ndarray
    numerator: np.ndarray
    input_lag: np.ndarray
    feedthrough: np.ndarray
    active: np.ndarray

    @property
    def strictly_proper(self) -> bool:
        """True when no element is a direct feed-through."""
        return not np.any(self.feedthrough != 0)


def discretize(model: PlantModel) -> DiscreteFopdt:
    """Zero-order-hold discretization of every element of ``model``.

    Parameters
    ----------
    model : PlantModel
        The continuous-time model; its delays are multiples of ``model.sample_time``.

    Returns
    -------
    DiscreteFopdt
        Element-wise poles, numerators, input lags (samples) and feed-through.
    """
    ts = model.sample_time
    gain, tau, nd = model.gain, model.time_constant, model.delay_samples
    lagged = tau > 0
    with np.errstate(divide="ignore", over="ignore"):
        a = np.where(lagged, np.exp(-ts / np.where(lagged, tau, 1.0)), 0.0)
    nonzero = gain != 0
    static_direct = nonzero & ~lagged & (nd == 0)
    active = nonzero & ~static_direct
    b = np.where(active, np.where(lagged, gain * (1.0 - a), gain), 0.0)
    m = np.where(lagged, nd, np.maximum(nd - 1, 0))
    m = np.where(active, m, 0).astype(int)
    d = np.where(static_direct, gain, 0.0)
    a = np.where(active, a, 0.0)
    return DiscreteFopdt(pole=a, numerator=b, input_lag=m, feedthrough=d, active=active)


@dataclasses.dataclass(frozen=True)
class StateSpace:
    """A discrete-time state-space model ``x(k+1) = A x(k) + B u(k)``, ``y(k) = C x(k) + D u(k)``.

    Attributes
    ----------
    A : ndarray, shape (n_states, n_states)
    B : ndarray, shape (n_states, n_inputs)
    C : ndarray, shape (n_outputs, n_states)
    D : ndarray, shape (n_outputs, n_inputs)
    sample_time : float
        Seconds per sample.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    sample_time: float

    @property
    def n_states(self) -> int:
        return self.A.shape[0]


def state_space(model: PlantModel) -> StateSpace:
    """Dense state-space realization of the discretized model (see the module docstring).

    The state holds the lag states of the active elements (row-major order) followed by, for each
    input ``j``, the shift register ``u_j(k-1), ..., u_j(k-L_j)`` with ``L_j`` the largest input lag
    of column ``j``.

    Parameters
    ----------
    model : PlantModel

    Returns
    -------
    StateSpace
        Exact ZOH equivalent including the integer delays.
    """
    disc = discretize(model)
    ny, nu = model.n_outputs, model.n_inputs
    elems = [(i, j) for i in range(ny) for j in range(nu) if disc.active[i, j]]
    n_lag = len(elems)
    reg_len = [int(np.max(disc.input_lag[:, j], initial=0, where=disc.active[:, j])) for j in range(nu)]
    # Start index of each input's shift register.
    reg_start = []
    pos = n_lag
    for j in range(nu):
        reg_start.append(pos)
        pos += reg_len[j]
    nx = pos
    A = np.zeros((nx, nx))
    B = np.zeros((nx, nu))
    C = np.zeros((ny, nx))
    for s, (i, j) in enumerate(elems):
        A[s, s] = disc.pole[i, j]
        m = disc.input_lag[i, j]
        if m == 0:
            B[s, j] = disc.numerator[i, j]
        else:
            A[s, reg_start[j] + m - 1] = disc.numerator[i, j]
        C[i, s] = 1.0
    for j in range(nu):
        if reg_len[j] == 0:
            continue
        r0 = reg_start[j]
        B[r0, j] = 1.0
        for l in range(1, reg_len[j]):
            A[r0 + l, r0 + l - 1] = 1.0
    return StateSpace(A=A, B=B, C=C, D=disc.feedthrough.copy(), sample_time=model.sample_time)


def simulate(model: PlantModel, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """Response of the discretized model to an input sequence, from rest (or from ``x0``).

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_inputs)
        Input in deviation variables, held constant over each sample.
    x0 : ndarray, shape (n_states,), optional
        Initial state of :func:`state_space` (zeros by default).

    Returns
    -------
    ndarray, shape (n_samples, n_outputs)
        ``y(k)`` for ``k = 0 .. n_samples - 1``.
    """
    ss = state_space(model)
    return simulate_state_space(ss, u, x0)


def simulate_state_space(ss: StateSpace, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """Response of a :class:`StateSpace` to ``u`` of shape (n_samples, n_inputs)."""
    from scipy import signal

    u = np.asarray(u, dtype=float)
    n = u.shape[0]
    ny = ss.C.shape[0]
    if n == 0:
        return np.zeros((0, ny))
    if ss.n_states == 0:
        return u @ ss.D.T
    x0 = np.zeros(ss.n_states) if x0 is None else np.asarray(x0, dtype=float)
    if n == 1:
        return (ss.C @ x0 + ss.D @ u[0])[None, :]
    _, y, _ = signal.dlsim((ss.A, ss.B, ss.C, ss.D, ss.sample_time), u, x0=x0)
    return np.asarray(y).reshape(n, ny)


def element_response(disc: DiscreteFopdt, u: np.ndarray, state: Optional[np.ndarray] = None,
                     past: Optional[np.ndarray] = None, rows: Optional[Sequence[int]] = None) -> np.ndarray:
    """Response of the element-wise form of :func:`discretize` to ``u``: the one element-wise simulation.

    ::

        s_ij(k+1) = a_ij s_ij(k) + b_ij u_j(k - m_ij),    y_i(k) = sum_j s_ij(k) + D_ij u_j(k)

    one first-order filter per element (``scipy.signal.lfilter``): ``O(n_samples n_outputs n_inputs)``
    instead of the ``O(n_samples n_states^2)`` of the dense realisation :func:`state_space`, with
    ``n_states`` up to a few hundred for a 20x20 plant with delays.  The results agree with it to
    rounding (the sums are taken in another order).

    Parameters
    ----------
    disc : DiscreteFopdt
    u : ndarray, shape (n_samples, n_inputs)
        Inputs ``u(0) .. u(n_samples - 1)``, held constant over each sample.
    state : ndarray, shape (n_outputs, n_inputs), optional
        Element states ``s_ij(0)``; updated in place to ``s_ij(n_samples)`` (the rows computed).
        Default: zeros (from rest).
    past : ndarray, shape (n_past, n_inputs), optional
        The inputs before ``u``, oldest first (``u(-n_past) .. u(-1)``), with ``n_past`` at least
        the largest input lag ``m_ij``.  Default: zeros.
    rows : sequence of int, optional
        Outputs computed (default: all of them, in order).

    Returns
    -------
    ndarray, shape (n_samples, len(rows))
        ``y_i(k)`` for ``k = 0 .. n_samples - 1``.
    """
    from .filters import lfilter

    u = np.asarray(u, dtype=float)
    n, nu = u.shape
    rows = range(disc.pole.shape[0]) if rows is None else rows
    if n == 0:
        return np.zeros((0, len(rows)))
    lag = disc.input_lag
    rest = state is None and past is None
    if rest:
        h, ext_t = 0, np.ascontiguousarray(u.T)                    # one contiguous row per input
    else:
        past = np.zeros((int(lag.max(initial=0)), nu)) if past is None else past
        h, ext_t = past.shape[0], np.ascontiguousarray(np.vstack([past, u]).T)
    y_t = np.zeros((len(rows), n))
    for r, i in enumerate(rows):
        for j in np.flatnonzero(disc.active[i]):
            m = int(lag[i, j])
            # s_ij(k) filters u_j(k - m - 1): s[k] = b u_j(k - m - 1) + a s[k - 1].
            num, den = [0.0, disc.numerator[i, j]], [1.0, -disc.pole[i, j]]
            if rest:               # s_ij(k) is zero up to k = m
                if m + 1 < n:
                    y_t[r, m:] += lfilter(num, den, ext_t[j, :n - m])
                continue
            s, zf = lfilter(num, den, ext_t[j, h - m:h - m + n], zi=[0.0 if state is None else state[i, j]])
            y_t[r] += s
            if state is not None:
                state[i, j] = zf[0]
    y = y_t.T.copy()
    feedthrough = disc.feedthrough[list(rows)]
    if np.any(feedthrough != 0):
        y += u @ feedthrough.T
    return y


def simulate_elements(model: PlantModel, u: np.ndarray, rows: Optional[Sequence[int]] = None) -> np.ndarray:
    """Response of the discretized model from rest, element by element (:func:`element_response`).

    The same response as :func:`simulate` without ``x0`` (the dense realisation of
    :func:`state_space`), to rounding, at a fraction of its cost.

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_inputs)
        Input in deviation variables, held constant over each sample.
    rows : sequence of int, optional
        Outputs computed (default: all of them).

    Returns
    -------
    ndarray, shape (n_samples, n_outputs) (or (n_samples, len(rows)))
        ``y(k)`` for ``k = 0 .. n_samples - 1``.
    """
    return element_response(discretize(model), u, rows=rows)


class ModelPredictor:
    """The controller's model run sample by sample from rest: ``yhat = Phat u``.

    The element-wise form of :func:`discretize` (see :func:`element_response`), which is the dense
    realisation of :func:`state_space` with its shift registers replaced by a short input history:
    ``O(n_outputs n_inputs)`` per sample.  :meth:`step` advances one sample, :meth:`run` a block.

    Parameters
    ----------
    model : PlantModel
    """

    def __init__(self, model: PlantModel):
        disc = discretize(model)
        self.disc = disc
        self.ny, self.nu = model.n_outputs, model.n_inputs
        self._pole = np.where(disc.active, disc.pole, 0.0)
        self._numerator = np.where(disc.active, disc.numerator, 0.0)
        self._lag = np.where(disc.active, disc.input_lag, 0).astype(int)
        self._feedthrough = np.asarray(disc.feedthrough, dtype=float)
        self._has_feedthrough = bool(np.any(self._feedthrough != 0))
        self.n_history = int(self._lag.max(initial=0))
        # u_j(k - m_ij) is entry (n_history - m_ij, j) of the history [u(k - n_history) .. u(k)].
        self._delayed_index = ((self.n_history - self._lag) * self.nu + np.arange(self.nu)).ravel()
        self.reset()

    def reset(self) -> None:
        """Back to rest: zero element states and zero past inputs."""
        self.state = np.zeros((self.ny, self.nu))
        self._history = np.zeros((self.n_history + 1, self.nu))   # u(k - n_history) .. u(k - 1), scratch row

    def step(self, u: np.ndarray) -> np.ndarray:
        """``yhat(k)`` of shape (n_outputs,) for the input ``u(k)``, then advance to ``k + 1``."""
        hist = self._history
        hist[-1] = u
        delayed = hist.ravel()[self._delayed_index].reshape(self.ny, self.nu)
        yhat = self.state.sum(axis=1)
        if self._has_feedthrough:
            yhat = yhat + self._feedthrough @ u
        self.state = self._pole * self.state + self._numerator * delayed
        hist[:-1] = hist[1:]
        return yhat

    def run(self, u: np.ndarray) -> np.ndarray:
        """``yhat`` of shape (n_samples, n_outputs) for the inputs ``u`` of shape (n_samples, n_inputs)."""
        u = np.asarray(u, dtype=float)
        h = self.n_history
        yhat = element_response(self.disc, u, state=self.state, past=self._history[:-1])
        if h:
            tail = np.vstack([self._history[:-1], u])[-h:] if u.shape[0] < h else u[-h:]
            self._history[:-1] = tail
        return yhat


def frequency_response(model: PlantModel, omega: np.ndarray, discrete: bool = True) -> np.ndarray:
    """Frequency response of every element.

    Parameters
    ----------
    model : PlantModel
    omega : ndarray, shape (n_freq,)
        Frequencies in rad/s (continuous) or rad/sample (discrete).
    discrete : bool
        True: the ZOH equivalent ``G(e^{j omega})`` with omega in rad/sample; False: the continuous
        ``K e^{-j omega theta} / (j omega tau + 1)`` with omega in rad/s.

    Returns
    -------
    ndarray of complex, shape (n_freq, n_outputs, n_inputs)
    """
    omega = np.asarray(omega, dtype=float)
    w = omega[:, None, None]
    if not discrete:
        return model.gain * np.exp(-1j * w * model.delay) / (1j * w * model.time_constant + 1.0)
    disc = discretize(model)
    z1 = np.exp(-1j * w)  # z^-1
    # s(k+1) = a s(k) + b u(k - m)  =>  S = b z^{-(m+1)} / (1 - a z^{-1})
    resp = disc.numerator * z1 ** (disc.input_lag + 1) / (1.0 - disc.pole * z1)
    resp = np.where(disc.active, resp, 0.0) + disc.feedthrough
    return resp


def settling_samples(model: PlantModel, fraction: float = 1e-3) -> int:
    """Samples after which every element's free response has decayed below ``fraction``.

    Parameters
    ----------
    model : PlantModel
    fraction : float
        Remaining fraction of the initial free response, in (0, 1).

    Returns
    -------
    int
        ``max_ij (delay_ij + tau_ij ln(1/fraction) / T)`` rounded up, in samples.
    """
    tau = model.time_constant / model.sample_time
    n = model.delay_samples + np.ceil(tau * np.log(1.0 / fraction))
    n = np.where(model.gain != 0, n, 0)
    return int(np.max(n)) + 1
