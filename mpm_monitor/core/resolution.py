"""Outputs and inputs logged with a coarse resolution: a rounding the tests would read as the model's error.

A transmitter's, a historian's or an export's resolution (a level in whole centimetres, a value written
with two decimals) rounds every logged sample to a grid of step ``q``.  Much finer than the output's
noise, the rounding is one more small white noise and changes nothing.  As coarse as the noise or
coarser, the rounding error is a function of the output itself, which the inputs move: the prediction
error then holds a part that follows the inputs and that no element of the model explains, and the
element test may locate an element that is right.  Measured by rounding the outputs of
``bench.monte_carlo``'s 200 loops to ``k`` times each output's noise standard deviation
(docs/benchmarks.md, "Outputs logged with a coarse resolution"): up to ``k = 1`` every located element
the same as unrounded; from ``k = 2`` false positives, at ``k = 10`` 16 of 56 clean runs with an alarm
(inputs, ``bench.quantized --inputs``: see :func:`column_resolution_warnings`).

:func:`resolution` finds the grid of a logged channel; :func:`resolution_warnings` names the outputs
whose grid is coarser than :data:`RESOLUTION_RATIO` times the standard deviation of their prediction
error, and :func:`column_resolution_warnings` the inputs and measured disturbances whose grid, through an
element's gain, is.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

#: An output logged on a grid coarser than this many times the standard deviation of its prediction
#: error is named (:func:`resolution_warnings`).
RESOLUTION_RATIO = 1.5
#: The gaps between a channel's distinct values must be whole multiples of the smallest to this
#: fraction of it for the channel to be on a grid.
GRID_TOLERANCE = 0.01
#: Samples whose distinct values are compared first (:func:`_coarse_step`).
HEAD_SAMPLES = 256


def resolution(x: np.ndarray) -> Optional[float]:
    """The step of the grid every value of ``x`` lies on, or None when there is none.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        A logged channel, any units (an offset, such as an operating point subtracted, changes nothing).

    Returns
    -------
    float or None
        ``q`` (the channel's units): the smallest gap between two of its distinct values, when every gap
        between neighbouring distinct values is a whole multiple of it (to :data:`GRID_TOLERANCE` of
        ``q``).  None for a channel with fewer than three distinct values (a switch, or a channel that
        never moves: no grid to tell) or whose values lie on no such grid (a channel logged to full
        precision: its smallest gap is tiny and the others are no multiples of it).
    """
    values = np.unique(np.asarray(x, dtype=float))
    values = values[np.isfinite(values)]
    if values.size < 3:
        return None
    gaps = np.diff(values)
    q = float(gaps.min())
    if not q > 0.0:
        return None
    ratio = gaps / q
    if float(np.max(np.abs(ratio - np.round(ratio)))) > GRID_TOLERANCE:
        return None
    return q


def resolution_warnings(outputs: Sequence[str], y: np.ndarray, error_std: np.ndarray, skip=()) -> list:
    """The warning naming the outputs logged on a grid coarser than :data:`RESOLUTION_RATIO` times the
    standard deviation of their prediction error (module docstring).

    Parameters
    ----------
    outputs : sequence of str
        The outputs' names.
    y : ndarray, shape (n_samples, n_outputs)
        The logged outputs (deviations or not), output units.
    error_std : ndarray, shape (n_outputs,)
        The standard deviations of their prediction errors ``y - yhat``, output units.
    skip : sequence of int
        Outputs not examined (outputs that never move).

    Returns
    -------
    list of str
        No warning or one.
    """
    y = np.asarray(y, dtype=float)
    named = []
    for i, name in enumerate(outputs):
        spread = float(error_std[i])
        if i in skip or not spread > 0.0:
            continue
        q = _coarse_step(y[:, i], RESOLUTION_RATIO * spread)
        if q is not None:
            named.append(f"{name} in steps of {q:.3g} ({q / spread:.3g} times the standard deviation of its "
                         f"prediction error)")
    if not named:
        return []
    return [f"outputs logged with a coarse resolution: {'; '.join(named)}. Their rounding error follows the "
            f"outputs, which the inputs move, and is no noise: the tests may locate an element of these rows that "
            f"is right. Log them with more digits (a resolution finer than their noise)"]


def column_resolution_warnings(columns: Sequence[str], outputs: Sequence[str], x: np.ndarray, gain: np.ndarray,
                               integrating: np.ndarray, error_std: np.ndarray, skip=()) -> list:
    """The warning naming the inputs and measured disturbances logged on a grid whose step, through an
    element's gain, exceeds :data:`RESOLUTION_RATIO` times the standard deviation of that row's prediction
    error.

    The plant moved with the exact values and the model runs on the rounded ones: its output, and so the
    prediction error, holds the element's response to the rounding error, which follows the column.
    Measured by ``bench.quantized --inputs`` (each input rounded to ``r`` times the step that moves an
    output by its noise through the largest element): up to ``r = 1`` every located element the same as
    unrounded, from ``r = 2`` false positives.  A self-regulating element passes a slow rounding error at
    its gain; an integrating element's response to it (its gain is per second) is not counted.  A column
    that only takes values on a grid (a count, a switch of several positions) is named too: the warning
    says that it is then no concern.

    Parameters
    ----------
    columns : sequence of str
        The inputs' and measured disturbances' names, in the model's column order.
    outputs : sequence of str
        The outputs' names.
    x : ndarray, shape (n_samples, n_columns)
        The logged columns (deviations or not), their units.
    gain : ndarray, shape (n_outputs, n_columns)
        The model's gains, output units per column unit.
    integrating : ndarray of bool, shape (n_outputs, n_columns)
        The elements not counted: the model's integrating ones (every element of an integrating output,
        where the analysis calls this).
    error_std : ndarray, shape (n_outputs,)
        The standard deviations of the outputs' prediction errors, output units.
    skip : sequence of int
        Outputs not counted (outputs that never move).

    Returns
    -------
    list of str
        No warning or one.
    """
    x = np.asarray(x, dtype=float)
    spreads = np.asarray(error_std, dtype=float)
    rows = [i for i in range(len(outputs)) if i not in skip and spreads[i] > 0.0]
    g = np.where(np.asarray(integrating, dtype=bool), 0.0, np.abs(np.asarray(gain, dtype=float)))
    named = []
    for j, name in enumerate(columns):
        # The smallest step that would be named: through the element of the largest gain per unit of error spread.
        per = [(g[i, j] / spreads[i], i) for i in rows if g[i, j] > 0.0]
        if not per:
            continue
        best, i = max(per)
        q = _coarse_step(x[:, j], RESOLUTION_RATIO / best)
        if q is not None:
            named.append(f"{name} in steps of {q:.3g} (through its gain to {outputs[i]}, {q * best:.3g} times the "
                         f"standard deviation of {outputs[i]}'s prediction error)")
    if not named:
        return []
    return [f"inputs logged with a coarse resolution: {'; '.join(named)}. If that is a rounding (the plant saw "
            f"values between), the model's output follows its error, which the plant never saw: the tests may "
            f"locate an element of these columns that is right; log them with more digits. A channel that only "
            f"takes these values (a count of pumps running, a switch) is no concern"]


def _coarse_step(x: np.ndarray, limit: float) -> Optional[float]:
    """:func:`resolution` of ``x`` (shape (n_samples,)) when it exceeds ``limit``, else None."""
    # A grid's step is at most the smallest gap between any two distinct values: one of the first
    # HEAD_SAMPLES already at or below the limit rules the channel out (a log to full precision, at once).
    head = np.diff(np.unique(x[:HEAD_SAMPLES]))
    if head.size and float(head.min()) <= limit:
        return None
    q = resolution(x)
    return q if q is not None and q > limit else None
