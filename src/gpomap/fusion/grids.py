"""The evidence layer on a grid: its counts per cell of any grid, and the written grid on them.

:class:`LayerGrids` is the part of :class:`~gpomap.fusion.EvidenceLayer` that answers per cell
of a grid rather than at points: the cells' counts (read from the counted lattice when the grid's
cells are its own, else counted afresh), the map's probability on them, the cells beams saw
through, and the written grid, whose GP is sampled coarsely and, when large, built in bands of
rows (:mod:`gpomap.fusion.written`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.config import PROFILES
from gpomap.evidence import COUNT_DTYPE, RayCounts, RayEvidence, next_to_hits
from gpomap.fusion.calibration import EvidenceCalibration, only_silent, surface_misses
from gpomap.fusion.written import (
    BlendedMoments,
    GPPredict,
    SpilledGrid,
    band_rows,
    gp_samples,
    gp_sampling_factor,
    in_bands,
    read_grid,
)
from gpomap.grid import GridSpec
from gpomap.lattice import AnyGrid, cell_offset, interpolate, overlap
from gpomap.revisit import RevisitCalibration
from gpomap.stages import Counted, StageChain

#: Whether the ternary map, per dimension of the data, never calls occupied a cell no beam ended in
#: (:func:`gpomap.grid.ternary`'s ``seen_through``), as neither occupancy grid would: one beams or
#: the robot crossed, or one nothing reached, that the map thinks likely occupied (a surface beside
#: it, the GP's guess) is unknown instead. Planar maps: grazing beams cross the cells in front of
#: walls, and unexplored space round a building takes the GP's guess (docs/choices.md). Point clouds
#: mark what no ray reached in their outputs instead (:attr:`gpomap.voxels.VoxelMap.observed`).
SEEN_THROUGH_NOT_OCCUPIED: dict[int, bool] = {d: p.seen_through_not_occupied for d, p in PROFILES.items()}


def without_hits(hits: ArrayLike) -> NDArray[np.bool_]:
    """Cells no beam ended in (no `hits`), which the ternary map never calls occupied
    (:data:`SEEN_THROUGH_NOT_OCCUPIED`; the shape of `hits`)."""
    return np.asarray(hits) == 0


class LayerGrids:
    """The evidence layer's answers per cell of a grid (a part of :class:`~gpomap.fusion.EvidenceLayer`).

    It reads the layer's counted lattice and fitted stages, which the layer sets (declared here only).
    """

    resolution: float
    lattice: AnyGrid | None
    calibration: EvidenceCalibration
    revisit: RevisitCalibration
    _dim: int
    _hits: NDArray[np.floating[Any]]
    _beam_misses: NDArray[np.floating[Any]]
    _near_misses: NDArray[np.floating[Any]]
    _silent: NDArray[np.number[Any]]
    _path: NDArray[np.integer[Any]]
    _at_surface: NDArray[np.bool_] | None
    _grid_cache: tuple[AnyGrid, RayCounts, NDArray[np.integer[Any]], NDArray[np.bool_]] | None

    if TYPE_CHECKING:
        # The layer's own, on its counted lattice (declared for the type checker only).
        @property
        def evidence(self) -> RayEvidence: ...

        def at_surface(self) -> NDArray[np.bool_]: ...

        def _weighs_surface(self) -> bool: ...

    def grid_seen_through(self, grid: AnyGrid) -> NDArray[np.bool_] | None:
        """:meth:`~gpomap.fusion.EvidenceLayer.seen_through_at` per cell of `grid`, counted on its own cells (the counts of
        :meth:`grid_counts`, cached), shape grid.shape; None where not used."""
        if not SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False):
            return None
        if self._grid_cache is None or self._grid_cache[0] != grid:
            self._grid_cache = (grid, *self._raw_grid_counts(grid))
        _, counts, _, _ = self._grid_cache
        return without_hits(counts.hits)

    def _on_lattice(self, grid: AnyGrid) -> bool:
        """Whether `grid`'s cells are cells of the counted lattice (same side, origin on a corner)."""
        if self.lattice is None or not math.isclose(grid.resolution, self.resolution, rel_tol=1e-12):
            return False
        d = (np.asarray(grid.origin) - np.asarray(self.lattice.origin)) / self.resolution
        return bool(np.all(np.abs(d - np.round(d)) < 1e-6))

    def _raw_grid_counts(self, grid: AnyGrid) -> tuple[RayCounts, NDArray[np.integer[Any]], NDArray[np.bool_]]:
        """The beams' counts, the path's passes and the cells at a surface
        (:func:`gpomap.evidence.next_to_hits`) per cell of `grid`."""
        if not self._on_lattice(grid):
            counts = self.evidence.counts(grid)
            at_surface = next_to_hits(counts.hits) if self._weighs_surface() else np.zeros(grid.shape, dtype=bool)
            return counts, self.evidence.path_passes(grid), at_surface
        # The grid's cells are lattice cells: read the running counts (zero beyond them), and
        # whether a cell is at a surface from the whole lattice's hits, its window's edges too.
        assert self.lattice is not None
        out = [np.zeros(grid.shape, dtype=COUNT_DTYPE) for _ in RayCounts._fields]
        path = np.zeros(grid.shape, dtype=np.int32)
        at_surface = np.zeros(grid.shape, dtype=bool)
        where = overlap(cell_offset(grid, self.lattice), grid.shape, self.lattice.shape)
        if where is not None:
            lattice = (self._hits, self._beam_misses, self._near_misses, self._silent, self._path)
            for o, a in zip((*out, path), lattice, strict=True):
                o[where[0]] = a[where[1]]
            if self._weighs_surface():
                at_surface[where[0]] = self.at_surface()[where[1]]
        return RayCounts(*out), path, at_surface

    def grid_observed(self, grid: AnyGrid) -> NDArray[np.bool_]:
        """Cells of `grid` a ray crossed or ended in, or the robot's path passed, shape grid.shape."""
        hits, misses, _ = self.grid_counts(grid)
        return np.asarray((hits + misses) > 0)

    def grid_counts(self, grid: AnyGrid) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Weighted hits (:meth:`EvidenceCalibration.hits`) and weighted misses
        (:meth:`EvidenceCalibration.misses`, path included) per cell of `grid`, counted on that
        grid's own cells (the last is cached), and the cells only beams that returned nothing
        reached (:func:`~gpomap.fusion.calibration.only_silent`), each of shape grid.shape."""
        if self._grid_cache is None or self._grid_cache[0] != grid:
            self._grid_cache = (grid, *self._raw_grid_counts(grid))
        _, counts, path, at_surface = self._grid_cache
        surface = surface_misses(counts.misses, counts.near, at_surface)
        return (
            self.calibration.hits(counts.hits, counts.near),
            self.calibration.misses(counts.misses, counts.near, path, surface),
            only_silent(counts.hits, counts.misses, counts.silent, path),
        )

    def grid_proba(
        self, grid: AnyGrid, p_gp: NDArray[np.float64], p_unseen: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Probability per cell of `grid`, shape grid.shape, from the GP's probabilities per cell (see :meth:`~gpomap.fusion.EvidenceLayer.proba`)."""
        h, m, silent = self.grid_counts(grid)
        unseen = None if p_unseen is None else np.asarray(p_unseen).reshape(grid.shape)
        counted = Counted(np.asarray(p_gp).reshape(grid.shape), unseen, h, m, silent)
        return StageChain.after_squash(self.calibration, self.revisit, counted)

    def written_grid(
        self,
        grid: AnyGrid,
        length_scale: float,
        predict_gp: GPPredict,
        moments: BlendedMoments | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """Probability and latent variance per cell of `grid`, each of shape grid.shape, and the
        cells beams saw through (:meth:`grid_seen_through`, or None): :meth:`written_bands`, read."""
        return read_grid(self.written_bands(grid, length_scale, predict_gp, moments))

    def written_bands(
        self,
        grid: AnyGrid,
        length_scale: float,
        predict_gp: GPPredict,
        moments: BlendedMoments | None = None,
    ) -> SpilledGrid | tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """:meth:`written_grid`'s arrays, or, for a grid made in bands, the bands waiting in a
        temporary file (:class:`~gpomap.fusion.written.SpilledGrid`) to be read once this layer
        and its map may be let go.

        The counts give each cell its detail; the smooth GP under them is sampled more coarsely
        (:func:`gp_sampling_factor`) and interpolated (bi- or trilinearly). A planar grid of more
        than :data:`~gpomap.resources.WRITTEN_BAND_CELLS` cells is built in bands of rows
        (:func:`~gpomap.fusion.written.in_bands`), each on the GP samples
        the whole grid would take (the band's rows a whole number of variance samples): the
        same map, up to the local prediction's tolerance and the round-off of the samples'
        coordinates. That round-off can turn which of two tiles' cores is nearer to a sample
        no tile reaches, when they are as near to it (the nearest predicts it alone), which moves
        a few cells far from the data (docs/choices.md, "The written map in bands of rows").

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
        length_scale : float
            The GP's length scale, metres.
        predict_gp : callable
            Points of shape (m, d) to the GP's probability, its latent variance and its probability
            for unseen space, each (m,).
        moments : BlendedMoments, optional
            The same GP's moments: the grid then takes the GP's variance
            :data:`~gpomap.fusion.written.VARIANCE_STEP_SAMPLES` samples apart instead of
            `predict_gp` at every sample.
        """
        factor = gp_sampling_factor(length_scale, grid.resolution)
        if not isinstance(grid, GridSpec) or grid.shape[0] <= band_rows(grid, factor):
            return self._written_block(grid, factor, predict_gp, moments)
        # Cells off the counted lattice are counted afresh, a traversal of every beam: once for
        # the whole grid (16 bytes a cell), not once per band.
        whole = None if self._on_lattice(grid) else self._raw_grid_counts(grid)

        def band(
            start: int, stop: int, rows: GridSpec
        ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
            if whole is not None:
                counts, path, at_surface = whole
                self._grid_cache = (rows, RayCounts(*(c[start:stop] for c in counts)), path[start:stop], at_surface[start:stop])
            return self._written_block(rows, factor, predict_gp, moments)

        def finished() -> None:
            nonlocal whole
            self._grid_cache = None  # the last band's counts: of no use to the next grid
            self._at_surface = None  # a bool a lattice cell, found again when asked
            whole = None

        return in_bands(grid, factor, band, moments, SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False), finished)

    def _written_block(
        self,
        grid: AnyGrid,
        factor: int,
        predict_gp: GPPredict,
        moments: BlendedMoments | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """:meth:`written_grid` of a grid in one piece, its GP sampled every `factor` cells."""
        sampled, p, var, p_unseen = gp_samples(grid, factor, predict_gp, moments)
        probability = self.grid_proba(grid, interpolate(p, sampled, grid), interpolate(p_unseen, sampled, grid))
        return probability, interpolate(var, sampled, grid), self.grid_seen_through(grid)
