"""``--bad-values gap`` and ``t`` (docs/interfaces.md, "Logged data (CSV)", "Gaps"): a row left out for a bad
value of the model's channels still has its ``t`` checked as a kept row's is.

A repeated or decreasing ``t`` was refused on a kept row but not noticed on a row left out as a gap: a file whose
left-out row's ``t`` went back (or whose next row's ``t`` went back from it) was read as if nothing were wrong.
It is refused now with the very message a kept row gets (file, line, the ``t`` it repeats or goes back from).
So is a left-out row's ``t`` off the sample grid (a step to it or from it not a whole number of sample times,
within the kept rows' tolerance), and one more than 2^53 sample times after the first row's: both were read
without a word.  A left-out row's empty or non-numeric ``t`` is refused as before (the row cannot be placed).

``start_csv_read`` forks a child for the parse: this module runs in ``make test``'s serial pass.
"""

import numpy as np
import pytest

from mpm_monitor.apps.cli import main
from mpm_monitor.core.errors import DataFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.csv_log import read_csv, start_csv_read
from mpm_monitor.io.model_file import save_model

HEADER = "t,r_y1,r_y2,u1,u2,u3,y1,y2"
COLUMNS = HEADER.split(",")


def _model(ts=1.0):
    return PlantModel(sample_time=ts, inputs=("u1", "u2", "u3"), outputs=("y1", "y2"),
                      gain=[[1.0, 2.0, 0.0], [0.5, 0.0, 3.0]], time_constant=[[10.0, 5.0, 0.0], [3.0, 0.0, 8.0]],
                      delay=[[1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])


def _rows(n=8):
    """Good data lines: row k (file line k + 2) has t = k and cells 10k + column index."""
    return [",".join([str(k)] + [str(10 * k + c) for c in range(1, 8)]) for k in range(n)]


def _set(rows, k, **cells):
    """``rows`` with the named cells of row k replaced."""
    rows = list(rows)
    fields = rows[k].split(",")
    for col, value in cells.items():
        fields[COLUMNS.index(col)] = value
    rows[k] = ",".join(fields)
    return rows


def _write(tmp_path, rows, name="data.csv"):
    path = tmp_path / name
    path.write_text("\n".join([HEADER] + rows) + "\n", encoding="utf-8")
    return path


def _refusal(path, **kwargs) -> str:
    with pytest.raises(DataFileError) as info:
        read_csv(path, _model(), **kwargs)
    return str(info.value)


@pytest.mark.parametrize("t", ["3", "1", "-7.5"])
def test_a_left_out_rows_t_that_repeats_or_goes_back_is_refused_as_on_a_kept_row(tmp_path, t):
    """Row 4 (line 6) has t = 3 (repeats line 5's), 1 or -7.5 (goes back): kept, it is refused; left out for an
    empty y1, it was read without a word.  Now the same message, byte for byte (but the file's name)."""
    kept = _refusal(_write(tmp_path, _set(_rows(), 4, t=t), "kept.csv"), bad_values="gap")
    gap = _refusal(_write(tmp_path, _set(_rows(), 4, t=t, y1=""), "gap.csv"), bad_values="gap")
    what = "repeats" if t == "3" else "goes back from"
    assert kept == f"{tmp_path / 'kept.csv'}: line 6: t = {float(t):g} s {what} t = 3 s on line 5: expected t to " \
                   f"increase by sample_time 1 s"
    assert gap == kept.replace("kept.csv", "gap.csv")
    assert "\n" not in gap


@pytest.mark.parametrize("cell", ["", "Bad", "nan", "-inf"])
def test_a_kept_rows_t_that_goes_back_from_a_left_out_row_is_refused(tmp_path, cell):
    """Row 3 (line 5, t = 9) is left out; row 4 (line 6, t = 4) increases over row 2's t but goes back from row 3's:
    the previous row's ``t`` counts whether that row is kept or left out, whatever its bad cell."""
    rows = _set(_set(_rows(), 3, t="9", u2=cell), 4, t="4")
    path = _write(tmp_path, rows)
    assert _refusal(path, bad_values="gap") == \
        f"{path}: line 6: t = 4 s goes back from t = 9 s on line 5: expected t to increase by sample_time 1 s"


def test_two_left_out_rows_in_a_row_are_checked_against_each_other(tmp_path):
    """Two neighbouring rows left out: the second's t repeats the first's (blank lines between are not rows)."""
    rows = _set(_set(_rows(), 3, y2="Bad"), 4, t="3", r_y1="")
    rows.insert(4, ",,,,,,,")                                # a blank line (a row of only empty cells): line 6
    path = _write(tmp_path, rows)
    assert _refusal(path, bad_values="gap") == \
        f"{path}: line 7: t = 3 s repeats t = 3 s on line 5: expected t to increase by sample_time 1 s"


def test_the_refusal_is_the_same_after_a_started_read(tmp_path):
    """The command line's early read (:func:`start_csv_read`) gives the same refusal as a plain read."""
    path = _write(tmp_path, _set(_rows(), 4, t="2", y1=""))
    plain = _refusal(path, bad_values="gap")
    assert plain.startswith(f"{path}: line 6: t = 2 s goes back from t = 3 s on line 5")
    with pytest.raises(DataFileError) as info:
        read_csv(path, _model(), started=start_csv_read(path), bad_values="gap")
    assert str(info.value) == plain


def test_left_out_rows_whose_t_increases_on_the_grid_are_read_as_before(tmp_path):
    """Left-out rows on the grid (one within the kept rows' 0.1 % tolerance of it, one just after a skipped grid
    point): read as the file with those rows deleted, as before."""
    rows = _set(_set(_set(_rows(10), 2, y1=""), 5, t="5.0005", u1="Bad"), 8, y2="nan")
    del rows[7]                                              # a gap of the file's own: row 8 follows row 6
    data = read_csv(_write(tmp_path, rows), _model(), bad_values="gap")
    ref = read_csv(_write(tmp_path, [r for k, r in enumerate(rows) if k not in (2, 5, 7)], "ref.csv"), _model())
    for key in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(data, key), getattr(ref, key))
    assert data.n_samples == 6 and len(data.notes) == 1 and data.notes[0].split(": ", 1)[1].startswith(
        "3 rows left out as missing samples")


@pytest.mark.parametrize("t, step", [("3.5", "0.5"), ("4.002", "1.002"), ("4.5", "1.5")])
def test_a_left_out_rows_t_off_the_grid_is_refused_as_on_a_kept_row(tmp_path, t, step):
    """Row 4 (line 6) has t = 3.5, 4.002 (0.2 % off, beyond the 0.1 % tolerance) or 4.5 after t = 3 on line 5:
    kept, it is refused as off the grid; left out for an empty y1, it was read without a word.  Now the same
    message, byte for byte (but the file's name)."""
    kept = _refusal(_write(tmp_path, _set(_rows(), 4, t=t), "kept.csv"), bad_values="gap")
    gap = _refusal(_write(tmp_path, _set(_rows(), 4, t=t, y1=""), "gap.csv"), bad_values="gap")
    assert kept.startswith(f"{tmp_path / 'kept.csv'}: line 6: t = {float(t):g} s follows t = 3 s: a step of {step} s "
                           f"(expected sample_time 1 s; a gap or an irregular sample: every step a whole number of "
                           f"sample times, within 0.1 % per sample time)")
    assert gap == kept.replace("kept.csv", "gap.csv")
    assert "\n" not in gap


def test_a_left_out_rows_t_off_a_grid_of_0_1_s_is_refused(tmp_path):
    """Sample time 0.1 s, the row on line 4 left out at t = 0.35 after t = 0.1: the step to it is refused (the kept
    rows alone, 0.1 then 0.4, skip two grid points and are read)."""
    model = _model(0.1)
    rows = [",".join([f"{k / 10:g}"] + [str(10 * k + c) for c in range(1, 8)]) for k in range(8)]
    rows = _set(_set(rows, 3, t="0.35", u3=""), 4, t="0.4")
    del rows[2]                                              # line 4 now holds row 3 (t = 0.35), after t = 0.1
    path = _write(tmp_path, rows)
    with pytest.raises(DataFileError) as info:
        read_csv(path, model, bad_values="gap")
    assert str(info.value).startswith(f"{path}: line 4: t = 0.35 s follows t = 0.1 s: a step of 0.25 s (expected "
                                      f"sample_time 0.1 s;")
    kept_only = [r for k, r in enumerate(rows) if k != 2]
    assert read_csv(_write(tmp_path, kept_only, "kept.csv"), model, bad_values="gap").n_samples == 6


def test_a_left_out_rows_t_beyond_2_53_sample_times_is_refused_as_on_a_kept_row(tmp_path):
    """The last row (line 9) left out at t = 1e19 s: on the grid step by step (float64 cannot tell), but 1e19
    sample times after the first row, more than 2^53; kept, it is refused so, left out it was read without a
    word.  Now the same message."""
    kept = _refusal(_write(tmp_path, _set(_rows(), 7, t="1e19"), "kept.csv"), bad_values="gap")
    gap = _refusal(_write(tmp_path, _set(_rows(), 7, t="1e19", r_y2="Bad"), "gap.csv"), bad_values="gap")
    assert kept == f"{tmp_path / 'kept.csv'}: line 9: t = 1e+19 s lies 1e+19 sample times after the first sample " \
                   f"(t = 0 s): expected at most 2^53 (a stray t, or is the sample time right?)"
    assert gap == kept.replace("kept.csv", "gap.csv")


@pytest.mark.parametrize("t, message", [("", "line 6, column 't': expected a number, got ''"),
                                        ("Bad", "line 6, column 't': expected a number, got 'Bad'"),
                                        ("inf", "line 6, column 't': expected a finite number, got 'inf'")])
def test_a_left_out_rows_bad_t_is_refused_as_before(tmp_path, t, message):
    """The rule for a bad t is unchanged: a row whose t is empty, not a number or not finite cannot be placed,
    left out or not."""
    path = _write(tmp_path, _set(_rows(), 4, t=t, y1=""))
    assert _refusal(path, bad_values="gap") == f"{path}: {message}"


def test_the_other_refusals_come_first_as_before(tmp_path):
    """A file that was refused for something else keeps its message: a kept row's step off the grid (checked
    first, as before), and every row left out."""
    rows = _set(_set(_rows(), 2, t="1", y1=""), 6, t="5.5")
    path = _write(tmp_path, rows)
    assert _refusal(path, bad_values="gap").startswith(f"{path}: line 8: t = 5.5 s follows t = 5 s: a step of 0.5 s")
    every = [",".join(r.split(",")[:-1] + [""]) for r in _set(_rows(3), 2, t="0")]
    path = _write(tmp_path, every, "every.csv")
    assert _refusal(path, bad_values="gap").startswith(f"{path}: every one of its 3 data lines left out")


def test_analyze_refuses_it_in_one_line(tmp_path, capsys):
    """``analyze --bad-values gap`` on such a file: exit 2 and the one-line message of a kept row."""
    save_model(_model(), tmp_path / "model.yaml")
    path = _write(tmp_path, _set(_rows(), 4, t="1", y1="NaN"))
    assert main(["analyze", "--model", str(tmp_path / "model.yaml"), "--data", str(path), "--bad-values", "gap",
                 "--no-repair"]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [f"error: {path}: line 6: t = 1 s goes back from t = 3 s on line 5: expected t "
                                        f"to increase by sample_time 1 s"]


def test_analyze_refuses_a_left_out_rows_t_off_the_grid_in_one_line(tmp_path, capsys):
    """``analyze --bad-values gap`` on a file whose left-out row's t is off the grid: exit 2, one line."""
    save_model(_model(), tmp_path / "model.yaml")
    path = _write(tmp_path, _set(_rows(), 4, t="3.5", y1="NaN"))
    assert main(["analyze", "--model", str(tmp_path / "model.yaml"), "--data", str(path), "--bad-values", "gap",
                 "--no-repair"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}: line 6: t = 3.5 s follows t = 3 s: a step of 0.5 s")
