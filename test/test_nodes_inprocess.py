"""The four nodes in one process and one executor, in simulated time (lock-step), isolated.

Isolation: every test builds its own ``rclpy`` context with ``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``
(:func:`mpm_monitor.apps.demo.private_context`), so its nodes see each other and nothing else, and puts
its nodes in a namespace of its own.

Acceptance (issue 4): within 3000 samples of simulated time the monitor's ``/diagnostics`` locate
exactly rows y1, y2 and elements (y1, u2), (y1, u3), (y2, u1) in paper case 3.2 and flag nothing in
case 3.1; a plain publisher of the contract topics gets the same answer as ``analyze`` on the same
samples.  Issue 5 (monitor): the diagnostics carry the suggested repair, and the
``~/write_repaired_model`` service (std_srvs/Trigger) writes the repaired model to the file of the
``repaired_model_file`` parameter, or answers ``success`` false with the reason.
"""

import os
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(180)   # above the run's own 120 s, so that a slow run fails with its message

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from mpm_monitor.apps.demo import Suite, case_parameters, private_context  # noqa: E402
from mpm_monitor.core.analysis import AnalysisOptions  # noqa: E402
from mpm_monitor.core.errors import ConfigurationError  # noqa: E402
from mpm_monitor.core.pipeline import analyze  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME, row_status_name  # noqa: E402
from mpm_monitor.nodes.ros_io import VectorCodec, diagnostics_qos, make_executor, spin_until, vector_qos  # noqa: E402
from mpm_monitor.sim.cases import paper_case  # noqa: E402
from mpm_monitor.sim.closed_loop import run_closed_loop  # noqa: E402

#: Samples of simulated time within which the monitor must have located the mismatch.
SAMPLES = 3000


class DiagnosticsListener:
    """Keeps the last DiagnosticArray received on a topic."""

    def __init__(self, context, namespace, topic="diagnostics"):
        self.node = Node("diag_listener", context=context, namespace=namespace)
        self.latest = None
        self.count = 0
        self.node.create_subscription(DiagnosticArray, topic, self._on, diagnostics_qos())

    def _on(self, msg):
        self.latest = msg
        self.count += 1

    def statuses(self):
        return {s.name: (s, {kv.key: kv.value for kv in s.values}) for s in self.latest.status}

    def summary_value(self, key):
        if self.latest is None:
            return None
        return self.statuses().get(SUMMARY_NAME, (None, {}))[1].get(key)


def located(listener, outputs):
    """(flagged rows, located elements, levels) read back from the published statuses."""
    st = listener.statuses()
    rows, elements, levels = [], [], {}
    for o in outputs:
        s, v = st[row_status_name(o)]
        levels[o] = s.level
        if v["mismatch"] == "true":
            rows.append(o)
        elements += [(o, i) for i in v["flagged_inputs"].split(",") if i]
    return rows, elements, levels


def run_suite(case, namespace, samples=SAMPLES):
    """Run the lock-step suite for ``samples`` samples; return (suite, listener, seconds)."""
    ctx = private_context()
    params = case_parameters(case, seed=1)
    params["plant"]["max_samples"] = samples
    # one analysis of the whole window, on the last sample; topics relative to the namespace; the data
    # stop with the run, so the statuses must not age to STALE while the last analysis runs
    params["monitor"].update(window_samples=samples, min_samples=samples, analysis_period=samples,
                             diagnostics_topic="diagnostics", stale_timeout=120.0)
    params["plant"]["clock_topic"] = "clock"
    params["setpoint"]["clock_topic"] = "clock"
    suite = Suite(ctx, params, namespace=namespace)
    listener = DiagnosticsListener(ctx, namespace)
    listener.rsi = []
    listener.node.create_subscription(Float64MultiArray, "mpm_monitor/rsi", lambda m: listener.rsi.append(list(m.data)),
                                      diagnostics_qos())
    suite.add_node(listener.node)
    t0 = time.monotonic()
    suite.start(diagnostics_listeners=1)
    assert suite.run(timeout=120.0), f"the suite stopped at sample {suite.plant.k}"
    final = suite.monitor.core.latest_outcome.job.seq
    assert suite.spin_until(lambda: listener.summary_value("analyses") == str(final)
                            and listener.summary_value("window_end") == repr(float(samples - 1)), 10.0)
    return suite, listener, time.monotonic() - t0


@pytest.fixture
def suites():
    made = []
    yield made
    for suite in made:
        suite.close()
        suite.context.try_shutdown()


def test_case_3_2_located_exactly_through_the_nodes_and_equal_to_the_batch_run(suites):
    case = paper_case("3.2")
    suite, listener, seconds = run_suite("3.2", "/t32")
    suites.append(suite)
    rows, elements, levels = located(listener, case.model.outputs)
    assert rows == ["y1", "y2"]
    assert sorted(elements) == [("y1", "u2"), ("y1", "u3"), ("y2", "u1")]
    assert levels == {"y1": DiagnosticStatus.WARN, "y2": DiagnosticStatus.WARN, "y3": DiagnosticStatus.OK}
    summary, values = listener.statuses()[SUMMARY_NAME]
    assert summary.level == DiagnosticStatus.WARN
    assert values["located_elements"] == "y1:u2,y1:u3,y2:u1"
    assert values["completed_samples"] == str(SAMPLES) and values["missing_samples"] == "0"
    assert seconds < 60.0
    # lock-step through DDS reproduces the batch closed loop with the same seed, sample for sample
    log = run_closed_loop(case.plant, case.model, SAMPLES, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    data = suite.monitor.core.latest_outcome.job.data
    np.testing.assert_array_equal(data.t, log.t)
    np.testing.assert_allclose(data.r, log.r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.u, log.u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.y, log.y, rtol=0, atol=1e-12)
    rsi = np.array([float(listener.statuses()[row_status_name(o)][1]["rsi"]) for o in case.model.outputs])
    assert rsi[0] > 1.2 and rsi[1] > 1.1 and abs(rsi[2] - 1.0) < 0.05
    # the suggested repair reaches /diagnostics (the monitor repairs by default)
    assert values["repair_changes"] == "3" and values["repair_validation"] == "passed"
    y1 = listener.statuses()[row_status_name("y1")][1]
    assert y1["repair"].startswith("u2: ") and "u3: gain 3.5->" in y1["repair"]
    assert y1["kind u3"] == "gain" and float(y1["error_after"]) < 0.5 * float(y1["error_before"])
    # the numeric RSI topic carries the same values, in model output order
    assert suite.spin_until(lambda: len(listener.rsi) >= 1, 5.0)
    np.testing.assert_array_equal(listener.rsi[-1], rsi)


def test_case_3_1_flags_nothing(suites):
    suite, listener, seconds = run_suite("3.1", "/t31")
    suites.append(suite)
    rows, elements, levels = located(listener, paper_case("3.1").model.outputs)
    assert rows == [] and elements == []
    assert set(levels.values()) == {DiagnosticStatus.OK}
    assert listener.statuses()[SUMMARY_NAME][0].level == DiagnosticStatus.OK
    assert seconds < 60.0


def _monitor(ctx, namespace, **params):
    from mpm_monitor.apps.demo import _overrides
    from mpm_monitor.nodes.monitor_node import MonitorNode

    p = {"case": "3.2", "diagnostics_topic": "diagnostics"}
    p.update(params)
    return MonitorNode(context=ctx, namespace=namespace, parameter_overrides=_overrides(p))


def _plain_publisher(ctx, namespace, monitor, name):
    """A bare publisher node of the three contract topics, a diagnostics listener and an executor that holds them
    and ``monitor``: ``(node, {topic: publisher}, listener, executor)``."""
    pub_node = Node(name, context=ctx, namespace=namespace)
    pubs = {t: pub_node.create_publisher(JointState, t, vector_qos()) for t in ("setpoint", "input", "output")}
    listener = DiagnosticsListener(ctx, namespace)
    ex = make_executor(ctx)
    for nd in (monitor, pub_node, listener.node):
        ex.add_node(nd)
    return pub_node, pubs, listener, ex


def test_a_plain_publisher_gets_the_same_answer_as_analyze():
    """No plant or MPC node: a bare rclpy publisher replays a batch log on the contract topics."""
    case = paper_case("3.2")
    n = 2000
    log = run_closed_loop(case.plant, case.model, n, seed=7, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    expected = analyze(case.model, log.as_logged_data(), AnalysisOptions(repair=False))
    ctx = private_context()
    ns = "/plain"
    monitor = _monitor(ctx, ns, window_samples=n, min_samples=n, analysis_period=n, analysis_niceness=3)
    pub_node, pubs, listener, ex = _plain_publisher(ctx, ns, monitor, "plain_publisher")
    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values())
                          and monitor._diag_pub.get_subscription_count() >= 1, 20.0)
        y_codec = VectorCodec(case.model.outputs, "output")
        u_codec = VectorCodec(tuple(reversed(case.model.inputs)), "input")  # channels in another order
        chunk = 100
        for start in range(0, n, chunk):
            for k in range(start, min(n, start + chunk)):
                stamp = k * 1_000_000_000
                # an arbitrary interleaving of the three topics, as a real stack would give
                order = [("output", y_codec, log.y[k]), ("input", u_codec, log.u[k][::-1]),
                         ("setpoint", y_codec, log.r[k])]
                for topic, codec, v in (order if k % 2 else order[::-1]):
                    pubs[topic].publish(codec.encode(v, stamp))
            done = min(n, start + chunk)
            assert spin_until(ex, lambda: monitor.core.window.n_completed >= done, 20.0)
        assert spin_until(ex, lambda: listener.summary_value("analyses") == "1", 60.0)
        rows, elements, _ = located(listener, case.model.outputs)
        assert rows == expected.flagged_rows
        assert sorted(elements) == sorted(expected.located_elements)
        st = listener.statuses()
        for r in expected.rows:
            v = st[row_status_name(r.output)][1]
            assert float(v["rsi"]) == pytest.approx(r.rsi, rel=1e-9)
            assert float(v["p_value"]) == pytest.approx(r.p_value, rel=1e-6, abs=1e-300)
        assert st[SUMMARY_NAME][1]["missing_samples"] == "0"
        # The analysis ran in the monitor's child process, at the niceness asked for above the monitor's.
        (child,) = monitor._process_analyzer._pool._processes
        assert os.getpriority(os.PRIO_PROCESS, child) == min(os.getpriority(os.PRIO_PROCESS, 0) + 3, 19)
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node, listener.node)


def test_with_split_gap_the_monitor_keeps_its_window_across_a_burst_and_answers_as_analyze():
    """A plain publisher that loses a burst of 30 samples (longer than max_gap 10): with the parameter split_gap
    the monitor keeps the samples on both sides and its answer is that of ``analyze`` on the same samples."""
    case = paper_case("3.2")
    n, burst = 2000, range(1000, 1030)
    log = run_closed_loop(case.plant, case.model, n, seed=7, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    kept = np.setdiff1d(np.arange(n), list(burst))
    expected = analyze(case.model, log.as_logged_data().take(kept), AnalysisOptions(repair=False))
    assert expected.gaps["longest"] == 30
    ctx = private_context()
    ns = "/burst"
    monitor = _monitor(ctx, ns, window_samples=n, min_samples=kept.size, analysis_period=kept.size, split_gap=100)
    pub_node, pubs, listener, ex = _plain_publisher(ctx, ns, monitor, "burst_publisher")
    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values())
                          and monitor._diag_pub.get_subscription_count() >= 1, 20.0)
        y_codec, u_codec = VectorCodec(case.model.outputs, "output"), VectorCodec(case.model.inputs, "input")
        for i, k in enumerate(kept):
            stamp = int(k) * 1_000_000_000
            for topic, codec, v in (("setpoint", y_codec, log.r[k]), ("input", u_codec, log.u[k]),
                                    ("output", y_codec, log.y[k])):
                pubs[topic].publish(codec.encode(v, stamp))
            if i % 100 == 99 or i == kept.size - 1:
                assert spin_until(ex, lambda: monitor.core.window.n_completed >= i + 1, 20.0)
        assert spin_until(ex, lambda: listener.summary_value("analyses") == "1", 60.0)
        rows, elements, _ = located(listener, case.model.outputs)
        assert rows == expected.flagged_rows and sorted(elements) == sorted(expected.located_elements)
        summary, values = listener.statuses()[SUMMARY_NAME]
        assert values["missing_samples"] == "30" and values["window_gaps"] == "1" and monitor.core.window.health().resets == 0
        assert f"{kept.size} samples up to t = {n - 1} s, 30 lost in 1 gap" in summary.message
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node, listener.node)


def test_bad_messages_give_error_then_stale_when_data_stop():
    ctx = private_context()
    ns = "/bad"
    monitor = _monitor(ctx, ns, window_samples=100, min_samples=50, analysis_period=50, stale_timeout=0.5,
                       republish_period=0.1)
    pub_node = Node("bad_publisher", context=ctx, namespace=ns)
    out_pub = pub_node.create_publisher(JointState, "output", vector_qos())
    listener = DiagnosticsListener(ctx, ns)
    ex = make_executor(ctx)
    for nd in (monitor, pub_node, listener.node):
        ex.add_node(nd)
    try:
        assert spin_until(ex, lambda: out_pub.get_subscription_count() >= 1
                          and monitor._diag_pub.get_subscription_count() >= 1, 20.0)
        msg = JointState(name=["y1", "y2", "flow"], position=[1.0, 2.0, 3.0])
        out_pub.publish(msg)

        def error_seen():
            return (listener.latest is not None
                    and listener.statuses()[SUMMARY_NAME][0].level == DiagnosticStatus.ERROR)

        assert spin_until(ex, error_seen, 5.0)
        summary = listener.statuses()[SUMMARY_NAME][0]
        assert "missing 'y3'" in summary.message and "unexpected 'flow'" in summary.message

        def all_stale():
            return listener.latest is not None and all(s.level == DiagnosticStatus.STALE for s in listener.latest.status)

        assert spin_until(ex, all_stale, 5.0)
        assert len(listener.latest.status) == 4
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node, listener.node)


def test_a_bad_parameter_is_refused_with_its_name():
    ctx = private_context()
    try:
        with pytest.raises(ConfigurationError, match="min_samples"):
            _monitor(ctx, "/param", window_samples=100, min_samples=500)
        with pytest.raises(ConfigurationError, match="window_samples") as refused:
            _monitor(ctx, "/param2", window_samples=3)
        # rclpy's exception appends ": window_samples" to its message; the line names it once, first
        assert str(refused.value).startswith("parameter window_samples: ")
        assert str(refused.value).endswith("value: 3")
    finally:
        ctx.try_shutdown()


def test_a_parameter_the_node_does_not_have_is_named_in_a_warning(capfd):
    """rclpy ignores a parameter the node does not declare (a misspelt name in a params file): the node
    warns of each, one line, with the closest of its own names; those it has are not named."""
    from mpm_monitor.nodes.ros_io import unknown_overrides

    ctx = private_context()
    try:
        node = _monitor(ctx, "/unknown", window=5000, analysis_perod=100, totally_unrelated=1, min_samples=500)
        try:
            assert unknown_overrides(node) == ["analysis_perod", "totally_unrelated", "window"]
        finally:
            node.close()                    # its analysis thread, which would stop later tests' forks
            node.destroy_node()
    finally:
        ctx.try_shutdown()
    err = capfd.readouterr().err
    warned = [line.split("]: ", 1)[1] for line in err.splitlines() if "is not a parameter of this node" in line]
    assert warned == [
        "parameter 'analysis_perod' is not a parameter of this node and is ignored: did you mean 'analysis_period'?",
        "parameter 'totally_unrelated' is not a parameter of this node and is ignored",
        "parameter 'window' is not a parameter of this node and is ignored: did you mean 'window_samples'?"]
    assert not [line for line in err.splitlines() if "parameters of other nodes of the suite" in line]
    assert "min_samples" not in err


def test_the_other_nodes_parameters_of_a_shared_params_file_are_named_in_one_info_line(capfd):
    """One params file for the whole launch (its ``/**`` section) gives every node the others' parameters:
    the monitor names those in one info line, not a warning each; a name no node declares still warns."""
    ctx = private_context()
    try:
        node = _monitor(ctx, "/shared", seed=3, prediction_horizon=20, topics=["a"], window_sampels=5000,
                        min_samples=500)
        try:
            assert node.has_parameter("window_samples") and not node.has_parameter("seed")
        finally:
            node.close()
            node.destroy_node()
    finally:
        ctx.try_shutdown()
    lines = [line.split("]: ", 1)[1] for line in capfd.readouterr().err.splitlines() if "]: " in line]
    assert [line for line in lines if "is not a parameter of this node" in line] == [
        "parameter 'window_sampels' is not a parameter of this node and is ignored: did you mean 'window_samples'?"]
    assert [line for line in lines if "other nodes of the suite" in line] == [
        "parameters of other nodes of the suite, ignored here (a params file's shared section): prediction_horizon "
        "(mpc), seed (plant, mpc, setpoint), topics (mpm_recorder, mpm_replay)"]


def test_an_integer_for_a_double_parameter_is_taken_as_that_double():
    """``stale_timeout: 10`` or ``output_weight: [2]`` in a params file, or ``ros2 param set`` of a live
    parameter to an integer: rclpy refuses an INTEGER for a DOUBLE parameter ("wrong type"); the nodes
    take it as the double it means."""
    from rclpy.parameter import Parameter

    from mpm_monitor.apps.demo import _overrides
    from mpm_monitor.nodes.mpc_node import MpcNode

    ctx = private_context()
    try:
        node = _monitor(ctx, "/ints", stale_timeout=10)
        mpc = MpcNode(context=ctx, namespace="/ints", parameter_overrides=_overrides(
            {"case": "3.2", "output_weight": [2, 2, 2], "max_dither": 1}))
        try:
            p = node.get_parameter("stale_timeout")
            assert p.type_ == Parameter.Type.DOUBLE and p.value == 10.0
            w = mpc.get_parameter("output_weight")
            assert w.type_ == Parameter.Type.DOUBLE_ARRAY and list(w.value) == [2.0, 2.0, 2.0]
            assert mpc.get_parameter("max_dither").value == 1.0
            # Set at run time (ros2 param set /mpc max_dither 2): a live parameter, taken as 2.0.
            (result,) = mpc.set_parameters([Parameter("max_dither", Parameter.Type.INTEGER, 2)])
            assert result.successful, result.reason
            p = mpc.get_parameter("max_dither")
            assert p.type_ == Parameter.Type.DOUBLE and p.value == 2.0
            # An integer for a read-only double is still refused, as read-only, not as the wrong type.
            (result,) = node.set_parameters([Parameter("stale_timeout", Parameter.Type.INTEGER, 3)])
            assert not result.successful and "read-only" in result.reason, result.reason
        finally:
            node.close()
            node.destroy_node()
            mpc.destroy_node()
    finally:
        ctx.try_shutdown()


def test_wall_clock_mode_runs_and_the_monitor_holds_the_setpoints(tmp_path):
    """Timer-driven plant and setpoints on the wall clock (50 Hz model), MPC and monitor holding setpoints."""
    from mpm_monitor.apps.demo import _overrides
    from mpm_monitor.core.model import PlantModel
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.mpc_node import MpcNode
    from mpm_monitor.nodes.plant_node import PlantNode
    from mpm_monitor.nodes.setpoint_node import SetpointNode

    ts = 0.02
    model = PlantModel(sample_time=ts, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=[[1.0, 0.3], [0.2, 1.0]],
                       time_constant=[[0.5, 0.6], [0.4, 0.5]], delay=[[0.04, 0.06], [0.04, 0.02]])
    path = str(tmp_path / "fast.yaml")
    save_model(model, path)
    seen = []

    def count_analysis(m, data, options):
        seen.append(data)
        from types import SimpleNamespace
        return SimpleNamespace(rows=[SimpleNamespace(output=o, rsi=1.0, mismatch=False, p_value=0.5)
                                     for o in m.outputs], elements=[], overall_rsi=1.0, warnings=[])

    ctx = private_context()
    ns = "/wall"
    kw = dict(context=ctx, namespace=ns)
    nodes = [PlantNode(parameter_overrides=_overrides({"model_file": path, "lock_step": False,
                                                        "publish_clock": False, "autostart": False}), **kw),
             SetpointNode(parameter_overrides=_overrides({"model_file": path, "trigger": "timer", "mode": "step",
                                                          "hold_samples": 20}), **kw),
             MpcNode(parameter_overrides=_overrides({"model_file": path, "hold_setpoint": True,
                                                     "prediction_horizon": 50, "control_horizon": 10}), **kw),
             MonitorNode(parameter_overrides=_overrides({"model_file": path, "hold_setpoint": True,
                                                         "window_samples": 100, "min_samples": 100,
                                                         "analysis_period": 50}),
                         analyze=count_analysis, **kw)]
    plant, setpoint, mpc, monitor = nodes
    ex = make_executor(ctx)
    for nd in nodes:
        ex.add_node(nd)
    try:
        assert spin_until(ex, lambda: plant._pub.get_subscription_count() >= 2
                          and mpc._pub.get_subscription_count() >= 2
                          and setpoint._pub.get_subscription_count() >= 2, 20.0)
        t0 = time.monotonic()
        plant.start()
        assert spin_until(ex, lambda: len(seen) >= 2, 20.0), monitor.core.window.health()
        elapsed = time.monotonic() - t0
        # real time: 150 samples of 20 ms take about 3 s (not as fast as possible)
        assert elapsed > 150 * ts * 0.8
        data = seen[-1]
        assert data.n_samples == 100
        np.testing.assert_allclose(np.diff(data.t), ts, atol=1e-6)  # on the plant nominal grid (float s of epoch time)
        assert set(np.unique(data.r)) <= {-1.0, 1.0}                   # held step setpoints
        h = monitor.core.window.health()
        assert h.off_grid == 0 and h.conflict == 0 and h.bad_value == 0
        assert h.gaps <= 1  # only the samples before the first setpoint, if any
    finally:
        monitor.close()
        close_nodes(ex, ctx, *nodes)


def test_plant_and_mpc_nodes_survive_bad_messages():
    """A bad vector is logged and ignored; the loop then runs on the good ones."""
    ctx = private_context()
    ns = "/robust"
    params = case_parameters("3.2", seed=1)
    params["plant"].update(max_samples=50, clock_topic="clock")
    params["setpoint"]["clock_topic"] = "clock"
    params["monitor"].update(window_samples=50, min_samples=50, analysis_period=50, diagnostics_topic="diagnostics")
    from types import SimpleNamespace

    suite = Suite(ctx, params, namespace=ns, analyze=lambda m, d, o: SimpleNamespace(
        rows=[], elements=[], overall_rsi=1.0, warnings=[]))
    bad = Node("bad", context=ctx, namespace=ns)
    pubs = {t: bad.create_publisher(JointState, t, vector_qos()) for t in ("input", "output", "setpoint")}
    suite.add_node(bad)
    try:
        assert suite.spin_until(lambda: all(p.get_subscription_count() >= 2 for p in pubs.values()), 20.0)
        pubs["output"].publish(JointState(name=["y1", "y2", "y3"], position=[1.0, float("nan"), 0.0]))
        pubs["setpoint"].publish(JointState(name=["y1"], position=[1.0, 2.0]))
        pubs["input"].publish(JointState(name=["u1", "u2", "u3"], position=[0.0, 0.0, 0.0]))  # plant not running
        assert suite.spin_until(lambda: suite.mpc.rejected >= 2, 5.0)
        suite.start()
        assert suite.run(timeout=30.0, final_analysis=False)
        assert suite.plant.k == 50 and suite.mpc.steps == 50
        assert suite.monitor.core.window.health().bad_value == 2
    finally:
        suite.close()
        ctx.try_shutdown()


def test_write_repaired_model_service(tmp_path):
    """The Trigger service: refused before an analysis, then the repaired model file, then a clear failure."""
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    from mpm_monitor.io.model_file import load_model

    case = paper_case("3.2")
    n = 1000
    log = run_closed_loop(case.plant, case.model, n, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    ctx = private_context()
    ns = "/srv"
    target = tmp_path / "repaired.yaml"
    monitor = _monitor(ctx, ns, window_samples=n, min_samples=n, analysis_period=n, repaired_model_file=str(target))
    other = Node("srv_client", context=ctx, namespace=ns)
    client = other.create_client(Trigger, "monitor/write_repaired_model")
    pubs = {t: other.create_publisher(JointState, t, vector_qos()) for t in ("setpoint", "input", "output")}
    ex = make_executor(ctx)
    for nd in (monitor, other):
        ex.add_node(nd)

    def call():
        future = client.call_async(Trigger.Request())
        assert spin_until(ex, future.done, 10.0)
        return future.result()

    try:
        assert spin_until(ex, lambda: client.service_is_ready()
                          and all(p.get_subscription_count() >= 1 for p in pubs.values()), 20.0)
        r = call()
        assert not r.success and r.message.startswith("no analysis yet") and not target.exists()
        y_codec, u_codec = VectorCodec(case.model.outputs, "output"), VectorCodec(case.model.inputs, "input")
        for start in range(0, n, 100):
            for k in range(start, start + 100):
                stamp = k * 1_000_000_000
                pubs["setpoint"].publish(y_codec.encode(log.r[k], stamp))
                pubs["input"].publish(u_codec.encode(log.u[k], stamp))
                pubs["output"].publish(y_codec.encode(log.y[k], stamp))
            assert spin_until(ex, lambda: monitor.core.window.n_completed >= start + 100, 20.0)
        assert spin_until(ex, lambda: monitor.results >= 1, 60.0)
        report = monitor.core.latest_report
        assert report is not None and sorted(report.located_elements) == [("y1", "u2"), ("y1", "u3"), ("y2", "u1")]
        r = call()
        assert r.success, r.message
        assert str(target) in r.message and "3 changes" in r.message
        assert load_model(target) == report.repaired_model != case.model
        # the target is fixed at start-up: nobody on the domain can point the node at another file
        res = monitor.set_parameters([Parameter("repaired_model_file", value=str(tmp_path / "elsewhere.yaml"))])
        assert not res[0].successful
        assert monitor.get_parameter("repaired_model_file").value == str(target)
        # a file that cannot be written: success false with the reason, and the node keeps serving
        monitor.params["repaired_model_file"] = str(tmp_path / "no_such_dir" / "m.yaml")
        r = call()
        assert not r.success and r.message.startswith("cannot write") and "no_such_dir" in r.message
        monitor.params["repaired_model_file"] = ""
        r = call()
        assert not r.success and "repaired_model_file" in r.message
        assert sorted(p.name for p in tmp_path.iterdir()) == ["repaired.yaml"]
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, other)
