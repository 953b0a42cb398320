"""A plant (or replay) process that leaves on its own first waits until its readers acknowledged every vector.

The monitor runs behind the lock-step loop; a plant process that left right after its last sample took the
last few hundred output vectors with it, and a monitor asked for the whole run never completed it (one run
in five of test_nodes_multiprocess.py hung so).  In-process, on a private context.
"""

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(60)

from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, case_parameters, private_context  # noqa: E402
from mpm_monitor.nodes import plant_node, ros_io  # noqa: E402
from mpm_monitor.nodes.ros_io import make_executor, spin_until, vector_qos, wait_acked  # noqa: E402


def test_wait_acked_is_done_once_a_reader_has_everything():
    ctx = private_context()
    talker = Node("talker", context=ctx, namespace="/acks")
    listener = Node("listener", context=ctx, namespace="/acks")
    got = []
    pub = talker.create_publisher(JointState, "vectors", vector_qos())
    listener.create_subscription(JointState, "vectors", lambda m: got.append(m.position[0]), vector_qos())
    ex = make_executor(ctx)
    ex.add_node(talker)
    ex.add_node(listener)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() == 1, 10.0)
        for k in range(500):
            pub.publish(JointState(position=[float(k)]))
        assert wait_acked([pub], 10.0) == []
        assert spin_until(ex, lambda: len(got) == 500, 10.0) and got == [float(k) for k in range(500)]
    finally:
        close_nodes(ex, ctx, talker, listener)


def test_the_plant_waits_for_acknowledgements_only_when_it_leaves_after_max_samples(monkeypatch):
    ctx = private_context()
    params = case_parameters("3.1", seed=1)["plant"]
    params.update(clock_topic="clock", max_samples=5, exit_when_done=True, exit_ack_timeout=7.5)
    plant = plant_node.PlantNode(parameter_overrides=_overrides(params), context=ctx, namespace="/acks2")
    calls = []
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: calls.append(
        (sorted(p.topic_name for p in pubs), timeout)) or [])
    ex = make_executor(ctx)
    ex.add_node(plant)
    try:
        plant.drain(ex)                        # not done: stopped by a signal, it leaves at once
        assert calls == []
        plant.exit_requested = True
        plant.drain(ex)
        assert calls == [(["/acks2/clock", "/acks2/output"], 7.5)]
    finally:
        close_nodes(ex, ctx, plant)


def test_the_plants_warning_says_messages_for_its_clock_topic(monkeypatch, capfd):
    """Readers late on the plant's /clock (rosgraph_msgs/Clock, not a vector topic) and its outputs: the one
    warning calls what they lack messages, not vectors."""
    ctx = private_context()
    params = case_parameters("3.1", seed=1)["plant"]
    params.update(clock_topic="clock", max_samples=5, exit_when_done=True, exit_ack_timeout=7.5)
    plant = plant_node.PlantNode(parameter_overrides=_overrides(params), context=ctx, namespace="/acks3")
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: ["/acks3/output", "/acks3/clock"])
    ex = make_executor(ctx)
    ex.add_node(plant)
    try:
        plant.exit_requested = True
        plant.drain(ex)
    finally:
        close_nodes(ex, ctx, plant)
    warnings = [line.split("]: ", 1)[1] for line in capfd.readouterr().err.splitlines() if line.startswith("[WARN]")]
    assert warnings == ["leaving after 7.5 s with messages not acknowledged on /acks3/output, /acks3/clock: a reader "
                        "may lack the last ones sent"]
