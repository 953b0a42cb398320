"""The plant node starts once its readers are matched: on its output and, a plant with measured disturbances, on
those too (a disturbance reader matched after the first sample would miss the first vectors).  In-process, on a
private context."""

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(60)

from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, case_parameters, private_context  # noqa: E402
from mpm_monitor.nodes import plant_node  # noqa: E402
from mpm_monitor.nodes.ros_io import make_executor, spin_until, stamp_to_ns, vector_qos  # noqa: E402


def _plant(ctx, namespace, case):
    params = case_parameters(case, seed=1)["plant"]
    params.update(lock_step=False, publish_clock=False, min_subscribers=1, start_delay=0.0)
    return plant_node.PlantNode(parameter_overrides=_overrides(params), context=ctx, namespace=namespace)


def test_a_plant_with_measured_disturbances_waits_for_their_reader_and_it_gets_the_first_vector():
    ctx = private_context()
    plant = _plant(ctx, "/start_dv", "level")
    reader = Node("reader", context=ctx, namespace="/start_dv")
    outputs, dvs = [], []
    reader.create_subscription(JointState, "output", outputs.append, vector_qos())
    ex = make_executor(ctx)
    ex.add_node(plant)
    ex.add_node(reader)
    try:
        assert spin_until(ex, lambda: plant._pub.get_subscription_count() == 1, 10.0)
        assert not spin_until(ex, lambda: plant.running, 1.0)       # the output's reader alone: not yet
        assert plant._missing() == ["0 of min_subscribers = 1 subscriber(s) on disturbance_topic /start_dv/disturbance"]
        reader.create_subscription(JointState, "disturbance", dvs.append, vector_qos())
        assert spin_until(ex, lambda: plant.running and dvs and outputs, 10.0)
        assert plant._missing() == []
        assert stamp_to_ns(dvs[0].header.stamp) == stamp_to_ns(outputs[0].header.stamp) == plant._t0_ns   # sample 0
    finally:
        close_nodes(ex, ctx, plant, reader)


def test_a_plant_without_measured_disturbances_starts_on_its_output_reader():
    ctx = private_context()
    plant = _plant(ctx, "/start_y", "3.1")
    reader = Node("reader", context=ctx, namespace="/start_y")
    ex = make_executor(ctx)
    ex.add_node(plant)
    ex.add_node(reader)
    try:
        assert plant._missing() == ["0 of min_subscribers = 1 subscriber(s) on output_topic /start_y/output"]
        reader.create_subscription(JointState, "output", lambda m: None, vector_qos())
        assert spin_until(ex, lambda: plant.running, 10.0)
    finally:
        close_nodes(ex, ctx, plant, reader)
