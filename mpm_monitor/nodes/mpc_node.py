"""MPC controller node: internal-model MPC from ``setpoint``, ``output`` (and ``disturbance``) to ``input``.

Wraps :class:`~mpm_monitor.sim.mpc.InternalModelMpc`.  The controller computes ``u(k)`` once it holds
the setpoint ``r(k)`` and the measurement ``y(k)`` with the same stamp (and the dither of that
stamp when ``use_dither``, and the measured disturbances ``dv(k)`` of that stamp on
``disturbance_topic`` when its model has some: its feedforward), and publishes it with that stamp;
vectors are buffered by stamp, so the arrival order of the topics does not matter and nothing is
dropped.  With ``hold_setpoint`` it computes ``u(k)`` as soon as ``y(k)`` (and ``dv(k)``) arrive,
with the latest setpoint (and dither) received: for a stack whose setpoints are published only
when they change.

Experiments: the service ``~/start_dither`` (``rcl_interfaces/srv/SetParameters``) starts a PRBS
dither on some inputs for a number of samples (docs/interfaces.md, "Detectability and experiment",
"Live experiment").  The request holds one DOUBLE per dithered input (its name; the PRBS amplitude,
input units) and one INTEGER ``samples``; the response one ``SetParametersResult`` (``successful``,
and in ``reason`` one line: what starts, or why not).  Refused: an amplitude above ``max_dither``
(0, the default, refuses every request), an amplitude that is not > 0, an unknown or repeated input,
``samples`` missing, < 1 or above ``max_dither_samples``, a dither already running, a node that adds
the dither of ``dither_topic`` (``use_dither``).  The dither starts with the next sample, is added to
``u`` by the controller (clipped to the input bounds) and stops by itself after ``samples`` samples;
while it runs the node publishes every sample's dither vector (``JointState`` of the inputs, zero on
the inputs not dithered) on ``dither_topic`` stamped with the sample, and after the last one a zero
vector stamped with the next sample, so that a bag shows when it ran.  The PRBS comes from a
generator seeded by ``seed`` (one stream for all the node's experiments).

Recovery in lock-step (the plant re-sends ``y(k)`` and the setpoint node ``r(k)`` when the loop
stalls): a vector re-sent for the stamp already answered is not a second sample; a re-sent ``y``
of that stamp gets the same ``u`` again (idempotent, in case the first one was lost), a re-sent
``r``, dither or ``dv`` is ignored.  A measurement whose stamp goes back (a restarted plant, at
``k = 0``), or a different ``y`` for the stamp just answered, restarts the controller: internal
model and previous move reset, with a warning.

**A controller that diverges.** Every reader refuses a vector holding a value that is not finite or beyond
:data:`~mpm_monitor.core.logged_data.MAX_ANALYSIS_SCALE` (1e40; :meth:`VectorCodec.decode
<mpm_monitor.nodes.ros_io.VectorCodec.decode>`): published, such a ``u(k)`` would keep the plant (lock-step)
re-sending ``y(k)`` for it, and the plant and the monitor warning of each, for ever.  When ``u(k)`` (or an
experiment's dither of sample ``k``) holds one -- an unstable loop, a near-singular controller -- the node
publishes nothing of sample ``k`` (no dither, no ``u(k)``) nor after it, logs one error naming the sample's
time, the channels and their values, takes no more vectors or experiments and asks to end:
:func:`~mpm_monitor.nodes.ros_io.run_node` lets its readers acknowledge the inputs (and dither) already
published, as a plant leaving on its own does (:meth:`MpcNode.drain`, at most 30 s), and returns its
``exit_code``.

**Exit codes** (the process, ``main``): 0 after a stop (SIGINT, SIGTERM); 1 after the controller diverged
(above); 2 for a bad parameter or params file; 130 for a Ctrl-C while it starts.

Parameters (all declared with type, description and range): see :data:`PARAMS`.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("mpc_node")  # imports this module under its own name and ends the process

import collections
import math
from typing import Optional, Sequence

import numpy as np
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from sensor_msgs.msg import JointState

from ..core.errors import ConfigurationError, InputError
from ..core.options import ParamSpec
from ..sim.excitation import TimedDither
from ..sim.mpc import InternalModelMpc, MpcOptions
from .ros_io import (
    MODEL_PARAMS,
    MessageError,
    VectorCodec,
    check_distinct_topics,
    declare_parameters,
    period_ns,
    resolve_model,
    run_node,
    topic_params,
    unreadable_text,
    unreadable_values,
    vector_qos,
    wait_for_readers,
)

PARAMS = MODEL_PARAMS + (
    ParamSpec("prediction_horizon", "int", 100, "Prediction horizon Hp, samples.", 1, 100000),
    ParamSpec("control_horizon", "int", 30, "Control horizon Hc, samples (<= prediction_horizon).", 1, 100000),
    ParamSpec("output_weight", "double_array", [1.0], "Weight Q on each output error (one value for all, or one "
              "per output), >= 0."),
    ParamSpec("input_weight", "double_array", [1.0], "Weight R on each input's distance from input_nominal (one "
              "value or one per input), >= 0."),
    ParamSpec("input_rate_weight", "double_array", [0.1], "Weight S on each input move (one value or one per "
              "input), >= 0."),
    ParamSpec("input_nominal", "double_array", None, "Nominal input u_nom, deviation variables, within 1e40 in "
              "magnitude (unset = 0)."),
    ParamSpec("u_min", "double_array", None, "Lower input bounds (one value or one per input, within 1e40 in "
              "magnitude; unset or -inf = none)."),
    ParamSpec("u_max", "double_array", None, "Upper input bounds (one value or one per input, within 1e40 in "
              "magnitude; unset or inf = none)."),
    ParamSpec("du_max", "double_array", None, "Largest input move per sample (unset = none)."),
    ParamSpec("qp_tolerance", "double", 1e-9, "Feasibility tolerance of the bounded QP (its exact active-set "
              "solver): how far a bound may be exceeded, relative to 1 + |value|.", 1e-15, 1.0),
    ParamSpec("use_dither", "bool", False, "Add the dither received on dither_topic to u (wait for it every sample)."),
    ParamSpec("hold_setpoint", "bool", False, "Compute u(k) on each y(k) with the latest setpoint instead of "
              "waiting for the setpoint of the same stamp."),
    ParamSpec("max_buffered", "int", 1000, "Vectors buffered per topic while waiting for their partners.", 1, 10**7),
    ParamSpec("max_dither", "double", 0.0, "Largest PRBS amplitude the ~/start_dither service accepts, input units "
              "(0 = the service refuses every request). Lowered while a dither runs above it, the dither ends at "
              "once.", 0.0, 1e6, live=True),
    ParamSpec("max_dither_samples", "int", 10000, "Longest dither the ~/start_dither service accepts, samples. "
              "Lowered below the samples a running dither has left, the dither ends at once.", 1, 10**7, live=True),
    ParamSpec("seed", "int", 1, "Seed of the PRBS of the ~/start_dither experiments.", 0, 2**31 - 1),
) + topic_params("setpoint", "output", "input", "dither", "disturbance")


def _weight(values, n: int, name: str):
    if values is None:
        return None
    if len(values) == 1:
        return float(values[0])
    if len(values) != n:
        raise ConfigurationError(f"parameter {name}: expected 1 or {n} values, got {len(values)}")
    return list(values)


def mpc_options_from_params(p: dict, n_outputs: int, n_inputs: int) -> MpcOptions:
    """:class:`~mpm_monitor.sim.mpc.MpcOptions` from the node's parameter values."""
    return MpcOptions(prediction_horizon=p["prediction_horizon"], control_horizon=p["control_horizon"],
                      output_weight=_weight(p["output_weight"], n_outputs, "output_weight"),
                      input_weight=_weight(p["input_weight"], n_inputs, "input_weight"),
                      input_rate_weight=_weight(p["input_rate_weight"], n_inputs, "input_rate_weight"),
                      input_nominal=_weight(p["input_nominal"], n_inputs, "input_nominal"),
                      u_min=_weight(p["u_min"], n_inputs, "u_min"), u_max=_weight(p["u_max"], n_inputs, "u_max"),
                      du_max=_weight(p["du_max"], n_inputs, "du_max"), qp_tolerance=p["qp_tolerance"])


def dither_text(inputs: Sequence[str], amplitudes) -> str:
    """``u4, u5 (amplitudes 0.08, 0.08)``: the dithered inputs of ``amplitudes`` (model order) in words."""
    on = [j for j, a in enumerate(amplitudes) if a > 0]
    word = "amplitude" if len(on) == 1 else "amplitudes"
    return f"{', '.join(inputs[j] for j in on)} ({word} {', '.join(f'{amplitudes[j]:g}' for j in on)})"


def parse_dither_request(parameters, inputs: Sequence[str], max_dither: float, max_samples: int) -> tuple:
    """The dither a ``~/start_dither`` request asks for, checked.

    Parameters
    ----------
    parameters : sequence of rcl_interfaces.msg.Parameter
        The request's parameters: one DOUBLE per dithered input (name = the input, value = PRBS
        amplitude in input units; an INTEGER is taken as a DOUBLE) and one INTEGER ``samples``.
    inputs : sequence of str
        The model's inputs.
    max_dither : float
        Largest amplitude accepted, input units (0: every request refused).
    max_samples : int
        Largest ``samples`` accepted.

    Returns
    -------
    amplitudes : ndarray, shape (n_inputs,)
        Amplitude of every input in model order (0 for the inputs not dithered).
    samples : int

    Raises
    ------
    InputError
        Why the request is refused, in one line.
    """
    if max_dither <= 0:
        raise InputError("dither experiments are disabled on this node (its max_dither parameter is 0)")
    index = {name: j for j, name in enumerate(inputs)}
    amplitudes = np.zeros(len(inputs))
    given, samples = set(), None
    for p in parameters:
        name, kind = str(p.name), p.value.type
        if name == "samples" and name not in index:
            if kind != ParameterType.PARAMETER_INTEGER:
                raise InputError("samples: expected an INTEGER number of samples")
            samples = int(p.value.integer_value)
            continue
        if name not in index:
            raise InputError(f"unknown input {name!r} (the inputs are {', '.join(inputs)}; and the INTEGER samples)")
        if name in given:
            raise InputError(f"input {name} given twice")
        given.add(name)
        if kind == ParameterType.PARAMETER_DOUBLE:
            a = float(p.value.double_value)
        elif kind == ParameterType.PARAMETER_INTEGER:
            a = float(p.value.integer_value)
        else:
            raise InputError(f"{name}: expected a DOUBLE amplitude (input units)")
        if not (math.isfinite(a) and a > 0):
            raise InputError(f"{name}: expected an amplitude > 0 (input units), got {a!r}")
        if a > max_dither:
            raise InputError(f"{name}: amplitude {a:g} above max_dither {max_dither:g} (input units)")
        amplitudes[index[name]] = a
    if not given:
        raise InputError("no input to dither: give one DOUBLE amplitude per input to dither")
    if samples is None:
        raise InputError("samples missing: give the INTEGER samples the dither lasts")
    if not 1 <= samples <= max_samples:
        raise InputError(f"samples {samples} outside [1, max_dither_samples = {max_samples}]")
    return amplitudes, samples


def divergence_text(stamp_ns: int, bad, dither: bool = False) -> str:
    """The error line of a controller whose input (or experiment's dither) left what readers take.

    Parameters
    ----------
    stamp_ns : int
        The sample's stamp, nanoseconds.
    bad : list of (str, float)
        :func:`~mpm_monitor.nodes.ros_io.unreadable_values` of ``u(k)``, or of the experiment's dither.
    dither : bool
        ``bad`` are the values of the dither, not of ``u(k)``.

    Returns
    -------
    str
        For example "the controller diverged: u3 = 4.1e+41 at t = 12 s is beyond 1e+40, which no reader takes;
        the controller stops (an unstable loop? check the model and the tuning)".
    """
    lead, hint = (("the dither left the range readers take", "check the ~/start_dither request")
                  if dither else
                  ("the controller diverged", "an unstable loop? check the model and the tuning"))
    label = "dither " if dither else ""
    return f"{lead}: {unreadable_text(stamp_ns, bad, label)}; the controller stops ({hint})"


class MpcNode(Node):
    """The MPC controller node (see the module docstring)."""

    def __init__(self, name: str = "mpc", **kwargs):
        super().__init__(name, **kwargs)
        self.params = p = declare_parameters(self, PARAMS)
        self.model = model = resolve_model(p["model_file"], p["case"])
        self.ctrl = InternalModelMpc(model, mpc_options_from_params(p, model.n_outputs, model.n_inputs))
        channels = (("r", "setpoint"), ("y", "output"), ("d", "dither"))
        if model.n_disturbances:
            channels += (("v", "disturbance"),)   # dv(k): the feedforward, stamp-matched like y(k)
        check_distinct_topics(self, p, [f"{ch}_topic" for _, ch in channels] + ["input_topic"])
        self._codecs = {key: VectorCodec.for_channel(model, ch, p[f"{ch}_topic"]) for key, ch in channels}
        self._u_codec = VectorCodec.for_channel(model, "input", p["input_topic"])
        self._buf = {key: collections.OrderedDict() for key, _ in channels}
        self._latest = {"r": None, "d": None}
        self._last_done: Optional[int] = None
        self._last_y: Optional[np.ndarray] = None   # y of the stamp last answered
        self._u_msg: Optional[JointState] = None    # u of the stamp last answered, as published
        self.steps = 0
        self.rejected = 0
        self.repeated = 0      # vectors re-sent for the stamp already answered (u re-sent for a y)
        self.restarts = 0      # stamps that went back: controller reset
        self.exit_requested = False
        #: 0, or 1 once the controller diverged (:meth:`_try`): the process's exit code (run_node returns it).
        self.exit_code = 0
        #: The error line once an input (or a dither) left what readers take ("" while bounded).
        self.diverged = ""
        self._pub = self.create_publisher(JointState, p["input_topic"], vector_qos())
        q = vector_qos()
        self._subs = [self.create_subscription(JointState, self._codecs[key].topic,
                                               (lambda msg, key=key: self._on_vector(key, msg)), q)
                      for key in ("r", "y") + (("d",) if p["use_dither"] else ())
                      + (("v",) if model.n_disturbances else ())]
        #: The experiment's dither while it runs (None otherwise); see the module docstring.
        self.experiment: Optional[TimedDither] = None
        self.experiments = 0   # dithers started by the service
        self._period_ns = period_ns(model.sample_time)
        self._dither_rng = np.random.default_rng(p["seed"])
        self._dither_pub = (None if p["use_dither"]
                            else self.create_publisher(JointState, p["dither_topic"], vector_qos()))
        self._dither_srv = self.create_service(SetParameters, "~/start_dither", self._on_start_dither)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(f"MPC {model.n_outputs}x{model.n_inputs}, Hp = {p['prediction_horizon']}, "
                               f"Hc = {p['control_horizon']}, {'hold' if p['hold_setpoint'] else 'stamp-matched'} "
                               f"setpoints{', dither' if p['use_dither'] else ''}"
                               f"{', feedforward of ' + ', '.join(model.disturbances) if model.n_disturbances else ''}")


    def _store(self, key: str, stamp: int, values: np.ndarray) -> bool:
        """Buffer a vector; False when it is not to be used (a repeat of the sample already answered)."""
        if self._last_done is not None and stamp <= self._last_done and not self._old_stamp(key, stamp, values):
            return False
        buf = self._buf[key]
        buf[stamp] = values
        if len(buf) > self.params["max_buffered"]:
            old, _ = buf.popitem(last=False)
            self.get_logger().warning(f"{key} stamped t = {old * 1e-9:.9g} s dropped: no partner arrived",
                                      throttle_duration_sec=1.0)
        return True

    def _old_stamp(self, key: str, stamp: int, values: np.ndarray) -> bool:
        """A vector stamped at or before the sample last answered (off the normal path): True = buffer it."""
        last = self._last_done
        if stamp == last:
            if key != "y":
                self.repeated += 1  # r, dither or dv re-sent on a stall: the sample is done
                return False
            if np.array_equal(values, self._last_y):
                self.repeated += 1  # y(k) re-sent on a stall: the same u(k) again, in case it was lost
                self._pub.publish(self._u_msg)
                self.get_logger().info(f"output of t = {stamp * 1e-9:.9g} s re-sent: the same input sent again",
                                       throttle_duration_sec=5.0)
                return False
        elif key != "y":
            return True  # may be the partner of a restarted plant's output: kept until that output comes
        self._restart(stamp)
        return True

    def _restart(self, stamp: int) -> None:
        """The plant's samples went back (a restarted plant): reset the controller and start again there."""
        self.get_logger().warning(f"output stamped t = {stamp * 1e-9:.9g} s after the sample of t = "
                                  f"{self._last_done * 1e-9:.9g} s: the plant restarted; controller reset "
                                  f"(internal model, previous move)")
        self.ctrl.reset()
        self._last_done = None
        self._last_y = self._u_msg = None
        for buf in self._buf.values():  # keep only what may belong to the new run's first sample
            for s in [s for s in buf if s != stamp]:
                del buf[s]
        self._latest["d"] = None
        self.restarts += 1
        if self.experiment is not None:
            self.get_logger().warning("dither experiment stopped: the plant restarted")
            self._end_experiment(stamp)

    def _on_vector(self, key: str, msg) -> None:
        """A setpoint (``r``), measurement (``y``), dither (``d``) or measured-disturbance (``v``) vector arrived."""
        if self.diverged:
            return  # stopped: the process is leaving (run_node), nothing more is answered
        try:
            stamp, values = self._codecs[key].decode(msg)
        except MessageError as exc:
            self.rejected += 1
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=1.0)
            return
        if key in ("r", "d") and self.params["hold_setpoint"]:
            first = self._latest[key] is None
            self._latest[key] = values
            if key == "r" and first:  # outputs that waited for the first setpoint
                for s in list(self._buf["y"]):
                    self._try(s)
            return
        if self._store(key, stamp, values):
            self._try(stamp)

    def _try(self, stamp: int) -> None:
        buf = self._buf
        y = buf["y"].get(stamp)
        if y is None:
            return
        dv = None
        if "v" in buf:
            dv = buf["v"].get(stamp)
            if dv is None:
                return  # y(k) waits for dv(k)
        dither = None
        if self.params["hold_setpoint"]:
            r = self._latest["r"]
            if r is None:
                return  # no setpoint yet: y waits for the first one
            if self.params["use_dither"]:
                dither = self._latest["d"] if self._latest["d"] is not None else np.zeros(self.model.n_inputs)
        else:
            r = buf["r"].get(stamp)
            if r is None:
                return
            if self.params["use_dither"]:
                dither = buf["d"].get(stamp)
                if dither is None:
                    return
        for key in buf:
            buf[key].pop(stamp, None)
        experiment = None
        if self.experiment is not None:
            experiment = self.experiment.next()
            bad = unreadable_values(self.model.inputs, experiment)
            if bad:                   # checked first: the controller would take it into u(k)
                self._stop_diverged(divergence_text(stamp, bad, dither=True))
                return
            dither = experiment if dither is None else dither + experiment
        u = self.ctrl.step(r, y, dither, dv=dv)
        bad = unreadable_values(self.model.inputs, u)
        if bad:
            self._stop_diverged(divergence_text(stamp, bad))
            return
        self._last_done = stamp
        self._last_y = y
        self.steps += 1
        if experiment is not None:
            self._dither_pub.publish(self._codecs["d"].encode(experiment, stamp))
        self._u_msg = msg = self._u_codec.encode(u, stamp)
        self._pub.publish(msg)
        if experiment is not None and not self.experiment.running:
            self.get_logger().info(f"dither experiment ended after {self.experiment.samples} samples")
            self._end_experiment(stamp + self._period_ns)

    def _stop_diverged(self, text: str) -> None:
        """The controller diverged: log ``text`` once as an error, stop (no vector answered, no experiment, the
        running one dropped without its zero vector) and ask to end with exit code 1.

        Publishing on would send inputs every reader refuses: the plant (lock-step) would re-send ``y(k)``
        for ever, answered with the same ``u(k)``, and every reader would warn of each.
        """
        self.diverged = text
        if self.experiment is not None:
            self.experiment.stop()
            self.experiment = None
        for buf in self._buf.values():
            buf.clear()
        self.get_logger().error(text)
        self.exit_requested, self.exit_code = True, 1

    def drain(self, executor) -> None:
        """Leaving on its own (diverged): wait until the readers have every input (and experiment dither) sent.

        As the plant's drain (:func:`~mpm_monitor.nodes.ros_io.wait_for_readers`, at most
        :data:`~mpm_monitor.nodes.ros_io.EXIT_ACK_TIMEOUT` s): a reader that runs behind the loop (the
        monitor, a recorder) has not yet received the last inputs when the controller stops, and a process that
        leaves at once takes them with it.  Nothing of the sample that diverged was published; stopped by a
        signal, the node leaves at once (its readers are being stopped too).

        Parameters
        ----------
        executor : rclpy executor
            The executor that spun the node (unused: the wait needs no spinning).
        """
        if self.exit_requested:
            wait_for_readers(self, (self._pub, self._dither_pub))

    # --------------------------------------------------------------------------- experiments
    def _end_experiment(self, stamp: int) -> None:
        """Stop the experiment and publish the zero dither vector stamped ``stamp`` (the first sample without)."""
        self.experiment.stop()
        self.experiment = None
        self._dither_pub.publish(self._codecs["d"].encode(np.zeros(self.model.n_inputs), stamp))

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Apply a change of the live parameters (``max_dither``, ``max_dither_samples``), checked as at
        start-up; a running dither beyond a lowered bound ends at once.  (The parameter services refuse
        every other parameter before this: they are read-only.)"""
        specs = {spec.name: spec for spec in PARAMS}
        staged = {}
        for prm in params:
            spec = specs.get(prm.name)
            if spec is None or not spec.live:
                continue
            try:
                staged[prm.name] = spec.check(prm.value)
            except ConfigurationError as exc:
                return SetParametersResult(successful=False, reason=str(exc).splitlines()[0])
        self.params.update(staged)
        e = self.experiment
        if e is not None and (float(np.max(e.amplitudes)) > self.params["max_dither"]
                              or e.samples_left > self.params["max_dither_samples"]):
            self.get_logger().warning(f"dither on {dither_text(self.model.inputs, e.amplitudes)} ended: beyond the "
                                      f"new max_dither {self.params['max_dither']:g} / max_dither_samples "
                                      f"{self.params['max_dither_samples']}")
            self._end_experiment(0 if self._last_done is None else self._last_done + self._period_ns)
        return SetParametersResult(successful=True)

    def _dither_refusal(self) -> Optional[str]:
        """Why no experiment can start now (None: it can)."""
        if self.diverged:
            return "the controller stopped: it diverged"
        if self.params["use_dither"]:
            return (f"this node adds the dither of {self.params['dither_topic']} (use_dither): no experiment "
                    f"on top of it")
        if self.experiment is not None:
            e = self.experiment
            return (f"a dither is already running on {dither_text(self.model.inputs, e.amplitudes)}, "
                    f"{e.samples_left} samples left")
        return None

    def _on_start_dither(self, request, response):
        """``~/start_dither`` (rcl_interfaces/SetParameters): start a dither experiment, or say why not."""
        p = self.params
        try:
            refusal = self._dither_refusal()
            if refusal is not None:
                raise InputError(refusal)
            amplitudes, samples = parse_dither_request(request.parameters, self.model.inputs, p["max_dither"],
                                                       p["max_dither_samples"])
            experiment = TimedDither(amplitudes, samples, self._dither_rng)
        except InputError as exc:
            ok, reason = False, f"refused: {exc}".splitlines()[0]
        except Exception as exc:  # a service call never takes the node down
            ok, reason = False, f"refused: {type(exc).__name__}: {exc}".splitlines()[0]
        else:
            self.experiment = experiment
            self.experiments += 1
            ok = True
            reason = (f"dither on {dither_text(self.model.inputs, amplitudes)} for {samples} samples, "
                      f"from the next sample")
        response.results = [SetParametersResult(successful=ok, reason=reason)]
        if ok:  # one call site per severity (rclpy refuses a severity change at the same call site)
            self.get_logger().info(f"~/start_dither: {reason}")
        else:
            self.get_logger().warning(f"~/start_dither: {reason}")
        return response


def main(args=None) -> int:
    """Console script ``mpc_node``."""
    return run_node(lambda context: MpcNode(context=context), args)

