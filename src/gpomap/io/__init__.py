"""Reading range data: :func:`read_scans` (2-D) and :func:`read_clouds` (3-D) pick the reader by format.

2-D formats: CARMEN logs (:mod:`gpomap.io.carmen`), ROS1 bags and ROS2 bag directories / ``.db3`` /
``.mcap`` files (:mod:`gpomap.io.rosbag`). Labelled points for users with their own
pre-processing are read by :func:`read_points` (:mod:`gpomap.io.arrays`); they are not scans.

3-D formats (:func:`read_clouds`, lists of :class:`~gpomap.clouds.CloudScan`): PCD files
(:mod:`gpomap.io.pcd`), PLY files with a poses file (:mod:`gpomap.io.ply`), a directory of either
(one scan per file, in natural order of the names), 3DMatch-style directories of depth images
(:mod:`gpomap.io.depth`), OctoMap ScanGraphs (:mod:`gpomap.io.scangraph`) and ``PointCloud2``
messages in ROS bags (:mod:`gpomap.io.pointcloud2`). OctoMap ``.bt`` / ``.ot`` trees are maps, not
scans: :func:`gpomap.io.octomap.read_octree` reads them, and :func:`describe` summarises them.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.clouds import CloudScan
from gpomap.errors import InputFormatError
from gpomap.io.arrays import read_points, write_points
from gpomap.io.carmen import is_carmen_text, read_carmen
from gpomap.io.checks import ros2_bag_directory
from gpomap.io.rosbag import load_rosbag, read_rosbag
from gpomap.scans import Scan

__all__ = [
    "read_scans",
    "read_clouds",
    "CLOUD_FORMATS",
    "describe",
    "detect_format",
    "read_carmen",
    "read_rosbag",
    "load_rosbag",
    "read_points",
    "write_points",
]

_CARMEN_SUFFIXES = (".log", ".clf", ".log.gz", ".clf.gz", ".gz", ".txt")
_ROS2_SUFFIXES = (".db3", ".mcap")
#: Formats whose data are 3-D scans (:func:`read_clouds`); "octomap" is a 3-D map.
CLOUD_FORMATS = ("pcd", "ply", "pcd-directory", "ply-directory", "depth-directory", "scangraph")
_BAG_OPTIONS = ("topic", "fixed_frame", "odom_topic", "time_offset")


def _natural_key(name: str) -> list[object]:
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _directory_format(p: Path) -> str | None:
    """The 3-D format of a directory (depth frames, PCD or PLY files), or None."""
    from gpomap.io.depth import is_depth_directory

    if not p.is_dir() or (p / "metadata.yaml").is_file():
        return None
    if is_depth_directory(p):
        return "depth-directory"
    for suffix in ("pcd", "ply"):
        if any(p.glob(f"*.{suffix}")):
            return f"{suffix}-directory"
    return None


def _head(path: Path, size: int = 65536) -> bytes:
    try:
        with path.open("rb") as f:
            head = f.read(size)
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc})", path=str(path)) from None
    if head[:2] == b"\x1f\x8b":
        # Decompress just the start: enough to see the first message names.
        try:
            return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head)
        except zlib.error:
            return b""
    return head


def detect_format(path: str | os.PathLike[str]) -> str:
    """Name the format of `path`.

    ``"carmen"``, ``"rosbag1"``, ``"rosbag2"`` (2-D scans; bags may hold ``PointCloud2`` too),
    ``"pcd"``, ``"ply"``, ``"scangraph"``, ``"pcd-directory"``, ``"ply-directory"``,
    ``"depth-directory"`` (3-D scans) or ``"octomap"`` (a ``.bt`` / ``.ot`` tree).

    Directories with a ``metadata.yaml`` are ROS2 bags, with ``camera-intrinsics.txt`` and depth
    images depth frames, with ``.pcd`` or ``.ply`` files sequences of clouds; for files the magic
    bytes decide, then the suffix, then the content (first message names).

    Raises
    ------
    InputFormatError
        Missing path, or a format none of the readers knows.
    """
    from gpomap.io.octomap import is_octree_file
    from gpomap.io.pcd import is_pcd
    from gpomap.io.ply import is_ply
    from gpomap.io.scangraph import is_scangraph

    p = Path(path)
    directory = _directory_format(p)
    if directory is not None:
        return directory
    if ros2_bag_directory(p, "CARMEN log or a ROS bag"):
        return "rosbag2"
    head = _head(p)
    if head.startswith(b"#ROSBAG"):
        return "rosbag1"
    if head.startswith(b"#ROSRECORD"):
        # ROS1 bags before format 2.0 (ROS C Turtle and older): rosbags reads 2.0 only.
        magic = head.split(b"\n", 1)[0].decode("ascii", "replace")
        raise InputFormatError(
            f"a ROS bag of the old format {magic[len('#ROSRECORD') :].strip()} ({magic!r}); gpomap reads ROS1 bags "
            "of format 2.0 and ROS2 bags. ROS's own rosbag reads the old format: "
            "`rosbag filter IN.bag OUT.bag True` writes it again as 2.0",
            path=str(p),
        )
    if head.startswith(b"SQLite format 3") or head.startswith(b"\x89MCAP"):
        return "rosbag2"
    if is_octree_file(head):
        return "octomap"
    if is_ply(head):
        return "ply"
    name = p.name.lower()
    if name.endswith(".pcd") or is_pcd(head):
        return "pcd"
    if name.endswith(".graph") or is_scangraph(head, p.stat().st_size):
        return "scangraph"
    if name.endswith(".bag"):
        return "rosbag1"
    if name.endswith(_ROS2_SUFFIXES):
        return "rosbag2"
    if name.endswith(_CARMEN_SUFFIXES) or is_carmen_text(head):
        return "carmen"
    raise InputFormatError(
        "unrecognised format; expected a CARMEN log (.log, .log.gz, .clf), a ROS1 bag (.bag), "
        "a ROS2 bag (directory, .db3, .mcap), a PCD or PLY point cloud (or a directory of them), "
        "a directory of depth images with camera-intrinsics.txt, an OctoMap ScanGraph (.graph) or tree (.bt, .ot)",
        path=str(p),
    )


def read_scans(path: str | os.PathLike[str], **options: Any) -> list[Scan]:
    """Read the laser scans in `path`, whatever its format.

    Parameters
    ----------
    path : path-like
        CARMEN log, ROS1 bag, or ROS2 bag (directory, ``.db3`` or ``.mcap``).
    **options
        Passed to the reader: :func:`gpomap.io.carmen.read_carmen` (``angles``, ``max_range``,
        ``laser_offset``) or :func:`gpomap.io.rosbag.read_rosbag` (``topic``, ``fixed_frame``,
        ``odom_topic``, ``time_offset``, ...).

    Returns
    -------
    list of Scan
    """
    fmt = detect_format(path)
    if fmt == "carmen":
        return read_carmen(path, **options)
    return read_rosbag(path, **options)


def _cloud_files(directory: Path, suffix: str) -> list[Path]:
    return sorted(directory.glob(f"*.{suffix}"), key=lambda q: _natural_key(q.name))


def read_clouds(
    path: str | os.PathLike[str],
    poses: str | os.PathLike[str] | None = None,
    max_range: float | None = None,
    **options: Any,
) -> list[CloudScan]:
    """Read the 3-D scans in `path`, whatever its format.

    Parameters
    ----------
    path : path-like
        A PCD or PLY file, a directory of them (one scan per file, natural order of the names:
        ``scan_2`` before ``scan_10``), a directory of depth frames, an OctoMap ScanGraph, or a
        ROS bag with ``PointCloud2`` messages.
    poses : path-like, optional
        A pose list (:func:`gpomap.io.poses.read_pose_list`), one sensor-to-map pose per file in
        order; the points are then in the sensor frame. Required for PLY; for PCD it replaces the
        files' ``VIEWPOINT``.
    max_range : float, optional
        Points farther than this from their sensor become no-return rays ending at it.
    **options
        Passed to the reader: ``points_frame`` (PCD), ``stride`` and ``depth_scale`` (depth
        frames), ``topic``, ``fixed_frame``, ``time_offset`` (bags).

    Returns
    -------
    list of CloudScan

    Raises
    ------
    InputFormatError
        An unknown format, an OctoMap tree (a map: :func:`gpomap.io.octomap.read_octree`), a poses
        file whose count differs from the files', PLY without poses, and each reader's errors.
    """
    from gpomap.io.depth import read_depth_frames
    from gpomap.io.pcd import read_pcd
    from gpomap.io.ply import read_ply
    from gpomap.io.poses import read_pose_list
    from gpomap.io.scangraph import read_scangraph

    p = Path(path)
    fmt = detect_format(p)
    if fmt in ("pcd", "ply", "pcd-directory", "ply-directory"):
        suffix = fmt.split("-")[0]
        files = _cloud_files(p, suffix) if fmt.endswith("directory") else [p]
        pose_list: list[Any] = [None] * len(files)
        if poses is not None:
            pose_list = read_pose_list(poses)
            if len(pose_list) != len(files):
                raise InputFormatError(
                    f"holds {len(pose_list)} poses for {len(files)} {suffix.upper()} files; expected one per file",
                    path=str(poses),
                )
        elif suffix == "ply":
            raise InputFormatError("PLY files carry no sensor pose; give a poses file (poses=, one pose per file)", path=str(p))
        if suffix == "pcd":
            return [read_pcd(f, pose=t, max_range=max_range, **options) for f, t in zip(files, pose_list)]
        return [read_ply(f, pose=t, max_range=max_range) for f, t in zip(files, pose_list)]
    if poses is not None:
        raise InputFormatError(f"a poses file applies to PCD and PLY files; this is {fmt}", path=str(p))
    if fmt == "depth-directory":
        return read_depth_frames(p, max_range=max_range, **options)
    if fmt == "scangraph":
        return read_scangraph(p, max_range=max_range)
    if fmt in ("rosbag1", "rosbag2"):
        from gpomap.io.pointcloud2 import read_pointcloud2

        return read_pointcloud2(p, max_range=max_range, **options)
    if fmt == "octomap":
        raise InputFormatError("is an OctoMap tree (a map, not scans); read it with gpomap.io.octomap.read_octree", path=str(p))
    raise InputFormatError(f"holds 2-D laser scans ({fmt}); read it with read_scans", path=str(p))


def _box(lower: np.ndarray, upper: np.ndarray) -> tuple[float, ...]:
    """(xmin, xmax, ymin, ymax, zmin, zmax) of a 3-D box."""
    return tuple(float(v) for pair in zip(lower, upper) for v in pair)


def _describe_3d(path: Path, fmt: str, **options: Any) -> dict[str, Any]:
    """:func:`describe` of a 3-D file: clouds or an OctoMap tree."""
    if fmt == "octomap":
        from gpomap.io.octomap import read_octree

        tree = read_octree(path)
        lower, upper = tree.extent() if tree.n_leaves else (np.zeros(3), np.zeros(3))
        return {
            "path": str(path),
            "format": f"octomap ({tree.kind})",
            "resolution": tree.resolution,
            "n_nodes": tree.n_nodes,
            "n_leaves": tree.n_leaves,
            "n_occupied": int(tree.occupied.sum()),
            "n_free": int((~tree.occupied).sum()),
            "leaf_sizes": _as_number(sorted({float(s) for s in tree.sizes.round(6)})) if tree.n_leaves else None,
            "extent": _box(lower, upper),
            **tree.params,
            "notes": [],
        }
    if fmt not in ("rosbag1", "rosbag2"):
        options = {k: v for k, v in options.items() if k not in _BAG_OPTIONS}
    clouds = read_clouds(path, **options)
    flags = [np.asarray(c.hit, dtype=bool) for c in clouds]  # never None once a CloudScan is built
    hits = [c.points[c.valid() & h] for c, h in zip(clouds, flags)]
    n_hits = int(sum(len(h) for h in hits))
    origins = np.array([c.origin for c in clouds])
    times = [c.time for c in clouds if c.time is not None]
    ranges = [c.max_range for c in clouds if c.max_range is not None]
    all_hits = np.concatenate(hits) if n_hits else None
    return {
        "path": str(path),
        "format": fmt,
        "n_scans": len(clouds),
        "points_per_scan": _as_number([c.n_points for c in clouds]),
        "max_range": _as_number(ranges) if ranges else None,
        "n_points": int(sum(c.n_points for c in clouds)),
        "n_hits": n_hits,
        "n_no_return": sum(int((c.valid() & ~h).sum()) for c, h in zip(clouds, flags)),
        "n_invalid": int(sum(int((~c.valid()).sum()) for c in clouds)),
        "origin_extent": _box(origins.min(axis=0), origins.max(axis=0)),
        "hit_extent": _box(all_hits.min(axis=0), all_hits.max(axis=0)) if all_hits is not None else None,
        "time_span": float(max(times) - min(times)) if len(times) == len(clouds) and times else None,
        "notes": [],
    }


def _as_number(values: Sequence[int | float]) -> Any:
    """One value if all are equal, else the sorted distinct values."""
    distinct = sorted(set(values))
    return distinct[0] if len(distinct) == 1 else distinct


def _extent(points: np.ndarray) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of points of shape (n, 2)."""
    return (
        float(points[:, 0].min()),
        float(points[:, 0].max()),
        float(points[:, 1].min()),
        float(points[:, 1].max()),
    )


def describe(path: str | os.PathLike[str], **options: Any) -> dict[str, Any]:
    """Summary of a range-data file, for ``gpomap info``.

    For 3-D scans (:data:`CLOUD_FORMATS`, or a bag with ``PointCloud2`` and no ``LaserScan``):
    ``path``, ``format``, ``n_scans``, ``points_per_scan``, ``max_range``, ``n_points``,
    ``n_hits``, ``n_no_return``, ``n_invalid``, ``origin_extent`` and ``hit_extent`` ((xmin, xmax,
    ymin, ymax, zmin, zmax), metres), ``time_span``, ``notes``. For an OctoMap tree:
    ``resolution``, ``n_nodes``, ``n_leaves``, ``n_occupied``, ``n_free``, ``leaf_sizes``,
    ``extent`` and the tree's sensor model (``prob_hit``, ``prob_miss``, ``clamping_min``,
    ``clamping_max``, ``occupancy_threshold``). Otherwise (2-D scans):

    Parameters
    ----------
    path : path-like
    **options
        Passed to :func:`read_scans`.

    Returns
    -------
    dict
        ``path``, ``format``, ``n_scans``, ``beams_per_scan`` and ``max_range`` (a number, or the
        sorted distinct values when scans differ), ``n_beams``, ``n_hits``, ``n_no_return``,
        ``n_invalid``, ``pose_extent`` and ``hit_extent`` ((xmin, xmax, ymin, ymax), metres),
        ``time_span`` (seconds; None without usable stamps) and, for bags, ``n_dropped``; then the
        no-return decision: ``no_return_code`` (the code value(s) found in the data, or None),
        ``no_return_source`` (``"user"``, ``"header"``, ``"data"`` or ``"none found"``; see
        :mod:`gpomap.io.noreturn`), ``no_return`` (the full decision, or a list of them when
        message types differ) and ``notes`` (lines saying what was decided, contradictions
        between the file's header and the data first).
    """
    from gpomap.io.pointcloud2 import bag_has_pointclouds_only

    fmt = detect_format(path)
    if fmt in CLOUD_FORMATS or fmt == "octomap" or (fmt in ("rosbag1", "rosbag2") and bag_has_pointclouds_only(path)):
        return _describe_3d(Path(path), fmt, **options)
    extra: dict[str, Any] = {}
    if fmt == "carmen":
        scans = read_carmen(path, **options)
    else:
        result = load_rosbag(path, **options)
        scans = result.scans
        extra = {"topic": result.topic, "n_dropped": result.n_dropped}
    poses = np.array([s.pose for s in scans])
    hits = [s.hits() for s in scans]
    n_hits = int(sum(len(h) for h in hits))
    times = [s.time for s in scans if s.time is not None]
    info: dict[str, Any] = {
        "path": str(path),
        "format": fmt,
        "n_scans": len(scans),
        "beams_per_scan": _as_number([s.n_beams for s in scans]),
        "max_range": _as_number([s.max_range for s in scans]),
        "n_beams": int(sum(s.n_beams for s in scans)),
        "n_hits": n_hits,
        "n_no_return": int(sum(int(s.no_return().sum()) for s in scans)),
        "n_invalid": int(sum(int((~s.valid()).sum()) for s in scans)),
        "pose_extent": _extent(poses[:, :2]),
        "hit_extent": _extent(np.concatenate(hits, axis=0)) if n_hits else None,
        "time_span": float(max(times) - min(times)) if len(times) == len(scans) and times else None,
    }
    info.update(extra)
    info.update(_no_return_report(scans))
    return info


def _no_return_report(scans: Sequence[Scan]) -> dict[str, Any]:
    """The readers' no-return decisions (shared dicts in ``Scan.meta``), for :func:`describe`."""
    decisions: list[dict[str, Any]] = []
    seen: set[int] = set()
    for s in scans:
        d = s.meta.get("no_return")
        if isinstance(d, dict) and id(d) not in seen:
            seen.add(id(d))
            decisions.append(d)
    codes = [d["code"] for d in decisions]
    sources = sorted({str(d["source"]) for d in decisions})
    contradictions = [d["contradiction"] for d in decisions if d.get("contradiction")]
    notes = contradictions + [n for d in decisions for n in d.get("notes", []) if n not in contradictions]
    return {
        "no_return_code": codes[0] if len(codes) == 1 else (codes or None),
        "no_return_source": sources[0] if len(sources) == 1 else (sources or None),
        "no_return": decisions[0] if len(decisions) == 1 else (decisions or None),
        "notes": notes,
    }
