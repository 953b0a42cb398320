"""What reading, writing and recovering a bag share: topic names, message types, the type store, opening a bag.

This module uses the ``rosbags`` library only (imported when first needed); it never imports rclpy.
"""

from __future__ import annotations

import re
import stat
from pathlib import Path, PurePath

from ...core.errors import BagError
from ..yaml_nesting import nests_deeper

#: Default names of the setpoint, input and output topics.
DEFAULT_TOPICS = ("setpoint", "input", "output")
#: Default name of the measured-disturbance topic (read for a model with measured disturbances).
DEFAULT_DISTURBANCE_TOPIC = "disturbance"
#: Message type of the stamped vectors.
JOINT_STATE = "sensor_msgs/msg/JointState"
#: Message type of ``/diagnostics``.
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"


def topic_name(name: str) -> str:
    """The fully qualified form of a topic name (``setpoint`` -> ``/setpoint``), as rosbag2 stores it; the topics of a
    bag are matched in this form too (a bag written by another tool may store ``setpoint``)."""
    name = str(name).strip()
    return name if name.startswith("/") else "/" + name


def default_typestore():
    """The ``rosbags`` type store of ROS 2 Jazzy (holds every message type the project records)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def one_line(exc: BaseException) -> str:
    """An exception's text on one line, at most 300 characters (for a one-line :class:`BagError`)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def shown_names(names, limit: int = 12) -> str:
    """Channel or topic names of a bag, comma-separated, for a one-line message: a name holding a line break or
    another control character shown escaped (``'u1\\nfoo'``: it split the message over lines, or coloured the
    terminal), a name longer than 60 characters cut, and past ``limit`` names the count instead of the rest (a
    message of 20,000 names was one line of 200 kB)."""
    names = [str(n) for n in names]
    shown = [_cut(n if n.isprintable() else repr(n)) for n in names[:limit]]
    more = f", ... ({len(names)} in all)" if len(names) > limit else ""
    return ", ".join(shown) + more


def _cut(text: str, limit: int = 60) -> str:
    """``text`` cut to at most ``limit`` characters, ``...`` ending a cut one."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def stamp_ns(stamp) -> int:
    """A ``builtin_interfaces/msg/Time`` as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


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
    meta = path / "metadata.yaml"
    if meta.exists() and not meta.is_file():
        kind = "a directory" if meta.is_dir() else "a named pipe" if meta.is_fifo() else "not a regular file"
        raise BagError(f"{path}: metadata.yaml is {kind}: expected the YAML file rosbag2 writes")
    if not meta.is_file():
        raise BagError(f"{path}: no metadata.yaml: not a rosbag2 directory, or its recorder was killed before "
                       f"closing it (python -m mpm_monitor recover --bag DIR --out NEW_DIR rewrites what it flushed)")
    _check_metadata_shape(path)
    reader = AnyReader([path], default_typestore=default_typestore())
    try:
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated classes for damaged bags
        raise BagError(f"{path}: cannot read bag: {_open_failure(exc)}") from None
    return reader


def _check_metadata_shape(path: Path) -> None:
    """Refuse a ``metadata.yaml`` that rosbags would take wrongly or word as Python's own error: text that is
    not UTF-8 (rosbags said "'utf-8' codec can't decode byte ...", with the hint of a truncated storage file),
    lists or mappings nested deeper than rosbag2 ever writes (:data:`METADATA_MAX_NESTING`; the parsers took
    seconds each to reach their recursion limit), YAML that is not rosbag2's (a mapping under
    ``rosbag2_bagfile_information``: rosbags said ``string indices must be integers``), keys of the wrong shape
    (``duration``, ``starting_time``, the topic list, a topic entry or its ``topic_metadata`` not a mapping or a
    list as rosbag2 writes them, a ``version`` that is not a number: the same words; a ``files`` that is not a list
    of mappings: an ``AttributeError`` traceback), a file list or topic entries of the wrong kind (a message
    count that is not a whole number, a topic named by a number: a ``TypeError`` traceback), and a storage file
    that is not a regular file (a named pipe: the reader waited for ever).  A file that does not parse otherwise is left to rosbags, whose failure :func:`open_reader`
    words as before.

    Raises
    ------
    BagError
    """
    import yaml

    try:
        text = (path / "metadata.yaml").read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BagError(f"{path}: cannot read bag: metadata.yaml is not UTF-8 text (byte {exc.start}) (expected "
                       f"metadata.yaml as rosbag2 writes it)") from None
    except OSError:
        return                      # rosbags meets it and open_reader says so
    if nests_deeper(text, METADATA_MAX_NESTING):
        raise BagError(f"{path}: cannot read bag: metadata.yaml nests lists or mappings more than "
                       f"{METADATA_MAX_NESTING} deep (expected metadata.yaml as rosbag2 writes it)")
    try:        # libyaml's loader when PyYAML has it (the nesting is bounded above): the same values, faster
        doc = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except Exception:  # noqa: BLE001 - YAMLError, ...: rosbags meets it and open_reader says so
        return
    if not isinstance(doc, dict) or not isinstance(doc.get("rosbag2_bagfile_information"), dict):
        raise BagError(f"{path}: metadata.yaml is not a rosbag2 bag's description: expected a mapping "
                       f"'rosbag2_bagfile_information' as rosbag2 writes it")
    info = doc["rosbag2_bagfile_information"]
    files = info.get("relative_file_paths")
    if files is not None and not (isinstance(files, list) and all(isinstance(f, str) for f in files)):
        raise BagError(f"{path}: metadata.yaml: key 'relative_file_paths': expected a list of file names, got "
                       f"{_shown(files)}")
    # The shapes rosbags reads without checking them (it said "string indices must be integers", or raised an
    # AttributeError traceback while closing for a 'files' that is not a list).
    for key, kind in (("duration", dict), ("starting_time", dict), ("topics_with_message_count", list),
                      ("files", list)):
        if key in info and not isinstance(info[key], kind):
            raise BagError(f"{path}: metadata.yaml: key '{key}': expected "
                           f"{'a mapping' if kind is dict else 'a list'}, got {_shown(info[key])}")
    version = info.get("version")
    if version is not None and (isinstance(version, bool) or not isinstance(version, int)):
        raise BagError(f"{path}: metadata.yaml: key 'version': expected a whole number (rosbag2's metadata "
                       f"version), got {_shown(version)}")
    for i, entry in enumerate(info.get("files") or ()):
        if not isinstance(entry, dict):
            raise BagError(f"{path}: metadata.yaml: key 'files[{i}]': expected a mapping (path, starting_time, "
                           f"duration, message_count), got {_shown(entry)}")
    for i, entry in enumerate(info.get("topics_with_message_count") or ()):
        key = f"topics_with_message_count[{i}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("topic_metadata", {}), dict):
            what, got = (key, entry) if not isinstance(entry, dict) else (f"{key}.topic_metadata",
                                                                         entry["topic_metadata"])
            raise BagError(f"{path}: metadata.yaml: key '{what}': expected a mapping, got {_shown(got)}")
        count = entry.get("message_count")
        if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 0):
            raise BagError(f"{path}: metadata.yaml: key '{key}.message_count': expected a whole number >= 0, got "
                           f"{_shown(count)}")
        meta = entry.get("topic_metadata") or {}         # a mapping, checked above
        for field in ("name", "type"):
            value = meta.get(field)
            if value is not None and not isinstance(value, str):
                raise BagError(f"{path}: metadata.yaml: key '{key}.topic_metadata.{field}': expected a string, got "
                               f"{_shown(value)}")
    for name in dict.fromkeys(files or ()):
        storage = path / PurePath(name).name        # where rosbags looks for it
        try:
            mode = storage.stat().st_mode
        except OSError:
            continue                # missing: rosbags names it
        if not stat.S_ISREG(mode):
            kind = "a directory" if stat.S_ISDIR(mode) else "a named pipe" if stat.S_ISFIFO(mode) else "a device"
            raise BagError(f"{path}: storage file {name!r} is {kind}, not a file: expected the storage file "
                           f"metadata.yaml names, as rosbag2 writes it")


#: Nesting of lists and mappings beyond which a ``metadata.yaml`` is refused before it is parsed: rosbag2's nests
#: 5 deep; the parsers recurse once per level (seconds to reach Python's recursion limit, and libyaml's C
#: composer overflows the stack).
METADATA_MAX_NESTING = 100


def _shown(value) -> str:
    """A value of ``metadata.yaml`` as a message shows it: its repr, at most 60 characters."""
    return _cut(" ".join(repr(value).split()))


#: What rosbags says of a record or chunk whose length field does not match the bytes that follow it.
_RECORD_OVERRUN = ("Truncated record", "size mismatch")


def read_failure(exc: BaseException) -> str:
    """Why reading the messages of an open bag failed, with what was expected: a chunk whose bytes no
    longer match its CRC, or a length field that does not match the bytes after it (a length so large
    that reading it asks for more memory than there is, or for more bytes than an index holds, is said
    in those terms, not as Python's ``MemoryError`` or ``OverflowError``); anything else as rosbags
    words it."""
    text = one_line(exc)
    if "checksum mismatch" in text:
        return f"{text} (its bytes changed after they were written: the storage file is damaged)"
    if isinstance(exc, (MemoryError, OverflowError)):
        return ("a record's length runs far past the end of its chunk: the storage file is damaged "
                "(expected a storage file as rosbag2 writes it)")
    if any(w in text for w in _RECORD_OVERRUN):
        return f"{text} (a length field does not match the bytes after it: the storage file is damaged)"
    return text


def _open_failure(exc: BaseException) -> str:
    """Why rosbags could not open a bag, with what was expected: its metadata file's fault, a type hash
    that the stored message definition does not give, a storage file whose record lengths are garbage
    (reading one asks for more memory than there is), or one truncated or not closed."""
    text = one_line(exc)
    if isinstance(exc, MemoryError):
        return ("a record's length runs far past the end of the storage file: the file is damaged "
                "(expected a storage file as rosbag2 writes it)")
    if "hash mismatch" in text:
        return (f"{text} (the message definition stored in the bag and the type hash recorded for it "
                f"disagree: expected metadata.yaml and the storage file as rosbag2 wrote them)")
    if "database files are missing" in text:
        return f"{text} (expected the storage file metadata.yaml names, beside it)"
    missing = re.fullmatch(r"A metadata key is missing KeyError\((['\"])(.*)\1\)\.", text)
    if missing:                     # rosbags' words show Python's exception
        return f"metadata.yaml lacks the key '{missing.group(2)}' (expected metadata.yaml as rosbag2 writes it)"
    if "not supported" in text:     # a version, storage plugin, compression or serialization metadata.yaml names
        return (f"{text.replace('; please report issue.', '.')} (expected metadata.yaml of a bag this reader reads: "
                f"metadata version 9 or lower, MCAP or SQLite 3 storage, CDR messages, zstd compression or none)")
    if any(w in text for w in ("metadata", "YAML")):
        return f"{text} (expected metadata.yaml as rosbag2 writes it)"
    if isinstance(exc, KeyError):   # (rosbags wraps metadata.yaml's own missing keys): a schema record's name
        return (f"the storage file's schema records name {text}, a schema encoding or message type this reader "
                f"does not know (expected message definitions as rosbag2 writes them: encoded ros2msg or ros2idl)")
    if isinstance(exc, TypeError) and text.startswith("ord() expected a character"):
        # rosbags read the first record's opcode past the end: nothing follows the magic bytes
        return ("the storage file ends after its first bytes, before any record (truncated or not closed "
                "properly? python -m mpm_monitor recover --bag DIR --out NEW rewrites what its chunks hold as a "
                "readable bag)")
    if isinstance(exc, UnicodeDecodeError):     # metadata.yaml's text is checked before: a record's string
        return f"{text} (a string in the storage file's records is not UTF-8 text: the storage file is damaged)"
    return (f"{text} (truncated or not closed properly? python -m mpm_monitor recover --bag DIR --out NEW "
            f"rewrites what its chunks hold as a readable bag)")


def none_read(path, topic: str, conns: list) -> BagError:
    """The error of a topic that ``metadata.yaml`` counts messages on but whose reading gave none: the
    metadata no longer describes the storage file (rosbags matches each topic's connection in the
    metadata to the storage file's channel, QoS profiles included).  ``conns``: connections of the bag;
    those of ``topic`` give the count."""
    counted = sum(c.msgcount for c in conns if topic_name(c.topic) == topic)
    return BagError(f"{path}: topic '{topic}': metadata.yaml counts {counted} message{'s' if counted != 1 else ''} "
                    f"but none could be read from the storage file: expected metadata.yaml as rosbag2 wrote it "
                    f"for this storage file (was it edited, or taken from another bag?)")


def topic_connections(reader, path, topic: str, msgtype: str) -> list:
    """The connections of ``topic`` in an open bag, checked to exist, have ``msgtype`` and hold messages.

    Raises
    ------
    BagError
        Naming the bag and the topic (and the topics the bag has, when it is missing).
    """
    conns = [c for c in reader.connections if topic_name(c.topic) == topic]     # a bag may store 'input' or '/input'
    if not conns:
        have = shown_names(sorted({c.topic for c in reader.connections})) or "none"
        raise BagError(f"{path}: no topic '{topic}' ({msgtype}) in the bag; topics in the bag: {have}")
    for c in conns:
        if c.msgtype != msgtype:
            raise BagError(f"{path}: topic '{topic}' has type {c.msgtype}, expected {msgtype}")
    if sum(c.msgcount for c in conns) == 0:
        raise BagError(f"{path}: topic '{topic}' holds no messages")
    return conns
