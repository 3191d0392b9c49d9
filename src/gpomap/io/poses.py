"""3-D sensor poses: quaternions, 4x4 matrices and pose files.

A pose is a 4x4 homogeneous matrix ``T`` (sensor to map frame: ``p_map = T[:3, :3] @ p_sensor +
T[:3, 3]``), the form the 3-D readers use. Sources:

- a PCD ``VIEWPOINT`` line, ``tx ty tz qw qx qy qz`` (:func:`pose_from_viewpoint`);
- a one-pose matrix file, 4 lines of 4 numbers, as 3DMatch's ``frame-*.pose.txt``
  (:func:`read_pose_matrix`);
- a pose list, one pose per line for a sequence of clouds (:func:`read_pose_list`), where the
  number of values on a line says the layout:

  ==========  ==========================================================================
  values      layout
  ==========  ==========================================================================
  7           ``tx ty tz qw qx qy qz`` (the PCD ``VIEWPOINT`` order)
  8           ``time tx ty tz qx qy qz qw`` (TUM RGB-D trajectories: quaternion w last)
  12          a 3x4 matrix ``[R | t]``, row by row (KITTI poses)
  16          a 4x4 matrix, row by row (last row 0 0 0 1)
  ==========  ==========================================================================

  Blank lines and lines starting with ``#`` are skipped.
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.io.checks import regular_file

__all__ = ["quaternion_matrix", "pose_matrix", "pose_from_viewpoint", "read_pose_matrix", "read_pose_list", "transform_points"]

#: A quaternion whose norm is farther than this from 1 is refused (a typo, or the wrong order).
QUATERNION_TOLERANCE = 1e-3
#: Largest pose file read, bytes (a pose list of a million poses is ~100 MB).
MAX_POSE_FILE_BYTES = 1 << 28


def quaternion_matrix(w: float, x: float, y: float, z: float) -> NDArray[np.float64]:
    """Rotation matrix of the unit quaternion ``w + xi + yj + zk``, shape (3, 3).

    Raises
    ------
    ValueError
        A non-finite component, or a norm not within :data:`QUATERNION_TOLERANCE` of 1.
    """
    q = np.array([w, x, y, z], dtype=float)
    n = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or abs(n - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"quaternion (w, x, y, z) = ({w:g}, {x:g}, {y:g}, {z:g}) has norm {n:.6g}; expected a unit quaternion")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_matrix(rotation: NDArray[np.float64], translation: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 homogeneous matrix of a rotation (3, 3) and a translation (3,)."""
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = translation
    return t


def pose_from_viewpoint(values: NDArray[np.float64] | list[float]) -> NDArray[np.float64]:
    """4x4 pose of ``tx ty tz qw qx qy qz`` (a PCD ``VIEWPOINT``), shape (4, 4).

    Raises
    ------
    ValueError
        Not 7 finite values, or not a unit quaternion.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.shape != (7,) or not np.isfinite(v).all():
        raise ValueError(f"expected 7 finite values tx ty tz qw qx qy qz, got {v.tolist()}")
    return pose_matrix(quaternion_matrix(*v[3:]), v[:3])


def _check_matrix(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """`m` (4, 4) if it is a rigid transform: finite, last row 0 0 0 1, rotation orthonormal."""
    if not np.isfinite(m).all():
        raise ValueError("pose matrix has non-finite values")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError(f"pose matrix's last row is {m[3].tolist()}; expected 0 0 0 1")
    r = m[:3, :3]
    err = float(np.abs(r @ r.T - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(r) < 0:
        raise ValueError(f"pose matrix's 3x3 block is not a rotation (|R R^T - I| = {err:.3g}, det {np.linalg.det(r):.3g})")
    return m


def _numbers(line: str, path: str, lineno: int) -> NDArray[np.float64]:
    try:
        return np.array([float(v) for v in line.replace(",", " ").split()])
    except ValueError:
        raise InputFormatError(f"expected numbers, got {line.strip()[:80]!r}", path=path, line=lineno) from None


def _lines(path: str | os.PathLike[str], what: str) -> list[tuple[int, str]]:
    """Non-blank, non-comment lines of a small text file, with their 1-based numbers."""
    p = regular_file(path, what)
    if p.stat().st_size > MAX_POSE_FILE_BYTES:
        raise InputFormatError(f"is {p.stat().st_size:,} bytes; a {what} is at most {MAX_POSE_FILE_BYTES:,}", path=str(p))
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(f"cannot read as a text {what} ({exc})", path=str(p)) from None
    return [(i, s) for i, s in enumerate(text.splitlines(), 1) if s.strip() and not s.lstrip().startswith("#")]


def read_pose_matrix(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """One 4x4 camera-to-world pose written as 4 lines of 4 numbers (3DMatch ``*.pose.txt``).

    Returns
    -------
    ndarray of shape (4, 4)

    Raises
    ------
    InputFormatError
        Not 4 lines of 4 numbers, or not a rigid transform (names the file and the line).
    """
    spath = str(path)
    rows = _lines(path, "pose matrix file")
    if len(rows) != 4:
        raise InputFormatError(f"has {len(rows)} lines of numbers; expected 4 lines of 4 (a 4x4 pose matrix)", path=spath)
    m = np.empty((4, 4))
    for k, (lineno, line) in enumerate(rows):
        v = _numbers(line, spath, lineno)
        if v.size != 4:
            raise InputFormatError(f"has {v.size} values; expected 4 (row {k + 1} of a 4x4 pose matrix)", path=spath, line=lineno)
        m[k] = v
    try:
        return _check_matrix(m)
    except ValueError as exc:
        raise InputFormatError(str(exc), path=spath) from None


def read_pose_list(path: str | os.PathLike[str]) -> list[NDArray[np.float64]]:
    """Poses one per line (7, 8, 12 or 16 values; see the module docstring).

    Returns
    -------
    list of ndarray of shape (4, 4)
        In file order.

    Raises
    ------
    InputFormatError
        A line with another number of values, text that is not numbers, a quaternion that is not
        a unit one, a matrix that is not a rigid transform (each with the file and the line), or no
        poses at all.
    """
    spath = str(path)
    poses: list[NDArray[np.float64]] = []
    for lineno, line in _lines(path, "pose file"):
        v = _numbers(line, spath, lineno)
        try:
            if v.size == 7:
                poses.append(pose_from_viewpoint(v))
            elif v.size == 8:
                poses.append(pose_matrix(quaternion_matrix(v[7], v[4], v[5], v[6]), v[1:4]))
            elif v.size in (12, 16):
                m = np.eye(4)
                m[: v.size // 4] = v.reshape(-1, 4)
                poses.append(_check_matrix(m))
            else:
                raise ValueError(
                    f"has {v.size} values; expected 7 (tx ty tz qw qx qy qz), 8 (TUM: time tx ty tz qx qy qz qw), "
                    "12 (3x4 matrix) or 16 (4x4 matrix)"
                )
        except ValueError as exc:
            raise InputFormatError(str(exc), path=spath, line=lineno) from None
    if not poses:
        raise InputFormatError("holds no poses; expected one pose per line", path=spath)
    return poses


def transform_points(pose: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points (n, 3) in the sensor frame to the map frame by `pose` (4, 4); shape (n, 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]
