"""The analysis as a pipeline (core/pipeline.py): detect, repair the located elements, detect again.

Checked against its parts run by hand on a paper case with a mismatch (case 3.2): the pipeline
adds exactly the repair and the second detection to what the detection alone reports.
"""

import dataclasses

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
