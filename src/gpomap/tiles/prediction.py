"""A tiled map's GP as its fitted map asks it, and the tiled map's fitted map.

The tiles' blended moments (:class:`~gpomap.tiles.blending.TileBlending`) are the GP under the
map; :class:`TiledField` gives them to :class:`~gpomap.fitted.FittedMap`, which makes every
answer: probabilities, the ternary map, grids (a large planar grid in bands of rows, the tiles
the bands have passed letting go of what they formed) and voxel maps.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.field import GPHyperparameters
from gpomap.fitted import FittedMap, MapAnswers
from gpomap.lapack import blas_limited
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
