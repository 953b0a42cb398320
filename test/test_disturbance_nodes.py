"""Measured disturbances through the ROS 2 nodes, in one process, in simulated lock-step time, isolated.

- The level case (an integrating level and a measured inflow on both outputs) through the plant,
  MPC, setpoint and monitor nodes: the monitor locates exactly the wrong inflow gain on the
  temperature (role ``disturbance``) and the wrong outflow integrator gain on the level (role
  ``input``), and the samples are those of the batch closed loop with the same seed, ``dv``
  included (the plant node generates the disturbance and publishes it on ``disturbance``).
- The MPC node waits for ``dv(k)`` before it answers ``y(k)``, and its feedforward is the batch
  controller's.
- The monitor reads the disturbance topic named by its parameter; the demo records it to a bag
  that ``read_bag`` and the replay node read back.
"""

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(180)

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import Suite, _overrides, case_parameters, private_context, run_demo  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME, row_status_name  # noqa: E402
from mpm_monitor.nodes.ros_io import (  # noqa: E402
    VectorCodec,
    diagnostics_qos,
    make_executor,
    spin_until,
    vector_qos,
)
from mpm_monitor.sim.cases import level_case  # noqa: E402
from mpm_monitor.sim.closed_loop import run_closed_loop  # noqa: E402
from mpm_monitor.sim.mpc import InternalModelMpc  # noqa: E402

SAMPLES = 3000


def test_level_case_located_live_with_roles_and_equal_to_the_batch_run():
    """The suite of the demo on the level case; the statuses are read from /diagnostics as published."""
    import time

    case = level_case()
    ctx = private_context()
    ns = "/tlevel"
    params = case_parameters("level", seed=1)
    params["plant"].update(max_samples=SAMPLES, clock_topic="clock")
    params["setpoint"]["clock_topic"] = "clock"
    # one analysis of the whole window, on the last sample; the statuses must not age to STALE meanwhile
    params["monitor"].update(window_samples=SAMPLES, min_samples=SAMPLES, analysis_period=SAMPLES,
                             diagnostics_topic="diagnostics", stale_timeout=120.0)
    suite = Suite(ctx, params, namespace=ns)
    try:
        listener = Node("diag_listener", context=ctx, namespace=ns)
        latest = []
        listener.create_subscription(DiagnosticArray, "diagnostics", latest.append, diagnostics_qos())
        suite.add_node(listener)
        t0 = time.monotonic()
        suite.start(diagnostics_listeners=1)
        assert suite.run(timeout=150.0), f"the suite stopped at sample {suite.plant.k}"
        seconds = time.monotonic() - t0

        def statuses():
            return {s.name: (s, {kv.key: kv.value for kv in s.values}) for s in latest[-1].status}

        def final_published():
            summary = statuses()[SUMMARY_NAME][1] if latest else {}
            return summary.get("window_end") == repr(SAMPLES - 1.0) and summary.get("analyses") == "1"

        assert suite.spin_until(final_published, 10.0)
        st = statuses()
        rows = [o for o in case.model.outputs if st[row_status_name(o)][1]["mismatch"] == "true"]
        elements = [(o, c) for o in case.model.outputs
                    for c in st[row_status_name(o)][1]["flagged_inputs"].split(",") if c]
        assert rows == ["temperature", "level"]
        assert sorted(elements) == [("level", "outflow"), ("temperature", "inflow")]
        values = st[SUMMARY_NAME][1]
        assert values["located_elements"] == "temperature:inflow,level:outflow"
        assert values["completed_samples"] == str(SAMPLES) and values["missing_samples"] == "0"
        report = suite.monitor.core.latest_report
        roles = {(e.output, e.input): e.role for e in report.elements if e.mismatch}
        assert roles == {("temperature", "inflow"): "disturbance", ("level", "outflow"): "input"}
        # lock-step through DDS reproduces the batch closed loop with the same seed, dv included
        log = run_closed_loop(case.plant, case.model, SAMPLES, seed=1, mpc=case.mpc, excitation=case.excitation,
                              disturbance=case.disturbance, measured_disturbance=case.measured_disturbance)
        data = suite.monitor.core.latest_outcome.job.data
        assert data.disturbances == ("inflow",)
        np.testing.assert_array_equal(data.t, log.t)
        for key in ("r", "u", "y", "dv"):
            np.testing.assert_allclose(getattr(data, key), getattr(log, key), rtol=0, atol=1e-12, err_msg=key)
        assert np.std(data.dv) > 0.2
        assert seconds < 90.0
    finally:
        suite.close()
        ctx.try_shutdown()


def _level_model_file(tmp_path, which="model"):
    from mpm_monitor.io.model_file import save_model

    case = level_case()
    path = str(tmp_path / f"{which}.yaml")
    save_model(case.model if which == "model" else case.plant, path)
    return case, path


def test_mpc_node_waits_for_dv_and_feeds_it_forward(tmp_path):
    from mpm_monitor.nodes.mpc_node import MpcNode, mpc_options_from_params

    case, path = _level_model_file(tmp_path)
    ctx = private_context()
    ns = "/ffnode"
    mpc = MpcNode(parameter_overrides=_overrides({"model_file": path, "prediction_horizon": 40,
                                                  "control_horizon": 10}), context=ctx, namespace=ns)
    other = Node("dv_publisher", context=ctx, namespace=ns)
    pubs = {t: other.create_publisher(JointState, t, vector_qos()) for t in ("setpoint", "output", "disturbance")}
    got = []
    other.create_subscription(JointState, "input", got.append, vector_qos())
    ex = make_executor(ctx)
    for nd in (mpc, other):
        ex.add_node(nd)
    ref = InternalModelMpc(case.model, mpc_options_from_params(mpc.params, 2, 2))
    y_codec = VectorCodec(case.model.outputs, "y")
    d_codec = VectorCodec(case.model.disturbances, "dv")
    u_codec = VectorCodec(case.model.inputs, "u")
    rng = np.random.default_rng(3)
    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values())
                          and mpc._pub.get_subscription_count() >= 1, 20.0)
        expected = []
        for k in range(5):
            r, y, dv = rng.normal(size=2), rng.normal(size=2), rng.normal(size=1) + 1.0
            stamp = k * 1_000_000_000
            pubs["setpoint"].publish(y_codec.encode(r, stamp))
            pubs["output"].publish(y_codec.encode(y, stamp))
            spin_until(ex, lambda: False, 0.3)
            assert len(got) == k and mpc.steps == k          # y(k) and r(k) wait for dv(k)
            pubs["disturbance"].publish(d_codec.encode(dv, stamp))
            assert spin_until(ex, lambda: len(got) == k + 1, 5.0)
            expected.append(ref.step(r, y, dv=dv))
        for k, msg in enumerate(got):
            stamp, u = u_codec.decode(msg)
            assert stamp == k * 1_000_000_000
            np.testing.assert_allclose(u, expected[k], rtol=0, atol=1e-12)
        # the feedforward acts: the same loop without dv would move otherwise
        blind = InternalModelMpc(case.model, mpc_options_from_params(mpc.params, 2, 2))
        assert np.abs(blind.step(np.zeros(2), np.zeros(2), dv=[0.0]) - expected[0]).max() > 1e-6
        # a dv re-sent for the stamp already answered is not a second sample
        pubs["disturbance"].publish(d_codec.encode([1.0], 4 * 1_000_000_000))
        assert spin_until(ex, lambda: mpc.repeated >= 1, 5.0)
        assert mpc.steps == 5 and len(got) == 5
    finally:
        close_nodes(ex, ctx, mpc, other)


def test_plant_node_publishes_dv_and_the_monitor_reads_its_named_topic(tmp_path):
    """The plant node publishes the generated dv with y's stamp on its disturbance_topic; a monitor
    listening on that (renamed) topic completes its samples with it."""
    from types import SimpleNamespace

    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.plant_node import PlantNode
    from mpm_monitor.sim.closed_loop import seeded_generators
    from mpm_monitor.sim.excitation import MeasuredDisturbanceGenerator

    case, path = _level_model_file(tmp_path, "plant")
    ctx = private_context()
    ns = "/dvtopic"
    plant = PlantNode(parameter_overrides=_overrides({"model_file": path, "autostart": False, "seed": 4,
                                                      "disturbance_topic": "inflow_dv", "clock_topic": "clock",
                                                      "max_samples": 20, "dv_step_amplitude": 2.0,
                                                      "dv_switch_probability": 0.2, "dv_min_hold": 2}),
                      context=ctx, namespace=ns)
    monitor = MonitorNode(parameter_overrides=_overrides({"model_file": path, "disturbance_topic": "inflow_dv",
                                                          "window_samples": 20, "min_samples": 10,
                                                          "analysis_period": 10}),
                          analyze=lambda m, d, o: SimpleNamespace(rows=[], elements=[], overall_rsi=1.0, warnings=[]),
                          context=ctx, namespace=ns)
    feeder = Node("feeder", context=ctx, namespace=ns)      # stands in for the MPC and the setpoint node
    u_pub = feeder.create_publisher(JointState, "input", vector_qos())
    r_pub = feeder.create_publisher(JointState, "setpoint", vector_qos())
    y_codec, u_codec = VectorCodec(case.plant.outputs, "setpoint"), VectorCodec(case.plant.inputs, "input")
    state = {"k": 0}

    def on_output(msg):
        stamp, _ = y_codec.decode(msg)
        r_pub.publish(y_codec.encode(np.zeros(2), stamp))
        u_pub.publish(u_codec.encode(np.zeros(2), stamp))
        state["k"] += 1

    feeder.create_subscription(JointState, "output", on_output, vector_qos())
    ex = make_executor(ctx)
    for nd in (plant, monitor, feeder):
        ex.add_node(nd)
    try:
        assert spin_until(ex, lambda: plant._dv_pub.get_subscription_count() >= 1
                          and plant._pub.get_subscription_count() >= 2 and u_pub.get_subscription_count() >= 2, 20.0)
        assert plant._dv_pub.topic_name == f"{ns}/inflow_dv"
        plant.start()
        assert spin_until(ex, lambda: plant.finished and monitor.core.window.n_completed >= 20, 20.0)
        data = monitor.core.window.data()
        gen = MeasuredDisturbanceGenerator(1, case.measured_disturbance.__class__(
            step_amplitude=2.0, switch_probability=0.2, min_hold=2), seeded_generators(4)["measured_disturbance"])
        np.testing.assert_array_equal(data.dv, gen.generate(20))
        assert len(np.unique(data.dv)) > 3
    finally:
        monitor.close()
        close_nodes(ex, ctx, plant, monitor, feeder)


def test_demo_level_records_the_disturbance_topic_and_the_replay_replays_it(tmp_path):
    import io

    from mpm_monitor.io.bags import read_bag
    from mpm_monitor.nodes.replay_node import ReplayNode

    case = level_case()
    out = io.StringIO()
    assert run_demo(case="level", samples=300, bag=str(tmp_path / "bag"), quiet=True, out=out) == 0
    text = out.getvalue()
    assert "300 samples through the nodes" in text and "0 dropped" in text
    data = read_bag(tmp_path / "bag", case.model)
    log = run_closed_loop(case.plant, case.model, 300, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance, measured_disturbance=case.measured_disturbance)
    np.testing.assert_allclose(data.dv, log.dv, rtol=0, atol=0)
    np.testing.assert_allclose(data.y, log.y, rtol=0, atol=1e-12)
    # the replay publishes the disturbance topic too (it is in the bag), with the three others
    ctx = private_context()
    try:
        listener = Node("listener", context=ctx)
        got = {t: 0 for t in ("setpoint", "input", "output", "disturbance")}
        for t in got:
            listener.create_subscription(JointState, t, lambda m, t=t: got.__setitem__(t, got[t] + 1), vector_qos())
        rep = ReplayNode(bag=tmp_path / "bag", context=ctx, rate=1000.0, wait_for_subscribers=1)
        assert set(rep._replay_pubs) == {"/setpoint", "/input", "/output", "/disturbance"}
        ex = make_executor(ctx, "single")
        ex.add_node(listener)
        ex.add_node(rep)
        assert spin_until(ex, lambda: all(v == 300 for v in got.values()), 30.0), got
        ex.remove_node(rep)
        rep.destroy_node()
        none = ReplayNode(bag=tmp_path / "bag", context=ctx, disturbance_topic="", node_name="r2")
        assert set(none._replay_pubs) == {"/setpoint", "/input", "/output"}
        none.destroy_node()
        ex.shutdown()
    finally:
        ctx.try_shutdown()
