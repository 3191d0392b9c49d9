"""The options of the written map: its directory, cells, region, thresholds, image and memory limit, and its heights in 3-D."""

from __future__ import annotations

import argparse
import math
from typing import Any

from gpomap.cli.options import Default, positive
from gpomap.config import CALIBRATED_THRESHOLDS, MapConfig

__all__ = ["extent", "pair", "heights", "z_range", "add_output_options", "add_3d_output_options", "resolution_from_evidence"]


def extent(text: str) -> tuple[float, float, float, float]:
    """``XMIN,XMAX,YMIN,YMAX``: four finite numbers, each minimum below its maximum."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"extent must be XMIN,XMAX,YMIN,YMAX in metres, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"extent must be four finite numbers XMIN,XMAX,YMIN,YMAX, got {text!r}")
    if len(values) != 4 or not (values[0] < values[1] and values[2] < values[3]):
        raise argparse.ArgumentTypeError(f"extent must be XMIN,XMAX,YMIN,YMAX with XMIN<XMAX and YMIN<YMAX, got {text!r}")
    return values[0], values[1], values[2], values[3]


def pair(text: str) -> tuple[float, float]:
    """``FREE,OCCUPIED``: two thresholds with 0 <= FREE <= OCCUPIED <= 1."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers FREE,OCCUPIED, got {text!r}") from None
    # Written out so that nan (for which every comparison is false) is refused too.
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi <= 1):
        raise argparse.ArgumentTypeError(f"thresholds must satisfy 0 <= FREE <= OCCUPIED <= 1, got {text!r}")
    return lo, hi


def heights(text: str) -> tuple[float, ...]:
    """``--slices z1,z2,...``: finite heights in metres."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"slices must be heights Z1,Z2,... in metres, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"slices must be finite heights Z1,Z2,... in metres, got {text!r}")
    return values


def z_range(text: str) -> tuple[float, float]:
    """``--z-range ZMIN,ZMAX`` with ZMIN < ZMAX, finite."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"z range must be ZMIN,ZMAX in metres, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise argparse.ArgumentTypeError(f"z range must be two finite numbers ZMIN,ZMAX with ZMIN < ZMAX, got {text!r}")
    return lo, hi


def add_output_options(p: argparse.ArgumentParser, default_resolution: Any) -> None:
    """The written map's options: the directory, its cells and region, thresholds, image and memory limit."""
    g = p.add_argument_group("the output")
    g.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="directory for map.yaml, map.pgm, map.npz, map.png")
    g.add_argument(
        "--resolution",
        type=positive(float),
        default=default_resolution,
        help="grid cell side of the written map, m" + (" (default: %(default)s)" if default_resolution else ""),
    )
    g.add_argument("--extent", type=extent, metavar="XMIN,XMAX,YMIN,YMAX", help="region of the written map (default: the data's)")
    g.add_argument(
        "--thresholds",
        type=pair,
        default=Default(MapConfig.thresholds, show=lambda _: f"{CALIBRATED_THRESHOLDS[0]:g},{CALIBRATED_THRESHOLDS[1]:g}"),
        metavar="FREE,OCCUPIED",
        help="ternary-map thresholds on the map's calibrated probabilities (default: %(default)s: occupied where "
        "more likely than not, free below map_server's free threshold)",
    )
    g.add_argument(
        "--pgm-mode",
        choices=["trinary", "scale"],
        default="trinary",
        help="map_server image: ternary map or probability grey levels (default: %(default)s)",
    )
    g.add_argument(
        "--memory-limit",
        type=positive(float),
        metavar="GB",
        help="refuse, before fitting, a run estimated to need more memory than this (default: half of this machine's)",
    )


def add_3d_output_options(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """``--z-range`` and ``--slices``: the 3-D output options of ``map``, ``convert``, ``render`` and ``update``; returns their group."""
    g = p.add_argument_group("3-D maps (point clouds, depth frames, OctoMap trees)")
    g.add_argument(
        "--z-range",
        type=z_range,
        metavar="ZMIN,ZMAX",
        help="heights of the written voxel map, m (with --extent for x and y; default: the data's)",
    )
    g.add_argument(
        "--slices",
        type=heights,
        metavar="Z1,Z2,...",
        help="heights of the horizontal slices in map-slices.png, m (default: four spread over the map)",
    )
    return g


def resolution_from_evidence(args: argparse.Namespace) -> None:
    """A 2-D written map's cell, when not given: the ray counts' (``--evidence-resolution``, given or not)."""
    if "resolution" in getattr(args, "library_defaults", ()):
        args.resolution = args.evidence_resolution
