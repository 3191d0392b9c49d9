"""What every map-maker in gpomap answers: the mapper protocol.

MSK-GPOM (:class:`~gpomap.mapping.AreaGPOM`, :class:`~gpomap.tiles.TiledGPOM`), the paper's
baselines (:class:`~gpomap.baselines.gpom.GPOM`, :class:`~gpomap.baselines.gpomik.GPOMIK`) and
the occupancy grid (:class:`~gpomap.baselines.ogm.OccupancyGridMapper`) are fitted, queried,
sampled on a grid and summarised the same way, so evaluation and benchmarks treat them alike.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable


@runtime_checkable
class Mapper(Protocol):
    """A map-maker: ``fit`` on scans, then probabilities anywhere, a grid, and a summary.

    ``fit(data)`` returns the fitted mapper; ``predict(points, return_var)`` gives the latent mean
    (a grid: its probability) and optionally the variance, each of shape (m,);
    ``predict_proba(points)`` the occupancy probability, shape (m,); ``grid(resolution, extent)``
    the map a user gets (:class:`~gpomap.grid.OccupancyMap`, or a
    :class:`~gpomap.voxels.VoxelMap` in 3-D); ``summary()`` a dict with at least ``"method"``.
    """

    def fit(self, data: Any) -> Any: ...

    def predict(self, points: Any, return_var: bool = ...) -> Any: ...

    def predict_proba(self, points: Any) -> Any: ...

    def grid(self, resolution: Any, extent: Any = ...) -> Any: ...

    def summary(self) -> dict[str, Any]: ...
