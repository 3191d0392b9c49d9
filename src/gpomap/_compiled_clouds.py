"""A cloud's valid rays and their geometry, compiled with numba (the fast paths of
:meth:`gpomap.clouds.CloudScan.valid` and :meth:`gpomap.observations.Rays.of`).

A cloud's rays are asked whether they are valid in many places (the rays of its free samples,
its ray counts, its reading counts), and numpy's answer makes four temporaries of the cloud's
size: the finite test, the offsets from the origin, their norms, the comparison. Here one pass
over the rows gives the same answer: a ray is valid where its endpoint is finite and its squared
distance from the origin is above zero (the norm is, exactly where its square is; the squares are
the numpy path's, so underflow decides alike). ``tests/test_observations.py`` compares the two.

A fit makes a cloud's rays (endpoints, unit directions, lengths) in several passes; numpy makes
five temporaries of the cloud's size for them, here one pass writes the three, with the same
operations in the same order (the squares summed x first, as numpy sums a row), so the same bits.

``ENABLED``: :meth:`gpomap.clouds.CloudScan.valid` takes this path for clouds of
:data:`MIN_ROWS` rays or more (read at each call; :func:`gpomap.compiled.compiled_by_default` at
import, tests switch it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "MIN_ROWS", "ray_geometry", "valid_rays"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`gpomap.clouds.CloudScan.valid` and :meth:`gpomap.observations.Rays.of` take
#: the compiled paths.
ENABLED: bool = compiled_by_default()

#: Rays below which numpy's answer is as quick as a compiled call.
MIN_ROWS: int = 4096


def _pays(points: NDArray[np.float64]) -> bool:
    """Whether a compiled pass over the cloud `points` (n, 3) pays and takes them as they are:
    :data:`MIN_ROWS` rays or more, C-ordered float64."""
    return points.shape[0] >= MIN_ROWS and points.dtype == np.float64 and bool(points.flags.c_contiguous)


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
    if not _pays(points):
        return None
    out = np.empty(points.shape[0], dtype=np.bool_)
    _valid(points, np.ascontiguousarray(origin, dtype=np.float64), out)
    return out


@jit(cache=True, nogil=True)
def _geometry(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    valid: NDArray[np.bool_],
    ends: NDArray[np.float64],
    directions: NDArray[np.float64],
    lengths: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    ox, oy, oz = origin[0], origin[1], origin[2]
    j = 0
    for i in range(points.shape[0]):
        if valid[i]:
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            ends[j, 0], ends[j, 1], ends[j, 2] = x, y, z
            dx, dy, dz = x - ox, y - oy, z - oz
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            lengths[j] = length
            directions[j, 0], directions[j, 1], directions[j, 2] = dx / length, dy / length, dz / length
            j += 1


def ray_geometry(
    points: NDArray[np.float64], origin: NDArray[np.float64], valid: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None:
    """The `valid` rays' (mask of shape (n,)) endpoints (m, 3), unit directions from `origin` (m, 3)
    and lengths (m,), in one compiled pass where it pays (as :func:`valid_rays`); else None."""
    if not _pays(points):
        return None
    m = int(np.count_nonzero(valid))
    ends, directions, lengths = np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
    _geometry(
        points,
        np.ascontiguousarray(origin, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        ends,
        directions,
        lengths,
    )
    return ends, directions, lengths
