"""Sliding window of aligned closed-loop samples, built from stamped setpoint/input/output (/disturbance) vectors.

The three topics (four when the model has measured disturbances) arrive independently and in any
interleaving.  :class:`SampleWindow` puts every vector on the sample grid by its stamp, completes
sample ``k`` once its setpoint ``r(k)``, input ``u(k)``, output ``y(k)`` and, with measured
disturbances, ``dv(k)`` are all present (DESIGN.md, time convention of a sample), appends
completed samples in order to a window of the last ``window_samples`` samples, and hands the window
to the analysis as :class:`~mpm_monitor.core.logged_data.LoggedData`.

Nothing is silently mis-aligned:

* a vector whose stamp is off the grid by more than ``stamp_tolerance * sample_time`` is refused
  (``off_grid``);
* a second vector for a sample already held is a ``duplicate`` (same values) or a ``conflict``
  (different values) and the first is kept;
* a vector for a sample that is already in the window, or already given up, is ``late``;
* when more than ``reorder_samples`` later samples are complete while one is not (counted, not their
  distance: one sample stamped far ahead waits), the incomplete samples are given up as a ``gap``.
  A gap of at most ``max_gap`` samples keeps the window: its samples stay, nothing is interpolated, and the analysis gets the window with its ``t``
  skipping the missing samples (it analyses around them; docs/interfaces.md, "Gaps").  A longer gap
  restarts the window after it, unless it is at most ``split_gap`` samples: then the window keeps its
  samples too, and the analysis splits the data there as it splits a log with a long gap;
* a vector of the wrong length or with a non-finite value, or stamped 0 (an unset ``header.stamp``)
  among wall-clock stamps, is a ``bad_value``;
* when more than ``reorder_samples + 1`` (at least 3) output vectors in a row are refused (late,
  off the grid, duplicate or conflicting) while no sample completes, the stream has restarted
  (stamps jumped back, or a new grid phase after a publisher restart): the alignment starts again
  from the refused vectors, reported as a ``restart``, and the window restarts empty.

With ``hold_setpoint`` the setpoint is treated as piecewise constant (a stack that publishes its
setpoints only when they change): sample ``k`` takes the latest setpoint stamped at or before its
time, and only the input, the output (and the measured disturbances) must be on the grid.

This module is pure Python and numpy (no rclpy); time is whatever stamps the caller passes in.
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
from typing import Optional, Sequence

import numpy as np

from ..core.errors import ConfigurationError
from ..core.logged_data import EARLY_BLOCK, LoggedData, early_limit_ns

#: The three channels of a sample, in the order of the slots.
CHANNELS = ("setpoint", "input", "output")
#: The fourth channel, of a model with measured disturbances.
DISTURBANCE = "disturbance"

#: Problem kinds that mean the data itself is wrong (the monitor reports them as ERROR).
ERROR_KINDS = frozenset({"bad_value", "conflict", "off_grid", "clock"})
#: Problem kinds that cost samples but not correctness (reported in the summary's values).
WARNING_KINDS = frozenset({"gap", "duplicate", "late", "out_of_order", "restart", "rephase", "behind"})
#: Vectors of a channel stamped 0 in a row, each with values other than the one before, past which the next is
#: refused as an unset ``header.stamp`` (the second may be a second publisher's: a conflict).
UNSET_STAMP_REPEATS = 2
#: A stamp later than this (nanoseconds: 1e9 s, 2001-09-09) is a wall-clock time; a stamp of exactly 0
#: among such stamps is an unset ``header.stamp``.
WALL_CLOCK_NS = 10**18
#: Fewest refused output vectors in a row (with no sample completed) taken as a stream restart.
MIN_RESTART_OUTPUTS = 3

NS_PER_S = 1_000_000_000


def seconds_text(stamp_ns) -> str:
    """A stamp (nanoseconds) as seconds in a message, to 15 significant digits: a wall-clock stamp keeps
    its fraction of a second to 10 microseconds (``1795395118.00184``)."""
    return f"{stamp_ns / NS_PER_S:.15g}"


def names_text(names, most: int = 5, longest: int = 40) -> str:
    """The first ``most`` of ``names`` (channel names of a message) for a message, each quoted and cut to
    ``longest`` characters, with how many more there are: a message of a vector that names thousands of
    channels stays one short line."""
    names = list(names)
    shown = ", ".join(repr(n if len(n) <= longest else n[:longest] + "...") for n in names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


@dataclasses.dataclass(frozen=True)
class WindowOptions:
    """Options of :class:`SampleWindow`.

    Attributes
    ----------
    window_samples : int
        Length of the sliding window, samples (>= 10).
    reorder_samples : int
        How many samples a later complete sample may run ahead of an incomplete one before the
        incomplete one is given up as a gap (>= 0).
    stamp_tolerance : float
        Largest distance of a stamp from the grid, as a fraction of the sample time, in (0, 0.5).
    hold_setpoint : bool
        Hold the latest setpoint instead of requiring one on every sample.
    max_pending : int
        Most incomplete samples kept; beyond it the oldest are given up (>= 1).
    max_gap : int
        Longest gap (missing samples) the window keeps its samples across; a longer gap restarts it
        (>= 0; 0 restarts it at every gap), unless ``split_gap`` keeps them.
    split_gap : int
        Longest gap (missing samples) after which the window still keeps its samples, when longer than
        ``max_gap`` (a lossy link that drops bursts of messages): the analysis splits the data there,
        each span analysed as a segment (the model restarts after a gap longer than the tests' longest
        lag), as ``analyze`` does with a log with a long gap.  A longer gap restarts the window (>= 0;
        0, the default: every gap longer than ``max_gap`` restarts it).
    """

    window_samples: int = 3000
    reorder_samples: int = 10
    stamp_tolerance: float = 0.25
    hold_setpoint: bool = False
    max_pending: int = 1000
    max_gap: int = 10
    split_gap: int = 0

    def __post_init__(self):
        check_window_options(self)


def check_window_options(o: WindowOptions) -> None:
    """Raise :class:`ConfigurationError` when an option is outside its range."""
    if int(o.window_samples) != o.window_samples or not 10 <= o.window_samples <= 10_000_000:
        raise ConfigurationError(f"window_samples: expected an integer in [10, 10000000], got {o.window_samples!r}")
    if int(o.reorder_samples) != o.reorder_samples or not 0 <= o.reorder_samples <= 100_000:
        raise ConfigurationError(f"reorder_samples: expected an integer in [0, 100000], got {o.reorder_samples!r}")
    if not 0.0 < o.stamp_tolerance < 0.5:
        raise ConfigurationError(f"stamp_tolerance: expected a fraction of the sample time in (0, 0.5), "
                                 f"got {o.stamp_tolerance!r}")
    if int(o.max_pending) != o.max_pending or not 1 <= o.max_pending <= 10_000_000:
        raise ConfigurationError(f"max_pending: expected an integer in [1, 10000000], got {o.max_pending!r}")
    if int(o.max_gap) != o.max_gap or not 0 <= o.max_gap <= 10_000_000:
        raise ConfigurationError(f"max_gap: expected an integer in [0, 10000000] (samples), got {o.max_gap!r}")
    if int(o.split_gap) != o.split_gap or not 0 <= o.split_gap <= 10_000_000:
        raise ConfigurationError(f"split_gap: expected an integer in [0, 10000000] (samples), got {o.split_gap!r}")


@dataclasses.dataclass(frozen=True)
class Problem:
    """One thing wrong with the incoming data.

    Attributes
    ----------
    kind : str
        ``bad_value``, ``conflict``, ``off_grid`` (errors) or ``gap``, ``duplicate``, ``late``,
        ``out_of_order`` (warnings).
    channel : str
        ``setpoint``, ``input``, ``output``, ``disturbance`` or ``""``.
    stamp_ns : int or None
        Stamp of the offending vector or first missing sample, nanoseconds.
    message : str
        One line for a control engineer.
    """

    kind: str
    channel: str
    stamp_ns: Optional[int]
    message: str

    @property
    def is_error(self) -> bool:
        return self.kind in ERROR_KINDS


@dataclasses.dataclass
class WindowHealth:
    """Counters of what the window received and gave up (since it was created)."""

    completed: int = 0
    received: dict = dataclasses.field(default_factory=lambda: {c: 0 for c in CHANNELS})
    bad_value: int = 0
    conflict: int = 0
    off_grid: int = 0
    duplicate: int = 0
    late: int = 0
    out_of_order: int = 0
    gaps: int = 0
    missing_samples: int = 0
    resets: int = 0
    restarts: int = 0

    def copy(self) -> "WindowHealth":
        return dataclasses.replace(self, received=dict(self.received))


class SampleWindow:
    """Aligns stamped setpoint, input, output (and measured-disturbance) vectors into a sliding window of samples.

    Parameters
    ----------
    outputs : sequence of str
        Output names (setpoint and output channels), in model order.
    inputs : sequence of str
        Input names, in model order.
    sample_time : float
        Seconds per sample.
    options : WindowOptions
    disturbances : sequence of str
        Measured-disturbance names, in model order (default none).  With some, a sample needs its
        ``disturbance`` vector too (:attr:`channels` has four entries).

    Notes
    -----
    The grid's phase is taken from the first output vector (``k = round((t - phase) / Ts)``);
    vectors of other channels that arrive before it wait for it.  Stamps are integer nanoseconds.
    """

    def __init__(self, outputs: Sequence[str], inputs: Sequence[str], sample_time: float,
                 options: WindowOptions = WindowOptions(), disturbances: Sequence[str] = ()):
        self.outputs = tuple(outputs)
        self.inputs = tuple(inputs)
        self.disturbances = tuple(disturbances)
        #: The channels a sample needs, in the order of the slots.
        self.channels = CHANNELS + ((DISTURBANCE,) if self.disturbances else ())
        self._slot = {c: i for i, c in enumerate(self.channels)}
        self._names = {"setpoint": self.outputs, "input": self.inputs, "output": self.outputs,
                       DISTURBANCE: self.disturbances}
        if not (np.isfinite(sample_time) and sample_time > 0):
            raise ConfigurationError(f"sample_time: expected a finite number > 0 (seconds), got {sample_time!r}")
        self.sample_time = float(sample_time)
        self.options = options
        self._period = int(round(self.sample_time * NS_PER_S))
        self._tol = int(options.stamp_tolerance * self._period)
        self._sizes = tuple(len(self._names[c]) for c in self.channels)
        cap = int(options.window_samples)
        self._k_buf = np.zeros(cap, dtype=np.int64)
        self._r_buf = np.zeros((cap, len(self.outputs)))
        self._u_buf = np.zeros((cap, len(self.inputs)))
        self._y_buf = np.zeros((cap, len(self.outputs)))
        self._d_buf = np.zeros((cap, len(self.disturbances)))
        self._bufs = (self._r_buf, self._u_buf, self._y_buf, self._d_buf)[:len(self.channels)]
        self._head = 0          # next write position
        self._count = 0         # samples in the window
        self._phase: Optional[int] = None
        self._early: list = []  # (channel, stamp_ns, values) before the phase is known
        self._pending: dict = {}
        self._complete: set = set()
        self._next_k: Optional[int] = None
        # hold mode: (stamp_ns, arrival number, values), in stamp order (arrivals out of order are put in
        # their place; the arrival number keeps a repeated stamp's later vector last, and the arrival
        # order a restart needs)
        self._setpoints: list = []
        self._setpoint_arrivals = 0
        self._last_stamp = {c: None for c in self.channels}
        # Of each channel whose last vectors were stamped 0 (an unset stamp?): the last, and how many in a row had
        # values other than the one before.
        self._last_zero: dict = {}
        self._health = WindowHealth(received={c: 0 for c in self.channels})
        self._problems: list = []
        self._since_reset = 0
        # restart detection: vectors refused since the last completed sample (replayed on a restart)
        self._restart_after = max(MIN_RESTART_OUTPUTS, int(options.reorder_samples) + 2)
        self._refused: collections.deque = collections.deque(maxlen=3 * self._restart_after + 3)
        self._refused_outputs = 0
        self._accepted = False
        # Until the first sample completes on a phase: every vector placed since it was set (to place again on a
        # phase moved to fit them all, :meth:`_rephase`), and whether a stamp was refused off the grid.
        self._unsettled: Optional[list] = []
        self._off_grid_seen = False
        self._problems_before = 0
        # Arrival times (ns, the caller's clock) of each pending sample's vectors, by slot; of the samples appended,
        # how early each channel's vector came (the last EARLY_BLOCK), and the arrival time per sample.
        self._arrival_now: Optional[int] = None
        self._arrivals: dict = {}
        self._early_by: dict = {c: collections.deque(maxlen=EARLY_BLOCK) for c in self.channels}
        # ... and how late: a channel late by the clock check's limit in a block's median is named once (a warning),
        # again only after a block where it was not.
        self._late_by: dict = {c: collections.deque(maxlen=EARLY_BLOCK) for c in self.channels}
        self._behind: set = set()
        self._last_arrival: Optional[int] = None
        self._per_sample: collections.deque = collections.deque(maxlen=4 * EARLY_BLOCK + 1)
        self._clock_count = 0
        self._clock_slots = [i for i, c in enumerate(self.channels)
                             if not (c == "setpoint" and options.hold_setpoint)]

    # ------------------------------------------------------------------------------ properties
    @property
    def sample_period_ns(self) -> int:
        """Sample time in nanoseconds."""
        return self._period

    @property
    def n_window(self) -> int:
        """Samples now in the window (at most ``window_samples``)."""
        return self._count

    @property
    def n_completed(self) -> int:
        """Samples completed since the window was created."""
        return self._health.completed

    @property
    def n_since_reset(self) -> int:
        """Samples completed since the window last restarted (a gap longer than ``max_gap`` and ``split_gap``, a
        stream restart)."""
        return self._since_reset

    def window_gaps(self) -> tuple:
        """``(samples lost, gaps)`` inside the window now: the missing samples it keeps its samples across."""
        n = self._count
        if n < 2:
            return 0, 0
        cap = self._k_buf.shape[0]
        k = self._k_buf[(np.arange(self._head - n, self._head)) % cap]
        steps = np.diff(k)
        return int(k[-1] - k[0] + 1 - n), int(np.count_nonzero(steps > 1))

    @property
    def n_pending(self) -> int:
        """Incomplete samples held."""
        return len(self._pending)

    def oldest_incomplete(self) -> Optional[tuple]:
        """The oldest incomplete sample the newer ones wait for: ``(stamp_ns, channels absent, samples held)``.

        None when no sample is held incomplete.  Samples complete in order, so every newer sample held waits
        for this one (until more than ``reorder_samples`` of them are complete, or ``max_pending`` are held).
        """
        if not self._pending:
            return None
        k = min(self._pending)
        return self._stamp_of(k), self._absent(k, self._pending[k]), len(self._pending)

    def _absent(self, k: int, entry) -> list:
        """The channels sample ``k`` (its held vectors ``entry``) lacks; with ``hold_setpoint``, the setpoint only
        when no setpoint holds at ``k`` yet."""
        held = self.options.hold_setpoint and entry[0] is None and self._held_setpoint(k) is not None
        return [c for i, (c, e) in enumerate(zip(self.channels, entry)) if e is None and not (i == 0 and held)]

    @property
    def last_sample_stamp_ns(self) -> Optional[int]:
        """Stamp of the newest completed sample, nanoseconds (None before the first)."""
        if self._count == 0:
            return None
        return self._stamp_of(int(self._k_buf[(self._head - 1) % self._k_buf.shape[0]]))

    def health(self) -> WindowHealth:
        """A copy of the counters."""
        return self._health.copy()

    def take_problems(self) -> list:
        """The :class:`Problem` s recorded since the last call (oldest first), and forget them."""
        out, self._problems = self._problems, []
        return out

    # ---------------------------------------------------------------------------------- input
    def report_bad(self, channel: str, stamp_ns: Optional[int], message: str) -> None:
        """Record a vector refused before it reached the window (e.g. wrong channel names)."""
        self._health.bad_value += 1
        self._problem("bad_value", channel, stamp_ns, message)

    def add(self, channel: str, stamp_ns: int, values, arrival_ns: Optional[int] = None) -> int:
        """Add one vector.

        Parameters
        ----------
        channel : str
            ``setpoint``, ``input``, ``output``, or ``disturbance`` (a window with measured disturbances).
        stamp_ns : int
            Its stamp, nanoseconds.
        values : array_like, shape (n_channels,)
            Values in model order (outputs for setpoint and output, inputs for input, measured
            disturbances for disturbance).
        arrival_ns : int, optional
            When it arrived, nanoseconds of the caller's clock: a topic whose vectors arrive well before the
            other topics' of the same sample has stamps that run ahead of theirs (:meth:`_check_clocks`).

        Returns
        -------
        int
            Number of samples appended to the window by this vector (0, 1 or more).
        """
        if channel not in self._slot:
            raise ValueError(f"channel: expected one of {', '.join(self.channels)}, got {channel!r}")
        slot = self._slot[channel]
        stamp_ns = int(stamp_ns)
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.shape[0] != self._sizes[slot]:
            names = self._names[channel]
            self.report_bad(channel, stamp_ns, f"{channel}: {v.shape[0]} value(s) at t = {seconds_text(stamp_ns)} s, "
                                               f"expected {len(names)} ({', '.join(names)})")
            return 0
        if not np.all(np.isfinite(v)):
            self.report_bad(channel, stamp_ns, f"{channel}: non-finite value at t = {seconds_text(stamp_ns)} s")
            return 0
        if stamp_ns == 0 and self._phase is not None and self.last_sample_stamp_ns is not None \
                and self.last_sample_stamp_ns > WALL_CLOCK_NS:
            # An unset header.stamp among wall-clock stamps (as the bag reader leaves out): it cannot
            # be placed on the grid, and taken as a time it would look like a stream restart.
            self.report_bad(channel, stamp_ns, f"{channel}: header.stamp unset (0) among wall-clock stamps; the vector "
                                               f"cannot be placed on the sample grid")
            return 0
        if stamp_ns == 0:
            # Every message stamped 0 (a publisher that never fills header.stamp): aligned by stamp they were
            # "two different vectors for one sample (two publishers on one topic?)" and "stream restarted ...
            # (publisher restart or clock jump)" by turns, the window restarting every few outputs, and never
            # the cause (an outside check).  A second vector at 0 with other values may be a second publisher
            # (a conflict, as before); a third in a row is an unset stamp.
            last = self._last_zero.get(channel)
            changed = 1 if last is None else last[1] + (not np.array_equal(last[0], v))
            self._last_zero[channel] = (v, changed)
            if changed > UNSET_STAMP_REPEATS:
                self.report_bad(channel, stamp_ns, f"{channel}: header.stamp unset (0) on successive messages with "
                                                   f"different values: its publisher does not stamp them, and the "
                                                   f"topics are aligned by stamp; the vector cannot be placed")
                return 0
        else:
            self._last_zero.pop(channel, None)
        self._health.received[channel] += 1
        last = self._last_stamp[channel]
        if last is not None and stamp_ns < last:
            self._health.out_of_order += 1
            self._problem("out_of_order", channel, stamp_ns,
                          f"{channel}: t = {seconds_text(stamp_ns)} s arrived after t = {seconds_text(last)} s")
        # the previous stamp, not the largest: one stamp far in the future must not make every
        # later vector out of order
        self._last_stamp[channel] = stamp_ns
        self._accepted = False
        self._off_grid_seen = False
        self._problems_before = len(self._problems)
        self._arrival_now = None if arrival_ns is None else int(arrival_ns)
        n = self._route(channel, stamp_ns, v)
        if self._unsettled is not None and self._phase is not None:
            if n:
                self._unsettled = None               # a sample completed: the phase holds
            else:
                self._unsettled.append((channel, stamp_ns, v))
                if len(self._unsettled) > self.options.max_pending:
                    self._unsettled.pop(0)
                if self._off_grid_seen:
                    n = self._rephase()
        if n:
            self._refused.clear()
            self._refused_outputs = 0
        elif not self._accepted and self._phase is not None:
            self._refused.append((channel, stamp_ns, v))
            if channel == "output":
                self._refused_outputs += 1
                if self._refused_outputs >= self._restart_after:
                    n += self._restart(stamp_ns)
        return n

    def _route(self, channel: str, stamp_ns: int, v: np.ndarray) -> int:
        """Place a checked vector (or keep it until the first output gives the grid phase)."""
        if self._phase is None:
            if channel != "output":
                self._early.append((channel, stamp_ns, v))
                if len(self._early) > self.options.max_pending:
                    self._early.pop(0)
                return 0
            self._phase = stamp_ns % self._period
            self._accepted = True
            n = self._place(channel, stamp_ns, v)
            early, self._early = self._early, []
            if self._unsettled is not None:          # placed again if the phase moves (_rephase)
                self._unsettled.extend(early)
            for ch, st, val in early:
                n += self._place(ch, st, val)
            return n
        return self._place(channel, stamp_ns, v)

    # ------------------------------------------------------------------------------- output
    def data(self, source: str = "ros") -> LoggedData:
        """The window as :class:`~mpm_monitor.core.logged_data.LoggedData` (a copy), oldest sample first.

        ``t`` is in seconds (the stamps on the grid); ``dv`` holds the measured disturbances (none
        without them).
        """
        cap = self._k_buf.shape[0]
        n = self._count
        idx = (np.arange(self._head - n, self._head)) % cap
        k = self._k_buf[idx]
        t = (k * self._period + (self._phase or 0)) / NS_PER_S
        return LoggedData(t=t, r=self._r_buf[idx].copy(), u=self._u_buf[idx].copy(), y=self._y_buf[idx].copy(),
                          inputs=self.inputs, outputs=self.outputs, sample_time=self.sample_time, source=source,
                          dv=self._d_buf[idx].copy(), disturbances=self.disturbances)

    # ----------------------------------------------------------------------------- internals
    def _stamp_of(self, k: int) -> int:
        return k * self._period + (self._phase or 0)

    def _problem(self, kind, channel, stamp_ns, message) -> None:
        self._problems.append(Problem(kind, channel, stamp_ns, message))
        if len(self._problems) > 1000:
            del self._problems[:500]

    def _grid_index(self, channel: str, stamp_ns: int) -> Optional[int]:
        rel = stamp_ns - self._phase
        k = (rel + self._period // 2) // self._period
        off = rel - k * self._period
        if abs(off) > self._tol:
            self._off_grid_seen = True
            self._health.off_grid += 1
            self._problem("off_grid", channel, stamp_ns,
                          f"{channel}: t = {seconds_text(stamp_ns)} s is {off / NS_PER_S:+.3g} s off the sample grid "
                          f"(sample_time {self.sample_time:g} s; a wrong sample time or unsynchronised stamps)")
            return None
        return int(k)

    def _place(self, channel: str, stamp_ns: int, v: np.ndarray) -> int:
        slot = self._slot[channel]
        if channel == "setpoint" and self.options.hold_setpoint:
            self._accepted = True
            self._setpoint_arrivals += 1
            bisect.insort(self._setpoints, (stamp_ns, self._setpoint_arrivals, v), key=lambda e: e[:2])
            if len(self._setpoints) > self.options.max_pending:
                del self._setpoints[0]
            self._hold_late_setpoint(stamp_ns)
            return self._advance()
        k = self._grid_index(channel, stamp_ns)
        if k is None:
            return 0
        if self._next_k is not None and k < self._next_k:
            self._late_or_duplicate(channel, k, slot, v)
            return 0
        entry = self._pending.get(k)
        if entry is None:
            entry = [None] * len(self.channels)
            self._pending[k] = entry
        if entry[slot] is not None:
            t = f"t = {seconds_text(stamp_ns)} s"
            self._repeated(channel, stamp_ns, entry[slot], v,
                           f"{channel}: sample {t} received twice (same values; kept once)",
                           f"{channel}: two different vectors for sample {t} (the first is kept; two publishers "
                           f"on one topic?)")
            return 0
        entry[slot] = v
        if self._arrival_now is not None:
            self._arrivals.setdefault(k, [None] * len(self.channels))[slot] = self._arrival_now
        self._accepted = True
        if self._is_complete(k, entry):
            self._complete.add(k)
        if len(self._pending) > self.options.max_pending:
            self._drop_oldest_pending()
        return self._advance()

    def _repeated(self, channel, stamp_ns, kept, v, duplicate_text, conflict_text) -> None:
        """Count and report a second vector for a sample that already has one (``kept`` stays)."""
        if np.array_equal(kept, v):
            self._health.duplicate += 1
            self._problem("duplicate", channel, stamp_ns, duplicate_text)
        else:
            self._health.conflict += 1
            self._problem("conflict", channel, stamp_ns, conflict_text)

    def _window_position(self, k: int) -> Optional[int]:
        """Where sample ``k`` sits in the window's ring buffers, or None when it is not in the window (its samples
        are in increasing order, with the gaps the window keeps between them: searched, not counted back)."""
        if not self._count:
            return None
        cap = self._k_buf.shape[0]
        first = self._head - self._count
        i = bisect.bisect_left(range(self._count), k, key=lambda q: int(self._k_buf[(first + q) % cap]))
        if i < self._count and int(self._k_buf[(first + i) % cap]) == k:
            return (first + i) % cap
        return None

    def _late_or_duplicate(self, channel, k, slot, v) -> None:
        stamp_ns = self._stamp_of(k)
        # A gap the window keeps lies between some of its samples: the position is searched (counted back from
        # the newest, a re-sent or conflicting vector before such a gap was taken as given up, "late").
        pos = self._window_position(k)
        if pos is not None:
            stored = self._bufs[slot][pos]
            t = f"t = {seconds_text(stamp_ns)} s"
            self._repeated(channel, stamp_ns, stored, v,
                           f"{channel}: sample {t} received again (same values; ignored)",
                           f"{channel}: a different vector for sample {t}, already in the window (ignored; "
                           f"two publishers on one topic?)")
            return
        self._health.late += 1
        self._problem("late", channel, stamp_ns,
                      f"{channel}: sample t = {seconds_text(stamp_ns)} s arrived after it was given up (ignored)")

    def _hold_late_setpoint(self, stamp_ns: int) -> None:
        """Hold mode: a setpoint stamped at or before samples already in the window (its message delivered after
        their input and output vectors: topics of different publishers arrive in no set order) holds for them.
        Their setpoints are taken again from the held ones, newest first, back to its stamp; samples that have
        left the window keep theirs.  Before, the new value started at the next sample to complete, a sample or
        more late, without a word."""
        cap = self._k_buf.shape[0]
        for q in range(1, self._count + 1):
            pos = (self._head - q) % cap
            k = int(self._k_buf[pos])
            if self._stamp_of(k) + self._tol < stamp_ns:
                break
            r = self._held_setpoint(k)
            if r is not None:
                self._r_buf[pos] = r

    def _latest_setpoint(self, k: int) -> int:
        """Index in the held setpoints of the one that holds at sample ``k`` (the latest stamped at or
        before it, within the grid tolerance; of equal stamps the last to arrive); -1 when none."""
        return bisect.bisect_right(self._setpoints, self._stamp_of(k) + self._tol, key=lambda e: e[0]) - 1

    def _held_setpoint(self, k: int) -> Optional[np.ndarray]:
        i = self._latest_setpoint(k)
        return self._setpoints[i][2] if i >= 0 else None

    def _is_complete(self, k: int, entry) -> bool:
        if self.options.hold_setpoint:
            return all(e is not None for e in entry[1:]) and self._held_setpoint(k) is not None
        return all(e is not None for e in entry)

    def _advance(self) -> int:
        appended = 0
        hold = self.options.hold_setpoint
        if hold:  # a new setpoint can complete samples that waited for one
            for k, entry in self._pending.items():
                if k not in self._complete and self._is_complete(k, entry):
                    self._complete.add(k)
        while self._complete:
            if self._next_k is None:
                self._next_k = min(self._complete)
                self._discard_pending_below(self._next_k, count=False)
            k = self._next_k
            if k in self._complete:
                entry = self._pending.pop(k)
                self._complete.discard(k)
                r = self._held_setpoint(k) if hold else entry[0]
                self._append(k, r, *entry[1:])
                self._next_k = k + 1
                appended += 1
                self._check_clocks(k)
                if hold:
                    self._prune_setpoints()
                continue
            # Sample k is given up once more than reorder_samples later samples are complete: counted,
            # not measured by their distance, so that one complete sample stamped far ahead (a stray
            # stamp) waits instead of opening a gap of a million samples.
            if len(self._complete) > self.options.reorder_samples:
                first = min(self._complete)
                self._gap(k, first)
                continue
            break
        return appended

    def _check_clocks(self, k: int) -> None:
        """After sample ``k`` was appended: how early each channel's vector arrived against the others' of the
        sample; a channel early by :func:`~mpm_monitor.core.logged_data.early_limit_ns` (3 samples of arrival time
        and 2 s) in the median of a block of :data:`EARLY_BLOCK` samples has stamps that run ahead
        (its publisher's clock jumped forward, or runs apart): aligned by stamp, its vectors pair with the other
        topics' of another time.  That is a data error, and the window restarts (no analysis of it).  A vector
        that arrived late is no sign of it: a delivery held up looks the same as stamps that run behind.  A
        channel late by that limit in a block's median is named in one warning (kind ``behind``; again only
        after a block where it was not), and the window keeps its samples.  Without arrival times, or with
        arrival times that do not advance, nothing is checked.  The held setpoint (``hold_setpoint``) is not
        compared."""
        arrivals = self._arrivals.pop(k, None)
        if len(self._arrivals) > 2 * int(self.options.max_pending):
            self._arrivals = {kk: a for kk, a in self._arrivals.items() if kk >= self._next_k}
        chans = self._clock_slots
        if arrivals is None or len(chans) < 2 or any(arrivals[i] is None for i in chans):
            return
        # Per sample only cheap Python (the monitor takes thousands of samples a second); the medians once a block.
        at = sorted(arrivals[i] for i in chans)
        middle = at[len(at) // 2]
        if self._last_arrival is not None:
            self._per_sample.append(middle - self._last_arrival)
        self._last_arrival = middle
        for i in chans:
            own = arrivals[i]
            first_other = at[1] if own == at[0] else at[0]
            last_other = at[-2] if own == at[-1] else at[-1]
            self._early_by[self.channels[i]].append(first_other - own)
            self._late_by[self.channels[i]].append(own - last_other)
        self._clock_count += 1
        if self._clock_count % EARLY_BLOCK or len(self._per_sample) < EARLY_BLOCK:
            return
        tau = float(np.median(self._per_sample))
        if not tau > 0:
            return
        limit = early_limit_ns(tau)
        for c in (self.channels[i] for i in chans):
            ahead = float(np.median(self._early_by[c]))
            if len(self._early_by[c]) == EARLY_BLOCK and ahead > limit:
                self._problem("clock", c, self._stamp_of(k),
                              f"{c}: its vectors arrive about {ahead / tau:.3g} samples ({ahead / NS_PER_S:.3g} s) "
                              f"before the other topics' vectors of the same sample, up to t = "
                              f"{seconds_text(self._stamp_of(k))} s: its stamps run ahead of theirs (a clock that "
                              f"jumped forward, or a publisher's clock set apart from the others'?); aligned by stamp "
                              f"its samples pair with the others' of another time: the window restarts")
                for d in self._early_by.values():
                    d.clear()
                self._reset_window()
                return
        for c in (self.channels[i] for i in chans):
            behind = float(np.median(self._late_by[c]))
            if len(self._late_by[c]) < EARLY_BLOCK or not behind > limit:
                self._behind.discard(c)
            elif c not in self._behind:
                self._behind.add(c)
                self._problem("behind", c, self._stamp_of(k),
                              f"{c}: its vectors arrive about {behind / tau:.3g} samples ({behind / NS_PER_S:.3g} s) "
                              f"after the other topics' vectors of the same sample, up to t = "
                              f"{seconds_text(self._stamp_of(k))} s: a delivery held up that long, or its stamps "
                              f"running behind the others' (a publisher's clock set apart?), which would pair its "
                              f"samples with the others' of another time; the window keeps them")

    def _prune_setpoints(self) -> None:
        last = self._latest_setpoint(self._next_k)
        if last > 0:
            del self._setpoints[:last]

    def _gap(self, first_missing: int, first_present: int) -> None:
        n_missing = first_present - first_missing
        entry = self._pending.get(first_missing)
        if entry is None:
            absent = "nothing received"
        else:
            names = self._absent(first_missing, entry)
            absent = "no " + " and no ".join(names) if names else "incomplete"
        t0 = self._stamp_of(first_missing) / NS_PER_S
        self._health.gaps += 1
        self._health.missing_samples += n_missing
        max_gap, split_gap = int(self.options.max_gap), int(self.options.split_gap)
        keep = 0 < n_missing <= max(max_gap, split_gap) and self._count > 0
        if not keep:
            then = "the window restarts after the gap"
            if self._count > 0 and n_missing > 0:
                then += (f" (longer than split_gap = {split_gap})" if split_gap > max_gap else
                         f" (longer than max_gap = {max_gap}; split_gap would keep its samples across such a gap)")
        elif n_missing <= max_gap:
            then = f"the window keeps its samples across the gap (at most max_gap = {max_gap})"
        else:
            then = (f"the window keeps its samples across the gap, longer than max_gap = {max_gap} (at most "
                    f"split_gap = {split_gap}): the data are analysed in spans split there")
        self._problem("gap", "", self._stamp_of(first_missing),
                      f"{n_missing} sample(s) missing from t = {t0:.15g} s ({absent}); {then}")
        self._discard_pending_below(first_present, count=False)
        if not keep:
            self._reset_window()
        self._next_k = first_present

    def _discard_pending_below(self, k: int, count: bool) -> None:
        for kk in [kk for kk in self._pending if kk < k]:
            del self._pending[kk]
            self._complete.discard(kk)

    def _drop_oldest_pending(self) -> None:
        oldest = min(self._pending)
        if self._next_k is not None and oldest == self._next_k:
            # Every incomplete sample but the newest reorder_samples, given up as one gap: a topic silent for
            # longer than max_pending samples was reported as one gap of one sample per sample received (212 gaps
            # for an outage of 1,200 samples), each said to keep the window across it.
            nxt = max(oldest + 1, max(self._pending) - int(self.options.reorder_samples))
            self._gap(oldest, nxt)
        else:
            entry = self._pending.pop(oldest)
            self._complete.discard(oldest)
            self._health.missing_samples += 1
            absent = [c for c, e in zip(self.channels, entry) if e is None]
            self._problem("gap", "", self._stamp_of(oldest),
                          f"sample t = {seconds_text(self._stamp_of(oldest))} s given up: no {' and no '.join(absent)} "
                          f"after {self.options.max_pending} newer incomplete samples")

    def _rephase(self) -> int:
        """Before the first sample completes, move the grid's phase to fit every stamp placed or refused since it
        was set, when one phase fits them all within ``stamp_tolerance``, and place them again on it.

        The phase comes from the first output's stamp (and those of the vectors before it).  A first output
        stamped 0.2 sample early put every input stamped 0.1 sample late 0.3 sample off the grid: refused, no
        sample ever completed, and with stamps jittered by 0.2 sample the stream restarted over and over.
        Returns the samples appended."""
        if self._count:                              # a sample completed (a restart's replay): the phase holds
            self._unsettled = None
            return 0
        stamps = np.array([st for _, st, _ in self._unsettled], dtype=np.int64)
        half = self._period // 2
        off = (stamps - self._phase + half) % self._period - half         # in [-period/2, period/2)
        lo, hi = int(off.min()), int(off.max())
        if hi - lo > 2 * self._tol or lo >= -self._tol and hi <= self._tol:
            return 0                                 # no phase fits them all, or this one already does
        replay, self._unsettled = self._unsettled, []
        # This vector's refusal was the old phase's, not the stamp's: no error.
        mine = self._problems[self._problems_before:]
        self._problems[self._problems_before:] = [p for p in mine if p.kind != "off_grid"]
        self._health.off_grid -= sum(p.kind == "off_grid" for p in mine)
        self._phase = (self._phase + (lo + hi) // 2) % self._period
        self._pending, self._complete, self._next_k = {}, set(), None
        self._setpoints = []                         # hold mode: the replay puts them back
        self._refused.clear()
        self._refused_outputs = 0
        self._problem("rephase", "", int(replay[-1][1]),
                      f"the sample grid's phase moved by {(lo + hi) / 2 / NS_PER_S:+.3g} s to fit the first "
                      f"{len(replay)} stamps (within stamp_tolerance {self.options.stamp_tolerance:g} sample)")
        n = 0
        for ch, st, val in replay:
            n += self._place(ch, st, val)
        self._unsettled = None if n else replay       # until a sample completes, the stamps so far count still
        return n

    def _restart(self, stamp_ns: int) -> int:
        """Forget the alignment (grid phase, pending samples, window; not the counters) and place
        the refused vectors again, as the start of a new stream."""
        if self._next_k is not None:
            where = (f"the latest at t = {seconds_text(stamp_ns)} s while t = {seconds_text(self._stamp_of(self._next_k))} s "
                     f"was expected")
        else:
            where = f"the latest at t = {seconds_text(stamp_ns)} s"
        self._health.restarts += 1
        self._unsettled = []
        self._problem("restart", "output", stamp_ns,
                      f"stream restarted: {self._refused_outputs} output vectors in a row did not fit the sample "
                      f"grid, {where} (publisher restart or clock jump); the window restarts from the new stamps")
        replay = list(self._refused)
        self._refused.clear()
        self._refused_outputs = 0
        self._phase = None
        self._early = []
        self._pending = {}
        self._complete = set()
        self._next_k = None
        if self._setpoints:  # hold mode: keep the setpoints that arrived after the last jump back
            sp = sorted(self._setpoints, key=lambda e: e[1])                      # in arrival order
            cut = max((i + 1 for i in range(len(sp) - 1) if sp[i + 1][0] < sp[i][0]), default=0)
            self._setpoints = sorted(sp[cut:], key=lambda e: e[:2])
        self._reset_window()
        n = 0
        for ch, st, val in replay:
            n += self._route(ch, st, val)
        if n:
            self._unsettled = None                   # the replay completed samples: the phase holds
        return n

    def _reset_window(self) -> None:
        if self._count:
            self._health.resets += 1
        self._count = 0
        self._since_reset = 0

    def _append(self, k, r, u, y, dv=None) -> None:
        cap = self._k_buf.shape[0]
        h = self._head
        self._k_buf[h] = k
        self._r_buf[h] = r
        self._u_buf[h] = u
        self._y_buf[h] = y
        if dv is not None:
            self._d_buf[h] = dv
        self._head = (h + 1) % cap
        self._count = min(self._count + 1, cap)
        self._since_reset += 1
        self._health.completed += 1
