"""The tiles' moments blended without seams.

A point's moments are the tiles' whose blend regions hold it, weighted by products of smoothstep
tapers that sum to one; where no tile's region holds a point, the tile whose square is nearest
predicts it alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

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
