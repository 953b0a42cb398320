"""Command-line bugs of fuzz audit 72: every bad input or output is one line ``error: ...`` on stderr and
exit code 2, before any output file is written.

- A standard output that cannot be written (``> /dev/full``): one line naming the standard output, not an
  OSError traceback with exit code 1.
- ``reproduce --plots`` that cannot be a directory: refused before the simulation, as ``analyze --report``.
- ``--samples 0`` of ``simulate`` and ``reproduce``: named by its flag, not as ``n_samples``.
- ``simulate``: ``--plant``, ``--model`` or ``--experiment`` with ``--case`` (ignored before), and
  ``--experiment`` with ``--dither`` (which it replaced), are refused naming both flags.
- ``-`` as the output file of ``simulate --csv``, ``simulate --write-model`` and ``export --csv``: refused
  as for ``analyze --repair-out -``, not written as a file named ``-``.
- The text summary of a method that estimates no delay (``--method xcorr``) does not print ``delay=None``.
- ``simulate --dither 1e308``: a loop that overflowed is refused before its CSV is written (now the dither
  itself, beyond 1e40).
"""

import errno
import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.model_file import save_model

REPO = Path(__file__).resolve().parents[1]

PLANT = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=[[1.2]], time_constant=[[4.0]],
                   delay=[[2.0]])


def _run_cli(capsys, argv):
    code = cli_main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _usage_error(capsys, argv) -> str:
    """stderr of a command line argparse refuses (exit code 2)."""
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    """Paper case 3.2 simulated for 800 samples: its model and its CSV log."""
    d = tmp_path_factory.mktemp("fuzz72")
    model, csv = d / "M.yaml", d / "D.csv"
    assert cli_main(["simulate", "--case", "3.2", "--samples", "800", "--csv", str(csv),
                     "--write-model", str(model)]) == 0
    return {"dir": d, "model": model, "csv": csv}


@pytest.fixture
def plant_files(tmp_path):
    """A 1x1 plant and model file (the same) and a report whose experiment dithers u1."""
    plant, model, report = tmp_path / "plant.yaml", tmp_path / "model.yaml", tmp_path / "report.json"
    save_model(PLANT, plant)
    save_model(PLANT, model)
    report.write_text(json.dumps({"experiment": {"dither": {"u1": 0.2}, "samples": 300}}), encoding="utf-8")
    return {"plant": plant, "model": model, "report": report}


# ------------------------------------------------------------------------------------------------
# 1. A standard output that cannot be written

class _FullStream(io.TextIOBase):
    """A standard output on a full disk: every write fails with ENOSPC."""

    def writable(self):
        return True

    def write(self, text):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_standard_output_is_one_line_in_process(tmp_path, capsys, monkeypatch):
    csv = tmp_path / "out.csv"
    monkeypatch.setattr(sys, "stdout", _FullStream())
    code = cli_main(["simulate", "--case", "3.2", "--samples", "300", "--csv", str(csv)])
    err = capsys.readouterr().err
    assert code == 2 and err == "error: standard output: cannot write: No space left on device\n", err


def test_demo_to_a_full_standard_output_is_one_line(capsys, monkeypatch):
    """Stop 73: ``demo > /dev/full`` wrote through the demo's own stream, not the checked one, and ended in an
    OSError traceback and exit code 1.  (The demo itself is replaced here: it runs ROS nodes.)"""
    import mpm_monitor.apps.demo as demo

    def run_demo(**kw):
        kw["out"].write("demo: case 3.2 ...\n")
        kw["out"].flush()
        return 0

    monkeypatch.setattr(demo, "run_demo", run_demo)
    monkeypatch.setattr(sys, "stdout", _FullStream())
    code = cli_main(["demo", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err == "error: standard output: cannot write: No space left on device\n", err


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("unbuffered", ["1", None], ids=["unbuffered", "buffered"])
@pytest.mark.parametrize("command", ["simulate", "analyze", "analyze --json -"])
def test_a_full_standard_output_is_one_line_and_exit_code_2(logged, tmp_path, unbuffered, command):
    """``... > /dev/full``: an OSError traceback and exit code 1 before (unbuffered: at the print; buffered: an
    ignored exception at the exit's flush); now one line and exit code 2, whether or not the output is buffered."""
    if command == "simulate":
        argv = ["simulate", "--case", "3.2", "--samples", "300", "--csv", str(tmp_path / "out.csv")]
    else:
        argv = ["analyze", "--jobs", "1", "--no-repair", "--model", str(logged["model"]), "--data", str(logged["csv"]),
                *command.split()[1:]]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    if unbuffered:
        env["PYTHONUNBUFFERED"] = unbuffered
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "mpm_monitor", *argv], stdout=full, stderr=subprocess.PIPE,
                              text=True, env=env, cwd=tmp_path, timeout=300)
    assert done.returncode == 2 and done.stderr == "error: standard output: cannot write: No space left on device\n", \
        (done.returncode, done.stderr)


# ------------------------------------------------------------------------------------------------
# 2. reproduce --plots

@pytest.fixture
def no_reproduction(monkeypatch):
    """Fail the test if the case is simulated and analysed (the plots' directory must be refused first)."""
    import mpm_monitor.apps.reproduce as reproduce_mod

    def never(*a, **k):
        raise AssertionError("the case was simulated and analysed")

    monkeypatch.setattr(reproduce_mod, "reproduce", never)


def test_reproduce_plots_on_a_file_is_refused_before_the_run(tmp_path, capsys, no_reproduction):
    afile = tmp_path / "afile"
    afile.write_text("keep\n", encoding="utf-8")
    code, out, err = _run_cli(capsys, ["reproduce", "--case", "3.2", "--samples", "400", "--jobs", "1",
                                       "--plots", str(afile)])
    assert code == 2 and err == f"error: --plots {afile}: is a file: expected a directory to write into\n", err
    assert afile.read_text(encoding="utf-8") == "keep\n"


@pytest.mark.parametrize("target, match", [
    ("{file}/plots", r"^error: --plots .*/afile/plots: .*/afile is a file, not a directory$"),
    ("/proc/mpm_plots", r"^error: --plots /proc/mpm_plots: /proc is not writable(: .+)?$"),
])
def test_reproduce_plots_that_cannot_be_made_are_refused_before_the_run(tmp_path, capsys, no_reproduction, target,
                                                                        match):
    (tmp_path / "afile").write_text("", encoding="utf-8")
    path = target.format(file=tmp_path / "afile")
    code, out, err = _run_cli(capsys, ["reproduce", "--case", "3.2", "--samples", "400", "--jobs", "1",
                                       "--plots", path])
    assert code == 2 and len(err.splitlines()) == 1 and re.search(match, err.strip()), err


# ------------------------------------------------------------------------------------------------
# 3. --samples below 1 (and above a million)

@pytest.mark.parametrize("command, value", [("simulate", "0"), ("simulate", "-5"), ("reproduce", "0"),
                                            ("reproduce", "-1"), ("simulate", "1000001"),
                                            ("reproduce", "999999999999")])
def test_samples_out_of_range_is_named_by_its_flag(tmp_path, capsys, command, value):
    """Below 1, and (stop 73's audit) above a million: 1e12 ran until the machine's memory was gone."""
    csv = tmp_path / "out.csv"
    extra = ["--csv", str(csv)] if command == "simulate" else ["--jobs", "1"]
    err = _usage_error(capsys, [command, "--case", "3.2", "--samples", value, *extra])
    assert err == (f"python -m mpm_monitor {command}: error: argument --samples: expected an integer in "
                   f"[1, 1,000,000], got '{value}'\n"), err
    assert not csv.exists()


# ------------------------------------------------------------------------------------------------
# 4. simulate: conflicting flags

@pytest.mark.parametrize("extra, expected", [
    (["--plant", "{plant}"], "--plant {plant} with --case 3.2: expected --case, or --plant and --model, not both"),
    (["--model", "{missing}"], "--model {missing} with --case 3.2: expected --case, or --plant and --model, not both"),
    (["--plant", "{plant}", "--model", "{model}"],
     "--plant {plant} with --case 3.2: expected --case, or --plant and --model, not both"),
    (["--experiment", "{missing}"], "--experiment {missing} with --case 3.2: expected --experiment with --plant and "
                                    "--model (with --case, give a dither with --dither)"),
])
def test_simulate_refuses_plant_model_or_experiment_with_case(tmp_path, capsys, plant_files, extra, expected):
    """They were ignored without a word (a missing file too): the case's plant and model were simulated."""
    names = {k: str(v) for k, v in plant_files.items()} | {"missing": str(tmp_path / "does_not_exist")}
    csv = tmp_path / "out.csv"
    code, out, err = _run_cli(capsys, ["simulate", "--case", "3.2", "--samples", "300", "--csv", str(csv),
                                       *[a.format(**names) for a in extra]])
    assert code == 2 and err == f"error: {expected.format(**names)}\n", err
    assert not csv.exists()


@pytest.mark.parametrize("dither", ["0.5", "0"])
def test_simulate_refuses_experiment_with_dither(tmp_path, capsys, plant_files, dither):
    """--experiment replaced --dither without a word; each alone still runs."""
    csv = tmp_path / "out.csv"
    base = ["simulate", "--plant", str(plant_files["plant"]), "--model", str(plant_files["model"]), "--samples", "300",
            "--csv", str(csv)]
    code, out, err = _run_cli(capsys, base + ["--experiment", str(plant_files["report"]), "--dither", dither])
    assert code == 2 and err == (f"error: --experiment {plant_files['report']} with --dither {float(dither)!r}: "
                                 f"expected one of them (the experiment gives the dither of every input, instead of "
                                 f"--dither)\n"), err
    assert not csv.exists()
    for alone in (["--experiment", str(plant_files["report"])], ["--dither", dither]):
        code, out, err = _run_cli(capsys, base + alone)
        assert code == 0 and err == "" and out.startswith(f"wrote 300 samples to {csv}; "), (alone, err)


# ------------------------------------------------------------------------------------------------
# 5. '-' as an output file

@pytest.mark.parametrize("argv, expected", [
    (["simulate", "--case", "3.2", "--samples", "300", "--csv", "-"],
     "--csv -: expected a file to write the CSV log to (standard output is not supported for --csv: it holds the "
     "summary line)"),
    (["simulate", "--case", "3.2", "--samples", "300", "--csv", "out.csv", "--write-model", "-"],
     "--write-model -: expected a file to write the controller model to (standard output is not supported for "
     "--write-model: it holds the summary line)"),
    (["export", "--bag", "bag", "--csv", "-"],
     "--csv -: expected a file to write the CSV log to (standard output is not supported for --csv: it holds the "
     "summary line)"),
])
def test_dash_as_an_output_file_is_refused(logged, tmp_path, capsys, monkeypatch, argv, expected):
    """It wrote a file named '-' in the current directory, where '-' means a standard stream elsewhere."""
    from mpm_monitor.io.bags import write_logged_data
    from mpm_monitor.io.csv_log import read_csv
    from mpm_monitor.io.model_file import load_model

    monkeypatch.chdir(tmp_path)
    if argv[0] == "export":
        write_logged_data(tmp_path / "bag", read_csv(logged["csv"], load_model(logged["model"])))
    code, out, err = _run_cli(capsys, argv)
    assert code == 2 and err == f"error: {expected}\n", err
    assert not (tmp_path / "-").exists() and not (tmp_path / "out.csv").exists()


# ------------------------------------------------------------------------------------------------
# 6. No delay=None in the text summary

@pytest.mark.parametrize("method", ["xcorr", "pcorr"])
def test_a_method_without_delays_prints_no_delay(logged, capsys, tmp_path, method):
    report = tmp_path / "r.json"
    code, out, err = _run_cli(capsys, ["analyze", "--jobs", "1", "--no-repair", "--model", str(logged["model"]),
                                       "--data", str(logged["csv"]), "--method", method, "--json", str(report)])
    assert code == 0, err
    located = [line for line in out.splitlines() if re.match(r"^  \(y\d, u\d\)  p=", line)]
    assert located, out
    assert "None" not in out and all(re.match(r"^  \(y\d, u\d\)  p=\S+  kind=\w+$", line) for line in located), out
    elements = [e for e in json.loads(report.read_text(encoding="utf-8"))["elements"] if e["mismatch"]]
    assert elements and all(e["delay"] is None for e in elements)      # the JSON is unchanged


# ------------------------------------------------------------------------------------------------
# 7. A simulated loop that overflows

def test_a_dither_that_overflows_the_loop_is_refused_before_the_csv(tmp_path, capsys):
    """--dither 1e308: exit 0, RMS nan printed and a CSV with inf cells before; then one line after the run (the
    loop overflowed); now refused as a flag before the run (beyond 1e40 no reader takes the log), the CSV not written
    (an older one of that name left as it was)."""
    csv = tmp_path / "big.csv"
    csv.write_text("keep\n", encoding="utf-8")
    with pytest.raises(SystemExit) as exited:
        cli_main(["simulate", "--case", "3.2", "--samples", "50", "--dither", "1e308", "--csv", str(csv)])
    out, err = capsys.readouterr()
    assert exited.value.code == 2 and out == "" and len(err.splitlines()) == 1, err
    assert err.endswith("error: argument --dither: expected at most 1e+40 (input units: a log dithered beyond it "
                        "cannot be analysed), got '1e308'\n"), err
    assert csv.read_text(encoding="utf-8") == "keep\n"


def test_a_huge_finite_log_prints_a_finite_rms(tmp_path, capsys):
    """--dither 1e200: the log is finite, but the squares of its prediction errors overflowed: RMS printed as inf.
    Such a dither is refused now (above); the RMS of values that large is still finite, and the largest dither
    taken prints one."""
    from mpm_monitor.apps.cli import _rms

    rms = _rms(np.array([[3e200, 1.0], [-4e200, 1.0]]))
    assert np.all(np.isfinite(rms)) and abs(rms[0] / (12.5 ** 0.5 * 1e200) - 1) < 1e-12 and rms[1] == 1.0
    csv = tmp_path / "big2.csv"
    code, out, err = _run_cli(capsys, ["simulate", "--case", "3.2", "--samples", "300", "--dither", "1e40",
                                       "--csv", str(csv)])
    assert code == 0 and err == "", err
    rms = dict(item.split("=") for item in out.strip().split("RMS: ")[1].split(", "))
    assert set(rms) == {"y1", "y2", "y3"} and all(0 <= float(v) < float("inf") for v in rms.values()), out
    assert float(rms["y1"]) > 1e35, out


@pytest.mark.parametrize("argv, flag", [
    (["analyze", "--model", "MODEL", "--data", "CSV", "--report", "-"], "--report"),
    (["reproduce", "--case", "3.2", "--samples", "100", "--plots", "-"], "--plots"),
    (["recover", "--bag", "BAG", "--out", "-"], "--out"),
])
def test_a_dash_as_an_output_directory_is_refused(tmp_path, monkeypatch, capsys, argv, flag):
    """``--report -``, ``--plots -`` and ``recover --out -`` made a directory named ``-``: refused in one line."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bag").mkdir()
    argv = [a.replace("MODEL", str(tmp_path / "m.yaml")).replace("CSV", str(tmp_path / "d.csv"))
            .replace("BAG", str(tmp_path / "bag")) for a in argv]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {flag} -: expected a directory") and err.count("\n") == 1, err
    assert not (tmp_path / "-").exists()


def test_recover_names_a_missing_bag_directory(tmp_path, capsys):
    """``recover --bag nonexist`` said "no .mcap file to recover"; it now says the directory does not exist, as
    ``analyze --bag`` does."""
    assert cli_main(["recover", "--bag", str(tmp_path / "nonexist"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {tmp_path / 'nonexist'}: no such bag directory\n", err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("method", ["xcorr", "pcorr"])
def test_reproduce_prints_no_delay_for_a_method_without_one(capsys, tmp_path, method):
    assert cli_main(["reproduce", "--case", "3.2", "--samples", "600", "--method", method, "--jobs", "1",
                 "--plots", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert "delay None" not in out and "kind " in out, out
