"""Detectability: the smallest gain error of each element that a window's element test detects.

The Delta element test (:mod:`mpm_monitor.core.element_test`) fits, for every output ``i``, the ARX
``A(q) d_i = sum_j B_ij(q) u_j + e`` on the lags ``1 .. L`` of every input (``L = max_delay + nb``)
and rejects ``B_ij = 0`` on the ``k_ij`` lags it examines with an F test.  When the model's element
``(i, j)`` has a relative gain error ``delta`` (the plant's element is ``(1 + delta) Phat_ij``), the
prediction error carries ``delta x_ij`` with ``x_ij = Phat_ij u_j`` the element's response to the
logged input, and the ARX, whose ``A`` whitens the disturbance, sees ``delta A(q) x_ij``.  Its F
statistic then follows the noncentral F distribution ``F'(k_ij, dof, lambda)`` with::

    lambda(delta) = delta^2 q_ij / sigma_i^2

* ``sigma_i^2``: the residual variance of row ``i``'s ARX (its equation-error variance),
* ``q_ij``: the drop in the residual sum of squares of the element's test when the target is
  ``x_f = A_i(q) x_ij`` (``A_i`` the row's fitted ``A``): with ``Z`` the window's centred input
  lags, ``theta = (Z'Z)^-1 Z' x_f`` and ``S`` the tested lags,
  ``q_ij = theta_S' [((Z'Z)^-1)_SS]^-1 theta_S``, the RSS of ``x_f`` on every lag but ``S`` minus
  its RSS on every lag (rank-aware as the test itself: directions of ``((Z'Z)^-1)_SS`` below
  ``1e-10`` of its largest are left out).

The element is located when its p-value, adjusted by Holm's procedure over the ``m`` elements of
the family and by the ``N_FAMILIES = 2`` families, is below ``alpha``; a single mismatched element
among ``m`` is located when its raw p-value is below ``alpha / (2 m)`` (Holm's first step).  The
smallest ``lambda`` detected with probability ``power`` (0.9) at that level is
``lambda_90 = ncfdtrinc(k, dof, 1 - power, F_crit)``, ``F_crit`` the ``1 - alpha / (2 m)`` quantile
of ``F(k, dof)`` (:func:`mpm_monitor.core.statistics.detection_noncentrality`), so::

    detectable_gain_change_ij = sqrt(c lambda_90 sigma_i^2 / q_ij)

with ``c`` = :data:`CALIBRATION` (1.12), the factor found by simulation that makes an error of the
reported size detected 90 % of the time in closed loop; relative to ``|K_ij|``.  For an element the model lacks (no ``Phat_ij``), ``x_ij`` is the response of
the row's typical element (the present element of row ``i`` whose ``|gain|`` is the median of the
row's) to ``u_j``, so the value is ``|dK| / |typical gain|``.  Everything comes from the window
itself: its noise (``sigma_i^2``, ``A_i``) and its excitation (``Z``, ``x_ij``).

With the whole-response test (``AnalysisOptions.element_response``,
:mod:`mpm_monitor.core.response_test`) each element's p-value is ``2 min(p_window, p_response)``:
the window test above runs at half the level (``split``) for the elements that have both tests, and
an element the model has also gets the response test's value,
``sqrt(c lambda_90(k, dof) / information)`` at the same level, ``k`` its numerator degrees of freedom
(1; 2 for an integrating element, whose test adds the time-constant sensitivity; its regressor ``x_ij``
is the gain error's exact shape, so ``delta^2 information`` is its noncentrality).  The reported value is the smaller
of the two: the element is located when either test rejects.

:class:`WindowInformation` keeps the per-sample moments (``Z'Z / n``, ``Z' x_f / n``), so the
experiment design (:mod:`mpm_monitor.core.experiment`) can add a dither's contribution to them and
predict the detectability of a window that has not been recorded yet.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import numpy as np
import scipy.linalg as sla

from .element_windows import element_window
from .filters import lfilter
from .model import PlantModel
from .noise_polynomial import undetermined_rows
from .parallel import split_map
from .response_moments import ResponseMoments, target_element, typical_element  # noqa: F401 (re-exported)
from .response_test import N_ELEMENT_TESTS
from .statistics import N_FAMILIES, detection_noncentrality

#: Probability of detection the detectable gain change is defined by.
POWER = 0.9
#: Factor on the noncentrality the test needs, found by simulation (``python -m bench.detectability``):
#: the first-order noncentrality ``delta^2 q / sigma^2`` of a window is optimistic in closed loop (the
#: gain error also changes the loop's inputs and the ARX's noise model), and an error of the uncorrected
#: size was detected in 0.83 of 143 simulated runs instead of 0.9.  The factor (1.12 on ``lambda``,
#: 1.06 on ``delta``) is the one that moves that rate to 0.9 for the noncentral F's power curve.
CALIBRATION = 1.12
#: Relative size of the eigen-directions of a tested block's covariance kept (as the element test).
KEEP_EIGEN = 1e-10
#: Ridge added to the unit diagonal of the scaled input moments before inverting them.
RIDGE = 1e-9
#: Steps of the fixed point in ``delta`` (the gain error also enters the own lags).
FIXED_POINT_STEPS = 2
#: Largest gain error put into the own lags (beyond it the first-order picture is meaningless).
MAX_OWN_LAG_DELTA = 1.0
#: Length of the impulse responses kept for a dither's contribution (samples).
IMPULSE_SAMPLES = 4000
#: Elements whose moments are stacked at once (bounds the memory of :meth:`WindowInformation.drops`).
CHUNK = 256


def filtered_impulse(element, a: np.ndarray, n: int) -> np.ndarray:
    """Impulse response ``h(0) .. h(n-1)`` of ``A(q) G(q)`` (the element as the whitened ARX sees it)."""
    return lfilter(np.concatenate([[1.0], a]), [1.0], element.impulse_response(n))


def quadratic_forms(Hss: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``theta' Hss^-1 theta`` of a stack of tested blocks, rank-aware as the element test's Wald test.

    Parameters
    ----------
    Hss : ndarray, shape (g, k, k)
        The tested block of the inverse regressor moments, per target.
    theta : ndarray, shape (g, k)
        The tested coefficients, per target.

    Returns
    -------
    ndarray, shape (g,)
        Directions of ``Hss`` below :data:`KEEP_EIGEN` of its largest are left out.
    """
    w, v = np.linalg.eigh(Hss)
    keep = w > KEEP_EIGEN * np.maximum(w.max(axis=1, initial=0.0), 1e-300)[:, None]
    proj = np.einsum("gkm,gk->gm", v, theta)
    return np.sum(np.where(keep, proj ** 2 / np.where(keep, w, 1.0), 0.0), axis=1)


def moment_inverse(G: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric moment matrix, by Cholesky on its unit-diagonal scaling plus a ridge.

    The ridge (:data:`RIDGE` times the unit diagonal) keeps a matrix of collinear lags invertible:
    its near-null directions get huge variances, so the gains of collinear inputs come out
    (correctly) as barely detectable, while the other inputs' are unaffected to about the ridge.
    """
    s = np.sqrt(np.maximum(np.diag(G), 0.0))
    s = np.where(s > 0, s, 1.0)
    Gs = G / np.outer(s, s)
    Gs[np.diag_indices_from(Gs)] += RIDGE
    try:
        L = np.linalg.cholesky(Gs)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(Gs, rcond=1e-13, hermitian=True) / np.outer(s, s)
    Li = sla.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
    return (Li.T @ Li) / np.outer(s, s)


def required_noncentrality(k: int, dof: int, level: float, power: float = POWER) -> float:
    """``lambda`` the element test of ``k`` lags and ``dof`` residual degrees of freedom needs at ``level``.

    :func:`~mpm_monitor.core.statistics.detection_noncentrality` (the noncentral F detected with
    probability ``power``) times :data:`CALIBRATION`.
    """
    return CALIBRATION * detection_noncentrality(k, dof, level, power)


@dataclasses.dataclass
class ElementTarget:
    """The moments the detectability of one element depends on (per sample, over the regression rows).

    ``Z``: the centred input lags; ``O``: the row's own lags ``d_i(t - 1) .. d_i(t - na)``; ``x``: the
    element's response to its input (centred); ``X``: its lags ``x(t - 1) .. x(t - na)``; ``x_f``:
    ``A_i(q) x``.

    Attributes
    ----------
    output, column : int
        Row ``i`` and the element's column ``j`` (index into the model's columns).
    tested : ndarray of int
        Columns of ``Z`` the element's test examines (input ``j``'s lags are the columns
        ``j L .. (j + 1) L - 1``).
    reference_gain : float
        ``|K|`` the relative change refers to.
    c : ndarray, shape (p,)
        ``Z' x_f / n``.
    c_own : ndarray, shape (na,)
        ``O' x_f / n``.
    zx : ndarray, shape (p, na)
        ``Z' X / n``.
    ox : ndarray, shape (na, na)
        ``O' X / n``.
    xx : ndarray, shape (na, na)
        ``X' X / n``.
    xxf : ndarray, shape (na,)
        ``X' x_f / n``.
    element : DiscreteElement
        The element whose response ``x`` is (the model's, or the row's typical one).
    a_poly : ndarray, shape (na + 1,)
        ``[1, a_1 .. a_na]``: the row's ``A_i``.
    impulse_samples : int
        Length ``m`` of :attr:`impulse` and :attr:`filtered`.
    """

    output: int
    column: int
    tested: np.ndarray
    reference_gain: float
    c: np.ndarray
    c_own: np.ndarray
    zx: np.ndarray
    ox: np.ndarray
    xx: np.ndarray
    xxf: np.ndarray
    element: object
    a_poly: np.ndarray
    impulse_samples: int

    @property
    def impulse(self) -> np.ndarray:
        """Impulse response ``g(0) .. g(m - 1)`` of the element, shape (m,) (computed on first use: only
        a dither's contribution needs it, for the few inputs an experiment dithers)."""
        cached = self.__dict__.get("_impulse")
        if cached is None:
            cached = self.__dict__["_impulse"] = self.element.impulse_response(self.impulse_samples)
        return cached

    @property
    def filtered(self) -> np.ndarray:
        """Impulse response ``h`` of ``A_i(q)`` times the element, shape (m,) (computed on first use)."""
        cached = self.__dict__.get("_filtered")
        if cached is None:
            cached = self.__dict__["_filtered"] = lfilter(self.a_poly, [1.0], self.impulse)
        return cached

    def dither_moments(self, n_lag: int) -> tuple:
        """What a white dither of unit amplitude on the element's input adds to its moments.

        A dither of amplitude ``a`` adds ``a^2`` times these (computed once, then cached).

        Returns
        -------
        dc : ndarray, shape (n_lag,)
            To ``c`` on the input's lags 1..L: ``a^2 h(l)`` (``g``, ``h``: :attr:`impulse`,
            :attr:`filtered`).
        dzx : ndarray, shape (n_lag, na)
            To ``zx`` on the input's lags: ``a^2 g(l - k)`` (0 for ``l < k``).
        dxx : ndarray, shape (na, na)
            To ``xx``: ``a^2 sum_m g(m) g(m + |k - k'|)``.
        dxxf : ndarray, shape (na,)
            To ``xxf``: ``a^2 sum_m g(m) h(m + k)``.
        """
        cached = self.__dict__.get("_dither")
        if cached is not None and cached[0] == n_lag:
            return cached[1]
        a2 = 1.0
        g, h = self.impulse, self.filtered
        na = self.xx.shape[0]
        m = g.size
        lags = np.arange(1, n_lag + 1)
        ks = np.arange(1, na + 1)
        diff = lags[:, None] - ks[None, :]
        dzx = np.where(diff >= 0, g[np.clip(diff, 0, m - 1)], 0.0) * a2
        auto = np.array([g[:m - t] @ g[t:] for t in range(na)])
        dxx = a2 * auto[np.abs(ks[:, None] - ks[None, :])]
        dxxf = a2 * np.array([g[:m - k] @ h[k:] for k in ks])
        out = (a2 * h[1:n_lag + 1], dzx, dxx, dxxf)
        self.__dict__["_dither"] = (n_lag, out)
        return out


class WindowInformation:
    """The per-sample information of one window about the gains of its elements.

    The element test of row ``i`` regresses ``d_i`` on the input lags ``Z`` and on its own lags
    ``O_i`` (see :class:`ElementTarget` for the notation).  With a gain error ``delta`` of element
    ``(i, j)`` the prediction error is ``delta x + v``, so its own lags are ``O_alt = O_i + delta X``
    and ``d_i + sum a_k d_i(t - k) = delta x_f + e``: the test's noncentrality is ``delta^2 q / sigma^2``
    with ``q`` the drop in the residual sum of squares of ``x_f`` on ``[Z, O_alt]`` when the tested
    lags ``S`` are left out::

        q / n = theta_S' [H_SS]^-1 theta_S,   H = (G - U D^-1 U')^-1,   theta = H (c - U D^-1 c_o)

    with ``G = Z'Z / n``, ``U = Z'O_alt / n``, ``D = O_alt'O_alt / n``, ``c = Z' x_f / n`` and
    ``c_o = O_alt' x_f / n`` (the partitioned inverse of the moments of ``[Z, O_alt]``).  In closed
    loop past inputs, past disturbances and past ``x`` are correlated, so the own lags take part of
    the information; ``delta`` enters through ``O_alt``, so :meth:`detectable` solves for it by a
    fixed point, with the worse of the two signs.

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
        The window's columns: the inputs, then the measured disturbances.
    d : ndarray, shape (n_samples, n_outputs)
        The window's prediction errors.
    testable : list of int
        Inputs that move; the lags of the others are zero columns (no information).
    n_lag : int
        Lags ``1 .. n_lag`` of every input.
    start : int
        First regression row.
    noise : dict
        Output index -> :class:`~mpm_monitor.core.noise_polynomial.RowNoise` of the rows tested.
    windows : dict
        ``(i, j)`` -> lags the element test examines (None: all).
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs ``(first, end)`` of the samples, stacked in ``u`` and ``d``
        (as the tests take them).  The moments are sums over the regression rows of every segment (its
        rows from sample ``start`` of the segment on), the element responses start from rest at each
        segment (or, a :class:`~mpm_monitor.core.segments.GapSegments`, run through its short gaps as the
        model does), and each segment's ``d`` and ``x`` are centred on their own, as the tests centre
        ``d``.  Default: one record.
    split : int
        :attr:`split`.
    moments : ResponseMoments, optional
        The window's element responses and their moments with the input lags, shared with the
        element test (:class:`~mpm_monitor.core.response_moments.ResponseMoments` of these ``u``,
        ``d``, ``testable``, ``n_lag``, ``start`` and ``segments``); built here when not given.  The
        rows of ``noise`` are taken from it.

    Attributes
    ----------
    G : ndarray, shape (p, p)
        ``Z'Z / n_rows`` of the centred column lags, ``p = n_columns n_lag`` (input ``j``'s lags at
        :meth:`block`).
    own : dict
        Output index -> ``(Z'O_i / n_rows, O_i'O_i / n_rows)``.
    n_rows : int
        Regression rows of the window.
    std : ndarray, shape (n_columns,)
        Standard deviation of every input over the window.
    targets : dict
        ``(i, j)`` -> :class:`ElementTarget` (absent when the model has no element at all).
    responses : dict
        ``(i, j)`` -> ``(information per regression row, numerator degrees of freedom)`` of the
        whole-response test of the targets that had one (:func:`element_detectability` sets it; empty
        otherwise): the experiment design adds a dither's share to it.
    """

    def __init__(self, model: PlantModel, u: np.ndarray, d: np.ndarray, testable: list, n_lag: int, start: int,
                 noise: dict, windows: dict, segments=None, split: int = 1, moments: Optional[ResponseMoments] = None):
        self.model, self.testable, self.n_lag, self.noise = model, list(testable), int(n_lag), noise
        self.split = int(split)
        na = {nz.a.size for nz in noise.values()}
        if moments is None:
            moments = ResponseMoments(model, u, d, self.testable, n_lag, start, max(na, default=0), segments)
        elif moments.n_lag != self.n_lag or moments.start != int(start) or (na and na != {moments.na}) \
                or not moments.of(u, segments) or moments.testable != self.testable:
            raise ValueError(f"moments of {moments.n_lag} input lags from row {moments.start} with {moments.na} own "
                             f"lags; the tests have {self.n_lag} from row {start} with {sorted(na)}")
        self.segments = moments.segments
        Z = moments.Z
        self.n_rows = n = max(Z.shape[0], 1)
        self.G = Z.T @ Z / n
        self.std = u.std(axis=0)
        self.own = {}
        self.targets = {}
        self.responses = {}
        n_imp = max(n_lag + 2, min(u.shape[0], IMPULSE_SAMPLES))
        for i, nz in noise.items():
            self._row_targets(moments.take(i), np.concatenate([[1.0], nz.a]), n_imp, windows)

    def _row_targets(self, rm, a_poly: np.ndarray, n_imp: int, windows: dict) -> None:
        """:attr:`own` and :attr:`targets` of one row, from its :class:`~mpm_monitor.core.response_moments.RowMoments`."""
        n, L = self.n_rows, self.n_lag
        i, na, m = rm.i, rm.oo.shape[0], len(rm.found)
        self.own[i] = (rm.zo / n, rm.oo / n)
        if not m:
            return
        # Z' [x, X] / n: (nu, L, na + 1, m), divided in place: the row's moments are no longer the window's (taken),
        # and in a forked child (the detectability beside the repair) its pages stay the ones the parent wrote,
        # not a second copy of every row's (353 MiB at 100x40 with 16 own lags).
        M = rm.zx
        if M.flags.writeable:
            M /= n
        else:                                       # read-only (not this process's to change): a copy
            M = M / n
        OW, WW = rm.ow / n, rm.ww / n
        for b, (j, element, ref) in enumerate(rm.found):
            cols = slice(b * (na + 1), (b + 1) * (na + 1))
            zw, ow, ww = M[..., b].reshape(-1, na + 1), OW[:, cols], WW[b, 1:]
            # x_f = A_i(q) x = x + X a on the rows
            k = windows.get((i, j))
            k = L if k is None else min(int(k), L)
            self.targets[(i, j)] = ElementTarget(
                output=i, column=j, tested=np.arange(j * L, j * L + k), reference_gain=ref,
                c=zw @ a_poly, c_own=ow @ a_poly, zx=zw[:, 1:], ox=ow[:, 1:], xx=ww[:, 1:], xxf=ww @ a_poly,
                element=element, a_poly=a_poly, impulse_samples=n_imp)

    def block(self, j: int) -> slice:
        """Columns of input ``j``'s lags."""
        return slice(j * self.n_lag, (j + 1) * self.n_lag)

    def level(self, family_size: int, alpha: float, split: Optional[int] = None) -> float:
        """Raw level of the window test at Holm's first step: ``alpha / (N_FAMILIES m split)``.

        ``split`` (default :attr:`split`) is 2 when the element's window test shares its level with
        the whole-response test (Bonferroni, :func:`~mpm_monitor.core.response_test.combined_p_value`),
        else 1 (no whole-response test, or none for this element: one the model lacks).
        """
        return alpha / (N_FAMILIES * max(int(family_size), 1) * (self.split if split is None else int(split)))

    @functools.cached_property
    def G_inverse(self) -> np.ndarray:
        """:func:`moment_inverse` of :attr:`G`, shape (p, p) (computed on first use, once per window)."""
        return moment_inverse(self.G)

    def split_of(self, key) -> int:
        """:attr:`split` for an element the model has (it gets the whole-response test too), else 1."""
        return self.split if self.split > 1 and bool(self.model.present[key]) else 1

    def stacked(self, keys, H: np.ndarray, dither: Optional[dict] = None) -> dict:
        """The moments of ``keys`` stacked, with their products with ``H`` (shared by every gain error).

        The gain error ``delta`` enters the own lags' moments linearly (``U = Z'O_alt / n = g_zo + delta
        zx``), so every product over the input lags that :meth:`drops` needs is a polynomial in
        ``delta`` whose coefficients are taken here once::

            U' H U = Q0 + delta (Q1 + Q1') + delta^2 Q3,   U' H c = r0 + delta r1,
            H U = hzo + delta hzx  (on the tested block only)

        with ``Q0 = g_zo' H g_zo``, ``Q1 = zx' H g_zo``, ``Q3 = zx' H zx``, ``r0 = g_zo' H c`` and
        ``r1 = zx' H c``; a gain error then costs products of ``na x na`` matrices only.

        Parameters
        ----------
        keys : sequence of (int, int)
            Elements (in :attr:`targets`).
        H, dither
            As in :meth:`drops`.

        Returns
        -------
        dict
            Per element (first axis): ``g_oo``, ``ox``, ``xx``, ``Q0``, ``Q1``, ``Q3`` (m, na, na);
            ``c_own``, ``xxf``, ``r0``, ``r1`` (m, na); on the element's block of ``L`` input lags,
            ``hc`` (m, L) of ``H c``, ``hzo`` and ``hzx`` (m, L, na) of ``H g_zo`` and ``H zx``, and
            ``H_block`` (m, L, L); ``ts``: the targets.
        """
        L = self.n_lag
        ts = [self.targets[k] for k in keys]
        c = np.stack([t.c for t in ts])                                     # (m, p)
        zx = np.stack([t.zx for t in ts])                                   # (m, p, na)
        xx = np.stack([t.xx for t in ts])                                   # (m, na, na)
        xxf = np.stack([t.xxf for t in ts])                                 # (m, na)
        if dither:
            for g, t in enumerate(ts):
                if t.column in dither:
                    a2 = dither[t.column] ** 2
                    dc, dzx, dxx, dxxf = t.dither_moments(L)
                    sl = self.block(t.column)
                    c[g, sl] += a2 * dc
                    zx[g, sl] += a2 * dzx
                    xx[g] += a2 * dxx
                    xxf[g] += a2 * dxxf
        m, p, na = zx.shape
        # H zx of every element as one product (p, m na): a stack of narrow products is about 4 times slower.
        hzx = (H @ zx.transpose(1, 0, 2).reshape(p, m * na)).reshape(p, m, na).transpose(1, 0, 2)
        hc = c @ H
        zx_t = np.swapaxes(zx, 1, 2)                                        # (m, na, p)
        Q0, Q1, r0 = np.empty((m, na, na)), np.empty((m, na, na)), np.empty((m, na))
        hzo = np.empty((m, L, na))
        block = np.array([t.column * L for t in ts], dtype=int)[:, None] + np.arange(L)     # (m, L)
        outputs = np.array([t.output for t in ts])
        for i in np.unique(outputs):                                        # the own lags are the row's
            sel = np.flatnonzero(outputs == i)
            g_zo = self.own[int(i)][0]                                      # (p, na)
            h_own = H @ g_zo
            Q0[sel] = g_zo.T @ h_own
            Q1[sel] = (zx_t[sel].reshape(-1, p) @ h_own).reshape(sel.size, na, na)
            r0[sel] = hc[sel] @ g_zo
            hzo[sel] = h_own[block[sel]]
        rows = np.arange(m)[:, None]
        return dict(ts=ts, g_oo=np.stack([self.own[t.output][1] for t in ts]), ox=np.stack([t.ox for t in ts]), xx=xx,
                    c_own=np.stack([t.c_own for t in ts]), xxf=xxf, Q0=Q0, Q1=Q1, Q3=np.matmul(zx_t, hzx), r0=r0,
                    r1=np.matmul(zx_t, hc[:, :, None])[:, :, 0], hc=hc[rows, block], hzo=hzo, hzx=hzx[rows, block],
                    H_block=H[block[:, :, None], block[:, None, :]])

    def drops(self, keys, H: np.ndarray, deltas=None, dither: Optional[dict] = None,
              stacked: Optional[dict] = None) -> dict:
        """Per-sample drop ``q / n`` of every element's test (see the class docstring).

        Parameters
        ----------
        keys : sequence of (int, int)
            Elements (in :attr:`targets`).
        H : ndarray, shape (p, p)
            Inverse of the input lags' moments ``G`` (:func:`moment_inverse`).
        deltas : dict or sequence of float, optional
            ``(i, j)`` -> signed gain error in the own lags, or one per key (default 0 for every
            element).
        dither : dict, optional
            Input index -> amplitude of a white dither whose contribution is added to the moments
            (the caller adds it to ``G`` before inverting it).
        stacked : dict, optional
            :meth:`stacked` of these keys, ``H`` and ``dither`` (computed here when not given, in
            chunks of :data:`CHUNK` elements so that memory stays bounded at any size).

        Returns
        -------
        dict or ndarray
            ``(i, j)`` -> float; an array aligned with ``keys`` when ``deltas`` is a sequence (a key
            may then appear more than once, with different gain errors).
        """
        keys = list(keys)
        as_array = deltas is not None and not isinstance(deltas, dict)
        if not keys:
            return np.zeros(0) if as_array else {}
        delta = np.asarray(deltas, dtype=float) if as_array else np.array([(deltas or {}).get(k, 0.0) for k in keys])
        if stacked is None:
            out = np.concatenate([self._drops(self.stacked(keys[a:a + CHUNK], H, dither), H, delta[a:a + CHUNK])
                                  for a in range(0, len(keys), CHUNK)])
        else:
            out = self._drops(stacked, H, delta)
        return out if as_array else dict(zip(keys, out.tolist()))

    @staticmethod
    def _drops(st: dict, H: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """:meth:`drops` of the stacked moments ``st`` with the gain errors ``delta`` (one per element).

        With ``U = Z'O_alt / n``, ``D = O_alt'O_alt / n`` and ``c_o = O_alt' x_f / n`` (class docstring):
        ``s = D^-1 c_o``, ``M = D - U'HU`` and ``w = M^-1 U'H (c - U s)``; on the tested lags ``S``,
        ``theta_S = (Hc)_S + (HU)_S (w - s)`` and ``[H_SS + (HU)_S M^-1 (HU)_S']^-1`` is their
        precision (the partitioned inverse of the moments of ``[Z, O_alt]``).
        """
        ts = st["ts"]
        dl = delta[:, None, None]
        ox = st["ox"]
        D = st["g_oo"] + dl * (ox + np.swapaxes(ox, 1, 2)) + dl * dl * st["xx"]   # O_alt' O_alt / n
        na = D.shape[1]
        theta_b = st["hc"]                                                  # (m, L)
        if na:
            Q1 = st["Q1"]
            S = st["Q0"] + dl * (Q1 + np.swapaxes(Q1, 1, 2)) + dl * dl * st["Q3"]      # U' H U
            s = np.linalg.solve(D, (st["c_own"] + delta[:, None] * st["xxf"])[..., None])[..., 0]
            M = D - S
            rhs = st["r0"] + delta[:, None] * st["r1"] - np.matmul(S, s[..., None])[..., 0]     # U' H (c - U s)
            w = np.linalg.solve(M, rhs[..., None])[..., 0]
            hb = st["hzo"] + dl * st["hzx"]                                 # (H U) on the block: (m, L, na)
            theta_b = theta_b + np.matmul(hb, (w - s)[..., None])[..., 0]
        out = np.zeros(len(ts))
        sizes = np.array([t.tested.size for t in ts])
        for k in np.unique(sizes):
            sel = np.flatnonzero(sizes == k)
            theta = theta_b[sel, :k]
            Hss = st["H_block"][sel, :k, :k]
            if na:
                hs = hb[sel, :k]                                            # (g, k, na)
                Hss = Hss + np.matmul(hs, np.linalg.solve(M[sel], np.swapaxes(hs, 1, 2)))
            out[sel] = quadratic_forms(Hss, theta)
        return out

    def detectable(self, keys, alpha: float, family_size: int, power: float = POWER,
                   split: Optional[int] = None, jobs: int = 1) -> dict:
        """Smallest relative gain change of each element detected with probability ``power``.

        Parameters
        ----------
        keys : iterable of (int, int)
            Elements (in :attr:`targets`).
        alpha : float
            The analysis's false-alarm rate.
        family_size : int
            Elements in Holm's family.
        power : float
        split : int, optional
            The window test's share of the level (:meth:`level`; default :attr:`split`).
        jobs : int
            With 2, a forked child process computes part of the chunks of :data:`CHUNK`
            elements (:func:`~mpm_monitor.core.parallel.split_map`; the same chunks, the same numbers).

        Returns
        -------
        dict
            ``(i, j)`` -> float (``inf`` when the window holds no information on the element).
        """
        keys = list(keys)
        H = self.G_inverse
        level = self.level(family_size, alpha, split)
        lam = {}

        def solve(drops):
            out = {}
            for key, q in drops.items():
                t = self.targets[key]
                nz = self.noise[t.output]
                k, dof = t.tested.size, max(self.n_rows - self.G.shape[0] - nz.a.size, 1)
                if (k, dof) not in lam:
                    lam[(k, dof)] = required_noncentrality(k, dof, level, power)
                out[key] = float(np.sqrt(lam[(k, dof)] * nz.sigma2 / (q * self.n_rows))) if q > 0 else float("inf")
            return out

        def chunk(part: list) -> dict:
            """The values of the elements ``part`` (one chunk, stacked together)."""
            value = {}
            st = self.stacked(part, H)
            value.update(solve(self.drops(part, H, stacked=st)))
            for _ in range(FIXED_POINT_STEPS):
                live = [g for g, k in enumerate(part) if np.isfinite(value[k])]
                if not live:
                    break
                live_keys = [part[g] for g in live]
                st_live = st if len(live) == len(part) else \
                    {name: [v[g] for g in live] if name == "ts" else v[live] for name, v in st.items()}
                step = np.array([min(value[k], MAX_OWN_LAG_DELTA) for k in live_keys])
                worse = [solve(dict(zip(live_keys, self.drops(live_keys, H, sign * step, stacked=st_live).tolist())))
                         for sign in (1.0, -1.0)]
                value.update({k: max(w[k] for w in worse) for k in live_keys})
            return value

        value = {}
        # Every element on its own: chunks bound the memory (and are the same whichever process takes them).
        for part in split_map(chunk, [keys[a:a + CHUNK] for a in range(0, len(keys), CHUNK)], jobs):
            value.update(part)
        return value


def element_detectability(model: PlantModel, u: np.ndarray, d: np.ndarray, design, noise: dict, layout, options,
                          segments=None, responses: Optional[dict] = None, moments: Optional[ResponseMoments] = None):
    """The detectable gain change of every element of the rows the ARX element test examined.

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
        The window's inputs, then its measured disturbances.
    d : ndarray, shape (n_samples, n_outputs)
        Prediction errors of the window.
    design : InputDesign
        The window's input lag blocks (:class:`mpm_monitor.core.input_design.InputDesign`): its
        ``testable`` inputs and collinear ``groups``.
    noise : dict
        Output index -> :class:`~mpm_monitor.core.noise_polynomial.RowNoise` of every row tested
        (``ElementTest.noise``).
    layout : RegressionLayout
    options : AnalysisOptions
        Its ``alpha``, ``nb`` and ``element_window``.
    segments : sequence of (int, int), optional
        Data with gaps: the segments of ``u`` and ``d`` (the samples of the segments the tests used,
        stacked), whose moments are summed (:class:`WindowInformation`).
    responses : dict, optional
        ``(i, j)`` -> :class:`~mpm_monitor.core.response_test.ResponseTest` of the elements whose
        whole response was tested (``ElementTest.responses``).  With ``options.element_response``
        their window test runs at half the level, and an element's value is the smaller of the window
        test's and the response test's, ``sqrt(c lambda_90(k, dof) / information)`` at the same
        level: the element is located when either test rejects, so the pair detects at least what
        the better one does.  The other elements (the model lacks them, or their response is zero
        on the window) have the window test alone, at the full level.
    moments : ResponseMoments, optional
        Shared with the element test (:class:`WindowInformation`).

    Returns
    -------
    info : WindowInformation
    values : dict
        ``(i, j)`` -> float, or None where it cannot be computed (an input that never moves, a
        model without elements).
    warnings : list of str
        Why a value is None.
    """
    # A row fitted exactly (a log without noise) has no noise to measure a detectable change against.
    # (RowNoise.exact: the element fit's residual is at most EXACT_FIT of its output's spread.)
    exact = [i for i, nz in noise.items() if nz.exact or not (np.isfinite(nz.sigma2) and nz.sigma2 > 0)]
    noisy = {i: nz for i, nz in noise.items() if i not in exact}
    windows = {(i, j): element_window(model, i, j, options.nb, options.element_window)
               for i in noisy for j in range(model.n_columns)}
    split = N_ELEMENT_TESTS if getattr(options, "element_response", False) else 1
    info = WindowInformation(model, u, d, design.testable, layout.n_lag_u, layout.start, noisy, windows, segments,
                             split=split, moments=moments)
    family = sum(1 for i in noise for j in design.testable if model.columns[j] not in design.group_of)
    values = {(i, j): None for i in noise for j in range(model.n_columns)}
    tested = [k for k in info.targets if k[1] in design.testable]
    # The window test runs at half the level only where the element has the whole-response test too:
    # an element the model lacks has the window test alone, at the full level.
    paired = set(responses or {})
    jobs = getattr(options, "jobs", 1)
    values.update(info.detectable([k for k in tested if k in paired], options.alpha, family, jobs=jobs))
    values.update(info.detectable([k for k in tested if k not in paired], options.alpha, family, split=1, jobs=jobs))
    level = info.level(family, options.alpha)
    for key, t in (responses or {}).items():
        if key in values and values[key] is not None and t.information > 0:
            lam = required_noncentrality(t.df_num, t.df_den, level)
            values[key] = min(values[key], float(np.sqrt(lam / t.information)))
            if key in info.targets and np.isfinite(t.information):
                info.responses[key] = (float(t.information) / info.n_rows, int(t.df_num))
    # A row whose element fit's noise polynomial is undetermined (RowNoise.undetermined): inputs that move only
    # with the controller's feedback, or a prediction error without noise (in a mismatched row of a log without
    # noise, an exact function of the inputs).  In the first the first-order values above assume the inputs
    # given, but there a gain error changes them too, and a square loop's controller ties each input to the
    # outputs it controls: ``python -m bench.detectability --still --first-order`` detected an error of the
    # computed size in 11 of 65 such rows (the rows of every square loop: 6 of 59), against 210 of 235
    # elsewhere.  In the second there is no noise to value a change against.  Nothing is reported there (the
    # element test's warning says why).
    feedback = set(undetermined_rows(noisy))
    values.update({k: None for k in values if k[0] in feedback})
    warnings = []
    # (An output that never moves, a stuck sensor, whose prediction error the model's own response fits exactly,
    # is not among the rows tested: analysis.still_output_warnings names it.)
    if exact:
        warnings.append(f"output{'s' if len(exact) > 1 else ''} {', '.join(model.outputs[i] for i in exact)}: the "
                        "prediction error is fitted exactly (a log without noise?): the smallest gain change this "
                        "window detects is not computed there (detectable_gain_change null)")
    if noise and design.constant:
        dvs = set(model.disturbances)
        parts = [f"{what} {', '.join(names)}" for what, names in (
            ("inputs", [c for c in design.constant if c not in dvs]),
            ("measured disturbances", [c for c in design.constant if c in dvs])) if names]
        warnings.append(f"{' and '.join(parts)} never move: the smallest gain change of their elements this window "
                        "detects cannot be computed (detectable_gain_change null)")
    blind = [k for k, v in values.items() if v is not None and not np.isfinite(v)]
    if blind:
        warnings.append("elements " + ", ".join(f"({model.outputs[i]}, {model.columns[j]})" for i, j in blind)
                        + ": this window holds no information on their gain (detectable_gain_change null)")
    if noise and not np.any(model.present):
        warnings.append("the model has no element: no gain to refer a detectable change to (detectable_gain_change "
                        "null)")
    return info, values, warnings
