"""Message conversion between ROS and gpomap, free of any ROS library.

The functions take and give plain values and duck-typed messages: anything with the fields of
``sensor_msgs/LaserScan`` (``angle_min``, ``angle_increment``, ``range_min``, ``range_max``,
``ranges``) and a stamp with ``secs``/``nsecs`` (ROS 1) or ``sec``/``nanosec`` (ROS 2). The
same code therefore serves the rospy node, an rclpy node, and tests that read messages out of a
bag with ``rosbags``.

Grids follow ``nav_msgs/OccupancyGrid``: ``data`` is row-major starting at the cell at
``info.origin`` (the lower-left corner), x along a row, one signed byte per cell. That is the
layout of :class:`gpomap.grid.OccupancyMap` arrays (row 0 at the lowest y), so no flip is needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.grid import FREE, OCCUPIED, GridSpec, OccupancyMap
from gpomap.io.rosbag import laserscan_angles, up_component, yaw_from_quaternion
from gpomap.scans import Scan

if TYPE_CHECKING:
    from gpomap.clouds import CloudScan

__all__ = [
    "UNKNOWN_CELL",
    "GridLayers",
    "stamp_seconds",
    "pose_from_transform",
    "is_upside_down",
    "scan_from_laserscan",
    "cloud_from_pointcloud2",
    "euler_matrix",
    "grid_layers",
]

#: ``nav_msgs/OccupancyGrid`` value of a cell whose occupancy is not known.
UNKNOWN_CELL = -1
#: map_server's trinary convention: free 0, occupied 100, unknown -1.
_TRINARY = {FREE: 0, OCCUPIED: 100}


def stamp_seconds(stamp: Any) -> float:
    """Seconds of a ROS 1 (``secs``, ``nsecs``) or ROS 2 (``sec``, ``nanosec``) time stamp.

    Parameters
    ----------
    stamp : rospy.Time, builtin_interfaces/Time, or any object with those fields

    Returns
    -------
    float
    """
    if hasattr(stamp, "secs"):
        return float(stamp.secs) + 1e-9 * float(stamp.nsecs)
    if hasattr(stamp, "sec"):
        return float(stamp.sec) + 1e-9 * float(stamp.nanosec)
    raise InputFormatError(f"time stamp {stamp!r} has neither secs/nsecs (ROS 1) nor sec/nanosec (ROS 2)")


def pose_from_transform(translation: Any, rotation: Any) -> tuple[float, float, float]:
    """The 2-D pose (x, y, yaw) of a ``geometry_msgs/Transform``'s translation and rotation.

    Parameters
    ----------
    translation : object with x, y, z
    rotation : object with x, y, z, w (a unit quaternion)

    Returns
    -------
    (float, float, float)
        x and y in metres, yaw (the heading of the frame's x axis) in radians.
    """
    return (
        float(translation.x),
        float(translation.y),
        yaw_from_quaternion(float(rotation.x), float(rotation.y), float(rotation.z), float(rotation.w)),
    )


def is_upside_down(rotation: Any) -> bool:
    """Whether a frame with this rotation (x, y, z, w; a unit quaternion) has its z axis pointing
    down: a laser mounted so turns clockwise seen from above, and its beams mirror."""
    return bool(up_component(float(rotation.x), float(rotation.y)) < 0)


def scan_from_laserscan(
    msg: Any,
    pose: tuple[float, float, float] | NDArray[np.float64],
    max_range: float | None = None,
    source: str = "LaserScan",
    upside_down: bool = False,
) -> Scan:
    """A :class:`~gpomap.scans.Scan` from a ``sensor_msgs/LaserScan`` and the laser's pose.

    Readings follow REP 117: below ``range_min`` or ``-inf`` (too close) and NaN are invalid;
    ``+inf`` and readings at or above the no-return threshold are no-return beams (free space
    along the beam, never a hit).

    Parameters
    ----------
    msg : LaserScan-like
        ``angle_min``, ``angle_increment``, ``range_min``, ``range_max``, ``ranges`` (n,).
    pose : (x, y, yaw)
        The laser frame's pose in the map's fixed frame at the scan's stamp.
    max_range : float, optional
        No-return threshold, metres; default the message's ``range_max``.
    source : str
        Where the message came from (topic name), for error messages.
    upside_down : bool
        The laser frame's z axis points down (:func:`is_upside_down`): its beam angles are
        mirrored about its heading.

    Returns
    -------
    Scan
        ``time`` is the header stamp in seconds when the message has a header.

    Raises
    ------
    InputFormatError
        Non-finite angles, a ``range_max`` that is not a positive number (and no `max_range`),
        or a pose that is not three finite numbers; the message names `source` and the field.
    """
    ranges = np.asarray(msg.ranges, dtype=float).reshape(-1)
    a0, da = float(msg.angle_min), float(msg.angle_increment)
    if not (math.isfinite(a0) and math.isfinite(da)):
        raise InputFormatError(f"{source}: angle_min {a0} and angle_increment {da} must be finite (radians)")
    limit = float(msg.range_max) if max_range is None else float(max_range)
    if not (math.isfinite(limit) and limit > 0):
        field = "range_max" if max_range is None else "max_range"
        raise InputFormatError(f"{source}: {field} must be a positive number of metres, got {limit}")
    rmin = float(msg.range_min)
    with np.errstate(invalid="ignore"):
        # +inf is "nothing within range" (REP 117): a no-return beam at the limit.
        ranges = np.where(np.isposinf(ranges), limit, ranges)
        if math.isfinite(rmin):
            ranges = np.where(ranges < rmin, np.nan, ranges)
    pose_arr = np.asarray(pose, dtype=float).reshape(-1)
    if pose_arr.shape != (3,) or not np.isfinite(pose_arr).all():
        raise InputFormatError(f"{source}: the laser pose must be three finite numbers (x, y, yaw), got {pose_arr.tolist()}")
    header = getattr(msg, "header", None)
    time = stamp_seconds(header.stamp) if header is not None else None
    meta = {"frame_id": str(header.frame_id).lstrip("/")} if header is not None else {}
    return Scan(
        pose=pose_arr,
        angles=laserscan_angles(a0, da, ranges.size, upside_down),
        ranges=ranges,
        max_range=limit,
        time=time,
        meta=meta,
    )


def euler_matrix(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of fixed-axis roll, pitch, yaw (radians): ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, as tf's RPY."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


class _CloudView:
    """A PointCloud2's layout fields with its data as a uint8 array."""

    def __init__(self, msg: Any, data: NDArray[np.uint8]) -> None:
        self.fields, self.is_bigendian, self.data = msg.fields, msg.is_bigendian, data
        self.point_step, self.row_step, self.height, self.width = msg.point_step, msg.row_step, msg.height, msg.width


def cloud_from_pointcloud2(
    msg: Any, pose: NDArray[np.float64], max_range: float | None = None, source: str = "PointCloud2"
) -> CloudScan:
    """A :class:`~gpomap.clouds.CloudScan` from a ``sensor_msgs/PointCloud2`` and the sensor's pose.

    The fields are decoded as the bag reader decodes them (:mod:`gpomap.io.pointcloud2`: x, y, z
    FLOAT32 or FLOAT64, either byte order, any padding); NaN points stay as invalid rays.

    Parameters
    ----------
    msg : PointCloud2-like
        ``fields`` (name, offset, datatype), ``is_bigendian``, ``point_step``, ``row_step``,
        ``height``, ``width``, ``data``, and a ``header``.
    pose : ndarray of shape (4, 4)
        The sensor frame (the message's ``frame_id``) in the map's fixed frame at the stamp.
    max_range : float, optional
        Points farther than this from the sensor become no-return rays ending at it.
    source : str
        The topic, for error messages.

    Returns
    -------
    CloudScan
        Points in the fixed frame, the origin at the pose's translation; ``time`` the header stamp.

    Raises
    ------
    InputFormatError
        No field x, y or z, non-float coordinates, data shorter than the geometry, or a pose that
        is not a finite 4 x 4 matrix; naming `source`.
    """
    from gpomap.clouds import cloud_from_points
    from gpomap.io.pointcloud2 import _xyz
    from gpomap.io.poses import transform_points

    t = np.asarray(pose, dtype=float)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise InputFormatError(f"{source}: the sensor pose must be a finite 4 x 4 matrix, got shape {t.shape}")
    # The decoder reads `data` as a uint8 array: rclpy gives array('B'), other sources bytes.
    view = _CloudView(msg, np.frombuffer(bytes(msg.data), dtype=np.uint8))
    points = transform_points(t, _xyz(view, source, None))  # type: ignore[arg-type]  # no file: the topic names it
    header = getattr(msg, "header", None)
    stamp = stamp_seconds(header.stamp) if header is not None else None
    meta = {"frame_id": str(header.frame_id).lstrip("/"), "topic": source} if header is not None else {"topic": source}
    return cloud_from_points(t[:3, 3], points, max_range=max_range, time=stamp, meta=meta)


@dataclass(frozen=True)
class GridLayers:
    """An occupancy map as the three ``nav_msgs/OccupancyGrid`` layers the node publishes.

    Attributes
    ----------
    grid : GridSpec
        Geometry: ``info.resolution``, ``info.width`` (nx), ``info.height`` (ny), ``info.origin``.
    trinary : ndarray of int8, shape (ny * nx,)
        map_server's convention: 0 free, 100 occupied, -1 unknown (the map's thresholds).
    probability : ndarray of int8, shape (ny * nx,)
        Occupancy probability in percent, 0..100.
    variance : ndarray of int8, shape (ny * nx,)
        Latent variance as a percentage of the prior variance, 0..100 (100 = the map knows
        nothing there); -1 where the map has no variance.
    """

    grid: GridSpec
    trinary: NDArray[np.int8]
    probability: NDArray[np.int8]
    variance: NDArray[np.int8]

    @property
    def width(self) -> int:
        """Cells along x (``info.width``)."""
        return self.grid.shape[1]

    @property
    def height(self) -> int:
        """Cells along y (``info.height``)."""
        return self.grid.shape[0]


def _percent(values: NDArray[np.float64]) -> NDArray[np.int8]:
    """Values in [0, 1] as int8 percentages 0..100; NaN becomes unknown (-1)."""
    v = np.asarray(values, dtype=float).ravel()
    out = np.full(v.size, UNKNOWN_CELL, dtype=np.int8)
    ok = np.isfinite(v)
    out[ok] = np.rint(100.0 * np.clip(v[ok], 0.0, 1.0)).astype(np.int8)
    return out


def grid_layers(occupancy_map: OccupancyMap, prior_variance: float | None = None) -> GridLayers:
    """The trinary, probability and variance layers of `occupancy_map`, ready for OccupancyGrid ``data``.

    Parameters
    ----------
    occupancy_map : OccupancyMap
        Arrays of shape (ny, nx), row 0 at the lowest y.
    prior_variance : float, optional
        The GP's prior (signal) variance: the variance layer is ``variance / prior_variance``
        in percent. Default the largest variance in the map.

    Returns
    -------
    GridLayers
    """
    ternary = occupancy_map.ternary.ravel()
    trinary = np.full(ternary.size, UNKNOWN_CELL, dtype=np.int8)
    for label, value in _TRINARY.items():
        trinary[ternary == label] = value
    probability = _percent(occupancy_map.probability)
    if occupancy_map.variance is None:
        variance = np.full(trinary.size, UNKNOWN_CELL, dtype=np.int8)
    else:
        var = np.asarray(occupancy_map.variance, dtype=float)
        scale = prior_variance if prior_variance is not None else (float(np.nanmax(var)) if np.isfinite(var).any() else 1.0)
        variance = _percent(var / scale if scale > 0 else np.zeros_like(var))
    return GridLayers(occupancy_map.grid, trinary, probability, variance)
