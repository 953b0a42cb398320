"""Candidate channels in the live monitor: CandidateWindow, MonitorCore with candidates, statuses, repaired model."""

import numpy as np
import pytest
from ros_domains import close_nodes

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.model_file import load_model
from mpm_monitor.monitor.candidate_window import CandidateWindow
from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.statuses import OK, SUMMARY_NAME, WARN
from mpm_monitor.monitor.window import WindowOptions
from mpm_monitor.monitor.worker import run_analysis
from mpm_monitor.sim.undeclared import EFFECT_CHANNEL, LOOP_CHANNEL, RANDOM_WALK_CHANNEL, undeclared_effect_run

NS = 1_000_000_000
SAMPLES = 2500


def test_candidate_vectors_of_very_many_channels_are_refused_in_a_short_line():
    """A vector naming 200,000 channels was kept whole (and its refusal for a repeated name printed every name):
    the window holds at most MAX_CANDIDATE_CHANNELS channels, and a message names five of them."""
    from mpm_monitor.monitor.candidate_window import MAX_CANDIDATE_CHANNELS

    w = CandidateWindow(sample_time=1.0, capacity=100)
    many = tuple(f"tag{k}" for k in range(200_000))
    why = w.add(0, many, np.zeros(len(many)))
    assert why.startswith("candidate: 200000 channel(s) at t = 0 s ('tag0', 'tag1', 'tag2', 'tag3', 'tag4' and "
                          "199995 more) would make 200000 candidate channels in the window: expected at most")
    assert w.names == () and len(why) < 300
    assert len(w.add(0, many + ("tag0",), np.zeros(len(many) + 1))) < 300
    first = tuple(f"a{k}" for k in range(MAX_CANDIDATE_CHANNELS))
    assert w.add(0, first, np.zeros(len(first))) is None
    assert w.add(1, first, np.ones(len(first))) is None              # the same channels again: kept
    assert w.add(2, ("b",), [1.0]).endswith(f"would make {MAX_CANDIDATE_CHANNELS + 1} candidate channels in the "
                                            f"window: expected at most {MAX_CANDIDATE_CHANNELS}")


def test_candidate_window_puts_the_vectors_on_the_samples():
    from mpm_monitor.core.logged_data import LoggedData

    w = CandidateWindow(sample_time=0.5, capacity=100)
    for k in range(10):
        jitter = 30_000_000 if k % 2 else -20_000_000          # within a quarter of the sample time
        names = ("a", "b") if k != 4 else ("a",)
        assert w.add(k * NS // 2 + jitter, names, np.arange(len(names)) + k) is None
    assert w.add(0, ("a", "b"), [1.0]).startswith("candidate: 1 value(s) for 2 name(s)")
    assert w.add(0, ("a", "a"), [1.0, 2.0]).startswith("candidate: empty or repeated channel names")
    clash = CandidateWindow(sample_time=0.5, capacity=10, reserved=("u", "y"))
    assert clash.add(0, ("u", "temp"), [1.0, 2.0]) == "candidate: 'u' at t = 0 s is a channel of the model, not a candidate"
    assert clash.names == ()
    t = np.arange(10) * 0.5
    data = LoggedData(t=t, r=np.zeros((10, 1)), u=np.zeros((10, 1)), y=np.zeros((10, 1)), inputs=("u",),
                      outputs=("y",), sample_time=0.5)
    out = w.attach(data)
    np.testing.assert_array_equal(out.extra["a"], np.arange(10.0))
    assert out.unusable == {"b": "partly missing: no finite value at 1 of the window's 10 samples"}
    assert w.names == ("a", "b")


def test_the_newest_samples_wait_for_their_candidate_vectors():
    """A candidate vector stamped like a sample that came after the sample's output vector made the channel
    "partly missing" at every analysis: the samples after the newest vector, up to late_samples of them, are
    left out of the analysis instead; more of them (a publisher that stopped) leave the channel missing there."""
    from mpm_monitor.core.logged_data import LoggedData

    t = np.arange(30, dtype=float)
    data = LoggedData(t=t, r=np.zeros((30, 1)), u=np.zeros((30, 1)), y=t[:, None].copy(), inputs=("u",),
                      outputs=("y",), sample_time=1.0)
    for late, kept in ((1, 29), (3, 27), (10, 20), (11, 30)):
        w = CandidateWindow(sample_time=1.0, capacity=100, late_samples=10)
        for k in range(30 - late):
            w.add(k * NS, ("c",), [2.0 * k])
        out = w.attach(data)
        assert out.n_samples == kept, late
        np.testing.assert_array_equal(out.y[:, 0], t[:kept])
        if kept < 30:
            assert out.unusable == {} and np.array_equal(out.extra["c"], 2.0 * t[:kept])
        else:
            assert out.unusable == {"c": "partly missing: no finite value at 11 of the window's 30 samples"}
    w = CandidateWindow(sample_time=1.0, capacity=100)               # late_samples 0: nothing waited for
    for k in range(29):
        w.add(k * NS, ("c",), [1.0])
    assert w.attach(data).unusable == {"c": "partly missing: no finite value at 1 of the window's 30 samples"}


def test_the_monitor_tests_a_candidate_published_after_its_sample():
    """The helper's case: each sample's candidate vector published right after its output vector.  The job
    taken when the last output completes the window used to find the channel missing at that sample."""
    run = undeclared_effect_run(600, seed=3)
    c = MonitorCore(run.model, MonitorOptions(window=WindowOptions(window_samples=500), min_samples=500,
                                              analysis_period=100, hardware_id="test", candidates=True))
    d, jobs = run.data, []
    for k in range(600):
        c.add("setpoint", k * NS, d.r[k], 0.0)
        c.add("input", k * NS, d.u[k], 0.0)
        c.add("output", k * NS, d.y[k], 0.0)
        if c.analysis_due():
            jobs.append(c.take_job())
        c.add_candidates(k * NS, (EFFECT_CHANNEL,), [d.extra[EFFECT_CHANNEL][k]], 0.0)
    assert len(jobs) == 2
    for job in jobs:
        assert job.data.unusable == {} and set(job.data.extra) == {EFFECT_CHANNEL}
        assert job.data.n_samples == 499 and job.last_stamp == job.data.t[-1]
        k0 = int(job.data.t[0])
        np.testing.assert_array_equal(job.data.extra[EFFECT_CHANNEL], d.extra[EFFECT_CHANNEL][k0:k0 + 499])


def test_the_candidate_channels_are_those_of_the_vectors_kept():
    """A channel leaves with its last vector: 20,000 distinct names over time keep the list bounded,
    and a channel no longer published stops being reported once its vectors are gone."""
    from mpm_monitor.core.logged_data import LoggedData

    w = CandidateWindow(sample_time=1.0, capacity=5)
    for k in range(20_000):
        assert w.add(k * NS, ("steady", f"name{k}"), [1.0, 2.0]) is None
    assert w.names == ("steady",) + tuple(f"name{k}" for k in range(19_995, 20_000))
    assert len(w._vectors) == 5
    t = np.arange(19_995, 20_000, dtype=float)
    data = LoggedData(t=t, r=np.zeros((5, 1)), u=np.zeros((5, 1)), y=np.zeros((5, 1)), inputs=("u",),
                      outputs=("y",), sample_time=1.0)
    out = w.attach(data)
    assert set(out.extra) == {"steady"} and set(out.unusable) == {f"name{k}" for k in range(19_995, 20_000)}
    for k in range(20_000, 20_005):
        w.add(k * NS, ("steady",), [1.0])
    assert w.names == ("steady",)


@pytest.fixture(scope="module")
def live():
    """A MonitorCore with candidates after one analysis of the undeclared-effect loop."""
    run = undeclared_effect_run(SAMPLES, seed=3)
    c = MonitorCore(run.model, MonitorOptions(window=WindowOptions(window_samples=SAMPLES), min_samples=SAMPLES,
                                              analysis_period=SAMPLES, hardware_id="test", candidates=True))
    d = run.data
    names = (EFFECT_CHANNEL, RANDOM_WALK_CHANNEL, LOOP_CHANNEL, "flaky")
    for k in range(SAMPLES):
        values = [d.extra[EFFECT_CHANNEL][k], d.extra[RANDOM_WALK_CHANNEL][k], d.extra[LOOP_CHANNEL][k],
                  np.nan if k == 100 else 1.0 + k]
        c.add_candidates(k * NS, names, values, 0.0)
        if k == 7:    # a publisher naming a model channel: refused at reception, the analyses go on
            c.add_candidates(k * NS, (run.model.inputs[0], "temp"), [1.0, 2.0], 0.0)
        c.add("setpoint", k * NS, d.r[k], 0.0)
        c.add("input", k * NS, d.u[k], 0.0)
        c.add("output", k * NS, d.y[k], 0.0)
    assert c.analysis_due()
    job = c.take_job()
    assert job.candidates == "all" and set(job.data.extra) == {EFFECT_CHANNEL, RANDOM_WALK_CHANNEL, LOOP_CHANNEL}
    outcome = run_analysis(analyze, run.model, AnalysisOptions(), job)
    assert outcome.error is None, outcome.error
    c.accept(outcome)
    return run, c


def test_the_statuses_name_the_candidate_effect(live):
    run, c = live
    st = {s.name: s for s in c.statuses(0.0)}
    row = st["mpm_monitor: row y1"]
    values = dict(row.values)
    assert row.level == WARN and EFFECT_CHANNEL in row.message and "candidate" in row.message
    assert values["candidate_effects"] == EFFECT_CHANNEL and values["flagged_inputs"] == ""
    assert st["mpm_monitor: row y2"].level == OK and dict(st["mpm_monitor: row y2"].values)["candidate_effects"] == ""
    summary = st[SUMMARY_NAME]
    sv = dict(summary.values)
    assert sv["candidates_added"] == EFFECT_CHANNEL
    assert sv["candidates_not_exogenous"] == LOOP_CHANNEL and sv["candidates_unusable"] == "flaky"
    assert f"candidate channel(s) {EFFECT_CHANNEL} added to the repaired model" in summary.message


def test_the_repaired_model_written_live_has_the_candidate(live, tmp_path):
    run, c = live
    ok, message = c.write_repaired_model(str(tmp_path / "repaired.yaml"))
    assert ok, message
    m = load_model(tmp_path / "repaired.yaml")
    assert m.disturbances == (EFFECT_CHANNEL,)
    g = m.gain[m.outputs.index("y1"), m.columns.index(EFFECT_CHANNEL)]
    assert abs(g - run.effect.gain) <= 0.1 * run.effect.gain


def test_without_candidates_the_monitor_ignores_them():
    run = undeclared_effect_run(200, seed=1)
    c = MonitorCore(run.model, MonitorOptions(window=WindowOptions(window_samples=100), min_samples=50,
                                              analysis_period=50))
    c.add_candidates(0, ("a",), [1.0], 0.0)
    for k in range(60):
        c.add("setpoint", k * NS, run.data.r[k], 0.0)
        c.add("input", k * NS, run.data.u[k], 0.0)
        c.add("output", k * NS, run.data.y[k], 0.0)
    job = c.take_job()
    assert c.candidates is None and job.candidates is None and job.data.extra == {}


def test_the_monitor_node_takes_candidate_topic(tmp_path):
    """A plain publisher of the contract topics and of ``candidate_topic``: the node's statuses name
    the candidate effect, and its service writes the repaired model with the candidate."""
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.ros_io import (
        VectorCodec,
        diagnostics_qos,
        make_executor,
        ns_to_stamp,
        spin_until,
        vector_qos,
    )

    n = 2000
    run = undeclared_effect_run(n, seed=5)
    save_model(run.model, tmp_path / "model.yaml")
    ctx = private_context()
    ns = "/cand"
    monitor = MonitorNode(context=ctx, namespace=ns, parameter_overrides=_overrides({
        "model_file": str(tmp_path / "model.yaml"), "case": "", "diagnostics_topic": "diagnostics",
        "window_samples": n, "min_samples": n, "analysis_period": n, "candidate_topic": "candidates",
        "repaired_model_file": str(tmp_path / "repaired.yaml")}))
    pub_node = Node("plain_publisher", context=ctx, namespace=ns)
    pubs = {t: pub_node.create_publisher(JointState, t, vector_qos())
            for t in ("setpoint", "input", "output", "candidates")}
    latest = {}
    pub_node.create_subscription(DiagnosticArray, "diagnostics", lambda m: latest.update(msg=m), diagnostics_qos())
    client = pub_node.create_client(Trigger, "monitor/write_repaired_model")
    ex = make_executor(ctx)
    for nd in (monitor, pub_node):
        ex.add_node(nd)

    def summary():
        if "msg" not in latest:
            return {}
        return {kv.key: kv.value for s in latest["msg"].status if s.name == SUMMARY_NAME for kv in s.values}

    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 20.0)
        y_codec, u_codec = VectorCodec(run.model.outputs, "output"), VectorCodec(run.model.inputs, "input")
        d = run.data
        names = [EFFECT_CHANNEL, RANDOM_WALK_CHANNEL, LOOP_CHANNEL]
        for start in range(0, n, 100):
            for k in range(start, start + 100):
                stamp = k * NS
                msg = JointState(name=names, position=[float(d.extra[c][k]) for c in names])
                msg.header.stamp = ns_to_stamp(stamp)
                pubs["candidates"].publish(msg)
                pubs["setpoint"].publish(y_codec.encode(d.r[k], stamp))
                pubs["input"].publish(u_codec.encode(d.u[k], stamp))
                pubs["output"].publish(y_codec.encode(d.y[k], stamp))
            assert spin_until(ex, lambda: monitor.core.window.n_completed >= start + 100, 20.0)
        assert spin_until(ex, lambda: summary().get("analyses") == "1", 90.0)
        values = summary()
        assert values["candidates_added"] == EFFECT_CHANNEL, values
        assert values["candidates_not_exogenous"] == LOOP_CHANNEL
        row = {kv.key: kv.value for s in latest["msg"].status if s.name == "mpm_monitor: row y1" for kv in s.values}
        assert row["candidate_effects"] == EFFECT_CHANNEL
        future = client.call_async(Trigger.Request())
        assert spin_until(ex, future.done, 20.0)
        assert future.result().success, future.result().message
        assert load_model(tmp_path / "repaired.yaml").disturbances == (EFFECT_CHANNEL,)
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node)
