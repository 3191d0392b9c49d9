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
signature is the fields of :class:`~gpomap.config.EstimatorConfig`, derived here, not written again.

The same estimator maps in 3-D: fitted on point clouds (:class:`~gpomap.clouds.CloudScan`), the
rays give 3-D points, the cells are cuboids, the tiles x, y columns, queries are (m, 3) points and
``grid`` returns a :class:`~gpomap.voxels.VoxelMap`:

    >>> from gpomap.io import read_clouds
    >>> clouds = read_clouds("../shared/data/la3dm-sim/sim_structured", max_range=8.0)  # doctest: +SKIP
    >>> voxels = AreaGPOM(kernel="se").fit(clouds).grid(resolution=0.1)  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable
from typing import Any, Concatenate, ParamSpec, TypeVar

from gpomap.config import EstimatorConfig, MapConfig, TilingConfig
from gpomap.tiles import TiledGPOM

#: The tiling arguments of :class:`AreaGPOM`: those :class:`~gpomap.tiles.TiledGPOM` names.
TILING_PARAMETERS = tuple(f.name for f in dataclasses.fields(TilingConfig))
#: The map settings of :class:`AreaGPOM`, in the order :class:`~gpomap.settings.MapSettings` keeps them.
_SETTINGS = tuple(f.name for f in dataclasses.fields(MapConfig))

_P = ParamSpec("_P")
_S = TypeVar("_S")


def _signature_of(
    config: Callable[_P, EstimatorConfig],
) -> Callable[[Callable[[_S, EstimatorConfig], None]], Callable[Concatenate[_S, _P], None]]:
    """An ``__init__`` whose parameters are the fields of `config`, a frozen dataclass: the decorated
    function is handed the arguments bound into one config, defaults applied.

    A type checker reads the parameters from the dataclass's own ``__init__`` (the ParamSpec), and
    ``inspect``, ``help`` and scikit-learn from ``__signature__``; so the names, types and defaults
    are written once, as the config's fields. (A dataclass estimator inheriting the fields cannot
    be: the config is frozen, the estimator is not.)
    """
    fields = inspect.signature(config, eval_str=True)
    self = inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY)
    signature = fields.replace(parameters=[self, *fields.parameters.values()], return_annotation=None)

    def decorate(configure: Callable[[_S, EstimatorConfig], None]) -> Callable[Concatenate[_S, _P], None]:
        def __init__(self: _S, /, *args: _P.args, **kwargs: _P.kwargs) -> None:
            try:
                bound = fields.bind(*args, **kwargs)
            except TypeError as exc:  # named as Python names a plain __init__'s wrong arguments
                raise TypeError(f"{configure.__qualname__}() {exc}") from None
            configure(self, config(*bound.args, **bound.kwargs))

        for name in ("__module__", "__name__", "__qualname__", "__doc__"):
            setattr(__init__, name, getattr(configure, name))
        __init__.__signature__ = signature  # type: ignore[attr-defined]
        return __init__

    return decorate


def _same(given: Any, kept: Any) -> bool:
    """Whether `kept` (a parameter as TiledGPOM stores it) is `given` to the type and the value:
    then the estimator keeps the object it was given."""
    if type(given) is not type(kept):
        return False
    if isinstance(given, tuple):
        return len(given) == len(kept) and all(_same(g, k) for g, k in zip(given, kept))
    return bool(given == kept)


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

    @_signature_of(EstimatorConfig)
    def __init__(self, params: EstimatorConfig) -> None:
        """Keep the arguments (the fields of :class:`~gpomap.config.EstimatorConfig`); nothing is fitted."""
        self._configure(params.kwargs())

    def _configure(self, params: dict[str, Any]) -> None:
        tiling = {n: params[n] for n in TILING_PARAMETERS}
        TiledGPOM.__init__(self, **tiling, **{n: params[n] for n in _SETTINGS})
        # TiledGPOM stores some arguments converted (an origin as a new tuple of floats); an argument
        # it stores unchanged in type and value is kept as the object given, as scikit-learn's
        # clone asks (the parameter it hands over is the one read back).
        for name, given in tiling.items():
            if getattr(self, name) is not given and _same(given, getattr(self, name)):
                setattr(self, name, given)

    def __repr__(self) -> str:
        defaults = EstimatorConfig().kwargs()
        changed = [f"{n}={v!r}" for n, v in self.get_params().items() if repr(v) != repr(defaults[n])]
        return f"AreaGPOM({', '.join(changed)})"

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
