"""Defects found by fuzzing the nodes' ROS parameters, at start-up and through the parameter services.

The rules (README, "Bad input, faults and security"): a bad value is refused in one line naming the parameter and
what was expected; at run time the ``set_parameters`` result is ``successful=False`` with that reason and the node
keeps running with its old value; a parameter that cannot change at run time says so; a node never crashes on input.

In-process, one isolated context (``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``, :func:`mpm_monitor.apps.demo.private_context`),
the requests sent through the nodes' real ``/set_parameters`` and ``/set_parameters_atomically`` services.
"""

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.timeout(120)

import rclpy  # noqa: E402
from rcl_interfaces.msg import Parameter as ParameterMsg  # noqa: E402
from rcl_interfaces.msg import ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters, SetParametersAtomically  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from mpm_monitor.apps.demo import private_context  # noqa: E402
from mpm_monitor.core.errors import ConfigurationError  # noqa: E402
from mpm_monitor.nodes.ros_io import make_executor, spin_until  # noqa: E402


@pytest.fixture
def ctx():
    context = private_context()
    yield context
    context.try_shutdown()


class Services:
    """A client of one node's ``set_parameters`` services, spun with the node on one executor."""

    def __init__(self, ctx, node, kind="events"):
        self.node = node
        self.client_node = rclpy.create_node("param_fuzz_client", context=ctx)
        self.executor = make_executor(ctx, kind)
        self.executor.add_node(node)
        self.executor.add_node(self.client_node)
        name = node.get_fully_qualified_name()
        self.set = self.client_node.create_client(SetParameters, f"{name}/set_parameters")
        self.atomic = self.client_node.create_client(SetParametersAtomically, f"{name}/set_parameters_atomically")
        assert spin_until(self.executor, lambda: self.set.service_is_ready() and self.atomic.service_is_ready(), 10)

    def call(self, name, value: ParameterValue, atomic=False):
        msg = ParameterMsg(name=name, value=value)
        if atomic:
            future = self.atomic.call_async(SetParametersAtomically.Request(parameters=[msg]))
        else:
            future = self.set.call_async(SetParameters.Request(parameters=[msg]))
        assert spin_until(self.executor, future.done, 10), "no answer"
        return future.result().result if atomic else future.result().results[0]

    def close(self):
        for n in (self.node, self.client_node):
            self.executor.remove_node(n)
            close = getattr(n, "close", None)
            if close is not None:
                close()
            n.destroy_node()


def _mpc(ctx, **values):
    from mpm_monitor.nodes.mpc_node import MpcNode

    values = {"case": "3.2", **values}
    return MpcNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


def _double(x):
    return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=x)


@pytest.mark.parametrize("atomic", [False, True])
def test_a_parameter_value_of_no_known_type_is_refused_and_the_node_keeps_running(ctx, atomic):
    """rclpy's parameter service turned a ParameterValue of type 99 into a ValueError out of the service callback:
    the executor raised it and the node process ended with a traceback, from one request of any peer."""
    services = Services(ctx, _mpc(ctx, max_dither=1.0))
    try:
        result = services.call("max_dither", ParameterValue(type=99), atomic=atomic)
        assert not result.successful
        assert result.reason.startswith("parameter max_dither: ") and "type 99" in result.reason, result.reason
        assert "\n" not in result.reason
        # still running, with its old value, and a good change still goes through
        assert services.node.get_parameter("max_dither").value == 1.0
        result = services.call("max_dither", _double(2.0), atomic=atomic)
        assert result.successful, result.reason
        assert services.node.params["max_dither"] == 2.0
    finally:
        services.close()


@pytest.mark.parametrize("atomic", [False, True])
def test_an_empty_or_undeclared_parameter_name_is_refused_naming_it(ctx, atomic):
    """rclpy took a parameter named '' as declared (its check tests the names' truth) and added it to the node; it
    refused another undeclared name with 'Invalid access to undeclared parameter(s): []', naming none."""
    services = Services(ctx, _mpc(ctx))
    try:
        result = services.call("", _double(1.0), atomic=atomic)
        assert not result.successful and not services.node.has_parameter("")
        assert result.reason == "parameter '': not a parameter of this node", result.reason
        result = services.call("max_dithr", _double(1.0), atomic=atomic)
        assert not result.successful and not services.node.has_parameter("max_dithr")
        assert result.reason == "parameter 'max_dithr': not a parameter of this node: did you mean 'max_dither'?"
    finally:
        services.close()


@pytest.mark.parametrize("value, said", [
    (ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="x"), "Wrong parameter type"),
    (ParameterValue(type=ParameterType.PARAMETER_NOT_SET), "cannot be undeclared"),
])
def test_a_refusal_of_rclpy_names_the_parameter(ctx, value, said):
    """rclpy's own refusals of a live parameter ('Wrong parameter type, expected ...', 'Static parameter cannot be
    undeclared') did not say which parameter they were about."""
    services = Services(ctx, _mpc(ctx))
    try:
        for name in ("max_dither", "use_sim_time"):
            result = services.call(name, value)
            assert not result.successful
            assert result.reason.startswith(f"parameter {name}: ") and said in result.reason, result.reason
    finally:
        services.close()


def test_use_sim_time_cannot_be_toggled_at_run_time(ctx):
    """``use_sim_time`` set at run time was taken: the node's clock switched to /clock time, so that a setpoint node
    on its timer (trigger timer), with no /clock, stopped publishing without a word, and a recorder's log times
    jumped from wall-clock time to simulated time within one bag.  It is fixed at start-up, as the nodes' own
    parameters read there; the refusal says so and the clock stays as it was."""
    from mpm_monitor.nodes.setpoint_node import SetpointNode

    node = SetpointNode(context=ctx, parameter_overrides=[Parameter("case", value="3.2"),
                                                           Parameter("trigger", value="timer")])
    services = Services(ctx, node)
    try:
        for atomic in (False, True):
            result = services.call("use_sim_time", ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True),
                                   atomic=atomic)
            assert not result.successful
            assert result.reason.startswith("parameter use_sim_time: ") and "start-up" in result.reason, result.reason
            assert node.get_parameter("use_sim_time").value is False
            assert not node.get_clock().ros_time_is_active
        # the same value again is no change: taken
        result = services.call("use_sim_time", ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=False))
        assert result.successful, result.reason
        before = node.published
        assert spin_until(services.executor, lambda: node.published >= before + 3, 10)
    finally:
        services.close()


@pytest.mark.parametrize("weight", ["input_weight", "output_weight"])
def test_an_mpc_weight_too_large_for_the_controller_is_refused_naming_it(ctx, weight):
    """``input_weight: [1e308]`` ended the MPC node in a LinAlgError traceback ('Singular matrix'), and
    ``output_weight: [1e308]`` was taken with gains that are not finite: the first input the node computed was NaN
    and it stopped as a diverged controller."""
    with pytest.raises(ConfigurationError) as refused:
        _mpc(ctx, **{weight: [1e308]})
    text = str(refused.value)
    assert text.startswith("MPC weights output_weight [") and "\n" not in text
    assert f"{weight} [1e+308]" in text, text


@pytest.mark.parametrize("given, said", [({"u_min": [1e308]}, "u_min: 1e+308 for input 'u1'"),
                                         ({"input_nominal": [0.0, -1e300, 0.0]}, "input_nominal: -1e+300 for input 'u2'")])
def test_an_input_bound_or_nominal_beyond_the_loops_scale_is_refused_naming_it(ctx, given, said):
    """``u_min: [1e308]`` was taken: the controller held the inputs at 1e308 and stopped as diverged."""
    with pytest.raises(ConfigurationError) as refused:
        _mpc(ctx, **given)
    text = str(refused.value)
    assert text.startswith(said) and "within 1e+40 in magnitude" in text and "\n" not in text, text


def test_a_band_edge_out_of_order_is_refused_naming_the_node_parameters(ctx):
    """``band_high:=0`` was refused as 'parameter band: expected 0 <= low < high <= pi', a parameter the node does
    not have (it has band_low and band_high)."""
    from mpm_monitor.nodes.monitor_node import MonitorNode

    with pytest.raises(ConfigurationError) as refused:
        MonitorNode(context=ctx, analyze=lambda *a: None, parameter_overrides=[
            Parameter("case", value="3.2"), Parameter("analysis_process", value=False),
            Parameter("band_high", value=0.0)])
    text = str(refused.value)
    assert text.startswith("parameters band_low and band_high: "), text
    assert "band_low 0 < band_high" in text or "band_low < band_high" in text, text


@pytest.mark.parametrize("given, said", [
    ("use_sim_time:=1", "parameter use_sim_time: wrong type: Trying to set parameter 'use_sim_time' to '1' of type "
                        "'INTEGER', expecting type 'BOOL'"),
    ("input_weight:=[1e308]", "MPC weights output_weight [1], input_weight [1e+308], input_rate_weight [0.1] give a "
                              "control problem that cannot be solved (expected weights of a moderate scale)"),
])
def test_a_node_started_with_such_a_value_says_one_line_and_exits_2(given, said):
    """``-p use_sim_time:=1`` (rclpy's own parameter, refused by rclpy.Node before the node declares its own) and
    ``-p input_weight:=[1e308]`` ended the process in a traceback, exit code 1."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from ros_domains import unique_domain

    from bench.ros_domain import domain_env

    with unique_domain(salt=len(given)) as domain:
        done = subprocess.run([sys.executable, "-m", "mpm_monitor.nodes.entry", "mpc_node", "--ros-args", "-p",
                               "case:=3.2", "-p", given], cwd=Path(__file__).resolve().parent.parent,
                              env=dict(os.environ, **domain_env(domain), RCUTILS_LOGGING_BUFFERED_STREAM="0"),
                              capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [f"error: {said}"], done.stderr


@pytest.mark.parametrize("node, given, said", [
    ("monitor", {"rsi_topic": "setpoint"}, "parameters setpoint_topic and rsi_topic name one topic /setpoint"),
    ("monitor", {"diagnostics_topic": "output"}, "parameters output_topic and diagnostics_topic name one topic /output"),
    ("monitor", {"rsi_topic": "/diagnostics"}, "parameters diagnostics_topic and rsi_topic name one topic /diagnostics"),
    ("plant", {"clock_topic": "output"}, "parameters output_topic and clock_topic name one topic /output"),
    ("setpoint", {"clock_topic": "setpoint"}, "parameters setpoint_topic and clock_topic name one topic /setpoint"),
])
def test_a_topic_of_one_node_given_two_message_types_is_refused_naming_both(ctx, node, given, said):
    """A node's topic of one type named for a topic of another type of the same node (the monitor's rsi_topic for
    setpoint_topic, the plant's clock_topic for output_topic) ended the node in rcl's RCLError 'create_publisher()
    called for existing topic name rt/setpoint with incompatible type', over several lines with an rcutils error
    state dump; the monitor creates its subscriptions once its model loads, so with a model file that loads late the
    error would come out of a timer's callback while it runs.  Refused in one line, as two vector topics are."""
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.plant_node import PlantNode
    from mpm_monitor.nodes.setpoint_node import SetpointNode

    build = {"monitor": (MonitorNode, {"analysis_process": False}), "plant": (PlantNode, {"autostart": False}),
             "setpoint": (SetpointNode, {})}
    cls, base = build[node]
    values = {"case": "3.2", **base, **given}
    kwargs = {"analyze": lambda *a: None} if node == "monitor" else {}
    with pytest.raises(ConfigurationError) as refused:
        cls(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()], **kwargs)
    assert str(refused.value) == f"{said}: expected a topic of its own for each"
