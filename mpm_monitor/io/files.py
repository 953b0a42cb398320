"""Reading a user's text file with one-line errors."""

from __future__ import annotations

from pathlib import Path


def read_text(path, error_cls, kind: str, expected: str, encoding: str = "utf-8") -> str:
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
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise error_cls(f"{path}: cannot read {kind}: {exc.strerror or exc}") from None
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise error_cls(f"{path}: not UTF-8 text (byte {exc.start}): expected {expected}") from None
