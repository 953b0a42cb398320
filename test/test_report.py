"""Report and figures (issue 6), on a short simulated run of paper case 3.2, and ``analyze --bag`` = ``--data``.

Case 3.2 (:mod:`mpm_monitor.sim.cases`): rows y1 and y2 mismatched, elements (y1, u2),
(y1, u3) and (y2, u1) located.  The report must render, hold those results, and embed non-empty
PNG figures that are also written as files.
"""

import base64
import json
import re
from types import SimpleNamespace

import numpy as np
import pytest

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io import plots
from mpm_monitor.io.bags import read_bag, write_logged_data
from mpm_monitor.io.model_file import save_model
from mpm_monitor.io.report import write_report
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SAMPLES = 1500


@pytest.fixture(scope="module")
def case32():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, SAMPLES, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    data = log.as_logged_data("case 3.2 simulation")
    report = analyze(case.model, data, AnalysisOptions())
    return case, data, report


def _assert_png_not_empty(path):
    import matplotlib.image as mpimg

    raw = path.read_bytes()
    assert raw[:8] == PNG_MAGIC and len(raw) > 5000, path
    img = mpimg.imread(path)
    assert img.shape[0] > 150 and img.shape[1] > 150
    assert float(img[..., :3].std()) > 0.02, f"{path} is blank"


def test_report_renders_with_figures(case32, tmp_path):
    case, data, report = case32
    assert set(report.located_elements) == set(case.mismatched_elements)  # the run is a meaningful example
    out = write_report(tmp_path / "rep", case.model, data, report)
    assert out == tmp_path / "rep" / "report.html"
    text = out.read_text(encoding="utf-8")
    for name in ("sdelta", "elements", "detectability", "steps", "residuals"):
        png = tmp_path / "rep" / f"{name}.png"
        _assert_png_not_empty(png)
        # embedded, byte for byte, in the self-contained HTML
        assert base64.b64encode(png.read_bytes()).decode() in text
    assert len(re.findall(r'src="data:image/png;base64,', text)) == 5
    for o, i in case.mismatched_elements:
        assert f"({o}, {i})" in text
    assert "Mismatch in rows y1, y2" in text
    rows = re.findall(r'<tr class="flag"><td class="name">(y\d)</td>', text)
    assert rows == ["y1", "y2"]


def test_the_step_curves_stand_behind_the_repair(case32):
    """The step figure draws the model's and the repaired model's elements only: on (y1, u2) (plant
    gain 1.77, time constant 60 s, delay 7 s; model 45 s, 4 s) and (y1, u3) (plant gain 5.88, model
    3.5) the repaired curve ends on the plant's, and no curve contradicts the repair."""
    case, _, report = case32
    n = 400
    for j in (1, 2):
        curves = plots.step_curves(report, case.model, 0, j, n)
        assert set(curves) == {"model", "repaired model"}
        plant = plots.element_step(case.plant, 0, j, n)
        assert abs(curves["repaired model"][-1] - plant[-1]) < 0.03 * abs(plant[-1])
        assert np.max(np.abs(curves["repaired model"] - plant)) < 0.05 * np.max(np.abs(plant))


def test_analyze_bag_equals_analyze_data(case32, tmp_path):
    """``analyze --bag`` on a bag of the samples gives the report ``analyze`` gives on the samples."""
    case, data, report = case32
    model_file, bag = tmp_path / "model.yaml", tmp_path / "bag"
    save_model(case.model, model_file)
    write_logged_data(bag, data)
    back = read_bag(bag, case.model)
    for a in ("t", "r", "u", "y"):
        np.testing.assert_array_equal(getattr(back, a), getattr(data, a))
    assert cli_main(["analyze", "--model", str(model_file), "--bag", str(bag), "--json", str(tmp_path / "b.json")]) == 0
    assert json.loads((tmp_path / "b.json").read_text()) == json.loads(json.dumps(report.to_dict()))


# --- plain figures and edge cases on a report-like object --------------------------------------------


def _model():
    return PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=[[2.0, 0.0], [1.0, 3.0]],
                      time_constant=[[10.0, 0.0], [5.0, 0.0]], delay=[[3.0, 0.0], [0.0, 2.0]])


def _fake_report(model, warnings=()):
    w = np.concatenate([[0.0], np.logspace(-3, np.log10(np.pi), 63)])
    rows = [SimpleNamespace(output="y1", rsi=1.02, mismatch=False, p_value=0.4),
            SimpleNamespace(output="y2", rsi=1.01, mismatch=False, p_value=0.7)]
    return SimpleNamespace(rows=rows, elements=[], frequencies=w, row_gains=np.ones((2, w.size)),
                           sigma_max=np.ones(w.size), overall_rsi=1.02, warnings=list(warnings),
                           repair={"changes": [], "error_before": {"y1": 0.01, "y2": 0.02},
                                   "error_after": {"y1": 0.01, "y2": 0.02}},
                           repaired_model=model, arx_tables=[])


def test_report_without_mismatch_escapes_text(tmp_path):
    model = _model()
    rng = np.random.default_rng(0)
    n = 200
    data = LoggedData(t=np.arange(n, dtype=float), r=rng.normal(size=(n, 2)), u=rng.normal(size=(n, 2)),
                      y=rng.normal(size=(n, 2)), inputs=model.inputs, outputs=model.outputs, sample_time=1.0)
    out = write_report(tmp_path / "rep", model, data, _fake_report(model, ["too little <excitation> & noise"]))
    text = out.read_text()
    assert "No model-plant mismatch found." in text
    assert "too little &lt;excitation&gt; &amp; noise" in text and "<excitation>" not in text
    assert not (tmp_path / "rep" / "steps.png").exists()  # nothing located: no step figure
    assert len(re.findall(r'src="data:image/png;base64,', text)) == 3
    for name in ("sdelta", "elements", "residuals"):
        _assert_png_not_empty(tmp_path / "rep" / f"{name}.png")


def test_element_step_matches_fopdt_formula():
    model = _model()
    n = 40
    k = np.arange(n)
    expected = np.where(k >= 3, 2.0 * (1.0 - np.exp(-(k - 3.0) / 10.0)), 0.0)  # step invariance of ZOH
    np.testing.assert_allclose(plots.element_step(model, 0, 0, n), expected, atol=1e-12)
    np.testing.assert_allclose(plots.element_step(model, 1, 1, n), np.where(k >= 2, 3.0, 0.0), atol=1e-12)


def _asdict_then_clean(report):
    """The report's dict as built before :func:`json_ready`: ``dataclasses.asdict`` of its records,
    then NaN and infinity to None, numpy values to Python ones, tuples to lists."""
    import dataclasses
    import math

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, np.floating):
            return clean(float(x))
        if isinstance(x, np.integer):
            return int(x)
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.ndarray):
            return clean(x.tolist())
        return x

    doc = report.to_dict()
    for key, records in (("rows", report.rows), ("elements", report.elements), ("arx_tables", report.arx_tables)):
        doc[key] = clean([dataclasses.asdict(r) for r in records])
    return doc


def test_the_json_dict_is_asdict_then_cleaned(case32):
    from mpm_monitor.core.analysis_report import json_ready

    _, _, report = case32
    doc = report.to_dict()
    assert json.dumps(doc, indent=2) == json.dumps(_asdict_then_clean(report), indent=2)
    odd = {"a": (np.float32(np.nan), np.float64(-np.inf), np.float64(2.5), np.int64(-3), True, None),
           "b": np.array([[1.0, np.nan], [np.inf, 4.0]]), "c": [float("nan"), 1, "x", np.float32(0.5)],
           "d": report.rows[0]}
    expected = {"a": [None, None, 2.5, -3, True, None], "b": [[1.0, None], [None, 4.0]], "c": [None, 1, "x", 0.5],
                "d": _asdict_then_clean(report)["rows"][0]}
    out = json_ready(odd)
    assert out == expected and json.dumps(out) == json.dumps(expected)
    assert [type(v) for v in out["a"]] == [type(None), type(None), float, int, bool, type(None)]


def test_a_reused_report_directory_keeps_no_stale_figure(tmp_path):
    """A directory that held a report with located elements (its step responses and detectability map), then
    one without: those figures of the first are gone, not left beside the second's; other files stay."""
    (tmp_path / "rep").mkdir()
    for name in ("steps.png", "detectability.png"):
        (tmp_path / "rep" / name).write_bytes(PNG_MAGIC + b"an earlier report's figure")
    (tmp_path / "rep" / "notes.txt").write_text("mine")
    model = _model()
    rng = np.random.default_rng(0)
    n = 200
    quiet = LoggedData(t=np.arange(n, dtype=float), r=rng.normal(size=(n, 2)), u=rng.normal(size=(n, 2)),
                       y=rng.normal(size=(n, 2)), inputs=model.inputs, outputs=model.outputs, sample_time=1.0)
    write_report(tmp_path / "rep", model, quiet, _fake_report(model, []))
    assert not (tmp_path / "rep" / "steps.png").exists()
    assert not (tmp_path / "rep" / "detectability.png").exists()
    assert (tmp_path / "rep" / "notes.txt").read_text() == "mine"
    for name in ("sdelta", "elements", "residuals"):
        _assert_png_not_empty(tmp_path / "rep" / f"{name}.png")
