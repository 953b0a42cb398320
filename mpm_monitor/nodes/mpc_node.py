"""MPC controller node: internal-model MPC from ``setpoint`` and ``output`` to ``input``.

Wraps :class:`~mpm_monitor.sim.mpc.InternalModelMpc`.  The controller computes ``u(k)`` once it holds
the setpoint ``r(k)`` and the measurement ``y(k)`` with the same stamp (and the dither of that
stamp when ``use_dither``), and publishes it with that stamp; vectors are buffered by stamp, so
the arrival order of the topics does not matter and nothing is dropped.  With ``hold_setpoint``
it computes ``u(k)`` as soon as ``y(k)`` arrives, with the latest setpoint (and dither) received:
for a stack whose setpoints are published only when they change.

Recovery in lock-step (the plant re-sends ``y(k)`` and the setpoint node ``r(k)`` when the loop
stalls): a vector re-sent for the stamp already answered is not a second sample; a re-sent ``y``
of that stamp gets the same ``u`` again (idempotent, in case the first one was lost), a re-sent
``r`` or dither is ignored.  A measurement whose stamp goes back (a restarted plant, at
``k = 0``), or a different ``y`` for the stamp just answered, restarts the controller: internal
model and previous move reset, with a warning.

Parameters (all declared with type, description and range): see :data:`PARAMS`.
"""

from __future__ import annotations

import collections
from typing import Optional

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState

from ..core.errors import ConfigurationError
from ..core.options import ParamSpec
from ..sim.mpc import InternalModelMpc, MpcOptions
from .ros_io import (
    MODEL_PARAMS,
    MessageError,
    VectorCodec,
    declare_parameters,
    resolve_model,
    run_node,
    topic_params,
    vector_qos,
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
    ParamSpec("input_nominal", "double_array", None, "Nominal input u_nom, deviation variables (unset = 0)."),
    ParamSpec("u_min", "double_array", None, "Lower input bounds (one value or one per input; unset = none)."),
    ParamSpec("u_max", "double_array", None, "Upper input bounds (one value or one per input; unset = none)."),
    ParamSpec("du_max", "double_array", None, "Largest input move per sample (unset = none)."),
    ParamSpec("qp_tolerance", "double", 1e-9, "OSQP tolerance when bounds are active.", 1e-15, 1.0),
    ParamSpec("use_dither", "bool", False, "Add the dither received on dither_topic to u (wait for it every sample)."),
    ParamSpec("hold_setpoint", "bool", False, "Compute u(k) on each y(k) with the latest setpoint instead of "
              "waiting for the setpoint of the same stamp."),
    ParamSpec("max_buffered", "int", 1000, "Vectors buffered per topic while waiting for their partners.", 1, 10**7),
) + topic_params("setpoint", "output", "input", "dither")


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


class MpcNode(Node):
    """The MPC controller node (see the module docstring)."""

    def __init__(self, name: str = "mpc", **kwargs):
        super().__init__(name, **kwargs)
        self.params = p = declare_parameters(self, PARAMS)
        self.model = model = resolve_model(p["model_file"], p["case"])
        self.ctrl = InternalModelMpc(model, mpc_options_from_params(p, model.n_outputs, model.n_inputs))
        self._codecs = {key: VectorCodec.for_channel(model, ch, p[f"{ch}_topic"])
                        for key, ch in (("r", "setpoint"), ("y", "output"), ("d", "dither"))}
        self._u_codec = VectorCodec.for_channel(model, "input", p["input_topic"])
        self._buf = {"r": collections.OrderedDict(), "y": collections.OrderedDict(), "d": collections.OrderedDict()}
        self._latest = {"r": None, "d": None}
        self._last_done: Optional[int] = None
        self._last_y: Optional[np.ndarray] = None   # y of the stamp last answered
        self._u_msg: Optional[JointState] = None    # u of the stamp last answered, as published
        self.steps = 0
        self.rejected = 0
        self.repeated = 0      # vectors re-sent for the stamp already answered (u re-sent for a y)
        self.restarts = 0      # stamps that went back: controller reset
        self._pub = self.create_publisher(JointState, p["input_topic"], vector_qos())
        q = vector_qos()
        self._subs = [self.create_subscription(JointState, self._codecs[key].topic,
                                               (lambda msg, key=key: self._on_vector(key, msg)), q)
                      for key in ("r", "y") + (("d",) if p["use_dither"] else ())]
        self.get_logger().info(f"MPC {model.n_outputs}x{model.n_inputs}, Hp = {p['prediction_horizon']}, "
                               f"Hc = {p['control_horizon']}, {'hold' if p['hold_setpoint'] else 'stamp-matched'} "
                               f"setpoints{', dither' if p['use_dither'] else ''}")


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
                self.repeated += 1  # r or dither re-sent on a stall: the sample is done
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

    def _on_vector(self, key: str, msg) -> None:
        """A setpoint (``r``), measurement (``y``) or dither (``d``) vector arrived."""
        try:
            stamp, values = self._codecs[key].decode(msg)
        except MessageError as exc:
            self.rejected += 1
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=1.0)
            return
        if key != "y" and self.params["hold_setpoint"]:
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
        u = self.ctrl.step(r, y, dither)
        self._last_done = stamp
        self._last_y = y
        self.steps += 1
        self._u_msg = msg = self._u_codec.encode(u, stamp)
        self._pub.publish(msg)


def main(args=None) -> int:
    """Console script ``mpc_node``."""
    return run_node(lambda context: MpcNode(context=context), args)


if __name__ == "__main__":
    raise SystemExit(main())
