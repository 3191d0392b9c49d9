"""An octree too large for one GP, converted in tiles: the cells and the hyperparameters once,
then square columns fitted, predicted and let go one after another (:class:`TiledOctreeModel`).
"""

from __future__ import annotations

import time
from dataclasses import fields
from typing import Any, Literal, overload

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from gpomap.config import DEFAULT_MAX_CELLS  # most cells of the one GP of a conversion, as for maps
from gpomap.convert.estimator import GridGPOM
from gpomap.convert.octree_tiling import ColumnTiling, TileQueries, predict_tiles
from gpomap.errors import GpomapError
from gpomap.fusion import ternary_thresholds
from gpomap.kernels.point import make_point_kernel
from gpomap.lattice import coarse, extent_bounds, interpolate, interpolation_block
from gpomap.observations import Observations
from gpomap.resources import largest_tile_cells, peak_rss_mb
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
from gpomap.voxels import VoxelMap, VoxelSpec

__all__ = ["TILE_SIDES", "VARIANCE_STEP_SOURCE_VOXELS", "BAND_LAYERS", "TiledOctreeModel"]

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


class TiledOctreeModel:
    """The continuous map of an octree too large for one GP: tiles fitted when asked and let go.

    The cells of the whole tree are built once (:meth:`gpomap.convert.GridGPOM.make_cells`, as a
    single-GP conversion builds them), and the hyperparameters learnt once on a compact sample of
    them, as :class:`~gpomap.tiles.TiledGPOM` learns a map's. A prediction (a voxel grid,
    :meth:`voxels`, or points, :meth:`predict_proba`) then runs tile by tile over square
    columns of side :attr:`tile_size_` spanning every height: each tile's GP is fitted on the
    cells meeting its square grown by the overlap (:func:`gpomap.tiles.fit_tile_task`), predicts
    the queries within its blend region, with the smoothstep weights of
    :class:`~gpomap.tiles.TiledGPOM` (:func:`gpomap.tiles.taper`), and is let go. Memory is the
    cells, the output, and the tiles in flight (``n_workers`` at most), whatever the tree's size.

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
    def thresholds_(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities."""
        return ternary_thresholds(self.base.thresholds, None)

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

    def _squash(self, mean: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
        a, b = self.hyperparameters_["alpha"], self.hyperparameters_["beta"]
        return np.asarray(ndtr((a * mean + b) / np.sqrt(1.0 + a * a * var)))

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
        """Occupancy probability at points, blended across tiles (each fitted for it and let go).

        Parameters
        ----------
        points : ndarray of shape (m, 3)
        return_var : bool
            Also return the blended latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        _, _, mean, var = self._predict(TileQueries(None, None, pts), "predicting tiles")
        p = self._squash(mean, var)
        return (p, var) if return_var else p

    def voxels(
        self, resolution: float, extent: tuple[float, ...], points: NDArray[np.float64] | None = None
    ) -> tuple[VoxelMap, NDArray[np.float64]]:
        """The map on a voxel grid, and the probability at `points`, in one pass over the tiles.

        Parameters
        ----------
        resolution : float
            Voxel side, metres.
        extent : (xmin, xmax, ymin, ymax, zmin, zmax)
            Voxel faces on multiples of `resolution` (as :meth:`gpomap.estimator.GPMapEstimator.voxels`).
        points : ndarray of shape (m, 3), optional
            Points whose probability is wanted too (predicted exactly, not interpolated).

        Returns
        -------
        VoxelMap
            Probability and latent variance of shape (nz, ny, nx): the mean at every voxel, the
            variance at the source's voxel pitch (:data:`VARIANCE_STEP_SOURCE_VOXELS`), interpolated.
        ndarray of shape (m,)
            The probability at `points`.
        """
        lo, hi = extent_bounds(extent)
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        source_pitch = 2.0 * self.base.pixel_pad
        step = max(1, round(VARIANCE_STEP_SOURCE_VOXELS * source_pitch / resolution)) if source_pitch > 0 else 1
        coarse_spec = coarse(spec, step)
        assert isinstance(coarse_spec, VoxelSpec)  # the coarse lattice of a voxel grid is one
        pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=float).reshape(-1, 3)
        mean, var_c, p_mean, p_var = self._predict(TileQueries(spec, coarse_spec, pts), "converting tiles")
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
            mean[k0:k1] = self._squash(mean[k0:k1], variance[k0:k1])
        del var_c
        info = self.summary()
        return VoxelMap(spec, mean, variance, thresholds=self.thresholds_, info=info), self._squash(p_mean, p_var)

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
