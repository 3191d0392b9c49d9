"""ROS bag reader: ``sensor_msgs/LaserScan`` messages with 2-D poses from tf or odometry.

Works for ROS1 bags and ROS2 bags (directory, ``.db3`` or ``.mcap``) through
``rosbags.highlevel.AnyReader`` (:mod:`gpomap.io.bags` opens the bag and picks the topic). The
tf tree (:class:`~gpomap.io.tftree.TfTree`) holds full 3-D transforms; the LaserScan poses are
their projections to (x, y, yaw), and :mod:`gpomap.io.pointcloud2` uses the same tree for 3-D
clouds.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.bags import TF_TOPICS, choose_topic, frame_name, open_bag, read_tf, stamp_seconds, topics_text
from gpomap.io.noreturn import decide_max_range
from gpomap.io.tftree import TfEdge, TfTree, planar, planar_transform, up_component, yaw_from_quaternion
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


def laserscan_angles(angle_min: float, angle_increment: float, n: int, upside_down: bool = False) -> NDArray[np.float64]:
    """A LaserScan's `n` beam angles in its laser frame, radians, shape (n,); mirrored about the
    laser's heading when the laser is mounted upside down (it then turns clockwise seen from above)."""
    angles = angle_min + angle_increment * np.arange(n, dtype=float)
    return -angles if upside_down else angles


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
                    f"topics in the bag: {topics_text(conns)}",
                    path=spath,
                )

        tf_conns = [c for c in conns if c.topic in TF_TOPICS]
        if not tf_conns and not odom_conns:
            # Nothing to take poses from; reader.messages(connections=[]) would read every message.
            raise InputFormatError(
                f"no /tf or /tf_static messages to take the scan poses from{odom_hint}; topics in the bag: {topics_text(conns)}",
                path=spath,
            )
        tree = TfTree()
        odom_edge: TfEdge | None = None
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
                        odom_parent = frame_name(msg.header.frame_id)
                        odom_edge = TfEdge(odom_parent, frame_name(msg.child_frame_id), static=False)
                    pose = msg.pose.pose
                    q = pose.orientation
                    odom_edge.add(
                        stamp_seconds(msg.header.stamp),
                        (float(pose.position.x), float(pose.position.y), float(pose.position.z), q.x, q.y, q.z, q.w),
                    )
            where = f"reading {topic}"
            for c, _, raw in reader.messages(connections=[c for c in scan_conns if c.topic == topic]):
                msg = reader.deserialize(raw, c.msgtype)
                stamps.append(stamp_seconds(msg.header.stamp))
                frames.append(frame_name(msg.header.frame_id))
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
    fixed = frame_name(fixed_frame if fixed_frame is not None else "odom")

    if not stamps:
        raise InputFormatError(f"no LaserScan messages on topic {topic!r}", path=spath)

    if odom_conns:
        # The laser may hang off the odometry child through tf; if tf does not know the laser
        # frame at all, the laser sits at the odometry child frame.
        child = odom_edge.child  # type: ignore[union-attr]
        for lf in sorted(set(frames)):
            if lf != child and lf not in tree.frames():
                warnings.warn(f"{spath}: laser frame {lf!r} not in tf; assuming it coincides with {child!r}", stacklevel=2)
                tree.add(child, lf, 0.0, planar_transform(0.0, 0.0, 0.0), static=True)
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
