"""Warnings on what the tests cannot see past in the model and the log.

Each names a flaw the tests would read as a mismatch, or that makes their figures mean something
else: step responses that have not settled within the model's samples (:func:`unsettled_warnings`),
outputs that never move or stop moving (:func:`still_output_warnings`, :func:`held_tail_warnings`),
an operating point the model file does not declare (:func:`offset_warnings`), and a time column in
other units than seconds (:func:`time_unit_note`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .logged_data import t_text
from .model import PlantModel

#: A row whose prediction error's mean exceeds this many times its standard deviation is named as
#: offset (:func:`offset_warnings`).
OFFSET_RATIO = 10.0


#: A step-response element that still changes by more than this fraction of its largest |value| over the last
#: tenth of its ``N`` samples (on a row without ``ramp``) has not settled within ``N`` (:func:`unsettled_warnings`).
UNSETTLED_FRACTION = 0.03


def longest_dead_time(model: PlantModel) -> tuple:
    """``(i, j, samples)``: the element of the model's longest dead time (the first such) and that dead time in
    samples (a model with outputs and columns)."""
    d = model.delay_samples
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    return int(i), int(j), int(d[i, j])


def short_max_delay_warnings(model: PlantModel, max_delay: Optional[int]) -> list:
    """The warning of a ``max_delay`` (samples) given below the parametric model's longest dead time, as a list
    (empty otherwise): the tests then search dead times up to it only, so the located elements' delays and the
    detectable changes are those of the shorter search (``--max-delay 0`` on case 3.2 reported every located
    element's delay as 1 sample, and doubled the detectable changes, without a word)."""
    if max_delay is None or model.is_step_response or model.n_outputs == 0 or model.n_columns == 0:
        return []
    i, j, longest = longest_dead_time(model)
    if longest <= max_delay:
        return []
    return [f"max_delay {max_delay} is below the model's longest dead time, ({model.outputs[i]}, {model.columns[j]}) "
            f"{longest} samples: the tests search dead times up to {max_delay} samples only, so the located "
            f"elements' delays and the detectable changes are those of the shorter search (without max_delay: the "
            f"model's longest + 5)"]


def unsettled_warnings(model: PlantModel) -> list:
    """One warning naming the step-response elements that have not settled within the model's ``N`` samples.

    The model holds each response at its last coefficient beyond ``N``: a plant whose response goes on
    rising differs from the model there, every such element can be located, and a repair that keeps the
    element's ``N`` cannot follow it.  A ``ramp`` row's elements end on a slope by design and are left out.
    "Still changing" is measured over the last tenth of the samples (the last step below 20 samples).
    """
    if not model.is_step_response or model.step_length < 2:     # (below 10 samples it was never checked)
        return []
    sr, n = model.step_response, model.step_length              # (n_outputs, n_columns, N)
    tail = np.abs(sr[..., -1] - sr[..., n - 1 - max(1, n // 10)])
    scale = np.max(np.abs(sr), axis=-1)
    cut = (tail > UNSETTLED_FRACTION * scale) & (scale > 0) & ~np.array(model.ramp, dtype=bool)[:, None]
    if not np.any(cut):
        return []
    pairs = [f"({model.outputs[i]}, {model.columns[j]})" for i, j in zip(*np.nonzero(cut))]
    shown = ", ".join(pairs[:6]) + (f" and {len(pairs) - 6} more" if len(pairs) > 6 else "")
    return [f"the step responses of {shown} have not settled within the model's {n} samples (they still change by "
            f"more than {UNSETTLED_FRACTION:.0%} of their size over its last tenth): the model holds each at its last "
            f"value beyond that, so a plant whose response goes on differs from it there, and a repair in "
            f"{n} samples cannot follow it; a longer step_response (more samples) is needed"]


def still_output_warnings(model: PlantModel, still) -> list:
    """One warning naming the outputs ``still`` (indices) that never move in the window
    (:func:`~mpm_monitor.core.logged_data.moving_columns` of the outputs): a stuck sensor or a held value,
    whose rows' elements the element test leaves untested and the repair leaves as they are."""
    still = [model.outputs[i] for i in still]
    if not still:
        return []
    rows = "their rows" if len(still) > 1 else "its row"
    return [f"output{'s' if len(still) > 1 else ''} {', '.join(still)} never move{'' if len(still) > 1 else 's'} in "
            f"this window (every value the same: a stuck sensor or a held value?): a fault of the measurement, not "
            f"of the model; the elements of {rows} are not tested (no p-value, detectable_gain_change null) and the "
            f"repair leaves them as they are (the row test reads a constant: check the measurement first)"]


#: An output whose last samples hold one value, at least this many of them and this fraction of the window, while
#: it changed at almost every sample before (:func:`held_tail_warnings`), is named as a sensor stuck there.
HELD_TAIL_SAMPLES, HELD_TAIL_FRACTION = 50, 0.05
#: ... "almost every sample": at most this fraction of its changes before the held value are zero (a quantized
#: measurement repeats its value often, and is not named).
HELD_TAIL_REPEATS = 0.01


def held_tail_warnings(model: PlantModel, y: np.ndarray, t: np.ndarray, still) -> list:
    """One warning per output (not in ``still``) whose last samples hold one value while it moved before.

    A sensor that sticks during the window (a transmitter gone, a historian holding its last value) leaves its
    output constant from there on: the tests then read the process before and the model's own response
    after, and may locate its row's elements.  Named, not left out: a held value cannot be told from a
    process at rest when the noise is below the measurement's resolution.

    Parameters
    ----------
    y : ndarray, shape (n_samples, n_outputs)
        The outputs of the window.
    t : ndarray, shape (n_samples,)
        Their times (s).
    still : sequence of int
        Outputs that never move (named by :func:`still_output_warnings`).
    """
    n = y.shape[0]
    least = max(HELD_TAIL_SAMPLES, int(HELD_TAIL_FRACTION * n))
    out = []
    for i in range(y.shape[1]):
        if i in still or n <= least:
            continue
        changes = y[1:, i] != y[:-1, i]
        moved = np.flatnonzero(changes)
        if moved.size == 0:
            continue
        held = n - 1 - int(moved[-1])           # samples after the last change, the last value's included
        before = changes[:moved[-1] + 1]
        if held >= least and np.count_nonzero(~before) <= HELD_TAIL_REPEATS * before.size:
            out.append(f"output {model.outputs[i]} holds one value over its last {held} samples (from t = "
                       f"{t_text(t[n - held])} s) while it changed at almost every sample before: a sensor stuck "
                       f"there or a held value? What the tests and the repair say of row {model.outputs[i]} mixes "
                       f"the process before with a constant after")
    return out


def offset_warnings(model: PlantModel, d: np.ndarray, y: np.ndarray, skip=(), t: Optional[np.ndarray] = None) -> list:
    """The warnings naming the rows whose prediction error sits far from zero, or ramps on an integrating
    output: an undeclared operating point?

    The model's elements act on deviations from the model file's ``input_nominal``, ``output_nominal``
    and ``disturbance_nominal``.  A log whose columns sit at an operating point the file does not
    declare (a feed temperature logged at 350) leaves the model's output offset from the outputs by a
    constant: the tests remove each signal's mean and do not see it, but the prediction-error figures
    (``error_before``, ``error_after``) do, and a step-response model, simulated from rest, starts
    with its response to the offset.  A row is named when the mean of its prediction error exceeds
    :data:`OFFSET_RATIO` times its standard deviation (and is not the rounding of a log without noise).

    An integrating output (a level) has no fixed level: its prediction error's offset is the level the log
    starts at, not a sign of anything, and is not named.  There an undeclared operating point of a column
    that feeds the level makes the model integrate it: the prediction error ramps, which the tests'
    centring does not remove (they may then locate an element of that row that is right).  Such a row is
    named when the change of its prediction error's straight-line fit over the window exceeds
    :data:`OFFSET_RATIO` times the standard deviation about that line.

    Parameters
    ----------
    model : PlantModel
    d : ndarray, shape (n_samples, n_outputs)
        Prediction errors ``y - yhat``, output units.
    y : ndarray, shape (n_samples, n_outputs)
        Outputs (deviations), output units: the scale below which an offset is rounding.
    skip : sequence of str
        Outputs not named (a diverged loop's).
    t : ndarray, shape (n_samples,), optional
        The samples' times, seconds (the ramp's abscissa; default the sample numbers).

    Returns
    -------
    list of str
        At most two warnings.
    """
    mean, std = d.mean(axis=0), d.std(axis=0)
    floor = 1e-6 * np.maximum(y.std(axis=0), np.abs(y).mean(axis=0))
    integrating = model.integrating_outputs
    named = [i for i in range(model.n_outputs) if model.outputs[i] not in skip and abs(mean[i]) > floor[i]
             and abs(mean[i]) > OFFSET_RATIO * std[i] and not integrating[i]]
    out = []
    if named:
        what = ", ".join(f"{model.outputs[i]} by {mean[i]:.4g} (" + ("no spread)" if std[i] <= 1e-12 * abs(mean[i])
                                                                       else f"{abs(mean[i]) / std[i]:.3g} times its "
                                                                       f"spread)") for i in named)
        out.append(f"the model's output is offset from the logged output: {what}; an operating point of the inputs, "
                   f"outputs or measured disturbances that the model file does not declare (input_nominal, "
                   f"output_nominal, disturbance_nominal)? The tests remove the mean, the prediction-error figures do "
                   f"not, and a step-response model starts from rest, with its response to the offset")
    levels = [i for i in range(model.n_outputs) if integrating[i] and model.outputs[i] not in skip]
    if levels and d.shape[0] > 2:
        x = np.arange(d.shape[0], dtype=float) if t is None else np.asarray(t, dtype=float)
        x = x - x.mean()
        sxx = float(x @ x)
        ramps = []
        for i in levels:
            di = d[:, i] - mean[i]
            slope = float(x @ di) / sxx if sxx > 0 else 0.0
            rest = float(np.std(di - slope * x))
            change = abs(slope) * float(x.max() - x.min())
            if change > floor[i] and change > OFFSET_RATIO * rest:
                ramps.append(f"{model.outputs[i]} by {slope:.4g} per {'second' if t is not None else 'sample'} "
                             f"({change:.4g} over the window, " + ("no spread about it)" if rest <= 1e-12 * change
                                                                   else f"{change / rest:.3g} times the spread about "
                                                                        f"it)"))
        if ramps:
            out.append(f"the prediction error of an integrating output ramps: {', '.join(ramps)}; an operating point "
                       f"of the inputs or measured disturbances that feed it that the model file does not declare "
                       f"(input_nominal, disturbance_nominal), which the model integrates, or a gain error of its "
                       f"integrating elements? The tests remove the mean, not a ramp: an element of that row may be "
                       f"located because of it")
    return out


#: Units a log's time column is often written in, and their seconds (:func:`time_unit_note`).
TIME_UNITS = (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9))


def time_unit_note(plan, sample_time: float) -> str:
    """``"; t advances by ..."`` when most rows of the data are followed by a gap: the time column is then
    likely in other units than seconds (a ROS stamp in nanoseconds: every row 1e9 sample times after the
    last), or the model's sample time is wrong; the unit is named when the step is 1e3, 1e6 or 1e9 sample
    times to 1 %.  ``""`` otherwise."""
    n_rows = sum(b - a for a, b in plan.segments)
    if plan.gap_lengths.size < max(10, n_rows // 2):
        return ""
    step = float(np.median(plan.gap_lengths)) + 1.0          # sample times from one row to the next
    unit = next((name for name, seconds in TIME_UNITS if abs(step * seconds - 1.0) < 0.01), None)
    return (f"; t advances by a median of {step * sample_time:.6g} from one row to the next, {step:.6g} times the "
            f"model's sample_time of {sample_time:g} s" + (f": t in {unit}?" if unit else ""))
