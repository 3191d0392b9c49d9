"""The tiles' geometry: the squares of the tile and block grids, their keys, and how far a tile's GP sees.

Tiles and blocks are squares in x, y on one origin (in 3-D, columns that hold every height). A
block's points get their own cell tree; a tile's GP is fitted on the cells meeting its square grown
by the overlap, and predicts within its square grown by half the blend.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from gpomap import _compiled_squares
from gpomap.config import PROFILES
from gpomap.lattice import column_bounds
from gpomap.tiles.attributes import TiledAttributes

# Block keys pack (ix, iy) into one int64 so grouping millions of points is one argsort.
_KEY_OFFSET = 1 << 30
_KEY_BASE = 1 << 31
# Points given block and tile keys at once (bounds the temporaries of a whole log's points).
_KEY_CHUNK = 1 << 20

#: Tile side by the map's dimension, metres. A tile's GP costs the cube of the cells it sees, its
#: square grown by the overlap, so tiles not much larger than the overlap are cheapest in all;
#: the cells, hyperparameters and variance scale do not depend on them (:data:`BLOCK_SIZE`).
#: Planar maps: 5 m squares; voxel maps: 3 m columns, which hold every height, so they fill
#: faster than planar squares. Both the fastest sizes tried, scores unchanged (docs/choices.md,
#: "Tiles: 5 m squares (3 m columns in 3-D)").
DEFAULT_TILE_SIZE: dict[int, float] = {d: p.tile_size for d, p in PROFILES.items()}

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


class TileGrid(TiledAttributes):
    """The squares of a map's tile and block grids: keys, bounds, grown squares, blend regions
    (a part of :class:`~gpomap.tiles.TiledGPOM`; ``origin_``, ``tile_size_``, ``overlap_`` and ``blend_`` set by its fit)."""

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
        if _compiled_squares.ENABLED:
            return _compiled_squares.square_indices(points, self.origin_, side)
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

    def _settled_origin(self, lower: NDArray[np.float64], upper: NDArray[np.float64]) -> tuple[float, float] | None:
        """The origin of tile (0, 0) as soon as more points cannot change it, for points so far
        within `lower`..`upper` (x, y at least): the one given, or :meth:`_default_origin`'s once
        their extent outgrows a block (it only grows); None before."""
        if self.origin is not None:
            return (float(self.origin[0]), float(self.origin[1]))
        if np.all(np.asarray(upper)[:2] - np.asarray(lower)[:2] < self.block_size_):
            return None
        return self._default_origin(lower, upper)

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

    def _blend_region(self, key: tuple[int, int]) -> tuple[float, float, float, float]:
        x0, x1, y0, y1 = self._core(key)
        h = 0.5 * self.blend_
        return x0 - h, x1 + h, y0 - h, y1 + h

    def _set_geometry(self) -> None:
        self.overlap_ = tile_reach(self.tile_size_, self.hyperparameters_["length_scale"], self.overlap)
        w = BLEND_FRACTION * min(self.overlap_, self.tile_size_) if self.blend is None else float(self.blend)
        if not 0 < w <= min(self.overlap_, self.tile_size_) + 1e-12:
            raise ValueError(
                f"blend must be in (0, min(overlap, tile_size)] = (0, {min(self.overlap_, self.tile_size_)}], got {w}"
            )
        self.blend_ = float(w)
