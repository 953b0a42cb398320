"""MonitorCore and AnalysisWorker: schedule, statuses (names, values, levels), STALE, ERROR, threading.

The analysis is a fake injected here (plain objects with the AnalysisReport fields the monitor
reads), so these tests check the plumbing only; the real analysis is exercised through the nodes in
test_nodes_inprocess.py.
"""

import subprocess
import sys
import threading
import types

import numpy as np
import pytest

from mpm_monitor.cases import paper_case
from mpm_monitor.errors import ConfigurationError
from mpm_monitor.monitor_core import (ERROR, OK, STALE, SUMMARY_NAME, WARN, AnalysisWorker, MonitorCore,
                                      MonitorOptions, run_analysis)
from mpm_monitor.window import WindowOptions

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
    np.testing.assert_array_equal(c.rsi_vector(), [1.5, 1.2, 1.0])


def test_no_mismatch_is_ok_everywhere():
    c = core()
    feed(c, 0, 20)
    c.accept(run_analysis(lambda m, d, o: fake_report(), MODEL, None, c.take_job()))
    assert all(s.level == OK for s in c.statuses(now=0.0))


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


def test_worker_runs_jobs_in_a_thread_and_replaces_a_waiting_job():
    c = core()
    release = threading.Event()
    started = threading.Event()
    seen = []

    def slow(model, data, options):
        started.set()
        release.wait(5.0)
        seen.append(data.n_samples)
        return fake_report()

    worker = AnalysisWorker(lambda job: run_analysis(slow, MODEL, None, job))
    try:
        feed(c, 0, 20)
        worker.submit(c.take_job())      # runs
        assert started.wait(5.0)
        feed(c, 20, 30)
        worker.submit(c.take_job())      # waits
        feed(c, 30, 40)
        worker.submit(c.take_job())      # replaces the waiting one
        assert worker.replaced == 1 and not worker.idle
        release.set()
        for _ in range(500):
            if worker.idle and len(seen) == 2:
                break
            threading.Event().wait(0.01)
        outcomes = worker.take_outcomes()
        assert [o.job.data.n_samples for o in outcomes] == [20, 40] == seen
    finally:
        release.set()
        worker.close()


def test_options_are_checked():
    with pytest.raises(ConfigurationError, match="min_samples"):
        MonitorOptions(window=WindowOptions(window_samples=100), min_samples=200)
    with pytest.raises(ConfigurationError, match="analysis_period"):
        MonitorOptions(analysis_period=0)
    with pytest.raises(ConfigurationError, match="stale_timeout"):
        MonitorOptions(stale_timeout=0.0)


def test_the_core_imports_without_rclpy():
    code = ("import sys; sys.modules['rclpy'] = None\n"
            "import mpm_monitor.monitor_core, mpm_monitor.window, mpm_monitor.ros_io\n"
            "assert 'rclpy' not in [m for m in sys.modules if sys.modules[m] is not None]\n")
    subprocess.run([sys.executable, "-c", code], check=True)
