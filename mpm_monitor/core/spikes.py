"""Isolated spikes in a log: one to three samples that leave a channel's course and come back.

A historian export or a bag often holds a few bad samples: a transmitter glitch, a communication
error, a placeholder written for a value of bad quality.  One such sample, tens of standard
deviations off, dominates every least-squares fit of the tests: on a 3x3 loop whose mismatch is
located at ``p < 1e-10``, one spike of 1,000 units on the outputs leaves every row at ``p = 1``
and nothing located.  :func:`find_spikes` finds them and :func:`without_spikes` leaves their
samples out, as missing samples (docs/interfaces.md, "Gaps"): a spike costs only the regression
rows whose lags reach it, and nothing is interpolated.

A burst of ``m`` samples (``1 <= m <=`` :data:`MAX_SPIKE`) of channel ``x`` between the samples
``lo`` and ``hi`` (both logged, adjacent on the grid) is a spike when

* every sample of the burst lies beyond both ``lo`` and ``hi`` on the same side, by more than
  :data:`SPIKE_THRESHOLD` times the channel's robust scale of sample-to-sample changes
  (:data:`NORMAL_MAD` times the median absolute deviation of its first differences within the segments;
  the median nonzero ``|change|`` where that is 0, as for a quantized channel), and
* the channel comes back: ``|hi - lo|`` is at most :data:`RETURN_FRACTION` of the excursion, and
* the excursion stands out of the channel's own movement around it: it exceeds
  :data:`LOCAL_FACTOR` times the largest change among the :data:`LOCAL_SAMPLES` samples before
  ``lo`` and after ``hi``.

A step (the channel stays at its new level), a ramp, or a controller's kick that decays (it does
not come back within the burst) is not a spike; nor is a controller's move after a setpoint step on
an input that is otherwise almost still (its robust scale is tiny, but its moves around the burst are
as large as the burst); nor is a burst of an input that starts with a setpoint step or up to
:data:`KICK_SAMPLES` - 1 samples after one and is no larger than :data:`KICK_FACTOR` times the
input's usual move at a setpoint step (an MPC's first moves after a step often overshoot and come
back within a sample or two: the loop's most informative samples, not a glitch).  The first and
last samples of a segment have one neighbour only and are never called spikes.
"""

from __future__ import annotations

import numpy as np

from .logged_data import LoggedData, t_text

#: A spike leaves the channel's course by more than this many robust standard deviations of its
#: sample-to-sample changes (on Gaussian noise such an excursion never happens).
SPIKE_THRESHOLD = 10.0
#: Longest burst of samples called a spike.
MAX_SPIKE = 3
#: The channel must come back: ``|hi - lo|`` at most this fraction of the excursion.
RETURN_FRACTION = 0.25
#: The excursion must exceed this many times the largest change of the channel around the burst ...
LOCAL_FACTOR = 3.0
#: ... among this many samples on either side.
LOCAL_SAMPLES = 5
#: An input's burst that starts at a setpoint step or within this many samples of it (counting the
#: step's own) is the controller's answer to the step, not a spike.
KICK_SAMPLES = 3
#: ... when its excursion is at most this many times the input's usual move at a setpoint step.
KICK_FACTOR = 3.0
#: Spikes named in the note, at most.
NAMED_SPIKES = 3
#: The median absolute deviation of a normal sample times this is its standard deviation (1 / Phi^-1(3/4)).
NORMAL_MAD = 1.482602218505602


def change_scale(x: np.ndarray, segments: list) -> float:
    """Robust standard deviation of a channel's sample-to-sample changes within ``segments``.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
    segments : list of (int, int)
        Contiguous runs of samples (no change is taken across a gap).

    Returns
    -------
    float
        :data:`NORMAL_MAD` times the median absolute deviation of the first differences; the median
        of the nonzero ``|differences|`` when that is 0 (a quantized or mostly constant channel); 0
        when the channel never changes.  Channel units.
    """
    return float(_change_scales(np.asarray(x, dtype=float)[None, :], segments)[0])


def _change_scales(rows: np.ndarray, segments: list) -> np.ndarray:
    """:func:`change_scale` of every row of ``rows`` (shape (n_channels, n_samples), one channel per
    row, so that the medians run along contiguous memory), shape (n_channels,)."""
    d = np.concatenate([np.diff(rows[:, a:b], axis=1) for a, b in segments], axis=1) if segments else \
        np.zeros((rows.shape[0], 0))
    if d.shape[1] == 0:
        return np.zeros(rows.shape[0])
    s = NORMAL_MAD * np.median(np.abs(d - np.median(d, axis=1)[:, None]), axis=1)
    for c in np.flatnonzero(~(s > 0)):
        nz = np.abs(d[c][d[c] != 0])
        s[c] = float(np.median(nz)) if nz.size else 0.0
    return s


def spike_mask(x: np.ndarray, segments: list, threshold: float = SPIKE_THRESHOLD) -> np.ndarray:
    """Samples of one channel that belong to a spike (module docstring).

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        The channel, any units.
    segments : list of (int, int)
        Its contiguous runs of samples (:attr:`LoggedData.segments`).
    threshold : float
        :data:`SPIKE_THRESHOLD`.

    Returns
    -------
    ndarray of bool, shape (n_samples,)
    """
    return _spike_masks(np.asarray(x, dtype=float)[None, :], segments, threshold)[0]


def _spike_masks(rows: np.ndarray, segments: list, threshold: float) -> np.ndarray:
    """:func:`spike_mask` of every row of ``rows`` (shape (n_channels, n_samples)) at once, shape
    (n_channels, n_samples).  A channel that never changes, or holds a non-finite value, has none."""
    mask = np.zeros(rows.shape, dtype=bool)
    limit = threshold * _change_scales(rows, segments)
    usable = np.flatnonzero((limit > 0) & np.all(np.isfinite(rows), axis=1))
    if not usable.size:
        return mask
    for a, b in segments:
        xs = rows[:, a:b]
        n = xs.shape[1]
        # A burst starts with a jump beyond the limit from its left neighbour: only those are examined.
        jumps = np.abs(np.diff(xs[usable], axis=1)) > limit[usable, None]
        chans, starts = np.nonzero(jumps)
        chans, starts = usable[chans], starts + 1                     # channel, first sample of a candidate
        for m in range(1, MAX_SPIKE + 1):
            ok = starts + m < n                                       # its right neighbour is in the segment
            c, k = chans[ok], starts[ok]
            if c.size == 0:
                continue
            lo, hi = xs[c, k - 1], xs[c, k + m]
            burst = np.stack([xs[c, k + t] for t in range(m)])
            top, bottom = burst.max(axis=0), burst.min(axis=0)
            excursion = np.maximum(bottom - np.maximum(lo, hi), np.minimum(lo, hi) - top)
            hit = (excursion > limit[c]) & (np.abs(hi - lo) <= RETURN_FRACTION * excursion)
            for ch, kk, ex in zip(c[hit], k[hit], excursion[hit]):
                before = xs[ch, max(kk - 1 - LOCAL_SAMPLES, 0):kk]              # up to lo
                after = xs[ch, kk + m:kk + m + 1 + LOCAL_SAMPLES]              # from hi on
                moves = np.abs(np.concatenate([np.diff(before), np.diff(after)]))
                if ex > LOCAL_FACTOR * moves.max(initial=0.0):
                    mask[ch, a + kk:a + kk + m] = True
    return mask


def find_spikes(data: LoggedData, threshold: float = SPIKE_THRESHOLD, jobs: int = 1) -> dict:
    """The spikes of every channel the tests use: setpoints, inputs, measured disturbances, outputs.

    Parameters
    ----------
    data : LoggedData
    threshold : float
    jobs : int
        With 2, a forked child examines one of two halves of the channels
        (:func:`~mpm_monitor.core.parallel.split_map`; each channel's by itself, so the same masks).

    Returns
    -------
    dict
        Channel label (``r_<output>``, the input, disturbance or output name) -> bool array of shape
        (n_samples,), for the channels with at least one spike.
    """
    labels = [f"r_{name}" for name in data.outputs] + list(data.inputs) + list(data.disturbances) + \
        list(data.outputs)
    if not labels:
        return {}
    rows = np.vstack([np.asarray(a, dtype=float).T for a in (data.r, data.u, data.dv, data.y)])
    if jobs > 1 and rows.shape[0] > 1:
        from .parallel import split_map

        half = (rows.shape[0] + 1) // 2
        masks = np.vstack(split_map(lambda part: _spike_masks(rows[part], data.segments, threshold),
                                    [slice(0, half), slice(half, rows.shape[0])], jobs))
    else:
        masks = _spike_masks(rows, data.segments, threshold)
    ny, nu = len(data.outputs), len(data.inputs)
    if masks[ny:ny + nu].any():
        _spare_kicks(masks[ny:ny + nu], np.asarray(data.u, dtype=float), np.asarray(data.r, dtype=float),
                     data.segments)
    return {label: masks[c] for c, label in enumerate(labels) if masks[c].any()}


def _spare_kicks(input_masks: np.ndarray, u: np.ndarray, r: np.ndarray, segments: list) -> None:
    """Clear, in place, the bursts of ``input_masks`` (shape (n_inputs, n_samples)) that start at a
    setpoint step of ``r`` (shape (n_samples, n_outputs)) or within :data:`KICK_SAMPLES` samples of it,
    and whose excursion is at most :data:`KICK_FACTOR` times the input's usual move at a setpoint step
    (the 90th percentile of its ``|change|`` there, from ``u``, shape (n_samples, n_inputs)).  A loop
    whose setpoints switch every few samples has a step near every sample: there a glitch is far
    larger than the moves at the steps, and stays a spike."""
    step = np.zeros(r.shape[0], dtype=bool)
    moved = np.zeros(r.shape[0], dtype=bool)        # samples whose change from the one before is logged
    for a, b in segments:
        step[a + 1:b] = np.any(r[a + 1:b] != r[a:b - 1], axis=1)
        moved[a + 1:b] = True
    near = step.copy()
    for lag in range(1, KICK_SAMPLES):
        near[lag:] |= step[:-lag]
    at_steps = near & moved
    if not at_steps.any():
        return
    for c, mask in enumerate(input_masks):
        starts = np.flatnonzero(mask & ~np.concatenate([[False], mask[:-1]]))
        starts = starts[near[starts] & (starts > 0)]
        if not starts.size:
            continue
        x = u[:, c]
        change = np.abs(np.diff(x, prepend=x[0]))
        usual = float(np.percentile(change[at_steps], 90))
        for k in starts:
            end = k
            while end < mask.size and mask[end]:
                end += 1
            lo = x[k - 1]
            hi = x[end] if end < x.size else lo
            burst = x[k:end]
            excursion = max(float(burst.min() - max(lo, hi)), float(min(lo, hi) - burst.max()))
            if excursion <= KICK_FACTOR * usual:
                mask[k:end] = False


def without_spikes(data: LoggedData, threshold: float = SPIKE_THRESHOLD, jobs: int = 1) -> tuple:
    """``data`` with the samples of its spikes left out (missing samples), and a note saying which.

    ``jobs``: as :func:`find_spikes`'s.

    Returns
    -------
    (LoggedData, Optional[str])
        The data (the same object when there is no spike) and the note (None without spikes); the
        note is also appended to the data's :attr:`~LoggedData.notes`.
    """
    spikes = find_spikes(data, threshold, jobs)
    if not spikes:
        return data, None
    bad = np.zeros(data.n_samples, dtype=bool)
    for mask in spikes.values():
        bad |= mask
    parts = []
    for label, mask in spikes.items():
        starts = np.flatnonzero(mask & ~np.concatenate([[False], mask[:-1]]))
        at = ", ".join(t_text(data.t[k]) for k in starts[:NAMED_SPIKES]) + (
            f" and {starts.size - NAMED_SPIKES} more" if starts.size > NAMED_SPIKES else "")
        parts.append(f"{label} at t = {at} s" if starts.size == 1 else f"{label} {starts.size} times (t = {at} s)")
    n_bad = int(bad.sum())
    note = (f"{data.source or 'data'}: spikes (one to {MAX_SPIKE} samples that leave a channel by more than "
            f"{threshold:g} robust standard deviations of its sample-to-sample changes and come back): "
            f"{'; '.join(parts)}; their {n_bad} sample{'s' if n_bad != 1 else ''} left out as missing samples, "
            f"nothing interpolated (option drop_spikes false keeps them)")
    kept = data.take(np.flatnonzero(~bad))
    kept.notes = tuple(data.notes) + (note,)
    # The samples of a spike in a setpoint or an output keep their logged inputs and measured
    # disturbances for the model's simulation (LoggedData.column_fill); a spike in a column is not kept.
    column_spike = np.zeros(data.n_samples, dtype=bool)
    for label in list(data.inputs) + list(data.disturbances):
        if label in spikes:
            column_spike |= spikes[label]
    sound = np.flatnonzero(bad & ~column_spike)
    if sound.size:
        columns = data.columns[sound]
        t_old, c_old = data.column_fill if data.column_fill is not None else \
            (np.zeros(0), np.zeros((0, columns.shape[1])))
        kept.column_fill = (np.concatenate([t_old, data.t[sound]]), np.vstack([c_old, columns]))
    return kept, note
