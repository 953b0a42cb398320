"""Logged closed-loop data as a CSV file (docs/interfaces.md, "Logged data (CSV)", "Measured disturbances").

One row per sample, header ``t, r_<output>..., <input>..., <disturbance>..., <output>...``; column
order is free.  Samples lie on the grid of the model's sample time: ``t`` may skip grid points (rows
missing: a gap, analysed around, never interpolated; docs/interfaces.md, "Gaps"), but a repeated or
decreasing ``t``, a ``t`` off the grid, a missing column or a non-numeric cell in a column the model
needs is refused with the line and column, never silently mis-aligned.  Every other named column is
kept: a numeric one in :attr:`LoggedData.extra`, one that is not numeric or partly missing in
:attr:`LoggedData.unusable` with the reason.

Reading has two paths that give the same result.  numpy's C parser (``numpy.loadtxt``) reads a file
of plain numbers (a 10,000-line file of 61 columns in about a quarter of a second); anything it
does not take, or that the checks below refuse, is read again by the careful parser (the ``csv``
module and one ``float`` per cell), which names the line and column of the first problem.

The command line starts the C parse early (:func:`start_csv_read`): the file's bytes are read and
numpy's parse of them runs in a forked child (:class:`~mpm_monitor.core.parallel.Forked`) while the
command imports the analysis and loads the model; :func:`read_csv` then takes the child's rows, and
parses from the end of the file back whatever the child has not reached yet (:class:`StartedCsvRead`).
Only what needs no model runs so (the checks and the call of :func:`_fast_cells`, line by line on the
same bytes); every check against the model, and every message, stays in :func:`parse_csv_text`, so
the result and the errors are those of a read in one process.
"""

from __future__ import annotations

import collections
import csv
import io
import math
import mmap
import os
import re
import stat
import unicodedata
import warnings
from pathlib import Path

import numpy as np

from ..core.errors import DataFileError
from ..core.logged_data import LoggedData, t_text
from ..core.model import PlantModel
from ..core.parallel import Forked
from .files import gunzipped, read_text, replace_file

#: Relative tolerance on the sample spacing, as a fraction of the sample time: a step of ``m`` sample times may be
#: off by ``m`` times this (a logger's clock a little fast or slow, over a gap), at most :data:`MAX_STEP_OFFSET`.
SPACING_TOLERANCE = 1e-3
#: Most a step may be off its whole number of sample times, in sample times (as a bag's stamps may be off their
#: samples): beyond it the number of samples a gap skipped is in doubt.
MAX_STEP_OFFSET = 0.25

#: Longest span of ``t``, in sample times, whose grid numbers float64 holds exactly (and int64 counts).
MAX_GRID_SAMPLES = 2.0 ** 53

#: A number as a CSV cell writes it: ASCII digits, an optional sign, point and exponent (and nan / inf,
#: refused later as not finite).  Python's ``float`` also takes ``1_0`` (as 10) and non-ASCII digits,
#: which no export means as a number.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)",
                     re.IGNORECASE)


def _cell_float(cell: str) -> float:
    """The number in a stripped cell; ValueError when it is not written as a plain number."""
    if not _NUMBER.fullmatch(cell):
        raise ValueError(cell)
    return float(cell)


def csv_header(inputs, outputs, disturbances=()) -> list:
    """Column names of the CSV log in the canonical order.

    ``t, r_<output>..., <input>..., <disturbance>..., <output>...``.
    """
    return ["t"] + [f"r_{o}" for o in outputs] + list(inputs) + list(disturbances) + list(outputs)


def write_csv(path, t, r, u, y, inputs, outputs, dv=None, disturbances=(), extra=None) -> None:
    """Write signals as the CSV log, with full float precision (lossless round trip).

    Parameters
    ----------
    path : str or Path
    t : ndarray, shape (n_samples,)
    r, y : ndarray, shape (n_samples, n_outputs)
    u : ndarray, shape (n_samples, n_inputs)
    inputs, outputs : sequence of str
    dv : ndarray, shape (n_samples, n_disturbances), optional
        Measured disturbances, written after the inputs.
    disturbances : sequence of str
        Their names.
    extra : dict, optional
        Other channels, ``name -> ndarray (n_samples,)``, written last in the dict's order.
    """
    t = np.asarray(t, dtype=float).reshape(-1, 1)
    n = t.shape[0]
    dv = np.zeros((n, 0)) if dv is None else np.asarray(dv, float).reshape(n, len(disturbances))
    extra = dict(extra or {})
    others = np.column_stack([np.asarray(v, float) for v in extra.values()]) if extra else np.zeros((n, 0))
    table = np.hstack([t, np.asarray(r, float), np.asarray(u, float), dv, np.asarray(y, float), others])
    header = csv_header(inputs, outputs, disturbances) + list(extra)
    def write(tmp):
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            # csv.writer quotes a name that starts with a quote (or holds one), so the header reads back
            csv.writer(fh, lineterminator="\n").writerow(header)
            for row in table:
                fh.write(",".join(_fmt(v) for v in row) + "\n")

    # Written beside the file and renamed over it once complete: a write cut short (Ctrl-C, a full disk)
    # leaves no shorter log that would read as a valid one.
    replace_file(path, write)


def _fmt(v: float) -> str:
    if float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return repr(float(v))


def write_log_csv(path, log) -> None:
    """Write a :class:`~mpm_monitor.sim.closed_loop.ClosedLoopLog` (or :class:`LoggedData`) as CSV.

    Its measured disturbances (``dv``, ``disturbances``) and other channels (``extra``) are written
    when it has them.
    """
    write_csv(path, log.t, log.r, log.u, log.y, log.inputs, log.outputs, dv=getattr(log, "dv", None),
              disturbances=getattr(log, "disturbances", ()), extra=getattr(log, "extra", None))


def read_csv(path, model: PlantModel, started: "StartedCsvRead | None" = None,
             bad_values: str = "refuse") -> LoggedData:
    """Read and validate a CSV log against a model.

    Parameters
    ----------
    path : str or Path
    model : PlantModel
        Gives the channel names (outputs, inputs, measured disturbances) and the sample time.
    started : StartedCsvRead, optional
        :func:`start_csv_read` of the same ``path``: its bytes and its child's parse are used (and the
        child is waited for, whatever the outcome).  The result and the errors are the same as without.
    bad_values : {"refuse", "gap"}
        A row whose cell of one of the model's channels (not ``t``) is empty, not a number or not
        finite: ``refuse`` the file, naming its line and column (the default), or leave the row out
        as a missing sample (``gap``: the analysis goes around it, as around a row missing from the
        file), said in one of :attr:`~mpm_monitor.core.logged_data.LoggedData.notes`.  A row left out
        still needs its ``t`` (a bad one is refused: the row cannot be placed), and that ``t`` is refused
        as a kept row's would be when it repeats or goes back from the previous row's, kept or left out,
        lies off the sample grid, or lies more than 2^53 sample times after the first row's.

    Returns
    -------
    LoggedData
        With ``dv`` in the model's disturbance order, every other numeric column in ``extra`` and
        the columns that cannot be used in ``unusable`` (name -> reason); ``t`` skips the grid
        points of missing rows (:attr:`~mpm_monitor.core.logged_data.LoggedData.segments`).

    Raises
    ------
    DataFileError
        One line naming the file, the line and the column.
    """
    if started is not None:
        if str(started.path) != str(path):
            started.close()
            raise ValueError(f"read_csv({str(path)!r}): started is the read of {str(started.path)!r}")
        try:
            text = started.text()
            if text is not None:
                return parse_csv_text(text, model, source=str(path), cells=started.cells, bad_values=bad_values)
        finally:
            started.close()
        # not read or not UTF-8: the reading below says so, or reads the foreign header, as without `started`
    try:
        text = read_text(path, DataFileError, "data file", "a CSV file", encoding="utf-8-sig", gzip_ok=True,
                         nul_error=_NulBytes)
    except _NulBytes as exc:       # refused before the rest is read (a device that never ends, a binary stream)
        raise DataFileError(f"{exc}: expected a CSV text file") from None
    except DataFileError:
        text = _text_with_a_foreign_header(path)     # None: the bytes are not UTF-8 below the header too
        needed = csv_header(model.inputs, model.outputs, model.disturbances)
        try:
            names = [] if text is None else \
                [h.strip() for h in next(csv.reader(io.StringIO(text.split("\n", 1)[0])), [])]
        except csv.Error:
            names = []
        if text is None or any(h not in names for h in needed):
            raise                                      # a column the model needs is the one not UTF-8
        data = parse_csv_text(text, model, source=str(path), bad_values=bad_values)
        for name in [n for n in list(data.extra) if BAD_NAME_CHAR in n]:
            del data.extra[name]
            data.unusable[name] = "its name in the header is not UTF-8 text"
        return data
    return parse_csv_text(text, model, source=str(path), bad_values=bad_values)


class _NulBytes(DataFileError):
    """NUL bytes at the start of a data file (:func:`~mpm_monitor.io.files.read_text`'s ``nul_error``)."""


#: What a row with a bad value of the model's channels does (:func:`read_csv`): refuse the file, or leave the row
#: out as a missing sample.
BAD_VALUES = ("refuse", "gap")

#: Stands for a byte of the header that is not UTF-8 (a column name written in Latin-1, say).
BAD_NAME_CHAR = "\ufffd"


def _text_with_a_foreign_header(path):
    """The file's text when only its header line has bytes that are not UTF-8 (replaced by
    :data:`BAD_NAME_CHAR`); None otherwise.  Extra columns are ignored, so a Latin-1 name of one of them
    does not refuse the file; a needed column so named is then missing, and refused as such.  A stream that is
    not a regular file (a pipe, a device) is not read again: None (its bytes are gone, and ``/dev/urandom``
    would be read until the memory ran out)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        raw = gunzipped(Path(path).read_bytes(), path, DataFileError, "a CSV file")
    except (OSError, DataFileError):
        return None
    nl = raw.find(b"\n")
    head, body = (raw, b"") if nl < 0 else (raw[:nl + 1], raw[nl + 1:])
    try:
        body_text = body.decode("utf-8")
    except UnicodeDecodeError:
        return None
    head_text = head.decode("utf-8-sig", errors="replace")
    if '"' in head_text:       # a quoted name may span lines: leave such files to the strict reading
        return None
    return head_text + body_text


def start_csv_read(path) -> "StartedCsvRead":
    """Read a CSV log's bytes now and start numpy's C parse of them in a forked child.

    For :func:`read_csv` (its ``started``), which checks the table against the model: meanwhile the
    caller does other work (the command line imports the analysis and loads the model).  Nothing is
    refused here: a file that cannot be read, that is not UTF-8 or that the C parser does not take
    is read by :func:`read_csv` as without a start, with the same messages.  In a process that runs
    other threads, or without ``fork``, the parse runs here at once (:class:`~mpm_monitor.core.parallel.Forked`).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    StartedCsvRead
        To pass to :func:`read_csv`; :meth:`StartedCsvRead.close` it when it is not read.
    """
    return StartedCsvRead(path)


#: Bytes of the body in one piece of a started read's parse (the child and the parent take pieces).
PIECE_BYTES = 1 << 20

_FREE, _CHILD, _PARENT = 0, 1, 2


class StartedCsvRead:
    """A CSV log's bytes and the child process parsing them (:func:`start_csv_read`).

    The body (below the header) is cut after line ends into pieces of about :data:`PIECE_BYTES`.  The
    child parses the pieces from the first on and writes their rows into shared memory; the parent,
    once it asks for the table (:meth:`cells`), parses the pieces from the last back, until the two
    meet.  Each claims a piece in a shared byte map before parsing it; a piece both claim at once is
    parsed twice and the parent's copy kept.  Each line is parsed by itself, so the pieces' rows
    stacked are the table :func:`_fast_cells` reads from the whole text, and a piece it would refuse
    means the whole is refused (:func:`_piece_cells`).

    Parameters
    ----------
    path : str or Path
    """

    def __init__(self, path):
        self.path = path
        try:   # a regular file: read again on the way of a refusal, it gives the same bytes (a pipe would not)
            raw = Path(path).read_bytes() if stat.S_ISREG(os.stat(path).st_mode) else None
            if raw is not None:
                raw = gunzipped(raw, path, DataFileError, "a CSV file")
        except (OSError, ValueError):   # DataFileError too: a damaged gzip file
            raw = None                  # read_csv reads the file as without a start, and says why
        self._raw, self._text, self._job = raw, None, None
        self._pieces = [] if raw is None else _pieces(raw, PIECE_BYTES)
        if not self._pieces:
            return                      # nothing to parse, or a header the fast path refuses: cells() says so
        try:
            # A row of c numbers takes at least 2 c bytes with its commas and line end, so 4 bytes of
            # float64 per byte of the body hold the table (a page is used only once written).
            self._claims = mmap.mmap(-1, len(self._pieces))
            self._shared = mmap.mmap(-1, 4 * (len(raw) - self._pieces[0][0] + 1))
        except (OSError, ValueError, OverflowError):
            self._pieces = []
            return
        pieces, claims, shared = self._pieces, self._claims, self._shared
        self._job = Forked(lambda: _child_pieces(raw, pieces, claims, shared))

    def text(self):
        """The bytes decoded as :func:`read_csv` decodes a file; None when they were not read or are not UTF-8."""
        if self._text is None and self._raw is not None:
            try:
                self._text = self._raw.decode("utf-8-sig")
            except UnicodeDecodeError:
                self._raw = None
        return self._text

    def cells(self):
        """:func:`_fast_cells` of :meth:`text` (None when there is no text): the child's pieces and this
        process's, or the whole parsed here when the child failed; called once."""
        if self.text() is None:
            self.close()
            return None
        job, self._job = self._job, None
        if job is None:
            return _fast_cells(self.text())
        mine, first = [], len(self._pieces)
        for k in range(len(self._pieces) - 1, -1, -1):
            if self._claims[k] != _FREE:
                break
            self._claims[k] = _PARENT
            part = _piece_cells(self._raw, *self._pieces[k])
            if part is None:
                self._claims[:] = bytes([_PARENT]) * len(self._pieces)   # the child stops at its next piece
                mine = None
                break
            mine.insert(0, part)
            first = k
        try:
            done = job.result()
        except Exception:           # noqa: BLE001 - the child failed: the same parse, here
            done = False
        if done is False or (done is not None and mine is not None and done[0] < first):
            table = _fast_cells(self.text())
        elif done is None or mine is None:
            table = None            # a piece is refused, so is the whole
        else:
            rows, n_cols = sum(done[1][:first]), done[2]
            child = np.frombuffer(self._shared, dtype=np.float64, count=rows * n_cols).reshape(rows, n_cols) \
                if rows else None
            table = _stacked([child] + mine)
        self._raw = self._shared = None
        return table

    def close(self) -> None:
        """Stop the child at its next piece and wait for it, if its table was not taken, and let go of the
        file's bytes and text; idempotent."""
        job, self._job = self._job, None
        if job is not None:
            self._claims[:] = bytes([_PARENT]) * len(self._pieces)
            try:
                job.result()
            except Exception:       # noqa: BLE001 - its table is not wanted
                pass
        self._raw = self._text = self._shared = None


def _pieces(raw: bytes, size: int) -> list:
    """``[(start, end)]`` of the body of ``raw`` (below the first line end) cut after line ends every
    ``size`` bytes or so; [] when there is no body, or a header :func:`_fast_cells` refuses (a quote, a
    carriage return that does not end it) or that is not UTF-8."""
    nl = raw.find(b"\n")
    if nl < 0 or nl + 1 == len(raw):
        return []
    head = raw[:nl]
    if b'"' in head or b"\r" in head.rstrip(b"\r"):
        return []
    try:
        head.decode("utf-8-sig")
    except UnicodeDecodeError:
        return []
    cuts = [nl + 1]
    while True:
        k = raw.find(b"\n", cuts[-1] + max(size, 1) - 1)
        if k < 0 or k + 1 >= len(raw):
            break
        cuts.append(k + 1)
    cuts.append(len(raw))
    return list(zip(cuts[:-1], cuts[1:]))


def _piece_cells(raw: bytes, start: int, end: int):
    """numpy's table of the lines of ``raw[start:end]`` (a piece of the body that ends at a line end or at
    the end of the file) under the checks of :func:`_fast_cells`, shape (n_rows, n_columns); (0, 0) when
    the piece has no line but empty ones (numpy skips them); None where :func:`_fast_cells` would refuse
    the whole text for this piece (a quote, a stray carriage return, a long line, a cell numpy does not
    take as a number, rows of different lengths)."""
    try:
        text = raw[start:end].decode("utf-8")
    except UnicodeDecodeError:
        return None
    lines = (text[:-1] if end < len(raw) else text).split("\n")     # the lines body.split("\n") holds here
    if not any(lines):            # only line ends: no quote or carriage return to refuse either
        return np.empty((0, 0))
    return _numpy_cells(text, lines)


def _child_pieces(raw: bytes, pieces: list, claims, shared):
    """The child's part of a started read: the pieces from the first on, until one the parent claimed,
    their rows written one after the other into ``shared``.

    Returns
    -------
    tuple or None
        ``(pieces done, rows of each, columns)``; None when a piece is refused (the parent then stops too).
    """
    rows, n_cols, offset = [], None, 0
    for k, (start, end) in enumerate(pieces):
        if claims[k] != _FREE:
            break
        claims[k] = _CHILD
        part = _piece_cells(raw, start, end)
        if part is not None and part.shape[0]:
            if offset + part.nbytes > len(shared):      # not by the bound above: the parent parses it all
                raise RuntimeError("the table does not fit the shared memory")
            if n_cols is not None and part.shape[1] != n_cols:
                part = None
            else:
                n_cols = part.shape[1]
                view = np.frombuffer(shared, dtype=np.float64, count=part.size, offset=offset)
                view.reshape(part.shape)[...] = part
                offset += part.nbytes
        if part is None:
            claims[:] = bytes([_CHILD]) * len(pieces)
            return None
        rows.append(part.shape[0])
    return len(rows), rows, n_cols


def _stacked(parts: list):
    """The tables of consecutive pieces (None or without rows: none there) as one, or None when no piece
    has a row or their numbers of columns differ (numpy refuses the whole)."""
    parts = [p for p in parts if p is not None and p.shape[0]]
    if not parts or len({p.shape[1] for p in parts}) > 1:
        return None
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def parse_csv_text(text: str, model: PlantModel, source: str = "data", cells=None,
                   bad_values: str = "refuse") -> LoggedData:
    """Parse the text of a CSV log (see :func:`read_csv`).

    Parameters
    ----------
    text : str
    model : PlantModel
    source : str
        Names the file in messages.
    cells : callable, optional
        ``cells()`` gives :func:`_fast_cells` of ``text`` computed elsewhere (:meth:`StartedCsvRead.cells`);
        called only once the header has been checked.  By default it is computed here.
    bad_values : {"refuse", "gap"}
        See :func:`read_csv`.
    """
    if bad_values not in BAD_VALUES:
        raise ValueError(f"bad_values: expected one of {', '.join(BAD_VALUES)}, got {bad_values!r}")
    if "\x00" in text:
        raise DataFileError(f"{source}: contains NUL bytes: expected a CSV text file")
    needed = csv_header(model.inputs, model.outputs, model.disturbances)
    layout = "t, r_<output>, <input>, " + ("<disturbance>, " if model.disturbances else "") + "<output>"
    header = _read_header(text, needed, layout, source)
    idx = [header.index(h) for h in needed]
    others, unusable = _other_columns(header, needed)
    table = _fast_table(text, len(header), cells)
    fast = table is not None and bool(np.isfinite(table).all())
    left_out = []
    if fast:
        values = table[:, idx]
        extra = {name: np.ascontiguousarray(table[:, k]) for name, k in others}
        lines = None
    else:
        values, lines, cells, left_out = _careful_table(text, header, needed, idx, [k for _, k in others], source,
                                                        gap=bad_values == "gap")
        notes = [_left_out_note(source, left_out)] if left_out else []
        extra = {}
        for (name, _), column in zip(others, cells):
            data, reason = _numeric_column(column, lines)
            if reason:
                unusable[name] = reason
            else:
                extra[name] = data
    if not _spacing_ok(values[:, 0], model.sample_time):
        if lines is None:   # the careful parser names the lines
            values, lines, _, _ = _careful_table(text, header, needed, idx, [], source)
        _refuse_spacing(values[:, 0], lines, model.sample_time, source)
    _refuse_span(values[:, 0], lines, model.sample_time, source, text, header, needed, idx)
    if left_out:
        _refuse_left_out_times(values[:, 0], lines, left_out, model.sample_time, source)
    ny, nu, nd = model.n_outputs, model.n_inputs, model.n_disturbances
    parts = np.split(values, np.cumsum([1, ny, nu, nd]), axis=1)
    t, r, u, dv, y = (np.ascontiguousarray(p) for p in parts)
    return LoggedData(t=t[:, 0], r=r, u=u, y=y, inputs=model.inputs, outputs=model.outputs,
                      sample_time=model.sample_time, source=source, dv=dv, disturbances=model.disturbances,
                      extra=extra, unusable=unusable, notes=() if fast else tuple(notes))


def _left_out_note(source: str, left_out: list) -> str:
    """The note of the rows ``bad_values="gap"`` left out (``[(line, column, cell, t)]``, in file order)."""
    line, col, cell, _ = left_out[0]
    n = len(left_out)
    return (f"{source}: {n} row{'s' if n != 1 else ''} left out as missing samples (a value of the model's channels "
            f"empty, not a number or not finite; the first on line {line}, column '{col}': {cell[:40]!r}); the "
            f"analysis goes around {'them' if n != 1 else 'it'} as around rows missing from the file")


def _csv_error_text(exc: csv.Error, lines: int = 1) -> str:
    """The csv module's error in the terms of a log file: those a damaged export gives, said as what was
    found and what was expected; any other as the module words it.  ``lines``: the lines the record it
    failed in had taken (more than one: a quoted cell ran over line ends)."""
    text = str(exc)
    if text.startswith("new-line character seen in unquoted field"):
        return "a carriage return (\\r) inside the line, outside quotes: expected lines ending in \\n or \\r\\n"
    if text.startswith("unexpected end of data"):
        return "a quote (\") opened on this line is never closed: the file ends inside it"
    found = re.match(r"field larger than field limit \((\d+)\)", text)
    if found:
        if lines > 1:
            return (f"a quote (\") opened on this line is not closed {lines - 1:,} lines further on, where the "
                    f"quoted cell passes {int(found.group(1)):,} characters: expected numbers")
        return f"a field longer than {int(found.group(1)):,} characters: expected numbers"
    if "expected" in text and "after" in text and '"' in text:    # '","' expected after '"': a quote inside a cell
        return f"a quote (\") inside a quoted cell: {text}"
    return text


def _read_header(text: str, needed: list, layout: str, source: str) -> list:
    """The header's names (stripped), once every needed column appears exactly once in it.

    ``layout`` describes the needed columns in the message of a missing one.
    """
    nl = text.find("\n")
    first = text if nl < 0 or '"' in text[:nl] else text[:nl + 1]   # a quoted name may hold a line break
    reader = csv.reader(io.StringIO(first))
    try:
        header = next(reader)
    except StopIteration:
        raise DataFileError(f"{source}: empty file: expected a header line {','.join(needed)}") from None
    except csv.Error as exc:
        raise DataFileError(f"{source}: line 1: not valid CSV: {_csv_error_text(exc)}") from None
    header = [h.strip() for h in header]
    # A name written in another Unicode normal form reads as the model's ("ü" as "u" and a combining diaeresis,
    # as macOS exports write it, was a "missing column 'ü1'" beside a header that printed 'ü1').
    canonical = {unicodedata.normalize("NFC", n): n for n in needed}
    header = [h if h in needed or h.isascii() else canonical.get(unicodedata.normalize("NFC", h), h) for h in header]
    dup = sorted(h for h, c in collections.Counter(header).items() if c > 1 and h)
    for h in dup:
        if h in needed:
            raise DataFileError(f"{source}: line 1 (header): column '{h}' appears more than once")
    missing = [h for h in needed if h not in header]
    if missing:
        raise DataFileError(
            f"{source}: line 1 (header): missing column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(repr(m) for m in missing)} (expected {layout} with the model's names); "
            f"{_header_seen(first)}")
    return header


def _header_seen(first: str, limit: int = 120) -> str:
    """What the header line holds, for the message of a missing column: the line as read (characters that
    do not print, such as a second byte-order mark or a zero-width space, escaped), and the separator
    when it is not a comma."""
    line = first.split("\n", 1)[0].rstrip("\r")
    shown = repr(line[:limit])[1:-1] + ("..." if len(line) > limit else "")
    if "," not in line:
        for sep, name in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
            if sep in line:
                return f"the header reads '{shown}', its columns separated by {name}: expected commas"
    return f"the header reads '{shown}'"


def _other_columns(header: list, needed: list):
    """``[(name, index)]`` of the named columns the model does not use, and ``{name: reason}`` of the
    names that appear more than once (which of them would be meant is unknown)."""
    needed = set(needed)
    counts = collections.Counter(header)
    others, unusable = [], {}
    for k, h in enumerate(header):
        if not h:
            unusable[f"(column {k + 1})"] = "the header gives it no name: name it there to test it"
            continue
        if h in needed:
            continue
        if counts[h] > 1:
            unusable[h] = "the header names this column more than once"
        else:
            others.append((h, k))
    return others, unusable


def _fast_table(text: str, n_fields: int, cells=None):
    """Every cell below the header as float64 by numpy's C parser, shape (n_rows, n_fields), or None.

    None whenever the careful parser might read the file differently: a header or cells with
    quotes, a carriage return that does not end a line, a line longer than the csv module's field
    limit, a cell numpy does not take as a number, a row of another length, no rows.  (Both
    parsers round a number the same way: Python's correctly rounded decimal conversion.)
    ``cells()``, when given, stands for ``_fast_cells(text)``.
    """
    table = _fast_cells(text) if cells is None else cells()
    if table is None or table.shape[0] == 0 or table.shape[1] != n_fields:
        return None
    return table


def _fast_cells(text: str):
    """The part of :func:`_fast_table` that needs no header: the table numpy's C parser reads below the
    first line (any number of columns), or None where the careful parser might read the file differently."""
    nl = text.find("\n")
    if nl < 0:
        return None
    body = text[nl + 1:]
    if '"' in text[:nl] or "\r" in text[:nl].rstrip("\r"):
        return None
    return _numpy_cells(body, body.split("\n"))


def _numpy_cells(body: str, lines: list):
    """numpy's C parse of ``lines`` (``body`` split at its line ends: the whole body, or a piece of it),
    or None where the careful parser might read them differently: a quote, a carriage return that does
    not end a line, a line longer than the csv module's field limit, a cell numpy does not take as a
    number, rows of different lengths, no data."""
    if '"' in body or ("\r" in body and body.count("\r") != body.count("\r\n")):
        return None
    if max(map(len, lines)) > csv.field_size_limit():
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")      # "input contained no data" is a warning
            return np.loadtxt(lines, delimiter=",", comments=None, dtype=float, ndmin=2)
    except Exception:                           # noqa: BLE001 - the careful parser says what is wrong
        return None


def _careful_table(text: str, header: list, needed: list, idx: list, other_idx: list, source: str,
                   gap: bool = False):
    """The needed columns as floats, line by line, refusing the first bad line or cell (with ``gap``, a row whose
    needed cell other than ``t`` is not a finite number is left out instead).

    Returns
    -------
    values : ndarray, shape (n_rows, len(needed))
    lines : list of int
        File line of every row (blank lines are skipped but counted).
    cells : list of list of str
        The raw cells of the columns ``other_idx``, one list per column.
    left_out : list of (int, str, str, float)
        With ``gap``: the line, column and cell of every row left out (its first bad cell), and its ``t``
        (a finite number: a bad ``t`` is refused, the row cannot be placed).

    Raises
    ------
    DataFileError
        The line (and column) of the first row of another length, the first needed cell that is not
        a finite number, or the first line the csv module cannot read; no data lines.
    """
    # strict: a quote left open refuses the file where it opens, instead of taking every line after it as
    # one cell (the rest of the log lost without a word when that cell is one the model does not read).
    reader = csv.reader(io.StringIO(text), strict=True)
    next(reader)
    n_fields = len(header)
    rows, lines = [], []
    cells = [[] for _ in other_idx]
    left_out = []
    read = reader.line_num        # lines read: a record starts on the next one (a quoted cell may span lines)
    try:
        for fields in reader:
            line_no, read = read + 1, reader.line_num
            if not fields or all(not f.strip() for f in fields):
                continue  # blank line
            if len(fields) != n_fields:
                raise DataFileError(f"{source}: line {line_no}: expected {n_fields} fields as in the header, "
                                    f"got {len(fields)}")
            vals = []
            for col, k in zip(needed, idx):
                cell = fields[k].strip()
                try:
                    x = _cell_float(cell)
                except ValueError:
                    x = None
                if x is None or not math.isfinite(x):
                    if gap and col != "t":      # t is needed[0]: read, and finite, before any other cell
                        left_out.append((line_no, col, cell, vals[0]))
                        break
                    what = "a number" if x is None else "a finite number"
                    raise DataFileError(f"{source}: line {line_no}, column '{col}': expected {what}, "
                                        f"got {cell[:40]!r}")
                vals.append(x)
            if len(vals) < len(needed):
                continue
            rows.append(vals)
            lines.append(line_no)
            for column, k in zip(cells, other_idx):
                column.append(fields[k])
    except csv.Error as exc:
        raise DataFileError(f"{source}: line {read + 1}: not valid CSV: "
                            f"{_csv_error_text(exc, reader.line_num - read)}") from None
    if not rows:
        if left_out:          # every row left out: name the columns that did it, with the first bad cell
            counts = collections.Counter(col for _, col, _, _ in left_out)
            line, col, cell, _ = left_out[0]
            worst = ", ".join(f"'{c}' ({n} row{'s' if n != 1 else ''})" for c, n in counts.most_common(3))
            raise DataFileError(f"{source}: every one of its {len(left_out)} data lines left out for a bad value "
                                f"(empty, not a number or not finite) in {worst}; the first on line {line}, column "
                                f"'{col}': {cell[:40]!r}: expected numbers in the model's columns")
        raise DataFileError(f"{source}: no data lines after the header")
    return np.array(rows, dtype=float), lines, cells, left_out


def _numeric_column(cells: list, lines: list):
    """``(values, "")`` of a column of finite numbers, or ``(None, reason)`` naming its first bad line."""
    values = np.empty(len(cells))
    for k, raw in enumerate(cells):
        cell = raw.strip()
        if not cell:
            return None, f"partly missing: line {lines[k]} is empty"
        try:
            x = _cell_float(cell)
        except ValueError:
            return None, f"not numeric: line {lines[k]} holds {cell[:40]!r}"
        if not math.isfinite(x):
            return None, f"not a finite number on line {lines[k]} ({cell[:40]!r})"
        values[k] = x
    return values, ""


def _steps_off_grid(t: np.ndarray, ts: float) -> np.ndarray:
    """True for every step of ``t`` that is not a whole number (>= 1) of sample times, shape (n - 1,).

    A step of ``m`` sample times (``m >= 2``) skips ``m - 1`` grid points: a gap, accepted.  It may be off by
    :data:`SPACING_TOLERANCE` per sample time it spans (a clock 0.04 % slow makes a step of three samples
    0.12 % long), at most :data:`MAX_STEP_OFFSET` of one.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # t near +-1e308: an infinite step, refused
        steps = np.diff(t)
        m = np.maximum(np.rint(steps / ts), 1.0)
        return ~(np.abs(steps - m * ts) <= np.minimum(SPACING_TOLERANCE * m, MAX_STEP_OFFSET) * ts)


def _spacing_ok(t: np.ndarray, ts: float) -> bool:
    return not bool(np.any(_steps_off_grid(t, ts)))


def _refuse_span(t: np.ndarray, lines, ts: float, source: str, text, header, needed, idx) -> None:
    """Raise when ``t`` spans more than :data:`MAX_GRID_SAMPLES` sample times (a stray far-off ``t``, such as
    1e19 s, would make a gap whose length no integer counts), naming the first line beyond.  ``text``,
    ``header``, ``needed`` and ``idx`` serve only to find the lines when ``lines`` is None."""
    with np.errstate(over="ignore", invalid="ignore"):
        far = np.flatnonzero(~((t - t[0]) / ts <= MAX_GRID_SAMPLES))
    if far.size == 0:
        return
    if lines is None:
        _, lines, _, _ = _careful_table(text, header, needed, idx, [], source)
    k = int(far[0])
    raise DataFileError(f"{source}: line {lines[k]}: t = {t_text(t[k])} s lies {(t[k] - t[0]) / ts:.3g} sample times "
                        f"after the first sample (t = {t_text(t[0])} s): expected at most 2^53 (a stray t, or is the "
                        f"sample time right?)")


def _refuse_spacing(t: np.ndarray, lines: list, ts: float, source: str) -> None:
    """Raise for the first step of ``t`` that is not a whole number of sample times (naming its lines)."""
    bad = np.flatnonzero(_steps_off_grid(t, ts))
    _refuse_step(t, lines, int(bad[0]), ts, source)


def _refuse_left_out_times(t: np.ndarray, lines: list, left_out: list, ts: float, source: str) -> None:
    """Raise, as :func:`_refuse_spacing` and :func:`_refuse_span` do for the kept rows, when the ``t`` of a row
    ``bad_values="gap"`` left out is wrong as a kept row's would be: it repeats or goes back from the previous
    row's, or the next row's ``t`` repeats or goes back from it (the previous row kept or left out); the step to it
    or from it is not a whole number of sample times (off the grid, within the same tolerance); or it lies more
    than :data:`MAX_GRID_SAMPLES` sample times after the first row's.  The checks and messages are the kept
    rows', run on every row in file order, kept or left out; the kept rows alone have been checked before.

    Parameters
    ----------
    t : ndarray, shape (n_rows,)
        The kept rows' ``t``.
    lines : list of int
        Their file lines.
    left_out : list of (int, str, str, float)
        The rows left out (:func:`_careful_table`): line, column, cell, ``t``.
    ts : float
        The sample time.
    source : str
        Names the file in the message.
    """
    rows = sorted([(line, float(x)) for line, x in zip(lines, t)] + [(line, x) for line, _, _, x in left_out])
    every_t = np.array([x for _, x in rows])
    every_line = [line for line, _ in rows]
    if not _spacing_ok(every_t, ts):
        _refuse_spacing(every_t, every_line, ts, source)
    _refuse_span(every_t, every_line, ts, source, text=None, header=None, needed=None, idx=None)


def _refuse_step(t: np.ndarray, lines: list, k: int, ts: float, source: str) -> None:
    """Raise for the step of ``t`` from row ``k`` to row ``k + 1`` (file lines ``lines[k]``, ``lines[k + 1]``): one
    that repeats or goes back, or one that is not a whole number of sample times."""
    with np.errstate(over="ignore", invalid="ignore"):
        step = np.diff(t[k:k + 2])[0]
    # A t so large that 64-bit floats cannot tell its samples apart (1e16 s: 2 s apart) reads as repeated or
    # uneven whatever the file says: name that instead of blaming the log.
    resolution = float(np.spacing(max(abs(float(t[k])), abs(float(t[k + 1])))))
    coarse = "" if not resolution > SPACING_TOLERANCE * ts else (
        f" (at t = {t_text(t[k])} s, 64-bit numbers are {resolution:g} s apart, too coarse for the sample time: "
        f"give t from a nearer origin, e.g. seconds since the log's start)")
    if step <= 0:
        what = "repeats" if step == 0 else "goes back from"
        raise DataFileError(f"{source}: line {lines[k + 1]}: t = {t_text(t[k + 1])} s {what} t = {t_text(t[k])} s "
                            f"on line {lines[k]}: expected t to increase by sample_time {ts:g} s{coarse}")
    raise DataFileError(f"{source}: line {lines[k + 1]}: t = {t_text(t[k + 1])} s follows t = {t_text(t[k])} s: a step "
                        f"of {step:g} s (expected sample_time {ts:g} s; a gap or an irregular sample: every step a "
                        f"whole number of sample times, within {SPACING_TOLERANCE * 100:g} % per sample time){coarse}")
