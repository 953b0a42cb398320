"""The prediction-error fit of the located elements of one output row (model-free).

:class:`_RowProblem` is the fit of the located elements of a row to ``z`` (the output minus the
row's fixed elements) with an AR noise model, the gains (and the lead coefficients ``K lead``) and
nuisance terms eliminated by variable projection; :func:`_search_row` searches its input lags on the
integer grid, its poles by least squares and its noise model, and records the lag profiles that
:func:`_lag_lr` and :func:`_lag_interval` read.  Each element is fitted in its form
(:class:`~mpm_monitor.core.repair.forms._Form`: lags, lead, integrator); the parameters convert
between seconds and the fit's ``(gain, poles, lead, lag)`` in :mod:`.forms`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..arx import lag_matrix, least_squares_ar
from ..discretize import REPEATED_POLE_TOLERANCE
from ..filters import lfilter
from .forms import _POLE_MAX, _POLE_MIN, FIRST_ORDER, _basis, _Form
from .lsq import least_squares_bounded, solver_scale, symmetric_pinv

#: Fewest cost samples of a segment of data with gaps that takes part in a fit (a shorter one would
#: mostly feed its own offset and free responses).
MIN_SEGMENT_ROWS = 20
#: The free responses ``a^k`` a row's fits keep for reuse take at most this many bytes (64 MiB; 838 poles' of
#: 10,000 cost samples), and at least :data:`POWER_CACHE_MIN` of them are kept.
POWER_CACHE_BYTES = 2 ** 26
POWER_CACHE_MIN = 32


class _TooShort(Exception):
    """The fit window is too short for the lags searched (turned into a warning)."""


@dataclasses.dataclass
class _ElementSpec:
    """Which parameters of a located element the fit may move.

    ``gain``, ``poles`` and ``lead`` are the held values (or the start values when free); ``window``
    is the inclusive range of input lags searched (``lo == hi`` holds the lag).  ``pole_free`` frees
    the shape: every lag of the form (as its pole) and its lead.
    """

    gain_free: bool
    pole_free: bool
    gain: float
    poles: tuple
    window: tuple
    form: _Form = FIRST_ORDER
    lead: float = 0.0

    @property
    def lag_free(self) -> bool:
        return self.window[0] != self.window[1]

    @property
    def linear(self) -> tuple:
        """The linear coefficients of the element in the fit: ``"K"`` (the gain) and/or ``"KL"``
        (``K lead``, when the lead is free); with the lead held, ``"K"`` multiplies ``G_a + lead G_b``."""
        lead_free = self.pole_free and self.form.lead
        if self.gain_free:
            return ("K", "KL") if lead_free else ("K",)
        return ("KL",) if lead_free else ()


@dataclasses.dataclass
class _Fit:
    """One converged fit of a row for given lags and noise model."""

    lags: tuple
    poles: np.ndarray   # (n_poles,): the poles of every located element, element after element
    coefs: np.ndarray   # (n_linear,): the free linear coefficients ("K", "KL") in element order
    gains: np.ndarray   # (n_located,)
    leads: np.ndarray   # (n_located,): seconds (0 without a lead)
    nuisance: np.ndarray
    ssr: float
    n_resid: int


class _RowProblem:
    """The prediction-error fit of the located elements of one row (see the module docstring).

    Parameters
    ----------
    z : ndarray, shape (n_samples,)
        Output minus the response of the row's fixed elements (from rest).
    u : ndarray, shape (n_samples, n_located)
        The columns (inputs or measured disturbances) of the located elements.
    specs : list of _ElementSpec
        One per located element.
    n_fit : int
        Samples ``0 .. n_fit - 1`` are used.
    skip : int
        Samples at the start left out of the cost: the largest input lag of the row (or the memory of
        its step-response elements), since the columns before the record are unknown.
    fixed_poles : dict
        ``{pole: multiplicity}`` of the row's fixed lag elements, whose free responses ``k^q a^k``
        are estimated.
    free_response : bool
        Estimate the free responses (the initial state) of the row.
    noise_order : int
        ``p`` of ``A(q)``.
    extra : ndarray, shape (n_samples, n_extra), optional
        Nuisance regressors for an unmeasured disturbance (a step, a ramp), filtered by ``A(q)``
        like the output, so that the disturbance is never absorbed by an element.
    sample_time : float
        Seconds per sample (to sample the forms other than first order).
    shared : dict, optional
        Arrays that depend only on the cost window and the poles (the free responses ``a^k``), kept
        across the problems of one row (:class:`~mpm_monitor.core.repair.row._RowData`).
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of samples ``(first, end)`` of the record (the samples of
        its segments stacked, in order).  Every segment is a record of its own: the filters restart
        from rest at its first sample, its first ``skip + p`` samples are left out of the cost, and it
        has its own offset and free responses (the state at its start is unknown, as at the start of
        a record).  Segments are cut at ``n_fit``; one with fewer than :data:`MIN_SEGMENT_ROWS` cost
        samples is left out.  Default: one record, ``(0, n_fit)``.
    segment_levels : bool
        With segments: an offset of each segment's own (a row with an integrator, whose level moves by
        the unknown inputs inside a gap), instead of one offset for all (a self-regulating row, whose
        level is the same on both sides of a gap: the state a gap leaves is in the free responses).

    Notes
    -----
    Filtering commutes, so ``A(q) G(q) u = G(q) (A(q) u)``: the inputs are prefiltered once per
    noise model.  For ``k >= p``, ``A(q) a^k = A(1/a) a^k``: a free response stays a free response
    with another (free) coefficient, and the cost window starts at ``skip + p``.  An integrator's free
    response is a constant, held in the offset.

    The search evaluates the cost many times with most of its parts unchanged: the free responses
    ``a^k`` (``k a^k``) of a pole and the unit responses of an element (for its poles, its lag and the
    noise model) are computed once and reused, and a pole fit takes its solution's cost and linear
    parameters from the solver's own evaluation there -- the same numbers: nothing is approximated.
    """

    #: Unit responses kept (the most recent), each ``n_fit - start`` floats.
    UNIT_CACHE_SIZE = 64
    #: Evaluations of a pole fit kept (:meth:`fit`), the solution's looked up there.
    RECENT_EVALUATIONS = 4

    def __init__(self, z, u, specs, n_fit, skip, fixed_poles, free_response, noise_order, extra=None,
                 sample_time=1.0, shared=None, segments=None, segment_levels=True):
        self.z = np.asarray(z, float)[:n_fit]
        self.extra = None if extra is None else np.asarray(extra, float).reshape(len(z), -1)[:n_fit]
        self.u = np.asarray(u, float)[:n_fit]
        self.specs = list(specs)
        self.ts = float(sample_time)
        self.n_fit = int(n_fit)
        self.p = int(noise_order)
        self.free = bool(free_response)
        self.start = int(skip) + self.p
        needed = max(150, 20 * (3 * len(self.specs) + self.p + 3))
        self.segments = None
        if segments is None:
            if self.n_fit - self.start < needed:
                raise _TooShort(f"{self.n_fit} samples are too few for input lags up to {skip} samples "
                                f"(at least {needed} beyond them needed)")
            self.kw = np.arange(self.start, self.n_fit, dtype=float)
            cache_key = ("powers", self.start, self.n_fit)
        else:
            self.segments = [(int(a), min(int(b), self.n_fit)) for a, b in segments
                             if min(int(b), self.n_fit) - int(a) - self.start >= MIN_SEGMENT_ROWS]
            n_cost = sum(b - a - self.start for a, b in self.segments)
            if n_cost < needed:
                raise _TooShort(f"{n_cost} samples of the spans between gaps are too few for input lags up to "
                                f"{skip} samples (at least {needed} beyond them needed)")
            # Local time of every cost sample in its segment, and where each segment's rows sit.
            self.kw = np.concatenate([np.arange(self.start, b - a, dtype=float) for a, b in self.segments])
            ends = np.cumsum([b - a - self.start for a, b in self.segments])
            self._blocks = list(zip(np.concatenate([[0], ends[:-1]]).tolist(), ends.tolist()))
            cache_key = ("powers", self.start, self.n_fit, tuple(self.segments))
        self._powers = {} if shared is None else shared.setdefault(cache_key, {})
        self._unit_cache = {}
        self._constant = None       # (noise model, _constant_part()) of the constant columns
        self._orders = {}           # _column_order
        self._moving = {}           # _varying's buffers, by their number of columns
        ones = np.ones_like(self.kw)
        cols = [self._spread(ones) if segment_levels else ones]
        if self.free:
            for a, mult in sorted(dict(fixed_poles).items()):
                if 0 < a < 1 and a ** self.start > 1e-12:
                    cols.extend(self._spread(self.kw ** q * self._power(a) if q else self._power(a))
                                for q in range(mult))
        self.fixed_cols = np.column_stack(cols)
        # Where each element's poles and linear coefficients sit in the flat vectors of the fit.
        self.slices, self.linear_index = [], []
        n_poles = n_lin = 0
        for spec in self.specs:
            self.slices.append(slice(n_poles, n_poles + spec.form.n_lags))
            n_poles += spec.form.n_lags
            self.linear_index.append(list(range(n_lin, n_lin + len(spec.linear))))
            n_lin += len(spec.linear)
        self.n_linear = n_lin
        self.pole_free_idx = [k for m, s in enumerate(self.specs) if s.pole_free
                              for k in range(self.slices[m].start, self.slices[m].stop)]
        self.set_ar(np.zeros(self.p))
        self.solver_scale = solver_scale(self.z)

    @property
    def n_located(self) -> int:
        return len(self.specs)

    @property
    def n_segments(self) -> int:
        """Segments the cost samples come from (1 for one record): each holds its own free responses
        (:meth:`_spread`)."""
        return 1 if self.segments is None else len(self._blocks)

    def _spread(self, col: np.ndarray) -> np.ndarray:
        """A column over the cost samples as nuisance columns: itself for one record; with segments one
        column per segment, ``col`` on that segment's samples and 0 elsewhere (an offset or a free
        response of each segment's own)."""
        if self.segments is None:
            return col
        out = np.zeros((col.shape[0], len(self._blocks)))
        for q, (lo, hi) in enumerate(self._blocks):
            out[lo:hi, q] = col[lo:hi]
        return out

    def _cost(self, x: np.ndarray) -> np.ndarray:
        """The cost samples of ``x`` (shape (n_fit, ...), the record's samples)."""
        if self.segments is None:
            return x[self.start:]
        return np.concatenate([x[a + self.start:b] for a, b in self.segments])

    def _lfilter(self, num, den, x: np.ndarray) -> np.ndarray:
        """``lfilter`` along the samples of ``x`` (shape (n_fit, ...)), restarted from rest at every
        segment (samples outside the segments are 0)."""
        if self.segments is None:
            return lfilter(num, den, x, axis=0)
        out = np.zeros_like(x)
        for a, b in self.segments:
            out[a:b] = lfilter(num, den, x[a:b], axis=0)
        return out

    def _kept_power(self, key):
        """The free response kept under ``key`` (the most recently used last), or None."""
        col = self._powers.pop(key, None)
        if col is not None:
            self._powers[key] = col
        return col

    def _keep_power(self, key, col: np.ndarray) -> np.ndarray:
        """Keep ``col`` under ``key``: at most :data:`POWER_CACHE_BYTES` of them (at least
        :data:`POWER_CACHE_MIN`), the least recently used dropped (a solver tries a new pole at every
        evaluation: on a long record an unbounded store grew by gigabytes)."""
        most = max(POWER_CACHE_MIN, POWER_CACHE_BYTES // max(col.nbytes, 1))
        while len(self._powers) >= most:
            del self._powers[next(iter(self._powers))]
        self._powers[key] = col
        return col

    def _power(self, a: float) -> np.ndarray:
        """``a^k`` over the cost window (a free response), computed once per pole while it is kept."""
        key = float(a)
        col = self._kept_power(key)
        if col is None:
            # exp(k ln a) is about 3 times faster than a ** k (and equal to about 1e-13 relative)
            col = self._keep_power(key, np.exp(self.kw * math.log(a)) if a > 0 else a ** self.kw)
        return col

    def _power_ramp(self, a: float) -> np.ndarray:
        """``k a^k`` over the cost window (the free response of a repeated pole), computed once per pole while
        it is kept."""
        key = ("ramp", float(a))
        col = self._kept_power(key)
        if col is None:
            col = self._keep_power(key, self.kw * self._power(a))
        return col

    def _filtered(self, ar):
        """``A(q) z`` and ``A(q) u`` for the noise model ``ar``."""
        if not self.p:
            return self.z, self.u
        num = np.concatenate([[1.0], ar])
        return self._lfilter(num, [1.0], self.z), self._lfilter(num, [1.0], self.u)

    def set_ar(self, ar) -> None:
        """Use the noise model ``A(q) = 1 + ar_1 q^-1 + ... + ar_p q^-p``."""
        self.ar = np.asarray(ar, float).copy()
        self.zf, self.uf = self._filtered(self.ar)
        self.xf = None if self.extra is None else self._filtered_extra(self.ar)
        self._unit_cache.clear()

    def _filtered_extra(self, ar):
        if self.p == 0:
            return self._cost(self.extra)
        return self._cost(self._lfilter(np.concatenate([[1.0], ar]), [1.0], self.extra))

    def start_poles(self) -> np.ndarray:
        """The specs' poles, element after element, shape (n_poles,)."""
        return np.array([a for s in self.specs for a in s.poles], float)

    def poles_from(self, x):
        poles = self.start_poles()
        poles[self.pole_free_idx] = x
        return poles

    def _units(self, src, m, poles, lag):
        """Windows of the unit responses ``G_a`` (and ``G_b``) of element ``m`` to ``src[:, m]``."""
        num_a, num_b, den = _basis(self.specs[m].form, poles[self.slices[m]], self.ts)
        if self.segments is not None:     # each segment from rest, its cost samples at the lag
            parts = [(src[a:b - lag, m], self.start - lag) for a, b in self.segments]
            cols = [np.concatenate([lfilter(num_a, den, x)[k:] for x, k in parts])]
            if num_b is not None:
                cols.append(np.concatenate([lfilter(num_b, den, x)[k:] for x, k in parts]))
            return cols
        x = src[:self.n_fit - lag, m]
        cols = [lfilter(num_a, den, x)[self.start - lag:]]
        if num_b is not None:
            cols.append(lfilter(num_b, den, x)[self.start - lag:])
        return cols

    def _cached_units(self, filtered: bool, m, poles, lag):
        """:meth:`_units` of the prefiltered (``uf``) or raw (``u``) columns, kept for reuse."""
        key = (filtered, m, poles[self.slices[m]].tobytes(), int(lag))
        cols = self._unit_cache.get(key)
        if cols is None:
            cols = self._units(self.uf if filtered else self.u, m, poles, lag)
            if len(self._unit_cache) >= self.UNIT_CACHE_SIZE:
                del self._unit_cache[next(iter(self._unit_cache))]
            self._unit_cache[key] = cols
        return cols

    def _element_columns(self, units, m):
        """``(known, columns)`` of element ``m`` from its unit responses ``units`` (:meth:`_units`):
        its response with the held coefficients (None when none is held), and the columns of its free
        linear coefficients (:attr:`_ElementSpec.linear`)."""
        spec = self.specs[m]
        linear = spec.linear
        if len(units) == 1:
            return (None, units) if linear else (spec.gain * units[0], [])
        ua, ub = units
        if linear == ("K", "KL"):
            return None, [ua, ub]
        if linear == ("K",):
            return None, [ua + spec.lead * ub]
        if linear == ("KL",):
            return spec.gain * ua, [ub]
        return spec.gain * (ua + spec.lead * ub), []

    def _free_response_pieces(self, poles) -> list:
        """The pieces of :meth:`_free_responses`, each a column or (with segments) a block of columns."""
        cols = []
        for m in range(self.n_located):
            own = poles[self.slices[m]]
            for q, a in enumerate(own):
                repeated = q > 0 and abs(a - own[q - 1]) < REPEATED_POLE_TOLERANCE
                cols.append(self._spread(self._power_ramp(a) if repeated else self._power(a)))
        return cols

    def _free_responses(self, poles):
        """Free responses of the located elements' lags: ``a^k`` per pole, ``k a^k`` for a repeated one."""
        cols = self._free_response_pieces(poles)
        return np.column_stack(cols) if cols else np.zeros((self.kw.shape[0], 0))

    def _located_columns(self, poles, lags, filtered=True):
        """``(known, columns)``: the located elements' response with their held coefficients, and the
        columns of their free linear coefficients (:meth:`_element_columns`), element after element."""
        known = np.zeros(self.kw.shape[0])
        gcols = []
        for m in range(self.n_located):
            held, cols = self._element_columns(self._cached_units(filtered, m, poles, lags[m]), m)
            if held is not None:
                known += held
            gcols.extend(cols)
        return known, gcols

    def _design(self, poles, lags, filtered=True):
        known, gcols = self._located_columns(poles, lags, filtered)
        cols = gcols + [self.fixed_cols]
        if self.free:
            cols.append(self._free_responses(poles))
        if self.extra is not None:
            cols.append(self.xf if filtered else self._cost(self.extra))
        return known, np.column_stack(cols)

    @staticmethod
    def _solve(phi, target):
        scale = np.sqrt(np.einsum("ij,ij->j", phi, phi))
        scale[scale == 0] = 1.0
        ps = phi / scale
        gram = ps.T @ ps
        beta = symmetric_pinv(gram, 1e-12) @ (ps.T @ target)
        return beta / scale

    def projected(self, poles, lags):
        """Prefiltered residual with the linear parameters eliminated, and those parameters.

        The least-squares problem of :meth:`_solve` on the design of :meth:`_design`, with the cross
        products of the columns that do not move with the poles and lags (the offsets, the fixed poles'
        free responses, the filtered nuisance regressors) taken once per noise model
        (:meth:`_constant_part`): each evaluation forms only the products with the columns that move.
        """
        known, v, n_gain = self._varying(poles, lags)
        target = self._cost(self.zf) - known
        c, cc = self._constant_part()
        kv = v.shape[1]
        order, inverse, pairs, blocks = self._column_order(kv, n_gain, c.shape[1])
        vc = v.T @ c
        blocks[:kv, :kv] = v.T @ v                              # [[V'V, V'C], [C'V, C'C]]
        blocks[:kv, kv:] = vc
        blocks[kv:, :kv] = vc.T
        blocks[kv:, kv:] = cc
        gram = blocks.take(pairs)                               # its rows and columns in the design's order
        rhs = np.concatenate([v.T @ target, c.T @ target])[order]
        scale = np.sqrt(np.diag(gram))                          # the columns' norms
        scale[scale == 0] = 1.0
        beta = symmetric_pinv(gram / np.outer(scale, scale), 1e-12) @ (rhs / scale) / scale
        b = beta[inverse]                                       # [moving, constant]
        return target - v @ b[:kv] - c @ b[kv:], beta

    def _column_order(self, kv: int, n_gain: int, kc: int) -> tuple:
        """``(order, inverse, pairs, blocks)``: the columns ``[V, C]`` of :meth:`projected` (``kv`` moving,
        the first ``n_gain`` of them the linear columns; ``kc`` constant) in the order of :meth:`_design`
        (the located elements' linear columns, the fixed columns, the free responses of the located
        poles, the filtered extra regressors), and back; the flat indices ``pairs`` (shape (k, k),
        ``k = kv + kc``) that take a ``(k, k)`` matrix of ``[V, C]``'s products into that order on both
        sides; and a ``(k, k)`` buffer for those products, kept for the next evaluation."""
        key = (kv, n_gain, kc)
        out = self._orders.get(key)
        if out is None:
            n_fixed = self.fixed_cols.reshape(self.kw.shape[0], -1).shape[1]
            order = np.concatenate([np.arange(n_gain), kv + np.arange(n_fixed), np.arange(n_gain, kv),
                                    kv + np.arange(n_fixed, kc)])
            inverse = np.empty_like(order)
            inverse[order] = np.arange(order.size)
            k = order.size
            out = self._orders[key] = (order, inverse, order[:, None] * k + order[None, :], np.empty((k, k)))
        return out

    def _constant_part(self):
        """``(C, C'C)`` of the columns of the design that do not move with the poles and lags:
        ``C = [fixed_cols, filtered extra]`` for the current noise model, computed once per model."""
        key = self.ar.tobytes()
        if self._constant is None or self._constant[0] != key:
            cols = [self.fixed_cols.reshape(self.kw.shape[0], -1)]
            if self.extra is not None:
                cols.append(self.xf.reshape(self.kw.shape[0], -1))
            c = np.ascontiguousarray(np.column_stack(cols))
            self._constant = (key, (c, c.T @ c))
        return self._constant[1]

    def _varying(self, poles, lags):
        """``(known, V, n_gain)``: the held part and the moving columns of :meth:`_design` (the located
        elements' linear columns, ``n_gain`` of them, then the free responses of their poles)."""
        known, cols = self._located_columns(poles, lags)
        n_gain = len(cols)
        if self.free:
            for piece in self._free_response_pieces(poles):
                cols.extend(piece.T if piece.ndim == 2 else [piece])
        # The columns written into a buffer kept for the next evaluation (the values and the layout of
        # np.column_stack(cols)): a fresh array of this size each time cost a few dozen page faults.
        n = self.kw.shape[0]
        v = self._moving.get(len(cols))
        if v is None:
            v = self._moving[len(cols)] = np.empty((n, len(cols)))
        for q, col in enumerate(cols):
            v[:, q] = col
        return known, v, n_gain

    def gains_and_leads(self, coefs):
        """Gains and leads (s) of the located elements from the free linear coefficients ``coefs``."""
        gains = np.array([s.gain for s in self.specs], float)
        leads = np.array([s.lead if s.form.lead else 0.0 for s in self.specs], float)
        for m, spec in enumerate(self.specs):
            idx = dict(zip(spec.linear, self.linear_index[m]))
            if "K" in idx:
                gains[m] = coefs[idx["K"]]
            if "KL" in idx:
                leads[m] = coefs[idx["KL"]] / gains[m] if gains[m] != 0 else 0.0
        return gains, leads

    def _make_fit(self, poles, lags, ssr: float, n_resid: int, beta):
        coefs = beta[:self.n_linear]
        gains, leads = self.gains_and_leads(coefs)
        return _Fit(lags=tuple(int(v) for v in lags), poles=np.asarray(poles, float).copy(), coefs=coefs.copy(),
                    gains=gains, leads=leads, nuisance=beta[self.n_linear:], ssr=ssr, n_resid=n_resid)

    def input_correlation(self, fit: _Fit, m: int, max_lag: int) -> np.ndarray:
        """``sqrt(N) |rho(tau)|`` of the fit's prefiltered residual with element ``m``'s prefiltered input at lags
        ``tau = 1 .. max_lag``, shape (max_lag,).

        ``rho(tau)`` is the correlation of the residual ``e(k)`` with ``A(q) u(k - tau)`` over the cost samples
        whose ``k - tau`` lies in their own record (segment), ``N`` their number.  Where the fit holds the
        plant and ``e`` is white, ``E e(k) u(k - tau) = 0`` for ``tau >= 1`` (in closed loop too: ``u(k - tau)``
        depends only on earlier noise) and ``sqrt(N) rho(tau)`` is about ``N(0, 1)`` whatever the input's
        colour (Ljung, *System Identification*, 1999, section 16.6): a large value at a lag the element's
        search did not reach says that the input acts there.
        """
        resid, _ = self.projected(fit.poles, fit.lags)
        x = self.uf[:, m]
        out = np.zeros(max_lag)
        if self.segments is None:          # the cost samples k = start .. n_fit - 1, those with k >= tau
            for tau in range(1, max_lag + 1):
                k0 = max(self.start, tau)
                e, v = resid[k0 - self.start:], x[k0 - tau:self.n_fit - tau]
                out[tau - 1] = _normalized_product(e, v)
            return out
        at = np.concatenate([np.arange(a + self.start, b) for a, b in self.segments])
        first = np.concatenate([np.full(b - a - self.start, a) for a, b in self.segments])
        for tau in range(1, max_lag + 1):
            ok = at - tau >= first
            out[tau - 1] = _normalized_product(resid[ok], x[at[ok] - tau])
        return out

    def evaluate(self, poles, lags) -> _Fit:
        """Fit with the poles held (linear parameters re-estimated)."""
        resid, beta = self.projected(poles, lags)
        return self._make_fit(poles, lags, float(resid @ resid), resid.shape[0], beta)

    def fit(self, lags, poles0) -> _Fit:
        """Least-squares fit of the free poles for the given lags and the current noise model
        (:func:`~mpm_monitor.core.repair.lsq.least_squares_bounded`, the poles within the bounds)."""
        poles0 = np.clip(np.asarray(poles0, float), _POLE_MIN, _POLE_MAX)
        if not self.pole_free_idx:
            return self.evaluate(poles0, lags)
        x0 = poles0[self.pole_free_idx]

        # The solver's last evaluations (``(ssr, n_resid, beta)`` by ``x``): its solution is one of
        # them, usually the last (a step that met ftol or xtol), else ``len(x) + 1`` back (the finite
        # differences of the Jacobian at which gtol was met).
        recent = {}

        scale = self.solver_scale             # exact: a power of two (solver_scale)

        def fun(x):
            resid, beta = self.projected(self.poles_from(x), lags)
            recent[x.tobytes()] = (float(resid @ resid), resid.shape[0], beta)
            if len(recent) > self.RECENT_EVALUATIONS:
                del recent[next(iter(recent))]
            return resid if scale == 1.0 else resid * scale

        sol = least_squares_bounded(fun, x0, (_POLE_MIN, _POLE_MAX), xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=60,
                                    diff_step=1e-6)
        done = recent.get(sol.x.tobytes())
        if done is None:
            return self.evaluate(self.poles_from(sol.x), lags)
        return self._make_fit(self.poles_from(sol.x), lags, *done)

    def update_ar(self, fit: _Fit) -> None:
        """Re-estimate ``A(q)`` by least squares on the unfiltered output error of ``fit``."""
        if self.p == 0:
            return
        known, phi = self._design(fit.poles, fit.lags, filtered=False)
        nl = self.n_linear
        r = self._cost(self.z) - known - phi[:, :nl] @ fit.coefs
        nuis = phi[:, nl:]
        r = r - nuis @ self._solve(nuis, r)
        if self.segments is None:
            self.set_ar(-least_squares_ar(r, self.p))
            return
        # The AR of each segment's residual on its own lags (no lag reaches across a gap), stacked.
        lags = np.vstack([lag_matrix(r[lo:hi], range(1, self.p + 1), self.p) for lo, hi in self._blocks])
        target = np.concatenate([r[lo + self.p:hi] for lo, hi in self._blocks])
        coef, *_ = np.linalg.lstsq(lags, target, rcond=None)
        self.set_ar(-coef)

    def full_residual(self, theta, lags, memo=None):
        """Prefiltered residual as a function of ``[free linear coefficients, free poles, ar, nuisance]``.

        ``memo`` (a dict) keeps the parts that depend only on the noise model and the poles, for a
        sequence of calls that change one parameter at a time (the finite differences of
        :meth:`covariance`).
        """
        memo = {} if memo is None else memo
        nl, npf = self.n_linear, len(self.pole_free_idx)
        coefs = theta[:nl]
        poles = self.poles_from(theta[nl:nl + npf])
        ar = theta[nl + npf:nl + npf + self.p]
        nuis = theta[nl + npf + self.p:]
        ar_key = ar.tobytes()
        if ("filtered", ar_key) not in memo:
            zf, uf = self._filtered(ar)
            memo[("filtered", ar_key)] = self._cost(zf), uf
        zf, uf = memo[("filtered", ar_key)]
        out = zf.copy()
        for m in range(self.n_located):
            key = ("units", ar_key, m, poles[self.slices[m]].tobytes(), int(lags[m]))
            if key not in memo:
                memo[key] = self._units(uf, m, poles, lags[m])
            held, cols = self._element_columns(memo[key], m)
            if held is not None:
                out -= held
            for k, col in zip(self.linear_index[m], cols):
                out -= coefs[k] * col
        # Without extra regressors the nuisance columns do not depend on the noise model: one matrix serves
        # every ``ar`` of the finite differences (the same columns, the same products).
        key = ("nuisance", ar_key if self.extra is not None else None, poles.tobytes())
        if key not in memo:
            cols = [self.fixed_cols]
            if self.free:
                cols.append(self._free_responses(poles))
            if self.extra is not None:
                cols.append(self._filtered_extra(ar))
            memo[key] = np.column_stack(cols)
        return out - memo[key] @ nuis

    def _jacobian(self, fit: _Fit, n_columns: int):
        """The residual of ``fit`` and its central-difference Jacobian in the first ``n_columns``
        entries of ``[free linear coefficients, free poles, ar, nuisance]`` (:meth:`full_residual`).

        Returns
        -------
        r0 : ndarray, shape (n_resid,)
        jac : ndarray, shape (n_resid, n_columns)
        """
        theta = np.concatenate([fit.coefs, fit.poles[self.pole_free_idx], self.ar, fit.nuisance])
        nl, npf = self.n_linear, len(self.pole_free_idx)
        memo = {}
        r0 = self.full_residual(theta, fit.lags, memo)
        jac = np.empty((r0.shape[0], n_columns))
        for m in range(n_columns):
            h = 1e-6 * max(1e-2, abs(theta[m]))
            if nl <= m < nl + npf:
                h = min(1e-6, 0.5 * (1.0 - theta[m]))
            tp, tm = theta.copy(), theta.copy()
            tp[m] += h
            tm[m] -= h
            jac[:, m] = (self.full_residual(tp, fit.lags, memo) - self.full_residual(tm, fit.lags, memo)) / (2 * h)
        return r0, jac

    @staticmethod
    def _unit_columns(jac: np.ndarray) -> tuple:
        """``(jac / scale, scale)``: the Jacobian ``jac`` (shape (n, k)) with each column divided by its
        norm (``scale``, shape (k,); a zero column's taken as 1)."""
        scale = np.sqrt(np.sum(jac ** 2, axis=0))
        scale[scale == 0] = 1.0
        return jac / scale, scale

    @staticmethod
    def _condition(js: np.ndarray) -> float:
        """Condition number of the column-scaled Jacobian block ``js`` of the free coefficients and poles."""
        if not js.shape[1]:
            return 1.0
        sv = np.linalg.svd(js, compute_uv=False)
        return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")

    def covariance(self, fit: _Fit):
        """Covariance of the free linear coefficients and poles from the Jacobian of the full residual.

        Returns
        -------
        cov : ndarray, shape (n_linear + n_free_poles, n_linear + n_free_poles)
            Of ``[free linear coefficients, free poles]`` (:attr:`_ElementSpec.linear`,
            :attr:`pole_free_idx`), variances clipped at 0.
        cond : float
            Condition number of the column-scaled Jacobian block of the free coefficients and poles
            (:meth:`condition`).
        """
        nl, npf = self.n_linear, len(self.pole_free_idx)
        n_theta = nl + npf + self.p + fit.nuisance.shape[0]
        r0, jac = self._jacobian(fit, n_theta)
        dof = max(r0.shape[0] - n_theta, 1)
        s2 = float(r0 @ r0) / dof
        js, scale = self._unit_columns(jac)
        # Only the free coefficients' and poles' block is unscaled: a nuisance column of negligible norm
        # (1e-156 next to 1e2, a step too small to move it) would overflow its own variance, unused.
        k = nl + npf
        block = s2 * symmetric_pinv(js.T @ js, 1e-13)[:k, :k] / np.outer(scale[:k], scale[:k])
        np.fill_diagonal(block, np.maximum(np.diag(block), 0.0))
        return block, self._condition(js[:, :k])

    def condition(self, fit: _Fit) -> float:
        """The ``cond`` of :meth:`covariance` alone, from the Jacobian columns of the free coefficients
        and poles only (the same numbers: each column is scaled by its own norm)."""
        k = self.n_linear + len(self.pole_free_idx)
        if not k:
            return 1.0
        _, jac = self._jacobian(fit, k)
        return self._condition(self._unit_columns(jac)[0])

    def variances(self, cov, fit: _Fit, m: int):
        """Variances of the gain, the lead and each pole of element ``m`` (0 for held parameters).

        The lead's from the delta method: ``lead = KL / K`` with both free, ``KL / K`` with ``K`` held.

        Returns
        -------
        var_gain, var_lead : float
        var_poles : ndarray, shape (n_lags,)
        """
        spec = self.specs[m]
        idx = dict(zip(spec.linear, self.linear_index[m]))
        var_gain = float(cov[idx["K"], idx["K"]]) if "K" in idx else 0.0
        var_lead = 0.0
        k = float(fit.gains[m])
        if "KL" in idx and k != 0:
            if "K" in idx:
                kl = float(fit.coefs[idx["KL"]])
                grad = np.zeros(cov.shape[0])
                grad[idx["K"]], grad[idx["KL"]] = -kl / k ** 2, 1.0 / k
                var_lead = max(float(grad @ cov @ grad), 0.0)
            else:
                var_lead = float(cov[idx["KL"], idx["KL"]]) / k ** 2
        var_poles = np.zeros(spec.form.n_lags)
        for q, flat in enumerate(range(self.slices[m].start, self.slices[m].stop)):
            if flat in self.pole_free_idx:
                pos = self.n_linear + self.pole_free_idx.index(flat)
                var_poles[q] = float(cov[pos, pos])
        return var_gain, var_lead, var_poles


class _FitCache:
    """Converged fits of a row problem by input lags: each lag vector is fitted once.

    Calling it with ``(lags, poles_start)`` returns the cached fit of ``lags`` (the start poles
    only matter the first time); ``fits`` maps ``tuple(lags)`` to the :class:`_Fit`, in the order
    they were computed.
    """

    def __init__(self, problem: _RowProblem):
        self.problem = problem
        self.fits: dict = {}

    def __call__(self, lags, poles_start) -> _Fit:
        key = tuple(int(v) for v in lags)
        if key not in self.fits:
            self.fits[key] = self.problem.fit(key, poles_start)
        return self.fits[key]


@dataclasses.dataclass
class _RowEstimate:
    """Result of the search of one row: the fit, the lag profiles and, on demand, the parameter covariance.

    The covariance (:attr:`cov`) and the condition number (:attr:`cond`) are computed from
    ``problem`` the first time they are read (the problem's noise model stays that of the fit),
    so that a fit whose intervals are never reported does not pay for them.
    """

    fit: _Fit
    profiles: list      # per located element: {lag: ssr} with the other lags at their optimum
    edge: list          # per element: True when the best lag is at the edge of its window
    ar: np.ndarray
    problem: _RowProblem = dataclasses.field(repr=False, default=None)
    fits: _FitCache = dataclasses.field(repr=False, default=None)  # more profile points on demand
    _cov: np.ndarray = dataclasses.field(init=False, repr=False, default=None)
    _cond: float = dataclasses.field(init=False, repr=False, default=None)

    @property
    def cov(self) -> np.ndarray:
        """Of [free linear coefficients, free poles] (see :meth:`_RowProblem.covariance`)."""
        if self._cov is None:
            self._cov, self._cond = self.problem.covariance(self.fit)
        return self._cov

    @property
    def cond(self) -> float:
        """Condition number of the scaled Jacobian of the free coefficients and poles
        (:meth:`_RowProblem.condition`; without the rest of the covariance when that is not read)."""
        if self._cond is None:
            self._cond = self.problem.condition(self.fit)
        return self._cond


def _normalized_product(e: np.ndarray, v: np.ndarray) -> float:
    """``sqrt(N) |e'v| / (|e| |v|)`` of two vectors of ``N`` samples (0 when either is 0 or ``N < 2``)."""
    if e.shape[0] < 2:
        return 0.0
    den = math.sqrt(float(e @ e) * float(v @ v))
    return math.sqrt(e.shape[0]) * abs(float(e @ v)) / den if den > 0 else 0.0


_TAU_GRID = (0.5, 0.7, 1.0, 1.4, 2.0)


def _search_row(problem: _RowProblem, lags0, max_sweeps: int, ar_iterations: int = 3) -> _RowEstimate:
    """Lags on the integer grid by coordinate search; poles by least squares; then the noise model.

    Phase 1 (output error, ``A = 1``): for each element with a free lag, a quick scan of (lag, pole) with the other
    parameters held picks candidates, which are fitted; sweeps repeat until no lag moves. Phase 1b: each one-lag
    element's shape with its lag gone (a pure gain), fitted only where its cost already lies below the fit's; where
    one was taken, the sweeps run again. Phase 1c: every two free lags moved by one sample together
    (:func:`_pair_lag_moves`), fitted only where that already beats the fit, then the sweeps again. Phase 2: the
    noise model and the fit are alternately re-estimated; then, for an element whose fitted shape has drifted off
    its spec's, the fit's and the spec's shapes are scanned once more under that noise model, and only the points
    whose cost already lies below the fit's are fitted (the ranking under output error can differ:
    ``bench.structures_mc`` run 140 settled at a lag of 6 samples with a lag of 2,000 s, where the model's own shape
    at the plant's lag of 3 fits better under the noise model).
    Phase 3: each lag is moved by one sample while that lowers the cost, and its profile is recorded.
    Phase 4: where phases 2b and 3 moved the fit, its noise model is estimated again from the moved fit, the fit
    redone under it and phase 3 repeated, up to ``ar_iterations`` times: a cost under the noise model of another
    fit is not the moved fit's (a step-response row's larger form, moved far by the scan of phase 2b, cost 0.91
    under its old noise model and 0.24 under its own, where the smaller form it was compared with cost 0.35;
    ``bench.step_models --lost-lag`` seed 4 run 66).  The profiles are those under the last noise model.
    """
    n = problem.n_located
    specs = problem.specs
    fits = _FitCache(problem)
    lags = [int(v) for v in lags0]
    best = fits(lags, problem.start_poles())
    best, lags = _sweep_lags(problem, fits, best, lags, max_sweeps)
    # Phase 1b: each one-lag element's shape with its lag gone, fitted where it already beats the fit; then sweep again.
    settled = best
    best, lags = _sweep_lags(problem, fits, best, lags, 1, lag_gone=True)
    if best is not settled:
        best, lags = _sweep_lags(problem, fits, best, lags, max_sweeps)
    # Phase 1c: two lags moved together, fitted where that already beats the fit; then sweep again.
    for _ in range(max_sweeps):
        settled = best
        best, lags = _pair_lag_moves(problem, fits, best, lags)
        if best is settled:
            break
        best, lags = _sweep_lags(problem, fits, best, lags, max_sweeps)
    # Phase 2: the noise model.
    for _ in range(ar_iterations if problem.p else 0):
        problem.update_ar(best)
        fits.fits.clear()
        best = fits(lags, best.poles)
    noise_of = best        # the fit the noise model was estimated from
    if problem.p:          # a drifted shape's scan again under the noise model, fitting only what beats the fit
        best, lags = _sweep_lags(problem, fits, best, lags, 1, better_only=True)
    best, lags = _local_lag_moves(problem, fits, best, lags)
    # Phase 4: where phases 2b and 3 moved the fit, its noise model is estimated again from it.
    for _ in range(ar_iterations if problem.p else 0):
        if best is noise_of:
            break
        problem.update_ar(best)
        fits.fits.clear()
        noise_of = best = fits(lags, best.poles)
        best, lags = _local_lag_moves(problem, fits, best, lags)
    # At an end of the searched lags, except the least an element may have (lag 1: the input acts a sample after
    # it is applied; nothing lies below it).
    edge = [specs[m].lag_free and (lags[m] == specs[m].window[1] or 1 < lags[m] == specs[m].window[0])
            for m in range(n)]
    return _RowEstimate(fit=best, profiles=_lag_profiles(fits, lags), edge=edge, ar=problem.ar.copy(),
                        problem=problem, fits=fits)


def _sweep_lags(problem: _RowProblem, fits: _FitCache, best: _Fit, lags: list, max_sweeps: int,
                better_only: bool = False, lag_gone: bool = False):
    """Phase 1 of :func:`_search_row`: coordinate sweeps over the free lags until none moves (with ``better_only``,
    the scan after the noise model, with ``lag_gone`` phase 1b: see :func:`_move_lag`).

    Returns the best fit and its lags.
    """
    for _ in range(max_sweeps):
        moved = False
        for m in range(problem.n_located):
            if not problem.specs[m].lag_free:
                continue
            best, lags, moved_m = _move_lag(problem, fits, best, lags, m, better_only, lag_gone)
            moved = moved or moved_m
        if not moved:
            break
    return best, lags


def _move_lag(problem: _RowProblem, fits: _FitCache, best: _Fit, lags: list, m: int, better_only: bool = False,
              lag_gone: bool = False):
    """Best lag of element ``m`` with the others held: the (lag, pole) scan, then fits of the 3 best lags.

    The scan multiplies every time constant of the element by the factors of :data:`_TAU_GRID`; where the
    fit's shape has drifted off the spec's (its poles outside the span of those), the spec's own poles are
    scanned too, so that a fit sent off by another element's error can come back; and a two-lag element's
    shapes with either lag gone (its pole at the bound), which the classification then takes to one lag
    (``classify._reduce_vanished_lags``): a plant that lost one lag of two elements of a row left
    their joint fit, scaled from the model's two lags, far from it (``bench.structures_mc --lost-lag`` run 146).
    ``better_only`` (the scan after the noise model, :func:`_search_row`): nothing unless the fit's shape has
    drifted off the spec's as above; then the fit's shape and the spec's alone are scanned, and only the points
    whose cost is already below the fit's are fitted.
    ``lag_gone`` (phase 1b of :func:`_search_row`): a one-lag element's shape with its lag gone, a pure gain, alone,
    fitted only where its cost is already below the fit's.  A pure gain's spec starts at the row's median time
    constant, so its own shape was otherwise never scanned (``bench.structures_mc --pure-gains`` seed 2 run 55: a
    pure gain 66 % high beside an element whose plant lost its only lag, fitted with both gains of the wrong sign at
    90 times the noise).  Scanned among the others from the start, the shape sent a sweep down another path to a
    worse fit (``bench.repair_mc --dither-fat`` seed 1 run 36); after the sweeps, it can only lower the cost.
    Returns the best fit, its lags and whether the lag of ``m`` moved.
    """
    spec = problem.specs[m]
    own = problem.slices[m]
    moved = False
    base_taus = [-1.0 / math.log(min(max(a, _POLE_MIN), _POLE_MAX)) for a in best.poles[own]]
    grid = _TAU_GRID if spec.pole_free and base_taus else (1.0,)
    shapes = [[min(max(math.exp(-1.0 / (tau * f)), _POLE_MIN), _POLE_MAX) for tau in base_taus] for f in grid]
    start = [float(a) for a in spec.poles]
    drifted = bool(spec.pole_free and base_taus) and not _within_grid(start, shapes)
    if lag_gone:
        if not (spec.pole_free and len(base_taus) == 1 and best.poles[own][0] > _POLE_MIN):
            return best, lags, False
        shapes, drifted = [[_POLE_MIN]], False
    elif better_only:
        if not drifted:
            return best, lags, False
        shapes = [shapes[grid.index(1.0)]]         # the fit's own shape (the spec's is added below)
    if drifted:
        shapes.append(start)             # the fit's shape drifted off the spec's: scan the spec's too
    if spec.pole_free and len(base_taus) == 2 and min(best.poles[own]) > _POLE_MIN and not better_only:
        a = [float(v) for v in best.poles[own]]
        shapes += [[a[0], _POLE_MIN], [_POLE_MIN, a[1]]]     # either lag gone (a plant that lost one)
    cand = []
    for lag in range(spec.window[0], spec.window[1] + 1):
        lg = list(lags)
        lg[m] = lag
        for shape in shapes:
            poles = best.poles.copy()
            poles[own] = shape
            cand.append((problem.evaluate(poles, lg).ssr, lag, poles))
    cand.sort(key=lambda c: c[0])
    if better_only or lag_gone:
        cand = [c for c in cand if c[0] < best.ssr * (1 - 1e-9)]
    tried = set()
    for _, lag, poles in cand:
        if lag in tried:
            continue
        if len(tried) >= 3:
            break
        tried.add(lag)
        lg = list(lags)
        lg[m] = lag
        f = fits(lg, poles)
        if f.ssr < best.ssr * (1 - 1e-12):
            moved = moved or lag != lags[m]
            best, lags = f, lg
    return best, lags, moved


def _pair_lag_moves(problem: _RowProblem, fits: _FitCache, best: _Fit, lags: list):
    """Phase 1c of :func:`_search_row`: every two free lags moved by one sample each, together (either way each),
    or exchanged.

    Each move's cost is evaluated at the fit's poles; the (at most 3) moves whose cost already lies below the fit's
    are fitted, best first, and the best fit kept.  Inputs that the loop moves together leave the cost a valley
    along such a diagonal, where moving one lag alone only climbs its side: a row whose two pure gains both gained
    a lag (the lag of a first-order element is its dead time plus one sample, a pure gain's its dead time) was
    fitted at the pure gains' lags with twelve times the cost of the lags one sample later
    (``bench.structures_mc --gained-lag`` seed 3 run 15: a gain of 0.012 where the plant's is -1.78).  Two inputs
    that move together can also trade their dead times whole: ``bench.repair_mc --dither-fat`` seed 6 run 120 (u2
    and u5's increments correlated 0.89) came to rest with u2's 8 s for the plant's 0 and u5's none for 8 s, eight
    samples from the plant's lags each way, where the exchanged lags already cost 0.82 of the fit's.

    Returns the best fit and its lags.
    """
    free = [m for m in range(problem.n_located) if problem.specs[m].lag_free]
    cand = []
    for k, a in enumerate(free):
        for b in free[k + 1:]:
            moves = [(lags[a] + sa, lags[b] + sb) for sa in (-1, 1) for sb in (-1, 1)]
            if abs(lags[a] - lags[b]) > 1:             # the two lags exchanged (one apart, a move above)
                moves.append((lags[b], lags[a]))
            for la, lb in moves:
                lg = list(lags)
                lg[a], lg[b] = la, lb
                if all(problem.specs[m].window[0] <= lg[m] <= problem.specs[m].window[1] for m in (a, b)) \
                        and tuple(lg) not in fits.fits:
                    cost = problem.evaluate(best.poles, lg).ssr
                    if cost < best.ssr * (1 - 1e-9):
                        cand.append((cost, lg))
    cand.sort(key=lambda c: c[0])
    for _, lg in cand[:3]:
        f = fits(lg, best.poles)
        if f.ssr < best.ssr * (1 - 1e-12):
            best, lags = f, lg
    return best, lags


def _within_grid(poles, shapes) -> bool:
    """Whether ``poles`` lie within the span of the scanned ``shapes`` (each pole between the smallest and
    the largest of its own in them)."""
    return all(min(s[q] for s in shapes) <= a <= max(s[q] for s in shapes) for q, a in enumerate(poles))


def _local_lag_moves(problem: _RowProblem, fits: _FitCache, best: _Fit, lags: list):
    """Phase 3 of :func:`_search_row`: move each free lag by one sample while that lowers the cost."""
    specs = problem.specs
    improved = True
    while improved:
        improved = False
        for m in range(problem.n_located):
            if not specs[m].lag_free:
                continue
            for step in (-1, 1):
                lag = lags[m] + step
                if specs[m].window[0] <= lag <= specs[m].window[1]:
                    lg = list(lags)
                    lg[m] = lag
                    f = fits(lg, best.poles)
                    if f.ssr < best.ssr * (1 - 1e-12):
                        best, lags, improved = f, lg, True
    return best, lags


def _lag_profiles(fits: _FitCache, lags) -> list:
    """Per element ``m``: ``{lag: ssr}`` of the fits so far whose other lags equal ``lags``."""
    n = len(lags)
    profiles = []
    for m in range(n):
        prof = {}
        for key, f in fits.fits.items():
            if all(key[q] == lags[q] for q in range(n) if q != m):
                prof[key[m]] = f.ssr
        profiles.append(prof)
    return profiles


def _lag_lr(est: _RowEstimate, m: int, lag: int) -> float:
    """Profile likelihood-ratio statistic ``n ln(SSR_lag / SSR_best)`` of element ``m`` at ``lag``, at least 0.

    A profile point first computed here starts from the fit's shape, and can fit better than the fit (its own
    search at that lag started elsewhere and stopped short): the data then show nothing against that lag, and
    the statistic is 0, not negative (whose chi-square tail is not a number: a delay test of an integrator with
    a lead read NaN at the model's own dead time, which fitted better than the free fit's, and its shape test then
    held the model's shape at the free fit's dead time only, ``bench.structures_mc`` seed 4 run 165)."""
    fit = est.fit
    if lag not in est.profiles[m]:
        lg = list(fit.lags)
        lg[m] = lag
        est.profiles[m][lag] = est.fits(lg, fit.poles).ssr
    return max(fit.n_resid * math.log(max(est.profiles[m][lag], 1e-300) / max(fit.ssr, 1e-300)), 0.0)


def _lag_interval(est: _RowEstimate, m: int, window: tuple, threshold: float):
    """Contiguous lags of element ``m`` within ``window`` whose profile statistic stays below ``threshold``."""
    lo = hi = est.fit.lags[m]
    while lo - 1 >= window[0] and _lag_lr(est, m, lo - 1) <= threshold:
        lo -= 1
    while hi + 1 <= window[1] and _lag_lr(est, m, hi + 1) <= threshold:
        hi += 1
    return lo, hi
