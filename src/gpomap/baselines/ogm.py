"""Occupancy grids with exact ray traversal: the two models users know.

- **log-odds** (OctoMap's sensor model and defaults): each scan adds ``l_occ`` = logit(0.7) =
  +0.85 to the cells holding its hits and ``l_free`` = logit(0.4) = -0.405 to every other cell its
  beams cross, **once per cell per scan** (a cell crossed by ten beams of one scan gets one miss),
  and a cell that is both a hit and crossed in the same scan counts as a hit only ("a hit wins").
  Log-odds are clamped to [logit(0.1192), logit(0.971)] = [-2.00, 3.51] after each update, so a cell
  can change its mind when the world does. This is ``OccupancyOcTreeBase::insertPointCloud``
  (``computeUpdate`` builds the scan's free and occupied key sets and erases occupied keys from the
  free set; ``updateNode`` then adds the log-odds with clamping).
- **counting** (the reflection / counting model of Burgard et al. and GMapping's
  ``PointAccumulator``): ``p = (hits + 1) / (hits + misses + 2)``, the posterior mean of a cell's
  hit rate under a uniform prior. As in GMapping's ``registerScan``, hits and misses are counted
  **per beam** (every beam crossing a cell adds a miss, every beam ending in it a hit); per scan
  (``update="scan"``, with hits winning as above) is available too.

Both: the cells a beam crosses are the exact set its segment passes through (Amanatides & Woo
1987, in 2-D grids and 3-D voxel lattices alike: fitted on point clouds the grid is the 3-D grid
baseline, an OctoMap at its finest level without the tree); the cell holding a returned beam's end point gets the hit and every other cell it crosses a
miss; a no-return beam only gives misses, up to ``max_range_free`` (10 m, as the GP methods'
no-return cap) and never a hit. Cells never observed have probability exactly 0.5. Everything is
vectorised over beams; the only Python loop is over scans, for the clamped log-odds sum (clamping
makes it order-dependent).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.evidence import RayEvidence
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.lattice import AnyGrid, bounds_extent, flat_index, grid_from_extent, grid_size
from gpomap.observations import ScanData, sensor_positions
from gpomap.raycast import ENTRIES_PER_CHUNK, traverse
from gpomap.voxels import VoxelMap, VoxelSpec


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


#: OctoMap's defaults (OccupancyOcTreeBase constructor): hit 0.7, miss 0.4, clamping 0.1192 / 0.971.
P_HIT, P_MISS, P_CLAMP_MIN, P_CLAMP_MAX = 0.7, 0.4, 0.1192, 0.971
L_HIT, L_MISS, L_MIN, L_MAX = _logit(P_HIT), _logit(P_MISS), _logit(P_CLAMP_MIN), _logit(P_CLAMP_MAX)
SENSOR_MODELS = ("logodds", "counting")


class OccupancyGridMapper:
    """Occupancy grid mapping: OctoMap's log-odds model or the counting model.

    Parameters
    ----------
    resolution : float
        Cell side, metres.
    extent : (xmin, xmax, ymin, ymax) or GridSpec, optional
        The grid to map on ((xmin, xmax, ymin, ymax, zmin, zmax) or a VoxelSpec for point
        clouds). Default: the box round the sensor positions and beam end points (no-return
        beams capped as below) plus a margin of three cells, with the origin snapped to a
        multiple of `resolution`.
    sensor_model : {"logodds", "counting"}
        See the module docstring.
    l_occ, l_free : float
        Log-odds added for a hit and for a miss ("logodds"; OctoMap's +0.847 and -0.405).
    l_min, l_max : float
        Clamping bounds of the log-odds ("logodds"; OctoMap's -2.000 and 3.511).
    max_range_free : float, optional
        No-return beams (range at or beyond the sensor's max range) give misses only up to this
        distance (10 m by default, as the GP methods; None: the range they recorded). They
        never give a hit.
    update : {"scan", "beam"}, optional
        Count each cell once per scan (a hit winning over a miss) or once per beam crossing it.
        Default: "scan" for "logodds" (OctoMap), "beam" for "counting" (GMapping).

    Attributes
    ----------
    grid_ : GridSpec, or VoxelSpec for point clouds
    log_odds_ : ndarray of shape grid_.shape, (ny, nx) or (nz, ny, nx)
        "logodds": accumulated, clamped log-odds; "counting": the log-odds of the counting
        probability. 0 where never observed.
    observed_ : ndarray of int, shape grid_.shape
        Number of updates (hits + misses) each cell received; 0 = never observed.
    hits_, misses_ : ndarray of int, shape grid_.shape
        Number of hit and miss updates each cell received.
    path_ : ndarray of shape (k, d)
        Sensor positions of the fitted scans.
    """

    def __init__(
        self,
        resolution: float = 0.1,
        extent: tuple[float, ...] | AnyGrid | None = None,
        sensor_model: str = "logodds",
        l_occ: float = L_HIT,
        l_free: float = L_MISS,
        l_min: float = L_MIN,
        l_max: float = L_MAX,
        max_range_free: float | None = 10.0,
        update: str | None = None,
    ) -> None:
        self.resolution = resolution
        self.extent = extent
        self.sensor_model = sensor_model
        self.l_occ = l_occ
        self.l_free = l_free
        self.l_min = l_min
        self.l_max = l_max
        self.max_range_free = max_range_free
        self.update = update

    def __repr__(self) -> str:
        return f"OccupancyGridMapper(resolution={self.resolution}, sensor_model={self.sensor_model!r}, update={self._update_mode()!r})"

    def _update_mode(self) -> str:
        if self.update is not None:
            return self.update
        return "scan" if self.sensor_model == "logodds" else "beam"

    # -- fitting ---------------------------------------------------------------------------

    def _default_grid(self, starts: NDArray[np.float64], ends: NDArray[np.float64]) -> AnyGrid:
        pts = np.concatenate([starts, ends])
        res = float(self.resolution)
        margin = 3 * res
        lo = np.floor((pts.min(axis=0) - margin) / res) * res
        hi = pts.max(axis=0) + margin
        return grid_from_extent(bounds_extent(lo, hi), res)

    def fit(self, scans: ScanData) -> OccupancyGridMapper:
        """Build the grid from planar scans (a 2-D grid) or point clouds (a 3-D grid), in the order given.

        Parameters
        ----------
        scans : sequence of Scan, or sequence of CloudScan

        Returns
        -------
        self
        """
        if self.sensor_model not in SENSOR_MODELS:
            raise ValueError(f"sensor_model must be one of {SENSOR_MODELS}, got {self.sensor_model!r}")
        if self._update_mode() not in ("scan", "beam"):
            raise ValueError(f"update must be 'scan' or 'beam', got {self.update!r}")
        if not self.l_min <= 0 <= self.l_max:
            raise ValueError(f"need l_min <= 0 <= l_max, got {self.l_min}, {self.l_max}")
        if len(scans) == 0:
            raise EmptyDataError("no scans to map")
        beams = RayEvidence.from_scans(scans, self.max_range_free)
        starts, ends, hit, scan_of = beams.starts, beams.ends, beams.hit, beams.scan
        if len(starts) == 0:
            raise EmptyDataError(f"no usable readings in {len(scans)} scan(s): nothing to map")
        if self.extent is None:
            grid = self._default_grid(starts, ends)
        elif isinstance(self.extent, GridSpec | VoxelSpec):
            grid = self.extent
        else:
            grid = grid_from_extent(tuple(self.extent), self.resolution)
        ncell = grid_size(grid)

        log_odds = np.zeros(ncell)
        hits = np.zeros(ncell, dtype=np.int64)
        misses = np.zeros(ncell, dtype=np.int64)
        # Stream the beams in batches of whole scans, so memory stays bounded for long logs.
        u0 = (starts - grid.origin) / grid.resolution
        u1 = (ends - grid.origin) / grid.resolution
        cost = np.cumsum(np.abs(np.floor(u1) - np.floor(u0)).sum(axis=1) + 2)
        scan_start = np.searchsorted(scan_of, np.arange(len(scans) + 1))
        lo = 0
        while lo < len(starts):
            base = cost[lo - 1] if lo > 0 else 0.0
            hi = int(np.searchsorted(cost, base + ENTRIES_PER_CHUNK, side="right"))
            # Round to a scan boundary (at least one whole scan).
            hi = int(scan_start[np.searchsorted(scan_start, hi, side="right") - 1])
            if hi <= lo:
                hi = int(scan_start[np.searchsorted(scan_start, lo, side="right")])
            self._apply(grid, starts[lo:hi], ends[lo:hi], hit[lo:hi], scan_of[lo:hi], log_odds, hits, misses)
            lo = hi
        if self.sensor_model == "counting":
            log_odds = np.log((hits + 1.0) / (misses + 1.0))  # logit of (h + 1) / (h + m + 2)
        self.hits_ = hits.reshape(grid.shape)
        self.misses_ = misses.reshape(grid.shape)
        self.observed_ = self.hits_ + self.misses_
        self.grid_ = grid
        self.log_odds_ = log_odds.reshape(grid.shape)
        self.path_ = sensor_positions(scans)
        return self

    def _apply(
        self,
        grid: AnyGrid,
        starts: NDArray[np.float64],
        ends: NDArray[np.float64],
        hit: NDArray[np.bool_],
        scan_of: NDArray[np.intp],
        log_odds: NDArray[np.float64],
        hits: NDArray[np.int64],
        misses: NDArray[np.int64],
    ) -> None:
        """Apply the beams of a batch of whole scans to the flat grid arrays, in place."""
        ncell = hits.size
        beam, *idx = traverse(grid, starts, ends)
        flat = np.ravel_multi_index(tuple(idx), grid.shape)
        # The hit cell is the one holding the end point (as GridSpec.index_of, so a query at a
        # hit lands on the cell it marked); every other cell the beam crosses is a miss.
        end_cell, hin = flat_index(grid, ends)
        hit_cell = np.where(hit & hin, end_cell, -1)
        is_miss = flat != hit_cell[beam]
        miss_cell, miss_scan = flat[is_miss], scan_of[beam[is_miss]]
        hit_beam = np.flatnonzero(hit_cell >= 0)
        hit_cell, hit_scan = hit_cell[hit_beam], scan_of[hit_beam]
        if self._update_mode() == "beam":
            hits += np.bincount(hit_cell, minlength=ncell)
            misses += np.bincount(miss_cell, minlength=ncell)
            if self.sensor_model == "logodds":
                self._clamped_sum(log_odds, miss_scan, miss_cell, hit_scan, hit_cell, unique=False)
            return
        # Once per cell per scan: the scan's distinct (scan, cell) keys, hits removed from misses.
        hkey = np.unique(hit_scan.astype(np.int64) * ncell + hit_cell)
        mkey = np.unique(miss_scan.astype(np.int64) * ncell + miss_cell)
        mkey = mkey[~np.isin(mkey, hkey, assume_unique=True)]
        hits += np.bincount(hkey % ncell, minlength=ncell)
        misses += np.bincount(mkey % ncell, minlength=ncell)
        if self.sensor_model == "logodds":
            self._clamped_sum(log_odds, mkey // ncell, mkey % ncell, hkey // ncell, hkey % ncell, unique=True)

    def _clamped_sum(
        self,
        log_odds: NDArray[np.float64],
        miss_scan: NDArray[np.integer],
        miss_cell: NDArray[np.integer],
        hit_scan: NDArray[np.integer],
        hit_cell: NDArray[np.integer],
        unique: bool,
    ) -> None:
        """Add the log-odds scan after scan (both lists sorted by scan), clamping after each.

        The clamp makes the order matter, so the updates cannot be one global sum. With `unique`
        a cell appears at most once per scan in each list (and never in both), and OctoMap clamps
        after every single update, which is then the same as clamping after the scan.
        """
        first = int(min(miss_scan[:1].min(initial=2**62), hit_scan[:1].min(initial=2**62)))
        last = int(max(miss_scan[-1:].max(initial=-1), hit_scan[-1:].max(initial=-1)))
        if last < first:
            return
        scans = np.arange(first, last + 2)
        mcut = np.searchsorted(miss_scan, scans)
        hcut = np.searchsorted(hit_scan, scans)
        for i in range(len(scans) - 1):
            mc = miss_cell[mcut[i] : mcut[i + 1]]
            hc = hit_cell[hcut[i] : hcut[i + 1]]
            if unique:
                log_odds[mc] = np.clip(log_odds[mc] + self.l_free, self.l_min, self.l_max)
                log_odds[hc] = np.clip(log_odds[hc] + self.l_occ, self.l_min, self.l_max)
            else:
                np.add.at(log_odds, mc, self.l_free)
                np.add.at(log_odds, hc, self.l_occ)
                touched = np.concatenate([mc, hc])
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
        points : array_like of shape (n, d)
            d the grid's dimension (2, or 3 for a grid fitted on point clouds).

        Returns
        -------
        ndarray of shape (n,)
            ``1 / (1 + exp(-log_odds))`` ("logodds") or ``(h + 1) / (h + m + 2)`` ("counting");
            exactly 0.5 in cells never observed and outside the grid.
        """
        self._check_fitted()
        p = np.asarray(points, dtype=float).reshape(-1, len(self.grid_.shape))
        cell, inside = flat_index(self.grid_, p)
        out = np.full(len(p), 0.5)
        out[inside] = self._probability_grid().reshape(-1)[cell[inside]]
        return out

    def predict(
        self, points: ArrayLike, return_var: bool = True
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability and a variance-like uncertainty.

        Parameters
        ----------
        points : array_like of shape (n, d)
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

    def grid_map(self) -> Any:
        """The fitted grid as an :class:`~gpomap.grid.OccupancyMap` (a :class:`~gpomap.voxels.VoxelMap` in 3-D).

        Probability 0.5 (unknown in the ternary map) where never observed; the variance layer is
        ``p (1 - p)`` as in :meth:`predict`.
        """
        self._check_fitted()
        p = self._probability_grid()
        info = {
            "method": f"ogm-{self.sensor_model}",
            "resolution": self.grid_.resolution,
            "update": self._update_mode(),
            "l_occ": self.l_occ,
            "l_free": self.l_free,
            "l_min": self.l_min,
            "l_max": self.l_max,
            "max_range_free": self.max_range_free,
        }
        if isinstance(self.grid_, VoxelSpec):
            return VoxelMap(self.grid_, p, variance=p * (1 - p), info=info)
        return OccupancyMap(self.grid_, p, variance=p * (1 - p), path=self.path_, info=info)

    def summary(self) -> dict[str, Any]:
        """The sensor model, the grid and how much of it the scans observed."""
        self._check_fitted()
        return {
            **self.grid_map().info,
            "grid_shape": list(self.grid_.shape),
            "n_scans": int(self.path_.shape[0]),
            "n_observed_cells": int((self.observed_ > 0).sum()),
            "n_occupied_cells": int((self._probability_grid() > 0.5).sum()),
        }

    def grid(self, resolution: float | None = None, extent: tuple[float, ...] | None = None) -> Any:
        """The map a user gets: the fitted grid itself (`resolution` and `extent` must match or be None).

        A grid has no finer map than its own cells, so unlike the GP estimators it is not
        resampled; this is here so every method answers ``grid(...)``.
        """
        self._check_fitted()
        if resolution is not None and not math.isclose(resolution, self.grid_.resolution):
            raise ValueError(f"this grid has {self.grid_.resolution} m cells; cannot give {resolution} m")
        if extent is not None:
            raise ValueError("an occupancy grid is written on its own extent; fit it with extent=... instead")
        return self.grid_map()
