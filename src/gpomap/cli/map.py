"""``gpomap map INPUT -o OUTDIR``: fit a map to range data and write it, with the fitted map file.

Planar scans (a CARMEN log, a ROS bag) and labelled points make a 2-D map written as map.yaml /
map.pgm (ROS map_server), map.npz, map.png and map.gpom; 3-D scans go to :mod:`gpomap.cli.map3d`.
The grid's memory is checked before the fit (:func:`plan_map`), and ``--chunk-scans`` grows the
map K scans at a time, rewriting it after each chunk.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from gpomap.apps.map3d import is_cloud_input
from gpomap.cli import map3d
from gpomap.cli.common import (
    EXIT_OK,
    bound_source,
    check_before_work,
    check_grid_memory,
    limit_threads,
    load_scans,
    outputs,
    print_map_summary,
    status,
    warn,
)
from gpomap.cli.input_options import add_cloud_reader_options, add_reader_options, add_selection_options, check_2d_options
from gpomap.cli.model_options import add_model_options, add_tiling_options, map_config, tiling_config
from gpomap.cli.options import Default, positive, resolve_library_defaults
from gpomap.cli.output_options import add_3d_output_options, add_output_options, resolution_from_evidence
from gpomap.config import MapConfig
from gpomap.errors import GpomapError

__all__ = ["add_parser", "run", "model", "fitted_model", "write_map", "write_grid", "save_model", "plan_map", "default_model"]

EPILOG = """examples:
  gpomap map ../shared/data/intel/intel-corrected.log.gz -o intel-map --scans 200 --beams 90
  gpomap map robot1.bag --topic /base_scan --fixed-frame odom --time-offset 0.1 -o arena --resolution 0.05
  gpomap map points.csv -o out --kernel se      (CSV with header x,y,occupied)
  gpomap map fr079.log.gz -o fr079 --workers 2 --free-step 0.3
  gpomap map intel.log.gz -o intel --chunk-scans 100      (the map grows as scans come)
  gpomap map intel.log.gz -o intel --scheduler tcp://127.0.0.1:8786
  gpomap map ../shared/data/la3dm-sim/sim_structured -o out3d --max-range 8 --slices 0.5,1.5
  gpomap map ../shared/data/3dmatch -o frames --stride 4 --resolution 0.05      (depth frames)
"""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap map`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "map",
        help="map a CARMEN log, ROS bag, labelled points, point clouds or depth frames",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Fit MSK-GPOM to range data and write map.yaml/.pgm (ROS map_server), map.npz and map.png; "
        "from 3-D scans, a voxel map: map.npz, map.bt (OctoMap), map.ply (surface mesh), map-slices.png and map-3d.png; "
        "and the fitted map itself, map.gpom, for gpomap render, query and update.",
    )
    p.add_argument(
        "input",
        help="CARMEN log (.log, .gz), ROS bag (.bag, ROS2 directory, .db3, .mcap), points (.csv, .npz), "
        "or 3-D scans: PCD / PLY files or a directory of them, depth frames, an OctoMap ScanGraph, a PointCloud2 bag",
    )
    add_reader_options(p)
    add_selection_options(p)
    add_model_options(p)
    # The written map's cells are the ray counts' cells unless asked otherwise: that is the map
    # the quality benchmark scores (a voxel map's default is gpomap.config.VOXEL_MAP_DEFAULTS').
    add_output_options(p, Default(MapConfig.evidence_resolution))
    add_tiling_options(p).add_argument(
        "--chunk-scans",
        type=positive(int),
        metavar="K",
        help="map incrementally, K scans at a time, rewriting the map after each chunk",
    )
    add_3d_output_options(p)
    add_cloud_reader_options(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap map``."""
    check_before_work(args)
    limit_threads(args)
    path = Path(args.input)
    title = f"gpomap: {path.name}"
    if path.suffix.lower() not in (".csv", ".npz") and is_cloud_input(path):
        return map3d.run(args)
    check_2d_options(args)
    resolution_from_evidence(args)
    if path.suffix.lower() in (".csv", ".npz"):
        from gpomap.io import read_points

        status(args, f"reading labelled points from {path}...")
        data: Any = read_points(path)
        n_scans: int | None = None
    else:
        status(args, f"reading scans from {path}...")
        data = load_scans(args)
        n_scans = len(data)
        status(args, f"  {n_scans} scans of {data[0].n_beams} beams")
    if args.chunk_scans is not None and n_scans is None:
        raise GpomapError("--chunk-scans needs scans (a CARMEN log or ROS bag), not labelled points")
    plan_map(args, data)
    if args.chunk_scans is not None:
        return _map_in_chunks(args, data, title)
    # The model is handed over, not kept here: it is let go before the grid's files are written.
    files, summary, bound = write_map(args, [fitted_model(args, data)], title, [save_model])
    print_map_summary(summary, files, bound)
    return EXIT_OK


def write_map(
    args: argparse.Namespace,
    holder: list[Any],
    title: str,
    files_of_model: Sequence[Callable[[Any, Path], Path]] = (),
    warn_fit: bool = True,
) -> tuple[list[Path], dict[str, Any], str | None]:
    """Write the planar map of the fitted model in `holder` as one output set, replacing the last.

    The grid is predicted first (a grid made in bands waits in a temporary file), then written by
    :func:`write_grid`: the files made from the model, the model let go, and only then the grid put
    together and its files written: a building's grid (800 MB at 0.05 m over 400 x 260 m) and its
    model are never in memory together, unless the caller keeps the model (``--chunk-scans``
    updates it). ``gpomap map``, ``demo``, ``render`` and ``update`` write a planar map here.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options: ``resolution``, ``extent``, ``output``, ``pgm_mode``, ``quiet``.
    holder : list
        A list of one fitted AreaGPOM, emptied here, so that this function's reference is the
        only one unless the caller kept its own.
    title : str
        The title of map.png.
    files_of_model : sequence of callable
        Each is called with the model and the staging directory, and returns the path of the
        file it wrote there (:func:`save_model`: map.gpom), before the model is let go.
    warn_fit : bool
        Say the model's and the written map's warnings (:func:`gpomap.diagnostics.fit_warnings`);
        ``gpomap render`` does not, as they were said when the map was fitted.

    Returns
    -------
    files : list of Path
        The final paths of the grid's files (map.yaml, map.pgm, map.npz, map.png), then those of
        `files_of_model`, in their order.
    summary : dict
        The model's :meth:`~gpomap.mapping.AreaGPOM.summary`.
    bound : str or None
        Its "at bound" note (:func:`gpomap.cli.common.bound_source`).
    """
    from gpomap.diagnostics import model_warnings

    fitted = holder.pop()
    t = time.perf_counter()
    later = fitted.map_.grid_later(args.resolution, args.extent)
    ny, nx = later.grid.shape
    status(args, f"  {nx} x {ny} cells predicted in {time.perf_counter() - t:.2f} s; writing {args.output}/")
    summary, bound, warnings = fitted.summary(), bound_source(fitted), model_warnings(fitted)
    handed = [fitted]
    del fitted
    files, map_warnings = write_grid(args, later, title, handed, files_of_model)
    if warn_fit:
        for message in warnings + map_warnings:
            warn(message)
    return files, summary, bound


def write_grid(
    args: argparse.Namespace,
    later: Callable[[], Any],
    title: str,
    handed: list[Any] | None = None,
    files_of_model: Sequence[Callable[[Any, Path], Path]] = (),
) -> tuple[list[Path], list[str]]:
    """Write a predicted planar grid, and the files of the model handed over, as one output set.

    The one place a command writes a planar map's files (:func:`write_map`; ``gpomap stream``
    and ``convert``, whose models are kept, call it with their grid). In the output set, the
    files of the model in `handed` are written first, the model is let go, and only then is the
    grid put together and its files written.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options: ``output``, ``pgm_mode``.
    later : callable
        Returns the OccupancyMap to write (a :class:`~gpomap.fitted.LaterGrid`, or a grid made
        already); called once, after the model is let go.
    title : str
        The title of map.png.
    handed : list, optional
        A list of one fitted model, emptied here: no model when None or empty.
    files_of_model : sequence of callable
        As :func:`write_map`'s, called with the handed model.

    Returns
    -------
    files : list of Path
        The final paths of the grid's files (map.yaml, map.pgm, map.npz, map.png), then those of
        `files_of_model`, in their order.
    warnings : list of str
        The written map's (:func:`gpomap.diagnostics.map_warnings`), not yet said.
    """
    from gpomap.diagnostics import map_warnings
    from gpomap.io.atomic import file_written
    from gpomap.io.export import write_map_files
    from gpomap.resources import release_freed_memory

    with outputs(args) as output:
        extra = []
        if handed:
            fitted = handed.pop()
            for write in files_of_model:
                extra.append(write(fitted, output.path))
                file_written()
            del fitted
            release_freed_memory()
        occupancy_map = later()
        staged = write_map_files(occupancy_map, output.path, pgm_mode=args.pgm_mode, title=title)
        warnings = map_warnings(occupancy_map.ternary)
    return [output.final(f) for f in [*staged, *extra]], warnings


def save_model(fitted: Any, directory: Path) -> Path:
    """Write the fitted map itself, ``map.gpom`` (:mod:`gpomap.io.mapfile`), into `directory`; returns its path."""
    from gpomap.io.mapfile import FILENAME, save_fitted_map

    return save_fitted_map(fitted, directory / FILENAME)


def plan_map(args: argparse.Namespace, data: Any) -> None:
    """Check the written grid's memory before fitting, over the box of the sensor and its beams' ends.

    The box comes from the scans (:func:`gpomap.scans.scan_extent`, no-return beams to the cap),
    not from the points they make (a whole log's are gigabytes with the cell tree); the tiles' GP
    sizes are checked by the fit once its cells exist (:meth:`gpomap.tiles.TiledGPOM.check_fit_memory`).
    """
    from gpomap.observations import Observations
    from gpomap.resources import grid_shape, points_extent
    from gpomap.scans import scan_extent

    if args.extent is not None:
        extent = args.extent
    elif isinstance(data, Observations):
        extent = points_extent(data.points)
    else:
        extent = scan_extent(data, include_no_return=True, no_return_cap=map_config(args).no_return_cap)
    check_grid_memory(args, grid_shape(extent, args.resolution), extent, 0)


def model(args: argparse.Namespace) -> Any:
    """The unfitted map of the parsed options (``gpomap map``, ``gpomap demo``)."""
    from gpomap.mapping import AreaGPOM

    return AreaGPOM(**tiling_config(args).kwargs(), **map_config(args).kwargs())


def fitted_model(args: argparse.Namespace, data: Any) -> Any:
    """:func:`model` fitted on `data`, saying so (``gpomap map``, ``gpomap demo``)."""
    from gpomap.compiled import compile_time

    fitted = model(args)
    status(args, f"fitting MSK-GPOM ({args.kernel})...")
    with compile_time() as compiling:
        fitted.fit(data)
    if compiling[0] >= 0.05:
        # A first run's compilation, not fitting: said apart (numba caches it for the next run).
        fitted.timings_["compiling (first run)"] = compiling[0]
    status(args, f"  {len(fitted.tiles_)} tiles, {fitted.n_inputs_} cells in {fitted.timings_['total_fit']:.2f} s")
    return fitted


def _map_in_chunks(args: argparse.Namespace, scans: list[Any], title: str) -> int:
    """Fit the first K scans, then add K at a time with ``update``, rewriting the map each time."""
    fitted = model(args)
    k = args.chunk_scans
    for start in range(0, len(scans), k):
        chunk = scans[start : start + k]
        t = time.perf_counter()
        if start == 0:
            fitted.fit(chunk)
            refit = len(fitted.tiles_)
        else:
            fitted.update(chunk)
            refit = len(fitted.last_refit_)
        status(args, f"scans {start}..{start + len(chunk) - 1}: {refit} tile(s) fitted in {time.perf_counter() - t:.2f} s")
        # The model is kept (the next chunk updates it): handed over in a list of its own.
        files, summary, bound = write_map(args, [fitted], f"{title} ({start + len(chunk)} of {len(scans)} scans)", [save_model])
    print_map_summary(summary, files, bound)
    return EXIT_OK


def default_model(**overrides: Any) -> tuple[Any, float]:
    """The unfitted model ``gpomap map CLOUDS -o OUT`` builds with its defaults, and its resolution
    (the model is the same whatever the clouds: the voxel profile is applied when it is fitted).

    Parameters
    ----------
    **overrides
        Values of the command's options (by dest) replacing the defaults (``min_cell=1.0``,
        ``kernel="se"``, ``workers=1``).

    Returns
    -------
    model : AreaGPOM
    resolution : float
        The voxel side ``gpomap map`` writes, metres.

    Raises
    ------
    ValueError
        An override that names no option of ``gpomap map``.
    """
    args = add_parser(argparse.ArgumentParser().add_subparsers()).parse_args(["clouds", "-o", "out"])
    resolve_library_defaults(args)
    map3d.apply_3d_defaults(args)
    for name, value in overrides.items():
        if not hasattr(args, name):
            raise ValueError(f"gpomap map has no option {name!r}")
        setattr(args, name, value)
    return map3d.unfitted_model(args), float(args.resolution)
