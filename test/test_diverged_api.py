"""The function API on a loop that diverged: ``analyze`` and ``detect`` raise the package's
``DataFileError`` with a one-line message naming the diverging output, never a bare numpy error;
the command line and the monitor keep their messages."""

import warnings

import numpy as np
import pytest

import mpm_monitor.core.pipeline as pipeline
import mpm_monitor.core.row_test as row_test
from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.errors import DataFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.csv_log import write_csv
from mpm_monitor.io.model_file import save_model
from mpm_monitor.monitor.worker import AnalysisJob, run_analysis
from mpm_monitor.sim.closed_loop import run_closed_loop
from test_divergence import MODEL
from test_divergence import _log as _growing_log

#: The plant of MODEL with y1's gain of the other sign: the MPC with MODEL drives it unstable.
UNSTABLE_PLANT = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1", "y2"), gain=[[-3.0], [0.5]],
                            time_constant=[[5.0], [8.0]], delay=[[1.0], [2.0]])


def _log(n=3000, total_growth=None, seed=0):
    """:func:`test_divergence._log` with y1's noise growing ``total_growth``-fold over the log."""
    return _growing_log(n, None if total_growth is None else np.log(total_growth) / n, seed)


def _singular(*args, **kwargs):
    raise np.linalg.LinAlgError("Singular matrix")


def _one_line_naming_y1(err):
    msg = str(err)
    assert "\n" not in msg and msg.startswith("diverging.csv: ")
    assert "the loop diverged (output 'y1' grows without bound)" in msg and "y2" not in msg
    assert "the tests need a bounded loop" in msg
    return msg


@pytest.mark.parametrize("run", [lambda d: analyze(MODEL, d), lambda d: detect(MODEL, d, AnalysisOptions())],
                         ids=["analyze", "detect"])
def test_a_loop_diverged_beyond_the_analysis_scale_is_refused_before_the_fits(run):
    data = _log(total_growth=1e160)                       # y1 reaches 1.4e159 at the last sample
    with warnings.catch_warnings():
        warnings.simplefilter("error")                    # refused before any fit overflows
        with pytest.raises(DataFileError) as info:
            run(data)
    msg = _one_line_naming_y1(info.value)
    assert "output 'y1' at t = 2999 s is 1.45e+159: too large for the analysis" in msg
    assert "rescale the units" not in msg


@pytest.mark.parametrize("where", ["detect", "repair"])
def test_a_numerical_breakdown_on_a_diverged_loop_names_the_output(monkeypatch, where):
    data = _log(total_growth=1e10)                        # within scale: the analysis runs
    if where == "detect":
        monkeypatch.setattr(row_test, "sdelta_row_test", _singular)
    else:
        monkeypatch.setattr(pipeline, "repair_model", _singular)
    with pytest.raises(DataFileError) as info:
        analyze(MODEL, data)
    msg = _one_line_naming_y1(info.value)
    assert "the analysis broke down numerically (Singular matrix): output 'y1' reaches" in msg
    assert "at t = " in msg
    assert isinstance(info.value.__cause__, np.linalg.LinAlgError)
    if where == "detect":
        with pytest.raises(DataFileError, match=r"broke down numerically \(Singular matrix\).*'y1'"):
            detect(MODEL, data, AnalysisOptions())


def test_a_numerical_breakdown_on_a_bounded_log_gives_the_general_hint(monkeypatch):
    monkeypatch.setattr(row_test, "sdelta_row_test", _singular)
    with pytest.raises(DataFileError) as info:
        detect(MODEL, _log(), AnalysisOptions())
    assert str(info.value) == ("diverging.csv: the analysis broke down numerically (Singular matrix): values or "
                               "model parameters too large or degenerate?")


def test_a_simulated_unstable_loop_never_raises_a_bare_numpy_error():
    with np.errstate(all="ignore"):
        data = run_closed_loop(UNSTABLE_PLANT, MODEL, 2000, seed=0).as_logged_data("unstable.csv")
    assert np.all(np.isfinite(data.y)) and 1e100 < np.abs(data.y).max() < 1e150
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            report = analyze(MODEL, data)
        except DataFileError as err:     # refused by check_scale, or the fits broke down (a LinAlgError before the fix)
            msg = str(err)
            assert "\n" not in msg and (msg.startswith("unstable.csv: the analysis broke down numerically")
                                        or "too large for the analysis" in msg)
            assert "the loop diverged (outputs 'y1', 'y2' grow without bound)" in msg
        else:
            assert any(w.startswith("output 'y1' grows without bound") for w in report.warnings)


def test_the_command_line_keeps_its_message_when_the_real_analyze_breaks_down(tmp_path, monkeypatch, capsys):
    data = _log(total_growth=1e10)
    model_path, csv_path = tmp_path / "m.yaml", tmp_path / "diverging.csv"
    save_model(MODEL, model_path)
    write_csv(csv_path, data.t, data.r, data.u, data.y, MODEL.inputs, MODEL.outputs)
    monkeypatch.setattr(row_test, "sdelta_row_test", _singular)
    assert cli_main(["analyze", "--model", str(model_path), "--data", str(csv_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"diverging.csv: the analysis broke down numerically with model {model_path} (Singular matrix): " \
           f"output 'y1' grows without bound" in err


def test_the_monitor_keeps_its_message_when_the_real_analyze_breaks_down(monkeypatch):
    monkeypatch.setattr(row_test, "sdelta_row_test", _singular)
    data = _log(total_growth=1e10)
    job = AnalysisJob(seq=1, data=data, first_stamp=0.0, last_stamp=float(data.t[-1]), completed=data.n_samples)
    outcome = run_analysis(analyze, MODEL, AnalysisOptions(), job)
    assert outcome.report is None and outcome.error == "analysis failed: LinAlgError: Singular matrix"
