"""The QoS of the project's topics, described once and without rclpy.

A :class:`QosSpec` says what a publisher or subscription asks for (reliability, history, depth,
durability, liveliness) as plain text and numbers.  The ROS 2 nodes build their ``rclpy`` profiles
from it (:func:`mpm_monitor.nodes.ros_io.qos_profile`); a bag writer stores it as the offered QoS of
a topic (:func:`rosbags_qos`) without importing rclpy.

The profiles (docs/interfaces.md, "ROS 2 topics and statuses"):

``VECTOR_QOS``
    The stamped-vector topics (``setpoint``, ``input``, ``output``, ``dither``) and the lock-step
    ``/clock``: RELIABLE, KEEP_LAST 1000, VOLATILE.  Lock step needs every message; the depth
    absorbs the bursts while a subscriber is busy.
``DIAGNOSTICS_QOS``
    ``/diagnostics`` and ``mpm_monitor/rsi``: RELIABLE, KEEP_LAST 10, VOLATILE.
``RECORDER_QOS``
    The recorder's subscriptions: as ``VECTOR_QOS`` with liveliness AUTOMATIC (it matches every
    publisher but a best-effort one, for which the recorder asks BEST_EFFORT instead).
``REPLAY_CLOCK_QOS``, ``CLOCK_LISTENER_QOS``
    The replay's ``/clock``: published RELIABLE, KEEP_LAST 10; followed BEST_EFFORT, KEEP_LAST 100
    (matches any clock publisher).
"""

from __future__ import annotations

import dataclasses

from ..core.errors import ConfigurationError

RELIABILITIES = ("reliable", "best_effort")
HISTORIES = ("keep_last", "keep_all")
DURABILITIES = ("volatile", "transient_local")
LIVELINESSES = ("system_default", "automatic")


@dataclasses.dataclass(frozen=True)
class QosSpec:
    """A QoS profile as plain data.

    Attributes
    ----------
    reliability : {"reliable", "best_effort"}
    history : {"keep_last", "keep_all"}
    depth : int
        Messages kept per topic (``keep_last``), >= 1.
    durability : {"volatile", "transient_local"}
    liveliness : {"system_default", "automatic"}
    """

    reliability: str = "reliable"
    history: str = "keep_last"
    depth: int = 10
    durability: str = "volatile"
    liveliness: str = "system_default"

    def __post_init__(self):
        for name, allowed in (("reliability", RELIABILITIES), ("history", HISTORIES),
                              ("durability", DURABILITIES), ("liveliness", LIVELINESSES)):
            if getattr(self, name) not in allowed:
                raise ConfigurationError(f"QoS {name}: expected one of {', '.join(allowed)}, "
                                         f"got {getattr(self, name)!r}")
        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 1:
            raise ConfigurationError(f"QoS depth: expected an integer >= 1, got {self.depth!r}")

    def best_effort(self) -> "QosSpec":
        """The same profile with BEST_EFFORT reliability."""
        return dataclasses.replace(self, reliability="best_effort")


VECTOR_QOS = QosSpec(reliability="reliable", history="keep_last", depth=1000, durability="volatile")
DIAGNOSTICS_QOS = QosSpec(reliability="reliable", history="keep_last", depth=10, durability="volatile")
RECORDER_QOS = dataclasses.replace(VECTOR_QOS, liveliness="automatic")
REPLAY_CLOCK_QOS = QosSpec(reliability="reliable", history="keep_last", depth=10, durability="volatile")
CLOCK_LISTENER_QOS = QosSpec(reliability="best_effort", history="keep_last", depth=100, durability="volatile")


def rosbags_qos(spec: QosSpec):
    """``spec`` as a publisher offers it, as a ``rosbags.interfaces.Qos`` for ``offered_qos_profiles``.

    System defaults are resolved as the middleware reports them for such a publisher: liveliness
    AUTOMATIC, and deadline, lifespan and liveliness lease infinite.
    """
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(9223372036, 854775807)
    return Qos(history=QosHistory[spec.history.upper()], depth=int(spec.depth),
               reliability=QosReliability[spec.reliability.upper()],
               durability=QosDurability[spec.durability.upper()], deadline=infinite, lifespan=infinite,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=infinite,
               avoid_ros_namespace_conventions=False)
