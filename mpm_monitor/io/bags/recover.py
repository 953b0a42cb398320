"""Recovering a bag whose recorder was killed: the flushed MCAP chunks rewritten as a closed bag."""

from __future__ import annotations

import struct
from pathlib import Path

from ...core.errors import BagError
from .mcap_records import (
    CHANNEL,
    CHUNK,
    DATA_END,
    FOOTER,
    MAGIC,
    MESSAGE,
    SCHEMA,
    chunk_parts,
    mcap_records,
    mcap_string,
)
from .write import BagWriter


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
    if buf[:len(MAGIC)] != MAGIC:
        raise BagError(f"{files[0]}: not an MCAP file (bad magic)")
    schemas, channels, messages = {}, {}, []

    def take(op, body):
        if op == SCHEMA:
            (sid,) = struct.unpack_from("<H", body, 0)
            name, _ = mcap_string(body, 2)
            schemas[sid] = name.decode()
        elif op == CHANNEL:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, pos = mcap_string(body, 4)
            _, pos = mcap_string(body, pos)  # message encoding
            metadata, _ = mcap_string(body, pos)
            channels[cid] = (topic.decode(), schemas.get(sid, ""), get_qos(metadata))
        elif op == MESSAGE:
            cid, _, log_time, _ = struct.unpack_from("<HIQQ", body, 0)
            messages.append((cid, log_time, body[22:]))

    for op, _, body in mcap_records(buf, len(MAGIC), len(buf)):
        if op == CHUNK:
            compression, _, inner = chunk_parts(body)
            if compression:
                raise BagError(f"{files[0]}: compressed chunks ({compression.decode()}) cannot be recovered")
            for op2, _, body2 in mcap_records(inner, 0, len(inner)):
                take(op2, body2)
        elif op in (DATA_END, FOOTER):  # the file was closed after all
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
