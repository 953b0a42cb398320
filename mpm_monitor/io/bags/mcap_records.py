"""The MCAP records this package reads itself (the MCAP format specification), below rosbags.

Two tasks need the file's records rather than its messages: :func:`~mpm_monitor.io.bags.recover_bag`
reads the chunks a killed recorder flushed (rosbags refuses a file without summary), and
:func:`~mpm_monitor.io.bags.write.write_chunk_crcs` writes the chunk CRCs rosbags' writer leaves at 0.
A record is an opcode byte, a little-endian ``uint64`` length and that many bytes of body.
"""

from __future__ import annotations

import struct
from typing import Iterator

#: The first (and last) eight bytes of an MCAP file.
MAGIC = b"\x89MCAP0\r\n"
#: Opcodes: schema, channel, message, chunk, data end, footer.
SCHEMA, CHANNEL, MESSAGE, CHUNK, DATA_END, FOOTER = 0x03, 0x04, 0x05, 0x06, 0x0F, 0x02
#: Offset of a chunk body's ``uncompressed_crc`` (after start time, end time and uncompressed size).
CHUNK_CRC_OFFSET = 24


def mcap_string(buf, pos: int) -> tuple:
    """``(bytes, position after it)`` of the ``uint32``-length-prefixed string at ``buf[pos]``."""
    (n,) = struct.unpack_from("<I", buf, pos)
    return buf[pos + 4:pos + 4 + n], pos + 4 + n


def mcap_records(buf, pos: int, end: int) -> Iterator[tuple]:
    """``(opcode, body start, body)`` of the complete records in ``buf[pos:end]``; stops at a torn record.

    ``buf`` is bytes or a ``memoryview`` (of a mapped file: the bodies are then views, not copies); the body
    start is its offset in ``buf``.
    """
    while pos + 9 <= end:
        op = buf[pos]
        (size,) = struct.unpack_from("<Q", buf, pos + 1)
        body_end = pos + 9 + size
        if body_end > end:
            return
        yield op, pos + 9, buf[pos + 9:body_end]
        pos = body_end


def chunk_parts(body: bytes) -> tuple:
    """``(compression, uncompressed size, records)`` of a chunk record's body (``compression`` empty
    when the records are stored as they are)."""
    (uncompressed_size,) = struct.unpack_from("<Q", body, 16)
    compression, pos = mcap_string(body, 28)
    (size,) = struct.unpack_from("<Q", body, pos)
    return compression, uncompressed_size, body[pos + 8:pos + 8 + size]
