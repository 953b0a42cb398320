"""A controller process that leaves after a divergence first lets its readers take the inputs it published.

The node stops at the sample whose ``u(k)`` no reader takes (test/test_mpc_divergence.py) and asks to end; the
process left at once, and a reader that had not yet received the last inputs lost them with it (the monitor,
which runs behind the lock-step loop).  Its ``drain`` now waits, as the plant's does, until every reliable reader
acknowledged what was sent (:func:`~mpm_monitor.nodes.ros_io.wait_for_readers`).

The controller is a process of its own, run by :func:`~mpm_monitor.nodes.ros_io.run_node` as ``mpc_node`` is; its
controller diverges at sample 5, the samples handed to it directly.  The reader is a process too, stopped
(SIGSTOP) from the moment it is matched until a second after the controller diverged: a reader behind, with no
race to win or lose.  Before the drain the controller's process ended at once and the reader, resumed, got none
of the five inputs.
"""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(180)

from ros_domains import close_nodes, stop_process, unique_domain  # noqa: E402

from bench.ros_domain import domain_env  # noqa: E402
from mpm_monitor.apps.demo import _overrides, private_context  # noqa: E402
from mpm_monitor.nodes import mpc_node, ros_io  # noqa: E402
from mpm_monitor.nodes.ros_io import make_executor  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NS = "/mpc_drain"
#: The sample whose u(k) no reader takes: u(0) .. u(DIVERGES_AT - 1) are published.
DIVERGES_AT = 5
NS_PER_S = 10**9
#: Seconds the reader stays stopped after the controller diverged.
READER_STOPPED = 1.0
#: Seconds the resumed reader waits for the inputs it lacks.
PATIENCE = 10.0
HINT = "which no reader takes; the controller stops (an unstable loop? check the model and the tuning)"

#: The reader process: "ready" once matched with the controller's publisher, then each input's stamp.
READER = textwrap.dedent("""
    import sys

    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from mpm_monitor.nodes.ros_io import make_executor, spin_until, stamp_to_ns, vector_qos

    topic, expected, patience = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    ctx = Context()
    rclpy.init(args=[], context=ctx)
    node = Node("reader", context=ctx)
    got = []

    def on_input(msg):
        got.append(stamp_to_ns(msg.header.stamp))
        print(got[-1], flush=True)

    sub = node.create_subscription(JointState, topic, on_input, vector_qos())
    ex = make_executor(ctx)
    ex.add_node(node)
    if spin_until(ex, lambda: sub.get_publisher_count() >= 1, 60.0):
        print("ready", flush=True)
        spin_until(ex, lambda: len(got) >= expected, patience)
    print("done", flush=True)
    node.destroy_node()
    ctx.try_shutdown()
""")

#: The controller process: ``mpc_node`` (run_node) whose controller diverges at sample ``at``; "matched" once its
#: input publisher has a reader, then, told "go" on stdin, the samples 0 .. at handed to it and "diverged".
CONTROLLER = textwrap.dedent("""
    import sys
    import time

    import numpy as np

    from divergence_stubs import diverging
    from mpm_monitor.apps.demo import _overrides
    from mpm_monitor.nodes import mpc_node, ros_io
    from mpm_monitor.nodes.ros_io import VectorCodec

    ns, at = sys.argv[1], int(sys.argv[2])


    def factory(context):
        node = mpc_node.MpcNode(context=context, namespace=ns, parameter_overrides=_overrides({"case": "3.1"}))
        node.ctrl.step, computed = diverging(node.ctrl.step, at, {2: 4.1e41})
        deadline = time.monotonic() + 60.0
        while node._pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        print("matched", flush=True)
        if sys.stdin.readline().strip() != "go":
            raise SystemExit(3)
        codec = VectorCodec(node.model.outputs, "output")
        for k in range(at + 1):
            node._on_vector("r", codec.encode(np.ones(codec.size), k * 10**9))
            node._on_vector("y", codec.encode(np.zeros(codec.size), k * 10**9))
        print(f"diverged {node.steps} {len(computed)} {node.exit_requested}", flush=True)
        return node


    sys.exit(ros_io.run_node(factory, ["mpc_node"]))
""")


class Lines:
    """The lines a process prints, read in a thread of their own."""

    def __init__(self, stream):
        self.lines = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in stream:
            self.lines.append(line.strip())

    def wait_for(self, prefix, timeout):
        """The first line starting with ``prefix`` within ``timeout`` s (None: none came)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hit = next((line for line in self.lines if line.startswith(prefix)), None)
            if hit is not None:
                return hit
            time.sleep(0.005)
        return None

    def join(self, timeout):
        self._thread.join(timeout)


def _start(code, *args, env, stdin=subprocess.DEVNULL):
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], cwd=Path(__file__).resolve().parent,
                            env=env, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_diverged_controller_leaves_only_once_a_reader_behind_has_its_last_inputs():
    with unique_domain(salt=41) as domain:
        env = dict(os.environ, **domain_env(domain))
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH", "")] if p])
        reader = _start(READER, f"{NS}/input", DIVERGES_AT, PATIENCE, env=env)
        mpc = _start(CONTROLLER, NS, DIVERGES_AT, env=env, stdin=subprocess.PIPE)
        read, said = Lines(reader.stdout), Lines(mpc.stdout)
        resume = threading.Timer(READER_STOPPED, lambda: reader.send_signal(signal.SIGCONT))
        try:
            assert said.wait_for("matched", 90.0) and read.wait_for("ready", 90.0), (said.lines, read.lines)
            reader.send_signal(signal.SIGSTOP)                  # behind: receives and acknowledges nothing
            mpc.stdin.write("go\n")
            mpc.stdin.flush()
            diverged = said.wait_for("diverged", 30.0)
            resumed_at = time.monotonic() + READER_STOPPED
            resume.start()
            assert diverged == f"diverged {DIVERGES_AT} {DIVERGES_AT + 1} True", said.lines
            mpc.wait(60.0)
            left_at = time.monotonic()
            reader.wait(PATIENCE + 30.0)
            read.join(5.0)
            said.join(5.0)
        finally:
            resume.cancel()
            if reader.poll() is None:
                reader.send_signal(signal.SIGCONT)
            stop_process(mpc)
            stop_process(reader)
    err = mpc.stderr.read()
    received = [int(line) for line in read.lines if line not in ("ready", "done")]
    assert received == [k * NS_PER_S for k in range(DIVERGES_AT)], (read.lines, reader.stderr.read())
    assert mpc.returncode == 1, err
    assert left_at >= resumed_at - 0.1, (left_at, resumed_at)       # it left only once the reader was back
    errors = [line.split("]: ", 1)[1] for line in err.splitlines() if line.startswith("[ERROR]")]
    assert errors == [f"the controller diverged: u3 = 4.1e+41 at t = {DIVERGES_AT} s is beyond 1e+40, {HINT}"], err
    assert "[WARN]" not in err, err


def test_the_controller_waits_for_acknowledgements_only_when_it_leaves_on_its_own(monkeypatch, capfd):
    """Stopped by a signal it leaves at once (its readers are being stopped too); diverged, it waits on its input
    publisher and the experiments' dither publisher, at most :data:`~mpm_monitor.nodes.ros_io.EXIT_ACK_TIMEOUT`
    s, and says in one warning which topics' readers had not acknowledged everything by then."""
    ctx = private_context()
    mpc = mpc_node.MpcNode(parameter_overrides=_overrides({"case": "3.1"}), context=ctx, namespace="/acks_mpc")
    calls = []
    monkeypatch.setattr(ros_io, "wait_acked", lambda pubs, timeout: calls.append(
        (sorted(p.topic_name for p in pubs), timeout)) or ["/acks_mpc/input"])
    ex = make_executor(ctx)
    ex.add_node(mpc)
    try:
        mpc.drain(ex)
        assert calls == []
        mpc._stop_diverged("the controller diverged: a test")
        mpc.drain(ex)
        assert calls == [(["/acks_mpc/dither", "/acks_mpc/input"], ros_io.EXIT_ACK_TIMEOUT)]
    finally:
        close_nodes(ex, ctx, mpc)
    warnings = [line.split("]: ", 1)[1] for line in capfd.readouterr().err.splitlines() if line.startswith("[WARN]")]
    assert warnings == ["leaving after 30 s with messages not acknowledged on /acks_mpc/input: a reader may lack "
                        "the last ones sent"]
