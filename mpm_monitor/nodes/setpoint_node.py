"""Setpoint generator node: PRBS or step/hold setpoints on ``setpoint``, optional input dither on ``dither``.

Wraps :class:`~mpm_monitor.sim.excitation.PrbsGenerator` and
:class:`~mpm_monitor.sim.excitation.StepHoldGenerator`.  One setpoint vector (and one dither vector) per
sample, triggered either

* by the simulated clock (``trigger: clock``): a vector stamped ``k * Ts`` each time the clock
  reaches a new grid point ``k * Ts`` (lock-step with the plant node); the same clock time again
  (the plant re-sends it when the loop stalls) re-sends the vectors of that stamp unchanged, and a
  clock that jumps back (a restarted plant) starts again from there, or
* by a timer (``trigger: timer``) every ``Ts`` of the node's clock, stamped with that clock.

With the same ``seed`` the PRBS equals the batch run's (:func:`~mpm_monitor.sim.closed_loop.seeded_generators`).

Parameters (all declared with type, description and range): see :data:`PARAMS`.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("setpoint_node")  # imports this module under its own name and ends the process

import time
from typing import Optional

import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState

from ..core.errors import ConfigurationError
from ..core.options import ParamSpec
from ..sim.closed_loop import seeded_generators
from ..sim.excitation import PrbsGenerator, PrbsOptions, StepHoldGenerator
from .ros_io import (
    MODEL_PARAMS,
    VectorCodec,
    check_distinct_topics,
    declare_parameters,
    period_ns,
    resolve_model,
    run_node,
    stamp_to_ns,
    topic_params,
    vector_qos,
)

PARAMS = MODEL_PARAMS + (
    ParamSpec("mode", "string", "prbs", "Setpoint signal: prbs (random binary, flat spectrum with "
              "switch_probability 0.5) or step (levels held for hold_samples each).", choices=("prbs", "step")),
    ParamSpec("seed", "int", 1, "Seed of the PRBS and the dither (same seed as a batch run gives the same data).",
              0, 2**31 - 1),
    ParamSpec("amplitude", "double", 1.0, "PRBS half peak-to-peak level, output units.", 0.0, 1e6),
    ParamSpec("switch_probability", "double", 0.5, "PRBS probability of a switch per sample.", 1e-6, 1.0),
    ParamSpec("min_hold", "int", 1, "PRBS minimum samples between switches.", 1, 10**6),
    ParamSpec("offset", "double", 0.0, "PRBS centre value, output units.", -1e6, 1e6),
    ParamSpec("levels", "double_array", None, "Step mode: setpoint vectors, flattened row by row "
              "(n_levels x n_outputs); unset = +amplitude then -amplitude on every output."),
    ParamSpec("hold_samples", "int", 100, "Step mode: samples each level is held.", 1, 10**9),
    ParamSpec("dither_amplitude", "double", 0.0, "PRBS dither added by the MPC to every input, input units "
              "(0 = no dither topic).", 0.0, 1e6),
    ParamSpec("dither_switch_probability", "double", 0.5, "Dither PRBS probability of a switch per sample.",
              1e-6, 1.0),
    ParamSpec("dither_min_hold", "int", 1, "Dither PRBS minimum samples between switches.", 1, 10**6),
    ParamSpec("trigger", "string", "clock", "clock: one sample per grid point of the clock topic (lock-step); "
              "timer: one sample every sample_time of the node's clock.", choices=("clock", "timer")),
) + topic_params("setpoint", "dither", "clock")


def build_setpoint_generator(p: dict, n_outputs: int, rng: np.random.Generator):
    """The setpoint generator from the node's parameter values."""
    if p["mode"] == "prbs":
        return PrbsGenerator(n_outputs, PrbsOptions(amplitude=p["amplitude"], switch_probability=p["switch_probability"],
                                                    min_hold=p["min_hold"], offset=p["offset"]), rng)
    levels = p["levels"]
    if levels is None:
        levels = [p["amplitude"]] * n_outputs + [-p["amplitude"]] * n_outputs
    if len(levels) == 0 or len(levels) % n_outputs:
        raise ConfigurationError(f"parameter levels: expected a multiple of {n_outputs} values (n_levels x n_outputs, "
                                 f"row by row), got {len(levels)}")
    return StepHoldGenerator(np.reshape(levels, (-1, n_outputs)), p["hold_samples"])


class SetpointNode(Node):
    """The setpoint generator node (see the module docstring)."""

    def __init__(self, name: str = "setpoint", **kwargs):
        super().__init__(name, **kwargs)
        self.params = p = declare_parameters(self, PARAMS)
        self.model = model = resolve_model(p["model_file"], p["case"])
        rngs = seeded_generators(p["seed"])
        self._gen = build_setpoint_generator(p, model.n_outputs, rngs["setpoint"])
        self._dither: Optional[PrbsGenerator] = None
        if p["dither_amplitude"] > 0:
            self._dither = PrbsGenerator(model.n_inputs, PrbsOptions(amplitude=p["dither_amplitude"],
                                                                     switch_probability=p["dither_switch_probability"],
                                                                     min_hold=p["dither_min_hold"]), rngs["dither"])
        self._period = period_ns(model.sample_time)
        check_distinct_topics(self, p, ["setpoint_topic", "dither_topic"]
                              + ["clock_topic"] * (p["trigger"] == "clock"))
        self._r_codec = VectorCodec.for_channel(model, "setpoint", p["setpoint_topic"])
        self._d_codec = VectorCodec.for_channel(model, "dither", p["dither_topic"])
        self._pub = self.create_publisher(JointState, p["setpoint_topic"], vector_qos())
        self._dither_pub = (self.create_publisher(JointState, p["dither_topic"], vector_qos())
                            if self._dither is not None else None)
        self._last_k: Optional[int] = None
        self._last_t: Optional[int] = None
        self._sent: tuple = ()          # the messages of the last clock-triggered sample, re-sent on a repeated clock
        self._resent_at = -1.0
        self.published = 0
        self.resent = 0
        if p["trigger"] == "clock":
            self._sub = self.create_subscription(ClockMsg, p["clock_topic"], self._on_clock, vector_qos())
        else:
            self._timer = self.create_timer(model.sample_time, self._on_timer)
        self.get_logger().info(f"{p['mode']} setpoints on {model.n_outputs} outputs"
                               + (f", dither {p['dither_amplitude']:g} on {model.n_inputs} inputs" if self._dither else "")
                               + f", trigger {p['trigger']}")

    def _publish(self, stamp_ns: int) -> tuple:
        r = self._r_codec.encode(self._gen.next(), stamp_ns)
        self._pub.publish(r)
        d = None
        if self._dither is not None:
            d = self._d_codec.encode(self._dither.next(), stamp_ns)
            self._dither_pub.publish(d)
        self.published += 1
        return r, d

    def _on_clock(self, msg: ClockMsg) -> None:
        t = stamp_to_ns(msg.clock)
        k = (t + self._period // 1000) // self._period  # the grid point reached (tolerates rounding)
        last = self._last_k
        if last is not None and k <= last:
            if t == self._last_t:
                self._resend()
            elif k < last:
                self.get_logger().warning(f"clock went back to t = {t * 1e-9:.9g} s (from sample {last}): "
                                          f"restarting the samples there")
                self._last_k, self._last_t = k, t
                self._sent = self._publish(k * self._period)
            return  # else a finer clock between grid points
        self._last_k, self._last_t = k, t
        self._sent = self._publish(k * self._period)

    def _resend(self) -> None:
        """The same clock time again (the plant re-sends it on a stall): the same r(k) (and dither) again."""
        now = time.monotonic()
        if now - self._resent_at < 0.05:
            return  # a paused simulator repeating its clock fast: at most 20 re-sends a second
        self._resent_at = now
        r, d = self._sent
        self._pub.publish(r)
        if d is not None:
            self._dither_pub.publish(d)
        self.resent += 1
        self.get_logger().info(f"clock t = {self._last_t * 1e-9:.9g} s again: setpoint of that sample re-sent",
                               throttle_duration_sec=5.0)

    def _on_timer(self) -> None:
        self._publish(self.get_clock().now().nanoseconds)


def main(args=None) -> int:
    """Console script ``setpoint_node``."""
    return run_node(lambda context: SetpointNode(context=context), args)

