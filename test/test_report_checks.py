"""The report comparison of report_checks catches what it is meant to catch.

Two holes it once had: a p-value of 0 on one side was skipped instead of compared, and the rows
were zipped before their counts were checked (a report missing a row compared equal on the rest).
"""

import copy

import pytest
from report_checks import P_UNDERFLOW, _close_log_p, assert_reports_match

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop


@pytest.fixture(scope="module")
def report():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 1500, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    return analyze(case.model, log.as_logged_data(), AnalysisOptions(repair=False, test_all_rows=True))


def test_a_report_matches_itself(report):
    assert_reports_match(copy.deepcopy(report), report)


def test_a_missing_row_is_caught_before_the_rows_are_zipped(report):
    short = copy.deepcopy(report)
    short.rows = short.rows[:-1]
    with pytest.raises(AssertionError, match="rows: 2 vs 3"):
        assert_reports_match(short, report)


def test_a_zero_p_value_is_compared_not_skipped():
    _close_log_p(0.0, 0.0, "p")
    _close_log_p(0.0, P_UNDERFLOW / 10, "p")      # both underflowed (or nearly): equal
    with pytest.raises(AssertionError, match="one p-value is 0"):
        _close_log_p(0.0, 0.01, "p")
    with pytest.raises(AssertionError, match="one p-value is 0"):
        _close_log_p(0.5, 0.0, "p")


def test_a_zero_element_p_value_against_a_real_one_fails_the_reports(report):
    i = next(k for k, e in enumerate(report.elements) if e.p_value_raw is not None and e.p_value_raw > 1e-6)
    other = copy.deepcopy(report)
    other.elements[i].p_value_raw = 0.0
    with pytest.raises(AssertionError, match="one p-value is 0"):
        assert_reports_match(other, report)
