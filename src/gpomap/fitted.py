"""The fitted map: the one object that answers for a GP occupancy map once it is fitted.

A fit ends in two things: the GP under the map (a :class:`~gpomap.field.LatentField`: a tiled
map's tiles blended without seams, or one dense GP; the protocol and its typed values are
:mod:`gpomap.field`'s) and, for maps built from scans, the ray evidence on top
(:class:`~gpomap.fusion.EvidenceLayer`, with its fitted calibration and later-visit
recalibration). :class:`FittedMap` holds both, with the fitted parameters of each stage as typed
values and their order (:attr:`FittedMap.stages`, :mod:`gpomap.stages`), and is the only code
that turns them into answers: probabilities and latent moments at points, the ternary map,
planar grids and voxel maps. Every estimator's ``predict_proba``,
``grid`` and the rest are this object's (``model.map_``), so a map fitted, streamed, converted
or loaded from its file answers through the same lines.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap.field import GPHyperparameters, LatentField, Moments, VoxelPass, as_points
from gpomap.grid import GridSpec, OccupancyMap, row_bands, ternary
from gpomap.lattice import data_extent, extent_bounds
from gpomap.resources import WRITTEN_BAND_CELLS
from gpomap.squash import ProbitSquash

if TYPE_CHECKING:
    from gpomap.fusion import EvidenceCalibration, EvidenceLayer
    from gpomap.revisit import RevisitCalibration
    from gpomap.stages import StageChain
    from gpomap.voxels import VoxelMap, VoxelSpec

# The field's protocol and typed values (gpomap.field) are named from here too, where they were first.
__all__ = ["FittedMap", "GPHyperparameters", "LatentField", "LaterGrid", "MapAnswers", "VoxelPass", "as_points"]


@dataclass(frozen=True)
class LaterGrid:
    """A written grid predicted already and put together when called (:meth:`FittedMap.grid_later`).

    Attributes
    ----------
    grid : GridSpec
        Its cells.
    make : callable
        Puts it together (once).
    """

    grid: GridSpec
    make: Callable[[], OccupancyMap]

    def __call__(self) -> OccupancyMap:
        """The OccupancyMap."""
        return self.make()


class FittedMap:
    """A fitted GP occupancy map: its GP, its ray evidence, and every answer made of them.

    Parameters
    ----------
    field : LatentField
        The GP under the map.
    evidence : EvidenceLayer or None
        The ray counts and their fitted calibration; None for a map of the GP alone.
    thresholds : (float, float) or None
        The ternary map's (free below, occupied above) probabilities given to the estimator; None
        for the map's own (:func:`gpomap.fusion.ternary_thresholds`).
    lower, upper : ndarray of shape (d,)
        Corners of the box of the data; a grid's default extent is this box grown by two cells
        (:func:`gpomap.lattice.data_extent`).
    path : ndarray of shape (k, 2) or None
        The sensor's positions, kept with every grid written.
    summary : callable
        What was fitted, as a dict (the estimator's ``summary``), kept with every grid written.
    timings : dict
        The estimator's stage timings; predictions add ``prediction`` and grids ``grid``.
    """

    def __init__(
        self,
        field: LatentField,
        evidence: EvidenceLayer | None,
        thresholds: tuple[float, float] | None,
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
        path: NDArray[np.float64] | None,
        summary: Callable[[], dict[str, Any]],
        timings: dict[str, float],
    ) -> None:
        self.field = field
        self.evidence = evidence
        self._given_thresholds = thresholds
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.path = path
        self._summary = summary
        self.timings = timings

    @property
    def dim(self) -> int:
        """2 for a planar map, 3 for a voxel map."""
        return self.field.dim

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """The GP's hyperparameters."""
        return self.field.hyperparameters

    @property
    def squash(self) -> ProbitSquash:
        """The GP's calibrated probit: alpha, beta and the variance scale for unseen space."""
        return self.field.squash

    @property
    def calibration(self) -> EvidenceCalibration | None:
        """The ray counts' fitted weights and surprise rate; None without ray evidence."""
        return None if self.evidence is None else self.evidence.calibration

    @property
    def revisit(self) -> RevisitCalibration | None:
        """The later visit's recalibration; None without ray evidence."""
        return None if self.evidence is None else self.evidence.revisit

    @property
    def stages(self) -> StageChain:
        """The map's fitted stages in order (:mod:`gpomap.stages`): the squash with its variance
        scale, then, with ray evidence, the ray-count fusion and the later visit's recalibration.
        Applied to the GP's calibrated moments and the cells' weighted counts
        (:meth:`~gpomap.stages.StageChain.apply`), they give :meth:`predict_proba`."""
        from gpomap.extrapolation import VarianceScale
        from gpomap.stages import StageChain

        return StageChain(VarianceScale(self.squash.variance_scale), self.calibration, self.revisit)

    @property
    def thresholds(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities."""
        from gpomap.fusion import ternary_thresholds

        return ternary_thresholds(self._given_thresholds, self.evidence)

    @contextlib.contextmanager
    def _timed(self, stage: str) -> Iterator[None]:
        t = time.perf_counter()
        with self.field.limited():
            yield
        self.timings[stage] = time.perf_counter() - t

    @overload
    def predict(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The GP's latent mean (and variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, d)
            d the map's dimension (:attr:`dim`).
        return_var : bool

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = as_points(points, self.dim)
        with self._timed("prediction"):
            mean, var = self.field.latent(pts, return_var)
        if not return_var:
            return mean
        assert var is not None  # the field gives it when asked
        return mean, var

    def _gp(self, points: NDArray[np.float64]) -> Moments:
        with self._timed("prediction"):
            return self.field.gp_probabilities(points)

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
        """Occupancy probability at points: the GP's, updated by the ray counts where there are any.

        Parameters
        ----------
        points : ndarray of shape (m, d)
            d the map's dimension (:attr:`dim`).
        return_var : bool
            Also return the GP's latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = as_points(points, self.dim)
        p, var, p_unseen = self._gp(pts)
        if self.evidence is not None:
            p = self.evidence.proba(pts, p, p_unseen)
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
        """The GP's own probability at points, before any ray evidence.

        Parameters
        ----------
        points : ndarray of shape (m, d)
        return_var : bool

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        p, var, _ = self._gp(as_points(points, self.dim))
        return (p, var) if return_var else p

    def predict_ternary(self, points: NDArray[np.float64], probability: NDArray[np.float64] | None = None) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, ndarray of shape (m,); never occupied
        in a cell beams saw through (:meth:`gpomap.fusion.EvidenceLayer.seen_through_at`), or, in
        3-D, in a voxel no ray went to (as :attr:`gpomap.voxels.VoxelMap.ternary`). `probability`,
        shape (m,): :meth:`predict_proba`'s at the same points when the caller has it already."""
        pts = as_points(points, self.dim)
        hidden = None
        if self.evidence is not None:
            hidden = self.evidence.seen_through_at(pts)
            if hidden is None:
                hidden = ~self.evidence.observed_at(pts)
        return ternary(self.predict_proba(pts) if probability is None else probability, self.thresholds, hidden)

    def default_extent(self, resolution: float) -> tuple[float, ...]:
        """The box of the data grown by two cells of `resolution`, on multiples of it:
        (xmin, xmax, ymin, ymax), and (..., zmin, zmax) in 3-D."""
        return data_extent(self.lower, self.upper, resolution)

    def grid(self, resolution: float, extent: tuple[float, ...] | None = None, supersample: int = 1) -> Any:
        """The map sampled on a regular grid: an OccupancyMap in 2-D, a VoxelMap (:meth:`voxels`) in 3-D.

        Parameters
        ----------
        resolution : float
            Grid cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
            Defaults to :meth:`default_extent`, whose cells are the ray counts' own.
        supersample : int
            Samples per cell side, for a map of the GP alone. 1 samples each cell's centre. K > 1
            samples K x K points spread over the cell and keeps the largest probability (a cell
            is as occupied as its most occupied part, as an occupancy grid marks a cell a wall
            crosses anywhere) and the mean variance; it costs K^2 as many predictions. A map
            with ray evidence takes each cell's counts instead.

        Returns
        -------
        OccupancyMap, or VoxelMap for a 3-D map
        """
        if self.dim == 3:
            if supersample != 1:
                raise ValueError("supersample is for 2-D maps; a voxel map samples each voxel's centre")
            return self.voxels(resolution, extent)
        if supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {supersample}")
        if self.evidence is not None:
            return self.grid_later(resolution, extent)()
        spec = self._planar_spec(resolution, extent)
        with self._timed("grid"):
            if supersample == 1:
                probability, variance = self._gp_grid(spec)
            else:
                probability, variance = self._supersampled(spec, int(supersample))
        self.field.grid_done()
        return OccupancyMap(spec, probability, variance, self.thresholds, self.path, self._summary())

    def grid_later(self, resolution: float, extent: tuple[float, ...] | None = None) -> LaterGrid:
        """:meth:`grid` of a planar map with ray evidence, predicted now and put together when
        the function returned is called: a grid made in bands waits in a temporary file until
        then, so the map (and its model) can be let go first. The function holds no reference to
        the map; call it once.

        Parameters
        ----------
        resolution : float
        extent : (xmin, xmax, ymin, ymax), optional
            As :meth:`grid`'s.

        Returns
        -------
        LaterGrid
            Called, the OccupancyMap :meth:`grid` gives.
        """
        from gpomap.fusion.written import read_grid

        if self.dim != 2:
            raise ValueError("grid_later is for planar maps; a voxel map is voxels(resolution)")
        if self.evidence is None:
            made = self.grid(resolution, extent)
            return LaterGrid(made.grid, lambda: made)
        spec = self._planar_spec(resolution, extent)
        with self._timed("grid"):
            bands = self._written(spec)
        self.field.grid_done()
        thresholds, path, info = self.thresholds, self.path, self._summary()

        def put_together() -> OccupancyMap:
            probability, variance, seen_through = read_grid(bands)
            return OccupancyMap(spec, probability, variance, thresholds, path, info, seen_through)

        return LaterGrid(spec, put_together)

    def _planar_spec(self, resolution: float, extent: tuple[float, ...] | None) -> GridSpec:
        """The planar grid of :meth:`grid`: `extent`'s, or :meth:`default_extent`'s aligned on the counts' cells."""
        box = self.default_extent(resolution) if extent is None else extent
        return GridSpec.from_extent((box[0], box[1], box[2], box[3]), resolution, align=extent is None)

    def voxels(self, resolution: float, extent: tuple[float, ...] | None = None) -> VoxelMap:
        """A 3-D map sampled on a voxel grid.

        Parameters
        ----------
        resolution : float
            Voxel side, metres.
        extent : (xmin, xmax, ymin, ymax, zmin, zmax), optional
            Defaults to :meth:`default_extent`. The voxel faces are put on multiples of
            `resolution`, where OctoMap puts its own.

        Returns
        -------
        VoxelMap
            Probability and latent variance per voxel, each of shape (nz, ny, nx). With ray
            evidence, each voxel's own counts update the GP's probability there, and the voxels
            no ray reached are marked unobserved.
        """
        return self.voxels_and_points(resolution, extent)[0]

    def voxels_and_points(
        self, resolution: float, extent: tuple[float, ...] | None = None, points: NDArray[np.float64] | None = None
    ) -> tuple[VoxelMap, NDArray[np.float64]]:
        """:meth:`voxels`, and :meth:`predict_proba` at `points` (predicted there, not read off the voxels).

        A field that makes its voxels in a pass of its own (:class:`VoxelPass`) answers both in
        that pass; any other field answers the grid, then the points.

        Parameters
        ----------
        resolution : float
        extent : (xmin, xmax, ymin, ymax, zmin, zmax), optional
            As :meth:`voxels`'.
        points : ndarray of shape (m, 3), optional

        Returns
        -------
        VoxelMap
            :meth:`voxels`' map.
        ndarray of shape (m,)
            The probability at `points` (size 0 without them).
        """
        from gpomap.voxels import VoxelMap, VoxelSpec

        if self.dim != 3:
            raise ValueError(f"voxels() is for 3-D maps; this map is {self.dim}-D: use grid()")
        lo, hi = extent_bounds(self.default_extent(resolution) if extent is None else extent)
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        pts = np.zeros((0, 3)) if points is None else as_points(points, 3)
        at_points: NDArray[np.float64] | None = None
        with self._timed("grid"):
            if self.evidence is not None:
                from gpomap.fusion.written import read_grid

                probability, variance, _ = read_grid(self._written(spec))
            elif isinstance(self.field, VoxelPass):
                probability, variance, at_points, _ = self.field.voxel_probabilities(spec, pts)
            else:
                p, var, _ = self.field.gp_probabilities(spec.centres())
                probability, variance = p.reshape(spec.shape), var.reshape(spec.shape)
        self.field.grid_done()
        observed = self.evidence.grid_observed(spec) if self.evidence is not None else None
        made = VoxelMap(spec, probability, variance, thresholds=self.thresholds, info=self._summary(), observed=observed)
        if at_points is None:
            at_points = self.predict_proba(pts) if len(pts) else np.zeros(0)
        return made, at_points

    def _written(self, spec: GridSpec | VoxelSpec) -> Any:
        """Probability, latent variance and the cells beams saw through, per cell of `spec`, with
        the ray counts: :meth:`gpomap.fusion.EvidenceLayer.written_bands` (read them with
        :func:`gpomap.fusion.written.read_grid`)."""
        assert self.evidence is not None
        field = self.field
        return self.evidence.written_bands(spec, field.hyperparameters.length_scale, field.gp_probabilities, field.blended)

    def _gp_grid(self, spec: GridSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The GP's probability and latent variance at every cell centre of `spec`, each spec.shape;
        a large grid in bands of rows, as the written map with counts is (the same values)."""
        ny, nx = spec.shape
        rows = max(1, WRITTEN_BAND_CELLS // nx)
        if ny <= rows:
            p, var, _ = self.field.gp_probabilities(spec.centres())
            return p.reshape(spec.shape), var.reshape(spec.shape)
        probability, variance = np.empty(spec.shape), np.empty(spec.shape)
        for start, stop, band in row_bands(spec, rows):
            p, var, _ = self.field.gp_probabilities(band.centres())
            probability[start:stop], variance[start:stop] = p.reshape(-1, nx), var.reshape(-1, nx)
            self.field.forget_below(spec.origin[1] + stop * spec.resolution)
        self.field.forget_below(np.inf)
        return probability, variance

    def _supersampled(self, spec: GridSpec, k: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The GP's largest probability and mean latent variance over k x k samples of each cell of `spec`."""
        fine = GridSpec(spec.origin, spec.resolution / k, (spec.shape[0] * k, spec.shape[1] * k))
        p, var, _ = self.field.gp_probabilities(fine.centres())
        # Fine row-major (ny*k, nx*k) -> (ny, k, nx, k): one k x k block per output cell.
        blocks = (spec.shape[0], k, spec.shape[1], k)
        return p.reshape(blocks).max(axis=(1, 3)), var.reshape(blocks).mean(axis=(1, 3))


class MapAnswers:
    """What an estimator answers once fitted: each answer is its fitted map's (:attr:`map_`).

    The estimator defines :attr:`map_`; scikit-learn's names (``predict``, ``predict_proba``,
    the trailing underscore of what was fitted) stay on the estimator.
    """

    @property
    def map_(self) -> FittedMap:
        """The fitted map (raises :class:`~gpomap.errors.NotFittedError` before ``fit``)."""
        raise NotImplementedError

    @property
    def thresholds_(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities (:attr:`FittedMap.thresholds`)."""
        return self.map_.thresholds

    @overload
    def predict(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The GP's latent mean (and variance) at points (:meth:`FittedMap.predict`)."""
        return self.map_.predict(points, return_var)

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
        """Occupancy probability at points, ndarray of shape (m,), with the latent variance when
        asked (:meth:`FittedMap.predict_proba`)."""
        return self.map_.predict_proba(points, return_var)

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
        """The GP's own probability at points, before any ray evidence (:meth:`FittedMap.predict_proba_gp`)."""
        return self.map_.predict_proba_gp(points, return_var)

    def predict_ternary(self, points: NDArray[np.float64], probability: NDArray[np.float64] | None = None) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, shape (m,) (:meth:`FittedMap.predict_ternary`)."""
        return self.map_.predict_ternary(points, probability)

    def grid(self, resolution: float, extent: tuple[float, ...] | None = None, supersample: int = 1) -> Any:
        """The map on a regular grid: an OccupancyMap in 2-D, a VoxelMap in 3-D (:meth:`FittedMap.grid`)."""
        return self.map_.grid(resolution, extent, supersample)

    def voxels(self, resolution: float, extent: tuple[float, ...] | None = None) -> VoxelMap:
        """A 3-D map on a voxel grid (:meth:`FittedMap.voxels`)."""
        return self.map_.voxels(resolution, extent)
