"""A plant that diverges stops: no vector its readers refuse (a value not finite or beyond 1e40) is published,
one error line says so, and the node asks to end with exit code 1.  In-process, on a private context.

The divergence is the simulator's ``measure`` (or the measured disturbances' generator) returning such a value
at one sample; a test controller answers every ``y(k)`` with ``u(k)`` in lock-step.
"""

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(60)

from rclpy.node import Node  # noqa: E402
from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: E402
from divergence_stubs import diverging as _diverging  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, case_parameters, private_context  # noqa: E402
from mpm_monitor.core.logged_data import MAX_ANALYSIS_SCALE  # noqa: E402
from mpm_monitor.nodes import plant_node  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, make_executor, spin_until, stamp_to_ns, vector_qos  # noqa: E402

#: The sample whose values leave what readers take (samples 0 .. DIVERGES_AT - 1 are published).
DIVERGES_AT = 5
HINT = "which no reader takes; the simulation stops (an unstable loop? check the model and the controller's tuning)"


class Controller:
    """Answers every y(k) with u(k) = 0 stamped like it, and keeps every vector and clock it receives."""

    def __init__(self, ctx, namespace, model, disturbances=False):
        self.node = Node("controller", context=ctx, namespace=namespace)
        self.outputs, self.dvs, self.clocks = [], [], []
        self._u = VectorCodec(model.inputs, "input")
        self._zero = np.zeros(len(model.inputs))
        self._pub = self.node.create_publisher(JointState, "input", vector_qos())
        self.node.create_subscription(JointState, "output", self._on_output, vector_qos())
        self.node.create_subscription(ClockMsg, "clock", self.clocks.append, vector_qos())
        if disturbances:
            self.node.create_subscription(JointState, "disturbance", self.dvs.append, vector_qos())

    def _on_output(self, msg):
        self.outputs.append(msg)
        self._pub.publish(self._u.encode(self._zero, stamp_to_ns(msg.header.stamp)))


def _plant(ctx, namespace, case):
    params = case_parameters(case, seed=1)["plant"]
    params.update(lock_step=True, clock_topic="clock", min_subscribers=1, start_delay=0.0, stall_timeout=3600.0)
    return plant_node.PlantNode(parameter_overrides=_overrides(params), context=ctx, namespace=namespace)


def _errors(err):
    return [line.split("]: ", 1)[1] for line in err.splitlines() if line.startswith("[ERROR]") and "]: " in line]


def _published_values(msgs):
    return np.array([list(m.position) for m in msgs], dtype=float)


@pytest.mark.parametrize("bad, expected", [
    ({1: 3.2e41}, f"the plant diverged: y2 = 3.2e+41 at t = {DIVERGES_AT} s is beyond 1e+40, {HINT}"),
    ({0: -math.inf, 2: math.nan},
     f"the plant diverged: y1 = -inf, y3 = nan at t = {DIVERGES_AT} s are not finite, {HINT}"),
])
def test_a_diverging_plant_publishes_nothing_readers_refuse_logs_one_error_and_asks_to_end(bad, expected, capfd):
    ctx = private_context()
    ns = "/diverge"
    plant = _plant(ctx, ns, "3.1")
    plant.sim.measure, measured = _diverging(plant.sim.measure, DIVERGES_AT, bad)
    ctrl = Controller(ctx, ns, plant.model)
    ex = make_executor(ctx)
    ex.add_node(plant)
    ex.add_node(ctrl.node)
    try:
        assert spin_until(ex, lambda: plant.exit_requested, 20.0), (plant.k, len(ctrl.outputs))
        assert spin_until(ex, lambda: len(ctrl.outputs) >= DIVERGES_AT and len(ctrl.clocks) >= DIVERGES_AT, 10.0)
        assert plant.exit_code == 1 and not plant.running and plant.k == DIVERGES_AT
        assert len(measured) == DIVERGES_AT + 1              # nothing simulated after the sample that diverged
        assert plant._stall_timer.is_canceled()              # no re-sent y(k): the last one is the last published
        values = _published_values(ctrl.outputs)
        assert [stamp_to_ns(m.header.stamp) for m in ctrl.outputs] == [k * 10**9 for k in range(DIVERGES_AT)]
        assert np.all(np.isfinite(values)) and np.all(np.abs(values) <= MAX_ANALYSIS_SCALE)
        assert np.array_equal(values, np.array(measured[:DIVERGES_AT]))      # the bounded samples as before
        assert [stamp_to_ns(c.clock) for c in ctrl.clocks] == [k * 10**9 for k in range(DIVERGES_AT)]
        assert plant.diverged == expected
    finally:
        close_nodes(ex, ctx, plant, ctrl.node)
    assert _errors(capfd.readouterr().err) == [expected]


def test_a_measured_disturbance_readers_refuse_stops_the_plant_before_that_sample_too(capfd):
    ctx = private_context()
    ns = "/diverge_dv"
    plant = _plant(ctx, ns, "level")
    plant.dv_generator.next, generated = _diverging(plant.dv_generator.next, DIVERGES_AT, {0: math.inf})
    ctrl = Controller(ctx, ns, plant.model, disturbances=True)
    ex = make_executor(ctx)
    ex.add_node(plant)
    ex.add_node(ctrl.node)
    expected = (f"the measured disturbances left the range readers take: measured disturbance inflow = inf at "
                f"t = {DIVERGES_AT} s is not finite, which no reader takes; the simulation stops (check the dv_* "
                f"parameters)")
    try:
        assert spin_until(ex, lambda: plant.exit_requested, 20.0), (plant.k, len(ctrl.outputs))
        assert spin_until(ex, lambda: len(ctrl.outputs) >= DIVERGES_AT and len(ctrl.dvs) >= DIVERGES_AT, 10.0)
        assert plant.exit_code == 1 and not plant.running and len(generated) == DIVERGES_AT + 1
        assert plant.diverged == expected
        for msgs in (ctrl.outputs, ctrl.dvs):
            assert [stamp_to_ns(m.header.stamp) for m in msgs] == [k * 10**9 for k in range(DIVERGES_AT)]
            values = _published_values(msgs)
            assert np.all(np.isfinite(values)) and np.all(np.abs(values) <= MAX_ANALYSIS_SCALE)
    finally:
        close_nodes(ex, ctx, plant, ctrl.node)
    assert _errors(capfd.readouterr().err) == [expected]


def test_the_process_of_a_diverged_plant_ends_with_exit_code_1(monkeypatch):
    """run_node ends the spin on the plant's request and returns its exit code (the drain's wait for
    acknowledgements is stubbed: nothing reads here)."""
    from mpm_monitor.nodes import ros_io

    made = []

    def factory(context):
        node = plant_node.PlantNode(context=context, parameter_overrides=_overrides(
            {"case": "3.1", "autostart": False}))
        node._stop_diverged("the plant diverged: a test")
        made.append(node)
        return node

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: [])
    assert ros_io.run_node(factory, ["plant_node"]) == 1
    assert len(made) == 1
