"""OctoMap itself as a 3-D baseline, through pyoctomap.

Each :class:`~gpomap.clouds.CloudScan` goes in with ``insertPointCloud(points, origin, max_range)``
as an OctoMap user would insert it: OctoMap's default sensor model (hit 0.7, miss 0.4, clamping
0.1192 .. 0.971), one ray per point, the endpoint voxel occupied and the voxels before it free.
No-return rays must never make an occupied voxel: their endpoints (at the sensor's max range) are
pushed just beyond `max_range`, so OctoMap truncates them there and marks them free only, which is
what it does with over-long readings itself.

:meth:`OctoMapBaseline.predict_proba` returns the occupancy of the leaf holding each point, and
exactly 0.5 where the tree knows nothing, as the 2-D grid baselines do.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.clouds import CloudScan
from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.extras import require

__all__ = ["OctoMapBaseline"]

# No-return endpoints are moved this fraction past max_range so OctoMap treats them as too long.
_BEYOND = 1e-3


class OctoMapBaseline:
    """OctoMap occupancy octree fitted on 3-D scans.

    Parameters
    ----------
    resolution : float
        Voxel side, metres (0.1: the 3-D benchmarks' usual voxel).
    max_range : float, optional
        Rays are cut at this range (free only beyond it). Default: each cloud's ``max_range``,
        else the longest no-return ray, else unlimited.
    prob_hit, prob_miss : float, optional
        Sensor model; default OctoMap's own (0.7, 0.4).
    """

    def __init__(
        self,
        resolution: float = 0.1,
        max_range: float | None = None,
        prob_hit: float | None = None,
        prob_miss: float | None = None,
    ) -> None:
        self.resolution = resolution
        self.max_range = max_range
        self.prob_hit = prob_hit
        self.prob_miss = prob_miss

    def __repr__(self) -> str:
        return f"OctoMapBaseline(resolution={self.resolution}, max_range={self.max_range})"

    def _range_of(self, cloud: CloudScan) -> float:
        if self.max_range is not None:
            return float(self.max_range)
        if cloud.max_range is not None:
            return float(cloud.max_range)
        valid = cloud.valid()
        miss = valid & ~np.asarray(cloud.hit, dtype=bool)
        if miss.any():
            return float(np.linalg.norm(cloud.points[miss] - cloud.origin, axis=1).max())
        return -1.0

    def fit(self, clouds: Sequence[CloudScan]) -> OctoMapBaseline:
        """Insert every cloud, in order.

        Parameters
        ----------
        clouds : sequence of CloudScan

        Returns
        -------
        self
        """
        pyoctomap = require("pyoctomap", "the OctoMap baseline")

        tree = pyoctomap.OcTree(float(self.resolution))
        if self.prob_hit is not None:
            tree.setProbHit(float(self.prob_hit))
        if self.prob_miss is not None:
            tree.setProbMiss(float(self.prob_miss))
        n_rays = 0
        for cloud in clouds:
            valid = cloud.valid()
            pts = cloud.points[valid].copy()
            hit = np.asarray(cloud.hit, dtype=bool)[valid]
            max_range = self._range_of(cloud)
            if (~hit).any():
                d = pts[~hit] - cloud.origin
                r = np.linalg.norm(d, axis=1)
                reach = max(max_range, float(r.max())) if max_range > 0 else float(r.max())
                if max_range <= 0:
                    max_range = reach
                pts[~hit] = cloud.origin + d * ((reach * (1 + _BEYOND)) / r)[:, None]
            if len(pts):
                tree.insertPointCloud(
                    np.ascontiguousarray(pts, dtype=np.float64), np.asarray(cloud.origin, dtype=np.float64), max_range
                )
                n_rays += len(pts)
        if n_rays == 0:
            raise EmptyDataError("no valid rays in the clouds to insert into the octree")
        self.tree_: Any = tree
        self.n_rays_ = n_rays
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "tree_"):
            raise NotFittedError("OctoMapBaseline is not fitted yet: call fit(clouds) first")

    def predict_proba(self, points: ArrayLike) -> NDArray[np.float64]:
        """Occupancy probability of the leaf holding each point.

        Parameters
        ----------
        points : array_like of shape (n, 3)

        Returns
        -------
        ndarray of shape (n,)
            Exactly 0.5 where the tree has no leaf (never observed) and outside it.
        """
        self._check_fitted()
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        out = np.full(len(p), 0.5)
        search = self.tree_.search
        for i, q in enumerate(p):
            node = search(q)
            if node is not None:
                out[i] = node.getOccupancy()
        return out

    def predict(
        self, points: ArrayLike, return_var: bool = True
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability and ``p (1 - p)`` (a Bernoulli variance, as the grid baselines give).

        Parameters
        ----------
        points : array_like of shape (n, 3)
        return_var : bool

        Returns
        -------
        p : ndarray of shape (n,)
        var : ndarray of shape (n,)
            Only if `return_var`.
        """
        p = self.predict_proba(points)
        return (p, p * (1 - p)) if return_var else p

    def memory_bytes(self) -> int:
        """Bytes the octree uses (OctoMap's own count)."""
        self._check_fitted()
        return int(self.tree_.memoryUsage())
