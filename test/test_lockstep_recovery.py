"""Lock-step recovery: the MPC node, then the plant node, destroyed and created again mid-run.

In lock-step simulated time the plant waits for u(k) before sample k + 1.  When no u(k) comes for
``stall_timeout`` it re-sends the clock and y(k) (same stamp, same values); the setpoint node answers
the repeated clock with r(k) again, so a new MPC node gets what it needs and the loop resumes.  A
restarted plant starts again at k = 0: the MPC resets its controller and follows it.

In-process, on a private context (:func:`mpm_monitor.apps.demo.private_context`), like
test_nodes_inprocess.py.
"""

import collections

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(60)

from rclpy.node import Node  # noqa: E402
from ros_domains import close_nodes  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from mpm_monitor.apps.demo import _overrides, case_parameters, private_context  # noqa: E402
from mpm_monitor.nodes.mpc_node import MpcNode  # noqa: E402
from mpm_monitor.nodes.plant_node import PlantNode  # noqa: E402
from mpm_monitor.nodes.ros_io import make_executor, spin_until, stamp_to_ns, vector_qos  # noqa: E402
from mpm_monitor.nodes.setpoint_node import SetpointNode  # noqa: E402


def test_mpc_then_plant_restarted_in_lock_step_the_loop_resumes_without_duplicate_inputs():
    ctx = private_context()
    ns = "/recover"
    params = case_parameters("3.1", seed=1)
    params["plant"].update(clock_topic="clock", stall_timeout=0.2, start_delay=0.2)
    params["setpoint"]["clock_topic"] = "clock"
    kw = dict(context=ctx, namespace=ns)

    def plant():
        return PlantNode(parameter_overrides=_overrides(params["plant"]), **kw)

    def mpc():
        return MpcNode(parameter_overrides=_overrides(params["mpc"]), **kw)

    nodes = {"plant": plant(), "setpoint": SetpointNode(parameter_overrides=_overrides(params["setpoint"]), **kw),
             "mpc": mpc()}
    watcher = Node("watcher", context=ctx, namespace=ns)
    inputs = []  # (stamp, values) of every u seen on the input topic, in arrival order
    watcher.create_subscription(JointState, "input",
                                lambda m: inputs.append((stamp_to_ns(m.header.stamp), tuple(m.position))),
                                vector_qos())
    ex = make_executor(ctx)
    for nd in (*nodes.values(), watcher):
        ex.add_node(nd)

    def replace(name, make):
        old = nodes[name]
        ex.remove_node(old)
        old.destroy_node()
        nodes[name] = make()
        ex.add_node(nodes[name])

    def no_duplicate_stamps(seen):
        counts = collections.Counter(stamp for stamp, _ in seen)
        return [s for s, c in counts.items() if c > 1]

    try:
        assert spin_until(ex, lambda: nodes["plant"].k >= 200, 20.0), nodes["plant"].k
        # 1. the MPC dies: the loop stalls ...
        old_mpc = nodes["mpc"]
        ex.remove_node(old_mpc)
        old_mpc.destroy_node()
        spin_until(ex, lambda: False, 0.5)
        k_stalled = nodes["plant"].k
        assert nodes["plant"].resent >= 1
        spin_until(ex, lambda: False, 0.3)
        assert nodes["plant"].k == k_stalled
        # ... and a new MPC (fresh internal model) picks it up from the re-sent y(k) and r(k)
        nodes["mpc"] = mpc()
        ex.add_node(nodes["mpc"])
        assert spin_until(ex, lambda: nodes["plant"].k >= k_stalled + 200, 10.0), (nodes["plant"].k, k_stalled)
        assert nodes["setpoint"].resent >= 1
        assert nodes["mpc"].steps >= 200 and nodes["mpc"].restarts == 0
        assert no_duplicate_stamps(inputs) == []
        stamps = [s for s, _ in inputs]
        assert stamps == sorted(stamps)
        assert nodes["plant"].rejected_inputs == 0

        # 2. the plant dies and a new one starts again at k = 0: the MPC resets and follows it
        n_before = len(inputs)
        steps_before = nodes["mpc"].steps
        replace("plant", plant)
        assert spin_until(ex, lambda: nodes["plant"].k >= 200, 10.0), nodes["plant"].k
        assert nodes["mpc"].restarts == 1
        assert nodes["mpc"].steps >= steps_before + 200
        after = [s for s, _ in inputs[n_before:]]
        first = after.index(0)  # before it, at most the old run's inputs still in flight
        assert all(s >= stamps[-1] for s in after[:first]) and first <= 2
        assert after[first:] == sorted(after[first:])
        assert no_duplicate_stamps(inputs[n_before + first:]) == []
        assert nodes["plant"].rejected_inputs == 0
    finally:
        close_nodes(ex, ctx, *nodes.values(), watcher)


def test_mpc_answers_a_resent_output_with_the_same_input_and_resets_on_a_new_run():
    """The MPC node alone, driven by a plain publisher: repeats, a different y for the same stamp, a stamp going back."""
    from mpm_monitor.nodes.ros_io import VectorCodec
    from mpm_monitor.sim.cases import paper_case

    ctx = private_context()
    ns = "/mpc_repeat"
    model = paper_case("3.1").model
    mpc = MpcNode(parameter_overrides=_overrides(case_parameters("3.1")["mpc"]), context=ctx, namespace=ns)
    other = Node("driver", context=ctx, namespace=ns)
    pubs = {t: other.create_publisher(JointState, t, vector_qos()) for t in ("output", "setpoint")}
    got = []
    other.create_subscription(JointState, "input", lambda m: got.append((stamp_to_ns(m.header.stamp),
                                                                         tuple(m.position))), vector_qos())
    ex = make_executor(ctx)
    for nd in (mpc, other):
        ex.add_node(nd)
    y_codec = VectorCodec(model.outputs, "output")
    ts = 1_000_000_000

    def send(topic, values, k):
        pubs[topic].publish(y_codec.encode(values, k * ts))

    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values())
                          and mpc._pub.get_subscription_count() >= 1, 20.0)
        r, y = [1.0, -1.0, 1.0], [0.1, 0.2, 0.3]
        for k in range(3):
            send("output", y, k)
            send("setpoint", r, k)
        assert spin_until(ex, lambda: len(got) == 3, 5.0)
        u2 = got[-1]
        # a re-sent y(2): the same u(2) again; a re-sent r(2): nothing
        send("setpoint", r, 2)
        send("output", y, 2)
        assert spin_until(ex, lambda: len(got) == 4, 5.0)
        assert got[-1] == u2 and mpc.steps == 3 and mpc.repeated == 2 and mpc.restarts == 0
        # the stamps go back (a restarted plant at k = 0): controller reset, u(0) of a fresh controller
        send("setpoint", r, 0)
        send("output", y, 0)
        assert spin_until(ex, lambda: len(got) == 5, 5.0)
        assert got[-1] == got[0] and mpc.restarts == 1 and mpc.steps == 4
        # a different y for the stamp just answered (a plant restarted right after its first sample)
        send("output", [0.0, 0.0, 0.0], 0)
        send("setpoint", r, 0)  # the partner arrives after the new y
        assert spin_until(ex, lambda: len(got) == 6, 5.0)
        assert mpc.restarts == 2 and got[-1][0] == 0 and got[-1] != got[0]
    finally:
        close_nodes(ex, ctx, mpc, other)
