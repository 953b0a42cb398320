"""Plant simulator node: a MIMO plant with disturbance and noise, measured on ``output``.

Wraps :class:`~mpm_monitor.sim.plant.PlantSimulator` (every element structure).  When the plant has
measured disturbances the node generates them too
(:class:`~mpm_monitor.sim.excitation.MeasuredDisturbanceGenerator`, seeded by ``seed``, sized by the
``dv_*`` parameters) and publishes ``dv(k)`` on ``disturbance_topic`` (a ``JointState`` of the
disturbances' names) with the stamp of ``y(k)``, before ``y(k)``; they act on the plant with ``u(k)``.
Two ways to run:

* **lock-step** (``lock_step: true``, simulated time): the node owns the clock.  For sample ``k`` it
  publishes ``/clock = k * Ts`` and then ``y(k)`` stamped ``k * Ts``; when ``u(k)`` (stamped
  ``k * Ts``) arrives on ``input`` it applies it, advances to ``k + 1`` and repeats, as fast as
  the other nodes answer.  Nothing is dropped: the next sample waits for the controller.  With no
  ``u(k)`` for ``stall_timeout`` it re-sends the clock, ``dv(k)`` and ``y(k)`` (same stamp, same
  values), so a restarted controller picks the loop up again.
* **timer** (``lock_step: false``): every ``Ts`` of the node's clock (wall-clock, or simulated
  time with ``use_sim_time``) it applies the latest ``u`` (held if none came), advances and
  publishes ``y``; with ``publish_clock`` it also paces ``/clock`` at ``k * Ts`` in real time.

**A plant that diverges.** Every reader refuses a vector holding a value that is not finite or beyond
:data:`~mpm_monitor.core.logged_data.MAX_ANALYSIS_SCALE` (1e40; :meth:`VectorCodec.decode
<mpm_monitor.nodes.ros_io.VectorCodec.decode>`).  When ``y(k)`` (or ``dv(k)``) holds one -- an unstable
loop -- the node publishes nothing of sample ``k`` (no clock, no ``dv(k)``, no ``y(k)``) nor after it, logs
one error naming the sample's time, the channels and their values, stops its timers and asks to end:
:func:`~mpm_monitor.nodes.ros_io.run_node` returns its ``exit_code``.

**Exit codes** (the process, ``main``): 0 after a stop (SIGINT, SIGTERM) or after ``max_samples`` with
``exit_when_done``; 1 after the plant diverged (above); 2 for a bad parameter or params file; 130 for a Ctrl-C
while it starts.

Parameters (all declared with type, description and range): see :data:`PARAMS`.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("plant_node")  # imports this module under its own name and ends the process

import time
from typing import Optional

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState

from ..core.options import ParamSpec
from ..sim.closed_loop import seeded_generators
from ..sim.excitation import MeasuredDisturbanceGenerator, MeasuredDisturbanceOptions
from ..sim.plant import DisturbanceOptions, PlantSimulator
from .ros_io import (
    EXIT_ACK_TIMEOUT,
    MODEL_PARAMS,
    MessageError,
    VectorCodec,
    check_distinct_topics,
    declare_parameters,
    ns_to_stamp,
    period_ns,
    resolve_model,
    run_node,
    topic_params,
    unreadable_text,
    unreadable_values,
    vector_qos,
    wait_for_readers,
)

_DV = MeasuredDisturbanceOptions()

PARAMS = MODEL_PARAMS + (
    ParamSpec("seed", "int", 1, "Seed of the disturbance, the noise and the measured disturbances (same seed as a "
              "batch run gives the same data).", 0, 2**31 - 1),
    ParamSpec("disturbance_std", "double", 7.5e-3, "Std of the white noise driving the output disturbance, "
              "output units.", 0.0, 1e6),
    ParamSpec("disturbance_pole", "double", 0.95, "Pole p of the disturbance filter z/(z - p).", 0.0, 0.999999),
    ParamSpec("noise_std", "double", 5.0e-3, "Std of the white measurement noise, output units.", 0.0, 1e6),
    ParamSpec("dv_step_amplitude", "double", _DV.step_amplitude, "Measured disturbances (a plant with some): largest "
              "step level, their units (levels uniform in [-a, a]; 0 = no steps).", 0.0, 1e6),
    ParamSpec("dv_switch_probability", "double", _DV.switch_probability, "Measured disturbances: probability of a step "
              "per sample after dv_min_hold samples.", 1e-6, 1.0),
    ParamSpec("dv_min_hold", "int", _DV.min_hold, "Measured disturbances: fewest samples between two steps.", 1, 10**6),
    ParamSpec("dv_noise_std", "double", _DV.noise_std, "Measured disturbances: std of the first-order filtered "
              "noise added to the steps, their units (0 = none).", 0.0, 1e6),
    ParamSpec("dv_noise_pole", "double", _DV.noise_pole, "Measured disturbances: pole of the noise filter.",
              0.0, 0.999999),
    ParamSpec("dv_offset", "double", _DV.offset, "Measured disturbances: centre value, their units.", -1e6, 1e6),
    ParamSpec("lock_step", "bool", True, "Advance one sample per received input (simulated time, as fast as "
              "possible); false = advance on a timer every sample_time."),
    ParamSpec("publish_clock", "bool", True, "Publish the simulated time k * sample_time on clock_topic."),
    ParamSpec("max_samples", "int", 0, "Stop after this many samples (0 = run forever).", 0, 10**9),
    ParamSpec("autostart", "bool", True, "Start by itself once min_subscribers listen on output_topic (and on "
              "disturbance_topic, a plant with measured disturbances; in lock-step, an input publisher and a clock "
              "listener are matched too); false: the owner calls start()."),
    ParamSpec("min_subscribers", "int", 1, "Subscribers on output_topic (and, for a plant with measured "
              "disturbances, on disturbance_topic) to wait for before the first sample.", 0, 1000),
    ParamSpec("start_delay", "double", 0.5, "Wall-clock seconds to wait after min_subscribers are matched (lets the "
              "other nodes finish discovery).", 0.0, 600.0),
    ParamSpec("stall_timeout", "double", 2.0, "Wall-clock seconds without the expected input before a warning "
              "and a re-sent clock and output y(k) (lock-step; lets a restarted MPC pick the loop up).", 0.05, 3600.0),
    ParamSpec("exit_when_done", "bool", False, "Leave the process after max_samples."),
    ParamSpec("exit_ack_timeout", "double", EXIT_ACK_TIMEOUT, "Wall-clock seconds the process, leaving after "
              "max_samples or a divergence, waits for its readers to acknowledge every vector sent (a reader "
              "running behind, such as the monitor, would otherwise lose the last samples).", 0.0, 3600.0),
) + topic_params("output", "input", "clock", "disturbance")


def measured_disturbance_options_from_params(p: dict) -> MeasuredDisturbanceOptions:
    """:class:`~mpm_monitor.sim.excitation.MeasuredDisturbanceOptions` from the node's ``dv_*`` parameter values."""
    return MeasuredDisturbanceOptions(step_amplitude=p["dv_step_amplitude"],
                                      switch_probability=p["dv_switch_probability"], min_hold=p["dv_min_hold"],
                                      noise_std=p["dv_noise_std"], noise_pole=p["dv_noise_pole"],
                                      offset=p["dv_offset"])


def divergence_text(stamp_ns: int, bad, disturbances: bool = False) -> str:
    """The error line of a plant whose outputs (or measured disturbances) left what readers take.

    Parameters
    ----------
    stamp_ns : int
        The sample's stamp, nanoseconds.
    bad : list of (str, float)
        :func:`~mpm_monitor.nodes.ros_io.unreadable_values` of ``y(k)``, or of ``dv(k)``.
    disturbances : bool
        ``bad`` are measured disturbances, not outputs.

    Returns
    -------
    str
        For example "the plant diverged: y2 = 3.2e+41 at t = 412 s is beyond 1e+40, which no reader takes; the
        simulation stops (an unstable loop? check the model and the controller's tuning)".
    """
    lead, hint = (("the measured disturbances left the range readers take", "check the dv_* parameters")
                  if disturbances else
                  ("the plant diverged", "an unstable loop? check the model and the controller's tuning"))
    label = "measured disturbance " if disturbances else ""
    return f"{lead}: {unreadable_text(stamp_ns, bad, label)}; the simulation stops ({hint})"


#: Seconds of waiting to start (autostart) before the plant logs what it waits for, and between two such lines.
WAITING_LOG_AFTER = 5.0
WAITING_LOG_PERIOD = 10.0


class PlantNode(Node):
    """The plant simulator node (see the module docstring)."""

    def __init__(self, name: str = "plant", **kwargs):
        super().__init__(name, **kwargs)
        self.params = p = declare_parameters(self, PARAMS)
        self.model = model = resolve_model(p["model_file"], p["case"], which="plant")
        dist = DisturbanceOptions(disturbance_std=p["disturbance_std"], disturbance_pole=p["disturbance_pole"],
                                  noise_std=p["noise_std"])
        rngs = seeded_generators(p["seed"])
        self.sim = PlantSimulator(model, dist, rngs["plant"])
        self._period = period_ns(model.sample_time)
        check_distinct_topics(self, p, ["output_topic", "input_topic"]
                              + ["disturbance_topic"] * bool(model.n_disturbances)
                              + ["clock_topic"] * p["publish_clock"])
        self._y_codec = VectorCodec.for_channel(model, "output", p["output_topic"])
        self._u_codec = VectorCodec.for_channel(model, "input", p["input_topic"])
        #: The measured disturbances' generator, codec and publisher (None: the plant has none).
        self.dv_generator = self._dv_codec = self._dv_pub = None
        if model.n_disturbances:
            self.dv_generator = MeasuredDisturbanceGenerator(model.n_disturbances,
                                                             measured_disturbance_options_from_params(p),
                                                             rngs["measured_disturbance"])
            self._dv_codec = VectorCodec.for_channel(model, "disturbance", p["disturbance_topic"])
            self._dv_pub = self.create_publisher(JointState, p["disturbance_topic"], vector_qos())
        self._pub = self.create_publisher(JointState, p["output_topic"], vector_qos())
        self._clock_pub = self.create_publisher(ClockMsg, p["clock_topic"], vector_qos()) if p["publish_clock"] else None
        self._sub = self.create_subscription(JointState, p["input_topic"], self._on_input, vector_qos())
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.k = 0
        self.running = False
        self.finished = False
        self.exit_requested = False
        #: 0, or 1 once the plant diverged (:meth:`_emit`): the process's exit code (run_node returns it).
        self.exit_code = 0
        #: The error line once an output or a measured disturbance left what readers take ("" while bounded).
        self.diverged = ""
        self.rejected_inputs = 0
        self.held_inputs = 0
        self._u_latest: Optional[np.ndarray] = None
        self._u_fresh = False
        self._last_progress = time.monotonic()
        self._matched_at: Optional[float] = None
        self._created_at = time.monotonic()
        self._start_timer = None
        self._tick_timer = None
        self._stall_timer = None
        self._t0_ns = 0
        self._expected_stamp = 0
        self._y_msg: Optional[JointState] = None  # y(k) as published, re-sent unchanged on a stall
        self._dv_msg: Optional[JointState] = None  # dv(k) as published, re-sent unchanged on a stall
        self.resent = 0
        if p["autostart"]:
            self._start_timer = self.create_timer(0.05, self._try_start, clock=self._steady)
        dv = f" + {model.n_disturbances} measured disturbance(s)" if model.n_disturbances else ""
        self.get_logger().info(
            f"plant {model.n_outputs}x{model.n_inputs}{dv} ({model.name or 'model'}), Ts = {model.sample_time:g} s, "
            f"{'lock-step' if p['lock_step'] else 'timer'} mode, max_samples = {p['max_samples'] or 'unlimited'}")

    # ------------------------------------------------------------------------------- start
    def _try_start(self) -> None:
        if self.running:
            return
        missing = self._missing()
        if missing:
            self._matched_at = None
            if time.monotonic() - self._created_at >= WAITING_LOG_AFTER:
                self.get_logger().info(f"waiting to start: {'; '.join(missing)}",
                                       throttle_duration_sec=WAITING_LOG_PERIOD)
            return
        now = time.monotonic()
        if self._matched_at is None:
            self._matched_at = now
        if now - self._matched_at >= self.params["start_delay"]:
            self.start()

    def _missing(self) -> list:
        """What the start still waits for, one phrase each (empty: the loop can close): listeners on output (and on
        the measured disturbances, a plant with some) and, in lock-step, on the clock and an input publisher.

        A disturbance reader matched after the first sample (the MPC's feedforward, the monitor) would miss the
        first vectors: the MPC would wait for them (stamp-matched) until a stall re-sent them, the monitor would
        start its window later.
        """
        need, missing = self.params["min_subscribers"], []
        for pub, topic in ((self._pub, "output_topic"), (self._dv_pub, "disturbance_topic")):
            have = None if pub is None else pub.get_subscription_count()
            if have is not None and have < need:
                missing.append(f"{have} of min_subscribers = {need} subscriber(s) on {topic} {pub.topic_name}")
        if self.params["lock_step"]:
            if self._sub.get_publisher_count() < 1:
                missing.append(f"no publisher on input_topic {self._sub.topic_name} (lock-step)")
            if self._clock_pub is not None and self._clock_pub.get_subscription_count() < 1:
                missing.append(f"no subscriber on clock_topic {self._clock_pub.topic_name} (lock-step)")
        return missing

    def start(self) -> None:
        """Publish the first sample (lock-step) or start the sample timer."""
        if self.running:
            return
        self.running = True
        if self._start_timer is not None:
            self._start_timer.cancel()
        self._last_progress = time.monotonic()
        if self.params["lock_step"]:
            self._stall_timer = self.create_timer(min(0.5, self.params["stall_timeout"]), self._check_stall,
                                                  clock=self._steady)
            self._emit()
        else:
            self._t0_ns = self.get_clock().now().nanoseconds
            self._tick_timer = self.create_timer(self.model.sample_time, self._on_tick)
            self._emit()

    # ---------------------------------------------------------------------------- samples
    def _stamp_ns(self) -> int:
        """Stamp of sample k: ``k Ts`` in simulated time, ``t0 + k Ts`` on the node's clock otherwise.

        In timer mode the stamp is the nominal sampling instant (first tick + k Ts), not the jittered
        time the callback ran, as a sampled-data system stamps its samples.
        """
        if self.params["lock_step"] or self.params["publish_clock"]:
            return self.k * self._period
        return self._t0_ns + self.k * self._period

    def _emit(self) -> None:
        """Publish the clock, dv(k) (a plant with measured disturbances) and y(k); or, when y(k) or dv(k)
        holds a value no reader takes (the plant diverged), nothing: stop instead (:meth:`_stop_diverged`)."""
        stamp = self._stamp_ns()
        dv = None
        if self.dv_generator is not None:
            dv = self.dv_generator.next()
            bad = unreadable_values(self.model.disturbances, dv)
            if bad:                   # checked first: the simulator refuses a dv that is not finite
                self._stop_diverged(divergence_text(stamp, bad, disturbances=True))
                return
        y = self.sim.measure(dv=dv)
        bad = unreadable_values(self.model.outputs, y)
        if bad:
            self._stop_diverged(divergence_text(stamp, bad))
            return
        if self._clock_pub is not None:
            self._clock_pub.publish(ClockMsg(clock=ns_to_stamp(stamp)))
        if dv is not None:
            self._dv_msg = self._dv_codec.encode(dv, stamp)
            self._dv_pub.publish(self._dv_msg)
        self._expected_stamp = stamp
        self._y_msg = msg = self._y_codec.encode(y, stamp)
        self._pub.publish(msg)

    def _halt(self) -> None:
        """No more samples: not running, the tick and stall timers cancelled (after max_samples, or diverged)."""
        self.running = False
        for t in (self._tick_timer, self._stall_timer):
            if t is not None:
                t.cancel()

    def _stop_diverged(self, text: str) -> None:
        """The plant diverged: log ``text`` once as an error, stop the timers and ask to end with exit code 1.

        Publishing on would send values every reader refuses, one warning each, for ever.
        """
        self.diverged = text
        self._halt()
        self.get_logger().error(text)
        self.exit_requested, self.exit_code = True, 1

    def _advance(self, u: np.ndarray) -> None:
        self.sim.apply(u)
        self.k += 1
        self._last_progress = time.monotonic()
        limit = self.params["max_samples"]
        if limit and self.k >= limit:
            self.finished = True
            self._halt()
            self.get_logger().info(f"done: {self.k} samples")
            if self.params["exit_when_done"]:
                self.exit_requested = True
            return
        self._emit()

    def drain(self, executor) -> None:
        """Leaving on its own (after max_samples with ``exit_when_done``, or diverged): wait until the readers
        have every vector sent.

        Lock-step runs at the MPC's pace; a reader that runs behind (the monitor) still has the last
        hundreds of samples to receive when the plant is done, and a process that leaves at once loses
        them: a monitor asked for the whole run then never completes it.  Stopped by a signal, the plant
        leaves at once (its readers are being stopped too).
        """
        if self.exit_requested:
            wait_for_readers(self, (self._pub, self._clock_pub, self._dv_pub), self.params["exit_ack_timeout"])

    def _on_input(self, msg: JointState) -> None:
        try:
            stamp, u = self._u_codec.decode(msg)
        except MessageError as exc:
            self.rejected_inputs += 1
            self.get_logger().warning(f"input ignored: {exc}", throttle_duration_sec=1.0)
            return
        if not self.params["lock_step"]:
            self._u_latest, self._u_fresh = u, True
            return
        if not self.running:
            self.get_logger().warning("input ignored: the plant is not running", throttle_duration_sec=1.0)
            return
        if stamp != self._expected_stamp:
            self.rejected_inputs += 1
            self.get_logger().warning(
                f"input stamped t = {stamp * 1e-9:.9g} s ignored: waiting for the input of t = "
                f"{self._expected_stamp * 1e-9:.9g} s", throttle_duration_sec=1.0)
            return
        self._advance(u)

    def _on_tick(self) -> None:
        if not self.running:
            return
        if self._u_latest is None:
            u = np.zeros(self.model.n_inputs)
        else:
            u = self._u_latest
        if not self._u_fresh:
            self.held_inputs += 1
        self._u_fresh = False
        self._advance(u)

    def _check_stall(self) -> None:
        """Lock-step: no u(k) for stall_timeout: re-send the clock, dv(k) and y(k), same stamp and values.

        A restarted controller (or setpoint node) gets what it missed and the loop resumes; the
        setpoint node answers the repeated clock by re-sending r(k), and the MPC and the monitor
        keep one copy of a vector re-sent for the same stamp.
        """
        if not self.running:
            return
        waited = time.monotonic() - self._last_progress
        if waited >= self.params["stall_timeout"]:
            self.get_logger().warning(
                f"no input for t = {self._expected_stamp * 1e-9:.9g} s after {waited:.1f} s; re-sending the clock "
                f"and the output of that sample", throttle_duration_sec=5.0)
            if self._clock_pub is not None:
                self._clock_pub.publish(ClockMsg(clock=ns_to_stamp(self._expected_stamp)))
            if self._dv_msg is not None:
                self._dv_pub.publish(self._dv_msg)
            if self._y_msg is not None:
                self._pub.publish(self._y_msg)
            self.resent += 1
            self._last_progress = time.monotonic()


def main(args=None) -> int:
    """Console script ``plant_node``."""
    return run_node(lambda context: PlantNode(context=context), args)

