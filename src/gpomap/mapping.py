"""MSK-GPOM: the multi-support GP occupancy map, as one scikit-learn style estimator.

    >>> from gpomap.simulate import paper_room_scans
    >>> model = AreaGPOM(kernel="se").fit(paper_room_scans())
    >>> occupancy_map = model.grid(resolution=0.5)

``fit`` runs the pipeline: beams to free and occupied points, points to cells (a cell tree per
tile square), hyperparameters learnt once on a compact sample of cells, one GP with an area kernel
per tile, blended without seams, and the ray counts on top (:mod:`gpomap.fusion`). A map whose data
fall in one tile square is one GP over its cells. Afterwards the map can be asked anywhere:
``predict_proba(points)``, ``predict(points, return_var=True)`` for the latent GP, or
``grid(resolution, extent)``.

:class:`AreaGPOM` is the local-GP engine :class:`~gpomap.tiles.TiledGPOM` with every setting
named in its signature (``get_params`` / ``set_params``), one worker process by default (like
scikit-learn's ``n_jobs``), and no other code path: a room and a building are mapped alike.

The same estimator maps in 3-D: fitted on point clouds (:class:`~gpomap.clouds.CloudScan`), the
rays give 3-D points, the cells are cuboids, the tiles x, y columns, queries are (m, 3) points and
``grid`` returns a :class:`~gpomap.voxels.VoxelMap`:

    >>> from gpomap.io import read_clouds
    >>> clouds = read_clouds("../shared/data/la3dm-sim/sim_structured", max_range=8.0)  # doctest: +SKIP
    >>> voxels = AreaGPOM(kernel="se").fit(clouds).grid(resolution=0.1)  # doctest: +SKIP
"""

from __future__ import annotations

import inspect
from typing import Any

from gpomap.config import DEFAULT_SCHEDULER_TIMEOUT, MapConfig, TilingConfig
from gpomap.tiles import TiledGPOM

#: The tiling arguments of :class:`AreaGPOM`: those :class:`~gpomap.tiles.TiledGPOM` names.
TILING_PARAMETERS = tuple(p for p in inspect.signature(TiledGPOM.__init__).parameters if p not in ("self", "options"))


class AreaGPOM(TiledGPOM):
    """Continuous occupancy mapping with local GPs over cells (MSK-GPOM).

    Parameters
    ----------
    kernel, area, normalisation, free_step, hit_margin, no_return_cap, free_clearance, min_cell, max_cell, cell_box
        The points and the cells: see :class:`~gpomap.settings.MapSettings`, which says what each
        does and why its default was chosen.
    variance, length_scale, noise, length_scale_bounds, noise_bounds, noise_model, quadrature_order
        The GP (:class:`~gpomap.settings.MapSettings`).
    objective, optimise, n_restarts, hyper_subset, prior_std, class_weight, seed
        How its hyperparameters are learnt (:class:`~gpomap.settings.MapSettings`).
    thresholds, chunk_size, ray_evidence, evidence_resolution, calibration_scans, evidence_resolution_3d, fit_surprise_rate, fit_revisit
        The map on top of the GP (:class:`~gpomap.settings.MapSettings`).
    tile_size, overlap, blend, origin, scheduler, hyper_sample, per_tile_hyperparameters, blas_threads, scheduler_timeout, worker_processes
        The local GPs: see :class:`~gpomap.tiles.TiledGPOM`.
    n_workers : int or None
        Local workers for the tiles (threads of this process, or processes with
        ``worker_processes``); 1 (default) runs them in this process, None uses every core.
    """

    def __init__(
        self,
        kernel: str = MapConfig.kernel,
        area: str | None = MapConfig.area,
        normalisation: str = MapConfig.normalisation,
        free_step: float = MapConfig.free_step,
        hit_margin: float | None = MapConfig.hit_margin,
        no_return_cap: float | None = MapConfig.no_return_cap,
        free_clearance: float = MapConfig.free_clearance,
        min_cell: float | None = MapConfig.min_cell,
        max_cell: float | None = MapConfig.max_cell,
        cell_box: str = MapConfig.cell_box,
        variance: float = MapConfig.variance,
        length_scale: float = MapConfig.length_scale,
        noise: float = MapConfig.noise,
        length_scale_bounds: tuple[float, float] = MapConfig.length_scale_bounds,
        noise_bounds: tuple[float, float] = MapConfig.noise_bounds,
        noise_model: str = MapConfig.noise_model,
        objective: str = MapConfig.objective,
        optimise: bool = MapConfig.optimise,
        n_restarts: int = MapConfig.n_restarts,
        hyper_subset: int | None = MapConfig.hyper_subset,
        prior_std: float | None = MapConfig.prior_std,
        class_weight: str | None = MapConfig.class_weight,
        seed: int = MapConfig.seed,
        quadrature_order: int = MapConfig.quadrature_order,
        thresholds: tuple[float, float] | None = MapConfig.thresholds,
        chunk_size: int = MapConfig.chunk_size,
        ray_evidence: bool = MapConfig.ray_evidence,
        evidence_resolution: float = MapConfig.evidence_resolution,
        calibration_scans: int = MapConfig.calibration_scans,
        evidence_resolution_3d: float = MapConfig.evidence_resolution_3d,
        fit_surprise_rate: bool = MapConfig.fit_surprise_rate,
        fit_revisit: bool = MapConfig.fit_revisit,
        tile_size: float | None = TilingConfig.tile_size,
        overlap: float | None = None,
        blend: float | None = None,
        origin: tuple[float, float] | None = None,
        n_workers: int | None = 1,
        scheduler: Any = None,
        hyper_sample: int | None = None,
        per_tile_hyperparameters: bool = False,
        blas_threads: int | None = None,
        scheduler_timeout: float = DEFAULT_SCHEDULER_TIMEOUT,
        worker_processes: bool = TilingConfig.worker_processes,
        memory_limit: float | None = TilingConfig.memory_limit,
    ) -> None:
        params = {name: value for name, value in locals().items() if name in _PARAMETERS}
        self._configure(params)

    def _configure(self, params: dict[str, Any]) -> None:
        tiling = {n: params[n] for n in TILING_PARAMETERS}
        TiledGPOM.__init__(self, **tiling, **{n: params[n] for n in MapConfig.__dataclass_fields__})

    def __repr__(self) -> str:
        return f"AreaGPOM({self.base!r}, tile_size={self.tile_size})"

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name."""
        return {**self.base.get_params(), **{n: getattr(self, n) for n in TILING_PARAMETERS}}

    def set_params(self, **params: Any) -> AreaGPOM:
        """Set constructor arguments by name (the fitted state, if any, is kept until the next fit); returns self."""
        current = self.get_params()
        unknown = sorted(set(params) - set(current))
        if unknown:
            raise ValueError(f"unknown parameter {unknown[0]!r} for AreaGPOM")
        self._configure({**current, **params})
        return self


_PARAMETERS = frozenset(p for p in inspect.signature(AreaGPOM.__init__).parameters if p != "self")
