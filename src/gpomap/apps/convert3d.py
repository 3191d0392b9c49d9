"""``gpomap convert MAP.bt -o OUTDIR``: an OctoMap octree to a continuous 3-D map (:mod:`gpomap.convert3d`).

:mod:`gpomap.cli` hands a ``convert`` run here when the input is an OctoMap ``.bt`` / ``.ot``
file. The region converted is the tree's extent, or ``--extent`` (x, y) and ``--z-range`` (z), one GP
or, when its cells are more than ``--max-cells``, tiles of at most that many
(:class:`gpomap.convert3d.TiledOctreeModel`); the voxel grid and then the largest GP are checked
against the memory limit before the fit; the map is
written as the 3-D output set of ``gpomap map`` (:func:`gpomap.io.voxel_outputs.write_voxel_outputs`)
and the agreement with the octree's known voxels is printed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["is_octree_input", "cmd_convert3d"]


def is_octree_input(path: str) -> bool:
    """Whether `path` names an OctoMap file (by its suffix; the reader checks the content)."""
    return Path(path).suffix.lower() in (".bt", ".ot")


def _corners(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    """The region's corners from ``--extent`` and ``--z-range`` (NaN: the tree's bound)."""
    lo, hi = np.full(3, np.nan), np.full(3, np.nan)
    if args.extent is not None:
        lo[:2], hi[:2] = (args.extent[0], args.extent[2]), (args.extent[1], args.extent[3])
    if args.z_range is not None:
        lo[2], hi[2] = args.z_range
    return lo, hi


def cmd_convert3d(args: argparse.Namespace) -> int:
    """Run ``gpomap convert`` on an OctoMap file (the output directory is checked already)."""
    from gpomap import cli
    from gpomap.cli.common import check_voxel_memory
    from gpomap.convert3d import convert_octree, region
    from gpomap.errors import GpomapError
    from gpomap.io.octomap import read_octree
    from gpomap.io.voxel_outputs import write_voxel_outputs

    for name in ("values", "occupied_fraction"):
        if getattr(args, name, None) not in (None, "auto"):
            raise GpomapError(f"--{name.replace('_', '-')} is for grids; {args.input} is an OctoMap tree")
    cli._status(args, f"reading the octree {args.input}...")
    tree = read_octree(args.input)
    lo, hi = region(tree, *_corners(args))
    if args.resolution is None:
        args.resolution = tree.resolution  # the tree's voxel (named in the messages)
    check_voxel_memory(args, lo, hi, 0)
    cli._status(args, f"  {tree.n_leaves} leaves of {tree.resolution:g} m; converting at {args.resolution:g} m...")

    def before_fit(n_cells: int) -> None:
        cli._check_fit_memory(args, n_cells, 1, f"one GP over the cells of {args.input}")
        check_voxel_memory(args, lo, hi, n_cells)
        cli._status(args, f"  at most {n_cells} cells in one GP; fitting...")

    options = cli._convert_options(args)
    result = convert_octree(tree, args.resolution, lo, hi, max_cells=args.max_cells, before_fit=before_fit, **options)
    cli._Run.outdir = args.output
    files = write_voxel_outputs(result.map, args.output, heights=args.slices, title=f"gpomap convert: {Path(args.input).name}")
    cli._report_fit(result.model, result.map)
    r = result.report
    print(json.dumps(r, indent=2, default=str) if args.json else _text(r))
    print("\n".join(f"wrote        {f}" for f in files))
    return cli.EXIT_OK


def _text(report: dict[str, Any]) -> str:
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
