"""The response to the unknown columns of a short gap, fitted to the prediction error after it.

The model runs through a gap of at most ``max_gap`` samples with its columns ``[u | dv]`` held at
their last logged values (:func:`mpm_monitor.core.signals.segment_signals`).  The plant received the
columns the controller really sent there, which the log lost.  Their difference from the held values,
``delta_j(p)`` for column ``j`` at each missing sample ``p``, reaches output ``i`` through the model's
impulse response ``g_ij``: the prediction error after the gap carries ``sum_{j, p} g_ij(t - p)
delta_j(p)``, a transient the size of the model's response to one move.  On a loop whose inputs move
at every sample (a PRBS dither, a busy controller) it reads as a step or as colour in every later test.

The ``delta_j(p)`` are unknown, like the model's state at the start of a record: they are estimated
the same way, row by row (so that a mismatch in one row can never leak into another), by least squares
on the row's prediction error about its mean over the run, and their response is subtracted.  Nothing
is interpolated: only the model's response to the unknown values enters, never a value of the log.
The fit is small beside the record: one unknown per missing sample and element of the row, each
acting on the samples until the element's impulse response has decayed to
:data:`GAP_RESPONSE_FRACTION` of its largest value.  Gaps further apart than that do not interact, so
the normal equations are banded (solved with :func:`scipy.linalg.solveh_banded`, with a ridge of
:data:`GAP_RIDGE` of their largest diagonal entry: a missing sample whose response never reaches a
logged one, or two consecutive missing samples of a slow element, are not identifiable and keep the
held value).

An integrating element's response never decays: a pulse of its input moves the output's level for
good, which every test already takes out segment by segment (an integrating output's level is
arbitrary).  An output with an integrating element is not fitted at all (decaying responses fitted
to an error that also steps at every gap would take up part of the steps): it keeps the held columns.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .model import PlantModel

#: A missing sample's unknown columns are fitted over the samples until the element's impulse response has
#: fallen for good below this fraction of its largest magnitude.
GAP_RESPONSE_FRACTION = 1e-3
#: Ridge added to the diagonal of the fit's normal equations, relative to their largest diagonal entry.
GAP_RIDGE = 1e-9


def decaying_impulses(model: PlantModel, i: int, n_max: int,
                      fraction: float = GAP_RESPONSE_FRACTION) -> list:
    """The impulse responses of row ``i``'s non-zero, non-integrating elements, each cut where it has decayed.

    Each is computed over its dead time and ``(tau + tau2) ln(1 / fraction)`` samples more (where its slowest
    lag has decayed to ``fraction``; a step-response element: its coefficients), at most ``n_max``, then cut
    after its last sample above ``fraction`` of its largest.

    Parameters
    ----------
    model : PlantModel
    i : int
        Output row.
    n_max : int
        Longest response kept, samples.
    fraction : float
        A response ends after its last sample of magnitude above ``fraction`` times its largest.

    Returns
    -------
    list of (int, ndarray)
        ``(column j, g_ij(0 .. m - 1))`` (output units per column unit), ``m <= n_max``.
    """
    out = []
    if n_max <= 0:
        return out
    step = model.step_response is not None
    for j in range(model.n_columns):
        if (model.ramp[i] if step else model.integrating[i, j]) or not model.present[i, j]:
            continue
        el = model.discrete_element(i, j)
        if el.is_zero:
            continue
        if step:            # a finite impulse response: its coefficients
            n = el.delay + el.num.size
        else:               # the slowest lag decays to the fraction within (tau + tau2) ln(1 / fraction)
            reach = (float(model.time_constant[i, j]) + float(model.time_constant2[i, j])) / model.sample_time \
                * math.log(1.0 / fraction)
            n = int(model.delay_samples[i, j]) + int(math.ceil(reach)) + 2 if reach < n_max else n_max
        h = el.impulse_response(int(min(n, n_max)))
        peak = float(np.max(np.abs(h))) if h.size else 0.0
        if not peak > 0.0:
            continue
        big = np.flatnonzero(np.abs(h) > fraction * peak)
        out.append((j, np.array(h[:int(big[-1]) + 1])))
    return out


def gap_response(model: PlantModel, d: np.ndarray, at: np.ndarray, unknown: Sequence[int],
                 fraction: float = GAP_RESPONSE_FRACTION, ridge: float = GAP_RIDGE) -> np.ndarray:
    """The fitted response of every output of one run to the unknown columns of its short gaps.

    Parameters
    ----------
    model : PlantModel
    d : ndarray, shape (n, n_outputs)
        The run's prediction error at its logged samples, the model run through the gaps with its
        columns held (output units).
    at : ndarray of int, shape (n,)
        The logged samples' places on the run's sample grid, increasing.
    unknown : sequence of int
        The places on the grid of the missing samples whose columns are unknown (held).
    fraction : float
        :data:`GAP_RESPONSE_FRACTION`.
    ridge : float
        :data:`GAP_RIDGE`.

    Returns
    -------
    ndarray, shape (n, n_outputs)
        The response to subtract from ``d`` (and to add to the model output); zero in a row with an
        integrating element or without a decaying one, and everywhere without an unknown sample.
    """
    d = np.asarray(d, dtype=float)
    at = np.asarray(at, dtype=np.int64)
    gaps = np.unique(np.asarray(unknown, dtype=np.int64))
    out = np.zeros(d.shape)
    if gaps.size == 0 or at.size == 0:
        return out
    gaps = gaps[gaps < at[-1]]              # a missing sample after the last logged one reaches none
    if gaps.size == 0:
        return out
    n_max = int(at[-1] - gaps[0])
    level = model.integrating_outputs
    for i in range(d.shape[1]):
        if level[i]:            # its level moves for good at every gap: the row is left as the model ran
            continue
        impulses = decaying_impulses(model, i, n_max, fraction)
        if impulses:
            out[:, i] = _row_response(d[:, i] - np.mean(d[:, i]), at, gaps, impulses, ridge)
    return out


def _row_response(dc: np.ndarray, at: np.ndarray, gaps: np.ndarray, impulses: list, ridge: float) -> np.ndarray:
    """:func:`gap_response` of one row: ``dc`` (shape (n,)) its prediction error about its mean, ``impulses``
    its :func:`decaying_impulses`; the fitted response, shape (n,)."""
    from scipy.linalg import solveh_banded

    nj = len(impulses)
    length = max(h.size for _, h in impulses)
    table = np.zeros((length, nj))
    for k, (_, h) in enumerate(impulses):
        table[:h.size, k] = h
    lo = np.searchsorted(at, gaps, side="right")           # the first logged sample after each gap's sample
    hi = np.searchsorted(at, gaps + length, side="left")   # the end of its response's reach
    blocks = [table[at[a:b] - p] for a, b, p in zip(lo, hi, gaps)]    # each shape (b - a, nj)
    n_gaps = gaps.size
    # The normal equations in upper banded form: a gap's block meets the later gaps whose reach starts in its own.
    reach = np.searchsorted(lo, hi, side="left")            # gaps g' < reach[g] overlap gap g's rows
    neighbours = max(1, int(np.max(reach - np.arange(n_gaps))))
    upper = nj * neighbours - 1
    size = n_gaps * nj
    ab = np.zeros((upper + 1, size))
    rhs = np.zeros(size)
    rr, cc = np.meshgrid(np.arange(nj), np.arange(nj), indexing="ij")
    for g in range(n_gaps):
        a, b, block = lo[g], hi[g], blocks[g]
        rhs[g * nj:(g + 1) * nj] = block.T @ dc[a:b]
        for h in range(g, int(reach[g])):
            end = min(b, hi[h])
            if end <= lo[h]:
                continue
            prod = block[lo[h] - a:end - a].T @ blocks[h][:end - lo[h]]
            rows, cols = g * nj + rr, h * nj + cc
            keep = rows <= cols
            ab[upper + rows[keep] - cols[keep], cols[keep]] = prod[keep]
    diagonal = ab[upper]
    top = float(np.max(diagonal))
    out = np.zeros(dc.shape)
    if not top > 0.0:
        return out
    ab[upper] = diagonal + ridge * top
    beta = solveh_banded(ab, rhs, check_finite=False)
    for g in range(n_gaps):
        out[lo[g]:hi[g]] += blocks[g] @ beta[g * nj:(g + 1) * nj]
    return out
