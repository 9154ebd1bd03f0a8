"""Writing test bags with rosbags, an independent ROS1 writer with its own record layout."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from darp.formats.realsense import ros_messages as rm


def realsense_typestore() -> Any:
    """rosbags' ROS1 Noetic type store with librealsense's StreamInfo and ImuIntrinsic registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    for msgtype in (rm.STREAM_INFO, rm.IMU_INTRINSIC):
        store.register(get_types_from_msg(msgtype.definition, msgtype.name.replace("/", "/msg/")))
    return store


def message_putter(writer: Any, store: Any) -> Callable[..., None]:
    """``put(topic, msgtype, message, time_ns=1)`` for an open rosbags ``Writer``: one connection per topic."""

    def put(topic: str, name: str, message: object, time_ns: int = 1) -> None:
        conn = next((c for c in writer.connections if c.topic == topic), None)
        conn = conn or writer.add_connection(topic, name, typestore=store)
        writer.write(conn, time_ns, store.serialize_ros1(message, name))

    return put
