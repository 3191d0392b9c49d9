"""Which rays of a cloud are valid, compiled with numba (:meth:`gpomap.clouds.CloudScan.valid`'s fast path).

A cloud's rays are asked whether they are valid in many places (the rays of its free samples,
its ray counts, its reading counts), and numpy's answer makes four temporaries of the cloud's
size: the finite test, the offsets from the origin, their norms, the comparison. Here one pass
over the rows gives the same answer: a ray is valid where its endpoint is finite and its squared
distance from the origin is above zero (the norm is, exactly where its square is; the squares are
the numpy path's, so underflow decides alike). ``tests/test_observations.py`` compares the two.

``ENABLED``: :meth:`gpomap.clouds.CloudScan.valid` takes this path for clouds of
:data:`MIN_ROWS` rays or more (read at each call; :func:`gpomap.compiled.compiled_by_default` at
import, tests switch it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "MIN_ROWS", "valid_rays"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`gpomap.clouds.CloudScan.valid` takes the compiled path.
ENABLED: bool = compiled_by_default()

#: Rays below which numpy's answer is as quick as a compiled call.
MIN_ROWS: int = 4096


@jit(cache=True, nogil=True)
def _valid(
    points: NDArray[np.float64], origin: NDArray[np.float64], out: NDArray[np.bool_]
) -> None:  # pragma: no cover - compiled
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
            dx, dy, dz = x - ox, y - oy, z - oz
            out[i] = dx * dx + dy * dy + dz * dz > 0.0
        else:
            out[i] = False


def valid_rays(points: NDArray[np.float64], origin: NDArray[np.float64]) -> NDArray[np.bool_] | None:
    """Which rays from `origin` (3,) to `points` (n, 3) have a finite endpoint away from the
    origin, shape (n,), in one compiled pass where it pays (:data:`MIN_ROWS` rays or more, C-ordered
    float64); else None."""
    if points.shape[0] < MIN_ROWS or points.dtype != np.float64 or not points.flags.c_contiguous:
        return None
    out = np.empty(points.shape[0], dtype=np.bool_)
    _valid(points, np.ascontiguousarray(origin, dtype=np.float64), out)
    return out
