"""The options of the model and of its tiles, each defaulting to its :mod:`gpomap.config` field, and the configs they make.

:func:`add_model_options` and :func:`map_config` are the :class:`~gpomap.config.MapConfig` a user
sets (``map``, ``demo``, ``evaluate``, ``stream``); :func:`add_tiling_options` and
:func:`tiling_config` the :class:`~gpomap.config.TilingConfig` of the local GPs (``map``, ``demo``).
"""

from __future__ import annotations

import argparse
import dataclasses

from gpomap.cli.options import Default, non_negative, positive
from gpomap.config import PROFILES, MapConfig, TilingConfig
from gpomap.errors import GpomapError

__all__ = ["add_model_options", "model_option_dests", "map_config", "add_tiling_options", "tiling_config"]


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
        help=f"drop free points closer than M metres to a hit (beams grazing walls; default: {by_profile('free_clearance')}; 0 keeps all)",
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
        help=f"smallest cell side, m (default: {by_profile('min_cell')})",
    )
    g.add_argument(
        "--max-cell",
        type=positive(float),
        default=Default(d.max_cell),
        help=f"largest pure cell side, m (default: {by_profile('max_cell')})",
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


def by_profile(field: str) -> str:
    """A :class:`~gpomap.config.MapProfile` field's planar and voxel defaults, for ``--help``."""
    return f"{getattr(PROFILES[2], field):g} for scans, {getattr(PROFILES[3], field):g} for point clouds"


def _tile_sizes(_: None) -> str:
    """The default tile sides by the data's profile, for ``--help``."""
    return by_profile("tile_size")


def add_tiling_options(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The options of :class:`~gpomap.config.TilingConfig`; returns their group (``gpomap map`` adds ``--chunk-scans`` to it)."""
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
    return g


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
