"""A live buffer of planar robot poses from ``nav_msgs/Odometry``, free of any ROS library.

The ROS 2 node takes its poses from odometry messages because neither ``tf2_ros`` nor
``tf2_msgs`` is on PyPI (``pip install "gpomap[ros2]"`` cannot subscribe to ``/tf``). The odometry
gives the robot's frame (its ``child_frame_id``) in the fixed frame; the laser's mounting on the
robot is the node's ``sensor_pose`` parameter, constant as a static transform is. A pose at a scan's
stamp is interpolated between the two odometry poses around it as the bag reader interpolates tf
(:mod:`gpomap.io.rosbag`): linearly in x and y, along the shorter arc in yaw.
:class:`PoseBuffer3D` keeps the odometry's full 6-DoF pose for point clouds: linear in position,
spherical (slerp) in rotation, as the bag reader interpolates tf for clouds.
"""

from __future__ import annotations

import bisect
import math
import threading

import numpy as np
from numpy.typing import NDArray

__all__ = ["PoseBuffer", "PoseBuffer3D"]

#: Stamps this close (seconds) to the newest or oldest pose are taken as at it (the bag reader's tolerance).
TIME_TOLERANCE = 1e-6


def _wrap(angle: float) -> float:
    """`angle` in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class PoseBuffer:
    """Planar poses (x, y, yaw) of the robot by time; the sensor's pose at any time between them.

    Parameters
    ----------
    sensor_pose : (x, y, yaw)
        The sensor frame's pose in the robot's frame (metres, radians).
    upside_down : bool
        The sensor is mounted upside down (its z axis points down): its beams are mirrored.
    cache_seconds : float
        Poses older than this behind the newest are forgotten (a robot runs for hours).

    Notes
    -----
    :meth:`add` may be called from a subscription's thread while :meth:`lookup` runs in another.
    """

    def __init__(
        self, sensor_pose: tuple[float, float, float] = (0.0, 0.0, 0.0), upside_down: bool = False, cache_seconds: float = 60.0
    ) -> None:
        if len(sensor_pose) != 3 or not all(math.isfinite(float(v)) for v in sensor_pose):
            raise ValueError(f"sensor_pose must be three finite numbers (x, y, yaw), got {list(sensor_pose)}")
        if not cache_seconds > 0:
            raise ValueError(f"cache_seconds must be positive, got {cache_seconds}")
        self.sensor_pose = (float(sensor_pose[0]), float(sensor_pose[1]), float(sensor_pose[2]))
        self.upside_down = bool(upside_down)
        self.cache_seconds = float(cache_seconds)
        self._t: list[float] = []
        self._p: list[tuple[float, float, float]] = []
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t: float, x: float, y: float, yaw: float) -> None:
        """Record the robot's pose at time `t` (seconds); a later pose of the same stamp replaces it."""
        values = (float(x), float(y), float(yaw))
        if not (math.isfinite(t) and all(math.isfinite(v) for v in values)):
            return
        with self._lock:
            i = bisect.bisect_left(self._t, t)
            if i < len(self._t) and self._t[i] == t:
                self._p[i] = values
            else:
                self._t.insert(i, t)
                self._p.insert(i, values)
            # Forget what is older than the cache behind the newest pose.
            keep = bisect.bisect_left(self._t, self._t[-1] - self.cache_seconds)
            if keep > 0:
                del self._t[:keep], self._p[:keep]

    def robot_pose(self, t: float) -> tuple[float, float, float] | None:
        """The robot's pose at `t`, interpolated; None outside the poses' time span (not known yet, or forgotten)."""
        with self._lock:
            if not self._t or t < self._t[0] - TIME_TOLERANCE or t > self._t[-1] + TIME_TOLERANCE:
                return None
            if len(self._t) == 1:
                return self._p[0]
            i = min(max(bisect.bisect_right(self._t, t) - 1, 0), len(self._t) - 2)
            t0, t1 = self._t[i], self._t[i + 1]
            (x0, y0, a0), (x1, y1, a1) = self._p[i], self._p[i + 1]
        f = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
        return x0 + f * (x1 - x0), y0 + f * (y1 - y0), _wrap(a0 + f * _wrap(a1 - a0))

    def lookup(self, frame: str, t: float) -> tuple[float, float, float, bool] | None:
        """The sensor's pose (x, y, yaw) at `t` in the odometry's frame and whether it is upside down.

        The signature of :data:`gpomap.ros.live.PoseLookup`; `frame` (the scan's ``frame_id``)
        is not used: the sensor is the one `sensor_pose` describes.
        """
        robot = self.robot_pose(t)
        if robot is None:
            return None
        x, y, yaw = robot
        sx, sy, syaw = self.sensor_pose
        c, s = math.cos(yaw), math.sin(yaw)
        return x + c * sx - s * sy, y + s * sx + c * sy, _wrap(yaw + syaw), self.upside_down


class PoseBuffer3D:
    """6-DoF poses of the robot by time; the 3-D sensor's pose (a 4 x 4 matrix) at any time between them.

    Parameters
    ----------
    sensor_pose : (x, y, z, roll, pitch, yaw)
        The sensor frame's pose in the robot's frame (metres; radians, fixed-axis roll, pitch, yaw as tf).
    cache_seconds : float
        Poses older than this behind the newest are forgotten.

    Notes
    -----
    :meth:`add` may be called from a subscription's thread while :meth:`lookup` runs in another.
    """

    def __init__(self, sensor_pose: tuple[float, ...] = (0.0,) * 6, cache_seconds: float = 60.0) -> None:
        from gpomap.io.poses import pose_matrix
        from gpomap.ros.messages import euler_matrix

        if len(sensor_pose) != 6 or not all(math.isfinite(float(v)) for v in sensor_pose):
            raise ValueError(f"sensor_pose must be six finite numbers (x, y, z, roll, pitch, yaw), got {list(sensor_pose)}")
        if not cache_seconds > 0:
            raise ValueError(f"cache_seconds must be positive, got {cache_seconds}")
        v = [float(a) for a in sensor_pose]
        #: The sensor in the robot's frame, shape (4, 4).
        self.mount = pose_matrix(euler_matrix(v[3], v[4], v[5]), np.array(v[:3]))
        self.cache_seconds = float(cache_seconds)
        self._t: list[float] = []
        self._p: list[NDArray[np.float64]] = []
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t: float, position: tuple[float, float, float], orientation: tuple[float, float, float, float]) -> None:
        """Record the robot's pose at `t`: position (x, y, z) and orientation quaternion (x, y, z, w); bad values are skipped."""
        q = np.array(orientation, dtype=float)
        values = np.concatenate([np.array(position, dtype=float), q])
        norm = float(np.linalg.norm(q))
        if not (math.isfinite(t) and np.isfinite(values).all() and norm > 0.5):
            return
        values[3:] /= norm
        with self._lock:
            i = bisect.bisect_left(self._t, t)
            if i < len(self._t) and self._t[i] == t:
                self._p[i] = values
            else:
                self._t.insert(i, t)
                self._p.insert(i, values)
            keep = bisect.bisect_left(self._t, self._t[-1] - self.cache_seconds)
            if keep > 0:
                del self._t[:keep], self._p[:keep]

    def robot_pose(self, t: float) -> NDArray[np.float64] | None:
        """The robot's pose at `t` as (x, y, z, qx, qy, qz, qw), shape (7,); None outside the poses' time span."""
        from gpomap.io.tftree import slerp

        with self._lock:
            if not self._t or t < self._t[0] - TIME_TOLERANCE or t > self._t[-1] + TIME_TOLERANCE:
                return None
            if len(self._t) == 1:
                return self._p[0].copy()
            i = min(max(bisect.bisect_right(self._t, t) - 1, 0), len(self._t) - 2)
            t0, t1 = self._t[i], self._t[i + 1]
            p0, p1 = self._p[i], self._p[i + 1]
        f = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
        q = slerp(p0[None, 3:], p1[None, 3:], np.array([f]))[0]
        return np.concatenate([p0[:3] + f * (p1[:3] - p0[:3]), q])

    def lookup(self, frame: str, t: float) -> NDArray[np.float64] | None:
        """The sensor's pose in the odometry's frame at `t`, shape (4, 4); None while not known.

        `frame` (the cloud's ``frame_id``) is not used: the sensor is the one `sensor_pose` describes.
        """
        from gpomap.io.poses import pose_matrix, quaternion_matrix

        robot = self.robot_pose(t)
        if robot is None:
            return None
        x, y, z, qx, qy, qz, qw = (float(v) for v in robot)
        return pose_matrix(quaternion_matrix(qw, qx, qy, qz), np.array([x, y, z])) @ self.mount
