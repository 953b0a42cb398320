"""A loop that diverged: its outputs are named in one warning each, by the analysis and by the
command line when the analysis breaks down on them."""

import numpy as np

import mpm_monitor.core.pipeline as pipeline
from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.logged_data import DIVERGENCE_RATIO, LoggedData, divergence_warnings
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.csv_log import write_csv
from mpm_monitor.io.model_file import save_model

MODEL = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1", "y2"), gain=[[1.0], [0.5]],
                   time_constant=[[5.0], [8.0]], delay=[[1.0], [2.0]])


def _log(n=3000, growth=None, seed=0):
    """A loop of MODEL driven by a PRBS-like input; ``growth`` (per sample) multiplies y1's noise."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice([-1.0, 1.0], size=n // 10 + 1), 10)[:n, None]
    yhat = np.column_stack([MODEL.discrete_element(i, 0).respond(u[:, 0]) for i in range(2)])
    noise = 0.05 * rng.standard_normal((n, 2))
    if growth is not None:
        noise[:, 0] *= np.exp(growth * np.arange(n))
    t = np.arange(n, dtype=float)
    return LoggedData(t=t, r=np.zeros((n, 2)), u=u, y=yhat + noise, inputs=MODEL.inputs, outputs=MODEL.outputs,
                      sample_time=1.0, source="diverging.csv")


def test_geometric_growth_is_named_once_per_output():
    y = _log(growth=np.log(1e10) / 3000).y              # y1's noise grows 1e10-fold, y2 stays bounded
    w = divergence_warnings(MODEL.outputs, y)
    assert len(w) == 1 and w[0].startswith("output 'y1' grows without bound") and "\n" not in w[0]
    assert "looks unstable (diverging)" in w[0]


def test_bounded_loops_are_not_named():
    rng = np.random.default_rng(1)
    quiet_then_moving = np.concatenate([1e-9 * rng.standard_normal(400), np.repeat(rng.choice([-5.0, 5.0], 26), 100)])
    assert divergence_warnings(["y"], quiet_then_moving[:, None]) == []      # at rest, then setpoint steps
    assert divergence_warnings(MODEL.outputs, _log().y) == []
    ramp = np.arange(3000.0)[:, None]                                      # a drift grows linearly, not without bound
    assert divergence_warnings(["y"], ramp) == []
    assert divergence_warnings(["y"], np.exp(np.arange(20.0))[:, None]) == []   # too short to say


def test_the_ratio_is_the_documented_one():
    n = 3000
    base = np.where(np.arange(n) < 9 * n // 10, 1.0, 0.0) * np.tile([1.0, -1.0], n // 2)
    below = base + np.where(np.arange(n) >= 9 * n // 10, 0.9 * DIVERGENCE_RATIO, 0.0) * np.tile([1.0, -1.0], n // 2)
    above = base + np.where(np.arange(n) >= 9 * n // 10, 1.1 * DIVERGENCE_RATIO, 0.0) * np.tile([1.0, -1.0], n // 2)
    assert divergence_warnings(["y"], below[:, None]) == []
    assert len(divergence_warnings(["y"], above[:, None])) == 1


def test_the_analysis_warns_on_a_diverging_loop():
    report = detect(MODEL, _log(growth=np.log(1e10) / 3000), AnalysisOptions(repair=False), detectability=False)
    assert any(w.startswith("output 'y1' grows without bound") for w in report.warnings)
    clean = detect(MODEL, _log(), AnalysisOptions(repair=False), detectability=False)
    assert not any("grows without bound" in w for w in clean.warnings)


def test_the_command_line_names_the_divergence_when_the_analysis_breaks_down(tmp_path, monkeypatch, capsys):
    data = _log(growth=np.log(1e10) / 3000)
    model_path, csv_path = tmp_path / "m.yaml", tmp_path / "diverging.csv"
    save_model(MODEL, model_path)
    write_csv(csv_path, data.t, data.r, data.u, data.y, MODEL.inputs, MODEL.outputs)

    def broken(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(pipeline, "analyze", broken)
    assert cli_main(["analyze", "--model", str(model_path), "--data", str(csv_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "diverging.csv: the analysis broke down numerically" in err and "(Singular matrix)" in err
    assert "output 'y1' grows without bound" in err


def test_the_command_line_keeps_its_old_hint_for_bounded_data(tmp_path, monkeypatch, capsys):
    data = _log()
    model_path, csv_path = tmp_path / "m.yaml", tmp_path / "bounded.csv"
    save_model(MODEL, model_path)
    write_csv(csv_path, data.t, data.r, data.u, data.y, MODEL.inputs, MODEL.outputs)
    monkeypatch.setattr(pipeline, "analyze", lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("x")))
    assert cli_main(["analyze", "--model", str(model_path), "--data", str(csv_path)]) == 2
    assert "values or model parameters too large or degenerate?" in capsys.readouterr().err


def test_no_detectable_change_or_experiment_on_a_diverging_loop():
    """The moments of signals that grow without bound mean nothing: every detectable_gain_change is
    null, no experiment is designed, and one warning says why; a bounded loop still gets values."""
    report = detect(MODEL, _log(growth=np.log(1e10) / 3000), AnalysisOptions(repair=False))
    assert [e.detectable_gain_change for e in report.elements] == [None, None]
    assert report.experiment is None
    said = [w for w in report.warnings if w.startswith("the loop diverged (y1)")]
    assert len(said) == 1 and "detectable_gain_change null" in said[0] and "\n" not in said[0]
    clean = detect(MODEL, _log(), AnalysisOptions(repair=False))
    assert all(e.detectable_gain_change is not None and np.isfinite(e.detectable_gain_change) for e in clean.elements)
    assert not any(w.startswith("the loop diverged") for w in clean.warnings)
