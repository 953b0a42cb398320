"""Replay node: publish a bag's contract topics so the live monitor can run against a recording.

Modes
-----
``time``
    Messages go out at their recorded (receive) times scaled by ``rate``: 1 = recorded speed,
    10 = ten times faster.  With ``publish_clock`` the node also publishes ``/clock`` with the
    replayed samples' stamps, so nodes with ``use_sim_time`` follow the recording.
``clock``
    Lock step with ``/clock``: each ``/clock`` message releases every recorded sample stamped at or
    before it, so whoever drives the clock (a simulator, a test, a stepping tool) sets the pace.

The messages are published as the recorded CDR bytes (no re-serialization), on topics named as
the ``topics`` parameter (relative names resolve in the node's namespace and can be remapped),
with the contract's vector QoS (RELIABLE, KEEP_LAST 1000, VOLATILE).

Parameters
----------
bag : str
    rosbag2 directory to replay.
topics : str[]
    Topics of the bag to replay, default ``setpoint``, ``input``, ``output``.
disturbance_topic : str
    The measured-disturbance topic, replayed as well when the bag holds it (default
    ``disturbance``; '' = not).
mode : str
    ``time`` or ``clock``.
rate : float
    Speed factor of ``time`` mode, 0.01 to 1000.
wait_for_subscribers : int
    ``time`` mode starts once every publisher has this many subscribers (0 = at once), 0 to 100.
publish_clock : bool
    ``time`` mode: also publish ``/clock``.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("replay_node")  # imports this module under its own name and ends the process

import bisect
import dataclasses
from typing import Optional, Sequence

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg

from ..core.errors import ConfigurationError
from ..core.options import ParamSpec
from ..io.bags import DEFAULT_DISTURBANCE_TOPIC, DEFAULT_TOPICS, read_raw_messages, topic_name
from ..io.qos import CLOCK_LISTENER_QOS, REPLAY_CLOCK_QOS
from .ros_io import (
    declare_parameters,
    message_class,
    ns_to_stamp,
    parameter_overrides,
    qos_profile,
    run_node,
    stamp_to_ns,
    vector_qos,
    wait_for_readers,
)

MODES = ("time", "clock")
#: Period of the publishing timer in ``time`` mode, seconds of steady time.
TICK = 0.005


@dataclasses.dataclass(frozen=True)
class ReplayOptions:
    """Validated replay settings (see the module docstring)."""

    bag: str
    topics: tuple = DEFAULT_TOPICS
    mode: str = "time"
    rate: float = 1.0
    wait_for_subscribers: int = 0
    publish_clock: bool = False
    disturbance_topic: str = DEFAULT_DISTURBANCE_TOPIC
    exit_ack_timeout: float = 30.0

    RATE_RANGE = (0.01, 1000.0)
    SUBSCRIBER_RANGE = (0, 100)
    ACK_TIMEOUT_RANGE = (0.0, 3600.0)

    def __post_init__(self):
        if not isinstance(self.bag, str) or not self.bag.strip():
            raise ConfigurationError(f"bag: expected a rosbag2 directory, got {self.bag!r}")
        if not self.topics or any(not str(t).strip() for t in self.topics):
            raise ConfigurationError(f"topics: expected a list of topic names, got {list(self.topics)!r}")
        if self.mode not in MODES:
            raise ConfigurationError(f"mode: expected one of {', '.join(MODES)}, got {self.mode!r}")
        lo, hi = self.RATE_RANGE
        if not isinstance(self.rate, (int, float)) or not lo <= self.rate <= hi:
            raise ConfigurationError(f"rate: expected a speed factor in [{lo:g}, {hi:g}], got {self.rate!r}")
        lo, hi = self.SUBSCRIBER_RANGE
        if int(self.wait_for_subscribers) != self.wait_for_subscribers or not lo <= self.wait_for_subscribers <= hi:
            raise ConfigurationError(f"wait_for_subscribers: expected an integer in [{lo}, {hi}], "
                                     f"got {self.wait_for_subscribers!r}")
        lo, hi = self.ACK_TIMEOUT_RANGE
        if not isinstance(self.exit_ack_timeout, (int, float)) or not lo <= self.exit_ack_timeout <= hi:
            raise ConfigurationError(f"exit_ack_timeout: expected seconds in [{lo:g}, {hi:g}], "
                                     f"got {self.exit_ack_timeout!r}")


PARAMS = (
    ParamSpec("bag", "string", "", "rosbag2 directory to replay."),
    ParamSpec("topics", "string_array", list(DEFAULT_TOPICS), "Topics of the bag to replay."),
    ParamSpec("disturbance_topic", "string", DEFAULT_DISTURBANCE_TOPIC, "The measured-disturbance topic, replayed as "
              "well when the bag holds it ('' = not).", empty_is_none=True),
    ParamSpec("mode", "string", "time", "time: at recorded speed x rate; clock: lock step with /clock (samples "
              "stamped <= clock)."),
    ParamSpec("rate", "double", 1.0, "Speed factor of time mode.", *ReplayOptions.RATE_RANGE),
    ParamSpec("wait_for_subscribers", "int", 0, "time mode starts once every publisher has this many subscribers.",
              *ReplayOptions.SUBSCRIBER_RANGE),
    ParamSpec("publish_clock", "bool", False, "time mode: also publish /clock with the replayed stamps."),
    ParamSpec("exit_ack_timeout", "double", ReplayOptions.exit_ack_timeout, "Wall-clock seconds the process, leaving "
              "once every message is out, waits for its readers to acknowledge them all (a reader running behind "
              "would otherwise lose the last ones).", *ReplayOptions.ACK_TIMEOUT_RANGE),
)


class ReplaySchedule:
    """Which recorded messages are due, by elapsed replay time or by ``/clock``.

    Parameters
    ----------
    messages : sequence of RawMessage
        In recording order (:func:`~mpm_monitor.io.bags.read_raw_messages`).
    mode : {"time", "clock"}
    rate : float
        Speed factor (``time`` mode).
    topic_order : sequence of str
        Topic order among messages with the same stamp (``clock`` mode); default: as recorded.
    """

    def __init__(self, messages: Sequence, mode: str = "time", rate: float = 1.0,
                 topic_order: Optional[Sequence[str]] = None):
        self.mode = mode
        if mode == "clock":
            missing = [m.topic for m in messages if m.stamp is None]
            if missing:
                raise ConfigurationError(f"mode clock: topic '{missing[0]}' has no header stamp to step by")
            rank = {t: k for k, t in enumerate(topic_order or ())}
            order = sorted(range(len(messages)),
                           key=lambda k: (messages[k].stamp, rank.get(messages[k].topic, len(rank)), k))
            self.messages = [messages[k] for k in order]
            self._keys = [m.stamp for m in self.messages]
        else:
            self.messages = list(messages)
            t0 = self.messages[0].log_time if self.messages else 0
            self._keys = [(m.log_time - t0) / rate for m in self.messages]
        self._next = 0

    @property
    def finished(self) -> bool:
        """Every message has been released."""
        return self._next >= len(self.messages)

    @property
    def released(self) -> int:
        """Messages released so far."""
        return self._next

    def _release(self, key) -> list:
        end = bisect.bisect_right(self._keys, key, lo=self._next)
        out = self.messages[self._next:end]
        self._next = end
        return out

    def due_by_elapsed(self, elapsed_ns: float) -> list:
        """``time`` mode: the messages whose scaled recorded offset is at most ``elapsed_ns``."""
        return self._release(elapsed_ns)

    def due_by_clock(self, clock_ns: int) -> list:
        """``clock`` mode: the messages stamped at or before ``clock_ns``."""
        return self._release(clock_ns)


class ReplayNode(Node):
    """Publishes a bag's topics in ``time`` or ``clock`` mode until every message is out.

    Parameters
    ----------
    bag : str or Path, optional
        Overrides the ``bag`` parameter.
    topics, mode, rate, wait_for_subscribers, publish_clock, disturbance_topic : optional
        Override the parameters of the same names.
    node_name : str
    context : rclpy.context.Context, optional
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    Raises
    ------
    InputError
        A bad parameter or an unreadable bag (:class:`~mpm_monitor.core.errors.BagError`).
    """

    def __init__(self, bag=None, *, topics: Optional[Sequence[str]] = None, mode: Optional[str] = None,
                 rate: Optional[float] = None, wait_for_subscribers: Optional[int] = None,
                 publish_clock: Optional[bool] = None, disturbance_topic: Optional[str] = None,
                 node_name: str = "mpm_replay", context=None, **kwargs):
        overrides = parameter_overrides(PARAMS, kwargs.pop("parameter_overrides", None), bag=bag, topics=topics,
                                        mode=mode, rate=rate, wait_for_subscribers=wait_for_subscribers,
                                        publish_clock=publish_clock, disturbance_topic=disturbance_topic)
        super().__init__(node_name, context=context, parameter_overrides=overrides, **kwargs)
        p = declare_parameters(self, PARAMS)
        self.options = o = ReplayOptions(bag=p["bag"], topics=tuple(p["topics"]), mode=p["mode"], rate=p["rate"],
                                         wait_for_subscribers=p["wait_for_subscribers"],
                                         publish_clock=p["publish_clock"], disturbance_topic=p["disturbance_topic"],
                                         exit_ack_timeout=p["exit_ack_timeout"])
        bag_topics = [topic_name(t) for t in o.topics]
        given = list(o.topics)
        optional = ()
        if o.disturbance_topic.strip() and topic_name(o.disturbance_topic) not in bag_topics:
            optional = (o.disturbance_topic,)
            given.append(o.disturbance_topic)
            bag_topics.append(topic_name(o.disturbance_topic))
        messages = read_raw_messages(o.bag, o.topics, optional=optional)
        self.schedule = ReplaySchedule(messages, o.mode, o.rate, topic_order=bag_topics)
        types = {m.topic: m.msgtype for m in messages}
        self._replay_pubs = {}
        for given_name, bag_topic in zip(given, bag_topics):
            if bag_topic in types:
                self._replay_pubs[bag_topic] = self.create_publisher(message_class(types[bag_topic]), given_name,
                                                                    vector_qos())
        self._clock_pub = self.create_publisher(ClockMsg, "/clock", qos_profile(REPLAY_CLOCK_QOS)) \
            if (o.publish_clock and o.mode == "time") else None
        self._last_clock = None
        self.published = 0
        self._start_ns = None
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = None
        if o.mode == "clock":
            self.create_subscription(ClockMsg, "/clock", self._on_clock, qos_profile(CLOCK_LISTENER_QOS))
        else:
            self._timer = self.create_timer(TICK, self._on_tick, clock=self._steady)
        self.get_logger().info(f"replaying {len(messages)} messages of {', '.join(self._replay_pubs)} from {o.bag} "
                               + (f"at {o.rate:g}x recorded speed" if o.mode == "time" else "in lock step with /clock"))

    @property
    def finished(self) -> bool:
        """Every message of the bag has been published."""
        return self.schedule.finished

    #: The node's main loop (:func:`~mpm_monitor.nodes.ros_io.run_node`) ends once every message is out.
    exit_requested = finished

    def drain(self, executor) -> None:
        """Spin a little so that the reliable publishers hand over what is queued before the process ends; once
        every message is out, also wait (at most ``exit_ack_timeout`` s) until the readers acknowledge them all:
        a reader running behind would otherwise lose the last messages when the process leaves.  The wait, and
        the one warning naming the topics whose readers had not acknowledged everything by then, are the plant's
        and the MPC's (:func:`~mpm_monitor.nodes.ros_io.wait_for_readers`)."""
        for _ in range(10):
            executor.spin_once(timeout_sec=0.02)
        if self.finished:
            wait_for_readers(self, [*self._replay_pubs.values(), self._clock_pub], self.options.exit_ack_timeout)

    def _publish(self, messages) -> None:
        for m in messages:
            if self._clock_pub is not None and m.stamp is not None and m.stamp != self._last_clock:
                self._clock_pub.publish(ClockMsg(clock=ns_to_stamp(m.stamp)))
                self._last_clock = m.stamp
            self._replay_pubs[m.topic].publish(m.data)
            self.published += 1
        if messages and self.schedule.finished:
            self.get_logger().info(f"replay finished: {self.published} messages")

    def _on_tick(self) -> None:
        now = self._steady.now().nanoseconds
        if self._start_ns is None:
            need = self.options.wait_for_subscribers
            if any(p.get_subscription_count() < need for p in self._replay_pubs.values()):
                return
            self._start_ns = now
        self._publish(self.schedule.due_by_elapsed(now - self._start_ns))
        if self.schedule.finished and self._timer is not None:
            self._timer.cancel()

    def _on_clock(self, msg: ClockMsg) -> None:
        self._publish(self.schedule.due_by_clock(stamp_to_ns(msg.clock)))


def main(args=None) -> int:
    """Console script ``replay_node``: replay until every message is out or SIGINT/SIGTERM (2: bad parameter)."""
    return run_node(lambda context: ReplayNode(context=context), args, executor_kind="single")

