"""Recovering a bag whose recorder was killed: the flushed MCAP chunks rewritten as a closed bag."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Iterator

from ...core.errors import BagError
from .write import BagWriter

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
