"""Fuzzing the live monitor (issue 7 acceptance): malformed message sequences never escape a callback.

* :func:`test_fuzz_callbacks_with_1200_malformed_sequences` drives one long-lived monitor node
  with 1,200 generated sequences (seeded generator, same sequences on every run) of
  ``sensor_msgs/JointState`` messages, calling the subscription callbacks directly (fast): wrong,
  repeated, missing, extra and unicode channel names, wrong lengths, NaN/Inf/1e308, empty messages,
  stamps out of order, duplicated, far in the future or the past (``sec`` at the int32 limits,
  ``nanosec`` beyond one second), off the grid, jumping back (publisher restarts), plus analysis
  results that fail, and the result/publish timers in between.  After every sequence the window
  handed to the analysis is checked (equally spaced, finite, each sample what was sent for its
  stamp) and every status is well formed; at the end good data bring every status back to OK.
* :func:`test_fuzz_window_with_hypothesis` does the same on the pure aligner with hypothesis.
* :func:`test_spinning_smoke_malformed_then_good` sends malformed and good messages through real
  publishers and an executor (the callbacks as ROS calls them).
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpm_monitor.monitor.statuses import ERROR, OK, STALE, SUMMARY_NAME, WARN, row_status_name
from mpm_monitor.monitor.window import SampleWindow, WindowOptions

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

NS = 1_000_000_000
OUT = ("y1", "y2")
INP = ("u1", "u2", "u3")
CHANNELS = ("setpoint", "input", "output")
NAMES = {"setpoint": OUT, "input": INP, "output": OUT}
INT32_MAX, INT32_MIN, UINT32_MAX = 2**31 - 1, -(2**31), 2**32 - 1


def true_values(channel, k):
    """What a good publisher sends for sample k (distinct per sample: a mis-alignment shows)."""
    k = float(k)
    return {"setpoint": np.array([k, -k]) + 0.1, "input": np.array([k, 2 * k, 3 * k]) + 0.2,
            "output": np.array([k, 0.5 * k]) + 0.3}[channel]


def make_msg(names, position, sec, nanosec):
    msg = JointState(name=list(names), position=[float(v) for v in position])
    msg.header.stamp = Time(sec=int(sec), nanosec=int(nanosec))
    return msg


def stamp_of(k):
    sec, nsec = divmod(int(k) * NS, NS)
    return sec, nsec


class SequenceGenerator:
    """Seeded generator of message sequences, good samples mixed with every kind of malformed one."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)
        self.k = 0          # next good sample of the current stream
        self.offset = 0     # stream start (changes on a simulated publisher restart)

    def good(self, k):
        order = list(CHANNELS)
        self.rng.shuffle(order)
        return [(ch, make_msg(NAMES[ch], true_values(ch, k - self.offset), *stamp_of(k)), "good") for ch in order]

    def bad(self):
        rng = self.rng
        ch = CHANNELS[rng.integers(3)]
        names = list(NAMES[ch])
        vals = list(true_values(ch, self.k - self.offset))
        sec, nsec = stamp_of(self.k)
        kind = rng.integers(16)
        if kind == 0:
            names = names[:-1]
            vals = vals[:-1]
        elif kind == 1:
            names = names + ["extra"]
            vals = vals + [1.0]
        elif kind == 2:
            names = [names[0]] * len(names)
        elif kind == 3:
            names = ["ÿ" + n for n in names]
        elif kind == 4:
            vals = vals[:-1]                                   # position shorter than name
        elif kind == 5:
            vals = vals + [0.0, 0.0]
        elif kind == 6:
            vals[rng.integers(len(vals))] = [math.nan, math.inf, -math.inf][rng.integers(3)]
        elif kind == 7:
            vals[rng.integers(len(vals))] = [1e308, -1.7976931348623157e308, 5e-324][rng.integers(3)]
        elif kind == 8:
            names, vals = [], []
        elif kind == 9:
            sec = int(rng.choice([INT32_MAX, INT32_MIN, 0, -1]))
        elif kind == 10:
            nsec = int(rng.integers(NS, UINT32_MAX, endpoint=True))   # nanosec beyond one second
        elif kind == 11:
            sec, nsec = stamp_of(max(self.k - int(rng.integers(1, 50)), -10))    # out of order / late
        elif kind == 12:
            nsec = int(rng.integers(1, NS // 2))                      # off the grid
        elif kind == 13:
            sec, nsec = stamp_of(self.k + int(rng.integers(2, 10**6)))  # ahead
        elif kind == 14:
            perm = rng.permutation(len(names))                    # valid: channels in another order
            names = [names[i] for i in perm]
            vals = [vals[i] for i in perm]
        else:
            vals = [v + 1.0 for v in vals]                         # a conflicting duplicate
            sec, nsec = stamp_of(max(self.k - 1, 0))
        return [(ch, make_msg(names, vals, sec, nsec), "bad")]

    def sequence(self):
        """5..40 messages: runs of good samples, malformed messages, gaps and restarts."""
        out = []
        for _ in range(self.rng.integers(2, 12)):
            r = self.rng.random()
            if r < 0.45:
                for _ in range(self.rng.integers(1, 5)):
                    out += self.good(self.k)
                    self.k += 1
            elif r < 0.85:
                out += self.bad()
            elif r < 0.93:
                self.k += int(self.rng.integers(1, 30))           # a gap: samples never sent
            else:                                                 # publisher restart: stamps jump back
                back = int(self.rng.integers(1, 500))
                self.k = max(self.k - back, 0)
                self.offset = self.k - int(self.rng.integers(0, 3))
        return out


class Analyses:
    """An injected analysis that returns a report, raises, or returns NaNs, at random (seeded)."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def __call__(self, model, data, options):
        from types import SimpleNamespace

        self.calls += 1
        # the window handed to the analysis is always clean, whatever came in
        assert data.n_samples >= 1
        np.testing.assert_allclose(np.diff(data.t), model.sample_time, rtol=0, atol=1e-9)
        for arr in (data.r, data.u, data.y):
            assert np.all(np.isfinite(arr))
        r = self.rng.random()
        if r < 0.2:
            raise np.linalg.LinAlgError("SVD did not converge")
        if r < 0.3:
            raise ValueError("multi\nline\nmessage")
        rsi = math.nan if r < 0.4 else 1.0 + r
        rows = [SimpleNamespace(output=o, rsi=rsi, mismatch=r > 0.7, p_value=1e-9 if r > 0.7 else 0.5)
                for o in model.outputs]
        elements = [SimpleNamespace(output=model.outputs[0], input=model.inputs[1], mismatch=r > 0.8,
                                    p_value=1e-12, kind="gain", ambiguous=False)]
        return SimpleNamespace(rows=rows, elements=elements, overall_rsi=rsi, warnings=["few samples"])


def check_statuses(statuses, outputs=OUT):
    assert [s.name for s in statuses] == [row_status_name(o) for o in outputs] + [SUMMARY_NAME]
    for s in statuses:
        assert s.level in (OK, WARN, ERROR, STALE)
        assert isinstance(s.message, str) and len(s.message.splitlines()) <= 1, s.message
        for k, v in s.values:
            assert isinstance(k, str) and isinstance(v, str)
        if s.name != SUMMARY_NAME:
            assert s.value("mismatch") in ("true", "false")
            float(s.value("rsi"))   # a number (or nan)


class Sent:
    """Every vector sent, by (channel, nearest sample k): what a window sample may hold."""

    def __init__(self, tolerance=0.25):
        self.tol = tolerance
        self.by_sample = {}

    def add(self, channel, stamp_ns, values):
        k = round(stamp_ns / NS)
        if abs(stamp_ns - k * NS) <= self.tol * NS:
            self.by_sample.setdefault((channel, k), []).append(np.asarray(values, dtype=float))

    def add_msg(self, channel, msg):
        self.add(channel, msg.header.stamp.sec * NS + msg.header.stamp.nanosec, msg.position)

    def check(self, data, setpoints=True, longest_gap=0):
        """Equally spaced (but for gaps of at most ``longest_gap`` missing samples), finite, and each sample holds
        vectors sent for its own stamp."""
        if data.n_samples == 0:
            return
        steps = np.diff(data.t)
        np.testing.assert_allclose(steps, np.round(steps), rtol=0, atol=1e-9)
        assert np.all(np.round(steps) >= 1) and np.all(np.round(steps) <= longest_gap + 1), steps
        for i, t in enumerate(data.t):
            k = round(t)
            for ch, arr in (("setpoint", data.r), ("input", data.u), ("output", data.y)):
                assert np.all(np.isfinite(arr[i]))
                if ch == "setpoint" and not setpoints:
                    continue
                sent = self.by_sample.get((ch, k), [])
                assert any(v.shape == arr[i].shape and np.array_equal(v, arr[i]) for v in sent), \
                    (ch, t, arr[i], sent)


@pytest.fixture
def monitor(tmp_path):
    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.core.model import PlantModel
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode

    path = tmp_path / "model.yaml"
    save_model(PlantModel(sample_time=1.0, inputs=INP, outputs=OUT, gain=np.ones((2, 3)),
                          time_constant=np.ones((2, 3)), delay=np.zeros((2, 3))), path)
    ctx = private_context()
    analyses = Analyses(seed=11)
    node = MonitorNode(context=ctx, namespace="/fuzz", analyze=analyses, parameter_overrides=_overrides({
        "model_file": str(path), "window_samples": 60, "min_samples": 20, "analysis_period": 15,
        "reorder_samples": 4, "analysis_thread": False, "stale_timeout": 3600.0,
        "diagnostics_topic": "diagnostics", "max_gap": 0}))      # every gap restarts the window
    node.get_logger().set_level(rclpy.logging.LoggingSeverity.FATAL)  # thousands of expected warnings
    yield node, analyses
    node.close()
    node.destroy_node()
    ctx.try_shutdown()


def test_fuzz_callbacks_with_1200_malformed_sequences(monitor):
    node, analyses = monitor
    gen = SequenceGenerator(seed=2024)
    n_sequences, n_messages, n_bad = 1200, 0, 0
    sent = Sent()
    for i in range(n_sequences):
        for channel, msg, what in gen.sequence():
            sent.add_msg(channel, msg)
            node._on_vector(channel, msg)          # an exception here fails the test
            n_messages += 1
            n_bad += what == "bad"
        node._on_results()
        if i % 50 == 0:
            node.publish_statuses()
            node.request_analysis()
        sent.check(node.core.window.data())
        check_statuses(node.current_statuses())
    assert n_messages > 20_000 and n_bad > 3000, (n_messages, n_bad)
    assert analyses.calls > 50
    h = node.core.window.health()
    for counter in ("bad_value", "conflict", "off_grid", "duplicate", "late", "gaps", "restarts"):
        assert getattr(h, counter) > 0, counter
    # good data return: within a window's worth of samples and two analysis periods, all is OK again
    analyses.rng = np.random.default_rng(0)
    analyses.__class__ = GoodAnalyses
    k0 = gen.k + 10**6  # far ahead of anything sent: a clean new stretch of the stream
    for k in range(k0, k0 + 200):
        for ch in CHANNELS:
            msg = make_msg(NAMES[ch], true_values(ch, k), *stamp_of(k))
            sent.add_msg(ch, msg)
            node._on_vector(ch, msg)
        node._on_results()
    sent.check(node.core.window.data())
    st = node.current_statuses()
    check_statuses(st)
    assert all(s.level == OK for s in st), [s.message for s in st]
    assert node.core.window.n_window == 60


class GoodAnalyses(Analyses):
    def __call__(self, model, data, options):
        from types import SimpleNamespace

        self.calls += 1
        rows = [SimpleNamespace(output=o, rsi=1.0, mismatch=False, p_value=0.5) for o in model.outputs]
        return SimpleNamespace(rows=rows, elements=[], overall_rsi=1.0, warnings=[])


# ------------------------------------------------------------------------------ the pure aligner

_op = st.one_of(
    st.tuples(st.just("good"), st.integers(-3, 3)),                  # a whole sample, k relative to now
    st.tuples(st.sampled_from(CHANNELS), st.integers(-60, 60),        # one vector at k + dk
              st.sampled_from(["ok", "nan", "short", "long", "conflict", "offgrid", "huge_t"])),
    st.tuples(st.just("jump"), st.integers(-10**6, 10**6)),
    st.tuples(st.just("jump"), st.integers(1, 45)),                  # a gap: short, split, or a restart
)


@pytest.mark.parametrize("max_gap, split_gap", [(0, 0), (3, 40)])
@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(_op, max_size=80), reorder=st.integers(0, 6), hold=st.booleans())
def test_fuzz_window_with_hypothesis(max_gap, split_gap, ops, reorder, hold):
    """Whatever arrives, the window only ever holds samples sent for their stamps, in order on the grid: equally
    spaced when every gap restarts it, with gaps of at most ``max(max_gap, split_gap)`` samples otherwise."""
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=30, reorder_samples=reorder, hold_setpoint=hold,
                                                  max_pending=50, max_gap=max_gap, split_gap=split_gap))
    base = 0
    sent = Sent()
    for op in ops:
        if op[0] == "good":
            k = base + op[1]
            for ch in CHANNELS:
                sent.add(ch, k * NS, true_values(ch, k))
                w.add(ch, k * NS, true_values(ch, k))
            base += 1
        elif op[0] == "jump":
            base += op[1]
        else:
            ch, dk, how = op
            k = base + dk
            v = true_values(ch, k)
            stamp = k * NS
            if how == "nan":
                v = v.copy()
                v[0] = np.nan
            elif how == "short":
                v = v[:-1]
            elif how == "long":
                v = np.r_[v, 1.0]
            elif how == "conflict":
                v = v + 1.0
            elif how == "offgrid":
                stamp += NS // 3
            elif how == "huge_t":
                stamp = (INT32_MAX if dk > 0 else INT32_MIN) * NS
            sent.add(ch, stamp, v)
            w.add(ch, stamp, v)
        w.take_problems()
        sent.check(w.data(), setpoints=not hold, longest_gap=max(max_gap, split_gap))
    assert w.data().n_samples <= 30
    assert w.n_pending <= 51


# ------------------------------------------------------------------------------ spinning smoke test

def test_spinning_smoke_malformed_then_good(monitor):
    """Real publishers and an executor: malformed messages, then good ones; nothing raises out of
    ``spin_once`` and the monitor ends OK with every good sample in its window."""
    from rclpy.node import Node

    from mpm_monitor.nodes.ros_io import make_executor, spin_until, vector_qos

    node, analyses = monitor
    analyses.__class__ = GoodAnalyses
    ctx = node.context
    pub_node = Node("fuzz_publisher", context=ctx, namespace="/fuzz")
    pubs = {ch: pub_node.create_publisher(JointState, ch, vector_qos()) for ch in CHANNELS}
    ex = make_executor(ctx, "single")
    ex.add_node(node)
    ex.add_node(pub_node)
    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 20.0)
        gen = SequenceGenerator(seed=5)
        sent = 0
        for _ in range(40):
            for ch, msg, what in gen.sequence():
                if what == "bad":
                    pubs[ch].publish(msg)
                    sent += 1
        received = lambda: sum(node.core.window.health().received.values()) + node.core.window.health().bad_value
        assert spin_until(ex, lambda: received() >= sent - 5, 20.0)
        k0 = 10**7
        for k in range(k0, k0 + 80):
            for ch in CHANNELS:
                pubs[ch].publish(make_msg(NAMES[ch], true_values(ch, k), *stamp_of(k)))
        # The grid's phase is the first accepted vector's, which may be a fuzzed one off the grid by less than
        # the stamp tolerance (a quarter of the sample time): the good samples land on that grid.
        last = lambda: node.core.window.last_sample_stamp_ns  # noqa: E731
        assert spin_until(ex, lambda: last() is not None and abs(last() - (k0 + 79) * NS) <= NS // 4, 20.0)
        node._on_results()
        assert spin_until(ex, lambda: all(s.level == OK for s in node.current_statuses()), 10.0), \
            [s.message for s in node.current_statuses()]
        assert node.core.window.n_window == 60
    finally:
        for nd in (node, pub_node):
            ex.remove_node(nd)
        pub_node.destroy_node()
        ex.shutdown()
