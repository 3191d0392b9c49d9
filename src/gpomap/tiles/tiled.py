"""TiledGPOM: the tiled map's arguments, and its fit in order.

The stages of the fit run in :meth:`TiledGPOM._fit`, written once: observations, cells,
hyperparameters, variance scale, the later visit's points, the tile fits, the ray evidence; the
later-visit recalibration last. The class puts together the parts of :mod:`gpomap.tiles` (each a
mixin with one job); the stages that fit this map again on other data (the variance scale, the ray
counts' calibration, the later visit) are :mod:`gpomap.tiles.calibration`'s, and ask
:meth:`TiledGPOM._refit`, here since it names the class fitted again.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, ClassVar, Self

from gpomap.config import MapConfig, TiledConfig, TilingConfig
from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.field import as_points
from gpomap.lattice import column_bounds
from gpomap.observations import Observations, ScanData, ScanPoints, data_dim, reading_counts, sensor_positions
from gpomap.resources import POINT_MEMORY, release_freed_memory
from gpomap.scans import Scan
from gpomap.settings import MapSettings
from gpomap.signature import init_from
from gpomap.tiles.blocks import PointFiling
from gpomap.tiles.calibration import CalibrationStages
from gpomap.tiles.executors import _blas_shared
from gpomap.tiles.hyperparameters import HyperparameterSearch, given_hyperparameters
from gpomap.tiles.points import _HeldParts
from gpomap.tiles.refit import Refit
from gpomap.tiles.store import TileStore
from gpomap.tiles.updates import TileUpdates

#: The map settings a TiledGPOM answers as its own attributes (read from its ``base``), in order.
_SETTINGS = tuple(MapConfig.__dataclass_fields__)
_SETTING_NAMES = frozenset(_SETTINGS)
#: The tiling arguments, kept as the model's own attributes.
_TILING = tuple(TilingConfig.__dataclass_fields__)


def _same(given: Any, kept: Any) -> bool:
    """Whether `kept` (an argument as TiledGPOM stores it) is `given` to the type and the value:
    then the model keeps the object it was given."""
    if type(given) is not type(kept):
        return False
    if isinstance(given, tuple):
        return len(given) == len(kept) and all(_same(g, k) for g, k in zip(given, kept))
    return bool(given == kept)


class TiledGPOM(TileUpdates, CalibrationStages, HyperparameterSearch):
    """MSK-GPOM over tiles, for maps larger than one GP can hold.

    Parameters
    ----------
    tile_size : float, optional
        Side of the square tiles, metres; default (``tile_size_`` after the fit)
        :data:`DEFAULT_TILE_SIZE` for the map's dimension. The cell trees are grown per block of
        :data:`BLOCK_SIZE` (of the tiles' side if that is larger), whatever the tiles.
    overlap : float, optional
        Each tile's GP sees the cells meeting its square grown by this much on every side.
        Default :data:`OVERLAP_LENGTH_SCALES` (1.5) learnt length scales, at most the block side
        (:attr:`block_size_`).
    blend : float, optional
        Width of the blending ramp across each tile border, centred on the border; at most
        `overlap` (so a tile only predicts where it has at least ``overlap - blend / 2`` of data
        beyond) and at most `tile_size`. Default :data:`BLEND_FRACTION` of the smaller of the two.
    origin : (float, float), optional
        Corner of tile (0, 0) and of block (0, 0). Default (``origin_``, set by the first fit):
        when the data's x, y extent fits in one tile, that tile centred on them, so a small map
        is one GP over one cell tree instead of being cut into up to four where the map frame's
        origin falls in it; else, when it fits in one block, that block centred on them (one
        cell tree, several tiles); otherwise the map frame's origin. Moving the grid of a larger map only moves its
        borders, and changes the cell trees (each grown from its block's points) at random, and a
        centred grid scored worse on a 3-D case (docs/choices.md, "Measured for the code"). The grid then
        stays fixed, so incremental updates line up with it.
    n_workers : int, optional
        Local workers (threads, or processes with `worker_processes`); 1 runs in this process without a pool; default the CPU count.
    scheduler : str or distributed.Client, optional
        A Dask distributed scheduler address ("tcp://...") or client; tiles then run there. An
        address is connected to at the start of ``fit``, ``update`` and prediction (before the
        local work) and closed at their end; a client given is used as it is and left open.
    scheduler_timeout : float
        Seconds to wait for the scheduler to answer, and for a worker to be connected: when
        none has been for this long while tiles are left, :class:`~gpomap.errors.DistributedError`
        is raised (never a hang). A tile whose worker dies is recomputed on another worker.
    hyper_sample : int, optional
        Most cells of the compact sample hyperparameters are learnt on; default
        :data:`DEFAULT_HYPER_SAMPLE` for the map's dimension.
    per_tile_hyperparameters : bool
        Learn hyperparameters in every tile (each on at most ``hyper_subset`` of its cells).
    blas_threads : int, optional
        BLAS threads per local worker, and of the stages that run in this process; default the
        cores divided among the workers and the BLAS libraries loaded (at least 1,
        :func:`gpomap.lapack.cores_share`), so the map never runs more threads than there are
        cores.
    worker_processes : bool
        Local workers are processes (forked where the platform can: they read their tasks from
        the memory they inherit; a worker that dies is retried) instead of threads of this
        process (the default): processes pay for the factors pickled back from tile fits and
        each stage's fork (docs/choices.md, "Local workers: threads of the process").
    memory_limit : float, optional
        Gigabytes the tile fits may plan to use (default: half of this machine's memory). Once
        the cells are built, before anything costlier, a fit whose largest tile's GP, times the
        GPs fitted at once, would need more raises :class:`~gpomap.resources.MemoryLimitError`
        (see :meth:`check_fit_memory`).
    kernel, area, normalisation, free_step, ..., fit_revisit
        The map settings, :class:`~gpomap.config.MapConfig`'s fields (see
        :class:`~gpomap.settings.MapSettings`, kept as ``base``). ``optimise=False`` keeps the
        given variance, length scale and noise; alpha and beta are then still fitted once on the
        sample.

    Notes
    -----
    The names, order, types and defaults are the fields of :class:`~gpomap.config.TiledConfig`
    (:class:`~gpomap.config.TilingConfig`'s, then :class:`~gpomap.config.MapConfig`'s): the
    signature is derived from them. As in scikit-learn, the arguments are kept as given and read
    back as attributes (``model.tile_size``, ``model.kernel``), ``get_params`` returns them,
    ``set_params`` changes them and ``repr`` shows those that differ from their defaults.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.tiles"

    #: The config whose fields are this class's parameters: its signature, get_params and repr.
    _parameters: ClassVar[type[TilingConfig]] = TiledConfig

    @init_from(TiledConfig)
    def __init__(self, params: TiledConfig) -> None:
        """Keep the arguments (the fields of :class:`~gpomap.config.TiledConfig`); nothing is fitted."""
        self._configure(params)

    def _configure(self, params: TiledConfig) -> None:
        """Check and keep the arguments: the tiling as attributes, the map settings as ``base``."""
        tile_size, scheduler_timeout, memory_limit = params.tile_size, params.scheduler_timeout, params.memory_limit
        if tile_size is not None and not tile_size > 0:
            raise ValueError(f"tile_size must be positive, got {tile_size}")
        self.tile_size = None if tile_size is None else float(tile_size)
        self.overlap = params.overlap
        self.blend = params.blend
        self.origin = None if params.origin is None else (float(params.origin[0]), float(params.origin[1]))
        self.n_workers = params.n_workers
        self.scheduler = params.scheduler
        self.hyper_sample = None if params.hyper_sample is None else int(params.hyper_sample)
        self.per_tile_hyperparameters = bool(params.per_tile_hyperparameters)
        self.blas_threads = None if params.blas_threads is None else int(params.blas_threads)
        self.worker_processes = bool(params.worker_processes)
        if not scheduler_timeout > 0:
            raise ValueError(f"scheduler_timeout must be positive seconds, got {scheduler_timeout}")
        self.scheduler_timeout = float(scheduler_timeout)
        if memory_limit is not None and not memory_limit > 0:
            raise ValueError(f"memory_limit must be positive gigabytes, got {memory_limit}")
        self.memory_limit = None if memory_limit is None else float(memory_limit)
        # An argument stored converted but unchanged in type and value (an origin as a new tuple of
        # floats) is kept as the object given, as scikit-learn's clone asks of the parameters read back.
        for name in _TILING:
            given = getattr(params, name)
            if getattr(self, name) is not given and _same(given, getattr(self, name)):
                setattr(self, name, given)
        self._client = None  # the distributed.Client of the stage running, if any
        # The map's own settings (kernel, cells, evidence).
        settings = {name: getattr(params, name) for name in _SETTINGS}
        self.base = MapSettings(**settings)
        self.options = settings

    def __repr__(self) -> str:
        defaults = self._parameters().kwargs()
        changed = [f"{n}={v!r}" for n, v in self.get_params().items() if repr(v) != repr(defaults[n])]
        return f"{type(self).__name__}({', '.join(changed)})"

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name (the map settings read from ``base``)."""
        return {name: getattr(self, name) for name in self._parameters.__dataclass_fields__}

    def set_params(self, **params: Any) -> Self:
        """Set constructor arguments by name (the fitted state, if any, is kept until the next fit); returns self."""
        current = self.get_params()
        unknown = sorted(set(params) - set(current))
        if unknown:
            raise ValueError(f"unknown parameter {unknown[0]!r} for {type(self).__name__}")
        self._configure(TiledConfig(**{**current, **params}))
        return self

    def __getattr__(self, name: str) -> Any:
        # The map's settings read as the model's own (model.kernel, model.thresholds, ...).
        if name in _SETTING_NAMES and "base" in self.__dict__:
            return getattr(self.__dict__["base"], name)
        if name.endswith("_") and not name.startswith("_") and "tiles_" not in self.__dict__:
            # A fitted attribute (map_, hyperparameters_, ...) asked before fit.
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit() first")
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def make_observations(self, data: ScanData | Observations) -> Observations:
        """The labelled points this map's settings make of `data` (free points near hits dropped); see
        :meth:`gpomap.settings.MapSettings.make_observations`."""
        return self.base.make_observations(data)

    @_blas_shared
    def fit(self, data: ScanData | Observations, hyperparameters: dict[str, float] | None = None) -> TiledGPOM:
        """Build the tiled map from scans (or labelled points).

        Parameters
        ----------
        data : sequence of Scan or CloudScan, or Observations
            Planar scans make a 2-D map; point clouds a 3-D map, tiled in x, y (each tile a
            column spanning every height).
        hyperparameters : dict, optional
            variance, length_scale, noise, alpha and beta to use as they are (no learning).

        Returns
        -------
        self

        Raises
        ------
        DistributedError
            With a `scheduler`: it cannot be reached (checked first, before any local work), or
            it had no workers for `scheduler_timeout` seconds.
        """
        with self._connected():
            return self._fit(data, hyperparameters)

    def _fit(self, data: ScanData | Observations, hyperparameters: dict[str, float] | None) -> TiledGPOM:
        given = None if hyperparameters is None else given_hyperparameters(hyperparameters)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        t = t0
        # No clearance here: it is applied per block (see _observations). Scans' points are made
        # a part at a time and counted, held (in memory, or a temporary file for a large log)
        # until the grid of blocks is known, then filed as they come; never all in memory at once.
        held = _HeldParts(POINT_MEMORY, with_scans=not isinstance(data, Observations))
        filing = PointFiling(self, held)
        source: Observations | ScanPoints | None
        kept = self._kept_points
        if kept is not None and not isinstance(data, Observations) and given is not None and "variance_scale" in given:
            # A map of some of a fitted map's scans: its points are the fitted map's without the others'.
            n_free, n_occupied, n_scans, lower, upper = self._file_kept(kept)
            n_invalid, n_no_return = reading_counts(data)
            source = None
        elif isinstance(data, Observations):
            source = self.base.make_observations(data, clearance=False)
            filing(source)
            n_free, n_occupied, n_scans = source.n_free, source.n_occupied, source.scan_index.max(initial=-1) + 1
            lower, upper = column_bounds(source.points) if source.occupied.size else (None, None)
            n_invalid, n_no_return = source.n_invalid, source.n_no_return
        else:
            b = self.base
            free_cube = b.free_cube(data_dim(data)) if len(data) else None
            source = ScanPoints(data, b.free_step, b.hit_margin, b.no_return_cap, each_part=filing, free_cube=free_cube)
            n_free, n_occupied, n_scans = source.n_free, source.n_occupied, source.n_scans
            lower, upper = source.lower, source.upper
            n_invalid, n_no_return = source.n_invalid, source.n_no_return
        if not isinstance(data, Observations):
            if n_free + n_occupied == 0:
                raise EmptyDataError(f"no usable readings in {len(data)} scan(s) ({n_invalid} invalid): nothing to map")
            if n_occupied == 0 or n_free == 0:
                raise EmptyDataError(f"need both free and occupied observations, got {n_free} free and {n_occupied} occupied")
        if source is not None:
            filing.finish(lower, upper)
        held.close()
        # The clearance applies to points sampled from scans, not to given points.
        self._clearance = 0.0 if isinstance(data, Observations) else self.base.clearance(self._dim)
        self._dirty = set()
        self._n_scans = int(n_scans)
        self._n_invalid, self._n_no_return = n_invalid, n_no_return
        self.path_ = None if isinstance(data, Observations) else sensor_positions(data)
        timings["observations"] = time.perf_counter() - t

        t = time.perf_counter()
        asked = self._asked_tiles(given)
        seen = None if asked is None else {b for tile in asked for b in self._blocks_seen_by(tile)}
        self._build_blocks(None if seen is None else sorted(seen & set(self._block_points)))
        timings["cells"] = time.perf_counter() - t
        start = hyperparameters.get("length_scale") if hyperparameters is not None else None
        self.check_fit_memory(self.base.length_scale if start is None else float(start))

        t = time.perf_counter()
        if given is not None:
            self.hyperparameters_ = given
            self.hyper_source_ = {"how": "given to fit()"}
        else:
            self.hyperparameters_ = self._learn_hyperparameters()
        timings["hyperparameters"] = time.perf_counter() - t
        self._set_geometry()
        t = time.perf_counter()
        self.extrapolation_ = (
            {"kappa": self.hyperparameters_["variance_scale"], "reason": "given to fit()"}
            if "variance_scale" in self.hyperparameters_ or source is None
            else self._fit_variance_scale(data, source)
        )
        self.hyperparameters_["variance_scale"] = float(self.extrapolation_["kappa"])
        timings["variance_scale"] = time.perf_counter() - t
        # The blocks hold every point from here on (a large log's hundreds of megabytes with their
        # labels and scans): labelled points given are let go before the ray counts.
        del source
        release_freed_memory()
        self._scans = None if isinstance(data, Observations) else list(data)

        t = time.perf_counter()
        tiles = [self._decode(k) for k in sorted(self._tiles_with_points)] if asked is None else asked
        jobs, gathered = self._fit_jobs(tiles)
        if asked is not None and len(jobs) < len(asked):
            # A tile asked for gathered no cells: which tile is nearest to a point no tile reaches
            # is then not known from the tiles with points alone; every block and tile after all.
            self._build_blocks([k for k in self._block_points if k not in self._blocks])
            jobs, gathered = self._fit_jobs([self._decode(k) for k in sorted(self._tiles_with_points)])
        self.tiles_ = TileStore()
        if self._tiles_when_asked:
            # A map asked at a few points (the later visit's map of the other stretches): each
            # tile is fitted when a prediction first needs it (:meth:`_fit_waiting`).
            self._waiting = dict(jobs)
        else:
            self._fit_tiles(jobs, "fitting tiles")
        self._signatures = {t: g.signature() for t, g in gathered.items()}
        del jobs, gathered
        release_freed_memory()  # the fits' matrices, most of them gone to the tile store's file
        timings["tile_fits"] = time.perf_counter() - t
        self.timings_ = timings
        t = time.perf_counter()
        self.evidence_ = self._make_evidence()
        release_freed_memory()  # the traversals' temporaries
        timings["evidence"] = time.perf_counter() - t
        # The map of the other stretches takes this map's calibration of the ray counts, so it
        # fits only the tiles the held-out stretches' points need (docs/choices.md, "The map's
        # probabilities for a later visit").
        t = time.perf_counter()
        later = self._later_visit_points()  # with this map's counts set aside while it fits another
        self.revisit_ = self._fit_revisit(later)
        del later
        release_freed_memory()
        timings["revisit"] = time.perf_counter() - t
        timings["total_fit"] = time.perf_counter() - t0
        self.timings_ = timings
        self.last_refit_ = sorted(self.tiles_)
        self._stale = {}
        self._reused = set()  # tiles last fitted reusing covariances
        return self

    def _asked_tiles(self, given: dict[str, float] | None) -> list[tuple[int, int]] | None:
        """The tiles a map asked only at :attr:`_asked_at` will predict them with (the tiles
        holding points, fitted when asked), or None for any other map. The hyperparameters given
        set the tiles' reach, so they are known before any cell is built: only the blocks these
        tiles gather cells from are built."""
        if self._asked_at is None or given is None or not self._tiles_when_asked or not self._tiles_with_points:
            return None
        self.hyperparameters_ = given
        self._set_geometry()
        keys = [self._decode(k) for k in sorted(self._tiles_with_points)]
        members, _ = self._tile_members(self._gp_queries(as_points(self._asked_at, self._dim)), sorted(keys))
        return sorted(members)

    def _refit(self) -> Refit:
        """This map's tiles, settings and hyperparameters so far, to fit again on part of its data
        (:class:`~gpomap.tiles.refit.Refit`), on local workers whatever the scheduler."""
        tiling = {
            "tile_size": self.tile_size_,
            "overlap": self.overlap,
            "blend": self.blend,
            "origin": self.origin_,
            "n_workers": self.n_workers,
            "hyper_sample": self.hyper_sample,
            "blas_threads": self.blas_threads,
            "worker_processes": self.worker_processes,
            "memory_limit": self.memory_limit,
        }
        return Refit(TiledGPOM, tiling, dict(self.options), dict(self.hyperparameters_))

    @_blas_shared
    def update(self, scans: Sequence[Scan]) -> TiledGPOM:
        """Add scans: rebuild the cells of the blocks they touch, refit only the tiles whose cell
        sets changed (hyperparameters kept fixed), and refit the ray evidence's calibration.

        For fixed hyperparameters the result equals ``fit(old + new)`` (cells depend only on their
        own block's points, a tile's GP only on its cell set, and the ray counts add over scans).

        Parameters
        ----------
        scans : sequence of Scan

        Returns
        -------
        self
        """
        with self._connected():
            if not hasattr(self, "tiles_"):
                return self._fit(scans, None)
            self._absorb(scans)
            self._refresh(None, exact=True)
            if self.evidence_ is not None:
                t = time.perf_counter()
                self.evidence_.recalibrate(self._gp_proba_written)
                self.timings_["update_calibration"] = time.perf_counter() - t
            return self
