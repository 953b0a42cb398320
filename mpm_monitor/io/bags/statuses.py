"""Recorded diagnostics: the statuses of a bag's ``/diagnostics`` and the monitor's verdict per row.

The status names and values are those the monitor publishes (docs/interfaces.md, "ROS 2 topics and
statuses").
"""

from __future__ import annotations

import dataclasses
from contextlib import closing
from typing import Sequence

from ...core.errors import BagError
from .common import DIAGNOSTIC_ARRAY, none_read, open_reader, read_failure, stamp_ns, topic_connections, topic_name


@dataclasses.dataclass(frozen=True)
class RecordedStatus:
    """One ``diagnostic_msgs/msg/DiagnosticStatus`` of a recorded ``DiagnosticArray``.

    Attributes
    ----------
    stamp : float
        ``header.stamp`` of the array, seconds.
    log_time : int
        Time the recorder received the array, nanoseconds.
    name, message, hardware_id : str
    level : int
        0 OK, 1 WARN, 2 ERROR, 3 STALE.
    values : dict of str -> str
        The key/value pairs, in message order.
    """

    stamp: float
    log_time: int
    name: str
    level: int
    message: str
    hardware_id: str
    values: dict


def read_diagnostics(bag, topic: str = "/diagnostics") -> list:
    """Every status of every recorded ``DiagnosticArray``, in recording order.

    Parameters
    ----------
    bag : str or Path
    topic : str

    Returns
    -------
    list of RecordedStatus
    """
    topic = topic_name(topic)
    out, read = [], 0
    with closing(open_reader(bag)) as reader:
        conns = topic_connections(reader, bag, topic, DIAGNOSTIC_ARRAY)
        try:
            for conn, log_time, raw in reader.messages(connections=conns):
                read += 1
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = stamp_ns(msg.header.stamp) / 1e9
                for st in msg.status:
                    level = st.level
                    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
                    out.append(RecordedStatus(stamp=stamp, log_time=int(log_time), name=st.name, level=level,
                                              message=st.message, hardware_id=st.hardware_id,
                                              values={kv.key: kv.value for kv in st.values}))
        except Exception as exc:
            raise BagError(f"{bag}: topic '{topic}': cannot read: {read_failure(exc)}") from None
    if not read:
        raise none_read(bag, topic, conns)
    return out


ROW_STATUS_PREFIX = "mpm_monitor: row "


def live_located_elements(statuses: Sequence[RecordedStatus]) -> dict:
    """The monitor's latest verdict per row, from recorded diagnostics.

    Parameters
    ----------
    statuses : sequence of RecordedStatus
        As returned by :func:`read_diagnostics`, in recording order.

    Returns
    -------
    dict
        ``{"rows": {output: mismatch (bool)}, "located": set of (output, input)}`` from the last
        ``mpm_monitor: row <output>`` status of every output (``mismatch`` and ``flagged_inputs``
        values).
    """
    last = {}
    for st in statuses:
        if st.name.startswith(ROW_STATUS_PREFIX):
            last[st.name[len(ROW_STATUS_PREFIX):]] = st
    rows = {out: st.values.get("mismatch", "").strip().lower() == "true" for out, st in last.items()}
    located = {(out, inp.strip()) for out, st in last.items()
               for inp in st.values.get("flagged_inputs", "").split(",") if inp.strip()}
    return {"rows": rows, "located": located}
