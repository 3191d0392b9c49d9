"""``gpomap update MAPFILE NEWLOG -o OUTDIR``: a saved map extended with new scans, written with its map file.

The map file (``map.gpom``; :mod:`gpomap.io.mapfile`) holds the fitted map and the scans it was
fitted on. NEWLOG's scans (read with the reading and selecting options of ``gpomap map``) are added
to it, and the output set is written as ``gpomap map`` writes one, with the updated ``map.gpom``
(to OUTDIR, which may be MAPFILE's own directory: the set then replaces it).

By default (:meth:`gpomap.tiles.TiledGPOM.update`) the new scans are absorbed with the saved
hyperparameters: the batch map of all the scans with those hyperparameters, up to the two
exceptions docs/mapfile.md names. With ``--relearn`` everything is fitted again on all the scans,
hyperparameters included: the map ``gpomap map`` makes of the saved scans followed by the new ones
with the saved map's settings, to the bit.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gpomap.apps.map3d import is_cloud_input
from gpomap.apps.render import map_header
from gpomap.apps.update import bounds_with, other_laser, repeated_scans, unfitted_like
from gpomap.cli.common import EXIT_OK, check_before_work, load_scans, print_map_summary, status, warn
from gpomap.cli.input_options import add_cloud_reader_options, add_reader_options, add_selection_options, check_2d_options
from gpomap.cli.map3d import load_clouds
from gpomap.cli.render import (
    add_output_arguments,
    check_dimension_options,
    check_map_memory,
    configure,
    default_resolution,
    load_for_command,
    write_outputs,
)
from gpomap.errors import GpomapError

__all__ = ["add_parser", "run"]

EPILOG = """examples:
  gpomap update arena/map.gpom robot1.bag --topic /base_scan --time-offset 0.1 --range 200: -o arena
  gpomap update arena/map.gpom robot1.bag --topic /base_scan --time-offset 0.1 --range 200: -o arena-all --relearn
"""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap update`` on the subparsers of :func:`gpomap.cli.build_parser`."""
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
    add_reader_options(p)
    add_selection_options(p)
    add_cloud_reader_options(p)
    add_output_arguments(p, "written map")
    p.set_defaults(func=run)
    return p


def _read_new_scans(args: argparse.Namespace, dim: int) -> list[Any]:
    """NEWLOG's scans, read as ``gpomap map`` reads them; refused when their dimension is not the map's."""
    clouds = is_cloud_input(args.input)
    if clouds != (dim == 3):
        holds = "3-D scans (point clouds)" if clouds else "planar scans"
        raise GpomapError(f"{args.input} holds {holds}; {args.mapfile} is a {dim}-D map")
    status(args, f"reading the new scans from {args.input}...")
    if dim == 3:
        return load_clouds(args)
    check_2d_options(args)
    return load_scans(args)


def _check_memory(args: argparse.Namespace, summary: dict[str, Any], scans: Sequence[Any]) -> None:
    """The written grid over the saved data and the new scans, refused before any fit if too large."""
    lo, hi = bounds_with(summary["bounds"], scans, summary.get("no_return_cap"))
    check_map_memory(args, {**summary, "bounds": [lo.tolist(), hi.tolist()]})


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap update``."""
    header = map_header(args.mapfile)
    summary = header["summary"]
    dim = int(summary["dim"])
    check_dimension_options(args, summary, args.mapfile)
    if not summary.get("scans_kept", False):
        raise GpomapError(f"{args.mapfile} was fitted on labelled points, not scans: it cannot take new scans")
    check_before_work(args)
    default_resolution(args, summary)
    new = _read_new_scans(args, dim)
    status(args, f"  {len(new)} new scans")
    _check_memory(args, summary, new)
    model = load_for_command(args, args.mapfile)
    saved = list(model._scans)
    repeated = repeated_scans(saved, new)
    if repeated:
        warn(
            f"{repeated} of the {len(new)} new scans are already in {args.mapfile} (the same pose and readings): they count twice"
        )
    laser = other_laser(saved, new) if saved else None
    if laser is not None:
        # Another robot's log, or the same one thinned otherwise: its poses must be in the map's frame.
        warn(
            f"the new scans' laser ({laser[0]}) is not the one of {args.mapfile} ({laser[1]}): another sensor or "
            "another --beams; they are added as they are, their poses taken in the map's frame"
        )
    t = time.perf_counter()
    if args.relearn:
        status(args, f"fitting the map of all {len(saved) + len(new)} scans again, hyperparameters included...")
        model = unfitted_like(model).fit(saved + new)  # its settings, --workers and --thresholds included
        how = f"all {len(saved) + len(new)} scans fitted again (--relearn)"
    else:
        status(args, f"adding {len(new)} scans with the saved hyperparameters...")
        model.update(new)
        how = f"{len(new)} scans added to {len(saved)}, {len(model.last_refit_)} of {len(model.tiles_)} tiles refitted"
    seconds = time.perf_counter() - t
    status(args, f"  done in {seconds:.2f} s")
    configure(args, model)
    # The model is handed over, not kept here (the scans with it): a planar map's is let go once
    # map.gpom is written, before its grid is put together.
    holder = [model]
    del model, saved, new
    title = f"gpomap: {Path(args.mapfile).name} + {Path(args.input).name}"
    files, fitted_summary = write_outputs(args, holder, title, save_model=True, warn_fit=True)
    print(f"update       {how} in {seconds:.2f} s")
    print_map_summary(fitted_summary, files)
    return EXIT_OK
