"""``gpomap render MAPFILE -o OUTDIR --resolution R``: a saved map written again, at any resolution, without refitting.

The map file (``map.gpom``, written by ``gpomap map``; :mod:`gpomap.io.mapfile`) holds the fitted
model; its grid at ``--resolution`` over ``--extent`` (default: the data's, as ``gpomap map`` takes
it) is written as ``gpomap map`` writes its own: ``map.yaml`` / ``map.pgm`` / ``map.npz`` /
``map.png`` for a 2-D map, through the same function (:func:`gpomap.cli.map.write_map`, the model
let go before the grid is put together), the voxel outputs for a 3-D one, as one output set. The
grid is the loaded model's ``grid(resolution, extent)``: the live model's cells to the bit. Its
memory is checked against ``--memory-limit`` from the file's header alone, before the map is loaded.

:func:`load_for_command`, :func:`check_map_memory`, :func:`write_outputs` and the option helpers
here serve ``gpomap query`` and ``gpomap update`` too.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.apps.render import check_not_replaced, map_header, padded_bounds, written_extent
from gpomap.cli.common import EXIT_OK, Run, check_before_work, check_grid_memory, check_voxel_memory, report_fit, status
from gpomap.cli.options import positive
from gpomap.cli.output_options import add_3d_output_options, add_output_options
from gpomap.errors import GpomapError

__all__ = [
    "add_parser",
    "run",
    "add_output_arguments",
    "configure",
    "load_for_command",
    "check_dimension_options",
    "default_resolution",
    "check_map_memory",
    "write_outputs",
]

EPILOG = """examples:
  gpomap render arena/map.gpom -o arena-1cm --resolution 0.01
  gpomap render arena/map.gpom -o door --resolution 0.005 --extent 0.5,1.5,-0.5,0.5
"""


def add_output_arguments(p: argparse.ArgumentParser, what: str) -> None:
    """The output options of ``render`` and ``update``: those of ``gpomap map``, 3-D ones included, and ``--workers``."""
    add_output_options(p, None)
    for action in p._actions:
        if action.dest == "resolution":
            action.help = f"grid cell side of the {what}, m (default: gpomap map's: the ray counts' cell, 0.1 m voxels in 3-D)"
    add_3d_output_options(p)
    p.add_argument("--workers", type=positive(int), help="local workers for the tiles (default: the map's own)")
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
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap render``."""
    header = map_header(args.mapfile)
    summary = header["summary"]
    check_dimension_options(args, summary, args.mapfile)
    check_before_work(args)
    check_not_replaced(args.mapfile, args.output)
    default_resolution(args, summary)
    check_map_memory(args, summary)
    # The model is handed over, not kept here: a planar map's is let go before its grid is put together.
    holder = [load_for_command(args, args.mapfile)]
    thresholds = holder[0].thresholds_
    files, _ = write_outputs(args, holder, f"gpomap: {Path(args.mapfile).name} at {args.resolution:g} m")
    print(f"map          {Path(args.mapfile)}: {summary['dim']}-D, {summary['n_scans']} scans, {summary['n_tiles']} tiles")
    print("ternary      free below {:.3f}, occupied above {:.3f}".format(*thresholds))
    print("\n".join(f"wrote        {f}" for f in files))
    return EXIT_OK


def configure(args: argparse.Namespace, model: Any) -> None:
    """``--workers`` and ``--thresholds``, when given, in place of the loaded map's own."""
    if getattr(args, "workers", None) is not None:
        model.n_workers = args.workers
    if getattr(args, "thresholds", None) is not None and "thresholds" not in getattr(args, "library_defaults", ()):
        model.base = model.base.replace(thresholds=tuple(args.thresholds))


def load_for_command(args: argparse.Namespace, path: str) -> Any:
    """The fitted map of `path`, with ``--workers`` and ``--thresholds`` when given (:func:`configure`), said on stderr."""
    from gpomap.io.mapfile import load_fitted_map

    status(args, f"loading the map from {path}...")
    t = time.perf_counter()
    model = load_fitted_map(path)
    configure(args, model)
    status(
        args, f"  {len(model.tiles_)} tiles, {model.n_inputs_} cells, {model._n_scans} scans in {time.perf_counter() - t:.2f} s"
    )
    return model


def check_dimension_options(args: argparse.Namespace, summary: dict[str, Any], path: str) -> None:
    """Refuse the 3-D output options on a 2-D map (they would be ignored)."""
    if summary["dim"] == 2:
        for name in ("z_range", "slices"):
            if getattr(args, name, None) is not None:
                raise GpomapError(f"--{name.replace('_', '-')} is for 3-D maps; {path} holds a 2-D map")


def default_resolution(args: argparse.Namespace, summary: dict[str, Any]) -> None:
    """``--resolution`` when not given: what ``gpomap map`` writes, the ray counts' cell in 2-D, :data:`gpomap.config.VOXEL_MAP_DEFAULTS`' voxel in 3-D."""
    from gpomap.config import VOXEL_MAP_DEFAULTS

    if args.resolution is None:
        args.resolution = VOXEL_MAP_DEFAULTS["resolution"] if summary["dim"] == 3 else float(summary["evidence_resolution"])


def _extent(args: argparse.Namespace, summary: dict[str, Any]) -> tuple[float, ...] | None:
    """:func:`gpomap.apps.render.written_extent` of ``--resolution``, ``--extent`` and ``--z-range``."""
    return written_extent(summary, args.resolution, args.extent, args.z_range)


def check_map_memory(args: argparse.Namespace, summary: dict[str, Any]) -> None:
    """Refuse, from the header alone, a written grid that needs more than ``--memory-limit`` (as ``gpomap map`` does)."""
    from gpomap.lattice import extent_bounds
    from gpomap.resources import grid_shape

    extent = _extent(args, summary)
    if summary["dim"] == 2:
        if extent is None:
            lo, hi = padded_bounds(summary, args.resolution)
            extent = (lo[0], hi[0], lo[1], hi[1])
        check_grid_memory(args, grid_shape(extent, args.resolution), extent, int(summary.get("largest_tile_cells", 0)))
        return
    if extent is None:
        lo, hi = padded_bounds(summary, args.resolution)
    else:
        lo, hi = (np.asarray(b, dtype=float) for b in extent_bounds(extent))
    check_voxel_memory(args, lo, hi, int(summary.get("largest_tile_cells", 0)))


def write_outputs(
    args: argparse.Namespace, holder: list[Any], title: str, save_model: bool = False, warn_fit: bool = False
) -> tuple[list[Path], dict[str, Any]]:
    """The grid of the model in `holder` (a list of one, emptied here) at ``--resolution`` over the
    chosen extent, written as one output set (with the model's map file too when `save_model`).

    A planar map is written through ``gpomap map``'s path (:func:`gpomap.cli.map.write_map`): the
    model is let go before its grid is put together. A voxel map is written beside its model
    (:func:`gpomap.io.voxel_outputs.write_voxel_outputs`). `warn_fit` says the fit's warnings
    (``gpomap update``'s new fit). Returns the files written and the model's summary.
    """
    from gpomap.cli.map import save_model as save_map_file
    from gpomap.cli.map import write_map

    if holder[0].dim_ == 2:
        files, summary, _ = write_map(args, holder, title, [save_map_file] if save_model else (), warn_fit=warn_fit)
        return files, summary
    from gpomap.io.mapfile import save_fitted_map
    from gpomap.io.voxel_outputs import write_voxel_outputs

    model = holder.pop()
    box = {"dim": model.dim_, "bounds": [list(model.bounds_[0]), list(model.bounds_[1])]}
    t = time.perf_counter()
    grid = model.grid(args.resolution, _extent(args, box))
    shape = "x".join(str(n) for n in reversed(grid.probability.shape))
    status(args, f"  {shape} cells of {args.resolution:g} m in {time.perf_counter() - t:.2f} s; writing {args.output}/")
    Run.outdir = args.output
    files = write_voxel_outputs(
        grid,
        args.output,
        heights=args.slices,
        title=title,
        save_model=functools.partial(save_fitted_map, model) if save_model else None,
    )
    if warn_fit:
        report_fit(model, grid)
    return files, model.summary()
