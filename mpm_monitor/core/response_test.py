"""The element's whole response as a regressor: a one-degree-of-freedom test beside the lag window
(two for an integrating element).

The Delta element test (:mod:`mpm_monitor.core.element_test`) leaves every lag ``1 .. n_lag`` of
every column free and tests the first lags of element ``(i, j)``'s block.  It knows nothing of the
element's shape, and pays for that generality: a slow element's mismatch spreads over many lags, or
beyond the last one, and each lag carries little of it.

This test uses what the model says of the element.  A gain error of element ``(i, j)`` adds
``g Phat_ij u_j`` to the prediction error ``d_i`` (``Delta_ij = g Phat_ij``), over the whole log,
however slow the element; a time-constant, lead or delay error adds a response of nearly the same
shape.  So, with ``A(q)`` the row's estimated noise polynomial (the element fit's own coefficients)
and ``x_ij = Phat_ij u_j`` the model element's response to its logged column, the test adds the one
regressor ``A(q) x_ij`` to the element fit of row ``i`` in place of column ``j``'s lag block::

    A(q) d_i = c A(q) x_ij + sum_{k != j} B_ik(q) u_k - sum_l a_l d_i(t - l) + e      (H0: c = 0)

and tests ``c = 0`` with the F test of nested least squares (one numerator degree of freedom).
Under "no mismatch of (i, j)" the element fit holds with ``B_ij = 0``, so dropping column ``j``'s
lags keeps it valid and ``c`` is zero: the test keeps its level as the lag-window test does.
Leaving column ``j``'s own lags out matters: they would absorb the regressor.

An integrating element ``Phat_ij = K G(q) / (1 - q^-1)`` is different: every error of it but its
gain's cancels the integrator, so it adds a stable response that ``x_ij`` (a random walk) hardly
resembles.  Its sensitivity to the time constant, ``s / (tau s + 1) x_ij`` (the response differenced
and lagged once more by the element's first lag, :func:`time_constant_sensitivity`), is that shape
for a time-constant error, and close to it for a second lag's, a lead's or a delay's.  So an
integrating element is tested with the two regressors ``[A(q) x_ij, A(q) s / (tau s + 1) x_ij]``
together, an F test of two numerator degrees of freedom; its information stays that of ``x_ij``
(the gain error's direction, which lies in the tested span).

The two tests of an element are combined by Bonferroni: its p-value is ``2 min(p_window,
p_response)`` (:func:`combined_p_value`), so the element test's level holds whichever rejects.  An
element the model does not have has no response to test; its p-value is the window test's alone
(the choice depends on the model only, never on the data).

With the stricter option ``confirm_responses`` a located element is tested once more with the other
elements' regressors of its row free beside its own tests (:func:`given_other_responses`), from the
same products.

Everything is computed from the element fit's factor and a few cross products (no new
factorisation): with ``W = [X | own]`` the element fit's regressors, ``G = W'W``, and ``J`` the
indices of column ``j``'s block, the residual cross products of any ``a``, ``b`` on ``W`` without
``J`` are::

    a' M_{-J} b = a' M b + (G^-1 W'a)_J' [(G^-1)_JJ]^-1 (G^-1 W'b)_J

(partitioned regression), with ``M`` the annihilator of the whole ``W``.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from .arx import BlockTest, segment_lag_matrix, segment_rows
from .elements import pulse_response
from .filters import lfilter
from .model import PlantModel
from .segments import centred_by, level_groups, segment_labels, through
from .statistics import f_tail

#: The tests combined for an element the model has: the lag window's and the whole response's.
N_ELEMENT_TESTS = 2


@dataclasses.dataclass
class ResponseTest(BlockTest):
    """The whole-response test of one element: the F test of ``c = 0`` (one numerator degree of freedom).

    Attributes
    ----------
    information : float
        ``x' M x / sigma^2``: the residual energy of the regressor ``A(q) x_ij`` after the other
        regressors, over the test's residual variance.  A relative gain error ``delta`` of the
        element gives the test the noncentrality ``delta^2 information`` (to first order), which
        is what the detectable gain change of the test is computed from
        (:mod:`mpm_monitor.core.detectability`).  0 where the test could not run.
    """

    information: float = 0.0


def combined_p_value(p_window: float, p_response: Optional[float]) -> float:
    """The element's p-value: ``min(1, 2 min(p_window, p_response))``, or ``p_window`` without a response test.

    Bonferroni over the two tests of :mod:`mpm_monitor.core.response_test`: under "no mismatch" the
    probability that either rejects at ``level / 2`` is at most ``level``.
    """
    if p_response is None:
        return float(p_window)
    return float(min(1.0, N_ELEMENT_TESTS * min(p_window, p_response)))


def element_responses(model: PlantModel, i: int, columns: Sequence[int], u_c: np.ndarray,
                      segments=None) -> dict:
    """The model elements' responses ``x_ij = Phat_ij u_j`` to the centred columns.

    Parameters
    ----------
    model : PlantModel
    i : int
        Output (row).
    columns : sequence of int
        Columns ``j`` (inputs, then measured disturbances).
    u_c : ndarray, shape (n_samples, n_columns)
        The model's columns, centred (column units).
    segments : sequence of (int, int) or GapSegments, optional
        Data with gaps: each contiguous run of rows is simulated from rest at its own start, or, given
        a :class:`~mpm_monitor.core.segments.GapSegments`, each of its runs through its short gaps with
        the columns held, as the model runs (:func:`~mpm_monitor.core.segments.through`).  Default: one
        run.

    Returns
    -------
    dict
        Column ``j`` -> response, shape (n_samples,) in output units, for every element the model
        has whose response moves; the others are left out.
    """
    out = {}
    for j in columns:
        if not model.present[i, j]:
            continue
        el = model.discrete_element(i, j)
        if el.is_zero:
            continue
        x = through(np.asarray(u_c[:, j], dtype=float), el.respond, segments, column=j)
        if np.any(x != 0):
            out[j] = x
    return out


def integrating_element(model: PlantModel, i: int, j: int) -> bool:
    """Whether element (``i``, ``j``) integrates: a parametric integrating element, or a present
    element of a ramp row of a step-response model (its response keeps the last slope)."""
    if model.is_step_response:
        return bool(model.ramp[i] and model.present[i, j])
    return bool(model.integrating[i, j])


def integrating_lag(model: PlantModel, i: int, j: int) -> float:
    """The first lag of integrating element (``i``, ``j``), samples: its :func:`time_constant_sensitivity`'s ``tau``.

    A parametric element's first time constant.  A step-response element on a ramp row has none: its
    slope ``h_l = s_l - s_(l-1)`` rises to the final ``h_N``, and the area ``sum_l (1 - h_l / h_N)``
    is its dead time plus the lag of an integrator behind a first-order lag (exactly so for that
    element, sampled; the equivalent lag, the mean residence time, of a higher order); that area less
    the dead time, at least 0.
    """
    if not model.is_step_response:
        return float(model.time_constant[i, j] / model.sample_time)
    h = pulse_response(model.step_response[i, j])
    if h.size == 0 or h[-1] == 0:
        return 0.0
    nz = np.flatnonzero(h != 0)
    dead = int(nz[0]) if nz.size else 0
    return max(float(np.sum(1.0 - h / h[-1])) - dead, 0.0)


def time_constant_sensitivity(x: np.ndarray, tau: float, segments=None) -> np.ndarray:
    """The shape ``s / (tau s + 1) x`` of an integrating element's time-constant error, from its response ``x``.

    ``x`` differenced (the response without the integrator) and lagged once more by the element's first
    lag (a unit-gain first-order filter with pole ``exp(-1 / tau)``; none when ``tau`` is 0), each run on
    its own from rest (:func:`~mpm_monitor.core.segments.through`: through the short gaps of a
    :class:`~mpm_monitor.core.segments.GapSegments`, ``x`` held inside them, so the difference across a
    gap falls on its first sample after it).

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        The element's response (output units).
    tau : float
        The element's first time constant, samples (>= 0).
    segments : sequence of (int, int), optional

    Returns
    -------
    ndarray, shape (n_samples,)
    """
    p = float(np.exp(-1.0 / tau)) if tau > 0 else 0.0

    def shape(run: np.ndarray) -> np.ndarray:
        dx = np.diff(run, prepend=0.0)             # from rest: the run's first sample keeps x
        return lfilter([1.0 - p], [1.0, -p], dx) if p > 0 else dx
    return through(np.asarray(x, dtype=float), shape, segments)


def centred_rows(X: np.ndarray, start: int, segments=None, groups: Optional[np.ndarray] = None) -> np.ndarray:
    """Regressors on the regression rows less their mean over each level group's rows (over all rows without gaps).

    The prediction error is centred over each level group (:func:`~mpm_monitor.core.segments.level_groups`: a
    run of segments the model runs through, or a segment), so a regressor's level in a group explains nothing of
    it; centred over all rows instead, the regressor's group levels stay in its cross products and its variance
    (with one sample in 100 missing and a level per segment, 28 of 6,837 clean p-values fell below 0.001, 16 when
    centred per segment and 11 without gaps, 6.8 expected: ``bench.element_level --drop``).

    Parameters
    ----------
    X : ndarray, shape (n_rows, k)
        The rows of the segments stacked (:func:`~mpm_monitor.core.arx.segment_rows`).
    start : int
        First regression row of every segment.
    segments : sequence of (int, int), optional
        The segments (a segment of at most ``start`` samples has no row).
    groups : ndarray of int, shape (n_segments,), optional
        The level group of every segment (:func:`~mpm_monitor.core.segments.level_groups`); default its own.

    Returns
    -------
    ndarray, shape (n_rows, k)
        A new array.
    """
    if segments is None or len(segments) < 2:
        return X - X.mean(axis=0)
    if groups is not None and len(set(np.asarray(groups).tolist())) < len(segments):
        return centred_by(X, np.asarray(groups, dtype=np.int64)[segment_labels(start, segments, X.shape[0])])
    out = np.array(X, dtype=float)
    at = 0
    for a, b in segments:
        k = max(int(b) - int(a) - start, 0)
        if k:
            out[at:at + k] -= out[at:at + k].mean(axis=0)
        at += k
    return out


def filtered_rows(x: np.ndarray, a: np.ndarray, start: int, segments=None) -> np.ndarray:
    """``A(q) x`` on the regression rows (``A(q) = 1 + a_1 q^-1 + ...``), each run filtered on its own.

    Parameters
    ----------
    x : ndarray, shape (n_samples, k)
    a : ndarray, shape (na,)
    start : int
        First regression row of every run (at least ``na``, so no row's filter reaches across a gap).
    segments : sequence of (int, int), optional

    Returns
    -------
    ndarray, shape (n_rows, k)
    """
    num = np.concatenate([[1.0], np.asarray(a, dtype=float)])
    runs = [(0, x.shape[0])] if segments is None else segments
    xf = np.zeros_like(x)
    for lo, hi in runs:
        xf[lo:hi] = lfilter(num, [1.0], x[lo:hi], axis=0)
    return segment_rows(xf, start, segments)


def response_tests(fit, g: np.ndarray, xx: np.ndarray, xy: np.ndarray, blocks: Sequence[np.ndarray],
                   groups: Optional[Sequence[Sequence[int]]] = None) -> list:
    """The F tests of ``c = 0`` for groups of response regressors, each group in place of one lag block.

    Parameters
    ----------
    fit : SharedFit or GramFit
        The element fit of the row: ``y`` on ``W = [common | own]`` (its ``rinv``, ``scale``, ``theta``,
        ``rss``, ``dof``).
    g : ndarray, shape (p, k)
        ``W' x`` of every regressor ``x`` (raw, unscaled columns of ``W``).
    xx : ndarray, shape (k, k)
        ``X' X`` of the regressors (only the blocks of each group are read).
    xy : ndarray, shape (k,)
        ``X' y``.
    blocks : sequence of ndarray of int
        For every test, the indices in ``W`` of the block its regressors replace.
    groups : sequence of sequence of int, optional
        For every test, the indices of its regressors among the ``k`` (default: regressor ``t`` alone
        for test ``t``, one numerator degree of freedom each).  The first of a group is the element's
        response, whose information :attr:`ResponseTest.information` reports.

    Returns
    -------
    list of ResponseTest
        One per test, with as many numerator degrees of freedom as its regressors have independent
        directions left after the other columns (``df_num`` 0 and ``p_value`` 1 where they have none).
    """
    xx = np.atleast_2d(np.asarray(xx, dtype=float))
    if groups is None:
        groups = [[k] for k in range(len(blocks))]
    scale = fit.scale
    rinv = fit.rinv
    g_s = g / scale[:, None]
    c_s = rinv @ (rinv.T @ g_s)                          # coefficients of each x on W, scaled
    theta_s = fit.theta * scale
    x_m_y = xy - g_s.T @ theta_s
    out = [None] * len(blocks)
    sizes = [(len(idx), len(grp)) for idx, grp in zip(blocks, groups)]
    # The tests whose blocks and groups are equally large are taken together (stacked decompositions).
    for kb, kg in sorted(set(sizes)):
        which = [t for t, sz in enumerate(sizes) if sz == (kb, kg)]
        idx = np.array([np.asarray(blocks[t], dtype=int) for t in which]).reshape(len(which), kb)
        grp = np.array([list(groups[t]) for t in which], dtype=int).reshape(len(which), kg)
        for t, test in zip(which, _stacked_tests(fit, xx, c_s, g_s, theta_s, x_m_y, idx, grp)):
            out[t] = test
    return out


def _stacked_tests(fit, xx, c_s, g_s, theta_s, x_m_y, idx: np.ndarray, grp: np.ndarray) -> list:
    """:func:`response_tests` of ``g`` tests whose blocks ``idx`` (g, kb) and groups ``grp`` (g, kg) are equally large.

    Directions of a block's covariance below 1e-10 of its largest, and of a group's residual moments
    below 1e-12 of its regressors' largest energy, are left out (they count neither in the numerator's
    nor in the denominator's degrees of freedom).
    """
    n_tests = idx.shape[0]
    cov = fit.covariance_blocks(idx)
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    keep = w > 1e-10 * np.maximum(w.max(axis=1, initial=0.0), 1e-300)[:, None]
    inv_sqrt = np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)              # (g, kb)
    vt = np.swapaxes(v, 1, 2)
    tx = (vt @ c_s[idx[:, :, None], grp[:, None, :]]) * inv_sqrt[:, :, None]           # (g, kb, kg)
    ty = (vt @ theta_s[idx][:, :, None])[:, :, 0] * inv_sqrt                            # (g, kb)
    gs, cs = g_s[:, grp], c_s[:, grp]                                                   # (p, g, kg)
    sxx = xx[grp[:, :, None], grp[:, None, :]] - np.einsum("pgi,pgj->gij", gs, cs) \
        + np.swapaxes(tx, 1, 2) @ tx
    sxy = x_m_y[grp] + np.einsum("gki,gk->gi", tx, ty)
    syy = fit.rss + np.sum(ty * ty, axis=1)
    sxx = 0.5 * (sxx + np.swapaxes(sxx, 1, 2))
    ws, vs = np.linalg.eigh(sxx)
    diag = np.diagonal(xx)[grp]                                                         # (g, kg)
    kept = ws > 1e-12 * np.maximum(diag.max(axis=1), 1e-300)[:, None]
    rank = kept.sum(axis=1)
    dof = int(fit.dof) + keep.sum(axis=1) - rank
    valid = (rank > 0) & (dof >= 1) & (sxx[:, 0, 0] > 1e-12 * np.maximum(diag[:, 0], 1e-300))
    z = np.einsum("gki,gk->gi", vs, sxy)
    explained = np.sum(np.where(kept, z * z / np.where(kept, ws, 1.0), 0.0), axis=1)
    rss = np.maximum(syy - explained, 1e-300 * syy)
    out = []
    for t in range(n_tests):
        if not valid[t]:
            out.append(ResponseTest(float("nan"), 1.0, 0, max(int(dof[t]), 1)))
            continue
        r, df = int(rank[t]), int(dof[t])
        floor = df * fit.exact_sigma2
        if floor > 0 and syy[t] - explained[t] <= floor:    # fitted exactly but for rounding (SharedFit.exact)
            f = float("inf") if syy[t] > floor else 0.0            # statistics.exact_fit_statistic's rule
            information = float("inf")
        elif rss[t] > 0 and np.isfinite(s2 := rss[t] / df) and s2 > 0:
            with np.errstate(over="ignore"):             # a residual many orders below the regressor: inf
                f = (explained[t] / r) / s2
                information = float(sxx[t, 0, 0] / s2)
        else:                                            # fitted exactly (a log without noise)
            f = float("inf") if explained[t] > 0 else 0.0
            information = float("inf")
        out.append(ResponseTest(float(f), float(f_tail(f, r, df)), r, df, information=information))
    return out


def row_response_tests(model: PlantModel, i: int, fit, testable: list, common: Optional[np.ndarray],
                       block_sizes: Sequence[int], u_c: np.ndarray, d_c: np.ndarray, start: int, na: int,
                       segments=None, a: Optional[np.ndarray] = None, columns: Optional[Sequence[int]] = None,
                       extra: Optional[np.ndarray] = None, moments=None, rows: Optional[np.ndarray] = None) -> dict:
    """The whole-response test of every element of row ``i`` the model has, in the row's element fit
    (module docstring).

    Parameters
    ----------
    model : PlantModel
    i : int
    fit : SharedFit or GramFit
        ``d_i`` on ``[common | own]``: the lag blocks of the columns ``testable`` (sizes
        ``block_sizes``), then ``-d_i`` at lags ``1 .. na``.
    testable : list of int
        The columns of the blocks, in order.
    common : ndarray, shape (n_rows, p_common), optional
        The lag blocks (built here from ``u_c`` when None and ``moments`` is not given).
    block_sizes : sequence of int
    u_c : ndarray, shape (n_samples, n_columns)
        Centred columns.
    d_c : ndarray, shape (n_samples, n_outputs)
        Centred prediction errors.
    start : int
        First regression row of every run.
    na : int
    segments : sequence of (int, int), optional
    a : ndarray, shape (na,), optional
        ``A(q)``'s coefficients filtering the regressors (default: the fit's own coefficients).
    columns : sequence of int, optional
        Test only these of ``testable`` (default: all).
    extra : ndarray, shape (n_rows, q), optional
        Further free regressors of ``fit``, after its own lags (then ``a`` must be given).
    moments : ResponseMoments, optional
        The window's element responses and their moments with the input lags
        (:class:`~mpm_monitor.core.response_moments.ResponseMoments`, built from the same ``u_c``,
        segments and ``start``, with ``na`` own lags): the regressors and their products with the lag
        blocks (every block ``moments.n_lag`` lags) are taken from them instead of simulated and
        multiplied again; the same values to rounding.
    rows : ndarray of bool, shape (n_rows,), optional
        The regression rows (of every segment from ``start`` on) that ``fit``, ``common`` and ``extra`` hold:
        the regressors are taken on these only, each centred over its level group's rows among them
        (without ``moments``).  Default: all.

    Returns
    -------
    dict
        Column ``j`` -> :class:`ResponseTest` (one degree of freedom; two for an integrating element,
        tested with its time-constant sensitivity too), for the columns whose model element has a
        response.
    """
    reg = row_response_regressors(model, i, fit, testable, common, block_sizes, u_c, d_c, start, na, segments, a,
                                  columns, extra, moments, rows)
    return {} if reg is None else reg.tests(fit)


@dataclasses.dataclass
class RowRegressors:
    """The whole-response regressors of one row and their products with its element fit
    (:func:`row_response_regressors`).

    Attributes
    ----------
    cols : list of int
        The columns whose model element has a response, in order.
    groups : list of list of int
        For each of ``cols``, the indices of its regressors among the ``k``: its response, then (an
        integrating element) its time-constant sensitivity.
    blocks : list of ndarray of int
        For each of ``cols``, the indices in the fit's ``W`` of its column's lag block.
    g : ndarray, shape (p, k)
        ``W' x`` of every regressor (raw, unscaled columns of ``W``).
    xx : ndarray, shape (k, k)
    xy : ndarray, shape (k,)
    """

    cols: list
    groups: list
    blocks: list
    g: np.ndarray
    xx: np.ndarray
    xy: np.ndarray
    #: The regressors' and the target's residual products on the whole ``W`` and their coefficients on
    #: it (:func:`_residual_products`), once computed.
    residual: Optional[tuple] = None

    def tests(self, fit) -> dict:
        """Column -> its whole-response :class:`ResponseTest` in ``fit`` (:func:`response_tests`)."""
        return dict(zip(self.cols, response_tests(fit, self.g, self.xx, self.xy, self.blocks, self.groups)))


def row_response_regressors(model: PlantModel, i: int, fit, testable: list, common: Optional[np.ndarray],
                            block_sizes: Sequence[int], u_c: np.ndarray, d_c: np.ndarray, start: int, na: int,
                            segments=None, a: Optional[np.ndarray] = None, columns: Optional[Sequence[int]] = None,
                            extra: Optional[np.ndarray] = None, moments=None,
                            rows: Optional[np.ndarray] = None) -> Optional[RowRegressors]:
    """The regressors of :func:`row_response_tests` (same arguments) and their products, or None
    when no element of ``columns`` has a response."""
    asked = testable if columns is None else columns
    a = np.asarray(fit.own_theta() if a is None else a, dtype=float)
    y = segment_rows(d_c[:, i], start, segments)
    if rows is not None:
        if moments is not None:
            raise ValueError("rows: the regressors from the moments are on every row")
        y = y[rows]
    if moments is None:
        resp = element_responses(model, i, asked, u_c, segments)
        cols = list(resp)
    else:
        if any(int(s) != moments.n_lag for s in block_sizes):
            raise ValueError(f"lag blocks of {sorted(set(block_sizes))} lags, the moments have {moments.n_lag}")
        rm = moments.row(i, keep_samples=True)
        cols = [j for j in asked if model.present[i, j] and rm.index(j) is not None and rm.moves[rm.index(j)]]
        integrating = [j for j in cols if integrating_element(model, i, j)]
        resp = moments.responses(rm, integrating)       # already simulated: no second run
    if not cols:
        return None
    levels = level_groups(segments, not model.integrating_outputs[i])
    groups = [[k] for k in range(len(cols))]
    sensitivity = []
    for k, j in enumerate(cols):
        if integrating_element(model, i, j):
            groups[k].append(len(cols) + len(sensitivity))
            sensitivity.append(time_constant_sensitivity(resp[j], integrating_lag(model, i, j), segments))
    if moments is None and rows is not None:       # on some rows: centred over each segment's rows among them
        if common is None:
            raise ValueError("rows: the lag blocks on those rows must be given (common)")
        X_t = filtered_rows(np.column_stack([resp[j] for j in cols] + sensitivity), a, start, segments)[rows]
        labels = segment_labels(start, segments, rows.size)
        X_t = centred_by(X_t, (labels if levels is None else levels[labels])[rows])
        parts = [common.T @ X_t]
    elif moments is None:
        X_t = centred_rows(filtered_rows(np.column_stack([resp[j] for j in cols] + sensitivity), a, start, segments),
                           start, segments, levels)
        if common is None:
            common = np.hstack([segment_lag_matrix(u_c[:, j], range(1, size + 1), start, segments)
                                for j, size in zip(testable, block_sizes)]) if testable else np.zeros((y.shape[0], 0))
        parts = [common.T @ X_t]
    else:
        L = moments.n_lag
        block_columns = np.concatenate([np.arange(j * L, (j + 1) * L) for j in testable]).astype(int)
        X_t, zx = moments.filtered_products(rm, cols, a, block_columns)
        if sensitivity:
            X_s = centred_rows(filtered_rows(np.column_stack(sensitivity), a, start, segments), start, segments, levels)
            X_t = np.hstack([X_t, X_s])
            zx = np.hstack([zx, (moments.Z.T @ X_s)[block_columns]])
        parts = [zx]
    if na:
        own = -segment_lag_matrix(d_c[:, i], range(1, na + 1), start, segments)
        parts.append((own if rows is None else own[rows]).T @ X_t)
    if extra is not None:
        parts.append(extra.T @ X_t)
    g = np.vstack(parts)
    starts = np.cumsum([0] + list(block_sizes))
    blocks = [np.arange(starts[testable.index(j)], starts[testable.index(j) + 1]) for j in cols]
    return RowRegressors(cols, groups, blocks, g, X_t.T @ X_t, X_t.T @ y)


#: A regressor direction left after the fit's others with at most this fraction of its energy counts
#: as none in :func:`given_other_responses` (rounding, not information).
NUISANCE_TOLERANCE = 1e-10


def _residual_products(fit, reg: RowRegressors, V: Sequence[int], B: np.ndarray) -> tuple:
    """The cross products of the regressors ``V`` (indices among ``reg``'s) and the target, residual on
    the fit's ``W`` without its columns ``B``: shape (len(V) + 1, len(V) + 1), the target last; and the
    number of independent directions of ``B`` (the partitioned regression of the module docstring).
    The products on the whole ``W`` are computed once per ``reg`` and kept in it."""
    if reg.residual is None:
        g_s = reg.g / fit.scale[:, None]
        c_s = fit.rinv @ (fit.rinv.T @ g_s)                 # coefficients of each regressor on W, scaled
        theta_s = fit.theta * fit.scale
        k = reg.xx.shape[0]
        S = np.empty((k + 1, k + 1))
        S[:k, :k] = reg.xx - g_s.T @ c_s
        S[:k, k] = S[k, :k] = reg.xy - g_s.T @ theta_s
        S[k, k] = fit.rss
        reg.residual = (S, np.column_stack([c_s, theta_s]))
    S_all, coef = reg.residual
    at = np.r_[np.asarray(V, dtype=int), S_all.shape[0] - 1]
    S = S_all[np.ix_(at, at)]
    if B.size == 0:
        return S, 0
    cov = fit.covariance_block(B)
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = w > 1e-10 * max(float(w.max(initial=0.0)), 1e-300)
    T = (v[:, keep].T @ coef[np.ix_(B, at)]) / np.sqrt(w[keep])[:, None]
    return S + T.T @ T, int(keep.sum())


def _rss_given(S: np.ndarray, U: Sequence[int], energy: np.ndarray) -> tuple:
    """The target's residual sum of squares after the regressors ``U`` (indices into ``S``'s first rows)
    and their number of independent directions (those keeping more than :data:`NUISANCE_TOLERANCE` of
    their ``energy``, the raw ``x' x``)."""
    U = np.asarray(U, dtype=int)
    if U.size == 0:
        return float(S[-1, -1]), 0
    norm = np.sqrt(np.maximum(energy[U], 1e-300))
    A = S[np.ix_(U, U)] / np.outer(norm, norm)
    w, v = np.linalg.eigh(0.5 * (A + A.T))
    keep = w > NUISANCE_TOLERANCE
    z = v[:, keep].T @ (S[U, -1] / norm)
    return float(S[-1, -1] - np.sum(z * z / w[keep])), int(keep.sum())


def _nested_p(rss0: float, rss1: float, df_num: int, dof: int) -> float:
    """p-value of the nested F test of residual sums of squares ``rss0`` (restricted) and ``rss1``."""
    if df_num < 1 or dof < 1:
        return 1.0
    s2 = rss1 / dof
    if not s2 > 0:
        return 0.0 if rss0 > rss1 else 1.0
    return float(f_tail(max(rss0 - rss1, 0.0) / df_num / s2, df_num, dof))


def given_other_responses(fit, reg: RowRegressors, j: int, window: np.ndarray, block: np.ndarray) -> Optional[float]:
    """The unadjusted p-value of element (``i``, ``j``) with the whole responses of the row's other elements
    free: its lag-window test and, for an element the model has, its whole-response test, each in the
    element fit with every other column's regressors of ``reg`` (response, and an integrating element's
    time-constant sensitivity) added as nuisance, combined by :func:`combined_p_value`.

    A mismatch of another element of the row, slow or integrating, outlives that column's lag block; in
    closed loop its remainder correlates with column ``j``'s lags and response and can make a
    well-modelled ``(i, j)`` look mismatched.  Most of that remainder is the other element's own modelled
    response (all of it for a gain error), which these nuisance regressors hold.  Under "no mismatch of
    (i, j)" they are free, so the test keeps its level.

    Parameters
    ----------
    fit : SharedFit or GramFit
        The row's element fit (``W``: every testable column's lag block, then the row's own lags).
    reg : RowRegressors
        The row's whole-response regressors with their products (:func:`row_response_regressors`, every
        column).
    j : int
        The column tested.
    window : ndarray of int
        Indices in ``W`` of the lags its window test examines.
    block : ndarray of int
        Indices in ``W`` of its whole lag block.

    Returns
    -------
    float or None
        None when no other element of the row has a response, or the fit is exact (a log without
        noise: its tests were decided outright).
    """
    others = [k for c, k in zip(reg.cols, reg.groups) if c != j]
    if not others or fit.exact:
        return None
    N = [x for grp in others for x in grp]
    energy = np.diagonal(reg.xx)
    own = reg.groups[reg.cols.index(j)] if j in reg.cols else []
    # The window test: the first lags of j's block, with every other response free.
    S1, _ = _residual_products(fit, reg, N, np.array([], dtype=int))
    rss1, r1 = _rss_given(S1, range(len(N)), energy[N])
    S0, r_window = _residual_products(fit, reg, N, np.asarray(window, dtype=int))
    rss0, r0 = _rss_given(S0, range(len(N)), energy[N])
    dof = int(fit.dof) - r1
    if rss1 <= dof * fit.exact_sigma2:
        return None
    p_window = _nested_p(rss0, rss1, r_window + r1 - r0, dof)
    if not own:
        return combined_p_value(p_window, None)
    # The whole-response test: j's response (and sensitivity) in place of its block, every other response free.
    V = N + list(own)
    S, r_block = _residual_products(fit, reg, V, np.asarray(block, dtype=int))
    rss0, r0 = _rss_given(S, range(len(N)), energy[V])
    rss1, r01 = _rss_given(S, range(len(V)), energy[V])
    p_response = _nested_p(rss0, rss1, r01 - r0, int(fit.dof) + r_block - r01)
    return combined_p_value(p_window, p_response)
