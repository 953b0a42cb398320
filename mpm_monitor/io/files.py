"""Reading a user's text file with one-line errors."""

from __future__ import annotations

import os
import stat
from pathlib import Path


#: The first bytes of a gzip file (RFC 1952).
GZIP_MAGIC = b"\x1f\x8b"
#: A gzip file's content is refused beyond this many times the file's size (a log of numbers compresses
#: 5 to 50 times; a "decompression bomb" of zeros a thousand times) ...
GZIP_MAX_RATIO = 1000
#: ... when it is also beyond this many bytes.
GZIP_MIN_LIMIT = 256 * 2 ** 20


def gunzipped(raw: bytes, path, error_cls, expected: str) -> bytes:
    """``raw`` itself, or its content when it is a gzip file (:data:`GZIP_MAGIC`); ``error_cls`` with one line naming
    the file when such a file is cut short or damaged, or when its content would exceed :data:`GZIP_MAX_RATIO`
    times its size and :data:`GZIP_MIN_LIMIT` bytes (decompressed up to that limit only: a small file that
    expands to gigabytes would take the memory before any message)."""
    if not raw.startswith(GZIP_MAGIC):
        return raw
    import gzip
    import io
    import zlib

    limit = max(GZIP_MIN_LIMIT, GZIP_MAX_RATIO * len(raw))
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as f:
            out = f.read(limit + 1)
    except (OSError, EOFError, zlib.error) as exc:
        why = " ".join(str(exc).split()) or "cut short"
        raise error_cls(f"{path}: a gzip file that cannot be decompressed ({why}): expected {expected} or one "
                        f"compressed whole with gzip") from None
    if len(out) > limit:
        raise error_cls(f"{path}: a gzip file of {len(raw):,} bytes whose content exceeds {limit:,} bytes (more than "
                        f"{GZIP_MAX_RATIO} times its size): expected {expected} or one compressed whole with gzip")
    return out


#: Bytes at the start of a file in which :func:`read_text` looks for NUL bytes before it reads the rest.
NUL_PEEK_BYTES = 1 << 16


def _utf8_start(raw: bytes) -> bool:
    """Whether ``raw`` (the start of a stream) is UTF-8 text, but for a character its end may cut."""
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.reason == "unexpected end of data"
    return True


def read_text(path, error_cls, kind: str, expected: str, encoding: str = "utf-8", max_bytes=None,
              gzip_ok: bool = False, nul_error=None) -> str:
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
    gzip_ok : bool
        A gzip file (``log.csv.gz``) is read as its content (:func:`gunzipped`).
    nul_error : type, optional
        Raised (``"PATH: contains NUL bytes"``) when the first :data:`NUL_PEEK_BYTES` bytes of a stream that is not
        a regular file (a device, a pipe) hold a NUL byte, are UTF-8 and not gzip, before the rest is read: a
        device such as ``/dev/zero`` never ends, and would be read until the memory runs out.  Such a start that
        is neither UTF-8 nor gzip (``/dev/urandom``) is refused then too, as not UTF-8 (the message it would get
        once read whole).  A regular file is read whole and refused as before (by the caller, or as not UTF-8).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            limit = -1 if max_bytes is None else max_bytes + 1
            if nul_error is None or stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raw = f.read(limit)                      # a regular file: read whole, as it always was
            else:                                        # a device or a pipe: its start looked at first
                raw = f.read(NUL_PEEK_BYTES if limit < 0 else min(NUL_PEEK_BYTES, limit))
                if b"\x00" in raw and not raw.startswith(GZIP_MAGIC) and _utf8_start(raw):
                    raise nul_error(f"{path}: contains NUL bytes")
                if not raw.startswith(GZIP_MAGIC) and not _utf8_start(raw):
                    # Refused now as it would be once read whole (the same first bad byte): /dev/urandom, an
                    # endless binary stream, was read until the memory ran out.
                    _decoded(raw, encoding, path, error_cls, expected)
                if limit < 0 or len(raw) < limit:
                    raw += f.read(limit if limit < 0 else limit - len(raw))
    except OSError as exc:
        raise error_cls(f"{path}: cannot read {kind}: {exc.strerror or exc}") from None
    if max_bytes is not None and len(raw) > max_bytes:
        raise error_cls(f"{path}: longer than {max_bytes:,} bytes: expected {expected}")
    if gzip_ok:
        raw = gunzipped(raw, path, error_cls, expected)
    return _decoded(raw, encoding, path, error_cls, expected)


def _decoded(raw: bytes, encoding: str, path, error_cls, expected: str) -> str:
    """``raw`` decoded, or ``error_cls`` naming the file, the first byte that is not UTF-8 and its line."""
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


def replace_file(path, write, fsync: bool = False) -> Path:
    """Write ``path`` through a temporary file beside it: ``write(tmp)`` fills the temporary file (its path, a
    ``str``), which is then renamed over ``path``, so a reader of the file sees either the old one or the whole
    new one, and a write cut short (Ctrl-C, a full disk) leaves the old file.  The mode of an existing file is
    kept (0644 for a new one); ``fsync`` flushes the new file to the disk before the rename.  A path that exists
    and is not a regular file (``/dev/stdout``, a pipe) is written as it is.  A symbolic link is followed: the
    file it points to is replaced and the link kept (``--repair-out model.yaml``, a link into a release
    directory, replaced the link with a file and left the release's model as it was).

    Returns
    -------
    Path
        The absolute path written.

    Raises
    ------
    OSError
        The directory does not exist or is not writable, ``path`` is a directory, ...
    """
    import os
    import tempfile

    target = Path(path).expanduser().absolute()
    if target.is_symlink():
        target = Path(os.path.realpath(target))     # the file the link points to (a loop: the path as given, refused)
    if target.is_dir():
        raise IsADirectoryError(21, "is a directory", str(target))
    if target.exists() and not target.is_file():
        write(str(target))
        return target
    mode = (target.stat().st_mode & 0o7777) if target.exists() else 0o644
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        os.close(fd)
        write(tmp)
        if fsync:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return target


def same_file(a, b) -> bool:
    """Whether the paths ``a`` and ``b`` name one file: the same file when both exist (a symbolic link, ``..``, a
    hard link), else the same path with ``~``, ``..`` and the links of its directories resolved."""
    a, b = Path(a).expanduser(), Path(b).expanduser()
    try:
        return os.path.samefile(a, b)
    except OSError:                 # one of them does not exist (yet)
        return a.resolve() == b.resolve()


def write_text_replacing(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replace_file`."""
    replace_file(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
