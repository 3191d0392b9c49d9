"""``gpomap map`` on 3-D inputs: point clouds and depth frames to a continuous voxel map.

:mod:`gpomap.cli` hands a ``map`` run here when :func:`is_cloud_input` says the input holds 3-D
scans (:data:`gpomap.io.CLOUD_FORMATS`, or a ROS bag with ``PointCloud2`` and no ``LaserScan``).
The steps mirror the 2-D command:

1. the clouds are read with :func:`gpomap.io.read_clouds` (``--poses``, ``--max-range``,
   ``--stride``, ``--depth-scale``, ``--points-frame``, the bag options) and selected
   (``--range``, ``--scans``, ``--beams``: rays per cloud);
2. before anything is fitted, the voxel grid and the GP are checked against the memory limit
   (:func:`gpomap.resources.voxel_grid_memory`, :func:`gpomap.resources.fit_memory`), and the
   map is built by the local GPs of every map, in x, y columns of ``--tile-size``;
3. the voxel map at ``--resolution`` (0.1 m by default, OctoMap's usual) is written as one output
   set by :func:`gpomap.io.voxel_outputs.write_voxel_outputs`: ``map.npz``, ``map.bt``,
   ``map.ply`` (the p = 0.5 surface), ``map-slices.png`` (at ``--slices`` heights),
   ``map-3d.png`` and ``map.gpom`` (the fitted map, :mod:`gpomap.io.mapfile`).

:func:`build_model` and :func:`load_clouds` are free of printing so that benchmarks use the very
model ``gpomap map`` builds (``benchmarks/quality3d.py``, ``benchmarks/volume_quality.py``).
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.config import VOXEL_MAP_DEFAULTS
from gpomap.errors import GpomapError

__all__ = [
    "add_cloud_options",
    "is_cloud_input",
    "load_clouds",
    "select_clouds",
    "voxel_bounds",
    "build_model",
    "default_model",
    "model_from_args",
    "apply_3d_defaults",
    "DEFAULTS_3D",
    "check_2d_options",
    "check_voxel_memory",
    "cmd_map3d",
]

#: Options whose default (measured on 2-D logs) a 3-D map replaces when the user leaves it unset:
#: :data:`gpomap.config.VOXEL_MAP_DEFAULTS`, where the measurements are quoted.
DEFAULTS_3D: dict[str, float] = VOXEL_MAP_DEFAULTS

#: Options of ``gpomap map`` that only 2-D inputs take, refused on clouds with this reason.
_TWO_D_ONLY = {
    "chunk_scans": ("--chunk-scans", "incremental mapping takes planar scans"),
}


# --------------------------------------------------------------------------- parsing
def _heights(text: str) -> tuple[float, ...]:
    """``--slices z1,z2,...``: finite heights in metres."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"slices must be heights Z1,Z2,... in metres, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"slices must be finite heights Z1,Z2,... in metres, got {text!r}")
    return values


def _z_range(text: str) -> tuple[float, float]:
    """``--z-range ZMIN,ZMAX`` with ZMIN < ZMAX, finite."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"z range must be ZMIN,ZMAX in metres, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise argparse.ArgumentTypeError(f"z range must be two finite numbers ZMIN,ZMAX with ZMIN < ZMAX, got {text!r}")
    return lo, hi


def add_output_options(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """``--z-range`` and ``--slices``: the 3-D output options ``map`` and ``convert`` share; returns their group."""
    g = p.add_argument_group("3-D maps (point clouds, depth frames, OctoMap trees)")
    g.add_argument(
        "--z-range",
        type=_z_range,
        metavar="ZMIN,ZMAX",
        help="heights of the written voxel map, m (with --extent for x and y; default: the data's)",
    )
    g.add_argument(
        "--slices",
        type=_heights,
        metavar="Z1,Z2,...",
        help="heights of the horizontal slices in map-slices.png, m (default: four spread over the map)",
    )
    return g


def add_cloud_options(p: argparse.ArgumentParser) -> None:
    """The reading and output options of 3-D inputs, added to the ``map`` parser."""
    add_output_options(p)
    add_cloud_reader_options(p)


def add_cloud_reader_options(p: argparse.ArgumentParser) -> None:
    """The reading options of 3-D inputs (``map`` and ``info`` take them alike)."""
    from gpomap import cli

    g = p.add_argument_group("reading 3-D inputs")
    g.add_argument(
        "--poses",
        metavar="FILE",
        help="PCD / PLY: one sensor-to-map pose per file, in the files' order (required for PLY; replaces PCD VIEWPOINTs)",
    )
    g.add_argument(
        "--points-frame",
        choices=["map", "sensor"],
        help="PCD with a VIEWPOINT: the points are already in the map frame, or in the sensor's (default: map)",
    )
    g.add_argument(
        "--stride", type=cli._positive(int), metavar="K", help="depth frames: every K-th pixel along both image axes (default: 1)"
    )
    g.add_argument(
        "--depth-scale",
        type=cli._positive(float),
        metavar="UNITS",
        help="depth frames: depth units per metre (default: 1000, millimetres; TUM: 5000)",
    )


def is_cloud_input(path: str | os.PathLike[str]) -> bool:
    """Whether `path` holds 3-D scans: a cloud format, or a bag with PointCloud2 and no LaserScan."""
    from gpomap.io import CLOUD_FORMATS, detect_format

    fmt = detect_format(path)
    if fmt in CLOUD_FORMATS:
        return True
    if fmt in ("rosbag1", "rosbag2"):
        from gpomap.io.pointcloud2 import bag_has_pointclouds_only

        return bag_has_pointclouds_only(path)
    return False


def reader_options(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.io.read_clouds` for `args.input`."""
    from gpomap.io import detect_format

    fmt = detect_format(args.input)
    opts: dict[str, Any] = {"poses": args.poses, "max_range": args.max_range}
    given = {k: getattr(args, k) for k in ("points_frame", "stride", "depth_scale") if getattr(args, k) is not None}
    takes = {"pcd": ("points_frame",), "pcd-directory": ("points_frame",), "depth-directory": ("stride", "depth_scale")}
    wrong = [k for k in given if k not in takes.get(fmt, ())]
    if wrong:
        names = ", ".join("--" + k.replace("_", "-") for k in wrong)
        raise GpomapError(f"{names}: not an option of {fmt} input ({args.input})")
    opts.update(given)
    if fmt in ("rosbag1", "rosbag2"):
        opts.update(topic=args.topic, fixed_frame=args.fixed_frame, time_offset=args.time_offset)
        if args.odom_topic is not None:
            raise GpomapError(f"--odom-topic is for LaserScan bags; {args.input} holds PointCloud2: give the poses on /tf")
    return opts


# --------------------------------------------------------------------------- reading and selecting
def select_clouds(
    clouds: Sequence[CloudScan],
    scan_range: tuple[int | None, int | None] | None = None,
    n_scans: int | None = None,
    n_rays: int | None = None,
    source: str = "input",
) -> list[CloudScan]:
    """A window of consecutive clouds, thinned to `n_scans` evenly spaced clouds of `n_rays` evenly spaced rays.

    Parameters
    ----------
    clouds : sequence of CloudScan
    scan_range : (first, last), optional
        Python slice bounds (last excluded; None open).
    n_scans, n_rays : int, optional
        Keep this many clouds / rays per cloud (all when there are fewer).
    source : str
        The input's name, for the message.

    Returns
    -------
    list of CloudScan

    Raises
    ------
    GpomapError
        The window selects no cloud.
    """
    out = list(clouds)
    if scan_range is not None:
        first, last = scan_range
        out = out[slice(first, last)]
        if not out:
            raise GpomapError(f"--range {first}:{last} selects no scans from {source}, which has {len(clouds)} scans")
    if n_scans is not None and n_scans < len(out):
        out = [out[i] for i in np.linspace(0, len(out) - 1, n_scans).round().astype(int)]
    if n_rays is not None:
        out = [_thin(c, n_rays) for c in out]
    return out


def _thin(cloud: CloudScan, n_rays: int) -> CloudScan:
    """`cloud` with `n_rays` evenly spaced rays (itself when it has no more)."""
    if cloud.n_points <= n_rays:
        return cloud
    keep = np.linspace(0, cloud.n_points - 1, n_rays).round().astype(int)
    hit = np.asarray(cloud.hit, dtype=bool)
    return CloudScan(cloud.origin, cloud.points[keep], hit[keep], cloud.max_range, cloud.time, dict(cloud.meta))


def load_clouds(args: argparse.Namespace) -> list[CloudScan]:
    """Read and select the clouds of ``args.input`` as ``gpomap map`` does.

    Raises
    ------
    GpomapError
        What the reader refuses, a window selecting nothing, clouds without a valid ray.
    """
    from gpomap.io import read_clouds

    clouds = read_clouds(args.input, **reader_options(args))
    if not clouds:
        raise GpomapError(f"{args.input}: holds no 3-D scans")
    clouds = select_clouds(clouds, args.scan_range, args.scans, args.beams, args.input)
    if not any(c.valid().any() for c in clouds):
        raise GpomapError(f"{args.input}: no valid ray in {len(clouds)} scans (every point non-finite or at its sensor)")
    return clouds


# --------------------------------------------------------------------------- the model
def voxel_bounds(
    points: NDArray[np.float64],
    extent: tuple[float, float, float, float] | None,
    z_range: tuple[float, float] | None,
    resolution: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lower and upper corners (x, y, z), shape (3,) each, of the written voxel map.

    The observation points' bounding box grown by :data:`gpomap.lattice.EXTENT_MARGIN_CELLS`
    voxels of side `resolution` on every side (as a planar map's default extent: a surface hit on
    the box's edge reaches into the voxel past it), with x and y from `extent` and z from
    `z_range` where given, as they are.
    """
    from gpomap.lattice import EXTENT_MARGIN_CELLS

    pad = EXTENT_MARGIN_CELLS * float(resolution)
    lo = np.asarray(points, dtype=float).min(axis=0) - pad
    hi = np.asarray(points, dtype=float).max(axis=0) + pad
    if extent is not None:
        lo[:2], hi[:2] = (extent[0], extent[2]), (extent[1], extent[3])
    if z_range is not None:
        lo[2], hi[2] = z_range
    return lo, hi


def tile_options(args: argparse.Namespace) -> dict[str, Any]:
    """:class:`~gpomap.tiles.TiledGPOM` arguments from the tiling options (:class:`~gpomap.config.TilingConfig`)."""
    from gpomap import cli

    return cli._tiling_config(args).kwargs()


def build_model(
    clouds: Sequence[CloudScan], tile_options: dict[str, Any] | None = None, **model_options: Any
) -> tuple[Any, Any, Any]:
    """The unfitted 3-D model for `clouds` (local GPs in x, y columns of tiles), with what the checks need.

    Parameters
    ----------
    clouds : sequence of CloudScan
    tile_options : dict, optional
        Tiling arguments of :class:`~gpomap.mapping.AreaGPOM` (tile_size, n_workers, ...).
    **model_options
        Its map settings (:class:`~gpomap.settings.MapSettings`).

    Returns
    -------
    model : AreaGPOM
    observations : Observations
        The labelled points of the clouds (for the extent and the memory checks).
    cells : Cells
        The cell tree over them, as one block (for the memory checks; the fit cuts it per tile).
    """
    from gpomap.mapping import AreaGPOM
    from gpomap.settings import MapSettings

    settings = MapSettings(**model_options)
    obs = settings.make_observations(list(clouds))
    return AreaGPOM(**(tile_options or {}), **model_options), obs, settings.make_cells(obs)


def apply_3d_defaults(args: argparse.Namespace) -> None:
    """Put :data:`DEFAULTS_3D` in place of the library defaults (2-D-measured) the user left unset."""
    for name, value in DEFAULTS_3D.items():
        if name in getattr(args, "library_defaults", ()):
            setattr(args, name, value)


def model_from_args(args: argparse.Namespace, clouds: Sequence[CloudScan]) -> tuple[Any, Any, Any]:
    """:func:`build_model` with the options of a parsed ``gpomap map`` command line."""
    from gpomap import cli

    return build_model(clouds, cli._tiling_config(args).kwargs(), **cli._map_config(args).kwargs())


def default_model(clouds: Sequence[CloudScan], **overrides: Any) -> tuple[Any, float]:
    """The unfitted model ``gpomap map CLOUDS -o OUT`` builds with its defaults, and its resolution.

    Parameters
    ----------
    clouds : sequence of CloudScan
    **overrides
        Namespace values replacing the defaults (``min_cell=1.0``, ``kernel="se"``, ``workers=1``).

    Returns
    -------
    model : AreaGPOM
    resolution : float
        The voxel side ``gpomap map`` writes, metres.
    """
    from gpomap import cli

    args = cli.build_parser().parse_args(["map", "clouds", "-o", "out"])
    cli._resolve_library_defaults(args)
    apply_3d_defaults(args)
    for name, value in overrides.items():
        if not hasattr(args, name):
            raise ValueError(f"gpomap map has no option {name!r}")
        setattr(args, name, value)
    return model_from_args(args, clouds)[0], float(args.resolution)


# --------------------------------------------------------------------------- the command
def check_2d_options(args: argparse.Namespace) -> None:
    """Refuse the 3-D reading and output options on a 2-D input (they would be ignored silently)."""
    for name in ("poses", "points_frame", "stride", "depth_scale", "z_range", "slices"):
        if getattr(args, name, None) is not None:
            option = "--" + name.replace("_", "-")
            raise GpomapError(f"{option} is for 3-D inputs (point clouds, depth frames); {args.input} holds 2-D data")


def _check_options(args: argparse.Namespace) -> None:
    for name, (option, why) in _TWO_D_ONLY.items():
        if getattr(args, name, None) is not None:
            raise GpomapError(f"{option} is for 2-D inputs ({why}); {args.input} holds 3-D scans")


def check_voxel_memory(args: argparse.Namespace, lo: NDArray[np.float64], hi: NDArray[np.float64], n_cells: int) -> None:
    """Refuse a voxel map between corners `lo` and `hi` at ``--resolution`` that needs more than ``--memory-limit``."""
    from gpomap import cli
    from gpomap.resources import check_memory, memory_limit, voxel_grid_memory, voxel_shape

    limit, source = memory_limit(args.memory_limit)
    nz, ny, nx = voxel_shape(lo, hi, args.resolution)
    origin = "--extent / --z-range" if args.extent is not None or args.z_range is not None else "the data's extent"
    what = (
        f"a {nx} x {ny} x {nz} voxel grid ({nx * ny * nz:.3g} voxels) at --resolution {args.resolution:g} m over "
        f"x {lo[0]:.6g}..{hi[0]:.6g}, y {lo[1]:.6g}..{hi[1]:.6g}, z {lo[2]:.6g}..{hi[2]:.6g} m ({origin})"
    )
    advice = cli._GRID_ADVICE.replace("--extent", "--extent / --z-range")
    check_memory(voxel_grid_memory((nz, ny, nx), n_cells), limit, what, advice, source)


def _plan(args: argparse.Namespace, clouds: Sequence[CloudScan]) -> tuple[Any, NDArray[np.float64], NDArray[np.float64], int]:
    """The model, the voxel map's corners and the cell count, with the memory checked before fitting."""
    from gpomap.resources import largest_tile_cells
    from gpomap.tiles import DEFAULT_TILE_SIZE, tile_reach

    model, obs, cells = model_from_args(args, clouds)
    lo, hi = voxel_bounds(obs.points, args.extent, args.z_range, args.resolution)
    check_voxel_memory(args, lo, hi, 0)
    # The fit refuses tiles too large for the memory itself, once its cells exist; the voxel
    # grid's prediction chunks are sized by the largest column too.
    tile = args.tile_size if args.tile_size is not None else DEFAULT_TILE_SIZE[3]
    per_tile = largest_tile_cells(0.5 * (cells.lower + cells.upper)[:, :2], tile, tile_reach(tile, model.length_scale))
    check_voxel_memory(args, lo, hi, per_tile)
    return model, lo, hi, len(cells)


def cmd_map3d(args: argparse.Namespace) -> int:
    """Run ``gpomap map`` on a 3-D input (the output directory is checked already)."""
    from gpomap import cli
    from gpomap.diagnostics import hyperparameter_source
    from gpomap.io.voxel_outputs import write_voxel_outputs
    from gpomap.lattice import bounds_extent

    _check_options(args)
    apply_3d_defaults(args)
    cli._status(args, f"reading 3-D scans from {args.input}...")
    clouds = load_clouds(args)
    n_rays = sum(c.n_points for c in clouds)
    cli._status(args, f"  {len(clouds)} scans, {n_rays} rays")
    model, lo, hi, n_cells = _plan(args, clouds)
    cli._status(args, f"fitting MSK-GPOM in 3-D ({args.kernel}, about {n_cells} cells)...")
    t = time.perf_counter()
    model.fit(clouds)
    fit_s = time.perf_counter() - t
    cli._status(args, f"  fitted in {fit_s:.2f} s; predicting voxels of {args.resolution:g} m...")
    t = time.perf_counter()
    voxel_map = model.grid(args.resolution, bounds_extent(lo, hi))
    grid_s = time.perf_counter() - t
    nz, ny, nx = voxel_map.spec.shape
    cli._status(args, f"  {nx} x {ny} x {nz} voxels in {grid_s:.2f} s; writing {args.output}/")
    cli._Run.outdir = args.output  # for a true message if interrupted while writing
    t = time.perf_counter()
    from gpomap.io.mapfile import save_fitted_map

    files = write_voxel_outputs(
        voxel_map,
        args.output,
        heights=args.slices,
        title=f"gpomap: {Path(args.input).name}",
        save_model=functools.partial(save_fitted_map, model),
    )
    write_s = time.perf_counter() - t
    cli._report_fit(model, voxel_map)
    summary = model.summary()
    source = hyperparameter_source(model)
    cli._print_map_summary(summary, [], source if source.startswith("at bound") else None)
    print(_voxel_line(voxel_map, grid_s, write_s))
    print("\n".join(f"wrote        {f}" for f in files))
    return cli.EXIT_OK


def _voxel_line(voxel_map: Any, grid_s: float, write_s: float) -> str:
    from gpomap.grid import FREE, OCCUPIED

    t = voxel_map.ternary
    nz, ny, nx = voxel_map.spec.shape
    n_occ, n_free = int((t == OCCUPIED).sum()), int((t == FREE).sum())
    seen_occ = int(((t == OCCUPIED) & voxel_map.seen).sum())
    return (
        f"voxels       {nx} x {ny} x {nz} of {voxel_map.spec.resolution:g} m: {n_occ} occupied ({seen_occ} where rays went; "
        f"map.bt and map.ply hold only those), {n_free} free, {t.size - n_occ - n_free} unknown; "
        f"predicted in {grid_s:.2f} s, written in {write_s:.2f} s"
    )
