"""``gpomap render MAPFILE -o OUTDIR --resolution R``: a saved map written again, at any resolution, without refitting.

The map file (``map.gpom``, written by ``gpomap map``; :mod:`gpomap.io.mapfile`) holds the fitted
model; its grid at `--resolution` over `--extent` (default: the data's, as ``gpomap map`` takes it)
is written as ``gpomap map`` writes its own: ``map.yaml`` / ``map.pgm`` / ``map.npz`` / ``map.png``
for a 2-D map, the voxel outputs (``map.npz``, ``map.bt``, ``map.ply``, ``map-slices.png``,
``map-3d.png``) for a 3-D one, as one output set (:func:`gpomap.io.atomic.output_set`). The grid is
the loaded model's ``grid(resolution, extent)``: the live model's cells to the bit. Its memory is
checked against ``--memory-limit`` from the file's header alone, before the map is loaded.

:func:`add_parser` and :func:`cmd_render` are the subcommand (registered in :mod:`gpomap.cli`);
:func:`load_for_command`, :func:`map_header` and :func:`check_map_memory` serve ``query`` and
``update`` too.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import GpomapError

__all__ = ["add_parser", "cmd_render", "map_header", "load_for_command", "check_map_memory", "write_outputs", "configure"]

EPILOG = """examples:
  gpomap render arena/map.gpom -o arena-1cm --resolution 0.01
  gpomap render arena/map.gpom -o door --resolution 0.005 --extent 0.5,1.5,-0.5,0.5
"""


def map_header(path: str) -> dict[str, Any]:
    """The header of the map file `path` (:func:`gpomap.io.mapfile.read_map_header`), refusing a
    streaming state still in its warm-up (it holds no map)."""
    from gpomap.io.mapfile import read_map_header

    header = read_map_header(path)
    summary = header["summary"]
    if header["kind"] == "stream" and not summary.get("ready", False):
        warm = summary.get("warmup", ["?", "?"])
        raise GpomapError(f"{path}: a streaming state still warming up ({warm[0]} of {warm[1]} scans): it holds no map yet")
    return header


def load_for_command(args: argparse.Namespace, path: str) -> Any:
    """The fitted map of `path`, with ``--workers`` and ``--thresholds`` when given (:func:`configure`), said on stderr."""
    from gpomap import cli
    from gpomap.io.mapfile import load_fitted_map

    cli._status(args, f"loading the map from {path}...")
    t = time.perf_counter()
    model = load_fitted_map(path)
    configure(args, model)
    cli._status(
        args, f"  {len(model.tiles_)} tiles, {model.n_inputs_} cells, {model._n_scans} scans in {time.perf_counter() - t:.2f} s"
    )
    return model


def _padded_bounds(summary: dict[str, Any], resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """The default written extent's corners: the data's box grown as ``TiledGPOM.grid`` grows it."""
    from gpomap.lattice import EXTENT_MARGIN_CELLS

    lo, hi = (np.asarray(b, dtype=float) for b in summary["bounds"])
    pad = EXTENT_MARGIN_CELLS * resolution
    return lo - pad, hi + pad


def written_extent(args: argparse.Namespace, summary: dict[str, Any]) -> tuple[float, ...] | None:
    """The extent to pass to ``grid``: None for the map's default, else ``--extent`` (2-D), or the
    data's box grown as the default grows it, with x, y from ``--extent`` and z from ``--z-range``
    (3-D)."""
    if summary["dim"] == 2:
        return None if args.extent is None else tuple(args.extent)
    if args.extent is None and args.z_range is None:
        return None
    lo, hi = _padded_bounds(summary, args.resolution)
    if args.extent is not None:
        lo[:2], hi[:2] = (args.extent[0], args.extent[2]), (args.extent[1], args.extent[3])
    if args.z_range is not None:
        lo[2], hi[2] = args.z_range
    from gpomap.lattice import bounds_extent

    return tuple(float(v) for v in bounds_extent(lo, hi))


def check_map_memory(args: argparse.Namespace, summary: dict[str, Any]) -> None:
    """Refuse, from the header alone, a written grid that needs more than ``--memory-limit`` (as ``gpomap map`` does)."""
    from gpomap import cli
    from gpomap.cli.common import check_voxel_memory
    from gpomap.lattice import extent_bounds
    from gpomap.resources import grid_shape

    extent = written_extent(args, summary)
    if summary["dim"] == 2:
        if extent is None:
            lo, hi = _padded_bounds(summary, args.resolution)
            extent = (lo[0], hi[0], lo[1], hi[1])
        cli._check_grid_memory(args, grid_shape(extent, args.resolution), extent, int(summary.get("largest_tile_cells", 0)))
        return
    if extent is None:
        lo, hi = _padded_bounds(summary, args.resolution)
    else:
        lo, hi = (np.asarray(b, dtype=float) for b in extent_bounds(extent))
    check_voxel_memory(args, lo, hi, int(summary.get("largest_tile_cells", 0)))


def check_dimension_options(args: argparse.Namespace, summary: dict[str, Any], path: str) -> None:
    """Refuse the 3-D output options on a 2-D map (they would be ignored)."""
    if summary["dim"] == 2:
        for name in ("z_range", "slices"):
            if getattr(args, name, None) is not None:
                raise GpomapError(f"--{name.replace('_', '-')} is for 3-D maps; {path} holds a 2-D map")


def default_resolution(args: argparse.Namespace, summary: dict[str, Any]) -> None:
    """``--resolution`` when not given: what ``gpomap map`` writes, the ray counts' cell in 2-D, 0.1 m voxels in 3-D."""
    from gpomap.config import VOXEL_MAP_DEFAULTS

    if args.resolution is None:
        args.resolution = VOXEL_MAP_DEFAULTS["resolution"] if summary["dim"] == 3 else float(summary["evidence_resolution"])


def _check_not_replaced(mapfile: str, outdir: str) -> None:
    """Refuse an OUTDIR whose output set holds MAPFILE: the new set would remove it."""
    from gpomap.io.atomic import MANIFEST

    m, out = Path(mapfile).resolve(), Path(outdir).resolve()
    if m.parent != out:
        return
    try:
        files = json.loads((out / MANIFEST).read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return
    if m.name in files:
        raise GpomapError(
            f"-o {outdir}: its output set holds {m.name}, the map being rendered, which the new set would remove; "
            "write the render to another directory"
        )


def write_outputs(args: argparse.Namespace, model: Any, title: str, save_model: bool = False) -> tuple[Any, list[Path]]:
    """The model's grid at ``--resolution`` over the chosen extent, written as one output set
    (with the model's map file too when `save_model`); returns the grid and the files."""
    from gpomap import cli
    from gpomap.io.export import write_map_files
    from gpomap.io.mapfile import FILENAME, save_fitted_map

    summary = {"dim": model.dim_, "bounds": [list(model.bounds_[0]), list(model.bounds_[1])]}
    extent = written_extent(args, summary)
    t = time.perf_counter()
    grid = model.grid(args.resolution, extent)
    shape = "x".join(str(n) for n in reversed(grid.probability.shape))
    cli._status(args, f"  {shape} cells of {args.resolution:g} m in {time.perf_counter() - t:.2f} s; writing {args.output}/")
    cli._Run.outdir = args.output
    if model.dim_ == 3:
        from gpomap.io.voxel_outputs import write_voxel_outputs

        return grid, write_voxel_outputs(
            grid,
            args.output,
            heights=args.slices,
            title=title,
            save_model=functools.partial(save_fitted_map, model) if save_model else None,
        )
    with cli._outputs(args) as outputs:
        staged = write_map_files(grid, outputs.path, pgm_mode=args.pgm_mode, title=title)
        if save_model:
            staged.append(save_fitted_map(model, outputs.path / FILENAME))
    return grid, [outputs.final(f) for f in staged]


def configure(args: argparse.Namespace, model: Any) -> None:
    """``--workers`` and ``--thresholds``, when given, in place of the loaded map's own."""
    if getattr(args, "workers", None) is not None:
        model.n_workers = args.workers
    if getattr(args, "thresholds", None) is not None and "thresholds" not in getattr(args, "library_defaults", ()):
        model.base.thresholds = tuple(args.thresholds)


def add_output_arguments(p: argparse.ArgumentParser, what: str) -> None:
    """The output options of ``render`` and ``update``: those of ``gpomap map``, 3-D ones included, and ``--workers``."""
    from gpomap import cli
    from gpomap.cli.options import add_3d_output_options as add_output_options

    cli._add_output_options(p, None)
    for action in p._actions:
        if action.dest == "resolution":
            action.help = f"grid cell side of the {what}, m (default: gpomap map's: the ray counts' cell, 0.1 m voxels in 3-D)"
    add_output_options(p)
    p.add_argument("--workers", type=cli._positive(int), help="local workers for the tiles (default: the map's own)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap render`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "render",
        help="write a saved map (map.gpom) at any resolution, without refitting",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Load a fitted map written by gpomap map (map.gpom) and write its grid at --resolution over "
        "--extent as gpomap map writes its own: map.yaml/.pgm, map.npz, map.png (2-D) or the voxel outputs (3-D).",
    )
    p.add_argument("mapfile", metavar="MAPFILE", help="a fitted map file (map.gpom, written by gpomap map)")
    add_output_arguments(p, "written map")
    p.set_defaults(func=cmd_render)
    return p


def cmd_render(args: argparse.Namespace) -> int:
    """Run ``gpomap render``."""
    from gpomap import cli

    header = map_header(args.mapfile)
    summary = header["summary"]
    check_dimension_options(args, summary, args.mapfile)
    cli._check_before_work(args)
    _check_not_replaced(args.mapfile, args.output)
    default_resolution(args, summary)
    check_map_memory(args, summary)
    model = load_for_command(args, args.mapfile)
    _, files = write_outputs(args, model, f"gpomap: {Path(args.mapfile).name} at {args.resolution:g} m")
    print(f"map          {Path(args.mapfile)}: {summary['dim']}-D, {summary['n_scans']} scans, {summary['n_tiles']} tiles")
    print("ternary      free below {:.3f}, occupied above {:.3f}".format(*model.thresholds_))
    print("\n".join(f"wrote        {f}" for f in files))
    return cli.EXIT_OK
