"""ros_io: JointState <-> numpy with validation, stamps, QoS profiles and parameter declaration."""

import math

import numpy as np
import pytest

from mpm_monitor.core.errors import ConfigurationError, InputError
from mpm_monitor.core.options import ParamSpec
from mpm_monitor.nodes.ros_io import (
    MessageError,
    VectorCodec,
    ns_to_stamp,
    period_ns,
    resolve_model,
    sample_stamp_ns,
    seconds_to_stamp,
    stamp_to_ns,
    stamp_to_seconds,
)

sensor_msgs = pytest.importorskip("sensor_msgs.msg")


def js(names, values, sec=3, nanosec=500):
    m = sensor_msgs.JointState()
    m.header.stamp.sec = sec
    m.header.stamp.nanosec = nanosec
    m.name = list(names)
    m.position = [float(v) for v in values]
    return m


CODEC = VectorCodec(("y1", "y2", "y3"), "output")


def test_round_trip_keeps_values_and_stamp_exactly():
    v = np.array([0.1, -2.5e-7, 3.0e5])
    msg = CODEC.encode(v, 1_234_567_890_123)
    assert list(msg.name) == ["y1", "y2", "y3"] and len(msg.velocity) == 0 and len(msg.effort) == 0
    stamp, back = CODEC.decode(msg)
    assert stamp == 1_234_567_890_123
    np.testing.assert_array_equal(back, v)


def test_channels_in_another_order_are_put_in_model_order():
    stamp, v = CODEC.decode(js(["y3", "y1", "y2"], [3.0, 1.0, 2.0]))
    np.testing.assert_array_equal(v, [1.0, 2.0, 3.0])
    assert stamp == 3_000_000_500


@pytest.mark.parametrize("names, values, match", [
    (["y1", "y2"], [1.0, 2.0], r"missing 'y3'"),
    (["y1", "y2", "y3", "y4"], [1.0, 2.0, 3.0, 4.0], r"unexpected 'y4'"),
    (["y1", "y1", "y3"], [1.0, 2.0, 3.0], r"'y1' repeat"),
    (["y1", "y2", "y3"], [1.0, 2.0], r"2 position value\(s\) for 3 name\(s\)"),
    (["y1", "y2", "y3"], [1.0, math.nan, 3.0], r"non-finite value\(s\) y2=nan"),
    (["y1", "y2", "y3"], [1.0, 2.0, math.inf], r"y3=inf"),
    # a bad-value sentinel: refused at reception (it made every analysis of the window fail while it stayed)
    (["y1", "y2", "y3"], [1.0, -1e300, 3.0], r"value\(s\) y2=-1e\+300 at t = .* beyond 1e\+40"),
])
def test_bad_messages_are_refused_naming_topic_channel_and_expectation(names, values, match):
    with pytest.raises(MessageError, match=match) as info:
        CODEC.decode(js(names, values))
    assert str(info.value).startswith("output: ")
    assert isinstance(info.value, InputError)


@pytest.mark.parametrize("names", [["y1", "y2"], ["y1", "y2", "y3", "y4"], ["y1", "y1", "y3"]])
def test_names_that_do_not_match_are_refused_at_their_stamp(names):
    """The refusals of names named the topic but not the stamp, as every other refusal of a vector does."""
    with pytest.raises(MessageError, match=r"at t = 1795395118\.00184 s") as info:
        CODEC.decode(js(names, [1.0] * len(names), sec=1_795_395_118, nanosec=1_840_000))
    assert str(info.value).startswith("output: ")


def test_a_vector_of_very_many_names_is_refused_naming_a_few():
    """One message of 100,000 names (about 1 MB): the codec compared every name with every other
    (``names.count``), 12 s for 20,000 names and about 20 minutes for 200,000, in which the node published
    nothing, not even its periodic statuses.  It is refused now, naming the first five and how many more."""
    names = [f"c{k}" for k in range(100_000)] + ["y1", "y2", "y3"]
    with pytest.raises(MessageError) as info:
        CODEC.decode(js(names, [1.0] * len(names)))
    text = str(info.value)
    assert "unexpected 'c0', 'c1', 'c2', 'c3', 'c4' and 99995 more" in text and len(text) < 300
    long = ["x" * 5000, "y1", "y2", "y3"]
    with pytest.raises(MessageError, match=r"unexpected 'x{40}\.\.\.' ") as info:
        CODEC.decode(js(long, [1.0] * 4))
    assert len(str(info.value)) < 300
    with pytest.raises(MessageError, match=r"'y1' repeat at t = "):
        CODEC.decode(js(["y1"] * 100_000 + ["y2", "y3"], [1.0] * 100_002))


@pytest.mark.parametrize("values", [[1.0, math.nan, 3.0], [1.0, 2.0], [1.0, 1e300, 3.0]])
def test_a_refused_wall_clock_stamp_keeps_its_fraction_of_a_second(values):
    # 15 significant digits, as the window's messages: 9 would print 1.7953951e+09 and lose the second itself
    with pytest.raises(MessageError, match=r"at t = 1795395118\.00184 s") as info:
        CODEC.decode(js(["y1", "y2", "y3"], values, sec=1_795_395_118, nanosec=1_840_000))
    assert "e+09" not in str(info.value)


def test_encode_refuses_a_wrong_length():
    with pytest.raises(ValueError, match="expected 3 values"):
        CODEC.encode([1.0, 2.0], 0)


def test_codec_refuses_repeated_names():
    with pytest.raises(ConfigurationError, match="repeat"):
        VectorCodec(("u1", "u1"), "input")


def test_stamps_are_exact_integer_nanoseconds_on_the_grid():
    p = period_ns(0.1)
    assert p == 100_000_000
    assert sample_stamp_ns(30, p) == 3_000_000_000  # no float drift at k = 30
    st = ns_to_stamp(sample_stamp_ns(12345, period_ns(1.0)))
    assert (st.sec, st.nanosec) == (12345, 0)
    assert stamp_to_ns(ns_to_stamp(7_000_000_001)) == 7_000_000_001
    assert stamp_to_seconds(seconds_to_stamp(2.25)) == 2.25
    with pytest.raises(ConfigurationError, match="sample_time"):
        period_ns(0.0)


def test_qos_profiles_follow_the_contract():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    from mpm_monitor.nodes.ros_io import diagnostics_qos, vector_qos

    q = vector_qos()
    assert (q.reliability, q.history, q.depth, q.durability) == (
        ReliabilityPolicy.RELIABLE, HistoryPolicy.KEEP_LAST, 1000, DurabilityPolicy.VOLATILE)
    d = diagnostics_qos()
    assert (d.reliability, d.depth) == (ReliabilityPolicy.RELIABLE, 10)


@pytest.mark.parametrize("spec, value, match", [
    (ParamSpec("n", "int", 1, "x", 1, 10), 11, r"parameter n: expected a value in \[1, 10\]"),
    (ParamSpec("n", "int", 1, "x", 1, 10), 2.5, "expected an integer"),
    (ParamSpec("a", "double", 1.0, "x", 0.0, 1.0), math.nan, "finite"),
    (ParamSpec("m", "string", "prbs", "x", choices=("prbs", "step")), "sine", "expected one of 'prbs', 'step'"),
    (ParamSpec("b", "bool", True, "x"), 1, "true or false"),
    (ParamSpec("w", "double_array", [1.0], "x"), [1.0, math.inf], "finite"),
])
def test_param_spec_check_refuses_with_the_parameter_name(spec, value, match):
    with pytest.raises(ConfigurationError, match=match):
        spec.check(value)


def test_declared_parameters_carry_type_description_and_range():
    import rclpy
    from rcl_interfaces.msg import ParameterType
    from rclpy.node import Node

    from mpm_monitor.apps.demo import private_context
    from mpm_monitor.nodes.ros_io import declare_parameters

    ctx = private_context()
    try:
        specs = [ParamSpec("window_samples", "int", 3000, "Window, samples.", 10, 100000),
                 ParamSpec("alpha", "double", 0.01, "Rate.", 1e-9, 0.49),
                 ParamSpec("bounds", "double_array", None, "Optional bounds.")]
        node = Node("param_test", context=ctx, parameter_overrides=[rclpy.parameter.Parameter("alpha", value=0.05)])
        values = declare_parameters(node, specs)
        assert values == {"window_samples": 3000, "alpha": 0.05, "bounds": None}
        d = node.describe_parameter("window_samples")
        assert d.type == ParameterType.PARAMETER_INTEGER and d.description == "Window, samples."
        assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (10, 100000)
        assert node.describe_parameter("alpha").floating_point_range[0].to_value == 0.49
        node.destroy_node()
        bad = Node("param_test_bad", context=ctx,
                   parameter_overrides=[rclpy.parameter.Parameter("window_samples", value=5)])
        with pytest.raises(ConfigurationError, match="window_samples"):
            declare_parameters(bad, specs)
        bad.destroy_node()
        wrong = Node("param_test_type", context=ctx,
                     parameter_overrides=[rclpy.parameter.Parameter("alpha", value="high")])
        with pytest.raises(ConfigurationError, match="alpha"):
            declare_parameters(wrong, specs)
        wrong.destroy_node()
    finally:
        ctx.try_shutdown()


@pytest.mark.parametrize("name, value, match", [
    ("setpoint_topic", "bad topic!", r"parameter setpoint_topic: invalid topic name 'bad topic!': topic name must not "
                                     r"contain characters"),
    ("diagnostics_topic", "/diag/", r"invalid topic name '/diag/': topic name must not end with a forward slash$"),
    ("candidate_topic", "a//b", r"invalid topic name 'a//b': topic name must not contain repeated '/'$"),
    ("experiment_service", "9bad", r"parameter experiment_service: invalid service name '9bad': .*must not start with "
                                   r"a number$"),
    ("topics", ["output", "bad topic=std_msgs/msg/String"], r"parameter topics: invalid topic name 'bad topic'"),
    # '' is none only where a parameter says so (candidate_topic): elsewhere rclpy's traceback, exit 1
    ("diagnostics_topic", "", r"parameter diagnostics_topic: invalid topic name '': topic name must not be empty"),
    ("experiment_service", "", r"parameter experiment_service: invalid service name '': .*must not be empty"),
])
def test_a_topic_or_service_name_ros_refuses_is_one_line_naming_the_parameter(name, value, match):
    """Not rclpy's multi-line exception when the publisher is created (a traceback and exit 1 from a node)."""
    import rclpy
    from rclpy.node import Node

    from mpm_monitor.apps.demo import private_context
    from mpm_monitor.nodes.ros_io import declare_parameters

    kind = "string_array" if isinstance(value, list) else "string"
    specs = [ParamSpec(name, kind, ["output"] if kind == "string_array" else "", "A name.")]
    ctx = private_context()
    try:
        node = Node("names_test", context=ctx, parameter_overrides=[rclpy.parameter.Parameter(name, value=value)])
        with pytest.raises(ConfigurationError, match=match) as info:
            declare_parameters(node, specs)
        assert "\n" not in str(info.value)
        node.destroy_node()
        good = Node("names_ok", context=ctx, parameter_overrides=[rclpy.parameter.Parameter(
            name, value=["output", "~/x=std_msgs/msg/String"] if kind == "string_array" else "~/fine_name")])
        declare_parameters(good, specs)
        good.destroy_node()
    finally:
        ctx.try_shutdown()


def test_an_empty_name_is_none_where_the_parameter_says_so():
    import rclpy
    from rclpy.node import Node

    from mpm_monitor.apps.demo import private_context
    from mpm_monitor.nodes import monitor_node, replay_node
    from mpm_monitor.nodes.ros_io import declare_parameters

    for module, name in ((monitor_node, "candidate_topic"), (replay_node, "disturbance_topic")):
        spec = next(s for s in module.PARAMS if s.name == name)
        assert spec.empty_is_none
        ctx = private_context()
        try:
            node = Node("empty_ok", context=ctx, parameter_overrides=[rclpy.parameter.Parameter(name, value="")])
            assert declare_parameters(node, [spec])[name] == ""
            node.destroy_node()
        finally:
            ctx.try_shutdown()


@pytest.mark.parametrize("node, overrides, match", [
    ("monitor", {"setpoint_topic": "output"},
     "parameters setpoint_topic and output_topic name one topic /output: expected a topic of its own for each"),
    ("monitor", {"candidate_topic": "/input"}, "parameters input_topic and candidate_topic name one topic /input"),
    ("mpc", {"input_topic": "output"}, "parameters output_topic and input_topic name one topic /output"),
    ("plant", {"input_topic": "/output"}, "parameters output_topic and input_topic name one topic /output"),
    ("setpoint", {"dither_topic": "setpoint"}, "parameters setpoint_topic and dither_topic name one topic /setpoint"),
])
def test_two_channels_on_one_topic_are_refused_at_start_up(node, overrides, match):
    """Stop 73's audit: setpoint_topic:=output ran, took every output vector as the setpoint too (r = y) and
    reported a mismatch in every row."""
    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.nodes import monitor_node, mpc_node, plant_node, setpoint_node

    cls = {"monitor": monitor_node.MonitorNode, "mpc": mpc_node.MpcNode, "plant": plant_node.PlantNode,
           "setpoint": setpoint_node.SetpointNode}[node]
    ctx = private_context()
    try:
        with pytest.raises(ConfigurationError, match=match):
            cls(context=ctx, parameter_overrides=_overrides({"case": "3.2", **overrides}))
        cls(context=ctx, parameter_overrides=_overrides({"case": "3.2"})).destroy_node()     # the defaults: fine
    finally:
        ctx.try_shutdown()


def test_a_params_file_that_is_missing_or_not_yaml_is_one_line(tmp_path):
    from mpm_monitor.nodes.ros_io import params_file_problem

    bad = tmp_path / "bad.yaml"
    bad.write_text("/**/monitor:\n  ros__parameters: [unclosed\n", encoding="utf-8")
    assert params_file_problem(["--ros-args", "--params-file", str(tmp_path / "none.yaml")]) == \
        f"--params-file {tmp_path / 'none.yaml'}: cannot read it: No such file or directory"
    assert params_file_problem(["--ros-args", "--params-file", str(bad)]).startswith(f"--params-file {bad}: not valid YAML")
    assert params_file_problem(["--ros-args", "-p", "case:=3.2"]) == ""


def test_resolve_model_from_case_or_file(tmp_path):
    from mpm_monitor.io.model_file import save_model

    plant = resolve_model("", "3.2", which="plant")
    model = resolve_model("", "3.2")
    assert plant.gain[0, 2] == 5.88 and model.gain[0, 2] == 3.5
    save_model(model, tmp_path / "m.yaml")
    assert resolve_model(str(tmp_path / "m.yaml"), "") == model
    with pytest.raises(ConfigurationError, match="model_file and case"):
        resolve_model("", "")
    with pytest.raises(ConfigurationError, match="case"):
        resolve_model("", "9.9")
    with pytest.raises(InputError):
        resolve_model(str(tmp_path / "missing.yaml"), "")


def test_every_qos_profile_is_built_from_its_one_description():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

    from mpm_monitor.io import qos
    from mpm_monitor.nodes.recorder_node import subscription_qos
    from mpm_monitor.nodes.ros_io import diagnostics_qos, qos_profile, vector_qos

    keep, rel, vol = HistoryPolicy.KEEP_LAST, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE
    # the profiles as the nodes spelled them out before they had one home
    assert vector_qos() == QoSProfile(history=keep, depth=1000, reliability=rel, durability=vol)
    assert diagnostics_qos() == QoSProfile(history=keep, depth=10, reliability=rel, durability=vol)
    for best_effort in (False, True):
        assert subscription_qos(best_effort) == QoSProfile(
            history=keep, depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else rel,
            durability=vol, liveliness=LivelinessPolicy.AUTOMATIC)
    assert qos_profile(qos.REPLAY_CLOCK_QOS) == QoSProfile(history=keep, depth=10, reliability=rel, durability=vol)
    assert qos_profile(qos.CLOCK_LISTENER_QOS) == QoSProfile(history=keep, depth=100,
                                                             reliability=ReliabilityPolicy.BEST_EFFORT, durability=vol)
    keep_all = qos_profile(qos.QosSpec(history="keep_all", durability="transient_local"))
    assert (keep_all.history, keep_all.durability) == (HistoryPolicy.KEEP_ALL, DurabilityPolicy.TRANSIENT_LOCAL)


def test_the_qos_description_needs_no_rclpy_and_is_what_a_bag_stores():
    import subprocess
    import sys

    from mpm_monitor.io.bags import contract_vector_qos
    from mpm_monitor.io.qos import VECTOR_QOS, QosSpec, rosbags_qos

    code = ("import sys, mpm_monitor.io.qos\n"
            "assert 'rclpy' not in [m for m in sys.modules if sys.modules[m] is not None]\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert rosbags_qos(VECTOR_QOS) == contract_vector_qos()
    with pytest.raises(ConfigurationError, match="QoS reliability: expected one of reliable, best_effort"):
        QosSpec(reliability="sometimes")
    with pytest.raises(ConfigurationError, match="QoS depth"):
        QosSpec(depth=0)


def test_keyword_overrides_take_the_type_of_their_parameter(tmp_path):
    from mpm_monitor.nodes.ros_io import parameter_overrides

    specs = (ParamSpec("bag", "string", "", "x"), ParamSpec("rate", "double", 1.0, "x", 0.01, 100.0),
             ParamSpec("n", "int", 0, "x", 0, 10), ParamSpec("topics", "string_array", ["a"], "x"),
             ParamSpec("on", "bool", False, "x"))
    given = parameter_overrides(specs, None, bag=tmp_path, rate=2, n=3, topics=("a", "b"), on=None)
    assert [(p.name, p.value) for p in given] == [("bag", str(tmp_path)), ("rate", 2.0), ("n", 3),
                                                  ("topics", ["a", "b"])]
    assert isinstance(given[1].value, float)
    first = parameter_overrides(specs, given[:1], rate=3.0)
    assert [p.name for p in first] == ["bag", "rate"]


def test_channel_codecs_and_topic_parameters_come_from_the_contract():
    from mpm_monitor.nodes.ros_io import CHANNELS, topic_params

    model = resolve_model("", "3.2")
    assert VectorCodec.for_channel(model, "setpoint", "r").names == model.outputs
    assert VectorCodec.for_channel(model, "dither", "d").names == model.inputs
    with pytest.raises(ValueError, match="channel"):
        VectorCodec.for_channel(model, "clock", "c")
    specs = topic_params(*CHANNELS, "clock")
    assert [(s.name, s.default) for s in specs] == [("setpoint_topic", "setpoint"), ("input_topic", "input"),
                                                    ("output_topic", "output"), ("dither_topic", "dither"),
                                                    ("disturbance_topic", "disturbance"), ("clock_topic", "/clock")]
    # the measured disturbances' channel carries the model's disturbance names
    level = resolve_model("", "level")
    assert VectorCodec.for_channel(level, "disturbance", "dv").names == ("inflow",)
    with pytest.raises(ConfigurationError, match="dv: expected at least one channel name"):
        VectorCodec.for_channel(model, "disturbance", "dv")
