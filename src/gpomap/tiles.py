"""Tiled MSK-GPOM: maps larger than one GP can hold, as many small GPs blended without seams.

One dense GP over every cell of a real log does not fit (tens of thousands of cells, O(N^3)
time and O(N^2) memory). :class:`TiledGPOM` cuts the plane into square tiles on a fixed grid
(anchored at the map frame's origin, or one tile centred on the data when they fit in one), and
fits one GP per tile on the cells near it:

1. **Observations once** for the whole log (beams to labelled points).
2. **Cells per block**: the points of each block (a square of :data:`BLOCK_SIZE`, or of the tile
   if larger, on the tile grid's origin) get their own cell tree (:func:`gpomap.cells.build_cells`
   on that block's points), whatever the tile size. A block's cells therefore depend only on the
   points inside it, so new data changes the cells of the blocks it falls in and
   nowhere else; that is what makes ``update`` give exactly the batch answer. The trees are cut
   at block borders, which costs a few extra cells there and nothing else.
3. **Hyperparameters once**: the signal variance, length scale, noise, and the squash's alpha and
   beta are learnt by one :class:`~gpomap.gp.SupportGP` on a compact sample of at most
   `hyper_sample` cells (the cells nearest the centroid of a block at the upper quartile of
   cells per block: a dense but typical patch; in planar maps the search treats it as compact
   groups of :data:`HYPER_GROUP_CELLS`, each its own GP), then every tile uses them as they are.
   With ``per_tile_hyperparameters=True`` each tile learns its own instead.
4. **One GP per tile**, fitted on the cells whose boxes meet the tile grown by `overlap` on each
   side. Tiles are independent tasks run in this process, in a local process pool, or on a Dask
   distributed cluster (:func:`fit_tile_task` and :func:`predict_tile_task` are plain picklable
   functions of arrays and settings).
5. **Blending**: a query point is predicted by every tile whose blend region (the core grown by
   `blend` / 2) holds it, with weights that are products of 1-D smoothstep tapers, zero at the
   edge of the blend region and summing to one (a partition of unity); the calibrated latent
   moments ``alpha m + beta`` and ``alpha^2 v`` are averaged with those weights and then
   squashed, so neither probability nor variance jumps at a tile border.

This is the one engine of every MSK-GPOM map, a room or a building, 2-D or 3-D
(:class:`~gpomap.mapping.AreaGPOM` is its scikit-learn style face). A map whose data fall in one
block is one GP over that block's cells.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import hashlib
import math
import multiprocessing
import os
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, MutableMapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace
from typing import Any, Concatenate, Literal, ParamSpec, TypeVar, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr

from gpomap.cells import build_cells
from gpomap.config import DEFAULT_SCHEDULER_TIMEOUT, MapConfig, TilingConfig
from gpomap.errors import DistributedError, EmptyDataError, GpomapError, NotFittedError
from gpomap.estimator import as_points
from gpomap.fusion import EvidenceLayer, ternary_thresholds
from gpomap.gp import GPPosterior, SupportGP, cholesky_solve, noisy_cholesky
from gpomap.grid import GridSpec, OccupancyMap, row_bands, ternary
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.point import make_point_kernel
from gpomap.lapack import available_cores, blas_limited, cores_share, limit_blas_threads
from gpomap.lattice import column_bounds, data_extent, stable_order
from gpomap.observations import (
    Observations,
    ScanData,
    ScanPoints,
    free_near_hits,
    observations_from_scans,
    sensor_positions,
)
from gpomap.progress import Progress, progress
from gpomap.resources import POINT_MEMORY, TILE_MEMORY, WRITTEN_BAND_CELLS, SpillFile, peak_rss_mb, release_freed_memory
from gpomap.scans import Scan
from gpomap.settings import MapSettings
from gpomap.squash import ProbitSquash, unseen_probit
from gpomap.supports import Supports

# Block keys pack (ix, iy) into one int64 so grouping millions of points is one argsort.
_KEY_OFFSET = 1 << 30
_KEY_BASE = 1 << 31
# Points given block and tile keys at once (bounds the temporaries of a whole log's points).
_KEY_CHUNK = 1 << 20

HYPER_NAMES = ("variance", "length_scale", "noise", "alpha", "beta")
#: What a fit learns of unseen space besides, taken as given when passed with the hyperparameters:
#: the variance scale (:mod:`gpomap.extrapolation`).
UNSEEN_NAMES = ("variance_scale",)

#: Of the hyperparameters, those that must be positive; beta is any number.
_POSITIVE_HYPER = ("variance", "length_scale", "noise", "alpha", "variance_scale")


def given_hyperparameters(hyperparameters: dict[str, float]) -> dict[str, float]:
    """The hyperparameters a fit is given (:data:`HYPER_NAMES`, and any of :data:`UNSEEN_NAMES`), as floats.

    Raises
    ------
    ValueError
        Naming the hyperparameter missing, not a finite number, or out of its range.
    """
    missing = [n for n in HYPER_NAMES if n not in hyperparameters]
    if missing:
        raise ValueError(f"hyperparameters must give {HYPER_NAMES}; missing {missing}")
    out: dict[str, float] = {}
    for n in (*HYPER_NAMES, *UNSEEN_NAMES):
        if n not in hyperparameters:
            continue
        try:
            v = float(hyperparameters[n])
        except (TypeError, ValueError):
            raise ValueError(f"hyperparameter {n} must be a number, got {hyperparameters[n]!r}") from None
        if not np.isfinite(v) or (n in _POSITIVE_HYPER and v <= 0):
            need = "positive" if n in _POSITIVE_HYPER else "finite"
            raise ValueError(f"hyperparameter {n} must be {need}, got {v}")
        out[n] = v
    return out


#: Most cells of the compact sample the hyperparameters are learnt on, by the map's dimension:
#: a larger sample pinned planar maps' hyperparameters better, while in 3-D each step of the cuboid
#: kernel is dearer and 300 scored as well (the measurements: docs/choices.md, "The hyperparameter
#: search in groups of 200 cells").
DEFAULT_HYPER_SAMPLE: dict[int, int] = {2: 800, 3: 300}

#: Most cells of each compact group the hyperparameter sample is cut into for the search, each
#: group its own GP (:class:`gpomap.gp.SupportGP`'s ``hyper_group``), by the map's dimension;
#: None: one GP over the sample. Planar maps: 200, so the 800 cells are four groups and each
#: evaluation of the objective is 16 times cheaper, while the written maps score as with one GP.
#: Voxel maps: one GP; their 300-cell search costs mostly kernel evaluations, which groups do not
#: make fewer, and smaller groups cost log loss (docs/choices.md, "The hyperparameter search in
#: groups of 200 cells").
HYPER_GROUP_CELLS: dict[int, int | None] = {2: 200, 3: None}

#: The hyperparameter sample is anchored only in a block whose share of occupied cells is at
#: least this fraction of the whole map's (when any block is): a sample of one class says nothing
#: of how occupied and free cells differ: the objective is flat there, the squash takes its lowest
#: alpha and the GP adds nothing to the map (docs/choices.md, "The hyperparameter sample").
MIN_SAMPLE_OCCUPIED_SHARE: float = 0.5


def hyper_anchor_block(sizes: ArrayLike, occupied_fractions: ArrayLike, map_occupied_fraction: float) -> int:
    """Index of the block the hyperparameter sample is anchored in: a dense, typical, mixed block.

    Among the blocks whose occupied fraction is at least :data:`MIN_SAMPLE_OCCUPIED_SHARE` of
    the map's (all blocks when none is), the one whose cell count is nearest the upper quartile
    of every block's (the first such in order on ties).

    Parameters
    ----------
    sizes : array_like of shape (b,)
        Cells per block.
    occupied_fractions : array_like of shape (b,)
        Fraction of each block's cells that are occupied.
    map_occupied_fraction : float
        Fraction of the map's cells that are occupied.

    Returns
    -------
    int
    """
    sizes = np.asarray(sizes, dtype=float)
    mixed = np.asarray(occupied_fractions, dtype=float) >= MIN_SAMPLE_OCCUPIED_SHARE * map_occupied_fraction
    candidates = np.flatnonzero(mixed) if mixed.any() else np.arange(sizes.size)
    # Dense but typical: the densest block can be one spot where the robot lingered, many tiny
    # cells whose squash comes out flat (docs/choices.md, "The hyperparameter sample").
    return int(candidates[np.argmin(np.abs(sizes[candidates] - np.quantile(sizes, 0.75)))])


#: Tile side by the map's dimension, metres. A tile's GP costs the cube of the cells it sees, its
#: square grown by the overlap, so tiles not much larger than the overlap are cheapest in all;
#: the cells, hyperparameters and variance scale do not depend on them (:data:`BLOCK_SIZE`).
#: Planar maps: 5 m squares; voxel maps: 3 m columns, which hold every height, so they fill
#: faster than planar squares. Both the fastest sizes tried, scores unchanged (docs/choices.md,
#: "Tiles: 5 m squares (3 m columns in 3-D)").
DEFAULT_TILE_SIZE: dict[int, float] = {2: 5.0, 3: 3.0}

#: A tile's GP sees the cells this many learnt length scales beyond its square, by default. 1.5
#: (it was 2.5, about where the SE kernel has decayed to 4 %): the scores did not move
#: with it while the time did, since a tile's cells grow with the square of the side it sees
#: (planar and voxel maps: docs/choices.md, "Tiles: 5 m squares"; docs/3d.md).
OVERLAP_LENGTH_SCALES: float = 1.5

#: Default blend width, as a fraction of the overlap (or of the tile, if smaller). A tile predicts
#: within half the blend of its square, where it still sees at least 3/4 of the overlap beyond,
#: and fewer tiles predict each point: less CPU, the same scores (docs/choices.md, "Tiles: 5 m
#: squares").
BLEND_FRACTION: float = 0.5

#: The map settings a TiledGPOM answers as its own attributes (read from its ``base``).
_SETTING_NAMES = frozenset(MapConfig.__dataclass_fields__)

#: Side of the blocks (metres), squares on the tile grid's origin whose points get their own cell
#: tree, whatever the tile size: the cells, the hyperparameter sample anchored in a typical block,
#: and the variance scale's region (one block from its centre each way, gpomap.extrapolation)
#: are then the same for any tiles, and smaller tiles only make the tiles' GPs cheaper. Smaller
#: blocks would cut the trees more often and moved the learnt noise and squash to other optima
#: (docs/choices.md, "Tiles: 5 m squares").
BLOCK_SIZE: float = 10.0


def block_side(tile_size: float) -> float:
    """Side of the blocks that get their own cell tree for tiles of `tile_size`: :data:`BLOCK_SIZE`, or the tiles' if larger."""
    return max(BLOCK_SIZE, float(tile_size))


def capped_overlap(overlap: float, tile_size: float) -> float:
    """How far a tile's GP sees past its square: `overlap`, at most one block (:func:`block_side`)."""
    return float(min(max(overlap, 1e-9), block_side(tile_size)))


def tile_reach(tile_size: float, length_scale: float, overlap: float | None = None) -> float:
    """How far a tile's GP sees past its square: `overlap`, by default :data:`OVERLAP_LENGTH_SCALES`
    length scales, at most one block (:func:`capped_overlap`)."""
    return capped_overlap(OVERLAP_LENGTH_SCALES * length_scale if overlap is None else float(overlap), tile_size)


def _box_offset(ij: NDArray[np.int64], lo: NDArray[np.int64], span: NDArray[np.int64]) -> NDArray[np.int64]:
    """Row-major offset of each square index (ix, iy) (shape (n, 2)) in the index box from `lo`
    spanning `span` squares per axis: ix major, the order of the squares' keys."""
    return (ij[:, 0] - lo[0]) * span[1] + (ij[:, 1] - lo[1])


# --------------------------------------------------------------------------- tasks (picklable)
@dataclass
class TileState:
    """A fitted tile: its GP's posterior and the hyperparameters it was fitted with.

    Attributes
    ----------
    key : (int, int)
        Tile index (ix, iy) on the tile grid.
    posterior : GPPosterior
        The tile's training cells (their member points only for the ``"summed"`` area kernel,
        which needs them), the Cholesky factor, the weights, the kernel and the squash.
    hyperparameters : dict
        variance, length_scale, noise, alpha, beta used by this tile.
    seconds : float
        Time the fit took on its worker.
    """

    key: tuple[int, int]
    posterior: GPPosterior
    hyperparameters: dict[str, float]
    seconds: float

    @property
    def n_cells(self) -> int:
        """Number of training cells."""
        return self.posterior.n_inputs


#: A factor's place in a state that waits in a :class:`TileStore`'s file.
_NO_FACTOR = np.zeros((0, 0))


class TileStore(MutableMapping[tuple[int, int], TileState]):
    """A map's fitted tiles by key, their Cholesky factors in memory within a budget.

    A building holds thousands of tiles, each with an n x n factor (a megabyte at 380 cells),
    and uses a few hundred at a time: the rows of a written map's band, the tiles round a
    calibration's points. The factors of the tiles read or stored last are kept while they and
    the inverses prediction forms beside them (counted as much again) fit in `budget` bytes; the
    least recently used beyond it wait in a temporary file (:class:`~gpomap.resources.SpillFile`:
    their lower triangle, the rest being zero as factors are, else the whole matrix) and are
    read back when asked, the same numbers to the bit and in the same memory order. Everything
    else of a state (cells, weights, hyperparameters, a few kilobytes) stays in memory:
    :meth:`light` gives it without its factor.

    Reading a tile moves it to the front; the states handed out stay valid whatever is evicted
    after. Safe to use from several threads.

    Parameters
    ----------
    budget : int, optional
        Bytes of factors (twice each factor's size) kept in memory; the last tile stored or read
        is kept whatever its size. Default :data:`gpomap.resources.TILE_MEMORY`.
    tiles : mapping, optional
        States to store first.
    """

    def __init__(self, budget: int | None = None, tiles: Mapping[tuple[int, int], TileState] | None = None) -> None:
        self.budget = int(TILE_MEMORY if budget is None else budget)
        self._light: dict[tuple[int, int], TileState] = {}
        self._resident: OrderedDict[tuple[int, int], TileState] = OrderedDict()
        # Where each factor waiting in the file is: (segment, rows, "C" or "F", lower triangle only).
        self._spilled: dict[tuple[int, int], tuple[tuple[int, int], int, str, bool]] = {}
        self._bytes = 0
        self._peeks = 0
        self._file: SpillFile | None = None
        self._lock = threading.RLock()
        if tiles is not None:
            self.update(tiles)

    @staticmethod
    def _cost(state: TileState) -> int:
        # The factor and the K^-1 a prediction forms beside it (as large).
        return 2 * int(state.posterior.L.nbytes)

    @staticmethod
    def _spillable(L: Any) -> bool:
        return isinstance(L, np.ndarray) and L.ndim == 2 and L.shape[0] == L.shape[1] and L.dtype == np.float64

    def __setitem__(self, key: tuple[int, int], state: TileState) -> None:
        with self._lock:
            self._forget(key)
            if not self._spillable(state.posterior.L):
                self._light[key] = state  # nothing to spill: kept whole
                return
            light = replace(state.posterior, L=_NO_FACTOR, precision=None)
            self._light[key] = TileState(state.key, light, state.hyperparameters, state.seconds)
            self._resident[key] = state
            self._bytes += self._cost(state)
            self._evict()

    def _forget(self, key: tuple[int, int]) -> None:
        state = self._resident.pop(key, None)
        if state is not None:
            self._bytes -= self._cost(state)
        spilled = self._spilled.pop(key, None)
        if spilled is not None and self._file is not None:
            self._file.free(spilled[0])
        self._light.pop(key, None)

    def __delitem__(self, key: tuple[int, int]) -> None:
        with self._lock:
            if key not in self._light:
                raise KeyError(key)
            self._forget(key)

    def __getitem__(self, key: tuple[int, int]) -> TileState:
        with self._lock:
            state = self._resident.get(key)
            if state is not None:
                self._resident.move_to_end(key)
                return state
            if key not in self._spilled:
                return self._light[key]  # kept whole
            state = self._read(key)
            self._resident[key] = state
            self._bytes += self._cost(state)
            self._evict()
            return state

    def peek(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s whole state, as reading it gives, but not kept in memory after (nor moved
        to the front): for a pass over every tile, such as the map file's."""
        with self._lock:
            state = self._resident.get(key)
            if state is not None:
                return state
            if key not in self._spilled:
                return self._light[key]
            self._peeks += 1
            if self._peeks % 256 == 0:
                release_freed_memory()  # the factors read and let go, scattered in the heap
            return self._read(key)

    def _read(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s state with its factor read back from the file."""
        assert self._file is not None
        light = self._light[key]
        where, n, order, lower = self._spilled[key]
        if lower:
            L = np.zeros((n, n), order="F" if order == "F" else "C")
            L[np.tri(n, dtype=bool)] = self._file.get(where, np.float64, (n * (n + 1) // 2,))
        else:
            L = self._file.get(where, np.float64, (n, n))
            if order == "F":
                L = np.asfortranarray(L)
        return TileState(light.key, replace(light.posterior, L=L), light.hyperparameters, light.seconds)

    def _evict(self, budget: int | None = None, keep: int = 1) -> None:
        """Send the least recently used factors to the file until the rest fit in the budget
        (or `budget`), keeping at least `keep`."""
        budget = self.budget if budget is None else budget
        while self._bytes > budget and len(self._resident) > keep:
            key, state = self._resident.popitem(last=False)
            self._bytes -= self._cost(state)
            if key in self._spilled:
                continue  # its factor is in the file already (factors never change)
            L = state.posterior.L
            order = "F" if L.flags.f_contiguous and not L.flags.c_contiguous else "C"
            below = np.tri(L.shape[0], dtype=bool)
            # Bit by bit, so a -0.0 above the diagonal is kept too.
            lower = not np.ascontiguousarray(L).view(np.uint64)[~below].any()
            if self._file is None:
                self._file = SpillFile()
            where = self._file.put(L[below] if lower else np.ascontiguousarray(L))
            self._spilled[key] = (where, int(L.shape[0]), order, lower)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return iter(list(self._light))

    def __len__(self) -> int:
        return len(self._light)

    def __contains__(self, key: object) -> bool:
        return key in self._light

    def shrink(self) -> None:
        """Send every factor in memory to the file, as if the budget were nothing (a map done
        predicting for now: the files of its written grid come next)."""
        with self._lock:
            self._evict(budget=0, keep=0)

    def light(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s state without its factor (an empty ``posterior.L``): cells, weights,
        hyperparameters, fit time; never read from the file."""
        return self._light[key]

    def light_states(self) -> list[TileState]:
        """Every tile's :meth:`light` state, in key order of storing."""
        with self._lock:
            return list(self._light.values())

    def resident(self) -> list[TileState]:
        """The states whose factors are in memory now."""
        with self._lock:
            return list(self._resident.values())

    @property
    def spilled_bytes(self) -> int:
        """Bytes of the temporary file (0 while every factor is in memory)."""
        return 0 if self._file is None else self._file.size

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled whole: a plain dict's worth of states.
        return (TileStore, (self.budget, dict(self.items())))


def light_tiles(tiles: Mapping[tuple[int, int], TileState]) -> Iterable[TileState]:
    """The states of `tiles` as far as their cells, weights and hyperparameters go, without
    reading factors back (:meth:`TileStore.light_states`; a plain dict's own values)."""
    return tiles.light_states() if isinstance(tiles, TileStore) else tiles.values()


@dataclass(frozen=True)
class TileSettings:
    """What a tile's tasks need of the map's settings: the kernel and noise and, for per-tile
    hyperparameters, how to learn them (the fields of :class:`~gpomap.config.MapConfig` they come from).

    Attributes
    ----------
    area : str
        The area kernel's method, resolved ("exact", "quadrature" or "summed"; the map's
        ``area_method``).
    per_tile : bool
        Learn each tile's hyperparameters, starting from the map's; False: use the map's.
    """

    area: str
    kernel: str = MapConfig.kernel
    normalisation: str = MapConfig.normalisation
    quadrature_order: int = MapConfig.quadrature_order
    length_scale_bounds: tuple[float, float] = MapConfig.length_scale_bounds
    noise_bounds: tuple[float, float] = MapConfig.noise_bounds
    noise_model: str = MapConfig.noise_model
    objective: str = MapConfig.objective
    n_restarts: int = MapConfig.n_restarts
    seed: int = MapConfig.seed
    hyper_subset: int | None = MapConfig.hyper_subset
    prior_std: float | None = MapConfig.prior_std
    class_weight: str | None = MapConfig.class_weight
    per_tile: bool = False

    def search_gp(
        self,
        kernel: AreaKernel,
        noise: float,
        optimise: bool,
        hyper_subset: int | None,
        hyper_group: int | None = None,
        n_threads: int = 1,
    ) -> SupportGP:
        """The GP that learns hyperparameters with these settings: MSK-GPOM's search, its objective
        per input, its groups on `n_threads` threads."""
        return SupportGP(
            kernel,
            noise=noise,
            noise_bounds=self.noise_bounds,
            noise_model=self.noise_model,
            objective=self.objective,
            optimise=optimise,
            n_restarts=self.n_restarts,
            seed=self.seed,
            hyper_subset=hyper_subset,
            prior_std=self.prior_std,
            class_weight=self.class_weight,
            hyper_group=hyper_group,
            objective_per_input=True,
            n_threads=n_threads,
        )


@dataclass
class TileCells:
    """The cells a tile's GP is fitted on (those meeting its grown square, in canonical order).

    Attributes
    ----------
    lower, upper : ndarray of shape (n, d)
        Boxes.
    counts : ndarray of shape (n,)
        Member points per cell.
    labels : ndarray of shape (n,)
        +1 occupied, -1 free.
    member_points : ndarray of shape (m, d) or None
        Only for the ``"summed"`` area kernel.
    member_offsets : ndarray of int, shape (n + 1,) or None
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    labels: NDArray[np.float64]
    member_points: NDArray[np.float64] | None = None
    member_offsets: NDArray[np.intp] | None = None

    def supports(self) -> Supports:
        """The cells as GP inputs."""
        return Supports(self.lower, self.upper, self.counts, self.member_points, self.member_offsets)

    def signature(self) -> tuple[bytes, ...]:
        """A digest of the cells' bytes (SHA-256 of their boxes, counts and labels; the bytes
        themselves would be the cells again): equal signatures, the same GP (an update refits a
        tile only when it changes)."""
        digest = hashlib.sha256()
        for a in (self.lower, self.upper, self.counts, self.labels):
            digest.update(np.ascontiguousarray(a).tobytes())
            digest.update(str(a.shape).encode())
        return (digest.digest(),)


@dataclass
class TileFitTask:
    """One tile's fit, as it is shipped to a worker (:func:`fit_tile_task`).

    Attributes
    ----------
    key : (int, int)
        Tile index (ix, iy).
    cells : TileCells
    settings : TileSettings
    hyperparameters : dict
        variance, length_scale, noise, alpha, beta: used as they are, or as the start with
        ``settings.per_tile``.
    previous : TileState or None
        This tile's last fit, whose covariances of the cells still there are reused (same
        hyperparameters only); None: every entry computed afresh.
    """

    key: tuple[int, int]
    cells: TileCells
    settings: TileSettings
    hyperparameters: dict[str, float]
    previous: TileState | None = None


def _area_kernel(settings: TileSettings, variance: float, length_scale: float) -> AreaKernel:
    base = make_point_kernel(
        settings.kernel, variance=variance, length_scale=length_scale, length_scale_bounds=settings.length_scale_bounds
    )
    kern = AreaKernel(base, settings.area, settings.normalisation, settings.quadrature_order)
    # Same path as SupportGP's factorisation (clone from log theta), so a one-tile map matches
    # one SupportGP over its cells to the last bits.
    return kern.clone_with_theta(kern.theta)


def _noise_vector(settings: TileSettings, noise: float, counts: NDArray[np.float64]) -> NDArray[np.float64]:
    scale = 1.0 / np.maximum(counts, 1.0) if settings.noise_model == "per_count" else np.ones(counts.size)
    return np.exp(np.log(noise)) * scale


def _box_keys(lower: NDArray[np.float64], upper: NDArray[np.float64]) -> list[bytes]:
    return [row.tobytes() for row in np.ascontiguousarray(np.concatenate([lower, upper], axis=1))]


def _gram_reusing(kern: AreaKernel, X: Supports, previous: TileState, settings: TileSettings) -> NDArray[np.float64] | None:
    """K(X, X), with the entries of cells the previous fit of this tile had copied from it.

    The previous covariance is recovered from its factor (``L L^T`` less its noise and jitter):
    a few matrix products instead of the kernel's quadrature, which is most of a tile fit. The
    copied entries carry rounding of about 1e-15 relative; :meth:`TiledGPOM.refresh` with
    ``exact=True`` refits without them. The caller checks that the hyperparameters are the same.
    None when too little can be reused: a kernel whose entries depend on more than the boxes
    (member points, counts), or fewer than half the cells in common.
    """
    if settings.area == "summed" or settings.normalisation == "sum":
        return None
    old_index = {k: i for i, k in enumerate(_box_keys(previous.posterior.inputs.lower, previous.posterior.inputs.upper))}
    new_keys = _box_keys(X.lower, X.upper)
    pairs = [(j, old_index[k]) for j, k in enumerate(new_keys) if k in old_index]
    if len(pairs) < 0.5 * len(new_keys):
        return None
    keep_new = np.array([j for j, _ in pairs], dtype=np.intp)
    keep_old = np.array([i for _, i in pairs], dtype=np.intp)
    before = previous.posterior
    Lk = before.L[keep_old]
    K = np.empty((len(X), len(X)))
    old_diag = _noise_vector(settings, previous.hyperparameters["noise"], before.inputs.counts[keep_old]) + before.jitter
    K_old = Lk @ Lk.T
    K_old[np.diag_indices_from(K_old)] -= old_diag
    K[np.ix_(keep_new, keep_new)] = K_old
    fresh = np.setdiff1d(np.arange(len(X)), keep_new)
    if fresh.size:
        rows = kern(X.subset(fresh), X)
        K[fresh, :] = rows
        K[:, fresh] = rows.T
        # The fresh-fresh block as the full Gram would give it (symmetrised).
        K[np.ix_(fresh, fresh)] = kern(X.subset(fresh))
    return K


def fit_tile_task(task: TileFitTask) -> TileState:
    """Fit one tile's GP (a top-level function so process pools and Dask can ship it).

    Parameters
    ----------
    task : TileFitTask

    Returns
    -------
    TileState
    """
    t0 = time.perf_counter()
    st = task.settings
    hyp = dict(task.hyperparameters)
    X = task.cells.supports()
    y = np.asarray(task.cells.labels, dtype=float)
    kern = _area_kernel(st, hyp["variance"], hyp["length_scale"])
    if st.per_tile:
        gp = st.search_gp(kern, hyp["noise"], optimise=True, hyper_subset=st.hyper_subset)
        gp.squash = ProbitSquash(hyp["alpha"], hyp["beta"])
        gp.fit(X, y)
        kern, L, weights, jitter = gp.kernel, gp.posterior_.L, gp.posterior_.weights, gp.posterior_.jitter
        hyp = {
            "variance": gp.kernel.base.variance,
            "length_scale": gp.kernel.base.length_scale,
            "noise": gp.noise,
            "alpha": gp.squash.alpha,
            "beta": gp.squash.beta,
        }
    else:
        # Fixed hyperparameters: one factorisation, no leave-one-out pass (alpha and beta are
        # global), which halves the work of SupportGP.fit.
        previous = task.previous
        same_hyp = previous is not None and all(
            previous.hyperparameters.get(n) == hyp[n] for n in ("variance", "length_scale", "noise")
        )
        K = _gram_reusing(kern, X, previous, st) if previous is not None and same_hyp else None
        if K is None:
            K = kern(X)
        L, jitter = noisy_cholesky(K, _noise_vector(st, hyp["noise"], X.counts), lambda: kern(X))
        weights = cholesky_solve(L, y)
    # Member points only where the kernel reads them.
    kept = X if st.area == "summed" else Supports(X.lower, X.upper, X.counts)
    hyp = {k: float(v) for k, v in hyp.items()}
    posterior = GPPosterior(kept, L, weights, kern, ProbitSquash(hyp["alpha"], hyp["beta"]), jitter)
    return TileState((int(task.key[0]), int(task.key[1])), posterior, hyp, time.perf_counter() - t0)


def predict_tile_task(
    state: TileState,
    points: NDArray[np.float64],
    chunk_size: int = 4096,
    variance: bool = True,
    local: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Latent mean and variance of one tile's GP at points (top-level, picklable):
    :meth:`~gpomap.gp.GPPosterior.latent` of its posterior.

    Parameters
    ----------
    state : TileState
    points : ndarray of shape (m, d)
    chunk_size : int
        Query points per block, bounding memory at ``n * chunk_size``.
    variance : bool
        Also the variance (the costly part); False gives None.
    local : bool
        Local prediction where it pays (equal to the dense one to :data:`gpomap.gp.LOCAL_TOL` and
        :data:`gpomap.gp.LOCAL_VARIANCE_TOL`); False: always dense (the reference).

    Returns
    -------
    mean, var : ndarray of shape (m,)
    """
    pts = np.asarray(points, dtype=float).reshape(-1, state.posterior.inputs.dim)
    return state.posterior.latent(Supports.from_points(pts), variance, local, chunk_size)


#: A prediction stage of fewer query points than this over all its tiles (one chunk of
#: :func:`predict_tile_task`; a point in the blend of several tiles counts once for each) runs
#: in this process: its tasks are too small for threads, which then
#: contend for the GIL more than they share the work; larger stages (a benchmark's test points)
#: stay on the threads (docs/choices.md, "Measured for the code").
SMALL_PREDICTION_POINTS: int = 4096


def _few_queries(fn: Callable[..., Any], jobs: list[tuple[tuple[int, int], tuple[Any, ...]]]) -> bool:
    """Whether `jobs` are tile predictions of fewer than :data:`SMALL_PREDICTION_POINTS` points, summed over the tiles."""
    return fn is predict_tile_task and sum(len(args[1]) for _, args in jobs) < SMALL_PREDICTION_POINTS


def _collect(
    futures: dict[cf.Future, tuple[int, int]], bar: Progress, results: MutableMapping[tuple[int, int], Any] | None = None
) -> tuple[MutableMapping[tuple[int, int], Any], dict[tuple[int, int], Exception]]:
    """Each tile's result into `results` (a new dict by default), as its task finishes, and the
    exception of each task that failed."""
    results = {} if results is None else results
    failed: dict[tuple[int, int], Exception] = {}
    for f in cf.as_completed(futures):
        # Each future let go once read: it holds its result (a fit's factor) as long as it lives.
        key = futures.pop(f)
        try:
            results[key] = f.result()
            bar.update()
        except Exception as e:  # reported per tile after the retry
            failed[key] = e
    return results, failed


def _worker_init(blas_threads: int) -> None:
    """Initialiser of the local pool's worker processes."""
    limit_blas_threads(blas_threads)


#: The tasks of each local pool stage running now, by a token: forked workers read them from the
#: memory they inherit (:func:`_inherited_task`) instead of each task's arguments being pickled
#: to them. A prediction stage sends every tile's state (its Cholesky factor: n^2 numbers), which
#: pickled cost a large share of a whole log's CPU (docs/choices.md, "Measured for the code").
_INHERITED: dict[str, tuple[Callable[..., Any], list[tuple[Any, ...]]]] = {}


def _inherited_task(token: str, index: int) -> Any:
    """Run task `index` of the stage `token` of :data:`_INHERITED` (in a forked pool worker)."""
    fn, args = _INHERITED[token]
    return fn(*args[index])


# --------------------------------------------------------------------------- helpers
#: Square-box pairs :func:`nearest_box` bounds at once (its temporaries stay at a few MB: a map
#: can hold thousands of tiles).
NEAREST_BOX_PAIRS: int = 1 << 20


def _axis_gap(lo: NDArray[np.float64], hi: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance along one axis from coordinates `x` to the intervals `lo`..`hi` (0 inside), broadcast."""
    return np.maximum(np.maximum(lo - x, x - hi), 0.0)


def nearest_box(points: NDArray[np.float64], boxes: NDArray[np.float64]) -> NDArray[np.intp]:
    """Index of the box nearest each point in x, y (distance 0 inside; the first box on ties).

    The points are grouped in squares as wide as the widest box. For each square, a box whose
    distance from the square exceeds the least, over boxes, of the farthest a point of the
    square can be from it cannot be nearest to any of its points; the points are measured against
    the few boxes left. A written map's points that no tile reaches are millions, its tiles
    thousands, so every point against every box is minutes; the squares and the boxes alone
    are a few million pairs (docs/choices.md, "Measured for the code").

    Parameters
    ----------
    points : ndarray of shape (m, d)
        Only x and y are used.
    boxes : ndarray of shape (k, 4)
        ``x0, x1, y0, y1`` per box, k >= 1.

    Returns
    -------
    ndarray of int, shape (m,)
    """
    out = np.empty(points.shape[0], dtype=np.intp)
    if points.shape[0] == 0:
        return out
    x, y = points[:, 0], points[:, 1]
    side = max(float(np.max(boxes[:, 1] - boxes[:, 0])), float(np.max(boxes[:, 3] - boxes[:, 2])))
    if not side > 0:
        side = 1.0  # point boxes: any square side gives the same answers
    origin = np.array([x.min(), y.min()])
    ix = np.floor((x - origin[0]) / side).astype(np.int64)
    iy = np.floor((y - origin[1]) / side).astype(np.int64)
    key = ix * (int(iy.max()) + 1) + iy
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    bounds = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1], True])
    first = order[bounds[:-1]]
    squares = np.column_stack([ix[first], iy[first]])
    bx0, bx1, by0, by1 = (boxes[None, :, j] for j in range(4))
    step = max(1, NEAREST_BOX_PAIRS // max(1, boxes.shape[0]))
    for s in range(0, squares.shape[0], step):
        sq = squares[s : s + step]
        sx0 = (origin[0] + sq[:, 0] * side)[:, None]
        sy0 = (origin[1] + sq[:, 1] * side)[:, None]
        sx1, sy1 = sx0 + side, sy0 + side
        # Squared distance from the square to each box (a lower bound for its points), and the
        # farthest its points can be from each box (at a corner: the distance is convex).
        lower = np.maximum(np.maximum(bx0 - sx1, sx0 - bx1), 0.0) ** 2 + np.maximum(np.maximum(by0 - sy1, sy0 - by1), 0.0) ** 2
        upper = (
            np.maximum(_axis_gap(bx0, bx1, sx0), _axis_gap(bx0, bx1, sx1)) ** 2
            + np.maximum(_axis_gap(by0, by1, sy0), _axis_gap(by0, by1, sy1)) ** 2
        )
        # A little slack: the bounds and the points' distances round differently.
        keep = lower <= upper.min(axis=1, keepdims=True) * (1 + 1e-9) + 1e-12
        for j in range(sq.shape[0]):
            cand = np.flatnonzero(keep[j])  # ascending: argmin keeps the first box on ties
            sel = order[bounds[s + j] : bounds[s + j + 1]]
            c = boxes[cand]
            dx = _axis_gap(c[None, :, 0], c[None, :, 1], x[sel, None])
            dy = _axis_gap(c[None, :, 2], c[None, :, 3], y[sel, None])
            out[sel] = cand[np.argmin(dx * dx + dy * dy, axis=1)]
    return out


def _smoothstep(t: NDArray[np.float64]) -> NDArray[np.float64]:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def taper(x: NDArray[np.float64], a: float, b: float, half: float) -> NDArray[np.float64]:
    """1-D partition-of-unity weight of the core interval [a, b].

    Rises from 0 at ``a - half`` to 1 at ``a + half`` and falls back to 0 from ``b - half`` to
    ``b + half`` (smoothstep, C1). With neighbouring cores sharing an edge and ``2 half <= b - a``
    the weights of neighbours sum to exactly one, since s(t) + s(1 - t) = 1.

    Parameters
    ----------
    x : ndarray of shape (m,)
    a, b : float
    half : float
        Half-width of the ramp, > 0.

    Returns
    -------
    ndarray of shape (m,)
    """
    return _smoothstep((x - (a - half)) / (2 * half)) * _smoothstep(((b + half) - x) / (2 * half))


@dataclass
class _BlockCells:
    """The cells of one block (tile square), in tree order."""

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    n_ambiguous: int
    member_points: NDArray[np.float64] | None
    member_offsets: NDArray[np.intp] | None


@dataclass(frozen=True)
class _SpilledPart:
    """Points of a block waiting in a :class:`~gpomap.resources.SpillFile` (a whole log's
    points filed under their blocks would be a gigabyte in memory)."""

    file: SpillFile
    points: tuple[int, int]
    occupied: tuple[int, int]
    shape: tuple[int, int]

    @classmethod
    def put(cls, file: SpillFile, points: NDArray[np.float64], occupied: NDArray[np.bool_]) -> _SpilledPart:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        return cls(
            file, file.put(pts), file.put(np.ascontiguousarray(occupied, dtype=bool)), (int(pts.shape[0]), int(pts.shape[1]))
        )

    def load(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        return self.file.get(self.points, np.float64, self.shape), self.file.get(self.occupied, np.bool_, (self.shape[0],))


class _BlockPoints:
    """The observation points of one block in arrival order; updates append, reads join them once
    (points waiting in a spill file are read back at each read instead, and let go after)."""

    def __init__(self, points: NDArray[np.float64] | _SpilledPart, occupied: NDArray[np.bool_] | None = None) -> None:
        self._parts: list[Any] = [points if isinstance(points, _SpilledPart) else (points, occupied)]
        # Which of the first `_n_checked` points are free within the clearance of a hit among them.
        self._near = np.zeros(0, dtype=bool)
        self._n_checked = 0

    def append(self, points: NDArray[np.float64] | _SpilledPart, occupied: NDArray[np.bool_] | None = None) -> None:
        self._parts.append(points if isinstance(points, _SpilledPart) else (points, occupied))

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        if any(isinstance(p, _SpilledPart) for p in self._parts):
            parts = [p.load() if isinstance(p, _SpilledPart) else p for p in self._parts]
            if len(parts) == 1:
                return parts[0]
            return np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])
        if len(self._parts) > 1:
            self._parts = [(np.concatenate([p for p, _ in self._parts]), np.concatenate([o for _, o in self._parts]))]
        return self._parts[0]

    @property
    def n_cleared(self) -> int:
        """Free points found within the clearance of a hit at the last :meth:`free_near_hits`."""
        return int(self._near.sum())

    def free_near_hits(
        self, clearance: float, arrays: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None
    ) -> NDArray[np.bool_]:
        """:func:`~gpomap.observations.free_near_hits` of the block's points, worked out for the new ones only.

        Hits are only ever added, so a free point once near a hit stays so. Of the points seen
        at the last call, the free ones not yet near a hit are checked against the new hits; the
        new free points against every hit. The answer is the whole computation's, at the cost
        of the points appended since. `arrays`: the block's :meth:`arrays`, when read already.
        """
        points, occupied = self.arrays() if arrays is None else arrays
        n0 = self._n_checked
        if n0 == 0:
            near = free_near_hits(points, occupied, clearance)
        else:
            near = np.zeros(occupied.shape, dtype=bool)
            near[:n0] = self._near
            new_hits = points[n0:][occupied[n0:]]
            if new_hits.size:
                old_free = np.flatnonzero(~occupied[:n0] & ~self._near)
                near[old_free] = _near_any(points[old_free], new_hits, clearance)
            new_free = n0 + np.flatnonzero(~occupied[n0:])
            near[new_free] = _near_any(points[new_free], points[occupied], clearance)
        self._near, self._n_checked = near, int(occupied.size)
        return near


class _HeldParts:
    """A log's labelled points, a part at a time, held until the grid of blocks is known.

    In memory while they come within `budget` bytes; past it every part waits in a temporary
    file instead, and the blocks they are filed under keep theirs in another
    (:attr:`blocks_file`), so that a building's points are never all in memory.
    """

    def __init__(self, budget: int) -> None:
        self.budget = int(budget)
        self._parts: list[Any] = []
        self._bytes = 0
        self._file: SpillFile | None = None
        self.blocks_file: SpillFile | None = None
        self.dim = 2

    def add(self, part: Observations) -> None:
        if part.occupied.size == 0:
            return
        self.dim = int(part.points.shape[1])
        self._bytes += int(part.points.nbytes + part.occupied.nbytes)
        if self._file is None and self._bytes > self.budget:
            self._file, self.blocks_file = SpillFile(), SpillFile()
            self._parts = [_SpilledPart.put(self._file, p, o) for p, o in self._parts]
        self._parts.append(
            _SpilledPart.put(self._file, part.points, part.occupied) if self._file is not None else (part.points, part.occupied)
        )

    def parts(self) -> Iterator[Observations]:
        """The parts in order, each read back (if it waited in the file) as it is asked."""
        for p in self._parts:
            points, occupied = p.load() if isinstance(p, _SpilledPart) else p
            yield Observations(points, occupied, np.zeros(0, dtype=np.int32))

    def close(self) -> None:
        self._parts = []
        if self._file is not None:
            self._file.close()


def _near_any(free: NDArray[np.float64], hits: NDArray[np.float64], clearance: float) -> NDArray[np.bool_]:
    """Which of the free points, shape (m, d), lie within `clearance` of one of the hits, shape (h, d)."""
    if free.shape[0] == 0 or hits.shape[0] == 0:
        return np.zeros(free.shape[0], dtype=bool)
    both = np.concatenate([free, hits])
    occupied = np.concatenate([np.zeros(free.shape[0], bool), np.ones(hits.shape[0], bool)])
    return free_near_hits(both, occupied, clearance)[: free.shape[0]]


# --------------------------------------------------------------------------- estimator
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

    # ------------------------------------------------------------------ settings
    def _settings(self) -> TileSettings:
        b = self.base
        # Every field but these two is the map setting of the same name.
        same = {f.name: getattr(b, f.name) for f in fields(TileSettings) if f.name not in ("area", "per_tile")}
        return TileSettings(area=b.area_method, per_tile=self.per_tile_hyperparameters, **same)

    @property
    def n_workers_(self) -> int:
        """Local workers used."""
        return int(self.n_workers) if self.n_workers is not None else max(1, os.cpu_count() or 1)

    # ------------------------------------------------------------------ geometry
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

    # ------------------------------------------------------------------ cells
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

    # ------------------------------------------------------------------ hyperparameters
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

    # ------------------------------------------------------------------ task running
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

    # ------------------------------------------------------------------ fitting
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

    # ------------------------------------------------------------------ prediction
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

    # ------------------------------------------------------------------ reporting
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
