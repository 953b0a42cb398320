"""A candidate vector the monitor node refuses (a channel name with a comma, one value too many, ...) is logged as a
refused setpoint, input or output vector is: one warning line, the reason the statuses give, throttled to one per
5 s as ``_on_vector``'s.  It used to show only in the diagnostics statuses."""

import pytest
from ros_domains import close_nodes

from mpm_monitor.monitor.statuses import SUMMARY_NAME
from mpm_monitor.sim.undeclared import undeclared_effect_run

rclpy = pytest.importorskip("rclpy")

NS = 1_000_000_000
COMMA = ("candidate: channel name 'feed,temp' at t = 0 s holds a comma: expected a channel name without commas, "
         "control characters (tabs, line breaks) or surrounding spaces, as a model's channel")


def _warnings(capfd) -> list:
    return [line.split("]: ", 1)[1] for line in capfd.readouterr().err.splitlines() if line.startswith("[WARN]")]


def _candidates(names, values, stamp_ns):
    from sensor_msgs.msg import JointState

    from mpm_monitor.nodes.ros_io import ns_to_stamp

    msg = JointState(name=list(names), position=[float(v) for v in values])
    msg.header.stamp = ns_to_stamp(stamp_ns)
    return msg


@pytest.fixture
def monitor(tmp_path):
    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.ros_io import make_executor

    run = undeclared_effect_run(50, seed=1)
    save_model(run.model, tmp_path / "model.yaml")
    ctx = private_context()
    node = MonitorNode(context=ctx, namespace="/candlog", parameter_overrides=_overrides({
        "model_file": str(tmp_path / "model.yaml"), "case": "", "diagnostics_topic": "diagnostics",
        "window_samples": 100, "min_samples": 100, "analysis_period": 100, "candidate_topic": "candidates"}))
    ex = make_executor(ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        node.close()
        close_nodes(ex, ctx, node)


def test_a_refused_candidate_vector_is_logged_once_and_throttled(monitor, capfd):
    """Three refused vectors within 5 s: three bad messages in the statuses, one warning (the first's reason, as
    the statuses word it); a good vector logs nothing."""
    node, _ = monitor
    capfd.readouterr()
    node._on_candidates(_candidates(["good"], [1.0], 0))
    assert _warnings(capfd) == []
    node._on_candidates(_candidates(["feed,temp", "good"], [1.0, 2.0], 0))
    node._on_candidates(_candidates(["good"], [1.0, 2.0], NS))                  # a value too many
    node._on_candidates(_candidates(["feed,temp"], [1.0], 2 * NS))
    assert _warnings(capfd) == [COMMA]
    assert node.core.data_errors == 3 and node.core.candidates.names == ("good",)
    summary = {s.name: s for s in node.core.statuses(0.0)}[SUMMARY_NAME]
    assert dict(summary.values)["bad_messages"] == "3"


def test_a_candidate_vector_refused_on_the_topic_is_logged(monitor, capfd):
    """The same through the subscription on ``candidate_topic``."""
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from mpm_monitor.nodes.ros_io import spin_until, vector_qos

    node, ex = monitor
    pub_node = Node("candidate_publisher", context=node.context, namespace="/candlog")
    pub = pub_node.create_publisher(JointState, "candidates", vector_qos())
    ex.add_node(pub_node)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1, 20.0)
        capfd.readouterr()
        pub.publish(_candidates(["feed,temp", "good"], [1.0, 2.0], 0))
        pub.publish(_candidates(["good"], [1.0], NS))
        assert spin_until(ex, lambda: node.core.candidates.received >= 1, 20.0)
        assert node.core.data_errors == 1
        assert _warnings(capfd) == [COMMA]
    finally:
        ex.remove_node(pub_node)
        pub_node.destroy_node()
