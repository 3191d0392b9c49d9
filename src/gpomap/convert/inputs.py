"""The GP inputs of a grid: a cell per pixel near anything occupied, merged free blocks farther
away, and a point where each occupied pixel's obstacle most likely is (:func:`grid_cells`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gpomap.cells import Cells
from gpomap.convert.pooling import PixelReading, pixel_lattice, read_pixels
from gpomap.supports import Supports

__all__ = ["WALL_REACH_PIXELS", "EDGE_STRIP_PIXELS", "CENTRE_NOISE", "GridCells", "grid_cells"]

#: Known pixels within this many pixels (chessboard distance) of an occupied one are cells of their
#: own; only free pixels farther away are merged into larger cells.
WALL_REACH_PIXELS = 3
#: Width, in source pixels, of the free strip put inside a free pixel along each edge it shares
#: with an occupied pixel: none by default, since a free pixel of a majority-pooled grid may be
#: up to half occupied (docs/convert.md).
EDGE_STRIP_PIXELS = 0.0
#: Noise of the point where an occupied pixel's obstacle most likely is, relative to a one-pixel cell's.
CENTRE_NOISE = 3.0


@dataclass(frozen=True)
class GridCells(Cells):
    """:class:`~gpomap.cells.Cells` whose GP inputs carry a noise weight each.

    Attributes
    ----------
    weight : ndarray of shape (n,) or None
        Multiplies each input's member count in :meth:`to_supports`. With the ``"per_count"``
        noise model an input's noise is the noise level divided by that count, so a weight of w
        makes the input w times surer (counts below 1 are read as 1 there, so weights are >= 1).
        None: every weight 1.
    target : ndarray of shape (n,) or None
        Each input's target in [-1, 1]; None: +1 occupied, -1 free.
    reading : PixelReading or None
        What each pixel was read as (:func:`read_pixels`), when the inputs were made from one.
    """

    weight: NDArray[np.float64] | None = None
    target: NDArray[np.float64] | None = None
    reading: PixelReading | None = None

    @property
    def labels(self) -> NDArray[np.float64]:
        """GP targets, ndarray of shape (n,): :attr:`target` when given, else +1 occupied, -1 free."""
        return super().labels if self.target is None else self.target

    def to_supports(self) -> Supports:
        """The cells as GP inputs, their counts multiplied by :attr:`weight`."""
        supports = super().to_supports()
        if self.weight is None:
            return supports
        return replace(supports, counts=supports.counts * self.weight)


def _extra_inputs(
    cells: Cells, lower: NDArray[np.float64], upper: NDArray[np.float64], occupied: NDArray[np.bool_], members: NDArray[np.intp]
) -> Cells:
    """`cells` followed by one-member inputs with boxes (lower, upper), labels and member indices."""
    n = lower.shape[0]
    counts = np.concatenate([cells.counts, np.ones(n, dtype=np.intp)])
    return Cells(
        lower=np.vstack([cells.lower, lower]),
        upper=np.vstack([cells.upper, upper]),
        node_lower=np.vstack([cells.node_lower, lower]),
        node_upper=np.vstack([cells.node_upper, upper]),
        occupied=np.concatenate([cells.occupied, occupied]),
        ambiguous=np.concatenate([cells.ambiguous, np.zeros(n, dtype=bool)]),
        member_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.intp),
        member_order=np.concatenate([cells.member_order, members]).astype(np.intp),
        points=cells.points,
    )


def _core_centres(
    pts: NDArray[np.float64], frac: NDArray[np.float64], free: NDArray[np.bool_], ij: NDArray[np.intp], pixel: float
) -> NDArray[np.float64]:
    """Where the occupied part of each pixel holding anything occupied most likely is, shape (m, 2).

    A wholly occupied pixel's is its centre. A partly occupied one (fraction f) is taken to be
    occupied away from the sides it shares with wholly free pixels: a strip `delta` pixels deep
    along each such side is free, `delta` such that the rest, its core, has area f; the point is
    the core's centre (a pixel with no free side: its centre). A 2 cm wall in a 0.05 m pixel
    between free ones is at its centre; one straddling two pixels (0.2 each) at their shared edge.

    Parameters
    ----------
    pts : ndarray of shape (m, 2)
        The pixels' centres.
    frac : ndarray of shape (m,)
        Their occupied fractions, each > 0.
    free : ndarray of bool, shape (ny, nx)
        Wholly free known pixels, on the lattice of `ij`.
    ij : ndarray of int, shape (m, 2)
        (column, row) of each pixel on that lattice.
    pixel : float
        Pixel side, metres.
    """
    padded = np.pad(free, 1)
    c, r = ij[:, 0], ij[:, 1]
    left = padded[1 + r, c].astype(float)
    right = padded[1 + r, 2 + c].astype(float)
    down = padded[r, 1 + c].astype(float)
    up = padded[2 + r, 1 + c].astype(float)
    a, b = left + right, down + up
    # (1 - a delta)(1 - b delta) = f: the smaller root, or the linear one when a or b is 0.
    ab = a * b
    disc = np.sqrt(np.maximum((a + b) ** 2 - 4.0 * ab * (1.0 - frac), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(ab > 0, ((a + b) - disc) / (2.0 * ab), (1.0 - frac) / (a + b))
    delta = np.where(a + b > 0, np.clip(np.nan_to_num(delta), 0.0, 1.0 / np.maximum(np.maximum(a, b), 1.0)), 0.0)
    shift = 0.5 * delta * pixel  # the core's centre moves half a strip away from each free side
    return pts + np.column_stack([(left - right) * shift, (down - up) * shift])


def grid_cells(
    points: NDArray[np.float64],
    occupied: NDArray[np.float64] | NDArray[np.bool_],
    pixel: float,
    max_cell: float,
    wall_reach: int = WALL_REACH_PIXELS,
    edge_strip: float = EDGE_STRIP_PIXELS,
    centre_noise: float | None = CENTRE_NOISE,
    occupied_fraction: float | None = None,
    pooling: str = "auto",
    pooling_factor: int | None = None,
) -> GridCells:
    """Wall-aware GP inputs for the known pixels of a grid, each pixel read as an occupied share.

    - Each pixel is read by :func:`read_pixels` (`pooling`, `occupied_fraction`, `pooling_factor`): the share of it
      taken as occupied, or none where its value says too little to be evidence.
    - Every known pixel within `wall_reach` pixels (chessboard distance) of one holding anything
      occupied is a cell of its own, covering its square, its target the mean of the +-1
      occupancy over it: 2 s - 1 for a pixel of occupied share s. Free pixels farther away are
      merged by a quadtree on the pixel lattice into square-ish blocks of at most `max_cell` whose
      pixels are all known and free. (Cells much larger than the length scale constrain only
      their average, and the map rang inside them: ghost walls beside real ones.)
    - Each pixel holding anything occupied also gets a point input, labelled occupied, where its
      obstacle most likely is (:func:`_core_centres`), with `centre_noise` times the noise of a
      one-pixel cell (every other input's count is multiplied by `centre_noise`, see
      :class:`GridCells`): the pixel's average says how much is occupied, the point where.
    - With `edge_strip` > 0, a wholly free pixel gets a free strip that many pixels wide along each
      edge it shares with a pixel holding anything occupied (a free pixel is free up to its edge).

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        Known pixel centres, on a lattice of pitch `pixel` (as :func:`~gpomap.convert.grids.grid_to_observations` gives).
    occupied : ndarray of shape (m,)
        The occupied fraction of each pixel in [0, 1], or bool (wholly occupied or free).
    pixel : float
        Source pixel side, metres.
    max_cell : float
        Largest side of a merged free cell, metres (at least one pixel is used).
    wall_reach : int
        Pixels around occupied ones that stay single cells.
    edge_strip : float
        Strip width in pixels; 0: no strips.
    centre_noise : float or None
        Noise of the points relative to a one-pixel cell; None: no points.
    occupied_fraction : float, optional
        The share taken for a 1 of a grid of 0s and 1s (:func:`read_pixels`), in (0, 1].
    pooling : {"auto", "any", "majority", "mean"}
        How the grid was made (:func:`read_pixels`).
    pooling_factor : int, optional
        Fine pixels per side of a pixel of the grid, when it was pooled from a finer one (:func:`read_pixels`).

    Returns
    -------
    GridCells
        The pixel cells first, then the strips (free), then the points (occupied), each with its
        target (:attr:`GridCells.target`, None when every target is +-1), and the reading
        (:attr:`GridCells.reading`). Strips and points have their pixel as their single member.

    Raises
    ------
    ValueError
        The points are not on a lattice of pitch `pixel`, a fraction is outside [0, 1], or the
        pooling or `occupied_fraction` is not one of those allowed.
    """
    pts = np.asarray(points, dtype=float)
    frac = np.asarray(occupied, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or frac.shape != (pts.shape[0],) or pts.shape[0] == 0:
        raise ValueError(f"points must have shape (m, 2) with m > 0 and occupied (m,), got {pts.shape} and {frac.shape}")
    if not ((frac >= 0.0) & (frac <= 1.0)).all():
        raise ValueError("occupied fractions must lie in [0, 1]")
    reading = read_pixels(pts, frac, pixel, pooling, occupied_fraction, pooling_factor)
    _, ij, all_index = pixel_lattice(pts, pixel)
    evidence = np.isfinite(reading.share)
    some = frac > 0.0  # anything occupied
    ny, nx = all_index.shape
    # Pixels that are not evidence get no input: for the inputs they are unknown.
    index = np.where(evidence[np.maximum(all_index, 0)] & (all_index >= 0), all_index, -1)
    some_grid = np.zeros((ny, nx), dtype=bool)
    some_grid[ij[:, 1], ij[:, 0]] = some
    known = index >= 0
    free_grid = known & ~some_grid
    if some_grid.any():
        dist = ndimage.distance_transform_cdt(~some_grid, metric="chessboard")
        far_free = free_grid & (dist > wall_reach)
    else:
        far_free = known.copy()
    max_side = max(1, math.floor(max_cell / pixel + 1e-9))

    half = 0.5 * pixel
    lower: list[NDArray[np.float64]] = []
    upper: list[NDArray[np.float64]] = []
    members: list[NDArray[np.intp]] = []
    stack = [(0, int(ny), 0, int(nx))]
    while stack:
        r0, r1, c0, c1 = stack.pop()
        block = index[r0:r1, c0:c1]
        if not (block >= 0).any():
            continue  # unknown pixels are no evidence
        h, w = r1 - r0, c1 - c0
        if (h == 1 and w == 1) or (max(h, w) <= max_side and far_free[r0:r1, c0:c1].all()):
            idx = block.ravel()
            p = pts[idx]
            lower.append(p.min(axis=0) - half)
            upper.append(p.max(axis=0) + half)
            members.append(idx)
            continue
        if h >= w:
            m = r0 + h // 2
            stack += [(m, r1, c0, c1), (r0, m, c0, c1)]
        else:
            m = c0 + w // 2
            stack += [(r0, r1, m, c1), (r0, r1, c0, m)]
    counts = np.array([m.size for m in members], dtype=np.intp)
    first = np.array([m[0] for m in members], dtype=np.intp)
    lo_a, hi_a = np.array(lower), np.array(upper)
    cells = Cells(
        lower=lo_a,
        upper=hi_a,
        node_lower=lo_a.copy(),
        node_upper=hi_a.copy(),
        occupied=some[first],
        ambiguous=np.zeros(len(members), dtype=bool),
        member_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.intp),
        member_order=np.concatenate(members).astype(np.intp),
        points=pts,
    )
    # Merged cells are wholly free, and free pixels' shares 0.
    targets = [2.0 * reading.share[first] - 1.0]

    if edge_strip > 0:
        s_lo, s_hi, s_idx = [], [], []
        padded = np.pad(some_grid, 1)
        width = edge_strip * pixel
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            # Wholly free pixels whose neighbour at (row + dy, column + dx) holds something occupied.
            neighbour = padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]
            rows, cols = np.nonzero(free_grid & neighbour)
            idx = index[rows, cols]
            c = pts[idx]
            lo, hi = c - half, c + half
            if dx:
                # The strip hugs the shared edge: x from the edge `width` into the free pixel.
                edge = c[:, 0] + dx * half
                lo[:, 0], hi[:, 0] = np.minimum(edge, edge - dx * width), np.maximum(edge, edge - dx * width)
            else:
                edge = c[:, 1] + dy * half
                lo[:, 1], hi[:, 1] = np.minimum(edge, edge - dy * width), np.maximum(edge, edge - dy * width)
            s_lo.append(lo)
            s_hi.append(hi)
            s_idx.append(idx)
        idx_all = np.concatenate(s_idx)
        cells = _extra_inputs(cells, np.vstack(s_lo), np.vstack(s_hi), np.zeros(idx_all.size, dtype=bool), idx_all)
        targets.append(np.full(idx_all.size, -1.0))

    n_inputs = len(cells)
    if centre_noise is not None:
        occ_idx = np.flatnonzero(some)
        # The share the pixel is read as, not its value: a 1 of a grid of 0s and 1s fills
        # `occupied_fraction` of it, away from its free sides.
        core = np.where(np.isfinite(reading.share) & (reading.share > 0.0), reading.share, frac)
        centres = _core_centres(pts[occ_idx], core[occ_idx], free_grid, ij[occ_idx], pixel)
        cells = _extra_inputs(cells, centres, centres.copy(), np.ones(occ_idx.size, dtype=bool), occ_idx)
        targets.append(np.ones(occ_idx.size))
    weight = np.ones(len(cells))
    if centre_noise is not None:
        weight[:n_inputs] = float(centre_noise)
    target = np.concatenate(targets)
    fields = {name: getattr(cells, name) for name in Cells.__dataclass_fields__}
    return GridCells(**fields, weight=weight, target=None if np.all(np.abs(target) == 1.0) else target, reading=reading)
