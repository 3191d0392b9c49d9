"""A tiled map's GP as its fitted map asks it, and the tiled map's fitted map.

The tiles' blended moments (:class:`~gpomap.tiles.blending.TileBlending`) are the GP under the
map; :class:`TiledField` gives them to :class:`~gpomap.fitted.FittedMap`, which makes every
answer: probabilities, the ternary map, grids (a large planar grid in bands of rows, the tiles
the bands have passed letting go of what they formed) and voxel maps.
"""

from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.field import GPHyperparameters, as_points
from gpomap.fitted import FittedMap, MapAnswers
from gpomap.fusion.written import variance_step
from gpomap.lapack import blas_limited
from gpomap.lattice import lattice_corners
from gpomap.squash import ProbitSquash
from gpomap.tiles.blending import TileBlending
from gpomap.tiles.report import MapReport
from gpomap.tiles.store import TileStore

if TYPE_CHECKING:
    from gpomap.fusion import EvidenceLayer


class TiledField:
    """The tiles' blended GP, as a fitted map asks it (:class:`~gpomap.field.LatentField`).

    Parameters
    ----------
    tiled : MapPrediction
        A fitted tiled map.
    """

    def __init__(self, tiled: MapPrediction) -> None:
        self._tiled = tiled

    @property
    def dim(self) -> int:
        """2 for a planar map, 3 for point clouds."""
        return self._tiled._dim

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """The hyperparameters every tile's GP shares."""
        return GPHyperparameters.from_mapping(self._tiled.hyperparameters_)

    @property
    def squash(self) -> ProbitSquash:
        """The tiles' calibrated probit (alpha, beta, the variance scale for unseen space)."""
        h = self._tiled.hyperparameters_
        return ProbitSquash(float(h["alpha"]), float(h["beta"]), float(h.get("variance_scale", 1.0)))

    @property
    def blended(self) -> MapPrediction:
        """The tiles' calibrated moments (:class:`~gpomap.fusion.BlendedMoments`)."""
        return self._tiled

    def latent(self, points: NDArray[np.float64], return_var: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Blended latent mean and variance at points, each (m,)."""
        _, mu, var, _ = self._tiled._predict_blended(points)
        return mu, var

    def gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The blended GP's probability, latent variance and probability for unseen space, each (m,)."""
        return self._tiled._gp_probabilities(points)

    def limited(self) -> contextlib.AbstractContextManager[Any]:
        """This process's BLAS held to one worker's share of the cores, as the map's fit is."""
        tiled = self._tiled
        return blas_limited(tiled._workers_and_threads(tiled.n_workers_)[1])

    def forget_below(self, y: float) -> None:
        """Drop the inverses the tiles whose blend region ends below `y` formed."""
        self._tiled.forget_below(y)

    def grid_done(self) -> None:
        """A map larger than its tile store's budget lets the store shrink: the grid's files come
        next, and its last tiles wait in the file meanwhile."""
        tiles = self._tiled.tiles_
        if isinstance(tiles, TileStore) and tiles.spilled_bytes:
            tiles.shrink()


class MapPrediction(MapAnswers, TileBlending, MapReport):
    """A tiled map's fitted map and the answers it makes (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    @property
    def map_(self) -> FittedMap:
        """The fitted map: the tiles' blended GP under the ray evidence (:class:`~gpomap.fitted.FittedMap`)."""
        return self._fitted_map(self.evidence_)

    def _gp_map(self) -> FittedMap:
        """The tiles' GP alone as a fitted map: what the fit's stages after the tile fits ask."""
        return self._fitted_map(None)

    def _fitted_map(self, evidence: EvidenceLayer | None) -> FittedMap:
        self._check_fitted()
        assert self._lower is not None and self._upper is not None  # fit sees both classes
        return FittedMap(
            TiledField(self),
            evidence,
            self.base.thresholds,
            self._lower,
            self._upper,
            self.path_,
            self.summary,
            self.timings_,
        )

    def _gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The blended GP's probability, latent variance and probability for unseen space, each (m,)."""
        p, _, var, p_unseen = self._predict_blended(points)
        return p, var, p_unseen

    def _gp_proba_as_written(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The blended GP's probability and probability for unseen space at points, each (m,), with
        the variance a written map takes: the mean at each point, the variance at the corners of
        its cell of a lattice :func:`~gpomap.fusion.variance_step` apart (for a map written on
        the ray counts' cells, its default), interpolated.

        What the calibrations fit is then the GP of the map a user gets, and its variance, the
        costly part of a prediction, is asked at a few corners instead of at every point. Points
        too sparse to share corners would ask more corners than points: there the GP is asked at
        the points (:meth:`_variance_corners`).
        """
        pts = as_points(points, self._dim)
        # Timed and held to a worker's BLAS threads as the fitted map's own predictions are.
        t = time.perf_counter()
        with TiledField(self).limited():
            lattice = self._variance_corners(pts)
            if lattice is None:
                p, _, p_unseen = self._gp_probabilities(pts)
            else:
                nodes, corner, weight = lattice
                num, _, _, _ = self.blended_moments(pts, variance=False)
                _, den_nodes, _, _ = self.blended_moments(nodes)
                assert den_nodes is not None  # asked with the variance
                p, p_unseen = self.squash_moments(num, np.einsum("ij,ij->i", weight, den_nodes[corner]))
        self.timings_["prediction"] = time.perf_counter() - t
        return p, p_unseen

    def _variance_corners(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.float64]] | None:
        """Where :meth:`_gp_proba_as_written` asks the variance for `points` (m, d): the corners
        (k, d), each point's (m, 2^d) and their weights (m, 2^d)
        (:func:`~gpomap.lattice.lattice_corners`); None where it asks at the points, too sparse
        for their cells to share corners (k >= m: a building's later visit), where the corners
        would cost more."""
        step = variance_step(float(self.hyperparameters_["length_scale"]), self.base.counted_resolution(self._dim))
        corners = lattice_corners(points, step)
        return corners if corners[0].shape[0] < points.shape[0] else None

    def _gp_queries(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Every point :meth:`_gp_proba_as_written` asks the GP at for `points` (m, d): them,
        and the corners that give them its variance."""
        corners = self._variance_corners(points)
        return points if corners is None else np.concatenate([points, corners[0]])

    def _gp_proba_written(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """The GP's probability at points, shape (m,), as :meth:`_gp_proba_as_written` takes it:
        what the ray counts' calibration fits against."""
        return self._gp_proba_as_written(points)[0]

    def _proba_as_written(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """The map's probability at points, shape (m,): the ray counts over the GP as
        :meth:`_gp_proba_as_written` takes it (what the later visit's recalibration fits)."""
        pts = as_points(points, self._dim)
        p, p_unseen = self._gp_proba_as_written(pts)
        return p if self.evidence_ is None else self.evidence_.proba(pts, p, p_unseen)
