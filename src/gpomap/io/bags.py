"""Opening ROS 1 and ROS 2 bags, choosing a topic, and the message fields every reader decodes.

Bags open through ``rosbags.highlevel.AnyReader`` (:func:`open_bag`): a ROS1 ``.bag`` file, a ROS2
bag directory, or a ROS2 ``.db3`` / ``.mcap`` file (its directory is opened). :func:`choose_topic`
picks the topic of one message type, naming the bag's topics when it cannot; :func:`read_tf`
fills a :class:`~gpomap.io.tftree.TfTree` from ``/tf`` and ``/tf_static``. Frame names lose any
leading slash (ROS1 ``/odom`` and ROS2 ``odom`` are the same frame).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.checks import ros2_bag_directory
from gpomap.io.tftree import TfTree

__all__ = ["open_bag", "choose_topic", "read_tf", "topics_text", "frame_name", "stamp_seconds", "TF_TOPICS"]

#: The topics tf is published on: ROS1 bags name them with a leading slash, ROS2 bags may not.
TF_TOPICS = ("/tf", "/tf_static", "tf", "tf_static")


def frame_name(name: str) -> str:
    """A tf frame's name without a leading slash, so ROS1's ``/odom`` and ROS2's ``odom`` match."""
    return name.lstrip("/")


def stamp_seconds(t: object) -> float:
    """A ``builtin_interfaces/Time`` (``sec``, ``nanosec``) as seconds."""
    return float(t.sec) + 1e-9 * float(t.nanosec)  # type: ignore[attr-defined]


def _bag_paths(path: Path) -> list[Path]:
    """What AnyReader opens: the .bag file, or the ROS2 bag directory."""
    if ros2_bag_directory(path, "ROS bag"):
        return [path]
    if path.suffix.lower() in (".db3", ".mcap"):
        if not (path.parent / "metadata.yaml").exists():
            raise InputFormatError(
                "ROS2 storage file without metadata.yaml beside it; expected a ROS2 bag directory",
                path=str(path),
            )
        return [path.parent]
    return [path]


def topics_text(connections: Iterable[object]) -> str:
    """The bag's topics with their message types, for error messages: ``"/scan (sensor_msgs/msg/LaserScan), ..."``."""
    items = sorted({f"{c.topic} ({c.msgtype})" for c in connections})  # type: ignore[attr-defined]
    return ", ".join(items) or "(none)"


def choose_topic(connections: Sequence[Any], msgtype: str, kind: str, topic: str | None, path: str) -> str:
    """The topic of `msgtype` messages to read: `topic`, checked, or the bag's only one.

    Parameters
    ----------
    connections : sequence of rosbags connections
    msgtype : str
        Message type, e.g. ``"sensor_msgs/msg/LaserScan"``.
    kind : str
        Its short name in messages, e.g. ``"LaserScan"``.
    topic : str or None
    path : str
        The bag, named in the error.

    Raises
    ------
    InputFormatError
        No such topic, or several and none chosen; the message lists the bag's topics.
    """
    topics = sorted({c.topic for c in connections if c.msgtype == msgtype})
    if topic is None:
        if len(topics) != 1:
            what = f"no {kind} topic" if not topics else f"several {kind} topics, choose one with topic="
            raise InputFormatError(f"{what}; topics in the bag: {topics_text(connections)}", path=path)
        return topics[0]
    if topic not in topics:
        which = f"is not a {kind} topic" if any(c.topic == topic for c in connections) else "unknown topic"
        raise InputFormatError(
            f"{which} {topic!r}; {kind} topics: {', '.join(topics) or '(none)'}; topics in the bag: {topics_text(connections)}",
            path=path,
        )
    return topic


def _transform(tr: object) -> tuple[float, ...]:
    """A geometry_msgs/Transform as (x, y, z, qx, qy, qz, qw)."""
    q = tr.rotation  # type: ignore[attr-defined]
    v = tr.translation  # type: ignore[attr-defined]
    return (float(v.x), float(v.y), float(v.z), float(q.x), float(q.y), float(q.z), float(q.w))


def read_tf(reader: Any, connections: list[Any], tree: TfTree) -> None:
    """Add every transform of the /tf and /tf_static `connections` of an open AnyReader to `tree`."""
    for c, _, raw in reader.messages(connections=connections):
        msg: Any = reader.deserialize(raw, c.msgtype)
        static = c.topic.lstrip("/") == "tf_static"
        for tr in msg.transforms:
            tree.add(
                frame_name(tr.header.frame_id),
                frame_name(tr.child_frame_id),
                stamp_seconds(tr.header.stamp),
                _transform(tr.transform),
                static,
            )


def _reader_failure(exc: Exception) -> str:
    """What the bag reader's exception says, or, for a bare failed check (an ``AssertionError``
    without a message: rosbags checks a ROS1 bag's index records so), what it means."""
    if str(exc):
        return str(exc)
    return (
        f"{type(exc).__name__} in the bag reader: a record or its index is not laid out as the bag "
        "format specifies; a ROS1 bag cut short or damaged in copying reads so, and `rosbag reindex` "
        "rebuilds its index"
    )


def open_bag(path: Path) -> Any:
    """An open ``rosbags.highlevel.AnyReader`` on a ROS1 or ROS2 bag; InputFormatError if it cannot be opened."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader(_bag_paths(path), default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except GpomapError:
        raise
    except Exception as exc:  # rosbags raises its own error types for unreadable bags
        raise InputFormatError(f"cannot open as a ROS bag ({_reader_failure(exc)})", path=str(path)) from None
    return reader
