"""An octree too large for one GP, converted in tiles: the cells and the hyperparameters once,
then square columns fitted, predicted and let go one after another (:class:`TiledOctreeModel`).

The blended columns are the GP under the model's fitted map (:class:`ColumnsField`, the model's
``map_``), which makes every answer: points, voxel grids, the ternary map.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.config import DEFAULT_MAX_CELLS  # most cells of the one GP of a conversion, as for maps
from gpomap.convert.estimator import GridGPOM
from gpomap.convert.octree_tiling import ColumnTiling, TileQueries, predict_tiles
from gpomap.errors import GpomapError, NotFittedError
from gpomap.extrapolation import VarianceScale
from gpomap.fitted import FittedMap, GPHyperparameters, MapAnswers
from gpomap.kernels.point import make_point_kernel
from gpomap.lattice import coarse, interpolate, interpolation_block
from gpomap.observations import Observations
from gpomap.resources import largest_tile_cells, peak_rss_mb
from gpomap.squash import ProbitSquash
from gpomap.stages import CalibratedMoments, GPProbability
from gpomap.supports import Supports
from gpomap.tiles import (
    BLEND_FRACTION,
    BLOCK_SIZE,
    DEFAULT_HYPER_SAMPLE,
    HYPER_GROUP_CELLS,
    TileSettings,
    given_hyperparameters,
    hyper_anchor_block,
    tile_reach,
)
from gpomap.voxels import VoxelSpec

__all__ = ["TILE_SIDES", "VARIANCE_STEP_SOURCE_VOXELS", "BAND_LAYERS", "ColumnsField", "TiledOctreeModel"]

#: Tile sides tried for a tree too large for one GP, largest first (metres): the first whose
#: densest column's GP holds at most ``max_cells`` cells. 3 m is a voxel map's tile
#: (:data:`gpomap.tiles.DEFAULT_TILE_SIZE`); an octree's known voxels are denser than a map's
#: cells, so most trees take a smaller one (docs/convert.md, "OctoMap trees, whole").
TILE_SIDES: tuple[float, ...] = (3.0, 2.0, 1.5, 1.0, 0.75, 0.5)
#: A tiled conversion predicts the latent mean at every output voxel, and the latent variance
#: this many source voxels apart (at least every output voxel), interpolated trilinearly: the
#: variance is most of a prediction's cost and varies with the distance to the data, which come
#: at the source's pitch, not with the walls' detail the mean carries (docs/convert.md).
VARIANCE_STEP_SOURCE_VOXELS = 1
#: Output voxel layers per band of the final interpolation and squash (bounds their temporaries).
BAND_LAYERS = 8


class TiledOctreeModel(MapAnswers):
    """The continuous map of an octree too large for one GP: tiles fitted when asked and let go.

    The cells of the whole tree are built once (:meth:`gpomap.convert.GridGPOM.make_cells`, as a
    single-GP conversion builds them), and the hyperparameters learnt once on a compact sample of
    them, as :class:`~gpomap.tiles.TiledGPOM` learns a map's. Every answer is the fitted map's
    (:attr:`map_`, over :class:`ColumnsField`). A prediction (a voxel grid, :meth:`voxels`, or
    points, :meth:`predict_proba`) runs tile by tile over square columns of side
    :attr:`tile_size_` spanning every height: each tile's GP is fitted on the cells meeting its
    square grown by the overlap (:func:`gpomap.tiles.fit_tile_task`), predicts the queries within
    its blend region, with the smoothstep weights of :class:`~gpomap.tiles.TiledGPOM`
    (:func:`gpomap.tiles.taper`), and is let go. Memory is the cells, the output, and the tiles in
    flight (``n_workers`` at most), whatever the tree's size.

    Every tile of the lattice over the queries takes part, a tile with no cells in its reach
    predicting the GP prior (mean 0, the signal variance), so the weights sum to one everywhere.
    With the alpha and beta learnt globally, a query's probability is the squash of its blended
    latent mean and variance, exactly as in a TiledGPOM.

    Parameters
    ----------
    base : GridGPOM
        The settings (kernel, cells, search), unfitted.
    tile_size : float, optional
        Column side, metres; default the first of :data:`TILE_SIDES` whose densest column holds at
        most `max_cells` cells.
    max_cells : int
        Most cells one tile's GP should hold.
    hyper_sample : int, optional
        Cells of the compact hyperparameter sample; default :data:`gpomap.tiles.DEFAULT_HYPER_SAMPLE` (3-D).
    n_workers : int
        Tiles fitted and predicted at once, on threads.
    """

    def __init__(
        self,
        base: GridGPOM,
        tile_size: float | None = None,
        max_cells: int = DEFAULT_MAX_CELLS,
        hyper_sample: int | None = None,
        n_workers: int = 1,
    ) -> None:
        if tile_size is not None and not tile_size > 0:
            raise ValueError(f"tile_size must be positive, got {tile_size}")
        if n_workers < 1:
            raise ValueError(f"n_workers must be at least 1, got {n_workers}")
        self.base = base
        self.tile_size = tile_size
        self.max_cells = int(max_cells)
        self.hyper_sample = hyper_sample
        self.n_workers = int(n_workers)

    # ------------------------------------------------------------------ fitting
    def fit(self, obs: Observations, hyperparameters: dict[str, float] | None = None) -> TiledOctreeModel:
        """Build the cells, learn the hyperparameters (unless given) and choose the tiles.

        Parameters
        ----------
        obs : Observations
            Known voxel centres (:func:`octree_to_observations`), points of shape (n, 3).
        hyperparameters : dict, optional
            variance, length_scale, noise, alpha and beta to use as they are.

        Returns
        -------
        self

        Raises
        ------
        GpomapError
            Even the smallest of :data:`TILE_SIDES` leaves a column with more than ``max_cells`` cells.
        """
        t0 = time.perf_counter()
        cells = self.base.make_cells(obs)
        supports = cells.to_supports()
        self.lower_, self.upper_ = supports.lower, supports.upper
        self.counts_ = np.asarray(supports.counts, dtype=float)
        self.labels_ = np.asarray(cells.labels, dtype=float)
        self.n_ambiguous_ = int(cells.ambiguous.sum())
        self.origin_ = (float(obs.points[:, 0].min()), float(obs.points[:, 1].min()))
        self.data_lower_, self.data_upper_ = obs.points.min(axis=0), obs.points.max(axis=0)
        self.timings_: dict[str, float] = {"cells": time.perf_counter() - t0}
        t = time.perf_counter()
        if hyperparameters is None:
            self.hyperparameters_ = self._learn_hyperparameters()
            self.hyper_source_ = dict(self._sample_report)
        else:
            self.hyperparameters_ = given_hyperparameters(hyperparameters)
            self.hyper_source_ = {"how": "given to fit()"}
        self.hyperparameters_.setdefault("variance_scale", 1.0)
        self.timings_["hyperparameters"] = time.perf_counter() - t
        self._choose_tiles()
        # Octree voxels are not rays: no held-out stretches, no variance scale (as GridGPOM).
        self.extrapolation_: dict[str, Any] = {"kappa": 1.0, "reason": "labelled voxels given, not scans"}
        return self

    @property
    def n_inputs_(self) -> int:
        """Number of cells over the whole tree."""
        return int(self.labels_.size)

    @property
    def map_(self) -> FittedMap:
        """The fitted map: the blended columns (:class:`ColumnsField`), every answer's maker
        (raises :class:`~gpomap.errors.NotFittedError` before ``fit``)."""
        if not hasattr(self, "tiling_"):
            raise NotFittedError("this TiledOctreeModel is not fitted yet: call fit() first")
        return FittedMap(
            ColumnsField(self), None, self.base.thresholds, self.data_lower_, self.data_upper_, None, self.summary, self.timings_
        )

    def _settings(self) -> TileSettings:
        b = self.base
        same = {f.name: getattr(b, f.name) for f in fields(TileSettings) if f.name not in ("area", "per_tile")}
        return TileSettings(area=b.area_method, **same)

    def _learn_hyperparameters(self) -> dict[str, float]:
        """All five hyperparameters, on the compact sample a TiledGPOM of these cells would take."""
        centres = 0.5 * (self.lower_ + self.upper_)
        block = np.floor((centres[:, :2] - np.asarray(self.origin_)) / BLOCK_SIZE).astype(np.int64)
        keys, inverse = np.unique(block[:, 0] * (1 << 32) + block[:, 1], return_inverse=True)
        sizes = np.bincount(inverse, minlength=keys.size)
        occupied = np.bincount(inverse, weights=(self.labels_ > 0).astype(float), minlength=keys.size) / sizes
        anchor_block = hyper_anchor_block(sizes, occupied, float(np.mean(self.labels_ > 0)))
        anchor = centres[inverse == anchor_block].mean(axis=0)
        k = self.hyper_sample if self.hyper_sample is not None else DEFAULT_HYPER_SAMPLE[3]
        n = self.labels_.size
        d = np.sum((centres - anchor) ** 2, axis=1)
        idx = np.arange(n) if n <= k else np.sort(np.argpartition(d, k - 1)[:k])
        b = self.base
        gp = self._settings().search_gp(
            b.make_kernel(), b.noise, optimise=b.optimise, hyper_subset=None, hyper_group=HYPER_GROUP_CELLS[3]
        )
        gp.fit(Supports(self.lower_[idx], self.upper_[idx], self.counts_[idx]), self.labels_[idx])
        self._sample_report = {
            "how": "learnt" if b.optimise else "given (alpha, beta fitted)",
            "sample_cells": int(idx.size),
            "sample_centre": [round(float(v), 2) for v in anchor],
            "sample_radius_m": round(float(np.sqrt(d[idx].max())), 2),
            "sample_occupied_fraction": round(float(np.mean(self.labels_[idx] > 0)), 4),
        }
        return {
            "variance": float(gp.kernel.base.variance),
            "length_scale": float(gp.kernel.base.length_scale),
            "noise": float(gp.noise),
            "alpha": float(gp.squash.alpha),
            "beta": float(gp.squash.beta),
        }

    def _choose_tiles(self) -> None:
        """The tile side (given, or the first of :data:`TILE_SIDES` within ``max_cells``), the overlap and the blend."""
        centres = 0.5 * (self.lower_ + self.upper_)
        ell = self.hyperparameters_["length_scale"]
        sides = (self.tile_size,) if self.tile_size is not None else TILE_SIDES
        for side in sides:
            assert side is not None
            overlap = tile_reach(side, ell)
            largest = largest_tile_cells(centres[:, :2], side, overlap, self.origin_)
            if largest <= self.max_cells or self.tile_size is not None:
                break
        else:
            raise GpomapError(
                f"the densest {side:g} m column of the tree holds {largest} cells, more than one GP holds ({self.max_cells}); "
                "raise --max-cells (max_cells) if the machine has the memory, or convert a smaller region (--extent, --z-range)"
            )
        self.tile_size_ = float(side)
        self.overlap_ = float(overlap)
        self.blend_ = float(BLEND_FRACTION * min(overlap, side))
        self.largest_tile_cells_ = int(largest)
        self.tiling_ = ColumnTiling(
            self.lower_, self.upper_, self.counts_, self.labels_, self.origin_, self.tile_size_, self.overlap_, self.blend_
        )

    def _predict(
        self, queries: TileQueries, desc: str
    ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64]]:
        """Blended latent moments (:func:`~gpomap.convert.octree_tiling.predict_tiles`): the mean at
        every voxel of ``queries.spec`` and the variance on ``queries.coarse`` (or None, None
        without a grid), the mean and variance at ``queries.points`` (each of shape (m,))."""
        mean, var, p_mean, p_var, stats = predict_tiles(
            self.tiling_, queries, self._settings(), self.hyperparameters_, self.base.chunk_size, self.n_workers, desc
        )
        self.last_prediction_ = stats
        return mean, var, p_mean, p_var

    def summary(self) -> dict[str, Any]:
        """Tiles, cells, hyperparameters and where they came from, timings, peak memory."""
        return {
            "method": "msk-gpom",
            "kernel": make_point_kernel(self.base.kernel).name,
            "area": self.base.area_method,
            "tiled": True,
            "tile_size": self.tile_size_,
            "tile_origin": list(self.origin_),
            "overlap": self.overlap_,
            "blend": self.blend_,
            "largest_tile_cells": self.largest_tile_cells_,
            "n_cells": self.n_inputs_,
            "n_ambiguous_cells": self.n_ambiguous_,
            "hyperparameters": dict(self.hyperparameters_),
            "hyperparameter_source": dict(self.hyper_source_),
            "last_prediction": dict(getattr(self, "last_prediction_", {})),
            "thresholds": list(self.thresholds_),
            "timings": dict(self.timings_),
            "peak_memory": peak_rss_mb(),
        }


class ColumnsField:
    """The tiled conversion's blended columns, as its fitted map asks them
    (:class:`~gpomap.fitted.LatentField`, and :class:`~gpomap.fitted.VoxelPass` for its voxels):
    every answer is one pass over the columns it needs, each fitted, asked and let go.

    Parameters
    ----------
    model : TiledOctreeModel
        Fitted.
    """

    def __init__(self, model: TiledOctreeModel) -> None:
        self._model = model

    @property
    def dim(self) -> int:
        """3: an octree's map is a voxel map."""
        return 3

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """The hyperparameters every column's GP shares."""
        return GPHyperparameters.from_mapping(self._model.hyperparameters_)

    @property
    def squash(self) -> ProbitSquash:
        """The columns' probit (alpha, beta; the variance scale is 1: voxels are not rays)."""
        h = self._model.hyperparameters_
        return ProbitSquash(float(h["alpha"]), float(h["beta"]), float(h["variance_scale"]))

    @property
    def blended(self) -> None:
        """None: the conversion has no ray counts, so no written grid asks for moments."""
        return None

    def _squash(self, mean: NDArray[np.float64], var: NDArray[np.float64]) -> GPProbability:
        """The probabilities of blended latent moments (any matching shapes), through the map's
        squash stage at variance scale 1 (voxels are not rays: the probability for unseen space
        is the probability)."""
        h = self._model.hyperparameters_
        a, b = h["alpha"], h["beta"]
        # Calibrated after the blend with the global alpha and beta, alpha^2 as a * a, as a tiled
        # map's tiles calibrate theirs before it (gpomap.tiles.TiledGPOM.blended_moments).
        return VarianceScale().apply(CalibratedMoments(a * mean + b, a * a * var))

    def latent(self, points: NDArray[np.float64], return_var: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Blended latent mean and variance at points (m, 3), each (m,)."""
        _, _, mean, var = self._model._predict(TileQueries(None, None, points), "predicting tiles")
        return mean, var if return_var else None

    def gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The probability, the latent variance, and the probability again (voxels are not rays:
        no unseen space apart), each (m,)."""
        mean, var = self.latent(points, True)
        assert var is not None  # asked for
        gp = self._squash(mean, var)
        return gp.probability, var, gp.unseen

    def voxel_probabilities(
        self, spec: VoxelSpec, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The voxels of `spec` and the points, in one pass over the columns.

        The latent mean is predicted at every voxel, the variance at the source's voxel pitch
        (:data:`VARIANCE_STEP_SOURCE_VOXELS`) and interpolated trilinearly; points are predicted
        exactly.

        Parameters
        ----------
        spec : VoxelSpec
        points : ndarray of shape (m, 3)

        Returns
        -------
        probability, variance : ndarray of shape ``spec.shape``
        point_probability, point_variance : ndarray of shape (m,)
        """
        model = self._model
        resolution = spec.resolution
        source_pitch = 2.0 * model.base.pixel_pad
        step = max(1, round(VARIANCE_STEP_SOURCE_VOXELS * source_pitch / resolution)) if source_pitch > 0 else 1
        coarse_spec = coarse(spec, step)
        assert isinstance(coarse_spec, VoxelSpec)  # the coarse lattice of a voxel grid is one
        mean, var_c, p_mean, p_var = model._predict(TileQueries(spec, coarse_spec, points), "converting tiles")
        assert mean is not None and var_c is not None
        # The squash in bands of layers, the variance interpolated band by band: the mean's array
        # becomes the probability's, and the temporaries stay a band's.
        variance = np.empty(spec.shape)
        for k0 in range(0, spec.shape[0], BAND_LAYERS):
            k1 = min(k0 + BAND_LAYERS, spec.shape[0])
            band = VoxelSpec(
                (spec.origin[0], spec.origin[1], spec.origin[2] + k0 * resolution), resolution, (k1 - k0, *spec.shape[1:])
            )
            src = interpolation_block(coarse_spec, band)
            sz, sy, sx = src[0], src[1], src[2]
            pitch = coarse_spec.resolution
            sub = VoxelSpec(
                (
                    coarse_spec.origin[0] + sx.start * pitch,
                    coarse_spec.origin[1] + sy.start * pitch,
                    coarse_spec.origin[2] + sz.start * pitch,
                ),
                pitch,
                (sz.stop - sz.start, sy.stop - sy.start, sx.stop - sx.start),
            )
            variance[k0:k1] = interpolate(var_c[src], sub, band)
            mean[k0:k1] = self._squash(mean[k0:k1], variance[k0:k1]).probability
        del var_c
        return mean, variance, self._squash(p_mean, p_var).probability, p_var

    def limited(self) -> contextlib.AbstractContextManager[Any]:
        """No limit: the columns run on this process's threads (``n_workers``) with its BLAS as it is."""
        return contextlib.nullcontext()

    def forget_below(self, y: float) -> None:
        """Nothing to let go of: no column outlives the pass that fitted it."""

    def grid_done(self) -> None:
        """Nothing to give back."""
