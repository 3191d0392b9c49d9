"""The evidence layer: a fitted GP map's fine cells, their ray counts on a growing lattice, and the calibration applied.

:class:`EvidenceLayer` counts the beams and the robot's path of every scan on a lattice that
grows as scans arrive, fits its calibration (:mod:`gpomap.fusion.calibration`) when asked, and
turns the GP's probability at points into the map's (the formula in :mod:`gpomap.fusion`); per
cell of a grid, and the written grids, it answers through its part :class:`~gpomap.fusion.grids.LayerGrids`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.config import MapConfig
from gpomap.counted_cells import CellCounts, CountsNear, count_cells, count_cells_without
from gpomap.evidence import RayCounts, RayEvidence, lattice_grid, next_to_hits, path_dtype
from gpomap.fusion.calibration import (
    CalibrationSample,
    EvidenceCalibration,
    GPApart,
    fit_calibration,
    fit_silent_rate,
    only_silent,
    surface_misses,
)

# Named by gpomap.fusion from this module, its first home (the fusion stage's rule for cells without counts).
from gpomap.fusion.calibration import _unseen_where_empty as _unseen_where_empty
from gpomap.fusion.grids import COUNT_DTYPE, SEEN_THROUGH_NOT_OCCUPIED, LayerGrids, without_hits
from gpomap.grid import CALIBRATED_THRESHOLDS, DEFAULT_THRESHOLDS
from gpomap.heldout import calibration_scans
from gpomap.lattice import AnyGrid, bounds_extent, cell_offset, column_bounds, extent_bounds, flat_index, grid_extent
from gpomap.observations import ScanData, data_dim
from gpomap.resources import SpillFile, release_freed_memory
from gpomap.revisit import RevisitCalibration
from gpomap.robot_path import PATH_RADIUS, path_steps
from gpomap.scans import Scan
from gpomap.stages import Counted, StageChain


def ternary_thresholds(given: tuple[float, float] | None, evidence: EvidenceLayer | None) -> tuple[float, float]:
    """A map's ternary (free below, occupied above) thresholds on the probabilities it gives: those
    `given`, else a calibrated map's (with ray evidence, :data:`gpomap.grid.CALIBRATED_THRESHOLDS`),
    else the paper's (:data:`gpomap.grid.DEFAULT_THRESHOLDS`)."""
    if given is not None:
        return given
    return CALIBRATED_THRESHOLDS if evidence is not None else DEFAULT_THRESHOLDS


#: How far (metres) the counted lattice reaches beyond the beams when scans arrive outside it: the
#: counts are copied into a larger array then, so a margin keeps that rare as the robot drives on.
LATTICE_GROWTH: float = 10.0


class EvidenceLayer(LayerGrids):
    """Ray counts and their calibration, applied on top of a fitted GP map.

    Counts add over scans, so new scans are counted on their own and added in
    (:meth:`add_scans`, at a cost proportional to the new beams); the calibration is refitted
    only when asked (:meth:`recalibrate`). Counts taken so equal counts taken at once, except
    where a beam ends exactly on a cell border, which lattices of different origins may round
    to either side (seen only in simulated worlds with walls on multiples of the cell side).

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
        The scans the GP was fitted on.
    resolution : float
        Side of the fine cells the counts of exact-point predictions are taken on, metres.
    predict_gp : callable
        Points of shape (m, 2) to the GP's probability, shape (m,) (used to calibrate).
    no_return_cap : float or None
    calibration_scans : int
        Scans held out in turn to fit the calibration.
    seed : int
    gp_apart : callable, optional
        The GP fitted on given scans, its hyperparameters held, that every calibration fits the
        surprise rate against (:func:`fit_calibration`); without it the rate is the prior.
    calibration : EvidenceCalibration, optional
        Taken as it is instead of fitted (a map of part of a log, calibrated as the whole log's).
    asked_at : ndarray of shape (m, d), optional
        With `calibration`: the only points the layer will be asked about (a map asked at a few
        points). The counts are then taken at their cells alone, window by window
        (:func:`gpomap.counted_cells.count_cells`), not over the whole lattice, and the layer
        takes no further scans and gives no grids.
    counted_without : (CountsNear, scans), optional
        With `asked_at`, when `scans` are some of another layer's: that layer's counts round the
        asked points and its other scans. The counts are then that layer's less the other scans'
        (:func:`gpomap.counted_cells.count_cells_without`), only their beams walked.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.fusion"
    # Set only on a layer counted at given points (asked_at), which no map file holds.
    _asked_at: NDArray[np.float64] | None = None
    _cells: CellCounts | None = None
    # Whether every count on the lattice was taken on the lattice itself, at once (not added
    # from scans counted on another lattice): then some scans' counts can be taken out of it
    # exactly (counts_near). Unknown (None) for a layer read from a map file.
    _counted_in_place: bool | None = None

    def __init__(
        self,
        scans: ScanData,
        resolution: float,
        predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        no_return_cap: float | None = MapConfig.no_return_cap,
        calibration_scans: int = MapConfig.calibration_scans,
        seed: int = 0,
        gp_apart: GPApart | None = None,
        calibration: EvidenceCalibration | None = None,
        asked_at: NDArray[np.float64] | None = None,
        counted_without: tuple[CountsNear, ScanData] | None = None,
    ) -> None:
        if asked_at is not None and calibration is None:
            raise ValueError("a layer counted only at given points takes its calibration as given")
        self.resolution = float(resolution)
        self._asked_at = None if asked_at is None else np.asarray(asked_at, dtype=float)
        self.gp_apart = gp_apart
        self._at_surface: NDArray[np.bool_] | None = None  # next_to_hits of the counts so far, when asked
        self.no_return_cap = no_return_cap
        self.calibration_scans = int(calibration_scans)
        self.seed = int(seed)
        self.calibration = EvidenceCalibration()
        self.report: dict[str, float] = {}
        self.sample = CalibrationSample()
        self.revisit = RevisitCalibration()
        self._scans: list[Scan | CloudScan] = []
        self._parts: list[RayEvidence] = []
        self._joined: RayEvidence | None = None
        self._dim = 2  # of the scans counted (set by add_scans)
        self.lattice: AnyGrid | None = None
        # Counts per lattice cell (COUNT_DTYPE) and the path's passes (path_dtype: 16-bit for most logs).
        self._hits: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._beam_misses: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._near_misses: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._silent: NDArray[np.number[Any]] = np.zeros((0, 0), dtype=np.int32)
        self._path: NDArray[np.integer[Any]] = np.zeros((0, 0), dtype=np.int32)
        self._grid_cache: tuple[AnyGrid, RayCounts, NDArray[np.integer[Any]], NDArray[np.bool_]] | None = None
        self._cells = None  # the counts of the asked points' cells alone (asked_at)
        self._add_scans(scans, counted_without)
        if calibration is None:
            self.recalibrate(predict_gp)
        else:
            self.calibration, self.report = calibration, {"given": 1.0}
            for part in self._parts:
                part.forget()

    # ------------------------------------------------------------------ counting
    @property
    def n_scans(self) -> int:
        """Scans counted so far."""
        return len(self._scans)

    @property
    def evidence(self) -> RayEvidence:
        """The beams and path of every scan counted, as one :class:`RayEvidence`."""
        if self._joined is None and len(self._parts) == 1:
            # One part is its own join, with the cells its counts kept for the calibration.
            self._joined = self._parts[0]
        if self._joined is None:
            offsets = np.cumsum([0] + [p.n_scans for p in self._parts[:-1]])
            parts = self._parts
            self._joined = RayEvidence(
                np.concatenate([p.starts for p in parts]).reshape(-1, self._dim),
                np.concatenate([p.ends for p in parts]).reshape(-1, self._dim),
                np.concatenate([p.hit for p in parts]).astype(bool),
                np.concatenate([p.scan + o for p, o in zip(parts, offsets)]).astype(np.intp),
                np.concatenate([p.path for p in parts]).reshape(-1, 2 * self._dim),
            )
            self._parts = [self._joined]
        return self._joined

    def add_scans(self, scans: ScanData) -> None:
        """Count the beams of `scans` (and the path to them from the last scan) and add them in.

        Parameters
        ----------
        scans : sequence of Scan
            Scans that follow those counted so far, in order.
        """
        self._add_scans(scans)

    def _add_scans(self, scans: ScanData, counted_without: tuple[CountsNear, ScanData] | None = None) -> None:
        """:meth:`add_scans`; a layer asked at a few points counts them as `counted_without` says (see the class)."""
        scans = list(scans)
        if not scans:
            return
        if self._asked_at is not None and self._scans:
            raise ValueError("a layer counted only at given points takes its scans once")
        part = RayEvidence.from_scans(scans, self.no_return_cap)
        d = self._dim = data_dim(scans)
        if self._scans:
            # The step from the last scan counted to the first new one is part of the path too.
            link = path_steps([self._scans[-1], scans[0]]).reshape(-1, 2 * d)
            part = RayEvidence(part.starts, part.ends, part.hit, part.scan, np.concatenate([link, part.path]))
        pts = np.concatenate([part.starts, part.ends, part.path[:, :d], part.path[:, d:]])
        if pts.size == 0:
            self._scans.extend(scans)
            self._parts.append(part)
            self._joined = None
            return
        # The margin holds the robot's body round a path at the data's edge.
        margin = self.resolution + PATH_RADIUS
        local = lattice_grid(bounds_extent(*column_bounds(pts)), self.resolution, margin=margin)
        del pts  # as large as the beams themselves, and not needed while they are counted
        if self._asked_at is not None:
            # The lattice's cells without its arrays: only the asked points' cells are counted.
            self.lattice = local
            cells, inside = flat_index(local, self._asked_at)
            counted = None
            if counted_without is not None:
                # Only the cells of points inside: those outside are never looked up (CellCounts.at).
                whole, others = counted_without
                left_out = RayEvidence.from_scans(list(others), self.no_return_cap)
                counted = count_cells_without(whole, left_out, part, local, cells[inside], COUNT_DTYPE)
            self._cells = counted if counted is not None else count_cells(part, local, cells, COUNT_DTYPE)
            self._scans.extend(scans)
            self._parts.append(part)
            self._joined = None
            return
        self._cover(local, path_dtype(len(self._scans) + len(scans)))
        # The first scans' counts are on the lattice itself: the calibration's held-out scans keep
        # their cells, so their leave-one-scan-out counts need no second traversal.
        keep = calibration_scans(len(scans), self.calibration_scans) if not self._scans else None
        assert self.lattice is not None
        block = self._block(local)
        if local.shape == self.lattice.shape and all(b.start == 0 for b in block):
            # The lattice is the new scans' own: counted into it, not beside it (a building's
            # lattice is tens of millions of cells, each array of them hundreds of megabytes).
            part.counts(local, keep=keep, out=self._counts())
            part.path_passes(local, out=self._path)
            self._counted_in_place = not self._scans
        else:
            self._counted_in_place = False
            counts = part.counts(local, keep=keep)
            for total, new in zip(self._counts(), counts, strict=True):
                window = total[block]
                np.add(window, new, out=window, casting="unsafe")
            del counts
            passes = self._path[block]
            np.add(passes, part.path_passes(local), out=passes, casting="unsafe")
        self._scans.extend(scans)
        self._parts.append(part)
        self._joined = None
        self._grid_cache = None
        self._at_surface = None

    def _counts(self) -> RayCounts:
        """The counted lattice's arrays, as :class:`~gpomap.evidence.RayCounts` (not copied)."""
        return RayCounts(self._hits, self._beam_misses, self._near_misses, self._silent)

    def _block(self, grid: AnyGrid) -> tuple[slice, ...]:
        """The slices of the lattice's arrays that `grid` (on the same cell lattice) covers."""
        assert self.lattice is not None
        return tuple(slice(o, o + n) for o, n in zip(cell_offset(grid, self.lattice), grid.shape, strict=True))

    def _cover(self, local: AnyGrid, path: Any = np.int32) -> None:
        """Grow the counted lattice (a copy, with :data:`LATTICE_GROWTH` to spare) to hold `local`,
        its path's passes of type `path` (:func:`path_dtype`) or wider."""
        if self.lattice is None:
            self.lattice = local
            self._hits = np.zeros(local.shape, dtype=COUNT_DTYPE)
            self._beam_misses = np.zeros(local.shape, dtype=COUNT_DTYPE)
            self._near_misses = np.zeros(local.shape, dtype=COUNT_DTYPE)
            # Whole updates, one a scan at most: as narrow as the path's passes.
            self._silent = np.zeros(local.shape, dtype=path)
            self._path = np.zeros(local.shape, dtype=path)
            return
        if np.iinfo(path).max > np.iinfo(self._path.dtype).max:
            self._path = self._path.astype(path)
            self._silent = self._silent.astype(path)
        offset = cell_offset(local, self.lattice)
        if all(o >= 0 and o + n <= m for o, n, m in zip(offset, local.shape, self.lattice.shape, strict=True)):
            return
        (alo, ahi), (blo, bhi) = extent_bounds(grid_extent(self.lattice)), extent_bounds(grid_extent(local))
        inner = self.resolution / 2  # the old edges, pulled in half a cell so they stay on the lattice
        union = bounds_extent(np.minimum(alo + inner, blo), np.maximum(ahi - inner, bhi))
        grown = lattice_grid(union, self.resolution, margin=LATTICE_GROWTH)
        old = self.lattice
        self.lattice = grown
        block = self._block(old)
        for name in ("_hits", "_beam_misses", "_near_misses", "_silent", "_path"):
            arr = np.zeros(grown.shape, dtype=getattr(self, name).dtype)
            arr[block] = getattr(self, name)
            setattr(self, name, arr)

    def counts_near(self, points: NDArray[np.float64]) -> CountsNear | None:
        """The counts round `points` (shape (m, 2)) that a map of some of these scans asked at
        them takes its own from (the `counted_without` of its layer); None for a layer without
        a planar lattice of counts, or whose counts were added from other lattices (updates)."""
        if not self._counted_in_place or self.lattice is None or self._asked_at is not None or self._dim != 2:
            return None
        return CountsNear.of(self.lattice, self._counts(), points)

    @contextmanager
    def set_aside(self) -> Iterator[None]:
        """Hold the counted lattice's arrays in a temporary file while the block runs, and read
        them back, the same to the bit, after it.

        A fit that fits another map of part of its data (the later visit's map of the other
        stretches) does so beside this layer, whose arrays are the building's size and unused
        meanwhile. Nothing may ask this layer for counts inside the block.
        """
        names = ("_hits", "_beam_misses", "_near_misses", "_silent", "_path")
        spill = SpillFile()
        held = {}
        for name in names:
            array = getattr(self, name)
            held[name] = (spill.put(array), array.dtype, array.shape)
            setattr(self, name, np.zeros((0,) * array.ndim, dtype=array.dtype))
        del array
        self._at_surface, self._grid_cache = None, None  # caches, made again when asked
        release_freed_memory()
        try:
            yield
        finally:
            for name, (where, dtype, shape) in held.items():
                setattr(self, name, spill.get(where, dtype, shape))
            spill.close()

    def fit_revisit(
        self,
        p_later: NDArray[np.float64],
        occupied_later: NDArray[np.bool_],
        silent_later: NDArray[np.bool_] | None = None,
    ) -> RevisitCalibration:
        """Fit the silent rate and the later visit's recalibration on a held-out stretch's points,
        as the map fitted without them gave them; both are then applied to every probability
        this layer gives.

        The silent rate (:attr:`EvidenceCalibration.silent_rate`, :func:`fit_silent_rate`) is
        fitted on the points whose cells only that map's beams without a return reached: a
        stretch held out shows how often such cells hold a surface, where scans held out one at a
        time see few of them and the map's GP has learnt their own points. The recalibration
        (:meth:`gpomap.revisit.RevisitCalibration.fit`) follows, on the held-out points and on
        this calibration's own sample, half each, the silent rate applied to both.

        Parameters
        ----------
        p_later : ndarray of shape (m,)
            The map of the other stretches' probability at the held-out stretch's points, with
            this layer's calibration and no silent rate.
        occupied_later : ndarray of bool, shape (m,)
        silent_later : ndarray of bool, shape (m,), optional
            Whether only that map's beams without a return reached each point's cell; without it
            the silent rate is not fitted.

        Returns
        -------
        RevisitCalibration
        """
        if silent_later is not None:
            rate, mix = fit_silent_rate(p_later[silent_later], occupied_later[silent_later])
            self.calibration = replace(self.calibration, silent_rate=rate, silent_mix=mix)
            self.report["silent_points"] = float(np.count_nonzero(silent_later))
            p_later = self.calibration.with_silent(p_later, silent_later)
        sample = self.sample
        p_among = self.calibration.with_silent(sample.probability, sample.silent)
        self.revisit = RevisitCalibration.fit(p_later, occupied_later, p_among, sample.occupied)
        return self.revisit

    def recalibrate(self, predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> None:
        """Refit the calibration's five weights and surprise rate on the scans counted so far (see
        :func:`fit_calibration`). The silent rate stays as the last :meth:`fit_revisit` fitted it,
        as the recalibration does.

        Parameters
        ----------
        predict_gp : callable
            Points of shape (m, 2) to the GP's probability, shape (m,).
        """
        if self.lattice is None:
            self.calibration, self.report, self.sample = EvidenceCalibration(), {"n_points": 0}, CalibrationSample()
            return
        silent = {"silent_rate": self.calibration.silent_rate, "silent_mix": self.calibration.silent_mix}
        fitted, self.report, self.sample = fit_calibration(
            self._scans,
            self.evidence,
            self.lattice,
            predict_gp,
            self.calibration_scans,
            2 * self.resolution,
            self.no_return_cap,
            self.seed,
            counts=self._counts(),
            gp_apart=self.gp_apart,
        )
        self.calibration = replace(fitted, **silent)
        # A cached grid's surface cells were found (or not) for the calibration before.
        self._grid_cache = None
        for part in self._parts:
            part.forget()

    # ------------------------------------------------------------------ applying
    def counts_at(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Weighted hits (:meth:`EvidenceCalibration.hits`) and weighted misses
        (:meth:`EvidenceCalibration.misses`, path included) of the fine cell holding each point (0
        outside the counted area), and whether only beams that returned nothing reached it
        (:func:`~gpomap.fusion.calibration.only_silent`), each of shape (m,)."""
        n = np.asarray(points).shape[0]
        if self.lattice is None:
            return np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)
        cell, inside = flat_index(self.lattice, points)
        at_surface: NDArray[np.bool_] | None
        path: NDArray[np.integer[Any]]
        if self._cells is not None:
            hits, beam, near, silent, path, at_surface = self._cells.at(cell, inside)
        else:
            hits, beam, near, silent = (a.reshape(-1)[cell] for a in self._counts())
            path = self._path.reshape(-1)[cell]
            at_surface = self.at_surface().reshape(-1)[cell] if self._weighs_surface() else None
        surface = surface_misses(beam, near, at_surface) if at_surface is not None and self._weighs_surface() else 0.0
        return (
            np.where(inside, self.calibration.hits(hits, near), 0.0),
            np.where(inside, self.calibration.misses(beam, near, path, surface), 0.0),
            inside & only_silent(hits, beam, silent, path),
        )

    def _weighs_surface(self) -> bool:
        """Whether the calibration weighs surface misses apart from other misses (else they need not be found)."""
        return self.calibration.surface_weight != 1.0

    def at_surface(self) -> NDArray[np.bool_]:
        """Cells of the counted lattice a beam ended in or next to one (:func:`gpomap.evidence.next_to_hits`), shape lattice.shape."""
        if self._at_surface is None or self._at_surface.shape != self._hits.shape:
            self._at_surface = next_to_hits(self._hits)
        return self._at_surface

    def proba(
        self, points: NDArray[np.float64], p_gp: NDArray[np.float64], p_unseen: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Probability at points, ndarray of shape (m,), from the GP's probability there: the
        map's stages after the squash (:meth:`gpomap.stages.StageChain.after_squash`) on each
        point's cell's counts.

        `p_unseen`, the GP's probability for unseen space, is taken where no beam (and no step of
        the path) crossed the point's cell; default `p_gp`.
        """
        h, m, silent = self.counts_at(points)
        return StageChain.after_squash(self.calibration, self.revisit, Counted(p_gp, p_unseen, h, m, silent))

    def observed_at(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether a ray crossed or ended in the fine cell holding each point, or the robot's path
        passed it (:meth:`grid_observed`'s rule at points), shape (m,)."""
        hits, misses, _ = self.counts_at(points)
        return np.asarray((hits + misses) > 0)

    def seen_through_at(self, points: NDArray[np.float64]) -> NDArray[np.bool_] | None:
        """Whether no beam ended in the fine cell holding each point (True outside the counted
        area), shape (m,); None where the ternary map does not use it (:data:`SEEN_THROUGH_NOT_OCCUPIED`)."""
        if not SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False):
            return None
        if self.lattice is None:
            return np.ones(np.asarray(points).shape[0], dtype=bool)
        cell, inside = flat_index(self.lattice, points)
        if self._cells is not None:
            return ~inside | without_hits(self._cells.at(cell, inside)[0])
        return ~inside | without_hits(self._hits.reshape(-1)[cell])

    def summary(self) -> dict[str, float]:
        """The calibration and how it was fitted."""
        c = self.calibration
        return {
            "hit_weight": c.hit_weight,
            "prior_weight": c.prior_weight,
            "near_weight": c.near_weight,
            "near_hit_weight": c.near_hit_weight,
            "surface_weight": c.surface_weight,
            **self.report,
            "surprise_rate": c.surprise_rate,
            "silent_rate": c.silent_rate,
            "silent_mix": c.silent_mix,
            "revisit_slope": self.revisit.slope,
            "revisit_shift": self.revisit.shift,
        }
