"""Every default of a map, stated once: typed, frozen settings for the model and the tiling.

:class:`MapConfig` holds the map settings of :class:`~gpomap.mapping.AreaGPOM` (and of
:class:`~gpomap.settings.MapSettings`, which builds from them), :class:`TilingConfig` its tiling
arguments (those of :class:`~gpomap.tiles.TiledGPOM`), and :class:`EstimatorConfig` and
:class:`TiledConfig` both: their fields are the parameters of AreaGPOM and of TiledGPOM, whose
signatures are derived from them (:func:`gpomap.signature.init_from`) and written nowhere else.
The ``gpomap`` command builds its options from these fields (their defaults are the options'
defaults, shown in ``--help``) and builds one config from the parsed options; the library receives
it as keyword arguments (:meth:`MapConfig.kwargs`), so a script and the command build the same
model:

    >>> config = MapConfig(kernel="se", free_step=0.1)
    >>> config.free_step, config.max_cell, PROFILES[2].max_cell
    (0.1, None, 0.5)
    >>> from gpomap.mapping import AreaGPOM
    >>> model = AreaGPOM(**config.kwargs())  # doctest: +SKIP

Why each value was chosen is said where it is used (the parameters of
:class:`~gpomap.settings.MapSettings` and :class:`~gpomap.tiles.TiledGPOM`).

This module imports no SciPy and no model: ``gpomap --help`` reads it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Self

from gpomap.grid import CALIBRATED_THRESHOLDS, DEFAULT_THRESHOLDS

__all__ = [
    "MapConfig",
    "TilingConfig",
    "EstimatorConfig",
    "TiledConfig",
    "DEFAULT_MAX_CELLS",
    "DEFAULT_SCHEDULER_TIMEOUT",
    "CALIBRATED_THRESHOLDS",
    "DEFAULT_THRESHOLDS",
    "VOXEL_MAP_DEFAULTS",
    "MapProfile",
    "PROFILES",
]

#: Most cells of the one GP of a grid or octree conversion (``gpomap convert --max-cells``; maps
#: from scans are local GPs in tiles whatever their size): a dense GP of this size factorises in
#: about a second, and its cost grows with the cube (docs/choices.md, "Measured for the code").
DEFAULT_MAX_CELLS = 3000

#: Seconds to wait for a Dask scheduler to answer, and for workers when none is connected
#: (``gpomap map --scheduler-timeout``).
DEFAULT_SCHEDULER_TIMEOUT = 60.0


@dataclass(frozen=True)
class MapProfile:
    """The defaults that differ between planar maps and voxel maps, applied by the library from the
    data's dimension wherever a setting is left unset (None), and the stages each kind of map runs.

    Each stage reads its own field from :data:`PROFILES` (its module names it, e.g.
    :data:`gpomap.tiles.DEFAULT_TILE_SIZE`); why each value was chosen is said there and in
    docs/choices.md.

    Attributes
    ----------
    min_cell, max_cell : float
        The cell tree's size thresholds, metres (:class:`MapConfig`).
    free_clearance : float
        Free points closer than this to a hit are dropped, metres (:class:`MapConfig`).
    merge_free : bool
        A scan of many free samples (:data:`gpomap.observations.MERGE_MIN_SAMPLES`, a depth
        frame's) has those in one cube of half the free step merged into one point that stands
        for them all (:func:`gpomap.observations.merged_ray_free_points`).
    resolution : float
        The side of the written map's cells, metres (``gpomap map --resolution``).
    tile_size : float
        The side of a tile's square (a column in 3-D), metres (:class:`TilingConfig`).
    hyper_sample : int
        Most cells of the compact sample the hyperparameters are learnt on.
    hyper_group_cells : int or None
        Most cells of each group the hyperparameter search cuts its sample into (None: one GP).
    unseen_resolution : float
        Cell side on which "no kept beam went" is decided for the variance scale, metres.
    fit_surface_weight : bool
        The ray counts' calibration weighs a miss beside a surface apart.
    surprise_rate_fitted : bool
        The surprise rate can be fitted on the map's own scans (when ``fit_surprise_rate`` asks).
    seen_through_not_occupied : bool
        The ternary map never calls occupied a cell no beam ended in.
    fit_revisit : bool
        The map is recalibrated for a later visit (when ``fit_revisit`` asks).
    fit_variance_scale : bool
        The GP's variance where no beam went is scaled by a factor fitted on held-out stretches
        (otherwise the GP's own).
    """

    min_cell: float
    max_cell: float
    free_clearance: float
    merge_free: bool
    resolution: float
    tile_size: float
    hyper_sample: int
    hyper_group_cells: int | None
    unseen_resolution: float
    fit_surface_weight: bool
    surprise_rate_fitted: bool
    seen_through_not_occupied: bool
    fit_revisit: bool
    fit_variance_scale: bool


#: The profile of each data dimension. Planar maps: 0.5 m cells (docs/choices.md, "Measured on more
#: logs") written on the ray counts' 0.05 m cells. Voxel maps: cells of 1 m, since a cube holds 8
#: times as many cells per volume at half the side where a square holds 4, for no gain across the
#: 3-D cases of ``benchmarks/quality3d.py`` (docs/3d.md, "3-D defaults"); voxels of 0.1 m, OctoMap's
#: usual. Free points are kept from 0.1 m of a hit in a plane, where the ray counts draw the walls
#: (docs/choices.md, "Free clearance: 0.1 m in a plane"), and from 0.3 m in 3-D, where a scan's free
#: samples sharing a cube are merged: a depth camera's rays crowd near the sensor, and the cells
#: need only how many samples each holds (docs/3d.md, "Free samples merged by cube"). The calibration
#: stages that were measured only on planar logs are off for voxel maps, and so is the variance
#: scale: fitted on a few frames' held-out stretches it cost ranking on every 3-D case (docs/3d.md,
#: "The variance scale switched off").
PROFILES: dict[int, MapProfile] = {
    2: MapProfile(
        min_cell=0.5,
        max_cell=0.5,
        free_clearance=0.1,
        merge_free=False,
        resolution=0.05,
        tile_size=5.0,
        hyper_sample=800,
        hyper_group_cells=200,
        unseen_resolution=0.05,
        fit_surface_weight=True,
        surprise_rate_fitted=True,
        seen_through_not_occupied=True,
        fit_revisit=True,
        fit_variance_scale=True,
    ),
    3: MapProfile(
        min_cell=1.0,
        max_cell=1.0,
        free_clearance=0.3,
        merge_free=True,
        resolution=0.1,
        tile_size=3.0,
        hyper_sample=300,
        hyper_group_cells=None,
        unseen_resolution=0.1,
        fit_surface_weight=False,
        surprise_rate_fitted=False,
        seen_through_not_occupied=False,
        fit_revisit=False,
        fit_variance_scale=False,
    ),
}

#: The voxel maps' profile as the options it sets (``gpomap map`` on point clouds, the ROS 2 node).
VOXEL_MAP_DEFAULTS: dict[str, float] = {
    "min_cell": PROFILES[3].min_cell,
    "max_cell": PROFILES[3].max_cell,
    "resolution": PROFILES[3].resolution,
}


class _Config:
    """What the configs share: keyword arguments for the library, and copies with changes."""

    def kwargs(self) -> dict[str, Any]:
        """The fields as keyword arguments of the class this config describes, by name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    def replace(self, **changes: Any) -> Self:
        """A copy with `changes` (field names) applied; unknown names raise a TypeError."""
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


@dataclass(frozen=True)
class MapConfig(_Config):
    """The settings of one MSK-GPOM map: the arguments of :class:`~gpomap.settings.MapSettings`.

    The fields, their order and their meaning are MapSettings' (see its parameters); the kernel
    first, then grouped as the pipeline runs: beams to points, points to cells, cells to a GP, the
    GP to a map. They are the first parameters of :class:`~gpomap.mapping.AreaGPOM`, in this order
    (:class:`EstimatorConfig`). A field left None that :class:`MapProfile` holds takes the profile
    of the data's dimension (:data:`PROFILES`) when the map is fitted, so a planar log and point
    clouds each get theirs.
    """

    # the kernel first (the estimator's first positional arguments), then as the pipeline runs
    kernel: str = "matern32"
    area: str | None = None
    normalisation: str = "mean"
    # the points: beams to free points and hits
    free_step: float = 0.2
    hit_margin: float | None = None
    no_return_cap: float | None = 10.0
    free_clearance: float | None = None
    # the cells
    min_cell: float | None = None
    max_cell: float | None = None
    cell_box: str = "node"
    # the GP's hyperparameters
    variance: float = 1.0
    length_scale: float = 1.0
    noise: float = 0.1
    length_scale_bounds: tuple[float, float] = (0.05, 20.0)
    noise_bounds: tuple[float, float] = (1e-4, 10.0)
    noise_model: str = "per_count"
    objective: str = "loo"
    optimise: bool = True
    n_restarts: int = 0
    hyper_subset: int | None = 300
    prior_std: float | None = 1.0
    class_weight: str | None = "balanced"
    seed: int = 0
    quadrature_order: int = 2
    # the map: thresholds, prediction chunks, the ray counts on top of the GP
    thresholds: tuple[float, float] | None = None
    chunk_size: int = 4096
    ray_evidence: bool = True
    evidence_resolution: float = 0.05
    calibration_scans: int = 25
    evidence_resolution_3d: float = 0.1
    fit_surprise_rate: bool = False
    fit_revisit: bool = True


@dataclass(frozen=True)
class TilingConfig(_Config):
    """How a map is split into local GPs: the arguments of :class:`~gpomap.tiles.TiledGPOM` other
    than the map settings, in the order of its signature (why each default was chosen is said there).

    Attributes
    ----------
    tile_size : float, optional
        Side of the square tiles, metres (default: 5 m for planar maps, 3 m for voxel maps,
        :data:`gpomap.tiles.DEFAULT_TILE_SIZE`).
    overlap : float, optional
        How far past its square each tile's GP sees, metres (default: 1.5 learnt length scales,
        :data:`gpomap.tiles.OVERLAP_LENGTH_SCALES`, at most the block side).
    blend : float, optional
        Width of the blending ramp across each tile border, metres (default: half the smaller of
        the overlap and the tile side, :data:`gpomap.tiles.BLEND_FRACTION`).
    origin : (float, float), optional
        Corner of tile (0, 0) and of block (0, 0) (default: set by the first fit from the data).
    n_workers : int, optional
        Local workers (default: the CPU count).
    scheduler : str or distributed.Client, optional
        Address of a Dask distributed scheduler that runs the tiles instead, or a client of one.
    hyper_sample : int, optional
        Most cells of the compact sample the hyperparameters are learnt on (default: the data's
        profile, :attr:`MapProfile.hyper_sample`).
    per_tile_hyperparameters : bool
        Learn hyperparameters in every tile instead of once for the map.
    blas_threads : int, optional
        BLAS threads of each worker and of the map's stages in this process (default: the cores
        divided by the workers and by the BLAS libraries loaded, at least 1).
    scheduler_timeout : float
        Seconds to wait for the scheduler, and for its workers.
    worker_processes : bool
        Run the local workers as processes (a worker that dies, killed for its memory say, is
        retried) instead of threads of this process (the default: the tiles' factors are not
        copied to and from workers, and the GP's compiled and BLAS work runs without the GIL).
    memory_limit : float, optional
        Gigabytes the fit may plan to use: once the cells are built, before the hyperparameters
        and the tiles, a fit whose largest tile's GP times the GPs fitted at once would need more
        is refused (default: half of this machine's memory,
        :data:`gpomap.resources.DEFAULT_MEMORY_FRACTION`).
    """

    tile_size: float | None = None
    overlap: float | None = None
    blend: float | None = None
    origin: tuple[float, float] | None = None
    n_workers: int | None = None
    # A distributed.Client is taken as well as an address; this module imports no Dask to name it.
    scheduler: Any = None
    hyper_sample: int | None = None
    per_tile_hyperparameters: bool = False
    blas_threads: int | None = None
    scheduler_timeout: float = DEFAULT_SCHEDULER_TIMEOUT
    worker_processes: bool = False
    memory_limit: float | None = None


@dataclass(frozen=True)
class TiledConfig(MapConfig, TilingConfig):
    """The parameters of :class:`~gpomap.tiles.TiledGPOM`: :class:`TilingConfig`'s fields (the
    first positional arguments, the tile side first), then :class:`MapConfig`'s, defaults
    unchanged. Its signature is these fields (derived by :func:`gpomap.signature.init_from`, so a
    type checker, ``help`` and ``get_params`` read the same names, types and defaults).
    """


@dataclass(frozen=True)
class EstimatorConfig(TilingConfig, MapConfig):
    """The parameters of :class:`~gpomap.mapping.AreaGPOM`: :class:`MapConfig`'s fields (the kernel
    first), then :class:`TilingConfig`'s. The estimator's signature is these fields (derived by
    :func:`gpomap.signature.init_from`, so a type checker, ``help`` and ``get_params`` read the
    same names, types and defaults), and one default is the estimator's own:

    Attributes
    ----------
    n_workers : int or None
        1: the estimator runs its tiles in this process unless told, like scikit-learn's
        ``n_jobs`` (None uses every core, the ``gpomap`` command's default).
    """

    n_workers: int | None = 1
