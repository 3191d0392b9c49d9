"""OctoMap ScanGraph files (``.graph``): 3-D scans with the pose each was taken from.

Layout (little-endian; OctoMap's ``ScanGraph::readBinary``, ``ScanNode``, ``Pointcloud`` and
``Pose6D`` are the reference): a uint32 node count, then per node

- a point cloud: uint32 point count, then each point as an int32 3 and three float64 (x, y, z) in
  the sensor frame;
- the sensor pose: int32 3 and three float64 (translation), int32 4 and four float64 (rotation
  quaternion w, x, y, z);
- a uint32 node id;

then a uint32 edge count and the edges (pose constraints between nodes, not needed for mapping
and not read). Each node becomes a :class:`~gpomap.clouds.CloudScan` whose points are the scan
transformed by its pose and whose origin is the pose's translation, as OctoMap inserts them.
``octomap/spherical_scan.graph`` holds one node of 10,201 points taken from (1, 0, -0.5).
"""

from __future__ import annotations

import os
import struct

import numpy as np

from gpomap.clouds import CloudScan, cloud_from_points
from gpomap.errors import InputFormatError
from gpomap.io.checks import regular_file
from gpomap.io.poses import pose_matrix, quaternion_matrix, transform_points

__all__ = ["read_scangraph", "is_scangraph"]

_POINT = np.dtype([("n", "<i4"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
_POSE = struct.Struct("<i3di4d")
#: Largest file read, bytes (a graph is read whole).
MAX_GRAPH_BYTES = 1 << 31


def is_scangraph(head: bytes, size: int) -> bool:
    """Whether a file of `size` bytes starting with `head` looks like a ScanGraph.

    The format has no magic number: the first node's first point must carry the int32 3 a
    ``Pointcloud`` writes before each point, and the announced points must fit in the file.
    """
    if len(head) < 12:
        return False
    n_nodes, n_points, three = struct.unpack_from("<IIi", head)
    return n_nodes > 0 and three == 3 and 8 + n_points * _POINT.itemsize <= size


def read_scangraph(path: str | os.PathLike[str], max_range: float | None = None) -> list[CloudScan]:
    """Read every scan of an OctoMap ScanGraph file.

    Parameters
    ----------
    path : path-like
    max_range : float, optional
        Points farther than this from their sensor become no-return rays ending at it.

    Returns
    -------
    list of CloudScan
        In file order; ``meta`` holds ``path``, ``node`` (index) and ``id``.

    Raises
    ------
    InputFormatError
        Not a regular file; the data end inside a node (says which node and field); a point or
        pose without its int32 3 / 4 element count; a non-unit quaternion.
    """
    p = regular_file(path, "OctoMap ScanGraph (.graph)")
    spath = str(p)
    if p.stat().st_size > MAX_GRAPH_BYTES:
        raise InputFormatError(f"is {p.stat().st_size:,} bytes; at most {MAX_GRAPH_BYTES:,} are read", path=spath)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc})", path=spath) from None

    def need(pos: int, n: int, what: str) -> None:
        if pos + n > len(data):
            raise InputFormatError(
                f"file ends at byte {len(data):,} inside {what}; expected {n} more bytes at byte {pos:,}", path=spath
            )

    need(0, 4, "the node count")
    (n_nodes,) = struct.unpack_from("<I", data, 0)
    pos = 4
    clouds: list[CloudScan] = []
    for node in range(n_nodes):
        need(pos, 4, f"node {node}'s point count")
        (n_points,) = struct.unpack_from("<I", data, pos)
        pos += 4
        need(pos, n_points * _POINT.itemsize, f"node {node}'s {n_points:,} points")
        pts = np.frombuffer(data, _POINT, n_points, pos)
        pos += n_points * _POINT.itemsize
        if n_points and (pts["n"] != 3).any():
            bad = int(np.flatnonzero(pts["n"] != 3)[0])
            raise InputFormatError(
                f"node {node}, point {bad}: element count {int(pts['n'][bad])}; expected 3 (x, y, z) (not a ScanGraph?)",
                path=spath,
            )
        need(pos, _POSE.size, f"node {node}'s pose")
        n3, tx, ty, tz, n4, qw, qx, qy, qz = _POSE.unpack_from(data, pos)
        pos += _POSE.size
        if n3 != 3 or n4 != 4:
            raise InputFormatError(
                f"node {node}'s pose has element counts {n3} and {n4}; expected 3 (translation) and 4 (quaternion)", path=spath
            )
        try:
            pose = pose_matrix(quaternion_matrix(qw, qx, qy, qz), np.array([tx, ty, tz]))
        except ValueError as exc:
            raise InputFormatError(f"node {node}'s pose: {exc}", path=spath) from None
        if not np.isfinite(pose).all():
            raise InputFormatError(f"node {node}'s translation ({tx}, {ty}, {tz}) is not finite", path=spath)
        need(pos, 4, f"node {node}'s id")
        (node_id,) = struct.unpack_from("<I", data, pos)
        pos += 4
        xyz = np.column_stack([pts["x"], pts["y"], pts["z"]])
        clouds.append(
            cloud_from_points(
                pose[:3, 3], transform_points(pose, xyz), max_range=max_range, meta={"path": spath, "node": node, "id": node_id}
            )
        )
    need(pos, 4, "the edge count")
    if not clouds:
        raise InputFormatError("graph has no nodes; expected at least one scan", path=spath)
    return clouds
