"""ROS bag reader: ``sensor_msgs/LaserScan`` messages with 2-D poses from tf or odometry.

Works for ROS1 bags and ROS2 bags (directory, ``.db3`` or ``.mcap``) through
``rosbags.highlevel.AnyReader``. The tf tree (:class:`TfTree`) holds full 3-D transforms; the
LaserScan poses are their projections to (x, y, yaw), and :mod:`gpomap.io.pointcloud2` uses the
same tree for 3-D clouds.

Poses. By default the sensor pose of each scan is the transform from `fixed_frame` (``odom``)
to the scan's ``header.frame_id``, composed along the tf tree (``/tf`` and ``/tf_static``) and
projected to 2-D (x, y, yaw from the quaternion). With `odom_topic`, the ``nav_msgs/Odometry``
messages replace the tf edge to the odometry's child frame, and the transforms from that child
to the laser frame still come from tf when the bag has them (identity otherwise). Each edge of the
tree is interpolated at the scan stamp (plus `time_offset`): linearly in x and y, along the shorter
arc in yaw. An edge from ``/tf_static``, or whose published values never change, is constant.
Scans outside the time range of the moving edges are dropped and counted. Frame names lose any
leading slash (ROS1 ``/odom`` and ROS2 ``odom`` are the same frame).

Stage bags (the simulator's, e.g. ``stage-arena/robot1.bag``): Stage stamps each scan with the
pose of the step *before* the one it matches, so their scans want a `time_offset` of one step,
:data:`STAGE_TIME_OFFSET`; the last scan then has no later pose and is dropped. Part of what is
left is stamp jitter, which no constant offset removes (the fit of hits to the true plan by
offset: docs/choices.md, "Measured for the code").
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.checks import ros2_bag_directory
from gpomap.io.noreturn import decide_max_range
from gpomap.scans import Scan

__all__ = [
    "read_rosbag",
    "load_rosbag",
    "RosbagScans",
    "STAGE_TIME_OFFSET",
    "yaw_from_quaternion",
    "up_component",
    "laserscan_angles",
]

#: Suggested `time_offset` (seconds) for Stage bags such as ``stage-arena/robot1.bag``: the scan
#: matches the pose one 10 Hz step later (docs/choices.md, "Measured for the code").
STAGE_TIME_OFFSET = 0.1

_LASERSCAN = "sensor_msgs/msg/LaserScan"
_ODOMETRY = "nav_msgs/msg/Odometry"
_TF_TOPICS = ("/tf", "/tf_static", "tf", "tf_static")
# Stamps closer than this (seconds) count as equal when checking the pose time range.
_TIME_TOL = 1e-6


@dataclass
class RosbagScans:
    """Scans read from a bag, with what was used and what was dropped.

    Attributes
    ----------
    scans : list of Scan
        In stamp order; ``Scan.time`` is the header stamp (seconds, without the offset).
    topic : str
        The LaserScan topic read.
    fixed_frame : str
        Frame the poses are expressed in.
    laser_frames : list of str
        The scans' ``header.frame_id`` values (normalised).
    n_messages : int
        LaserScan messages on the topic.
    n_dropped : int
        Scans dropped because their (offset) stamp lies outside the time range of the poses.
    """

    scans: list[Scan]
    topic: str
    fixed_frame: str
    laser_frames: list[str] = field(default_factory=list)
    n_messages: int = 0
    n_dropped: int = 0


#: Laser planes tilted more than this from level (degrees) are worth a warning: a planar map
#: projects each scan as if level, so its ranges are off by 1 - cos(tilt) along the tilt (1.5 %
#: at 10 degrees) and a tilted scan may strike the floor.
MAX_LEVEL_TILT_DEG: float = 10.0


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about z) of a unit quaternion, radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def up_component(qx: Any, qy: Any) -> Any:
    """The z component of a frame's z axis rotated by the unit quaternion (qx, qy, qz, qw), in the
    parent frame: 1 level, 0 on its side, -1 upside down. Scalars or arrays."""
    return 1.0 - 2.0 * (np.square(qx) + np.square(qy))


def laserscan_angles(angle_min: float, angle_increment: float, n: int, upside_down: bool = False) -> NDArray[np.float64]:
    """A LaserScan's `n` beam angles in its laser frame, radians, shape (n,); mirrored about the
    laser's heading when the laser is mounted upside down (it then turns clockwise seen from above)."""
    angles = angle_min + angle_increment * np.arange(n, dtype=float)
    return -angles if upside_down else angles


def _frame(name: str) -> str:
    return name.lstrip("/")


def _stamp(t: object) -> float:
    return float(t.sec) + 1e-9 * float(t.nanosec)  # type: ignore[attr-defined]


# Transforms in the tf tree are 3-D, rows of (x, y, z, qx, qy, qz, qw) (ROS's quaternion order),
# so the same tree serves LaserScan (projected to x, y, yaw at the end) and PointCloud2.


def _qmul(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hamilton products of quaternions (k, 4) in (x, y, z, w) order."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.column_stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def _rotate(q: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectors (k, 3) rotated by unit quaternions (k, 4)."""
    u, w = q[:, :3], q[:, 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _compose(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pose `b` (expressed in frame `a`) in `a`'s parent frame; arrays of shape (k, 7)."""
    return np.column_stack([a[:, :3] + _rotate(a[:, 3:], b[:, :3]), _qmul(a[:, 3:], b[:, 3:])])


def _inverse(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse transforms, shape (k, 7)."""
    q = a[:, 3:] * np.array([-1.0, -1.0, -1.0, 1.0])
    return np.column_stack([-_rotate(q, a[:, :3]), q])


def _slerp(q0: NDArray[np.float64], q1: NDArray[np.float64], f: NDArray[np.float64]) -> NDArray[np.float64]:
    """Spherical interpolation along the shorter arc between unit quaternions (k, 4), by f (k,)."""
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-9
    s = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - f, np.sin((1.0 - f) * theta) / s)
    w1 = np.where(small, f, np.sin(f * theta) / s)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def planar(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """3-D transforms (k, 7) projected to (x, y, yaw), shape (k, 3)."""
    x, y, z, w = pose[:, 3], pose[:, 4], pose[:, 5], pose[:, 6]
    return np.column_stack([pose[:, 0], pose[:, 1], np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))])


def _attitude_notes(up: NDArray[np.float64], frames: NDArray[np.str_], fixed: str) -> list[str]:
    """What the scans' laser attitudes call for: a note for lasers mounted upside down (mirrored
    beams) and a warning (also a note) for laser planes tilted from level by more than
    :data:`MAX_LEVEL_TILT_DEG`, which a planar map takes as level."""
    notes = []
    flipped = up < 0
    if flipped.any():
        names = ", ".join(repr(f) for f in sorted(set(frames[flipped].tolist())))
        notes.append(
            f"laser frame {names} is upside down in {fixed!r} (its z axis points down) in {int(flipped.sum())} of "
            f"{up.size} scans: their beam angles are mirrored"
        )
    tilt = np.degrees(np.arccos(np.clip(np.abs(up), 0.0, 1.0)))
    tilted = tilt > MAX_LEVEL_TILT_DEG
    if tilted.any():
        note = (
            f"{int(tilted.sum())} of {up.size} scans' laser planes are tilted more than {MAX_LEVEL_TILT_DEG:g} degrees "
            f"from level in {fixed!r} (up to {tilt.max():.0f}); a planar map takes every scan as level"
        )
        warnings.warn(note, stacklevel=3)
        notes.append(note)
    return notes


def _planar_transform(x: float, y: float, yaw: float) -> tuple[float, ...]:
    """The 3-D transform (7 values) of a planar pose."""
    return (x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


class _Edge:
    """Time series of one parent -> child transform (rows of x, y, z, qx, qy, qz, qw)."""

    def __init__(self, parent: str, child: str, static: bool) -> None:
        self.parent = parent
        self.child = child
        self.static = static
        self._t: list[float] = []
        self._p: list[tuple[float, ...]] = []
        self.t: NDArray[np.float64] = np.empty(0)
        self.p: NDArray[np.float64] = np.empty((0, 7))

    def add(self, t: float, pose: tuple[float, ...]) -> None:
        self._t.append(t)
        self._p.append(pose)

    def finish(self) -> None:
        t = np.asarray(self._t, dtype=float)
        p = np.asarray(self._p, dtype=float).reshape(-1, 7)
        norm = np.linalg.norm(p[:, 3:], axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            p[:, 3:] = p[:, 3:] / norm  # a zero quaternion becomes NaN: that pose is unusable
        order = np.argsort(t, kind="stable")
        t, p = t[order], p[order]
        # Keep the last of equal stamps, so interpolation never divides by zero.
        last = np.append(np.diff(t) > 0, True)
        self.t, self.p = t[last], p[last]
        # A transform that is republished unchanged (e.g. base_link -> laser on ROS1 /tf) is static.
        if len(self.p) and np.ptp(self.p, axis=0).max() <= 1e-9:
            self.static = True

    def at(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Interpolated transforms at times `t` (k,): poses (k, 7) and a mask of times in range."""
        if self.static or len(self.t) == 1:
            return np.repeat(self.p[-1:], len(t), axis=0), np.ones(len(t), dtype=bool)
        ok = (t >= self.t[0] - _TIME_TOL) & (t <= self.t[-1] + _TIME_TOL)
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[i], self.t[i + 1]
        f = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
        p0, p1 = self.p[i], self.p[i + 1]
        xyz = p0[:, :3] + f[:, None] * (p1[:, :3] - p0[:, :3])
        return np.column_stack([xyz, _slerp(p0[:, 3:], p1[:, 3:], f)]), ok


class TfTree:
    """A tf tree: each child frame has one parent edge; transforms are rows of (x, y, z, qx, qy, qz, qw)."""

    def __init__(self) -> None:
        self.edges: dict[str, _Edge] = {}

    def add(self, parent: str, child: str, t: float, pose: tuple[float, ...], static: bool) -> None:
        edge = self.edges.get(child)
        if edge is None:
            edge = self.edges[child] = _Edge(parent, child, static)
        elif edge.parent != parent:
            # tf allows one parent per frame; a second one would be a broken tree. Keep the first.
            return
        edge.add(t, pose)

    def finish(self) -> None:
        for e in self.edges.values():
            e.finish()

    def frames(self) -> list[str]:
        names = set(self.edges)
        names.update(e.parent for e in self.edges.values())
        return sorted(names)

    def chain(self, frame: str) -> list[str]:
        """`frame` and its ancestors, up to the root."""
        out = [frame]
        seen = {frame}
        while out[-1] in self.edges:
            parent = self.edges[out[-1]].parent
            if parent in seen:  # a cycle: stop rather than loop
                break
            out.append(parent)
            seen.add(parent)
        return out

    def _down(self, ancestor: str, frame: str, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Pose of `frame` in `ancestor` at times `t`, shape (k, 7)."""
        pose = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (len(t), 1))
        ok = np.ones(len(t), dtype=bool)
        for f in self.chain(frame):
            if f == ancestor:
                break
            p, m = self.edges[f].at(t)
            pose = _compose(p, pose)
            ok &= m
        return pose, ok

    def path_edges(self, fixed: str, target: str) -> list[_Edge]:
        """The edges between `fixed` and `target` (through their common ancestor)."""
        up = self.chain(target)
        common = next((f for f in self.chain(fixed) if f in up), None)
        edges = []
        for start in (fixed, target):
            for f in self.chain(start):
                if f == common:
                    break
                edges.append(self.edges[f])
        return edges

    def lookup(self, fixed: str, target: str, t: NDArray[np.float64], path: str) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Pose of `target` in `fixed` at times `t` (k,): 3-D transforms (k, 7) and in-range mask (k,)."""
        known = self.frames()
        for name, what in ((fixed, "fixed frame"), (target, "laser frame")):
            if name not in known:
                raise InputFormatError(f"unknown {what} {name!r}; known tf frames: {', '.join(known) or '(none)'}", path=path)
        up = self.chain(target)
        common = next((f for f in self.chain(fixed) if f in up), None)
        if common is None:
            raise InputFormatError(
                f"no tf path from {fixed!r} to {target!r}: they are in different trees; known tf frames: {', '.join(known)}",
                path=path,
            )
        a, ok_a = self._down(common, fixed, t)
        b, ok_b = self._down(common, target, t)
        return _compose(_inverse(a), b), ok_a & ok_b


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


def _topics_text(connections: Iterable[object]) -> str:
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
            raise InputFormatError(f"{what}; topics in the bag: {_topics_text(connections)}", path=path)
        return topics[0]
    if topic not in topics:
        which = f"is not a {kind} topic" if any(c.topic == topic for c in connections) else "unknown topic"
        raise InputFormatError(
            f"{which} {topic!r}; {kind} topics: {', '.join(topics) or '(none)'}; topics in the bag: {_topics_text(connections)}",
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
                _frame(tr.header.frame_id), _frame(tr.child_frame_id), _stamp(tr.header.stamp), _transform(tr.transform), static
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


def load_rosbag(
    path: str | os.PathLike[str],
    topic: str | None = None,
    fixed_frame: str | None = None,
    odom_topic: str | None = None,
    time_offset: float = 0.0,
    max_range: float | None = None,
) -> RosbagScans:
    """Read LaserScan messages and their sensor poses from a ROS1 or ROS2 bag.

    Parameters
    ----------
    path : path-like
        ROS1 ``.bag`` file, ROS2 bag directory, or a ROS2 ``.db3`` / ``.mcap`` file (its directory
        is opened).
    topic : str, optional
        LaserScan topic; default the only one in the bag.
    fixed_frame : str, optional
        Frame the poses are expressed in. Default ``odom``, or with `odom_topic` the odometry's
        ``header.frame_id``.
    odom_topic : str, optional
        ``nav_msgs/Odometry`` topic to take the robot poses from instead of tf.
    time_offset : float
        Seconds added to each scan stamp before the pose lookup (0.1 for Stage bags, see
        :data:`STAGE_TIME_OFFSET`).
    max_range : float, optional
        No-return threshold, metres; always wins. Default: decided over all kept scans
        (:func:`gpomap.io.noreturn.decide_max_range`): the messages' ``range_max`` (the most
        common value) when the readings agree with it, else the no-return code found in the
        readings, else none. The decision is in each ``Scan.meta["no_return"]``.

    Returns
    -------
    RosbagScans
        Each scan's ``meta`` holds ``frame_id``, ``topic``, ``no_return``, ``fixed_frame`` and
        ``frames_above``: the frames tf places the fixed frame in, nearest first (``["map"]``
        for a bag recorded while a SLAM ran; empty with an odometry topic).

    Raises
    ------
    InputFormatError
        Missing file, not a regular file or ROS2 bag directory, unreadable or corrupt bag,
        unknown or ambiguous topic (lists the topics with their types), no /tf and no odometry
        topic (lists the topics and names the Odometry topics to pass as `odom_topic`), unknown
        frame (lists the tf frames), no scans with a pose (gives the time ranges of the
        transforms and the tf frames), non-finite beam angles.
    """
    p = Path(path)
    spath = str(p)
    reader = open_bag(p)
    try:
        conns = reader.connections
        scan_conns = [c for c in conns if c.msgtype == _LASERSCAN]
        topic = choose_topic(conns, _LASERSCAN, "LaserScan", topic, spath)
        odom_conns = []
        odom_topics = sorted({c.topic for c in conns if c.msgtype == _ODOMETRY})
        odom_hint = f"; use --odom-topic NAME (odom_topic=) with {', '.join(odom_topics)}" if odom_topics else ""
        if odom_topic is not None:
            odom_conns = [c for c in conns if c.topic == odom_topic and c.msgtype == _ODOMETRY]
            if not odom_conns:
                raise InputFormatError(
                    f"unknown Odometry topic {odom_topic!r}; Odometry topics: {', '.join(odom_topics) or '(none)'}; "
                    f"topics in the bag: {_topics_text(conns)}",
                    path=spath,
                )

        tf_conns = [c for c in conns if c.topic in _TF_TOPICS]
        if not tf_conns and not odom_conns:
            # Nothing to take poses from; reader.messages(connections=[]) would read every message.
            raise InputFormatError(
                f"no /tf or /tf_static messages to take the scan poses from{odom_hint}; topics in the bag: {_topics_text(conns)}",
                path=spath,
            )
        tree = TfTree()
        odom_edge: _Edge | None = None
        odom_parent = None
        stamps: list[float] = []
        frames: list[str] = []
        ranges: list[NDArray[np.float64]] = []
        geometry: list[tuple[float, float, int, float, float]] = []
        where = "opening the bag"
        try:
            if tf_conns:
                where = "reading /tf"
                read_tf(reader, tf_conns, tree)
            if odom_conns:
                where = f"reading {odom_topic}"
                for c, _, raw in reader.messages(connections=odom_conns):
                    # Message classes are built from the bag's definitions at run time: no static type.
                    msg: Any = reader.deserialize(raw, c.msgtype)
                    if odom_edge is None:
                        odom_parent = _frame(msg.header.frame_id)
                        odom_edge = _Edge(odom_parent, _frame(msg.child_frame_id), static=False)
                    pose = msg.pose.pose
                    q = pose.orientation
                    odom_edge.add(
                        _stamp(msg.header.stamp),
                        (float(pose.position.x), float(pose.position.y), float(pose.position.z), q.x, q.y, q.z, q.w),
                    )
            where = f"reading {topic}"
            for c, _, raw in reader.messages(connections=[c for c in scan_conns if c.topic == topic]):
                msg = reader.deserialize(raw, c.msgtype)
                stamps.append(_stamp(msg.header.stamp))
                frames.append(_frame(msg.header.frame_id))
                ranges.append(np.asarray(msg.ranges, dtype=float))
                geometry.append(
                    (
                        float(msg.angle_min),
                        float(msg.angle_increment),
                        len(msg.ranges),
                        float(msg.range_min),
                        float(msg.range_max),
                    )
                )
        except GpomapError:
            raise
        except Exception as exc:  # rosbags and its deserialisers raise many types on corrupt data
            raise InputFormatError(f"corrupt bag while {where} ({type(exc).__name__}: {exc})", path=spath) from None
    finally:
        reader.close()

    if odom_conns:
        if odom_edge is None:
            raise InputFormatError(f"no messages on Odometry topic {odom_topic!r}", path=spath)
        # Odometry replaces whatever tf said about the odometry child frame.
        tree.edges[odom_edge.child] = odom_edge
        if fixed_frame is None:
            fixed_frame = odom_parent
    fixed = _frame(fixed_frame if fixed_frame is not None else "odom")

    if not stamps:
        raise InputFormatError(f"no LaserScan messages on topic {topic!r}", path=spath)

    if odom_conns:
        # The laser may hang off the odometry child through tf; if tf does not know the laser
        # frame at all, the laser sits at the odometry child frame.
        child = odom_edge.child  # type: ignore[union-attr]
        for lf in sorted(set(frames)):
            if lf != child and lf not in tree.frames():
                warnings.warn(f"{spath}: laser frame {lf!r} not in tf; assuming it coincides with {child!r}", stacklevel=2)
                tree.add(child, lf, 0.0, _planar_transform(0.0, 0.0, 0.0), static=True)
    tree.finish()

    t = np.asarray(stamps) + float(time_offset)
    poses = np.full((len(t), 3), np.nan)
    # The laser frame's z axis in the fixed frame, z component: -1 for a laser mounted upside down.
    up = np.full(len(t), np.nan)
    ok = np.zeros(len(t), dtype=bool)
    frame_arr = np.asarray(frames)
    for lf in sorted(set(frames)):
        sel = frame_arr == lf
        transforms, ok[sel] = tree.lookup(fixed, lf, t[sel], spath)
        poses[sel] = planar(transforms)
        up[sel] = up_component(transforms[:, 3], transforms[:, 4])
    # A NaN quaternion or translation in the bag gives a pose no scan can use.
    ok &= np.isfinite(poses).all(axis=1)

    order = np.argsort(np.asarray(stamps), kind="stable")
    kept = [int(i) for i in order if ok[i]]
    beams: dict[int, NDArray[np.float64]] = {}
    for i in kept:
        a0, da, n, rmin, _ = geometry[i]
        # ROS: readings below range_min are not measurements.
        ranges[i] = np.where(ranges[i] < rmin, np.nan, ranges[i])
        beams[i] = laserscan_angles(a0, da, n, upside_down=bool(up[i] < 0))
        if not np.isfinite(beams[i]).all():
            raise InputFormatError(
                f"LaserScan on {topic} at stamp {stamps[i]:.9g} s has non-finite beam angles "
                f"(angle_min {a0}, angle_increment {da}); expected radians",
                path=spath,
            )
    decision = None
    if kept:
        header_values = [geometry[i][4] for i in kept if math.isfinite(geometry[i][4]) and geometry[i][4] > 0]
        header = None
        if header_values:
            values, counts = np.unique(np.asarray(header_values), return_counts=True)
            header = float(values[np.argmax(counts)])
        decision = decide_max_range(np.concatenate([ranges[i] for i in kept]), header, "LaserScan range_max", user=max_range)
        if header_values and len(values) > 1:
            decision.notes.append(
                f"LaserScan range_max differs between messages ({', '.join(f'{v:g}' for v in values[:5])}); "
                f"compared the most common, {header:g} m, with the data"
            )
    # Frames tf places the fixed frame in (a SLAM's map above odom), from the nearest up, as far as
    # they give poses at most scan stamps (a SLAM stamping with the wall clock in a simulation
    # does not); with an odometry topic the user chose the poses' source, and none is suggested.
    above: list[str] = []
    for frame in [] if odom_conns or not kept else tree.chain(fixed)[1:]:
        if tree.lookup(frame, fixed, t[kept], spath)[1].mean() < 0.5:
            break
        above.append(frame)
    if decision is not None:
        decision.notes.extend(_attitude_notes(up[kept], frame_arr[kept], fixed))
        if fixed_frame is None and above:
            # A robot that ran SLAM or localisation while recording has its correction above odom.
            decision.notes.append(
                f"tf also places {fixed!r} in {', then '.join(repr(f) for f in above)} (a SLAM or localisation "
                f"correction, when the robot ran one): --fixed-frame {above[-1]} (fixed_frame=) maps in that frame instead"
            )
    info = decision.as_dict() if decision is not None else {}
    if info:
        info["topic"] = topic
    scans = [
        Scan(
            pose=poses[i],
            angles=beams[i],
            ranges=ranges[i],
            max_range=decision.max_range,  # type: ignore[union-attr]
            time=stamps[i],
            meta={"frame_id": frames[i], "topic": topic, "no_return": info, "fixed_frame": fixed, "frames_above": above},
        )
        for i in kept
    ]
    n_dropped = int((~ok).sum())
    if not scans:
        lf = frames[0]
        pose_src = f"odometry topic {odom_topic!r}" if odom_conns else f"tf ({fixed!r} -> {lf!r})"
        spans = [
            f"{e.parent} -> {e.child}: {e.t[0]:.9g} .. {e.t[-1]:.9g} s"
            for e in tree.path_edges(fixed, lf)
            if not e.static and len(e.t) > 1
        ]
        raise InputFormatError(
            f"no scans left: all {len(stamps)} scan stamps ({min(stamps):.9g} .. {max(stamps):.9g} s, with "
            f"time_offset {time_offset:g} s) lie outside the time range of the poses from {pose_src}"
            f" ({'; '.join(spans) or 'no moving transforms'}), or the poses are not finite; "
            f"is {fixed!r} the right fixed frame? tf frames: {', '.join(tree.frames())}",
            path=spath,
        )
    return RosbagScans(
        scans=scans,
        topic=topic,
        fixed_frame=fixed,
        laser_frames=sorted(set(frames)),
        n_messages=len(stamps),
        n_dropped=n_dropped,
    )


def read_rosbag(
    path: str | os.PathLike[str],
    topic: str | None = None,
    fixed_frame: str | None = None,
    odom_topic: str | None = None,
    time_offset: float = 0.0,
    max_range: float | None = None,
) -> list[Scan]:
    """The scans of :func:`load_rosbag`; warns when scans were dropped for lack of a pose.

    Parameters and errors are those of :func:`load_rosbag`.

    Returns
    -------
    list of Scan
    """
    result = load_rosbag(path, topic, fixed_frame, odom_topic, time_offset, max_range)
    if result.n_dropped:
        warnings.warn(
            f"{path}: dropped {result.n_dropped} of {result.n_messages} scans outside the pose time range",
            stacklevel=2,
        )
    return result.scans
