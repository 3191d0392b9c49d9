"""The tiles' geometry: the squares of the tile and block grids, their keys, and how far a tile's GP sees.

Tiles and blocks are squares in x, y on one origin (in 3-D, columns that hold every height). A
block's points get their own cell tree; a tile's GP is fitted on the cells meeting its square grown
by the overlap, and predicts within its square grown by half the blend.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

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
