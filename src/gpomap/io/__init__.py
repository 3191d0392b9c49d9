"""Reading range data: one entry point, :func:`read_scans`, that picks the reader by format.

Formats: CARMEN logs (:mod:`gpomap.io.carmen`), ROS1 bags and ROS2 bag directories / ``.db3`` /
``.mcap`` files (:mod:`gpomap.io.rosbag`). Labelled points for users with their own
pre-processing are read by :func:`read_points` (:mod:`gpomap.io.arrays`); they are not scans.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import InputFormatError
from gpomap.io.arrays import read_points, write_points
from gpomap.io.carmen import is_carmen_text, read_carmen
from gpomap.io.checks import ros2_bag_directory
from gpomap.io.rosbag import load_rosbag, read_rosbag
from gpomap.scans import Scan

__all__ = [
    "read_scans",
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
    """Name the format of `path`: ``"carmen"``, ``"rosbag1"`` or ``"rosbag2"``.

    Directories with a ``metadata.yaml`` are ROS2 bags; otherwise the suffix decides, and the
    content (magic bytes, first message names) where the suffix is unknown or misleading.

    Raises
    ------
    InputFormatError
        Missing path, or a format none of the readers knows.
    """
    p = Path(path)
    if ros2_bag_directory(p, "CARMEN log or a ROS bag"):
        return "rosbag2"
    head = _head(p)
    if head.startswith(b"#ROSBAG"):
        return "rosbag1"
    if head.startswith(b"SQLite format 3") or head.startswith(b"\x89MCAP"):
        return "rosbag2"
    name = p.name.lower()
    if name.endswith(".bag"):
        return "rosbag1"
    if name.endswith(_ROS2_SUFFIXES):
        return "rosbag2"
    if name.endswith(_CARMEN_SUFFIXES) or is_carmen_text(head):
        return "carmen"
    raise InputFormatError(
        "unrecognised format; expected a CARMEN log (.log, .log.gz, .clf), a ROS1 bag (.bag) "
        "or a ROS2 bag (directory, .db3, .mcap)",
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
    fmt = detect_format(path)
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
