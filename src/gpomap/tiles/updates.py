"""A fitted map taking in new scans, at a cost proportional to them, and refreshed.

Absorbing files the scans' points under their blocks and counts their rays; a refresh rebuilds the
cell trees of the blocks they touched and refits the tiles whose cells changed (at most so many a
call, the longest waiting first).
"""

from __future__ import annotations

import time

import numpy as np

from gpomap.errors import EmptyDataError
from gpomap.observations import Observations, ScanData, observations_from_scans, sensor_positions
from gpomap.tiles.executors import _blas_shared
from gpomap.tiles.fits import TileFits
from gpomap.tiles.report import MapReport


class TileUpdates(TileFits, MapReport):
    """New scans taken into a fitted map (a part of :class:`~gpomap.tiles.TiledGPOM`; its ``update`` does both steps)."""

    def _observations(self, scans: ScanData) -> Observations:
        # No free_clearance here: it is applied per block when the cells are built, so a hit
        # that arrives in a later update clears the free points near it just as a batch fit would.
        b = self.base
        return observations_from_scans(scans, b.free_step, b.hit_margin, b.no_return_cap, free_cube=b.free_cube(self._dim))

    def absorb(self, scans: ScanData) -> set[tuple[int, int]]:
        """Take in scans at a cost proportional to them: their points are filed under their
        blocks and their rays counted, but no cell tree is rebuilt and no tile refitted until
        :meth:`refresh`. Predictions use the new ray counts at once, over the GP as it was.

        Parameters
        ----------
        scans : sequence of Scan

        Returns
        -------
        set of (int, int)
            The blocks waiting for :meth:`refresh` (the new ones and any left before).
        """
        self._check_fitted()
        if not isinstance(self._scans, list):
            raise ValueError("absorb() needs a map fitted on scans, not on labelled points")
        self._absorb(scans)
        return {self._decode(k) for k in self._dirty}

    def _absorb(self, scans: ScanData) -> None:
        t0 = time.perf_counter()
        scans = list(scans)
        if not scans:
            return
        try:
            obs = self._observations(scans)
        except EmptyDataError:  # scans with no usable beam add a pose to the path and nothing else
            obs = None
        if obs is not None:
            # Each point's scan, numbered as the map's scans (those kept): a block then knows them.
            numbered = None if self._scans is None else np.asarray(obs.scan_index) + len(self._scans)
            self._dirty |= self._add_points(
                np.asarray(obs.points, dtype=float), np.asarray(obs.occupied, dtype=bool), scans=numbered, weights=obs.weight
            )
            self._n_invalid += obs.n_invalid
            self._n_no_return += obs.n_no_return
        self._n_scans += len(scans)
        path = sensor_positions(scans).reshape(-1, self._dim)
        self.path_ = path if self.path_ is None else np.concatenate([self.path_, path])
        t1 = time.perf_counter()
        if self._scans is not None:
            self._scans.extend(scans)
            if self.evidence_ is not None:
                self.evidence_.add_scans(scans)
        self.timings_["absorb_points"] = t1 - t0
        self.timings_["absorb_evidence"] = time.perf_counter() - t1

    @_blas_shared
    def refresh(self, max_tiles: int | None = None, exact: bool = False) -> list[tuple[int, int]]:
        """Rebuild the cells of the blocks absorbed since the last refresh and refit the tiles
        whose cell sets changed.

        Parameters
        ----------
        max_tiles : int, optional
            Refit at most this many tiles now, those waiting longest first; the rest stay
            waiting for the next call (a bounded cost per call when data arrive faster than
            tiles can be refitted). Default: all.
        exact : bool
            Compute every covariance afresh, and refit the tiles an earlier refresh fitted by
            reusing covariances. Without it a tile reuses the covariances of the cells it had
            before (most of a refit's work), which changes its GP by rounding only (~1e-15
            relative); with it the map is the batch map of the same scans to the last bits.

        Returns
        -------
        list of (int, int)
            The tiles refitted.
        """
        self._check_fitted()
        with self._connected():
            return self._refresh(max_tiles, exact)

    @property
    def pending_tiles_(self) -> int:
        """Work waiting for :meth:`refresh`: blocks absorbed and not yet rebuilt, plus tiles not yet refitted."""
        return len(self._stale) + len(self._dirty)

    def _refresh(self, max_tiles: int | None, exact: bool) -> list[tuple[int, int]]:
        t0 = time.perf_counter()
        # Every tile that sees a block absorbed since it was fitted is waiting (oldest first).
        for k in sorted(self._dirty):
            for t in self._tiles_seeing(int(k)):
                if t not in self._stale:
                    self._stale[t] = None  # dict as an ordered set: oldest first
        if exact:
            for t in self._reused:
                self._stale.setdefault(t, None)
        waiting = list(self._stale)
        take = waiting if max_tiles is None else waiting[: max(0, int(max_tiles))]
        # Only the blocks the tiles refitted now gather from are rebuilt, so a capped refresh
        # rebuilds a bounded number of cell trees too; the rest wait with their tiles.
        need = {k for t in take for k in self._blocks_seen_by(t)}
        rebuild = sorted(self._dirty & need)
        self._build_blocks(rebuild)
        self._dirty -= set(rebuild)
        t1 = time.perf_counter()
        jobs, gathered = self._fit_jobs(take, reuse=not exact)
        todo = [j for j in jobs if j[0] in self._reused or self._signatures.get(j[0]) != gathered[j[0]].signature()]
        self._fit_tiles(todo, "refitting tiles")
        for key, (task,) in todo:
            self._signatures[key] = gathered[key].signature()
            if task.previous is not None:
                self._reused.add(key)
            else:
                self._reused.discard(key)
        for t in take:
            del self._stale[t]
        self.last_refit_ = sorted(k for k, _ in todo)
        self.timings_["update_cells"] = t1 - t0
        self.timings_["update_tile_fits"] = time.perf_counter() - t1
        return self.last_refit_
