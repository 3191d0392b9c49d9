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
scikit-learn's ``n_jobs``), and no other code path: a room and a building are mapped alike. Its
signature is the fields of :class:`~gpomap.config.EstimatorConfig` (the kernel first), derived by
:func:`gpomap.signature.init_from` as TiledGPOM's is, not written again.

The same estimator maps in 3-D: fitted on point clouds (:class:`~gpomap.clouds.CloudScan`), the
rays give 3-D points, the cells are cuboids, the tiles x, y columns, queries are (m, 3) points and
``grid`` returns a :class:`~gpomap.voxels.VoxelMap`:

    >>> from gpomap.io import read_clouds
    >>> clouds = read_clouds("../shared/data/la3dm-sim/sim_structured", max_range=8.0)  # doctest: +SKIP
    >>> voxels = AreaGPOM(kernel="se").fit(clouds).grid(resolution=0.1)  # doctest: +SKIP
"""

from __future__ import annotations

from gpomap.config import EstimatorConfig, TiledConfig
from gpomap.signature import init_from
from gpomap.tiles import TiledGPOM


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
    tile_size, overlap, blend, origin, scheduler, hyper_sample, per_tile_hyperparameters, blas_threads, scheduler_timeout, worker_processes, memory_limit
        The local GPs: see :class:`~gpomap.tiles.TiledGPOM`.
    n_workers : int or None
        Local workers for the tiles (threads of this process, or processes with
        ``worker_processes``); 1 (default) runs them in this process, None uses every core.

    Notes
    -----
    The names, types and defaults are the fields of :class:`~gpomap.config.EstimatorConfig`
    (:class:`~gpomap.config.MapConfig`'s, then :class:`~gpomap.config.TilingConfig`'s): the
    signature is derived from them. As in scikit-learn, the arguments are kept as given and read
    back as attributes (``model.kernel``, ``model.tile_size``), ``get_params`` returns them,
    ``set_params`` changes them and ``repr`` shows those that differ from their defaults.
    """

    _parameters = EstimatorConfig

    @init_from(EstimatorConfig)
    def __init__(self, params: EstimatorConfig) -> None:
        """Keep the arguments (the fields of :class:`~gpomap.config.EstimatorConfig`); nothing is fitted."""
        self._configure(TiledConfig(**params.kwargs()))
