"""The square columns a tiled octree conversion is cut into (:class:`ColumnTiling`), and one pass
of their predictions, blended over a voxel grid and points (:func:`predict_tiles`).

Each column spans every height; its GP sees the cells meeting its square grown by the overlap, and
its predictions are weighted by the smoothstep tapers of :class:`~gpomap.tiles.TiledGPOM`
(:func:`gpomap.tiles.taper`) over its square grown by half the blend width, so the weights of the
columns over a point sum to one. A pass fits the columns one after another (or a few at once, on
threads) and lets each go once its predictions are added.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.progress import progress
from gpomap.tiles import HYPER_NAMES, TileCells, TileFitTask, TileSettings, fit_tile_task, predict_tile_task, taper
from gpomap.voxels import VoxelSpec

__all__ = ["ColumnTiling", "TileQueries", "predict_tiles"]

#: A column of the tiling, by its (x, y) index from the tiling's origin.
Key = tuple[int, int]


@dataclass
class ColumnTiling:
    """Square columns of side `side` over a set of cells, from `origin`.

    Attributes
    ----------
    lower, upper : ndarray of shape (n, 3)
        The cells' boxes (GP inputs), metres.
    counts : ndarray of shape (n,)
        Their member counts.
    labels : ndarray of shape (n,)
        Their targets.
    origin : (float, float)
        (x, y) of column (0, 0)'s lower corner.
    side : float
        Column side, metres.
    overlap : float
        A column's GP sees the cells meeting its square grown by this much (metres).
    blend : float
        Width of the band over which neighbouring columns' predictions are blended (metres).
    by_column : dict
        The cells by the column holding their centre: (x, y) index -> ndarray of cell indices.
    reach_columns : int
        Columns on each side whose cells may meet a column's grown square.
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    labels: NDArray[np.float64]
    origin: tuple[float, float]
    side: float
    overlap: float
    blend: float
    by_column: dict[Key, NDArray[np.intp]] = field(init=False, repr=False)
    reach_columns: int = field(init=False)

    def __post_init__(self) -> None:
        # Cells by the column holding their centre, so each tile looks at its neighbours' only.
        centres = 0.5 * (self.lower + self.upper)
        col = np.floor((centres[:, :2] - np.asarray(self.origin)) / self.side).astype(np.int64)
        order = np.lexsort((col[:, 1], col[:, 0]))
        keys = col[order]
        starts = np.flatnonzero(np.r_[True, (np.diff(keys, axis=0) != 0).any(axis=1)])
        stops = np.r_[starts[1:], order.size]
        self.by_column = {(int(keys[a, 0]), int(keys[a, 1])): order[a:b] for a, b in zip(starts, stops, strict=True)}
        half = 0.5 * float(np.max(self.upper[:, :2] - self.lower[:, :2])) if self.labels.size else 0.0
        self.reach_columns = math.ceil((self.overlap + half) / self.side)

    def core(self, key: Key) -> tuple[float, float, float, float]:
        """The column's square: (x0, x1, y0, y1), metres."""
        t = self.side
        x0, y0 = self.origin[0] + key[0] * t, self.origin[1] + key[1] * t
        return x0, x0 + t, y0, y0 + t

    def tile_cells(self, key: Key) -> TileCells | None:
        """The cells meeting the column's square grown by the overlap, in the cells' order (None: none)."""
        x0, x1, y0, y1 = self.core(key)
        o, r = self.overlap, self.reach_columns
        near = [
            self.by_column[c]
            for c in ((key[0] + i, key[1] + j) for i in range(-r, r + 1) for j in range(-r, r + 1))
            if c in self.by_column
        ]
        if not near:
            return None
        idx = np.sort(np.concatenate(near))
        lo, hi = self.lower[idx], self.upper[idx]
        keep = (lo[:, 0] <= x1 + o) & (hi[:, 0] >= x0 - o) & (lo[:, 1] <= y1 + o) & (hi[:, 1] >= y0 - o)
        if not keep.any():
            return None
        idx = idx[keep]
        return TileCells(self.lower[idx], self.upper[idx], self.counts[idx], self.labels[idx])

    def tiles_over(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> list[Key]:
        """The columns whose blend region meets the box [lo, hi] in x, y (each of shape (2,) or more)."""
        t, h = self.side, 0.5 * self.blend
        rx = range(math.floor((lo[0] - self.origin[0] - h) / t), math.ceil((hi[0] - self.origin[0] + h) / t))
        ry = range(math.floor((lo[1] - self.origin[1] - h) / t), math.ceil((hi[1] - self.origin[1] + h) / t))
        return [(ix, iy) for ix in rx for iy in ry]

    def blend_box(self, key: Key) -> tuple[float, float, float, float]:
        """Where the column's weight is not zero: its square grown by half the blend, (x0, x1, y0, y1)."""
        x0, x1, y0, y1 = self.core(key)
        h = 0.5 * self.blend
        return x0 - h, x1 + h, y0 - h, y1 + h

    def weights(self, key: Key, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """The column's blend weight at (x, y), each of shape (m,) (or broadcasting)."""
        x0, x1, y0, y1 = self.core(key)
        h = 0.5 * self.blend
        return np.asarray(taper(x, x0, x1, h) * taper(y, y0, y1, h))


@dataclass
class TileQueries:
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
    coarse: VoxelSpec | None
    points: NDArray[np.float64]


def predict_tiles(
    tiling: ColumnTiling,
    queries: TileQueries,
    settings: TileSettings,
    hyperparameters: dict[str, float],
    chunk_size: int,
    n_workers: int,
    desc: str,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
    """Blended latent moments over the columns that meet the queries, each fitted and let go.

    Every column of the tiling over the queries takes part; a column with no cells in its reach
    adds the GP prior (mean 0, the signal variance), so the weights sum to one everywhere.

    Parameters
    ----------
    tiling : ColumnTiling
    queries : TileQueries
    settings : TileSettings
        The GP settings of every column's fit.
    hyperparameters : dict
        variance, length_scale, noise, alpha and beta of every column.
    chunk_size : int
        Query points per block of a column's prediction.
    n_workers : int
        Columns fitted and predicted at once, on threads (their results are added in the columns'
        order, so the sums are the same for any number).
    desc : str
        The progress bar's label.

    Returns
    -------
    mean_grid : ndarray of shape ``queries.spec.shape``, or None without a grid
        The latent mean at every voxel.
    var_grid : ndarray of shape ``queries.coarse.shape``, or None without a grid
        The latent variance on the coarse lattice.
    point_mean, point_var : ndarray of shape (m,)
        The latent mean and variance at ``queries.points``.
    stats : dict
        ``tiles`` (columns taking part), ``tiles_fitted``, ``fit_seconds``, ``predict_seconds``.
    """
    pts = queries.points
    spec, coarse = queries.spec, queries.coarse
    boxes = [pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)] if pts.size else []
    if coarse is not None:
        boxes += [np.asarray(coarse.origin[:2]), np.asarray(coarse.upper[:2])]
    lo, hi = np.min(boxes, axis=0), np.max(boxes, axis=0)
    tiles = tiling.tiles_over(lo, hi)
    mean_grid = np.zeros(spec.shape) if spec is not None else None
    var_grid = np.zeros(coarse.shape) if coarse is not None else None
    p_mean, p_var, p_wsum = np.zeros(len(pts)), np.zeros(len(pts)), np.zeros(len(pts))
    axes = {}
    for name, g in (("fine", spec), ("coarse", coarse)):
        if g is not None:
            axes[name] = (g.axis_centres("x"), g.axis_centres("y"), g.axis_centres("z"))
    prior_var = float(hyperparameters["variance"])
    hyp = {k: hyperparameters[k] for k in HYPER_NAMES}
    seconds = {"fit": 0.0, "predict": 0.0}
    n_fitted = 0

    def in_box(key: Key) -> dict[str, Any]:
        bx0, bx1, by0, by1 = tiling.blend_box(key)
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

    def work(key: Key, sel: dict[str, Any]) -> tuple[Any, ...] | None:
        """The column's moments at its queries (None: no cells in its reach, the prior's)."""
        cells = tiling.tile_cells(key)
        if cells is None:
            return None
        t = time.perf_counter()
        state = fit_tile_task(TileFitTask(key, cells, settings, hyp))
        t_fit = time.perf_counter() - t
        t = time.perf_counter()
        mu_f = var_c = pm = pv = None
        if sel["fine"] is not None:
            mu_f, _ = predict_tile_task(state, block_points("fine", *sel["fine"]), chunk_size, variance=False)
        if sel["coarse"] is not None:
            _, var_c = predict_tile_task(state, block_points("coarse", *sel["coarse"]), chunk_size, variance=True)
        if sel["points"].size:
            pm, pv = predict_tile_task(state, pts[sel["points"]], chunk_size, variance=True)
        return mu_f, var_c, pm, pv, t_fit, time.perf_counter() - t

    def accumulate(key: Key, sel: dict[str, Any], out: tuple[Any, ...] | None) -> None:
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
            w = tiling.weights(key, xs[ix][None, :], ys[iy][:, None])
            mean_grid[:, iy[0] : iy[-1] + 1, ix[0] : ix[-1] + 1] += w[None] * mu_f.reshape(-1, iy.size, ix.size)
        if sel["coarse"] is not None and var_grid is not None:
            ix, iy = sel["coarse"]
            xs, ys, _ = axes["coarse"]
            w = tiling.weights(key, xs[ix][None, :], ys[iy][:, None])
            v = prior_var if var_c is None else var_c.reshape(-1, iy.size, ix.size)
            var_grid[:, iy[0] : iy[-1] + 1, ix[0] : ix[-1] + 1] += w[None] * v
        ip = sel["points"]
        if ip.size:
            w = tiling.weights(key, pts[ip, 0], pts[ip, 1])
            p_wsum[ip] += w
            if pm is not None:
                p_mean[ip] += w * pm
            p_var[ip] += w * (prior_var if pv is None else pv)

    jobs = [(key, in_box(key)) for key in tiles]
    jobs = [(k, s) for k, s in jobs if s["fine"] is not None or s["coarse"] is not None or s["points"].size]
    with progress(len(jobs), desc, "tile") as bar:
        if n_workers <= 1:
            for key, sel in jobs:
                accumulate(key, sel, work(key, sel))
                bar.update()
        else:
            # At most n_workers tiles in flight; results added in the tiles' order (the same sums).
            with cf.ThreadPoolExecutor(n_workers) as pool:
                waiting: collections.deque[tuple[Key, dict[str, Any], cf.Future[Any]]] = collections.deque()
                for key, sel in jobs:
                    waiting.append((key, sel, pool.submit(work, key, sel)))
                    if len(waiting) >= n_workers:
                        k, s, f = waiting.popleft()
                        accumulate(k, s, f.result())
                        bar.update()
                while waiting:
                    k, s, f = waiting.popleft()
                    accumulate(k, s, f.result())
                    bar.update()
    if pts.size and not np.allclose(p_wsum, 1.0):
        raise AssertionError("tile weights do not sum to one")  # the tapers are a partition of unity
    stats = {"tiles": len(jobs), "tiles_fitted": n_fitted, "fit_seconds": seconds["fit"], "predict_seconds": seconds["predict"]}
    return mean_grid, var_grid, p_mean, p_var, stats
