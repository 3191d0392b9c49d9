"""The truth a 3-D map is scored against: the lattice points some ray came near, labelled by the boxes.

As the 2-D rule of :mod:`gpomap.truth`: the points of a fine lattice (:data:`TRUTH_LATTICE`, a
quarter of a 0.1 m voxel) whose cell lies within :data:`OBSERVED_RADIUS` (half a 0.1 m voxel) of a
lattice cell some ray passed through (from the sensor to its end point,
:func:`gpomap.raycast.traverse`) are scored, each once (:func:`truth_points`); a point is occupied
when it lies inside a box; "boundary" points lie within
:data:`~gpomap.simulate3d.scene.BOUNDARY_RADIUS` of a box. Space no ray came near is never scored,
and a surface scores as thick as it is: a map that smears surfaces over free space pays for it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.simulate3d.scene import BOUNDARY_RADIUS, Scene
from gpomap.voxels import VoxelSpec

__all__ = ["TruthVolume", "truth_points", "observed_cells", "TRUTH_LATTICE", "OBSERVED_RADIUS"]

#: Side (m) of the truth lattice: 64 points per 0.1 m voxel, each nested in one voxel of a
#: grid whose faces lie on multiples of 0.1 m (OctoMap's and gpomap's voxel maps).
TRUTH_LATTICE: float = 0.025
#: A truth point is scored if its lattice cell lies this close (m, centre to centre) to a cell a
#: ray passed through: half a 0.1 m voxel, as the 2-D rule takes half a 0.05 m cell.
OBSERVED_RADIUS: float = 0.05


@dataclass(frozen=True)
class TruthVolume:
    """The scored points of a scene for some rays (:func:`truth_points`).

    Attributes
    ----------
    points : ndarray of shape (n, 3)
        Lattice points.
    occupied : ndarray of bool, shape (n,)
        Inside a box.
    boundary : ndarray of bool, shape (n,)
        Within :data:`BOUNDARY_RADIUS` of a box.
    n_observed : int
        Scored points before any subsampling.
    """

    points: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    boundary: NDArray[np.bool_]
    n_observed: int


def observed_cells(clouds: Sequence[CloudScan], spec: VoxelSpec, radius: float = OBSERVED_RADIUS) -> NDArray[np.bool_]:
    """Cells of `spec` (a VoxelSpec) within `radius` (centre to centre) of a cell some ray of
    `clouds` passed through, from its sensor to its end point (hits and no-return rays alike),
    shape ``spec.shape``."""
    from scipy.ndimage import binary_dilation

    from gpomap.raycast import traverse

    shape = spec.shape
    crossed = np.zeros(shape, dtype=bool)
    for c in clouds:
        valid = c.valid()
        if not valid.any():
            continue
        _, k, j, i = traverse(spec, np.broadcast_to(c.origin, (int(valid.sum()), 3)), c.points[valid])
        crossed[k, j, i] = True
    r = int(np.floor(radius / spec.resolution + 1e-9))
    if r == 0:
        return crossed
    g = np.arange(-r, r + 1)
    ball = (g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2) * spec.resolution**2 <= radius**2 + 1e-12
    return np.asarray(binary_dilation(crossed, structure=ball))


def truth_points(
    scene: Scene,
    clouds: Sequence[CloudScan],
    lattice: float = TRUTH_LATTICE,
    radius: float = OBSERVED_RADIUS,
    boundary: float = BOUNDARY_RADIUS,
    max_points: int | None = None,
    seed: int = 0,
) -> TruthVolume:
    """The lattice points of `scene` that `clouds` observed, labelled by the boxes.

    Parameters
    ----------
    scene : Scene
    clouds : sequence of CloudScan
    lattice : float
        Lattice side (m); its cells' faces lie on multiples of it, so each point nests in one voxel
        of any grid whose faces lie on multiples of a multiple of `lattice`.
    radius : float
        See :func:`observed_cells`.
    boundary : float
        See :attr:`TruthVolume.boundary`.
    max_points : int, optional
        Keep at most this many, drawn uniformly (seeded).
    seed : int

    Returns
    -------
    TruthVolume
    """
    from gpomap.clouds import clouds_extent

    lo, hi = clouds_extent(clouds)
    spec = VoxelSpec.from_extent(lo - radius - lattice, hi + radius + lattice, lattice)
    seen = observed_cells(clouds, spec, radius).reshape(-1)
    flat = np.flatnonzero(seen)
    n_observed = len(flat)
    if max_points is not None and n_observed > max_points:
        flat = np.sort(np.random.default_rng(seed).choice(flat, max_points, replace=False))
    occupied, near = scene.rasterise(spec, boundary)
    _, ny, nx = spec.shape
    k, rest = np.divmod(flat, ny * nx)
    j, i = np.divmod(rest, nx)
    points = spec.lower + (np.column_stack([i, j, k]) + 0.5) * lattice
    return TruthVolume(points, occupied.reshape(-1)[flat], near.reshape(-1)[flat], n_observed)
