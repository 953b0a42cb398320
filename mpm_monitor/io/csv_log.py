"""Logged closed-loop data as a CSV file (docs/interfaces.md, "Logged data (CSV)").

One row per sample, header ``t, r_<output>..., <input>..., <output>...``; column order is free and
extra columns are ignored.  Samples must be equally spaced at the model's sample time: a gap, a
repeated or decreasing ``t``, a missing column or a non-numeric cell is refused with the line and
column, never silently mis-aligned.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np

from ..core.errors import DataFileError
from ..core.logged_data import LoggedData
from ..core.model import PlantModel
from .files import read_text

#: Relative tolerance on the sample spacing, as a fraction of the sample time.
SPACING_TOLERANCE = 1e-3


def csv_header(inputs, outputs) -> list:
    """Column names of the CSV log in the canonical order: ``t, r_<output>..., <input>..., <output>...``."""
    return ["t"] + [f"r_{o}" for o in outputs] + list(inputs) + list(outputs)


def write_csv(path, t, r, u, y, inputs, outputs) -> None:
    """Write signals as the CSV log, with full float precision (lossless round trip).

    Parameters
    ----------
    path : str or Path
    t : ndarray, shape (n_samples,)
    r, y : ndarray, shape (n_samples, n_outputs)
    u : ndarray, shape (n_samples, n_inputs)
    inputs, outputs : sequence of str
    """
    t = np.asarray(t, dtype=float).reshape(-1, 1)
    table = np.hstack([t, np.asarray(r, float), np.asarray(u, float), np.asarray(y, float)])
    with open(path, "w", encoding="utf-8", newline="") as fh:
        # csv.writer quotes a name that starts with a quote (or holds one), so the header reads back
        csv.writer(fh, lineterminator="\n").writerow(csv_header(inputs, outputs))
        for row in table:
            fh.write(",".join(_fmt(v) for v in row) + "\n")


def _fmt(v: float) -> str:
    if float(v).is_integer() and abs(v) < 1e15:
        return str(int(v))
    return repr(float(v))


def write_log_csv(path, log) -> None:
    """Write a :class:`~mpm_monitor.sim.closed_loop.ClosedLoopLog` (or :class:`LoggedData`) as CSV."""
    write_csv(path, log.t, log.r, log.u, log.y, log.inputs, log.outputs)


def read_csv(path, model: PlantModel) -> LoggedData:
    """Read and validate a CSV log against a model.

    Parameters
    ----------
    path : str or Path
    model : PlantModel
        Gives the channel names and the sample time.

    Returns
    -------
    LoggedData

    Raises
    ------
    DataFileError
        One line naming the file, the line and the column.
    """
    text = read_text(path, DataFileError, "data file", "a CSV file", encoding="utf-8-sig")
    return parse_csv_text(text, model, source=str(path))


def parse_csv_text(text: str, model: PlantModel, source: str = "data") -> LoggedData:
    """Parse the text of a CSV log (see :func:`read_csv`)."""
    if "\x00" in text:
        raise DataFileError(f"{source}: contains NUL bytes: expected a CSV text file")
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except StopIteration:
        raise DataFileError(f"{source}: empty file: expected a header line {','.join(csv_header(model.inputs, model.outputs))}") from None
    except csv.Error as exc:
        raise DataFileError(f"{source}: line 1: not valid CSV: {exc}") from None
    header = [h.strip() for h in header]
    dup = sorted({h for h in header if header.count(h) > 1 and h})
    needed = csv_header(model.inputs, model.outputs)
    for h in dup:
        if h in needed:
            raise DataFileError(f"{source}: line 1 (header): column '{h}' appears more than once")
    missing = [h for h in needed if h not in header]
    if missing:
        raise DataFileError(
            f"{source}: line 1 (header): missing column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(repr(m) for m in missing)} (expected t, r_<output>, <input>, <output> with the model's names)")
    idx = [header.index(h) for h in needed]
    n_fields = len(header)
    rows = []
    try:
        for line_no, fields in enumerate(reader, start=2):
            if not fields or all(not f.strip() for f in fields):
                continue  # blank line
            if len(fields) != n_fields:
                raise DataFileError(f"{source}: line {line_no}: expected {n_fields} fields as in the header, "
                                    f"got {len(fields)}")
            vals = []
            for col, k in zip(needed, idx):
                cell = fields[k].strip()
                try:
                    x = float(cell)
                except ValueError:
                    raise DataFileError(f"{source}: line {line_no}, column '{col}': expected a number, "
                                        f"got {cell[:40]!r}") from None
                if not math.isfinite(x):
                    raise DataFileError(f"{source}: line {line_no}, column '{col}': expected a finite number, "
                                        f"got {cell[:40]!r}")
                vals.append(x)
            rows.append((line_no, vals))
    except csv.Error as exc:
        raise DataFileError(f"{source}: line {reader.line_num}: not valid CSV: {exc}") from None
    if not rows:
        raise DataFileError(f"{source}: no data lines after the header")
    table = np.array([v for _, v in rows], dtype=float)
    lines = [ln for ln, _ in rows]
    t = table[:, 0]
    ts = model.sample_time
    with np.errstate(over="ignore", invalid="ignore"):  # t near +-1e308: an infinite step, refused below
        steps = np.diff(t)
        bad = np.flatnonzero(~(np.abs(steps - ts) <= SPACING_TOLERANCE * ts))
    if bad.size:
        k = int(bad[0])
        step = steps[k]
        if step <= 0:
            what = "repeats" if step == 0 else "goes back from"
            raise DataFileError(f"{source}: line {lines[k + 1]}: t = {t[k + 1]:g} s {what} t = {t[k]:g} s on line "
                                f"{lines[k]}: expected t to increase by sample_time {ts:g} s")
        raise DataFileError(f"{source}: line {lines[k + 1]}: t = {t[k + 1]:g} s follows t = {t[k]:g} s: a step of "
                            f"{step:g} s (expected sample_time {ts:g} s; a gap or an irregular sample)")
    ny, nu = model.n_outputs, model.n_inputs
    r = table[:, 1:1 + ny]
    u = table[:, 1 + ny:1 + ny + nu]
    y = table[:, 1 + ny + nu:]
    return LoggedData(t=t, r=r, u=u, y=y, inputs=model.inputs, outputs=model.outputs, sample_time=ts,
                      source=source)
