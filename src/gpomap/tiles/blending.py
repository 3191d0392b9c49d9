"""The tiles' moments blended without seams.

A point's moments are the tiles' whose blend regions hold it, weighted by products of smoothstep
tapers that sum to one; where no tile's region holds a point, the tile whose square is nearest
predicts it alone.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import MutableMapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.extrapolation import VarianceScale
from gpomap.field import as_points
from gpomap.lattice import stable_order
from gpomap.progress import progress
from gpomap.stages import CalibratedMoments
from gpomap.tiles.fits import TileFits
from gpomap.tiles.store import TileStore
from gpomap.tiles.tasks import TileState, predict_tile_task

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


class TileBlending(TileFits):
    """The tiles' latent moments at points, blended (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

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
        return VarianceScale(self.hyperparameters_.get("variance_scale", 1.0)).apply(CalibratedMoments(num, den))

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

    def _tile_members(
        self, pts: NDArray[np.float64], keys: list[tuple[int, int]]
    ) -> tuple[dict[tuple[int, int], tuple[NDArray[np.intp], NDArray[np.float64]]], NDArray[np.float64]]:
        """Which of the tiles `keys` (sorted) predict each of the points `pts` (m, d), and with
        what blend weight: per tile, the points' indices and weights; and each point's weight sum,
        shape (m,). A point no tile reaches is the nearest core's alone, at weight 1."""
        m = pts.shape[0]
        h = 0.5 * self.blend_
        members: dict[tuple[int, int], tuple[NDArray[np.intp], NDArray[np.float64]]] = {}
        wsum = np.zeros(m)
        # Points bucketed once in squares of half a tile (a stable sort of integers), so each
        # tile scans only the few squares its blend region reaches: strips of x alone made each
        # tile of a tall map scan dozens of tiles' points (docs/choices.md, "Measured for the
        # code"). Squares as narrow as a short blend would be millions (a hard switch).
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
        return members, wsum

    def blended_moments(
        self, points: NDArray[np.float64], variance: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64] | None]:
        """The tiles' calibrated latent moments at points, blended: alpha mu + beta, alpha^2 var, mu, var.

        Each of shape (m,); the two variances None without `variance` (the mean costs a small
        part of a prediction). :meth:`squash_moments` turns the first two into probabilities.
        """
        pts = as_points(points, self._dim)
        m = pts.shape[0]
        chunk = self.base.chunk_size
        waiting = getattr(self, "_waiting", {})
        members, wsum = self._tile_members(pts, sorted([*self.tiles_, *waiting]) if waiting else sorted(self.tiles_))
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
