"""Reading a user's text file with one-line errors."""

from __future__ import annotations

from pathlib import Path


def read_text(path, error_cls, kind: str, expected: str, encoding: str = "utf-8", max_bytes=None) -> str:
    """The text of a file, or ``error_cls`` with one line naming the file.

    Parameters
    ----------
    path : str or Path
    error_cls : type
        A subclass of :class:`InputError` to raise.
    kind : str
        What the file is ("data file"), for the message.
    expected : str
        What the file should be ("a CSV file"), for the message.
    encoding : str
        "utf-8", or "utf-8-sig" to accept a byte-order mark.
    max_bytes : int, optional
        Refuse a file longer than this (bytes), without reading more of it (a device such as
        ``/dev/zero`` never ends).
    """
    path = Path(path)
    try:
        if max_bytes is None:
            raw = path.read_bytes()
        else:
            with open(path, "rb") as f:
                raw = f.read(max_bytes + 1)
    except OSError as exc:
        raise error_cls(f"{path}: cannot read {kind}: {exc.strerror or exc}") from None
    if max_bytes is not None and len(raw) > max_bytes:
        raise error_cls(f"{path}: longer than {max_bytes:,} bytes: expected {expected}")
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise error_cls(f"{path}: not UTF-8 text (byte {exc.start}) {_where_in_text(raw, exc.start)}: expected "
                        f"{expected}") from None


def _where_in_text(raw: bytes, pos: int) -> str:
    """``on line L, character C`` of the byte at offset ``pos`` of ``raw`` (both from 1; the characters of
    the line before it counted as UTF-8, each byte that is not counted as one)."""
    start = raw.rfind(b"\n", 0, pos) + 1
    before = raw[start:pos].decode("utf-8", errors="replace")
    line = raw.count(b"\n", 0, pos) + 1
    return f"on line {line}, character {len(before) + 1}"


def write_text_replacing(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` beside it and rename it over ``path`` once complete, so that a reader
    of the file (a controller loading a repaired model) never sees half of it, and a write cut short leaves the
    old file.  A path that exists and is not a regular file (``/dev/stdout``, a pipe) is written as it is."""
    import os

    target = Path(path)
    if target.exists() and not target.is_file():
        target.write_text(text, encoding="utf-8")
        return
    tmp = target.with_name(f".{target.name}.{os.getpid()}.partial")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise

