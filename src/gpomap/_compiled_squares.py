"""Tile and block squares of points compiled with numba (:meth:`gpomap.tiles.geometry.TileGrid._square_indices`'s fast path).

Filing a log's points under their blocks asks, for every point, the square of the tile grid and
of the block grid holding it, several times (the squares present, then each point's block). The
numpy expression ``floor((points[:, :2] - origin) / side)`` makes four temporaries the size of
the points; here one compiled pass writes the indices only. The arithmetic is the same, in the
same order (a subtraction, a division, a floor), so the indices are the numpy path's exactly
(``tests/test_tile_squares.py`` compares the two).

``ENABLED``: :meth:`~gpomap.tiles.geometry.TileGrid._square_indices` takes this path (read at each
call; :func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "square_indices"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`~gpomap.tiles.geometry.TileGrid._square_indices` takes the compiled path.
ENABLED: bool = compiled_by_default()


@jit(cache=True, nogil=True)
def _square_indices(
    points: NDArray[np.float64], ox: float, oy: float, side: float, out: NDArray[np.int64]
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    for i in range(points.shape[0]):
        out[i, 0] = np.int64(np.floor((points[i, 0] - ox) / side))
        out[i, 1] = np.int64(np.floor((points[i, 1] - oy) / side))


def square_indices(points: NDArray[np.float64], origin: tuple[float, float], side: float) -> NDArray[np.int64]:
    """Integer (ix, iy) of the square of `side` on `origin` holding each point.

    Parameters
    ----------
    points : ndarray of shape (n, d), d >= 2
        Points; only x and y are read.
    origin : (float, float)
        Corner of square (0, 0).
    side : float
        Side of the squares.

    Returns
    -------
    ndarray of int64, shape (n, 2)
    """
    out = np.empty((points.shape[0], 2), dtype=np.int64)
    _square_indices(np.asarray(points, dtype=np.float64), float(origin[0]), float(origin[1]), float(side), out)
    return out
