"""The classic log-odds occupancy grid with an inverse sensor model and exact ray traversal.

Each beam updates the cells it crosses: the cell holding its end point gets the occupied
log-odds increment ``l_occ`` (if the beam returned), every other cell it passes through gets the
free increment ``l_free`` once. Cells are the exact set the segment passes through
(Amanatides & Woo 1987). Log-odds are clamped to ``[l_min, l_max]`` after each scan, so a cell
can change its mind when the world does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.scans import Scan

# Traversal entries (grid-line crossings) handled per chunk: bounds temporary memory.
_ENTRIES_PER_CHUNK: int = 1 << 22


def _line_crossings(u0: NDArray[np.float64], u1: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Where segments u0 -> u1 (1-D, in cell units) cross integer lines, in travel order.

    Returns
    -------
    seg : ndarray of int, shape (c,)
        Segment of each crossing, non-decreasing.
    t : ndarray of shape (c,)
        Crossing parameter in (0, 1), increasing within each segment.
    """
    lo, hi = np.minimum(u0, u1), np.maximum(u0, u1)
    first = np.floor(lo) + 1  # first integer strictly above lo
    counts = np.maximum(np.ceil(hi) - first, 0).astype(np.intp)  # integers strictly inside
    seg = np.repeat(np.arange(u0.size, dtype=np.intp), counts)
    starts = np.cumsum(counts) - counts
    j = np.arange(seg.size, dtype=np.intp) - np.repeat(starts, counts)
    # Walk the lines in the direction of travel so t increases.
    down = (u1 < u0)[seg]
    k = np.where(down, first[seg] + (counts[seg] - 1 - j), first[seg] + j)
    t = (k - u0[seg]) / (u1[seg] - u0[seg])
    return seg, t


def traverse(grid: GridSpec, starts: ArrayLike, ends: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Every grid cell each segment passes through, in order from start to end.

    This is the Amanatides & Woo traversal done for all segments at once. Their algorithm steps
    to whichever grid line, x or y, comes next along the ray; the cells it visits are the
    intervals between the segment's grid-line crossings taken in increasing order. We list each
    segment's x and y crossings (each already in travel order), merge the two lists exactly
    (no sort: a merge position is an index plus a count from ``searchsorted``), and take the
    cell holding the midpoint of each interval. Where a segment passes exactly through a grid
    corner the interval between the two crossings has zero length and is dropped, so the
    diagonal neighbour is visited and the side neighbours are not.

    Parameters
    ----------
    grid : GridSpec
    starts, ends : array_like of shape (b, 2)
        Segment end points in the map frame.

    Returns
    -------
    beam : ndarray of int, shape (m,)
        Segment index of each visited cell (non-decreasing).
    rows, cols : ndarray of int, shape (m,)
        The visited cells, in order along each segment. Cells outside the grid are left out;
        the cells of one segment are distinct.
    """
    p0 = (np.asarray(starts, dtype=float).reshape(-1, 2) - grid.origin) / grid.resolution
    p1 = (np.asarray(ends, dtype=float).reshape(-1, 2) - grid.origin) / grid.resolution
    b = len(p0)
    # Crossings per segment (an upper bound), to cut the work into chunks of bounded memory.
    cost = np.cumsum(np.abs(np.floor(p1) - np.floor(p0)).sum(axis=1) + 2)
    out_b, out_r, out_c = [], [], []
    lo = 0
    while lo < b:
        base = cost[lo - 1] if lo > 0 else 0.0
        hi = max(lo + 1, int(np.searchsorted(cost, base + _ENTRIES_PER_CHUNK, side="right")))
        bb, rr, cc = _traverse_chunk(p0[lo:hi], p1[lo:hi], grid.shape)
        out_b.append(bb + lo)
        out_r.append(rr)
        out_c.append(cc)
        lo = hi
    if not out_b:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty.copy(), empty.copy()
    return np.concatenate(out_b), np.concatenate(out_r), np.concatenate(out_c)


def _traverse_chunk(
    p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, int]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    b = len(p0)
    sx, tx = _line_crossings(p0[:, 0], p1[:, 0])
    sy, ty = _line_crossings(p0[:, 1], p1[:, 1])
    # Merge the x and y crossings by (segment, t). Keys 4 seg + 2 t stay inside a segment's own
    # range [4 seg, 4 seg + 2] whatever the rounding, and both key arrays are sorted, so the
    # positions below are an exact merge (ties: x first).
    kx, ky = 4.0 * sx + 2.0 * tx, 4.0 * sy + 2.0 * ty
    nx_, ny_ = kx.size, ky.size
    pos_x = np.arange(nx_) + np.searchsorted(ky, kx, side="left")
    pos_y = np.arange(ny_) + np.searchsorted(kx, ky, side="right")
    n_cross = np.bincount(sx, minlength=b) + np.bincount(sy, minlength=b)
    # Full per-segment sequences [0, crossings..., 1]: each segment gains two entries.
    first = np.cumsum(n_cross + 2) - (n_cross + 2)
    t = np.empty(nx_ + ny_ + 2 * b)
    t[first] = 0.0
    t[first + n_cross + 1] = 1.0
    t[pos_x + 2 * sx + 1] = tx
    t[pos_y + 2 * sy + 1] = ty
    seg = np.repeat(np.arange(b, dtype=np.intp), n_cross + 2)
    # Intervals between consecutive entries of the same segment.
    same = seg[1:] == seg[:-1]
    dt = t[1:] - t[:-1]
    length = np.hypot(*(p1 - p0).T)[seg[:-1]]
    # Drop zero-length intervals (x and y lines crossed at once, at a grid corner), but keep the
    # single [0, 1] interval of a zero-length segment so it still visits its own cell.
    keep = same & ((dt * length > 1e-9) | (length == 0))
    s = seg[:-1][keep]
    tm = 0.5 * (t[:-1][keep] + t[1:][keep])
    mid = p0[s] + tm[:, None] * (p1[s] - p0[s])
    cols = np.floor(mid[:, 0]).astype(np.intp)
    rows = np.floor(mid[:, 1]).astype(np.intp)
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    return s[inside], rows[inside], cols[inside]


class OccupancyGridMapper:
    """Log-odds occupancy grid mapping.

    Parameters
    ----------
    resolution : float
        Cell side, metres.
    extent : (xmin, xmax, ymin, ymax) or GridSpec, optional
        The grid to map on. Default: the box round the sensor positions and beam end points
        (no-return beams capped as below) plus a margin of three cells, with the origin snapped
        to a multiple of `resolution`.
    l_occ : float
        Log-odds added to the cell holding a beam's end point.
    l_free : float
        Log-odds added to each cell a beam passes through before its end cell.
    l_min, l_max : float
        Clamping bounds of the log-odds, applied after each scan.
    max_range_free : float, optional
        No-return beams (range at or beyond the sensor's max range) clear free space only up to
        this distance (10 m by default, as the GP methods; None: the range they recorded). They
        never mark a cell occupied.

    Attributes
    ----------
    grid_ : GridSpec
    log_odds_ : ndarray of shape (ny, nx)
        Accumulated, clamped log-odds; 0 where never observed.
    observed_ : ndarray of int, shape (ny, nx)
        Number of beam updates (free or occupied) each cell received; 0 = never observed.
    hits_ : ndarray of int, shape (ny, nx)
        Number of occupied updates (beam end points) each cell received.
    path_ : ndarray of shape (k, 2)
        Sensor positions of the fitted scans.
    """

    def __init__(
        self,
        resolution: float = 0.1,
        extent: tuple[float, float, float, float] | GridSpec | None = None,
        l_occ: float = 0.85,
        l_free: float = -0.4,
        l_min: float = -4.0,
        l_max: float = 4.0,
        max_range_free: float | None = 10.0,
    ) -> None:
        self.resolution = resolution
        self.extent = extent
        self.l_occ = l_occ
        self.l_free = l_free
        self.l_min = l_min
        self.l_max = l_max
        self.max_range_free = max_range_free

    # -- fitting ---------------------------------------------------------------------------

    def _beams(self, scans: Sequence[Scan]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.intp]]:
        """Starts, ends, hit flags and scan index of every usable beam, all scans stacked."""
        starts, ends, hit, scan_of = [], [], [], []
        for i, s in enumerate(scans):
            valid = s.valid()
            no_ret = s.no_return()
            length = s.ranges.copy()
            if self.max_range_free is not None:
                length = np.where(no_ret, np.minimum(length, self.max_range_free), length)
            a = s.world_angles()[valid]
            length = length[valid]
            n = int(valid.sum())
            starts.append(np.broadcast_to(s.pose[:2], (n, 2)))
            ends.append(s.pose[:2] + length[:, None] * np.column_stack([np.cos(a), np.sin(a)]))
            hit.append(~no_ret[valid])
            scan_of.append(np.full(n, i, dtype=np.intp))
        return (np.concatenate(starts), np.concatenate(ends), np.concatenate(hit), np.concatenate(scan_of))

    def _default_grid(self, starts: NDArray[np.float64], ends: NDArray[np.float64]) -> GridSpec:
        pts = np.concatenate([starts, ends])
        res = float(self.resolution)
        margin = 3 * res
        lo = np.floor((pts.min(axis=0) - margin) / res) * res
        hi = pts.max(axis=0) + margin
        return GridSpec.from_extent((lo[0], hi[0], lo[1], hi[1]), res)

    def fit(self, scans: Sequence[Scan]) -> OccupancyGridMapper:
        """Build the grid from scans, in the order given.

        Parameters
        ----------
        scans : sequence of Scan

        Returns
        -------
        self
        """
        if not self.l_min <= 0 <= self.l_max:
            raise ValueError(f"need l_min <= 0 <= l_max, got {self.l_min}, {self.l_max}")
        if len(scans) == 0:
            raise EmptyDataError("no scans to map")
        starts, ends, hit, scan_of = self._beams(scans)
        if len(starts) == 0:
            raise EmptyDataError(f"no usable readings in {len(scans)} scan(s): nothing to map")
        if isinstance(self.extent, GridSpec):
            grid = self.extent
        elif self.extent is not None:
            grid = GridSpec.from_extent(self.extent, self.resolution)
        else:
            grid = self._default_grid(starts, ends)
        ny, nx = grid.shape
        ncell = ny * nx

        log_odds = np.zeros(ncell)
        observed = np.zeros(ncell, dtype=np.int64)
        hits = np.zeros(ncell, dtype=np.int64)
        # Stream the beams in batches of whole scans, so memory stays bounded for long logs.
        u0 = (starts - grid.origin) / grid.resolution
        u1 = (ends - grid.origin) / grid.resolution
        cost = np.cumsum(np.abs(np.floor(u1) - np.floor(u0)).sum(axis=1) + 2)
        scan_start = np.searchsorted(scan_of, np.arange(len(scans) + 1))
        lo = 0
        while lo < len(starts):
            base = cost[lo - 1] if lo > 0 else 0.0
            hi = int(np.searchsorted(cost, base + _ENTRIES_PER_CHUNK, side="right"))
            # Round to a scan boundary (at least one whole scan).
            hi = int(scan_start[np.searchsorted(scan_start, hi, side="right") - 1])
            if hi <= lo:
                hi = int(scan_start[np.searchsorted(scan_start, lo, side="right")])
            self._update(grid, starts[lo:hi], ends[lo:hi], hit[lo:hi], scan_of[lo:hi], log_odds, observed, hits)
            lo = hi
        self.observed_ = observed.reshape(ny, nx)
        self.hits_ = hits.reshape(ny, nx)
        self.grid_ = grid
        self.log_odds_ = log_odds.reshape(ny, nx)
        self.path_ = np.array([s.pose[:2] for s in scans])
        return self

    def _update(
        self,
        grid: GridSpec,
        starts: NDArray[np.float64],
        ends: NDArray[np.float64],
        hit: NDArray[np.bool_],
        scan_of: NDArray[np.intp],
        log_odds: NDArray[np.float64],
        observed: NDArray[np.int64],
        hits: NDArray[np.int64],
    ) -> None:
        """Apply the beams of a batch of whole scans to the flat grid arrays, in place."""
        nx = grid.shape[1]
        beam, rows, cols = traverse(grid, starts, ends)
        flat = rows * nx + cols
        # The hit cell is the one holding the end point (as GridSpec.index_of, so a query at a
        # hit lands on the cell it marked); every other traversed cell is free, once per beam.
        hr, hc, hin = grid.index_of(ends)
        hit_cell = np.where(hit & hin, hr * nx + hc, -1)
        is_free = flat != hit_cell[beam]
        free_cell, free_scan = flat[is_free], scan_of[beam[is_free]]
        occ_beam = np.flatnonzero(hit_cell >= 0)
        occ_cell, occ_scan = hit_cell[occ_beam], scan_of[occ_beam]
        np.add.at(observed, free_cell, 1)
        np.add.at(observed, occ_cell, 1)
        np.add.at(hits, occ_cell, 1)
        # Both lists are ordered by scan: apply scan after scan, clamping after each. The clamp
        # makes the order matter, so the updates cannot be one global sum.
        scans = np.arange(scan_of[0], scan_of[-1] + 2)
        fcut = np.searchsorted(free_scan, scans)
        ocut = np.searchsorted(occ_scan, scans)
        for i in range(len(scans) - 1):
            fc = free_cell[fcut[i] : fcut[i + 1]]
            oc = occ_cell[ocut[i] : ocut[i + 1]]
            np.add.at(log_odds, fc, self.l_free)
            np.add.at(log_odds, oc, self.l_occ)
            touched = np.concatenate([fc, oc])
            log_odds[touched] = np.clip(log_odds[touched], self.l_min, self.l_max)

    # -- prediction ------------------------------------------------------------------------

    def _check_fitted(self) -> None:
        if not hasattr(self, "log_odds_"):
            raise NotFittedError("OccupancyGridMapper is not fitted yet: call fit(scans) first")

    def _probability_grid(self) -> NDArray[np.float64]:
        p = 1.0 / (1.0 + np.exp(-self.log_odds_))
        return np.where(self.observed_ > 0, p, 0.5)

    def predict_proba(self, points: ArrayLike) -> NDArray[np.float64]:
        """Occupancy probability of the cell holding each point.

        Parameters
        ----------
        points : array_like of shape (n, 2)

        Returns
        -------
        ndarray of shape (n,)
            ``1 / (1 + exp(-log_odds))``; exactly 0.5 in cells never observed and outside the grid.
        """
        self._check_fitted()
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        rows, cols, inside = self.grid_.index_of(p)
        out = np.full(len(p), 0.5)
        out[inside] = self._probability_grid()[rows[inside], cols[inside]]
        return out

    def predict(self, points: ArrayLike, return_var: bool = True) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability and a variance-like uncertainty.

        Parameters
        ----------
        points : array_like of shape (n, 2)
        return_var : bool
            Also return ``p (1 - p)``: the variance of a Bernoulli occupancy with probability p.
            It is not a posterior variance as a GP gives (a grid has none), but it is largest
            (0.25) where the map knows nothing and falls as evidence piles up, so it can stand in
            for one in figures and comparisons.

        Returns
        -------
        p : ndarray of shape (n,)
        var : ndarray of shape (n,)
            Only if `return_var`.
        """
        p = self.predict_proba(points)
        return (p, p * (1 - p)) if return_var else p

    def grid_map(self) -> OccupancyMap:
        """The fitted grid as an :class:`~gpomap.grid.OccupancyMap`.

        Probability 0.5 (unknown in the ternary map) where never observed; the variance layer is
        ``p (1 - p)`` as in :meth:`predict`.
        """
        self._check_fitted()
        p = self._probability_grid()
        info = {
            "method": "ogm",
            "resolution": self.grid_.resolution,
            "l_occ": self.l_occ,
            "l_free": self.l_free,
            "l_min": self.l_min,
            "l_max": self.l_max,
            "max_range_free": self.max_range_free,
        }
        return OccupancyMap(self.grid_, p, variance=p * (1 - p), path=self.path_, info=info)
