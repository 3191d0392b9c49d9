"""A tiled map's answers: latent moments, probabilities, the ternary map, grids and voxel maps.

A probability is the ray evidence's over the tiles' blended GP (or the GP's alone); a large planar
grid is predicted in bands of rows, the tiles the bands have passed letting go of what they formed.
"""

from __future__ import annotations

import time
from typing import Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap.grid import GridSpec, OccupancyMap, row_bands, ternary
from gpomap.lattice import data_extent
from gpomap.resources import WRITTEN_BAND_CELLS
from gpomap.tiles.blending import TileBlending
from gpomap.tiles.executors import _blas_shared
from gpomap.tiles.report import MapReport
from gpomap.tiles.store import TileStore


class MapPrediction(TileBlending, MapReport):
    """Predictions and grids of a fitted map (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    @overload
    def predict(self, /, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict(
        self, /, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict(
        self, /, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @_blas_shared
    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Blended latent mean (and variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        self._check_fitted()
        _, mu, var, _ = self._predict_blended(points)
        return (mu, var) if return_var else mu

    @overload
    def predict_proba(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability at points, blended across tiles.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool
            Also return the blended latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        p, var, p_unseen = self._timed_prediction(points)
        if self.evidence_ is not None:
            p = self.evidence_.proba(np.asarray(points, dtype=float).reshape(-1, self._dim), p, p_unseen)
        return (p, var) if return_var else p

    @overload
    def predict_proba_gp(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The tiles' blended GP probability at points, before any ray evidence.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        p, var, _ = self._timed_prediction(points)
        return (p, var) if return_var else p

    @_blas_shared
    def _timed_prediction(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`_gp_probabilities` at points, its time kept as the ``prediction`` stage."""
        self._check_fitted()
        t = time.perf_counter()
        out = self._gp_probabilities(points)
        self.timings_["prediction"] = time.perf_counter() - t
        return out

    def predict_ternary(self, points: NDArray[np.float64]) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, ndarray of shape (m,); never occupied
        in a cell beams saw through (:meth:`gpomap.fusion.EvidenceLayer.seen_through_at`)."""
        seen = self.evidence_.seen_through_at(points) if self.evidence_ is not None else None
        return ternary(self.predict_proba(points), self.thresholds_, seen)

    @_blas_shared
    def grid(self, resolution: float, extent: tuple[float, ...] | None = None) -> Any:
        """The map sampled at grid-cell centres; each tile predicts only the grid cells it covers.

        Parameters
        ----------
        resolution : float
            Grid cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
            Defaults to the bounding box of the observations grown by two cells
            (:func:`gpomap.lattice.data_extent`); (..., zmin, zmax) in 3-D.

        Returns
        -------
        OccupancyMap, or VoxelMap for a 3-D map
        """
        self._check_fitted()
        aligned = extent is None  # the default grid's cells are the ray counts' (no recount)
        if extent is None:
            assert self._lower is not None and self._upper is not None
            extent = data_extent(self._lower, self._upper, resolution)
        if self._dim == 3:
            return self._voxels(resolution, extent)
        spec = GridSpec.from_extent((extent[0], extent[1], extent[2], extent[3]), resolution, align=aligned)
        t = time.perf_counter()
        probability, variance, seen_through = self._sample(spec)
        self.timings_["grid"] = time.perf_counter() - t
        if isinstance(self.tiles_, TileStore) and self.tiles_.spilled_bytes:
            # A map larger than the store's budget: the grid's files come next, its last tiles wait in the file meanwhile.
            self.tiles_.shrink()
        return OccupancyMap(
            grid=spec,
            probability=probability,
            variance=variance,
            thresholds=self.thresholds_,
            path=self.path_,
            info=self.summary(),
            seen_through=seen_through,
        )

    def _gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The blended GP's probability, latent variance and probability for unseen space, each (m,)."""
        p, _, var, p_unseen = self._predict_blended(points)
        return p, var, p_unseen

    def _sample(self, spec: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """Probability and latent variance per cell of a GridSpec or VoxelSpec, and the cells beams
        saw through (:meth:`gpomap.fusion.EvidenceLayer.written_grid`; None without ray counts)."""
        if self.evidence_ is not None:
            return self.evidence_.written_grid(spec, self.hyperparameters_["length_scale"], self._gp_probabilities, self)
        ny, nx = spec.shape[-2:]
        rows = max(1, WRITTEN_BAND_CELLS // nx)
        if not isinstance(spec, GridSpec) or ny <= rows:
            p, _, var, _ = self._predict_blended(spec.centres())
            return p.reshape(spec.shape), var.reshape(spec.shape), None
        # The GP alone, in bands of rows as the written map with counts is (the same values).
        probability, variance = np.empty(spec.shape), np.empty(spec.shape)
        for start, stop, band in row_bands(spec, rows):
            p, _, var, _ = self._predict_blended(band.centres())
            probability[start:stop], variance[start:stop] = p.reshape(-1, nx), var.reshape(-1, nx)
            self.forget_below(spec.origin[1] + stop * spec.resolution)
        self.forget_below(np.inf)
        return probability, variance, None

    def _voxels(self, resolution: float, extent: tuple[float, ...]) -> Any:
        from gpomap.lattice import extent_bounds
        from gpomap.voxels import VoxelMap, VoxelSpec

        lo, hi = extent_bounds(extent)
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        t = time.perf_counter()
        probability, variance, _ = self._sample(spec)
        self.timings_["grid"] = time.perf_counter() - t
        observed = self.evidence_.grid_observed(spec) if self.evidence_ is not None else None
        return VoxelMap(spec, probability, variance, thresholds=self.thresholds_, info=self.summary(), observed=observed)
