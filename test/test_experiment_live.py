"""The experiment, live: the MPC node's ``~/start_dither`` service and the monitor's ``auto_experiment``.

In-process and isolated, as test_nodes_inprocess.py: every test has its own ``rclpy`` context with
``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF`` and its own namespace, and the loop runs in lock-step
simulated time.

Acceptance ("Detectability, and the experiment that resolves what the data cannot", part 3): a fat
plant (2 outputs, 4 inputs, one mismatched element) monitored with ``auto_experiment: true`` goes
from ambiguous (the inputs move together, no element located) to the experiment the analysis itself
recommends (the monitor asks the MPC node for that dither, which runs and stops by itself) to the
exact located element, in the analysis of the window that includes the experiment.
"""


import types

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(300)

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue, SetParametersResult  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import Suite, _overrides, private_context  # noqa: E402
from mpm_monitor.core.model import PlantModel  # noqa: E402
from mpm_monitor.core.pipeline import analyze as real_analyze  # noqa: E402
from mpm_monitor.io.model_file import save_model  # noqa: E402
from mpm_monitor.monitor.experiment import END_MARGIN  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, diagnostics_qos, make_executor, spin_until, vector_qos  # noqa: E402
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
        close_nodes(self.ex, self.ctx, *self.nodes)


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
    assert res.successful
    assert res.reason == "dither on u1, u3 (amplitudes 0.1, 0.2) for 20 samples, from the next sample"
    for k in range(5, 8):
        drv.step(k, r_all[k], y_all[k])
    res = call(dither_request({"u2": 0.1}, 5))
    assert not res.successful
    assert res.reason == "refused: a dither is already running on u1, u3 (amplitudes 0.1, 0.2), 17 samples left"
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


def test_max_dither_is_live_and_every_other_parameter_read_only(harness):
    """Lowering max_dither while the node runs takes effect (a request above it is refused, a running dither
    above it ends at once); a change of a parameter read only at start-up is refused, not silently ignored."""
    from rclpy.parameter import Parameter

    from mpm_monitor.nodes.mpc_node import MpcNode

    h = harness("/live")
    model = paper_case("3.2").model
    mpc = h.add(MpcNode(context=h.ctx, namespace=h.ns, parameter_overrides=_overrides(
        {"case": "3.2", "max_dither": 0.5, "max_dither_samples": 50})))
    drv = Driver(h, model)
    client = drv.node.create_client(SetParameters, "mpc/start_dither")
    assert h.spin_until(lambda: client.service_is_ready() and all(p.get_subscription_count() >= 1
                                                                  for p in drv.pubs.values())
                        and mpc._dither_pub.get_subscription_count() >= 1)

    def call(request):
        return h.call(client, request).results[0]

    res = mpc.set_parameters([Parameter("max_dither", value=0.1)])
    assert res[0].successful and mpc.params["max_dither"] == 0.1
    res = call(dither_request({"u1": 0.4}, 10))
    assert not res.successful and res.reason == "refused: u1: amplitude 0.4 above max_dither 0.1 (input units)"
    res = mpc.set_parameters([Parameter("max_dither", value=-1.0)])
    assert not res[0].successful and mpc.params["max_dither"] == 0.1
    # a running dither above a lowered bound ends at once, with the zero dither vector
    for k in range(3):
        drv.step(k, np.zeros(3), np.zeros(3))
    assert call(dither_request({"u2": 0.08}, 40)).successful
    for k in range(3, 6):
        drv.step(k, np.zeros(3), np.zeros(3))
    assert mpc.experiment is not None
    assert mpc.set_parameters([Parameter("max_dither", value=0.05)])[0].successful
    assert mpc.experiment is None
    assert h.spin_until(lambda: len(drv.dither) >= 4, 5.0)
    stamp, last = drv.dither[-1]
    assert stamp == 6 * NS and not np.any(last)       # the zero vector, stamped with the next sample
    # read once at start-up: refused with the reason instead of accepted and ignored
    for name, value in (("prediction_horizon", 5), ("input_topic", "elsewhere"), ("case", "3.3")):
        res = mpc.set_parameters([Parameter(name, value=value)])
        assert not res[0].successful and "read-only" in res[0].reason, (name, res[0].reason)
    assert mpc.get_parameter("prediction_horizon").value == mpc.params["prediction_horizon"]


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


# ----------------------------------------------------------------------------- the monitor
def fake_report(model, experiment):
    """A report with row y1 mismatched, its inputs ambiguous, and ``experiment`` (the fields the monitor reads)."""
    rows = [types.SimpleNamespace(output=o, rsi=1.3 if o == "y1" else 1.0, mismatch=o == "y1", p_value=1e-6)
            for o in model.outputs]
    elements = [types.SimpleNamespace(output="y1", input=i, mismatch=False, p_value=0.5, kind=None, ambiguous=True)
                for i in model.inputs]
    return types.SimpleNamespace(rows=rows, elements=elements, overall_rsi=1.3, warnings=[], experiment=experiment)


RECOMMENDED = types.SimpleNamespace(dither={"u3": 0.1, "u2": 0.1}, samples=60, expected_detectable_gain_change=0.2,
                                    why="u2 and u3 move with u1")


class Summaries:
    """Keeps every summary status received on ``diagnostics``."""

    def __init__(self, h):
        self.node = h.add(Node("summaries", context=h.ctx, namespace=h.ns))
        self.seen = []
        self.node.create_subscription(DiagnosticArray, "diagnostics", self._on, diagnostics_qos())

    def _on(self, msg):
        for s in msg.status:
            if s.name == SUMMARY_NAME:
                self.seen.append((s.message, {kv.key: kv.value for kv in s.values}))

    def latest(self):
        return self.seen[-1] if self.seen else ("", {})

    def any(self, text):
        return any(text in m for m, _ in self.seen)


class Stack:
    """A plain publisher of the vector topics and the dither, sample by sample, for a monitor."""

    def __init__(self, h, model, monitor):
        self.node = h.add(Node("stack", context=h.ctx, namespace=h.ns))
        self.h, self.monitor = h, monitor
        self.pubs = {t: self.node.create_publisher(JointState, t, vector_qos())
                     for t in ("setpoint", "input", "output", "dither")}
        self.y = VectorCodec(model.outputs, "output")
        self.u = VectorCodec(model.inputs, "input")
        self.rng = np.random.default_rng(0)

    def feed(self, k0, k1, dither=None):
        for k in range(k0, k1):
            stamp = k * NS
            if dither is not None:
                self.pubs["dither"].publish(self.u.encode(dither, stamp))
            self.pubs["setpoint"].publish(self.y.encode(self.rng.normal(size=3), stamp))
            self.pubs["input"].publish(self.u.encode(self.rng.normal(size=3), stamp))
            self.pubs["output"].publish(self.y.encode(self.rng.normal(size=3), stamp))
        assert self.h.spin_until(lambda: self.monitor.core.window.n_completed >= k1, 10.0)


def analysed(monitor, n):
    """True when ``n`` analysis jobs were run or replaced.

    The worker replaces a job still waiting when the next one is due: on a loaded machine the job
    at sample 150 may never run because the one at 200 came before the worker was free.
    """
    return monitor.results + monitor.worker.replaced >= n


def _monitor(h, analyze, **params):
    from mpm_monitor.nodes.monitor_node import MonitorNode

    p = dict(case="3.2", diagnostics_topic="diagnostics", window_samples=200, min_samples=100, analysis_period=50,
             republish_period=0.05, stale_timeout=600.0, auto_experiment=True, repair=False)
    p.update(params)
    return h.add(MonitorNode(context=h.ctx, namespace=h.ns, analyze=analyze, parameter_overrides=_overrides(p)))


def test_the_monitor_calls_the_service_once_follows_the_dither_and_analyses_the_window_that_includes_it(harness):
    """A fake dither service that accepts; the stack plays the dither. One call, statuses at every step."""
    h = harness("/auto")
    model = paper_case("3.2").model
    windows = []

    def analyze(m, data, options):   # recommends the experiment every time (the stack's data never settle it)
        windows.append((data.t[0], data.t[-1]))
        return fake_report(m, RECOMMENDED)

    monitor = _monitor(h, analyze, experiment_cooldown=1000)
    requests = []
    service_node = h.add(Node("mpc", context=h.ctx, namespace=h.ns))

    def start_dither(request, response):
        requests.append(request)
        response.results = [SetParametersResult(successful=True, reason="dither on u2, u3 for 60 samples")]
        return response

    service_node.create_service(SetParameters, "~/start_dither", start_dither)
    summaries = Summaries(h)
    stack = Stack(h, model, monitor)
    assert h.spin_until(lambda: monitor._dither_client.service_is_ready()
                        and all(p.get_subscription_count() >= 1 for p in stack.pubs.values()))
    stack.feed(0, 100)
    assert h.spin_until(lambda: monitor.core.experiment.phase == "running", 10.0)
    assert len(requests) == 1
    got = {p.name: (p.value.type, p.value.double_value, p.value.integer_value) for p in requests[0].parameters}
    assert got == {"u2": (ParameterType.PARAMETER_DOUBLE, 0.1, 0), "u3": (ParameterType.PARAMETER_DOUBLE, 0.1, 0),
                   "samples": (ParameterType.PARAMETER_INTEGER, 0.0, 60)}
    assert h.spin_until(lambda: summaries.any("experiment running: dither on u2, u3 (amplitudes 0.1, 0.1; 60 samples "
                                              "left)"), 5.0)
    dither = np.array([0.0, 0.1, -0.1])
    stack.feed(100, 140, dither)
    assert h.spin_until(lambda: "experiment running: dither on u2, u3 (amplitudes 0.1, 0.1; 20 samples left)"
                        in summaries.latest()[0], 5.0)
    stack.feed(140, 155, dither)
    assert h.spin_until(lambda: monitor.results >= 2, 10.0)   # the analysis at sample 150 recommends again...
    stack.feed(155, 160, dither)
    stack.pubs["dither"].publish(stack.u.encode(np.zeros(3), 160 * NS))   # the zero vector: the end
    assert h.spin_until(lambda: monitor.core.experiment.phase == "done", 10.0)
    assert len(requests) == 1                                  # ...and no second call while it ran
    assert windows[-1] == (0.0, 159.0)                         # analysed at once, the window holding all of it
    assert h.spin_until(lambda: "this analysis includes the experiment: dither on u2, u3 for 60 samples "
                        "(t = 100-159 s)" in summaries.latest()[0], 5.0)
    message, values = summaries.latest()
    assert "experiment recommended: dither on u2, u3 for 60 samples (amplitudes 0.1, 0.1; not before sample 1160 " \
           "(experiment_cooldown))" in message
    assert values["experiments"] == "1" and values["experiment_detail"] == "dither on u2, u3 for 60 samples"
    stack.feed(160, 260)
    assert h.spin_until(lambda: analysed(monitor, 5), 10.0)
    assert len(requests) == 1


def test_without_the_service_or_refused_the_monitor_only_reports_the_recommendation(harness):
    """No dither service; a real MPC node whose max_dither refuses; auto_experiment false."""
    from mpm_monitor.nodes.mpc_node import MpcNode

    h = harness("/nosrv")
    model = paper_case("3.2").model
    monitor = _monitor(h, lambda m, d, o: fake_report(m, RECOMMENDED))
    summaries = Summaries(h)
    stack = Stack(h, model, monitor)
    assert h.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in stack.pubs.values())
                        and monitor._diag_pub.get_subscription_count() >= 1)
    stack.feed(0, 100)
    assert h.spin_until(lambda: summaries.any("experiment recommended: dither on u2, u3 for 60 samples (amplitudes "
                                              "0.1, 0.1; no dither service at /nosrv/mpc/start_dither)"), 10.0)
    assert monitor.core.experiment.phase == "idle" and summaries.latest()[1]["experiment"] == "recommended"

    h2 = harness("/refused")
    mpc = h2.add(MpcNode(context=h2.ctx, namespace=h2.ns, parameter_overrides=_overrides(
        {"case": "3.2", "max_dither": 0.05})))
    monitor = _monitor(h2, lambda m, d, o: fake_report(m, RECOMMENDED))
    summaries = Summaries(h2)
    stack = Stack(h2, model, monitor)
    assert h2.spin_until(lambda: monitor._dither_client.service_is_ready()
                         and all(p.get_subscription_count() >= 1 for p in stack.pubs.values()))
    stack.feed(0, 100)
    assert h2.spin_until(lambda: summaries.any("(amplitudes 0.1, 0.1; refused by /refused/mpc/start_dither: "
                                               "u2: amplitude 0.1 above max_dither 0.05 (input units); not before "
                                               "sample 10100 (experiment_cooldown))"), 10.0)
    assert mpc.experiment is None and monitor.core.experiment.phase == "refused"
    stack.feed(100, 200)
    assert h2.spin_until(lambda: analysed(monitor, 3), 10.0)
    assert monitor.core.experiment.phase == "refused"   # not asked again (cooldown)

    h3 = harness("/off")
    monitor = _monitor(h3, lambda m, d, o: fake_report(m, RECOMMENDED), auto_experiment=False)
    summaries = Summaries(h3)
    stack = Stack(h3, model, monitor)
    assert h3.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in stack.pubs.values() if p.topic_name
                                     != "/off/dither") and monitor._diag_pub.get_subscription_count() >= 1)
    assert monitor._dither_client is None
    stack.feed(0, 100)
    assert h3.spin_until(lambda: summaries.any("experiment recommended: dither on u2, u3 for 60 samples (amplitudes "
                                               "0.1, 0.1; auto_experiment is false)"), 10.0)


# ------------------------------------------------------------------------------ acceptance
#: The fat plant: 2 outputs, 4 inputs; the controller's model has the gain of (y1, u4) 60 % too high.
FAT_PLANT = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3", "u4"), outputs=("y1", "y2"),
                       gain=[[1.0, 0.6, 0.8, 0.5], [0.4, 1.2, 0.5, 0.9]],
                       time_constant=[[10, 15, 12, 20], [14, 10, 18, 12]], delay=[[1, 2, 1, 3], [2, 1, 2, 1]],
                       name="fat plant")
FAT_MODEL = FAT_PLANT.replace(gain=[[1.0, 0.6, 0.8, 0.8], [0.4, 1.2, 0.5, 0.9]], name="fat model, (y1, u4) off")


def test_acceptance_a_fat_plant_goes_from_ambiguous_to_an_experiment_to_the_exact_element(tmp_path):
    ctx = private_context()
    ns = "/fat"
    plant_file, model_file = str(tmp_path / "plant.yaml"), str(tmp_path / "model.yaml")
    save_model(FAT_PLANT, plant_file)
    save_model(FAT_MODEL, model_file)
    analyses, input_std = [], []

    def analyze(model, data, options):
        report = real_analyze(model, data, options)      # the real pipeline, with its own experiment
        analyses.append((float(data.t[0]), float(data.t[-1]), report))
        input_std.append(data.u.std(axis=0))
        return report

    # The experiment (capped to fit the window: 3000 - END_MARGIN samples) starts once an analysis has
    # recommended it: after the first (1500 samples), or a later one when the analysis, which runs beside
    # the lock-step simulation, lags it. Once it has started, the run is cut to end 5 samples after it.
    samples = 20000
    params = {
        "plant": {"model_file": plant_file, "seed": 3, "max_samples": samples, "clock_topic": "clock"},
        "setpoint": {"model_file": model_file, "mode": "prbs", "seed": 3, "amplitude": 1.0,
                     "switch_probability": 0.05, "clock_topic": "clock"},
        "mpc": {"model_file": model_file, "prediction_horizon": 60, "control_horizon": 15, "max_dither": 0.2,
                "max_dither_samples": 5000, "seed": 3},
        "monitor": {"model_file": model_file, "window_samples": 3000, "min_samples": 1500, "analysis_period": 1000,
                    "auto_experiment": True, "repair": False, "diagnostics_topic": "diagnostics",
                    "stale_timeout": 600.0, "republish_period": 0.2},
    }
    suite = Suite(ctx, params, namespace=ns, analyze=analyze)
    listener = Node("listener", context=ctx, namespace=ns)
    summaries, dither = [], []
    listener.create_subscription(DiagnosticArray, "diagnostics", lambda m: summaries.extend(
        (s.message, {kv.key: kv.value for kv in s.values}) for s in m.status if s.name == SUMMARY_NAME),
        diagnostics_qos())
    codec = VectorCodec(FAT_MODEL.inputs, "dither")
    listener.create_subscription(JointState, "dither", lambda m: dither.append(codec.decode(m)), vector_qos())
    suite.add_node(listener)
    try:
        suite.start(diagnostics_listeners=1)
        assert suite.spin_until(lambda: dither or suite.plant.finished, 120.0) and dither, "no experiment started"
        samples = int(dither[0][0] / NS) + suite.monitor.core.experiment.current.samples + 5
        assert suite.plant.k < samples
        suite.plant.params["max_samples"] = suite.samples = samples
        assert suite.run(timeout=240.0), f"the suite stopped at sample {suite.plant.k}"
        assert suite.spin_until(lambda: suite.monitor.core.experiment.phase == "done", 10.0)
        # 1. ambiguous: the first analysis flags row y1 but cannot tell its inputs apart, and recommends the experiment
        first = analyses[0][2]
        assert analyses[0][:2] == (0.0, 1499.0)
        assert first.flagged_rows == ["y1"] and first.located_elements == []
        assert {e.input for e in first.elements if e.output == "y1" and e.ambiguous} == {"u1", "u2", "u3", "u4"}
        # the core's own recommendation: the controller moves the 4 inputs in 2 directions, so 2 inputs are
        # dithered, each within half its std in the window, for more samples than the window holds
        exp = first.experiment
        assert exp is not None and len(exp.dither) == 2 and exp.expected_detectable_gain_change <= 0.2
        assert all(0 < a <= 0.5 * input_std[0][FAT_MODEL.inputs.index(k)] + 1e-3 for k, a in exp.dither.items())
        assert exp.samples > 3000
        assert exp.why.startswith("the closed loop moves u1, u2, u3, u4 together")
        # 2. the experiment: one call, the dither on the recommended inputs for its samples, then the zero vector
        rec = suite.monitor.core.experiment.current
        assert rec.samples == 3000 - END_MARGIN and set(rec.inputs) == set(exp.dither)  # capped to fit the window
        assert suite.mpc.experiments == 1 and suite.monitor.core.experiment.started == 1
        assert len(dither) == rec.samples + 1 and not np.any(dither[-1][1])
        on = [FAT_MODEL.inputs[j] for j in np.flatnonzero(dither[0][1])]
        assert tuple(on) == rec.inputs
        start, end = dither[0][0] / NS, dither[-2][0] / NS
        assert 1500 <= start and end == start + rec.samples - 1
        assert any(m.startswith("mismatch in row(s) y1; elements not located") and
                   f"experiment running: dither on {', '.join(rec.inputs)} ({rec.amplitudes_text()}; " in m
                   for m, _ in summaries)
        # 3. the analysis of the window that includes the experiment locates exactly the mismatched element
        t0, t1, after = next(a for a in analyses if a[0] <= start and a[1] >= end)
        assert t1 <= end + END_MARGIN     # taken as soon as the experiment ended, not at the next analysis_period
        assert after.flagged_rows == ["y1"] and after.located_elements == [("y1", "u4")]
        assert not any(e.ambiguous for e in after.elements)
        # and every later window holding it says the same, on /diagnostics too
        assert all(r.located_elements == [("y1", "u4")] for a, b, r in analyses if a <= start and b >= end)
        assert suite.spin_until(lambda: summaries and summaries[-1][1].get("located_elements") == "y1:u4"
                                and summaries[-1][1].get("window_end") == repr(float(samples - 1)), 10.0)
        # (a window of 3000 samples holds the 2990 samples of the experiment only when it ends within 10 after it)
        assert any(f"this analysis includes the experiment: dither on {', '.join(rec.inputs)} for {rec.samples} "
                   f"samples (t = {start:g}-{end:g} s)" in m and v.get("located_elements") == "y1:u4"
                   for m, v in summaries)
    finally:
        suite.close()
        ctx.try_shutdown()
