"""Fault injection (issue 7, item 3): kill and restart each node while the others run.

The suite runs in wall-clock time, as beside a real plant: the plant node samples on a 50 Hz timer
and holds the last input when none comes, the setpoint node publishes on its own timer, the MPC and
the monitor hold the latest setpoint.  All nodes share one private context and one
SingleThreadedExecutor; a node is "killed" by removing it from the executor and destroying it (its
publishers and subscriptions disappear from the graph, as when its process dies) and restarted by
building it again with the same name and parameters.

What must happen (checked from the monitor's published ``/diagnostics`` and its window):

* MPC down: the inputs stop, the summary turns STALE naming the input topic; when the MPC is back
  the missing samples are reported as a gap and the analysis windows hold only samples after it;
* plant down and restarted: STALE naming the output; the new plant's stamps start a new sample grid,
  which the monitor reports as a restart, continuing with a fresh window;
* setpoint node down: with held setpoints nothing is lost (the loop and the monitor hold the last
  setpoint);
* monitor restarted: the new monitor starts with a fresh window and publishes statuses again;
* recorder restarted: the first bag holds every message the first recorder received (closed
  properly, readable), the second recorder records on.

Every analysis window the monitor hands over is checked: equally spaced on one grid, never spanning
a gap.

Two process-level faults complete the set: the monitor as its own process on a unique
``ROS_DOMAIN_ID`` (``LOCALHOST`` discovery) is SIGKILLed while the stack publishes and started
again (fresh window, analyses again; then the stack pauses: STALE, and a gap on resuming), and a
SIGKILLed monitor leaves no analysis process behind.
"""

import time

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.node import Node  # noqa: E402

from mpm_monitor.apps.demo import _overrides, private_context  # noqa: E402
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.model_file import save_model  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME  # noqa: E402
from mpm_monitor.nodes.ros_io import diagnostics_qos, make_executor, spin_until  # noqa: E402

TS = 0.02
NS = 1_000_000_000
MODEL = PlantModel(sample_time=TS, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=[[1.0, 0.3], [0.2, 1.0]],
                   time_constant=[[0.5, 0.6], [0.4, 0.5]], delay=[[0.04, 0.06], [0.04, 0.02]])
#: Seconds a killed node stays down (30 samples).
OUTAGE = 0.6


class Windows:
    """Injected analysis: records every window, checks it, returns a no-mismatch report."""

    def __init__(self):
        self.seen = []

    def __call__(self, model, data, options):
        from types import SimpleNamespace

        np.testing.assert_allclose(np.diff(data.t), model.sample_time, rtol=0, atol=1e-6)
        assert np.all(np.isfinite(data.y)) and np.all(np.isfinite(data.u))
        self.seen.append(data)
        return SimpleNamespace(rows=[SimpleNamespace(output=o, rsi=1.0, mismatch=False, p_value=0.5)
                                     for o in model.outputs], elements=[], overall_rsi=1.0, warnings=[])


class Listener:
    """Every DiagnosticArray the monitor publishes, with the arrival time."""

    def __init__(self, ctx, ns):
        self.node = Node("diag_listener", context=ctx, namespace=ns)
        self.arrays = []
        self.node.create_subscription(DiagnosticArray, "diagnostics",
                                      lambda m: self.arrays.append((time.monotonic(), m)), diagnostics_qos())

    def summaries(self, since=0.0):
        return [(t, s) for t, m in self.arrays if t >= since for s in m.status if s.name == SUMMARY_NAME]

    def latest_summary(self):
        s = self.summaries()
        return (s[-1][1], {kv.key: kv.value for kv in s[-1][1].values}) if s else (None, {})


class WallSuite:
    """Plant, setpoint, MPC and monitor on the wall clock in one executor; nodes can be killed."""

    NS = "/faults"

    def __init__(self, tmp_path):
        self.model_file = str(tmp_path / "model.yaml")
        save_model(MODEL, self.model_file)
        self.ctx = private_context()
        self.ex = make_executor(self.ctx, "single")
        self.windows = Windows()
        self.params = {
            "plant": {"model_file": self.model_file, "lock_step": False, "publish_clock": False, "autostart": False,
                      "min_subscribers": 0, "start_delay": 0.0},
            "setpoint": {"model_file": self.model_file, "trigger": "timer", "mode": "step", "hold_samples": 20},
            "mpc": {"model_file": self.model_file, "hold_setpoint": True, "prediction_horizon": 50,
                    "control_horizon": 10},
            "monitor": {"model_file": self.model_file, "hold_setpoint": True, "window_samples": 100,
                        "min_samples": 40, "analysis_period": 20, "stale_timeout": 0.3, "republish_period": 0.05,
                        "diagnostics_topic": "diagnostics", "analysis_thread": False},
        }
        self.nodes = {}
        for name in ("plant", "setpoint", "mpc", "monitor"):
            self.start_node(name)
        self.listener = Listener(self.ctx, self.NS)
        self.ex.add_node(self.listener.node)

    def build(self, name):
        from mpm_monitor.nodes.monitor_node import MonitorNode
        from mpm_monitor.nodes.mpc_node import MpcNode
        from mpm_monitor.nodes.plant_node import PlantNode
        from mpm_monitor.nodes.setpoint_node import SetpointNode

        cls = {"plant": PlantNode, "setpoint": SetpointNode, "mpc": MpcNode, "monitor": MonitorNode}[name]
        kw = dict(context=self.ctx, namespace=self.NS, parameter_overrides=_overrides(self.params[name]))
        if name == "monitor":
            kw["analyze"] = self.windows
        return cls(**kw)

    def start_node(self, name):
        node = self.build(name)
        self.nodes[name] = node
        self.ex.add_node(node)
        return node

    def kill(self, name):
        node = self.nodes.pop(name)
        self.ex.remove_node(node)
        if name == "monitor":
            node.close()
        node.destroy_node()

    @property
    def monitor(self):
        return self.nodes["monitor"]

    def spin(self, seconds):
        end = time.monotonic() + seconds
        spin_until(self.ex, lambda: time.monotonic() >= end, seconds + 5.0, step=0.01)

    def spin_until(self, cond, timeout):
        return spin_until(self.ex, cond, timeout, step=0.01)

    def start(self):
        """Wait for discovery, start the plant and run until the monitor has analysed once."""
        plant, mpc, sp = self.nodes["plant"], self.nodes["mpc"], self.nodes["setpoint"]
        assert self.spin_until(lambda: plant._pub.get_subscription_count() >= 2 and mpc._pub.get_subscription_count() >= 2
                               and sp._pub.get_subscription_count() >= 2
                               and self.monitor._diag_pub.get_subscription_count() >= 1, 20.0)
        plant.start()
        assert self.spin_until(lambda: len(self.windows.seen) >= 1, 20.0), self.monitor.core.window.health()

    def close(self):
        for name in list(self.nodes):
            self.kill(name)
        self.ex.remove_node(self.listener.node)
        self.listener.node.destroy_node()
        self.ex.shutdown()
        self.ctx.try_shutdown()


@pytest.fixture
def suite(tmp_path):
    s = WallSuite(tmp_path)
    yield s
    s.close()


def _ok_after(suite, t0, timeout=10.0):
    """Spin until a fresh analysis and an OK summary came after t0."""
    n0 = len(suite.windows.seen)

    def ok():
        s, _ = suite.listener.latest_summary()
        return (len(suite.windows.seen) > n0 and s is not None and suite.listener.arrays[-1][0] > t0
                and s.level == DiagnosticStatus.OK)
    return suite.spin_until(ok, timeout)


def _ages(message):
    """{'setpoint': seconds, ...} from a STALE message ("... last setpoint 0.1 s ago, input 0.5 s ago, ...")."""
    import re

    return {ch: float(a) for ch, a in re.findall(r"(setpoint|input|output) ([0-9.]+) s ago", message)}


def _stale_seen(suite, since, *topics_silent):
    """STALE summaries after ``since`` whose silent topics (no vector for 0.25 s) are ``topics_silent``."""
    out = []
    for _, s in suite.listener.summaries(since):
        if s.level != DiagnosticStatus.STALE:
            continue
        ages = _ages(s.message)
        silent = {ch for ch, a in ages.items() if a >= 0.25}
        if silent == set(topics_silent):
            out.append(s)
    return out


def test_mpc_killed_and_restarted_gives_stale_then_a_gap_and_fresh_windows(suite):
    suite.start()
    suite.spin(0.3)
    t_kill = time.monotonic()
    last_before = suite.monitor.core.window.last_sample_stamp_ns
    suite.kill("mpc")
    suite.spin(OUTAGE)
    assert _stale_seen(suite, t_kill, "input"), [s.message for _, s in suite.listener.summaries(t_kill)]
    suite.start_node("mpc")
    t_back = time.monotonic()
    n_windows = len(suite.windows.seen)
    assert _ok_after(suite, t_back), suite.listener.latest_summary()[0].message
    _, values = suite.listener.latest_summary()
    h = suite.monitor.core.window.health()
    assert h.gaps >= 1 and int(values["gaps"]) >= 1
    assert h.missing_samples >= int(0.8 * OUTAGE / TS)          # the outage, in samples
    assert "no input" in suite.monitor.core._recent_warnings[0] or any(
        "no input" in w for w in suite.monitor.core._recent_warnings)
    # no analysis window after the restart reaches back across the gap
    for data in suite.windows.seen[n_windows:]:
        assert data.t[0] * NS > last_before + OUTAGE * NS * 0.8


def test_plant_killed_and_restarted_gives_stale_then_a_restart_on_the_new_grid(suite):
    suite.start()
    suite.spin(0.3)
    t_kill = time.monotonic()
    last_before = suite.monitor.core.window.last_sample_stamp_ns
    suite.kill("plant")
    suite.spin(OUTAGE)
    assert _stale_seen(suite, t_kill, "output", "input")   # no y, so the MPC computes no u either
    plant = suite.start_node("plant")
    plant.start()
    t_back = time.monotonic()
    n_windows = len(suite.windows.seen)
    assert _ok_after(suite, t_back), suite.listener.latest_summary()[0].message
    h = suite.monitor.core.window.health()
    # the new plant samples on a new grid phase: a restart (or, by chance on the old phase, a gap)
    assert h.restarts + h.gaps >= 1
    for data in suite.windows.seen[n_windows:]:
        assert data.t[0] * NS > last_before + OUTAGE * NS * 0.8


def test_setpoint_node_killed_loses_nothing_with_held_setpoints(suite):
    suite.start()
    suite.spin(0.2)
    h0 = suite.monitor.core.window.health()
    suite.kill("setpoint")
    suite.spin(OUTAGE)
    suite.start_node("setpoint")
    t_back = time.monotonic()
    assert _ok_after(suite, t_back)
    h = suite.monitor.core.window.health()
    assert h.missing_samples == h0.missing_samples and h.completed > h0.completed + int(0.8 * OUTAGE / TS)
    t_kill_end = t_back - OUTAGE
    assert not [s for t, s in suite.listener.summaries(t_kill_end) if s.level == DiagnosticStatus.STALE]


def test_monitor_killed_and_restarted_starts_a_fresh_window(suite):
    suite.start()
    suite.spin(0.2)
    suite.kill("monitor")
    suite.spin(OUTAGE)
    t_back = time.monotonic()
    monitor = suite.start_node("monitor")
    first_stamp = None

    def got_sample():
        nonlocal first_stamp
        d = monitor.core.window.data()
        if d.n_samples and first_stamp is None:
            first_stamp = d.t[0]
        return first_stamp is not None

    assert suite.spin_until(got_sample, 10.0)
    n_windows = len(suite.windows.seen)
    assert _ok_after(suite, t_back)
    summary, values = suite.listener.latest_summary()
    assert int(values["completed_samples"]) < 100      # counted since the new monitor started
    for data in suite.windows.seen[n_windows:]:
        assert data.t[0] >= first_stamp - 1e-9             # nothing from before the restart


def test_recorder_restarted_loses_nothing_it_received(suite, tmp_path):
    from mpm_monitor.io.bags import read_raw_messages
    from mpm_monitor.nodes.recorder_node import RecorderNode

    topics = ["setpoint", "input", "output", "diagnostics"]
    rec1 = RecorderNode(tmp_path / "bag1", topics=topics, context=suite.ctx, namespace=WallSuite.NS,
                        flush_period=0.1, qos_wait=0.5)
    suite.ex.add_node(rec1)
    suite.start()
    suite.spin(0.5)
    # stop the first recorder mid-run (as on SIGTERM): what it received is what its bag holds
    suite.ex.remove_node(rec1)
    received = rec1.message_count
    in_bag = rec1.close()
    rec1.destroy_node()
    assert received == in_bag and received > 50
    rec2 = RecorderNode(tmp_path / "bag2", topics=topics, context=suite.ctx, namespace=WallSuite.NS,
                        flush_period=0.1, qos_wait=0.5)
    suite.ex.add_node(rec2)
    assert suite.spin_until(lambda: rec2.message_count > 50, 10.0)
    suite.ex.remove_node(rec2)
    n2 = rec2.close()
    rec2.destroy_node()
    full = [f"{WallSuite.NS}/{t}" for t in topics]
    msgs1 = read_raw_messages(tmp_path / "bag1", topics=full)
    msgs2 = read_raw_messages(tmp_path / "bag2", topics=full)
    assert len(msgs1) == in_bag and len(msgs2) == n2 > 0
    # inside the first recording the output samples are contiguous: nothing lost
    stamps = [m.stamp for m in msgs1 if m.topic == f"{WallSuite.NS}/output"]
    assert len(stamps) > 10
    np.testing.assert_allclose(np.diff(stamps), TS * NS, atol=1e3)
    # and the second recorder picked up where the loop was, not from the start
    stamps2 = [m.stamp for m in msgs2 if m.topic == f"{WallSuite.NS}/output"]
    assert stamps2 and stamps2[0] > stamps[-1]


def _children(pid):
    """PIDs whose parent is ``pid`` and whose command line is a multiprocessing spawn worker."""
    import os

    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as fh:
                cmd = fh.read()
        except OSError:
            continue
        if ppid == pid and b"spawn_main" in cmd:
            out.append(int(entry))
    return out


@pytest.mark.skipif(not __import__("os").path.isdir("/proc"), reason="needs /proc")
def test_a_monitor_killed_hard_leaves_no_analysis_process_behind(tmp_path):
    """SIGKILL of the monitor's process: its analysis process leaves by itself within a second."""
    import os
    import signal
    import subprocess
    import sys

    script = tmp_path / "analyzer_parent.py"
    script.write_text(
        "import time\n"
        "from mpm_monitor.monitor.worker import ProcessAnalyzer\n"
        "if __name__ == '__main__':\n"
        "    pa = ProcessAnalyzer(max)\n"
        "    print(pa(1, 2, 3), flush=True)\n"
        "    time.sleep(60)\n", encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "3"
        children = _children(proc.pid)
        assert children, "no analysis process found"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    deadline = time.monotonic() + 5.0
    alive = children
    while alive and time.monotonic() < deadline:
        time.sleep(0.1)
        alive = [c for c in alive if os.path.exists(f"/proc/{c}") and
                 open(f"/proc/{c}/stat").read().rsplit(")", 1)[1].split()[0] != "Z"]
    assert not alive, f"analysis process(es) {alive} outlived the monitor"


# ------------------------------------------------------------------------------ separate processes

def _unique_domain():
    """A ROS_DOMAIN_ID locked against other test processes (shared with test_nodes_multiprocess)."""
    from ros_domains import unique_domain

    return unique_domain(salt=7)


def test_monitor_process_sigkilled_and_restarted_while_the_stack_publishes(tmp_path):
    """The monitor as its own process on a unique domain (LOCALHOST): SIGKILL it while the stack
    (this test's publisher) keeps publishing, start it again: the new monitor analyses a fresh
    window.  Then the stack stops for a while: STALE, and a gap when it resumes."""
    import os
    import signal
    import subprocess
    import sys
    import threading
    from pathlib import Path

    import rclpy
    from rclpy.context import Context
    from ros_domains import close_listener, stop_process
    from sensor_msgs.msg import JointState

    from mpm_monitor.apps.demo import _env
    from mpm_monitor.nodes.ros_io import VectorCodec, vector_qos

    ts = 0.005
    model = PlantModel(sample_time=ts, inputs=("u1", "u2"), outputs=("y1", "y2"), gain=[[1.0, 0.3], [0.2, 1.0]],
                       time_constant=[[0.05, 0.05], [0.05, 0.05]], delay=[[0.005, 0.0], [0.0, 0.005]])
    model_file = tmp_path / "model.yaml"
    save_model(model, model_file)
    ns = f"/mpf{os.getpid()}"
    root = Path(__file__).resolve().parents[1]
    with _unique_domain() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        cmd = [sys.executable, "-m", "mpm_monitor.nodes.monitor_node", "--ros-args", "-r", f"__ns:={ns}",
               "-p", f"model_file:={model_file}", "-p", "window_samples:=300", "-p", "min_samples:=200",
               "-p", "analysis_period:=100", "-p", "repair:=false", "-p", "stale_timeout:=0.4",
               "-p", "republish_period:=0.1", "-p", "diagnostics_topic:=diagnostics"]
        ctx = Context()
        with _env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain)}):
            rclpy.init(args=[], context=ctx, domain_id=domain)
        node = Node("stack", context=ctx, namespace=ns)
        pubs = {c: node.create_publisher(JointState, c, vector_qos()) for c in ("setpoint", "input", "output")}
        summaries = []
        node.create_subscription(DiagnosticArray, "diagnostics",
                                 lambda m: summaries.extend((time.monotonic(), s) for s in m.status
                                                            if s.name == SUMMARY_NAME), diagnostics_qos())
        ex = make_executor(ctx, "single")
        ex.add_node(node)
        yc, uc = VectorCodec(model.outputs, "output"), VectorCodec(model.inputs, "input")
        rng = np.random.default_rng(3)
        state = {"k": 0, "run": True, "pause": False}

        def stack():
            t0 = time.monotonic()
            while state["run"]:
                k = state["k"]
                target = t0 + k * ts
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if not state["pause"]:
                    stamp = k * int(ts * NS)
                    pubs["output"].publish(yc.encode(rng.normal(size=2), stamp))
                    pubs["input"].publish(uc.encode(rng.normal(size=2), stamp))
                    pubs["setpoint"].publish(yc.encode(np.sign(rng.normal(size=2)), stamp))
                state["k"] = k + 1

        def values(s):
            return {kv.key: kv.value for kv in s.values}

        def analysed_after(t):
            return any(tt > t and s.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN)
                       and int(values(s).get("analyses", "0")) >= 1 for tt, s in summaries)

        procs = []
        thread = threading.Thread(target=stack, daemon=True)
        try:
            procs.append(subprocess.Popen(cmd, env=env, cwd=str(root), stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
            thread.start()
            assert spin_until(ex, lambda: analysed_after(0.0), 40.0), [s.message for _, s in summaries[-3:]]
            procs[0].send_signal(signal.SIGKILL)          # the monitor dies hard; the stack goes on
            procs[0].wait(10)
            t_kill = time.monotonic()
            spin_until(ex, lambda: time.monotonic() > t_kill + 0.5, 5.0)
            procs.append(subprocess.Popen(cmd, env=env, cwd=str(root), stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
            t_restart = time.monotonic()
            assert spin_until(ex, lambda: analysed_after(t_restart), 40.0), [s.message for _, s in summaries[-3:]]
            fresh = [values(s) for tt, s in summaries if tt > t_restart]
            assert int(fresh[0]["completed_samples"]) < 200      # counted from the restart, not from t = 0
            # the stack stops for a while, then resumes: STALE, then a gap
            state["pause"] = True
            t_pause = time.monotonic()
            assert spin_until(ex, lambda: any(tt > t_pause and s.level == DiagnosticStatus.STALE
                                              for tt, s in summaries), 10.0)
            state["pause"] = False
            t_resume = time.monotonic()
            assert spin_until(ex, lambda: any(tt > t_resume and int(values(s)["gaps"]) >= 1 and
                                              s.level != DiagnosticStatus.STALE for tt, s in summaries), 10.0)
            assert spin_until(ex, lambda: analysed_after(time.monotonic() - 0.05), 40.0)
        finally:
            state["run"] = False
            thread.join(5)
            for p in procs:
                stop_process(p, 10.0)
            close_listener(ex, node, ctx)
