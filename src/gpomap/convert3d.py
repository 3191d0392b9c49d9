"""From an OctoMap octree to a continuous GP occupancy map: :mod:`gpomap.convert` in 3-D.

An octree already says which voxels are free and which occupied; its leaves are cubes of the
tree's resolution or, where pruning merged eight equal children, of a power of two times it. Each
known leaf is split into the resolution-sized voxels it covers (:meth:`Octree.voxel_centres`), and
each voxel becomes one labelled point at its centre, exactly as :func:`gpomap.convert.grid_to_observations`
makes one point per known pixel; unknown space gives no point. The cell tree then merges
neighbourhoods of same-label voxels into boxes, :class:`gpomap.convert.GridGPOM` widens every box by
half a voxel so that it covers its voxels' cubes (a voxel is a volume observation), the SE GP with
the exact box kernel is fitted with :func:`gpomap.convert.model_defaults` (cell sizes and length
scale in source voxels), and the map is sampled on a voxel grid of any resolution.

Size. One GP holds a few thousand cells, and a real octree gives tens or hundreds of thousands
(docs/convert.md, "OctoMap trees, whole"). A region whose
cells one GP holds (at most ``max_cells``) is converted by one GP, trained on the known voxels
inside it grown by a margin of :data:`MARGIN_VOXELS` voxels (so the map at the region's faces sees
the data beyond them). A larger one, up to the whole tree, is converted in tiles
(:class:`TiledOctreeModel`): the cells and the hyperparameters once, then square columns fitted,
predicted and let go one after another, blended as :class:`~gpomap.tiles.TiledGPOM` blends its
tiles, so memory holds the cells, the output and the tiles in flight, not every tile's GP.

Agreement is measured as in 2-D: the fraction of the source's known voxels inside the region whose
ternary label the continuous map keeps, per class, and the ROC AUC of the map's probability at
their centres against their labels (on a seeded sample of at most ``max_check`` voxels).
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, Literal, Union, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr

from gpomap.config import DEFAULT_MAX_CELLS  # most cells of the one GP of a conversion, as for maps
from gpomap.convert import FOOTPRINT_PIXELS, GridGPOM, _agreement, model_defaults
from gpomap.errors import EmptyDataError, GpomapError
from gpomap.fusion import ternary_thresholds
from gpomap.io.octomap import Octree, read_octree
from gpomap.kernels.point import make_point_kernel
from gpomap.lattice import coarse, extent_bounds, in_box, interpolate, interpolation_block
from gpomap.observations import Observations
from gpomap.progress import progress
from gpomap.resources import largest_tile_cells, peak_rss_mb
from gpomap.supports import Supports
from gpomap.tiles import (
    BLEND_FRACTION,
    BLOCK_SIZE,
    DEFAULT_HYPER_SAMPLE,
    HYPER_GROUP_CELLS,
    HYPER_NAMES,
    TileCells,
    TileFitTask,
    TileSettings,
    fit_tile_task,
    given_hyperparameters,
    hyper_anchor_block,
    predict_tile_task,
    taper,
    tile_reach,
)
from gpomap.voxels import VoxelMap, VoxelSpec

__all__ = [
    "OctreeConversion",
    "TiledOctreeModel",
    "octree_to_observations",
    "convert_octree",
    "region",
    "MARGIN_VOXELS",
    "DEFAULT_MAX_CELLS",
    "TILE_SIDES",
    "VARIANCE_STEP_SOURCE_VOXELS",
]

OctreeSource = Union[Octree, str, "os.PathLike[str]"]

#: The training region reaches this many source voxels past the converted region on every side.
MARGIN_VOXELS = 4
#: Known voxels scored for the agreement, at most (a seeded sample beyond).
MAX_CHECK = 200_000


@dataclass
class OctreeConversion:
    """The continuous map made from an octree, the model behind it, and what was measured.

    Attributes
    ----------
    map : VoxelMap
        Probability and latent variance, ndarrays of shape (nz, ny, nx).
    model : GridGPOM or TiledOctreeModel
        The fitted estimator, one GP or tiles fitted when asked (``predict_proba(points)``
        anywhere, points of shape (m, 3)).
    report : dict
        ``leaves`` (``n``, ``occupied``, ``free`` of the whole tree), ``voxels`` (known source
        voxels trained on: ``free``, ``occupied``), ``region`` (``lower``, ``upper`` of the
        converted box and of the training box), ``cells`` (``n``, ``occupied``, ``ambiguous``,
        ``min_cell``, ``max_cell``), ``hyperparameters``, ``agreement`` (``ternary``, ``free``,
        ``occupied``, ``auc``, ``n_checked``, ``n_known``), ``grid`` (``origin``, ``resolution``,
        ``shape``) and ``timings`` (seconds: ``read``, ``observations``, ``fit``, ``prediction``,
        ``agreement``, ``total``).
    """

    map: VoxelMap
    model: GridGPOM | TiledOctreeModel
    report: dict[str, Any] = field(default_factory=dict)


def _inside(points: NDArray[np.float64], lower: NDArray[np.float64], upper: NDArray[np.float64]) -> NDArray[np.bool_]:
    return in_box(points, lower, upper)


def octree_to_observations(
    tree: Octree, lower: ArrayLike | None = None, upper: ArrayLike | None = None
) -> tuple[Observations, NDArray[np.float64]]:
    """Known voxels of an octree (inside a box) as labelled points at their centres.

    Parameters
    ----------
    tree : Octree
    lower, upper : array_like of shape (3,), optional
        Keep the voxels whose centre lies in this box (default: all).

    Returns
    -------
    observations : Observations
        ``points`` of shape (n, 3), occupied voxels first, ``occupied`` of shape (n,),
        ``scan_index`` all 0.
    centres : ndarray of shape (n, 3)
        The same points (for callers that score at them).

    Raises
    ------
    EmptyDataError
        No known voxel in the box, or only one class of them.
    """
    occ = tree.voxel_centres(True)
    free = tree.voxel_centres(False)
    if lower is not None and upper is not None:
        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        occ, free = occ[_inside(occ, lo, hi)], free[_inside(free, lo, hi)]
    where = "" if lower is None else " in the region"
    if len(occ) == 0 or len(free) == 0:
        raise EmptyDataError(
            f"the octree has {len(occ)} occupied and {len(free)} free voxels{where}: "
            "a GP occupancy map needs both free and occupied ones"
        )
    points = np.concatenate([occ, free])
    occupied = np.concatenate([np.ones(len(occ), dtype=bool), np.zeros(len(free), dtype=bool)])
    obs = Observations(points=points, occupied=occupied, scan_index=np.zeros(len(points), dtype=np.intp))
    return obs, points


def region(tree: Octree, lower: ArrayLike | None, upper: ArrayLike | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The converted box: the tree's extent, with the given corners' finite values in place."""
    lo, hi = tree.extent()
    lo, hi = lo.astype(float).copy(), hi.astype(float).copy()
    for given, out in ((lower, lo), (upper, hi)):
        if given is not None:
            g = np.asarray(given, dtype=float).reshape(3)
            out[np.isfinite(g)] = g[np.isfinite(g)]
    if not (hi > lo).all():
        raise GpomapError(f"the region to convert is empty: x, y, z from {lo.tolist()} to {hi.tolist()}")
    return lo, hi


#: Tile sides tried for a tree too large for one GP, largest first (metres): the first whose
#: densest column's GP holds at most ``max_cells`` cells. 3 m is a voxel map's tile
#: (:data:`gpomap.tiles.DEFAULT_TILE_SIZE`); an octree's known voxels are denser than a map's
#: cells, so most trees take a smaller one (docs/convert.md, "OctoMap trees, whole").
TILE_SIDES: tuple[float, ...] = (3.0, 2.0, 1.5, 1.0, 0.75, 0.5)
#: A tiled conversion predicts the latent mean at every output voxel, and the latent variance
#: this many source voxels apart (at least every output voxel), interpolated trilinearly: the
#: variance is most of a prediction's cost and varies with the distance to the data, which come
#: at the source's pitch, not with the walls' detail the mean carries (docs/convert.md).
VARIANCE_STEP_SOURCE_VOXELS = 1
#: Output voxel layers per band of the final interpolation and squash (bounds their temporaries).
BAND_LAYERS = 8


@dataclass
class _Queries:
    """What a tiled prediction is asked for: a voxel grid, points, or both.

    Attributes
    ----------
    spec : VoxelSpec or None
        The latent mean at every voxel centre, the variance on :attr:`coarse`.
    coarse : VoxelSpec or None
        The lattice the variance is predicted on, spanning `spec` (:func:`gpomap.lattice.coarse`).
    points : ndarray of shape (m, 3)
        Points predicted exactly (mean and variance).
    """

    spec: VoxelSpec | None
    coarse: Any
    points: NDArray[np.float64]


class TiledOctreeModel:
    """The continuous map of an octree too large for one GP: tiles fitted when asked and let go.

    The cells of the whole tree are built once (:meth:`gpomap.convert.GridGPOM.make_cells`, as a
    single-GP conversion builds them), and the hyperparameters learnt once on a compact sample of
    them, as :class:`~gpomap.tiles.TiledGPOM` learns a map's. A prediction (a voxel grid,
    :meth:`voxels`, or points, :meth:`predict_proba`) then runs tile by tile over square
    columns of side :attr:`tile_size_` spanning every height: each tile's GP is fitted on the
    cells meeting its square grown by the overlap (:func:`gpomap.tiles.fit_tile_task`), predicts
    the queries within its blend region, with the smoothstep weights of
    :class:`~gpomap.tiles.TiledGPOM` (:func:`gpomap.tiles.taper`), and is let go. Memory is the
    cells, the output, and the tiles in flight (``n_workers`` at most), whatever the tree's size.

    Every tile of the lattice over the queries takes part, a tile with no cells in its reach
    predicting the GP prior (mean 0, the signal variance), so the weights sum to one everywhere.
    With the alpha and beta learnt globally, a query's probability is the squash of its blended
    latent mean and variance, exactly as in a TiledGPOM.

    Parameters
    ----------
    base : GridGPOM
        The settings (kernel, cells, search), unfitted.
    tile_size : float, optional
        Column side, metres; default the first of :data:`TILE_SIDES` whose densest column holds at
        most `max_cells` cells.
    max_cells : int
        Most cells one tile's GP should hold.
    hyper_sample : int, optional
        Cells of the compact hyperparameter sample; default :data:`gpomap.tiles.DEFAULT_HYPER_SAMPLE` (3-D).
    n_workers : int
        Tiles fitted and predicted at once, on threads.
    """

    def __init__(
        self,
        base: GridGPOM,
        tile_size: float | None = None,
        max_cells: int = DEFAULT_MAX_CELLS,
        hyper_sample: int | None = None,
        n_workers: int = 1,
    ) -> None:
        if tile_size is not None and not tile_size > 0:
            raise ValueError(f"tile_size must be positive, got {tile_size}")
        if n_workers < 1:
            raise ValueError(f"n_workers must be at least 1, got {n_workers}")
        self.base = base
        self.tile_size = tile_size
        self.max_cells = int(max_cells)
        self.hyper_sample = hyper_sample
        self.n_workers = int(n_workers)

    # ------------------------------------------------------------------ fitting
    def fit(self, obs: Observations, hyperparameters: dict[str, float] | None = None) -> TiledOctreeModel:
        """Build the cells, learn the hyperparameters (unless given) and choose the tiles.

        Parameters
        ----------
        obs : Observations
            Known voxel centres (:func:`octree_to_observations`), points of shape (n, 3).
        hyperparameters : dict, optional
            variance, length_scale, noise, alpha and beta to use as they are.

        Returns
        -------
        self

        Raises
        ------
        GpomapError
            Even the smallest of :data:`TILE_SIDES` leaves a column with more than ``max_cells`` cells.
        """
        t0 = time.perf_counter()
        cells = self.base.make_cells(obs)
        supports = cells.to_supports()
        self.lower_, self.upper_ = supports.lower, supports.upper
        self.counts_ = np.asarray(supports.counts, dtype=float)
        self.labels_ = np.asarray(cells.labels, dtype=float)
        self.n_ambiguous_ = int(cells.ambiguous.sum())
        self.origin_ = (float(obs.points[:, 0].min()), float(obs.points[:, 1].min()))
        self.timings_: dict[str, float] = {"cells": time.perf_counter() - t0}
        t = time.perf_counter()
        if hyperparameters is None:
            self.hyperparameters_ = self._learn_hyperparameters()
            self.hyper_source_ = dict(self._sample_report)
        else:
            self.hyperparameters_ = given_hyperparameters(hyperparameters)
            self.hyper_source_ = {"how": "given to fit()"}
        self.hyperparameters_.setdefault("variance_scale", 1.0)
        self.timings_["hyperparameters"] = time.perf_counter() - t
        self._choose_tiles()
        # Octree voxels are not rays: no held-out stretches, no variance scale (as GridGPOM).
        self.extrapolation_: dict[str, Any] = {"kappa": 1.0, "reason": "labelled voxels given, not scans"}
        return self

    @property
    def n_inputs_(self) -> int:
        """Number of cells over the whole tree."""
        return int(self.labels_.size)

    @property
    def thresholds_(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities."""
        return ternary_thresholds(self.base.thresholds, None)

    def _settings(self) -> TileSettings:
        b = self.base
        same = {f.name: getattr(b, f.name) for f in fields(TileSettings) if f.name not in ("area", "per_tile")}
        return TileSettings(area=b.area_method, **same)

    def _learn_hyperparameters(self) -> dict[str, float]:
        """All five hyperparameters, on the compact sample a TiledGPOM of these cells would take."""
        centres = 0.5 * (self.lower_ + self.upper_)
        block = np.floor((centres[:, :2] - np.asarray(self.origin_)) / BLOCK_SIZE).astype(np.int64)
        keys, inverse = np.unique(block[:, 0] * (1 << 32) + block[:, 1], return_inverse=True)
        sizes = np.bincount(inverse, minlength=keys.size)
        occupied = np.bincount(inverse, weights=(self.labels_ > 0).astype(float), minlength=keys.size) / sizes
        anchor_block = hyper_anchor_block(sizes, occupied, float(np.mean(self.labels_ > 0)))
        anchor = centres[inverse == anchor_block].mean(axis=0)
        k = self.hyper_sample if self.hyper_sample is not None else DEFAULT_HYPER_SAMPLE[3]
        n = self.labels_.size
        d = np.sum((centres - anchor) ** 2, axis=1)
        idx = np.arange(n) if n <= k else np.sort(np.argpartition(d, k - 1)[:k])
        b = self.base
        gp = self._settings().search_gp(
            b.make_kernel(), b.noise, optimise=b.optimise, hyper_subset=None, hyper_group=HYPER_GROUP_CELLS[3]
        )
        gp.fit(Supports(self.lower_[idx], self.upper_[idx], self.counts_[idx]), self.labels_[idx])
        self._sample_report = {
            "how": "learnt" if b.optimise else "given (alpha, beta fitted)",
            "sample_cells": int(idx.size),
            "sample_centre": [round(float(v), 2) for v in anchor],
            "sample_radius_m": round(float(np.sqrt(d[idx].max())), 2),
            "sample_occupied_fraction": round(float(np.mean(self.labels_[idx] > 0)), 4),
        }
        return {
            "variance": float(gp.kernel.base.variance),
            "length_scale": float(gp.kernel.base.length_scale),
            "noise": float(gp.noise),
            "alpha": float(gp.squash.alpha),
            "beta": float(gp.squash.beta),
        }

    def _choose_tiles(self) -> None:
        """The tile side (given, or the first of :data:`TILE_SIDES` within ``max_cells``), the overlap and the blend."""
        centres = 0.5 * (self.lower_ + self.upper_)
        ell = self.hyperparameters_["length_scale"]
        sides = (self.tile_size,) if self.tile_size is not None else TILE_SIDES
        for side in sides:
            assert side is not None
            overlap = tile_reach(side, ell)
            largest = largest_tile_cells(centres[:, :2], side, overlap, self.origin_)
            if largest <= self.max_cells or self.tile_size is not None:
                break
        else:
            raise GpomapError(
                f"the densest {side:g} m column of the tree holds {largest} cells, more than one GP holds ({self.max_cells}); "
                "raise --max-cells (max_cells) if the machine has the memory, or convert a smaller region (--extent, --z-range)"
            )
        self.tile_size_ = float(side)
        self.overlap_ = float(overlap)
        self.blend_ = float(BLEND_FRACTION * min(overlap, side))
        self.largest_tile_cells_ = int(largest)
        # Cells by the column holding their centre, so each tile looks at its neighbours' only.
        col = np.floor((centres[:, :2] - np.asarray(self.origin_)) / side).astype(np.int64)
        order = np.lexsort((col[:, 1], col[:, 0]))
        keys = col[order]
        starts = np.flatnonzero(np.r_[True, (np.diff(keys, axis=0) != 0).any(axis=1)])
        stops = np.r_[starts[1:], order.size]
        self._by_column = {(int(keys[a, 0]), int(keys[a, 1])): order[a:b] for a, b in zip(starts, stops, strict=True)}
        half = 0.5 * float(np.max(self.upper_[:, :2] - self.lower_[:, :2])) if self.labels_.size else 0.0
        self._reach_columns = math.ceil((overlap + half) / side)

    # ------------------------------------------------------------------ tiles
    def _core(self, key: tuple[int, int]) -> tuple[float, float, float, float]:
        t = self.tile_size_
        x0, y0 = self.origin_[0] + key[0] * t, self.origin_[1] + key[1] * t
        return x0, x0 + t, y0, y0 + t

    def _tile_cells(self, key: tuple[int, int]) -> TileCells | None:
        """The cells meeting the tile's square grown by the overlap, in the cells' order (None: none)."""
        x0, x1, y0, y1 = self._core(key)
        o, r = self.overlap_, self._reach_columns
        near = [
            self._by_column[c]
            for c in ((key[0] + i, key[1] + j) for i in range(-r, r + 1) for j in range(-r, r + 1))
            if c in self._by_column
        ]
        if not near:
            return None
        idx = np.sort(np.concatenate(near))
        lo, hi = self.lower_[idx], self.upper_[idx]
        keep = (lo[:, 0] <= x1 + o) & (hi[:, 0] >= x0 - o) & (lo[:, 1] <= y1 + o) & (hi[:, 1] >= y0 - o)
        if not keep.any():
            return None
        idx = idx[keep]
        return TileCells(self.lower_[idx], self.upper_[idx], self.counts_[idx], self.labels_[idx])

    def _tiles_over(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> list[tuple[int, int]]:
        """The tiles whose blend region meets the box [lo, hi] in x, y."""
        t, h = self.tile_size_, 0.5 * self.blend_
        rx = range(math.floor((lo[0] - self.origin_[0] - h) / t), math.ceil((hi[0] - self.origin_[0] + h) / t))
        ry = range(math.floor((lo[1] - self.origin_[1] - h) / t), math.ceil((hi[1] - self.origin_[1] + h) / t))
        return [(ix, iy) for ix in rx for iy in ry]

    def _blend_box(self, key: tuple[int, int]) -> tuple[float, float, float, float]:
        x0, x1, y0, y1 = self._core(key)
        h = 0.5 * self.blend_
        return x0 - h, x1 + h, y0 - h, y1 + h

    def _weights(self, key: tuple[int, int], x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """The tile's blend weight at (x, y), each of shape (m,) (or broadcasting)."""
        x0, x1, y0, y1 = self._core(key)
        h = 0.5 * self.blend_
        return taper(x, x0, x1, h) * taper(y, y0, y1, h)

    def _predict(
        self, queries: _Queries, desc: str
    ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64]]:
        """Blended latent moments: the mean at every voxel of ``queries.spec`` and the variance on
        ``queries.coarse`` (or None, None without a grid), the mean and variance at ``queries.points``."""
        pts = queries.points
        spec, coarse = queries.spec, queries.coarse
        boxes = [pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)] if pts.size else []
        if coarse is not None:
            boxes += [np.asarray(coarse.origin[:2]), np.asarray(coarse.upper[:2])]
        lo, hi = np.min(boxes, axis=0), np.max(boxes, axis=0)
        tiles = self._tiles_over(lo, hi)
        mean_grid = np.zeros(spec.shape) if spec is not None else None
        var_grid = np.zeros(coarse.shape) if coarse is not None else None
        p_mean, p_var, p_wsum = np.zeros(len(pts)), np.zeros(len(pts)), np.zeros(len(pts))
        axes = {}
        for name, g in (("fine", spec), ("coarse", coarse)):
            if g is not None:
                axes[name] = (g.axis_centres("x"), g.axis_centres("y"), g.axis_centres("z"))
        prior_var = float(self.hyperparameters_["variance"])
        settings = self._settings()
        hyp = {k: self.hyperparameters_[k] for k in HYPER_NAMES}
        chunk = self.base.chunk_size
        seconds = {"fit": 0.0, "predict": 0.0}
        n_fitted = 0

        def in_box(key: tuple[int, int]) -> dict[str, Any]:
            bx0, bx1, by0, by1 = self._blend_box(key)
            sel: dict[str, Any] = {"fine": None, "coarse": None}
            for name, (xs, ys, _) in axes.items():
                ix = np.flatnonzero((xs > bx0) & (xs < bx1))
                iy = np.flatnonzero((ys > by0) & (ys < by1))
                sel[name] = (ix, iy) if ix.size and iy.size else None
            ip = (
                np.flatnonzero((pts[:, 0] > bx0) & (pts[:, 0] < bx1) & (pts[:, 1] > by0) & (pts[:, 1] < by1))
                if pts.size
                else np.zeros(0, dtype=np.intp)
            )
            sel["points"] = ip
            return sel

        def block_points(name: str, ix: NDArray[np.intp], iy: NDArray[np.intp]) -> NDArray[np.float64]:
            xs, ys, zs = axes[name]
            z, y, x = np.meshgrid(zs, ys[iy], xs[ix], indexing="ij")
            return np.column_stack([x.ravel(), y.ravel(), z.ravel()])

        def work(key: tuple[int, int], sel: dict[str, Any]) -> tuple[Any, ...] | None:
            """The tile's moments at its queries (None: no cells in its reach, the prior's)."""
            cells = self._tile_cells(key)
            if cells is None:
                return None
            t = time.perf_counter()
            state = fit_tile_task(TileFitTask(key, cells, settings, hyp))
            t_fit = time.perf_counter() - t
            t = time.perf_counter()
            mu_f = var_c = pm = pv = None
            if sel["fine"] is not None:
                mu_f, _ = predict_tile_task(state, block_points("fine", *sel["fine"]), chunk, variance=False)
            if sel["coarse"] is not None:
                _, var_c = predict_tile_task(state, block_points("coarse", *sel["coarse"]), chunk, variance=True)
            if sel["points"].size:
                pm, pv = predict_tile_task(state, pts[sel["points"]], chunk, variance=True)
            return mu_f, var_c, pm, pv, t_fit, time.perf_counter() - t

        def accumulate(key: tuple[int, int], sel: dict[str, Any], out: tuple[Any, ...] | None) -> None:
            nonlocal n_fitted
            mu_f = var_c = pm = pv = None
            if out is not None:
                mu_f, var_c, pm, pv, t_fit, t_pred = out
                seconds["fit"] += t_fit
                seconds["predict"] += t_pred
                n_fitted += 1
            if sel["fine"] is not None and mean_grid is not None and mu_f is not None:
                ix, iy = sel["fine"]
                xs, ys, _ = axes["fine"]
                w = self._weights(key, xs[ix][None, :], ys[iy][:, None])
                mean_grid[:, iy[0] : iy[-1] + 1, ix[0] : ix[-1] + 1] += w[None] * mu_f.reshape(-1, iy.size, ix.size)
            if sel["coarse"] is not None and var_grid is not None:
                ix, iy = sel["coarse"]
                xs, ys, _ = axes["coarse"]
                w = self._weights(key, xs[ix][None, :], ys[iy][:, None])
                v = prior_var if var_c is None else var_c.reshape(-1, iy.size, ix.size)
                var_grid[:, iy[0] : iy[-1] + 1, ix[0] : ix[-1] + 1] += w[None] * v
            ip = sel["points"]
            if ip.size:
                w = self._weights(key, pts[ip, 0], pts[ip, 1])
                p_wsum[ip] += w
                if pm is not None:
                    p_mean[ip] += w * pm
                p_var[ip] += w * (prior_var if pv is None else pv)

        jobs = [(key, in_box(key)) for key in tiles]
        jobs = [(k, s) for k, s in jobs if s["fine"] is not None or s["coarse"] is not None or s["points"].size]
        with progress(len(jobs), desc, "tile") as bar:
            if self.n_workers <= 1:
                for key, sel in jobs:
                    accumulate(key, sel, work(key, sel))
                    bar.update()
            else:
                # At most n_workers tiles in flight; results added in the tiles' order (the same sums).
                with cf.ThreadPoolExecutor(self.n_workers) as pool:
                    waiting: collections.deque[tuple[tuple[int, int], dict[str, Any], cf.Future[Any]]] = collections.deque()
                    for key, sel in jobs:
                        waiting.append((key, sel, pool.submit(work, key, sel)))
                        if len(waiting) >= self.n_workers:
                            k, s, f = waiting.popleft()
                            accumulate(k, s, f.result())
                            bar.update()
                    while waiting:
                        k, s, f = waiting.popleft()
                        accumulate(k, s, f.result())
                        bar.update()
        if pts.size and not np.allclose(p_wsum, 1.0):
            raise AssertionError("tile weights do not sum to one")  # the tapers are a partition of unity
        self.last_prediction_ = {
            "tiles": len(jobs),
            "tiles_fitted": n_fitted,
            "fit_seconds": seconds["fit"],
            "predict_seconds": seconds["predict"],
        }
        return mean_grid, var_grid, p_mean, p_var

    def _squash(self, mean: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
        a, b = self.hyperparameters_["alpha"], self.hyperparameters_["beta"]
        return np.asarray(ndtr((a * mean + b) / np.sqrt(1.0 + a * a * var)))

    # ------------------------------------------------------------------ prediction
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
        """Occupancy probability at points, blended across tiles (each fitted for it and let go).

        Parameters
        ----------
        points : ndarray of shape (m, 3)
        return_var : bool
            Also return the blended latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        _, _, mean, var = self._predict(_Queries(None, None, pts), "predicting tiles")
        p = self._squash(mean, var)
        return (p, var) if return_var else p

    def voxels(
        self, resolution: float, extent: tuple[float, ...], points: NDArray[np.float64] | None = None
    ) -> tuple[VoxelMap, NDArray[np.float64]]:
        """The map on a voxel grid, and the probability at `points`, in one pass over the tiles.

        Parameters
        ----------
        resolution : float
            Voxel side, metres.
        extent : (xmin, xmax, ymin, ymax, zmin, zmax)
            Voxel faces on multiples of `resolution` (as :meth:`gpomap.estimator.GPMapEstimator.voxels`).
        points : ndarray of shape (m, 3), optional
            Points whose probability is wanted too (predicted exactly, not interpolated).

        Returns
        -------
        VoxelMap
            Probability and latent variance of shape (nz, ny, nx): the mean at every voxel, the
            variance at the source's voxel pitch (:data:`VARIANCE_STEP_SOURCE_VOXELS`), interpolated.
        ndarray of shape (m,)
            The probability at `points`.
        """
        lo, hi = extent_bounds(extent)
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        source_pitch = 2.0 * self.base.pixel_pad
        step = max(1, round(VARIANCE_STEP_SOURCE_VOXELS * source_pitch / resolution)) if source_pitch > 0 else 1
        coarse_spec = coarse(spec, step)
        assert isinstance(coarse_spec, VoxelSpec)  # the coarse lattice of a voxel grid is one
        pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=float).reshape(-1, 3)
        mean, var_c, p_mean, p_var = self._predict(_Queries(spec, coarse_spec, pts), "converting tiles")
        assert mean is not None and var_c is not None
        # The squash in bands of layers, the variance interpolated band by band: the mean's array
        # becomes the probability's, and the temporaries stay a band's.
        variance = np.empty(spec.shape)
        for k0 in range(0, spec.shape[0], BAND_LAYERS):
            k1 = min(k0 + BAND_LAYERS, spec.shape[0])
            band = VoxelSpec(
                (spec.origin[0], spec.origin[1], spec.origin[2] + k0 * resolution), resolution, (k1 - k0, *spec.shape[1:])
            )
            src = interpolation_block(coarse_spec, band)
            sz, sy, sx = src[0], src[1], src[2]
            pitch = coarse_spec.resolution
            sub = VoxelSpec(
                (
                    coarse_spec.origin[0] + sx.start * pitch,
                    coarse_spec.origin[1] + sy.start * pitch,
                    coarse_spec.origin[2] + sz.start * pitch,
                ),
                pitch,
                (sz.stop - sz.start, sy.stop - sy.start, sx.stop - sx.start),
            )
            variance[k0:k1] = interpolate(var_c[src], sub, band)
            mean[k0:k1] = self._squash(mean[k0:k1], variance[k0:k1])
        del var_c
        info = self.summary()
        return VoxelMap(spec, mean, variance, thresholds=self.thresholds_, info=info), self._squash(p_mean, p_var)

    def summary(self) -> dict[str, Any]:
        """Tiles, cells, hyperparameters and where they came from, timings, peak memory."""
        return {
            "method": "msk-gpom",
            "kernel": make_point_kernel(self.base.kernel).name,
            "area": self.base.area_method,
            "tiled": True,
            "tile_size": self.tile_size_,
            "tile_origin": list(self.origin_),
            "overlap": self.overlap_,
            "blend": self.blend_,
            "largest_tile_cells": self.largest_tile_cells_,
            "n_cells": self.n_inputs_,
            "n_ambiguous_cells": self.n_ambiguous_,
            "hyperparameters": dict(self.hyperparameters_),
            "hyperparameter_source": dict(self.hyper_source_),
            "last_prediction": dict(getattr(self, "last_prediction_", {})),
            "thresholds": list(self.thresholds_),
            "timings": dict(self.timings_),
            "peak_memory": peak_rss_mb(),
        }


def convert_octree(
    source: OctreeSource,
    resolution: float | None = None,
    lower: ArrayLike | None = None,
    upper: ArrayLike | None = None,
    max_cells: int | None = DEFAULT_MAX_CELLS,
    max_check: int = MAX_CHECK,
    seed: int = 0,
    before_fit: Callable[[int], None] | None = None,
    tile_size: float | None = None,
    hyperparameters: dict[str, float] | None = None,
    n_workers: int = 1,
    **model_options: Any,
) -> OctreeConversion:
    """Turn an OctoMap octree (or a region of it) into a continuous GP map, sampled on voxels.

    Parameters
    ----------
    source : Octree, or path to a ``.bt`` / ``.ot`` file
    resolution : float, optional
        Output voxel side, metres; default the tree's.
    lower, upper : array_like of shape (3,), optional
        Corners (x, y, z) of the region to convert (default the tree's extent; a non-finite value
        keeps the tree's bound on that axis).
    max_cells : int or None
        Most cells of one GP: a region with more is converted in tiles (:class:`TiledOctreeModel`)
        whose GPs each hold at most this many. None: one GP whatever the size.
    max_check : int
        Known voxels scored for the agreement, at most.
    seed : int
        Seed of that sample.
    before_fit : callable, optional
        Called with the most cells one GP will hold (the region's, or the largest tile's) before
        any GP is fitted (a memory check may raise there).
    tile_size : float, optional
        Convert in tiles of this side (metres) whatever the region's size; default only when the
        cells are more than `max_cells`, of the side :class:`TiledOctreeModel` chooses.
    hyperparameters : dict, optional
        variance, length_scale, noise, alpha and beta, used as they are by a tiled conversion (a
        single GP takes its starting values from `model_options`).
    n_workers : int
        Tiles in flight at once (threads).
    **model_options
        :class:`~gpomap.convert.GridGPOM` arguments overriding :func:`gpomap.convert.model_defaults`.

    Returns
    -------
    OctreeConversion

    Raises
    ------
    EmptyDataError
        No known voxels (or one class only) in the training region.
    GpomapError
        An empty region, or a column too dense for `max_cells` even in the smallest tiles.
    InputFormatError
        The file cannot be read (see :func:`gpomap.io.octomap.read_octree`).
    """
    t_start = time.perf_counter()
    tree = source if isinstance(source, Octree) else read_octree(source)
    t_read = time.perf_counter() - t_start
    res = tree.resolution
    lo, hi = region(tree, lower, upper)
    margin = MARGIN_VOXELS * res
    t = time.perf_counter()
    obs, _ = octree_to_observations(tree, lo - margin, hi + margin)
    options = model_defaults(res)
    options["pixel_pad"] = FOOTPRINT_PIXELS * res
    options.update(model_options)
    settings = GridGPOM(**options)
    cells = settings.make_cells(obs)
    t_obs = time.perf_counter() - t
    tiled = tile_size is not None or (max_cells is not None and len(cells) > max_cells)
    out = resolution if resolution is not None else res
    extent = tuple(float(v) for pair in zip(lo, hi) for v in pair)
    check = _inside(obs.points, lo, hi)
    idx = np.flatnonzero(check)
    if idx.size > max_check:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_check, replace=False))
    model: GridGPOM | TiledOctreeModel
    if tiled:
        limit = DEFAULT_MAX_CELLS if max_cells is None else max_cells
        model = TiledOctreeModel(settings, tile_size=tile_size, max_cells=limit, n_workers=n_workers)
        t = time.perf_counter()
        model.fit(obs, hyperparameters)
        t_fit = time.perf_counter() - t
        if before_fit is not None:
            before_fit(model.largest_tile_cells_)
        t = time.perf_counter()
        voxel_map, p_check = model.voxels(out, extent, obs.points[idx])
        t_pred = time.perf_counter() - t
        t_agree = 0.0  # scored in the same pass over the tiles
    else:
        if before_fit is not None:
            before_fit(len(cells))
        model = settings
        t = time.perf_counter()
        model.fit(obs)
        t_fit = time.perf_counter() - t
        t = time.perf_counter()
        voxel_map = model.grid(out, extent)
        t_pred = time.perf_counter() - t
        t = time.perf_counter()
        p_check = model.predict_proba(obs.points[idx]) if idx.size else np.zeros(0)
        t_agree = time.perf_counter() - t

    agreement: dict[str, Any] = {"n_known": int(check.sum()), "n_checked": int(idx.size)}
    occupied = obs.occupied[idx]
    if occupied.any() and not occupied.all():
        agreement.update(_agreement(p_check, occupied, model.thresholds_))

    spec: VoxelSpec = voxel_map.spec
    report: dict[str, Any] = {
        "leaves": {"n": tree.n_leaves, "occupied": int(tree.occupied.sum()), "free": int((~tree.occupied).sum())},
        "voxels": {"free": obs.n_free, "occupied": obs.n_occupied, "resolution": res},
        "region": {
            "lower": lo.tolist(),
            "upper": hi.tolist(),
            "train_lower": (lo - margin).tolist(),
            "train_upper": (hi + margin).tolist(),
        },
        "cells": {
            "n": len(cells),
            "occupied": int(cells.occupied.sum()),
            "ambiguous": int(cells.ambiguous.sum()),
            "min_cell": settings.cell_sides(3)[0],
            "max_cell": settings.cell_sides(3)[1],
        },
        "hyperparameters": dict(model.hyperparameters_),
        "agreement": agreement,
        "grid": {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape},
    }
    if isinstance(model, TiledOctreeModel):
        report["tiles"] = {
            "tile_size": model.tile_size_,
            "overlap": model.overlap_,
            "blend": model.blend_,
            "largest_tile_cells": model.largest_tile_cells_,
            **model.last_prediction_,
        }
    report["timings"] = {
        "read": t_read,
        "observations": t_obs,
        "fit": t_fit,
        "prediction": t_pred,
        "agreement": t_agree,
        "total": time.perf_counter() - t_start,
    }
    report["peak_memory_mb"] = peak_rss_mb()
    voxel_map.info = {
        **voxel_map.info,
        "source": "octree conversion",
        "conversion": {k: report[k] for k in report if k not in ("timings", "peak_memory_mb")},
    }
    return OctreeConversion(map=voxel_map, model=model, report=report)
