"""``gpomap query MAPFILE POINTS``: the saved map's probability and variance at given points.

POINTS is a CSV file of ``x,y`` (``x,y,z`` for a 3-D map) per line, a header line optional, or an
NPZ holding one array of shape (m, 2) or (m, 3) (named ``points`` when it holds several). The answer,
per point, is the loaded map's ``predict_proba(points, return_var=True)``: the occupancy probability
and the GP's latent variance, the live model's to the bit. A point far from the data gets what the
map says there, the prior: probability 1/2 (the squash's offset, 0 for the maps of the shared logs,
through the unseen-space variance scale) and the kernel's variance. It is printed as CSV
(``x,y[,z],probability,variance``, each number the shortest decimal that reads back to it exactly), or written with ``-o`` to a
CSV or an NPZ (``points``, ``probability``, ``variance``), atomically.

:func:`read_query_points` reads POINTS; :func:`add_parser` and :func:`cmd_query` are the subcommand.
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError, InputFormatError

__all__ = ["read_query_points", "add_parser", "cmd_query"]

EPILOG = """examples:
  gpomap query arena/map.gpom points.csv
  gpomap query arena/map.gpom points.npz -o answers.npz
"""

_AXES = "xyz"


def _columns(dim: int) -> str:
    return ",".join(_AXES[:dim])


def read_query_points(path: str, dim: int, mapfile: str = "the map") -> NDArray[np.float64]:
    """The points of a CSV (``x,y[,z]``, a header line optional) or NPZ file, shape (m, `dim`).

    Raises
    ------
    InputFormatError
        One line naming the file (and line): not numbers, rows of unequal length, non-finite
        values, no point, or not `dim` columns (the map's dimension).
    """
    from gpomap.io.checks import load_npz, regular_file

    p = regular_file(path, f"points file (CSV of {_columns(dim)}, or NPZ)")
    if p.suffix.lower() == ".npz":
        arrays = load_npz(p, "NumPy .npz of points")
        if "points" in arrays:
            points = arrays["points"]
        elif len(arrays) == 1:
            points = next(iter(arrays.values()))
        else:
            raise InputFormatError(f"holds {sorted(arrays)}; expected one array, or one named 'points'", path=path)
        if not (np.issubdtype(points.dtype, np.floating) or np.issubdtype(points.dtype, np.integer)):
            raise InputFormatError(f"points have dtype {points.dtype}; expected real numbers", path=path)
        points = np.asarray(points, dtype=float)
        if points.ndim != 2:
            raise InputFormatError(f"points have shape {points.shape}; expected (m, {dim}): {_columns(dim)} per row", path=path)
    else:
        points = _read_csv(p, path)
    if points.shape[1] != dim:
        raise InputFormatError(
            f"points have {points.shape[1]} coordinates per row; {mapfile} is a {dim}-D map: expected {_columns(dim)}", path=path
        )
    if points.shape[0] == 0:
        raise InputFormatError(f"holds no points; expected {_columns(dim)} per row", path=path)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputFormatError(f"point {int(np.argmax(bad))} is not finite: {points[int(np.argmax(bad))].tolist()}", path=path)
    return points


def _read_csv(p: Path, path: str) -> NDArray[np.float64]:
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputFormatError("not a text file; expected a CSV of coordinates or an .npz", path=path) from None
    rows: list[list[float]] = []
    width = None
    header = False
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not rows and not header:  # the header line
                header = True
                continue
            raise InputFormatError(
                f"expected numbers separated by commas, got {stripped[:80]!r}", path=path, line=number
            ) from None
        if width is not None and len(values) != width:
            raise InputFormatError(f"{len(values)} values; the rows above have {width}", path=path, line=number)
        width = len(values)
        rows.append(values)
    return np.array(rows, dtype=float).reshape(-1, width or 0)


def _csv(points: NDArray[np.float64], probability: NDArray[np.float64], variance: NDArray[np.float64]) -> str:
    dim = points.shape[1]
    out = io.StringIO()
    out.write(f"{_columns(dim)},probability,variance\n")
    # Each number as its shortest decimal that reads back to the same float.
    for row in np.column_stack([points, probability, variance]).tolist():
        out.write(",".join(map(repr, row)) + "\n")
    return out.getvalue()


def _output_kind(text: str) -> Path:
    p = Path(text)
    if p.suffix.lower() not in (".csv", ".npz"):
        raise argparse.ArgumentTypeError(f"the answers file must end in .csv or .npz, got {text!r}")
    return p


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap query`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    from gpomap import cli

    p: argparse.ArgumentParser = sub.add_parser(
        "query",
        help="probability and variance of a saved map (map.gpom) at given points",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Load a fitted map written by gpomap map (map.gpom) and print, for each point of POINTS (a CSV of "
        "x,y or x,y,z per line, a header optional, or an NPZ of one (m, d) array), its occupancy probability and "
        "latent variance, or write them with -o.",
    )
    p.add_argument("mapfile", metavar="MAPFILE", help="a fitted map file (map.gpom, written by gpomap map)")
    p.add_argument("points", metavar="POINTS", help="CSV (x,y[,z] per line) or NPZ of points")
    p.add_argument(
        "-o",
        "--output",
        dest="answers",
        type=_output_kind,
        metavar="OUT.csv|OUT.npz",
        help="write the answers here (CSV: x,y[,z],probability,variance; NPZ: points, probability, variance) instead of printing them",
    )
    p.add_argument("--workers", type=cli._positive(int), help="local workers for the tiles (default: the map's own)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_query)
    return p


def cmd_query(args: argparse.Namespace) -> int:
    """Run ``gpomap query``."""
    from gpomap import cli
    from gpomap.apps.render import load_for_command, map_header
    from gpomap.io.atomic import atomic_write

    summary = map_header(args.mapfile)["summary"]
    points = read_query_points(args.points, int(summary["dim"]), args.mapfile)
    if args.answers is not None and args.answers.is_dir():
        raise GpomapError(f"-o {args.answers}: is a directory; expected a .csv or .npz file to write")
    model = load_for_command(args, args.mapfile)
    probability, variance = model.predict_proba(points, return_var=True)
    if args.answers is None:
        sys.stdout.write(_csv(points, probability, variance))
        return cli.EXIT_OK
    if args.answers.suffix.lower() == ".npz":
        with atomic_write(args.answers, "wb") as f:
            np.savez(f, points=points, probability=probability, variance=variance)
    else:
        with atomic_write(args.answers, "w") as f:
            f.write(_csv(points, probability, variance))
    cli._status(args, f"wrote {args.answers}: {points.shape[0]} points")
    return cli.EXIT_OK
