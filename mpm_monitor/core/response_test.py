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
from .filters import lfilter
from .model import PlantModel
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
    segments : sequence of (int, int), optional
        Data with gaps: each contiguous run of rows is simulated from rest at its own start (the
        columns inside a gap are unknown).  Default: one run.

    Returns
    -------
    dict
        Column ``j`` -> response, shape (n_samples,) in output units, for every element the model
        has whose response moves; the others are left out.
    """
    runs = [(0, u_c.shape[0])] if segments is None else segments
    out = {}
    for j in columns:
        if not model.present[i, j]:
            continue
        el = model.discrete_element(i, j)
        if el.is_zero:
            continue
        x = np.zeros(u_c.shape[0])
        for a, b in runs:
            x[a:b] = el.respond(u_c[a:b, j])
        if np.any(x != 0):
            out[j] = x
    return out


def time_constant_sensitivity(x: np.ndarray, tau: float, segments=None) -> np.ndarray:
    """The shape ``s / (tau s + 1) x`` of an integrating element's time-constant error, from its response ``x``.

    ``x`` differenced (the response without the integrator) and lagged once more by the element's first
    lag (a unit-gain first-order filter with pole ``exp(-1 / tau)``; none when ``tau`` is 0), each run on
    its own from rest.

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
    out = np.zeros(x.shape[0])
    for lo, hi in ([(0, x.shape[0])] if segments is None else segments):
        dx = np.diff(x[lo:hi], prepend=0.0)             # from rest: the run's first sample keeps x
        out[lo:hi] = lfilter([1.0 - p], [1.0, -p], dx) if p > 0 else dx
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
    out = []
    for idx, grp in zip(blocks, groups):
        grp = list(grp)
        cov = fit.covariance_block(idx)
        w, v = np.linalg.eigh(0.5 * (cov + cov.T))
        keep = w > 1e-10 * max(w.max(initial=0.0), 1e-300)
        tx = v[:, keep].T @ c_s[np.ix_(idx, grp)] / np.sqrt(w[keep])[:, None]
        ty = v[:, keep].T @ theta_s[idx] / np.sqrt(w[keep])
        sxx = xx[np.ix_(grp, grp)] - g_s[:, grp].T @ c_s[:, grp] + tx.T @ tx
        sxy = x_m_y[grp] + tx.T @ ty
        syy = fit.rss + ty @ ty
        sxx = 0.5 * (sxx + sxx.T)
        ws, vs = np.linalg.eigh(sxx)
        diag = np.diag(xx)[grp]
        kept = ws > 1e-12 * max(float(diag.max()), 1e-300)
        rank = int(kept.sum())
        dof = int(fit.dof) + int(keep.sum()) - rank
        if rank == 0 or dof < 1 or not sxx[0, 0] > 1e-12 * max(diag[0], 1e-300):
            out.append(ResponseTest(float("nan"), 1.0, 0, max(dof, 1)))
            continue
        z = vs[:, kept].T @ sxy
        explained = float(z @ (z / ws[kept]))
        rss = max(syy - explained, 1e-300 * syy)
        if rss > 0 and np.isfinite(s2 := rss / dof) and s2 > 0:
            with np.errstate(over="ignore"):             # a residual many orders below the regressor: inf
                f = (explained / rank) / s2
                information = float(sxx[0, 0] / s2)
        else:                                            # fitted exactly (a log without noise)
            f = float("inf") if explained > 0 else 0.0
            information = float("inf")
        out.append(ResponseTest(float(f), float(f_tail(f, rank, dof)), rank, dof, information=information))
    return out


def row_response_tests(model: PlantModel, i: int, fit, testable: list, common: Optional[np.ndarray],
                       block_sizes: Sequence[int], u_c: np.ndarray, d_c: np.ndarray, start: int, na: int,
                       segments=None, a: Optional[np.ndarray] = None, columns: Optional[Sequence[int]] = None,
                       extra: Optional[np.ndarray] = None) -> dict:
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
        The lag blocks (built here from ``u_c`` when None).
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

    Returns
    -------
    dict
        Column ``j`` -> :class:`ResponseTest` (one degree of freedom; two for an integrating element,
        tested with its time-constant sensitivity too), for the columns whose model element has a
        response.
    """
    resp = element_responses(model, i, testable if columns is None else columns, u_c, segments)
    if not resp:
        return {}
    cols = list(resp)
    a = np.asarray(fit.own_theta() if a is None else a, dtype=float)
    regressors = [resp[j] for j in cols]
    groups = [[k] for k in range(len(cols))]
    for k, j in enumerate(cols):
        if model.integrating[i, j]:
            groups[k].append(len(regressors))
            regressors.append(time_constant_sensitivity(resp[j], model.time_constant[i, j] / model.sample_time,
                                                        segments))
    X_t = filtered_rows(np.column_stack(regressors), a, start, segments)
    X_t = X_t - X_t.mean(axis=0)
    y = segment_rows(d_c[:, i], start, segments)
    if common is None:
        common = np.hstack([segment_lag_matrix(u_c[:, j], range(1, size + 1), start, segments)
                            for j, size in zip(testable, block_sizes)]) if testable else np.zeros((y.shape[0], 0))
    parts = [common.T @ X_t]
    if na:
        own = -segment_lag_matrix(d_c[:, i], range(1, na + 1), start, segments)
        parts.append(own.T @ X_t)
    if extra is not None:
        parts.append(extra.T @ X_t)
    g = np.vstack(parts)
    starts = np.cumsum([0] + list(block_sizes))
    blocks = [np.arange(starts[testable.index(j)], starts[testable.index(j) + 1]) for j in cols]
    tests = response_tests(fit, g, X_t.T @ X_t, X_t.T @ y, blocks, groups)
    return dict(zip(cols, tests))
