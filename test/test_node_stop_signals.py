"""SIGINT and SIGTERM while a node stops: never a ``KeyboardInterrupt`` inside rclpy, and the third ends it at once.

A terminal's Ctrl-C reaches a launcher's whole process group and the ``suite_processes`` launcher then sends
its nodes a SIGINT of its own: a node gets two.  :func:`~mpm_monitor.nodes.ros_io.run_node` gave back the
default SIGINT handler before it closed and destroyed the node, so the second raised ``KeyboardInterrupt``
there, inside rclpy's C++ code, which aborted the process (exit -6).  Here the signals come from the node
itself, at fixed points of its stop (``signal.raise_signal`` runs the handler before it returns): no timing.
"""

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def no_discovery(monkeypatch):
    pytest.importorskip("rclpy")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")


def handlers():
    return signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)


def fake_node_class():
    """A node that records its stop and sends its own process the signals it is given at each step."""
    from rclpy.node import Node

    class FakeNode(Node):
        def __init__(self, context, at, events, exit_code=None):
            super().__init__("fake_node", context=context)
            self.at = at
            self.events = events
            if exit_code is not None:           # asks to end at once: no signal stops the spin
                self.exit_requested = True
                self.exit_code = exit_code

        def send(self, step):
            for sig in self.at.get(step, ()):
                self.events.append((step, sig))
                signal.raise_signal(sig)

        def close(self):
            self.send("close")
            self.events.append("closed")

        def destroy_node(self):
            self.send("destroy_node")
            super().destroy_node()
            self.events.append("destroyed")

    return FakeNode


def run(at, exit_code=None, stop_with=None):
    """``run_node`` with a :func:`fake_node_class` node; ``stop_with``: the signal that stops its spin, sent
    as it is built (the handlers are in place then)."""
    from mpm_monitor.nodes import ros_io

    FakeNode = fake_node_class()
    events = []
    made = []

    def factory(context):
        node = FakeNode(context, at, events, exit_code)
        made.append(node)
        if stop_with is not None:
            events.append(("built", stop_with))
            signal.raise_signal(stop_with)
        return node

    try:
        code = ros_io.run_node(factory, ["fake_node"])
    except KeyboardInterrupt:
        pytest.fail(f"a KeyboardInterrupt got out of run_node (in the process, raised inside rclpy: an abort); "
                    f"{events}")
    return code, events, made


@pytest.mark.parametrize("step", ["close", "destroy_node"])
@pytest.mark.parametrize("stop_with", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_second_signal_while_the_node_stops_is_taken_quietly(no_discovery, capfd, step, stop_with):
    """The group's Ctrl-C (or a SIGTERM) stops the spin; the launcher's SIGINT comes as the node closes or
    is destroyed: the stop goes on to its end and the node ends with its code, the handlers given back."""
    before = handlers()
    code, events, made = run({step: [signal.SIGINT]}, stop_with=stop_with)
    assert code == 0
    assert events[0] == ("built", stop_with) and (step, signal.SIGINT) in events
    assert [e for e in events if isinstance(e, str)] == ["closed", "destroyed"] and events[-1] == "destroyed"
    assert not made[0].context.ok()
    assert handlers() == before
    assert "interrupted" not in capfd.readouterr().err


def test_signals_while_a_node_that_asked_to_end_stops_keep_its_exit_code(no_discovery, capfd):
    """No signal stopped the spin (the node asked to end, exit code 5); one comes as it closes, one as it is
    destroyed: the second does not end it either."""
    before = handlers()
    code, events, made = run({"close": [signal.SIGINT], "destroy_node": [signal.SIGINT]}, exit_code=5)
    assert code == 5
    assert events == [("close", signal.SIGINT), "closed", ("destroy_node", signal.SIGINT), "destroyed"]
    assert not made[0].context.ok()
    assert handlers() == before
    assert "interrupted" not in capfd.readouterr().err


def test_the_third_signal_and_not_before_ends_the_stop_at_once(no_discovery, monkeypatch):
    """The stop's signal, the launcher's, then one more while the node closes: ``end_at_once`` with that signal
    (here only recorded, not ``os._exit``, so the stop goes on; the real one: the test below)."""
    from mpm_monitor.nodes import ros_io

    ended = []
    monkeypatch.setattr(ros_io, "end_at_once", ended.append)
    before = handlers()
    code, events, made = run({"close": [signal.SIGINT, signal.SIGTERM]}, stop_with=signal.SIGINT)
    assert code == 0
    assert events[:3] == [("built", signal.SIGINT), ("close", signal.SIGINT), ("close", signal.SIGTERM)]
    assert ended == [signal.SIGTERM]
    assert not made[0].context.ok()
    assert handlers() == before


HUNG_NODE = textwrap.dedent("""\
    import signal, sys, threading
    from rclpy.node import Node
    from mpm_monitor.nodes import ros_io

    THIRD = signal.{third}

    class HungNode(Node):
        def close(self):
            signal.raise_signal(signal.SIGINT)     # the launcher's SIGINT: taken quietly
            signal.raise_signal(THIRD)             # the user's next Ctrl-C: ends the process at once
            print("still closing", file=sys.stderr)
            threading.Event().wait()               # a close that hangs

    def factory(context):
        node = HungNode("fake_node", context=context)
        signal.raise_signal(signal.SIGINT)         # the Ctrl-C that stops the spin
        return node

    try:
        sys.exit(ros_io.run_node(factory, []))
    except KeyboardInterrupt:
        sys.exit("KeyboardInterrupt")
    """)


@pytest.mark.parametrize("third, code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_third_signal_ends_a_hung_stop_with_one_line(no_discovery, tmp_path, third, code):
    """The real ``os._exit``, in a process of its own whose node's ``close()`` hangs after the signals: exit code
    128 + the third signal's number and one line, no traceback."""
    script = tmp_path / "fake_node.py"
    script.write_text(HUNG_NODE.format(third=third), encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run([sys.executable, str(script)], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == code, done.stderr
    assert done.stderr == "fake_node: interrupted while stopping\n"
