"""Free samples near hits compiled with numba (:func:`gpomap.observations.free_near_hits`'s fast path).

The numpy path settles most free samples with a distance transform over a lattice of boxes and
asks a k-d tree about the band it leaves; in 3-D that band is most of the samples, and for a
single scan the lattice spans the scan's whole reach (figures: docs/choices.md, "Measured for
the code"). Here the hits are
filed by boxes, each with the bounding box of its hits; each box is given the list of the boxes
round it that hold hits (nearest first), and one compiled pass asks each free sample about those
of its own box, stopping at the first hit within the clearance (most samples, far from any
surface, have none to ask). The answer is
the numpy path's exactly (``tests/test_clearance.py`` checks both against brute force).

``ENABLED``: :func:`gpomap.observations.free_near_hits` takes this path (read at each call;
:func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit
from gpomap.lattice import box_index, box_shape, column_bounds

__all__ = ["AVAILABLE", "ENABLED", "SIDE_MARGIN", "BOXES_PER_CLEARANCE", "near_hits"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.observations.free_near_hits` takes the compiled path.
ENABLED: bool = compiled_by_default()

#: The boxes are this much wider than the clearance (relatively), so that a hit within the
#: clearance of a sample is in a neighbouring box despite the rounding of box indices.
SIDE_MARGIN: float = 1e-6

#: Boxes per clearance: the coarsest, and finer ones taken where the hits are dense. A box's hits
#: are skipped at once when their bounding box is a clearance away, and taken at once when its
#: farthest corner is nearer, so only samples at about a clearance from a box's hits read them
#: one by one; smaller boxes leave fewer such reads but more boxes round each sample, and more
#: boxes to file. Two was the fastest or near it on planar blocks, planar logs, 3-D scans and
#: single scans (timings of 1, 2 and 3: docs/choices.md, "Measured for the code"); with only the
#: boxes that hold hits asked, finer boxes pay where a box of two per clearance holds more than
#: :data:`DENSE_HITS` hits on average and the samples asked outnumber the hits: a depth frame's
#: samples unmerged (docs/benchmarks.md, "3-D against OctoMap"). Merged, 3DMatch's 92 k samples
#: against 1.3 M hits take 0.19 s with two boxes a clearance, 0.5-0.7 s with four.
BOXES_PER_CLEARANCE: tuple[int, ...] = (2, 3, 4)

#: Hits per box (of the coarsest boxes that hold any, on average) above which finer boxes are
#: taken: a surface's hits per box fall with the square of the boxes' side.
DENSE_HITS: float = 100.0


@jit(cache=True, nogil=True)
def _boxes_around(
    hit_boxes: NDArray[np.int64], n_boxes: int, shape: NDArray[np.int64], steps: NDArray[np.int64], pad: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:  # pragma: no cover - compiled
    """For each box a sample can fall in (`pad` boxes or more from the lattice's faces), the boxes
    `steps` away from it that hold hits (`hit_boxes`, flat indices), in the steps' order: where
    each box's list starts (the end of the last one at the end), and the lists."""
    dim = shape.shape[0]
    offset = np.zeros(steps.shape[0], dtype=np.int64)
    for s in range(steps.shape[0]):
        for a in range(dim):
            offset[s] = offset[s] * shape[a] + steps[s, a]
    index = np.empty((hit_boxes.shape[0], dim), dtype=np.int64)
    for h in range(hit_boxes.shape[0]):
        rest = hit_boxes[h]
        for a in range(dim - 1, -1, -1):
            index[h, a] = rest % shape[a]
            rest //= shape[a]
    # Each hit box is in the list of every box a step from it where samples can fall; step by
    # step, so that every list comes out in the steps' order.
    count = np.zeros(n_boxes + 1, dtype=np.int64)
    for rep in range(2):
        if rep == 1:
            total = 0
            for b in range(n_boxes):
                c = count[b]
                count[b] = total
                total += c
            count[n_boxes] = total
            fill = count[:-1].copy()
            around = np.empty(total, dtype=np.int64)
        for s in range(steps.shape[0]):
            for h in range(hit_boxes.shape[0]):
                interior = True
                for a in range(dim):
                    i = index[h, a] - steps[s, a]
                    if i < pad or i > shape[a] - 1 - pad:
                        interior = False
                if interior:
                    b = hit_boxes[h] - offset[s]
                    if rep == 0:
                        count[b] += 1
                    else:
                        around[fill[b]] = hit_boxes[h]
                        fill[b] += 1
    return count, around


@jit(cache=True, nogil=True)
def _mark_near(
    free_points: NDArray[np.float64],
    hit_points: NDArray[np.float64],
    starts: NDArray[np.int64],
    hits_lo: NDArray[np.float64],
    hits_hi: NDArray[np.float64],
    lo: NDArray[np.float64],
    scale: float,
    shape: NDArray[np.int64],
    pad: int,
    clearance: float,
    around_start: NDArray[np.int64],
    around: NDArray[np.int64],
    skip: NDArray[np.bool_],
    out: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    n, dim = free_points.shape
    c2 = clearance * clearance
    # The bounds are widened a little so that rounding never decides a box wrongly.
    skip_beyond = c2 * (1.0 + 1e-9)
    take_within = c2 * (1.0 - 1e-9)
    for i in range(n):
        if skip.size and skip[i]:
            continue
        own = np.int64(0)
        for a in range(dim):
            own = own * shape[a] + min(np.int64((free_points[i, a] - lo[a]) * scale) + pad, shape[a] - 1 - pad)
        found = False
        # Only the boxes round the sample's that hold hits (none for most samples, far from any
        # surface), nearest first.
        for q in range(around_start[own], around_start[own + 1]):
            c = around[q]
            j0, j1 = starts[c], starts[c + 1]
            # The box's hits lie in their bounding box (kept at the box's first hit): none is
            # near if it is a clearance away, all are if its farthest corner is nearer.
            near2 = 0.0
            far2 = 0.0
            for a in range(dim):
                x = free_points[i, a]
                below, above = hits_lo[j0, a] - x, x - hits_hi[j0, a]
                t = max(below, above, 0.0)
                near2 += t * t
                u = max(x - hits_lo[j0, a], hits_hi[j0, a] - x)
                far2 += u * u
            if near2 > skip_beyond:
                continue
            if far2 < take_within:
                found = True
                break
            for j in range(j0, j1):
                d2 = 0.0
                for a in range(dim):
                    t = free_points[i, a] - hit_points[j, a]
                    d2 += t * t
                # The same rounding as a Euclidean distance compared with the clearance.
                if math.sqrt(d2) < clearance:
                    found = True
                    break
            if found:
                break
        out[i] = found


@jit(cache=True, nogil=True)
def _filed_by_box(
    points: NDArray[np.float64], box: NDArray[np.int64], starts: NDArray[np.int64], out: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    """`points` (n, d) written into `out` box by box, each box's in their order (a stable counting
    sort: the order of a stable argsort of `box`, in one pass); `starts` (boxes + 1,): where each
    box's rows begin."""
    at = starts[:-1].copy()
    for i in range(points.shape[0]):
        k = at[box[i]]
        at[box[i]] = k + 1
        for a in range(points.shape[1]):
            out[k, a] = points[i, a]


def near_hits(
    free_points: NDArray[np.float64],
    hit_points: NDArray[np.float64],
    clearance: float,
    max_boxes: int,
    skip: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_] | None:
    """Which free points lie closer than `clearance` to a hit, or None when the boxes would exceed `max_boxes`.

    Parameters
    ----------
    free_points : ndarray of shape (n, d)
    hit_points : ndarray of shape (h, d)
        At least one hit.
    clearance : float
        Metres, > 0.
    max_boxes : int
        Most boxes (of side ``clearance / k``, k of :data:`BOXES_PER_CLEARANCE`) over the
        points' bounding box: the tables of where each box's hits and list start hold 16 bytes
        per box.
    skip : ndarray of bool, shape (n,), optional
        Points not asked about (False in the answer): a block's hits among its points, which
        are then handed whole instead of as a copy of their free ones. The lattice spans the
        points and the hits alike, so the answer for the others is the same.

    Returns
    -------
    ndarray of bool, shape (n,), or None
        None past `max_boxes`: the numpy path is the one to take.
    """
    dim = free_points.shape[1]
    (free_lo, free_hi), (hit_lo, hit_hi) = column_bounds(free_points), column_bounds(hit_points)
    lo, hi = np.minimum(free_lo, hit_lo).astype(float), np.maximum(free_hi, hit_hi).astype(float)
    # Boxes per metre: so many boxes a clearance, a little wider (SIDE_MARGIN); empty boxes on
    # either side of the occupied ones, so every neighbour of a box exists.
    coarsest = BOXES_PER_CLEARANCE[0]
    scale = coarsest / (clearance * (1.0 + SIDE_MARGIN))
    shape = box_shape(lo, hi, scale, coarsest)
    if math.prod(shape) > max_boxes:
        return None
    pad = coarsest
    hit_box = box_index(hit_points, lo, scale, shape, pad)
    per_box = np.bincount(hit_box, minlength=math.prod(shape))
    # Finer boxes, where the samples asked outnumber the hits, while a box that holds hits would
    # hold more than DENSE_HITS on average (a surface's hits per box fall with the square of the
    # side) and the lattice fits the budget.
    dense = hit_points.shape[0] / max(int(np.count_nonzero(per_box)), 1)
    asked = free_points.shape[0] - (0 if skip is None else int(np.count_nonzero(skip)))
    per_clearance = coarsest
    for finer in BOXES_PER_CLEARANCE[1:] if asked >= hit_points.shape[0] else ():
        if dense * (coarsest / per_clearance) ** (dim - 1) <= DENSE_HITS:
            break
        finer_scale = finer / (clearance * (1.0 + SIDE_MARGIN))
        finer_shape = box_shape(lo, hi, finer_scale, finer)
        if math.prod(finer_shape) > max_boxes:
            break
        per_clearance, scale, shape, pad = finer, finer_scale, finer_shape, finer
    if per_clearance != coarsest:
        hit_box = box_index(hit_points, lo, scale, shape, pad)
        per_box = np.bincount(hit_box, minlength=math.prod(shape))
    starts = np.zeros(math.prod(shape) + 1, dtype=np.int64)
    np.cumsum(per_box, out=starts[1:])
    hits = np.empty((hit_points.shape[0], dim))
    _filed_by_box(np.ascontiguousarray(hit_points, dtype=float), hit_box, starts, hits)
    # Each box's bounding box of its hits, at the row of its first hit.
    first = starts[:-1][per_box > 0]
    hits_lo, hits_hi = np.empty_like(hits), np.empty_like(hits)
    for j in range(dim):
        hits_lo[first, j] = np.minimum.reduceat(hits[:, j], first)
        hits_hi[first, j] = np.maximum.reduceat(hits[:, j], first)
    # The sample's own box first: most samples near a hit find it there.
    steps = sorted(itertools.product(range(-pad, pad + 1), repeat=dim), key=lambda s: sum(map(abs, s)))
    around_start, around = _boxes_around(
        np.flatnonzero(per_box).astype(np.int64),
        math.prod(shape),
        np.array(shape, dtype=np.int64),
        np.array(steps, dtype=np.int64),
        pad,
    )
    out = np.zeros(free_points.shape[0], dtype=bool)
    _mark_near(
        np.ascontiguousarray(free_points, dtype=float),
        hits,
        starts,
        hits_lo,
        hits_hi,
        lo,
        scale,
        np.array(shape, dtype=np.int64),
        pad,
        float(clearance),
        around_start,
        around,
        np.zeros(0, dtype=np.bool_) if skip is None else np.ascontiguousarray(skip, dtype=np.bool_),
        out,
    )
    return out
