"""The calibration stages of a tiled map's fit, each of which fits further maps of it.

Three of the fit's stages are fitted on what this map would say without some of its data: the
squash's variance scale (on a GP of kept stretches of the scans, :mod:`gpomap.extrapolation`),
the ray counts' calibration (its surprise rate against the GP without the held-out scans,
:mod:`gpomap.fusion`), and the later visit's recalibration (on the whole map of the other
stretches, :mod:`gpomap.revisit`). Each asks the map's :class:`~gpomap.tiles.refit.Refit`, which
:class:`~gpomap.tiles.TiledGPOM` makes (it names the class fitted again); :class:`CalibrationStages`
runs them in the order :meth:`TiledGPOM.fit <gpomap.tiles.TiledGPOM.fit>` asks.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.fusion import EvidenceLayer
from gpomap.observations import Observations, ScanData, ScanPoints
from gpomap.tiles.points import FiledPoints, KeptPoints
from gpomap.tiles.prediction import MapPrediction
from gpomap.tiles.refit import Refit


class CalibrationStages(MapPrediction):
    """The fit's stages that fit further maps of this one (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    if TYPE_CHECKING:
        # TiledGPOM's own: the map's tiling, settings and hyperparameters, to fit again (declared
        # for the type checker only).
        def _refit(self) -> Refit: ...

    def _fit_variance_scale(self, data: ScanData | Observations, obs: Observations | ScanPoints) -> dict[str, Any]:
        """The squash's variance scale from held-out stretches of the scans, and its report.

        See :mod:`gpomap.extrapolation`. The held-in GP covers the whole map when it is within a
        block of its centre; a larger map, the square of two blocks' side round the hyperparameter
        sample's centre (the median point when hyperparameters were given), or where that holds
        too few unseen points, of four (or the whole map, if smaller), so its cost is bounded
        whatever the map's size.
        """
        if isinstance(data, Observations):
            return {"kappa": 1.0, "reason": "labelled points given, not scans"}
        from gpomap.extrapolation import FIT_VARIANCE_SCALE, fit_variance_scale, whole_map_region

        if not FIT_VARIANCE_SCALE[self._dim]:
            return {"kappa": 1.0, "reason": "voxel maps do not fit it"}

        centre, half = whole_map_region(obs if isinstance(obs, ScanPoints) else obs.points)
        margin = 0.0
        wider: tuple[NDArray[np.float64], float, float] | None = None
        if half > self.block_size_:
            # Larger than the region: round the hyperparameter sample, off the region's edge; a
            # region twice as wide (or the whole map) where that holds too few unseen points.
            whole = (centre, half, 0.0)
            source = getattr(self, "hyper_source_", {})
            centre = np.asarray(source["sample_centre"]) if "sample_centre" in source else self._median_point(obs)
            half, margin = self.block_size_, min(self.overlap_, 0.5 * self.block_size_)
            wider = whole if whole[1] <= 2.0 * half else (centre, 2.0 * half, margin)
        refit = self._refit()

        def fit_held_in(held: Observations) -> Any:
            return refit.gp(held, variance_scale=1.0)

        _, report = fit_variance_scale(
            data,
            self.hyperparameters_,
            self._filed_points(obs),  # the map's own points: the kept scans are not observed again
            self._clearance,
            fit_held_in,
            centre=centre,
            region_half=half,
            margin=margin,
            no_return_cap=self.base.no_return_cap,
            seed=self.base.seed,
            wider=wider,
        )
        return report

    def _filed_points(self, obs: Observations | ScanPoints) -> Observations | ScanPoints | FiledPoints:
        """The map's points as its blocks hold them (:class:`~gpomap.tiles.points.FiledPoints`),
        when made from scans and every block knows its points' scans; else `obs`."""
        if not isinstance(obs, ScanPoints) or not self._blocks_know_their_scans():
            return obs
        side = self.block_size_

        def meeting(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> list[int]:
            squares = self._meeting((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), side)
            return [self._encode(ix, iy) for ix, iy in squares]

        return FiledPoints(self._block_points, meeting, obs.lower, obs.upper)

    @staticmethod
    def _median_point(obs: Observations | ScanPoints) -> NDArray[np.float64]:
        """The median x, y of every point (made again, a part at a time, from scans)."""
        if isinstance(obs, ScanPoints):
            return np.median(np.concatenate([p.points[:, :2] for p in obs.parts()]), axis=0)
        return np.median(obs.points[:, :2], axis=0)

    def _make_evidence(self) -> EvidenceLayer | None:
        """Ray counts over every scan so far, calibrated against the tiles' GP (see gpomap.fusion)."""
        if self._scans is None:
            return None
        return self.base.make_evidence(
            self._scans,
            self._gp_proba_written,
            self._gp_apart,
            self._given_calibration,
            self._asked_at,
            self._counted_without,
        )

    def _later_visit_points(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_] | None, dict[str, Any]] | None:
        """This map's probabilities, fitted without them, at a held-out stretch's points
        (:func:`gpomap.revisit.later_visit_points`), their classes, and whether only that map's
        beams without a return reached their cells (None when it was not fitted); None when the
        map does not recalibrate."""
        if self._scans is None or not self.base.ray_evidence or not self.base.fit_revisit:
            return None
        from gpomap.revisit import later_visit_points

        refit, layer = self._refit(), self.evidence_
        silent: list[NDArray[np.bool_]] = []

        def fit_rest(scans: list[Any], points: NDArray[np.float64]) -> NDArray[np.float64]:
            # This map's counts round the points, taken before its lattice is set aside: the map
            # of the other stretches counts only the held-out stretches' beams, and takes them out.
            split = self._left_out_of(scans)
            near = None if layer is None or split is None else layer.counts_near(points)
            assert self._scans is not None
            without = None if near is None or split is None else (near, [self._scans[i] for i in split[1]])
            with layer.set_aside() if layer is not None else nullcontext():
                # The silent rate is fitted on these points: the map of the others is without one.
                calibration = None if layer is None else replace(layer.calibration, silent_rate=0.0, silent_mix=0.0)
                p, reached = refit.map_proba(scans, calibration, points, self._kept_points_of(scans), without)
            silent.append(reached)
            return p

        p, occupied, report = later_visit_points(self._scans, fit_rest, self.base.no_return_cap, self.base.seed)
        return p, occupied, silent[0] if silent else None, report

    def _left_out_of(self, scans: list[Any]) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
        """The kept and the held-out stretches' scans (indices in this map's), when `scans` are the
        kept ones (:func:`gpomap.heldout.holdout_stretches`); else None."""
        from gpomap.heldout import holdout_stretches

        if self._scans is None:
            return None
        kept, held = holdout_stretches(len(self._scans))
        if len(scans) != kept.size or any(s is not self._scans[i] for s, i in zip(scans, kept.tolist(), strict=True)):
            return None
        return kept, held

    def _blocks_know_their_scans(self) -> bool:
        """Whether every block's points came with their scans' runs."""
        return all(b.knows_its_scans() for b in self._block_points.values())

    def _kept_points_of(self, scans: list[Any]) -> KeptPoints | None:
        """This map's points without those of the scans not in `scans` (:class:`~gpomap.tiles.points.KeptPoints`),
        when `scans` are this map's held-out stretches' others (:meth:`_left_out_of`) and every
        block knows its points' scans; else None."""
        split = self._left_out_of(scans)
        if split is None or not self._blocks_know_their_scans():
            return None
        kept, held = split
        return KeptPoints(self._block_points, held, kept, self._dim, self._clearance)

    def _fit_revisit(
        self, later: tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_] | None, dict[str, Any]] | None
    ) -> dict[str, Any]:
        """Fit the ray evidence's silent rate and recalibration for a later visit
        (:meth:`~gpomap.fusion.EvidenceLayer.fit_revisit`) on the `later` points
        (:meth:`_later_visit_points`) and the calibration's own; its report."""
        if later is None or self.evidence_ is None:
            return {"reason": "off" if not self.base.fit_revisit else "no ray evidence"}
        p_later, occupied, silent, report = later
        if "reason" in report:
            return report
        revisit = self.evidence_.fit_revisit(p_later, occupied, silent)
        return {"slope": revisit.slope, "shift": revisit.shift, **report}

    def _gp_apart(self, scans: ScanData) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """This map's GP fitted on `scans` alone, its hyperparameters held: its
        :meth:`predict_proba_gp`, which the ray-count calibration fits the surprise rate against
        (:func:`gpomap.fusion.fit_calibration`; the evidence layer keeps it for later updates, and
        a map file saves it as this method)."""
        return self._refit().gp_proba(scans)
