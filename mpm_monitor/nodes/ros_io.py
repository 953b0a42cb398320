"""ROS 2 message conversion and node plumbing (docs/interfaces.md, "ROS 2 topics and statuses").

A "stamped vector" is a ``sensor_msgs/msg/JointState`` whose ``header.stamp`` is the sample's time,
whose ``name`` lists the channels (the model's outputs for ``setpoint`` and ``output``, its inputs
for ``input`` and ``dither``, its measured disturbances for ``disturbance``) and whose ``position``
holds the values; ``velocity`` and ``effort``
are ignored.  This module turns such messages into numpy vectors in the model's channel order and
back, checking the names, the lengths and that every value is finite, and it holds what the nodes
share: the stamp arithmetic, the ``rclpy`` QoS profiles built from :mod:`mpm_monitor.io.qos`, the
declaration of the parameters and the main loop.

The conversion functions only touch message attributes, so they run (and are tested) on any object
with the same fields; ``rclpy`` and the message packages are imported lazily, where a profile, a
message or a node is really built.

Stamps are handled as integer nanoseconds so that the sample grid ``k * sample_time`` is exact:
``sample_stamp_ns(k, period_ns) = k * period_ns`` with ``period_ns = round(sample_time * 1e9)``.
"""

from __future__ import annotations

import collections
import difflib
import importlib
import math
import os
import sys
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .. import limit_blas_threads
from ..core.errors import ConfigurationError, InputError
from ..core.logged_data import MAX_ANALYSIS_SCALE
from ..core.options import ParamSpec
from ..io.qos import DIAGNOSTICS_QOS, VECTOR_QOS, QosSpec
from ..monitor.window import NS_PER_S, names_text, seconds_text
from .params_file_check import params_file_problem

#: The stamped-vector channels and whose names they carry: the model's ``outputs``, ``inputs`` or ``disturbances``.
CHANNELS = {"setpoint": "outputs", "input": "inputs", "output": "outputs", "dither": "inputs",
            "disturbance": "disturbances"}


class MessageError(InputError):
    """A message that cannot be used: wrong channel names, lengths or non-finite values."""


# --------------------------------------------------------------------------------------- stamps
def period_ns(sample_time: float) -> int:
    """The sample time in integer nanoseconds.

    Parameters
    ----------
    sample_time : float
        Seconds per sample, > 0.
    """
    if not (isinstance(sample_time, (int, float)) and math.isfinite(sample_time) and sample_time > 0):
        raise ConfigurationError(f"sample_time: expected a finite number > 0 (seconds), got {sample_time!r}")
    ns = int(round(float(sample_time) * NS_PER_S))
    if ns < 1:
        raise ConfigurationError(f"sample_time: {sample_time!r} s is below one nanosecond")
    return ns


def sample_stamp_ns(k: int, sample_period_ns: int) -> int:
    """Stamp of sample ``k`` on the grid, in nanoseconds: ``k * sample_period_ns``."""
    return int(k) * int(sample_period_ns)


def stamp_to_ns(stamp) -> int:
    """A ``builtin_interfaces/msg/Time`` (``sec``, ``nanosec``) as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def stamp_to_seconds(stamp) -> float:
    """A ``builtin_interfaces/msg/Time`` as float seconds."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def ns_to_stamp(ns: int):
    """Integer nanoseconds as a ``builtin_interfaces/msg/Time``."""
    from builtin_interfaces.msg import Time

    sec, nanosec = divmod(int(ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def seconds_to_stamp(t: float):
    """Float seconds as a ``builtin_interfaces/msg/Time`` (rounded to the nanosecond)."""
    return ns_to_stamp(int(round(float(t) * NS_PER_S)))


# ----------------------------------------------------------------------------- stamped vectors
class VectorCodec:
    """Conversion between stamped-vector messages and numpy vectors for one topic.

    Parameters
    ----------
    names : sequence of str
        The channels in the order the core uses (the model's outputs or inputs).
    topic : str
        Topic name, for messages.

    Notes
    -----
    The channels of a message may come in any order; they are put in ``names`` order.  The
    permutation is cached per distinct ``name`` list, so a steady publisher costs one dict look-up.
    """

    def __init__(self, names: Sequence[str], topic: str):
        self.names = tuple(str(n) for n in names)
        if not self.names:
            raise ConfigurationError(f"{topic}: expected at least one channel name")
        if len(set(self.names)) != len(self.names):
            raise ConfigurationError(f"{topic}: channel names repeat: {', '.join(self.names)}")
        self.topic = topic
        self._index = {n: i for i, n in enumerate(self.names)}
        self._perm_cache: dict = {}

    @classmethod
    def for_channel(cls, model, channel: str, topic: str) -> "VectorCodec":
        """The codec of a contract channel: the model's outputs for ``setpoint`` and ``output``, its
        inputs for ``input`` and ``dither``, its measured disturbances for ``disturbance`` (a model
        with some)."""
        if channel not in CHANNELS:
            raise ValueError(f"channel: expected one of {', '.join(CHANNELS)}, got {channel!r}")
        return cls(getattr(model, CHANNELS[channel]), topic)

    @property
    def size(self) -> int:
        return len(self.names)

    def _permutation(self, names: tuple, stamp_ns: int) -> Optional[np.ndarray]:
        """The order of ``names`` (a message's) into :attr:`names` (None: the same order), in time linear in
        their number (a message of 200,000 names once held the node for minutes); :class:`MessageError`
        naming the topic, the stamp and the names that do not match."""
        perm = self._perm_cache.get(names, False)
        if perm is not False:
            return perm
        at = f"at t = {seconds_text(stamp_ns)} s"
        expected = ", ".join(self.names)
        counts = collections.Counter(names)
        dup = sorted(n for n, c in counts.items() if c > 1)
        if dup:
            raise MessageError(f"{self.topic}: channel name(s) {names_text(dup)} repeat {at} "
                               f"(expected each of {expected} once)")
        missing = [n for n in self.names if n not in counts]
        extra = [n for n in names if n not in self._index]
        if missing or extra:
            what = []
            if missing:
                what.append("missing " + ", ".join(repr(m) for m in missing))
            if extra:
                what.append(f"unexpected {names_text(extra)}")
            raise MessageError(f"{self.topic}: channel names do not match the model {at}: {'; '.join(what)} "
                               f"(expected {expected})")
        if names == self.names:
            perm = None
        else:
            where = {n: k for k, n in enumerate(names)}
            perm = np.array([where[n] for n in self.names])
        if len(self._perm_cache) < 64:
            self._perm_cache[names] = perm
        return perm

    def decode(self, msg) -> tuple:
        """Stamp and values of a message.

        Parameters
        ----------
        msg : sensor_msgs.msg.JointState (or an object with ``header.stamp``, ``name``, ``position``)

        Returns
        -------
        stamp_ns : int
            ``header.stamp`` in nanoseconds.
        values : ndarray, shape (n_channels,)
            ``position`` in :attr:`names` order.

        Raises
        ------
        MessageError
            When the names do not match, ``position`` and ``name`` differ in length, or a value is
            not finite or beyond :data:`~mpm_monitor.core.logged_data.MAX_ANALYSIS_SCALE`; the
            message names the topic, the channel and what was expected.
        """
        stamp_ns = stamp_to_ns(msg.header.stamp)
        names = tuple(msg.name)
        values = np.asarray(msg.position, dtype=float)
        if values.ndim != 1 or values.shape[0] != len(names):
            raise MessageError(f"{self.topic}: {values.size} position value(s) for {len(names)} name(s) at "
                               f"t = {seconds_text(stamp_ns)} s (expected one value per name, "
                               f"{self.size} channels: {', '.join(self.names)})")
        perm = self._permutation(names, stamp_ns)
        if perm is not None:
            values = values[perm]
        else:
            values = values.copy()
        if not np.all(np.isfinite(values)):
            bad = [f"{self.names[i]}={float(values[i])!r}" for i in np.flatnonzero(~np.isfinite(values))]
            raise MessageError(f"{self.topic}: non-finite value(s) {', '.join(bad)} at t = {seconds_text(stamp_ns)} s "
                               f"(expected finite numbers)")
        huge = np.abs(values) > MAX_ANALYSIS_SCALE
        if np.any(huge):      # a bad-value sentinel such as 1e300: refused like a NaN (one sample), not analysed
            bad = [f"{self.names[i]}={float(values[i])!r}" for i in np.flatnonzero(huge)]
            raise MessageError(f"{self.topic}: value(s) {', '.join(bad)} at t = {seconds_text(stamp_ns)} s beyond "
                               f"{MAX_ANALYSIS_SCALE:g} (expected numbers the analysis can take; a bad-value sentinel?)")
        return stamp_ns, values

    def encode(self, values, stamp_ns: int, frame_id: str = ""):
        """A ``sensor_msgs/msg/JointState`` holding ``values`` (shape (n_channels,)) at ``stamp_ns``."""
        from sensor_msgs.msg import JointState

        v = np.asarray(values, dtype=float).reshape(-1)
        if v.shape[0] != self.size:
            raise ValueError(f"{self.topic}: expected {self.size} values ({', '.join(self.names)}), got shape {v.shape}")
        msg = JointState()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = frame_id
        msg.name = list(self.names)
        msg.position = v.tolist()
        return msg


def unreadable_values(names, values) -> list:
    """The channels whose values no reader takes: not finite or beyond
    :data:`~mpm_monitor.core.logged_data.MAX_ANALYSIS_SCALE` (what :meth:`VectorCodec.decode` refuses).

    Parameters
    ----------
    names : sequence of str
        The channels' names.
    values : array_like, shape (len(names),)

    Returns
    -------
    list of (str, float)
        ``(name, value)`` of each such channel, in channel order (empty: all can be published).
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    bad = ~np.isfinite(v)
    bad[~bad] = np.abs(v[~bad]) > MAX_ANALYSIS_SCALE
    return [(names[i], float(v[i])) for i in np.flatnonzero(bad)]


def unreadable_text(stamp_ns: int, bad, label: str = "") -> str:
    """What a publisher about to send :func:`unreadable_values` says of them, for its one error line.

    Parameters
    ----------
    stamp_ns : int
        The sample's stamp, nanoseconds.
    bad : list of (str, float)
        :func:`unreadable_values` of the vector (not empty).
    label : str
        Put before each channel's name ("measured disturbance ", "dither "), or "".

    Returns
    -------
    str
        For example "y2 = 3.2e+41 at t = 412 s is beyond 1e+40, which no reader takes".
    """
    finite = [bool(np.isfinite(v)) for _, v in bad]
    what = (f"beyond {MAX_ANALYSIS_SCALE:g}" if all(finite) else "not finite" if not any(finite)
            else f"not finite or beyond {MAX_ANALYSIS_SCALE:g}")
    values = ", ".join(f"{label}{n} = {v:.3g}" for n, v in bad)
    verb = "is" if len(bad) == 1 else "are"
    return f"{values} at t = {seconds_text(stamp_ns)} s {verb} {what}, which no reader takes"


def message_class(msgtype: str):
    """The Python class of ``pkg/msg/Type``; :class:`ConfigurationError` if it is not installed."""
    pkg, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError):
        raise ConfigurationError(f"topics: message type {msgtype} is not installed") from None


# ----------------------------------------------------------------------------------------- QoS
def qos_profile(spec: QosSpec):
    """The ``rclpy.qos.QoSProfile`` of a :class:`~mpm_monitor.io.qos.QosSpec`."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(reliability=ReliabilityPolicy[spec.reliability.upper()],
                      history=HistoryPolicy[spec.history.upper()], depth=int(spec.depth),
                      durability=DurabilityPolicy[spec.durability.upper()],
                      liveliness=LivelinessPolicy[spec.liveliness.upper()])


def vector_qos():
    """QoS of the vector topics and of the lock-step ``/clock``: RELIABLE, KEEP_LAST 1000, VOLATILE."""
    return qos_profile(VECTOR_QOS)


def diagnostics_qos():
    """QoS of ``/diagnostics`` and of the RSI topic: RELIABLE, KEEP_LAST 10, VOLATILE."""
    return qos_profile(DIAGNOSTICS_QOS)


# ---------------------------------------------------------------------------------- parameters
# A parameter's type, default, description and range: :class:`mpm_monitor.core.options.ParamSpec`.
_PARAM_TYPES = {"bool": "PARAMETER_BOOL", "int": "PARAMETER_INTEGER", "double": "PARAMETER_DOUBLE",
                "string": "PARAMETER_STRING", "double_array": "PARAMETER_DOUBLE_ARRAY",
                "string_array": "PARAMETER_STRING_ARRAY"}


def descriptor(spec: ParamSpec):
    """The ``rcl_interfaces/msg/ParameterDescriptor`` of a :class:`ParamSpec` (type, description, range)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

    d = ParameterDescriptor(name=spec.name, type=getattr(ParameterType, _PARAM_TYPES[spec.kind]),
                            description=spec.description)
    if spec.numbers_as_text:
        d.dynamic_typing = True
    d.read_only = bool(spec.read_only or not spec.live)    # read once at start-up: a later change would be ignored
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if spec.kind == "int" and spec.low is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=0)]
    if spec.kind == "double" and spec.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    return d


def declare_parameters(node, specs: Sequence[ParamSpec]) -> dict:
    """Declare ``specs`` on ``node`` and return their checked values by name; a parameter given to the
    node that none of ``specs`` names is logged as a warning, one line each, with the closest name
    (:func:`unknown_overrides`: a misspelt name would otherwise be ignored without a word), unless another
    node of the suite declares it (:func:`suite_parameters`: those are named in one line at info level),
    and an integer given for a double parameter is taken as that double (:func:`_widen_integer_overrides`).

    Raises
    ------
    ConfigurationError
        A value of the wrong type or out of range (one line naming the parameter).
    """
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.parameter import Parameter

    _widen_integer_overrides(node, specs)
    out = {}
    for spec in specs:
        if spec.default is None:
            initial = Parameter.Type.DOUBLE_ARRAY if spec.kind == "double_array" else Parameter.Type.STRING_ARRAY
        else:
            initial = spec.default
        try:
            param = node.declare_parameter(spec.name, initial, descriptor(spec))
        except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
            raise ConfigurationError(_rclpy_refusal(exc, spec.name)) from None
        out[spec.name] = spec.check(param.value)
        for name in _ros_names(spec, out[spec.name]):
            check_ros_name(node, spec.name, name, service=spec.name.endswith("_service"))
    unknown = unknown_overrides(node)
    others = suite_parameters(exclude=specs) if unknown else {}
    for name in unknown:
        if name in others:
            continue
        node.get_logger().warning(f"parameter '{name}' is not a parameter of this node and is ignored"
                                  + _did_you_mean(name, [spec.name for spec in specs]))
    theirs = [name for name in unknown if name in others]
    if theirs:
        node.get_logger().info("parameters of other nodes of the suite, ignored here (a params file's shared "
                               "section): " + ", ".join(f"{name} ({', '.join(others[name])})" for name in theirs))
    node.add_on_set_parameters_callback(lambda params: _fixed_sim_time(node, params))
    guard_parameter_services(node)
    return out


def _fixed_sim_time(node, params):
    """Refuse a run-time change of ``use_sim_time`` (rclpy's, declared by every node): the nodes read their clock's
    kind once, at start-up (a setpoint node on its timer stopped without a word when its clock became /clock time,
    a recorder's log times jumped within one bag).  Runs before rclpy's own callback, which switches the clock."""
    from rcl_interfaces.msg import SetParametersResult

    for p in params:
        if p.name == "use_sim_time" and p.value != node.get_parameter("use_sim_time").value:
            return SetParametersResult(successful=False, reason="parameter use_sim_time: fixed at start-up (give "
                                       "-p use_sim_time:=true when the node starts)")
    return SetParametersResult(successful=True)


def _parameter_refusal(node, msg) -> Optional[str]:
    """Why a ``rcl_interfaces/msg/Parameter`` of a set request is refused before rclpy sees it (None: it is not): a
    name the node does not declare (rclpy took ``''`` as declared and added it; it refused others naming none) or a
    type no ParameterValue has (rclpy raised a ValueError out of the service callback, which ended the node)."""
    from rclpy.parameter import Parameter

    name = str(msg.name)
    if not name or not node.has_parameter(name):
        return (f"parameter {name!r}: not a parameter of this node"
                + (_did_you_mean(name, node.list_parameters([], 0).names) if name else ""))
    try:
        Parameter.Type(msg.value.type)
    except ValueError:
        return f"parameter {name}: value of type {msg.value.type}, which no ROS 2 parameter has"
    return None


def _named(name: str, result):
    """``result`` (a ``SetParametersResult``) whose refusal reason starts with ``parameter <name>: `` when it does not
    name the parameter (rclpy's "Wrong parameter type, expected ...", "Static parameter cannot be undeclared")."""
    if not result.successful and not result.reason.startswith(f"parameter {name}"):
        reason = " ".join(result.reason.split()) or "refused"
        result.reason = f"parameter {name}: {reason}"
    return result


def guard_parameter_services(node) -> None:
    """Put a guard before rclpy's ``~/set_parameters`` and ``~/set_parameters_atomically`` callbacks on ``node``.

    A request is refused, ``successful=False`` with one line naming the parameter, when a parameter's name is not
    one the node declares or its value's type is none ROS 2 has (:func:`_parameter_refusal`); any other exception
    of rclpy's callback is a refusal too, never one out of the executor (which ended the node).  rclpy's own
    refusals are given the parameter's name (:func:`_named`).
    """
    from rcl_interfaces.msg import SetParametersResult
    from rcl_interfaces.srv import SetParameters, SetParametersAtomically

    def refused(reason: str):
        return SetParametersResult(successful=False, reason=reason)

    def failed(exc: Exception) -> str:
        return f"{type(exc).__name__}: {exc}".splitlines()[0]

    def set_each(inner):
        def callback(request, response):
            for msg in request.parameters:
                reason = _parameter_refusal(node, msg)
                if reason is None:
                    try:
                        one = inner(SetParameters.Request(parameters=[msg]), SetParameters.Response())
                        result = _named(str(msg.name), one.results[0])
                    except Exception as exc:    # noqa: BLE001 - a service call never takes the node down
                        result = refused(f"parameter {msg.name}: {failed(exc)}")
                else:
                    result = refused(reason)
                response.results.append(result)
            return response
        return callback

    def set_atomically(inner):
        def callback(request, response):
            reasons = [r for r in (_parameter_refusal(node, msg) for msg in request.parameters) if r]
            if reasons:
                response.result = refused(reasons[0])
                return response
            try:
                response = inner(request, response)
            except Exception as exc:            # noqa: BLE001 - as above
                response.result = refused(failed(exc))
            if len(request.parameters) == 1:
                _named(str(request.parameters[0].name), response.result)
            return response
        return callback

    full = node.get_fully_qualified_name().rstrip("/")
    wrap = {(SetParameters, f"{full}/set_parameters"): set_each,
            (SetParametersAtomically, f"{full}/set_parameters_atomically"): set_atomically}
    for service in node.services:        # rclpy's parameter services, not ~/start_dither (a SetParameters too)
        guard = wrap.get((service.srv_type, node.resolve_service_name(service.srv_name)))
        if guard is not None and not getattr(service, "_mpm_guarded", False):
            service.callback = guard(service.callback)
            service._mpm_guarded = True


def _did_you_mean(name: str, names) -> str:
    """``": did you mean 'x'?"`` with the parameter of ``names`` closest to ``name``, or '' when none is close."""
    close = difflib.get_close_matches(name, list(names), n=1)
    return f": did you mean '{close[0]}'?" if close else ""


def _rclpy_refusal(exc: Exception, name: str) -> str:
    """The one line of rclpy's refusal ``exc`` of parameter ``name`` (an ``InvalidParameterValueException``, or an
    ``InvalidParameterTypeException``: "wrong type: ...")."""
    from rclpy.exceptions import InvalidParameterTypeException

    wrong = "wrong type: " if isinstance(exc, InvalidParameterTypeException) else ""
    return f"parameter {name}: {wrong}{_reason(exc, name)}"


def _reason(exc: Exception, name: str) -> str:
    """The first line of rclpy's parameter exception, without the ``": <name>"`` it appends (the message names
    the parameter first already)."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    suffix = f": {name}"
    return text[:-len(suffix)] if text.endswith(suffix) and len(text) > len(suffix) else text


def suite_parameters(exclude: Sequence[ParamSpec] = ()) -> dict:
    """Parameter name -> the default names of the suite's nodes that declare it (``plant``, ``mpc``,
    ``setpoint``, ``monitor``, ``mpm_recorder``, ``mpm_replay``), leaving out the names of ``exclude``.

    One params file often serves every node of a launch, its common settings in a ``/**`` section:
    each node is then given the others' parameters too.  :func:`declare_parameters` names those in one
    line at info level instead of a warning each (a warning stays for a name no node declares: a
    misspelling).  The nodes' modules are imported here (only when a node was given a parameter it does
    not declare).
    """
    from .params_files import NODES

    skip = {spec.name for spec in exclude}
    out: dict = {}
    for node_name, (module, _) in NODES.items():
        for spec in importlib.import_module(f"mpm_monitor.nodes.{module}").PARAMS:
            if spec.name not in skip:
                out.setdefault(spec.name, []).append(node_name)
    return out


def _given(node) -> dict:
    """The parameters given to ``node`` (params files, ``--ros-args -p``, ``parameter_overrides``) by name:
    rclpy keeps them, with no public accessor, in ``Node._parameter_overrides`` ({} if absent)."""
    given = getattr(node, "_parameter_overrides", None)
    return given if isinstance(given, dict) else {}


def _widened(p, kinds: dict):
    """``p`` (an ``rclpy.parameter.Parameter``) with an integer (array) value as a double (array) when
    ``kinds[p.name]`` is ``"double"`` (``"double_array"``); else ``p`` itself."""
    from rclpy.parameter import Parameter

    kind = kinds.get(p.name)
    if kind == "double" and p.type_ == Parameter.Type.INTEGER:
        return Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
    if kind == "double_array" and p.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in p.value])
    return p


def _widen_integer_overrides(node, specs: Sequence[ParamSpec]) -> None:
    """Give a double (or double array) parameter set to an integer (``stale_timeout: 10`` in a params file,
    ``-p stale_timeout:=10``, and later ``ros2 param set`` of a live one) its value as a double: rclpy
    refuses an INTEGER value for a DOUBLE parameter ("wrong type"), which no user means.  The values
    given at start-up are widened before they are declared (declaring calls no callback); a set
    afterwards, by a pre-set callback."""
    kinds = {spec.name: spec.kind for spec in specs if spec.kind in ("double", "double_array")}
    if not kinds:
        return
    given = _given(node)
    for name in kinds:
        if name in given:
            given[name] = _widened(given[name], kinds)
    node.add_pre_set_parameters_callback(lambda params: [_widened(p, kinds) for p in params])


def unknown_overrides(node) -> list:
    """The parameters given to ``node`` (a params file, ``--ros-args -p``, ``parameter_overrides``) that it
    has not declared, sorted: a misspelt name, or a parameter meant for other nodes (a params file's
    ``/**`` section).  rclpy ignores them without a word; :func:`declare_parameters` warns of each.
    ``qos_overrides.*`` are left out (rclpy declares them as publishers are made)."""
    return sorted(n for n in _given(node) if not node.has_parameter(n) and not n.startswith("qos_overrides."))


def _ros_names(spec: ParamSpec, value) -> list:
    """The topic or service names a parameter's value holds: a ``*_topic`` or ``*_service`` string (``''``
    none where ``spec.empty_is_none``), or the entries of a ``topics`` list (``name`` or ``name=pkg/msg/Type``)."""
    if spec.kind == "string" and (spec.name.endswith("_topic") or spec.name.endswith("_service")):
        return [value] if value or not spec.empty_is_none else []
    if spec.kind == "string_array" and spec.name == "topics":
        return [name for name in (str(v).split("=", 1)[0] for v in value or ()) if name]
    return []


def check_ros_name(node, param: str, name: str, service: bool = False) -> None:
    """Refuse a topic or service name that ROS 2 cannot use, as expanded on ``node``.

    Raises
    ------
    ConfigurationError
        One line naming the parameter, the name and why (instead of rclpy's exception, with its
        multi-line message, when the publisher, subscription or service is created).
    """
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name

    try:
        validate_full_topic_name(expand_topic_name(name, node.get_name(), node.get_namespace()), is_service=service)
    except Exception as exc:       # noqa: BLE001 - ValueError or rclpy's Invalid*NameException
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        text = text.split(" is invalid: ", 1)[-1].split(", at /", 1)[0].split(" name: ", 1)[-1].rstrip(":")
        what = "service" if service else "topic"
        raise ConfigurationError(f"parameter {param}: invalid {what} name {name!r}: {text}") from None


def check_distinct_topics(node, params: dict, names: Sequence[str]) -> None:
    """Refuse two of the parameters ``names`` (``setpoint_topic``, ``output_topic``, ...) whose topics are one
    topic on ``node`` (as given, expanded or remapped): each vector would be taken as both channels
    (``setpoint_topic:=output`` analysed r = y and reported a mismatch in every row).  Empty names are skipped.

    Raises
    ------
    ConfigurationError
        One line naming both parameters and the topic.
    """
    twice = repeated_topic((param, node.resolve_topic_name(params[param])) for param in names if params.get(param))
    if twice is not None:
        raise ConfigurationError(f"parameters {twice[0]} and {twice[1]} name one topic {twice[2]}: expected a topic "
                                 f"of its own for each")


def repeated_topic(named) -> Optional[tuple]:
    """The first two entries of ``named`` (``(label, resolved topic name)`` pairs, in order) that name one topic, as
    ``(first label, second label, topic)``; None when every topic is named once."""
    seen: dict = {}
    for label, topic in named:
        if topic in seen:
            return seen[topic], label, topic
        seen[topic] = label
    return None


def parameter_overrides(specs: Sequence[ParamSpec], overrides=None, **values) -> list:
    """``overrides`` plus one ``rclpy.parameter.Parameter`` per keyword value that is not None.

    For nodes whose constructor takes some parameters as keyword arguments (the recorder's
    ``bag_dir``, the replay's ``rate``, ...): each value is converted to its spec's type (a ``Path``
    to text, an int to a double, ...), so that it is declared and checked like a ``-p`` override.

    Parameters
    ----------
    specs : sequence of ParamSpec
        The node's parameters; every keyword must name one.
    overrides : list of rclpy.parameter.Parameter, optional
        Overrides given as such (kept first).
    """
    from rclpy.parameter import Parameter

    convert = {"bool": bool, "int": int, "double": float, "string": str,
               "double_array": lambda v: [float(x) for x in v], "string_array": lambda v: [str(x) for x in v]}
    kinds = {spec.name: spec.kind for spec in specs}
    out = list(overrides or [])
    out += [Parameter(name, value=convert[kinds[name]](v)) for name, v in values.items() if v is not None]
    return out


# ----------------------------------------------------------------------------------- spinning
def wait_acked(publishers, timeout: float) -> list:
    """Wait until every reliable reader of ``publishers`` acknowledged all they were sent, at most ``timeout`` s.

    A process that leaves right after its last message loses whatever its readers had not yet received: a
    reader that runs behind (the monitor, while the lock-step loop runs at the MPC's pace) never gets the
    last samples.  Before it leaves on its own, a node waits here.

    Parameters
    ----------
    publishers : sequence of rclpy.publisher.Publisher
    timeout : float
        Wall-clock seconds for all of them together.

    Returns
    -------
    list of str
        The topics whose readers had not acknowledged everything when the time ran out (empty: all had).
    """
    import time

    from rclpy.duration import Duration

    deadline = time.monotonic() + max(0.0, float(timeout))
    late = []
    for pub in publishers:
        left = max(0.0, deadline - time.monotonic())
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            late.append(pub.topic_name)
    return late


#: Wall-clock seconds a node leaving on its own waits at most for its readers (:func:`wait_for_readers`): the
#: plant's ``exit_ack_timeout`` by default, the MPC's after a divergence.
EXIT_ACK_TIMEOUT = 30.0


def wait_for_readers(node, publishers, timeout: float = EXIT_ACK_TIMEOUT) -> list:
    """The drain of a node that leaves on its own (done, or diverged): :func:`wait_acked` on its ``publishers``,
    and one warning when some readers had not acknowledged everything in time ("leaving after 30 s with messages
    not acknowledged on /output, /clock: a reader may lack the last ones sent": the plant's and the replay's
    /clock is not a vector topic, so the warning says messages).

    Parameters
    ----------
    node : rclpy.node.Node
        The node whose logger says it.
    publishers : sequence of rclpy.publisher.Publisher or None
        The publishers whose readers must have everything they were sent (None entries are left out: a
        publisher the node does not have).
    timeout : float
        Wall-clock seconds for all of them together.

    Returns
    -------
    list of str
        :func:`wait_acked`'s topics whose readers had not acknowledged everything (empty: all had).
    """
    late = wait_acked([p for p in publishers if p is not None], timeout)
    if late:
        # "messages", not "vectors": the topics named may be /clock (rosgraph_msgs/Clock) as well as vector topics.
        node.get_logger().warning(f"leaving after {timeout:g} s with messages not acknowledged on {', '.join(late)}: "
                                  f"a reader may lack the last ones sent")
    return late


def make_executor(context, kind: str = "events"):
    """An executor on ``context``: ``events`` (rclpy.experimental.EventsExecutor, fastest) or ``single``.

    The events executor must be driven by :func:`spin_until` (its ``spin()`` does not run timers on
    this rclpy version); the MultiThreadedExecutor is deliberately not offered (it collapses with a
    fast timer and many subscriptions).
    """
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    if kind == "single":
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor(context=context)
    raise ConfigurationError(f"executor: expected 'events' or 'single', got {kind!r}")


def spin_until(executor, done: Callable[[], bool], timeout: Optional[float] = None, context=None,
               step: float = 0.05) -> bool:
    """Spin ``executor`` with ``spin_once`` until ``done()`` is true, the context shuts down or ``timeout``.

    Parameters
    ----------
    executor : rclpy executor
    done : callable returning bool
    timeout : float or None
        Wall-clock seconds; None = no limit.
    context : rclpy.context.Context, optional
        Stop when it is no longer ``ok()``.
    step : float
        Longest wait of one ``spin_once``, seconds.

    Returns
    -------
    bool
        ``done()`` at the end.
    """
    import time

    deadline = None if timeout is None else time.monotonic() + timeout
    while not done():
        if context is not None and not context.ok():
            break
        if deadline is not None and time.monotonic() >= deadline:
            break
        try:
            executor.spin_once(timeout_sec=step)
        except Exception as exc:  # ExternalShutdownException and friends end the loop
            if type(exc).__name__ in ("ExternalShutdownException", "ShutdownException"):
                break
            raise
    return bool(done())


#: The SIGINT or SIGTERM (counted from the one that stops the node) that ends a node at once, however far
#: its stop has come (:func:`run_node`): the stop takes one, a launcher's forwarded copy of the same Ctrl-C
#: a second, and the third is a user who will not wait.
SIGNALS_TO_END_AT_ONCE = 3


def end_at_once(signum: int) -> None:
    """End the process now, with one line ``<program>: interrupted while stopping`` on stderr and exit code
    128 + ``signum`` (130 after SIGINT, 143 after SIGTERM).

    ``os._exit``: no ``finally`` runs and nothing unwinds through ``rclpy``'s C++ code (an exception raised
    there aborts the process); the node is not closed.

    Parameters
    ----------
    signum : int
        The signal that ended it.
    """
    from .entry import interrupted, program_name

    interrupted(program_name(), "while stopping")
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):    # closed or gone: the exit code says it
            pass
    os._exit(128 + int(signum))


def run_node(node_factory: Callable[..., Any], args=None, executor_kind: str = "events") -> int:
    """``main()`` of every node: init, build the node, spin until told to stop; bad parameters exit 2.

    Parameters
    ----------
    node_factory : callable
        Called with ``context=`` to build the node.
    args : list of str, optional
        Command-line arguments (``--ros-args ...``); default ``sys.argv``.
    executor_kind : {"events", "single"}

    Returns
    -------
    int
        0 after a stop, 2 (with one line ``error: ...`` on stderr) when the node refuses its
        parameters or inputs (:class:`~mpm_monitor.core.errors.InputError`) or a ``--params-file`` of its
        ROS arguments is no params file rcl reads (:mod:`~mpm_monitor.nodes.params_file_check`: said
        before ``rclpy.init``, so that rcl prints nothing of its own), 130 (with one line
        ``<program>: interrupted while starting``) after a Ctrl-C that came before the signal
        handlers below were in place, or the node's ``exit_code`` when it asked to end (the
        recorder's 1: its bag could not be written; the plant's and the MPC's 1: it diverged).

    Notes
    -----
    BLAS is limited to one thread first (:func:`mpm_monitor.limit_blas_threads`; the monitor's
    analysis process starts after this).  Until ``rclpy`` is imported and initialised, a Ctrl-C
    raises ``KeyboardInterrupt`` as usual: it is caught, the context shut down if it was
    initialised, and the process ends quietly (:func:`mpm_monitor.nodes.entry.interrupted`).
    From then on SIGINT and SIGTERM only set a flag that the spin loop
    checks, so a callback is never interrupted half-way.  The loop also ends when the node's
    ``exit_requested`` turns true.  Then the node's ``drain(executor)``, if it has one, handles what
    is already under way (the recorder takes the messages already delivered, the replay lets its
    publishers hand over what is queued; the plant and the MPC, leaving on their own, wait for their
    readers' acknowledgements, :func:`wait_for_readers`), its ``close()``, if any, runs (the monitor
    stops its analysis, the recorder closes its bag), the node is destroyed and the context shut down.

    The handlers stay in place until all of that is done, and only then are the previous ones (Python's
    ``KeyboardInterrupt`` for SIGINT) given back: a terminal's Ctrl-C reaches a launcher's whole process
    group and the launcher then forwards a SIGINT to its nodes, and that second SIGINT raised
    ``KeyboardInterrupt`` inside ``rclpy``'s C++ code as the node was destroyed, which aborted the
    process (``terminate called after throwing an instance of 'pybind11::error_already_set'``).  A
    second signal is taken quietly; the third (:data:`SIGNALS_TO_END_AT_ONCE`) ends the process at once
    (:func:`end_at_once`: one line, exit code 130 or 143), whether the spin, the drain or the close hangs.
    """
    import signal

    from .entry import interrupted, program_name

    limit_blas_threads()
    stop = {"requested": False, "signals": 0}

    def on_signal(signum, frame):
        stop["requested"] = True
        stop["signals"] += 1
        if stop["signals"] >= SIGNALS_TO_END_AT_ONCE:
            end_at_once(signum)

    context = None
    previous = {}
    try:
        problem = params_file_problem(sys.argv if args is None else args)   # before rclpy: no need of it
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
        import rclpy
        from rclpy.context import Context
        from rclpy.signals import SignalHandlerOptions

        context = Context()
        try:
            rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
        except Exception as exc:       # noqa: BLE001 - bad --ros-args (a -p rule, a remap; a params file the
            # check passed and rcl refuses): rcl has printed its own line before this one
            text = " ".join(str(exc).split())
            print(f"error: ROS arguments: {text[:300] or type(exc).__name__}", file=sys.stderr)
            return 2
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    except KeyboardInterrupt:          # a Ctrl-C before the handlers were in place
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if context is not None and context.ok():
            context.try_shutdown()
        return interrupted(program_name())
    node = None
    try:
        from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

        try:
            node = node_factory(context=context)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            # rclpy's own parameter (use_sim_time:=1), refused by rclpy.Node before the node declares its own
            name = str(exc).splitlines()[0].rsplit(": ", 1)[-1] if str(exc) else "?"   # rclpy ends it ": <name>"
            print(f"error: {_rclpy_refusal(exc, name)}", file=sys.stderr)
            return 2
        executor = make_executor(context, executor_kind)
        executor.add_node(node)
        spin_until(executor, lambda: stop["requested"] or getattr(node, "exit_requested", False), context=context,
                   step=0.1)
        drain = getattr(node, "drain", None)
        if drain is not None and context.ok():
            drain(executor)
        return int(getattr(node, "exit_code", 0) or 0)
    finally:
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
                node.destroy_node()
            if context.ok():
                context.try_shutdown()
        finally:
            for sig, handler in previous.items():     # only now: nothing of rclpy's runs after this
                signal.signal(sig, handler)


def resolve_model(model_file: str, case: str, which: str = "model"):
    """The model a node works with: from ``model_file``, or else from the paper ``case``.

    Parameters
    ----------
    model_file : str
        Path of a model file (docs/interfaces.md, "Model file"); "" = use ``case``.
    case : str
        A simulation case ("3.1", "3.2", "3.3" of the paper, or "level"); used when ``model_file`` is "".
    which : {"model", "plant"}
        The controller's model or the true plant of the case.
    """
    from ..io.model_file import load_model
    from ..sim.cases import CASE_NAMES, DEMO_CASES, simulation_case

    if model_file:
        return load_model(model_file)
    if not case:
        raise ConfigurationError("parameters model_file and case: give a model file (model_file) or a paper case "
                                 f"(case: one of {', '.join(CASE_NAMES)}) or the level case (case: level)")
    if case not in DEMO_CASES:
        raise ConfigurationError(f"parameter case: expected one of {', '.join(DEMO_CASES)} or '', got {case!r}")
    c = simulation_case(case)
    return c.plant if which == "plant" else c.model


MODEL_PARAMS = (
    ParamSpec("model_file", "string", "", "Model file (YAML, as in docs/interfaces.md, 'Model file'); '' = use the "
              "case."),
    ParamSpec("case", "string", "", "Simulation case used when model_file is '' (the paper's 3.1, 3.2 or 3.3, or "
              "level).", choices=("", "3.1", "3.2", "3.3", "level"), numbers_as_text=True),
)

#: The topic parameters of the contract's channels, ``<channel>_topic``, defaulting to the contract's names.
TOPIC_PARAMS = {
    "setpoint": ParamSpec("setpoint_topic", "string", "setpoint", "Topic of the setpoints r (JointState, one value "
                          "per output)."),
    "input": ParamSpec("input_topic", "string", "input", "Topic of the plant inputs u (JointState, one value per "
                       "input)."),
    "output": ParamSpec("output_topic", "string", "output", "Topic of the measured outputs y (JointState, one value "
                        "per output)."),
    "dither": ParamSpec("dither_topic", "string", "dither", "Topic of the input dither (JointState, one value per "
                        "input)."),
    "disturbance": ParamSpec("disturbance_topic", "string", "disturbance", "Topic of the measured disturbances dv "
                             "(JointState, one value per measured disturbance; used when the model has some)."),
    "clock": ParamSpec("clock_topic", "string", "/clock", "Topic of the simulated time (rosgraph_msgs/Clock)."),
}


def topic_params(*channels: str) -> tuple:
    """The :data:`TOPIC_PARAMS` of ``channels``, in that order (a node's ``PARAMS`` ends with them)."""
    return tuple(TOPIC_PARAMS[c] for c in channels)
