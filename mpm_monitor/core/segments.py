"""Data with gaps: the contiguous segments of the stacked samples, and the runs a response is simulated through.

The analysis of data with gaps stacks the segments long enough for a regression row
(:mod:`mpm_monitor.core.gaps`); no regression row's lags reach across a gap.  The controller's model,
though, runs through a short gap (at most ``max_gap`` missing samples) with its columns held at their
last logged values, and restarts only after a longer one
(:func:`mpm_monitor.core.signals.segment_signals`): the prediction error ``d`` carries the state of
both the plant and the model across a short gap.  Any other response the tests regress ``d`` on (an
element's response to its column, :func:`~mpm_monitor.core.response_test.element_responses`, and what
follows from it) is simulated the same way, through :func:`through`, so that it carries the same
state; simulated from rest at every segment's start, it would start a transient that ``d`` does not
have after every gap.  Where a missing sample's columns are known (a segment too short for a regression row, left
out of the stacked samples, or a spike's sample), the model runs on them, and so does a column's response: the
:class:`GapSegments` carry them (``columns``), and :func:`centred_fill` gives them as a caller's centred columns
(:func:`through` and :func:`run_lag_matrix` with ``column``).

:class:`GapSegments` is the list of segments ``(first, end)`` of the stacked samples (every function
that takes ``segments`` reads it as such) with the runs (:func:`gap_runs`) and the places of the
samples on each run's sample grid.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from .arx import lag_matrix


def unknown_span(lo: int, hi: int, known: Optional[np.ndarray] = None) -> int:
    """The longest stretch of consecutive missing samples whose columns are unknown, between grid numbers ``lo``
    and ``hi`` (the samples before and after a gap): all ``hi - lo - 1`` of them, less the samples in ``known``.

    Parameters
    ----------
    lo, hi : int
        Grid numbers of the logged samples on either side of the gap.
    known : ndarray of int, optional
        Sorted grid numbers of missing samples whose columns are known (logged, the samples of a segment too short
        for a regression row or of a spike: :meth:`~mpm_monitor.core.gaps.GapPlan.left_out_fill`).

    Returns
    -------
    int
    """
    n = max(int(hi) - int(lo) - 1, 0)
    if known is None or n == 0:
        return n
    inside = known[(known > lo) & (known < hi)]
    if not inside.size:
        return n
    return int(np.max(np.diff(np.concatenate([[int(lo)], inside, [int(hi)]])) - 1))


def gap_runs(segments, grid: np.ndarray, max_gap: int, known: Optional[np.ndarray] = None) -> list:
    """The segments grouped into runs the model is simulated through: a new run after every gap with more than
    ``max_gap`` consecutive samples whose columns are unknown (:func:`unknown_span`).

    Parameters
    ----------
    segments : sequence of (int, int)
        Contiguous runs of rows, in order.
    grid : ndarray of int, shape (n_samples,)
        Sample number of every row on the sample grid.
    max_gap : int
    known : array_like of int, optional
        Grid numbers of missing samples whose columns are known (the model takes them): two drops a few samples
        apart with such a segment between them are two short gaps, not one of their span.

    Returns
    -------
    list of list of int
        The indices of the segments of every run, in order.
    """
    known = None if known is None else np.unique(np.asarray(known, dtype=np.int64))
    runs = []
    for k, (a, _) in enumerate(segments):
        if k and unknown_span(int(grid[segments[k - 1][1] - 1]), int(grid[a]), known) <= max_gap:
            runs[-1].append(k)
        else:
            runs.append([k])
    return runs


def held_rows(grid: np.ndarray) -> tuple:
    """The rows of a run on its sample grid, held through its gaps.

    Parameters
    ----------
    grid : ndarray of int, shape (n,)
        Sample number of every row of the run, increasing.

    Returns
    -------
    held : ndarray of int, shape (grid[-1] - grid[0] + 1,)
        For every point of the run's grid, the last row at or before it.
    at : ndarray of int, shape (n,)
        The place of every row on the run's grid.
    """
    at = np.asarray(grid, dtype=np.int64) - int(grid[0])
    held = np.searchsorted(at, np.arange(int(at[-1]) + 1), side="right") - 1
    return held, at


class GapSegments(list):
    """The segments ``(first, end)`` of stacked samples with gaps, and the runs the model is simulated through.

    A list of the segments (every function that takes ``segments`` reads it as one), with
    :attr:`runs`: for every run of segments separated by gaps of at most ``max_gap`` missing samples
    (:func:`gap_runs`), its first and end row, and :func:`held_rows` of its samples (None for a run of
    one segment).

    Parameters
    ----------
    segments : sequence of (int, int)
        Contiguous runs of rows of the stacked samples, in order, covering them.
    grid : ndarray of int, shape (n_samples,)
        Sample number of every stacked row on the sample grid.
    max_gap : int
        Longest gap (missing samples whose columns are unknown) the model runs through.
    known : array_like of int, optional
        Grid numbers of missing samples whose columns are known (:func:`gap_runs`).
    columns : ndarray, shape (len(known), n_columns), optional
        Their columns (:meth:`~mpm_monitor.core.gaps.GapPlan.left_out_fill`: a segment too short for a regression
        row, a spike): the model runs on them, and so does a column's response (:func:`through` with
        ``column``), once :meth:`filled` has them as the caller's columns are.

    Attributes
    ----------
    runs : list of (int, int, tuple or None)
        Every run's first and end row and :func:`held_rows` of its samples.
    run_of : ndarray of int, shape (n_segments,)
        The run of every segment.
    columns : ndarray or None
        The known samples' columns as given.
    values : ndarray or None
        As :meth:`filled` gave them (None: every gap held).
    """

    def __init__(self, segments, grid: np.ndarray, max_gap: int, known: Optional[np.ndarray] = None,
                 columns: Optional[np.ndarray] = None):
        super().__init__((int(a), int(b)) for a, b in segments)
        self.max_gap = int(max_gap)
        self.runs = []
        self.run_of = np.zeros(len(self), dtype=np.int64)
        for r, run in enumerate(gap_runs(self, grid, self.max_gap, known)):
            a, b = self[run[0]][0], self[run[-1]][1]
            self.runs.append((a, b, held_rows(grid[a:b]) if len(run) > 1 else None))
            self.run_of[run] = r
        self.columns = None if columns is None or known is None else np.asarray(columns, dtype=float)
        self.values = None
        # Every run's known samples inside its gaps: their places on the run's grid and their rows of ``columns``.
        self._known_at = {}
        if self.columns is not None:
            known = np.asarray(known, dtype=np.int64)
            for a, b, held in self.runs:
                if held is None:
                    continue
                where = known - int(grid[a])
                inside = np.flatnonzero((where > 0) & (where < held[1][-1]))
                if inside.size:
                    self._known_at[a] = (where[inside], inside)

    def filled(self, values: np.ndarray) -> "GapSegments":
        """These segments, with ``values`` for the known columns inside the runs' gaps.

        Parameters
        ----------
        values : ndarray, shape (n_known, n_columns)
            :attr:`columns` as the caller's columns are (centred, say), one row per known sample; NaN where a
            column is not known (a candidate channel added to the model since: held, as the model takes it).

        Returns
        -------
        GapSegments
            A copy whose :meth:`run_fill` gives them (the segments and runs shared).
        """
        out = GapSegments.__new__(GapSegments)
        list.extend(out, self)
        out.__dict__.update(self.__dict__)
        out.values = np.asarray(values, dtype=float)
        return out

    def run_fill(self, run: tuple, column=None) -> Optional[tuple]:
        """The known columns inside the gaps of one run (of :attr:`runs`), as :meth:`filled` gave them.

        Parameters
        ----------
        run : (int, int, tuple or None)
        column : int or slice or None
            The column(s) of :attr:`values` taken; None: none (the caller's samples are not these columns).

        Returns
        -------
        (ndarray of int, ndarray) or None
            Places on the run's grid, shape (m,), and values, shape (m,) or (m, k); None without any.
        """
        got = None if self.values is None or column is None else self._known_at.get(run[0])
        if got is None:
            return None
        if isinstance(column, (int, np.integer)) and not 0 <= int(column) < self.values.shape[1]:
            return None                       # a column added since: held
        where, rows = got
        return where, self.values[rows][:, column]

    @property
    def joined(self) -> bool:
        """Whether some run holds more than one segment (a response carries its state across a gap)."""
        return any(h is not None for _, _, h in self.runs)


def level_groups(segments, one_per_run: bool) -> Optional[np.ndarray]:
    """The level group of every segment: the span over which a row's prediction error, and every regressor the
    tests centre with it, keeps one level.

    A row whose model has no integrating element keeps one level through a short gap: the model runs through
    it (:func:`through`), the plant's disturbance does not jump, and the model's response to the gap's unknown
    columns is a transient (fitted and taken out, :mod:`~mpm_monitor.core.gap_inputs`), not a step.  So its
    level group is its run (``one_per_run``); a level per segment would take a level out of every stretch
    between two drops and, with it, the slow part of the whole-response regressor (its p-values moved more than
    twice as far with one sample in 500 dropped as with the same rows cut off the end: ``bench.element_level
    --drop 0.002 --cut``).  A row with an integrating element has a level per segment: the unknown columns inside
    a gap move its level for good.

    Parameters
    ----------
    segments : sequence of (int, int) or GapSegments or None
    one_per_run : bool
        One level per run of a :class:`GapSegments` (a row without an integrating element).

    Returns
    -------
    ndarray of int, shape (n_segments,), or None
        The group of every segment (its run's index, or its own); None without segments.
    """
    if segments is None:
        return None
    run_of = getattr(segments, "run_of", None)
    if one_per_run and run_of is not None:
        return run_of
    return np.arange(len(segments), dtype=np.int64)


def centred_by_level(x: np.ndarray, segments, groups: Optional[np.ndarray]) -> np.ndarray:
    """Samples ``x`` (shape (n_samples, ...), the segments stacked) less their mean over each level group's samples
    (:func:`level_groups`; over all samples without segments); a new array."""
    x = np.asarray(x, dtype=float)
    if segments is None or groups is None:
        return x - x.mean(axis=0)
    out = x.copy()
    for g in dict.fromkeys(np.asarray(groups).tolist()):
        spans = [(int(a), int(b)) for (a, b), h in zip(segments, groups) if h == g]
        mean = np.concatenate([x[a:b] for a, b in spans]).mean(axis=0)
        for a, b in spans:
            out[a:b] -= mean
    return out


def errors_centred_by_level(d: np.ndarray, segments, integrating) -> np.ndarray:
    """Prediction errors centred as the tests take them: each row over its level groups (:func:`level_groups`: one
    per run for a row without an integrating element, one per segment for a row with one).

    Parameters
    ----------
    d : ndarray, shape (n_samples, n_outputs)
        The segments stacked (output units).
    segments : sequence of (int, int) or GapSegments
    integrating : sequence of bool, length n_outputs
        Whether each row's model has an integrating element (:attr:`~mpm_monitor.core.model.PlantModel.integrating_outputs`).

    Returns
    -------
    ndarray, shape (n_samples, n_outputs)
        A new array (a sample outside every segment as it is).
    """
    d = np.asarray(d, dtype=float)
    out = d.copy()
    for one_per_run in (False, True):
        at = [i for i, flag in enumerate(integrating) if bool(flag) != one_per_run]
        if at:
            out[:, at] = centred_by_level(d[:, at], segments, level_groups(segments, one_per_run))
    return out


def centred_fill(segments, mean: np.ndarray, zeroed=()):
    """``segments`` with their known columns inside the runs' gaps (:attr:`GapSegments.columns`) as a caller's
    centred columns are: ``columns - mean``, 0 in the columns ``zeroed``, NaN (held) in a column the known samples
    lack (a candidate channel added since); ``segments`` as they are without any.

    Parameters
    ----------
    segments : sequence of (int, int) or GapSegments or None
    mean : ndarray, shape (n_columns,)
        What the caller took from each column (column units).
    zeroed : sequence of int
        Columns the caller set to 0.

    Returns
    -------
    sequence of (int, int) or GapSegments or None
    """
    cols = getattr(segments, "columns", None)
    if cols is None:
        return segments
    mean = np.asarray(mean, dtype=float).ravel()
    values = np.full((cols.shape[0], mean.size), np.nan)
    k = min(cols.shape[1], mean.size)
    values[:, :k] = cols[:, :k] - mean[:k]
    values[:, list(zeroed)] = 0.0
    return segments.filled(values)


def through(x: np.ndarray, f: Callable[[np.ndarray], np.ndarray], segments=None, column=None) -> np.ndarray:
    """``f`` run over the samples ``x`` as the model runs: through the short gaps, from rest after a long one.

    Parameters
    ----------
    x : ndarray, shape (n_samples, ...)
        Stacked samples (a column, or columns along the first axis).
    f : callable
        Takes a run of samples (shape (m, ...), contiguous on the sample grid) and returns an array of
        the same length along its first axis (a response from rest at the run's first sample).
    segments : sequence of (int, int) or GapSegments, optional
        None: ``x`` is one run.  A plain sequence: every segment is a run of its own.  A
        :class:`GapSegments`: its runs, each over its sample grid with the samples inside its gaps held at
        the last sample before them (what the controller's hold does between moves); the result is read
        at the stacked samples only.
    column : int or slice, optional
        ``x`` is this column (or these) of the model's columns: inside a run's gaps, the samples whose columns
        are known take them (:meth:`GapSegments.filled`), as the model's run does, and hold them on.

    Returns
    -------
    ndarray, shape (n_samples, ...)
        ``f``'s result at every stacked sample (0 on samples outside every segment).
    """
    x = np.asarray(x)
    if segments is None:
        return np.asarray(f(x))
    out: Optional[np.ndarray] = None
    for run in _runs(segments, x.shape[0]):
        a, b, held = run
        part = np.asarray(f(run_samples(x, run, _run_fill(segments, run, column))))
        if held is not None:              # read at the logged samples only
            part = part[run_places(run)]
        if out is None:
            out = np.zeros((x.shape[0],) + part.shape[1:], dtype=part.dtype)
        out[a:b] = part
    return np.zeros(x.shape) if out is None else out


def as_segments(segments):
    """``segments`` as a list of ``(int, int)`` (None stays None; a :class:`GapSegments` is kept as it is)."""
    if segments is None or isinstance(segments, GapSegments):
        return segments
    return [(int(a), int(b)) for a, b in segments]


def _runs(segments, n: int) -> list:
    """``(first, end, held)`` of every run (:attr:`GapSegments.runs`; every segment of a plain sequence a run of
    its own, one run of ``n`` samples without segments)."""
    if segments is None:
        return [(0, int(n), None)]
    runs = getattr(segments, "runs", None)
    return runs if runs is not None else [(int(a), int(b), None) for a, b in segments]


def _run_fill(segments, run: tuple, column) -> Optional[tuple]:
    """:meth:`GapSegments.run_fill` of ``run`` for ``column`` (None for a run without gaps, without a column, or
    segments that are no :class:`GapSegments`)."""
    if run[2] is None or column is None or not isinstance(segments, GapSegments):
        return None
    return segments.run_fill(run, column)


def run_places(run: tuple) -> np.ndarray:
    """The places of the rows of one run ``(first, end, held)`` (:attr:`GapSegments.runs`) on its sample grid,
    int, shape (end - first,)."""
    a, b, held = run
    return np.arange(b - a) if held is None else held[1]


def run_samples(x: np.ndarray, run: tuple, fill: Optional[tuple] = None) -> np.ndarray:
    """``x`` (stacked samples) on the sample grid of one run ``(first, end, held)``, held through its gaps,
    shape (grid samples, ...); its own rows are at :func:`run_places`.

    ``fill``: ``(places, values)`` of samples inside the gaps whose values are known (:meth:`GapSegments.run_fill`;
    NaN: not known): they take them, and a missing sample after one holds it, as the model's run takes a left-out
    segment's or a spike's columns (:func:`~mpm_monitor.core.signals.segment_signals`)."""
    a, b, held = run
    if held is None:
        return x[a:b]
    if fill is None:
        return x[a:b][held[0]]
    where, values = fill
    at = held[1]
    full = np.full((int(at[-1]) + 1,) + x.shape[1:], np.nan)
    full[at] = x[a:b]
    full[where] = values
    known = ~np.isnan(full)
    last = np.maximum.accumulate(np.where(known, np.arange(full.shape[0]).reshape((-1,) + (1,) * (x.ndim - 1)), 0),
                                 axis=0)
    return np.take_along_axis(full, last, axis=0)


def run_positions(start: int, segments=None, n: Optional[int] = None) -> np.ndarray:
    """The place of every regression row on its run's sample grid (samples since the run's first).

    Parameters
    ----------
    start : int
        First regression row of every segment.
    segments : sequence of (int, int) or GapSegments or None
    n : int, optional
        Samples (needed without ``segments``).

    Returns
    -------
    ndarray of int, shape (n_rows,)
        For the rows of every segment from its ``start``-th sample on, stacked
        (:func:`~mpm_monitor.core.arx.segment_rows`).
    """
    spans = [(0, int(n))] if segments is None else [(int(a), int(b)) for a, b in segments]
    place = np.empty(spans[-1][1] if spans else 0, dtype=np.int64)
    for run in _runs(segments, 0 if n is None else n):
        place[run[0]:run[1]] = run_places(run)
    return np.concatenate([place[a + start:b] for a, b in spans if b - a > start] or [place[:0]])


def run_lag_matrix(x: np.ndarray, lags, start: int, segments=None, column=None) -> np.ndarray:
    """Lagged copies of ``x`` on the regression rows, read on each run's sample grid.

    As :func:`~mpm_monitor.core.arx.segment_lag_matrix`, but a lag may reach back past its segment's first
    sample: inside a short gap of a :class:`GapSegments` it reads the last sample before the gap (the
    columns held, as the model runs), and before the run's first sample it reads 0 (from rest); the
    rows whose lags reach that far are for the caller to leave out (:func:`run_positions`).

    Parameters
    ----------
    x : ndarray, shape (n_samples,) or (n_samples, n_channels)
    lags : sequence of int
        Lags (samples, >= 0).
    start : int
        First regression row of every segment.
    segments : sequence of (int, int) or GapSegments or None
    column : int, optional
        ``x`` is this one of the model's columns (:func:`through`'s ``column``): the known samples inside the gaps
        take their values.

    Returns
    -------
    ndarray, shape (n_rows, n_channels * len(lags))
        Column ``c * len(lags) + l`` holds channel ``c`` at lag ``lags[l]``.
    """
    x = np.asarray(x, dtype=float)
    one = x.ndim == 1
    if one:
        x = x[:, None]
    lags = [int(lag) for lag in lags]
    back = max(lags, default=0)
    spans = [(0, x.shape[0])] if segments is None else [(int(a), int(b)) for a, b in segments]
    rows = []
    for run in _runs(segments, x.shape[0]):
        a, b, _ = run
        fill = _run_fill(segments, run, column)
        if fill is not None and one:
            fill = (fill[0], fill[1][:, None])
        padded = np.vstack([np.zeros((back, x.shape[1])), run_samples(x, run, fill)])
        lagged = lag_matrix(padded, lags, back)[run_places(run)]          # at the run's own samples
        rows += [lagged[s - a + start:e - a] for s, e in spans if a <= s and e <= b and e - s > start]
    return np.vstack(rows) if rows else np.zeros((0, x.shape[1] * len(lags)))


def centred_by(X: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Rows of ``X`` (shape (n_rows, k)) less the mean of the rows with the same label (``labels``: shape
    (n_rows,) of int); a new array."""
    X = np.asarray(X, dtype=float)
    labels = np.asarray(labels, dtype=np.int64)
    if X.shape[0] == 0:
        return X.copy()
    count = np.bincount(labels).astype(float)
    sums = np.zeros((count.size,) + X.shape[1:])
    np.add.at(sums, labels, X)
    return X - (sums / np.maximum(count, 1.0).reshape((-1,) + (1,) * (X.ndim - 1)))[labels]


def segment_labels(start: int, segments=None, n_rows: int = 0) -> np.ndarray:
    """The segment of every regression row (stacked as :func:`~mpm_monitor.core.arx.segment_rows`), shape
    (n_rows,) of int: its index among ``segments`` (all 0 without them: ``n_rows`` rows)."""
    if segments is None:
        return np.zeros(int(n_rows), dtype=np.int64)
    return np.concatenate([np.full(max(int(b) - int(a) - start, 0), k, dtype=np.int64)
                           for k, (a, b) in enumerate(segments)] or [np.zeros(0, dtype=np.int64)])
