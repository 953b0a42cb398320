"""Robustness of the live monitor (issue 7, item 1): bad data in, clear diagnostics out, recovery.

Three levels, fastest first:

* the sample aligner (:class:`~mpm_monitor.monitor.window.SampleWindow`), fed stamps in integer
  nanoseconds: NaN/Inf, wrong lengths, stamps out of order, duplicated, far in the future or past,
  gaps, a publisher restart (stamps jump back or move to a new grid phase).  Invariant checked on
  every window handed to the analysis: equally spaced stamps on one grid, finite values, each
  sample's values those sent for that stamp (nothing interpolated, nothing mis-aligned);
* the monitor core (:class:`~mpm_monitor.monitor.monitor_core.MonitorCore`) with an injected wall clock:
  which status says what, STALE naming the silent topic, ERROR with the reason, recovery;
* the node (:class:`~mpm_monitor.nodes.monitor_node.MonitorNode`) in a private context, its
  subscription callbacks called directly with constructed ``JointState`` messages (wrong names,
  lengths, non-finite values), and a model file that does not load.
"""

import time

import numpy as np
import pytest

from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.statuses import ERROR, OK, STALE, SUMMARY_NAME, WARN, row_status_name
from mpm_monitor.monitor.window import SampleWindow, WindowOptions
from mpm_monitor.monitor.worker import AnalysisOutcome

NS = 1_000_000_000
OUT = ("y1", "y2")
INP = ("u1", "u2", "u3")


def values(k):
    """Distinct values per sample (r, u, y) so that any mis-alignment shows."""
    k = float(k)
    return np.array([k, -k]) + 0.1, np.array([k, 2 * k, 3 * k]) + 0.2, np.array([k, k * k]) + 0.3


def send(w, k, stamp=None, order=("setpoint", "input", "output"), vals=None):
    r, u, y = values(k) if vals is None else vals
    v = {"setpoint": r, "input": u, "output": y}
    st = k * NS if stamp is None else stamp
    return sum(w.add(ch, st, v[ch]) for ch in order)


def assert_window_consistent(w, value_of=values):
    """Equally spaced, on the grid, finite, and sample i holds exactly what was sent for its stamp."""
    d = w.data()
    if d.n_samples == 0:
        return d
    ts = w.sample_time
    np.testing.assert_allclose(np.diff(d.t), ts, rtol=0, atol=1e-9)
    for arr in (d.r, d.u, d.y):
        assert np.all(np.isfinite(arr))
    for i, t in enumerate(d.t):
        r, u, y = value_of(t / ts)
        np.testing.assert_array_equal(d.r[i], r)
        np.testing.assert_array_equal(d.u[i], u)
        np.testing.assert_array_equal(d.y[i], y)
    return d


def kinds(w):
    return [p.kind for p in w.take_problems()]


# ------------------------------------------------------------------------------ the sample aligner

def test_publisher_restart_with_stamps_jumping_back_restarts_the_window():
    """A simulation restarted from t = 0 while the monitor runs: reported once as a restart, and
    the new stream fills a fresh window from its first sample (none of it is lost)."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    for k in range(100, 130):
        send(w, k)
    kinds(w)
    for k in range(0, 40):
        send(w, k)
    problems = w.take_problems()
    restarts = [p for p in problems if p.kind == "restart"]
    assert len(restarts) == 1
    assert "t = 130 s was expected" in restarts[0].message and "restart" in restarts[0].message
    d = assert_window_consistent(w)
    np.testing.assert_array_equal(d.t, np.arange(0, 40.0))   # the whole new stream, nothing of the old
    h = w.health()
    assert h.restarts == 1 and h.completed == 30 + 40
    # good data keep coming: the window slides on normally
    for k in range(40, 100):
        assert send(w, k) == 1
    assert w.take_problems() == [] and w.n_window == 50


def test_publisher_restart_with_held_setpoints_restarts_the_window():
    """hold_setpoint mode (setpoints only on change): the setpoints sent before the jump back are
    not used for the new stream."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50, hold_setpoint=True))
    r_old, r_new = np.array([5.0, 5.0]), np.array([-1.0, -1.0])
    w.add("setpoint", 100 * NS, r_old)
    for k in range(100, 130):
        send(w, k, order=("input", "output"))
    w.add("setpoint", 0, r_new)
    for k in range(0, 40):
        send(w, k, order=("input", "output"))
    assert [p.kind for p in w.take_problems()].count("restart") == 1
    d = w.data()
    np.testing.assert_array_equal(d.t, np.arange(0, 40.0))
    assert np.all(d.r == r_new)


def test_publisher_restart_on_a_new_grid_phase_restarts_the_window():
    """A wall-clock publisher restarted half a sample later: its stamps are all off the old grid."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    for k in range(30):
        send(w, k)
    for k in range(30, 60):
        send(w, k, stamp=k * NS + NS // 2)
    problems = w.take_problems()
    assert [p.kind for p in problems].count("restart") == 1
    assert any(p.kind == "off_grid" for p in problems)          # reported (ERROR) before the restart
    d = assert_window_consistent(w, value_of=lambda kk: values(kk - 0.5))
    np.testing.assert_array_equal(d.t, np.arange(30, 60) + 0.5)


def test_one_stamp_far_in_the_future_costs_nothing_and_is_reported_once():
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    for k in range(30):
        send(w, k)
    w.add("output", 10**9 * NS, values(0)[2])     # a corrupted stamp, 30 years ahead
    w.add("input", -(10**9) * NS, values(0)[1])   # and one as far in the past (late)
    for k in range(30, 60):
        assert send(w, k) == 1
    ks = kinds(w)
    assert ks.count("out_of_order") == 2 and ks.count("late") == 1 and "restart" not in ks
    assert_window_consistent(w)
    assert w.n_window == 50 and w.health().missing_samples == 0


def test_a_whole_sample_far_in_the_future_waits_and_the_stream_goes_on():
    """All three topics glitch to one stamp 11 days ahead, then the stream goes on.  A sample is given
    up once more than reorder_samples later samples are complete (counted, not their distance), so the
    stray one waits as pending: no gap of a million samples, no restart, the window keeps every good
    sample.  (Before, the window followed it, counted 999,970 samples missing and restarted twice.)"""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    for k in range(30):
        send(w, k)
    send(w, 10**6)
    for k in range(30, 80):
        send(w, k)
    ks = kinds(w)
    assert "gap" not in ks and "restart" not in ks
    assert w.health().missing_samples == 0
    d = assert_window_consistent(w)
    assert d.t[-1] == 79.0 and d.n_samples == 50


def test_a_clock_that_jumps_ahead_for_good_is_a_gap_and_a_restart():
    """The control: when the stream goes on from the far stamp (a clock that really jumped), the samples
    before it are given up once more than reorder_samples later samples are complete, and the window
    restarts after the long gap."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    for k in range(30):
        send(w, k)
    for k in range(10**6, 10**6 + 40):
        send(w, k)
    ks = kinds(w)
    assert "gap" in ks
    d = assert_window_consistent(w)
    assert d.t[-1] == 10**6 + 39 and d.t[0] >= 10**6


def test_an_unset_stamp_among_wall_clock_stamps_is_refused():
    """A vector stamped 0 (header.stamp never filled in) in a wall-clock stream is a bad message, not a
    time: no restart, no gap of 1.7e9 s."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50))
    base = 1_700_000_000
    for k in range(base, base + 20):
        send(w, k)
    for _ in range(15):
        send(w, 0)
    for k in range(base + 20, base + 40):
        send(w, k)
    problems = w.take_problems()
    assert any(p.kind == "bad_value" and "header.stamp unset" in p.message for p in problems)
    assert not any(p.kind in ("restart", "gap") for p in problems)
    d = assert_window_consistent(w)
    assert d.n_samples == 40 and d.t[-1] == base + 39


@pytest.mark.parametrize("bad", [np.array([np.nan, 1.0]), np.array([1.0, np.inf]), np.array([-np.inf, 0.0]),
                                 np.array([1.0]), np.array([1.0, 2.0, 3.0]), np.zeros(0)])
def test_bad_values_are_excluded_and_the_sample_becomes_a_gap(bad):
    """A NaN/Inf or wrong-length output at sample 10 is refused (ERROR kind); sample 10 is then a
    gap and the window restarts after it (never bridged by interpolation)."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=100, reorder_samples=3, max_gap=0))
    for k in range(10):
        send(w, k)
    r, u, _ = values(10)
    w.add("setpoint", 10 * NS, r)
    w.add("input", 10 * NS, u)
    w.add("output", 10 * NS, bad)
    for k in range(11, 30):
        send(w, k)
    problems = w.take_problems()
    assert problems[0].kind == "bad_value" and problems[0].is_error and "t = 10 s" in problems[0].message
    assert [p.kind for p in problems[1:]] == ["gap"] and "no output" in problems[1].message
    d = assert_window_consistent(w)
    np.testing.assert_array_equal(d.t, np.arange(11, 30.0))   # only after the gap
    assert w.health().bad_value == 1 and w.health().missing_samples == 1


def test_a_gap_is_never_bridged():
    """Samples 20..24 never arrive: the window holds only samples after the gap."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=100, reorder_samples=2, max_gap=0))
    for k in list(range(20)) + list(range(25, 40)):
        send(w, k)
    problems = w.take_problems()
    assert [p.kind for p in problems] == ["gap"] and "5 sample(s) missing from t = 20 s" in problems[0].message
    d = assert_window_consistent(w)
    np.testing.assert_array_equal(d.t, np.arange(25, 40.0))


def test_out_of_order_within_the_reorder_limit_loses_nothing():
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=100, reorder_samples=5))
    order = [0, 1, 3, 2, 4, 8, 5, 7, 6, 9, 10]
    for k in order:
        send(w, k, order=("output", "setpoint", "input") if k % 2 else ("input", "output", "setpoint"))
    d = assert_window_consistent(w)
    np.testing.assert_array_equal(d.t, np.arange(11.0))
    assert set(kinds(w)) == {"out_of_order"}


def test_duplicates_keep_the_first_and_conflicts_are_errors():
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=100))
    for k in range(10):
        send(w, k)
        send(w, k, order=("output",))                                # same values again
    r, u, y = values(10)
    send(w, 10, vals=(r, u, y + 1.0), order=("output",))
    send(w, 10, order=("setpoint", "input", "output"))             # a second, different output
    problems = w.take_problems()
    assert sum(p.kind == "duplicate" for p in problems) == 10
    conflicts = [p for p in problems if p.kind == "conflict"]
    assert len(conflicts) == 1 and conflicts[0].is_error
    # the first output (y + 1) was kept: it is what the sample holds
    np.testing.assert_array_equal(w.data().y[-1], y + 1.0)


def test_stamps_far_in_the_past_at_start_work():
    """Negative and tiny stamps (a clock starting at 0 or before the epoch) are just stamps."""
    w = SampleWindow(OUT, INP, 0.001, WindowOptions(window_samples=100))
    for k in range(-50, 50):
        r, u, y = values(k)
        st = k * 1_000_000
        w.add("setpoint", st, r), w.add("input", st, u), w.add("output", st, y)
    d = w.data()
    assert d.n_samples == 100 and d.t[0] == pytest.approx(-0.05) and w.take_problems() == []


# ------------------------------------------------------------------------------------- the core

class FakeReport:
    """The parts of an AnalysisReport the statuses read."""

    def __init__(self, outputs, flags=()):
        class Row:
            def __init__(self, o, m):
                self.output, self.rsi, self.mismatch, self.p_value = o, 2.0 if m else 1.0, m, 1e-9 if m else 0.5

        self.rows = [Row(o, o in flags) for o in outputs]
        self.elements, self.warnings, self.overall_rsi = [], [], 1.0


def make_core(**kw):
    from mpm_monitor.core.model import PlantModel

    model = PlantModel(sample_time=1.0, inputs=INP, outputs=OUT, gain=np.ones((2, 3)),
                       time_constant=np.ones((2, 3)), delay=np.zeros((2, 3)))
    # max_gap 0: every gap restarts the window (a gap up to max_gap keeps it since the interface "Gaps")
    win = WindowOptions(window_samples=kw.pop("window_samples", 50), reorder_samples=kw.pop("reorder_samples", 3),
                        max_gap=kw.pop("max_gap", 0))
    opts = dict(analysis_period=10, min_samples=20, stale_timeout=2.0)
    opts.update(kw)
    return MonitorCore(model, MonitorOptions(window=win, **opts))


def core_send(c, k, now, stamp=None, vals=None, order=("setpoint", "input", "output")):
    r, u, y = values(k) if vals is None else vals
    v = {"setpoint": r, "input": u, "output": y}
    return sum(c.add(ch, k * NS if stamp is None else stamp, v[ch], now) for ch in order)


def analyse_if_due(c, flags=()):
    """Run a fake analysis when one is due; check the job's window; return the job or None."""
    if not c.analysis_due():
        return None
    job = c.take_job()
    d = job.data
    np.testing.assert_allclose(np.diff(d.t), 1.0, atol=1e-9)
    for i, t in enumerate(d.t):
        np.testing.assert_array_equal(d.y[i], values(t)[2])
    c.accept(AnalysisOutcome(job, report=FakeReport(OUT, flags)))
    return job


def by_name(statuses):
    return {s.name: s for s in statuses}


def test_a_silent_topic_turns_every_status_stale_naming_it_then_recovers():
    c = make_core()
    now = 0.0
    for k in range(30):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c)
    assert all(s.level == OK for s in c.statuses(now))
    # the input topic stops; setpoint and output go on
    for k in range(30, 60):
        now += 0.1
        core_send(c, k, now, order=("setpoint", "output"))
    st = by_name(c.statuses(now))
    assert all(s.level == STALE for s in st.values())
    msg = st[SUMMARY_NAME].message
    assert "no complete sample for" in msg and "input 3.0 s ago" in msg and "output 0.0 s ago" in msg
    # the input comes back: statuses fresh again, the missing samples reported as a gap, the new
    # window holds only samples after it
    for k in range(60, 100):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c)
    st = by_name(c.statuses(now))
    assert all(s.level == OK for s in st.values())
    values_ = dict(st[SUMMARY_NAME].values)
    assert int(values_["missing_samples"]) >= 30 and int(values_["gaps"]) >= 1
    assert c.latest_outcome.job.first_stamp >= 60.0


def test_bad_data_give_error_with_the_reason_and_clear_after_a_clean_period():
    c = make_core()
    now = 0.0
    for k in range(25):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c)
    c.add("output", 25 * NS, np.array([np.nan, 1.0]), now)
    c.bad_message("input", "input: channel names do not match the model: missing 'u3'", now)
    st = by_name(c.statuses(now))
    assert st[SUMMARY_NAME].level == ERROR
    assert "bad input data" in st[SUMMARY_NAME].message and "missing 'u3'" in st[SUMMARY_NAME].message
    for k in range(26, 60):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c)
    st = by_name(c.statuses(now))
    assert st[SUMMARY_NAME].level == OK, st[SUMMARY_NAME].message
    assert dict(st[SUMMARY_NAME].values)["bad_messages"] == "2"


def test_a_restart_is_reported_and_the_next_analysis_sees_only_the_new_stream():
    c = make_core()
    now = 0.0
    for k in range(100, 140):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c, flags=("y1",))
    assert by_name(c.statuses(now))[row_status_name("y1")].level == WARN
    jobs = []
    for k in range(0, 40):
        now += 0.1
        core_send(c, k, now)
        job = analyse_if_due(c)
        if job is not None:
            jobs.append(job)
    assert jobs and all(j.first_stamp < 100 for j in jobs)   # never mixes the two streams
    st = by_name(c.statuses(now))
    v = dict(st[SUMMARY_NAME].values)
    assert v["restarts"] == "1" and "stream restarted" in v["last_data_problem"]
    assert st[row_status_name("y1")].level == OK                # the new stream's result


def test_an_analysis_that_raises_is_error_with_the_reason_and_the_core_goes_on():
    from mpm_monitor.monitor.worker import run_analysis

    c = make_core()
    now = 0.0

    def broken(model, data, options):
        raise np.linalg.LinAlgError("SVD did not converge")

    for k in range(25):
        now += 0.1
        core_send(c, k, now)
    job = c.take_job()
    c.accept(run_analysis(broken, c.model, None, job))
    st = by_name(c.statuses(now))
    assert st[SUMMARY_NAME].level == ERROR
    assert "analysis failed: LinAlgError: SVD did not converge" in st[SUMMARY_NAME].message
    for k in range(25, 45):
        now += 0.1
        core_send(c, k, now)
        analyse_if_due(c)
    assert all(s.level == OK for s in c.statuses(now))


def test_a_sentinel_value_like_1e308_is_error_not_a_silent_all_clear():
    """Finite but absurd values (a sensor's 'bad value' sentinel) pass the aligner; the analysis
    refuses them with the channel and time instead of returning a meaningless no-mismatch."""
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.monitor.worker import run_analysis

    c = make_core(window_samples=300, min_samples=200, analysis_period=100)
    rng = np.random.default_rng(0)
    for k in range(200):
        r, u, y = rng.normal(size=2), rng.normal(size=3), rng.normal(size=2)
        if k == 150:
            y[1] = 1e308
        for ch, v in (("setpoint", r), ("input", u), ("output", y)):
            c.add(ch, k * NS, v, 0.0)
    outcome = run_analysis(analyze, c.model, AnalysisOptions(repair=False), c.take_job())
    c.accept(outcome)
    summary = by_name(c.statuses(0.0))[SUMMARY_NAME]
    assert summary.level == ERROR
    assert "output 'y2' at t = 150 s is 1e+308" in summary.message and "too large" in summary.message


# ------------------------------------------------------------------------------------- the node

rclpy = pytest.importorskip("rclpy")


def _joint_state(names, position, stamp_ns=0):
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import JointState

    msg = JointState(name=list(names), position=[float(v) for v in position])
    msg.header.stamp = Time(sec=stamp_ns // NS, nanosec=stamp_ns % NS)
    return msg


def _fake_analyze(model, data, options):
    return FakeReport(model.outputs)


@pytest.fixture
def ros_context():
    from mpm_monitor.apps.demo import private_context

    ctx = private_context()
    yield ctx
    ctx.try_shutdown()


def _monitor_node(ctx, model_file, **params):
    from mpm_monitor.apps.demo import _overrides
    from mpm_monitor.nodes.monitor_node import MonitorNode

    p = {"model_file": str(model_file), "diagnostics_topic": "diagnostics", "window_samples": 50,
         "min_samples": 20, "analysis_period": 10, "analysis_thread": False, "republish_period": 0.05}
    p.update(params)
    return MonitorNode(context=ctx, namespace="/robust", parameter_overrides=_overrides(p), analyze=_fake_analyze)


@pytest.fixture
def model_file(tmp_path):
    from mpm_monitor.core.model import PlantModel
    from mpm_monitor.io.model_file import save_model

    path = tmp_path / "model.yaml"
    save_model(PlantModel(sample_time=1.0, inputs=INP, outputs=OUT, gain=np.ones((2, 3)),
                          time_constant=np.ones((2, 3)), delay=np.zeros((2, 3))), path)
    return path


def node_send(node, k, stamp=None, names=None):
    r, u, y = values(k)
    st = k * NS if stamp is None else stamp
    node._on_vector("setpoint", _joint_state(OUT, r, st))
    node._on_vector("input", _joint_state(names or INP, u, st))
    node._on_vector("output", _joint_state(OUT, y, st))


def test_node_refuses_malformed_messages_with_the_reason_and_recovers(ros_context, model_file):
    """Wrong names, wrong lengths, NaN, repeated names, empty messages: each is refused with a
    one-line reason in the summary (ERROR); the sample they belonged to is a gap; the node keeps
    running and goes back to OK on good data."""
    node = _monitor_node(ros_context, model_file, max_gap=0)     # every gap restarts the window
    try:
        for k in range(25):
            node_send(node, k)
        node._on_results()
        assert all(s.level == OK for s in node.current_statuses())
        cases = [
            ("input", _joint_state(("u1", "u2", "flow"), [1, 2, 3], 25 * NS), "missing 'u3'; unexpected 'flow'"),
            ("input", _joint_state(INP, [1, 2], 26 * NS), "2 position value(s) for 3 name(s)"),
            ("output", _joint_state(OUT, [np.nan, 1], 27 * NS), "non-finite value(s) y1=nan"),
            ("output", _joint_state(OUT, [np.inf, 1], 28 * NS), "non-finite value(s) y1=inf"),
            ("output", _joint_state(("y1", "y1"), [1, 1], 29 * NS), "'y1' repeat"),
            ("setpoint", _joint_state((), (), 30 * NS), "missing 'y1', 'y2'"),
        ]
        for k, (channel, msg, reason) in zip(range(25, 31), cases):
            r, u, y = values(k)
            good = {"setpoint": _joint_state(OUT, r, k * NS), "input": _joint_state(INP, u, k * NS),
                    "output": _joint_state(OUT, y, k * NS)}
            good[channel] = msg
            for ch in ("setpoint", "input", "output"):
                node._on_vector(ch, good[ch])
            summary = by_name(node.current_statuses())[SUMMARY_NAME]
            assert summary.level == ERROR and reason in summary.message, summary.message
            assert len(summary.message.splitlines()) == 1
        for k in range(31, 80):
            node_send(node, k)
            node._on_results()
        st = by_name(node.current_statuses())
        assert all(s.level == OK for s in st.values()), st[SUMMARY_NAME].message
        v = dict(st[SUMMARY_NAME].values)
        assert v["bad_messages"] == "6" and int(v["missing_samples"]) == 6
        d = node.core.window.data()
        assert d.t[0] >= 31 and np.all(np.diff(d.t) == 1.0)   # nothing from before the bad samples
    finally:
        node.close()
        node.destroy_node()


def test_a_stale_topic_with_a_publisher_of_another_type_names_it(ros_context, model_file):
    """A publisher of Float64MultiArray on the output topic: DDS never connects it to the monitor's JointState
    subscription, and the statuses only said "output never".  Once STALE they now name the topic and the type
    found there (the graph's answer is faked here: one process cannot hold a topic of two types)."""
    import types

    node = _monitor_node(ros_context, model_file, stale_timeout=0.5)
    graph = {"/robust/output": ["std_msgs/msg/Float64MultiArray", "sensor_msgs/msg/JointState"]}
    node.get_publishers_info_by_topic = lambda topic: [types.SimpleNamespace(topic_type=t)
                                                       for t in graph.get(topic, [])]
    try:
        hint = "topic /robust/output has a publisher of type std_msgs/msg/Float64MultiArray (expected " \
               "sensor_msgs/msg/JointState)"
        fresh = node.current_statuses(time.monotonic())
        assert not any(s.level == STALE or hint in s.message for s in fresh)
        st = node.current_statuses(time.monotonic() + 60.0)
        assert all(s.level == STALE and s.message.endswith(hint) for s in st), st[-1].message
        assert len(st[-1].message.splitlines()) == 1
        graph.clear()
        assert not any(hint in s.message for s in node.current_statuses(time.monotonic() + 60.0))
    finally:
        node.close()
        node.destroy_node()


def test_model_file_that_fails_to_load_is_error_with_the_reason_then_loads_when_fixed(ros_context, model_file,
                                                                                         tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node

    from mpm_monitor.monitor.statuses import SUMMARY_NAME as SUMMARY
    from mpm_monitor.nodes.ros_io import diagnostics_qos, make_executor, spin_until

    bad = tmp_path / "edited.yaml"
    good_text = model_file.read_text()
    bad.write_text(good_text.replace("time_constant: [[1", "time_constant: [[-1"), encoding="utf-8")
    node = _monitor_node(ros_context, bad)
    listener = Node("listener", context=ros_context, namespace="/robust")
    seen = []
    listener.create_subscription(DiagnosticArray, "diagnostics", seen.append, diagnostics_qos())
    ex = make_executor(ros_context, "single")
    ex.add_node(node)
    ex.add_node(listener)
    try:
        assert node.core is None
        # published on /diagnostics: one summary, ERROR, naming the file and the key
        assert spin_until(ex, lambda: len(seen) >= 1, 10.0)
        (status,) = seen[-1].status
        assert status.name == SUMMARY and status.level == bytes([ERROR])
        assert "model not loaded" in status.message and "edited.yaml" in status.message
        assert "key 'time_constant'" in status.message
        node._on_vector  # noqa: B018 - exists, but no subscription is made without a model
        assert node.request_analysis() is False
        # the file is fixed: the next retry loads it and monitoring starts
        bad.write_text(good_text, encoding="utf-8")
        assert spin_until(ex, lambda: node.core is not None, 10.0)
        assert node.model_error is None and len(node._subs) == 3
        for k in range(25):
            node_send(node, k)
        node._on_results()
        assert all(s.level == OK for s in node.current_statuses())
    finally:
        node.close()
        for nd in (node, listener):
            ex.remove_node(nd)
            nd.destroy_node()
        ex.shutdown()


def test_a_missing_model_file_is_error_not_a_crash(ros_context, tmp_path):
    node = _monitor_node(ros_context, tmp_path / "nowhere.yaml")
    try:
        (status,) = node.current_statuses()
        assert status.level == ERROR and "cannot read model file" in status.message
        node._retry_model()  # still missing: still ERROR, no exception
        assert node.core is None
    finally:
        node.close()
        node.destroy_node()


def test_no_sample_dropped_at_a_modest_rate_while_the_real_analysis_runs():
    """3x3 at 200 Hz from a plain publisher, the real analysis in the monitor's child process every
    100 samples: every sample sent is aligned into the window (the figures for 20x20 at 10 Hz and
    3x3 at 1 kHz come from ``python -m bench.monitor_load``, not from a unit test)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.monitor_load import run_load

    res = run_load(3, 200.0, samples=500, window_samples=300, min_samples=200, analysis_period=100)
    assert res.dropped == 0 and res.missing == 0 and res.gaps == 0 and res.late == 0
    assert res.completed == res.sent == 500
    assert res.analyses >= 2 and res.analysis_in == "process"


def _analysis_in_child(model, data, options):
    """Stands in for analyze() in the child process: dies on request, else says where it ran."""
    import os

    if options == "die":
        os._exit(7)
    return os.getpid()


def _sleep_in_child(model, data, options):
    import time

    time.sleep(options)
    return options


def test_closing_the_analysis_process_leaves_no_pool_thread_behind():
    """close() shut the pool down without waiting: its manager thread went on closing its wake-up pipe while the
    interpreter's exit wrote to it, and about one stop of the monitor in five printed "Exception ignored ...
    OSError: [Errno 9] Bad file descriptor".  close() now returns once that thread has finished, idle or with
    an analysis running (which is abandoned)."""
    import threading

    from concurrent.futures.process import _ExecutorManagerThread

    from mpm_monitor.monitor.worker import ProcessAnalyzer

    def managers():
        return [t for t in threading.enumerate() if isinstance(t, _ExecutorManagerThread) and t.is_alive()]

    before = managers()
    pa = ProcessAnalyzer(_sleep_in_child)
    assert pa(None, None, 0.0) == 0.0
    pa.close()
    assert managers() == before
    pa = ProcessAnalyzer(_sleep_in_child)
    assert pa(None, None, 0.0) == 0.0
    errors = []

    def long_call():
        try:
            pa(None, None, 600.0)
        except RuntimeError as exc:
            errors.append(str(exc))
    caller = threading.Thread(target=long_call)
    caller.start()
    time.sleep(0.5)
    pa.close()                                  # returns without waiting the 600 s
    caller.join(30)
    assert not caller.is_alive() and managers() == before
    assert errors and "analysis process died" in errors[0]


def test_the_analysis_process_dying_is_an_error_and_the_next_analysis_gets_a_new_one():
    import os

    from mpm_monitor.monitor.worker import ProcessAnalyzer

    pa = ProcessAnalyzer(_analysis_in_child)
    try:
        pid = pa(None, None, "ok")
        assert pid != os.getpid()
        with pytest.raises(RuntimeError, match="analysis process died"):
            pa(None, None, "die")
        pid2 = pa(None, None, "ok")
        assert pid2 not in (pid, os.getpid())
    finally:
        pa.close()


def _niceness_in_child(model, data, options):
    """Stands in for analyze() in the child process: its pid and niceness."""
    import os

    return os.getpid(), os.getpriority(os.PRIO_PROCESS, 0)


@pytest.mark.parametrize("niceness", [0, 7, 19])
def test_the_analysis_process_runs_at_the_niceness_asked_for(niceness):
    """The analysis process's niceness is the monitor's plus ``niceness`` (at most 19), so that where the cores
    are busy the monitor's callbacks are served before the analysis."""
    import os

    from mpm_monitor.monitor.worker import ProcessAnalyzer

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    pa = ProcessAnalyzer(_niceness_in_child, niceness=niceness)
    try:
        pid, nice = pa(None, None, None)
    finally:
        pa.close()
    assert pid != os.getpid() and os.getpriority(os.PRIO_PROCESS, 0) == mine      # the monitor's own is unchanged
    assert nice == min(mine + niceness, 19)
