"""A controller that diverges stops: no input (nor experiment dither) its readers refuse -- a value not finite
or beyond 1e40 -- is published, one error line says so, and the node asks to end with exit code 1.  In-process,
on a private context.

The divergence is the controller's ``step`` (or the running experiment's dither) returning such a value at one
sample; a test plant answers every ``u(k)`` with ``y(k + 1)`` and ``r(k + 1)`` in lock-step.
"""

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(60)

from rclpy.node import Node  # noqa: E402
from divergence_stubs import diverging as _diverging  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, case_parameters, private_context  # noqa: E402
from mpm_monitor.core.logged_data import MAX_ANALYSIS_SCALE  # noqa: E402
from mpm_monitor.nodes import mpc_node  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, make_executor, spin_until, stamp_to_ns, vector_qos  # noqa: E402
from mpm_monitor.sim.excitation import TimedDither  # noqa: E402

#: The sample whose values leave what readers take (samples 0 .. DIVERGES_AT - 1 are answered).
DIVERGES_AT = 5
NS = 10**9
HINT = "which no reader takes; the controller stops (an unstable loop? check the model and the tuning)"


class Plant:
    """Sends y(k) and r(k), and answers every u(k) with y(k + 1) and r(k + 1) up to y(DIVERGES_AT); keeps every
    input and dither it receives and every y it sent."""

    def __init__(self, ctx, namespace, model):
        self.node = Node("plant", context=ctx, namespace=namespace)
        self.inputs, self.dithers, self.outputs = [], [], {}
        self._y = VectorCodec(model.outputs, "output")
        self._rng = np.random.default_rng(3)
        self.pubs = {t: self.node.create_publisher(JointState, t, vector_qos()) for t in ("output", "setpoint")}
        self.node.create_subscription(JointState, "input", self._on_input, vector_qos())
        self.node.create_subscription(JointState, "dither", self.dithers.append, vector_qos())

    def send(self, k):
        """Send r(k) and y(k) (the same y(k) again when it was sent already: a re-sent sample)."""
        y = self.outputs.setdefault(k, self._rng.normal(size=self._y.size))
        self.pubs["setpoint"].publish(self._y.encode(np.ones(self._y.size), k * NS))
        self.pubs["output"].publish(self._y.encode(y, k * NS))

    def _on_input(self, msg):
        self.inputs.append(msg)
        k = stamp_to_ns(msg.header.stamp) // NS + 1
        if k <= DIVERGES_AT:
            self.send(k)


def _recorded(pub):
    """Keep every vector ``pub`` publishes (as the node hands it over, before the middleware)."""
    sent = []
    real = pub.publish

    def publish(msg):
        sent.append(msg)
        real(msg)

    pub.publish = publish
    return sent


def _errors(err):
    return [line.split("]: ", 1)[1] for line in err.splitlines() if line.startswith("[ERROR]") and "]: " in line]


def _stamps(msgs):
    return [stamp_to_ns(m.header.stamp) for m in msgs]


def _values(msgs):
    return np.array([list(m.position) for m in msgs], dtype=float)


def _run_until_diverged(mpc, plant, ex, reached):
    """Drive ``mpc`` in lock-step until ``reached()`` (the sample that diverges was computed); then send what a
    plant on a stall would (r(k) and y(k) again) and the next sample, and spin until the node has taken them."""
    taken = []
    real = mpc._on_vector

    def on_vector(key, msg):
        taken.append((key, stamp_to_ns(msg.header.stamp)))
        real(key, msg)

    mpc._on_vector = on_vector      # the subscriptions call it through the attribute
    assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in plant.pubs.values())
                      and mpc._pub.get_subscription_count() >= 1 and mpc._dither_pub.get_subscription_count() >= 1,
                      20.0)
    plant.send(0)
    assert spin_until(ex, reached, 20.0), (mpc.steps, len(plant.inputs))
    assert spin_until(ex, lambda: len(plant.inputs) >= DIVERGES_AT, 10.0)
    before = len(taken)
    plant.send(DIVERGES_AT)              # r(k) and y(k) re-sent on a stall, then the next sample
    plant.send(DIVERGES_AT + 1)
    assert spin_until(ex, lambda: len(taken) >= before + 4, 10.0), taken[before:]


def _loop(ns, mpc, ctx):
    plant = Plant(ctx, ns, mpc.model)
    ex = make_executor(ctx)
    ex.add_node(mpc)
    ex.add_node(plant.node)
    return plant, ex


@pytest.mark.parametrize("bad, expected", [
    ({2: 4.1e41}, f"the controller diverged: u3 = 4.1e+41 at t = {DIVERGES_AT} s is beyond 1e+40, {HINT}"),
    ({0: -math.inf, 1: math.nan},
     f"the controller diverged: u1 = -inf, u2 = nan at t = {DIVERGES_AT} s are not finite, {HINT}"),
])
def test_a_diverging_controller_publishes_nothing_readers_refuse_logs_one_error_and_asks_to_end(bad, expected,
                                                                                                 capfd):
    ctx = private_context()
    ns = "/mpc_diverge"
    mpc = mpc_node.MpcNode(parameter_overrides=_overrides(case_parameters("3.1")["mpc"]), context=ctx,
                           namespace=ns)
    mpc.ctrl.step, computed = _diverging(mpc.ctrl.step, DIVERGES_AT, bad)
    sent = _recorded(mpc._pub)
    plant, ex = _loop(ns, mpc, ctx)
    try:
        _run_until_diverged(mpc, plant, ex, lambda: len(computed) > DIVERGES_AT)
        assert _stamps(sent) == [k * NS for k in range(DIVERGES_AT)]         # no u(k) of or after the sample
        values = _values(sent)
        assert np.all(np.isfinite(values)) and np.all(np.abs(values) <= MAX_ANALYSIS_SCALE)
        assert mpc.exit_requested and mpc.exit_code == 1 and mpc.diverged == expected
        assert len(computed) == DIVERGES_AT + 1 and mpc.steps == DIVERGES_AT   # nothing computed after it
        assert np.array_equal(values, np.array(computed[:DIVERGES_AT]))      # the bounded samples as before
        assert _stamps(plant.inputs) == [k * NS for k in range(DIVERGES_AT)]
        assert mpc._dither_refusal() == "the controller stopped: it diverged"
    finally:
        close_nodes(ex, ctx, mpc, plant.node)
    assert _errors(capfd.readouterr().err) == [expected]


def test_an_experiment_dither_readers_refuse_stops_the_controller_before_that_sample(capfd):
    ctx = private_context()
    ns = "/mpc_diverge_dither"
    mpc = mpc_node.MpcNode(parameter_overrides=_overrides(case_parameters("3.1")["mpc"]), context=ctx,
                           namespace=ns)
    experiment = TimedDither([0.1, 0.0, 0.0], 100, np.random.default_rng(1))
    experiment.next, dithers = _diverging(experiment.next, DIVERGES_AT, {0: math.inf})
    mpc.experiment = experiment
    steps = []
    real_step = mpc.ctrl.step
    mpc.ctrl.step = lambda *a, **kw: steps.append(a) or real_step(*a, **kw)
    sent, sent_dither = _recorded(mpc._pub), _recorded(mpc._dither_pub)
    expected = (f"the dither left the range readers take: dither u1 = inf at t = {DIVERGES_AT} s is not finite, "
                f"which no reader takes; the controller stops (check the ~/start_dither request)")
    plant, ex = _loop(ns, mpc, ctx)
    try:
        _run_until_diverged(mpc, plant, ex, lambda: len(dithers) > DIVERGES_AT)
        for msgs in (sent, sent_dither):                                      # no zero dither vector either
            assert _stamps(msgs) == [k * NS for k in range(DIVERGES_AT)]
            values = _values(msgs)
            assert np.all(np.isfinite(values)) and np.all(np.abs(values) <= MAX_ANALYSIS_SCALE)
        assert mpc.exit_requested and mpc.exit_code == 1 and mpc.diverged == expected and mpc.experiment is None
        assert len(dithers) == DIVERGES_AT + 1 and len(steps) == DIVERGES_AT  # u(k) not computed with it
    finally:
        close_nodes(ex, ctx, mpc, plant.node)
    assert _errors(capfd.readouterr().err) == [expected]


def test_the_process_of_a_diverged_controller_ends_with_exit_code_1(monkeypatch, capfd):
    """run_node ends the spin on the controller's request and returns its exit code (the node diverges on its
    first sample, handed to it before the spin)."""
    from mpm_monitor.nodes import ros_io

    made = []

    def factory(context):
        node = mpc_node.MpcNode(context=context, parameter_overrides=_overrides({"case": "3.1"}))
        made.append(node)
        node.ctrl.step = lambda r, y, dither=None, dv=None: np.full(node.model.n_inputs, 4.1e41)
        codec = VectorCodec(node.model.outputs, "output")
        node._on_vector("r", codec.encode(np.ones(codec.size), 0))
        node._on_vector("y", codec.encode(np.zeros(codec.size), 0))
        assert getattr(node, "exit_requested", False), "the node did not ask to end"
        return node

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    assert ros_io.run_node(factory, ["mpc_node"]) == 1
    assert len(made) == 1
    assert _errors(capfd.readouterr().err) == [f"the controller diverged: u1 = 4.1e+41, u2 = 4.1e+41, u3 = 4.1e+41 "
                                               f"at t = 0 s are beyond 1e+40, {HINT}"]
