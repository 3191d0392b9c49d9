"""PLY point clouds (ascii or binary, through plyfile) as :class:`CloudScan`.

A PLY file has no sensor pose, so one comes from the caller: a 4x4 sensor-to-map `pose` (a row of
a poses file, :func:`gpomap.io.poses.read_pose_list`), in which case the vertices are in the
sensor frame and are transformed by it, or an `origin` when the vertices are already in the map
frame. The ``vertex`` element's ``x``, ``y`` and ``z`` properties are the points; faces and other
properties are ignored.
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan, cloud_from_points
from gpomap.errors import InputFormatError
from gpomap.extras import require
from gpomap.io.checks import regular_file
from gpomap.io.poses import transform_points

__all__ = ["read_ply", "is_ply"]


def is_ply(head: bytes) -> bool:
    """Whether the start of a file is a PLY header."""
    return head.startswith(b"ply\n") or head.startswith(b"ply\r\n")


def read_ply(
    path: str | os.PathLike[str],
    pose: NDArray[np.float64] | None = None,
    origin: NDArray[np.float64] | None = None,
    max_range: float | None = None,
    time: float | None = None,
) -> CloudScan:
    """Read the vertices of a PLY file as rays from the sensor.

    Parameters
    ----------
    path : path-like
    pose : ndarray of shape (4, 4), optional
        Sensor to map; the vertices are in the sensor frame.
    origin : ndarray of shape (3,), optional
        Sensor position when the vertices are in the map frame already (give `pose` or `origin`).
    max_range : float, optional
        Vertices farther than this from the sensor become no-return rays ending at it.
    time : float, optional

    Returns
    -------
    CloudScan

    Raises
    ------
    InputFormatError
        Not a regular file, not a PLY file (plyfile's message), no ``vertex`` element, or no
        ``x``, ``y`` or ``z`` property.
    """
    PlyData = require("plyfile", "reading PLY files").PlyData

    if (pose is None) == (origin is None):
        raise ValueError(
            "read_ply needs the sensor pose (vertices in the sensor frame) or its origin (vertices in the map frame), not both"
        )
    p = regular_file(path, "PLY point cloud")
    spath = str(p)
    try:
        with open(p, "rb") as f:
            ply = PlyData.read(f)
        if "vertex" not in ply:
            names = ", ".join(e.name for e in ply.elements) or "(none)"
            raise InputFormatError(f"no 'vertex' element (elements: {names}); expected a point cloud", path=spath)
        vertices = ply["vertex"]
        props = vertices.data.dtype.names or ()
        missing = [k for k in ("x", "y", "z") if k not in props]
        if missing:
            raise InputFormatError(f"vertex element has no {', '.join(missing)} (properties: {', '.join(props)})", path=spath)
        xyz = np.column_stack([np.asarray(vertices[k], dtype=float) for k in ("x", "y", "z")]).reshape(-1, 3)
    except InputFormatError:
        raise
    except Exception as exc:  # plyfile raises PlyParseError, PlyHeaderParseError, ValueError, EOFError...
        raise InputFormatError(f"cannot read as a PLY file ({type(exc).__name__}: {str(exc)[:200]})", path=spath) from None
    if pose is not None:
        m = np.asarray(pose, dtype=float)
        return cloud_from_points(m[:3, 3], transform_points(m, xyz), max_range=max_range, time=time, meta={"path": spath})
    return cloud_from_points(np.asarray(origin, dtype=float), xyz, max_range=max_range, time=time, meta={"path": spath})
