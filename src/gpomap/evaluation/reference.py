"""Where the training scans reached: observed cells, the far field and the robot's path.

The reference grid (:func:`reference_grid`, the counting grid of the training scans at
:data:`REFERENCE_RESOLUTION`) tells test points in cells a training beam crossed from the rest;
:class:`FarField` measures the distance to those cells on a coarse lattice, to score what a map
says far from all data; :func:`path_points` samples the robot's own path, which a map should not
call occupied.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.points import NO_RETURN_CAP
from gpomap.grid import GridSpec
from gpomap.scans import Scan

#: The reference grid telling observed cells from unobserved ones (counting grid, metres).
REFERENCE_RESOLUTION = 0.05
#: "Far from all data": farther than this (m) from any cell a training beam crossed.
FAR_DISTANCE = 5.0
#: Far-field lattice spacing (m) and most lattice points predicted.
FAR_LATTICE = 0.25
FAR_MAX_POINTS = 2000
#: The robot's path is checked every this many metres (half the reference cell: no cell skipped).
PATH_STEP = 0.025


def reference_grid(train: Sequence[Scan], resolution: float = REFERENCE_RESOLUTION) -> Any:
    """The counting grid of the training scans: which cells any training beam crossed."""
    from gpomap.baselines.ogm import OccupancyGridMapper

    return OccupancyGridMapper(resolution, sensor_model="counting", max_range_free=NO_RETURN_CAP).fit(train)


def observed_at(reference: Any, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether each point lies in a cell the reference grid observed, shape (n,)."""
    rows, cols, inside = reference.grid_.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.zeros(len(rows), dtype=bool)
    out[inside] = reference.observed_[rows[inside], cols[inside]] > 0
    return out


def path_points(scans: Sequence[Scan], step: float = PATH_STEP) -> NDArray[np.float64]:
    """Points every `step` along the robot's path through `scans` (in log order), shape (n, 2).

    The path joins consecutive scans' sensor positions where the map takes the robot to have
    driven (:func:`gpomap.robot_path.path_steps`); jumps in the log are left out.
    """
    from gpomap.observations import sensor_positions
    from gpomap.robot_path import path_steps

    if len(scans) == 0:
        return np.zeros((0, 2))
    out = [sensor_positions(scans)]
    for a, b in zip(*np.split(path_steps(scans), 2, axis=1)):
        length = float(np.hypot(*(b - a)))
        if length > 0:
            t = np.arange(step, length, step) / length
            out.append(a + t[:, None] * (b - a))
    return np.concatenate(out)


@dataclass(frozen=True)
class FarField:
    """Distance to the data on a coarse lattice round it.

    Attributes
    ----------
    grid : GridSpec
        The lattice: the reference grid's box padded by ``2 * FAR_DISTANCE``, cells of FAR_LATTICE.
    distance : ndarray of shape (ny, nx)
        Distance (m) from each lattice cell centre to the nearest lattice cell holding an
        observed reference cell (exact to about one lattice cell).
    """

    grid: GridSpec
    distance: NDArray[np.float64]

    @classmethod
    def from_reference(cls, reference: Any, spacing: float = FAR_LATTICE, pad: float = 2 * FAR_DISTANCE) -> FarField:
        """The lattice round a fitted reference grid (see :func:`reference_grid`)."""
        from scipy.ndimage import distance_transform_edt

        x0, x1, y0, y1 = reference.grid_.extent
        grid = GridSpec.from_extent((x0 - pad, x1 + pad, y0 - pad, y1 + pad), spacing)
        seen = np.zeros(grid.shape, dtype=bool)
        r, c = np.nonzero(reference.observed_ > 0)
        centres = np.column_stack(reference.grid_.origin) + (np.column_stack([c, r]) + 0.5) * reference.grid_.resolution
        rr, cc, inside = grid.index_of(centres)
        seen[rr[inside], cc[inside]] = True
        return cls(grid, distance_transform_edt(~seen) * spacing)

    def distance_at(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance to the data of each point (inf outside the lattice), shape (n,)."""
        rows, cols, inside = self.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
        out = np.full(len(rows), np.inf)
        out[inside] = self.distance[rows[inside], cols[inside]]
        return out

    def far_points(self, distance: float = FAR_DISTANCE, max_points: int = FAR_MAX_POINTS, seed: int = 0) -> NDArray[np.float64]:
        """Lattice cell centres farther than `distance` from the data, at most `max_points` (seeded)."""
        idx = np.flatnonzero(self.distance.ravel() > distance)
        if idx.size > max_points:
            idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
        return self.grid.centres()[idx]
