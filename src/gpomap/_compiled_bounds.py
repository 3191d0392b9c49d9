"""The least and greatest coordinate of points compiled with numba (:func:`gpomap.lattice.column_bounds`'s fast path).

A log's points are bounded in many places (the blocks they are filed under, their tiles, the
cells grown from them). numpy reduces each column of an (n, d) array as a strided pass, one for
the minimum and one for the maximum of each; here one pass over the rows keeps both bounds of
every column at once. Minima and maxima are exact, so the bounds are the numpy path's to the bit
(``tests/test_lattice_block.py`` compares the two).

``ENABLED``: :func:`gpomap.lattice.column_bounds` takes this path for planar and 3-D points of
float64 (read at each call; :func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "bounds"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.lattice.column_bounds` takes the compiled path.
ENABLED: bool = compiled_by_default()

#: Rows below which numpy's reductions are as fast as a compiled call.
MIN_ROWS: int = 4096


@jit(cache=True, nogil=True)
def _bounds_2(a: NDArray[np.float64]) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    # Scalars, not arrays indexed by column: the loop keeps them in registers.
    lx = hx = a[0, 0]
    ly = hy = a[0, 1]
    nan = False
    for i in range(1, a.shape[0]):
        x, y = a[i, 0], a[i, 1]
        nan |= (x != x) | (y != y)
        lx, hx, ly, hy = min(lx, x), max(hx, x), min(ly, y), max(hy, y)
    return (np.nan, np.nan, np.nan, np.nan) if nan else (lx, ly, hx, hy)


@jit(cache=True, nogil=True)
def _bounds_3(a: NDArray[np.float64]) -> tuple[float, float, float, float, float, float]:  # pragma: no cover - compiled
    lx = hx = a[0, 0]
    ly = hy = a[0, 1]
    lz = hz = a[0, 2]
    nan = False
    for i in range(1, a.shape[0]):
        x, y, z = a[i, 0], a[i, 1], a[i, 2]
        nan |= (x != x) | (y != y) | (z != z)
        lx, hx, ly, hy, lz, hz = min(lx, x), max(hx, x), min(ly, y), max(hy, y), min(lz, z), max(hz, z)
    return (np.nan, np.nan, np.nan, np.nan, np.nan, np.nan) if nan else (lx, ly, lz, hx, hy, hz)


def bounds(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """``a.min(axis=0)`` and ``a.max(axis=0)`` of C-ordered float64 points (n, d), n >= 1, in one
    compiled pass where it pays (d of 2 or 3, :data:`MIN_ROWS` rows or more); else None.

    Points with a NaN coordinate are left to numpy (whose minimum propagates it): None.
    """
    d = a.shape[1] if a.ndim == 2 else 0
    if d not in (2, 3) or a.shape[0] < MIN_ROWS or a.dtype != np.float64 or not a.flags.c_contiguous:
        return None
    both = np.array(_bounds_2(a) if d == 2 else _bounds_3(a))
    if np.isnan(both).any():
        return None
    return both[:d], both[d:]
