"""Writing a bag: :class:`BagWriter` (rosbag2, MCAP storage) and logged data as a bag.

:class:`BagWriter` writes a rosbag2 directory (MCAP storage, metadata version 9) message by message
from serialized CDR bytes and can flush complete MCAP chunks to disk while recording; the
recorder node wraps it.  :func:`write_logged_data` is the inverse of
:func:`~mpm_monitor.io.bags.read.read_bag`.
"""

from __future__ import annotations

import mmap
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
from .mcap_records import CHUNK, CHUNK_CRC_OFFSET, DATA_END, MAGIC, chunk_parts, mcap_records


class BagWriter:
    """Write a rosbag2 directory (MCAP storage, metadata version 9) from serialized messages.

    Topics are added with the QoS profiles their publishers offered; messages are written as the
    CDR bytes received.  :meth:`flush` closes the pending MCAP chunk and writes it to disk, so a
    process that dies later leaves every message up to the last flush in complete chunk records
    on disk; :meth:`close` writes the MCAP summary and ``metadata.yaml`` (without it, readers
    refuse the bag) and every chunk's CRC (:func:`write_chunk_crcs`).

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
            raise BagError(f"{self.path}: cannot create bag: {one_line(exc)}") from None
        self._storage_path = Path(self._writer.storage.path)
        self._connections: dict = {}
        self.message_count = 0
        self.flushed_count = 0
        self.closed = False
        self.crc_error = None       # why close() could not write the chunks' CRCs (the bag reads without them)

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
        try:
            write_chunk_crcs(self._storage_path, fsync=self._fsync)
        except (OSError, struct.error) as exc:     # the bag is complete without them; say why they are missing
            self.crc_error = f"{self._storage_path}: chunk CRCs not written: {one_line(exc)}"


def write_chunk_crcs(mcap_path, fsync: bool = False) -> int:
    """Write the CRC-32 of every uncompressed chunk of a closed MCAP file into its chunk record.

    rosbags' writer leaves every chunk's ``uncompressed_crc`` at 0 ("not computed"), so a reader
    cannot tell a flipped bit inside a message's numbers from the value.  With the CRC in place,
    rosbags (and any MCAP reader that checks CRCs) refuses such a chunk.  Chunks that are compressed
    are left as they are.  The file is mapped, not read into memory.

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
        if os.fstat(f.fileno()).st_size == 0:             # mmap refuses an empty file: no chunk in it
            return 0
        with mmap.mmap(f.fileno(), 0) as buf:
            for op, start, body in mcap_records(buf, len(MAGIC), len(buf)):
                if op == DATA_END:
                    break
                if op == CHUNK:
                    compression, size, records = chunk_parts(body)
                    if not compression and len(records) == size:
                        struct.pack_into("<I", buf, start + CHUNK_CRC_OFFSET, zlib.crc32(records))
                        done += 1
            buf.flush()
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
