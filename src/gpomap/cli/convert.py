"""``gpomap convert INPUT -o OUTDIR``: an occupancy grid or an OctoMap tree turned into a continuous GP map.

A ROS map_server map or a gpomap ``.npz`` becomes one GP over its cells (:mod:`gpomap.convert`),
written as ``gpomap map`` writes a planar map; an OctoMap ``.bt`` / ``.ot`` becomes a voxel map
(:mod:`gpomap.convert.octree`), one GP or, when its cells are more than ``--max-cells``, tiles of at
most that many, written as ``gpomap map`` writes a 3-D map. The output grid and the GP are
checked against the memory limit before the fit.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.cli.common import (
    EXIT_OK,
    Run,
    check_before_work,
    check_fit_memory,
    check_grid_memory,
    check_voxel_memory,
    report_fit,
    status,
    warn,
)
from gpomap.cli.input_options import check_2d_options
from gpomap.cli.map import write_grid
from gpomap.cli.options import Default, positive
from gpomap.cli.output_options import add_3d_output_options, add_output_options
from gpomap.config import DEFAULT_MAX_CELLS
from gpomap.errors import GpomapError

__all__ = ["add_parser", "run", "convert_options"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap convert`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "convert",
        help="turn an occupancy grid into a continuous GP map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Read a ROS map_server map (or a gpomap .npz), merge its known pixels into cells, fit "
        "the GP and write the continuous map at any resolution.",
        epilog="examples:\n  gpomap convert ../shared/data/turtlebot3-world-map/map.yaml -o tb3 --resolution 0.025\n"
        "  gpomap convert ../shared/data/octomap/geb079.bt -o geb --resolution 0.04 --extent 5,6,-1.5,1.5",
    )
    p.add_argument("input", help="map.yaml (ROS map_server), map.npz, or an OctoMap tree (.bt, .ot)")
    p.add_argument("--kernel", choices=["se", "matern32"], help="point kernel (default: se, measured best for grids)")
    p.add_argument(
        "--values",
        choices=["auto", "fraction", "ternary"],
        default="auto",
        help="grids: a pixel's value is the fraction of it that is occupied, or free / occupied / unknown by the "
        "thresholds (auto: ternary for trinary ROS maps and gpomap's own maps, else fraction; docs/convert.md)",
    )
    p.add_argument(
        "--pooling",
        choices=["auto", "any", "majority", "mean"],
        default="auto",
        help="grids: how the grid was made from a finer one. any: a pixel is occupied if any of its fine pixels "
        "is (as occupancy grids mark the cell a beam ended in), so a 0 is wholly free and a 1 holds anything from "
        "a sliver to all of it; majority: occupied if more than half is, so a 1 holds more than half and a 0 at "
        "most half (thin walls vanish from such grids); mean: each value is the occupied share of the pixel. "
        "auto (default): values between 0 and 1 are read as mean, a grid of 0s and 1s as any unless its walls "
        "are broken as majority pooling breaks them; a grid read by its thresholds as any (docs/convert.md)",
    )
    p.add_argument(
        "--occupied-fraction",
        type=positive(float),
        metavar="F",
        help="grids of 0s and 1s pooled by any or majority: the share of an occupied pixel taken as occupied, in "
        "(0, 1]; it sets the pixel's GP target and where its obstacle's point sits, not the bounds the pooling "
        "holds the map to (default: 0.7, which suits every pooling: 1.0 on majority-pooled grids beat "
        "interpolation in fewer of the measured cases, docs/convert.md). A mean-pooled grid's values are its shares",
    )
    p.add_argument(
        "--pooling-factor",
        type=positive(int),
        metavar="K",
        help="grids pooled by any: the side of one of the grid's pixels in pixels of the finer grid it was made "
        "from. Told it, a 1 beside unknown space is read as the front of a wall no sensor saw behind, its share "
        "from the walls' thickness the grid shows (docs/convert.md). Default: the grid's pixel over --resolution "
        "when that is a whole number of 2 or more (the map made continuous at the finer grid's pixel), else none",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_output_options(p, None)
    # The options of octrees only.
    add_3d_output_options(p).add_argument(
        "--max-cells",
        type=positive(int),
        default=Default(DEFAULT_MAX_CELLS),
        help="octree: most cells of one GP; a larger region is converted in tiles of at most this many (default: %(default)s)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap convert``."""
    from gpomap.convert import convert_grid, converter_for, grid_to_observations, load_grid, output_grid
    from gpomap.diagnostics import model_warnings

    check_before_work(args)
    if _is_octree_input(args.input):
        return _convert_octree(args)
    check_2d_options(args)
    if "max_cells" not in args.library_defaults:
        raise GpomapError(f"--max-cells is for OctoMap trees; {args.input} is converted as one GP over its cells")
    status(args, f"converting {args.input}...")
    options = convert_options(args)
    # Read once, check the memory the output grid and the GP need, then convert what was read.
    source = load_grid(args.input)
    spec = output_grid(source.grid, args.resolution, args.extent)
    if args.resolution is None:
        args.resolution = spec.resolution  # the source's pixel size (named in the messages)
    factor = output_factor(source.grid.resolution, spec.resolution)
    if "pooling_factor" not in options and factor is not None:
        options["pooling_factor"] = factor
    check_grid_memory(args, spec.shape, spec.extent, 0)
    # The converter's own inputs (wall-aware, several per wall pixel), not a plain cell tree's.
    n_cells = len(converter_for(source.grid.resolution, **options).make_cells(grid_to_observations(source, args.values)))
    check_fit_memory(args, n_cells, 1, f"one GP over the cells of {args.input}")
    check_grid_memory(args, spec.shape, spec.extent, n_cells)
    result = convert_grid(source, resolution=args.resolution, extent=args.extent, values=args.values, **options)
    # gpomap map's writing path; the converter hands back its grid made whole beside its model.
    files, warnings = write_grid(args, lambda: result.map, f"gpomap convert: {Path(args.input).name}")
    for message in model_warnings(result.model) + warnings:
        warn(message)
    r = result.report
    print(json.dumps(r, indent=2, default=str) if args.json else _convert_text(r))
    for f in files:
        print(f"wrote        {f}")
    return EXIT_OK


def output_factor(pixel: float, resolution: float) -> int | None:
    """How many output cells a side of a grid's pixel spans, when a whole number of 2 or more
    (within a millionth), else None: the pooling factor ``gpomap convert`` assumes untold."""
    ratio = pixel / resolution
    k = round(ratio)
    return k if k >= 2 and abs(ratio - k) <= 1e-6 * ratio else None


def convert_options(args: argparse.Namespace) -> dict[str, Any]:
    """The model options of ``gpomap convert`` (the rest are the converter's own, see gpomap.convert.model_defaults)."""
    options: dict[str, Any] = {"thresholds": args.thresholds}
    if args.pooling != "auto":
        options["pooling"] = args.pooling
    if args.pooling_factor is not None:
        options["pooling_factor"] = args.pooling_factor
    if args.kernel:
        options["kernel"] = args.kernel
    if args.occupied_fraction is not None:
        if args.occupied_fraction > 1:
            raise GpomapError(f"--occupied-fraction must be in (0, 1], got {args.occupied_fraction:g}")
        options["occupied_fraction"] = args.occupied_fraction
    return options


def _convert_text(report: dict[str, Any]) -> str:
    """The report of a grid's conversion (:attr:`gpomap.convert.ConversionResult.report`) as text."""
    px, cells, agree = report["pixels"], report["cells"], report["agreement"]
    hp = report["hyperparameters"]
    return "\n".join(
        [
            f"pixels       {px.get('free')} free, {px.get('occupied')} occupied, {px.get('unknown')} unknown",
            f"cells        {cells.get('n')}",
            f"pooling      {report.get('pooling')}"
            + (f", a pixel {report['pooling_factor']} finer pixels a side" if report.get("pooling_factor") else ""),
            "hyperparams  " + ", ".join(f"{k} {v:.4g}" for k, v in hp.items()),
            f"agreement    {100 * agree['ternary']:.2f} % of known pixels keep their label (AUC {agree['auc']:.4f})",
            "timings (s)  " + ", ".join(f"{k} {v:.2f}" for k, v in report["timings"].items() if isinstance(v, float)),
        ]
    )


# --------------------------------------------------------------------------- OctoMap trees
def _is_octree_input(path: str) -> bool:
    """Whether `path` names an OctoMap file (by its suffix; the reader checks the content)."""
    return Path(path).suffix.lower() in (".bt", ".ot")


def _corners(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    """The region's corners, shape (3,) each, from ``--extent`` and ``--z-range`` (NaN: the tree's bound)."""
    lo, hi = np.full(3, np.nan), np.full(3, np.nan)
    if args.extent is not None:
        lo[:2], hi[:2] = (args.extent[0], args.extent[2]), (args.extent[1], args.extent[3])
    if args.z_range is not None:
        lo[2], hi[2] = args.z_range
    return lo, hi


def _convert_octree(args: argparse.Namespace) -> int:
    """Run ``gpomap convert`` on an OctoMap file (the output directory is checked already).

    The region converted is the tree's extent, or ``--extent`` (x, y) and ``--z-range`` (z); the
    voxel grid and then the largest GP are checked against the memory limit before the fit, and
    the agreement with the octree's known voxels is printed.
    """
    from gpomap.convert import convert_octree, region
    from gpomap.io.octomap import read_octree
    from gpomap.io.voxel_outputs import write_voxel_outputs

    for name in ("values", "pooling", "occupied_fraction", "pooling_factor"):
        if getattr(args, name, None) not in (None, "auto"):
            raise GpomapError(f"--{name.replace('_', '-')} is for grids; {args.input} is an OctoMap tree")
    status(args, f"reading the octree {args.input}...")
    tree = read_octree(args.input)
    lo, hi = region(tree, *_corners(args))
    if args.resolution is None:
        args.resolution = tree.resolution  # the tree's voxel (named in the messages)
    check_voxel_memory(args, lo, hi, 0)
    status(args, f"  {tree.n_leaves} leaves of {tree.resolution:g} m; converting at {args.resolution:g} m...")

    def before_fit(n_cells: int) -> None:
        check_fit_memory(args, n_cells, 1, f"one GP over the cells of {args.input}")
        check_voxel_memory(args, lo, hi, n_cells)
        status(args, f"  at most {n_cells} cells in one GP; fitting...")

    options = convert_options(args)
    result = convert_octree(tree, args.resolution, lo, hi, max_cells=args.max_cells, before_fit=before_fit, **options)
    Run.outdir = args.output
    files = write_voxel_outputs(result.map, args.output, heights=args.slices, title=f"gpomap convert: {Path(args.input).name}")
    report_fit(result.model, result.map)
    r = result.report
    print(json.dumps(r, indent=2, default=str) if args.json else _octree_text(r))
    print("\n".join(f"wrote        {f}" for f in files))
    return EXIT_OK


def _octree_text(report: dict[str, Any]) -> str:
    """The report of an octree's conversion (:func:`gpomap.convert.convert_octree`) as text."""
    lv, vx, cells, agree = report["leaves"], report["voxels"], report["cells"], report["agreement"]
    lo, hi = report["region"]["lower"], report["region"]["upper"]
    nz, ny, nx = report["grid"]["shape"]
    lines = [
        f"octree       {lv['n']} leaves ({lv['occupied']} occupied, {lv['free']} free) of {vx['resolution']:g} m",
        f"region       x {lo[0]:.4g}..{hi[0]:.4g}, y {lo[1]:.4g}..{hi[1]:.4g}, z {lo[2]:.4g}..{hi[2]:.4g} m; "
        f"trained on {vx['occupied']} occupied and {vx['free']} free voxels in it and around it",
        f"cells        {cells['n']} ({cells['occupied']} occupied, {cells['ambiguous']} from ambiguous min-size cells)",
        "hyperparams  " + ", ".join(f"{k} {v:.4g}" for k, v in report["hyperparameters"].items()),
    ]
    if "ternary" in agree:
        lines.append(
            f"agreement    {100 * agree['ternary']:.2f} % of {agree['n_checked']} known voxels keep their label "
            f"(free {100 * agree['free']:.2f} %, occupied {100 * agree['occupied']:.2f} %; AUC {agree['auc']:.4f})"
            + (f", a sample of {agree['n_known']}" if agree["n_checked"] < agree["n_known"] else "")
        )
    tiles = report.get("tiles")
    if tiles:
        lines.append(
            f"tiles        {tiles['tiles_fitted']} columns of {tiles['tile_size']:g} m fitted one after another "
            f"(at most {tiles['largest_tile_cells']} cells each; {tiles['tiles']} blended)"
        )
    lines.append(f"voxels       {nx} x {ny} x {nz} of {report['grid']['resolution']:g} m")
    lines.append("timings (s)  " + ", ".join(f"{k} {v:.2f}" for k, v in report["timings"].items()))
    return "\n".join(lines)
