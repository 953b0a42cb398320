"""Recorder node: the contract topics, ``/diagnostics``, ``mpm_monitor/rsi`` and ``/clock`` to a rosbag2.

The bag is a rosbag2 directory with MCAP storage and metadata version 9, written with ``rosbags``
(:class:`~mpm_monitor.io.bags.BagWriter`) from the serialized bytes of ``raw=True`` subscriptions, so
every message is stored exactly as its publisher sent it.  Each topic is stored with the QoS
profiles its publishers really offer (``get_publishers_info_by_topic``), as ``ros2 bag record``
does; the subscription itself is RELIABLE and VOLATILE (it matches every publisher but a
best-effort one, for which it switches to BEST_EFFORT).

Loss bound
----------
Every ``flush_period`` seconds (steady time) the pending MCAP chunk is closed, written and
``fsync``-ed.  On SIGINT or SIGTERM (and on :meth:`RecorderNode.close`) the node stops spinning,
takes what the middleware has already delivered (for at most ``drain_timeout`` seconds), writes it
and closes the bag properly (MCAP summary and ``metadata.yaml``): every message received before the
signal is kept, and a message can only be lost if it was still in transit when the recorder
stopped.  After a hard kill (SIGKILL, power loss) the chunks up to the last flush -- all but at most
``flush_period`` seconds of messages -- are on disk, but the bag lacks ``metadata.yaml`` and the
MCAP summary and must be re-indexed before readers accept it.

Parameters
----------
bag_dir : str
    Bag directory to create (must not exist); default ``mpm_bag_<date>-<time>``.
topics : str[]
    Topics to record; a known name (``setpoint``, ``input``, ``output``, ``disturbance``, ``dither``,
    ``/diagnostics``, ``mpm_monitor/rsi``, ``/clock``) or ``name=pkg/msg/Type``.  By default all of
    them but ``dither``; a topic nobody publishes (``disturbance`` of a loop without measured
    disturbances) leaves no trace in the bag.  Two entries that name one topic (``clock`` and
    ``/clock``, or a remapping) are refused, before the bag is made.
flush_period : float
    Seconds between flushes to disk, 0.01 to 60.
drain_timeout : float
    Seconds to keep taking already-delivered messages after a stop request, 0 to 10.
qos_wait : float
    Seconds to wait for the graph to show a topic's publishers before storing its first messages
    with the subscription's QoS instead, 0 to 10.
fsync : bool
    ``fsync`` on every flush.
max_bag_size : int
    Bytes after which the recording goes on in a new storage file (``<bag>_0.mcap``, ``<bag>_1.mcap``,
    ...), at the next flush; 0: no size limit.
max_bag_duration : float
    Seconds of messages after which the recording goes on in a new storage file, at the next flush;
    0: no duration limit.  With neither limit the bag holds one storage file, which grows for as long
    as the recorder runs, and so does the writer's index of its chunks in memory (about 210 bytes a
    flush: 18 MB a day at the default ``flush_period``); each split closes its file and frees its index.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("recorder_node")  # imports this module under its own name and ends the process

import dataclasses
import threading
import time
from typing import Optional, Sequence

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ..core.errors import BagError, ConfigurationError
from ..core.options import ParamSpec
from ..io.bags import BagWriter
from ..io.qos import RECORDER_QOS
from .ros_io import declare_parameters, message_class, parameter_overrides, qos_profile, repeated_topic, run_node

#: Message types of the topics the project publishes (docs/interfaces.md, "ROS 2 topics and statuses").
KNOWN_TOPIC_TYPES = {
    "setpoint": "sensor_msgs/msg/JointState",
    "input": "sensor_msgs/msg/JointState",
    "output": "sensor_msgs/msg/JointState",
    "dither": "sensor_msgs/msg/JointState",
    "disturbance": "sensor_msgs/msg/JointState",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "mpm_monitor/rsi": "std_msgs/msg/Float64MultiArray",
    "/clock": "rosgraph_msgs/msg/Clock",
    "clock": "rosgraph_msgs/msg/Clock",
}
#: What the recorder records by default.
DEFAULT_RECORD_TOPICS = ("setpoint", "input", "output", "disturbance", "/diagnostics", "mpm_monitor/rsi", "/clock")


@dataclasses.dataclass(frozen=True)
class RecorderOptions:
    """Validated recorder settings (see the module docstring for the meaning of each).

    Attributes
    ----------
    bag_dir : str
    topics : tuple of (str, str)
        (topic name as given, ``pkg/msg/Type``).
    flush_period, drain_timeout, qos_wait : float
        Seconds.
    fsync : bool
    max_bag_size : int
        Bytes; 0: none.
    max_bag_duration : float
        Seconds; 0: none.
    """

    bag_dir: str
    topics: tuple
    flush_period: float = 1.0
    drain_timeout: float = 0.5
    qos_wait: float = 1.0
    fsync: bool = True
    max_bag_size: int = 0
    max_bag_duration: float = 0.0

    RANGES = {"flush_period": (0.01, 60.0), "drain_timeout": (0.0, 10.0), "qos_wait": (0.0, 10.0),
              "max_bag_duration": (0.0, 1e9)}
    #: The largest ``max_bag_size``, bytes (a petabyte).
    MAX_BAG_SIZE = 10**15

    def __post_init__(self):
        if not isinstance(self.bag_dir, str) or not self.bag_dir.strip():
            raise ConfigurationError(f"bag_dir: expected a directory path, got {self.bag_dir!r}")
        for key, (lo, hi) in self.RANGES.items():
            val = getattr(self, key)
            if not isinstance(val, (int, float)) or not lo <= val <= hi:
                raise ConfigurationError(f"{key}: expected a number of seconds in [{lo:g}, {hi:g}], got {val!r}")
        if isinstance(self.max_bag_size, bool) or not isinstance(self.max_bag_size, int) \
                or not 0 <= self.max_bag_size <= self.MAX_BAG_SIZE:
            raise ConfigurationError(f"max_bag_size: expected a number of bytes in [0, {self.MAX_BAG_SIZE:g}] "
                                     f"(0: no limit), got {self.max_bag_size!r}")
        if not self.topics:
            raise ConfigurationError("topics: expected at least one topic to record")
        names = [n for n, _ in self.topics]
        if len(set(names)) != len(names):
            raise ConfigurationError(f"topics: a topic is listed twice: {', '.join(names)}")


_RANGES = RecorderOptions.RANGES
PARAMS = (
    ParamSpec("bag_dir", "string", "", "Bag directory to create (must not exist); '' = mpm_bag_<date>-<time>."),
    ParamSpec("topics", "string_array", list(DEFAULT_RECORD_TOPICS), "Topics to record: a known name (setpoint, "
              "input, output, disturbance, dither, /diagnostics, mpm_monitor/rsi, /clock) or name=pkg/msg/Type."),
    ParamSpec("flush_period", "double", 1.0, "Seconds between flushes to disk.", *_RANGES["flush_period"]),
    ParamSpec("drain_timeout", "double", 0.5, "Seconds to take already-delivered messages after a stop request.",
              *_RANGES["drain_timeout"]),
    ParamSpec("qos_wait", "double", 1.0, "Seconds to wait for a topic's publishers to show in the graph before "
              "storing it with the subscription QoS.", *_RANGES["qos_wait"]),
    ParamSpec("fsync", "bool", True, "fsync the bag file on every flush."),
    ParamSpec("max_bag_size", "int", 0, "Bytes after which the recording goes on in a new storage file "
              "(named after the bag directory: NAME_0.mcap, NAME_1.mcap, ...), at the next flush; 0 = no limit.",
              0, RecorderOptions.MAX_BAG_SIZE),
    ParamSpec("max_bag_duration", "double", 0.0, "Seconds of messages after which the recording goes on in a new "
              "storage file, at the next flush; 0 = no limit.", *_RANGES["max_bag_duration"]),
)


def parse_topic_specs(specs: Sequence[str]) -> tuple:
    """Topic list entries (``name`` or ``name=pkg/msg/Type``) as ``(name, type)`` pairs.

    Raises
    ------
    ConfigurationError
        An unknown name without a type, or a type not of the form ``pkg/msg/Type``.
    """
    out = []
    for spec in specs:
        spec = str(spec).strip()
        name, _, msgtype = spec.partition("=")
        name, msgtype = name.strip(), msgtype.strip()
        if not msgtype:
            msgtype = KNOWN_TOPIC_TYPES.get(name, "")
            if not msgtype:
                raise ConfigurationError(
                    f"topics: entry {spec!r}: unknown topic; give its type as name=pkg/msg/Type "
                    f"(known: {', '.join(sorted(KNOWN_TOPIC_TYPES))})")
        parts = msgtype.split("/")
        if not name or len(parts) != 3 or parts[1] != "msg" or not all(parts):
            raise ConfigurationError(f"topics: entry {spec!r}: expected name or name=pkg/msg/Type")
        out.append((name, msgtype))
    return tuple(out)


def bag_qos(profile: QoSProfile):
    """A rclpy QoS profile as the ``rosbags`` Qos stored in ``offered_qos_profiles``."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def enum(cls, policy):
        return cls.__members__.get(getattr(policy, "name", ""), cls.UNKNOWN)

    def dur(d):
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(history=enum(QosHistory, profile.history), depth=int(profile.depth),
               reliability=enum(QosReliability, profile.reliability),
               durability=enum(QosDurability, profile.durability),
               deadline=dur(profile.deadline), lifespan=dur(profile.lifespan),
               liveliness=enum(QosLiveliness, profile.liveliness),
               liveliness_lease_duration=dur(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def subscription_qos(best_effort: bool) -> QoSProfile:
    """The recorder's subscription profile (:data:`mpm_monitor.io.qos.RECORDER_QOS`), best effort if told so."""
    return qos_profile(RECORDER_QOS.best_effort() if best_effort else RECORDER_QOS)


def default_bag_dir(now: Optional[float] = None) -> str:
    """``mpm_bag_<YYYYmmdd-HHMMSS>`` for the given (default current) time."""
    return time.strftime("mpm_bag_%Y%m%d-%H%M%S", time.localtime(now))


class _Topic:
    """Book-keeping of one recorded topic."""

    def __init__(self, name: str, msgtype: str):
        self.name, self.msgtype = name, msgtype
        self.msg_class = message_class(msgtype)
        self.subscription = None
        self.best_effort = False
        self.resolved = ""
        self.pending: list = []       # (t_ns, bytes) before the topic's connection is in the bag
        self.pending_since = 0.0      # monotonic seconds
        self.received = 0


def _check_distinct(topics) -> None:
    """Refuse two entries of ``topics`` that name one topic (``clock`` and ``/clock``, a remapping): each message
    would be recorded twice."""
    twice = repeated_topic((tp.name, tp.resolved) for tp in topics)
    if twice is not None:
        raise ConfigurationError(f"topics: {twice[0]} and {twice[1]} are the same topic {twice[2]}: "
                                 f"expected each topic once")


class RecorderNode(Node):
    """Records topics to a rosbag2 (MCAP) directory until :meth:`close`.

    Parameters
    ----------
    bag_dir : str or Path, optional
        Overrides the ``bag_dir`` parameter.
    topics : sequence of str, optional
        Overrides the ``topics`` parameter (entries ``name`` or ``name=pkg/msg/Type``).
    node_name : str
    context : rclpy.context.Context, optional
    flush_period, drain_timeout, qos_wait : float, optional
        Override the parameters of the same names (seconds).
    **kwargs
        Passed to :class:`rclpy.node.Node` (``parameter_overrides``, ``namespace``, ...).

    Raises
    ------
    InputError
        A bad parameter value or an existing bag directory.
    """

    def __init__(self, bag_dir=None, *, topics: Optional[Sequence[str]] = None, node_name: str = "mpm_recorder",
                 context=None, flush_period: Optional[float] = None, drain_timeout: Optional[float] = None,
                 qos_wait: Optional[float] = None, **kwargs):
        overrides = parameter_overrides(PARAMS, kwargs.pop("parameter_overrides", None), bag_dir=bag_dir,
                                        topics=topics, flush_period=flush_period, drain_timeout=drain_timeout,
                                        qos_wait=qos_wait)
        super().__init__(node_name, context=context, parameter_overrides=overrides, **kwargs)
        self._lock = threading.RLock()
        self._closed = False
        self._writer = None
        self._timer = None
        self.failure = ""             # why the bag could not be written (the recording then stops)
        self.exit_requested = False   # run_node ends the spin: set when the bag cannot be written
        self.exit_code = 0
        p = declare_parameters(self, PARAMS)
        self.options = RecorderOptions(bag_dir=p["bag_dir"] or default_bag_dir(), topics=parse_topic_specs(p["topics"]),
                                       flush_period=p["flush_period"], drain_timeout=p["drain_timeout"],
                                       qos_wait=p["qos_wait"], fsync=p["fsync"], max_bag_size=p["max_bag_size"],
                                       max_bag_duration=p["max_bag_duration"])
        # The topics' types and names are checked before the bag is made: a refused parameter leaves no bag
        # behind (an empty one would make the corrected command's bag_dir "exist already").
        self._topics = [_Topic(n, t) for n, t in self.options.topics]
        for tp in self._topics:
            self._subscribe(tp, best_effort=self._publishers_best_effort(tp.name))
        _check_distinct(self._topics)
        self._writer = BagWriter(self.options.bag_dir, fsync=self.options.fsync, split_bytes=self.options.max_bag_size,
                                 split_seconds=self.options.max_bag_duration)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(self.options.flush_period, self._on_flush_timer, clock=steady)
        limits = [f"{self.options.max_bag_size:,} bytes"] * bool(self.options.max_bag_size) + \
            [f"{self.options.max_bag_duration:g} s"] * bool(self.options.max_bag_duration)
        self.get_logger().info(
            f"recording {', '.join(tp.resolved for tp in self._topics)} to {self.options.bag_dir} "
            f"(MCAP, flush every {self.options.flush_period:g} s"
            + (f", a new storage file after {' or '.join(limits)}" if limits else "") + ")")

    # -- set-up -----------------------------------------------------------------------------------

    def _subscribe(self, tp: _Topic, best_effort: bool) -> None:
        if tp.subscription is not None:
            self.destroy_subscription(tp.subscription)
        tp.best_effort = best_effort
        tp.subscription = self.create_subscription(
            tp.msg_class, tp.name, lambda data, tp=tp: self._on_message(tp, data),
            subscription_qos(best_effort), raw=True)
        tp.resolved = tp.subscription.topic_name

    def _publishers_best_effort(self, name: str) -> bool:
        return any(info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                   for info in self.get_publishers_info_by_topic(name))

    # -- recording --------------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        """Messages received so far (written or waiting for their topic's QoS)."""
        with self._lock:
            return sum(tp.received for tp in self._topics)

    @property
    def flushed_count(self) -> int:
        """Messages on disk so far."""
        with self._lock:
            return self._writer.flushed_count if self._writer is not None else 0

    @property
    def bag_dir(self) -> str:
        return self.options.bag_dir

    def _on_message(self, tp: _Topic, data: bytes) -> None:
        t = self.get_clock().now().nanoseconds
        with self._lock:
            if self._closed or self.failure:
                return
            tp.received += 1
            try:
                if self._writer.has_topic(tp.resolved):
                    self._writer.write(tp.resolved, t, data)
                    return
                if not tp.pending:
                    tp.pending_since = time.monotonic()
                tp.pending.append((t, data))
                self._add_to_bag(tp, force=False)
            except (OSError, BagError) as exc:
                self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        """The bag cannot be written (a full disk, a file system gone read-only): say so once, stop recording and
        ask :func:`~mpm_monitor.nodes.ros_io.run_node` to end the node (exit code 1) instead of raising from a
        callback.  Called with the lock held."""
        if self.failure:
            return
        why = getattr(exc, "strerror", None) or " ".join(str(exc).split()) or type(exc).__name__
        self.failure = f"cannot write the bag {self.options.bag_dir}: {why}"
        self.exit_requested, self.exit_code = True, 1
        self.get_logger().error(
            f"{self.failure}: recording stopped; {self._writer.flushed_count} messages are on disk up to the last "
            f"flush (if the bag cannot be closed, python -m mpm_monitor recover --bag {self.options.bag_dir} --out "
            f"NEW makes them readable)")

    def _add_to_bag(self, tp: _Topic, force: bool) -> None:
        """Register the topic with its publishers' QoS (once the graph shows them) and write its backlog."""
        infos = self.get_publishers_info_by_topic(tp.resolved)
        waited = time.monotonic() - tp.pending_since
        if not infos and not force and waited < self.options.qos_wait:
            return
        if infos:
            profiles = [bag_qos(info.qos_profile) for info in infos]
        else:
            self.get_logger().warning(f"{tp.resolved}: publishers not visible in the graph after {waited:.1f} s; "
                                      f"storing the recorder's subscription QoS")
            profiles = [bag_qos(subscription_qos(tp.best_effort))]
        self._writer.add_topic(tp.resolved, tp.msgtype, profiles)
        for t, data in tp.pending:
            self._writer.write(tp.resolved, t, data)
        tp.pending = []

    def _on_flush_timer(self) -> None:
        with self._lock:
            if self._closed or self.failure:
                return
            before = len(self._writer.closed_files)
            try:
                for tp in self._topics:
                    if tp.pending:
                        self._add_to_bag(tp, force=False)
                n = self._writer.flush()
            except (OSError, BagError) as exc:
                self._fail(exc)
                return
            closed = self._writer.closed_files[-1] if len(self._writer.closed_files) > before else None
        self.get_logger().debug(f"flushed {n} messages to disk")
        if closed:
            self.get_logger().info(f"closed storage file {closed} ({n} messages in the bag so far); the next message "
                                   f"begins the next one")
        for tp in self._topics:
            if not tp.best_effort and self._publishers_best_effort(tp.resolved):
                self.get_logger().warning(f"{tp.resolved}: a publisher offers BEST_EFFORT; re-subscribing best effort")
                self._subscribe(tp, best_effort=True)

    def drain(self, executor, timeout: Optional[float] = None) -> int:
        """Take messages the middleware has already delivered, until none arrive for 0.1 s or ``timeout``.

        Returns
        -------
        int
            Messages taken.
        """
        timeout = self.options.drain_timeout if timeout is None else timeout
        start = self.message_count
        deadline = time.monotonic() + timeout
        last, last_change = start, time.monotonic()
        while time.monotonic() < deadline and not self._closed:
            executor.spin_once(timeout_sec=0.02)
            now_count = self.message_count
            if now_count != last:
                last, last_change = now_count, time.monotonic()
            elif time.monotonic() - last_change > 0.1:
                break
        return self.message_count - start

    def close(self) -> int:
        """Stop recording, write everything received and close the bag properly.  Idempotent.

        Returns
        -------
        int
            Messages in the bag.
        """
        with self._lock:
            if self._closed or self._writer is None:
                return self._writer.message_count if self._writer is not None else 0
            self._closed = True
            try:
                if not self.failure:
                    for tp in self._topics:
                        if tp.pending:
                            self._add_to_bag(tp, force=True)
                self._writer.close()
            except (OSError, BagError) as exc:
                self._fail(exc)
                self.get_logger().error(f"the bag {self.options.bag_dir} could not be closed: its messages up to the "
                                        f"last flush are on disk for python -m mpm_monitor recover")
                return self._writer.flushed_count
            n = self._writer.message_count
        if self._timer is not None:
            self._timer.cancel()
        self.get_logger().info(f"closed bag {self.options.bag_dir}: {n} messages")
        if self._writer.crc_error:
            self.get_logger().warning(self._writer.crc_error)
        return n

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None) -> int:
    """Console script ``recorder_node``: record until SIGINT or SIGTERM, then close the bag (exit 2: bad parameter)."""
    return run_node(lambda context: RecorderNode(context=context), args, executor_kind="single")

