"""The map fitted again on part of its data: what three of its calibration stages ask.

The variance scale (:mod:`gpomap.extrapolation`) asks the GP of kept stretches of the scans; the
fitted surprise rate (:func:`gpomap.fusion.fit_surprise_rate`) asks the GP without the
calibration's held-out scans; the later visit (:mod:`gpomap.revisit`) asks the whole map of the
other stretches. Each is the same map (its tiles, settings and hyperparameters) fitted on those
data: :class:`Refit` holds what they share, taken from the fitted map when a stage asks, so no
stage needs the map itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.counted_cells import CountsNear
from gpomap.fusion import EvidenceCalibration
from gpomap.observations import Observations, ScanData
from gpomap.tiles.points import KeptPoints

Predict = Callable[[NDArray[np.float64]], NDArray[np.float64]]


@dataclass(frozen=True)
class Refit:
    """A fitted map's tiles, settings and hyperparameters, to fit again on other data.

    Parameters
    ----------
    make : callable
        The map's class: ``make(**tiling, **options)`` is an unfitted map.
    tiling : dict
        Its tiling arguments as fitted (the tile side and origin the fit chose), on local workers.
    options : dict
        Its map settings (:class:`~gpomap.settings.MapSettings` options) as given.
    hyperparameters : dict
        Its hyperparameters as fitted so far, held in every refit.
    """

    make: Callable[..., Any]
    tiling: dict[str, Any]
    options: dict[str, Any]
    hyperparameters: dict[str, float]

    def unfitted(self, **changes: Any) -> Any:
        """An unfitted map with these tiles and settings, `changes` (MapSettings options) applied."""
        return self.make(**self.tiling, **{**self.options, **changes})

    def gp(self, data: ScanData | Observations, **hyperparameters: float) -> Any:
        """The map's GP alone (no ray evidence) fitted on `data`, the hyperparameters held
        (`hyperparameters` given here replacing theirs): this map's GP had it seen only `data`."""
        return self.unfitted(ray_evidence=False).fit(data, hyperparameters={**self.hyperparameters, **hyperparameters})

    def gp_proba(self, scans: ScanData) -> Predict:
        """The GP's probability (before ray evidence) of the map fitted on `scans` alone, as the
        calibrations take it (:meth:`~gpomap.tiles.prediction.MapPrediction._gp_proba_written`)."""
        return self.gp(scans)._gp_proba_written

    def map_proba(
        self,
        scans: ScanData,
        calibration: EvidenceCalibration | None,
        points: NDArray[np.float64],
        kept_points: KeptPoints | None = None,
        counted_without: tuple[CountsNear, list[Any]] | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The probability at `points` (shape (m, d); returns (m,)) of the whole map fitted on
        `scans` alone, with its own ray counts calibrated as `calibration` says and no later-visit
        recalibration of its own, and whether only its beams without a return reached each point's
        cell (:func:`gpomap.fusion.only_silent`; shape (m,)). It fits only the tiles the points
        need, and counts the rays only at their cells (the same tiles and counts, so the same
        answers as the whole map's). With `kept_points` (the fitted map's points without the scans
        left out), it files those instead of making the scans' points again: the same points in
        the same order. With
        `counted_without` (the fitted map's counts round `points` and its scans not in `scans`),
        its ray counts are those less the others' (:func:`gpomap.counted_cells.count_cells_without`)."""
        rest = self.unfitted(fit_revisit=False)
        rest._tiles_when_asked = True
        rest._given_calibration = calibration
        rest._kept_points = kept_points
        rest._counted_without = counted_without
        if calibration is not None:
            rest._asked_at = np.asarray(points, dtype=float)
        fitted = rest.fit(scans, hyperparameters=dict(self.hyperparameters))
        p = np.asarray(fitted._proba_as_written(points), dtype=float)
        layer = fitted.evidence_
        return p, np.zeros(p.shape, dtype=bool) if layer is None else layer.counts_at(points)[2]
