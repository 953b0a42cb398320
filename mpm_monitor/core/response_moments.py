"""The model elements' responses on one window and their moments with the input lags, computed once.

Two parts of the analysis need, for every row ``i`` tested, the responses ``x_ij = Phat_ij u_j`` of
its elements to the logged columns and their cross products with the lagged inputs over the
regression rows:

* the whole-response test (:mod:`mpm_monitor.core.response_test`) regresses ``d_i`` on
  ``A_i(q) x_ij``, and needs ``Z' A_i(q) x_ij``;
* the detectability (:mod:`mpm_monitor.core.detectability`) needs ``Z' x_ij`` and ``Z' x_ij(t - k)``,
  ``k = 1 .. na``, for every element (the model's, or the row's typical one for an element the model
  lacks).

``Z`` is ``n_rows x (n_columns n_lag)`` and there are ``n_outputs n_columns`` elements, so these
products are most of the cost of an analysis at industrial size.  :class:`ResponseMoments` takes them
once per row: ``Z' x`` from the element's difference equation and the Gram of the input lags, lag
after lag (:meth:`ResponseMoments._fill_lags`); for a finite impulse response with more taps than the
lags (a step-response model's element), from its taps and a longer Gram out to the longest response
(:attr:`ResponseMoments.fir_gram`, once per window; :meth:`ResponseMoments._fir_moments`); by a
product over the rows for any other element of more poles than ``na`` or more numerator taps than
the lags.  The lags of ``x`` follow by sums along the diagonals of lag pairs (the shift structure of
lagged columns) from their products with the columns at lag 0, which follow from the same difference
equation but for the element's last ``order`` lags (:meth:`ResponseMoments._lag_zero`).  The element
responses (:attr:`RowMoments.R`) are kept only while the row's whole-response test uses them.  The
whole-response test's ``Z' A_i(q) x`` then follows from these moments exactly
(:func:`filtered_products`).

Notation: ``u_c`` the columns centred over the window (the columns that never move set to 0, as they
carry no information), ``Z`` their lags ``1 .. L`` on the regression rows (column ``c L + l - 1`` is
column ``c`` at lag ``l``), ``x`` an element's response to ``u_c``, simulated from rest at the start of
each segment and centred over each segment's samples (``x_raw = x + mu_s`` in segment ``s``; the tests
centre ``A(q) x_raw`` over each level group, :meth:`ResponseMoments.levels`).  With
segments that say how the model runs through the short gaps
(:class:`~mpm_monitor.core.segments.GapSegments`), ``x_raw`` is simulated as the model runs instead
(:func:`~mpm_monitor.core.segments.through`): every relation above that holds on a segment's samples
holds for it too (the difference equations, the sums along lag diagonals), and the long Gram reads the
columns on each run's grid.  Inside a gap the columns are held, but where a missing sample's columns are known (a
segment too short for a row, a spike) they take those, centred as ``u_c``
(:func:`~mpm_monitor.core.segments.centred_fill`), as the model's run does.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional

import numpy as np

from .arx import lag_matrix, segment_lag_matrix, segment_rows
from .model import PlantModel
from .segments import centred_fill, errors_centred_by_level, level_groups, run_places, run_samples, through


#: The largest :attr:`ResponseMoments.fir_gram` built (bytes); beyond it, the long finite impulse responses'
#: moments are products over the rows, as any other element's (128 MiB: 40 columns, 18 lags and 400
#: step-response coefficients after a dead time of 8 samples take about 96 MiB).
FIR_GRAM_MAX_BYTES = 2 ** 27
#: :attr:`ResponseMoments.fir_gram` takes the products of its lag 0 this many bytes of lagged windows at a time.
FIR_COPY_BYTES = 2 ** 25


def typical_element(model: PlantModel, i: int):
    """``(a, b)``: the present element of row ``i`` whose ``|gain|`` is the median of the row's.

    Taken over the whole model when row ``i`` has no element; None when the model has none.
    """
    present = model.present
    cols = np.flatnonzero(present[i])
    cands = [(i, int(c)) for c in cols] if cols.size else [(int(a), int(b)) for a, b in np.argwhere(present)]
    if not cands:
        return None
    gains = np.array([abs(float(model.gain[a, b])) for a, b in cands])
    return cands[int(np.argsort(gains, kind="stable")[(len(gains) - 1) // 2])]


def target_element(model: PlantModel, i: int, j: int):
    """The element whose response stands for a gain error of ``(i, j)``, and its reference gain.

    Returns
    -------
    element : DiscreteElement or None
        The model's element when it has one; otherwise the row's typical element
        (:func:`typical_element`); None when the model has no element at all.
    reference_gain : float
        ``|K|`` the relative change refers to (the typical element's for an absent element).
    """
    if model.present[i, j]:
        return model.discrete_element(i, j), abs(float(model.gain[i, j]))
    typical = typical_element(model, i)
    if typical is None:
        return None, float("nan")
    return model.discrete_element(*typical), abs(float(model.gain[typical]))


@dataclasses.dataclass
class RowMoments:
    """Row ``i``'s element responses and their moments over the regression rows (sums, not means).

    ``m`` elements (:attr:`found`), ``na`` own lags, ``S`` segments, ``n_columns`` columns, ``L`` input lags.

    Attributes
    ----------
    i : int
        The row.
    found : list of (int, DiscreteElement, float)
        ``(j, element, reference_gain)`` of every column ``j`` with a target element
        (:func:`target_element`), in column order.
    moves : ndarray of bool, shape (m,)
        Whether the element's response ``x_raw`` is not identically 0.
    zx : ndarray, shape (n_columns, L, na + 1, m)
        ``sum_t u_c(t - l) x(t - k)``, ``l = 1 .. L``, ``k = 0 .. na``: ``Z' [x, X]`` (output units times
        column units).
    uw : ndarray, shape (n_columns, m (na + 1))
        ``u_c(t)' [x, X]`` (lag 0 of the columns).
    zo : ndarray, shape (n_columns L, na)
        ``Z' O``, ``O`` the row's own lags ``d_i(t - 1) .. d_i(t - na)`` (``d_i`` centred over each level group,
        :meth:`ResponseMoments.levels`).
    oo : ndarray, shape (na, na)
        ``O' O``.
    ow : ndarray, shape (na, m (na + 1))
        ``O' [x, X]``.
    ww : ndarray, shape (m, na + 1, na + 1)
        ``[x, X]' [x, X]`` of every element.
    xsum : ndarray, shape (m, na + 1)
        ``sum_t x(t - k)`` over the rows.
    mu : ndarray, shape (S, m)
        Mean of ``x_raw`` over each segment's samples.
    R : ndarray, shape (n_samples, m), or None
        ``x`` on every sample (each segment's centred on its own); dropped by
        :meth:`ResponseMoments.release` once the whole-response test has used it.
    """

    i: int
    found: list
    moves: np.ndarray
    zx: np.ndarray
    uw: np.ndarray
    zo: np.ndarray
    oo: np.ndarray
    ow: np.ndarray
    ww: np.ndarray
    xsum: np.ndarray
    mu: np.ndarray
    R: Optional[np.ndarray] = None

    def __getstate__(self) -> dict:
        """The fields for a pickle (to another process), every array as raw contiguous data out of band: a
        strided view (:attr:`zx` is one, of the moments at every input lag) as its contiguous base and where
        it lies in it (:class:`_StridedView`), so that neither process copies it; another array not
        contiguous as a copy.  The elements of :attr:`found` are left out (None): they are the model's,
        which the receiving process holds, and :meth:`ResponseMoments.keep` puts them back (at 100x40 they
        were 80 of the 90 arrays of a row)."""
        state = {k: _portable(v) for k, v in self.__dict__.items()}
        state["found"] = [(j, None, ref) for j, _, ref in self.found]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update({k: v.view() if isinstance(v, _StridedView) else v for k, v in state.items()})

    def index(self, j: int) -> Optional[int]:
        """Position of column ``j`` in :attr:`found` (None when it has no target element)."""
        for b, f in enumerate(self.found):
            if f[0] == j:
                return b
        return None


class _StridedView(NamedTuple):
    """A view into a C-contiguous array, pickled as that array and the view's place in it (:meth:`RowMoments.__getstate__`)."""

    base: np.ndarray
    offset: int
    shape: tuple
    strides: tuple

    def view(self) -> np.ndarray:
        return np.ndarray(self.shape, dtype=self.base.dtype, buffer=self.base, offset=self.offset, strides=self.strides)


def _portable(v):
    """``v`` as :meth:`RowMoments.__getstate__` pickles it."""
    if not isinstance(v, np.ndarray) or v.flags.c_contiguous:
        return v
    base = v.base
    if isinstance(base, np.ndarray) and base.base is None and base.flags.c_contiguous and base.dtype == v.dtype \
            and np.all(np.asarray(v.strides) >= 0):
        offset = v.__array_interface__["data"][0] - base.__array_interface__["data"][0]
        end = offset + sum((n - 1) * st for n, st in zip(v.shape, v.strides)) + v.itemsize if v.size else offset
        if 0 <= offset and end <= base.nbytes:
            return _StridedView(base, int(offset), tuple(v.shape), tuple(v.strides))
    return np.ascontiguousarray(v)


class ResponseMoments:
    """The element responses of one window and their moments with the input lags, row by row (module docstring).

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
        The window's columns (inputs, then measured disturbances), the segments stacked.
    d : ndarray, shape (n_samples, n_outputs)
        The window's prediction errors.
    testable : sequence of int
        Columns that move; the others are set to 0 (their lags carry no information).
    n_lag : int
        Lags ``1 .. n_lag`` of every column.
    start : int
        First regression row of every segment (at least ``na``).
    na : int
        Own lags of the element fits.
    segments : sequence of (int, int) or GapSegments, optional
        Data with gaps: the contiguous runs of samples; those with no regression row are left out.  A
        :class:`~mpm_monitor.core.segments.GapSegments` (every segment with a row) runs the responses
        through its short gaps.

    Attributes
    ----------
    u_c : ndarray, shape (n_samples, n_columns)
    Z : ndarray, shape (n_rows, n_columns n_lag)
    n_rows : int
    segments : list of (int, int) or GapSegments or None
    joined : bool
        Whether the responses run through gaps (module docstring).
    """

    def __init__(self, model: PlantModel, u: np.ndarray, d: np.ndarray, testable, n_lag: int, start: int, na: int,
                 segments=None):
        self.model, self.n_lag, self.start, self.na = model, int(n_lag), int(start), int(na)
        self.testable = list(testable)
        self.u, self.d = u, d
        self._given_segments = None if segments is None else [(int(a), int(b)) for a, b in segments]
        self._given_joined = bool(getattr(segments, "joined", False))
        nu = model.n_columns
        u_c = u - u.mean(axis=0)
        u_c[:, [j for j in range(nu) if j not in self.testable]] = 0.0
        self.u_c = u_c
        self.segments = None if segments is None else [(int(a), int(b)) for a, b in segments if b - a > start]
        # Responses run through the short gaps (GapSegments), unless a segment without a row is left out here.
        self.joined = bool(getattr(segments, "joined", False)) and len(self.segments) == len(segments)
        if self.joined:         # the known columns inside the gaps as u_c is (the responses run on them)
            self.segments = centred_fill(segments, u.mean(axis=0),
                                         [j for j in range(nu) if j not in self.testable])
        self.segs = [(0, u.shape[0])] if self.segments is None else self.segments
        L = self.n_lag
        self._Z = None
        self.n_rows = self.Z.shape[0]
        # u(t) on the rows, and u at the lags just before each segment's first row and before its end
        # (the corrections of the sums along lag diagonals, see _compute).
        self.u_rows = segment_rows(u_c, start, self.segments)
        self.u_head = np.stack([u_c[a + start - np.arange(1, L + 1)].T for a, _ in self.segs])    # (S, nu, L)
        self.u_tail = np.stack([u_c[b - np.arange(1, L + 1)].T for _, b in self.segs])            # (S, nu, L)
        self.seg_rows = np.array([b - a - start for a, b in self.segs], dtype=float)     # (S,)
        # Column sums of Z (the whole-response test's centring) and of u(t) over each segment's rows.
        self.z_sums = self._segment_sums(self.Z)                 # (S, p)
        self.u_sums = self._segment_sums(self.u_rows)            # (S, nu)
        self._rows = {}
        self._gram = None
        self._fir_gram = None
        self._fir_span = None
        self._own = None
        self._centred = None

    @property
    def Z(self) -> np.ndarray:
        """The lags ``1 .. n_lag`` of the centred columns on the regression rows, shape (n_rows, n_columns n_lag)
        (built again, the same numbers, after :meth:`forget`)."""
        if self._Z is None:
            self._Z = segment_lag_matrix(self.u_c, range(1, self.n_lag + 1), self.start, self.segments)
        return self._Z

    def forget(self) -> None:
        """Drop what was computed from the samples: the lag matrix, the rows' moments and the products shared
        by the rows.  Each is computed again, to the same numbers, when next read: a process that has left
        the moments' readers to another one (the detectability in a forked child, :func:`~mpm_monitor.core.analysis.detect`)
        keeps only what rebuilds them (at 100x40 about 160 MB fewer while it repairs)."""
        self._Z, self._rows, self._own, self._gram, self._fir_gram = None, {}, None, None, None
        self._centred = None

    def of(self, u: np.ndarray, segments=None) -> bool:
        """Whether these are the moments of the columns ``u`` with these ``segments``."""
        given = None if segments is None else [(int(a), int(b)) for a, b in segments]
        return given == self._given_segments and bool(getattr(segments, "joined", False)) == self._given_joined \
            and (u is self.u or (u.shape == self.u.shape and np.array_equal(u, self.u)))

    def row(self, i: int, keep_samples: bool = False) -> RowMoments:
        """Row ``i``'s :class:`RowMoments` (computed on first use, then kept until :meth:`take`).

        ``keep_samples``: keep :attr:`RowMoments.R` (the responses) for the row's whole-response
        test, until :meth:`release`.
        """
        got = self._rows.get(i)
        if got is None or (keep_samples and got.R is None):
            got = self._rows[i] = self._compute(i, keep_samples)
        return got

    def kept(self, i: int) -> Optional[RowMoments]:
        """Row ``i``'s moments if computed and kept (None otherwise)."""
        return self._rows.get(i)

    def keep(self, rm: RowMoments) -> None:
        """Keep ``rm`` as its row's moments (computed elsewhere: by a child process of the element test,
        :func:`~mpm_monitor.core.parallel.split_map`), unless the row's are kept already; the elements its
        pickle left out are this model's (:func:`target_element`, as :meth:`_compute` found them)."""
        if any(element is None for _, element, _ in rm.found):
            rm.found = [(j, target_element(self.model, rm.i, j)[0] if element is None else element, ref)
                        for j, element, ref in rm.found]
        self._rows.setdefault(rm.i, rm)

    def release(self, i: int) -> None:
        """Drop row ``i``'s responses (its moments stay)."""
        got = self._rows.get(i)
        if got is not None:
            got.R = None

    def take(self, i: int) -> RowMoments:
        """Row ``i``'s moments, no longer kept here (the detectability turns them into its targets)."""
        got = self._rows.pop(i, None)
        if got is None:
            got = self._compute(i, False)
        got.R = None
        return got

    def responses(self, rm: RowMoments, columns) -> dict:
        """Column ``j`` -> ``x_raw`` on every sample (shape (n_samples,)): the response of the row's element
        of each of ``columns`` from rest at each segment's start (or through the short gaps of a
        :class:`~mpm_monitor.core.segments.GapSegments`), as simulated for the moments (``x + mu_s``;
        0 on the samples of a segment without a regression row).  ``rm`` with :attr:`RowMoments.R` kept."""
        out = {}
        for j in columns:
            b = rm.index(j)
            x = rm.R[:, b].copy()
            for s, (a0, b0) in enumerate(self.segs):
                x[a0:b0] += rm.mu[s, b]
            out[j] = x
        return out

    def centred_errors(self) -> np.ndarray:
        """With segments, the prediction errors centred over each row's level groups (:meth:`levels`), shape
        (n_samples, n_outputs): the own lags the element fits take (the samples of a segment left out as they are).
        Computed once per window."""
        if self._centred is None:
            self._centred = errors_centred_by_level(self.d, self.segments, self.model.integrating_outputs)
        return self._centred

    def levels(self, i: int) -> Optional[np.ndarray]:
        """The level group of every segment for row ``i`` (:func:`~mpm_monitor.core.segments.level_groups`: one per
        run the responses run through, for a row without an integrating element); None without segments."""
        if self.segments is None:
            return None
        # Not joined, the segments are a plain list: a level per segment.
        return level_groups(self.segments, not self.model.integrating_outputs[i])

    def _segment_sums(self, A: np.ndarray) -> np.ndarray:
        """Column sums of ``A`` (shape (n_rows, q), on the regression rows) over each segment's rows, shape (S, q)."""
        rows = self.seg_rows.astype(int)
        return np.array([A[e - k:e].sum(axis=0) for e, k in zip(np.cumsum(rows), rows)])

    def _lagged(self, R: np.ndarray, k: int) -> np.ndarray:
        """``R(t - k)`` on the regression rows, shape (n_rows, m) (a view without gaps)."""
        if len(self.segs) == 1:
            a, b = self.segs[0]
            return R[a + self.start - k:b - k]
        return np.concatenate([R[a + self.start - k:b - k] for a, b in self.segs])

    def _compute(self, i: int, keep_samples: bool) -> RowMoments:
        model, u_c, start, segs, na, L = self.model, self.u_c, self.start, self.segs, self.na, self.n_lag
        if self.segments is None:
            O = lag_matrix(self.d[:, i] - self.d[:, i].mean(), range(1, na + 1), start)
        else:
            d = self.centred_errors()[:, i]
            O = np.vstack([lag_matrix(d[a:b], range(1, na + 1), start) for a, b in segs])
        found = [(j,) + target_element(model, i, j) for j in range(model.n_columns)]
        found = [f for f in found if f[1] is not None]
        m, S = len(found), len(segs)
        # The responses on every sample, centred per segment, one column per element (column-major: each
        # is written at once, and the lags on the rows are views of row ranges).
        R = np.zeros((u_c.shape[0], m), order="F")          # samples of segments without a row stay 0
        mu, moves = np.zeros((S, m)), np.zeros(m, dtype=bool)
        for b, (j, element, _) in enumerate(found):
            # From rest at each segment's start, or through the short gaps as the model runs (GapSegments).
            x_all = through(u_c[:, j], element.respond, self.segments, column=j) if self.joined else None
            for s, (a0, b0) in enumerate(segs):
                x = element.respond(u_c[a0:b0, j]) if x_all is None else x_all[a0:b0]
                moves[b] |= bool(np.any(x != 0))
                mu[s, b] = x.mean()
                R[a0:b0, b] = x - mu[s, b]
        x_head = np.stack([R[a + start - np.arange(1, na + 1)].T for a, _ in segs])      # (S, m, na): x(start - k)
        x_tail = np.stack([R[b0 - np.arange(1, na + 1)].T for _, b0 in segs])            # (S, m, na): x(N - k)
        lags = [self._lagged(R, k) for k in range(na + 1)]                               # (n_rows, m) each
        # [x, X]' [x, X] along the diagonals of lag pairs too: sum x(t - k) x(t - k') = the sum at
        # (k - 1, k' - 1) + x(start - k) x(start - k') - x(N - k) x(N - k'); only lag 0 with every lag
        # takes a pass over the rows.
        ww = np.empty((m, na + 1, na + 1))
        for k in range(na + 1):
            ww[:, 0, k] = np.einsum("tb,tb->b", lags[0], lags[k])
        ww[:, 1:, 0] = ww[:, 0, 1:]
        for k in range(1, na + 1):
            ww[:, 1:, k] = ww[:, :-1, k - 1] + np.einsum("sbl,sb->bl", x_head, x_head[:, :, k - 1]) \
                - np.einsum("sbl,sb->bl", x_tail, x_tail[:, :, k - 1])
        upper = np.triu_indices(na + 1, 1)
        ww[:, upper[1], upper[0]] = ww[:, upper[0], upper[1]]          # exactly symmetric
        # u(t)' and O' with every lag of every element (lag 0 of the columns and the own lags, _lag_zero).
        nu = u_c.shape[1]
        rec_lags = np.array([self._recursive_lags(element) for _, element, _ in found], dtype=int)
        # The long finite impulse responses (a step-response model's elements beyond the lags): Z' x and
        # u_c(t)' x(t - k) from their taps and the long Gram (_fir_moments); O' x(t - k) by products.
        fir = {b: self._fir_moments(found[b], mu[:, b]) for b in range(m)
               if rec_lags[b] < 0 and self._long_fir(found[b][1])}
        P = self._own_lags(i, O)
        V = self._lag_zero(O, P, lags, found, rec_lags, mu, {b: uw for b, (uw, _) in fir.items()})
        uw = np.moveaxis(V[:nu], 1, 2).reshape(nu, m * (na + 1))
        ow = np.moveaxis(V[nu:], 1, 2).reshape(na, m * (na + 1))
        xsum = np.stack([x.sum(axis=0) for x in lags], axis=1)                          # (m, na + 1)
        # The elements whose Z' x follows from their difference equation (see _fill_lags); the long finite
        # impulse responses' from their taps (fir, above); the others' is taken by a product over the rows.
        rec = [b for b in range(m) if rec_lags[b] >= 0]
        direct = [b for b in range(m) if rec_lags[b] < 0 and b not in fir]
        u_head, u_tail = self.u_head, self.u_tail                           # (S, nu, L): u(start - l), u(N - l)
        # M[c, l, k, e] = sum over the rows of u_c(t - l) x_e(t - k) (l = 0 .. L, k = 0 .. na).  Z' X is a sum
        # along diagonals of lag pairs: M(l, k) = M(l - 1, k - 1) + u(start - l) x(start - k) - u(N - l) x(N - k)
        # (summed over the segments), so only the lags k = 0 (with every input lag) and l = 0 (with every
        # element lag, _lag_zero) are needed, each by a product over the rows or by the recursions.
        M = np.empty((nu, L + 1, na + 1, m))
        M[:, 0] = V[:nu]
        if direct:
            M[:, 1:, 0, direct] = (self.Z.T @ lags[0][:, direct]).reshape(nu, L, len(direct))
        for b, (_, zx) in fir.items():
            M[:, 1:, 0, b] = zx
        head, tail = np.empty((nu, L, na, m)), np.empty((nu, L, na, m))
        for k in range(1, na + 1):
            if u_head.shape[0] == 1:  # one record: the plain products (einsum rounds differently)
                head[:, :, k - 1] = u_head[0][:, :, None] * x_head[0][None, None, :, k - 1]
                tail[:, :, k - 1] = u_tail[0][:, :, None] * x_tail[0][None, None, :, k - 1]
            else:
                head[:, :, k - 1] = np.einsum("snl,sm->nlm", u_head, x_head[:, :, k - 1])
                tail[:, :, k - 1] = np.einsum("snl,sm->nlm", u_tail, x_tail[:, :, k - 1])
        self._fill_lags(M, head, tail, [found[b] for b in rec], rec, mu)
        # zx contiguous (lag 0 left behind): its targets (detectability) are views of it, divided in place.
        return RowMoments(i=i, found=found, moves=moves, zx=np.ascontiguousarray(M[:, 1:]), uw=uw,
                          zo=P[:, 1:].reshape(nu * L, na), oo=O.T @ O, ow=ow, ww=ww, xsum=xsum, mu=mu,
                          R=R if keep_samples else None)

    def _lag_zero(self, O: np.ndarray, P: np.ndarray, lags: list, found: list, rec_lags: np.ndarray,
                  mu: np.ndarray, fir: Optional[dict] = None) -> np.ndarray:
        """``V' x(t - k)`` of every element, ``V = [u_c(t), O]`` on the rows (the columns at lag 0, then the
        row's own lags ``d_i(t - 1) .. d_i(t - na)``), ``k = 0 .. na``: shape (n_columns + na, na + 1, m)
        (column units, then output units, times output units).

        Lag ``k`` of element ``e`` takes a product over the rows where ``k > rec_lags[e]``; the lags
        ``k = rec_lags[e] .. 0`` follow, downward, from its difference equation at ``t - k`` (as
        :meth:`_fill_lags` at ``t``; ``x_raw = x + mu_s`` in segment ``s``, ``D = sum_q den_q``)::

            V' x(t - k) = sum_m num_m V' u_j(t - k - delay - m) - D sum_s mu_s V_s' 1
                          - sum_{q >= 1} den_q V' x(t - k - q)

        with ``V' u_j(t - s)`` from the Gram (:attr:`gram`, ``G(0, s)``) and from ``P`` (the own lags), and
        ``V_s' 1`` the column sums over segment ``s``'s rows.  An element of order ``r`` so takes ``r``
        products instead of ``na + 1`` (more where its numerator's lags would leave the Gram,
        :meth:`_recursive_lags`).  The recursion runs towards later ``t - k``, as :meth:`_fill_lags`'s:
        stable for a stable or integrating element.

        Parameters
        ----------
        O : ndarray, shape (n_rows, na)
            The row's own lags on the rows (output units).
        P : ndarray, shape (n_columns, L + 1, na)
            :meth:`_own_lags` of the row.
        lags : list of ndarray, shape (n_rows, m)
            ``x(t - k)`` on the rows, ``k = 0 .. na``.
        found : list of (int, DiscreteElement, float)
            :attr:`RowMoments.found`.
        rec_lags : ndarray of int, shape (m,)
            :meth:`_recursive_lags` of every element.
        mu : ndarray, shape (S, m)
            Every element's mean response over each segment (output units).
        fir : dict, optional
            Position ``e`` -> ``u_c(t)' x_e(t - k)``, shape (n_columns, na + 1), of the long finite impulse
            responses (:meth:`_fir_moments`): placed as given; their ``O' x(t - k)`` by products.
        """
        nu, na, m = self.u_c.shape[1], self.na, len(found)
        fir = fir or {}
        on_u = np.array([b not in fir for b in range(m)], dtype=bool)
        V = np.empty((nu + na, na + 1, m))
        for k in range(na + 1):
            by_product = np.flatnonzero(rec_lags < k)
            if by_product.size:
                x = lags[k] if by_product.size == m else lags[k][:, by_product]
                own = on_u[by_product]
                if np.all(own):
                    V[:nu, k, by_product] = self.u_rows.T @ x
                elif np.any(own):
                    V[:nu, k, by_product[own]] = self.u_rows.T @ x[:, own]
                V[nu:, k, by_product] = O.T @ x
        for b, uw in fir.items():
            V[:nu, :, b] = uw
        rec = np.flatnonzero(rec_lags >= 0)
        if rec.size:
            # V' u_j(t - s), shape (nu + na, nu, L + 1)
            cross = np.concatenate([self.gram[:, 0], np.moveaxis(P, 2, 0)])
            sums = np.hstack([self.u_sums, self._segment_sums(O)])                   # (S, nu + na)
            F = self._forcing(cross, sums, [found[b] for b in rec], mu[:, rec], rec_lags[rec])
            den = self._denominators([found[b] for b in rec])
            for k in range(int(rec_lags[rec].max()), -1, -1):
                at = np.flatnonzero(rec_lags[rec] >= k)
                V[:, k, rec[at]] = F[:, k, at] - np.einsum("vke,ke->ve", V[:, k + 1:, rec[at]], den[:na - k, at])
        return V

    def _own_lags(self, i: int, O: np.ndarray) -> np.ndarray:
        """``P[c, l, k - 1] = sum_t u_c(t - l) d_i(t - k)`` of row ``i`` over the rows, ``l = 0 .. L``, ``k = 1 .. na``
        (shape (n_columns, L + 1, na); ``P[:, 1:]`` is ``Z' O``), ``O`` its own lags ``d_i(t - 1) .. d_i(t - na)``
        on the rows (``d_i`` centred over each level group's samples, :meth:`levels`).

        Along the diagonals of lag pairs, as ``M`` in :meth:`_compute`: with ``P(l, k) = sum_t u_c(t - l)
        d_i(t - k)``, ``P(l, k) = P(l - 1, k - 1) + u(start - l) d(start - k) - u(N - l) d(N - k)`` (summed
        over the segments).  Lag ``k = 0`` is ``Z' d_i``, taken for every output in one product per window
        (:meth:`_own_moments`); lag ``l = 0`` is ``u_c(t)' [d_i, O]`` on the rows.  So no row reads ``Z``.
        """
        na, L, nu = self.na, self.n_lag, self.u_c.shape[1]
        if na == 0:
            return np.zeros((nu, L + 1, 0))
        zd, rows, d_head, d_tail = self._own_moments()
        P = np.empty((nu, L + 1, na + 1))
        P[:, 1:, 0] = zd[:, i].reshape(nu, L)
        P[:, 0] = self.u_rows.T @ np.column_stack([rows[:, i], O])
        u_head, u_tail = self.u_head, self.u_tail                           # (S, nu, L)
        for k in range(1, na + 1):
            P[:, 1:, k] = P[:, :-1, k - 1] + np.einsum("snl,s->nl", u_head, d_head[:, k - 1, i]) \
                - np.einsum("snl,s->nl", u_tail, d_tail[:, k - 1, i])
        return P[:, :, 1:]

    def _own_moments(self) -> tuple:
        """``(Z' D, D, d_head, d_tail)`` of the prediction errors of every output, taken once per window:
        ``D`` (n_rows, n_outputs) the errors on the rows, each centred over its level groups' samples (:meth:`levels`),
        ``d_head[s, k - 1]`` and ``d_tail[s, k - 1]`` (S, na, n_outputs) the centred errors at ``start_s - k``
        and ``N_s - k``."""
        if self._own is None:
            na, start = self.na, self.start
            lags = np.arange(1, na + 1)
            if self.segments is None:
                centred = [self.d[a:b] - self.d[a:b].mean(axis=0) for a, b in self.segs]
            else:
                d = self.centred_errors()
                centred = [d[a:b] for a, b in self.segs]
            rows = np.vstack([c[start:] for c in centred])
            d_head = np.stack([c[start - lags] for c in centred])
            d_tail = np.stack([c[c.shape[0] - lags] for c in centred])
            self._own = (self.Z.T @ rows, rows, d_head, d_tail)
        return self._own

    def _recursive(self, element) -> bool:
        """Whether :meth:`_fill_lags` gives ``Z' x`` of ``element``: its denominator of at most ``na``
        lags, and every input lag of its numerator among the Gram's (``<= L``) and inside each segment's
        samples on every regression row (``<= start``)."""
        if element.order > self.na:
            return False
        taps = np.flatnonzero(element.num != 0)
        return taps.size == 0 or element.delay + int(taps[-1]) <= min(self.n_lag, self.start)

    def _long_fir(self, element) -> bool:
        """Whether ``element`` is a finite impulse response (no pole: a step-response model's element) that
        :meth:`_fir_moments` takes: one with an effect, not :meth:`_recursive`, whose taps and ``na`` more
        lie within the long Gram (:attr:`fir_gram`), which takes at most :data:`FIR_GRAM_MAX_BYTES`."""
        if element.order != 0 or element.is_zero or self._recursive(element):
            return False
        nu = self.u_c.shape[1]
        fits = nu * nu * (self.fir_span + 1) * (self.n_lag + 1) * 8 <= FIR_GRAM_MAX_BYTES
        return fits and element.delay + element.num.size + self.na <= self._fir_spans[0] + 1

    @property
    def fir_span(self) -> int:
        """The last lag ``s`` of :attr:`fir_gram`: over the model's elements without poles, the largest
        ``delay + len(num) - 1``, plus ``na`` (0 when the model has none); at most the last lag at which a
        column's sample still reaches a row (:attr:`fir_reach`): beyond it every product is 0, and the taps
        of a response longer than the window multiply zeros there (:meth:`_fir_moments` leaves them out)."""
        return self._fir_spans[1]

    @property
    def fir_reach(self) -> int:
        """The last lag ``s`` at which ``u_j(t - s)`` is not 0 on some row ``t``: the longest segment's samples less
        one (or, when the responses run through the short gaps, the largest place on a run's grid)."""
        if self.joined:
            return max(int(run_places(run)[-1]) for run in self.segments.runs)
        return max(b - a for a, b in self.segs) - 1

    @property
    def _fir_spans(self) -> tuple:
        """``(the model's span, fir_span)``: the first without the cap at :attr:`fir_reach`."""
        spans = self._fir_span
        if spans is None:
            model = self.model
            span = 0
            for a, b in zip(*np.nonzero(model.present)):
                element = model.discrete_element(int(a), int(b))
                if element.order == 0 and not element.is_zero:
                    span = max(span, element.delay + element.num.size - 1 + self.na)
            spans = self._fir_span = (span, min(span, self.fir_reach))
        return spans

    @property
    def fir_gram(self) -> np.ndarray:
        """``E[j, s, c, l] = sum_t u_j(t - s) u_c(t - l)`` over the rows, ``s = 0 ..`` :attr:`fir_span`,
        ``l = 0 .. L``, with ``u_j(t - s) = 0`` before the start of ``t``'s segment (a response from rest
        there), shape (n_columns, fir_span + 1, n_columns, L + 1) (column units squared); taken once per
        window.  When the responses run through gaps (:attr:`joined`), ``u_j(t - s)`` is read on the
        sample grid of ``t``'s run, the columns held in its short gaps and 0 before its first sample, as
        :func:`~mpm_monitor.core.segments.through` simulates the responses.

        Lag ``l = 0`` takes a product over the rows per column ``j``; lag ``s = 0`` is the Gram's
        (:attr:`gram`); the others are sums along the diagonals of lag pairs, as ``M`` in
        :meth:`_compute`: ``E(s, l) = E(s - 1, l - 1) + u_j(start - s) u_c(start - l) - u_j(N - s) u_c(N - l)``
        (summed over the segments; ``start`` a segment's first row, ``N`` its end).
        """
        E = self._fir_gram
        if E is None:
            nu, L, S, start = self.u_c.shape[1], self.n_lag, self.fir_span, self.start
            # u_j(t - s) on each segment's rows, s = 0 .. S: a window over the segment padded with S zeros
            # before it (or the S samples of its run's grid before it), read backwards; the head and tail
            # corrections at s = 1 .. S likewise.
            padded = self._run_windows(S) if self.joined else \
                [np.vstack([np.zeros((S, nu)), self.u_c[a:b]]) for a, b in self.segs]
            E = np.empty((nu, S + 1, nu, L + 1))
            # The product takes a contiguous copy of the lagged windows: lags a few at a time, at most
            # FIR_COPY_BYTES of them (a long response over a long window would copy rows x lags).
            step = max(1, FIR_COPY_BYTES // (8 * max(max(b - a - start for a, b in self.segs), 1)))
            for j in range(nu):
                lagged = [np.lib.stride_tricks.sliding_window_view(p[:, j], S + 1)[start:, ::-1] for p in padded]
                for s0 in range(0, S + 1, step):
                    E[j, s0:s0 + step, :, 0] = sum(w[:, s0:s0 + step].T @ self.u_c[a + start:b]
                                                   for w, (a, b) in zip(lagged, self.segs))
            E[:, 0, :, 1:] = np.transpose(self.gram[:, 1:, :, 0], (2, 0, 1))         # u_j(t)' u_c(t - l)
            back = np.arange(1, S + 1)
            head = np.stack([p[S + start - back].T for p in padded])                 # (S_seg, nu, S): u_j(start - s)
            tail = np.stack([p[p.shape[0] - back].T for p in padded])                # u_j(N - s)
            for lag in range(1, L + 1):
                E[:, 1:, :, lag] = E[:, :-1, :, lag - 1] + np.einsum("sjm,sc->jmc", head, self.u_head[:, :, lag - 1]) \
                    - np.einsum("sjm,sc->jmc", tail, self.u_tail[:, :, lag - 1])
            self._fir_gram = E
        return E

    def _run_windows(self, S: int) -> list:
        """For every segment, the centred columns on its run's sample grid from ``S`` samples before the
        segment's first to its last (held in the run's short gaps, 0 before the run's first sample), shape
        (S + segment samples, n_columns) each (:attr:`fir_gram` with :attr:`joined`)."""
        out = []
        for run in self.segments.runs:
            a, b, _ = run
            at = run_places(run)
            full = np.vstack([np.zeros((S, self.u_c.shape[1])),                # full[p + S]: place p
                              run_samples(self.u_c, run, self.segments.run_fill(run, slice(None)))])
            for lo, hi in self.segs:
                if a <= lo and hi <= b:
                    first = int(at[lo - a])
                    out.append(full[first:first + S + hi - lo])
        return out

    def _fir_moments(self, entry, mu: np.ndarray) -> tuple:
        """``(u_c(t)' x(t - k), u_c(t - l)' x)``, ``k = 0 .. na``, ``l = 1 .. L``, of a long finite impulse
        response (:meth:`_long_fir`) from its taps and :attr:`fir_gram`, shapes (n_columns, na + 1) and
        (n_columns, L) (column units times output units): ``_compute``'s ``V[:nu, :, e]`` and ``M[:, 1:, 0, e]``.

        ``x_raw(t) = sum_m num_m u_j(t - delay - m)`` from rest at each segment's start (or its run's, on the
        run's grid: :attr:`fir_gram`) and ``x = x_raw - mu_s``
        in segment ``s``, so ``u_c(t - l)' x(t - k) = sum_m num_m E(delay + k + m, l) - sum_s mu_s u_s(l)``,
        ``u_s(l)`` the column sums of ``u_c(t - l)`` over segment ``s``'s rows.

        Parameters
        ----------
        entry : (int, DiscreteElement, float)
            The element (an entry of :attr:`RowMoments.found`).
        mu : ndarray, shape (S,)
            Its mean response over each segment (output units).
        """
        j, element, _ = entry
        nu, L, na = self.u_c.shape[1], self.n_lag, self.na
        num, delay = element.num, element.delay
        # (T + na, nu, L + 1); fewer rows when the response is longer than the window reaches (fir_span): the taps
        # past the Gram's last lag multiply zeros and are left out.
        block = self.fir_gram[j, delay:delay + num.size + na]
        S = self.z_sums.shape[0]
        T = min(num.size, block.shape[0])
        zx = (num[:T] @ block[:T].reshape(T, nu * (L + 1))).reshape(nu, L + 1)[:, 1:] \
            - np.tensordot(mu, self.z_sums.reshape(S, nu, L), axes=(0, 0))
        uw = np.stack([num[:len(w)] @ w for w in (block[k:k + num.size, :, 0] for k in range(na + 1))],
                      axis=1) - (mu @ self.u_sums)[:, None]
        return uw, zx

    def _recursive_lags(self, element) -> int:
        """The last lag ``k`` of ``element``'s response from which :meth:`_lag_zero` takes ``V' x(t - k)`` by its
        difference equation instead of a product over the rows (-1: none, not :meth:`_recursive`).

        The equation at ``t - k`` needs the numerator's input lags ``k + delay + m`` among the Gram's and
        inside each segment (``<= min(L, start)``), and ``r`` (the order) lags above ``k`` (``<= na``).
        """
        if not self._recursive(element):
            return -1
        taps = np.flatnonzero(element.num != 0)
        last = element.delay + int(taps[-1]) if taps.size else 0
        return min(self.na - element.order, min(self.n_lag, self.start) - last)

    def _denominators(self, found: list) -> np.ndarray:
        """``den_1 .. den_na`` of every element of ``found`` (order at most ``na``; 0 beyond it), shape (na, q)."""
        den = np.zeros((self.na, len(found)))
        for q, (_, element, _) in enumerate(found):
            den[:element.order, q] = element.den[1:]
        return den

    @staticmethod
    def _forcing(cross: np.ndarray, sums: np.ndarray, found: list, mu: np.ndarray, last) -> np.ndarray:
        """The right side of the elements' difference equations ``num(q) u_j(t - delay) - D mu_s`` at ``t - k``,
        times the columns of a ``V`` and summed over the rows (:meth:`_fill_lags`, :meth:`_lag_zero`).

        Parameters
        ----------
        cross : ndarray, shape (rows..., n_columns, L + 1)
            ``sum_t V(t) u_j(t - s)``, ``s = 0 .. L``.
        sums : ndarray, shape (S, rows...)
            ``V``'s column sums over each segment's rows.
        found : list of (int, DiscreteElement, float)
            The elements (``(j, element, reference_gain)``).
        mu : ndarray, shape (S, q)
            Their mean responses over each segment (output units).
        last : sequence of int
            Per element, its last lag ``k`` (every input lag ``k + delay + m`` at most ``L``).

        Returns
        -------
        ndarray, shape (rows..., max(last) + 1, q)
            ``sum_m num_m cross[..., j, k + delay + m] - D sum_s mu_s sums_s`` of element ``e`` at
            ``k = 0 .. last[e]`` (``D = sum den``); 0 above.
        """
        last = np.asarray(last, dtype=int)
        taps = [np.flatnonzero(element.num != 0) for _, element, _ in found]
        # Every element's taps side by side (padded by taps of coefficient 0), at lags k = 0 .. max(last).
        shift = np.zeros((len(found), max((t.size for t in taps), default=0)), dtype=int)
        coef = np.zeros(shift.shape)
        for q, ((_, element, _), t) in enumerate(zip(found, taps)):
            shift[q, :t.size] = element.delay + t
            coef[q, :t.size] = element.num[t]
        k = np.arange(last.max(initial=0) + 1)[:, None, None]
        at = np.minimum(k + shift, cross.shape[-1] - 1)                 # (K + 1, q, taps); above last[e]: any
        columns = np.array([j for j, _, _ in found], dtype=int)[:, None]
        dc = np.array([element.den.sum() for _, element, _ in found])
        F = np.einsum("...kqt,qt->...kq", cross[..., columns, at], coef) \
            - (np.tensordot(sums, mu, axes=(0, 0)) * dc)[..., None, :]
        F[..., k[:, :, 0] > last] = 0.0
        return F

    @property
    def gram(self) -> np.ndarray:
        """``G[c, l, j, m] = sum_t u_c(t - l) u_j(t - m)`` over the rows, ``l, m = 0 .. L``, shape
        (n_columns, L + 1, n_columns, L + 1) (column units squared); taken once per window.

        Only ``l = 0`` or ``m = 0`` takes a product over the rows (``[u, Z]' u``); the others are sums
        along the diagonals of lag pairs, as ``M`` in :meth:`_compute`.
        """
        G = self._gram
        if G is None:
            nu, L = self.u_c.shape[1], self.n_lag
            G = np.empty((nu, L + 1, nu, L + 1))
            G[:, 0, :, 0] = self.u_rows.T @ self.u_rows
            G[:, 1:, :, 0] = (self.Z.T @ self.u_rows).reshape(nu, L, nu)
            G[:, 0, :, 1:] = np.transpose(G[:, 1:, :, 0], (2, 0, 1))       # u_c(t)' u_j(t - m)
            h, t = self.u_head, self.u_tail                                 # (S, nu, L)
            for lag in range(1, L + 1):
                G[:, lag, :, 1:] = G[:, lag - 1, :, :-1] + np.einsum("sc,sjm->cjm", h[:, :, lag - 1], h) \
                    - np.einsum("sc,sjm->cjm", t[:, :, lag - 1], t)
            self._gram = G
        return G

    def _fill_lags(self, M, head, tail, found, at, mu) -> None:
        """Fill ``M`` (see :meth:`_compute`) lag ``l`` after lag ``l``: ``M(l, k >= 1)`` along the diagonals,
        then ``M(l, 0)`` of the elements ``found`` (at positions ``at``; none is fine) from their difference
        equation instead of a product over the rows.

        An element is ``den(q) x_raw(t) = num(q) u_j(t - delay)`` on every sample of a segment (from rest,
        so while the numerator's lags stay in the segment, as on every regression row).  With
        ``x_raw = x + mu_s`` in segment ``s`` and ``D = sum_k den_k``, multiplying by ``u_c(t - l)`` and
        summing over the rows::

            M(l, 0) = sum_m num_m G(l, delay + m) - D sum_s mu_s Z_s' 1 (l) - sum_{k >= 1} den_k M(l, k)

        with ``G`` the Gram of the input lags (:attr:`gram`), ``Z_s' 1`` the column sums of segment
        ``s``'s rows, and ``M(l, k >= 1)`` from lag ``l - 1`` along the diagonals.  For a stable or
        integrating element the recursion is stable (its errors are those of ``M(l - 1, .)`` times the
        poles).  The other elements' ``M(l, 0)`` are already in ``M``.

        Parameters
        ----------
        M : ndarray, shape (n_columns, L + 1, na + 1, m)
            ``sum_t u_c(t - l) x_e(t - k)`` (column units times output units): lag ``l = 0`` given,
            ``M(l, 0)`` given for the elements not in ``at``; filled in place.
        head, tail : ndarray, shape (n_columns, L, na, m)
            The diagonal corrections ``sum_s u(start_s - l) x(start_s - k)`` and ``sum_s u(N_s - l) x(N_s - k)``
            (``l = 1 .. L``, ``k = 1 .. na``).
        found : list of (int, DiscreteElement, float)
            The elements by the recursion (:attr:`RowMoments.found`'s entries).
        at : list of int
            Their positions among the row's ``m`` elements.
        mu : ndarray, shape (S, m)
            Every element's mean response over each segment (output units).
        """
        L, nu = self.n_lag, self.u_c.shape[1]
        den = self._denominators(found)
        if found:
            S = self.z_sums.shape[0]
            F = self._forcing(self.gram[:, 1:], self.z_sums.reshape(S, nu, L), found, mu[:, at],
                              [0] * len(found))[:, :, 0]                                   # (nu, L, q)
        for lag in range(1, L + 1):
            M[:, lag, 1:] = M[:, lag - 1, :-1] + head[:, lag - 1] - tail[:, lag - 1]
            if found:
                M[:, lag, 0, at] = F[:, lag - 1] - np.einsum("ckq,kq->cq", M[:, lag, 1:][:, :, at], den)

    def filtered_products(self, rm: RowMoments, columns, a: np.ndarray, block_columns: np.ndarray) -> tuple:
        """The whole-response test's regressors and their products with the input lags, from the moments.

        For every column ``j`` of ``columns`` (each with a target element in ``rm``), the regressor is
        ``A(q) x_raw`` on the rows, centred over the rows, and with gaps over each level group's rows
        (:meth:`levels`; as :func:`~mpm_monitor.core.response_test.row_response_tests` builds it,
        :func:`~mpm_monitor.core.response_test.centred_rows`).  With ``x_raw = x + mu_s`` in segment
        ``s``, ``A(q) x_raw = sum_k a_k x(t - k) + A(1) mu_s``, whose second part is constant in each
        segment.  One record (``n`` rows, ``Z' 1`` the column sums of ``Z``)::

            Z' (A(q) x_raw - mean) = sum_k a_k Z' x(t - k) - Z' 1 sum_k a_k 1' x(t - k) / n

        With a level per segment, ``m_s`` the mean of ``sum_k a_k x(t - k)`` over segment ``s``'s rows and
        ``Z_s' 1`` the column sums of ``Z`` over them::

            Z' (A(q) x_raw - m_s - A(1) mu_s) = sum_k a_k Z' x(t - k) - sum_s Z_s' 1 m_s

        With one level over the segments of a group ``g`` (a run the model runs through), ``m_g`` the mean of
        ``A(q) x_raw`` over its rows::

            Z' (A(q) x_raw - m_g) = sum_k a_k Z' x(t - k) + sum_s Z_s' 1 A(1) mu_s - sum_g Z_g' 1 m_g

        Parameters
        ----------
        rm : RowMoments
            With :attr:`RowMoments.R` kept.
        columns : sequence of int
        a : ndarray, shape (na,)
            ``A(q) = 1 + a_1 q^-1 + ...``.
        block_columns : ndarray of int, shape (p_common,)
            The columns of ``Z`` the test's lag blocks are (in their order).

        Returns
        -------
        X : ndarray, shape (n_rows, k)
            The centred regressors.
        ZX : ndarray, shape (p_common, k)
            Their products with the lag blocks.
        """
        na = self.na
        a_poly = np.concatenate([[1.0], np.asarray(a, dtype=float)])
        if a_poly.size != na + 1:
            raise ValueError(f"A(q) of {a_poly.size - 1} lags, the moments have {na}")
        b = [rm.index(j) for j in columns]
        n = max(self.n_rows, 1)
        m = rm.zx.shape[-1]
        zx = np.tensordot(rm.zx.reshape(-1, na + 1, m), a_poly, axes=(1, 0))[block_columns][:, b]   # (p, k)
        z_sums = self.z_sums[:, block_columns]                                      # (S, p)
        # The regressors on the rows: A(q) x_raw = [x, X] a + A(1) mu_s; A(1) mu_s is constant in each segment.
        Rb = rm.R[:, b]
        X = sum(a_k * self._lagged(Rb, k) for k, a_k in enumerate(a_poly))
        if len(self.segs) == 1:         # one record: centred over the rows
            ZX = zx - np.outer(z_sums.sum(axis=0), a_poly @ rm.xsum[b].T / n)
            X -= X.mean(axis=0)
            return X, ZX
        groups = self.levels(rm.i)
        if len(set(groups.tolist())) == len(self.segs):
            # With gaps, centred over each segment's rows, as the prediction error is (centred_rows).
            means = self._segment_sums(X) / self.seg_rows[:, None]                  # (S, k)
            X -= np.repeat(means, self.seg_rows.astype(int), axis=0)
            return X, zx - z_sums.T @ means
        # One level over several segments: A(1) mu_s is no longer constant over a group; it is put back on each
        # segment's rows before the group's mean (over its rows) is taken out.
        level = a_poly.sum() * rm.mu[:, b]                                          # (S, k)
        X += np.repeat(level, self.seg_rows.astype(int), axis=0)
        rows = np.bincount(groups, weights=self.seg_rows)
        to_group = np.zeros((rows.size, len(self.segs)))
        to_group[groups, np.arange(len(self.segs))] = 1.0
        means = (to_group @ self._segment_sums(X)) / np.maximum(rows, 1.0)[:, None]    # (G, k)
        X -= np.repeat(means[groups], self.seg_rows.astype(int), axis=0)
        return X, zx + z_sums.T @ level - (to_group @ z_sums).T @ means
