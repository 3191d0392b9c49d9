"""``gpomap update MAPFILE NEWLOG -o OUTDIR``: a saved map extended with new scans, written with its map file.

The map file (``map.gpom``; :mod:`gpomap.io.mapfile`) holds the fitted map and the scans it was
fitted on. NEWLOG's scans (read with the reading and selecting options of ``gpomap map``) are added
to it, and the output set is written as ``gpomap map`` writes one, with the updated ``map.gpom``
(to OUTDIR, which may be MAPFILE's own directory: the set then replaces it).

What the result is:

- by default (:meth:`gpomap.tiles.TiledGPOM.update`), the new scans are absorbed with the saved
  hyperparameters (the variance scale among them): the cell trees of the blocks they reach are
  rebuilt, every tile whose cells changed is refitted afresh, the new beams are counted, and the
  ray counts' calibration is refitted on every scan. The map is then the batch map of all the scans
  with the saved hyperparameters on the saved map's tile grid (``fit(old + new,
  hyperparameters=saved)`` with ``origin`` the saved ``origin_``; a batch fit chooses its own grid,
  centred on the data of a small map), as :meth:`gpomap.streaming.StreamingGPOM.finish` is, up to
  two things. The recalibration for a later visit (:mod:`gpomap.revisit`) stays the saved map's, as
  a streaming map keeps that of its last whole fit (a batch fit of 100 scans or more fits it again,
  on a second map of 70 % of the scans). And the new scans are counted on a lattice of their own
  before they are added in, so a beam end or a step of the robot's path lying exactly on a cell
  border may be counted in the cell beside (as on the simulated Stage arena's path).
  ``tests/test_mapfile.py`` checks the map against the batch map to 1e-9 (the
  paper's room, off the lattice), and on the Stage arena the GP to 1e-9 and the beams' counts
  exactly;
- with ``--relearn``, everything is fitted again on all the scans, hyperparameters included: the map
  ``gpomap map`` makes of the saved scans followed by the new ones with the saved map's settings,
  to the bit.

:func:`add_parser` and :func:`cmd_update` are the subcommand (registered in :mod:`gpomap.cli`).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import GpomapError

__all__ = ["add_parser", "cmd_update", "unfitted_like", "repeated_scans"]

EPILOG = """examples:
  gpomap update arena/map.gpom robot1.bag --topic /base_scan --time-offset 0.1 --range 200: -o arena
  gpomap update arena/map.gpom robot1.bag --topic /base_scan --time-offset 0.1 --range 200: -o arena-all --relearn
"""


def unfitted_like(model: Any) -> Any:
    """An unfitted map of `model`'s class with its settings (its tiling as given, not as resolved by its fit)."""
    from gpomap.mapping import AreaGPOM
    from gpomap.tiles import TiledGPOM

    if isinstance(model, AreaGPOM):
        return AreaGPOM(**model.get_params())
    return TiledGPOM(
        model.tile_size,
        model.overlap,
        model.blend,
        model.origin,
        n_workers=model.n_workers,
        hyper_sample=model.hyper_sample,
        per_tile_hyperparameters=model.per_tile_hyperparameters,
        blas_threads=model.blas_threads,
        scheduler_timeout=model.scheduler_timeout,
        worker_processes=model.worker_processes,
        memory_limit=model.memory_limit,
        **model.options,
    )


def _scan_key(scan: Any) -> bytes:
    from gpomap.clouds import CloudScan

    if isinstance(scan, CloudScan):
        return scan.origin.tobytes() + scan.points.tobytes()
    return scan.pose.tobytes() + scan.ranges.tobytes()


def repeated_scans(saved: Sequence[Any], new: Sequence[Any]) -> int:
    """How many of the `new` scans are already among the `saved` ones (the same pose and readings)."""
    keys = {_scan_key(s) for s in saved}
    return sum(_scan_key(s) in keys for s in new)


def _read_new_scans(args: argparse.Namespace, dim: int) -> list[Any]:
    from gpomap import cli
    from gpomap.apps.map3d import is_cloud_input
    from gpomap.cli.map3d import load_clouds
    from gpomap.cli.options import check_2d_options

    clouds = is_cloud_input(args.input)
    if clouds != (dim == 3):
        holds = "3-D scans (point clouds)" if clouds else "planar scans"
        raise GpomapError(f"{args.input} holds {holds}; {args.mapfile} is a {dim}-D map")
    cli._status(args, f"reading the new scans from {args.input}...")
    if dim == 3:
        return load_clouds(args)
    check_2d_options(args)
    return cli._load_scans(args)


def _check_memory(args: argparse.Namespace, summary: dict[str, Any], scans: Sequence[Any]) -> None:
    """The written grid over the saved data and the new scans, refused before any fit if too large."""
    from gpomap.apps.render import check_map_memory
    from gpomap.observations import Rays

    lo, hi = (np.asarray(b, dtype=float) for b in summary["bounds"])
    cap = summary.get("no_return_cap")
    for s in scans:
        rays = Rays.of(s)
        # The data's box: the sensor, the hits, and no-return rays as far as they clear free space.
        lengths = rays.lengths if cap is None else np.where(rays.hit, rays.lengths, np.minimum(rays.lengths, cap))
        pts = np.concatenate([rays.origin.reshape(1, -1), rays.origin + lengths[:, None] * rays.directions])
        lo, hi = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
    check_map_memory(args, {**summary, "bounds": [lo.tolist(), hi.tolist()]})


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap update`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    from gpomap import cli
    from gpomap.apps.render import add_output_arguments
    from gpomap.cli.options import add_cloud_reader_options

    p: argparse.ArgumentParser = sub.add_parser(
        "update",
        help="add the scans of a new log to a saved map (map.gpom) and write it again",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Load a fitted map written by gpomap map (map.gpom), add NEWLOG's scans to it with the saved "
        "hyperparameters (the batch map of all the scans with those hyperparameters; --relearn: fit everything again, "
        "as gpomap map would on all the scans), and write the output set with the updated map.gpom.",
    )
    p.add_argument("mapfile", metavar="MAPFILE", help="a fitted map file (map.gpom, written by gpomap map or gpomap update)")
    p.add_argument("input", metavar="NEWLOG", help="the new scans: a CARMEN log, ROS bag, or 3-D scans for a 3-D map")
    p.add_argument(
        "--relearn",
        action="store_true",
        help="fit everything again on all the scans, hyperparameters included (gpomap map's map of all of them); "
        "default: keep the saved hyperparameters and refit only the tiles the new scans reach",
    )
    cli._add_reader_options(p)
    cli._add_selection_options(p)
    add_cloud_reader_options(p)
    add_output_arguments(p, "written map")
    p.set_defaults(func=cmd_update)
    return p


def cmd_update(args: argparse.Namespace) -> int:
    """Run ``gpomap update``."""
    from gpomap import cli
    from gpomap.apps.render import (
        check_dimension_options,
        configure,
        default_resolution,
        load_for_command,
        map_header,
        write_outputs,
    )

    header = map_header(args.mapfile)
    summary = header["summary"]
    dim = int(summary["dim"])
    check_dimension_options(args, summary, args.mapfile)
    if not summary.get("scans_kept", False):
        raise GpomapError(f"{args.mapfile} was fitted on labelled points, not scans: it cannot take new scans")
    cli._check_before_work(args)
    default_resolution(args, summary)
    new = _read_new_scans(args, dim)
    cli._status(args, f"  {len(new)} new scans")
    _check_memory(args, summary, new)
    model = load_for_command(args, args.mapfile)
    saved = list(model._scans)
    repeated = repeated_scans(saved, new)
    if repeated:
        cli._warn(
            f"{repeated} of the {len(new)} new scans are already in {args.mapfile} (the same pose and readings): they count twice"
        )
    t = time.perf_counter()
    if args.relearn:
        cli._status(args, f"fitting the map of all {len(saved) + len(new)} scans again, hyperparameters included...")
        model = unfitted_like(model).fit(saved + new)  # its settings, --workers and --thresholds included
        how = f"all {len(saved) + len(new)} scans fitted again (--relearn)"
    else:
        cli._status(args, f"adding {len(new)} scans with the saved hyperparameters...")
        model.update(new)
        how = f"{len(new)} scans added to {len(saved)}, {len(model.last_refit_)} of {len(model.tiles_)} tiles refitted"
    seconds = time.perf_counter() - t
    cli._status(args, f"  done in {seconds:.2f} s")
    configure(args, model)
    grid, files = write_outputs(args, model, f"gpomap: {Path(args.mapfile).name} + {Path(args.input).name}", save_model=True)
    cli._report_fit(model, grid)
    print(f"update       {how} in {seconds:.2f} s")
    cli._print_map_summary(model.summary(), files)
    return cli.EXIT_OK
