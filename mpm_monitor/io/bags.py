"""rosbag2 recordings of the contract topics (CONTRACTS section 4): read, align, export and write.

A bag holds the stamped vectors ``setpoint``, ``input`` and ``output`` (``sensor_msgs/msg/JointState``:
``header.stamp`` = sample time, ``name`` = channel names, ``position`` = values).  :func:`read_bag`
aligns them by stamp on the model's sample grid into a :class:`~mpm_monitor.core.logged_data.LoggedData`, so
``analyze --bag`` and ``analyze --data`` see the same samples.  Anything that would silently
mis-align the samples (a missing topic, wrong channel names, a gap, two messages for one sample) is
refused with a :class:`~mpm_monitor.core.errors.BagError` of one line naming the bag and the topic.

:class:`BagWriter` writes a rosbag2 directory (MCAP storage, metadata version 9) message by message
from serialized CDR bytes and can flush complete MCAP chunks to disk while recording; the
recorder node wraps it.

This module uses the ``rosbags`` library only; it never imports rclpy.
"""

from __future__ import annotations

import dataclasses
import os
import struct
import sys
from contextlib import closing
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np

from ..core.errors import BagError, InputError
from ..core.logged_data import LoggedData
from ..core.model import FopdtModel
from .csv_log import write_csv

#: Default names of the setpoint, input and output topics.
DEFAULT_TOPICS = ("setpoint", "input", "output")
#: Message type of the stamped vectors.
JOINT_STATE = "sensor_msgs/msg/JointState"
#: Message type of ``/diagnostics``.
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
#: A stamp may lie this fraction of the sample time off the sample grid and still be aligned.
GRID_TOLERANCE = 0.1
#: Bags with at least this many messages on the read topics get a progress bar (``progress=True``).
LONG_BAG_MESSAGES = 20_000

_ROLES = ("setpoint", "input", "output")


def topic_name(name: str) -> str:
    """The fully qualified form of a topic name as stored in a bag (``setpoint`` -> ``/setpoint``)."""
    name = str(name).strip()
    return name if name.startswith("/") else "/" + name


def default_typestore():
    """The ``rosbags`` type store of ROS 2 Jazzy (holds every message type the project records)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


# ----------------------------------------------------------------------------------------------------
# Reading


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


def open_reader(path):
    """Open a rosbag2 directory with :class:`rosbags.highlevel.AnyReader`.

    Parameters
    ----------
    path : str or Path
        The bag directory (holding ``metadata.yaml`` and the storage file).

    Returns
    -------
    rosbags.highlevel.AnyReader
        Open; close it (``with contextlib.closing(open_reader(path)) as reader``).

    Raises
    ------
    BagError
        The directory is missing, empty, has no ``metadata.yaml`` or cannot be read (a truncated or
        unclosed storage file).
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag directory")
    if not path.is_dir():
        raise BagError(f"{path}: not a directory: expected a rosbag2 directory (metadata.yaml + storage file)")
    if not any(path.iterdir()):
        raise BagError(f"{path}: empty directory: expected a rosbag2 directory (metadata.yaml + storage file)")
    if not (path / "metadata.yaml").is_file():
        raise BagError(f"{path}: no metadata.yaml: not a rosbag2 directory, or its recorder was killed before "
                       f"closing it (mpm_monitor.io.bags.recover_bag rewrites what it flushed)")
    reader = AnyReader([path], default_typestore=default_typestore())
    try:
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated classes for damaged bags
        raise BagError(f"{path}: cannot read bag: {_one_line(exc)} (truncated or not closed properly?)") from None
    return reader


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def _connections(reader, path, topic: str, msgtype: str) -> list:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise BagError(f"{path}: no topic '{topic}' ({msgtype}) in the bag; topics in the bag: {have}")
    for c in conns:
        if c.msgtype != msgtype:
            raise BagError(f"{path}: topic '{topic}' has type {c.msgtype}, expected {msgtype}")
    if sum(c.msgcount for c in conns) == 0:
        raise BagError(f"{path}: topic '{topic}' holds no messages")
    return conns


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclasses.dataclass
class _Series:
    """The messages of one stamped-vector topic, sorted by stamp."""

    topic: str
    names: tuple                # channel names of the first message
    stamps: np.ndarray          # (n,) int64 nanoseconds
    values: np.ndarray          # (n, len(channels)) values reordered to ``channels``


def _read_vectors(path, topics: Sequence[str], channels: Optional[dict], progress) -> dict:
    """Read the three stamped-vector topics; ``channels[role]`` = expected names or None (= first message's)."""
    topics = [topic_name(t) for t in topics]
    if len(topics) != 3:
        raise BagError(f"{path}: expected three topics (setpoint, input, output), got {len(topics)}")
    if len(set(topics)) != 3:
        raise BagError(f"{path}: the setpoint, input and output topics must differ, got {', '.join(topics)}")
    role_of = dict(zip(topics, _ROLES))
    with closing(open_reader(path)) as reader:
        conns = []
        for t in topics:
            conns += _connections(reader, path, t, JOINT_STATE)
        total = sum(c.msgcount for c in conns)
        stream = (sys.stderr if progress is True else progress) if progress else None
        bar = _Progress(total, stream, f"reading {Path(path).name}") if stream and total >= LONG_BAG_MESSAGES else None
        expected = dict(channels) if channels is not None else _first_names(reader, path, topics)
        index_cache: dict = {}
        stamps = {t: [] for t in topics}
        rows = {t: [] for t in topics}
        done = 0
        try:
            for conn, _, raw in reader.messages(connections=conns):
                topic = conn.topic
                role = role_of[topic]
                count = len(stamps[topic]) + 1
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    raise BagError(f"{path}: topic '{topic}': message {count} cannot be decoded as {JOINT_STATE}: "
                                   f"{_one_line(exc)}") from None
                names = tuple(msg.name)
                stamp = _stamp_ns(msg.header.stamp)
                values = np.asarray(msg.position, dtype=float)
                if values.shape != (len(names),):
                    raise BagError(f"{path}: topic '{topic}': message {count} (stamp {stamp / 1e9:g} s) has "
                                   f"{values.size} positions for {len(names)} names")
                key = (role, names)
                idx = index_cache.get(key)
                if idx is None:
                    want = tuple(expected[role])
                    missing = [n for n in want if n not in names]
                    if missing or len(set(names)) != len(names):
                        what = {"setpoint": "outputs", "input": "inputs", "output": "outputs"}[role]
                        raise BagError(
                            f"{path}: topic '{topic}': message {count} (stamp {stamp / 1e9:g} s) has channel names "
                            f"[{', '.join(names)}], expected the {what} [{', '.join(want)}]")
                    idx = np.array([names.index(n) for n in want], dtype=int)
                    index_cache[key] = idx
                if not np.all(np.isfinite(values[idx])):
                    raise BagError(f"{path}: topic '{topic}': message {count} (stamp {stamp / 1e9:g} s) holds a "
                                   f"non-finite value")
                stamps[topic].append(stamp)
                rows[topic].append(values[idx])
                done += 1
                if bar is not None and done % 256 == 0:
                    bar.update(done)
        except BagError:
            raise
        except Exception as exc:  # damaged chunk inside an otherwise valid file
            raise BagError(f"{path}: cannot read bag: {_one_line(exc)}") from None
        if bar is not None:
            bar.finish()
    series = {}
    for t, role in zip(topics, _ROLES):
        st = np.array(stamps[t], dtype=np.int64)
        vals = np.array(rows[t], dtype=float).reshape(len(st), len(expected[role]))
        order = np.argsort(st, kind="stable")
        series[role] = _Series(t, tuple(expected[role]), st[order], vals[order])
    return series


def _first_names(reader, path, topics) -> dict:
    """Channel names of the first input and output messages (a bag read without a model)."""
    names = {}
    for role, topic in (("input", topics[1]), ("output", topics[2])):
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            try:
                names[role] = tuple(reader.deserialize(raw, conn.msgtype).name)
            except Exception as exc:
                raise BagError(f"{path}: topic '{topic}': message 1 cannot be decoded as {JOINT_STATE}: "
                               f"{_one_line(exc)}") from None
            break
    names["setpoint"] = names["output"]
    return names


def _align(path, series: dict, sample_time: float, inputs, outputs) -> LoggedData:
    """Put the three topics on one sample grid and check that every sample is there exactly once."""
    ts_ns = sample_time * 1e9
    origin = min(int(s.stamps[0]) for s in series.values())
    ks = {}
    for role, s in series.items():
        rel = (s.stamps - origin).astype(float)
        k = np.rint(rel / ts_ns).astype(np.int64)
        off = np.abs(rel - k * ts_ns) > GRID_TOLERANCE * ts_ns
        if np.any(off):
            i = int(np.flatnonzero(off)[0])
            raise BagError(f"{path}: topic '{s.topic}': stamp {s.stamps[i] / 1e9:.9g} s is off the sample grid "
                           f"(sample_time {sample_time:g} s from {origin / 1e9:.9g} s, tolerance "
                           f"{GRID_TOLERANCE:g} sample)")
        dup = np.flatnonzero(np.diff(k) == 0)
        if dup.size:
            i = int(dup[0])
            raise BagError(f"{path}: topic '{s.topic}': duplicate stamp: two messages for the sample at "
                           f"{s.stamps[i] / 1e9:.9g} s and {s.stamps[i + 1] / 1e9:.9g} s")
        ks[role] = k
    k_first = max(int(k[0]) for k in ks.values())
    k_last = min(int(k[-1]) for k in ks.values())
    if k_last < k_first:
        spans = "; ".join(f"'{s.topic}' {s.stamps[0] / 1e9:g}..{s.stamps[-1] / 1e9:g} s" for s in series.values())
        raise BagError(f"{path}: the topics do not overlap in time ({spans})")
    n = k_last - k_first + 1
    out = {}
    for role, s in series.items():
        k = ks[role]
        sel = (k >= k_first) & (k <= k_last)
        kk = k[sel]
        if kk.size != n:
            expect = np.arange(k_first, k_last + 1)
            missing = np.setdiff1d(expect, kk)
            m = int(missing[0])
            nmiss = int(missing.size)
            raise BagError(f"{path}: topic '{s.topic}': gap: no message for the sample at "
                           f"{(origin + m * ts_ns) / 1e9:.9g} s ({nmiss} sample{'s' if nmiss > 1 else ''} missing "
                           f"between {(origin + k_first * ts_ns) / 1e9:.9g} s and "
                           f"{(origin + k_last * ts_ns) / 1e9:.9g} s)")
        out[role] = s.values[sel]
    t = (origin + np.arange(k_first, k_last + 1) * ts_ns) / 1e9
    return LoggedData(t=t, r=out["setpoint"], u=out["input"], y=out["output"], inputs=tuple(inputs),
                      outputs=tuple(outputs), sample_time=float(sample_time), source=str(path))


def read_bag(path, model: FopdtModel, topics: Sequence[str] = DEFAULT_TOPICS, progress=False) -> LoggedData:
    """Read a bag's setpoint, input and output topics as logged data on the model's sample grid.

    Samples are aligned by ``header.stamp``: a message belongs to sample ``k`` when its stamp is
    ``t0 + k * sample_time`` within :data:`GRID_TOLERANCE` of a sample, ``t0`` the earliest stamp of
    the three topics.  Samples before the last topic starts or after the first one ends (a
    recording started or stopped mid-sample) are dropped; inside that span every topic must hold
    every sample exactly once.  Channels are matched by name, so their order in the messages is
    free; extra channels are ignored.

    Parameters
    ----------
    path : str or Path
        rosbag2 directory.
    model : FopdtModel
        Gives the channel names (outputs for the setpoint and output topics, inputs for the input
        topic) and the sample time in seconds.
    topics : sequence of 3 str
        Setpoint, input and output topic names (relative names are taken as ``/name``).
    progress : bool or file-like
        Draw a progress bar on stderr (or on the given stream) for bags of at least
        :data:`LONG_BAG_MESSAGES` messages.

    Returns
    -------
    LoggedData
        ``t`` in seconds, ``r`` and ``y`` of shape (n_samples, n_outputs), ``u`` of shape
        (n_samples, n_inputs).

    Raises
    ------
    BagError
        One line naming the bag and the topic.
    """
    channels = {"setpoint": model.outputs, "input": model.inputs, "output": model.outputs}
    series = _read_vectors(path, topics, channels, progress)
    return _align(path, series, model.sample_time, model.inputs, model.outputs)


def infer_sample_time(path, stamps: np.ndarray, topic: str) -> float:
    """Sample time in seconds as the median spacing of a topic's distinct stamps (nanoseconds)."""
    diffs = np.diff(np.unique(stamps))
    if diffs.size == 0:
        raise BagError(f"{path}: topic '{topic}': needs at least two samples to infer the sample time "
                       f"(or give --model)")
    return float(np.median(diffs)) / 1e9


def read_bag_channels(path, topics: Sequence[str] = DEFAULT_TOPICS, sample_time: Optional[float] = None,
                      progress=False) -> LoggedData:
    """Read a bag without a model: channel names from the first messages, sample time from the stamps.

    Parameters
    ----------
    path : str or Path
    topics : sequence of 3 str
        Setpoint, input and output topic names.
    sample_time : float, optional
        Seconds per sample; default the median stamp spacing of the output topic.
    progress : bool or file-like

    Returns
    -------
    LoggedData
    """
    series = _read_vectors(path, topics, None, progress)
    if sample_time is None:
        sample_time = infer_sample_time(path, series["output"].stamps, series["output"].topic)
    return _align(path, series, sample_time, series["input"].names, series["output"].names)


def export_csv(bag, csv, model_path=None, topics: Sequence[str] = DEFAULT_TOPICS, progress=False) -> int:
    """Write a bag's setpoint, input and output topics as the contract CSV (CONTRACTS section 2).

    Parameters
    ----------
    bag : str or Path
        rosbag2 directory.
    csv : str or Path
        Output CSV file.
    model_path : str or Path, optional
        Model file giving the channel names, their order and the sample time.  Without it the
        names come from the first messages and the sample time from the stamps.
    topics : sequence of 3 str
    progress : bool or file-like

    Returns
    -------
    int
        Number of samples written.
    """
    if model_path is not None:
        from .model_file import load_model

        data = read_bag(bag, load_model(model_path), topics=topics, progress=progress)
    else:
        data = read_bag_channels(bag, topics=topics, progress=progress)
    try:
        write_csv(csv, data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    except OSError as exc:
        raise InputError(f"{csv}: cannot write CSV file: {exc.strerror or exc}") from None
    return data.n_samples


@dataclasses.dataclass(frozen=True)
class RecordedStatus:
    """One ``diagnostic_msgs/msg/DiagnosticStatus`` of a recorded ``DiagnosticArray``.

    Attributes
    ----------
    stamp : float
        ``header.stamp`` of the array, seconds.
    log_time : int
        Time the recorder received the array, nanoseconds.
    name, message, hardware_id : str
    level : int
        0 OK, 1 WARN, 2 ERROR, 3 STALE.
    values : dict of str -> str
        The key/value pairs, in message order.
    """

    stamp: float
    log_time: int
    name: str
    level: int
    message: str
    hardware_id: str
    values: dict


def read_diagnostics(bag, topic: str = "/diagnostics") -> list:
    """Every status of every recorded ``DiagnosticArray``, in recording order.

    Parameters
    ----------
    bag : str or Path
    topic : str

    Returns
    -------
    list of RecordedStatus
    """
    topic = topic_name(topic)
    out = []
    with closing(open_reader(bag)) as reader:
        conns = _connections(reader, bag, topic, DIAGNOSTIC_ARRAY)
        try:
            for conn, log_time, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = _stamp_ns(msg.header.stamp) / 1e9
                for st in msg.status:
                    level = st.level
                    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
                    out.append(RecordedStatus(stamp=stamp, log_time=int(log_time), name=st.name, level=level,
                                              message=st.message, hardware_id=st.hardware_id,
                                              values={kv.key: kv.value for kv in st.values}))
        except Exception as exc:
            raise BagError(f"{bag}: topic '{topic}': cannot read: {_one_line(exc)}") from None
    return out


ROW_STATUS_PREFIX = "mpm_monitor: row "


def live_located_elements(statuses: Sequence[RecordedStatus]) -> dict:
    """The monitor's latest verdict per row, from recorded diagnostics (CONTRACTS section 4).

    Parameters
    ----------
    statuses : sequence of RecordedStatus
        As returned by :func:`read_diagnostics`, in recording order.

    Returns
    -------
    dict
        ``{"rows": {output: mismatch (bool)}, "located": set of (output, input)}`` from the last
        ``mpm_monitor: row <output>`` status of every output (``mismatch`` and ``flagged_inputs``
        values).
    """
    last = {}
    for st in statuses:
        if st.name.startswith(ROW_STATUS_PREFIX):
            last[st.name[len(ROW_STATUS_PREFIX):]] = st
    rows = {out: st.values.get("mismatch", "").strip().lower() == "true" for out, st in last.items()}
    located = {(out, inp.strip()) for out, st in last.items()
               for inp in st.values.get("flagged_inputs", "").split(",") if inp.strip()}
    return {"rows": rows, "located": located}


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


def read_raw_messages(bag, topics: Sequence[str] = DEFAULT_TOPICS) -> list:
    """The serialized messages of some topics in recording order, with their header stamps.

    Parameters
    ----------
    bag : str or Path
    topics : sequence of str
        Topic names; each must be in the bag.

    Returns
    -------
    list of RawMessage
    """
    out = []
    with closing(open_reader(bag)) as reader:
        conns = []
        for t in topics:
            t = topic_name(t)
            found = [c for c in reader.connections if c.topic == t]
            if not found:
                have = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
                raise BagError(f"{bag}: no topic '{t}' in the bag; topics in the bag: {have}")
            conns += found
        try:
            for conn, log_time, raw in reader.messages(connections=conns):
                raw = bytes(raw)
                msg = reader.deserialize(raw, conn.msgtype)
                header = getattr(msg, "header", None)
                stamp = _stamp_ns(header.stamp) if header is not None and hasattr(header, "stamp") else None
                out.append(RawMessage(conn.topic, conn.msgtype, int(log_time), stamp, raw))
        except Exception as exc:
            raise BagError(f"{bag}: cannot read bag: {_one_line(exc)}") from None
    return out


# ----------------------------------------------------------------------------------------------------
# Writing


class BagWriter:
    """Write a rosbag2 directory (MCAP storage, metadata version 9) from serialized messages.

    Topics are added with the QoS profiles their publishers offered; messages are written as the
    CDR bytes received.  :meth:`flush` closes the pending MCAP chunk and writes it to disk, so a
    process that dies later leaves every message up to the last flush in complete chunk records
    on disk; :meth:`close` writes the MCAP summary and ``metadata.yaml`` (without it, readers
    refuse the bag).

    Parameters
    ----------
    path : str or Path
        Bag directory to create; it must not exist.
    typestore : rosbags type store, optional
        Gives message definitions and type hashes; default :func:`default_typestore`.
    fsync : bool
        Also ask the OS to write flushed data to the device (survives a power loss).

    Raises
    ------
    BagError
        The directory exists already or cannot be created.
    """

    def __init__(self, path, typestore=None, fsync: bool = True):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self._typestore = typestore or default_typestore()
        self._fsync = fsync
        if self.path.exists():
            raise BagError(f"{self.path}: exists already: give a new bag directory (a bag is never overwritten)")
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
        except Exception as exc:
            raise BagError(f"{self.path}: cannot create bag: {_one_line(exc)}") from None
        self._connections: dict = {}
        self.message_count = 0
        self.flushed_count = 0
        self.closed = False

    def has_topic(self, topic: str) -> bool:
        """Whether :meth:`add_topic` was called for ``topic``."""
        return topic in self._connections

    @property
    def topics(self) -> dict:
        """Topic name -> message type of the topics added so far."""
        return {t: c.msgtype for t, c in self._connections.items()}

    def add_topic(self, topic: str, msgtype: str, qos_profiles: Sequence = ()) -> None:
        """Register a topic.

        Parameters
        ----------
        topic : str
            Fully qualified topic name.
        msgtype : str
            ``pkg/msg/Type``; must be known to the type store.
        qos_profiles : sequence of rosbags.interfaces.Qos
            The QoS profiles offered by the topic's publishers (``offered_qos_profiles``).
        """
        if self.closed:
            raise BagError(f"{self.path}: bag is closed")
        if topic in self._connections:
            raise BagError(f"{self.path}: topic '{topic}' added twice")
        if msgtype not in self._typestore.types:
            raise BagError(f"{self.path}: topic '{topic}': unknown message type {msgtype}")
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=self._typestore, serialization_format="cdr",
            offered_qos_profiles=list(qos_profiles))

    def write(self, topic: str, timestamp: int, data: bytes) -> None:
        """Append one serialized message.

        Parameters
        ----------
        topic : str
            A topic added with :meth:`add_topic`.
        timestamp : int
            Receive time, nanoseconds.
        data : bytes
            CDR bytes (with the 4-byte encapsulation header).
        """
        if self.closed:
            raise BagError(f"{self.path}: bag is closed")
        self._writer.write(self._connections[topic], int(timestamp), bytes(data))
        self.message_count += 1

    def flush(self) -> int:
        """Close the pending MCAP chunk and write it to disk.

        Returns
        -------
        int
            Messages on disk so far (all messages written before this call).
        """
        if self.closed or self.message_count == self.flushed_count:
            return self.flushed_count
        storage = self._writer.storage
        # rosbags 0.11 keeps the current chunk in memory until it reaches 1 MiB; closing it early
        # writes a complete chunk record (messages + message index) after the previous ones.
        storage.close_chunk()
        storage.bio.flush()
        if self._fsync:
            os.fsync(storage.bio.fileno())
        self.flushed_count = self.message_count
        return self.flushed_count

    def close(self) -> None:
        """Write the pending messages, the MCAP summary and ``metadata.yaml``.  Idempotent."""
        if self.closed:
            return
        self.closed = True
        self._writer.close()
        self.flushed_count = self.message_count


def joint_state_cdr(typestore, stamp_ns: int, names: Sequence[str], values) -> bytes:
    """A ``sensor_msgs/msg/JointState`` stamped vector as CDR bytes (``velocity``/``effort`` empty)."""
    js = typestore.types[JOINT_STATE]
    header = typestore.types["std_msgs/msg/Header"]
    time_t = typestore.types["builtin_interfaces/msg/Time"]
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    msg = js(header=header(stamp=time_t(sec=sec, nanosec=nsec), frame_id=""), name=list(names),
             position=np.asarray(values, dtype=np.float64), velocity=np.zeros(0), effort=np.zeros(0))
    return bytes(typestore.serialize_cdr(msg, JOINT_STATE))


def write_logged_data(path, data: LoggedData, topics: Sequence[str] = DEFAULT_TOPICS, qos_profiles=None) -> int:
    """Write logged data as a bag of the three stamped-vector topics (the inverse of :func:`read_bag`).

    Sample ``k`` becomes one message per topic stamped ``t[k]``, published in the loop's order
    (output, input, setpoint) and logged at the stamp.

    Parameters
    ----------
    path : str or Path
        Bag directory to create.
    data : LoggedData
    topics : sequence of 3 str
        Setpoint, input and output topic names.
    qos_profiles : sequence of rosbags Qos, optional
        Offered QoS stored for each topic; default the contract's vector QoS (RELIABLE, KEEP_LAST
        1000, VOLATILE).

    Returns
    -------
    int
        Messages written.
    """
    ts = default_typestore()
    if qos_profiles is None:
        qos_profiles = [contract_vector_qos()]
    setpoint, inp, out = (topic_name(t) for t in topics)
    writer = BagWriter(path, typestore=ts, fsync=False)
    try:
        for t in (out, inp, setpoint):
            writer.add_topic(t, JOINT_STATE, qos_profiles)
        stamps = np.rint(np.asarray(data.t, dtype=float) * 1e9).astype(np.int64)
        for k, stamp in enumerate(stamps):
            writer.write(out, stamp, joint_state_cdr(ts, stamp, data.outputs, data.y[k]))
            writer.write(inp, stamp + 1, joint_state_cdr(ts, stamp, data.inputs, data.u[k]))
            writer.write(setpoint, stamp + 2, joint_state_cdr(ts, stamp, data.outputs, data.r[k]))
    finally:
        writer.close()
    return writer.message_count


def contract_vector_qos():
    """The vector topics' QoS (RELIABLE, KEEP_LAST 1000, VOLATILE) as a rosbags ``Qos``."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(9223372036, 854775807)
    return Qos(history=QosHistory.KEEP_LAST, depth=1000, reliability=QosReliability.RELIABLE,
               durability=QosDurability.VOLATILE, deadline=infinite, lifespan=infinite,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=infinite,
               avoid_ros_namespace_conventions=False)


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _mcap_string(buf: bytes, pos: int) -> tuple:
    (n,) = struct.unpack_from("<I", buf, pos)
    return buf[pos + 4:pos + 4 + n], pos + 4 + n


def _mcap_records(buf: bytes, pos: int, end: int) -> Iterator[tuple]:
    """``(opcode, body)`` of the complete records in ``buf[pos:end]``; stops at a torn record."""
    while pos + 9 <= end:
        op = buf[pos]
        (size,) = struct.unpack_from("<Q", buf, pos + 1)
        body_end = pos + 9 + size
        if body_end > end:
            return
        yield op, buf[pos + 9:body_end]
        pos = body_end


def recover_bag(src, dst) -> int:
    """Rewrite what a hard-killed recorder left on disk as a new, properly closed bag.

    A recorder killed by SIGKILL or a power loss leaves an MCAP file without summary or footer and
    no ``metadata.yaml``; every chunk it flushed is complete on disk.  This reads those complete
    chunk records (a torn last record is dropped) and writes their messages, in order and with the
    recorded QoS profiles, to ``dst``.

    Parameters
    ----------
    src : str or Path
        The unclosed bag directory.
    dst : str or Path
        New bag directory (must not exist).

    Returns
    -------
    int
        Messages recovered.

    Raises
    ------
    BagError
        No MCAP file, not an MCAP file, or compressed chunks.
    """
    from rosbags.rosbag2.storage_mcap import get_qos

    src = Path(src)
    files = sorted(src.glob("*.mcap")) if src.is_dir() else []
    if not files:
        raise BagError(f"{src}: no .mcap file to recover")
    buf = files[0].read_bytes()
    if buf[:8] != _MCAP_MAGIC:
        raise BagError(f"{files[0]}: not an MCAP file (bad magic)")
    schemas, channels, messages = {}, {}, []

    def take(op, body):
        if op == 0x03:
            (sid,) = struct.unpack_from("<H", body, 0)
            name, _ = _mcap_string(body, 2)
            schemas[sid] = name.decode()
        elif op == 0x04:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, pos = _mcap_string(body, 4)
            _, pos = _mcap_string(body, pos)  # message encoding
            metadata, _ = _mcap_string(body, pos)
            channels[cid] = (topic.decode(), schemas.get(sid, ""), get_qos(metadata))
        elif op == 0x05:
            cid, _, log_time, _ = struct.unpack_from("<HIQQ", body, 0)
            messages.append((cid, log_time, body[22:]))

    for op, body in _mcap_records(buf, 8, len(buf)):
        if op == 0x06:
            pos = 28
            compression, pos = _mcap_string(body, pos)
            if compression:
                raise BagError(f"{files[0]}: compressed chunks ({compression.decode()}) cannot be recovered")
            (size,) = struct.unpack_from("<Q", body, pos)
            inner = body[pos + 8:pos + 8 + size]
            for op2, body2 in _mcap_records(inner, 0, len(inner)):
                take(op2, body2)
        elif op in (0x0F, 0x02):  # data end, footer: the file was closed after all
            break
        else:
            take(op, body)
    writer = BagWriter(dst, fsync=False)
    try:
        for cid, log_time, data in messages:
            topic, msgtype, qos = channels[cid]
            if not writer.has_topic(topic):
                writer.add_topic(topic, msgtype, qos)
            writer.write(topic, log_time, data)
    finally:
        writer.close()
    return writer.message_count


def iter_topic_messages(bag, topic: str) -> Iterator[tuple]:
    """``(log_time_ns, message)`` of one topic, deserialized with rosbags (for tests and tools)."""
    topic = topic_name(topic)
    with closing(open_reader(bag)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise BagError(f"{bag}: no topic '{topic}' in the bag")
        for conn, log_time, raw in reader.messages(connections=conns):
            yield int(log_time), reader.deserialize(raw, conn.msgtype)
