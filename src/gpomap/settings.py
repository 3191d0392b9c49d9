"""The settings of an MSK-GPOM map and the pieces they build, shared by every path of the engine.

:class:`MapSettings` turns scans into labelled points (:meth:`~MapSettings.make_observations`),
points into cells (:meth:`~MapSettings.make_cells`), settings into an area kernel
(:meth:`~MapSettings.make_kernel`) and scans into the ray-evidence layer
(:meth:`~MapSettings.make_evidence`). The engine (:class:`~gpomap.tiles.TiledGPOM`, whose
scikit-learn style face is :class:`~gpomap.mapping.AreaGPOM`) and grid conversion
(:class:`~gpomap.convert.GridGPOM`) read their settings from here, so each is stated once.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.cells import Cells, build_cells
from gpomap.config import PROFILES, MapConfig
from gpomap.counted_cells import CountsNear
from gpomap.fusion import EvidenceCalibration, EvidenceLayer, GPApart
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.point import make_point_kernel
from gpomap.observations import Observations, ScanData, data_dim, labelled_observations


@dataclass(frozen=True, repr=False)
class MapSettings(MapConfig):
    """The settings of one MSK-GPOM map, and what they build: observations, cells, kernel, ray evidence.

    Not an estimator: :class:`~gpomap.mapping.AreaGPOM` holds one and fits with it. Its fields are
    :class:`~gpomap.config.MapConfig`'s, defaults included (written there once); why each was
    chosen is said below. Frozen, as the config is: settings changed are a new object
    (:meth:`~gpomap.config.MapConfig.replace`).

    Parameters
    ----------
    kernel : {"matern32", "se"}
        Point kernel under the area kernel.
    area : {"exact", "quadrature", "summed"}, optional
        How cell averages are computed; default "exact" for "se", "quadrature" for "matern32".
    normalisation : {"mean", "sum"}
        Average the kernel over cells ("mean") or sum it over member points ("sum", the paper).
    free_step : float
        Spacing of free points along beams, metres.
    hit_margin : float, optional
        Free points stop this short of a hit (default half of `free_step`).
    no_return_cap : float or None
        Free points along a no-return beam go this far (never beyond the max range; None: to the
        max range). 10 m by default: laser logs record no-return at their far code (tens of
        metres), and trusting free space that far fills a huge square around a building for no
        gain in held-out AUC (docs/choices.md, "Measured for the code").
    free_clearance : float or None
        Free points closer than this (metres) to any hit are dropped, so beams grazing a wall do
        not mark the wall free (see :func:`gpomap.observations.free_near_hits`); applies to scans,
        not to labelled points given to ``fit``. None takes the data's profile
        (:data:`gpomap.config.PROFILES`, :meth:`clearance`): 0.1 m in a plane, where the ray
        counts draw the walls and a wider clearance leaves the GP a band round each wall with
        hits alone (docs/choices.md, "Free clearance: 0.1 m in a plane"); 0.3 m in 3-D.
    min_cell, max_cell : float or None
        Cell-tree size thresholds (see :func:`gpomap.cells.build_cells`); None takes the data
        dimension's profile (:meth:`cell_sides`, :data:`gpomap.config.PROFILES`): 0.5 m for planar
        data, 1 m for point clouds. ``max_cell`` is 0.5 m on planar data: with mean normalisation a cell much larger than the length scale has a small
        prior variance and says little about the points inside it, and real logs learn length
        scales shorter than 1 m: 0.5 m was better on every real log for about twice the cells,
        while the synthetic room, whose length scale is longer, prefers 1 m (docs/choices.md,
        "Measured on more logs").
    cell_box : {"node", "tight"}
        Each cell's box: the tree node ("node") or its points' bounding box ("tight").
    variance, length_scale, noise : float
        Starting hyperparameters (kept as they are with ``optimise=False``).
    length_scale_bounds, noise_bounds : (float, float)
        Bounds of the hyperparameter search.
    noise_model : {"constant", "per_count"}
        Noise per cell: one level for all, or divided by the cell's member count (default: a cell
        averaging m points is m times surer than one; docs/choices.md, "The answers").
    objective : {"loo", "lml"}
        Hyperparameter objective: leave-one-out probit predictive probability (default; the
        marginal likelihood collapses on real cells, see the docs) or log marginal likelihood.
    optimise : bool
        Learn the hyperparameters; False keeps them (alpha and beta are still fitted).
    n_restarts : int
        Extra seeded starts of the hyperparameter search.
    hyper_subset : int or None
        Learn hyperparameters on a compact block of at most this many cells (None: all).
    prior_std : float or None
        Width (log space) of the weak prior keeping length scale and noise near their starting
        values where the objective is flat; None: no prior.
    class_weight : {"balanced", None}
        Weighting of free and occupied cells in the leave-one-out objective and the squash fit.
        "balanced" (default) weighs both classes equally: free cells outnumber occupied ones
        several times over, and unweighted the search can settle on maps that call everything
        free (docs/choices.md, "Class weights").
    seed : int
        Seed of those starts.
    quadrature_order : int
        Gauss-Legendre nodes per cell side for ``area="quadrature"``. 2 is as accurate as 3 at a
        fraction of the cost (docs/choices.md, "Results").
    thresholds : (float, float) or None
        Free-below and occupied-above probabilities of the ternary map. None (the default): a
        calibrated map's, free below 0.196 and occupied above 0.5 (with ray evidence,
        :data:`gpomap.grid.CALIBRATED_THRESHOLDS`), else the paper's 0.33 and 0.66.
    chunk_size : int
        Query points per prediction chunk.
    ray_evidence : bool
        Update the GP's probability with each fine cell's ray counts (see :mod:`gpomap.fusion`):
        scans that ended a beam in the cell and scans that crossed it, weighed by a calibration
        fitted on the map's own scans, one held out at a time. Only for scans (labelled points
        carry no rays). True by default: where the robot has data the map is then as sharp as an
        occupancy grid and its probabilities are calibrated, and elsewhere it is the GP's.
    evidence_resolution : float
        Side of the fine cells of exact-point predictions, metres (a written grid counts on its
        own cells).
    evidence_resolution_3d : float
        The same for 3-D maps (voxels). 0.1 m, OctoMap's usual resolution: a 3-D lidar's rays are
        sparse, and at 5 cm few voxels would be crossed by more than one scan (docs/3d.md, "At
        0.05 m voxels").
    calibration_scans : int
        Scans held out in turn to fit the evidence calibration.
    fit_surprise_rate : bool
        Fit the surprise rate (the share of observations the counts cannot foresee: a visitor where
        every scan saw free space) on the map's own scans instead of taking the prior one in a
        hundred, which stays its floor (planar scans, :func:`gpomap.fusion.fit_calibration`). It
        refits the GP without the calibration's held-out scans, so a fit costs more time and
        memory. Off by default: it changes little where nothing moves and pays on logs with
        crowds (docs/choices.md, "The surprise rate, fitted per map").
    fit_revisit : bool
        Recalibrate the map's probabilities for a later visit (:mod:`gpomap.revisit`): the same map
        fitted on seven tenths of the scans predicts the other three (a stretch of the log), and
        a monotone map of the probabilities that keeps 1/2 is fitted on those points and the
        calibration's own, half each. Planar maps of 100 scans or more; on by default (it costs a
        second fit of the tiles and the ray counts on seven tenths of the scans; docs/choices.md,
        "The map's probabilities for a later visit").
    """

    def __repr__(self) -> str:
        return f"kernel={self.kernel!r}, area={self.area_method!r}, min_cell={self.min_cell}, max_cell={self.max_cell}"

    def get_params(self) -> dict[str, Any]:
        """The settings, by name (the fields of :class:`~gpomap.config.MapConfig`)."""
        return {name: getattr(self, name) for name in MapConfig.__dataclass_fields__}

    @property
    def area_method(self) -> str:
        """The area-kernel method in use (the default depends on the kernel)."""
        if self.area is not None:
            return self.area
        return "exact" if make_point_kernel(self.kernel).name == "se" else "quadrature"

    def make_kernel(self) -> AreaKernel:
        """The area kernel these settings describe, at the starting hyperparameters."""
        base = make_point_kernel(
            self.kernel, variance=self.variance, length_scale=self.length_scale, length_scale_bounds=self.length_scale_bounds
        )
        return AreaKernel(base, self.area_method, self.normalisation, self.quadrature_order)

    def make_observations(self, data: ScanData | Observations, clearance: bool = True) -> Observations:
        """Labelled points from scans, or `data` itself when it already is (taken as it is).

        Parameters
        ----------
        data : sequence of Scan or CloudScan, or Observations
        clearance : bool
            Drop free points within ``free_clearance`` of a hit (the engine applies it per block
            instead, so that hits arriving later clear them too).

        Raises
        ------
        EmptyDataError
            When either class is missing.
        """
        if isinstance(data, Observations) or not len(data):
            return labelled_observations(data, self.free_step, self.hit_margin, self.no_return_cap)
        dim = data_dim(data)
        cut = self.clearance(dim) if clearance else 0.0
        return labelled_observations(data, self.free_step, self.hit_margin, self.no_return_cap, cut, self.free_cube(dim))

    def clearance(self, dim: int) -> float:
        """``free_clearance`` for data of dimension `dim`: the one given, or the dimension's
        profile's (:data:`gpomap.config.PROFILES`)."""
        return PROFILES[dim].free_clearance if self.free_clearance is None else float(self.free_clearance)

    def free_cube(self, dim: int) -> float | None:
        """Side of the cubes a scan's free samples are merged by for data of dimension `dim`: half
        the free step where the dimension's profile merges them (:data:`gpomap.config.PROFILES`),
        else None (every sample kept)."""
        return 0.5 * float(self.free_step) if PROFILES[dim].merge_free else None

    def cell_sides(self, dim: int) -> tuple[float, float]:
        """``(min_cell, max_cell)`` for data of dimension `dim`: those given, the rest from the
        dimension's profile (:data:`gpomap.config.PROFILES`); one given alone beyond the profile's
        other bound moves it along, so that the pair stays ordered."""
        profile = PROFILES[dim]
        if self.min_cell is not None and self.max_cell is not None:
            return float(self.min_cell), float(self.max_cell)
        if self.min_cell is not None:
            return float(self.min_cell), max(profile.max_cell, float(self.min_cell))
        if self.max_cell is not None:
            return min(profile.min_cell, float(self.max_cell)), float(self.max_cell)
        return profile.min_cell, profile.max_cell

    def make_cells(self, obs: Observations) -> Cells:
        """The GP's inputs: the cell tree over `obs` with these settings."""
        return build_cells(obs.points, obs.occupied, *self.cell_sides(obs.points.shape[1]), self.cell_box, obs.weight)

    def counted_resolution(self, dim: int) -> float:
        """Side of the ray counts' fine cells of a `dim`-D map, metres: the written map's default cell."""
        return self.evidence_resolution_3d if dim == 3 else self.evidence_resolution

    def make_evidence(
        self,
        data: ScanData | Observations,
        predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        gp_apart: GPApart | None = None,
        calibration: EvidenceCalibration | None = None,
        asked_at: NDArray[np.float64] | None = None,
        counted_without: tuple[CountsNear, ScanData] | None = None,
    ) -> EvidenceLayer | None:
        """The ray-evidence layer for `data` on top of a fitted GP (None without scans or when off),
        with `gp_apart` the GP its surprise rate is fitted against with ``fit_surprise_rate``
        (:func:`gpomap.fusion.fit_calibration`), or `calibration` taken as it is, its counts taken
        only at the points `asked_at` when given, from another layer's less some scans' with
        `counted_without` (:class:`~gpomap.fusion.EvidenceLayer`)."""
        if not self.ray_evidence or isinstance(data, Observations):
            return None
        resolution = self.counted_resolution(data_dim(data))
        apart = gp_apart if self.fit_surprise_rate else None
        return EvidenceLayer(
            data,
            resolution,
            predict_gp,
            self.no_return_cap,
            self.calibration_scans,
            self.seed,
            apart,
            calibration,
            asked_at,
            counted_without,
        )
