"""Data with gaps: which contiguous spans the analysis uses, and what the gaps cost.

Logged data may miss samples: ``t`` skips grid points (:attr:`LoggedData.grid_index`), splitting
the rows into contiguous segments (:attr:`LoggedData.segments`).  Nothing is ever interpolated
(docs/interfaces.md, "Gaps").  The analysis (:func:`mpm_monitor.core.analysis.detect`) stacks the
segments: the model runs through a gap of at most ``max_gap`` samples (its columns held; after a
longer gap it restarts, :func:`mpm_monitor.core.signals.segment_signals`) and each segment gives
its own regression rows, from its ``start``-th sample on
(:class:`~mpm_monitor.core.regressions.RegressionLayout`), so that no row's lags reach across a gap.
A segment of at most ``start`` samples gives no row and is left out.

The cost of the gaps is counted against the same span without them: ``samples_lost`` (the missing
samples plus those of the segments left out) and ``rows_lost`` (the regression rows the span would
give without a gap, less the rows kept).  A gap up to ``max_gap`` samples is short (the model runs
through it); a longer one restarts the model, splits the rows in the same way and is named louder in
the warning.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .discretize import model_columns
from .logged_data import LoggedData, t_text

#: Gaps named one by one in the warning; the JSON's ``where`` lists them all.
NAMED_GAPS = 3
#: A gap longer than this many times the samples analysed is named as a likely stray ``t``.
STRAY_GAP_FACTOR = 100


@dataclasses.dataclass(frozen=True)
class GapPlan:
    """The spans of data with gaps that the analysis uses.

    Attributes
    ----------
    segments : list of (int, int)
        Every contiguous segment, ``(first row, end row)`` of the data.
    used : list of (int, int)
        The segments long enough to give a regression row (more than ``start`` samples).
    start : int
        First sample of a segment used as a regression row.
    gap_lengths : ndarray of int, shape (n_gaps,)
        Missing samples of every gap, in order.
    gap_where : list of (float, float)
        Time of the first and of the last missing sample of every gap, seconds.
    grid_samples : int
        Samples of the span from the first to the last row, had nothing been missing.
    max_gap : int
        Longest gap (samples) called short.
    """

    segments: list
    used: list
    start: int
    gap_lengths: np.ndarray
    gap_where: list
    grid_samples: int
    max_gap: int

    @property
    def samples_used(self) -> int:
        return sum(b - a for a, b in self.used)

    @property
    def rows_kept(self) -> int:
        """Regression rows of the segments used."""
        return sum(b - a - self.start for a, b in self.used)

    @property
    def rows_lost(self) -> int:
        """Regression rows the span would give without a gap, less the rows kept."""
        return max(self.grid_samples - self.start, 0) - self.rows_kept

    @property
    def samples_missing(self) -> int:
        return int(self.gap_lengths.sum())

    @property
    def samples_lost(self) -> int:
        """The missing samples and the samples of the segments left out."""
        return self.grid_samples - self.samples_used

    @property
    def local_segments(self) -> list:
        """The used segments as runs of rows of the used rows stacked (:meth:`take`)."""
        edges = np.cumsum([0] + [b - a for a, b in self.used])
        return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]

    @property
    def longest(self) -> tuple:
        """The longest used segment, ``(first row, end row)`` of the data."""
        return max(self.used, key=lambda s: s[1] - s[0])

    def take(self, x: np.ndarray) -> np.ndarray:
        """The rows of the used segments of ``x`` (shape (n_samples, ...)), stacked."""
        return np.concatenate([x[a:b] for a, b in self.used]) if self.used else x[:0]

    def left_out_fill(self, data: LoggedData) -> Optional[tuple]:
        """The logged columns of the segments left out (too short for a regression row), on the sample grid.

        The model still runs through them (:func:`~mpm_monitor.core.signals.segment_signals` takes them as it
        takes a spike's logged columns): left out of the stacked samples, two short gaps a few samples apart
        would otherwise be one gap of their span held through, and the model's response to the held columns
        would reach far beyond either.

        Parameters
        ----------
        data : LoggedData
            The data this plan is of (its ``u`` and ``dv`` as the model takes them: in deviations).

        Returns
        -------
        (ndarray of int, ndarray) or None
            Grid numbers (:attr:`LoggedData.grid_index`) and columns, shape (m, n_columns), of the samples
            of the segments left out, joined to ``data``'s own column fill; that fill alone when none is left
            out.
        """
        own = data.fill_on_grid()
        used = set(self.used)
        rows = [np.arange(a, b) for a, b in self.segments if (a, b) not in used]
        if not rows:
            return own
        rows = np.concatenate(rows)
        dv = None if data.dv is None else np.asarray(data.dv, dtype=float)[rows]
        grid, cols = data.grid_index[rows], model_columns(np.asarray(data.u, dtype=float)[rows], dv)
        if own is not None:
            width = min(cols.shape[1], np.asarray(own[1]).shape[1])
            grid = np.concatenate([np.asarray(own[0], dtype=np.int64), grid])
            cols = np.vstack([np.asarray(own[1], dtype=float)[:, :width], cols[:, :width]])
        return grid, cols

    def to_dict(self) -> dict:
        """The report's JSON ``gaps`` object (docs/interfaces.md, "Gaps")."""
        return {"count": int(self.gap_lengths.size), "longest": int(self.gap_lengths.max(initial=0)),
                "samples_lost": int(self.samples_lost), "samples_missing": self.samples_missing,
                "rows_lost": int(self.rows_lost), "rows_kept": int(self.rows_kept),
                "segments_used": len(self.used), "segments_left_out": len(self.segments) - len(self.used),
                "max_gap": int(self.max_gap), "where": [[float(a), float(b)] for a, b in self.gap_where]}

    def warning(self) -> str:
        """The gaps in words, e.g. ``3 gaps (longest 2 samples, at t = 120 s, 431 s and 1022 s): ...``."""
        n = self.gap_lengths.size
        at = [t_text(a) for a, _ in self.gap_where[:NAMED_GAPS]]
        if n > NAMED_GAPS:             # "at t = 100, 300, 400 s and 2 more", not "... 400 and 2 more s"
            where = ", ".join(at) + f" s and {n - NAMED_GAPS} more"
        else:
            where = ((", ".join(at[:-1]) + " and " + at[-1]) if len(at) > 1 else at[0]) + " s"
        longest = int(self.gap_lengths.max())
        text = (f"{n} gap{'s' if n != 1 else ''} in the data (longest {longest} sample{'s' if longest != 1 else ''}, "
                f"at t = {where}): {self.samples_missing} sample{'s' if self.samples_missing != 1 else ''} "
                f"missing, {self.rows_lost} regression rows lost; nothing is interpolated, no regression row "
                f"reaches across a gap")
        long_gaps = int(np.sum(self.gap_lengths > self.max_gap))
        if long_gaps:
            text += (f"; {long_gaps} gap{'s' if long_gaps != 1 else ''} longer than max_gap = {self.max_gap} samples "
                     f"split{'' if long_gaps != 1 else 's'} the data into spans analysed as separate segments")
        if longest > STRAY_GAP_FACTOR * max(self.samples_used, 1):
            text += (f"; the longest gap is {longest / max(self.samples_used, 1):.3g} times the samples analysed: "
                     f"a stray t, or a wrong sample time?")
        left_out = len(self.segments) - len(self.used)
        if left_out:
            lost = sum(b - a for a, b in self.segments) - self.samples_used
            text += (f"; {left_out} span{'s' if left_out != 1 else ''} between gaps too short for a regression row "
                     f"(at most {self.start} samples) left out ({lost} sample{'s' if lost != 1 else ''})")
        return text


def plan_gaps(data: LoggedData, start: int, max_gap: Optional[int] = None) -> Optional[GapPlan]:
    """The :class:`GapPlan` of ``data``, or None when no sample is missing.

    Parameters
    ----------
    data : LoggedData
    start : int
        First sample of a segment used as a regression row (the longest lag of the tests).
    max_gap : int, optional
        Longest gap (samples) called short; default ``start``.
    """
    segments = data.segments
    if len(segments) <= 1:
        return None
    k = data.grid_index
    first = np.array([a for a, _ in segments[1:]])
    lengths = k[first] - k[first - 1] - 1
    ts = float(data.sample_time)
    # Both ends from the sample before the gap: on a clock a little off the grid, the sample after it gave a last
    # missing time before the first of a one-sample gap.
    where = [(float(data.t[f - 1]) + ts, float(data.t[f - 1]) + int(n) * ts) for f, n in zip(first, lengths)]
    used = [(a, b) for a, b in segments if b - a > start]
    return GapPlan(segments=segments, used=used, start=int(start), gap_lengths=lengths.astype(int), gap_where=where,
                   grid_samples=int(k[-1] + 1), max_gap=int(start if max_gap is None else max_gap))
