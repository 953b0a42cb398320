"""Replay node (issue 6): a bag's contract topics published at a rate factor or in lock step with /clock."""

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import private_context  # noqa: E402
from mpm_monitor.core.errors import InputError  # noqa: E402
from mpm_monitor.core.logged_data import LoggedData  # noqa: E402
from mpm_monitor.io.bags import RawMessage, write_logged_data  # noqa: E402
from mpm_monitor.nodes.replay_node import ReplayNode, ReplaySchedule  # noqa: E402
from mpm_monitor.nodes.ros_io import spin_until  # noqa: E402

QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.VOLATILE)
N = 12
TS = 0.05  # seconds per sample in the bag


def _data():
    rng = np.random.default_rng(5)
    return LoggedData(t=10.0 + TS * np.arange(N), r=rng.normal(size=(N, 2)), u=rng.normal(size=(N, 1)),
                      y=rng.normal(size=(N, 2)), inputs=("u1",), outputs=("y1", "y2"), sample_time=TS)


def _raw(topic, log_ms, stamp_ms):
    return RawMessage(topic, "sensor_msgs/msg/JointState", log_ms * 10**6, stamp_ms * 10**6, b"")


def test_schedule_time_mode_scales_recorded_times():
    msgs = [_raw("/output", 1000, 0), _raw("/input", 1010, 0), _raw("/output", 2000, 1000)]
    s = ReplaySchedule(msgs, "time", rate=10.0)
    assert s.due_by_elapsed(0) == msgs[:1]
    assert s.due_by_elapsed(0.5e6) == []          # 1 ms: /input is due at 10 ms / 10
    assert s.due_by_elapsed(1e6) == msgs[1:2]
    assert s.due_by_elapsed(99e6) == [] and not s.finished
    assert s.due_by_elapsed(100e6) == msgs[2:] and s.finished


def test_schedule_clock_mode_releases_by_stamp_in_topic_order():
    msgs = [_raw("/output", 5, 1000), _raw("/setpoint", 1, 0), _raw("/output", 2, 0), _raw("/input", 3, 0)]
    s = ReplaySchedule(msgs, "clock", topic_order=["/setpoint", "/input", "/output"])
    assert [m.topic for m in s.due_by_clock(999 * 10**6)] == ["/setpoint", "/input", "/output"]
    assert s.due_by_clock(999 * 10**6) == []
    assert s.due_by_clock(1000 * 10**6) == msgs[:1] and s.finished


@pytest.fixture
def ctx():
    context = private_context()
    yield context
    context.try_shutdown()


def _listener(ctx):
    node = rclpy.create_node("listener", context=ctx)
    got = []
    for topic in ("setpoint", "input", "output"):
        node.create_subscription(JointState, topic, lambda m, t=topic: got.append((t, m)), QOS)
    return node, got


def test_replay_faster_than_recorded(ctx, tmp_path):
    data = _data()
    write_logged_data(tmp_path / "bag", data)  # log times = stamps: N samples over 0.55 s
    listener, got = _listener(ctx)
    rep = ReplayNode(bag=tmp_path / "bag", context=ctx, rate=5.0, wait_for_subscribers=1)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(listener)
    ex.add_node(rep)
    start = time.monotonic()
    assert spin_until(ex, lambda: len(got) == 3 * N, 10), len(got)
    elapsed = time.monotonic() - start
    assert rep.finished and rep.published == 3 * N
    assert elapsed >= (N - 1) * TS / 5.0 * 0.9  # not faster than asked
    y = np.array([m.position for t, m in got if t == "output"])
    np.testing.assert_array_equal(y, data.y)
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for t, m in got if t == "input"]
    np.testing.assert_allclose(stamps, data.t, atol=1e-9)
    rep.destroy_node()
    listener.destroy_node()


def test_replay_in_lock_step_with_clock(ctx, tmp_path):
    data = _data()
    write_logged_data(tmp_path / "bag", data)
    listener, got = _listener(ctx)
    rep = ReplayNode(bag=tmp_path / "bag", context=ctx, mode="clock")
    driver = rclpy.create_node("sim", context=ctx)
    clock_pub = driver.create_publisher(Clock, "/clock", 10)
    ex = SingleThreadedExecutor(context=ctx)
    for n in (listener, rep, driver):
        ex.add_node(n)
    assert spin_until(ex, lambda: clock_pub.get_subscription_count() >= 1, 5)
    for k_last in (-1, 3, 7, N - 1):
        t = 10.0 + TS * k_last + 0.01  # just after sample k_last
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = int(t), int(round((t - int(t)) * 1e9))
        clock_pub.publish(msg)
        want = 3 * (k_last + 1)
        assert spin_until(ex, lambda: len(got) >= want, 5)
        spin_until(ex, lambda: False, 0.05)  # nothing beyond the clock may come
        assert len(got) == want
    # within a sample, setpoint, input and output go out in that order
    assert [t for t, _ in got[:3]] == ["setpoint", "input", "output"]
    assert rep.finished
    for n in (listener, rep, driver):
        n.destroy_node()


def test_replay_waits_for_its_readers_acknowledgements_once_every_message_is_out(ctx, tmp_path, monkeypatch):
    from mpm_monitor.nodes import ros_io

    write_logged_data(tmp_path / "bag", _data())
    listener, got = _listener(ctx)
    rep = ReplayNode(bag=tmp_path / "bag", context=ctx, rate=50.0, wait_for_subscribers=1,
                     parameter_overrides=[rclpy.parameter.Parameter("exit_ack_timeout", value=4.5)])
    calls = []
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: calls.append(
        (sorted(p.topic_name for p in pubs), timeout)) or [])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(listener)
    ex.add_node(rep)
    rep.drain(ex)                                   # not finished (stopped by a signal): no wait
    assert calls == []
    assert spin_until(ex, lambda: rep.finished, 10)
    rep.drain(ex)
    assert calls == [(["/input", "/output", "/setpoint"], 4.5)]
    rep.destroy_node()
    listener.destroy_node()


def test_replay_says_which_readers_had_not_acknowledged_everything(ctx, tmp_path, monkeypatch, capfd):
    """The wait is the plant's and the MPC's (:func:`~mpm_monitor.nodes.ros_io.wait_for_readers`): readers late after
    ``exit_ack_timeout`` s (its /clock publisher waited for too) make one warning naming their topics and the time."""
    from mpm_monitor.nodes import ros_io

    write_logged_data(tmp_path / "bag", _data())
    listener, got = _listener(ctx)
    rep = ReplayNode(bag=tmp_path / "bag", context=ctx, rate=50.0, wait_for_subscribers=1, publish_clock=True,
                     parameter_overrides=[rclpy.parameter.Parameter("exit_ack_timeout", value=4.5)])
    calls = []
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: calls.append(
        ([p.topic_name for p in pubs], timeout)) or ["/clock", "/output"])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(listener)
    ex.add_node(rep)
    assert spin_until(ex, lambda: rep.finished, 10)
    rep.drain(ex)
    assert calls == [(["/setpoint", "/input", "/output", "/clock"], 4.5)]
    rep.destroy_node()
    listener.destroy_node()
    warnings = [line.split("]: ", 1)[1] for line in capfd.readouterr().err.splitlines() if line.startswith("[WARN]")]
    assert warnings == ["leaving after 4.5 s with messages not acknowledged on /clock, /output: a reader may lack "
                        "the last ones sent"]


def test_bad_replay_parameters(ctx, tmp_path):
    with pytest.raises(InputError, match="no such bag directory"):
        ReplayNode(bag=tmp_path / "missing", context=ctx)
    write_logged_data(tmp_path / "bag", _data())
    with pytest.raises(InputError, match="mode: expected one of time, clock"):
        ReplayNode(bag=tmp_path / "bag", context=ctx, mode="fast", node_name="r2")
    with pytest.raises(InputError, match="rate: .*out of range"):
        ReplayNode(bag=tmp_path / "bag", context=ctx, rate=0.0, node_name="r3")
    with pytest.raises(InputError, match="exit_ack_timeout: .*out of range"):
        ReplayNode(bag=tmp_path / "bag", context=ctx, node_name="r4",
                   parameter_overrides=[rclpy.parameter.Parameter("exit_ack_timeout", value=-1.0)])


def _replay_process(args, tmp_path):
    import os
    import subprocess
    import sys

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="OFF")
    return subprocess.run([sys.executable, "-m", "mpm_monitor.nodes.replay_node", "--ros-args", *args], env=env,
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)


def test_replay_process_ends_by_itself_once_every_message_is_out(tmp_path):
    write_logged_data(tmp_path / "bag", _data())
    res = _replay_process(["-p", f"bag:={tmp_path / 'bag'}", "-p", "rate:=100.0"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert f"replay finished: {3 * N} messages" in res.stderr


def test_replay_process_refuses_a_bad_parameter_in_one_line(tmp_path):
    write_logged_data(tmp_path / "bag", _data())
    res = _replay_process(["-p", f"bag:={tmp_path / 'bag'}", "-p", "rate:=0.0"], tmp_path)
    assert res.returncode == 2
    assert res.stderr.startswith("error: parameter rate: ") and "out of range" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
