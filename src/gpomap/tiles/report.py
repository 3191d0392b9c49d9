"""What a fitted tiled map says of itself: its summary, extent, dimension, cells and labelled points, and its ternary thresholds."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import NotFittedError
from gpomap.fusion import ternary_thresholds
from gpomap.kernels.point import make_point_kernel
from gpomap.resources import peak_rss_mb
from gpomap.tiles.blocks import BlockCells
from gpomap.tiles.executors import TileExecutors
from gpomap.tiles.hyperparameters import HYPER_NAMES
from gpomap.tiles.store import light_tiles


class MapReport(BlockCells, TileExecutors):
    """A fitted map's facts and summary (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    def _check_fitted(self) -> None:
        if not hasattr(self, "tiles_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit() first")

    @property
    def bounds_(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper corners of the labelled points' bounding box (the default map extent), each (d,)."""
        self._check_fitted()
        assert self._lower is not None and self._upper is not None  # fit sees both classes
        return self._lower.copy(), self._upper.copy()

    @property
    def kept_bounds_(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper corners of the points the cells were grown from, each (d,): the
        labelled points without the free ones the clearance dropped (a voxel map's default extent)."""
        self._check_fitted()
        for key in self._block_points.keys() - (self._kept_bounds or {}).keys():
            self._kept_arrays(key)  # a block not built since the map was read
        bounds = list((self._kept_bounds or {}).values())
        return np.min([lo for lo, _ in bounds], axis=0), np.max([hi for _, hi in bounds], axis=0)

    @property
    def dim_(self) -> int:
        """Dimension of the fitted map: 2 for planar scans, 3 for point clouds."""
        self._check_fitted()
        return self._dim

    @property
    def n_inputs_(self) -> int:
        """Number of cells over the whole map (each counted once)."""
        self._check_fitted()
        return int(sum(len(b.counts) for b in self._blocks.values()))

    def cell_boxes(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Every cell of the map once, in block order.

        Returns
        -------
        lower, upper : ndarray of shape (n, d)
            The cells' boxes.
        labels : ndarray of shape (n,)
            +1 occupied, -1 free.
        """
        self._check_fitted()
        lo, hi, _, lab, _ = self._all_cells()
        return lo, hi, lab

    def training_points(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The labelled points the cells were built from (free points near hits dropped).

        Returns
        -------
        points : ndarray of shape (m, d)
        occupied : ndarray of bool, shape (m,)
        """
        self._check_fitted()
        parts = []
        for k in sorted(self._block_points):
            points, occupied = self._block_points[k].arrays()
            keep = ~self._block_points[k].free_near_hits(self._clearance)
            parts.append((points[keep], occupied[keep]))
        return np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])

    def summary(self) -> dict[str, Any]:
        """Tiles, cells per tile, hyperparameters and where they came from, stage timings, peak memory."""
        self._check_fitted()
        states = list(light_tiles(self.tiles_))
        per = np.array([s.n_cells for s in states])
        secs = np.array([s.seconds for s in states])
        out: dict[str, Any] = {
            "method": "msk-gpom",
            "kernel": make_point_kernel(self.base.kernel).name,
            "area": self.base.area_method,
            "tile_size": self.tile_size_,
            "block_size": self.block_size_,
            "tile_origin": [float(self.origin_[0]), float(self.origin_[1])],
            "overlap": self.overlap_,
            "blend": self.blend_,
            "n_tiles": len(self.tiles_),
            "n_cells": self.n_inputs_,
            "n_ambiguous_cells": int(sum(b.n_ambiguous for b in self._blocks.values())),
            "cells_per_tile": {"min": int(per.min()), "median": float(np.median(per)), "max": int(per.max())},
            "tile_fit_seconds": {
                "min": float(secs.min()),
                "median": float(np.median(secs)),
                "max": float(secs.max()),
                "sum": float(secs.sum()),
            },
            "n_points": self._n_points,
            "n_occupied_points": self._n_occupied_points,
            "n_free_samples": self._n_free_samples,
            "n_scans": self._n_scans,
            "n_invalid_readings": self._n_invalid,
            "n_no_return_readings": self._n_no_return,
            "n_free_points_cleared": sum(b.n_cleared for b in self._block_points.values()),
            "hyperparameters": dict(self.hyperparameters_),
            "variance_scale_fit": dict(self.extrapolation_),
            "revisit": dict(getattr(self, "revisit_", {})),
            "hyperparameter_source": dict(self.hyper_source_),
            "evidence": self.evidence_.summary() if self.evidence_ is not None else None,
            "thresholds": list(ternary_thresholds(self.base.thresholds, self.evidence_)),
            "timings": dict(self.timings_),
            "peak_memory": peak_rss_mb(),
            "executor": "dask"
            if self.scheduler is not None
            else (
                "in-process"
                if self.n_workers_ <= 1
                else f"{'process pool' if self.worker_processes else 'threads'} x{self.n_workers_}"
            ),
        }
        if self.per_tile_hyperparameters:
            out["per_tile_hyperparameters"] = {
                n: {"min": float(np.min(v)), "median": float(np.median(v)), "max": float(np.max(v))}
                for n in HYPER_NAMES
                for v in [[s.hyperparameters[n] for s in states]]
            }
        return out
