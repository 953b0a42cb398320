"""Writing a bag: :class:`BagWriter` (rosbag2, MCAP storage) and logged data as a bag.

:class:`BagWriter` writes a rosbag2 directory (MCAP storage, metadata version 9) message by message
from serialized CDR bytes and can flush complete MCAP chunks to disk while recording; the
recorder node wraps it.  :func:`write_logged_data` is the inverse of
:func:`~mpm_monitor.io.bags.read.read_bag`.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from ...core.errors import BagError
from ...core.logged_data import LoggedData
from ..qos import VECTOR_QOS, rosbags_qos
from .common import DEFAULT_DISTURBANCE_TOPIC, DEFAULT_TOPICS, JOINT_STATE, default_typestore, one_line, topic_name
from .mcap_records import CHUNK, CHUNK_CRC_OFFSET, DATA_END, MAGIC, chunk_parts


class BagWriter:
    """Write a rosbag2 directory (MCAP storage, metadata version 9) from serialized messages.

    Topics are added with the QoS profiles their publishers offered; messages are written as the
    CDR bytes received.  :meth:`flush` closes the pending MCAP chunk and writes it to disk, so a
    process that dies later leaves every message up to the last flush in complete chunk records
    on disk; :meth:`close` writes the MCAP summary and ``metadata.yaml`` (without it, readers
    refuse the bag) and every chunk's CRC (:func:`write_chunk_crcs`).

    Split storage (``split_bytes`` or ``split_seconds``), as ``ros2 bag record --max-bag-size`` and
    ``--max-bag-duration`` do: the storage files are ``<name>_0.mcap``, ``<name>_1.mcap``, ... in the
    bag directory.  At the first :meth:`flush` after the current file holds ``split_bytes`` bytes or
    its messages span ``split_seconds`` (their timestamps), the file is closed (summary and CRCs: it
    reads on its own) and the next message begins the next one.  A writer that runs for months
    then keeps neither one ever-growing file nor its index in memory (an MCAP writer keeps a chunk
    index entry per flush until its file closes), and a hard kill leaves closed files and one
    unclosed one, which :func:`~mpm_monitor.io.bags.recover_bag` reads in order.  The file being
    written is created as ``.split_<k>/.split_<k>.mcap`` and moved to its name at once; the
    ``.split_<k>`` directory, empty, is removed when the file closes.  Without either limit, the bag
    holds one storage file, ``<name>.mcap``.

    Parameters
    ----------
    path : str or Path
        Bag directory to create; it must not exist.
    typestore : rosbags type store, optional
        Gives message definitions and type hashes; default :func:`default_typestore`.
    fsync : bool
        Also ask the OS to write flushed data to the device (survives a power loss).
    split_bytes : int
        Begin a new storage file at the first flush after the current one reaches this many bytes;
        0: no size limit.
    split_seconds : float
        Begin a new storage file at the first flush after the current one's messages span this many
        seconds; 0: no duration limit.

    Raises
    ------
    BagError
        The directory exists already or cannot be created, or a limit is negative.
    """

    def __init__(self, path, typestore=None, fsync: bool = True, split_bytes: int = 0, split_seconds: float = 0.0):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self._typestore = typestore or default_typestore()
        self._fsync = fsync
        if not (split_bytes >= 0 and split_seconds >= 0):
            raise BagError(f"{self.path}: split limits must be 0 (none) or positive, got {split_bytes!r} bytes and "
                           f"{split_seconds!r} s")
        self._split_bytes = int(split_bytes)
        self._split_ns = int(round(float(split_seconds) * 1e9))
        self._splitting = self._split_bytes > 0 or self._split_ns > 0
        if self.path.exists():
            raise BagError(f"{self.path}: exists already: give a new bag directory (a bag is never overwritten)")
        self._writer = None
        self._connections: dict = {}
        self._topics: dict = {}         # topic -> (message type, QoS profiles), in the order added
        self._closed_files: list = []   # (name, start ns, duration ns, messages) of each storage file closed (split)
        self._bag_info = None           # split storage: the first closed file's metadata, with every topic's counts
        self._span = None               # (first, last) message timestamp of the current file
        self.message_count = 0
        self.flushed_count = 0
        self.closed = False
        self.crc_error = None       # why close() could not write the chunks' CRCs (the bag reads without them)
        if self._splitting:
            try:
                self.path.mkdir(parents=True)
            except OSError as exc:
                raise BagError(f"{self.path}: cannot create bag: {one_line(exc)}") from None
            self._open_file()
            return
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
        except Exception as exc:
            raise BagError(f"{self.path}: cannot create bag: {one_line(exc)}") from None
        self._storage_path = Path(self._writer.storage.path)

    def has_topic(self, topic: str) -> bool:
        """Whether :meth:`add_topic` was called for ``topic``."""
        return topic in self._topics

    @property
    def topics(self) -> dict:
        """Topic name -> message type of the topics added so far."""
        return {t: msgtype for t, (msgtype, _) in self._topics.items()}

    @property
    def closed_files(self) -> list:
        """Names of the storage files closed so far, in order (split storage only: empty without it)."""
        return [name for name, *_ in self._closed_files]

    @property
    def storage_files(self) -> list:
        """The storage files' names so far, in order (the one being written last)."""
        return self.closed_files + ([self._storage_path.name] if self._writer is not None else [])

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
        if topic in self._topics:
            raise BagError(f"{self.path}: topic '{topic}' added twice")
        if msgtype not in self._typestore.types:
            raise BagError(f"{self.path}: topic '{topic}': unknown message type {msgtype}")
        self._topics[topic] = (msgtype, list(qos_profiles))
        if self._writer is not None:
            try:
                self._connect(topic)
            except BaseException:
                del self._topics[topic]
                raise

    def _connect(self, topic: str) -> None:
        msgtype, qos_profiles = self._topics[topic]
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
        if self._writer is None:            # split storage: the first message after a split begins the next file
            self._open_file()
        timestamp = int(timestamp)
        self._writer.write(self._connections[topic], timestamp, bytes(data))
        if self._split_ns:
            self._span = (timestamp, timestamp) if self._span is None else \
                (min(self._span[0], timestamp), max(self._span[1], timestamp))
        self.message_count += 1

    def flush(self) -> int:
        """Close the pending MCAP chunk and write it to disk; with split storage, close the storage file too
        when it has reached its limit.

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
        if self._splitting and self._split_due(storage.bio.tell()):
            self._close_file()
        return self.flushed_count

    def _split_due(self, size: int) -> bool:
        """Whether the current storage file, ``size`` bytes, has reached a limit."""
        if self._split_bytes and size >= self._split_bytes:
            return True
        return bool(self._split_ns) and self._span is not None and self._span[1] - self._span[0] >= self._split_ns

    def _open_file(self) -> None:
        """Begin storage file ``<name>_<k>.mcap`` (split storage) with every topic added so far."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        k = len(self._closed_files)
        writer = Writer(self.path / f".split_{k}", version=9, storage_plugin=StoragePlugin.MCAP)
        target = self.path / f"{self.path.name}_{k}.mcap"
        try:
            writer.open()
            os.rename(writer.storage.path, target)      # the open file moves with its name
            if self._fsync:                             # the new name survives a power loss too
                fd = os.open(self.path, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        except Exception as exc:
            raise BagError(f"{target}: cannot create the storage file: {one_line(exc)}") from None
        self._writer, self._storage_path, self._span = writer, target, None
        self._connections = {}
        for topic in self._topics:
            self._connect(topic)

    def _close_file(self) -> None:
        """Close the current storage file (split storage): its summary, its CRCs, its metadata kept for the bag's."""
        import yaml

        writer, self._writer = self._writer, None
        writer.close()              # the MCAP summary; rosbags' metadata.yaml of this file alone, in .split_<k>
        info = yaml.safe_load(writer.metapath.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        writer.metapath.unlink()
        writer.path.rmdir()
        self._crcs()
        entry = info["files"][0]
        self._closed_files.append((self._storage_path.name, int(entry["starting_time"]["nanoseconds_since_epoch"]),
                                   int(entry["duration"]["nanoseconds"]), int(entry["message_count"])))
        if self._bag_info is None:      # kept once, not per file: what the bag's metadata takes from them
            self._bag_info = dict(info, topics_with_message_count=[])
        topics = {tp["topic_metadata"]["name"]: tp for tp in self._bag_info["topics_with_message_count"]}
        for tp in info["topics_with_message_count"]:
            name = tp["topic_metadata"]["name"]
            if name in topics:
                topics[name]["message_count"] += tp["message_count"]
            else:
                self._bag_info["topics_with_message_count"].append(dict(tp))

    def _crcs(self) -> None:
        try:
            write_chunk_crcs(self._storage_path, fsync=self._fsync)
        except (OSError, struct.error) as exc:     # the bag is complete without them; say why they are missing
            self.crc_error = self.crc_error or f"{self._storage_path}: chunk CRCs not written: {one_line(exc)}"

    def close(self) -> None:
        """Write the pending messages, the MCAP summary and ``metadata.yaml``.  Idempotent."""
        if self.closed:
            return
        self.closed = True
        self.flushed_count = self.message_count
        if not self._splitting:
            self._writer.close()
            self._crcs()
            return
        if self._writer is not None:
            self._close_file()
        _write_split_metadata(self.path / "metadata.yaml", self._bag_info, self._closed_files)


def _write_split_metadata(path: Path, info: dict, entries: list) -> None:
    """``metadata.yaml`` of a split bag: ``info`` (a storage file's metadata, with every topic and its messages
    over all files) with the ``files`` entry of every storage file, in order (``entries``: ``(name, start ns,
    duration ns, messages)``)."""
    import yaml

    info = dict(info)
    entries = [{"path": name, "starting_time": {"nanoseconds_since_epoch": start}, "duration": {"nanoseconds": span},
                "message_count": count} for name, start, span, count in entries]
    spans = [(e["starting_time"]["nanoseconds_since_epoch"], e["duration"]["nanoseconds"]) for e in entries
             if e["message_count"]]
    start = min(s for s, _ in spans) if spans else info["starting_time"]["nanoseconds_since_epoch"]
    end = max(s + d for s, d in spans) if spans else start
    info.update({
        "relative_file_paths": [e["path"] for e in entries],
        "duration": {"nanoseconds": end - start},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(e["message_count"] for e in entries),
        "files": entries,
    })
    tmp = path.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False, default_flow_style=False),
                   encoding="utf-8")
    tmp.replace(path)


def write_chunk_crcs(mcap_path, fsync: bool = False) -> int:
    """Write the CRC-32 of every uncompressed chunk of a closed MCAP file into its chunk record.

    rosbags' writer leaves every chunk's ``uncompressed_crc`` at 0 ("not computed"), so a reader
    cannot tell a flipped bit inside a message's numbers from the value.  With the CRC in place,
    rosbags (and any MCAP reader that checks CRCs) refuses such a chunk.  Chunks that are compressed
    are left as they are.  The file is read a record at a time and each CRC written in place, so
    the memory used is that of one chunk, whatever the file's length (a map of the whole file
    counted every page of a months-long recording in the recorder's resident memory).

    Parameters
    ----------
    mcap_path : str or Path
        The MCAP storage file, closed (its data section ends with a DataEnd record).
    fsync : bool
        Also ask the OS to write the CRCs to the device.

    Returns
    -------
    int
        Chunks given their CRC.
    """
    done = 0
    with open(mcap_path, "r+b") as f:
        size = os.fstat(f.fileno()).st_size
        pos = len(MAGIC)
        while pos + 9 <= size:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                break
            op, (length,) = head[0], struct.unpack_from("<Q", head, 1)
            if op == DATA_END or pos + 9 + length > size:
                break
            if op == CHUNK:
                body = f.read(length)
                compression, n, records = chunk_parts(body)
                if not compression and len(records) == n:
                    f.seek(pos + 9 + CHUNK_CRC_OFFSET)
                    f.write(struct.pack("<I", zlib.crc32(records)))
                    done += 1
            pos += 9 + length
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    return done


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
    """Write logged data as a bag of the stamped-vector topics (the inverse of :func:`read_bag`).

    Sample ``k`` becomes one message per topic stamped ``t[k]``, published in the loop's order
    (measured disturbances and output, input, setpoint) and logged at the stamp.  The disturbance
    topic is written when the data hold measured disturbances.

    Parameters
    ----------
    path : str or Path
        Bag directory to create.
    data : LoggedData
    topics : sequence of 3 or 4 str
        Setpoint, input and output topic names, and the disturbance topic's (default
        ``disturbance``).
    qos_profiles : sequence of rosbags Qos, optional
        Offered QoS stored for each topic; default the vector topics' QoS (RELIABLE, KEEP_LAST
        1000, VOLATILE).

    Returns
    -------
    int
        Messages written.
    """
    ts = default_typestore()
    if qos_profiles is None:
        qos_profiles = [contract_vector_qos()]
    names = [topic_name(t) for t in topics]
    if len(names) not in (3, 4):
        raise BagError(f"{path}: expected three topics (setpoint, input, output) or four (and disturbance), "
                       f"got {len(names)}")
    setpoint, inp, out = names[:3]
    dist = (names[3] if len(names) == 4 else topic_name(DEFAULT_DISTURBANCE_TOPIC)) if data.disturbances else None
    writer = BagWriter(path, typestore=ts, fsync=False)
    try:
        for t in ((dist,) if dist else ()) + (out, inp, setpoint):
            writer.add_topic(t, JOINT_STATE, qos_profiles)
        stamps = np.rint(np.asarray(data.t, dtype=float) * 1e9).astype(np.int64)
        for k, stamp in enumerate(stamps):
            if dist:
                writer.write(dist, stamp, joint_state_cdr(ts, stamp, data.disturbances, data.dv[k]))
            writer.write(out, stamp, joint_state_cdr(ts, stamp, data.outputs, data.y[k]))
            writer.write(inp, stamp + 1, joint_state_cdr(ts, stamp, data.inputs, data.u[k]))
            writer.write(setpoint, stamp + 2, joint_state_cdr(ts, stamp, data.outputs, data.r[k]))
    finally:
        writer.close()
    return writer.message_count


def contract_vector_qos():
    """The vector topics' QoS (:data:`mpm_monitor.io.qos.VECTOR_QOS`) as a rosbags ``Qos``."""
    return rosbags_qos(VECTOR_QOS)
