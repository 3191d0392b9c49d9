"""The options the commands share: argument types, defaults stated once, option groups, and the configs they make.

An option's default is a :class:`Default` naming a config field (:mod:`gpomap.config`) or a
library value; :func:`resolve_library_defaults` puts the values in place after parsing and records
which options were left out, so a command can tell a default from the same value given.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any

from gpomap.config import CALIBRATED_THRESHOLDS, PROFILES, MapConfig, TilingConfig
from gpomap.errors import GpomapError

__all__ = [
    "extent",
    "pair",
    "scan_range",
    "heights",
    "z_range",
    "number",
    "positive",
    "non_negative",
    "Default",
    "signature_default",
    "module_default",
    "resolve_library_defaults",
    "given",
    "flag",
    "add_reader_options",
    "reader_options",
    "add_cloud_reader_options",
    "cloud_reader_options",
    "check_2d_options",
    "add_selection_options",
    "add_model_options",
    "model_option_dests",
    "map_config",
    "add_tiling_options",
    "tiling_config",
    "add_output_options",
    "add_3d_output_options",
    "resolution_from_evidence",
]


# --------------------------------------------------------------------------- argument types
def extent(text: str) -> tuple[float, float, float, float]:
    """``XMIN,XMAX,YMIN,YMAX``: four finite numbers, each minimum below its maximum."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"extent must be XMIN,XMAX,YMIN,YMAX in metres, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"extent must be four finite numbers XMIN,XMAX,YMIN,YMAX, got {text!r}")
    if len(values) != 4 or not (values[0] < values[1] and values[2] < values[3]):
        raise argparse.ArgumentTypeError(f"extent must be XMIN,XMAX,YMIN,YMAX with XMIN<XMAX and YMIN<YMAX, got {text!r}")
    return values[0], values[1], values[2], values[3]


def pair(text: str) -> tuple[float, float]:
    """``FREE,OCCUPIED``: two thresholds with 0 <= FREE <= OCCUPIED <= 1."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers FREE,OCCUPIED, got {text!r}") from None
    # Written out so that nan (for which every comparison is false) is refused too.
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi <= 1):
        raise argparse.ArgumentTypeError(f"thresholds must satisfy 0 <= FREE <= OCCUPIED <= 1, got {text!r}")
    return lo, hi


def scan_range(text: str) -> tuple[int | None, int | None]:
    """``FIRST:LAST``: slice bounds of scan indices, either left out for an open end."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        return tuple(int(p) if p else None for p in parts)  # type: ignore[return-value]
    except ValueError:
        raise argparse.ArgumentTypeError(f"range must be FIRST:LAST (scan indices, LAST excluded), got {text!r}") from None


def heights(text: str) -> tuple[float, ...]:
    """``--slices z1,z2,...``: finite heights in metres."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"slices must be heights Z1,Z2,... in metres, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"slices must be finite heights Z1,Z2,... in metres, got {text!r}")
    return values


def z_range(text: str) -> tuple[float, float]:
    """``--z-range ZMIN,ZMAX`` with ZMIN < ZMAX, finite."""
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"z range must be ZMIN,ZMAX in metres, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise argparse.ArgumentTypeError(f"z range must be two finite numbers ZMIN,ZMAX with ZMIN < ZMAX, got {text!r}")
    return lo, hi


def number(kind: type, low: float | None = None, strict: bool = True) -> Callable[[str], Any]:
    """An argparse type: a finite `kind` (int or float), above `low` (or at least `low` if not `strict`).

    nan and inf are refused: ``float("nan") <= 0`` is false, so a plain sign test lets nan through.
    """
    if low is None:
        expected = "a finite number"
    elif low == 0:
        expected = "a positive number" if strict else "a number >= 0"
    else:
        expected = f"a number {'>' if strict else '>='} {low:g}"
    if kind is int:
        expected = expected.replace("number", "integer")

    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not math.isfinite(v) or (low is not None and (v <= low if strict else v < low)):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v

    return parse


def positive(kind: type) -> Callable[[str], Any]:
    """An argparse type: a finite number > 0."""
    return number(kind, 0.0)


def non_negative(kind: type) -> Callable[[str], Any]:
    """An argparse type: a finite number >= 0."""
    return number(kind, 0.0, strict=False)


# --------------------------------------------------------------------------- defaults
class Default:
    """An option's default, stated in one place: a config field (:mod:`gpomap.config`) or a library module.

    argparse keeps a default that is not a string as it is, so an option still holding a
    ``Default`` after parsing was not given: :func:`resolve_library_defaults` replaces it by its
    value and names it in ``args.library_defaults`` (a 3-D map replaces some of them,
    :func:`gpomap.cli.map3d.apply_3d_defaults`). A default found in a module that imports SciPy
    is looked up only when shown or used (`lookup`), so that ``gpomap --help`` stays fast.

    Parameters
    ----------
    value : object, optional
        The default itself.
    lookup : callable, optional
        Returns the default (instead of `value`).
    show : callable, optional
        Formats the value for ``--help`` (default: ``str``).
    """

    def __init__(self, value: Any = None, lookup: Callable[[], Any] | None = None, show: Callable[[Any], str] = str) -> None:
        self._value, self._lookup, self._show = value, lookup, show

    @property
    def value(self) -> Any:
        """The default's value (looked up now, if it is looked up)."""
        return self._lookup() if self._lookup is not None else self._value

    def __str__(self) -> str:
        return self._show(self.value)


def signature_default(module: str, name: str, parameter: str) -> Default:
    """The default of `parameter` of the function or class `name` in `module`, looked up when needed."""

    def lookup() -> Any:
        return inspect.signature(getattr(importlib.import_module(module), name)).parameters[parameter].default

    return Default(lookup=lookup)


def module_default(module: str, name: str, convert: Callable[[Any], Any] | None = None) -> Default:
    """The constant `name` of `module` (through `convert`, if given), looked up when needed."""

    def lookup() -> Any:
        value = getattr(importlib.import_module(module), name)
        return value if convert is None else convert(value)

    return Default(lookup=lookup)


def resolve_library_defaults(args: argparse.Namespace) -> None:
    """Replace each :class:`Default` by its value; ``args.library_defaults`` names the options left at one."""
    defaulted = {name for name, value in vars(args).items() if isinstance(value, Default)}
    for name in defaulted:
        setattr(args, name, getattr(args, name).value)
    args.library_defaults = frozenset(defaulted)


def given(args: argparse.Namespace, dests: Sequence[str]) -> list[str]:
    """Which of `dests` the command line set (a default is a :class:`Default` or None)."""
    return [d for d in dests if d not in args.library_defaults and getattr(args, d) is not None]


def flag(dest: str) -> str:
    """The command-line spelling of the option stored as `dest`."""
    return {
        "ray_evidence": "--no-ray-evidence",
        "fit_revisit": "--no-revisit",
        "scan_range": "--range",
        "test_points": "--test-points",
    }.get(dest, "--" + dest.replace("_", "-"))


# --------------------------------------------------------------------------- reading and selecting
def add_reader_options(p: argparse.ArgumentParser) -> None:
    """The options of the planar readers (CARMEN logs, ROS bags)."""
    g = p.add_argument_group("reading the input")
    g.add_argument(
        "--angles",
        choices=["gmapping", "linspace"],
        default=signature_default("gpomap.io.carmen", "read_carmen", "angles"),
        help="CARMEN FLASER beam-angle convention (default: %(default)s)",
    )
    g.add_argument("--max-range", type=positive(float), help="sensor max range in metres (readings at or above it are no-return)")
    g.add_argument("--topic", help="ROS bag: sensor_msgs/LaserScan topic (default: the only one)")
    g.add_argument("--fixed-frame", help="ROS bag: fixed frame of the poses, from /tf (default: odom)")
    g.add_argument("--odom-topic", help="ROS bag: take poses from this nav_msgs/Odometry topic instead of /tf")
    g.add_argument(
        "--time-offset",
        type=number(float),
        default=signature_default("gpomap.io.rosbag", "read_rosbag", "time_offset"),
        help="ROS bag: seconds added to scan stamps before the pose lookup (default: %(default)s)",
    )


def reader_options(args: argparse.Namespace, path: str) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.io.read_scans` for the planar input `path`."""
    from gpomap.io import detect_format

    fmt = detect_format(path)
    if fmt == "carmen":
        opts: dict[str, Any] = {"angles": args.angles}
    else:
        opts = {
            "topic": args.topic,
            "fixed_frame": args.fixed_frame,
            "odom_topic": args.odom_topic,
            "time_offset": args.time_offset,
        }
    if args.max_range is not None:
        opts["max_range"] = args.max_range
    return opts


def add_cloud_reader_options(p: argparse.ArgumentParser) -> None:
    """The reading options of 3-D inputs (``map``, ``info`` and ``update`` take them alike)."""
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
        "--stride", type=positive(int), metavar="K", help="depth frames: every K-th pixel along both image axes (default: 1)"
    )
    g.add_argument(
        "--depth-scale",
        type=positive(float),
        metavar="UNITS",
        help="depth frames: depth units per metre (default: 1000, millimetres; TUM: 5000)",
    )


def cloud_reader_options(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.io.read_clouds` for ``args.input``.

    Raises
    ------
    GpomapError
        A 3-D reading option the input's format does not take, or ``--odom-topic`` on a bag.
    """
    from gpomap.io import detect_format

    fmt = detect_format(args.input)
    opts: dict[str, Any] = {"poses": args.poses, "max_range": args.max_range}
    set_here = {k: getattr(args, k) for k in ("points_frame", "stride", "depth_scale") if getattr(args, k) is not None}
    takes = {"pcd": ("points_frame",), "pcd-directory": ("points_frame",), "depth-directory": ("stride", "depth_scale")}
    wrong = [k for k in set_here if k not in takes.get(fmt, ())]
    if wrong:
        names = ", ".join("--" + k.replace("_", "-") for k in wrong)
        raise GpomapError(f"{names}: not an option of {fmt} input ({args.input})")
    opts.update(set_here)
    if fmt in ("rosbag1", "rosbag2"):
        opts.update(topic=args.topic, fixed_frame=args.fixed_frame, time_offset=args.time_offset)
        if args.odom_topic is not None:
            raise GpomapError(f"--odom-topic is for LaserScan bags; {args.input} holds PointCloud2: give the poses on /tf")
    return opts


def check_2d_options(args: argparse.Namespace) -> None:
    """Refuse the 3-D reading and output options on a 2-D input (they would be ignored silently)."""
    for name in ("poses", "points_frame", "stride", "depth_scale", "z_range", "slices"):
        if getattr(args, name, None) is not None:
            option = "--" + name.replace("_", "-")
            raise GpomapError(f"{option} is for 3-D inputs (point clouds, depth frames); {args.input} holds 2-D data")


def add_selection_options(p: argparse.ArgumentParser) -> None:
    """``--range``, ``--scans`` and ``--beams``: which scans and beams of the input are used."""
    g = p.add_argument_group("selecting data")
    g.add_argument(
        "--range",
        dest="scan_range",
        type=scan_range,
        metavar="FIRST:LAST",
        help="use only this window of consecutive scans (LAST excluded)",
    )
    g.add_argument("--scans", type=positive(int), metavar="N", help="thin to N evenly spaced scans")
    g.add_argument("--beams", type=positive(int), metavar="M", help="keep M evenly spaced beams per scan")


# --------------------------------------------------------------------------- the model
def add_model_options(p: argparse.ArgumentParser) -> None:
    """The options of :class:`~gpomap.config.MapConfig` a user sets, each defaulting to its field (:func:`map_config`)."""
    d = MapConfig()
    g = p.add_argument_group("the model")
    g.add_argument("--kernel", choices=["matern32", "se"], default=Default(d.kernel), help="point kernel (default: %(default)s)")
    g.add_argument(
        "--area",
        choices=["exact", "quadrature", "summed"],
        default=d.area,
        help="area-kernel computation (default: exact for se, quadrature for matern32)",
    )
    g.add_argument(
        "--normalisation",
        choices=["mean", "sum"],
        default=Default(d.normalisation),
        help="area-kernel normalisation (default: %(default)s)",
    )
    g.add_argument(
        "--objective",
        choices=["loo", "lml"],
        default=Default(d.objective),
        help="hyperparameter objective (default: %(default)s)",
    )
    g.add_argument(
        "--class-weight",
        choices=["balanced", "none"],
        default=Default(d.class_weight, show=lambda v: str(v).lower()),
        help="weigh free and occupied cells equally in the leave-one-out fit, or each cell once (default: %(default)s)",
    )
    g.add_argument(
        "--free-step",
        type=positive(float),
        default=Default(d.free_step),
        help="free-point spacing along beams, m (default: %(default)s)",
    )
    g.add_argument(
        "--free-clearance",
        type=non_negative(float),
        default=Default(d.free_clearance),
        metavar="M",
        help="drop free points closer than M metres to a hit (beams grazing walls; default: %(default)s; 0 keeps all)",
    )
    g.add_argument(
        "--no-return-cap",
        type=non_negative(float),
        default=Default(d.no_return_cap),
        metavar="M",
        help="free points along no-return beams reach M metres (default: %(default)s; 0 ignores such beams)",
    )
    g.add_argument(
        "--min-cell",
        type=positive(float),
        default=Default(d.min_cell),
        help=f"smallest cell side, m (default: {PROFILES[2].min_cell:g} for scans, {PROFILES[3].min_cell:g} for point clouds)",
    )
    g.add_argument(
        "--max-cell",
        type=positive(float),
        default=Default(d.max_cell),
        help=f"largest pure cell side, m (default: {PROFILES[2].max_cell:g} for scans, {PROFILES[3].max_cell:g} for point clouds)",
    )
    g.add_argument(
        "--length-scale",
        type=positive(float),
        help=f"fix the length scale (m) instead of learning it (default: learnt, from {d.length_scale:g})",
    )
    g.add_argument("--seed", type=int, default=Default(d.seed), help="seed of restarts and samples (default: %(default)s)")
    g.add_argument(
        "--no-ray-evidence",
        dest="ray_evidence",
        action="store_false",
        default=Default(d.ray_evidence),
        help="the GP alone, without each fine cell's hit and miss counts on top (see gpomap.fusion)",
    )
    g.add_argument(
        "--evidence-resolution",
        type=positive(float),
        default=Default(d.evidence_resolution),
        metavar="M",
        help="fine cells whose ray counts update exact-point predictions, m (default: %(default)s; a written map counts on its own cells)",
    )
    g.add_argument(
        "--fit-surprise-rate",
        action="store_true",
        default=Default(d.fit_surprise_rate),
        help="fit the share of surprises (visitors where scans saw free space) on the log's own scans instead "
        "of the prior 0.01, its floor: for logs with crowds; refits the GP once more (planar scans)",
    )
    g.add_argument(
        "--no-revisit",
        dest="fit_revisit",
        action="store_false",
        default=Default(d.fit_revisit),
        help="keep the probabilities as the log's own scans, held out one at a time, calibrate them, without "
        "the recalibration for a later visit fitted on a held-out stretch (saves fitting the map a second time "
        "on 70 %% of the scans; see gpomap.revisit)",
    )


def model_option_dests() -> tuple[str, ...]:
    """The dests of :func:`add_model_options`."""
    p = argparse.ArgumentParser(add_help=False)
    add_model_options(p)
    return tuple(a.dest for a in p._actions)


def map_config(args: argparse.Namespace) -> MapConfig:
    """The :class:`~gpomap.config.MapConfig` of the parsed options: each field from the option of its name, if any.

    Two options are not their field: ``--class-weight none`` is None, and ``--length-scale``
    fixes the length scale (``optimise=False``) rather than setting where the search starts.
    Fields without an option (and options left out, as ``--length-scale`` by default) keep
    the config's default.

    Raises
    ------
    GpomapError
        ``--min-cell`` above ``--max-cell``.
    """
    fields = {f.name: getattr(args, f.name) for f in dataclasses.fields(MapConfig) if hasattr(args, f.name)}
    if "class_weight" in fields:
        fields["class_weight"] = None if fields["class_weight"] == "none" else fields["class_weight"]
    if fields.get("length_scale") is not None:
        fields["optimise"] = False
    else:
        fields.pop("length_scale", None)
    # Also checked before any work (check_before_work); here for callers that set the values (default_model).
    if fields.get("min_cell") is not None and fields.get("max_cell") is not None and fields["min_cell"] > fields["max_cell"]:
        raise GpomapError(f"--min-cell ({fields['min_cell']}) must not exceed --max-cell ({fields['max_cell']})")
    return MapConfig(**fields)


def _tile_sizes(_: None) -> str:
    """The default tile sides by the data's profile, for ``--help``."""
    return f"{PROFILES[2].tile_size:g} for scans, {PROFILES[3].tile_size:g} for point clouds"


def add_tiling_options(p: argparse.ArgumentParser, chunks: bool = True) -> None:
    """The options of :class:`~gpomap.config.TilingConfig` (and ``--chunk-scans`` with `chunks`)."""
    g = p.add_argument_group("the local GPs (one per tile, blended without seams)")
    g.add_argument(
        "--tile-size",
        type=positive(float),
        default=Default(TilingConfig.tile_size, show=_tile_sizes),
        help="tile side, m (default: %(default)s)",
    )
    g.add_argument("--workers", type=positive(int), help="local workers for tiles (default: the CPU count)")
    g.add_argument(
        "--processes",
        action="store_true",
        default=Default(TilingConfig.worker_processes),
        help="run the workers as processes, so that one that dies is retried (default: threads of this process)",
    )
    g.add_argument(
        "--threads",
        type=positive(int),
        metavar="N",
        help="BLAS threads of each tile worker and of the map's stages in this process (default: the cores "
        "divided by the workers and by the BLAS libraries loaded, at least 1)",
    )
    g.add_argument("--scheduler", metavar="ADDRESS", help="run tiles on this Dask distributed scheduler (tcp://host:port)")
    g.add_argument(
        "--scheduler-timeout",
        type=positive(float),
        default=Default(TilingConfig.scheduler_timeout),
        metavar="SECONDS",
        help="give up when the scheduler does not answer, or has no workers, for this long (default: %(default)s)",
    )
    if not chunks:
        return
    g.add_argument(
        "--chunk-scans",
        type=positive(int),
        metavar="K",
        help="map incrementally, K scans at a time, rewriting the map after each chunk",
    )


def tiling_config(args: argparse.Namespace) -> TilingConfig:
    """The :class:`~gpomap.config.TilingConfig` of the tiling options (``--workers`` is ``n_workers``, ``--threads`` ``blas_threads``)."""
    return TilingConfig(
        tile_size=args.tile_size,
        n_workers=args.workers,
        blas_threads=args.threads,
        worker_processes=args.processes,
        scheduler=args.scheduler,
        scheduler_timeout=args.scheduler_timeout,
        memory_limit=args.memory_limit,
    )


# --------------------------------------------------------------------------- the written map
def add_output_options(p: argparse.ArgumentParser, default_resolution: Any) -> None:
    """The written map's options: the directory, its cells and region, thresholds, image and memory limit."""
    g = p.add_argument_group("the output")
    g.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="directory for map.yaml, map.pgm, map.npz, map.png")
    g.add_argument(
        "--resolution",
        type=positive(float),
        default=default_resolution,
        help="grid cell side of the written map, m" + (" (default: %(default)s)" if default_resolution else ""),
    )
    g.add_argument("--extent", type=extent, metavar="XMIN,XMAX,YMIN,YMAX", help="region of the written map (default: the data's)")
    g.add_argument(
        "--thresholds",
        type=pair,
        default=Default(MapConfig.thresholds, show=lambda _: f"{CALIBRATED_THRESHOLDS[0]:g},{CALIBRATED_THRESHOLDS[1]:g}"),
        metavar="FREE,OCCUPIED",
        help="ternary-map thresholds on the map's calibrated probabilities (default: %(default)s: occupied where "
        "more likely than not, free below map_server's free threshold)",
    )
    g.add_argument(
        "--pgm-mode",
        choices=["trinary", "scale"],
        default="trinary",
        help="map_server image: ternary map or probability grey levels (default: %(default)s)",
    )
    g.add_argument(
        "--memory-limit",
        type=positive(float),
        metavar="GB",
        help="refuse, before fitting, a run estimated to need more memory than this (default: half of this machine's)",
    )


def add_3d_output_options(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """``--z-range`` and ``--slices``: the 3-D output options of ``map``, ``convert``, ``render`` and ``update``; returns their group."""
    g = p.add_argument_group("3-D maps (point clouds, depth frames, OctoMap trees)")
    g.add_argument(
        "--z-range",
        type=z_range,
        metavar="ZMIN,ZMAX",
        help="heights of the written voxel map, m (with --extent for x and y; default: the data's)",
    )
    g.add_argument(
        "--slices",
        type=heights,
        metavar="Z1,Z2,...",
        help="heights of the horizontal slices in map-slices.png, m (default: four spread over the map)",
    )
    return g


def resolution_from_evidence(args: argparse.Namespace) -> None:
    """A 2-D written map's cell, when not given: the ray counts' (``--evidence-resolution``, given or not)."""
    if "resolution" in getattr(args, "library_defaults", ()):
        args.resolution = args.evidence_resolution
