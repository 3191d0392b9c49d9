"""``sensor_msgs/PointCloud2`` messages with their sensor poses from /tf, from ROS 1 and ROS 2 bags.

Each message is one :class:`~gpomap.clouds.CloudScan`: its ``x``, ``y``, ``z`` fields (FLOAT32
or FLOAT64, either byte order, any point and row padding) are in the message's
``header.frame_id``; the transform from `fixed_frame` to that frame at the stamp (plus
`time_offset`), composed along the tf tree of :mod:`gpomap.io.rosbag` (the same tree, the same
interpolation: linear in position, spherical in rotation), moves them to the map frame, and its
translation is the ray origin. NaN points (no return in most drivers' organised clouds) are
invalid rays; with `max_range`, points farther than it become no-return rays ending at it.
Clouds whose stamp lies outside the time range of the moving transforms are dropped (counted in
a warning).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan, cloud_from_points
from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.bags import TF_TOPICS, choose_topic, frame_name, open_bag, read_tf, stamp_seconds, topics_text
from gpomap.io.poses import pose_matrix, quaternion_matrix, transform_points
from gpomap.io.tftree import TfTree

__all__ = ["read_pointcloud2", "bag_has_pointclouds_only", "POINTCLOUD2"]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
_LASERSCAN = "sensor_msgs/msg/LaserScan"
# sensor_msgs/PointField datatypes that can hold a coordinate.
_FLOAT_TYPES = {7: "f4", 8: "f8"}


def bag_has_pointclouds_only(path: str | os.PathLike[str]) -> bool:
    """Whether a bag has ``PointCloud2`` topics and no ``LaserScan`` one (a 3-D bag)."""
    reader = open_bag(Path(path))
    try:
        types = {c.msgtype for c in reader.connections}
    finally:
        reader.close()
    return POINTCLOUD2 in types and _LASERSCAN not in types


def _xyz(msg: Any, topic: str, path: str) -> NDArray[np.float64]:
    """The points of one PointCloud2 message, shape (height * width, 3)."""
    fields = {f.name: f for f in msg.fields}
    missing = [k for k in ("x", "y", "z") if k not in fields]
    if missing:
        listed = ", ".join(fields) or "(none)"
        raise InputFormatError(
            f"PointCloud2 on {topic} has no field {', '.join(missing)} (fields: {listed}); expected x, y, z", path=path
        )
    order = ">" if msg.is_bigendian else "<"
    names: list[str] = []
    formats: list[str] = []
    offsets: list[int] = []
    for k in ("x", "y", "z"):
        f = fields[k]
        if f.datatype not in _FLOAT_TYPES:
            raise InputFormatError(
                f"PointCloud2 on {topic}: field {k!r} has datatype {f.datatype}; expected FLOAT32 (7) or FLOAT64 (8)", path=path
            )
        names.append(k)
        formats.append(order + _FLOAT_TYPES[f.datatype])
        offsets.append(int(f.offset))
    step, row, h, w = int(msg.point_step), int(msg.row_step), int(msg.height), int(msg.width)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step}) if step else None
    data = np.asarray(msg.data, dtype=np.uint8)
    fits = all(o + int(f[-1]) <= step for o, f in zip(offsets, formats))
    if dtype is None or not fits or row < w * step or data.size < h * row:
        raise InputFormatError(
            f"PointCloud2 on {topic}: {data.size} data bytes for height {h}, width {w}, point_step {step}, row_step {row} "
            "(fields at offsets "
            + ", ".join(map(str, offsets))
            + "); expected height x row_step bytes and fields inside each point",
            path=path,
        )
    rows = data[: h * row].reshape(h, row)[:, : w * step]
    pts = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype)
    return np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(float)


def read_pointcloud2(
    path: str | os.PathLike[str],
    topic: str | None = None,
    fixed_frame: str | None = None,
    time_offset: float = 0.0,
    max_range: float | None = None,
    odom_topic: str | None = None,
) -> list[CloudScan]:
    """Read the ``PointCloud2`` messages of a bag as clouds in `fixed_frame`.

    Parameters
    ----------
    path : path-like
        ROS1 ``.bag``, ROS2 bag directory, or a ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        The PointCloud2 topic; default the only one.
    fixed_frame : str, optional
        The map frame (default ``odom``, else ``map`` if the tree has it and not ``odom``).
    time_offset : float
        Seconds added to each stamp before the tf lookup.
    max_range : float, optional
    odom_topic : None
        Not supported for clouds (accepted so the 2-D reader's options pass through); give poses on /tf.

    Returns
    -------
    list of CloudScan
        In stamp order; ``time`` is the header stamp, ``meta`` has ``frame_id`` and ``topic``.

    Raises
    ------
    InputFormatError
        Unreadable bag, no or several PointCloud2 topics (lists them), no /tf, unknown frames,
        no field x, y or z, non-float coordinates, data shorter than the message's geometry, no
        cloud with a pose.
    """
    if odom_topic is not None:
        raise InputFormatError("odometry poses are not supported for PointCloud2 clouds; give the poses on /tf", path=str(path))
    p = Path(path)
    spath = str(p)
    reader = open_bag(p)
    tree = TfTree()
    stamps: list[float] = []
    frames: list[str] = []
    points: list[NDArray[np.float64]] = []
    try:
        conns = reader.connections
        topic = choose_topic(conns, POINTCLOUD2, "PointCloud2", topic, spath)
        tf_conns = [c for c in conns if c.topic in TF_TOPICS]
        if not tf_conns:
            raise InputFormatError(
                f"no /tf or /tf_static messages to take the cloud poses from; topics in the bag: {topics_text(conns)}",
                path=spath,
            )
        where = "reading /tf"
        try:
            read_tf(reader, tf_conns, tree)
            where = f"reading {topic}"
            for c, _, raw in reader.messages(connections=[c for c in conns if c.topic == topic]):
                msg: Any = reader.deserialize(raw, c.msgtype)
                stamps.append(stamp_seconds(msg.header.stamp))
                frames.append(frame_name(msg.header.frame_id))
                points.append(_xyz(msg, topic, spath))
        except GpomapError:
            raise
        except Exception as exc:  # rosbags and its deserialisers raise many types on corrupt data
            raise InputFormatError(f"corrupt bag while {where} ({type(exc).__name__}: {exc})", path=spath) from None
    finally:
        reader.close()
    if not stamps:
        raise InputFormatError(f"no PointCloud2 messages on topic {topic!r}", path=spath)
    tree.finish()
    if fixed_frame is None:
        known = tree.frames()
        fixed_frame = "map" if "map" in known and "odom" not in known else "odom"
    fixed = frame_name(fixed_frame)
    t = np.asarray(stamps) + float(time_offset)
    poses = np.full((len(t), 7), np.nan)
    ok = np.zeros(len(t), dtype=bool)
    frame_arr = np.asarray(frames)
    for lf in sorted(set(frames)):
        sel = frame_arr == lf
        poses[sel], ok[sel] = tree.lookup(fixed, lf, t[sel], spath)
    ok &= np.isfinite(poses).all(axis=1)
    if not ok.any():
        raise InputFormatError(
            f"no clouds left: none of the {len(t)} stamps ({t.min():.9g} .. {t.max():.9g} s with time_offset {time_offset:g}) "
            f"has a tf pose from {fixed!r} to {frames[0]!r}; tf frames: {', '.join(tree.frames())}",
            path=spath,
        )
    if not ok.all():
        warnings.warn(f"{spath}: dropped {int((~ok).sum())} of {len(t)} clouds outside the pose time range", stacklevel=2)
    clouds = []
    for i in np.argsort(np.asarray(stamps), kind="stable"):
        if not ok[i]:
            continue
        x, y, z, qx, qy, qz, qw = poses[i]
        m = pose_matrix(quaternion_matrix(qw, qx, qy, qz), np.array([x, y, z]))
        clouds.append(
            cloud_from_points(
                m[:3, 3],
                transform_points(m, points[i]),
                max_range=max_range,
                time=stamps[i],
                meta={"frame_id": frames[i], "topic": topic},
            )
        )
    return clouds
