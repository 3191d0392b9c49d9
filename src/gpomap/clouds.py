"""The 3-D scan: one point cloud with the sensor origin it was measured from.

A 3-D lidar sweep, a depth frame or a PCD file gives endpoints in the map frame and the
sensor position they were seen from. Each endpoint is a ray from `origin`: a hit (the surface
is there) or a no-return ray (the sensor saw nothing up to that point: free space, never a hit).
Readers (PCD, PLY, depth images, PointCloud2 bags, OctoMap scan graphs) produce lists of
:class:`CloudScan`; the 3-D map consumes them as the 2-D map consumes :class:`~gpomap.scans.Scan`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gpomap import _compiled_clouds
from gpomap.errors import InputFormatError


@dataclass(frozen=True)
class CloudScan:
    """One 3-D point cloud in the map frame.

    Parameters
    ----------
    origin : ndarray of shape (3,)
        Sensor position in the map frame, metres.
    points : ndarray of shape (n, 3)
        Ray endpoints in the map frame, metres. Rows with a non-finite coordinate are invalid
        readings (kept, so indices match the source, but never used).
    hit : ndarray of bool, shape (n,), optional
        True where the ray ended on a surface; False for a no-return ray (free up to its
        endpoint, which the reader places at the sensor's maximum range). Default all True.
    max_range : float, optional
        The sensor's maximum range, metres, where the source gives one.
    time : float, optional
        Time stamp in seconds, where the source has a usable one.
    """

    origin: NDArray[np.float64]
    points: NDArray[np.float64]
    hit: NDArray[np.bool_] | None = None
    max_range: float | None = None
    time: float | None = None
    meta: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=float).reshape(-1)
        points = np.asarray(self.points, dtype=float)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise InputFormatError(f"cloud origin must be 3 finite values (x, y, z), got {origin.tolist()}")
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputFormatError(f"cloud points must have shape (n, 3), got {points.shape}")
        hit = np.ones(points.shape[0], dtype=bool) if self.hit is None else np.asarray(self.hit, dtype=bool).reshape(-1)
        if hit.shape != (points.shape[0],):
            raise InputFormatError(f"cloud has {points.shape[0]} points but {hit.size} hit flags; expected equal counts")
        if self.max_range is not None and not (np.isfinite(self.max_range) and self.max_range > 0):
            raise InputFormatError(f"cloud max_range must be a positive number, got {self.max_range}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "hit", hit)
        object.__setattr__(self, "max_range", None if self.max_range is None else float(self.max_range))

    @property
    def n_points(self) -> int:
        """Number of rays in the cloud."""
        return int(self.points.shape[0])

    def valid(self) -> NDArray[np.bool_]:
        """Mask of rays with finite endpoints away from the origin, shape (n,)."""
        if _compiled_clouds.ENABLED:
            found = _compiled_clouds.valid_rays(self.points, self.origin)
            if found is not None:
                return found
        finite: NDArray[np.bool_] = np.asarray(np.isfinite(self.points).all(axis=1))
        with np.errstate(invalid="ignore"):
            away = np.linalg.norm(np.where(finite[:, None], self.points - self.origin, 0.0), axis=1) > 0
        return finite & away


def clouds_extent(clouds: Sequence[CloudScan]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Bounding box of every valid endpoint and origin.

    Returns
    -------
    lower, upper : ndarray of shape (3,)
    """
    parts = [c.points[c.valid()] for c in clouds] + [np.array([c.origin for c in clouds]).reshape(-1, 3)]
    allp = np.concatenate(parts)
    if allp.size == 0:
        raise InputFormatError("no valid 3-D points to take an extent of")
    return allp.min(axis=0), allp.max(axis=0)


def cloud_from_points(
    origin: NDArray[np.float64],
    points: NDArray[np.float64],
    max_range: float | None = None,
    time: float | None = None,
    meta: dict | None = None,
) -> CloudScan:
    """A cloud of hits from `origin`; points beyond `max_range` become no-return rays ending at it.

    Parameters
    ----------
    origin : ndarray of shape (3,)
    points : ndarray of shape (n, 3)
        Map frame; non-finite rows stay (invalid rays).
    max_range : float, optional
    time : float, optional
    meta : dict, optional

    Returns
    -------
    CloudScan
    """
    origin = np.asarray(origin, dtype=float)
    points = np.array(points, dtype=float)
    hit = np.ones(len(points), dtype=bool)
    if max_range is not None:
        d = points - origin
        with np.errstate(invalid="ignore"):
            r = np.linalg.norm(d, axis=1)
            far = r > max_range
        points[far] = origin + d[far] * (max_range / r[far])[:, None]
        hit[far] = False
    return CloudScan(origin, points, hit, max_range=max_range, time=time, meta=meta or {})
