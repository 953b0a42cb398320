"""Logged data CSV (docs/interfaces.md, "Logged data (CSV)"): lossless round trip and refusal of every bad file.

Every bad file must raise :class:`DataFileError` with a one-line message naming the file and,
where there is one, the line and the column.
"""

import re

import numpy as np
import pytest

from mpm_monitor.core.errors import DataFileError, InputError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.csv_log import csv_header, parse_csv_text, read_csv, write_csv, write_log_csv

HEADER = "t,r_y1,r_y2,u1,u2,u3,y1,y2"


def _model(ts=1.0):
    return PlantModel(sample_time=ts, inputs=("u1", "u2", "u3"), outputs=("y1", "y2"),
                      gain=[[1.0, 2.0, 0.0], [0.5, 0.0, 3.0]], time_constant=[[10.0, 5.0, 0.0], [3.0, 0.0, 8.0]],
                      delay=[[1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])


def _rows(n=5, ts=1.0):
    """Good data lines: row k has t = k ts and cells 10k + column index."""
    return [",".join([repr(k * ts)] + [str(10 * k + c) for c in range(1, 8)]) for k in range(n)]


def _text(lines):
    return "\n".join(lines) + "\n"


def _write(tmp_path, content, name="data.csv"):
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- good files


@pytest.mark.parametrize("ts", [1.0, 0.1, 0.02])
def test_write_read_round_trip_is_lossless(tmp_path, ts):
    # Full-precision floats of all magnitudes (and exact integers) come back bit-identical.
    rng = np.random.default_rng(int(ts * 100))
    n = 257
    model = _model(ts)
    t = np.arange(n) * ts
    scale = 10.0 ** rng.integers(-300, 300, size=(n, 1))
    r = rng.standard_normal((n, 2)) * scale
    u = rng.standard_normal((n, 3))
    y = rng.standard_normal((n, 2)) * 1e-7
    u[::7] = np.round(u[::7] * 1000)  # integer-valued cells take the integer format
    r[3, 0], u[4, 1], y[5, 1] = 0.0, 5e-324, -1.7976931348623157e308  # extremes
    path = tmp_path / "log.csv"
    write_csv(path, t, r, u, y, model.inputs, model.outputs)
    data = read_csv(path, model)
    for key, ref in (("t", t), ("r", r), ("u", u), ("y", y)):
        np.testing.assert_array_equal(getattr(data, key), ref)  # exact, no tolerance
    assert data.inputs == model.inputs and data.outputs == model.outputs
    assert data.sample_time == ts and data.n_samples == n and data.source == str(path)
    assert path.read_text(encoding="utf-8").splitlines()[0] == HEADER


def test_write_log_csv_round_trip(tmp_path):
    from mpm_monitor.sim.cases import paper_case
    from mpm_monitor.sim.closed_loop import run_closed_loop
    from mpm_monitor.sim.mpc import MpcOptions

    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 60, mpc=MpcOptions(prediction_horizon=30, control_horizon=5))
    path = tmp_path / "log.csv"
    write_log_csv(path, log)
    data = read_csv(path, case.model)
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(data, key), getattr(log, key))


def test_header_is_the_contract_order():
    assert ",".join(csv_header(("u1", "u2", "u3"), ("y1", "y2"))) == HEADER


def test_column_order_free_and_extra_columns_ignored(tmp_path):
    model = _model()
    canonical = read_csv(_write(tmp_path, _text([HEADER] + _rows()), "a.csv"), model)
    # Shuffle the columns, add extra columns (one of them non-numeric), pad with spaces.
    names = HEADER.split(",")
    rng = np.random.default_rng(0)
    order = rng.permutation(len(names))
    lines = [" , ".join(["note"] + [names[i] for i in order] + ["y3_extra"])]
    for k, row in enumerate(_rows()):
        cells = row.split(",")
        lines.append(",".join([f"free text {k}"] + [cells[i] for i in order] + ["not a number"]))
    shuffled = read_csv(_write(tmp_path, _text(lines), "b.csv"), model)
    assert list(order) != list(range(len(names)))
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(shuffled, key), getattr(canonical, key))
    # The values went to the right columns: cell (k, c) = 10 k + c in canonical order.
    k = np.arange(5)[:, None]
    np.testing.assert_array_equal(canonical.r, 10 * k + np.array([1, 2]))
    np.testing.assert_array_equal(canonical.u, 10 * k + np.array([3, 4, 5]))
    np.testing.assert_array_equal(canonical.y, 10 * k + np.array([6, 7]))


def test_crlf_bom_and_blank_lines_accepted(tmp_path):
    model = _model()
    text = "\r\n".join([HEADER] + _rows()[:2] + [""] + _rows()[2:]) + "\r\n"
    data = read_csv(_write(tmp_path, b"\xef\xbb\xbf" + text.encode("utf-8")), model)
    assert data.n_samples == 5
    np.testing.assert_array_equal(data.t, np.arange(5.0))


def test_spacing_within_tolerance_accepted(tmp_path):
    # t written with 0.1 steps accumulates rounding (0.30000000000000004): still equally spaced.
    model = _model(0.1)
    t = np.cumsum(np.full(50, 0.1)) - 0.1
    lines = [HEADER] + [",".join([repr(float(tk))] + ["0"] * 7) for tk in t]
    assert read_csv(_write(tmp_path, _text(lines)), model).n_samples == 50


# --------------------------------------------------------------------------- bad files


def _with_line(k, new_line):
    """Good file with data line k (0-based; file line k + 2) replaced."""
    rows = _rows()
    rows[k] = new_line
    return _text([HEADER] + rows)


def _with_cell(k, col, value):
    cells = _rows()[k].split(",")
    cells[HEADER.split(",").index(col)] = value
    return _with_line(k, ",".join(cells))


BAD_FILES = {
    "missing column": (_text([HEADER.replace(",u2", "")] + [",".join(r.split(",")[:4] + r.split(",")[5:]) for r in _rows()]),
                       r"line 1 \(header\): missing column 'u2'"),
    "missing columns": (_text(["t,r_y1,u1,u2,u3,y1"] + ["0,1,2,3,4,5"]),
                        r"line 1 \(header\): missing columns 'r_y2', 'y2'"),
    "missing t": (_text([HEADER.replace("t,", "time,")] + _rows()), r"line 1 \(header\): missing column 't'"),
    "duplicate column": (_text([HEADER + ",u1"] + [r + ",0" for r in _rows()]),
                         r"line 1 \(header\): column 'u1' appears more than once"),
    "non-numeric cell": (_with_cell(2, "u2", "abc"), r"line 4, column 'u2': expected a number, got 'abc'"),
    "empty cell": (_with_cell(1, "y1", ""), r"line 3, column 'y1': expected a number, got ''"),
    "NaN cell": (_with_cell(3, "r_y2", "NaN"), r"line 5, column 'r_y2': expected a finite number, got 'NaN'"),
    "nan cell lower case": (_with_cell(0, "y2", "nan"), r"line 2, column 'y2': expected a finite number"),
    "inf cell": (_with_cell(4, "u3", "inf"), r"line 6, column 'u3': expected a finite number, got 'inf'"),
    "-Infinity cell": (_with_cell(2, "t", "-Infinity"), r"line 4, column 't': expected a finite number"),
    "off the grid after a gap": (_with_cell(3, "t", "4.5"),
                                 r"line 5: t = 4.5 s follows t = 2 s: a step of 2.5 s \(expected sample_time 1 s; "
                                 r"a gap"),
    "repeated t": (_with_cell(2, "t", "1.0"), r"line 4: t = 1 s repeats t = 1 s on line 3"),
    "decreasing t": (_with_cell(3, "t", "0.5"), r"line 5: t = 0.5 s goes back from t = 2 s on line 4"),
    "irregular t": (_with_cell(2, "t", "2.5"), r"line 4: t = 2.5 s follows t = 1 s"),
    "too few fields": (_with_line(2, "2,21,22,23"), r"line 4: expected 8 fields as in the header, got 4"),
    "too many fields": (_with_line(1, _rows()[1] + ",99"), r"line 3: expected 8 fields as in the header, got 9"),
    "empty file": ("", r"empty file: expected a header line t,r_y1,r_y2,u1,u2,u3,y1,y2"),
    "header only": (_text([HEADER]), r"no data lines after the header"),
    "header and blank lines only": (_text([HEADER, "", " , ", ""]), r"no data lines after the header"),
    "not UTF-8": (_text([HEADER] + _rows()).encode("utf-8").replace(b"\n2.0,", b"\n2\xff.0,"),
                  r"not UTF-8 text \(byte \d+\)"),
    "binary": (b"\x00\x01\x02t,r_y1\n", r"contains NUL bytes"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_csv_refused_with_one_line_naming_line_and_column(tmp_path, case):
    content, pattern = BAD_FILES[case]
    path = _write(tmp_path, content)
    with pytest.raises(DataFileError, match=pattern) as info:
        read_csv(path, _model())
    msg = str(info.value)
    assert "\n" not in msg, msg
    assert msg.startswith(str(path) + ": "), msg
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)


def _read_capped(device: str):
    """``read_csv(device, ...)`` in a child whose address space is capped at 1.5 GB, with a time limit: a reader
    that reads an endless device whole fails there instead of taking the machine's memory."""
    import resource
    import subprocess
    import sys

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))

    code = ("from mpm_monitor.io.csv_log import read_csv\n"
            "from mpm_monitor.core.model import PlantModel\n"
            "m = PlantModel(sample_time=1.0, inputs=('u1',), outputs=('y1',), gain=[[1.0]], time_constant=[[5.0]],"
            " delay=[[1.0]])\n"
            f"read_csv({device!r}, m)\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, preexec_fn=cap)


def test_an_endless_binary_input_is_refused_before_it_is_read_whole():
    """``--data /dev/zero`` was read until the kernel killed the process (24 GB); the NUL bytes at its start now
    refuse it at once.  Run in a child with its address space capped at 1.5 GB and a time limit, so that the old
    behaviour fails the test instead of taking the machine's memory."""
    res = _read_capped("/dev/zero")
    assert res.returncode == 1 and "DataFileError: /dev/zero: contains NUL bytes: expected a CSV text file" in \
        res.stderr, res.stderr[-500:]


def test_an_endless_stream_that_is_not_utf8_is_refused_before_it_is_read_whole():
    """An outside check: ``--data /dev/urandom`` was read at about 250 MB/s until the memory ran out (its start is
    not UTF-8 and holds no NUL byte that would refuse it at once; the reader's fallback for a Latin-1 header then
    read the stream again).  Refused at once, as it would be read whole: the first byte that is not UTF-8, and its
    line.  A child with its address space capped at 1.5 GB, so that the old behaviour fails instead."""
    res = _read_capped("/dev/urandom")
    assert res.returncode == 1 and re.search(r"DataFileError: /dev/urandom: not UTF-8 text \(byte \d+\) on line \d+, "
                                             r"character \d+: expected a CSV file", res.stderr), res.stderr[-500:]


def test_a_piped_log_not_utf8_after_its_start_gets_the_message_of_a_file(tmp_path):
    """The same log through a pipe and as a file: the same refusal (a stream's start is looked at first)."""
    import subprocess
    import sys

    good = _text([HEADER] + _rows())
    path = tmp_path / "bad.csv"
    path.write_bytes(good.encode() + b"1,2,\xff\n")
    with pytest.raises(DataFileError) as info:
        read_csv(path, _model())
    code = ("import sys\nfrom mpm_monitor.io.csv_log import read_csv\n"
            "from mpm_monitor.core.model import PlantModel\n"
            "m = PlantModel(sample_time=1.0, inputs=('u1', 'u2', 'u3'), outputs=('y1', 'y2'), gain=[[1.0, 2.0, 0.0], "
            "[0.5, 0.0, 3.0]], time_constant=[[10.0, 5.0, 0.0], [3.0, 0.0, 8.0]], delay=[[1.0, 2.0, 0.0], "
            "[0.0, 0.0, 1.0]])\n"
            "try:\n    read_csv('/dev/stdin', m)\nexcept Exception as e:\n    print(e)\n")
    res = subprocess.run([sys.executable, "-c", code], input=path.read_bytes(), capture_output=True, timeout=120)
    assert res.stdout.decode().strip() == str(info.value).replace(str(path), "/dev/stdin"), res


def test_line_numbers_count_blank_lines(tmp_path):
    # A blank line is skipped but still counted: the error names the line as an editor shows it.
    rows = _rows()
    rows[3] = rows[3].replace(",31,", ",x,")
    text = _text([HEADER, rows[0], "", rows[1], rows[2], rows[3], rows[4]])
    with pytest.raises(DataFileError, match=r"line 6, column 'r_y1': expected a number, got 'x'"):
        read_csv(_write(tmp_path, text), _model())


def test_spacing_checked_against_the_model_sample_time(tmp_path):
    # Samples 1.5 s apart are off the grid of a 1 s model: refused, not silently re-timed.
    with pytest.raises(DataFileError,
                       match=r"line 3: t = 1.5 s follows t = 0 s: a step of 1.5 s \(expected sample_time 1 s"):
        read_csv(_write(tmp_path, _text([HEADER] + _rows(ts=1.5))), _model(1.0))


# --------------------------------------------------------------------------- gaps (docs/interfaces.md, "Gaps")
# Until the interface "Gaps" a t that skipped grid points was refused ("gap in t"); it now reads as data with gaps.


def test_a_t_that_skips_grid_points_is_read_as_data_with_gaps(tmp_path):
    rows = _rows(8)
    del rows[5], rows[3]            # rows of t = 3 and t = 5 missing
    data = read_csv(_write(tmp_path, _text([HEADER] + rows)), _model())
    np.testing.assert_array_equal(data.t, [0, 1, 2, 4, 6, 7])
    np.testing.assert_array_equal(data.grid_index, [0, 1, 2, 4, 6, 7])
    assert data.segments == [(0, 3), (3, 4), (4, 6)]
    np.testing.assert_array_equal(data.u[:, 0], 10 * np.array([0, 1, 2, 4, 6, 7]) + 3)   # nothing interpolated


def test_samples_1_s_apart_for_a_half_second_model_are_every_other_sample(tmp_path):
    # On the grid (every other point missing), so read as gaps; the analysis then finds no span to use.
    data = read_csv(_write(tmp_path, _text([HEADER] + _rows())), _model(0.5))
    np.testing.assert_array_equal(data.grid_index, [0, 2, 4, 6, 8])
    assert len(data.segments) == 5


def test_gaps_read_the_same_by_the_fast_and_the_careful_parser(tmp_path):
    rows = _rows(8)
    del rows[4]
    text = _text([HEADER] + rows)
    fast = read_csv(_write(tmp_path, text), _model())
    noted = _text([HEADER + ",note"] + [row + ",x" for row in rows])      # text cells: the careful parser
    careful = read_csv(_write(tmp_path, noted, "noted.csv"), _model())
    assert "note" in careful.unusable
    np.testing.assert_array_equal(fast.t, careful.t)
    np.testing.assert_array_equal(fast.y, careful.y)
    assert fast.segments == careful.segments == [(0, 4), (4, 7)]


@pytest.mark.parametrize("t3, pattern", [("2.0", r"line 5: t = 2 s repeats t = 2 s on line 4"),
                                         ("1.0", r"line 5: t = 1 s goes back from t = 2 s on line 4"),
                                         ("3.5", r"line 5: t = 3.5 s follows t = 2 s: a step of 1.5 s"),
                                         ("5.2", r"line 5: t = 5.2 s follows t = 2 s: a step of 3.2 s")])
def test_repeated_decreasing_or_off_grid_t_still_refused_next_to_gaps(tmp_path, t3, pattern):
    rows = _rows(8)
    rows[3] = ",".join([t3] + rows[3].split(",")[1:])
    del rows[6]                     # a real gap later in the file
    with pytest.raises(DataFileError, match=pattern):
        read_csv(_write(tmp_path, _text([HEADER] + rows)), _model())


def test_t_beyond_the_precision_of_floats_is_named_so(tmp_path):
    """t = 1e16 + k s: 64-bit floats are 2 s apart there, so the log's own steps of 1 s read as repeats; the
    refusal says why, and what to do.  A plain repeat of a small t keeps its message without the hint."""
    rows = [",".join([str(10 ** 16 + k)] + line.split(",")[1:]) for k, line in enumerate(_rows(6))]
    with pytest.raises(DataFileError, match=r"line 3: t = 1e\+16 s repeats .* 64-bit numbers are 2 s apart, too "
                                            r"coarse for the sample time: give t from a nearer origin") as err:
        read_csv(_write(tmp_path, _text([HEADER] + rows)), _model())
    assert "\n" not in str(err.value)
    rows = _rows(6)
    rows[3] = ",".join(["2.0"] + rows[3].split(",")[1:])
    with pytest.raises(DataFileError) as err:
        read_csv(_write(tmp_path, _text([HEADER] + rows), "small.csv"), _model())
    assert "64-bit" not in str(err.value)


def test_unreadable_path_refused(tmp_path):
    with pytest.raises(DataFileError, match=r"cannot read data file"):
        read_csv(tmp_path / "missing.csv", _model())


def test_parse_text_uses_source_name():
    with pytest.raises(DataFileError, match=r"^mylog: line 1 \(header\): missing column 'y2'"):
        parse_csv_text("t,r_y1,r_y2,u1,u2,u3,y1\n0,0,0,0,0,0,0\n", _model(), source="mylog")


# --------------------------------------------------------------------------- measured disturbances, other columns


def _dv_model():
    return PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), disturbances=("feed_temp",),
                      gain=[[1.0, 0.5, 0.2]], time_constant=[[5.0, 5.0, 8.0]], delay=[[0.0, 1.0, 2.0]])


def test_disturbance_columns_written_after_the_inputs_and_read_by_name(tmp_path):
    model = _dv_model()
    rng = np.random.default_rng(3)
    n = 40
    t, r, u, dv, y = np.arange(n) * 1.0, rng.normal(size=(n, 1)), rng.normal(size=(n, 2)), \
        rng.normal(size=(n, 1)), rng.normal(size=(n, 1))
    path = tmp_path / "dv.csv"
    write_csv(path, t, r, u, y, model.inputs, model.outputs, dv=dv, disturbances=model.disturbances)
    assert path.read_text().splitlines()[0] == "t,r_y1,u1,u2,feed_temp,y1"
    assert csv_header(model.inputs, model.outputs, model.disturbances) == ["t", "r_y1", "u1", "u2", "feed_temp", "y1"]
    data = read_csv(path, model)
    assert data.disturbances == ("feed_temp",)
    np.testing.assert_array_equal(data.dv, dv)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)
    assert data.extra == {} and data.unusable == {}
    # Column order is free: the disturbance is found by its name.
    lines = path.read_text().splitlines()
    moved = [",".join([c.split(",")[4]] + c.split(",")[:4] + c.split(",")[5:]) for c in lines]
    again = read_csv(_write(tmp_path, _text(moved), "moved.csv"), model)
    np.testing.assert_array_equal(again.dv, dv)
    np.testing.assert_array_equal(again.t, t)


def test_bad_disturbance_column_refused_like_any_column_the_model_needs(tmp_path):
    model = _dv_model()
    header = "t,r_y1,u1,u2,feed_temp,y1"
    rows = [f"{k},1,2,3,4,5" for k in range(5)]
    with pytest.raises(DataFileError, match=r"line 1 \(header\): missing column 'feed_temp' \(expected t, "
                                            r"r_<output>, <input>, <disturbance>, <output>"):
        read_csv(_write(tmp_path, _text(["t,r_y1,u1,u2,y1"] + [r[:-4] + ",5" for r in rows])), model)
    rows[3] = "3,1,2,3,n/a,5"
    with pytest.raises(DataFileError, match=r"line 5, column 'feed_temp': expected a number, got 'n/a'"):
        read_csv(_write(tmp_path, _text([header] + rows)), model)


def test_other_numeric_columns_kept_as_extra_and_bad_ones_reported_unusable(tmp_path):
    lines = [HEADER + ",feed,status,ambient,partly,  ,dup,dup"]
    for k, row in enumerate(_rows(6)):
        partly = "" if k == 4 else str(k)
        ambient = "1e-3" if k % 2 else "-7"
        lines.append(row + f",{k * 0.5},{'OK' if k else 'start'},{ambient},{partly},,{k},{k}")
    data = read_csv(_write(tmp_path, _text(lines)), _model())
    assert sorted(data.extra) == ["ambient", "feed"]
    np.testing.assert_array_equal(data.extra["feed"], np.arange(6) * 0.5)
    np.testing.assert_array_equal(data.extra["ambient"], [-7, 1e-3, -7, 1e-3, -7, 1e-3])
    # The column without a name (a blank header cell) was left out without a word, so that a channel logged under
    # it was missing from --candidates all: it is named by its place instead.
    blank = f"(column {HEADER.count(',') + 6})"
    assert data.unusable == {"status": "not numeric: line 2 holds 'start'",
                             "partly": "partly missing: line 6 is empty",
                             "dup": "the header names this column more than once",
                             blank: "the header gives it no name: name it there to test it"}
    # The model's own columns are unaffected.
    np.testing.assert_array_equal(data.t, np.arange(6.0))
    assert data.u.shape == (6, 3)
    sliced = data.slice(1, 4)
    np.testing.assert_array_equal(sliced.extra["feed"], [0.5, 1.0, 1.5])


def test_non_finite_extra_cell_makes_the_column_unusable_not_the_file(tmp_path):
    lines = [HEADER + ",feed"] + [row + (",nan" if k == 2 else f",{k}") for k, row in enumerate(_rows())]
    data = read_csv(_write(tmp_path, _text(lines)), _model())
    assert data.extra == {}
    assert data.unusable == {"feed": "not a finite number on line 4 ('nan')"}
    assert data.n_samples == 5


def test_extra_columns_round_trip_through_the_writer(tmp_path):
    model = _model()
    n = 30
    rng = np.random.default_rng(5)
    extra = {"feed": rng.normal(size=n), "valve pos": np.round(rng.normal(size=n) * 100)}
    path = tmp_path / "extra.csv"
    write_csv(path, np.arange(n), rng.normal(size=(n, 2)), rng.normal(size=(n, 3)), rng.normal(size=(n, 2)),
              model.inputs, model.outputs, extra=extra)
    data = read_csv(path, model)
    assert list(data.extra) == ["feed", "valve pos"]
    for name, values in extra.items():
        np.testing.assert_array_equal(data.extra[name], values)


GOOD_VARIANTS = {
    "plain": _text([HEADER] + _rows()),
    "crlf": "\r\n".join([HEADER] + _rows()) + "\r\n",
    "blank lines": _text([HEADER, "", _rows()[0], "", ""] + _rows()[1:]) + "\n\n",
    "no final newline": "\n".join([HEADER] + _rows()),
    "spaces around cells": _text([HEADER] + [" " + r.replace(",", " , ") + " " for r in _rows()]),
    "exponents and signs": _text([HEADER] + [r.replace(",1", ",+1e0").replace(",2", ",2.0E+0") for r in _rows()]),
    "quoted cells": _text([HEADER] + [",".join(f'"{c}"' if k == 3 else c for k, c in enumerate(r.split(",")))
                                      for r in _rows()]),
    "shuffled with extra": _text(["note,y2,u1,t,r_y1,u3,y1,r_y2,u2"] + [
        ",".join(["x" if k == 2 else str(k)] + [r.split(",")[c] for c in (7, 3, 0, 1, 5, 6, 2, 4)])
        for k, r in enumerate(_rows())]),
    "one row": _text([HEADER] + _rows()[:1]),
    "integers as decimals": _text([HEADER] + [",".join([repr(float(k))] + [f"{10 * k + c}.0" for c in range(1, 8)])
                                              for k in range(5)]),
}


@pytest.mark.parametrize("case", sorted(GOOD_VARIANTS))
def test_fast_and_careful_parsers_give_the_same_data(tmp_path, case, monkeypatch):
    from mpm_monitor.io import csv_log

    path = _write(tmp_path, GOOD_VARIANTS[case])
    fast = read_csv(path, _model())
    monkeypatch.setattr(csv_log, "_fast_table", lambda *args: None)
    careful = read_csv(path, _model())
    for key in ("t", "r", "u", "y", "dv"):
        np.testing.assert_array_equal(getattr(fast, key), getattr(careful, key))
    assert fast.extra.keys() == careful.extra.keys() and fast.unusable == careful.unusable
    for name in fast.extra:
        np.testing.assert_array_equal(fast.extra[name], careful.extra[name])


def test_a_file_of_plain_numbers_takes_the_fast_path(tmp_path, monkeypatch):
    from mpm_monitor.io import csv_log

    def no_careful(*args):
        raise AssertionError("the careful parser ran on a file of plain numbers")

    monkeypatch.setattr(csv_log, "_careful_table", no_careful)
    rng = np.random.default_rng(9)
    n = 300
    model = _model(0.1)
    t = np.arange(n) * 0.1
    r, u, y = rng.normal(size=(n, 2)), rng.normal(size=(n, 3)) * 1e-200, rng.normal(size=(n, 2)) * 1e200
    path = tmp_path / "plain.csv"
    write_csv(path, t, r, u, y, model.inputs, model.outputs, extra={"feed": rng.normal(size=n)})
    data = read_csv(path, model)
    for key, ref in (("t", t), ("r", r), ("u", u), ("y", y)):
        np.testing.assert_array_equal(getattr(data, key), ref)
    assert list(data.extra) == ["feed"]


# --------------------------------------------------------------------------- the read started in a child process


def _children() -> set:
    """Process ids of this process's children (Linux /proc), or None where /proc does not list them."""
    import os
    from pathlib import Path

    tasks = Path(f"/proc/{os.getpid()}/task")
    try:
        return {int(p) for f in tasks.glob("*/children") for p in f.read_text().split()}
    except OSError:
        return None


def _outcome(read):
    """``("data", LoggedData)`` or ``("error", message)``."""
    try:
        return "data", read()
    except DataFileError as exc:
        return "error", str(exc)


def _assert_same_bits(a, b):
    """The same arrays bit for bit (dtype, shape, bytes), the same extra columns and unusable ones."""
    for key in ("t", "r", "u", "y", "dv"):
        x, y = getattr(a, key), getattr(b, key)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), key
    assert list(a.extra) == list(b.extra) and a.unusable == b.unusable
    for name in a.extra:
        assert a.extra[name].dtype == b.extra[name].dtype and a.extra[name].tobytes() == b.extra[name].tobytes(), name
    assert (a.source, a.sample_time, a.inputs, a.outputs) == (b.source, b.sample_time, b.inputs, b.outputs)


def _big_log(tmp_path, n=2000):
    """A log of random full-precision floats of all magnitudes, with a numeric and a non-numeric extra column."""
    rng = np.random.default_rng(5)
    model = _model(0.1)
    t = np.arange(n) * 0.1
    scale = 10.0 ** rng.integers(-300, 300, size=(n, 1))
    r, u, y = rng.normal(size=(n, 2)) * scale, rng.normal(size=(n, 3)), rng.normal(size=(n, 2)) * 1e-7
    path = tmp_path / "big.csv"
    write_csv(path, t, r, u, y, model.inputs, model.outputs, extra={"feed": rng.normal(size=n)})
    lines = path.read_text(encoding="utf-8").splitlines()
    lines = [lines[0] + ",note"] + [f"{line},{'x' if k % 7 == 3 else k}" for k, line in enumerate(lines[1:])]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path, model


def _started_variants(tmp_path):
    """``{name: (path, model)}``: every good variant, the big log, the big log with a BOM and CRLF."""
    out = {name: (_write(tmp_path, text, f"{k}.csv"), _model()) for k, (name, text) in enumerate(GOOD_VARIANTS.items())}
    path, model = _big_log(tmp_path)
    out["big"] = (path, model)
    text = path.read_text(encoding="utf-8").replace("\n", "\r\n")
    out["big, BOM and CRLF"] = (_write(tmp_path, b"\xef\xbb\xbf" + text.encode("utf-8"), "bom.csv"), model)
    return out


@pytest.mark.parametrize("piece_bytes", [1 << 20, 300, 1])
def test_a_started_read_gives_the_same_data_bit_for_bit(tmp_path, monkeypatch, piece_bytes):
    """The fast parse in a child (in pieces of a line up to the whole file), the same in one process and
    the careful parser: the same arrays."""
    from mpm_monitor.io import csv_log
    from mpm_monitor.io.csv_log import start_csv_read

    monkeypatch.setattr(csv_log, "PIECE_BYTES", piece_bytes)
    for name, (path, model) in _started_variants(tmp_path).items():
        here = read_csv(path, model)
        started = read_csv(path, model, started=start_csv_read(path))
        _assert_same_bits(here, started)
        with monkeypatch.context() as mp:
            mp.setattr(csv_log, "_fast_table", lambda *args: None)
            careful = read_csv(path, model)
        _assert_same_bits(here, careful)
    assert list(started.extra) == ["feed"] and started.unusable == {"note": "not numeric: line 5 holds 'x'"}


def test_the_childs_table_is_the_one_read(tmp_path, monkeypatch):
    """Once started, the parent does not parse the file again: numpy's parse here would fail the test."""
    from mpm_monitor.core.parallel import can_fork
    from mpm_monitor.io import csv_log
    from mpm_monitor.io.csv_log import start_csv_read

    if not can_fork():
        pytest.skip("this process runs threads: the parse runs in it")
    path, model = _big_log(tmp_path)
    reference = read_csv(path, model)
    started = start_csv_read(path)

    def no_parse_here(text):
        raise AssertionError("parsed in the parent")

    monkeypatch.setattr(csv_log, "_fast_cells", no_parse_here)
    _assert_same_bits(read_csv(path, model, started=started), reference)


@pytest.mark.parametrize("failure", ["raises", "dies", "no fork"])
def test_a_failing_child_leaves_the_parse_to_the_parent(tmp_path, monkeypatch, failure):
    """A child that raises or dies without a result, or no child at all: the parent reads as today."""
    import os

    from mpm_monitor.core import parallel
    from mpm_monitor.io import csv_log
    from mpm_monitor.io.csv_log import start_csv_read

    path, model = _big_log(tmp_path)
    reference = read_csv(path, model)
    if failure == "no fork":
        monkeypatch.setattr(parallel, "can_fork", lambda: False)
    elif not parallel.can_fork():
        pytest.skip("this process runs threads: no child")
    elif failure == "raises":
        monkeypatch.setattr(csv_log, "_child_pieces", lambda *args: 1 / 0)
    else:
        monkeypatch.setattr(csv_log, "_child_pieces", lambda *args: os._exit(3))
    started = start_csv_read(path)
    monkeypatch.undo()
    _assert_same_bits(read_csv(path, model, started=started), reference)


@pytest.mark.parametrize("case", sorted(BAD_FILES))
@pytest.mark.parametrize("piece_bytes", [1 << 20, 1])
def test_a_started_read_refuses_a_bad_file_with_the_same_message(tmp_path, monkeypatch, case, piece_bytes):
    from mpm_monitor.io import csv_log
    from mpm_monitor.io.csv_log import start_csv_read

    monkeypatch.setattr(csv_log, "PIECE_BYTES", piece_bytes)
    path = _write(tmp_path, BAD_FILES[case][0])
    before = _children()
    here = _outcome(lambda: read_csv(path, _model()))
    started = _outcome(lambda: read_csv(path, _model(), started=start_csv_read(path)))
    assert here[0] == "error" and started == here
    assert before is None or _children() == before          # the child was waited for


def test_a_started_read_of_other_files_reads_them_as_today(tmp_path):
    """A missing file, a directory, a header in Latin-1 (an extra column's: read; a needed one's: refused)."""
    from mpm_monitor.io.csv_log import start_csv_read

    lines = _text([HEADER + ",temp"] + [r + ",20.5" for r in _rows()]).encode("utf-8")
    latin1_extra = _write(tmp_path, lines.replace(b"temp", b"temp\xb0C", 1), "latin1_extra.csv")
    latin1_needed = _write(tmp_path, lines.replace(b"u1", b"\xfc1", 1), "latin1_needed.csv")
    for path in (tmp_path / "missing.csv", tmp_path, latin1_extra, latin1_needed):
        here = _outcome(lambda: read_csv(path, _model()))
        started = _outcome(lambda: read_csv(path, _model(), started=start_csv_read(path)))
        assert started[0] == here[0], path
        if here[0] == "error":
            assert started == here
        else:
            _assert_same_bits(started[1], here[1])
            assert started[1].unusable == {"temp\ufffdC": "its name in the header is not UTF-8 text"}


def test_a_started_read_of_another_file_is_a_programming_error(tmp_path):
    from mpm_monitor.io.csv_log import start_csv_read

    path = _write(tmp_path, _text([HEADER] + _rows()))
    with pytest.raises(ValueError, match="started is the read of"):
        read_csv(path, _model(), started=start_csv_read(tmp_path / "other.csv"))


def test_analyze_waits_for_the_child_when_the_model_is_refused(tmp_path, capsys):
    """A refused model file: its one-line error, and no child process left behind."""
    from mpm_monitor.apps.cli import main

    path, _ = _big_log(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_text("sample_time: [\n", encoding="utf-8")
    before = _children()
    assert main(["analyze", "--model", str(bad), "--data", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bad}") and len(err.splitlines()) == 1, err
    assert before is None or _children() == before


def test_help_starts_no_read():
    """``--help`` imports no reader and starts no child process (it is as fast as the argument parser)."""
    import subprocess
    import sys

    code = ("import sys\nfrom mpm_monitor.apps.cli import main\n"
            "for argv in (['--help'], ['analyze', '--help'], ['simulate', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "print(sorted(m for m in ('mpm_monitor.io.csv_log', 'scipy') "
            "if m in sys.modules), file=sys.stderr)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr.strip() == "[]", proc.stderr


def _piece_texts() -> dict:
    """Bodies that the pieces of a started read must take or refuse as numpy does the whole text."""
    rows = [",".join(repr(float(v)) for v in np.random.default_rng(k).normal(size=4) * 10.0 ** (k % 40 - 20))
            for k in range(60)]
    head = "t,a,b,c"
    out = {
        "plain": _text([head] + rows),
        "crlf": "\r\n".join([head] + rows) + "\r\n",
        "crlf without a final line end": "\r\n".join([head] + rows),
        "no final line end": "\n".join([head] + rows),
        "blank lines everywhere": _text([head, "", ""] + rows[:20] + [""] * 30 + rows[20:] + ["", ""]),
        "blank lines only": _text([head, "", "", ""]),
        "header only": head + "\n",
        "header without a line end": head,
        "a line of spaces": _text([head] + rows[:30] + ["   "] + rows[30:]),
        "nan and inf": _text([head] + rows[:10] + ["nan,inf,-inf,1e999"] + rows[10:]),
        "a quote in the last row": _text([head] + rows[:-1] + ['"1",2,3,4']),
        "a quote in the header": _text(['"t",a,b,c'] + rows),
        "a stray carriage return in the last row": _text([head] + rows[:-1] + ["1,2\r,3,4"]),
        "a carriage return in the header": _text(["t,a\r,b,c"] + rows),
        "text in the last row": _text([head] + rows[:-1] + ["1,2,x,4"]),
        "an empty cell in the last row": _text([head] + rows[:-1] + ["1,2,,4"]),
        "a longer last row": _text([head] + rows + ["1,2,3,4,5"]),
        "more columns from the middle on": _text([head] + rows[:30] + [r + ",9" for r in rows[30:]]),
        "a line longer than the csv limit": _text([head] + rows[:-1] + ["1," * 70_000 + "1"]),
        "one column": _text(["t"] + [str(k) for k in range(50)]),
        "one row": _text([head] + rows[:1]),
        "a BOM": "\ufeff" + _text([head] + rows),
        "non-ASCII in the header": _text(["t,\u00e4,b,\u00b0C"] + rows),
    }
    return out


def _same_table(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("timing", ["child ahead", "child slow", "child slow per piece", "no fork"])
@pytest.mark.parametrize("piece_bytes", [1, 37, 1 << 20])
def test_the_pieces_stacked_are_numpys_table_of_the_whole_text(tmp_path, monkeypatch, piece_bytes, timing):
    """Whoever parses which piece (the child ahead of the parent, the parent taking most or all of the
    pieces, no child), the table is ``_fast_cells`` of the whole text, bit for bit, or None as it is."""
    import os
    import time

    from mpm_monitor.core import parallel
    from mpm_monitor.io import csv_log

    if timing != "no fork" and not parallel.can_fork():
        pytest.skip("this process runs threads: no child")
    monkeypatch.setattr(csv_log, "PIECE_BYTES", piece_bytes)
    parent = os.getpid()
    if timing == "no fork":
        monkeypatch.setattr(parallel, "can_fork", lambda: False)
    elif timing == "child slow":
        child_pieces = csv_log._child_pieces
        monkeypatch.setattr(csv_log, "_child_pieces", lambda *args: (time.sleep(0.2), child_pieces(*args))[1])
    elif timing == "child slow per piece":
        piece_cells = csv_log._piece_cells
        monkeypatch.setattr(csv_log, "_piece_cells",
                            lambda *args: (time.sleep(0.002 if os.getpid() != parent else 0), piece_cells(*args))[1])
    for name, text in _piece_texts().items():
        path = _write(tmp_path, text, "pieces.csv")
        expected = csv_log._fast_cells(text.removeprefix("\ufeff"))
        started = csv_log.start_csv_read(path)
        assert started.text() == text.removeprefix("\ufeff"), name
        assert _same_table(started.cells(), expected), name
        started.close()
    assert not os.path.exists(tmp_path / "never") and os.getpid() == parent


def test_analyze_runs_without_the_cycle_collector_and_gives_it_back(tmp_path, monkeypatch):
    """The one-shot ``analyze`` turns the cyclic garbage collector off while it runs (time only: the same
    report) and on again when it returns, also after an error; a caller that had it off keeps it off."""
    import gc

    from mpm_monitor.apps import cli
    from mpm_monitor.core import pipeline

    from mpm_monitor.io.model_file import save_model

    rng = np.random.default_rng(3)
    model, n = _model(), 400
    path, model_file = tmp_path / "log.csv", tmp_path / "m.yaml"
    write_csv(path, np.arange(n, dtype=float), rng.normal(size=(n, 2)), rng.normal(size=(n, 3)),
              rng.normal(size=(n, 2)), model.inputs, model.outputs)
    save_model(model, model_file)
    seen = []

    def fake(*args, **kwargs):
        seen.append(gc.isenabled())
        raise InputError("stop here")
    monkeypatch.setattr(pipeline, "analyze", fake)
    assert gc.isenabled()
    assert cli.main(["analyze", "--model", str(model_file), "--data", str(path)]) == 2
    assert seen == [False] and gc.isenabled()
    gc.disable()
    try:
        assert cli.main(["analyze", "--model", str(model_file), "--data", str(path)]) == 2
        assert seen == [False, False] and not gc.isenabled()
    finally:
        gc.enable()


# --------------------------------------------------------------------------- --bad-values gap
def test_bad_values_as_gaps_read_as_the_rows_deleted(tmp_path):
    """A historian's missing values (an empty cell, 'Bad', NaN, inf in a model channel): with bad_values='gap'
    each such row is left out as a missing sample, the data the same as the file with those rows deleted, and
    one note counts them and names the first."""
    rows = _rows(12)
    bad = {3: ("y1", ""), 4: ("u2", "Bad"), 8: ("r_y2", "NaN"), 9: ("u3", "-inf")}
    edited = []
    for k, line in enumerate(rows):
        if k in bad:
            cells = line.split(",")
            cells[HEADER.split(",").index(bad[k][0])] = bad[k][1]
            line = ",".join(cells)
        edited.append(line)
    path = _write(tmp_path, _text([HEADER] + edited))
    with pytest.raises(DataFileError, match=r"line 5, column 'y1': expected a number, got ''"):
        read_csv(path, _model())                            # the default refuses, as before
    data = read_csv(path, _model(), bad_values="gap")
    ref = read_csv(_write(tmp_path, _text([HEADER] + [r for k, r in enumerate(rows) if k not in bad]), "ref.csv"),
                   _model())
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(data, key), getattr(ref, key))
    assert data.n_samples == 8 and len(data.segments) == 3
    assert data.notes == (f"{path}: 4 rows left out as missing samples (a value of the model's channels empty, not a "
                          f"number or not finite; the first on line 5, column 'y1': ''); the analysis goes around them "
                          f"as around rows missing from the file",)


def test_bad_values_as_gaps_keep_the_other_refusals(tmp_path):
    """A bad t cannot be placed: still refused; so is a row of another length.  Every row bad leaves no data."""
    for content, pattern in ((_with_cell(2, "t", ""), r"line 4, column 't': expected a number, got ''"),
                             (_with_line(2, "2,21,22,23"), r"line 4: expected 8 fields as in the header, got 4")):
        with pytest.raises(DataFileError, match=pattern):
            read_csv(_write(tmp_path, content), _model(), bad_values="gap")
    every = [",".join(r.split(",")[:-1] + [""]) for r in _rows(3)]
    # The refusal names the column that left every row out (it said only "3 left out for a bad value").
    last = HEADER.split(",")[-1]
    with pytest.raises(DataFileError, match=rf"every one of its 3 data lines left out for a bad value \(empty, not a "
                                            rf"number or not finite\) in '{last}' \(3 rows\); the first on line 2, "
                                            rf"column '{last}': ''"):
        read_csv(_write(tmp_path, _text([HEADER] + every), "every.csv"), _model(), bad_values="gap")
    with pytest.raises(ValueError, match="bad_values"):
        parse_csv_text(_text([HEADER] + _rows()), _model(), bad_values="skip")


def test_bad_values_as_gaps_leave_an_extra_column_as_it_was(tmp_path):
    """A bad cell of a channel the model does not use is that channel's problem (unusable), not the row's."""
    lines = [HEADER + ",feed"] + [r + f",{k}" for k, r in enumerate(_rows(6))]
    lines[3] = lines[3].rsplit(",", 1)[0] + ",n/a"
    data = read_csv(_write(tmp_path, _text(lines)), _model(), bad_values="gap")
    assert data.n_samples == 6 and data.notes == () and data.unusable["feed"] == "not numeric: line 4 holds 'n/a'"


# --------------------------------------------------------------------------- compressed and piped logs
def test_a_gzip_compressed_log_reads_as_the_log(tmp_path):
    """A historian export kept as log.csv.gz was 'not UTF-8 text (byte 1)'; it reads as its content now, with the
    same refusals (naming the .gz file) and a one-line error for a file cut short."""
    import gzip

    text = _text([HEADER] + _rows(40))
    plain = read_csv(_write(tmp_path, text), _model())
    packed = _write(tmp_path, gzip.compress(text.encode()), "log.csv.gz")
    data = read_csv(packed, _model())
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(data, key), getattr(plain, key))
    from mpm_monitor.io.csv_log import start_csv_read

    started = start_csv_read(packed)                     # the command's path: its child parses the content
    data = read_csv(packed, _model(), started=started)
    np.testing.assert_array_equal(data.y, plain.y)
    bad = _write(tmp_path, gzip.compress(_with_cell(2, "u2", "abc").encode()), "bad.csv.gz")
    with pytest.raises(DataFileError, match=r"bad.csv.gz: line 4, column 'u2': expected a number, got 'abc'"):
        read_csv(bad, _model())
    cut = _write(tmp_path, gzip.compress(text.encode())[:-12], "cut.csv.gz")
    with pytest.raises(DataFileError) as info:
        read_csv(cut, _model())
    msg = str(info.value)
    assert msg.startswith(f"{cut}: a gzip file that cannot be decompressed (") and "\n" not in msg
    latin = _write(tmp_path, gzip.compress((HEADER + ",temp\xe9rature\n").encode("latin-1")
                                           + "".join(r + ",1\n" for r in _rows(5)).encode()), "latin.csv.gz")
    data = read_csv(latin, _model())                     # a foreign name of an extra column, inside gzip too
    assert data.n_samples == 5 and list(data.unusable.values()) == ["its name in the header is not UTF-8 text"]


def test_a_gzip_file_that_expands_a_thousand_fold_is_refused_before_it_takes_the_memory(tmp_path, monkeypatch):
    """A "decompression bomb" (a few kB of gzip that expand to gigabytes) was decompressed whole before any
    check.  Decompression stops at GZIP_MAX_RATIO times the file's size (and at least GZIP_MIN_LIMIT bytes),
    here made small; a log of numbers, which compresses far less, still reads."""
    import gzip

    import mpm_monitor.io.files as files_mod
    from mpm_monitor.io.csv_log import start_csv_read

    monkeypatch.setattr(files_mod, "GZIP_MIN_LIMIT", 2 ** 20)
    text = _text([HEADER] + _rows(40))
    assert read_csv(_write(tmp_path, gzip.compress(text.encode()), "log.csv.gz"), _model()).n_samples == 40
    bomb = _write(tmp_path, gzip.compress(text.encode() + b"0" * (40 * 2 ** 20)), "bomb.csv.gz")
    size = bomb.stat().st_size
    assert size * files_mod.GZIP_MAX_RATIO < 40 * 2 ** 20
    for read in (lambda: read_csv(bomb, _model()), lambda: read_csv(bomb, _model(), started=start_csv_read(bomb))):
        with pytest.raises(DataFileError) as info:
            read()
        msg = str(info.value)
        assert msg.startswith(f"{bomb}: a gzip file of {size:,} bytes whose content exceeds ") and "\n" not in msg
        assert "more than 1000 times its size" in msg


def test_analyze_reads_the_log_from_standard_input(tmp_path):
    """``--data -``: the log piped in (``zcat log.csv.gz | ... --data -``), its messages naming /dev/stdin."""
    import subprocess
    import sys

    from mpm_monitor.io.model_file import save_model

    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=[[1.0]], time_constant=[[5.0]],
                       delay=[[0.0]])
    save_model(model, tmp_path / "m.yaml")
    rng = np.random.default_rng(1)
    n = 600
    u = rng.standard_normal((n, 1))
    y = np.convolve(u[:, 0], 0.2 * 0.8 ** np.arange(40))[:n, None] + 0.01 * rng.standard_normal((n, 1))
    write_csv(tmp_path / "log.csv", np.arange(n, dtype=float), np.zeros((n, 1)), u, y, ("u1",), ("y1",))
    text = (tmp_path / "log.csv").read_text()
    cmd = [sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(tmp_path / "m.yaml"), "--data", "-",
           "--no-repair", "--json", "-"]
    done = subprocess.run(cmd, input=text, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    import json

    assert json.loads(done.stdout)["samples"] == n
    bad = text.replace("\n5,", "\n5,x", 1)
    done = subprocess.run(cmd, input=bad, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.startswith("error: /dev/stdin: line 7, column ")


def test_a_header_name_in_another_unicode_normal_form_is_the_models(tmp_path):
    """An outside check: a header name in decomposed form (NFD: "u" and a combining diaeresis, as macOS exports write
    it) against the model's composed name gave "missing column 'ü1'" beside a header that printed 'ü1'."""
    import unicodedata

    name = "\u00fc1"                                    # ü1, composed (NFC)
    model = PlantModel(sample_time=1.0, inputs=(name,), outputs=("y1",), gain=[[2.0]], time_constant=[[10.0]],
                       delay=[[1.0]])
    rows = [f"{k},1,{k % 3},{0.1 * k}" for k in range(5)]
    for form in ("NFC", "NFD"):
        header = f"t,r_y1,{unicodedata.normalize(form, name)},y1"
        data = read_csv(_write(tmp_path, _text([header] + rows), name=f"{form}.csv"), model)
        assert data.inputs == (name,) and list(data.u[:, 0]) == [0, 1, 2, 0, 1]
    both = f"t,r_y1,{name},{unicodedata.normalize('NFD', name)},y1"        # both forms: one column twice
    with pytest.raises(DataFileError, match=f"column '{name}' appears more than once"):
        read_csv(_write(tmp_path, _text([both] + [r + ",0" for r in rows]), name="both.csv"), model)
