"""rosbag2 recordings of the project's topics: read, align, export, write, recover, recorded statuses.

The topics and messages are described in docs/interfaces.md ("ROS 2 topics and statuses").  One
module per job:

- :mod:`.common`: topic names, message types, the type store, opening a bag;
- :mod:`.read`: the setpoint, input, output (and disturbance) topics aligned into logged data
  (:func:`read_bag`, :func:`read_bag_channels`), CSV export, raw messages for replay; its
  tolerances (``GRID_TOLERANCE``, ``LONG_BAG_MESSAGES``) live there;
- :mod:`.write`: :class:`BagWriter` and :func:`write_logged_data`;
- :mod:`.recover`: a bag whose recorder was killed, rewritten as a closed bag;
- :mod:`.statuses`: the recorded ``/diagnostics`` and the monitor's verdict per row.

The package uses the ``rosbags`` library only; it never imports rclpy.
"""

from .common import (
    DEFAULT_DISTURBANCE_TOPIC,
    DEFAULT_TOPICS,
    DIAGNOSTIC_ARRAY,
    JOINT_STATE,
    default_typestore,
    open_reader,
    topic_name,
)
from .read import RawMessage, export_csv, infer_sample_time, read_bag, read_bag_channels, read_raw_messages
from .recover import recover_bag
from .statuses import ROW_STATUS_PREFIX, RecordedStatus, live_located_elements, read_diagnostics
from .write import BagWriter, contract_vector_qos, joint_state_cdr, write_logged_data

__all__ = [
    "BagWriter", "DEFAULT_DISTURBANCE_TOPIC", "DEFAULT_TOPICS", "DIAGNOSTIC_ARRAY", "JOINT_STATE",
    "ROW_STATUS_PREFIX", "RawMessage",
    "RecordedStatus", "contract_vector_qos", "default_typestore", "export_csv", "infer_sample_time",
    "joint_state_cdr", "live_located_elements", "open_reader", "read_bag", "read_bag_channels",
    "read_diagnostics", "read_raw_messages", "recover_bag", "topic_name", "write_logged_data",
]
