"""Depth images with camera intrinsics and poses (the 3DMatch layout) as :class:`CloudScan`.

A directory holds ``camera-intrinsics.txt`` (the 3x3 matrix K: fx 0 cx / 0 fy cy / 0 0 1) and,
per frame, ``NAME.depth.png`` (16-bit, depth in millimetres by default, 0 = no reading) with
``NAME.pose.txt`` (4x4 camera-to-world, :func:`gpomap.io.poses.read_pose_matrix`). TUM RGB-D
depth images are 16-bit too, at 5000 units per metre: pass ``depth_scale=5000``.

Each valid pixel (u, v) of depth d (metres) is a ray from the camera centre to
``((u - cx) d / fx, (v - cy) d / fy, d)`` in the camera frame (x right, y down, z forward; pixel
(0, 0) is the top-left one and integer coordinates are pixel centres, as OpenCV has it), moved to
the world by the pose. A 0 pixel is no measurement at all (a depth camera reports 0 for too
near, too far and no texture alike), so it is an invalid ray, never free space. With `max_range`,
deeper readings become no-return rays ending at that range.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan, cloud_from_points
from gpomap.errors import InputFormatError
from gpomap.io.checks import regular_file
from gpomap.io.poses import read_pose_matrix, transform_points

__all__ = ["read_depth_frames", "read_depth_image", "read_intrinsics", "is_depth_directory", "INTRINSICS_NAME"]

INTRINSICS_NAME = "camera-intrinsics.txt"
_DEPTH_SUFFIX = ".depth.png"


def is_depth_directory(path: Path) -> bool:
    """Whether `path` is a directory with camera intrinsics and at least one depth image."""
    return path.is_dir() and (path / INTRINSICS_NAME).is_file() and any(path.glob(f"*{_DEPTH_SUFFIX}"))


def read_intrinsics(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """The 3x3 camera matrix K from a text file of 3 lines of 3 numbers.

    Raises
    ------
    InputFormatError
        Not 3 x 3 numbers, a non-positive focal length, or a non-zero skew / last row other than
        0 0 1 (names the line).
    """
    p = regular_file(path, "camera intrinsics file")
    spath = str(p)
    try:
        lines = [(i, s) for i, s in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if s.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(f"cannot read as text ({exc})", path=spath) from None
    if len(lines) != 3:
        raise InputFormatError(f"has {len(lines)} lines of numbers; expected 3 lines of 3 (the camera matrix K)", path=spath)
    k = np.empty((3, 3))
    for row, (lineno, line) in enumerate(lines):
        try:
            v = [float(x) for x in line.split()]
        except ValueError:
            raise InputFormatError(f"expected 3 numbers, got {line.strip()[:80]!r}", path=spath, line=lineno) from None
        if len(v) != 3:
            raise InputFormatError(f"has {len(v)} values; expected 3 (row {row + 1} of K)", path=spath, line=lineno)
        k[row] = v
    if not (np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], [0, 0, 1]) and k[1, 0] == 0):
        raise InputFormatError(
            f"camera matrix {k.tolist()} is not [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0", path=spath
        )
    return k


def _load_depth(path: Path) -> NDArray[np.uint16]:
    from PIL import Image, UnidentifiedImageError

    spath = str(regular_file(path, "16-bit depth PNG"))
    try:
        with Image.open(path) as im:
            if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise InputFormatError(f"image mode {im.mode!r}; expected a 16-bit single-channel depth image", path=spath)
            a = np.asarray(im)
    except InputFormatError:
        raise
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
        raise InputFormatError(f"cannot read as an image ({exc})", path=spath) from None
    if a.ndim != 2 or a.min(initial=0) < 0 or a.max(initial=0) > 65535:
        raise InputFormatError(
            f"depth image of shape {a.shape} and range {a.min()}..{a.max()}; expected 16-bit values", path=spath
        )
    return a.astype(np.uint16)


def read_depth_image(
    depth_path: str | os.PathLike[str],
    intrinsics: NDArray[np.float64],
    pose: NDArray[np.float64],
    depth_scale: float = 1000.0,
    stride: int = 1,
    max_range: float | None = None,
) -> CloudScan:
    """One depth image as a cloud of rays from the camera centre.

    Parameters
    ----------
    depth_path : path-like
        16-bit PNG.
    intrinsics : ndarray of shape (3, 3)
    pose : ndarray of shape (4, 4)
        Camera to world.
    depth_scale : float
        Image units per metre (1000: millimetres).
    stride : int
        Keep every `stride`-th pixel along both image axes (a 640 x 480 frame gives 307,200 rays;
        stride 4 gives 19,200).
    max_range : float, optional

    Returns
    -------
    CloudScan
        One ray per kept pixel (0 pixels invalid: NaN endpoints); ``meta`` has ``path``,
        ``image_shape`` and ``stride``.
    """
    if stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride}")
    depth = _load_depth(Path(depth_path))
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    d = depth[::stride, ::stride].astype(float) / depth_scale
    d[d == 0] = np.nan
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    cam = np.column_stack([((u - cx) * d / fx).ravel(), ((v - cy) * d / fy).ravel(), d.ravel()])
    return cloud_from_points(
        pose[:3, 3],
        transform_points(pose, cam),
        max_range=max_range,
        meta={"path": str(depth_path), "image_shape": (h, w), "stride": stride},
    )


def _natural_key(name: str) -> list[object]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def read_depth_frames(
    directory: str | os.PathLike[str],
    depth_scale: float = 1000.0,
    stride: int = 1,
    max_range: float | None = None,
) -> list[CloudScan]:
    """Every ``NAME.depth.png`` + ``NAME.pose.txt`` pair of a 3DMatch-style directory.

    Parameters
    ----------
    directory : path-like
        Holding ``camera-intrinsics.txt`` and the frames.
    depth_scale, stride, max_range
        As in :func:`read_depth_image`.

    Returns
    -------
    list of CloudScan
        In natural order of the frame names.

    Raises
    ------
    InputFormatError
        Not a directory, no intrinsics file, no depth images, a depth image without its pose
        file, and the errors of :func:`read_intrinsics`, :func:`read_pose_matrix` and the image
        reader.
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputFormatError("is not a directory; expected a directory of depth frames and camera-intrinsics.txt", path=str(d))
    k = read_intrinsics(d / INTRINSICS_NAME)
    frames = sorted(d.glob(f"*{_DEPTH_SUFFIX}"), key=lambda q: _natural_key(q.name))
    if not frames:
        raise InputFormatError(f"no *{_DEPTH_SUFFIX} images in the directory", path=str(d))
    clouds = []
    for f in frames:
        pose_path = f.with_name(f.name[: -len(_DEPTH_SUFFIX)] + ".pose.txt")
        if not pose_path.is_file():
            raise InputFormatError(f"depth image {f.name} has no pose file {pose_path.name} beside it", path=str(d))
        clouds.append(read_depth_image(f, k, read_pose_matrix(pose_path), depth_scale, stride, max_range))
    _warn_if_not_metres(clouds, depth_scale, str(d))
    return clouds


#: A median depth beyond this (m) is not a depth camera's: the units are likely not `depth_scale`'s.
DEPTH_CAMERA_REACH: float = 8.0


def _warn_if_not_metres(clouds: list[CloudScan], depth_scale: float, path: str) -> None:
    """Warn when the frames' median depth is beyond a depth camera's reach (TUM's 5000 units per
    metre read as millimetres put a 4 m room 20 m across)."""
    depths = [np.linalg.norm(c.points[c.valid()] - c.origin, axis=1) for c in clouds]
    every = np.concatenate(depths) if depths else np.zeros(0)
    if every.size and float(np.median(every)) > DEPTH_CAMERA_REACH:
        warnings.warn(
            f"{path}: the median depth is {float(np.median(every)):.1f} m at {depth_scale:g} units per metre, beyond a "
            f"depth camera's reach; if the images are not in those units, give --depth-scale (TUM RGB-D: 5000)",
            stacklevel=3,
        )
