"""Candidate channel names the live monitor refuses: a comma, a control character (tab, line break) or
surrounding spaces, the rule of a model's channel names (:func:`mpm_monitor.core.model.name_problem`).

The statuses join candidate names with commas (``candidate_effects``, ``candidates_unusable``, ...), and
the offline analysis finds a candidate so named unusable: such a vector used to be kept, and its channel
reached every analysis."""

import numpy as np
import pytest
from ros_domains import close_nodes

from mpm_monitor.monitor.candidate_window import CandidateWindow
from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.statuses import ERROR, SUMMARY_NAME
from mpm_monitor.monitor.window import WindowOptions
from mpm_monitor.sim.undeclared import EFFECT_CHANNEL, undeclared_effect_run

NS = 1_000_000_000
EXPECTED = ("expected a channel name without commas, control characters (tabs, line breaks) or surrounding "
            "spaces, as a model's channel")

BAD_NAMES = [
    ("feed,temp", "'feed,temp'", "holds a comma"),
    ("feed\ttemp", "'feed\\ttemp'", "holds a control character"),
    ("feed\ntemp", "'feed\\ntemp'", "holds a control character"),
    ("feed\r\ntemp", "'feed\\r\\ntemp'", "holds a control character"),
    ("feed\x00", "'feed\\x00'", "holds a control character"),
    ("feed\u2028temp", "'feed\\u2028temp'", "holds a control character"),
    (" feed", "' feed'", "has surrounding spaces"),
]


@pytest.mark.parametrize("name, shown, why", BAD_NAMES, ids=[b[1] for b in BAD_NAMES])
def test_a_vector_naming_a_bad_channel_name_is_refused_in_one_line(name, shown, why):
    w = CandidateWindow(sample_time=1.0, capacity=10)
    problem = w.add(3 * NS, ("good", name), [1.0, 2.0])
    assert problem == f"candidate: channel name {shown} at t = 3 s {why}: {EXPECTED}"
    assert "\n" not in problem and "\r" not in problem and "\t" not in problem
    assert w.names == () and w.received == 0                      # nothing of the vector is kept
    assert w.add(4 * NS, ("good",), [1.0]) is None                # the next good vector is
    assert w.names == ("good",) and w.received == 1


def test_an_empty_name_is_still_refused():
    w = CandidateWindow(sample_time=1.0, capacity=10)
    assert w.add(0, ("good", ""), [1.0, 2.0]).startswith("candidate: empty or repeated channel names at t = 0 s")
    assert w.names == ()


def test_a_long_bad_name_is_cut_in_the_message():
    w = CandidateWindow(sample_time=1.0, capacity=10)
    problem = w.add(0, ("x" * 5000 + ",y",), [1.0])
    assert problem.startswith(f"candidate: channel name '{'x' * 40}...' at t = 0 s holds a comma: ")
    assert len(problem) < 300


def test_the_monitor_refuses_the_vector_and_the_other_channels_keep_flowing():
    """A bad name is a bad message of the channel ``candidate`` (summary ERROR naming it); the setpoint, input
    and output vectors keep completing samples, and the analyses get the good candidate channel only."""
    run = undeclared_effect_run(120, seed=2)
    c = MonitorCore(run.model, MonitorOptions(window=WindowOptions(window_samples=100), min_samples=100,
                                              analysis_period=100, hardware_id="test", candidates=True))
    d = run.data
    for k in range(120):
        c.add_candidates(k * NS, (EFFECT_CHANNEL,), [d.extra[EFFECT_CHANNEL][k]], 0.0)
        if k == 110:
            c.add_candidates(k * NS, ("feed,temp",), [1.0], 0.0)
        c.add("setpoint", k * NS, d.r[k], 0.0)
        c.add("input", k * NS, d.u[k], 0.0)
        c.add("output", k * NS, d.y[k], 0.0)
    assert c.window.n_completed == 120 and c.data_errors == 1
    assert c.candidates.names == (EFFECT_CHANNEL,)
    summary = {s.name: s for s in c.statuses(0.0)}[SUMMARY_NAME]
    assert summary.level == ERROR
    assert f"candidate: channel name 'feed,temp' at t = 110 s holds a comma: {EXPECTED}" in summary.message
    job = c.take_job()
    assert set(job.data.extra) == {EFFECT_CHANNEL} and job.data.unusable == {}
    assert job.data.n_samples == 100


def test_the_monitor_node_refuses_a_candidate_message_with_a_comma(tmp_path):
    """In process: a JointState on ``candidate_topic`` naming ``feed,temp`` is refused by the node's core;
    one naming a good channel is kept."""
    pytest.importorskip("rclpy")
    from sensor_msgs.msg import JointState

    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.ros_io import make_executor, ns_to_stamp, spin_until, vector_qos

    run = undeclared_effect_run(50, seed=1)
    save_model(run.model, tmp_path / "model.yaml")
    ctx = private_context()
    ns = "/candnames"
    monitor = MonitorNode(context=ctx, namespace=ns, parameter_overrides=_overrides({
        "model_file": str(tmp_path / "model.yaml"), "case": "", "diagnostics_topic": "diagnostics",
        "window_samples": 100, "min_samples": 100, "analysis_period": 100, "candidate_topic": "candidates"}))
    from rclpy.node import Node

    pub_node = Node("candidate_publisher", context=ctx, namespace=ns)
    pub = pub_node.create_publisher(JointState, "candidates", vector_qos())
    ex = make_executor(ctx)
    for nd in (monitor, pub_node):
        ex.add_node(nd)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1, 20.0)
        for k, names in enumerate((["feed,temp", "good"], ["good"])):
            msg = JointState(name=names, position=[1.0] * len(names))
            msg.header.stamp = ns_to_stamp(k * NS)
            pub.publish(msg)
        assert spin_until(ex, lambda: monitor.core.candidates.received >= 1, 20.0)
        assert monitor.core.data_errors == 1 and monitor.core.candidates.names == ("good",)
        summary = {s.name: s for s in monitor.core.statuses(0.0)}[SUMMARY_NAME]
        assert "candidate: channel name 'feed,temp' at t = 0 s holds a comma" in summary.message
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node)
