"""``gpomap map`` on 3-D inputs: point clouds and depth frames to a continuous voxel map.

:mod:`gpomap.cli.map` hands a run here when :func:`gpomap.apps.map3d.is_cloud_input` says the input
holds 3-D scans. The steps mirror the 2-D command:

1. the clouds are read (``--poses``, ``--max-range``, ``--stride``, ``--depth-scale``,
   ``--points-frame``, the bag options) and selected (``--range``, ``--scans``, ``--beams``: rays
   per cloud);
2. before anything is fitted, the voxel grid is checked against the memory limit, and the map is
   built by the local GPs of every map, in x, y columns of ``--tile-size`` (the fit checks its
   tiles' GPs, and the voxel grid is checked again with its largest tile's cells);
3. the voxel map at ``--resolution`` (the voxel profile's, :data:`gpomap.config.PROFILES`, when not given) is
   written as one output set by :func:`gpomap.io.voxel_outputs.write_voxel_outputs`, with the
   fitted map, ``map.gpom``.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gpomap.apps.map3d import enclosing_box, labelled_box, new_model, read_selected_clouds, voxel_bounds
from gpomap.cli.common import EXIT_OK, Run, bound_source, check_voxel_memory, print_map_summary, report_fit, status
from gpomap.cli.input_options import cloud_reader_options
from gpomap.cli.model_options import map_config, tiling_config
from gpomap.clouds import CloudScan
from gpomap.config import PROFILES
from gpomap.errors import GpomapError

__all__ = ["apply_3d_defaults", "load_clouds", "unfitted_model", "run"]

#: Options of ``gpomap map`` that only 2-D inputs take, refused on clouds with this reason.
_TWO_D_ONLY = {
    "chunk_scans": ("--chunk-scans", "incremental mapping takes planar scans"),
}


def apply_3d_defaults(args: argparse.Namespace) -> None:
    """The voxel maps' written resolution (:data:`gpomap.config.PROFILES`) in place of the planar
    default, where the user left it unset; the library applies the rest of the profile itself."""
    if "resolution" in getattr(args, "library_defaults", ()):
        args.resolution = PROFILES[3].resolution


def load_clouds(args: argparse.Namespace) -> list[CloudScan]:
    """Read and select the clouds of ``args.input`` as ``gpomap map`` does (:func:`gpomap.apps.map3d.read_selected_clouds`)."""
    return read_selected_clouds(args.input, cloud_reader_options(args), args.scan_range, args.scans, args.beams)


def unfitted_model(args: argparse.Namespace) -> Any:
    """The unfitted model of a parsed ``gpomap map`` command line on 3-D input (:func:`gpomap.apps.map3d.new_model`)."""
    return new_model(tiling_config(args).kwargs(), **map_config(args).kwargs())


def _check_options(args: argparse.Namespace) -> None:
    """Refuse the options of ``gpomap map`` that only 2-D inputs take."""
    for name, (option, why) in _TWO_D_ONLY.items():
        if getattr(args, name, None) is not None:
            raise GpomapError(f"{option} is for 2-D inputs ({why}); {args.input} holds 3-D scans")


def _plan(args: argparse.Namespace, clouds: Sequence[CloudScan]) -> tuple[Any, int]:
    """The unfitted model and the clouds' hits, with the voxel grid's own memory checked before fitting.

    The grid is checked over a box round the rays (:func:`gpomap.apps.map3d.enclosing_box`), and
    only where that is too large over the labelled points' exact box
    (:func:`gpomap.apps.map3d.labelled_box`), which the fit works out anyway; the fit refuses
    tiles too large for the memory itself, once its cells exist, and the grid with its prediction
    chunks (sized by the largest tile) is checked again after it (:func:`_check_grid_after_fit`).
    """
    import numpy as np

    from gpomap.resources import MemoryLimitError

    model_options = map_config(args).kwargs()
    try:
        check_voxel_memory(
            args, *voxel_bounds(enclosing_box(clouds, **model_options), args.extent, args.z_range, args.resolution), 0
        )
    except MemoryLimitError:
        box = labelled_box(clouds, **model_options)
        check_voxel_memory(args, *voxel_bounds(box, args.extent, args.z_range, args.resolution), 0)
    n_hits = sum(int((c.valid() & np.asarray(c.hit, dtype=bool)).sum()) for c in clouds)
    return new_model(tiling_config(args).kwargs(), **model_options), n_hits


def _check_grid_after_fit(args: argparse.Namespace, model: Any, lo: Any, hi: Any) -> None:
    """Refuse the voxel grid between `lo` and `hi` whose prediction, by the fitted `model`'s largest tile, needs more than ``--memory-limit``."""
    from gpomap.tiles.store import light_tiles

    check_voxel_memory(args, lo, hi, max((s.n_cells for s in light_tiles(model.tiles_)), default=0))


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap map`` on a 3-D input (the output directory is checked already)."""
    import numpy as np

    from gpomap.io.mapfile import save_fitted_map
    from gpomap.io.voxel_outputs import write_voxel_outputs
    from gpomap.lattice import bounds_extent

    _check_options(args)
    apply_3d_defaults(args)
    status(args, f"reading 3-D scans from {args.input}...")
    clouds = load_clouds(args)
    n_rays = sum(c.n_points for c in clouds)
    status(args, f"  {len(clouds)} scans, {n_rays} rays")
    model, n_hits = _plan(args, clouds)
    status(args, f"fitting MSK-GPOM in 3-D ({args.kernel}, {n_hits} hits)...")
    t = time.perf_counter()
    model.fit(clouds)
    fit_s = time.perf_counter() - t
    lo, hi = voxel_bounds(np.array(model.kept_bounds_), args.extent, args.z_range, args.resolution)
    _check_grid_after_fit(args, model, lo, hi)
    status(args, f"  fitted {model.n_inputs_} cells in {fit_s:.2f} s; predicting voxels of {args.resolution:g} m...")
    t = time.perf_counter()
    voxel_map = model.grid(args.resolution, bounds_extent(lo, hi))
    grid_s = time.perf_counter() - t
    nz, ny, nx = voxel_map.spec.shape
    status(args, f"  {nx} x {ny} x {nz} voxels in {grid_s:.2f} s; writing {args.output}/")
    Run.outdir = args.output  # for a true message if interrupted while writing
    t = time.perf_counter()
    files = write_voxel_outputs(
        voxel_map,
        args.output,
        heights=args.slices,
        title=f"gpomap: {Path(args.input).name}",
        save_model=functools.partial(save_fitted_map, model),
    )
    write_s = time.perf_counter() - t
    report_fit(model, voxel_map)
    print_map_summary(model.summary(), [], bound_source(model))
    print(_voxel_line(voxel_map, grid_s, write_s))
    print("\n".join(f"wrote        {f}" for f in files))
    return EXIT_OK


def _voxel_line(voxel_map: Any, grid_s: float, write_s: float) -> str:
    """The summary's line on the voxels: how many of each class, and the seconds to predict and write them."""
    from gpomap.grid import FREE, OCCUPIED

    t = voxel_map.ternary
    nz, ny, nx = voxel_map.spec.shape
    n_occ, n_free = int((t == OCCUPIED).sum()), int((t == FREE).sum())
    # The GP's guess behind the surfaces: above the occupied threshold where no ray went.
    guessed = int(((voxel_map.probability > voxel_map.thresholds[1]) & ~voxel_map.seen).sum())
    return (
        f"voxels       {nx} x {ny} x {nz} of {voxel_map.spec.resolution:g} m: {n_occ} occupied, {n_free} free, "
        f"{t.size - n_occ - n_free} unknown ({guessed} of them above the occupied threshold where no ray went); "
        f"predicted in {grid_s:.2f} s, written in {write_s:.2f} s"
    )
