"""The report and its figures for every element structure and for measured-disturbance columns.

The step figure draws each element from its own sampled form (an integrator's step response is a
ramp, a step-response element's its coefficients), the element map and the step figure take the
measured disturbances' columns, and the repair table names the keys of each structure.
"""

import re

import numpy as np
import pytest
from structure_models import rich_model, step_model
from test_detection_columns import open_loop

from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io import plots
from mpm_monitor.io.report import write_report


def test_element_step_is_the_elements_own_sampled_form():
    model = rich_model()
    n = 200
    for i in range(model.n_outputs):
        for j in range(model.n_columns):
            np.testing.assert_array_equal(plots.element_step(model, i, j, n),
                                          model.discrete_element(i, j).step_response(n))
    # (y2, u1): 0.05 per second through a 5 s lag after 3 s: a ramp of slope 0.05 per sample.
    ramp = plots.element_step(model, 1, 0, n)
    assert np.diff(ramp)[-50:] == pytest.approx(0.05, rel=1e-9)
    assert ramp[-1] == pytest.approx(0.05 * (n - 1 - 3 - 5), rel=1e-6)
    steps = step_model(40)
    np.testing.assert_allclose(plots.element_step(steps, 0, 0, 41)[1:], steps.step_response[0, 0], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def disturbance_report():
    model = rich_model()
    plant = model.with_element(1, 2, gain=-0.8)
    data = open_loop(plant, model, 3000, seed=14, burn_in=300)
    return model, plant, data, analyze(model, data)


def test_a_report_with_measured_disturbances_renders(disturbance_report, tmp_path):
    model, plant, data, report = disturbance_report
    assert report.located_elements == [("y2", "dv1")]
    out = write_report(tmp_path / "rep", model, data, report)
    text = out.read_text(encoding="utf-8")
    assert len(re.findall(r'src="data:image/png;base64,', text)) == 5     # with the detectability map
    assert "1 measured disturbance (dv1)" in text
    assert "(y2, dv1)" in text
    # The repair table names the element's lead and second lag.
    assert "&tau;<sub>2</sub> 3 s, lead 2 s" in text
    assert plots.element_states(report, model).shape == (2, 3)
    curves = plots.step_curves(report, model, 1, 2, 300)
    true = plots.element_step(plant, 1, 2, 300)
    assert np.max(np.abs(curves["repaired model"] - true)) < 0.05 * np.max(np.abs(true))


def test_a_step_response_report_and_an_estimate_not_applied(tmp_path):
    model = step_model(60)
    k = np.arange(1, 61)
    sr = np.array(model.step_response)
    sr[0, 0] = np.where(k > 3, 2.1 * (1 - np.exp(-(k - 3) / 6.0)), 0.0)
    plant = model.replace(step_response=sr)
    data = open_loop(plant, model, 3000, seed=16, burn_in=300)
    report = analyze(model, data)
    assert report.located_elements == [("y1", "u1")]
    out = write_report(tmp_path / "rep", model, data, report)
    text = out.read_text(encoding="utf-8")
    assert "step response of 60 samples: final value 1.5, dead time 3 s" in text
    # On a ramp output the cell says the final slope per second, as the text summary does (it said "final value").
    from mpm_monitor.io.report import _params
    cell = {"step_response": [0.0] * 60, "gain": 0.05, "delay": 3.0}
    assert _params(cell, ramp=True) == "step response of 60 samples: final slope 0.05 per s, dead time 3 s"
    curves = plots.step_curves(report, model, 0, 0, 100)
    assert set(curves) == {"model", "repaired model"}
    assert curves["repaired model"][-1] == pytest.approx(2.1, rel=0.03)
    # An estimate the repair did not apply is drawn as such (here: the held-out check made strict).
    change = dict(report.repair["changes"][0], applied=False, reason="rejected by held-out validation")
    rejected = type("R", (), {"repaired_model": model, "repair": {"changes": [change]}, "elements": report.elements})
    curves = plots.step_curves(rejected, model, 0, 0, 100)
    assert set(curves) == {"model", "repaired model", "re-estimated (not applied)"}
    np.testing.assert_array_equal(curves["repaired model"], curves["model"])
    assert curves["re-estimated (not applied)"][-1] == pytest.approx(2.1, rel=0.03)
    assert plots.plot_step_responses(rejected, model, tmp_path / "steps.png").stat().st_size > 5000


def test_a_candidate_explained_by_another_is_said_so_in_the_report_not_no_effect():
    """A candidate whose test rejected in a row but that the row's other located column explains (released, its
    explained_by set) read "no effect found" beside its p-value below 1e-16 in the HTML report."""
    import types

    from mpm_monitor.io.report import _candidates_section, _explained_candidates

    cands = types.SimpleNamespace(tried=["feed", "sensor2"], p_values={"feed": {"y1": 1e-20}, "sensor2": {"y1": 1e-18}},
                                  located=[("y1", "feed")], added=["feed"], not_exogenous={}, unusable={})
    elements = [types.SimpleNamespace(output="y1", input="feed", role="candidate", explained_by=(), mismatch=True),
                types.SimpleNamespace(output="y1", input="sensor2", role="candidate", explained_by=("feed",),
                                      mismatch=False)]
    report = types.SimpleNamespace(candidates=cands, rows=[types.SimpleNamespace(output="y1")], elements=elements)
    explained = _explained_candidates(report)
    assert explained == {"sensor2": ["feed"]}
    html = _candidates_section(report, explained, {})
    assert "flagged, explained by feed (see the warnings)" in html and "no effect found" not in html


def test_a_candidate_released_in_a_quiet_row_is_said_so_in_the_report_not_no_effect():
    """A candidate located in a row the S_Delta row test does not flag and released because the element test with
    max_na own lags does not locate it (unlocated_at_na) reads so in the HTML report, not "no effect found"."""
    import types

    from mpm_monitor.io.report import _candidates_section, _unlocated_candidates

    cands = types.SimpleNamespace(tried=["feed"], p_values={"feed": {"y1": 1e-5}}, located=[], added=[],
                                  not_exogenous={}, unusable={})
    elements = [types.SimpleNamespace(output="y1", input="feed", role="candidate", explained_by=(), mismatch=False,
                                      unlocated_at_na=16),
                types.SimpleNamespace(output="y1", input="u1", role="input", explained_by=(), mismatch=False,
                                      unlocated_at_na=16)]
    report = types.SimpleNamespace(candidates=cands, rows=[types.SimpleNamespace(output="y1")], elements=elements)
    unlocated = _unlocated_candidates(report)
    assert unlocated == {"feed": 16}
    html = _candidates_section(report, {}, unlocated)
    assert "flagged, not with na = 16 own lags (see the warnings)" in html and "no effect found" not in html
