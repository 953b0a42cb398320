"""Reading a bag: the vector topics aligned into logged data, CSV export, raw messages.

A bag holds the stamped vectors ``setpoint``, ``input`` and ``output`` (``sensor_msgs/msg/JointState``:
``header.stamp`` = sample time, ``name`` = channel names, ``position`` = values), and ``disturbance``
(the measured disturbances) when the loop has some.  :func:`read_bag` aligns them by stamp on the
model's sample grid into a :class:`~mpm_monitor.core.logged_data.LoggedData` (the disturbance topic into
``dv``, for a model with measured disturbances), so ``analyze --bag`` and ``analyze --data`` see the
same samples.  A sample some topic lacks is a gap: the data's ``t`` skips it, as a CSV's may
(docs/interfaces.md, "Gaps"; nothing is interpolated).  Anything that would silently mis-align the
samples (a missing topic, wrong channel names, a stamp off the grid, two messages for one sample) is
refused with a :class:`~mpm_monitor.core.errors.BagError` of one line naming the bag and the topic.
:func:`read_raw_messages` gives the serialized messages for replay.
"""

from __future__ import annotations

import dataclasses
import sys
from contextlib import closing
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ...core.errors import BagError, InputError
from ...core.logged_data import EARLY_BLOCK, LoggedData, early_limit_ns
from ...core.model import PlantModel
from ..csv_log import BAD_VALUES, write_log_csv
from .common import (
    DEFAULT_DISTURBANCE_TOPIC,
    DEFAULT_TOPICS,
    JOINT_STATE,
    none_read,
    one_line,
    open_reader,
    read_failure,
    shown_names,
    stamp_ns,
    topic_connections,
    topic_name,
)

#: A stamp may lie this fraction of the sample time off the sample grid and still be aligned: the live
#: monitor's default ``stamp_tolerance``, so that a recording of a stream the monitor analysed reads.
GRID_TOLERANCE = 0.25
#: A header stamp of exactly 0 is unset (a publisher that never filled it in, or a clock not yet set)
#: when the bag's other stamps are wall-clock times, later than this many seconds since the epoch
#: (2001-09-09); such messages are left out, with a note.  A bag on simulated time that starts at 0
#: keeps its first sample.
WALL_CLOCK_S = 1e9
#: Bags with at least this many messages on the read topics get a progress bar (``progress=True``).
LONG_BAG_MESSAGES = 20_000

_ROLES = ("setpoint", "input", "output", "disturbance")
#: What each topic's channel names are, for messages.
_WHAT = {"setpoint": "outputs", "input": "inputs", "output": "outputs", "disturbance": "measured disturbances"}


class _Progress:
    """A one-line text progress bar on a stream (stderr), redrawn at most every 1 %."""

    def __init__(self, total: int, stream, label: str, width: int = 30):
        self.total, self.stream, self.label, self.width = max(int(total), 1), stream, label, width
        self.shown = -1

    def update(self, done: int) -> None:
        pct = min(100, int(100 * done / self.total))
        if pct == self.shown:
            return
        self.shown = pct
        filled = self.width * pct // 100
        self.stream.write(f"\r{self.label}: [{'#' * filled}{' ' * (self.width - filled)}] {pct:3d}% "
                          f"{done}/{self.total} messages")
        self.stream.flush()

    def finish(self) -> None:
        self.update(self.total)
        self.stream.write("\n")
        self.stream.flush()


@dataclasses.dataclass
class _Series:
    """The messages of one stamped-vector topic, sorted by stamp."""

    topic: str
    names: tuple                # channel names of the first message
    stamps: np.ndarray          # (n,) int64 nanoseconds
    values: np.ndarray          # (n, len(channels)) values reordered to ``channels``
    back: tuple = ()            # in recorded order, the largest step back of the stamps: (message, stamp, previous)
    logs: Optional[np.ndarray] = None   # (n,) int64 ns, the recorder's time of each message (in the stamps' order)
    back_unset: tuple = ()      # ``back`` with the unset stamps (0) counted as stamps (a bag in simulated time)


def _seconds(ns) -> str:
    """A stamp in nanoseconds as seconds with every digit it has (``1700000070.5``, ``12``): ``%g`` printed a
    wall-clock stamp as ``1.7e+09``, which no longer says which message it is."""
    ns = int(ns)
    sec, frac = divmod(abs(ns), 10**9)          # integers: a float of 1.7e18 ns keeps no nanoseconds
    return ("-" if ns < 0 else "") + f"{sec}.{frac:09d}".rstrip("0").rstrip(".")


#: A topic's stamps may go back by at most this many sample times in recorded order (messages delivered a few
#: samples out of order are put in order); a larger step back is a clock stepped back, refused.
MAX_REORDER_SAMPLES = 10
#: Samples of one topic outside the span every topic covers that are left out without a note (a recording
#: started or stopped in the middle of a sample).
MAX_SILENT_TRIM = 10


def _check_topics(path, topics: Sequence[str]) -> list:
    """The setpoint, input, output (and disturbance) topic names, fully qualified and checked."""
    topics = [topic_name(t) for t in topics]
    if len(topics) not in (3, 4):
        raise BagError(f"{path}: expected three topics (setpoint, input, output) or four (and disturbance), "
                       f"got {len(topics)}")
    if len(set(topics)) != len(topics):
        raise BagError(f"{path}: the {', '.join(_ROLES[:len(topics)])} topics must differ, got {', '.join(topics)}")
    return topics


def _read_vectors(path, topics: Sequence[str], channels: Optional[dict], progress, optional: bool = False,
                  left_out: Optional[dict] = None) -> dict:
    """Read the stamped-vector topics (setpoint, input, output, and disturbance when four are given);
    ``channels[role]`` = expected names or None (= first message's).  With ``optional``, the fourth
    (disturbance) topic is read only if the bag holds messages on it.  A message holding a non-finite value
    is refused, or with ``left_out`` (a dict) left out and counted there, ``topic -> [count, first stamp, stamps]``
    (its sample is then a gap)."""
    topics = _check_topics(path, topics)
    with closing(open_reader(path)) as reader:
        if optional and len(topics) == 4 and not any(topic_name(c.topic) == topics[3] and c.msgcount
                                                     for c in reader.connections):
            topics = topics[:3]
        role_of = dict(zip(topics, _ROLES))
        conns = []
        for t in topics:
            conns += topic_connections(reader, path, t, JOINT_STATE)
        total = sum(c.msgcount for c in conns)
        stream = (sys.stderr if progress is True else progress) if progress else None
        bar = _Progress(total, stream, f"reading {Path(path).name}") if stream and total >= LONG_BAG_MESSAGES else None
        expected = dict(channels) if channels is not None else _first_names(reader, path, topics)
        index_cache: dict = {}
        stamps = {t: [] for t in topics}
        logs = {t: [] for t in topics}
        rows = {t: [] for t in topics}
        done = 0
        try:
            for conn, log_time, raw in reader.messages(connections=conns):
                topic = topic_name(conn.topic)
                role = role_of[topic]
                count = len(stamps[topic]) + 1
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    raise BagError(f"{path}: topic '{topic}': message {count} cannot be decoded as {JOINT_STATE}: "
                                   f"{one_line(exc)}") from None
                names = tuple(msg.name)
                stamp = stamp_ns(msg.header.stamp)
                values = np.asarray(msg.position, dtype=float)
                if values.shape != (len(names),):
                    raise BagError(f"{path}: topic '{topic}': message {count} (stamp {_seconds(stamp)} s) has "
                                   f"{values.size} positions for {len(names)} names")
                key = (role, names)
                idx = index_cache.get(key)
                if idx is None:
                    want = tuple(expected[role])
                    where = {n: i for i, n in enumerate(names)}     # (names.index per name: 10 s at 20,000 names)
                    missing = [n for n in want if n not in where]
                    if missing or len(where) != len(names):
                        what = _WHAT[role]
                        raise BagError(
                            f"{path}: topic '{topic}': message {count} (stamp {_seconds(stamp)} s) has channel names "
                            f"[{shown_names(names)}], expected the {what} [{shown_names(want)}]")
                    idx = np.array([where[n] for n in want], dtype=int)
                    index_cache[key] = idx
                if not np.all(np.isfinite(values[idx])):
                    if left_out is not None:
                        entry = left_out.setdefault(topic, [0, stamp, []])
                        entry[0] += 1
                        entry[2].append(stamp)
                        continue
                    raise BagError(f"{path}: topic '{topic}': message {count} (stamp {_seconds(stamp)} s) holds a "
                                   f"non-finite value")
                stamps[topic].append(stamp)
                logs[topic].append(log_time)
                rows[topic].append(values[idx])
                done += 1
                if bar is not None and done % 256 == 0:
                    bar.update(done)
        except BagError:
            raise
        except Exception as exc:  # damaged chunk inside an otherwise valid file
            raise BagError(f"{path}: cannot read bag: {read_failure(exc)}") from None
        if bar is not None:
            bar.finish()
    series = {}
    for t, role in role_of.items():
        bad = left_out[t][0] if left_out and t in left_out else 0
        if not stamps[t] and bad:
            raise BagError(f"{path}: topic '{t}': every one of its {bad} messages holds a non-finite value")
        if not stamps[t]:
            raise none_read(path, t, conns)
        counted = sum(c.msgcount for c in conns if topic_name(c.topic) == t)
        if len(stamps[t]) + bad < counted:
            # A damaged index (the summary's chunk times, which no CRC covers) makes the reader skip chunks.
            raise BagError(f"{path}: topic '{t}': metadata.yaml counts {counted} messages, {len(stamps[t]) + bad} could "
                           f"be read from the storage file: the storage file is damaged (python -m mpm_monitor "
                           f"recover rewrites every message its chunks hold as a new bag)")
        st = np.array(stamps[t], dtype=np.int64)
        vals = np.array(rows[t], dtype=float).reshape(len(st), len(expected[role]))
        # Unset stamps (0) left aside: among wall-clock stamps they are left out later, with a note; in simulated
        # time 0 is a stamp like any other (back_unset).
        back, back_unset = _step_back(st, st != 0), _step_back(st, np.ones(st.size, dtype=bool))
        order = np.argsort(st, kind="stable")
        series[role] = _Series(t, tuple(expected[role]), st[order], vals[order], back,
                               np.array(logs[t], dtype=np.int64)[order], back_unset)
    return series


def _step_back(st: np.ndarray, counted: np.ndarray) -> tuple:
    """The largest step back of the stamps ``st`` (int64 ns, recorded order) among those ``counted`` (bool):
    ``(message number, its stamp, the stamp before it)``, or ``()``."""
    stamped = np.flatnonzero(counted)
    steps = np.diff(st[stamped])
    if not steps.size or steps.min() >= 0:
        return ()
    i = int(np.argmin(steps))
    return int(stamped[i + 1]) + 1, int(st[stamped[i + 1]]), int(st[stamped[i]])


def _first_names(reader, path, topics) -> dict:
    """Channel names of the first input, output (and disturbance) messages (a bag read without a model)."""
    names = {}
    for role, topic in list(zip(_ROLES, topics))[1:]:
        conns = [c for c in reader.connections if topic_name(c.topic) == topic]
        try:
            first = next(iter(reader.messages(connections=conns)), None)
        except Exception as exc:  # damaged chunk inside an otherwise valid file
            raise BagError(f"{path}: cannot read bag: {read_failure(exc)}") from None
        if first is None:
            raise none_read(path, topic, conns)
        conn, _, raw = first
        try:
            names[role] = tuple(reader.deserialize(raw, conn.msgtype).name)
        except Exception as exc:
            raise BagError(f"{path}: topic '{topic}': message 1 cannot be decoded as {JOINT_STATE}: "
                           f"{one_line(exc)}") from None
        if not names[role]:
            raise BagError(f"{path}: topic '{topic}': message 1 names no channel (an empty JointState name "
                           f"list); without a model the {_WHAT[role]} are named by the first message: give "
                           f"the model (--model) or record the channel names")
    names["setpoint"] = names["output"]
    return names


def _without_unset_stamps(path, series: dict) -> tuple:
    """The series without their messages of unset stamp (0 among wall-clock stamps: :data:`WALL_CLOCK_S`),
    and the notes that say how many each topic lost."""
    for s in series.values():
        if s.stamps.size > 1 and not s.stamps.any():
            raise BagError(f"{path}: topic '{s.topic}': every message has an unset header.stamp (0); the samples "
                           f"are aligned by stamp: the publisher must fill in header.stamp")
    stamped = [s.stamps[s.stamps != 0] for s in series.values()]
    if not all(st.size and st[0] > WALL_CLOCK_S * 1e9 for st in stamped):
        # Simulated time: a stamp of 0 is its first sample's.  A message stamped 0 recorded long after it is a
        # step back like any other (it was put on the first sample without a word).
        return {role: dataclasses.replace(s, back=s.back_unset) for role, s in series.items()}, ()
    kept, notes = {}, []
    for role, s in series.items():
        unset = s.stamps == 0
        n = int(unset.sum())
        kept[role] = dataclasses.replace(s, stamps=s.stamps[~unset], values=s.values[~unset],
                                         logs=s.logs[~unset]) if n else s
        if n:
            notes.append(f"{path}: topic '{s.topic}': {n} message{'s' if n != 1 else ''} of {s.stamps.size} with an "
                         f"unset header.stamp (0, among wall-clock stamps) left out; the samples are aligned by "
                         f"stamp, so {'these' if n != 1 else 'this'} cannot be placed")
    return kept, tuple(notes)


def _grid_origin(stamps: list, ts_ns: float) -> int:
    """The sample grid's origin (ns) for the stamps of every topic (int64 arrays, each sorted): the earliest
    stamp, moved to the mean phase of all stamps on the grid of ``ts_ns`` when that is more than 1 % of a
    sample away.  Anchored on the earliest stamp alone, a first stamp 0.2 sample early and another 0.2 late,
    both within :data:`GRID_TOLERANCE` of their samples, lay 0.4 sample apart, and the bag was refused."""
    first = min(int(st[0]) for st in stamps)
    every = np.concatenate([np.asarray(st, dtype=np.int64) - first for st in stamps])
    angle = 2 * np.pi * np.mod(every.astype(float), ts_ns) / ts_ns
    phase = float(np.arctan2(np.sin(angle).mean(), np.cos(angle).mean())) / (2 * np.pi)     # in (-0.5, 0.5]
    if abs(phase) <= 0.01:
        return first
    return first + int(round(phase * ts_ns))


def _check_clocks_apart(path, series: dict, ks: dict, common: np.ndarray, origin: int, ts_ns: float) -> list:
    """Refuse a bag in which a topic's messages are recorded well before every other topic's message of the same
    sample, over :data:`EARLY_BLOCK` samples in a row: its stamps run ahead of theirs (its publisher's clock jumped
    forward, or is set apart from the others').  Aligned by stamp, its samples would pair with the others' of
    another time, silently (a gap where its clock jumped, nothing else).

    A message recorded late (a delivery stalled, then caught up) is no sign: only early ones count, by at least
    :func:`~mpm_monitor.core.logged_data.early_limit_ns` (3 samples of the recorder's time and 2 s).  A bag whose
    recorder times do not advance with its samples (written by a converter) is not checked.  A topic recorded as
    late in a block's median (stamps that run behind look the same as a delivery held up) gets a note, and its
    samples are kept as stamped.

    ``ks``: each topic's sample numbers (sorted, once each); ``common``: the samples every topic holds.

    Returns
    -------
    list of str
        The notes of the topics recorded late.
    """
    notes = []
    if len(series) < 2 or common.size < EARLY_BLOCK or any(s.logs is None for s in series.values()):
        return notes
    logs = {role: s.logs[np.searchsorted(ks[role], common)].astype(np.float64) for role, s in series.items()}
    together = np.median(np.vstack(list(logs.values())), axis=0)
    per_sample = np.diff(together)[np.diff(common) == 1]
    tau = float(np.median(per_sample)) if per_sample.size else 0.0
    if not tau > 0:
        return notes
    limit = early_limit_ns(tau)
    blocks = common.size // EARLY_BLOCK
    for role, log in logs.items():
        others = np.min(np.vstack([lg for r, lg in logs.items() if r != role]), axis=0)
        early = others - log
        bad = np.flatnonzero(np.median(early[:blocks * EARLY_BLOCK].reshape(blocks, EARLY_BLOCK), axis=1) > limit)
        if bad.size:
            ahead = float(np.median(early[bad[0] * EARLY_BLOCK:(bad[0] + 1) * EARLY_BLOCK]))
            start = max(int(bad[0]) - 1, 0) * EARLY_BLOCK          # where it began: in that block or the one before
            i = start + int(np.argmax(early[start:] > limit))
            t0 = _seconds(round(origin + int(common[i]) * ts_ns))
            raise BagError(f"{path}: topic '{series[role].topic}': from its sample at {t0} s on, its messages are "
                           f"recorded about {ahead / tau:.3g} samples ({ahead / 1e9:.3g} s) before the other topics' "
                           f"messages of the same sample: its stamps run ahead of theirs (a clock that jumped forward, "
                           f"or a publisher's clock set apart from the others'?); aligned by stamp, its samples would "
                           f"pair with the others' of another time: expected the topics stamped by one clock")
        late = log - np.max(np.vstack([lg for r, lg in logs.items() if r != role]), axis=0)
        slow = np.flatnonzero(np.median(late[:blocks * EARLY_BLOCK].reshape(blocks, EARLY_BLOCK), axis=1) > limit)
        if slow.size:
            behind = float(np.median(late[slow[0] * EARLY_BLOCK:(slow[0] + 1) * EARLY_BLOCK]))
            t0 = _seconds(round(origin + int(common[slow[0] * EARLY_BLOCK]) * ts_ns))
            notes.append(f"{path}: topic '{series[role].topic}': from about its sample at {t0} s, its messages are "
                         f"recorded about {behind / tau:.3g} samples ({behind / 1e9:.3g} s) after the other topics' "
                         f"messages of the same sample ({slow.size} of {blocks} blocks of {EARLY_BLOCK} samples): a "
                         f"delivery held up that long, or its stamps running behind the others' (a publisher's clock "
                         f"set apart?), which would pair its samples with the others' of another time; they are "
                         f"kept as stamped")
    return notes


def _align(path, series: dict, sample_time: float, inputs, outputs, disturbances=(),
           hold_setpoint: bool = False) -> LoggedData:
    """Put the topics on one sample grid (every sample at most once per topic; the samples a topic lacks are gaps);
    with ``hold_setpoint`` every sample takes the latest setpoint stamped at or before it (:func:`_held_setpoints`)."""
    series, notes = _without_unset_stamps(path, series)
    series, notes = dict(series), list(notes)
    ts_ns = sample_time * 1e9
    for s in series.values():
        if s.back and s.back[2] - s.back[1] > MAX_REORDER_SAMPLES * ts_ns:
            n, stamp, before = s.back
            raise BagError(f"{path}: topic '{s.topic}': message {n}'s stamp {_seconds(stamp)} s goes back "
                           f"{_seconds(before - stamp)} s from the stamp before it ({_seconds(before)} s): expected "
                           f"stamps that increase (a clock stepped back?); messages a few samples out of order "
                           f"are put in order")
    held = series.pop("setpoint") if hold_setpoint else None
    origin = _grid_origin([s.stamps for s in series.values()], ts_ns)
    ks = {}
    for role, s in series.items():
        rel = (s.stamps - origin).astype(float)
        k = np.rint(rel / ts_ns).astype(np.int64)
        off = np.abs(rel - k * ts_ns) > GRID_TOLERANCE * ts_ns
        if np.any(off):
            i = int(np.flatnonzero(off)[0])
            raise BagError(f"{path}: topic '{s.topic}': stamp {_seconds(s.stamps[i])} s is off the sample grid "
                           f"(sample_time {sample_time:g} s from {_seconds(origin)} s, tolerance "
                           f"{GRID_TOLERANCE:g} sample)")
        dup = np.flatnonzero(np.diff(k) == 0)
        if dup.size:
            same = np.all(s.values[dup] == s.values[dup + 1], axis=1)
            if not np.all(same):
                i = int(dup[~same][0])
                a, b = _seconds(s.stamps[i]), _seconds(s.stamps[i + 1])
                where = f"stamped {a} s" if a == b else f"for the sample at {a} s and {b} s"
                stepped = ""
                if s.back:
                    n, stamp, before = s.back
                    stepped = (f"; message {n}'s stamp {_seconds(stamp)} s goes back {_seconds(before - stamp)} s from "
                               f"the stamp before it (a clock stepped back?)")
                raise BagError(f"{path}: topic '{s.topic}': duplicate stamp: two different messages {where}{stepped}")
            # The same vector sent again for one sample (the plant node re-sends y(k) after a lock-step stall):
            # kept once, as the live monitor keeps it.
            keep = np.ones(k.size, dtype=bool)
            keep[dup + 1] = False
            s = series[role] = dataclasses.replace(s, stamps=s.stamps[keep], values=s.values[keep], logs=s.logs[keep])
            k = k[keep]
            notes.append(f"{path}: topic '{s.topic}': {dup.size} message{'s' if dup.size != 1 else ''} sent again for "
                         f"a sample (the same values) kept once")
        ks[role] = k
    k_first = max(int(k[0]) for k in ks.values())
    k_last = min(int(k[-1]) for k in ks.values())
    if k_last < k_first:
        spans = "; ".join(f"'{s.topic}' {_seconds(s.stamps[0])}..{_seconds(s.stamps[-1])} s" for s in series.values())
        raise BagError(f"{path}: the topics do not overlap in time ({spans})")
    for role, k in ks.items():
        outside = int(np.count_nonzero((k < k_first) | (k > k_last)))
        if outside > MAX_SILENT_TRIM:
            notes.append(f"{path}: topic '{series[role].topic}': {outside} of its {k.size} samples lie outside the "
                         f"span every topic covers ({_seconds(round(origin + k_first * ts_ns))} to "
                         f"{_seconds(round(origin + k_last * ts_ns))} s) and are left out")
    # A sample is kept when every topic has it; the others are gaps (t skips them; nothing interpolated).
    # (intersected topic by topic: a dense grid over the span would be as long as a clock jump is wide)
    common = None
    for k in ks.values():
        k = k[(k >= k_first) & (k <= k_last)]
        common = k if common is None else np.intersect1d(common, k, assume_unique=True)
    notes += _check_clocks_apart(path, series, ks, common, origin, ts_ns)
    if held is not None:
        common, r = _held_setpoints(path, held, origin + common * ts_ns, common, ts_ns, notes)
    out = {role: s.values[np.isin(ks[role], common)] for role, s in series.items()}
    if held is not None:
        out["setpoint"] = r
    t = (origin + common * ts_ns) / 1e9
    dv = out.get("disturbance")
    return LoggedData(t=t, r=out["setpoint"], u=out["input"], y=out["output"], inputs=tuple(inputs),
                      outputs=tuple(outputs), sample_time=float(sample_time), source=str(path), dv=dv,
                      disturbances=tuple(disturbances) if dv is not None else (), notes=tuple(notes))


def _held_setpoints(path, held, t_ns: np.ndarray, common: np.ndarray, ts_ns: float, notes: list) -> tuple:
    """The setpoint of every sample (stamps ``t_ns``, sample numbers ``common``) as the live monitor's
    ``hold_setpoint`` takes it: the latest setpoint message stamped at or before the sample (within
    :data:`GRID_TOLERANCE` of a sample; of equal stamps the last recorded), on the grid or not.  The samples before
    the first setpoint message are left out (a note counts them).

    Returns
    -------
    common : ndarray of int
        The samples kept.
    r : ndarray, shape (len(common), n_outputs)
    """
    order = np.argsort(held.stamps, kind="stable")
    stamps, values = held.stamps[order], held.values[order]
    at = np.searchsorted(stamps, t_ns + GRID_TOLERANCE * ts_ns, side="right") - 1
    before = int(np.count_nonzero(at < 0))
    if before == len(at):
        raise BagError(f"{path}: topic '{held.topic}': no setpoint message stamped at or before the last sample "
                       f"({_seconds(int(t_ns[-1]))} s; the first is stamped {_seconds(int(stamps[0]))} s): with "
                       f"--hold-setpoint every sample takes the latest setpoint before it")
    if before:
        notes.append(f"{path}: topic '{held.topic}': the {before} sample{'s' if before != 1 else ''} before its first "
                     f"message ({_seconds(int(stamps[0]))} s) left out (no setpoint to hold yet)")
    return common[at >= 0], values[at[at >= 0]]


def read_bag(path, model: PlantModel, topics: Sequence[str] = DEFAULT_TOPICS, progress=False,
             bad_values: str = "refuse", hold_setpoint: bool = False) -> LoggedData:
    """Read a bag's setpoint, input and output topics (and disturbance topic) as logged data on the model's sample grid.

    Samples are aligned by ``header.stamp``: a message belongs to sample ``k`` when its stamp is
    ``t0 + k * sample_time`` within :data:`GRID_TOLERANCE` of a sample, ``t0`` the earliest stamp of
    the topics, moved to the stamps' mean phase on the grid when that is more than 1 % of a sample off
    (:func:`_grid_origin`).  Samples before the last topic starts or after the first one ends (a recording
    started or stopped mid-sample) are dropped; inside that span a topic holds a sample at most once,
    and a sample some topic lacks is left out (a gap: ``t`` skips it).  Channels are matched by
    name, so their order in the messages is free; extra channels are ignored.  A model with
    measured disturbances reads them from the disturbance topic (the fourth of ``topics``, default
    ``disturbance``) into ``dv``.

    Parameters
    ----------
    path : str or Path
        rosbag2 directory.
    model : PlantModel
        Gives the channel names (outputs for the setpoint and output topics, inputs for the input
        topic, measured disturbances for the disturbance topic) and the sample time in seconds.
    topics : sequence of 3 or 4 str
        Setpoint, input and output topic names, and optionally the disturbance topic's (relative
        names are taken as ``/name``); a fourth name needs a model with measured disturbances.
    progress : bool or file-like
        Draw a progress bar on stderr (or on the given stream) for bags of at least
        :data:`LONG_BAG_MESSAGES` messages.
    bad_values : {"refuse", "gap"}
        A message whose values of the model's channels are not all finite: ``refuse`` the bag, naming
        the topic, the message and its stamp (the default), or leave it out (``gap``: its sample is
        missing, and the analysis goes around it), said in one note per topic.
    hold_setpoint : bool
        As the live monitor's parameter of that name, for a stack that publishes its setpoints only on change:
        every sample takes the latest setpoint message stamped at or before it (on the grid or not), instead of
        the one of its own stamp; the samples before the first setpoint message are left out.

    Returns
    -------
    LoggedData
        ``t`` in seconds, ``r`` and ``y`` of shape (n_samples, n_outputs), ``u`` of shape
        (n_samples, n_inputs), ``dv`` of shape (n_samples, n_disturbances).

    Raises
    ------
    BagError
        One line naming the bag and the topic.
    """
    topics = _check_topics(path, topics)
    channels = {"setpoint": model.outputs, "input": model.inputs, "output": model.outputs}
    if model.n_disturbances:
        channels["disturbance"] = model.disturbances
        if len(topics) == 3:
            topics.append(topic_name(DEFAULT_DISTURBANCE_TOPIC))
    elif len(topics) == 4:
        raise BagError(f"{path}: a fourth topic ({topics[3]}, measured disturbances) is given but the model has no "
                       f"measured disturbances")
    left_out = _left_out(bad_values)
    series = _read_vectors(path, topics, channels, progress, left_out=left_out)
    data = _align(path, series, model.sample_time, model.inputs, model.outputs, model.disturbances,
                  hold_setpoint=hold_setpoint)
    return _with_left_out_notes(path, data, left_out, series, model.sample_time)


def _left_out(bad_values: str):
    """The dict :func:`_read_vectors` counts the messages it leaves out in (``bad_values="gap"``), or None
    (``"refuse"``)."""
    if bad_values not in BAD_VALUES:
        raise ValueError(f"bad_values: expected one of {', '.join(BAD_VALUES)}, got {bad_values!r}")
    return {} if bad_values == "gap" else None


def _with_left_out_notes(path, data: LoggedData, left_out, series: dict, sample_time: float) -> LoggedData:
    """``data`` with a note per topic that lost messages holding a non-finite value (:func:`_left_out`).

    A message left out whose sample another message of its topic holds (sent again with finite values) is no gap:
    the note says so (it said the analysis went around every such sample as a gap)."""
    notes = []
    kept = {s.topic: s.stamps for s in series.values()}
    for topic, (n, first, stamps) in (left_out or {}).items():
        have = kept.get(topic, np.zeros(0, dtype=np.int64))
        again = 0
        if have.size:
            st = np.asarray(stamps, dtype=np.int64)
            near = np.clip(np.searchsorted(have, st), 1, have.size) - 1
            gap = np.minimum(np.abs(have[near] - st), np.abs(have[np.minimum(near + 1, have.size - 1)] - st))
            again = int(np.count_nonzero(gap <= GRID_TOLERANCE * sample_time * 1e9))
        text = (f"{path}: topic '{topic}': {n} message{'s' if n != 1 else ''} holding a non-finite value left out (the "
                f"first stamped {_seconds(first)} s)")
        if again == n:
            text += (f"; {'each was' if n != 1 else 'it was'} sent again with finite values for "
                     f"{'its' if n == 1 else 'the same'} sample, which is kept")
        else:
            gaps = n - again
            text += (f"; the analysis goes around {'their samples' if gaps != 1 else 'its sample'} as gaps"
                     if not again else f"; the analysis goes around {gaps} of their samples as gaps ({again} sent "
                     f"again with finite values for the same sample, kept)")
        notes.append(text)
    return dataclasses.replace(data, notes=tuple(notes) + data.notes) if notes else data


def infer_sample_time(path, stamps: np.ndarray, topic: str) -> float:
    """Sample time in seconds from a topic's distinct stamps (nanoseconds): the median spacing when every stamp
    lies on its grid, else the slope of the stamps over their sample numbers (gaps skip numbers).  The median
    alone takes the jitter of the steps (0.999979 s for 1 s), and ``t`` then drifted by a whole sample over a
    long bag."""
    unique = np.unique(stamps)
    diffs = np.diff(unique)
    if diffs.size == 0:
        raise BagError(f"{path}: topic '{topic}': needs at least two samples to infer the sample time "
                       f"(or give --model)")
    step = int(np.median(diffs))
    rel = unique - unique[0]
    if step <= 0 or not np.any(rel % step):         # every stamp on the median step's grid: that step, exactly
        return step / 1e9
    # Jittered stamps: the slope of the stamps over their sample numbers, taken over a span that doubles
    # (each fit's error keeps the next span's numbering right), then rounded to the nanosecond.
    ts, n = float(step), 16
    while True:
        sel = rel[rel <= n * ts]
        k = np.rint(sel / ts)
        if np.ptp(k) > 0:
            kc = k - k.mean()
            ts = float(kc @ (sel - sel.mean()) / (kc @ kc))
        if sel.size == rel.size:
            return round(ts) / 1e9
        n *= 2


def read_bag_channels(path, topics: Sequence[str] = DEFAULT_TOPICS, sample_time: Optional[float] = None,
                      progress=False, bad_values: str = "refuse", hold_setpoint: bool = False) -> LoggedData:
    """Read a bag without a model: channel names from the first messages, sample time from the stamps.

    Parameters
    ----------
    path : str or Path
    topics : sequence of 3 or 4 str
        Setpoint, input and output topic names, and the disturbance topic's: with three names the
        disturbance topic ``disturbance`` is read when the bag holds messages on it, a fourth name
        must be in the bag.
    sample_time : float, optional
        Seconds per sample; default the median stamp spacing of the output topic.
    progress : bool or file-like
    bad_values : {"refuse", "gap"}
        As :func:`read_bag`.
    hold_setpoint : bool
        As :func:`read_bag`.

    Returns
    -------
    LoggedData
    """
    topics = _check_topics(path, topics)
    optional = len(topics) == 3
    if optional:
        topics.append(topic_name(DEFAULT_DISTURBANCE_TOPIC))
    left_out = _left_out(bad_values)
    series = _read_vectors(path, topics, None, progress, optional=optional, left_out=left_out)
    if sample_time is None:
        sample_time = infer_sample_time(path, series["output"].stamps, series["output"].topic)
        _refuse_faster_topics(path, series, sample_time)
    dv = series.get("disturbance")
    data = _align(path, series, sample_time, series["input"].names, series["output"].names,
                  dv.names if dv is not None else (), hold_setpoint=hold_setpoint)
    return _with_left_out_notes(path, data, left_out, series, sample_time)


def _refuse_faster_topics(path, series: dict, sample_time: float) -> None:
    """Refuse a bag whose setpoint, input or disturbance topic sends at least 1.5 times as often as its output
    topic, whose spacing set the sample time ``sample_time`` (s) without a model (a recorder that kept every
    other output message: the faster topic's stamps were then refused as off the grid, without the reason).

    Raises
    ------
    BagError
        Naming the topic, both spacings and ``--model``.
    """
    out = series["output"].topic
    for role in ("setpoint", "input", "disturbance"):
        s = series.get(role)
        diffs = np.diff(np.unique(s.stamps)) if s is not None else np.zeros(0)
        if diffs.size and 1.5 * float(np.median(diffs)) <= sample_time * 1e9:
            raise BagError(f"{path}: topic '{s.topic}' sends every {_seconds(int(np.median(diffs)))} s, the output "
                           f"topic '{out}' every {_seconds(int(round(sample_time * 1e9)))} s: without a model the "
                           f"output's spacing is the sample time; give --model for the loop's own (the output's "
                           f"missing samples are then gaps)")


def export_csv(bag, csv, model_path=None, topics: Sequence[str] = DEFAULT_TOPICS, progress=False,
               warn=None, bad_values: str = "refuse", hold_setpoint: bool = False) -> int:
    """Write a bag's setpoint, input, output (and disturbance) topics as a CSV log.

    The format is that of docs/interfaces.md, "Logged data (CSV)".

    Parameters
    ----------
    bag : str or Path
        rosbag2 directory.
    csv : str or Path
        Output CSV file.
    model_path : str or Path, optional
        Model file giving the channel names, their order and the sample time.  Without it the
        names come from the first messages and the sample time from the stamps.
    topics : sequence of 3 or 4 str
        As :func:`read_bag` (with a model) or :func:`read_bag_channels` (without).
    progress : bool or file-like
    warn : callable, optional
        Called with each of the reader's notes (:attr:`~mpm_monitor.core.logged_data.LoggedData.notes`,
        for example messages left out for an unset stamp), one line each.
    bad_values : {"refuse", "gap"}
        As :func:`read_bag`: with ``gap`` a message holding a non-finite value is left out, and its
        sample is missing from the CSV (``t`` skips it).
    hold_setpoint : bool
        As :func:`read_bag`: every sample takes the latest setpoint message stamped at or before it.

    Returns
    -------
    int
        Number of samples written.
    """
    if model_path is not None:
        from ..model_file import load_model

        data = read_bag(bag, load_model(model_path), topics=topics, progress=progress, bad_values=bad_values,
                        hold_setpoint=hold_setpoint)
    else:
        data = read_bag_channels(bag, topics=topics, progress=progress, bad_values=bad_values,
                                 hold_setpoint=hold_setpoint)
    try:
        write_log_csv(csv, data)
    except OSError as exc:
        raise InputError(f"{csv}: cannot write CSV file: {exc.strerror or exc}") from None
    for note in data.notes if warn is not None else ():
        warn(note)
    if warn is not None and model_path is not None and len(data.segments) > 1:
        warn(_gaps_note(data))
    return data.n_samples


def _gaps_note(data) -> str:
    """What an exported log's gaps on the model's sample grid are: their count and the samples missing, and where
    every sample follows a gap (a model of the wrong sample time: ``analyze`` refuses such a log), the median step
    of the bag's stamps."""
    import numpy as np

    from ...core.gaps import plan_gaps

    plan = plan_gaps(data, 0)          # the gaps as the analysis counts them
    n_gaps, ts = int(plan.gap_lengths.size), float(data.sample_time)
    text = f"{n_gaps} gap{'s' if n_gaps != 1 else ''} in the samples on the model's grid of {ts:g} s " \
           f"({plan.samples_missing} missing)"
    if all(b - a == 1 for a, b in data.segments):
        step = float(np.median(np.diff(np.asarray(data.t, dtype=float))))
        return (f"{text}: every sample follows a gap, the bag's stamps a median {step:g} s apart: is the model's "
                f"sample_time right? (analyze refuses such a log)")
    return f"{text}: the analysis goes around them (nothing is interpolated)"


@dataclasses.dataclass(frozen=True)
class RawMessage:
    """A serialized message of a bag, for replay.

    Attributes
    ----------
    topic : str
        Topic name in the bag (fully qualified).
    msgtype : str
        ``pkg/msg/Type``.
    log_time : int
        Time the recorder received it, nanoseconds.
    stamp : int or None
        ``header.stamp`` in nanoseconds for messages with a header, else None.
    data : bytes
        CDR bytes as recorded.
    """

    topic: str
    msgtype: str
    log_time: int
    stamp: Optional[int]
    data: bytes


def read_raw_messages(bag, topics: Sequence[str] = DEFAULT_TOPICS, optional: Sequence[str] = ()) -> list:
    """The serialized messages of some topics in recording order, with their header stamps.

    Parameters
    ----------
    bag : str or Path
    topics : sequence of str
        Topic names; each must be in the bag.
    optional : sequence of str
        Further topic names, read when the bag has them (e.g. ``disturbance``).

    Returns
    -------
    list of RawMessage

    Raises
    ------
    BagError
        A topic missing, a damaged storage file, or a topic that ``metadata.yaml`` counts messages on
        but none of whose messages can be read (:func:`~mpm_monitor.io.bags.common.none_read`).
    """
    out = []
    with closing(open_reader(bag)) as reader:
        conns = []
        for required, t in [(True, t) for t in topics] + [(False, t) for t in optional]:
            t = topic_name(t)
            found = [c for c in reader.connections if topic_name(c.topic) == t]
            if not found and not required:
                continue
            if not found:
                have = shown_names(sorted({c.topic for c in reader.connections})) or "none"
                raise BagError(f"{bag}: no topic '{t}' in the bag; topics in the bag: {have}")
            conns += found
        try:
            for conn, log_time, raw in reader.messages(connections=conns):
                raw = bytes(raw)
                msg = reader.deserialize(raw, conn.msgtype)
                header = getattr(msg, "header", None)
                stamp = stamp_ns(header.stamp) if header is not None and hasattr(header, "stamp") else None
                out.append(RawMessage(conn.topic, conn.msgtype, int(log_time), stamp, raw))
        except Exception as exc:
            raise BagError(f"{bag}: cannot read bag: {read_failure(exc)}") from None
    read = {m.topic for m in out}
    for t in dict.fromkeys(c.topic for c in conns if c.msgcount):     # the topics the metadata counts
        if t not in read:
            raise none_read(bag, t, conns)
    return out

