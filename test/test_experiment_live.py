"""The experiment, live: the MPC node's ``~/start_dither`` service and the monitor's ``auto_experiment``.

In-process and isolated, as test_nodes_inprocess.py: every test has its own ``rclpy`` context with
``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF`` and its own namespace, and the loop runs in lock-step
simulated time.

Acceptance ("Detectability, and the experiment that resolves what the data cannot", part 3): a fat
plant (2 outputs, 4 inputs, one mismatched element) monitored with ``auto_experiment: true`` goes
from ambiguous (the inputs move together, no element located) to an experiment (the monitor asks
the MPC node for a dither, which runs and stops by itself) to the exact located element, in the
analysis of the window that includes the experiment.
"""


import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(300)

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, private_context  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, make_executor, spin_until, vector_qos  # noqa: E402
from mpm_monitor.sim.cases import paper_case  # noqa: E402

NS = 1_000_000_000


def dither_request(amplitudes=None, samples=None, raw=None):
    """A ``~/start_dither`` request: DOUBLE amplitudes, INTEGER samples, and ``raw`` {name: ParameterValue}."""
    params = [Parameter(name=n, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(a)))
              for n, a in (amplitudes or {}).items()]
    if samples is not None:
        params.append(Parameter(name="samples", value=ParameterValue(type=ParameterType.PARAMETER_INTEGER,
                                                                     integer_value=int(samples))))
    params += [Parameter(name=n, value=v) for n, v in (raw or {}).items()]
    return SetParameters.Request(parameters=params)


class Harness:
    """Nodes on a private context and one executor; stopped and destroyed by :meth:`close`."""

    def __init__(self, namespace):
        self.ctx = private_context()
        self.ns = namespace
        self.ex = make_executor(self.ctx)
        self.nodes = []

    def add(self, node):
        self.ex.add_node(node)
        self.nodes.append(node)
        return node

    def spin_until(self, done, timeout=20.0):
        return spin_until(self.ex, done, timeout, context=self.ctx, step=0.02)

    def call(self, client, request, timeout=10.0):
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout)
        return future.result()

    def close(self):
        for nd in self.nodes:
            close = getattr(nd, "close", None)
            if close is not None:
                close()
        for nd in self.nodes:
            self.ex.remove_node(nd)
            nd.destroy_node()
        self.ex.shutdown()
        self.ctx.try_shutdown()


@pytest.fixture
def harness():
    made = []

    def make(namespace):
        made.append(Harness(namespace))
        return made[-1]

    yield make
    for h in made:
        h.close()


class Driver:
    """A plain node that plays plant and setpoints for an MPC node: publishes r(k), y(k), collects u and dither."""

    def __init__(self, h, model):
        self.node = h.add(Node("driver", context=h.ctx, namespace=h.ns))
        self.h = h
        self.model = model
        self.pubs = {t: self.node.create_publisher(JointState, t, vector_qos()) for t in ("setpoint", "output")}
        self.y_codec = VectorCodec(model.outputs, "output")
        self.u_codec = VectorCodec(model.inputs, "input")
        self.u, self.dither = {}, []
        self.node.create_subscription(JointState, "input", lambda m: self.u.__setitem__(*self.u_codec.decode(m)),
                                      vector_qos())
        self.node.create_subscription(JointState, "dither", lambda m: self.dither.append(self.u_codec.decode(m)),
                                      vector_qos())

    def step(self, k, r, y):
        stamp = k * NS
        self.pubs["setpoint"].publish(self.y_codec.encode(r, stamp))
        self.pubs["output"].publish(self.y_codec.encode(y, stamp))
        assert self.h.spin_until(lambda: stamp in self.u, 10.0), f"no u for sample {k}"


# ----------------------------------------------------------------------------- the service
def test_start_dither_refusals_the_dither_and_its_topic(harness):
    """Refused with one line (each check), then a dither of its length, on u, and on the dither topic."""
    from mpm_monitor.nodes.mpc_node import MpcNode, mpc_options_from_params
    from mpm_monitor.sim.mpc import InternalModelMpc

    h = harness("/dith")
    model = paper_case("3.2").model   # inputs u1, u2, u3
    mpc = h.add(MpcNode(context=h.ctx, namespace=h.ns, parameter_overrides=_overrides(
        {"case": "3.2", "max_dither": 0.5, "max_dither_samples": 50, "seed": 5})))
    h.add(MpcNode("mpc_off", context=h.ctx, namespace=h.ns, parameter_overrides=_overrides(
        {"case": "3.2", "input_topic": "input_off", "dither_topic": "dither_off"})))
    h.add(MpcNode("mpc_ext", context=h.ctx, namespace=h.ns, parameter_overrides=_overrides(
        {"case": "3.2", "input_topic": "input_ext", "use_dither": True, "max_dither": 1.0})))
    drv = Driver(h, model)
    clients = {name: drv.node.create_client(SetParameters, f"{name}/start_dither")
               for name in ("mpc", "mpc_off", "mpc_ext")}
    assert h.spin_until(lambda: all(c.service_is_ready() for c in clients.values())
                        and all(p.get_subscription_count() >= 3 for p in drv.pubs.values())
                        and mpc._pub.get_subscription_count() >= 1 and mpc._dither_pub.get_subscription_count() >= 1)

    def call(request, name="mpc"):
        res = h.call(clients[name], request).results
        assert len(res) == 1 and "\n" not in res[0].reason
        return res[0]

    text = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="0.1")
    refusals = [
        (dither_request({"u1": 0.6}, 10), "refused: u1: amplitude 0.6 above max_dither 0.5 (input units)"),
        (dither_request({"u9": 0.1}, 10), "refused: unknown input 'u9' (the inputs are u1, u2, u3; and the INTEGER "
                                          "samples)"),
        (dither_request({"u1": 0.1}, 0), "refused: samples 0 outside [1, max_dither_samples = 50]"),
        (dither_request({"u1": 0.1}, 51), "refused: samples 51 outside [1, max_dither_samples = 50]"),
        (dither_request({"u1": 0.1}), "refused: samples missing: give the INTEGER samples the dither lasts"),
        (dither_request({}, 10), "refused: no input to dither: give one DOUBLE amplitude per input to dither"),
        (dither_request({"u1": -0.1}, 10), "refused: u1: expected an amplitude > 0 (input units), got -0.1"),
        (dither_request(None, 10, {"u2": text}), "refused: u2: expected a DOUBLE amplitude (input units)"),
        (dither_request({"u1": 0.1}, None, {"samples": ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                                                     double_value=10.0)}),
         "refused: samples: expected an INTEGER number of samples"),
    ]
    for request, reason in refusals:
        res = call(request)
        assert not res.successful and res.reason == reason
    res = call(dither_request({"u1": 0.1}, 10), "mpc_off")
    assert not res.successful and res.reason == ("refused: dither experiments are disabled on this node (its "
                                                 "max_dither parameter is 0)")
    res = call(dither_request({"u1": 0.1}, 10), "mpc_ext")
    assert not res.successful and "(use_dither)" in res.reason
    assert mpc.experiment is None and mpc.experiments == 0

    rng = np.random.default_rng(0)
    r_all, y_all = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    for k in range(5):
        drv.step(k, r_all[k], y_all[k])
    res = call(dither_request({"u3": 0.2, "u1": 0.1}, 20))
    assert res.successful and res.reason == "dither on u1, u3 (amplitudes 0.1, 0.2) for 20 samples, from the next sample"
    for k in range(5, 8):
        drv.step(k, r_all[k], y_all[k])
    res = call(dither_request({"u2": 0.1}, 5))
    assert not res.successful and res.reason == ("refused: a dither is already running: u1, u3 (amplitudes 0.1, 0.2; "
                                                 "17 samples left)")
    for k in range(8, 40):
        drv.step(k, r_all[k], y_all[k])
    assert h.spin_until(lambda: len(drv.dither) >= 21, 5.0)
    h.spin_until(lambda: False, 0.2)   # nothing more comes
    assert mpc.experiment is None and mpc.experiments == 1
    # 20 dither vectors stamped with samples 5..24, then one zero vector stamped with sample 25
    stamps = [s for s, _ in drv.dither]
    values = np.array([v for _, v in drv.dither])
    assert stamps == [k * NS for k in range(5, 26)]
    np.testing.assert_array_equal(np.abs(values[:20]), np.tile([0.1, 0.0, 0.2], (20, 1)))
    np.testing.assert_array_equal(values[20], 0.0)
    # u is the controller's answer with that dither added, sample for sample
    ctrl = InternalModelMpc(model, mpc_options_from_params(mpc.params, 3, 3))
    dither = {s: v for s, v in drv.dither[:20]}
    for k in range(40):
        u = ctrl.step(r_all[k], y_all[k], dither.get(k * NS))
        np.testing.assert_array_equal(drv.u[k * NS], u)
    # after the end, another experiment is accepted
    res = call(dither_request({"u2": 0.05}, 3))
    assert res.successful and mpc.experiments == 2


def test_a_bag_records_the_dither_topic(harness, tmp_path):
    from mpm_monitor.io.bags import read_raw_messages
    from mpm_monitor.nodes.mpc_node import MpcNode
    from mpm_monitor.nodes.recorder_node import RecorderNode

    h = harness("/bag")
    model = paper_case("3.2").model
    mpc = h.add(MpcNode(context=h.ctx, namespace=h.ns, parameter_overrides=_overrides(
        {"case": "3.2", "max_dither": 0.5})))
    rec = h.add(RecorderNode(bag_dir=tmp_path / "bag", topics=["dither"], context=h.ctx, namespace=h.ns,
                             flush_period=0.05))
    drv = Driver(h, model)
    client = drv.node.create_client(SetParameters, "mpc/start_dither")
    assert h.spin_until(lambda: client.service_is_ready() and mpc._dither_pub.get_subscription_count() >= 2
                        and all(p.get_subscription_count() >= 1 for p in drv.pubs.values()))
    assert h.call(client, dither_request({"u2": 0.3}, 4)).results[0].successful
    for k in range(8):
        drv.step(k, np.zeros(3), np.zeros(3))
    assert h.spin_until(lambda: rec.message_count >= 5, 5.0)
    rec.close()
    msgs = read_raw_messages(tmp_path / "bag", topics=["/bag/dither"])
    # four dither vectors stamped with samples 0..3 (the dither starts with the next sample), the zero vector at 4
    assert [m.stamp for m in msgs] == [k * NS for k in range(5)]
    assert {m.msgtype for m in msgs} == {"sensor_msgs/msg/JointState"}
