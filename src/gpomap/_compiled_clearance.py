"""Free samples near hits compiled with numba (:func:`gpomap.observations.free_near_hits`'s fast path).

The numpy path settles most free samples with a distance transform over a lattice of boxes and
asks a k-d tree about the band it leaves; in 3-D that band is most of the samples (la3dm
sim_structured: 194,000 of 321,000 free samples, 0.24 s of k-d tree queries per call, three
calls a fit). Here the hits are filed by boxes one clearance wide, and one compiled pass asks
each free sample about the hits in its own and the neighbouring boxes, stopping at the first
within the clearance. The answer is the numpy path's exactly (``tests/test_clearance.py``
checks both against brute force). Where a wall was scanned thousands of times its boxes hold
hundreds of hits, which a sample just beyond the clearance reads one by one: there the numpy
path stays (:data:`MAX_MEAN_HITS_PER_BOX`).

``ENABLED``: :func:`gpomap.observations.free_near_hits` may take this path (read at each call;
:func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "SIDE_MARGIN", "MAX_MEAN_HITS_PER_BOX", "BOXES_PER_CLEARANCE", "near_hits"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.observations.free_near_hits` takes the compiled path.
ENABLED: bool = compiled_by_default()

#: The boxes are this much wider than the clearance (relatively), so that a hit within the
#: clearance of a sample is in a neighbouring box despite the rounding of box indices.
SIDE_MARGIN: float = 1e-6

#: Most hits per box holding any, on average, for this path to be taken: a sample just beyond
#: the clearance of a wall reads every hit of the boxes round it, and walls scanned again and
#: again fill them. Measured against the numpy path (FR079, seconds): one scan (4-5 hits a
#: box) 0.0005 against 0.005-0.08; 40 scans (57) 0.034 against 0.10; 400 scans (104) 0.37
#: against 0.62; 800 scans (162) 1.39 against 1.37; a 10 m block of 1,500 scans (423) 0.94
#: against 0.33. la3dm sim_structured's clouds: 22.
MAX_MEAN_HITS_PER_BOX: int = 64

#: Boxes per clearance: smaller boxes hold fewer hits to compare but are more to look up (la3dm
#: sim_structured's 351,000 samples: 0.065 s a call with 1, 0.09 s with 2, 0.21 s with 3).
BOXES_PER_CLEARANCE: int = 1


@jit(cache=True, nogil=True)
def _mark_near(
    free_points: NDArray[np.float64],
    hit_points: NDArray[np.float64],
    starts: NDArray[np.int64],
    lo: NDArray[np.float64],
    side: float,
    shape: NDArray[np.int64],
    steps: NDArray[np.int64],
    pad: int,
    clearance: float,
    out: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    n, dim = free_points.shape
    index = np.empty(dim, dtype=np.int64)
    below = np.empty(dim)  # distance to the box's lower face, in boxes
    # A neighbouring box is skipped when even its nearest face is a clearance away; the bound is
    # shrunk a little so that rounding in the box indices never skips a box it should not.
    reach = (clearance / side) ** 2 * (1.0 + 1e-9)
    for i in range(n):
        for a in range(dim):
            u = (free_points[i, a] - lo[a]) / side
            k = min(np.int64(u) + pad, shape[a] - 1 - pad)
            index[a] = k
            below[a] = u - (k - pad)
        found = False
        for s in range(steps.shape[0]):
            c = np.int64(0)
            bound = 0.0
            for a in range(dim):
                step = steps[s, a]
                c = c * shape[a] + index[a] + step
                if step < 0:
                    t = below[a] - step - 1.0
                    bound += t * t
                elif step > 0:
                    t = max(step - below[a], 0.0)
                    bound += t * t
            if bound * (1.0 - 1e-9) >= reach:
                continue
            for j in range(starts[c], starts[c + 1]):
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


def near_hits(
    free_points: NDArray[np.float64], hit_points: NDArray[np.float64], clearance: float, max_boxes: int
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
        Most boxes of side `clearance` over the points' bounding box (the table of where each
        box's hits start holds 8 bytes per box).

    Returns
    -------
    ndarray of bool, shape (n,), or None
        None past `max_boxes` or :data:`MAX_MEAN_HITS_PER_BOX`: the numpy path is the one to take.
    """
    dim = free_points.shape[1]
    both = np.concatenate([free_points, hit_points])
    lo = np.array([both[:, j].min() for j in range(dim)])
    hi = np.array([both[:, j].max() for j in range(dim)])
    side = clearance * (1.0 + SIDE_MARGIN) / BOXES_PER_CLEARANCE
    # Empty boxes on either side of the occupied ones, so every neighbour of a box exists.
    pad = BOXES_PER_CLEARANCE
    shape = [int(v) + 1 + 2 * pad for v in np.floor((hi - lo) / side)]
    if math.prod(shape) > max_boxes:
        return None

    def flat_box(points: NDArray[np.float64]) -> NDArray[np.int64]:
        flat = np.zeros(points.shape[0], dtype=np.int64)
        for j, size in enumerate(shape):
            flat *= size
            flat += np.minimum(((points[:, j] - lo[j]) / side).astype(np.int64) + pad, size - 1 - pad)
        return flat

    hit_box = flat_box(hit_points)
    per_box = np.bincount(hit_box, minlength=math.prod(shape))
    if hit_points.shape[0] > MAX_MEAN_HITS_PER_BOX * np.count_nonzero(per_box):
        return None
    order = np.argsort(hit_box, kind="stable")
    starts = np.zeros(math.prod(shape) + 1, dtype=np.int64)
    np.cumsum(per_box, out=starts[1:])
    # The sample's own box first: most samples near a hit find it there.
    steps = sorted(itertools.product(range(-pad, pad + 1), repeat=dim), key=lambda s: sum(map(abs, s)))
    out = np.zeros(free_points.shape[0], dtype=bool)
    _mark_near(
        np.ascontiguousarray(free_points, dtype=float),
        np.ascontiguousarray(hit_points[order], dtype=float),
        starts,
        lo,
        side,
        np.array(shape, dtype=np.int64),
        np.array(steps, dtype=np.int64),
        pad,
        float(clearance),
        out,
    )
    return out
