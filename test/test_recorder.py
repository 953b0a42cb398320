"""Recorder node (issue 6): every message intact and in order, QoS as offered, nothing lost on SIGINT/SIGTERM.

Loss bound under test: on SIGINT or SIGTERM the recorder closes the bag properly and keeps every
message it received; in particular every message up to the last flush it reported before the
signal.  Only messages still in transit when it stopped may be missing, and then only at the end:
the bag holds a gap-free prefix of what was published.  After SIGKILL the bag is not closed, but
``recover_bag`` gets back every message up to the last flush (at most ``flush_period`` of data
lost).
"""

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from contextlib import closing

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from ros_domains import unique_domain  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from mpm_monitor.apps.demo import private_context  # noqa: E402
from mpm_monitor.core.errors import InputError  # noqa: E402
from mpm_monitor.core.model import PlantModel  # noqa: E402
from mpm_monitor.io.bags import read_bag, read_diagnostics, recover_bag  # noqa: E402
from mpm_monitor.nodes.recorder_node import RecorderNode, parse_topic_specs  # noqa: E402
from mpm_monitor.nodes.ros_io import spin_until  # noqa: E402

VECTOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
MODEL = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=np.ones((2, 2)),
                   time_constant=np.ones((2, 2)), delay=np.zeros((2, 2)))
TYPES = {"/setpoint": JointState, "/input": JointState, "/output": JointState, "/diagnostics": DiagnosticArray,
         "/mpm_monitor/rsi": Float64MultiArray, "/clock": Clock}


def _vector(k, names, offset):
    m = JointState()
    m.header.stamp.sec = k
    m.name = list(names)
    m.position = [offset + k + 0.25 * j for j in range(len(names))]
    return m


def _diag(k):
    arr = DiagnosticArray()
    arr.header.stamp.sec = k
    st = DiagnosticStatus(level=DiagnosticStatus.WARN if k % 2 else DiagnosticStatus.OK,
                          name="mpm_monitor: row y1", message=f"sample {k}", hardware_id="mpm")
    st.values = [KeyValue(key="rsi", value=f"{1 + k / 100:.3f}"), KeyValue(key="mismatch", value="false")]
    arr.status = [st]
    return arr


def _messages(n):
    """Per sample k, what the loop publishes: r, u, y, rsi, diagnostics, clock."""
    for k in range(n):
        rsi = Float64MultiArray()
        rsi.data = [1.0 + k, 2.0]
        clock = Clock()
        clock.clock.sec = k
        yield k, [("/clock", clock), ("/output", _vector(k, ("y1", "y2"), 0.0)),
                  ("/setpoint", _vector(k, ("y1", "y2"), 100.0)), ("/input", _vector(k, ("u1", "u2"), -50.0)),
                  ("/mpm_monitor/rsi", rsi), ("/diagnostics", _diag(k))]


@pytest.fixture
def ctx():
    context = private_context()
    yield context
    context.try_shutdown()


def test_records_every_message_intact_and_in_order(ctx, tmp_path):
    bag = tmp_path / "bag"
    rec = RecorderNode(bag_dir=bag, context=ctx, flush_period=0.05)
    pub_node = rclpy.create_node("loop", context=ctx)
    clock_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {t: pub_node.create_publisher(cls, t.lstrip("/"), clock_qos if t == "/clock" else VECTOR_QOS)
            for t, cls in TYPES.items()}
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(rec)
    ex.add_node(pub_node)
    assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 10)
    n = 150
    sent = {t: [] for t in TYPES}
    for k, batch in _messages(n):
        for topic, msg in batch:
            pubs[topic].publish(msg)
            sent[topic].append(msg)
        ex.spin_once(timeout_sec=0)
    assert spin_until(ex, lambda: rec.message_count >= 6 * n, 10), rec.message_count
    assert rec.flushed_count > 0  # flushed while recording, before close
    assert rec.close() == 6 * n
    rec.destroy_node()
    pub_node.destroy_node()

    got = {t: [] for t in TYPES}
    with AnyReader([bag]) as reader:
        assert {c.topic for c in reader.connections} == set(TYPES)
        for conn, _, raw in reader.messages():
            got[conn.topic].append(deserialize_message(bytes(raw), TYPES[conn.topic]))
            reader.deserialize(raw, conn.msgtype)  # rosbags decodes every message too
    for topic in TYPES:
        assert got[topic] == sent[topic], topic

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["message_count"] == 6 * n
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
           for t in meta["topics_with_message_count"]}
    assert qos["/output"][0]["reliability"] == "reliable" and qos["/output"][0]["durability"] == "volatile"

    data = read_bag(bag, MODEL)
    assert data.n_samples == n
    np.testing.assert_array_equal(data.y[:, 1], np.arange(n) + 0.25)
    diags = read_diagnostics(bag)
    assert [d.level for d in diags] == [k % 2 for k in range(n)]
    assert diags[7].values == {"rsi": "1.070", "mismatch": "false"}


def test_best_effort_publisher_qos_is_recorded(ctx, tmp_path):
    bag = tmp_path / "bag"
    rec = RecorderNode(bag_dir=bag, context=ctx, topics=["/clock"], flush_period=0.05)
    pub_node = rclpy.create_node("sim", context=ctx)
    pub = pub_node.create_publisher(Clock, "/clock", QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(rec)
    ex.add_node(pub_node)
    # the recorder subscribed reliably before the publisher existed; it re-subscribes best effort
    assert spin_until(ex, lambda: pub.get_subscription_count() >= 1, 10)
    for k in range(20):
        pub.publish(Clock())
        ex.spin_once(timeout_sec=0.01)
    assert spin_until(ex, lambda: rec.message_count > 0, 5)
    rec.close()
    rec.destroy_node()
    pub_node.destroy_node()
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    (topic,) = meta["topics_with_message_count"]
    assert topic["topic_metadata"]["offered_qos_profiles"][0]["reliability"] == "best_effort"


def test_bad_parameters_are_refused(ctx, tmp_path):
    with pytest.raises(InputError, match="topics: entry 'foo': unknown topic"):
        parse_topic_specs(["foo"])
    assert parse_topic_specs(["foo=std_msgs/msg/String"]) == (("foo", "std_msgs/msg/String"),)
    (tmp_path / "exists").mkdir()
    with pytest.raises(InputError, match="exists already"):
        RecorderNode(bag_dir=tmp_path / "exists", context=ctx)
    with pytest.raises(InputError, match=r"flush_period: .*out of range"):
        RecorderNode(bag_dir=tmp_path / "new", context=ctx, node_name="r2", flush_period=0.0)


def test_one_topic_under_two_names_is_refused_and_no_bag_is_left(ctx, tmp_path):
    """Stop 73's audit: [clock, /clock] recorded every message twice, and a type not installed left a bag of
    43 bytes behind, so that the corrected command found its bag_dir existing."""
    for k, (topics, match) in enumerate([
            (["clock", "/clock"], "topics: clock and /clock are the same topic /clock: expected each topic once"),
            (["output", "/output=sensor_msgs/msg/JointState"], "topics: output and /output are the same topic"),
            (["output", "x=foo_msgs/msg/Bar"], "message type foo_msgs/msg/Bar is not installed")]):
        bag = tmp_path / f"bag{k}"
        with pytest.raises(InputError, match=match):
            RecorderNode(bag_dir=bag, topics=topics, context=ctx, node_name=f"dup{k}")
        assert not bag.exists()


def test_recorder_process_refuses_a_bad_parameter_in_one_line(tmp_path):
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="OFF")
    res = subprocess.run([sys.executable, "-m", "mpm_monitor.nodes.recorder_node", "--ros-args", "-p",
                          f"bag_dir:={tmp_path / 'bag'}", "-p", "flush_period:=0.0"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.startswith("error: parameter flush_period: ") and "out of range" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not (tmp_path / "bag").exists()


# --- kill test: the recorder as a process ----------------------------------------------------------------


class _Lines(threading.Thread):
    """Collects a stream's lines and the flush counts the recorder reports."""

    def __init__(self, stream):
        super().__init__(daemon=True)
        self.stream, self.lines, self.flushed = stream, [], 0

    def run(self):
        for line in iter(self.stream.readline, ""):
            self.lines.append(line)
            m = re.search(r"flushed (\d+) messages", line)
            if m:
                self.flushed = max(self.flushed, int(m.group(1)))


def _run_and_signal(tmp_path, monkeypatch, signum, extra=(), ready=None):
    """Record /output from a publisher in this process; signal the recorder once it reported a
    flush of at least 200 messages (and ``ready(lines)`` holds for its log lines, if given), keep publishing
    100 more, and wait for it to end.

    Runs on a ROS_DOMAIN_ID no other test process holds.  ``extra``: more ``-p name:=value`` arguments of the
    recorder.  Returns (bag dir, exit code, flushed count reported before the signal, messages published,
    recorder log).
    """
    with unique_domain(salt=int(signum)) as domain:
        return _record_and_signal(tmp_path, monkeypatch, signum, domain, extra, ready)


@contextlib.contextmanager
def _recorder_and_publisher(monkeypatch, domain, ros_args, preexec_fn=None):
    """The recorder as a process (``--ros-args`` ``ros_args``) on ``domain``, and a publisher of ``output`` in this
    process that it has matched: yields ``(process, publisher, log)``, ``log`` the process's stderr lines
    (:class:`_Lines`).  The process is killed if it still runs at the end."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "mpm_monitor.nodes.recorder_node", "--ros-args", *ros_args],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=preexec_fn)
    log = _Lines(proc.stderr)
    log.start()
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = Context()
    try:
        rclpy.init(context=context, domain_id=domain)
        node = rclpy.create_node("plant", context=context)
        pub = node.create_publisher(JointState, "output", VECTOR_QOS)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() < 1:
            assert time.monotonic() < deadline and proc.poll() is None, "".join(log.lines)
            time.sleep(0.02)
        yield proc, pub, log
    finally:
        if proc.poll() is None:
            proc.kill()
        rclpy.try_shutdown(context=context)
    log.join(timeout=5)


def _record_and_signal(tmp_path, monkeypatch, signum, domain, extra=(), ready=None):
    bag = tmp_path / "bag"
    args = ["-p", f"bag_dir:={bag}", "-p", "flush_period:=0.1", *[a for value in extra for a in ("-p", value)],
            "--log-level", "mpm_recorder:=debug"]
    with _recorder_and_publisher(monkeypatch, domain, args) as (proc, pub, log):
        k, flushed_at_signal, signalled_at = 0, None, None
        deadline = time.monotonic() + 20
        while signalled_at is None or k < signalled_at + 100:
            assert time.monotonic() < deadline, "".join(log.lines)
            pub.publish(_vector(k, ("y1", "y2"), 0.0))
            k += 1
            if signalled_at is None and log.flushed >= 200 and (ready is None or ready(list(log.lines))):
                flushed_at_signal = log.flushed
                proc.send_signal(signum)
                signalled_at = k
            time.sleep(0.002)
        rc = proc.wait(timeout=15)
    return bag, rc, flushed_at_signal, k, "".join(log.lines)


def _stamps(bag):
    with closing(AnyReader([bag])) as reader:
        reader.open()
        return [reader.deserialize(raw, c.msgtype).header.stamp.sec for c, _, raw in reader.messages()]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_mid_run_keeps_everything_up_to_the_last_flush(tmp_path, monkeypatch, signum):
    bag, rc, flushed, published, log = _run_and_signal(tmp_path, monkeypatch, signum)
    assert rc == 0, log
    stamps = _stamps(bag)
    # a gap-free prefix of what was published, holding at least everything flushed before the signal
    assert stamps == list(range(len(stamps)))
    assert flushed <= len(stamps) <= published


def test_sigkill_loses_at_most_what_was_not_flushed(tmp_path, monkeypatch):
    bag, rc, flushed, published, log = _run_and_signal(tmp_path, monkeypatch, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    with pytest.raises(InputError, match="no metadata.yaml"):
        read_bag(bag, MODEL)
    n = recover_bag(bag, tmp_path / "recovered")
    stamps = _stamps(tmp_path / "recovered")
    assert len(stamps) == n and stamps == list(range(n))
    assert flushed <= n <= published


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGKILL])
def test_a_split_recording_stopped_or_killed_keeps_its_messages_in_order(tmp_path, monkeypatch, signum):
    """``max_bag_size``: the recorder goes on in a new storage file at the first flush past the size, and says so.
    Stopped, the bag reads whole (every file, in order); killed, ``recover`` reads every file."""
    def third_file_flushed(lines):
        """bag_1 closed and a flush after it: bag_2 holds messages on disk (a slow first flush can pass 200
        messages in one file, so the count alone does not make three files)."""
        closed = [k for k, line in enumerate(lines) if "closed storage file bag_1.mcap" in line]
        return bool(closed) and any("flushed" in line for line in lines[closed[0] + 1:])

    bag, rc, flushed, published, log = _run_and_signal(tmp_path, monkeypatch, signum, extra=("max_bag_size:=4000",),
                                                       ready=third_file_flushed)
    files = sorted(f.name for f in bag.glob("*.mcap"))
    assert len(files) >= 3, (files, log)
    assert "a new storage file after 4,000 bytes" in log and "closed storage file bag_0.mcap" in log, log
    if signum == signal.SIGKILL:
        assert rc == -signal.SIGKILL
        n = recover_bag(bag, tmp_path / "recovered")
        stamps = _stamps(tmp_path / "recovered")
        assert len(stamps) == n and stamps == list(range(n)) and flushed <= n <= published
    else:
        assert rc == 0, log
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["relative_file_paths"] == [f"bag_{k}.mcap" for k in range(len(files))]
        stamps = _stamps(bag)
        assert stamps == list(range(len(stamps))) and flushed <= len(stamps) <= published
        assert meta["message_count"] == len(stamps)
        assert not [f for f in bag.iterdir() if f.is_dir()]     # the files' directories while written, removed


def test_a_bad_split_limit_is_refused(ctx, tmp_path):
    from rclpy.parameter import Parameter

    with pytest.raises(InputError, match=r"max_bag_size: .*out of range"):
        RecorderNode(bag_dir=tmp_path / "a", context=ctx, node_name="r3",
                     parameter_overrides=[Parameter("max_bag_size", value=-1)])
    with pytest.raises(InputError, match=r"max_bag_duration: .*out of range"):
        RecorderNode(bag_dir=tmp_path / "b", context=ctx, node_name="r4",
                     parameter_overrides=[Parameter("max_bag_duration", value=-1.0)])
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_bag_that_cannot_be_written_stops_the_recorder_with_one_error(ctx, tmp_path, monkeypatch):
    """A full disk (here, a flush that raises ENOSPC): the flush timer raised from its callback, and the node ended in
    a traceback.  It now says so once, stops taking messages and asks to end with exit code 1; close() does not
    raise."""
    import errno

    from mpm_monitor.io.bags import BagWriter

    rec = RecorderNode(bag_dir=tmp_path / "bag", context=ctx, topics=["output"], flush_period=0.05)
    pub_node = rclpy.create_node("plant_full", context=ctx)
    pub = pub_node.create_publisher(JointState, "output", VECTOR_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(rec)
    ex.add_node(pub_node)
    assert spin_until(ex, lambda: pub.get_subscription_count() >= 1, 10)
    for k in range(20):
        pub.publish(_vector(k, ("y1", "y2"), 0.0))
    assert spin_until(ex, lambda: rec.flushed_count >= 20, 10), rec.flushed_count

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(BagWriter, "flush", full)
    for k in range(20, 40):
        pub.publish(_vector(k, ("y1", "y2"), 0.0))
    assert spin_until(ex, lambda: rec.exit_requested, 10)
    assert rec.exit_code == 1 and rec.failure == f"cannot write the bag {tmp_path / 'bag'}: No space left on device"
    received = rec.message_count
    pub.publish(_vector(40, ("y1", "y2"), 0.0))
    ex.spin_once(timeout_sec=0.2)
    assert rec.message_count == received                    # no message is taken once the bag cannot be written
    monkeypatch.undo()
    rec.close()                                             # the bag closes if the disk allows it now
    rec.destroy_node()
    pub_node.destroy_node()
    assert _stamps(tmp_path / "bag")[:20] == list(range(20))


def test_the_recorder_process_ends_with_one_error_when_its_file_cannot_grow(tmp_path, monkeypatch):
    """The recorder as a process whose files may not grow past 1 MB (RLIMIT_FSIZE: writes fail with EFBIG, as on a
    full disk): one error line, exit code 1, no traceback; what was flushed before is recovered."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, 1_000_000))

    bag = tmp_path / "bag"
    args = ["-p", f"bag_dir:={bag}", "-p", "flush_period:=0.05", "-p", "topics:=[output]"]
    with unique_domain(salt=77) as domain:
        with _recorder_and_publisher(monkeypatch, domain, args, preexec_fn=limit) as (proc, pub, log):
            k, names = 0, [f"y{j}" for j in range(40)]       # about 1 kB a message: 0.5 MB/s
            while proc.poll() is None and k < 5000:
                pub.publish(_vector(k, names, 0.0))
                k += 1
                time.sleep(0.002)
            rc = proc.wait(timeout=20)
    err = "".join(log.lines)
    assert rc == 1, err
    assert "Traceback" not in err and err.count("cannot write the bag") == 1, err
    assert "File too large: recording stopped;" in err and "python -m mpm_monitor recover" in err, err
    n = recover_bag(bag, tmp_path / "back")
    stamps = _stamps(tmp_path / "back")
    assert 0 < n == len(stamps) and stamps == list(range(n))
