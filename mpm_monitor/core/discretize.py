"""The model's transfer matrix in discrete time: element-wise simulation, state space, frequency response.

The columns of the model are its manipulated inputs, then its measured disturbances
(:attr:`~mpm_monitor.core.model.PlantModel.columns`); every signal called ``u`` here has one column
per model column.  Every element (output ``i``, column ``j``) is a
:class:`~mpm_monitor.core.elements.DiscreteElement` ``G_ij(z) = z^-delay num(z^-1) / den(z^-1)``,
whatever its structure (first order, lead, second lag, integrator, step response), the exact
zero-order-hold equivalent of the element (:mod:`mpm_monitor.core.elements`).  For simulation it
is split into a direct feed-through and a strictly proper part that acts on the column delayed by
``m_ij`` samples::

    G_ij(z) = D_ij + z^{-m_ij} c_ij(z^-1) / a_ij(z^-1),
    c_ij(z^-1) = c_1 z^-1 + ... + c_p z^-p,    a_ij(z^-1) = 1 + a_1 z^-1 + ... + a_n z^-n

with ``D_ij = num[0]`` when the element has neither delay nor leading zero (then ``m_ij = 0`` and
``c`` is the rest ``num - D den``), and otherwise ``D_ij = 0`` and ``m_ij`` one less than the
element's input lag (delay plus leading zeros of ``num``).  A first-order element
``K e^{-theta s} / (tau s + 1)`` with ``theta = n_d T`` is ``K (1 - a) z^{-(n_d + 1)} / (1 - a z^-1)``,
``a = exp(-T / tau)`` (Franklin, Powell & Workman, *Digital Control of Dynamic Systems*, 3rd ed.,
section 4.3): ``m = n_d``, ``c_1 = K (1 - a)``, ``a_1 = -a``; a static element with delay
``K z^{-n_d}`` has ``m = n_d - 1``, ``c_1 = K`` and no denominator.

Element-wise simulation (:func:`element_response`): each element filters its delayed column through
``c / a`` (:func:`mpm_monitor.core.filters.lfilter`); its *element state* is the state of that
filter (direct form II transposed, ``max(p, n)`` values; for a first-order element the lag state
``s(k+1) = a s(k) + b u_j(k - m)``).  A step-response element is a finite impulse response: no
denominator, ``p`` up to ``N``; a ramp element has the denominator ``1 - z^-1``.

State space (:func:`state_space`): every element with a strictly proper part has
``n_s = max(n, 1)`` states in observable canonical form::

    x_1(k+1) = -a_1 x_1(k) + x_2(k) + c_1 u_j(k - m)
    ...
    x_ns(k+1) = -a_ns x_1(k) + sum_{l >= ns} c_l u_j(k - m - (l - ns))

and contributes ``x_1(k)`` to ``y_i(k)``; the delayed values ``u_j(k - 1) .. u_j(k - L_j)`` come
from one shift register per column, shared by the elements of that column.  A first-order element
is a single state with ``A = a``, ``B = K (1 - a)`` (and a static element with delay a state with
``A = 0``), a step-response element one state fed by ``N`` taps of the register.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional, Sequence

import numpy as np

from .model import PlantModel

#: Poles within this distance of each other (in the z-plane) count as one repeated pole.
REPEATED_POLE_TOLERANCE = 1e-6
#: A pole above ``1 - INTEGRATOR_TOLERANCE`` is an integrator (a constant free response).
INTEGRATOR_TOLERANCE = 1e-9


def _split(el) -> tuple:
    """``(D, m, b, a)`` of a :class:`~mpm_monitor.core.elements.DiscreteElement` (see the module docstring).

    ``b = [0, c_1 .. c_p]`` and ``a = den`` are the filter of the strictly proper part on the
    column delayed by ``m``; ``b`` is None when the element has no strictly proper part.
    """
    if el.is_zero:
        return 0.0, 0, None, None
    num, den = el.num, el.den
    if el.delay == 0 and num[0] != 0:
        d = float(num[0])
        size = max(num.size, den.size)
        rest = np.zeros(size)
        rest[:num.size] = num
        rest[:den.size] -= d * den
        rest[0] = 0.0
        m = 0
    else:
        d = 0.0
        first = int(np.flatnonzero(num != 0)[0])
        rest = np.concatenate([[0.0], num[first:]])
        m = el.delay + first - 1
    nz = np.flatnonzero(rest != 0)
    if nz.size == 0:
        return d, 0, None, None
    return d, m, rest[:int(nz[-1]) + 1], den


def _split_of(model: PlantModel, i: int, j: int) -> tuple:
    """:func:`_split` of element (i, j), kept with the model's sampled elements (a copy of the model
    with another element changed keeps it, see :meth:`PlantModel.with_element`)."""
    cache = model._elements
    key = ("split", i, j)
    if key not in cache:
        cache[key] = _split(model.discrete_element(i, j))
    return cache[key]


@dataclasses.dataclass(frozen=True)
class DiscreteElements:
    """The model's elements in the split form of the module docstring.

    Attributes
    ----------
    elements : tuple of tuple of DiscreteElement
        ``elements[i][j]``, shape (n_outputs, n_columns).
    n_inputs : int
        The first ``n_inputs`` columns are the manipulated inputs, the others measured disturbances.
    feedthrough : ndarray, shape (n_outputs, n_columns)
        ``D_ij``.
    input_lag : ndarray of int, shape (n_outputs, n_columns)
        ``m_ij``: the strictly proper part reads ``u_j(k - m_ij)`` (0 where ``active`` is false).
    active : ndarray of bool, shape (n_outputs, n_columns)
        Elements with a strictly proper part (non-zero and not a pure feed-through).
    numerators, denominators : tuple of tuple of ndarray or None
        ``b = [0, c_1 .. c_p]`` and ``a = [1, a_1 .. a_n]`` of each active element (None elsewhere).
    """

    elements: tuple
    n_inputs: int
    feedthrough: np.ndarray
    input_lag: np.ndarray
    active: np.ndarray
    numerators: tuple
    denominators: tuple

    @property
    def n_outputs(self) -> int:
        return self.feedthrough.shape[0]

    @property
    def n_columns(self) -> int:
        return self.feedthrough.shape[1]

    @property
    def strictly_proper(self) -> bool:
        """True when no element is a direct feed-through."""
        return not np.any(self.feedthrough != 0)

    @property
    def first_order(self) -> np.ndarray:
        """Active elements of the form ``b z^{-(m+1)} / (1 - a z^-1)`` (``a`` may be 0), bool (n_outputs, n_columns)."""
        out = np.zeros(self.active.shape, dtype=bool)
        for i, j in zip(*np.nonzero(self.active)):
            out[i, j] = self.numerators[i][j].size <= 2 and self.denominators[i][j].size <= 2
        return out

    def _first_order_coefficient(self, which: str) -> np.ndarray:
        out = np.zeros(self.active.shape)
        for i, j in zip(*np.nonzero(self.active)):
            b, a = self.numerators[i][j], self.denominators[i][j]
            if b.size > 2 or a.size > 2:
                out[i, j] = np.nan
            elif which == "pole":
                out[i, j] = -a[1] if a.size == 2 else 0.0
            else:
                out[i, j] = b[1]
        return out

    @property
    def pole(self) -> np.ndarray:
        """``a`` of the first-order elements, shape (n_outputs, n_columns): 0 where not active, NaN
        where the element is not first order (see :attr:`first_order`; :meth:`poles` for every structure)."""
        return self._first_order_coefficient("pole")

    @property
    def numerator(self) -> np.ndarray:
        """``b`` of the first-order elements, shape (n_outputs, n_columns) (0 / NaN as :attr:`pole`)."""
        return self._first_order_coefficient("numerator")

    @property
    def state_order(self) -> np.ndarray:
        """Length of each element's filter state, ``max(p, n)``, int (n_outputs, n_columns) (0 where not active)."""
        out = np.zeros(self.active.shape, dtype=int)
        for i, j in zip(*np.nonzero(self.active)):
            out[i, j] = max(self.numerators[i][j].size, self.denominators[i][j].size) - 1
        return out

    @functools.cached_property
    def register_length(self) -> np.ndarray:
        """``L_j``: past values of each column the state space keeps, int (n_columns,) (read-only; computed once)."""
        out = np.zeros(self.n_columns, dtype=int)
        for i, j in zip(*np.nonzero(self.active)):
            out[j] = max(out[j], int(self.input_lag[i, j]) + self._taps_beyond_states(i, j))
        out.setflags(write=False)
        return out

    def _taps_beyond_states(self, i: int, j: int) -> int:
        """Numerator taps of element (i, j) past its input lag that its denominator states do not hold (the
        shift register it needs beyond the input lag; a finite impulse response's whole length but one)."""
        n_s = max(self.denominators[i][j].size - 1, 1)
        return max(self.numerators[i][j].size - 1 - n_s, 0)

    @property
    def memory(self) -> int:
        """Samples after which the inputs before a record act on the outputs only through the elements'
        denominator states (free responses ``a^k``): the longest shift register."""
        return int(self.register_length.max(initial=0))

    @functools.cached_property
    def transient_onset(self) -> int:
        """Samples after which the inputs before a record act on the outputs only through responses that
        decay as a free response does: :attr:`memory` for the elements with a denominator, the input lag
        (the dead time) for a finite impulse response (a step-response element, whose coefficients after
        its dead time act as the free response of a parametric element; its settling is
        :func:`settling_samples`'s).  Equal to :attr:`memory` unless a finite impulse response has more
        than two coefficients."""
        out = 0
        for i, j in zip(*np.nonzero(self.active)):
            fir = self.denominators[i][j].size == 1
            out = max(out, int(self.input_lag[i, j]) + (0 if fir else self._taps_beyond_states(i, j)))
        return out

    def poles(self, i: int, j: int) -> np.ndarray:
        """Poles of the strictly proper part of element (i, j) in the z-plane, shape (n,) (exact for first order)."""
        if not self.active[i, j]:
            return np.zeros(0)
        a = self.denominators[i][j]
        if a.size == 1:
            return np.zeros(0)
        if a.size == 2:
            return np.array([-a[1]])
        return np.roots(a)

    def lag_poles(self, i: int) -> dict:
        """The decaying real poles of row ``i``'s elements: ``{pole: multiplicity}``, poles in (0, 1).

        Each element's poles are rounded to 12 digits; poles of one element closer than
        :data:`REPEATED_POLE_TOLERANCE` are one repeated pole; across elements a pole keeps its
        largest multiplicity.  Integrators (pole 1), poles at 0 and complex poles are left out.
        """
        out = {}
        for j in np.flatnonzero(self.active[i]):
            p = self.poles(i, j)
            p = np.real(p[np.abs(np.imag(p)) < REPEATED_POLE_TOLERANCE])
            clusters = []
            for v in np.sort(p):
                if clusters and v - clusters[-1][-1] < REPEATED_POLE_TOLERANCE:
                    clusters[-1].append(v)
                else:
                    clusters.append([v])
            for c in clusters:
                v = float(np.round(np.mean(c) if len(c) > 1 else c[0], 12))
                if 0.0 < v < 1.0 - INTEGRATOR_TOLERANCE:
                    out[v] = max(out.get(v, 0), len(c))
        return dict(sorted(out.items()))


def discretize(model: PlantModel) -> DiscreteElements:
    """The split form (module docstring) of every element of ``model`` (cached on the model).

    Parameters
    ----------
    model : PlantModel
        Any structure; delays are multiples of ``model.sample_time``.

    Returns
    -------
    DiscreteElements
    """
    cache = model._derived
    if "discrete" not in cache:
        ny, nc = model.n_outputs, model.n_columns
        d = np.zeros((ny, nc))
        m = np.zeros((ny, nc), dtype=int)
        active = np.zeros((ny, nc), dtype=bool)
        els, nums, dens = [], [], []
        for i in range(ny):
            row_el, row_b, row_a = [], [], []
            for j in range(nc):
                el = model.discrete_element(i, j)
                d[i, j], mij, b, a = _split_of(model, i, j)
                active[i, j] = b is not None
                m[i, j] = mij if b is not None else 0
                row_el.append(el)
                row_b.append(b)
                row_a.append(a)
            els.append(tuple(row_el))
            nums.append(tuple(row_b))
            dens.append(tuple(row_a))
        for arr in (d, m, active):
            arr.setflags(write=False)
        cache["discrete"] = DiscreteElements(elements=tuple(els), n_inputs=model.n_inputs, feedthrough=d,
                                             input_lag=m, active=active, numerators=tuple(nums),
                                             denominators=tuple(dens))
    return cache["discrete"]


@dataclasses.dataclass(frozen=True)
class StateSpace:
    """A discrete-time state-space model ``x(k+1) = A x(k) + B u(k)``, ``y(k) = C x(k) + D u(k)``.

    ``u`` holds the model's columns: the manipulated inputs, then the measured disturbances
    (:attr:`B_inputs`, :attr:`B_disturbances` split them).

    Attributes
    ----------
    A : ndarray, shape (n_states, n_states)
    B : ndarray, shape (n_states, n_columns)
    C : ndarray, shape (n_outputs, n_states)
    D : ndarray, shape (n_outputs, n_columns)
    sample_time : float
        Seconds per sample.
    n_inputs : int, optional
        The first ``n_inputs`` columns of ``B`` and ``D`` are the manipulated inputs; default all.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    sample_time: float
    n_inputs: Optional[int] = None

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def _nu(self) -> int:
        return self.B.shape[1] if self.n_inputs is None else self.n_inputs

    @property
    def B_inputs(self) -> np.ndarray:
        """The columns of ``B`` of the manipulated inputs, shape (n_states, n_inputs)."""
        return self.B[:, :self._nu]

    @property
    def B_disturbances(self) -> np.ndarray:
        """The columns of ``B`` of the measured disturbances, shape (n_states, n_disturbances)."""
        return self.B[:, self._nu:]

    @property
    def D_inputs(self) -> np.ndarray:
        """The columns of ``D`` of the manipulated inputs, shape (n_outputs, n_inputs)."""
        return self.D[:, :self._nu]

    @property
    def D_disturbances(self) -> np.ndarray:
        """The columns of ``D`` of the measured disturbances, shape (n_outputs, n_disturbances)."""
        return self.D[:, self._nu:]


#: Most states :func:`state_space` builds: its matrices are dense (``A`` alone 8 bytes x n_states^2, 2 GiB here, and a
#: simulation builds the plant's and the controller's: 4 GB at 16,000 states).  A dead time of 100,000 samples made
#: numpy fail to allocate (``out of memory``, exit 1), 30,000 took 14 GB, 2^31 - 1 a traceback.
MAX_STATES = 2 ** 14


def _checked_state_count(model: PlantModel, disc) -> int:
    """The states of ``model``'s :func:`state_space` (``disc``: its :func:`discretize`): ``max(n, 1)`` per active
    element, then each column's shift register; :class:`~mpm_monitor.core.errors.ModelFileError` above
    :data:`MAX_STATES`, naming the element whose dead time (or step response) makes the longest shift register."""
    nx = sum(max(disc.denominators[i][j].size - 1, 1) for i in range(model.n_outputs)
             for j in range(model.n_columns) if disc.active[i, j]) + int(np.sum(disc.register_length))
    if nx > MAX_STATES:
        _refuse_states(model, disc, nx)
    return nx


def _refuse_states(model: PlantModel, disc, nx: int) -> None:
    """Raise :class:`~mpm_monitor.core.errors.ModelFileError` for a state space of ``nx`` > :data:`MAX_STATES` states,
    naming the element whose dead time (or step response) makes the longest shift register (a column's past values)."""
    from .errors import ModelFileError

    size = f"{nx:,} states ({8 * nx * nx / 2 ** 30:,.0f} GiB as the dense matrix A)"
    reg_len = disc.register_length
    j = int(np.argmax(reg_len))
    if int(reg_len[j]) < nx // (2 * max(model.n_columns, 1)):
        raise ModelFileError(f"simulation: the model's state space would have {size}; a simulation holds at most "
                             f"{MAX_STATES:,}")
    i = max((int(disc.input_lag[i, j]) + disc._taps_beyond_states(i, j), i)
            for i in range(model.n_outputs) if disc.active[i, j])[1]
    where = f"row {i + 1} ({model.outputs[i]}), column {j + 1} ({model.columns[j]})"
    if model.is_step_response:
        what, fits = f"key 'step_response': {where}: a response of {model.step_length:,} coefficients", "responses"
    else:
        what, fits = f"key 'delay': {where}: a dead time of {int(model.delay_samples[i, j]):,} samples", "dead times"
    raise ModelFileError(f"simulation: {what} (the model's longest) makes its state space {size}; a simulation holds "
                         f"at most {MAX_STATES:,} ({fits} up to about {MAX_STATES // 1000 * 1000:,} samples)")


def check_state_count(model: PlantModel) -> None:
    """Refuse a model whose :func:`state_space` would hold more than :data:`MAX_STATES` states, before building it.

    Parameters
    ----------
    model : PlantModel

    Raises
    ------
    ModelFileError
        The message of :func:`state_space`'s refusal (``simulation: ...``, naming the element).
    """
    _checked_state_count(model, discretize(model))


def state_space(model: PlantModel) -> StateSpace:
    """Dense state-space realisation of the model over all its columns (see the module docstring).

    The state holds the states of the active elements (row-major order, ``max(n, 1)`` each), then,
    for each column ``j``, the shift register ``u_j(k-1), ..., u_j(k-L_j)``.  For a model of
    first-order elements this is one lag state per element and a register as long as the column's
    longest input lag.

    Parameters
    ----------
    model : PlantModel

    Returns
    -------
    StateSpace
        Exact ZOH equivalent including the integer delays; ``n_inputs`` set to the model's.
    """
    disc = discretize(model)
    _checked_state_count(model, disc)           # refused before anything is allocated
    ny, nc = model.n_outputs, model.n_columns
    elems = [(i, j) for i in range(ny) for j in range(nc) if disc.active[i, j]]
    n_s = {e: max(disc.denominators[e[0]][e[1]].size - 1, 1) for e in elems}
    el_start, pos = {}, 0
    for e in elems:
        el_start[e] = pos
        pos += n_s[e]
    reg_len = disc.register_length
    reg_start = []
    for j in range(nc):
        reg_start.append(pos)
        pos += int(reg_len[j])
    nx = pos
    A = np.zeros((nx, nx))
    B = np.zeros((nx, nc))
    C = np.zeros((ny, nx))
    for (i, j) in elems:
        s0, ns = el_start[(i, j)], n_s[(i, j)]
        a = disc.denominators[i][j]
        c = disc.numerators[i][j][1:]
        m = int(disc.input_lag[i, j])
        for q in range(ns):
            A[s0 + q, s0] = -a[q + 1] if q + 1 < a.size else 0.0
            if q + 1 < ns:
                A[s0 + q, s0 + q + 1] = 1.0
        # c_l feeds state min(l, ns) with u_j(k - m - max(l - ns, 0)).
        for l_, cl in enumerate(c, start=1):
            if cl == 0.0:
                continue
            row = s0 + min(l_, ns) - 1
            back = m + max(l_ - ns, 0)
            if back == 0:
                B[row, j] += cl
            else:
                A[row, reg_start[j] + back - 1] += cl
        C[i, s0] = 1.0
    for j in range(nc):
        if reg_len[j] == 0:
            continue
        r0 = reg_start[j]
        B[r0, j] = 1.0
        for l_ in range(1, int(reg_len[j])):
            A[r0 + l_, r0 + l_ - 1] = 1.0
    return StateSpace(A=A, B=B, C=C, D=np.array(disc.feedthrough), sample_time=model.sample_time,
                      n_inputs=model.n_inputs)


def simulate(model: PlantModel, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """Response of the discretized model to its columns, from rest (or from ``x0``).

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
        Inputs then measured disturbances, in deviation variables, held constant over each sample.
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
    """Response of a :class:`StateSpace` to ``u`` of shape (n_samples, n_columns)."""
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


def element_response(disc: DiscreteElements, u: np.ndarray, state: Optional[np.ndarray] = None,
                     past: Optional[np.ndarray] = None, rows: Optional[Sequence[int]] = None) -> np.ndarray:
    """Response of the elements of :func:`discretize` to ``u``: the one element-wise simulation.

    ::

        y_i(k) = sum_j [ (c_ij / a_ij)(q) u_j(k - m_ij) + D_ij u_j(k) ]

    one filter per element (:func:`mpm_monitor.core.filters.lfilter`): ``O(n_samples n_outputs
    n_columns)`` instead of the ``O(n_samples n_states^2)`` of the dense realisation
    :func:`state_space`, with ``n_states`` up to a few hundred for a 20x20 plant with delays.  The
    results agree with it to rounding (the sums are taken in another order).  Exact for every
    structure: step-response elements are finite impulse responses, integrators have the pole 1.

    Parameters
    ----------
    disc : DiscreteElements
    u : ndarray, shape (n_samples, n_columns)
        Inputs then measured disturbances ``u(0) .. u(n_samples - 1)``, held constant over each sample.
    state : ndarray, shape (n_outputs, n_columns, n_state) or (n_outputs, n_columns), optional
        Element states at sample 0 (each element's filter state, its first
        ``state_order[i, j]`` entries; ``n_state`` at least the largest); updated in place to
        those at ``n_samples`` (the rows computed).  Two-dimensional when every element has at most
        one (a model of first-order elements).  Default: zeros (from rest).
    past : ndarray, shape (n_past, n_columns), optional
        The columns before ``u``, oldest first (``u(-n_past) .. u(-1)``), with ``n_past`` at least
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
    n, nc = u.shape
    rows = range(disc.n_outputs) if rows is None else rows
    if n == 0:
        return np.zeros((0, len(rows)))
    lag = disc.input_lag
    rest = state is None and past is None
    if rest:
        h, ext_t = 0, np.ascontiguousarray(u.T)                    # one contiguous row per column
    else:
        past = np.zeros((int(lag.max(initial=0)), nc)) if past is None else past
        h, ext_t = past.shape[0], np.ascontiguousarray(np.vstack([past, u]).T)
    st = None if state is None else (state[:, :, None] if state.ndim == 2 else state)
    y_t = np.zeros((len(rows), n))
    for r, i in enumerate(rows):
        for j in np.flatnonzero(disc.active[i]):
            m = int(lag[i, j])
            b, a = disc.numerators[i][j], disc.denominators[i][j]
            if rest:               # the filter output is zero up to k = m (b[0] = 0)
                if m + 1 < n:
                    y_t[r, m:] += lfilter(b, a, ext_t[j, :n - m])
                continue
            k = max(b.size, a.size) - 1
            zi = np.zeros(k) if st is None else st[i, j, :k]
            s, zf = lfilter(b, a, ext_t[j, h - m:h - m + n], zi=zi)
            y_t[r] += s
            if st is not None:
                st[i, j, :k] = zf
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
    u : ndarray, shape (n_samples, n_columns)
        Inputs then measured disturbances, in deviation variables, held constant over each sample.
    rows : sequence of int, optional
        Outputs computed (default: all of them).

    Returns
    -------
    ndarray, shape (n_samples, n_outputs) (or (n_samples, len(rows)))
        ``y(k)`` for ``k = 0 .. n_samples - 1``.
    """
    return element_response(discretize(model), u, rows=rows)


def model_columns(u: np.ndarray, dv: Optional[np.ndarray]) -> np.ndarray:
    """``[u | dv]``: the model's columns from the inputs and the measured disturbances (``u`` when there are none)."""
    if dv is None:
        return u
    dv = np.asarray(dv, dtype=float)
    if dv.ndim == u.ndim and dv.shape[-1] == 0:
        return u
    return np.concatenate([u, dv], axis=-1)


class ModelPredictor:
    """The controller's model run sample by sample from rest: ``yhat = Phat [u | dv]``.

    The element-wise form of :func:`discretize` (see :func:`element_response`), which is the dense
    realisation of :func:`state_space` with its shift registers replaced by a short history of the
    columns: ``O(n_outputs n_columns n_state)`` per sample.  :meth:`step` advances one sample,
    :meth:`run` a block; both can be mixed.

    Parameters
    ----------
    model : PlantModel
        Any structure, with or without measured disturbances.
    """

    def __init__(self, model: PlantModel):
        disc = discretize(model)
        self.disc = disc
        self.ny, self.nu, self.nc = model.n_outputs, model.n_inputs, model.n_columns
        self.nd = model.n_disturbances
        self._lag = np.where(disc.active, disc.input_lag, 0).astype(int)
        self._feedthrough = np.asarray(disc.feedthrough, dtype=float)
        self._has_feedthrough = bool(np.any(self._feedthrough != 0))
        self.n_history = int(self._lag.max(initial=0))
        self.n_state = max(int(disc.state_order.max(initial=0)), 1)
        self._first_order = bool(np.all(disc.first_order == disc.active))
        if self._first_order:
            self._pole = np.where(disc.active, disc.pole, 0.0)
            self._numerator = np.where(disc.active, disc.numerator, 0.0)
        else:
            # Coefficients 1 .. n_state of every element's filter, zero-padded (direct form II transposed).
            k = self.n_state
            self._b = np.zeros((self.ny, self.nc, k))
            self._a = np.zeros((self.ny, self.nc, k))
            for i, j in zip(*np.nonzero(disc.active)):
                b, a = disc.numerators[i][j], disc.denominators[i][j]
                self._b[i, j, :b.size - 1] = b[1:]
                self._a[i, j, :a.size - 1] = a[1:]
        # u_j(k - m_ij) is entry (n_history - m_ij, j) of the history [u(k - n_history) .. u(k)].
        self._delayed_index = ((self.n_history - self._lag) * self.nc + np.arange(self.nc)).ravel()
        self.reset()

    def reset(self) -> None:
        """Back to rest: zero element states and zero past columns."""
        self.state = np.zeros((self.ny, self.nc, self.n_state))
        self._history = np.zeros((self.n_history + 1, self.nc))   # u(k - n_history) .. u(k - 1), scratch row

    def _columns(self, u, dv):
        if dv is None and self.nd:
            raise ValueError(f"the model has {self.nd} measured disturbances: give dv")
        return model_columns(np.asarray(u, dtype=float), dv)

    def step(self, u: np.ndarray, dv: Optional[np.ndarray] = None) -> np.ndarray:
        """``yhat(k)`` of shape (n_outputs,) for ``u(k)`` (n_inputs,) and ``dv(k)`` (n_disturbances,), then advance."""
        x = self._columns(u, dv)
        hist = self._history
        hist[-1] = x
        delayed = hist.ravel()[self._delayed_index].reshape(self.ny, self.nc)
        if self._first_order:
            state = self.state[:, :, 0]
            yhat = state.sum(axis=1)
            self.state[:, :, 0] = self._pole * state + self._numerator * delayed
        else:
            z = self.state
            ye = z[:, :, 0].copy()
            yhat = ye.sum(axis=1)
            new = self._b * delayed[:, :, None] - self._a * ye[:, :, None]
            new[:, :, :-1] += z[:, :, 1:]
            self.state = new
        if self._has_feedthrough:
            yhat = yhat + self._feedthrough @ x
        hist[:-1] = hist[1:]
        return yhat

    def run(self, u: np.ndarray, dv: Optional[np.ndarray] = None) -> np.ndarray:
        """``yhat`` of shape (n_samples, n_outputs) for ``u`` (n_samples, n_inputs) and ``dv`` (n_samples, n_disturbances)."""
        x = self._columns(u, dv)
        h = self.n_history
        yhat = element_response(self.disc, x, state=self.state, past=self._history[:-1])
        if h:
            tail = np.vstack([self._history[:-1], x])[-h:] if x.shape[0] < h else x[-h:]
            self._history[:-1] = tail
        return yhat


def frequency_response(model: PlantModel, omega: np.ndarray, discrete: bool = True) -> np.ndarray:
    """Frequency response of every element, over all columns.

    Parameters
    ----------
    model : PlantModel
    omega : ndarray, shape (n_freq,)
        Frequencies in rad/sample (discrete) or rad/s (continuous).
    discrete : bool
        True: the ZOH equivalent ``G(e^{j omega})``; False: the continuous element
        ``K (lead j omega + 1) e^{-j omega theta} / ((tau j omega + 1)(tau2 j omega + 1))`` (divided by
        ``j omega`` when integrating).  A step-response model has no continuous form.

    Returns
    -------
    ndarray of complex, shape (n_freq, n_outputs, n_columns)
        Integrating elements are infinite (``inf + 0j``) at ``omega = 0``.

    Raises
    ------
    ValueError
        ``discrete=False`` for a step-response model.
    """
    from .elements import continuous_frequency_response

    omega = np.asarray(omega, dtype=float)
    if not discrete and model.is_step_response:
        raise ValueError("frequency_response: a step-response model has only a discrete form (discrete=True)")
    out = np.zeros((omega.size, model.n_outputs, model.n_columns), dtype=complex)
    present = model.present
    for i in range(model.n_outputs):
        for j in range(model.n_columns):
            if not present[i, j]:
                continue
            if discrete:
                el = model.discrete_element(i, j)
                out[:, i, j] = el.frequency_response(omega)
                if el.integrating:           # den(1) is 0 only to rounding for a higher-order element
                    out[omega == 0, i, j] = np.inf
            else:
                out[:, i, j] = continuous_frequency_response(
                    omega, model.gain[i, j], model.time_constant[i, j], model.delay[i, j],
                    lead=model.lead[i, j], time_constant2=model.time_constant2[i, j],
                    integrating=bool(model.integrating[i, j]))
    bad = ~np.isfinite(out)
    if np.any(bad):
        out[bad] = complex(np.inf, 0.0)
    return out


#: Cap of :func:`settling_samples` (far beyond any log): a lag so slow that its settling time overflows.
MAX_SETTLING_SAMPLES = 2 ** 53


def settling_samples(model: PlantModel, fraction: float = 1e-3) -> int:
    """Samples after which every element's free response has decayed below ``fraction``.

    The lag part only: an integrator never settles (its free response is a constant), a
    step-response element has no free response beyond its ``N`` samples.

    Parameters
    ----------
    model : PlantModel
    fraction : float
        Remaining fraction of the initial free response, in (0, 1).

    Returns
    -------
    int
        ``max_ij (delay_ij + (tau_ij + tau2_ij) ln(1/fraction) / T)`` rounded up, + 1, in samples
        (parametric elements); ``max_ij`` of the samples to the element's last impulse-response
        coefficient, + 1 (step-response elements; computed once per model).
    """
    present = model.present
    if model.is_step_response:
        key = ("settling_samples", "step_response")        # every fraction: no free response to decay
        out = model._derived.get(key)
        if out is None:
            n = []
            for i, j in zip(*np.nonzero(present)):
                el = model.discrete_element(i, j)
                n.append(el.delay + int(np.flatnonzero(el.num)[-1]) + 1)
            out = model._derived[key] = int(max(n, default=0)) + 1
        return out
    with np.errstate(over="ignore"):        # a lag of 1e308 s: never settles (capped below)
        tau = (model.time_constant + model.time_constant2) / model.sample_time
        n = model.delay_samples + np.ceil(tau * np.log(1.0 / fraction))
    n = np.where(present, np.minimum(n, MAX_SETTLING_SAMPLES), 0)
    return int(np.max(n)) + 1
