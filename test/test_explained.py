"""Tests of the release of located elements that another located element of their row explains.

:func:`mpm_monitor.core.repair.explained_elements` re-estimates a row's located elements jointly
(the repair's classification) and releases an element that does not differ from the model while
another located element of the row does.  :func:`mpm_monitor.core.pipeline.analyze` runs it before
the repair, with or without the repair, so the located elements never depend on ``repair``.
"""

import pytest

from mpm_monitor.core import pipeline
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.repair import explained_elements, repair_model
from mpm_monitor.sim.cases import shell_plant
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.plant import DisturbanceOptions

N_SAMPLES = 4000


def _loop(plant, model, seed):
    log = run_closed_loop(plant, model, N_SAMPLES, seed=seed, disturbance=DisturbanceOptions())
    return log.as_logged_data()


@pytest.fixture(scope="module")
def wrong_gain():
    """The shell plant; the model's (y2, u2) gain is 4.0 (the plant's 5.72)."""
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=4.0)
    return sh, model, _loop(sh, model, 21)


@pytest.mark.parametrize("clean", [0, 2])
def test_a_clean_element_located_beside_the_mismatched_one_is_released(wrong_gain, clean):
    _, model, data = wrong_gain
    found = explained_elements(model, data, [(1, 1), (1, clean)])
    assert found.released == {(1, clean): [1]}
    js, (free, verdicts, _) = found.rows[1]
    assert js == tuple(sorted((1, clean))) and verdicts[1].kind == "gain" and verdicts[clean].kind == "unknown"


def test_an_element_alone_in_its_row_is_never_released_and_nothing_is_fitted(wrong_gain, monkeypatch):
    _, model, data = wrong_gain
    from mpm_monitor.core.repair import explained

    def fail(*args, **kwargs):
        raise AssertionError("a row with one located element was classified")

    monkeypatch.setattr(explained, "_classify_row", fail)
    found = explained_elements(model, data, [(1, 1), (0, 2)])
    assert found.released == {} and found.rows == {}


def test_two_mismatched_elements_of_a_row_are_both_kept():
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=4.0).with_element(1, 0, time_constant=3 * sh.time_constant[1, 0])
    data = _loop(sh, model, 22)
    found = explained_elements(model, data, [(1, 0), (1, 1)])
    assert found.released == {}
    verdicts = found.rows[1][1][1]
    assert verdicts[1].kind == "gain" and verdicts[0].kind in ("time_constant", "mixed")


def test_the_release_is_repeated_on_the_elements_kept_until_it_releases_nothing(wrong_gain, monkeypatch):
    # The row's classification is replaced by a script: with u1, u2, u3 located u2 does not change;
    # with u1 and u3 left, u3 does not either; so both go, both explained by u1, the one kept.
    from types import SimpleNamespace

    from mpm_monitor.core.repair import explained

    script = {(0, 1, 2): {0: "gain", 1: "unknown", 2: "delay"}, (0, 2): {0: "gain", 2: "unknown"}}
    calls = []

    def classify(row, js, settings):
        calls.append(tuple(js))
        return "free", {j: SimpleNamespace(kind=k) for j, k in script[tuple(js)].items()}, ["w"]

    monkeypatch.setattr(explained, "_classify_row", classify)
    _, model, data = wrong_gain
    found = explained_elements(model, data, [(1, 0), (1, 1), (1, 2)])
    assert calls == [(0, 1, 2), (0, 2)]
    assert found.released == {(1, 1): [0], (1, 2): [0]}
    assert found.rows[1][0] == (0, 2)      # the last classification: not the row's located elements


def test_the_repair_reuses_the_classification_with_the_same_result(wrong_gain):
    _, model, data = wrong_gain
    located = [(1, 1), (1, 2)]
    again = repair_model(model, data, located)
    reused = repair_model(model, data, located, classified=explained_elements(model, data, located))
    assert reused.to_dict() == again.to_dict()


def test_a_row_where_no_element_changed_keeps_its_elements(wrong_gain):
    sh, _, _ = wrong_gain
    data = _loop(sh, sh, 23)
    found = explained_elements(sh, data, [(0, 0), (0, 1)])
    assert found.released == {}
    assert {v.kind for v in found.rows[0][1][1].values()} == {"unknown"}


@pytest.mark.parametrize("repair", [True, False])
def test_analyze_releases_before_the_repair_and_says_so(wrong_gain, monkeypatch, repair):
    _, model, data = wrong_gain
    real_detect = pipeline.detect

    def first_detection(m, d, o, **kw):      # the detection of the repaired model is pipeline.detect's
        report = real_detect(m, d, o, **kw)
        for e in report.elements:
            e.mismatch = (e.output, e.input) in {("y2", "u2"), ("y2", "u3")}
        return report

    monkeypatch.setattr(pipeline, "detect_unless_coloured", first_detection)
    report = pipeline.analyze(model, data, AnalysisOptions(repair=repair))
    assert report.located_elements == [("y2", "u2")]
    released = [e for e in report.elements if e.explained_by]
    assert [(e.output, e.input, e.explained_by, e.mismatch) for e in released] == [("y2", "u3", ("u2",), False)]
    assert any("y2: the element test also flagged u3" in w and "u2 explains" in w for w in report.warnings)
    doc = report.to_dict()
    assert doc["located"] == [{"output": "y2", "input": "u2"}]
    assert [e["explained_by"] for e in doc["elements"] if e["input"] == "u3" and e["output"] == "y2"] == [["u2"]]
    if repair:
        assert [(c["output"], c["input"], c["kind"]) for c in doc["repair"]["changes"]] == [("y2", "u2", "gain")]
    else:
        assert doc["repair"]["changes"] == []


def test_analyze_without_release_keeps_both(wrong_gain, monkeypatch):
    _, model, data = wrong_gain
    real_detect = pipeline.detect

    def detect(m, d, o, **kw):
        report = real_detect(m, d, o, **kw)
        for e in report.elements:
            e.mismatch = (e.output, e.input) in {("y2", "u2"), ("y2", "u3")}
        return report

    monkeypatch.setattr(pipeline, "detect_unless_coloured", detect)
    report = pipeline.analyze(model, data, AnalysisOptions(repair=False, release_explained=False))
    assert report.located_elements == [("y2", "u2"), ("y2", "u3")]
    assert not any(e.explained_by for e in report.elements)
