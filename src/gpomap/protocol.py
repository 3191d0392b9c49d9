"""What every planar map-maker in gpomap answers: the mapper protocol.

MSK-GPOM (:class:`~gpomap.mapping.AreaGPOM`, :class:`~gpomap.tiles.TiledGPOM`), the paper's
baselines (:class:`~gpomap.baselines.gpom.GPOM`, :class:`~gpomap.baselines.gpomik.GPOMIK`) and
the occupancy grid (:class:`~gpomap.baselines.ogm.OccupancyGridMapper`) are fitted on scans,
queried, sampled on a grid and summarised the same way, so evaluation and benchmarks treat them
alike: :mod:`gpomap.evaluation` builds them from its registry of methods
(:mod:`gpomap.evaluation.methods`) and calls only what :class:`Mapper` names, and asks the two
narrower protocols below where maps differ. The same classes fitted on point clouds give a
:class:`~gpomap.voxels.VoxelMap`, outside this planar protocol.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from gpomap.grid import OccupancyMap
from gpomap.scans import Scan


@runtime_checkable
class Mapper(Protocol):
    """A planar map-maker: ``fit`` on scans, then probabilities anywhere, a grid, and a summary."""

    def fit(self, scans: Sequence[Scan], /) -> Mapper:
        """Fit on `scans` (planar sweeps); returns the fitted mapper itself.

        Positional only: the maps name it ``scans`` or ``data`` (the latter also takes observations).
        """
        ...

    def predict(
        self, points: NDArray[np.float64], return_var: bool = ...
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The latent mean at `points`, shape (m, 2), each of shape (m,) (a grid: its probability), with the
        variance as a second array when `return_var`."""
        ...

    def predict_proba(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """The occupancy probability at `points`, shape (m, 2): ndarray of shape (m,)."""
        ...

    def grid(self, resolution: float, extent: tuple[float, ...] | None = ...) -> OccupancyMap:
        """The map a user gets, cells of `resolution` metres over `extent` ``(xmin, xmax, ymin, ymax)``
        (default: the data's); an occupancy grid gives its own cells (see :class:`OwnGrid`)."""
        ...

    def summary(self) -> dict[str, Any]:
        """What was fitted, as plain values; at least ``"method"``."""
        ...


@runtime_checkable
class TernaryPredictor(Protocol):
    """A map with a ternary map of its own (a fitted occupied threshold; MSK-GPOM's never calls
    occupied a cell beams saw through), where other maps take the paper's thresholds."""

    def predict_ternary(self, points: NDArray[np.float64]) -> NDArray[np.int8]:
        """Free (0), occupied (1) or unknown (-1) at `points`, shape (m, 2): ndarray of shape (m,)."""
        ...


@runtime_checkable
class OwnGrid(Protocol):
    """A map that is a grid (the occupancy grids): it has no finer map to give, so the map it
    writes is its own cells, whatever resolution is asked."""

    def grid_map(self) -> OccupancyMap:
        """The fitted grid itself."""
        ...
