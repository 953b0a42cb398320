"""Exception classes of mpm_monitor.

Every error raised for bad input (a model file, a CSV log, a bag, a parameter) is a subclass of
:class:`InputError`, itself a :class:`ValueError`, so the command-line tools can turn it into one
line on stderr and exit code 2 instead of a traceback.
"""


class InputError(ValueError):
    """Bad input given by a user: the message names the file, line, key or topic."""


class ModelFileError(InputError):
    """A model file (CONTRACTS section 1) that cannot be used."""


class DataFileError(InputError):
    """A logged-data CSV file (CONTRACTS section 2) that cannot be used."""


class BagError(InputError):
    """A rosbag2 directory that cannot be read or does not hold the expected topics."""


class ConfigurationError(InputError):
    """An option or parameter value outside its allowed range."""


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
    from pathlib import Path

    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise error_cls(f"{path}: cannot read {kind}: {exc.strerror or exc}") from None
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise error_cls(f"{path}: not UTF-8 text (byte {exc.start}): expected {expected}") from None
