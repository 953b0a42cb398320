"""MonitorCore and AnalysisWorker: schedule, statuses (names, values, levels), STALE, ERROR, threading.

Most tests inject a fake analysis (plain objects with the AnalysisReport fields the monitor reads)
to check the plumbing; the suggested repair in the statuses and the writing of the repaired model
are checked on a real AnalysisReport (with the repair) of a short run of paper case 3.2.  The
analysis through the nodes is exercised in test_nodes_inprocess.py.
"""

import dataclasses
import os
import subprocess
import sys
import threading
import types

import numpy as np
import pytest

from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.statuses import ERROR, OK, STALE, SUMMARY_NAME, WARN
from mpm_monitor.monitor.window import WindowOptions
from mpm_monitor.monitor.worker import AnalysisWorker, run_analysis
from mpm_monitor.sim.cases import paper_case

NS = 1_000_000_000
MODEL = paper_case("3.2").model  # outputs y1..y3, inputs u1..u3, Ts = 1 s


def fake_report(flags=None, rsi=(1.5, 1.2, 1.0), samples=0, warnings=()):
    """An object with the fields of AnalysisReport that the monitor reads; ``flags`` = {output: [inputs]}."""
    flags = flags or {}
    rows = [types.SimpleNamespace(output=o, rsi=r, mismatch=o in flags, p_value=1e-9 if o in flags else 0.4)
            for o, r in zip(MODEL.outputs, rsi)]
    elements = [types.SimpleNamespace(output=o, input=i, mismatch=i in flags.get(o, ()), p_value=1e-12,
                                      kind="gain", ambiguous=False)
                for o in flags for i in MODEL.inputs]
    return types.SimpleNamespace(rows=rows, elements=elements, overall_rsi=max(rsi), warnings=list(warnings),
                                 samples=samples)


def core(**kw):
    win = kw.pop("window", WindowOptions(window_samples=50))
    opts = dict(analysis_period=10, min_samples=20, stale_timeout=2.0, hardware_id="test")
    opts.update(kw)
    return MonitorCore(MODEL, MonitorOptions(window=win, **opts))


def feed(c, k0, k1, now=0.0):
    for k in range(k0, k1):
        c.add("setpoint", k * NS, np.full(3, 0.1 * k), now)
        c.add("input", k * NS, np.full(3, 0.2 * k), now)
        c.add("output", k * NS, np.full(3, 0.3 * k), now)


def by_name(statuses):
    return {s.name: s for s in statuses}


def test_statuses_before_the_first_analysis_are_named_per_contract():
    c = core()
    feed(c, 0, 5)
    st = c.statuses(now=0.0)
    assert [s.name for s in st] == ["mpm_monitor: row y1", "mpm_monitor: row y2", "mpm_monitor: row y3", SUMMARY_NAME]
    assert all(s.level == OK and s.hardware_id == "test" for s in st)
    assert st[0].value("analyzed") == "false" and st[0].value("mismatch") == "false"
    assert "5 of 20 samples" in st[-1].message


def test_analysis_is_due_at_min_samples_then_every_period_on_the_window():
    c = core()
    feed(c, 0, 19)
    assert not c.analysis_due()
    feed(c, 19, 20)
    assert c.analysis_due()
    job = c.take_job()
    assert job.data.n_samples == 20 and job.first_stamp == 0.0 and job.last_stamp == 19.0
    np.testing.assert_allclose(job.data.u[:, 0], 0.2 * np.arange(20))
    feed(c, 20, 29)
    assert not c.analysis_due() and c.analysis_due(force=True)
    feed(c, 29, 30)
    assert c.analysis_due()
    feed(c, 30, 80)
    job = c.take_job()
    assert job.data.n_samples == 50 and job.last_stamp == 79.0  # the sliding window


def test_a_report_becomes_row_and_summary_statuses():
    c = core()
    feed(c, 0, 20)
    job = c.take_job()
    c.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u2", "u3"], "y2": ["u1"]}, samples=d.n_samples),
                          MODEL, None, job))
    st = by_name(c.statuses(now=0.0))
    y1, y2, y3, summary = (st["mpm_monitor: row y1"], st["mpm_monitor: row y2"], st["mpm_monitor: row y3"],
                           st[SUMMARY_NAME])
    assert y1.level == WARN and y1.value("mismatch") == "true" and y1.value("flagged_inputs") == "u2,u3"
    assert float(y1.value("rsi")) == 1.5 and float(y1.value("p_value")) == 1e-9
    assert y1.value("kind u2") == "gain" and y1.value("p_value u3") == "1e-12"
    assert y2.level == WARN and y2.value("flagged_inputs") == "u1"
    assert y3.level == OK and y3.value("mismatch") == "false" and y3.value("flagged_inputs") == ""
    assert summary.level == WARN and summary.value("flagged_rows") == "y1,y2"
    assert summary.value("located_elements") == "y1:u2,y1:u3,y2:u1"
    assert summary.value("samples") == "20" and summary.value("window_end") == "19.0"
    assert summary.value("na") is None                         # a report without noise_order (a baseline method)
    np.testing.assert_array_equal(c.rsi_vector(), [1.5, 1.2, 1.0])


def test_the_summary_names_the_arx_order_the_tests_ran_with():
    c = core()
    feed(c, 0, 20)
    rep = fake_report({"y1": ["u2"]}, samples=20)
    rep.noise_order = {"na": 8, "requested": 4, "max_na": 16, "coloured": [], "p_values": {"y1": 0.3}}
    c.accept(run_analysis(lambda m, d, o: rep, MODEL, None, c.take_job()))
    assert by_name(c.statuses(now=0.0))[SUMMARY_NAME].value("na") == "8"


def test_a_released_element_is_named_in_its_rows_status_and_not_located():
    c = core()
    feed(c, 0, 20)
    rep = fake_report({"y1": ["u2"]}, samples=20)
    for e in rep.elements:
        e.explained_by = ("u2",) if e.input == "u3" else ()
    c.accept(run_analysis(lambda m, d, o: rep, MODEL, None, c.take_job()))
    st = by_name(c.statuses(now=0.0))
    y1, y2 = st["mpm_monitor: row y1"], st["mpm_monitor: row y2"]
    assert y1.value("explained_inputs") == "u3" and y1.value("flagged_inputs") == "u2"
    assert y1.value("kind u3") is None and y2.value("explained_inputs") is None


def test_an_element_released_in_a_quiet_row_is_named_in_its_rows_status_and_not_located():
    c = core()
    feed(c, 0, 20)
    rep = fake_report({"y1": ["u2"], "y2": []}, samples=20)
    for e in rep.elements:
        e.unlocated_at_na = 16 if (e.output, e.input) == ("y2", "u1") else None
    c.accept(run_analysis(lambda m, d, o: rep, MODEL, None, c.take_job()))
    st = by_name(c.statuses(now=0.0))
    y1, y2 = st["mpm_monitor: row y1"], st["mpm_monitor: row y2"]
    assert y2.value("unlocated_inputs") == "u1" and y2.value("flagged_inputs") == ""
    assert y1.value("unlocated_inputs") is None and y1.value("flagged_inputs") == "u2"
    assert st[SUMMARY_NAME].value("located_elements") == "y1:u2"


def test_a_stuck_output_is_an_error_of_its_row_and_of_the_summary():
    """An output that never moves in the window (the report's ``still_outputs``): its row's status was WARN
    ("mismatch in row y2: no single element located"), the summary's too; a stuck sensor is bad input data."""
    c = core()
    feed(c, 0, 20)
    rep = fake_report({"y1": ["u2"]}, samples=20)
    rep.rows[1].mismatch = True
    rep.still_outputs = ["y2"]
    c.accept(run_analysis(lambda m, d, o: rep, MODEL, None, c.take_job()))
    st = by_name(c.statuses(now=0.0))
    y1, y2, y3, summary = (st["mpm_monitor: row y1"], st["mpm_monitor: row y2"], st["mpm_monitor: row y3"],
                           st[SUMMARY_NAME])
    assert y2.level == ERROR and y2.message.startswith("output y2 never moves in this window (every value the same")
    assert y2.value("mismatch") == "true" and y2.value("flagged_inputs") == ""
    assert y1.level == WARN and y3.level == OK
    assert summary.level == ERROR and summary.value("still_outputs") == "y2"
    assert summary.message.startswith("output y2 never moves (a stuck sensor or a held value?); mismatch in row(s)")


def test_a_window_too_short_for_the_tests_is_waited_on_not_an_error():
    """A window whose samples (a small min_samples), or whose regression rows between its gaps (a lossy link),
    are fewer than the tests need: every such analysis was ERROR ("analysis failed: DataFileError: ros: 132
    regression rows ... need at least 191 rows").  It is waited on now: OK with the reason before a first result,
    the latest result kept after one (the summary value ``last_analysis_skipped`` says why)."""
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze

    c = core()
    feed(c, 0, 20)
    c.accept(run_analysis(analyze, MODEL, AnalysisOptions(), c.take_job()))     # 20 samples: the tests need more
    st = by_name(c.statuses(now=0.0))
    summary = st[SUMMARY_NAME]
    assert all(s.level == OK for s in st.values()), summary.message
    assert summary.message.startswith("no analysis yet: the window is still too short for the tests (the window: "
                                      "20 samples; the tests with na=4")
    assert c.results == 0
    feed(c, 20, 30)
    c.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u2"]}, samples=d.n_samples), MODEL, None,
                          c.take_job()))
    assert by_name(c.statuses(now=0.0))[SUMMARY_NAME].value("last_analysis_skipped") is None
    feed(c, 30, 40)
    c.accept(run_analysis(analyze, MODEL, AnalysisOptions(), c.take_job()))
    summary = by_name(c.statuses(now=0.0))[SUMMARY_NAME]
    assert summary.level == WARN and summary.value("located_elements") == "y1:u2" and c.results == 1
    assert summary.value("last_analysis_skipped").startswith("the window: 40 samples; the tests with na=4")


def test_a_full_window_too_short_for_the_tests_is_an_error_that_says_to_raise_window_samples():
    """Stop 73's audit: window_samples 200 on a model whose tests need 206 said "no analysis yet: the window is
    still too short" at OK for ever."""
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze

    c = core(window=WindowOptions(window_samples=30))
    feed(c, 0, 40)
    c.accept(run_analysis(analyze, MODEL, AnalysisOptions(), c.take_job()))
    st = by_name(c.statuses(now=0.0))
    summary = st[SUMMARY_NAME]
    assert summary.level == ERROR and st["mpm_monitor: row y1"].level == ERROR
    assert summary.message.startswith("window_samples 30 is too short for the tests even when the window is full "
                                      "(the window: 30 samples; the tests with na=4"), summary.message
    assert summary.message.endswith("): raise window_samples")


def test_no_mismatch_is_ok_everywhere():
    c = core()
    feed(c, 0, 20)
    c.accept(run_analysis(lambda m, d, o: fake_report(), MODEL, None, c.take_job()))
    assert all(s.level == OK for s in c.statuses(now=0.0))


def test_the_statuses_are_functions_of_the_outcome_and_the_window_alone():
    from mpm_monitor.monitor.statuses import mark_stale, row_statuses, stale_reason, summary_status, window_values

    c = core()
    feed(c, 0, 20)
    outcome = run_analysis(lambda m, d, o: fake_report({"y2": ["u1"]}), MODEL, None, c.take_job())
    c.accept(outcome)
    window = window_values(c.window.health(), c.window.n_window)
    rows = row_statuses(MODEL.outputs, outcome, None, "waiting", "test")
    summary = summary_status(outcome, 1, None, "waiting", window, None, None, "test")
    assert rows + [summary] == c.statuses(now=0.0)
    assert row_statuses(MODEL.outputs, outcome, None, "waiting", "test") == rows  # nothing kept between calls
    assert summary_status(outcome, 1, None, "waiting", window, "off grid", None, "test").level == ERROR
    assert summary_status(outcome, 1, None, "waiting", window, None, None, "test") == summary
    assert [s.level for s in row_statuses(MODEL.outputs, None, None, "waiting", "test")] == [OK] * 3
    arrival = {"setpoint": 0.0, "input": 0.0, "output": None}
    assert stale_reason(1.0, 2.0, 0.0, 0.0, arrival) is None
    reason = stale_reason(3.0, 2.0, None, 0.0, arrival)
    assert reason == "no complete sample yet for 3.0 s (last setpoint 3.0 s ago, input 3.0 s ago, output never)"
    stale = mark_stale(rows, reason)
    assert all(s.level == STALE and s.message.startswith(reason + "; last result: ") for s in stale)
    assert mark_stale(rows, None) == rows


def test_an_analysis_failure_is_error_with_the_reason_until_the_next_success():
    c = core()
    feed(c, 0, 20)

    def broken(m, d, o):
        raise np.linalg.LinAlgError("singular matrix")

    c.accept(run_analysis(broken, MODEL, None, c.take_job()))
    st = c.statuses(now=0.0)
    assert all(s.level == ERROR for s in st)
    assert "analysis failed: LinAlgError: singular matrix" in st[-1].message
    feed(c, 20, 30)
    c.accept(run_analysis(lambda m, d, o: fake_report(), MODEL, None, c.take_job()))
    assert all(s.level == OK for s in c.statuses(now=0.0))


def test_bad_data_makes_the_summary_error_until_a_clean_analysis_period():
    c = core()
    feed(c, 0, 20)
    c.accept(run_analysis(lambda m, d, o: fake_report(), MODEL, None, c.take_job()))
    c.bad_message("output", "output: non-finite value(s) y2=nan at t = 20 s (expected finite numbers)", 0.0)
    assert c.data_errors == 1
    st = by_name(c.statuses(now=0.0))
    assert st[SUMMARY_NAME].level == ERROR and "y2=nan" in st[SUMMARY_NAME].message
    assert st[SUMMARY_NAME].value("bad_messages") == "1"
    assert st["mpm_monitor: row y1"].level == OK  # the rows keep the last result
    feed(c, 20, 29)
    assert c.statuses(now=0.0)[-1].level == ERROR
    feed(c, 29, 31)
    assert c.statuses(now=0.0)[-1].level == OK


def test_statuses_turn_stale_when_samples_stop():
    c = core(stale_timeout=2.0)
    feed(c, 0, 20, now=10.0)
    c.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u3"]}), MODEL, None, c.take_job()))
    assert c.statuses(now=11.9)[0].level == WARN
    c.add("output", 20 * NS, np.zeros(3), 13.0)  # an output alone completes nothing
    st = c.statuses(now=12.5)
    assert all(s.level == STALE for s in st)
    assert "no complete sample for 2.5 s" in st[-1].message and "input 2.5 s ago" in st[-1].message
    assert st[0].value("flagged_inputs") == "u3"  # the last result is kept in the values


def test_no_data_at_all_is_stale_after_the_timeout():
    c = core(stale_timeout=1.0)
    c.start(now=0.0)
    assert c.statuses(now=0.5)[-1].level == OK
    st = c.statuses(now=1.5)
    assert all(s.level == STALE for s in st) and "setpoint never" in st[-1].message


def test_an_older_result_does_not_replace_a_newer_one():
    c = core()
    feed(c, 0, 20)
    j1 = c.take_job()
    feed(c, 20, 30)
    j2 = c.take_job()
    c.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u1"]}), MODEL, None, j2))
    c.accept(run_analysis(lambda m, d, o: fake_report(), MODEL, None, j1))
    assert c.statuses(now=0.0)[0].level == WARN


class _HeldWorker:
    """An :class:`AnalysisWorker` whose analyses wait for :attr:`release` and record their window lengths."""

    def __init__(self):
        self.release, self.started, self.seen = threading.Event(), threading.Event(), []

        def slow(model, data, options):
            self.started.set()
            self.release.wait(5.0)
            self.seen.append(data.n_samples)
            return fake_report()

        self.worker = AnalysisWorker(lambda job: run_analysis(slow, MODEL, None, job))

    def finish(self, n: int) -> list:
        """Release the analyses, wait until ``n`` ran and the worker is idle; the outcomes' window lengths."""
        self.release.set()
        for _ in range(500):
            if self.worker.idle and len(self.seen) == n:
                break
            threading.Event().wait(0.01)
        return [o.job.data.n_samples for o in self.worker.take_outcomes()]

    def close(self):
        self.release.set()
        self.worker.close()


def test_worker_runs_jobs_in_a_thread_and_replaces_a_waiting_job():
    c = core()
    held = _HeldWorker()
    worker = held.worker
    try:
        feed(c, 0, 20)
        worker.submit(c.take_job())      # runs
        assert held.started.wait(5.0)
        feed(c, 20, 30)
        worker.submit(c.take_job())      # waits
        feed(c, 30, 40)
        worker.submit(c.take_job())      # replaces the waiting one
        assert worker.replaced == 1 and not worker.idle
        assert held.finish(2) == [20, 40] == held.seen
    finally:
        held.close()


def test_worker_never_replaces_a_kept_job_and_runs_the_newest_other_one_after_it():
    c = core()
    held = _HeldWorker()
    worker = held.worker
    try:
        feed(c, 0, 20)
        worker.submit(c.take_job())                                    # runs
        assert held.started.wait(5.0)
        feed(c, 20, 30)
        worker.submit(dataclasses.replace(c.take_job(), keep=True))    # waits: e.g. the window of an experiment
        for end in (40, 50):
            feed(c, end - 10, end)
            worker.submit(c.take_job())        # waits behind it; the one of 50 samples replaces the one of 40
        assert worker.replaced == 1 and not worker.idle
        assert held.finish(3) == [20, 30, 50] == held.seen
    finally:
        held.close()


def test_a_keyboard_interrupt_in_an_analysis_is_an_error_outcome_and_the_worker_goes_on():
    """The worker's thread survives anything an analysis raises, ``KeyboardInterrupt`` too (what a child process
    interrupted by Ctrl-C passed back before it ignored SIGINT): that job's outcome is an error, the next runs."""
    c = core()
    calls = []

    def interrupted_once(job):
        calls.append(job.data.n_samples)
        if len(calls) == 1:
            raise KeyboardInterrupt
        return run_analysis(lambda model, data, options: fake_report(), MODEL, None, job)

    done = threading.Event()
    worker = AnalysisWorker(interrupted_once, on_done=done.set)
    try:
        feed(c, 0, 20)
        worker.submit(c.take_job())
        assert done.wait(5.0)
        done.clear()
        feed(c, 20, 30)
        worker.submit(c.take_job())
        assert done.wait(5.0)
        for _ in range(500):
            if worker.idle:
                break
            threading.Event().wait(0.01)
        first, second = worker.take_outcomes()
        assert first.error == "analysis failed: KeyboardInterrupt" and first.report is None
        assert second.error is None and second.report is not None and calls == [20, 30]
    finally:
        worker.close()


def test_the_analysis_process_ignores_sigint():
    """A terminal's Ctrl-C reaches the analysis process with the monitor's: the child ignores it (the monitor stops
    it), so it prints no traceback and ends no analysis; SIGINT sent to the child alone changes nothing."""
    import signal

    from mpm_monitor.monitor.worker import ProcessAnalyzer

    pa = ProcessAnalyzer(_handler_in_child)
    try:
        assert pa(signal.SIGINT, None, None) == signal.SIG_IGN
    finally:
        pa.close()


def _handler_in_child(signum, data, options):
    """Run in the analysis process (as ``analyze(model, data, options)``): its handler of ``signum``."""
    import signal

    return signal.getsignal(signum)


def test_options_are_checked():
    with pytest.raises(ConfigurationError, match="min_samples"):
        MonitorOptions(window=WindowOptions(window_samples=100), min_samples=200)
    with pytest.raises(ConfigurationError, match="analysis_period"):
        MonitorOptions(analysis_period=0)
    with pytest.raises(ConfigurationError, match="stale_timeout"):
        MonitorOptions(stale_timeout=0.0)


def test_the_core_imports_without_rclpy():
    code = ("import sys; sys.modules['rclpy'] = None\n"
            "import mpm_monitor.monitor.monitor_core, mpm_monitor.monitor.window, mpm_monitor.nodes.ros_io\n"
            "assert 'rclpy' not in [m for m in sys.modules if sys.modules[m] is not None]\n")
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------------- the suggested repair
# A real AnalysisReport (with the repair) of a short run of paper case 3.2, through the core's window.

REPAIR_SAMPLES = 1000


@pytest.fixture(scope="module")
def repaired_core():
    """(core, report) after one real analysis with the repair of 1000 samples of case 3.2 (seed 1)."""
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.sim.closed_loop import run_closed_loop

    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, REPAIR_SAMPLES, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    c = core(window=WindowOptions(window_samples=REPAIR_SAMPLES), min_samples=REPAIR_SAMPLES,
             analysis_period=REPAIR_SAMPLES)
    for k in range(REPAIR_SAMPLES):
        c.add("setpoint", k * NS, log.r[k], 0.0)
        c.add("input", k * NS, log.u[k], 0.0)
        c.add("output", k * NS, log.y[k], 0.0)
    assert c.analysis_due()
    outcome = run_analysis(analyze, MODEL, AnalysisOptions(repair=True), c.take_job())
    assert outcome.error is None, outcome.error
    c.accept(outcome)
    return c, outcome.report


def test_describe_change_names_only_the_changed_parameters_with_units():
    from mpm_monitor.core.wording import describe_change, row_repair_text

    before = {"gain": 1.77, "time_constant": 45.0, "delay": 4.0}
    ch = {"output": "y1", "input": "u2", "applied": True, "before": before,
          "after": {"gain": 1.77, "time_constant": 60.0057, "delay": 7.0}}
    assert describe_change(ch) == "time_constant 45->60 s, delay 4->7 s"
    g = {"output": "y1", "input": "u3", "applied": True, "before": {"gain": 3.5, "time_constant": 50.0, "delay": 6.0},
         "after": {"gain": 5.8773, "time_constant": 50.0, "delay": 6.0}}
    assert describe_change(g) == "gain 3.5->5.88"
    kept = {"output": "y2", "input": "u1", "applied": False, "before": before, "after": before,
            "reason": "rejected by held-out validation"}
    assert describe_change(kept) == ""
    assert row_repair_text([ch, g, kept], "y1") == "u2: time_constant 45->60 s, delay 4->7 s; u3: gain 3.5->5.88"
    assert row_repair_text([ch, g, kept], "y2") == "u1: kept (rejected by held-out validation)"
    assert row_repair_text([ch, g, kept], "y3") == ""
    # A change hidden by the three digits (2 -> 2) is worded with the digits that tell it apart.
    small = {"output": "y1", "input": "u1", "applied": True, "before": {"gain": 1.9992, "time_constant": 10.0,
                                                                       "delay": 2.0},
             "after": {"gain": 2.0033, "time_constant": 10.0, "delay": 2.0}}
    assert describe_change(small) == "gain 1.999->2.003"
    step = {"output": "y1", "input": "u1", "applied": True, "before": {"gain": 1.9992, "delay": 2.0,
                                                                      "step_response": [0.0, 1.0, 1.9992]},
            "after": {"gain": 2.0033, "delay": 2.0, "step_response": [0.0, 1.0, 2.0033]}}
    assert describe_change(step) == "step response re-estimated: final value 1.999->2.003"


def test_the_suggested_repair_is_in_the_row_statuses(repaired_core):
    from mpm_monitor.core.wording import describe_change

    c, rep = repaired_core
    assert sorted(rep.located_elements) == [("y1", "u2"), ("y1", "u3"), ("y2", "u1")]
    st = by_name(c.statuses(now=0.0))
    changes = rep.repair["changes"]
    for o in MODEL.outputs:
        s = st[f"mpm_monitor: row {o}"]
        row = next(r for r in rep.rows if r.output == o)
        # the contract keys are unchanged by the repair
        assert float(s.value("rsi")) == row.rsi and s.value("mismatch") == ("true" if row.mismatch else "false")
        assert s.value("flagged_inputs") == ",".join(i for oo, i in rep.located_elements if oo == o)
        assert float(s.value("error_before")) == rep.repair["error_before"][o]
        assert float(s.value("error_after")) == rep.repair["error_after"][o]
        assert float(s.value("rsi_after")) == rep.repair["rsi_after"][o]
        row_changes = [ch for ch in changes if ch["output"] == o]
        for ch in row_changes:
            assert ch["applied"]
            assert f"{ch['input']}: {describe_change(ch)}" in s.value("repair")
            e = next(e for e in rep.elements if (e.output, e.input) == (o, ch["input"]))
            assert s.value(f"kind {ch['input']}") == e.kind == ch["kind"] != "unknown"
            assert float(s.value(f"confidence {ch['input']}")) == ch["confidence"]
        if row_changes:
            # what the repair guarantees on a located row: at least halves the prediction error
            assert float(s.value("error_after")) < 0.5 * float(s.value("error_before"))
            assert float(s.value("holdout_error_after")) < float(s.value("holdout_error_before"))
            assert "suggested repair of" in s.message
        else:
            assert s.value("repair") == ""
            assert float(s.value("error_after")) == pytest.approx(float(s.value("error_before")), rel=0.05)
    y1 = st["mpm_monitor: row y1"].value("repair")
    assert y1.startswith("u2: ") and "; u3: gain 3.5->" in y1 and "delay 4->7 s" in y1
    assert st["mpm_monitor: row y2"].value("repair").startswith("u1: time_constant 70->")


def test_a_row_status_names_what_the_repaired_models_detection_still_locates(repaired_core):
    """``located_after`` in a row's status: the inputs of the repair's ``located_after`` in that row, absent where
    there are none (the repaired model of case 3.2 leaves no row flagged)."""
    c, rep = repaired_core
    assert rep.repair["located_after"] == []
    assert all(s.value("located_after") is None for s in c.statuses(now=0.0))
    rep.repair["located_after"] = [{"output": "y2", "input": "u3", "p_value": 1e-4},
                                   {"output": "y2", "input": "u1", "p_value": 1e-3}]
    try:
        st = by_name(c.statuses(now=0.0))
    finally:
        rep.repair["located_after"] = []
    assert st["mpm_monitor: row y2"].value("located_after") == "u3,u1"
    assert st["mpm_monitor: row y1"].value("located_after") is None


def test_a_row_status_names_the_elements_the_repair_ran_again_with(repaired_core):
    """``second_round`` in a row's status: the inputs of the repair's ``second_round`` in that row, absent elsewhere."""
    c, rep = repaired_core
    assert "second_round" not in rep.repair
    assert all(s.value("second_round") is None for s in c.statuses(now=0.0))
    rep.repair["second_round"] = [{"output": "y1", "input": "u1", "p_value": 1e-4}]
    try:
        st = by_name(c.statuses(now=0.0))
    finally:
        del rep.repair["second_round"]
    assert st["mpm_monitor: row y1"].value("second_round") == "u1"
    assert st["mpm_monitor: row y2"].value("second_round") is None


def test_the_summary_counts_the_changes_and_gives_the_held_out_verdict(repaired_core):
    c, rep = repaired_core
    s = c.statuses(now=0.0)[-1]
    assert s.name == SUMMARY_NAME and s.level == WARN
    assert s.value("located_elements") == "y1:u2,y1:u3,y2:u1"  # contract values unchanged
    assert s.value("repair_changes") == "3" == str(sum(ch["applied"] for ch in rep.repair["changes"]))
    assert s.value("repair_validation") == "passed"
    detail = s.value("repair_validation_detail")
    assert detail.startswith("passed for y1 (") and "y2 (" in detail and "250 samples" in detail
    assert "suggested repair: 3 changes, held-out validation passed" in s.message


def _with_repair(rep, changes, **doc):
    """A copy of ``rep`` whose repair dict has these ``changes`` (and other keys replaced)."""
    import dataclasses

    new_doc = dict(rep.repair, changes=changes, **doc)
    return dataclasses.replace(rep, repair=new_doc)


def test_the_held_out_verdicts(repaired_core):
    from mpm_monitor.core.wording import repair_verdict

    _, rep = repaired_core
    changes = rep.repair["changes"]
    y2_rejected = [dict(ch, applied=False, after=ch["before"], kind="unknown", reason="rejected by held-out validation")
                   if ch["output"] == "y2" else ch for ch in changes]
    v = repair_verdict(_with_repair(rep, y2_rejected))
    assert v.verdict == "mixed" and v.changes == 2
    assert "passed for y1" in v.detail and "rejected for y2" in v.detail
    all_rejected = [dict(ch, applied=False, after=ch["before"], reason="rejected by held-out validation")
                    for ch in changes]
    v = repair_verdict(_with_repair(rep, all_rejected))
    assert v.verdict == "rejected" and v.changes == 0
    unknown = [dict(ch, applied=False, after=ch["before"], kind="unknown") for ch in changes]
    v = repair_verdict(_with_repair(rep, unknown))
    assert v.verdict == "not_run" and "nothing to re-estimate for y1, y2" in v.detail
    # A row that passed one step ahead while its held-out simulation error rose says both.
    hb = dict(rep.repair["holdout_error_before"])
    rose = _with_repair(rep, changes, holdout_error_after=dict(rep.repair["holdout_error_after"], y2=hb["y2"] * 1.01),
                        holdout_one_step_error_before={"y2": 0.0106}, holdout_one_step_error_after={"y2": 0.0101})
    v = repair_verdict(rose)
    assert v.verdict == "passed" and "; one step ahead 0.0106->0.0101)" in v.detail
    assert "one step ahead" not in repair_verdict(_with_repair(rep, changes)).detail
    v = repair_verdict(_with_repair(rep, changes, holdout_fraction=0.0))
    assert v.verdict == "not_validated" and v.changes == 3
    assert repair_verdict(_with_repair(rep, [])).verdict == "none"
    assert repair_verdict(fake_report({"y1": ["u2"]})).verdict == "off"  # no repair in the report


def test_without_the_repair_the_statuses_say_so_and_carry_no_repair_values():
    c = core()
    feed(c, 0, 20)
    c.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u2"]}), MODEL, None, c.take_job()))
    st = c.statuses(now=0.0)
    assert st[0].value("repair") is None and st[0].value("error_after") is None
    assert st[-1].value("repair_validation") == "off" and st[-1].value("repair_changes") == "0"
    assert "suggested repair" not in st[-1].message


# ------------------------------------------------------------------------ writing the repaired model
def test_write_repaired_model_writes_a_file_that_loads_as_the_repaired_model(repaired_core, tmp_path):
    from mpm_monitor.io.model_file import load_model

    c, rep = repaired_core
    path = tmp_path / "repaired.yaml"
    path.write_text("old contents\n")
    ok, msg = c.write_repaired_model(str(path))
    assert ok, msg
    assert str(path) in msg and "3 changes" in msg and "y1/u3: gain 3.5->" in msg
    assert load_model(path) == rep.repaired_model != MODEL
    assert sorted(p.name for p in tmp_path.iterdir()) == ["repaired.yaml"]  # no temporary file left


def test_write_repaired_model_refuses_the_monitored_file_under_another_name(repaired_core, tmp_path):
    c, _ = repaired_core
    protected = tmp_path / "controller.yaml"
    # the same file under another name: "..", a symbolic link to its directory, a hard link
    protected.write_text("controller model\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "linked").symlink_to(tmp_path)
    os.link(protected, tmp_path / "hard.yaml")
    for other in (tmp_path / "sub" / ".." / "controller.yaml", tmp_path / "linked" / "controller.yaml",
                  tmp_path / "hard.yaml"):
        ok, msg = c.write_repaired_model(str(other), protected=(str(protected),))
        assert not ok and "refusing to overwrite the monitored model file" in msg, other
        assert protected.read_text() == "controller model\n"
    # a file of its own beside it is written
    ok, msg = c.write_repaired_model(str(tmp_path / "linked" / "other.yaml"), protected=(str(protected),))
    assert ok, msg


def test_write_repaired_model_refuses_clearly_and_never_raises(repaired_core, tmp_path):
    c, rep = repaired_core
    fresh = core()
    ok, msg = fresh.write_repaired_model(str(tmp_path / "a.yaml"))
    assert not ok and msg.startswith("no analysis yet")
    ok, msg = c.write_repaired_model("")
    assert not ok and "repaired_model_file" in msg
    ok, msg = c.write_repaired_model(str(tmp_path / "missing_dir" / "a.yaml"))
    assert not ok and msg.startswith("cannot write") and "No such file or directory" in msg
    ok, msg = c.write_repaired_model(str(tmp_path))
    assert not ok and msg.startswith("cannot write")
    protected = tmp_path / "controller.yaml"
    ok, msg = c.write_repaired_model(str(protected), protected=(str(protected),))
    assert not ok and "refusing to overwrite the monitored model file" in msg and not protected.exists()
    # no change to write: the repair kept every element
    kept = [dict(ch, applied=False, after=ch["before"], reason="rejected by held-out validation")
            for ch in rep.repair["changes"]]
    import dataclasses
    c2 = core(window=WindowOptions(window_samples=50))
    feed(c2, 0, 20)
    c2.accept(run_analysis(lambda m, d, o: dataclasses.replace(_with_repair(rep, kept), repaired_model=MODEL),
                           MODEL, None, c2.take_job()))
    ok, msg = c2.write_repaired_model(str(tmp_path / "b.yaml"))
    assert not ok and msg.startswith("no change to write") and "rejected" in msg
    # the analysis ran without the repair
    c3 = core()
    feed(c3, 0, 20)
    c3.accept(run_analysis(lambda m, d, o: fake_report({"y1": ["u2"]}), MODEL, None, c3.take_job()))
    ok, msg = c3.write_repaired_model(str(tmp_path / "c.yaml"))
    assert not ok and "without the repair" in msg
    assert sorted(p.name for p in tmp_path.iterdir()) == []
