"""The options of the data a command reads: the planar readers', the 3-D readers', and which scans and beams are used.

Each group is registered on a command's parser (``add_*_options``) and turned back into the
readers' keyword arguments (:func:`reader_options`, :func:`cloud_reader_options`) by the same
module, so an option and the place it is read sit together.
"""

from __future__ import annotations

import argparse
from typing import Any

from gpomap.cli.options import number, positive, signature_default
from gpomap.errors import GpomapError

__all__ = [
    "scan_range",
    "add_reader_options",
    "reader_options",
    "add_cloud_reader_options",
    "cloud_reader_options",
    "check_2d_options",
    "add_selection_options",
]


def scan_range(text: str) -> tuple[int | None, int | None]:
    """``FIRST:LAST``: slice bounds of scan indices, either left out for an open end."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        return tuple(int(p) if p else None for p in parts)  # type: ignore[return-value]
    except ValueError:
        raise argparse.ArgumentTypeError(f"range must be FIRST:LAST (scan indices, LAST excluded), got {text!r}") from None


def add_reader_options(p: argparse.ArgumentParser) -> None:
    """The options of the planar readers (CARMEN logs, ROS bags)."""
    g = p.add_argument_group("reading the input")
    g.add_argument(
        "--angles",
        choices=["gmapping", "linspace"],
        default=signature_default("gpomap.io.carmen", "read_carmen", "angles"),
        help="CARMEN FLASER beam-angle convention (default: %(default)s)",
    )
    g.add_argument("--max-range", type=positive(float), help="sensor max range in metres (readings at or above it are no-return)")
    g.add_argument("--topic", help="ROS bag: sensor_msgs/LaserScan topic (default: the only one)")
    g.add_argument("--fixed-frame", help="ROS bag: fixed frame of the poses, from /tf (default: odom)")
    g.add_argument("--odom-topic", help="ROS bag: take poses from this nav_msgs/Odometry topic instead of /tf")
    g.add_argument(
        "--time-offset",
        type=number(float),
        default=signature_default("gpomap.io.rosbag", "read_rosbag", "time_offset"),
        help="ROS bag: seconds added to scan stamps before the pose lookup (default: %(default)s)",
    )


def reader_options(args: argparse.Namespace, path: str) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.io.read_scans` for the planar input `path`."""
    from gpomap.io import detect_format

    fmt = detect_format(path)
    if fmt == "carmen":
        opts: dict[str, Any] = {"angles": args.angles}
    else:
        opts = {
            "topic": args.topic,
            "fixed_frame": args.fixed_frame,
            "odom_topic": args.odom_topic,
            "time_offset": args.time_offset,
        }
    if args.max_range is not None:
        opts["max_range"] = args.max_range
    return opts


def add_cloud_reader_options(p: argparse.ArgumentParser) -> None:
    """The reading options of 3-D inputs (``map``, ``info`` and ``update`` take them alike)."""
    g = p.add_argument_group("reading 3-D inputs")
    g.add_argument(
        "--poses",
        metavar="FILE",
        help="PCD / PLY: one sensor-to-map pose per file, in the files' order (required for PLY; replaces PCD VIEWPOINTs)",
    )
    g.add_argument(
        "--points-frame",
        choices=["map", "sensor"],
        help="PCD with a VIEWPOINT: the points are already in the map frame, or in the sensor's (default: map)",
    )
    g.add_argument(
        "--stride", type=positive(int), metavar="K", help="depth frames: every K-th pixel along both image axes (default: 1)"
    )
    g.add_argument(
        "--depth-scale",
        type=positive(float),
        metavar="UNITS",
        help="depth frames: depth units per metre (default: 1000, millimetres; TUM: 5000)",
    )


def cloud_reader_options(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.io.read_clouds` for ``args.input``.

    Raises
    ------
    GpomapError
        A 3-D reading option the input's format does not take, or ``--odom-topic`` on a bag.
    """
    from gpomap.io import detect_format

    fmt = detect_format(args.input)
    opts: dict[str, Any] = {"poses": args.poses, "max_range": args.max_range}
    set_here = {k: getattr(args, k) for k in ("points_frame", "stride", "depth_scale") if getattr(args, k) is not None}
    takes = {"pcd": ("points_frame",), "pcd-directory": ("points_frame",), "depth-directory": ("stride", "depth_scale")}
    wrong = [k for k in set_here if k not in takes.get(fmt, ())]
    if wrong:
        names = ", ".join("--" + k.replace("_", "-") for k in wrong)
        raise GpomapError(f"{names}: not an option of {fmt} input ({args.input})")
    opts.update(set_here)
    if fmt in ("rosbag1", "rosbag2"):
        opts.update(topic=args.topic, fixed_frame=args.fixed_frame, time_offset=args.time_offset)
        if args.odom_topic is not None:
            raise GpomapError(f"--odom-topic is for LaserScan bags; {args.input} holds PointCloud2: give the poses on /tf")
    return opts


def check_2d_options(args: argparse.Namespace) -> None:
    """Refuse the 3-D reading and output options on a 2-D input (they would be ignored silently)."""
    for name in ("poses", "points_frame", "stride", "depth_scale", "z_range", "slices"):
        if getattr(args, name, None) is not None:
            option = "--" + name.replace("_", "-")
            raise GpomapError(f"{option} is for 3-D inputs (point clouds, depth frames); {args.input} holds 2-D data")


def add_selection_options(p: argparse.ArgumentParser) -> None:
    """``--range``, ``--scans`` and ``--beams``: which scans and beams of the input are used."""
    g = p.add_argument_group("selecting data")
    g.add_argument(
        "--range",
        dest="scan_range",
        type=scan_range,
        metavar="FIRST:LAST",
        help="use only this window of consecutive scans (LAST excluded)",
    )
    g.add_argument("--scans", type=positive(int), metavar="N", help="thin to N evenly spaced scans")
    g.add_argument("--beams", type=positive(int), metavar="M", help="keep M evenly spaced beams per scan")
