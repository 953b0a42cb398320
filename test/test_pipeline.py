"""The analysis as a pipeline (core/pipeline.py): detect, repair the located elements, detect again.

Checked against its parts run by hand on a paper case with a mismatch (case 3.2): the pipeline
adds exactly the repair and the second detection to what the detection alone reports.
"""

import dataclasses
from types import SimpleNamespace

import pytest

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop


@pytest.fixture(scope="module")
def case_data():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 3000, seed=11, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    data = LoggedData(t=log.t, r=log.r, u=log.u, y=log.y, inputs=log.inputs, outputs=log.outputs,
                      sample_time=log.sample_time)
    return case, data


def test_detect_runs_the_tests_only(case_data):
    case, data = case_data
    rep = detect(case.model, data, AnalysisOptions(repair=True))
    assert set(rep.located_elements) == set(case.mismatched_elements)
    assert rep.repaired_model == case.model and rep.repair_result is None
    assert rep.repair["changes"] == [] and rep.repair["error_before"] == rep.repair["error_after"]
    assert "rsi_after" not in rep.repair
    assert {e.kind for e in rep.elements if e.mismatch} == {"unknown"}
    assert {e.kind for e in rep.elements if not e.mismatch} == {None}
    no_repair = analyze(case.model, data, AnalysisOptions(repair=False))
    assert no_repair.to_dict() == rep.to_dict()


def test_analyze_is_detect_then_repair_then_detect_again(case_data):
    case, data = case_data
    options = AnalysisOptions()
    rep = analyze(case.model, data, options)
    first = detect(case.model, data, options)
    assert [r.p_value for r in rep.rows] == [r.p_value for r in first.rows]
    assert rep.located_elements == first.located_elements
    located = [(case.model.outputs.index(o), case.model.inputs.index(i)) for o, i in first.located_elements]
    result = repair_model(case.model, data, located, RepairOptions(initial_state=options.initial_state),
                          signals=first.signals)
    assert result.model != case.model and rep.repaired_model == result.model
    after = detect(result.model, data, dataclasses.replace(options, test_all_rows=False))
    assert rep.repair["rsi_after"] == {r.output: r.rsi for r in after.rows}
    assert rep.repair["rows_flagged_after"] == after.flagged_rows
    for e in rep.elements:
        if e.mismatch:
            key = (case.model.outputs.index(e.output), case.model.inputs.index(e.input))
            assert e.kind == result.kinds[key] != "unknown"
    assert all(w in rep.warnings for w in result.warnings)


def _element(output, column, mismatch=False, ambiguous=False):
    return SimpleNamespace(output=output, input=column, mismatch=mismatch, ambiguous=ambiguous)


def test_a_repaired_row_still_flagged_is_warned_of():
    """Only a row whose repair was applied and that the repaired model's detection still flags gets a warning.  One
    that holds an ambiguous element not located: it names the repaired and the ambiguous elements; one that holds
    none (since stop 73): the repaired element's structure may lack the plant's shape, or an element was missed."""
    from mpm_monitor.core.pipeline import _still_flagged

    report = SimpleNamespace(elements=[
        _element("y1", "u1", mismatch=True), _element("y1", "u2", ambiguous=True), _element("y1", "u3", ambiguous=True),
        _element("y2", "u1", mismatch=True), _element("y2", "u2", ambiguous=True),
        _element("y3", "u1", mismatch=True), _element("y3", "u2"),
        _element("y4", "u1", mismatch=True), _element("y4", "u2", ambiguous=True)])
    changes = [{"output": o, "input": "u1", "applied": o != "y4"} for o in ("y1", "y2", "y3", "y4")]
    warnings = _still_flagged(report, changes, ["y1", "y3", "y4"])
    assert len(warnings) == 2              # y2 is not flagged after, y4 not applied
    assert warnings[0].startswith("y1: still flagged after the repair of u1; the elements of u2, u3 cannot be told "
                                  "apart from these data (ambiguous) and were held as the model has them")
    assert "the re-estimated element of u1 may have taken part of it" in warnings[0]
    assert warnings[1].startswith("y3: still flagged after the repair of u1; the re-estimated element, in the "
                                  "structure the model gives it, does not explain the row's mismatch whole")
    assert _still_flagged(report, changes, []) == []


def test_a_repair_beside_an_ambiguous_mismatch_is_applied_with_a_warning():
    """bench.structures_mc --lost-lag run 267: the plant lost the second lags of (y1, u1) and (y1, u3); u3 moves with
    the other inputs (variance inflation 252), so (y1, u3) is ambiguous and only (y1, u1) is located.  Its repair,
    fitted with (y1, u3) held as the model has it, takes part of that element's error (its step response 14 % off,
    3 % before), while the row's prediction improves (held-out error 0.24 -> 0.11, the noise about 0.03) and the
    row stays flagged.  The report said nothing of that; it now warns."""
    from bench.structures_mc import StructuresOptions
    from test_repair_structures import structures_scenario_report

    _, report = structures_scenario_report(StructuresOptions(lost_lag=True), 267)
    assert report.located_elements == [("y1", "u1")] and ("y1", "u3") in report.ambiguous_elements
    assert report.repair["rows_flagged_after"] == ["y1"]
    warned = [w for w in report.warnings if w.startswith("y1: still flagged after the repair of u1; the element of u3 "
                                                          "cannot be told apart")]
    assert len(warned) == 1 and warned[0] in report.repair["warnings"]
