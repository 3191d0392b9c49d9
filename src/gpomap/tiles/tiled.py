"""TiledGPOM: the tiled map (see :mod:`gpomap.tiles`)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import math
import multiprocessing
import os
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, MutableMapping, Sequence
from contextlib import contextmanager
from dataclasses import fields
from typing import Any, Concatenate, Literal, ParamSpec, TypeVar, overload

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from gpomap.cells import build_cells
from gpomap.config import DEFAULT_SCHEDULER_TIMEOUT, MapConfig, TilingConfig
from gpomap.errors import DistributedError, EmptyDataError, GpomapError, NotFittedError
from gpomap.estimator import as_points
from gpomap.fusion import EvidenceLayer, ternary_thresholds
from gpomap.grid import GridSpec, OccupancyMap, row_bands, ternary
from gpomap.kernels.point import make_point_kernel
from gpomap.lapack import available_cores, blas_limited, cores_share
from gpomap.lattice import column_bounds, data_extent, stable_order
from gpomap.observations import Observations, ScanData, ScanPoints, observations_from_scans, sensor_positions
from gpomap.progress import Progress, progress
from gpomap.resources import POINT_MEMORY, WRITTEN_BAND_CELLS, SpillFile, peak_rss_mb, release_freed_memory
from gpomap.scans import Scan
from gpomap.settings import MapSettings
from gpomap.squash import unseen_probit
from gpomap.supports import Supports
from gpomap.tiles.blending import nearest_box, taper
from gpomap.tiles.executors import _INHERITED, _collect, _few_queries, _inherited_task, _worker_init
from gpomap.tiles.geometry import (
    _KEY_BASE,
    _KEY_CHUNK,
    _KEY_OFFSET,
    BLEND_FRACTION,
    DEFAULT_TILE_SIZE,
    _box_offset,
    block_side,
    tile_reach,
)
from gpomap.tiles.hyperparameters import (
    DEFAULT_HYPER_SAMPLE,
    HYPER_GROUP_CELLS,
    HYPER_NAMES,
    given_hyperparameters,
    hyper_anchor_block,
)
from gpomap.tiles.points import _BlockCells, _BlockPoints, _HeldParts, _SpilledPart
from gpomap.tiles.store import TileStore, light_tiles
from gpomap.tiles.tasks import TileCells, TileFitTask, TileSettings, TileState, fit_tile_task, predict_tile_task

#: The map settings a TiledGPOM answers as its own attributes (read from its ``base``).
_SETTING_NAMES = frozenset(MapConfig.__dataclass_fields__)

_Tiled = TypeVar("_Tiled", bound="TiledGPOM")
_P = ParamSpec("_P")
_R = TypeVar("_R")
#: A stage's tasks (each tile's key and its task's arguments), where their results go, and what
#: a runner gives back: the results and each failed task's exception (:meth:`TiledGPOM._run`).
_Jobs = list[tuple[tuple[int, int], tuple[Any, ...]]]
_Results = MutableMapping[tuple[int, int], Any]
_Outcome = tuple[_Results, Mapping[tuple[int, int], BaseException]]


def _blas_shared(method: Callable[Concatenate[_Tiled, _P], _R]) -> Callable[Concatenate[_Tiled, _P], _R]:
    """Run a :class:`TiledGPOM` stage with this process's BLAS held to one worker's share of the
    cores (:meth:`TiledGPOM._workers_and_threads`), as its workers' is: the stages that run here
    (the hyperparameter search, the variance scale, the ray evidence, small predictions) would
    otherwise take every core in each BLAS library while workers or the other library spin on
    them (see :func:`gpomap.lapack.blas_libraries`)."""

    @functools.wraps(method)
    def shared(self: _Tiled, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with blas_limited(self._workers_and_threads(self.n_workers_)[1]):
            return method(self, *args, **kwargs)

    return shared


def _check_scheduler_address(addr: str) -> None:
    """Refuse a Dask scheduler address whose scheme no Dask transport knows, before a client is made:
    a client built on one fails half-made, and its clean-up waits two minutes on exit."""
    from distributed.comm import parse_address
    from distributed.comm.registry import get_backend

    try:
        get_backend(parse_address(addr)[0])
    except ValueError as e:
        raise DistributedError(f"Dask scheduler address {addr!r}: {e}; expected e.g. tcp://HOST:8786") from None


class TiledGPOM:
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
    **options
        :class:`~gpomap.settings.MapSettings` options (kernel, free_step, min_cell, max_cell,
        length_scale, noise, optimise, ...). ``optimise=False`` keeps the given variance,
        length scale and noise; alpha and beta are then still fitted once on the sample.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.tiles"

    #: Fit each tile when a prediction first needs it (set on a map asked at a few points only).
    _tiles_when_asked: bool = False
    # Set by fit: the observation points per block, their cell trees, and the points' extent.
    _block_points: dict[int, _BlockPoints]
    _blocks: dict[int, _BlockCells]
    _tiles_with_points: set[int]
    tile_size_: float
    _lower: NDArray[np.float64] | None
    _upper: NDArray[np.float64] | None
    _n_points: int
    _n_occupied_points: int

    def __init__(
        self,
        tile_size: float | None = TilingConfig.tile_size,
        overlap: float | None = None,
        blend: float | None = None,
        origin: tuple[float, float] | None = None,
        n_workers: int | None = None,
        scheduler: Any = None,
        hyper_sample: int | None = None,
        per_tile_hyperparameters: bool = False,
        blas_threads: int | None = None,
        scheduler_timeout: float = DEFAULT_SCHEDULER_TIMEOUT,
        worker_processes: bool = TilingConfig.worker_processes,
        memory_limit: float | None = TilingConfig.memory_limit,
        **options: Any,
    ) -> None:
        if tile_size is not None and not tile_size > 0:
            raise ValueError(f"tile_size must be positive, got {tile_size}")
        self.tile_size = None if tile_size is None else float(tile_size)
        self.overlap = overlap
        self.blend = blend
        self.origin = None if origin is None else (float(origin[0]), float(origin[1]))
        self.n_workers = n_workers
        self.scheduler = scheduler
        self.hyper_sample = None if hyper_sample is None else int(hyper_sample)
        self.per_tile_hyperparameters = bool(per_tile_hyperparameters)
        self.blas_threads = None if blas_threads is None else int(blas_threads)
        self.worker_processes = bool(worker_processes)
        if not scheduler_timeout > 0:
            raise ValueError(f"scheduler_timeout must be positive seconds, got {scheduler_timeout}")
        self.scheduler_timeout = float(scheduler_timeout)
        if memory_limit is not None and not memory_limit > 0:
            raise ValueError(f"memory_limit must be positive gigabytes, got {memory_limit}")
        self.memory_limit = None if memory_limit is None else float(memory_limit)
        self._client: Any = None  # the distributed.Client of the stage running, if any
        # The map's own settings (kernel, cells, evidence), with their defaults.
        self.base = MapSettings(**options)
        self.options = dict(options)

    def __repr__(self) -> str:
        return f"TiledGPOM(tile_size={self.tile_size}, overlap={self.overlap}, {self.base!r})"

    def __getattr__(self, name: str) -> Any:
        # The map's settings read as the model's own (model.kernel, model.thresholds, ...).
        if name in _SETTING_NAMES and "base" in self.__dict__:
            return getattr(self.__dict__["base"], name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _settings(self) -> TileSettings:
        b = self.base
        # Every field but these two is the map setting of the same name.
        same = {f.name: getattr(b, f.name) for f in fields(TileSettings) if f.name not in ("area", "per_tile")}
        return TileSettings(area=b.area_method, per_tile=self.per_tile_hyperparameters, **same)

    @property
    def n_workers_(self) -> int:
        """Local workers used."""
        return int(self.n_workers) if self.n_workers is not None else max(1, os.cpu_count() or 1)

    @property
    def block_size_(self) -> float:
        """Side of the blocks that get their own cell tree: :data:`BLOCK_SIZE`, or the tiles' if larger."""
        return block_side(self.tile_size_)

    def _block_keys(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        return self._square_keys(points, self.block_size_)

    def _square_keys(self, points: NDArray[np.float64], side: float) -> NDArray[np.int64]:
        # Tiles and blocks are squares in x, y; in 3-D they are columns spanning every height.
        # By chunks: a whole log's temporaries would be several copies of its points.
        keys = np.empty(points.shape[0], dtype=np.int64)
        for s in range(0, points.shape[0], _KEY_CHUNK):
            ij = self._square_indices(points[s : s + _KEY_CHUNK], side)
            keys[s : s + _KEY_CHUNK] = self._encode(ij[:, 0], ij[:, 1])
        return keys

    def _square_indices(self, points: NDArray[np.float64], side: float) -> NDArray[np.int64]:
        """Integer (ix, iy) of the square of `side` on the tile grid's origin holding each point, shape (n, 2)."""
        return np.floor((points[:, :2] - np.asarray(self.origin_)) / side).astype(np.int64)

    def _present_keys(self, points: NDArray[np.float64], side: float) -> NDArray[np.int64]:
        """The keys of the squares of `side` holding any of `points`, sorted: ``np.unique`` of their
        :meth:`_square_keys`, found by counting over the squares' index box instead of sorting."""
        if points.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        ij = self._square_indices(points, side)
        lo, hi = column_bounds(ij)
        span = hi - lo + 1
        if int(span[0]) * int(span[1]) > max(4 * points.shape[0], 1 << 16):
            # A few points spread very wide: sorting them is cheaper than counting the box.
            return np.unique(self._encode(ij[:, 0], ij[:, 1]))
        # Row-major over (ix, iy), the order of the keys.
        flat = np.flatnonzero(np.bincount(_box_offset(ij, lo, span), minlength=int(span.prod())))
        return self._encode(flat // span[1] + lo[0], flat % span[1] + lo[1])

    def _meeting(self, lo: tuple[float, float], hi: tuple[float, float], side: float) -> Iterator[tuple[int, int]]:
        """Indices of the squares of `side` on the tile grid's origin that meet the closed box [lo, hi] in x, y."""
        ox, oy = self.origin_
        xs = range(math.ceil((lo[0] - ox) / side) - 1, math.floor((hi[0] - ox) / side) + 1)
        ys = range(math.ceil((lo[1] - oy) / side) - 1, math.floor((hi[1] - oy) / side) + 1)
        return ((ix, iy) for ix in xs for iy in ys)

    def _grown(self, square: tuple[float, float, float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
        """A square (x0, x1, y0, y1) grown by the overlap on every side, as its corners (lo, hi): a
        tile's GP sees the cells meeting its grown square."""
        x0, x1, y0, y1 = square
        o = self.overlap_
        return (x0 - o, y0 - o), (x1 + o, y1 + o)

    def _default_origin(self, lower: NDArray[np.float64] | None, upper: NDArray[np.float64] | None) -> tuple[float, float]:
        """Corner of tile (0, 0) and block (0, 0) for points within `lower`..`upper` (d,): one tile
        centred on them if their x, y extent fits in one, else one block centred on them if it
        fits in one (one cell tree), else the map frame's origin (also without points: None)."""
        if lower is None or upper is None:
            return (0.0, 0.0)
        lo, hi = np.asarray(lower)[:2], np.asarray(upper)[:2]
        for side in (self.tile_size_, self.block_size_):
            if np.all(hi - lo < side):
                corner = 0.5 * (lo + hi) - 0.5 * side
                return float(corner[0]), float(corner[1])
        return (0.0, 0.0)

    @overload
    @staticmethod
    def _decode(key: int) -> tuple[int, int]: ...

    @overload
    @staticmethod
    def _decode(key: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]: ...

    @staticmethod
    def _decode(key: Any) -> Any:
        """Square (ix, iy) of a key, or the index arrays of an array of keys (:meth:`_encode`'s inverse)."""
        ix, iy = key // _KEY_BASE - _KEY_OFFSET, key % _KEY_BASE - _KEY_OFFSET
        return (ix, iy) if isinstance(key, np.ndarray) else (int(ix), int(iy))

    @overload
    @staticmethod
    def _encode(ix: int, iy: int) -> int: ...

    @overload
    @staticmethod
    def _encode(ix: NDArray[np.int64], iy: NDArray[np.int64]) -> NDArray[np.int64]: ...

    @staticmethod
    def _encode(ix: Any, iy: Any) -> Any:
        """The key of square (ix, iy), or of each pair of index arrays."""
        return (ix + _KEY_OFFSET) * _KEY_BASE + (iy + _KEY_OFFSET)

    def _core(self, key: tuple[int, int]) -> tuple[float, float, float, float]:
        return self._square(key, self.tile_size_)

    def _square(self, index: tuple[int, int], side: float) -> tuple[float, float, float, float]:
        """Bounds (x0, x1, y0, y1) of square `index` of `side` on the tile grid's origin (a tile or a block)."""
        x0 = self.origin_[0] + index[0] * side
        y0 = self.origin_[1] + index[1] * side
        return x0, x0 + side, y0, y0 + side

    def _build_block(self, key: int) -> _BlockCells:
        b = self.base
        block = self._block_points[key]
        points, occupied = block.arrays()
        keep = ~block.free_near_hits(self._clearance, (points, occupied))
        c = build_cells(points[keep], occupied[keep], b.min_cell, b.max_cell, b.cell_box)
        summed = b.area_method == "summed"
        return _BlockCells(
            lower=c.lower,
            upper=c.upper,
            counts=c.counts.astype(float),
            occupied=c.occupied,
            n_ambiguous=int(c.ambiguous.sum()),
            member_points=c.points[c.member_order] if summed else None,
            member_offsets=c.member_offsets if summed else None,
        )

    def _add_points(self, points: NDArray[np.float64], occupied: NDArray[np.bool_], spill: SpillFile | None = None) -> set[int]:
        """File points under their blocks (in observation order within each) and note their tiles; returns the blocks touched.

        With `spill`, each block's new points wait in that file (:class:`_SpilledPart`) instead of in memory."""
        # Keys per chunk of points, blocks then numbered 0..b-1 in key order: a whole log's int64
        # keys and their sorted copy would be hundreds of megabytes.
        chunks = range(0, points.shape[0], _KEY_CHUNK)
        found = [np.zeros(0, dtype=np.int64)]
        for s in chunks:
            part = points[s : s + _KEY_CHUNK]
            self._tiles_with_points.update(self._present_keys(part, self.tile_size_).tolist())
            found.append(self._present_keys(part, self.block_size_))
        block_keys = np.unique(np.concatenate(found))
        ids = np.empty(points.shape[0], dtype=np.int16 if block_keys.size <= np.iinfo(np.int16).max else np.int32)
        # Each block's id looked up in a table over the blocks' index box (a search per point
        # where that box is too large for a table).
        table = None
        if block_keys.size:
            bxy = np.column_stack(self._decode(block_keys))
            b_lo, b_hi = column_bounds(bxy)
            b_span = b_hi - b_lo + 1
            if int(b_span[0]) * int(b_span[1]) <= _KEY_CHUNK:
                table = np.zeros(int(b_span.prod()), dtype=ids.dtype)
                table[_box_offset(bxy, b_lo, b_span)] = np.arange(block_keys.size)
        for s in chunks:
            part = points[s : s + _KEY_CHUNK]
            if table is None:
                ids[s : s + _KEY_CHUNK] = np.searchsorted(block_keys, self._block_keys(part))
            else:
                ids[s : s + _KEY_CHUNK] = table[_box_offset(self._square_indices(part, self.block_size_), b_lo, b_span)]
        # Stable (a radix sort for 16-bit ids): keeps observation order per block.
        order = np.argsort(ids, kind="stable")
        cuts = np.cumsum(np.bincount(ids, minlength=block_keys.size))[:-1]
        del ids
        touched = set()
        for k, grp in zip(block_keys.tolist(), np.split(order, cuts)):
            if grp.size == 0:
                continue
            filed: Any = _SpilledPart.put(spill, points[grp], occupied[grp]) if spill is not None else points[grp]
            labels = None if spill is not None else occupied[grp]
            if k in self._block_points:
                self._block_points[k].append(filed, labels)
            else:
                self._block_points[k] = _BlockPoints(filed, labels)
            touched.add(k)
        if points.shape[0]:
            lo, hi = column_bounds(points)
            self._lower = lo if self._lower is None else np.minimum(self._lower, lo)
            self._upper = hi if self._upper is None else np.maximum(self._upper, hi)
        self._n_points += int(points.shape[0])
        self._n_occupied_points += int(occupied.sum())
        return touched

    def _build_blocks(self, keys: Sequence[int] | None = None) -> None:
        """(Re)build the cell trees of the given blocks (all when None)."""
        if keys is None:
            self._blocks = {}
            keys = list(self._block_points)
        for k in keys:
            self._blocks[int(k)] = self._build_block(int(k))

    def _blocks_seen_by(self, tile: tuple[int, int]) -> list[int]:
        """Keys of the blocks whose squares meet the tile's grown square (those it gathers cells from)."""
        return [self._encode(*b) for b in self._meeting(*self._grown(self._core(tile)), self.block_size_)]

    def _tiles_seeing(self, block: int) -> list[tuple[int, int]]:
        """The tiles holding points whose grown squares meet the block's square."""
        lo, hi = self._grown(self._square(self._decode(block), self.block_size_))
        return [t for t in self._meeting(lo, hi, self.tile_size_) if self._encode(*t) in self._tiles_with_points]

    def _gather(self, tile: tuple[int, int]) -> TileCells | None:
        """The cells meeting the tile's grown square, in canonical (block key, tree) order."""
        (gx0, gy0), (gx1, gy1) = self._grown(self._core(tile))
        parts = []
        for key in self._blocks_seen_by(tile):
            bc = self._blocks.get(key)
            if bc is None:
                continue
            keep = (bc.lower[:, 0] <= gx1) & (bc.upper[:, 0] >= gx0) & (bc.lower[:, 1] <= gy1) & (bc.upper[:, 1] >= gy0)
            if keep.any():
                parts.append((key, bc, np.flatnonzero(keep)))
        if not parts:
            return None
        parts.sort(key=lambda p: p[0])
        out = TileCells(
            lower=np.concatenate([bc.lower[k] for _, bc, k in parts]),
            upper=np.concatenate([bc.upper[k] for _, bc, k in parts]),
            counts=np.concatenate([bc.counts[k] for _, bc, k in parts]),
            labels=np.concatenate([np.where(bc.occupied[k], 1.0, -1.0) for _, bc, k in parts]),
        )
        if self.base.area_method == "summed":
            sup = [Supports(bc.lower, bc.upper, bc.counts, bc.member_points, bc.member_offsets).subset(k) for _, bc, k in parts]
            from gpomap.supports import concatenate

            s = concatenate(sup)
            out.member_points, out.member_offsets = s.member_points, s.member_offsets
        return out

    def _all_cells(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], list[int]]:
        keys = sorted(self._blocks)
        lo = np.concatenate([self._blocks[k].lower for k in keys])
        hi = np.concatenate([self._blocks[k].upper for k in keys])
        cnt = np.concatenate([self._blocks[k].counts for k in keys])
        lab = np.concatenate([np.where(self._blocks[k].occupied, 1.0, -1.0) for k in keys])
        return lo, hi, cnt, lab, keys

    def _learn_hyperparameters(self) -> dict[str, float]:
        """Learn all five hyperparameters once, on a compact sample round a dense, typical block."""
        b = self.base
        keys = sorted(self._blocks)
        lo, hi, cnt, lab, _ = self._all_cells()
        sizes = np.array([len(self._blocks[k].counts) for k in keys])
        shares = np.array([float(np.mean(self._blocks[k].occupied)) if n else 0.0 for k, n in zip(keys, sizes, strict=True)])
        bc = self._blocks[keys[hyper_anchor_block(sizes, shares, float(np.mean(lab > 0)))]]
        anchor = 0.5 * (bc.lower + bc.upper).mean(axis=0)
        n = lab.size
        k = self.hyper_sample if self.hyper_sample is not None else DEFAULT_HYPER_SAMPLE[self._dim]
        if n <= k:
            idx = np.arange(n)
        else:
            d = np.sum((0.5 * (lo + hi) - anchor) ** 2, axis=1)
            idx = np.sort(np.argpartition(d, k - 1)[:k])
        if b.area_method == "summed":
            blocks = [self._blocks[k] for k in keys]
            from gpomap.supports import concatenate

            X = concatenate([Supports(c.lower, c.upper, c.counts, c.member_points, c.member_offsets) for c in blocks]).subset(idx)
        else:
            X = Supports(lo[idx], hi[idx], cnt[idx])
        # The search runs in this process, its groups on the local workers' cores.
        gp = self._settings().search_gp(
            b.make_kernel(),
            b.noise,
            optimise=b.optimise,
            hyper_subset=None,
            hyper_group=HYPER_GROUP_CELLS[self._dim],
            n_threads=min(self.n_workers_, available_cores()),
        )
        gp.fit(X, lab[idx])
        hyp = {
            "variance": float(gp.kernel.base.variance),
            "length_scale": float(gp.kernel.base.length_scale),
            "noise": float(gp.noise),
            "alpha": float(gp.squash.alpha),
            "beta": float(gp.squash.beta),
        }
        r = np.sqrt(np.max(np.sum((0.5 * (lo[idx] + hi[idx]) - anchor) ** 2, axis=1)))
        self.hyper_source_ = {
            "how": "learnt" if b.optimise else "given (alpha, beta fitted)",
            "sample_cells": int(idx.size),
            "sample_centre": [round(float(anchor[0]), 2), round(float(anchor[1]), 2)],
            "sample_radius_m": round(float(r), 2),
            "sample_occupied_fraction": round(float(np.mean(lab[idx] > 0)), 4),
            "evaluations": gp.fit_report_.n_evaluations if gp.fit_report_ is not None else 0,
            "sample_groups": gp.fit_report_.groups if gp.fit_report_ is not None else 1,
        }
        return hyp

    def _scheduler_address(self) -> str:
        s = self.scheduler
        return str(s) if isinstance(s, str) else str(getattr(getattr(s, "scheduler", None), "address", s))

    @contextmanager
    def _connected(self) -> Iterator[None]:
        """Hold a Dask client for one stage (fit, update, prediction) when a scheduler is set.

        Connecting first, before the stage's local work, makes a wrong or unreachable address fail
        within `scheduler_timeout` instead of after it. Nested stages share the outer client.
        """
        if self.scheduler is None or self._client is not None:
            yield
            return
        try:
            from distributed import Client
        except ImportError as e:
            raise DistributedError(
                "running tiles on a Dask scheduler needs dask distributed: pip install 'gpomap[distributed]'"
            ) from e
        if isinstance(self.scheduler, Client):
            self._client = self.scheduler
            try:
                yield
            finally:
                self._client = None  # the caller's client: theirs to close
            return
        addr = self._scheduler_address()
        _check_scheduler_address(addr)
        try:
            # Never the default client: this one is only ours, passed explicitly everywhere.
            client = Client(addr, timeout=self.scheduler_timeout, set_as_default=False)
        except (OSError, TimeoutError, ValueError, TypeError) as e:
            raise DistributedError(
                f"could not connect to the Dask scheduler at {addr} within {self.scheduler_timeout:g} s "
                f"({type(e).__name__}: {e}); check that a scheduler runs there ('dask scheduler'), or allow "
                "longer with --scheduler-timeout (scheduler_timeout)"
            ) from e
        self._client = client
        try:
            yield
        finally:
            self._client = None
            client.close()

    def _run(
        self,
        fn: Callable[..., Any],
        jobs: list[tuple[tuple[int, int], tuple[Any, ...]]],
        what: str,
        desc: str,
        into: MutableMapping[tuple[int, int], Any] | None = None,
    ) -> MutableMapping[tuple[int, int], Any]:
        """Run ``fn(*args)`` for every (tile, args); each failed task is retried once.

        Parameters
        ----------
        fn : callable
            A top-level (picklable) task function.
        jobs : list of ((ix, iy), args)
        what : str
            The stage, for error messages ("tile fit").
        desc : str
            The stage, for progress ("fitting tiles").
        into : mutable mapping, optional
            Where each result goes as its task finishes (a :class:`TileStore`: a fit's factors
            never all in memory at once); default a new dict.

        Returns
        -------
        dict or `into`
            Tile key to ``fn``'s result, for every job.

        Raises
        ------
        GpomapError
            Naming every tile whose task failed twice.
        DistributedError
            When the scheduler had no workers for `scheduler_timeout` seconds.
        """
        if not jobs:
            return {} if into is None else into
        # Results go straight into `into` when given (a runner's own dict otherwise).
        where: dict[str, Any] = {} if into is None else {"results": into}
        if self.scheduler is not None:
            runner = self._run_dask
        elif self.n_workers_ <= 1 or len(jobs) == 1 or _few_queries(fn, jobs):
            runner = self._run_inprocess
        elif self.worker_processes:
            runner = self._run_pool
        else:
            runner = self._run_threads
        with self._connected(), progress(len(jobs), desc, unit="tile") as bar:
            results, failed = runner(fn, jobs, bar, what, **where)
            if failed:
                retry = [j for j in jobs if j[0] in failed]
                more, failed2 = runner(fn, retry, bar, what, **where)
                if into is None:
                    results.update(more)
                if failed2:
                    names = ", ".join(f"tile {k} ({type(e).__name__}: {e})" for k, e in failed2.items())
                    raise GpomapError(f"{what} failed twice (retried once) for {len(failed2)} tile(s): {names}")
        return results

    @staticmethod
    def _run_inprocess(
        fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        results = {} if results is None else results
        failed: dict[tuple[int, int], Exception] = {}
        for key, args in jobs:
            try:
                results[key] = fn(*args)
                bar.update()
            except Exception as e:  # reported per tile after the retry
                failed[key] = e
        return results, failed

    def _workers_and_threads(self, n_jobs: int) -> tuple[int, int]:
        """Local workers for `n_jobs` tasks, and BLAS threads for each (the cores shared out)."""
        workers = min(self.n_workers_, n_jobs)
        return workers, self.blas_threads if self.blas_threads is not None else cores_share(workers)

    def _run_threads(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        """The jobs on threads of this process, BLAS held to the cores' share of each meanwhile."""
        workers, threads = self._workers_and_threads(len(jobs))
        with blas_limited(threads), cf.ThreadPoolExecutor(workers) as pool:
            return _collect({pool.submit(fn, *args): key for key, args in jobs}, bar, results)

    def _run_pool(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        ctx = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
        workers, threads = self._workers_and_threads(len(jobs))
        # With fork, the workers are forked after the tasks are filed and read them from there.
        token = uuid.uuid4().hex
        if ctx is not None:
            _INHERITED[token] = (fn, [args for _, args in jobs])
        try:
            with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=(threads,)) as pool:
                if ctx is not None:
                    futs = {pool.submit(_inherited_task, token, i): key for i, (key, _) in enumerate(jobs)}
                else:
                    futs = {pool.submit(fn, *args): key for key, args in jobs}
                return _collect(futs, bar, results)  # a dead worker breaks the pool: its tasks are retried
        finally:
            _INHERITED.pop(token, None)

    def _run_dask(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        """Run the jobs on the scheduler of ``self._client`` (see :meth:`_connected`).

        A task whose worker dies is rescheduled by the scheduler itself onto another worker (same
        function, same arguments, so the same result); the tasks are not given ``retries=``,
        since exceptions they raise already get the one retry of :meth:`_run`.
        """
        from distributed import as_completed

        client = self._client
        self._check_client(client, what, len(jobs), len(jobs))
        tag = uuid.uuid4().hex[:8]
        futs: dict[Any, tuple[int, int]] = {}  # Dask futures to their tiles
        for key, args in jobs:
            f = client.submit(fn, *args, key=f"gpomap-{fn.__name__}-{key[0]}_{key[1]}-{tag}", pure=False)
            futs[f] = key
        # as_completed takes the event loop of the futures' client; without it, it looks for a
        # default client and fails with "No clients found". It also fetches the results in the
        # background: a result lost with its worker before we fetched it is recomputed there,
        # while this loop keeps watching for workers (a blocking f.result() would hang).
        pending = as_completed(list(futs), loop=client.loop, with_results=True, raise_errors=False)
        results = {} if results is None else results
        failed: dict[tuple[int, int], BaseException] = {}
        n_done = 0
        timeout = self.scheduler_timeout
        alive = time.monotonic()  # last time a worker was seen or a task finished
        next_check = alive
        try:
            while not pending.is_empty():
                done = pending.next_batch(block=False)
                for f, res in done:
                    key = futs[f]
                    if f.status == "finished":
                        results[key] = res
                        n_done += 1
                        bar.update()
                    elif f.status == "error":  # res is (type, exception, traceback): retried
                        failed[key] = res[1]
                    else:  # cancelled (the scheduler forgot it): retried
                        failed[key] = res if isinstance(res, BaseException) else RuntimeError(f"task {f.key} {f.status}")
                    f.release()
                now = time.monotonic()
                if done:
                    alive = now
                    continue
                if now >= next_check:
                    next_check = now + min(1.0, timeout / 5)
                    self._check_client(client, what, len(jobs) - n_done - len(failed), len(jobs))
                    if self._n_dask_workers(client) > 0:
                        alive = now
                    elif now - alive > timeout:
                        left = len(jobs) - n_done - len(failed)
                        raise DistributedError(
                            f"{what}: no Dask worker has been connected to the scheduler at {self._scheduler_address()} "
                            f"for {timeout:g} s, with {left} of {len(jobs)} tile(s) left; start workers "
                            f"('dask worker {self._scheduler_address()}'), or allow longer with --scheduler-timeout "
                            "(scheduler_timeout)"
                        )
                time.sleep(0.05)
        finally:
            pending.clear()
            unfinished = [f for f in futs if not f.done()]
            if unfinished:  # stopped early: drop our tasks from the cluster
                client.cancel(unfinished)
        return results, failed

    def _check_client(self, client: Any, what: str, left: int, total: int) -> None:
        """Raise DistributedError once the client has given up on its scheduler."""
        if client.status in ("closing", "closed"):
            raise DistributedError(
                f"{what}: lost the connection to the Dask scheduler at {self._scheduler_address()}, with {left} of "
                f"{total} tile(s) left; check that the scheduler still runs, then run again"
            )

    @staticmethod
    def _n_dask_workers(client: Any) -> int:
        """Workers connected to the client's scheduler (0 when the scheduler does not answer)."""
        try:
            return len(client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # a lost scheduler counts as no workers
            return 0

    def make_observations(self, data: ScanData | Observations) -> Observations:
        """The labelled points this map's settings make of `data` (free points near hits dropped); see
        :meth:`gpomap.settings.MapSettings.make_observations`."""
        return self.base.make_observations(data)

    def _observations(self, scans: ScanData) -> Observations:
        # No free_clearance here: it is applied per block when the cells are built, so a hit
        # that arrives in a later update clears the free points near it just as a batch fit would.
        b = self.base
        return observations_from_scans(scans, b.free_step, b.hit_margin, b.no_return_cap)

    def _fit_jobs(
        self, tiles: Sequence[tuple[int, int]], reuse: bool = False
    ) -> tuple[list[tuple[tuple[int, int], tuple[TileFitTask]]], dict[tuple[int, int], TileCells]]:
        settings = self._settings()
        jobs, gathered = [], {}
        for t in tiles:
            g = self._gather(t)
            if g is None:
                continue
            gathered[t] = g
            previous = self.tiles_[t] if reuse and t in self.tiles_ else None
            jobs.append((t, (TileFitTask(t, g, settings, self.hyperparameters_, previous),)))
        return jobs, gathered

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
        # until the grid of blocks is known, then filed; never all in memory at once.
        held = _HeldParts(POINT_MEMORY)
        source: Observations | ScanPoints
        if isinstance(data, Observations):
            source = self.base.make_observations(data, clearance=False)
            held.add(source)
            n_free, n_occupied, n_scans = source.n_free, source.n_occupied, source.scan_index.max(initial=-1) + 1
            lower, upper = column_bounds(source.points) if source.occupied.size else (None, None)
            n_invalid, n_no_return = source.n_invalid, source.n_no_return
        else:
            b = self.base
            source = ScanPoints(data, b.free_step, b.hit_margin, b.no_return_cap, each_part=held.add)
            n_free, n_occupied, n_scans = source.n_free, source.n_occupied, source.n_scans
            lower, upper = source.lower, source.upper
            n_invalid, n_no_return = source.n_invalid, source.n_no_return
            if n_free + n_occupied == 0:
                raise EmptyDataError(f"no usable readings in {len(data)} scan(s) ({n_invalid} invalid): nothing to map")
            if n_occupied == 0 or n_free == 0:
                raise EmptyDataError(f"need both free and occupied observations, got {n_free} free and {n_occupied} occupied")
        # The clearance applies to points sampled from scans, not to given points.
        self._clearance = 0.0 if isinstance(data, Observations) else float(self.base.free_clearance)
        self._block_points = {}
        self._blocks = {}
        self._tiles_with_points = set()
        self._lower = None
        self._upper = None
        self._n_points = self._n_occupied_points = 0
        self._dim = held.dim
        self.tile_size_ = self.tile_size if self.tile_size is not None else DEFAULT_TILE_SIZE[self._dim]
        self.origin_ = self.origin if self.origin is not None else self._default_origin(lower, upper)
        self._dirty: set[int] = set()
        self._n_scans = int(n_scans)
        self._n_invalid, self._n_no_return = n_invalid, n_no_return
        self.path_ = None if isinstance(data, Observations) else sensor_positions(data)
        timings["observations"] = time.perf_counter() - t

        t = time.perf_counter()
        for part in held.parts():
            self._add_points(np.asarray(part.points, dtype=float), np.asarray(part.occupied, dtype=bool), held.blocks_file)
        held.close()
        self._build_blocks()
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
        self.extrapolation_: dict[str, Any] = (
            {"kappa": self.hyperparameters_["variance_scale"], "reason": "given to fit()"}
            if "variance_scale" in self.hyperparameters_
            else self._fit_variance_scale(data, source)
        )
        self.hyperparameters_["variance_scale"] = float(self.extrapolation_["kappa"])
        timings["variance_scale"] = time.perf_counter() - t
        # The blocks hold every point from here on (a large log's hundreds of megabytes with their
        # labels and scans): labelled points given are let go before the ray counts.
        del source
        release_freed_memory()
        self._scans: list[Any] | None = None if isinstance(data, Observations) else list(data)

        # The map of the other stretches is fitted, asked and let go before this map's tiles are
        # fitted and its rays counted, so the two are never in memory together; the allocator
        # keeps what it freed until told (docs/choices.md, "The map's probabilities for a later
        # visit").
        t = time.perf_counter()
        later = self._later_visit_points()
        release_freed_memory()
        timings["revisit"] = time.perf_counter() - t

        t = time.perf_counter()
        tiles = [self._decode(k) for k in sorted(self._tiles_with_points)]
        jobs, gathered = self._fit_jobs(tiles)
        self.tiles_: MutableMapping[tuple[int, int], TileState] = TileStore()
        if self._tiles_when_asked:
            # A map asked at a few points (the later visit's map of the other stretches): each
            # tile is fitted when a prediction first needs it (:meth:`_fit_waiting`).
            self._waiting: dict[tuple[int, int], tuple[TileFitTask]] = dict(jobs)
        else:
            self._run(fit_tile_task, jobs, "tile fit", "fitting tiles", into=self.tiles_)
        self._signatures = {t: g.signature() for t, g in gathered.items()}
        del jobs, gathered
        release_freed_memory()  # the fits' matrices, most of them gone to the tile store's file
        timings["tile_fits"] = time.perf_counter() - t
        self.timings_ = timings
        t = time.perf_counter()
        self.evidence_ = self._make_evidence()
        release_freed_memory()  # the traversals' temporaries
        timings["evidence"] = time.perf_counter() - t
        self.revisit_: dict[str, Any] = self._fit_revisit(later)
        timings["total_fit"] = time.perf_counter() - t0
        self.timings_ = timings
        self.last_refit_: list[tuple[int, int]] = sorted(self.tiles_)
        self._stale: dict[tuple[int, int], None] = {}
        self._reused: set[tuple[int, int]] = set()  # tiles last fitted reusing covariances
        return self

    def _fit_variance_scale(self, data: ScanData | Observations, obs: Observations | ScanPoints) -> dict[str, Any]:
        """The squash's variance scale from held-out stretches of the scans, and its report.

        See :mod:`gpomap.extrapolation`. The held-in GP covers the whole map when it is within a
        block of its centre; a larger map, the square of two blocks' side round the hyperparameter
        sample's centre (the median point when hyperparameters were given), or where that holds
        too few unseen points, of four (or the whole map, if smaller), so its cost is bounded
        whatever the map's size.
        """
        if isinstance(data, Observations):
            return {"kappa": 1.0, "reason": "labelled points given, not scans"}
        from gpomap.extrapolation import fit_variance_scale, whole_map_region

        centre, half = whole_map_region(obs if isinstance(obs, ScanPoints) else obs.points)
        margin = 0.0
        wider: tuple[NDArray[np.float64], float, float] | None = None
        if half > self.block_size_:
            # Larger than the region: round the hyperparameter sample, off the region's edge; a
            # region twice as wide (or the whole map) where that holds too few unseen points.
            whole = (centre, half, 0.0)
            source = getattr(self, "hyper_source_", {})
            centre = np.asarray(source["sample_centre"]) if "sample_centre" in source else self._median_point(obs)
            half, margin = self.block_size_, min(self.overlap_, 0.5 * self.block_size_)
            wider = whole if whole[1] <= 2.0 * half else (centre, 2.0 * half, margin)
        fixed = {**self.hyperparameters_, "variance_scale": 1.0}

        def fit_held_in(held: Observations) -> TiledGPOM:
            return self._gp_like().fit(held, hyperparameters=fixed)

        _, report = fit_variance_scale(
            data,
            self.hyperparameters_,
            obs,  # the map's own points: the kept scans are not observed again
            self._clearance,
            fit_held_in,
            centre=centre,
            region_half=half,
            margin=margin,
            no_return_cap=self.base.no_return_cap,
            seed=self.base.seed,
            wider=wider,
        )
        return report

    @staticmethod
    def _median_point(obs: Observations | ScanPoints) -> NDArray[np.float64]:
        """The median x, y of every point (made again, a part at a time, from scans)."""
        if isinstance(obs, ScanPoints):
            return np.median(np.concatenate([p.points[:, :2] for p in obs.parts()]), axis=0)
        return np.median(obs.points[:, :2], axis=0)

    def _make_evidence(self) -> EvidenceLayer | None:
        """Ray counts over every scan so far, calibrated against the tiles' GP (see gpomap.fusion)."""
        if self._scans is None:
            return None
        return self.base.make_evidence(self._scans, self.predict_proba_gp, self._gp_apart)

    def _later_visit_points(self) -> tuple[NDArray[np.float64], NDArray[np.bool_], dict[str, Any]] | None:
        """This map's probabilities, fitted without them, at a held-out stretch's points
        (:func:`gpomap.revisit.later_visit_points`); None when the map does not recalibrate."""
        if self._scans is None or not self.base.ray_evidence or not self.base.fit_revisit:
            return None
        from gpomap.revisit import later_visit_points

        fixed = dict(self.hyperparameters_)

        def fit_rest(scans: list[Any]) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
            # The same map on the other scans: its tiles, settings and hyperparameters, its own ray
            # evidence and calibration, no recalibration of its own. Asked at a few points only,
            # it fits the tiles those need when they are asked (the same tiles, so the same answers).
            rest = self._like(fit_revisit=False)
            rest._tiles_when_asked = True
            return rest.fit(scans, hyperparameters=fixed).predict_proba

        return later_visit_points(self._scans, fit_rest, self.base.no_return_cap, self.base.seed)

    def _fit_revisit(self, later: tuple[NDArray[np.float64], NDArray[np.bool_], dict[str, Any]] | None) -> dict[str, Any]:
        """Fit the ray evidence's recalibration for a later visit (:func:`gpomap.revisit.fit_revisit`)
        on the `later` points and the calibration's own; its report."""
        if later is None or self.evidence_ is None:
            return {"reason": "off" if not self.base.fit_revisit else "no ray evidence"}
        from gpomap.revisit import fit_revisit

        p_later, occupied, report = later
        if "reason" in report:
            return report
        sample = self.evidence_.sample
        self.evidence_.revisit = fit_revisit(p_later, occupied, sample.probability, sample.occupied)
        return {"slope": self.evidence_.revisit.slope, "shift": self.evidence_.revisit.shift, **report}

    def _like(self, **options: Any) -> TiledGPOM:
        """An unfitted map with this one's tiles and settings, `options` (of
        :class:`~gpomap.settings.MapSettings`) changed, on local workers whatever the scheduler."""
        return TiledGPOM(
            self.tile_size_,
            self.overlap,
            self.blend,
            self.origin_,
            n_workers=self.n_workers,
            hyper_sample=self.hyper_sample,
            blas_threads=self.blas_threads,
            worker_processes=self.worker_processes,
            memory_limit=self.memory_limit,
            **{**self.options, **options},
        )

    def _gp_like(self) -> TiledGPOM:
        """An unfitted map with this one's tiles and settings but no ray evidence (:meth:`_like`):
        fitted on other data with this map's hyperparameters, it is this map's GP on those data."""
        return self._like(ray_evidence=False)

    def _gp_apart(self, scans: ScanData) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """This map's GP fitted on `scans` alone, its hyperparameters held: its
        :meth:`predict_proba_gp`, which the ray-count calibration fits the surprise rate against
        (:func:`gpomap.fusion.fit_calibration`)."""
        return self._gp_like().fit(scans, hyperparameters=dict(self.hyperparameters_)).predict_proba_gp

    def check_fit_memory(self, length_scale: float) -> int:
        """Refuse tile fits whose largest GP, times the GPs fitted at once, needs more than `memory_limit`.

        Called by :meth:`fit` once the cells are built, before the hyperparameters are learnt:
        a tile's GP is taken to reach past its square by the overlap of `length_scale` (the
        learnt one is not known yet; the overlap is at most a block either way).

        Parameters
        ----------
        length_scale : float
            The length scale the overlap is taken from, metres.

        Returns
        -------
        int
            The largest tile's cells (an estimate: cells are counted by centre).

        Raises
        ------
        MemoryLimitError
            The estimate exceeds the limit.
        """
        from gpomap.resources import check_memory, fit_memory, largest_tile_cells, memory_limit

        overlap = tile_reach(self.tile_size_, length_scale, self.overlap)
        blocks = list(self._blocks.values())
        centres = np.concatenate([0.5 * (b.lower + b.upper)[:, :2] for b in blocks]) if blocks else np.zeros((0, 2))
        per_tile = largest_tile_cells(centres, self.tile_size_, overlap, self.origin_)
        n_at_once = 1 if self.scheduler is not None else self.n_workers_
        limit, source = memory_limit(self.memory_limit)
        check_memory(
            fit_memory(per_tile, n_at_once),
            limit,
            f"fitting {n_at_once} GP(s) of {per_tile} cells at once (the largest of the tiles of {self.tile_size_:g} m)",
            "use a larger --min-cell (min_cell), a smaller --tile-size (tile_size), fewer --workers (n_workers), "
            "or a larger --memory-limit GB (memory_limit) if the machine has the memory",
            source,
        )
        return per_tile

    def _set_geometry(self) -> None:
        self.overlap_ = tile_reach(self.tile_size_, self.hyperparameters_["length_scale"], self.overlap)
        w = BLEND_FRACTION * min(self.overlap_, self.tile_size_) if self.blend is None else float(self.blend)
        if not 0 < w <= min(self.overlap_, self.tile_size_) + 1e-12:
            raise ValueError(
                f"blend must be in (0, min(overlap, tile_size)] = (0, {min(self.overlap_, self.tile_size_)}], got {w}"
            )
        self.blend_ = float(w)

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
                self.evidence_.recalibrate(self.predict_proba_gp)
                self.timings_["update_calibration"] = time.perf_counter() - t
            return self

    def absorb(self, scans: ScanData) -> set[tuple[int, int]]:
        """Take in scans at a cost proportional to them: their points are filed under their
        blocks and their rays counted, but no cell tree is rebuilt and no tile refitted until
        :meth:`refresh`. Predictions use the new ray counts at once, over the GP as it was.

        Parameters
        ----------
        scans : sequence of Scan

        Returns
        -------
        set of (int, int)
            The blocks waiting for :meth:`refresh` (the new ones and any left before).
        """
        self._check_fitted()
        if not isinstance(self._scans, list):
            raise ValueError("absorb() needs a map fitted on scans, not on labelled points")
        self._absorb(scans)
        return {self._decode(k) for k in self._dirty}

    def _absorb(self, scans: ScanData) -> None:
        t0 = time.perf_counter()
        scans = list(scans)
        if not scans:
            return
        try:
            obs = self._observations(scans)
        except EmptyDataError:  # scans with no usable beam add a pose to the path and nothing else
            obs = None
        if obs is not None:
            self._dirty |= self._add_points(np.asarray(obs.points, dtype=float), np.asarray(obs.occupied, dtype=bool))
            self._n_invalid += obs.n_invalid
            self._n_no_return += obs.n_no_return
        self._n_scans += len(scans)
        path = sensor_positions(scans).reshape(-1, self._dim)
        self.path_ = path if self.path_ is None else np.concatenate([self.path_, path])
        t1 = time.perf_counter()
        if self._scans is not None:
            self._scans.extend(scans)
            if self.evidence_ is not None:
                self.evidence_.add_scans(scans)
        self.timings_["absorb_points"] = t1 - t0
        self.timings_["absorb_evidence"] = time.perf_counter() - t1

    @_blas_shared
    def refresh(self, max_tiles: int | None = None, exact: bool = False) -> list[tuple[int, int]]:
        """Rebuild the cells of the blocks absorbed since the last refresh and refit the tiles
        whose cell sets changed.

        Parameters
        ----------
        max_tiles : int, optional
            Refit at most this many tiles now, those waiting longest first; the rest stay
            waiting for the next call (a bounded cost per call when data arrive faster than
            tiles can be refitted). Default: all.
        exact : bool
            Compute every covariance afresh, and refit the tiles an earlier refresh fitted by
            reusing covariances. Without it a tile reuses the covariances of the cells it had
            before (most of a refit's work), which changes its GP by rounding only (~1e-15
            relative); with it the map is the batch map of the same scans to the last bits.

        Returns
        -------
        list of (int, int)
            The tiles refitted.
        """
        self._check_fitted()
        with self._connected():
            return self._refresh(max_tiles, exact)

    @property
    def pending_tiles_(self) -> int:
        """Work waiting for :meth:`refresh`: blocks absorbed and not yet rebuilt, plus tiles not yet refitted."""
        return len(self._stale) + len(self._dirty)

    def _refresh(self, max_tiles: int | None, exact: bool) -> list[tuple[int, int]]:
        t0 = time.perf_counter()
        # Every tile that sees a block absorbed since it was fitted is waiting (oldest first).
        for k in sorted(self._dirty):
            for t in self._tiles_seeing(int(k)):
                if t not in self._stale:
                    self._stale[t] = None  # dict as an ordered set: oldest first
        if exact:
            for t in self._reused:
                self._stale.setdefault(t, None)
        waiting = list(self._stale)
        take = waiting if max_tiles is None else waiting[: max(0, int(max_tiles))]
        # Only the blocks the tiles refitted now gather from are rebuilt, so a capped refresh
        # rebuilds a bounded number of cell trees too; the rest wait with their tiles.
        need = {k for t in take for k in self._blocks_seen_by(t)}
        rebuild = sorted(self._dirty & need)
        self._build_blocks(rebuild)
        self._dirty -= set(rebuild)
        t1 = time.perf_counter()
        jobs, gathered = self._fit_jobs(take, reuse=not exact)
        todo = [j for j in jobs if j[0] in self._reused or self._signatures.get(j[0]) != gathered[j[0]].signature()]
        self._run(fit_tile_task, todo, "tile fit", "refitting tiles", into=self.tiles_)
        for key, (task,) in todo:
            self._signatures[key] = gathered[key].signature()
            if task.previous is not None:
                self._reused.add(key)
            else:
                self._reused.discard(key)
        for t in take:
            del self._stale[t]
        self.last_refit_ = sorted(k for k, _ in todo)
        self.timings_["update_cells"] = t1 - t0
        self.timings_["update_tile_fits"] = time.perf_counter() - t1
        return self.last_refit_

    def _check_fitted(self) -> None:
        if not hasattr(self, "tiles_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit() first")

    def _blend_region(self, key: tuple[int, int]) -> tuple[float, float, float, float]:
        x0, x1, y0, y1 = self._core(key)
        h = 0.5 * self.blend_
        return x0 - h, x1 + h, y0 - h, y1 + h

    def _predict_blended(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Blended probability, latent mean, latent variance and probability for unseen space at points, each (m,)."""
        num, den, lat_m, lat_v = self.blended_moments(points)
        assert den is not None and lat_v is not None
        p, p_unseen = self.squash_moments(num, den)
        return p, lat_m, lat_v, p_unseen

    def squash_moments(
        self, num: NDArray[np.float64], den: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Probability, and probability for unseen space, from :meth:`blended_moments`' calibrated moments, each (m,)."""
        p = ndtr(num / np.sqrt(1.0 + den))
        # Where no beam went the latent variance is scaled by kappa (gpomap.extrapolation).
        p_unseen = ndtr(unseen_probit(num, den, self.hyperparameters_.get("variance_scale", 1.0)))
        return p, p_unseen

    def forget_below(self, y: float) -> None:
        """Drop the K^-1 that tiles whose blend region ends below `y` formed when they predicted.

        A planar written map is built in bands of rows, upwards (:meth:`EvidenceLayer.written_grid
        <gpomap.fusion.EvidenceLayer.written_grid>`): a tile the bands have passed is not asked
        again, and its K^-1 is as large as its factor (gigabytes over a building; docs/choices.md,
        "The written map in bands"). Asked again, a tile forms the same K^-1 afresh.
        """
        tiles = self.tiles_
        states = tiles.resident() if isinstance(tiles, TileStore) else tiles.values()
        for tile in states:
            if self._blend_region(tile.key)[3] < y:
                tile.posterior.precision = None

    def _fit_waiting(self, keys: list[tuple[int, int]]) -> None:
        """Fit the tiles of `keys` that wait to be asked (a map fitted with ``_tiles_when_asked``)."""
        if keys:
            self._run(fit_tile_task, [(k, self._waiting.pop(k)) for k in keys], "tile fit", "fitting tiles", into=self.tiles_)

    def _light_tile(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s state, its factor left where it is (:meth:`TileStore.light`)."""
        tiles = self.tiles_
        return tiles.light(key) if isinstance(tiles, TileStore) else tiles[key]

    def _prediction_batches(self, keys: list[tuple[int, int]]) -> list[list[tuple[int, int]]]:
        """`keys` in consecutive batches whose factors (and the inverses prediction forms) fit in
        the tile store's budget together; one batch when the tiles are in a plain dict."""
        tiles = self.tiles_
        if not isinstance(tiles, TileStore):
            return [keys] if keys else []
        batches: list[list[tuple[int, int]]] = []
        size = tiles.budget  # a full batch: the next key starts a new one
        for key in keys:
            n = tiles.light(key).posterior.n_inputs
            cost = 2 * 8 * n * n
            if batches and size + cost <= tiles.budget:
                batches[-1].append(key)
                size += cost
            else:
                batches.append([key])
                size = cost
        return batches

    def blended_moments(
        self, points: NDArray[np.float64], variance: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64] | None]:
        """The tiles' calibrated latent moments at points, blended: alpha mu + beta, alpha^2 var, mu, var.

        Each of shape (m,); the two variances None without `variance` (the mean costs a small
        part of a prediction). :meth:`squash_moments` turns the first two into probabilities.
        """
        pts = as_points(points, self._dim)
        m = pts.shape[0]
        h = 0.5 * self.blend_
        chunk = self.base.chunk_size
        # Per tile: which points it predicts and with what weight.
        members: dict[tuple[int, int], tuple[NDArray[np.intp], NDArray[np.float64]]] = {}
        wsum = np.zeros(m)
        # Points bucketed once in squares of half a tile (a stable sort of integers), so each
        # tile scans only the few squares its blend region reaches: strips of x alone made each
        # tile of a tall map scan dozens of tiles' points (docs/choices.md, "Measured for the
        # code"). Squares as narrow as a short blend would be millions (a hard switch).
        waiting = getattr(self, "_waiting", {})
        keys = sorted([*self.tiles_, *waiting]) if waiting else sorted(self.tiles_)
        side = 0.5 * self.tile_size_
        regions = np.array([self._blend_region(k) for k in keys])
        lo = regions[:, [0, 2]].min(axis=0)
        n_sq = np.ceil((regions[:, [1, 3]].max(axis=0) - lo) / side).astype(np.int64) + 1
        # Square indices -1..n (points beyond every region are clipped to the edge squares).
        sq_x = np.clip(np.floor((pts[:, 0] - lo[0]) / side), -1, n_sq[0]).astype(np.int64) + 1
        sq_y = np.clip(np.floor((pts[:, 1] - lo[1]) / side), -1, n_sq[1]).astype(np.int64) + 1
        row = int(n_sq[1]) + 2
        sq_key = sq_x * row + sq_y
        by_square = stable_order(sq_key)
        sorted_key = sq_key[by_square]
        for key, (bx0, bx1, by0, by1) in zip(keys, regions, strict=True):
            fx, lx = (math.floor((v - lo[0]) / side) + 1 for v in (bx0, bx1))
            fy, ly = (math.floor((v - lo[1]) / side) + 1 for v in (by0, by1))
            # One slice of the sorted points per column of squares the region reaches.
            starts = np.searchsorted(sorted_key, np.arange(fx, lx + 1) * row + fy, side="left")
            stops = np.searchsorted(sorted_key, np.arange(fx, lx + 1) * row + ly, side="right")
            near = np.concatenate([by_square[a:b] for a, b in zip(starts, stops, strict=True)])
            inside = (pts[near, 0] > bx0) & (pts[near, 0] < bx1) & (pts[near, 1] > by0) & (pts[near, 1] < by1)
            idx = np.sort(near[inside])
            if idx.size == 0:
                continue
            x0, x1, y0, y1 = self._core(key)
            w = taper(pts[idx, 0], x0, x1, h) * taper(pts[idx, 1], y0, y1, h)
            nz = w > 0
            if nz.any():
                members[key] = (idx[nz], w[nz])
                wsum[idx[nz]] += w[nz]  # indices distinct within a tile
        # Points no tile reaches (blocks without data): the tile whose core is nearest, alone.
        orphans = np.flatnonzero(wsum <= 0)
        if orphans.size:
            nearest = nearest_box(pts[orphans], np.array([self._core(k) for k in keys]))
            for j in np.unique(nearest):
                sel = orphans[nearest == j]
                key = keys[int(j)]
                if key in members:
                    idx, w = members[key]
                    members[key] = (np.concatenate([idx, sel]), np.concatenate([w, np.ones(sel.size)]))
                else:
                    members[key] = (sel, np.ones(sel.size))
                wsum[sel] = 1.0
        # A written map predicts the mean at every GP sample, then both moments at fewer: say which.
        desc = "predicting tiles" if variance else "predicting tile means"
        if waiting:
            self._fit_waiting([k for k in members if k in waiting])
        # The mean needs no factor: the tiles' states without theirs, all at once. The variance:
        # tiles in batches whose factors fit in a TileStore's budget, each batch's states read
        # (from the store's file, if there) only while it runs.
        batches = self._prediction_batches(list(members)) if variance else [list(members)]
        state = self.tiles_.__getitem__ if variance else self._light_tile
        res: MutableMapping[tuple[int, int], Any] = {}
        with progress(len(members), desc, unit="tile") if len(batches) > 1 else contextlib.nullcontext() as bar:
            for batch in batches:
                jobs = [(key, (state(key), pts[members[key][0]], chunk, variance)) for key in batch]
                res.update(self._run(predict_tile_task, jobs, "tile prediction", desc))
                del jobs
                if bar is not None:
                    bar.update(len(batch))
        num = np.zeros(m)
        lat_m = np.zeros(m)
        den = np.zeros(m) if variance else None
        lat_v = np.zeros(m) if variance else None
        for key, (idx, w) in members.items():
            mu, var = res[key]
            hp = self._light_tile(key).hyperparameters
            a, b = hp["alpha"], hp["beta"]
            # Blend the calibrated latent moments so per-tile alpha and beta blend too; with
            # global alpha and beta this is exactly squash(blended mean, blended variance).
            # idx is distinct within a tile, so fancy-index sums add each once, in tile order.
            num[idx] += w * (a * mu + b)
            lat_m[idx] += w * mu
            if den is not None and lat_v is not None and var is not None:
                den[idx] += w * (a * a * var)
                lat_v[idx] += w * var
        return num / wsum, None if den is None else den / wsum, lat_m / wsum, None if lat_v is None else lat_v / wsum

    @overload
    def predict(self, /, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict(
        self, /, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict(
        self, /, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @_blas_shared
    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Blended latent mean (and variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        self._check_fitted()
        _, mu, var, _ = self._predict_blended(points)
        return (mu, var) if return_var else mu

    @overload
    def predict_proba(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability at points, blended across tiles.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool
            Also return the blended latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        p, var, p_unseen = self._timed_prediction(points)
        if self.evidence_ is not None:
            p = self.evidence_.proba(np.asarray(points, dtype=float).reshape(-1, self._dim), p, p_unseen)
        return (p, var) if return_var else p

    @overload
    def predict_proba_gp(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The tiles' blended GP probability at points, before any ray evidence.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        p, var, _ = self._timed_prediction(points)
        return (p, var) if return_var else p

    @_blas_shared
    def _timed_prediction(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`_gp_probabilities` at points, its time kept as the ``prediction`` stage."""
        self._check_fitted()
        t = time.perf_counter()
        out = self._gp_probabilities(points)
        self.timings_["prediction"] = time.perf_counter() - t
        return out

    @property
    def thresholds_(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities (:func:`gpomap.fusion.ternary_thresholds`)."""
        return ternary_thresholds(self.base.thresholds, self.evidence_)

    def predict_ternary(self, points: NDArray[np.float64]) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, ndarray of shape (m,); never occupied
        in a cell beams saw through (:meth:`gpomap.fusion.EvidenceLayer.seen_through_at`)."""
        seen = self.evidence_.seen_through_at(points) if self.evidence_ is not None else None
        return ternary(self.predict_proba(points), self.thresholds_, seen)

    @_blas_shared
    def grid(self, resolution: float, extent: tuple[float, ...] | None = None) -> Any:
        """The map sampled at grid-cell centres; each tile predicts only the grid cells it covers.

        Parameters
        ----------
        resolution : float
            Grid cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
            Defaults to the bounding box of the observations grown by two cells
            (:func:`gpomap.lattice.data_extent`); (..., zmin, zmax) in 3-D.

        Returns
        -------
        OccupancyMap, or VoxelMap for a 3-D map
        """
        self._check_fitted()
        aligned = extent is None  # the default grid's cells are the ray counts' (no recount)
        if extent is None:
            assert self._lower is not None and self._upper is not None
            extent = data_extent(self._lower, self._upper, resolution)
        if self._dim == 3:
            return self._voxels(resolution, extent)
        spec = GridSpec.from_extent((extent[0], extent[1], extent[2], extent[3]), resolution, align=aligned)
        t = time.perf_counter()
        probability, variance, seen_through = self._sample(spec)
        self.timings_["grid"] = time.perf_counter() - t
        if isinstance(self.tiles_, TileStore) and self.tiles_.spilled_bytes:
            # A map larger than the store's budget: the grid's files come next, its last tiles wait in the file meanwhile.
            self.tiles_.shrink()
        return OccupancyMap(
            grid=spec,
            probability=probability,
            variance=variance,
            thresholds=self.thresholds_,
            path=self.path_,
            info=self.summary(),
            seen_through=seen_through,
        )

    def _gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The blended GP's probability, latent variance and probability for unseen space, each (m,)."""
        p, _, var, p_unseen = self._predict_blended(points)
        return p, var, p_unseen

    def _sample(self, spec: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """Probability and latent variance per cell of a GridSpec or VoxelSpec, and the cells beams
        saw through (:meth:`gpomap.fusion.EvidenceLayer.written_grid`; None without ray counts)."""
        if self.evidence_ is not None:
            return self.evidence_.written_grid(spec, self.hyperparameters_["length_scale"], self._gp_probabilities, self)
        ny, nx = spec.shape[-2:]
        rows = max(1, WRITTEN_BAND_CELLS // nx)
        if not isinstance(spec, GridSpec) or ny <= rows:
            p, _, var, _ = self._predict_blended(spec.centres())
            return p.reshape(spec.shape), var.reshape(spec.shape), None
        # The GP alone, in bands of rows as the written map with counts is (the same values).
        probability, variance = np.empty(spec.shape), np.empty(spec.shape)
        for start, stop, band in row_bands(spec, rows):
            p, _, var, _ = self._predict_blended(band.centres())
            probability[start:stop], variance[start:stop] = p.reshape(-1, nx), var.reshape(-1, nx)
            self.forget_below(spec.origin[1] + stop * spec.resolution)
        self.forget_below(np.inf)
        return probability, variance, None

    def _voxels(self, resolution: float, extent: tuple[float, ...]) -> Any:
        from gpomap.lattice import extent_bounds
        from gpomap.voxels import VoxelMap, VoxelSpec

        lo, hi = extent_bounds(extent)
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        t = time.perf_counter()
        probability, variance, _ = self._sample(spec)
        self.timings_["grid"] = time.perf_counter() - t
        observed = self.evidence_.grid_observed(spec) if self.evidence_ is not None else None
        return VoxelMap(spec, probability, variance, thresholds=self.thresholds_, info=self.summary(), observed=observed)

    @property
    def bounds_(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper corners of the labelled points' bounding box (the default map extent), each (d,)."""
        self._check_fitted()
        assert self._lower is not None and self._upper is not None  # fit sees both classes
        return self._lower.copy(), self._upper.copy()

    @property
    def dim_(self) -> int:
        """Dimension of the fitted map: 2 for planar scans, 3 for point clouds."""
        self._check_fitted()
        return self._dim

    @property
    def n_inputs_(self) -> int:
        """Number of cells over the whole map (each counted once)."""
        self._check_fitted()
        return int(sum(len(b.counts) for b in self._blocks.values()))

    def cell_boxes(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Every cell of the map once, in block order.

        Returns
        -------
        lower, upper : ndarray of shape (n, d)
            The cells' boxes.
        labels : ndarray of shape (n,)
            +1 occupied, -1 free.
        """
        self._check_fitted()
        lo, hi, _, lab, _ = self._all_cells()
        return lo, hi, lab

    def training_points(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The labelled points the cells were built from (free points near hits dropped).

        Returns
        -------
        points : ndarray of shape (m, d)
        occupied : ndarray of bool, shape (m,)
        """
        self._check_fitted()
        parts = []
        for k in sorted(self._block_points):
            points, occupied = self._block_points[k].arrays()
            keep = ~self._block_points[k].free_near_hits(self._clearance)
            parts.append((points[keep], occupied[keep]))
        return np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])

    def summary(self) -> dict[str, Any]:
        """Tiles, cells per tile, hyperparameters and where they came from, stage timings, peak memory."""
        self._check_fitted()
        states = list(light_tiles(self.tiles_))
        per = np.array([s.n_cells for s in states])
        secs = np.array([s.seconds for s in states])
        out: dict[str, Any] = {
            "method": "msk-gpom",
            "kernel": make_point_kernel(self.base.kernel).name,
            "area": self.base.area_method,
            "tile_size": self.tile_size_,
            "block_size": self.block_size_,
            "tile_origin": [float(self.origin_[0]), float(self.origin_[1])],
            "overlap": self.overlap_,
            "blend": self.blend_,
            "n_tiles": len(self.tiles_),
            "n_cells": self.n_inputs_,
            "n_ambiguous_cells": int(sum(b.n_ambiguous for b in self._blocks.values())),
            "cells_per_tile": {"min": int(per.min()), "median": float(np.median(per)), "max": int(per.max())},
            "tile_fit_seconds": {
                "min": float(secs.min()),
                "median": float(np.median(secs)),
                "max": float(secs.max()),
                "sum": float(secs.sum()),
            },
            "n_points": self._n_points,
            "n_occupied_points": self._n_occupied_points,
            "n_scans": self._n_scans,
            "n_invalid_readings": self._n_invalid,
            "n_no_return_readings": self._n_no_return,
            "n_free_points_cleared": sum(b.n_cleared for b in self._block_points.values()),
            "hyperparameters": dict(self.hyperparameters_),
            "variance_scale_fit": dict(self.extrapolation_),
            "revisit": dict(getattr(self, "revisit_", {})),
            "hyperparameter_source": dict(self.hyper_source_),
            "evidence": self.evidence_.summary() if self.evidence_ is not None else None,
            "thresholds": list(self.thresholds_),
            "timings": dict(self.timings_),
            "peak_memory": peak_rss_mb(),
            "executor": "dask"
            if self.scheduler is not None
            else (
                "in-process"
                if self.n_workers_ <= 1
                else f"{'process pool' if self.worker_processes else 'threads'} x{self.n_workers_}"
            ),
        }
        if self.per_tile_hyperparameters:
            out["per_tile_hyperparameters"] = {
                n: {"min": float(np.min(v)), "median": float(np.median(v)), "max": float(np.max(v))}
                for n in HYPER_NAMES
                for v in [[s.hyperparameters[n] for s in states]]
            }
        return out
