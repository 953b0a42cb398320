"""Outputs logged with a coarse resolution: a quantization the tests would read as the model's error.

A transmitter's, a historian's or an export's resolution (a level in whole centimetres, a value written
with two decimals) rounds every logged sample to a grid of step ``q``.  Much finer than the output's
noise, the rounding is one more small white noise and changes nothing.  As coarse as the noise or
coarser, the rounding error is a function of the output itself, which the inputs move: the prediction
error then holds a part that follows the inputs and that no element of the model explains, and the
element test may locate an element that is right.  Measured by rounding the outputs of
``bench.monte_carlo``'s 200 loops to ``k`` times each output's noise standard deviation
(docs/benchmarks.md, "Outputs logged with a coarse resolution"): up to ``k = 1`` every located element
the same as unrounded; from ``k = 2`` false positives, at ``k = 10`` 16 of 56 clean runs with an alarm.

:func:`resolution` finds the grid of a logged channel; :func:`resolution_warnings` names the outputs
whose grid is coarser than :data:`RESOLUTION_RATIO` times the standard deviation of their prediction
error.
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
#: Samples whose distinct values are compared first (:func:`resolution_warnings`).
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


def resolution_warnings(outputs: Sequence[str], y: np.ndarray, d: np.ndarray, skip=()) -> list:
    """The warning naming the outputs logged on a grid coarser than :data:`RESOLUTION_RATIO` times the
    standard deviation of their prediction error (module docstring).

    Parameters
    ----------
    outputs : sequence of str
        The outputs' names.
    y : ndarray, shape (n_samples, n_outputs)
        The logged outputs (deviations or not), output units.
    d : ndarray, shape (n_samples, n_outputs)
        Their prediction errors ``y - yhat``, output units.
    skip : sequence of int
        Outputs not examined (outputs that never move).

    Returns
    -------
    list of str
        No warning or one.
    """
    y, d = np.asarray(y, dtype=float), np.asarray(d, dtype=float)
    named = []
    spreads = np.std(d, axis=0) if d.size else np.zeros(len(outputs))
    for i, name in enumerate(outputs):
        spread = float(spreads[i])
        if i in skip or not spread > 0.0:
            continue
        # A grid's step is at most the smallest gap between any two distinct values: one of the first
        # HEAD_SAMPLES already at or below the limit rules the output out (a log to full precision, at once).
        head = np.diff(np.unique(y[:HEAD_SAMPLES, i]))
        if head.size and float(head.min()) <= RESOLUTION_RATIO * spread:
            continue
        q = resolution(y[:, i])
        if q is not None and q > RESOLUTION_RATIO * spread:
            named.append(f"{name} in steps of {q:.3g} ({q / spread:.3g} times the standard deviation of its "
                         f"prediction error)")
    if not named:
        return []
    return [f"outputs logged with a coarse resolution: {'; '.join(named)}. Their rounding error follows the "
            f"outputs, which the inputs move, and is no noise: the tests may locate an element of these rows that "
            f"is right. Log them with more digits (a resolution finer than their noise)"]
