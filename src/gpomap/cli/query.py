"""``gpomap query MAPFILE POINTS...``: the saved map's probability and variance at given points.

The points, files or written out, are read by :func:`gpomap.apps.query.query_points`; the answers are the loaded
map's ``predict_proba(points, return_var=True)`` and ``predict_ternary(points)``, printed as CSV or
written with ``-o`` to a CSV or an NPZ, atomically.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.apps.query import answers_csv, query_points
from gpomap.apps.render import map_header
from gpomap.cli.common import EXIT_OK, status
from gpomap.cli.options import positive
from gpomap.cli.render import load_for_command
from gpomap.errors import GpomapError

__all__ = ["add_parser", "run"]

EPILOG = """examples:
  gpomap query arena/map.gpom points.csv
  gpomap query arena/map.gpom points.npz -o answers.npz
  gpomap query arena/map.gpom 1.5,2 0.2,2.5
  gpomap query arena/map.gpom -- -1.5,2      (after --, a point whose x is negative)
"""


def _output_kind(text: str) -> Path:
    """``-o``: the answers file, a .csv or an .npz."""
    p = Path(text)
    if p.suffix.lower() not in (".csv", ".npz"):
        raise argparse.ArgumentTypeError(f"the answers file must end in .csv or .npz, got {text!r}")
    return p


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap query`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "query",
        help="probability and variance of a saved map (map.gpom) at given points",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Load a fitted map written by gpomap map (map.gpom) and print, for each point of POINTS (a CSV of "
        "x,y or x,y,z per line, a header optional, an NPZ of one (m, d) array, or points written out as x,y[,z]), its "
        "occupancy probability, latent variance and ternary label (0 free, -1 unknown, 1 occupied, as the written map "
        "calls it), or write them with -o.",
    )
    p.add_argument("mapfile", metavar="MAPFILE", help="a fitted map file (map.gpom, written by gpomap map)")
    p.add_argument(
        "points", metavar="POINTS", nargs="+", help="CSV (x,y[,z] per line) or NPZ of points, or a point x,y[,z]; one or more"
    )
    p.add_argument(
        "-o",
        "--output",
        dest="answers",
        type=_output_kind,
        metavar="OUT.csv|OUT.npz",
        help="write the answers here (CSV: x,y[,z],probability,variance,ternary; NPZ: points, probability, variance, "
        "ternary) instead of printing them",
    )
    p.add_argument("--workers", type=positive(int), help="local workers for the tiles (default: the map's own)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap query``."""
    from gpomap.io.atomic import atomic_write

    summary = map_header(args.mapfile)["summary"]
    points = query_points(args.points, int(summary["dim"]), args.mapfile)
    if args.answers is not None and args.answers.is_dir():
        raise GpomapError(f"-o {args.answers}: is a directory; expected a .csv or .npz file to write")
    model = load_for_command(args, args.mapfile)
    probability, variance = model.predict_proba(points, return_var=True)
    ternary = model.predict_ternary(points, probability)
    if args.answers is None:
        sys.stdout.write(answers_csv(points, probability, variance, ternary))
        return EXIT_OK
    if args.answers.suffix.lower() == ".npz":
        with atomic_write(args.answers, "wb") as f:
            np.savez(f, points=points, probability=probability, variance=variance, ternary=ternary)
    else:
        with atomic_write(args.answers, "w") as f:
            f.write(answers_csv(points, probability, variance, ternary))
    status(args, f"wrote {args.answers}: {points.shape[0]} points")
    return EXIT_OK
