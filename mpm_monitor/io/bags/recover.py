"""Recovering a bag whose recorder was killed: the flushed MCAP chunks rewritten as a closed bag."""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
import zlib
from pathlib import Path
from typing import Iterator

from ...core.errors import BagError
from .mcap_records import (
    CHANNEL,
    CHUNK,
    CHUNK_CRC_OFFSET,
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


#: A chunk's ``uncompressed_crc`` of 0 means "not computed" (rosbags' writer; BagWriter before it closes).
NO_CRC = 0
#: The chunk compressions MCAP writers use (any other name in a chunk is a damaged byte).
COMPRESSIONS = (b"zstd", b"lz4")


def recover_bag(src, dst, warn=None) -> int:
    """Rewrite what a hard-killed recorder left on disk as a new, properly closed bag.

    A recorder killed by SIGKILL or a power loss leaves an MCAP file without summary or footer and
    no ``metadata.yaml``; every chunk it flushed is complete on disk.  This reads those complete
    chunk records of every storage file (a split recording's ``bag_0.mcap``, ``bag_1.mcap``, ... in
    order; a torn last record is dropped, and said through ``warn``) and writes their messages, in
    order and with the recorded QoS profiles, to ``dst``.

    A storage file damaged besides (bytes changed on disk) keeps what can still be trusted: a chunk
    whose CRC (when the writer computed one) does not match its bytes is left out, and so is a schema
    or channel record that cannot be parsed, a message record too short to hold its header, and the
    messages of a channel with no readable channel record or no schema (their type is unknown; in a
    file that was closed, the summary's copies of the schema and channel records are read too).  What
    was left out is said through ``warn``, one line; a message whose own bytes were changed is
    recovered as it is, and the reader that decodes it names it.

    The storage files are mapped, not read into memory (the pages walked handed back to the kernel as
    the walk goes), and the messages are written as they are read: a recording of any length is
    recovered in the same memory.

    Parameters
    ----------
    src : str or Path
        The unclosed bag directory.
    dst : str or Path
        New bag directory (must not exist).
    warn : callable, optional
        Called with one line when records were left out as damaged.

    Returns
    -------
    int
        Messages recovered.

    Raises
    ------
    BagError
        No MCAP file, not an MCAP file, compressed chunks, or no message left to recover (``dst`` is
        then not created).
    """
    src = Path(src)
    if not src.exists():
        raise BagError(f"{src}: no such bag directory")
    if not src.is_dir():
        raise BagError(f"{src}: is a file: expected the bag directory (the folder that holds its .mcap files)")
    files = sorted((f for f in src.glob("*.mcap") if f.is_file()), key=_split_order)
    if not files:
        raise BagError(f"{src}: no .mcap file to recover")
    names = sorted({_split_order(f)[0] for f in files})
    if len(names) > 1:      # two recordings in one folder were merged into one bag, without a word
        shown = ", ".join(f"{name}_*.mcap" for name in names[:4]) + (", ..." if len(names) > 4 else "")
        raise BagError(f"{src}: holds the storage files of {len(names)} recordings ({shown}): expected one "
                       f"recording's NAME_0.mcap, NAME_1.mcap, ... (move the others to folders of their own)")
    found = _Records()
    for path in files:                  # a split recording: its storage files in order (bag_0, bag_1, ...)
        found.file(path)
    left_out = found.left_out()
    where = files[0] if len(files) == 1 else src
    if not found.typed:
        damaged = found.left_out(torn=False)
        raise BagError(f"{where}: no complete message to recover{': ' + damaged if damaged else ''} "
                       f"(expected at least one complete chunk of messages after the MCAP header)")
    writer = BagWriter(dst, fsync=False)
    try:
        for (topic, msgtype, qos), log_time, data in found.typed_messages():
            if not writer.has_topic(topic):
                writer.add_topic(topic, msgtype, qos)
            writer.write(topic, log_time, data)
    finally:
        writer.close()
    if left_out and warn is not None:
        warn(f"{where}: the storage file{'s are' if len(files) > 1 else ' is'} damaged: {left_out}")
    return writer.message_count


def _split_order(path: Path) -> tuple:
    """Sort key of a split recording's storage files: ``bag_2.mcap`` before ``bag_10.mcap`` (rosbag2 numbers them)."""
    stem, _, number = path.stem.rpartition("_")
    return (stem, int(number), "") if number.isdigit() else (path.stem, -1, path.name)


class _Records:
    """The schemas, channels and messages of a recording's storage files, and what was left out as damaged.

    Each file is read twice, mapped into memory rather than read: :meth:`file` takes its schema and channel
    records and counts its messages and damage; :meth:`typed_messages` then walks the same records again and
    yields the typed messages one at a time.  What stays in memory between the two is each file's channels and
    the offsets of its damaged chunks, so a recording of any length is recovered in the same memory.
    """

    def __init__(self):
        from rosbags.rosbag2.storage_mcap import get_qos

        self._get_qos = get_qos         # imported once, not per record
        self.bad_chunks = self.bad_records = self.untyped = self.typed = 0
        self.torn = []                  # (file, bytes) of a record cut at the end of a file (the kill)
        self.files = []                 # (path, channels, starts of the damaged chunks) of each file read
        self.schemas, self.channels, self.counts, self.skip = {}, {}, {}, set()

    def file(self, path) -> None:
        """Take the records of one storage file (its chunks, and its summary's schemas and channels): its
        messages are typed by its own schema and channel records (each file of a split recording numbers
        its channels anew).  Messages are only counted here."""
        self.schemas, self.channels, self.counts, self.skip = {}, {}, {}, set()
        with _mapped(path) as mapped:
            buf = mapped.view
            if len(buf) < len(MAGIC) and MAGIC.startswith(bytes(buf)):
                return                  # killed before even the magic reached the disk: nothing in it
            if buf[:len(MAGIC)] != MAGIC:
                raise BagError(f"{path}: not an MCAP file (bad magic)")
            end = len(MAGIC)
            for op, start, body, summary in _top_records(mapped):
                end = start + len(body)
                if op == FOOTER:
                    end = len(buf)
                elif summary:               # the file was closed after all: its summary repeats the schemas and
                    if op in (SCHEMA, CHANNEL):   # channels, of use where a chunk holding them is damaged
                        self.take(op, body, again=True)
                elif op == CHUNK:
                    self.chunk(path, start, body)
                else:
                    self.take(op, body)
                del body
            if _written(buf, end):              # a record cut by the kill (zeros: space never written)
                self.torn.append((path, len(buf) - end))
        for cid, n in self.counts.items():
            channel = self.channels.get(cid)
            if channel is None or not channel[1]:
                self.untyped += n
            else:
                self.typed += n
        self.files.append((path, self.channels, self.skip))

    def chunk(self, path, start, body) -> None:
        """Take the records of a chunk, or count it damaged (too short, a compression no writer names, or
        its CRC does not match) and note its offset, so that :meth:`typed_messages` skips it."""
        try:
            compression, _, inner = chunk_parts(body)
            (crc,) = struct.unpack_from("<I", body, CHUNK_CRC_OFFSET)
        except struct.error:
            self.bad_chunks += 1
            self.skip.add(start)
            return
        if compression in COMPRESSIONS:
            raise BagError(f"{path}: compressed chunks ({bytes(compression).decode()}) cannot be recovered")
        if compression or (crc != NO_CRC and zlib.crc32(inner) != crc):   # a compression no writer names: damage
            self.bad_chunks += 1
            self.skip.add(start)
            return
        for op, _, body2 in mcap_records(inner, 0, len(inner)):
            self.take(op, body2)

    def take(self, op, body, again: bool = False) -> None:
        """Take one schema or channel record, or count one message record (others are skipped); count it
        damaged when it cannot be parsed.  With ``again`` (the summary's copy of a schema or channel record),
        one already read is kept and a damaged copy is not counted."""
        try:
            if op == SCHEMA:
                (sid,) = struct.unpack_from("<H", body, 0)
                name, _ = mcap_string(body, 2)
                if not (again and sid in self.schemas):
                    self.schemas[sid] = bytes(name).decode()
            elif op == CHANNEL:
                cid, sid = struct.unpack_from("<HH", body, 0)
                topic, pos = mcap_string(body, 4)
                _, pos = mcap_string(body, pos)  # message encoding
                metadata, _ = mcap_string(body, pos)
                if not (again and cid in self.channels):
                    self.channels[cid] = (bytes(topic).decode(), self.schemas.get(sid, ""),
                                          self._get_qos(bytes(metadata)))
            elif op == MESSAGE:
                cid, _, _, _ = struct.unpack_from("<HIQQ", body, 0)
                self.counts[cid] = self.counts.get(cid, 0) + 1
        except Exception:  # untrusted bytes: any parse failure of a schema or channel record is damage
            self.bad_records += not again

    def typed_messages(self) -> Iterator[tuple]:
        """``(channel, log_time, data)`` of the messages whose channel and schema were read, file after file and
        in the order of their records, ``channel`` = ``(topic, message type, QoS profiles)``, ``data`` the
        message's bytes; the others were counted in :attr:`untyped`.  Reads the files again."""
        for path, channels, skip in self.files:
            with _mapped(path) as mapped:
                for op, start, body, summary in _top_records(mapped):
                    if summary or op == FOOTER:
                        continue
                    if op == CHUNK:
                        if start in skip:
                            continue
                        inner = chunk_parts(body)[2]
                        records = ((op2, body2) for op2, _, body2 in mcap_records(inner, 0, len(inner)))
                    else:
                        records = ((op, body),)
                    for op2, body2 in records:
                        message = _message(op2, body2, channels)
                        if message is not None:
                            yield message
                    del body, records

    def left_out(self, torn: bool = True) -> str:
        """What was left out, in words ('' when nothing was); ``torn``: with the records cut short at the end
        of a file."""
        parts = []
        if self.bad_chunks:
            parts.append(f"{self.bad_chunks} damaged chunk{'s' if self.bad_chunks != 1 else ''} (a CRC, length or "
                         f"compression field that does not match the bytes)")
        if self.bad_records:
            parts.append(f"{self.bad_records} record{'s' if self.bad_records != 1 else ''} that cannot be parsed")
        if self.untyped:
            parts.append(f"{self.untyped} message{'s' if self.untyped != 1 else ''} of a channel with no readable "
                         f"channel or schema record")
        for path, n in (self.torn if torn else ()):
            parts.append(f"the last {n:,} bytes of {Path(path).name}, a record cut short (the messages it held are "
                         f"lost)")
        return ("left out " + ", ".join(parts)) if parts else ""


def _message(op, body, channels):
    """``(channel, log_time, data)`` of a message record whose channel was read, else None (a record of another
    kind, one too short to hold its header, or a message of a channel with no readable channel or schema)."""
    if op != MESSAGE:
        return None
    try:
        cid, _, log_time, _ = struct.unpack_from("<HIQQ", body, 0)
    except struct.error:
        return None
    channel = channels.get(cid)
    if channel is None or not channel[1]:
        return None
    return channel, log_time, bytes(body[22:])


def _top_records(mapped) -> Iterator[tuple]:
    """``(opcode, body start, body, in summary)`` of a storage file's top-level records after the magic, up to and
    with its footer; ``in summary``: after the data end record (a closed file's summary section).  The pages of
    the records already walked are handed back as the walk goes (:meth:`_Mapped.done`)."""
    summary = False
    buf = mapped.view
    for op, start, body in mcap_records(buf, len(MAGIC), len(buf)):
        mapped.done(start - 9)
        yield op, start, body, summary
        if op == FOOTER:
            return
        if op == DATA_END:
            summary = True


def _written(buf, end: int, block: int = 1 << 20) -> bool:
    """Whether ``buf[end:]`` holds a byte other than 0 (looked at a block at a time)."""
    for pos in range(end, len(buf), block):
        if bytes(buf[pos:pos + block]).strip(b"\x00"):
            return True
    return False


class _Mapped:
    """A storage file mapped read-only: :attr:`view`, a ``memoryview`` of it (an empty file: an empty view).

    The pages of a mapped file count in the process's resident memory once read, though they are the page
    cache's; :meth:`done` hands those of the part walked back to the kernel (``MADV_DONTNEED``: read again from
    the file if touched again), so that the resident memory stays about one step of :data:`RELEASE_BYTES`
    whatever the file's length."""

    #: Bytes walked between two hand-backs of the pages.
    RELEASE_BYTES = 1 << 26

    def __init__(self, mm):
        self._mm = mm
        self.view = memoryview(mm) if mm is not None else memoryview(b"")
        self._released = 0

    def done(self, upto: int) -> None:
        """The bytes before ``upto`` are walked: their pages may go (every :data:`RELEASE_BYTES`)."""
        if self._mm is None or upto - self._released < self.RELEASE_BYTES or not hasattr(mmap, "MADV_DONTNEED"):
            return
        end = upto - upto % mmap.PAGESIZE
        self._mm.madvise(mmap.MADV_DONTNEED, self._released, end - self._released)
        self._released = end


@contextlib.contextmanager
def _mapped(path):
    """:class:`_Mapped` of a storage file; the map is closed at the end, or left to the garbage collector when a
    view of it is still held (an exception's traceback)."""
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:       # mmap refuses an empty file
            yield _Mapped(None)
            return
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    mapped = _Mapped(mm)
    try:
        yield mapped
    finally:
        mapped.view.release()
        try:
            mm.close()
        except BufferError:     # a slice of it is still referenced: closed when that goes
            pass
