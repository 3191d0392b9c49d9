"""Regular 3-D voxel grids and the occupancy map sampled on them (the 3-D :mod:`gpomap.grid`).

Conventions:

- `origin` is the map-frame position (x, y, z) of the *lower* corner (least x, y and z) of the
  first voxel; every voxel is a cube of side `resolution`.
- Arrays are indexed ``[k, j, i]`` = ``[z, y, x]``, shape ``(nz, ny, nx)``: a horizontal slice at
  one height is ``array[k]``, an ``(ny, nx)`` image with row 0 at the lowest y, exactly the 2-D
  grids' ``[row, col]`` layout, so a slice is a 2-D map.
- Voxel ``(k, j, i)`` has its centre at ``origin + ((i + 0.5) r, (j + 0.5) r, (k + 0.5) r)``.
  :meth:`VoxelSpec.centres` lists the centres in C order of ``[k, j, i]`` (x fastest), so
  ``probability.reshape(-1)`` lines up with it.
- A point on a face between two voxels belongs to the upper one (``floor``); points outside the
  grid have no voxel.
- An origin that is a multiple of the resolution puts the voxel faces where OctoMap puts its own
  (OctoMap voxel faces sit at multiples of its resolution), so a grid and an octree of the same
  resolution share voxels one for one (:meth:`VoxelSpec.from_extent` aligns so by default).

The ternary layer uses :data:`gpomap.grid.FREE` (0), :data:`~gpomap.grid.OCCUPIED` (1) and
:data:`~gpomap.grid.UNKNOWN` (-1) with the map's thresholds, as the 2-D map does, and as there
never calls occupied a voxel no ray went to (the 2-D map's ``seen_through``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap import _compiled_raycast
from gpomap.grid import DEFAULT_THRESHOLDS, ternary

__all__ = ["VoxelSpec", "VoxelMap"]


@dataclass(frozen=True)
class VoxelSpec:
    """Geometry of a regular 3-D grid.

    Parameters
    ----------
    origin : array_like of shape (3,)
        (x, y, z) of the lower corner of voxel ``[0, 0, 0]``, metres.
    resolution : float
        Voxel side, metres.
    shape : tuple of int
        ``(nz, ny, nx)``.
    """

    origin: tuple[float, float, float]
    resolution: float
    shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"voxel resolution must be a positive number, got {self.resolution}")
        origin = tuple(float(v) for v in np.asarray(self.origin, dtype=float).reshape(-1))
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise ValueError(f"voxel origin must be 3 finite numbers (x, y, z), got {self.origin}")
        shape = tuple(int(v) for v in self.shape)
        if len(shape) != 3 or min(shape) <= 0:
            raise ValueError(f"voxel shape must be 3 positive integers (nz, ny, nx), got {self.shape}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "resolution", float(self.resolution))

    @classmethod
    def from_extent(cls, lower: ArrayLike, upper: ArrayLike, resolution: float, align: bool = True) -> VoxelSpec:
        """The grid of voxels of side `resolution` covering the box from `lower` to `upper` (x, y, z).

        Parameters
        ----------
        lower, upper : array_like of shape (3,)
        resolution : float
        align : bool
            Put the origin on a multiple of `resolution` (OctoMap's voxel faces) at or below
            `lower`; otherwise the origin is `lower`.
        """
        lo = np.asarray(lower, dtype=float).reshape(3)
        hi = np.asarray(upper, dtype=float).reshape(3)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
            raise ValueError(f"voxel extent needs finite lower < upper on every axis, got {lo.tolist()} .. {hi.tolist()}")
        if align:
            lo = np.floor(lo / resolution + 1e-9) * resolution
        n = np.maximum(1, np.ceil((hi - lo) / resolution - 1e-9).astype(int))
        return cls((float(lo[0]), float(lo[1]), float(lo[2])), resolution, (int(n[2]), int(n[1]), int(n[0])))

    @property
    def n_voxels(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    @property
    def lower(self) -> NDArray[np.float64]:
        """Lower corner (x, y, z), shape (3,)."""
        return np.asarray(self.origin)

    @property
    def upper(self) -> NDArray[np.float64]:
        """Upper corner (x, y, z), shape (3,)."""
        nz, ny, nx = self.shape
        return self.lower + self.resolution * np.array([nx, ny, nz], dtype=float)

    def axis_centres(self, axis: str) -> NDArray[np.float64]:
        """Voxel-centre coordinates along ``"x"``, ``"y"`` or ``"z"``, shape (nx,), (ny,) or (nz,)."""
        a = "xyz".index(axis)
        n = self.shape[2 - a]
        return np.asarray(self.origin[a] + (np.arange(n) + 0.5) * self.resolution, dtype=np.float64)

    def centres(self) -> NDArray[np.float64]:
        """Every voxel centre, shape (nz * ny * nx, 3), in C order of ``[k, j, i]`` (x fastest)."""
        z, y, x = np.meshgrid(self.axis_centres("z"), self.axis_centres("y"), self.axis_centres("x"), indexing="ij")
        return np.column_stack([x.ravel(), y.ravel(), z.ravel()]).astype(np.float64)

    def index_of(self, points: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """Voxel indices of points (n, 3): ``k``, ``j``, ``i`` (n,) each and ``inside`` (n,).

        Indices of points outside the grid (or non-finite) are clipped to it; use `inside`.
        """
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if _compiled_raycast.ENABLED:
            return _compiled_raycast.voxel_index(p, self.lower, self.resolution, self.shape)
        with np.errstate(invalid="ignore"):
            f = np.floor((p - self.lower) / self.resolution)
        nz, ny, nx = self.shape
        size = np.array([nx, ny, nz])
        inside = np.asarray(np.isfinite(f).all(axis=1) & (f >= 0).all(axis=1) & (f < size).all(axis=1), dtype=bool)
        f = np.where(np.isfinite(f), f, 0)
        ijk = np.clip(f, 0, size - 1).astype(np.intp)
        return ijk[:, 2], ijk[:, 1], ijk[:, 0], inside

    def slice_index(self, z: float) -> int:
        """Index ``k`` of the horizontal slice holding height `z` (clipped to the grid)."""
        return int(np.clip(math.floor((z - self.origin[2]) / self.resolution), 0, self.shape[0] - 1))


@dataclass
class VoxelMap:
    """A 3-D occupancy map: probability (and optionally variance) on a :class:`VoxelSpec`.

    Parameters
    ----------
    spec : VoxelSpec
    probability : ndarray of shape (nz, ny, nx)
        Occupancy probability; 0.5 where nothing is known.
    variance : ndarray of shape (nz, ny, nx), optional
        Latent variance (a GP's), where the method has one.
    thresholds : tuple of float
        Free below the first, occupied above the second, unknown between (the ternary layer).
    info : dict
        What made the map (method, settings), written with it.
    observed : ndarray of bool, shape (nz, ny, nx), optional
        Voxels a ray crossed or ended in (None: not known, every voxel taken as observed). The
        others hold the GP's guess only: an OctoMap tree and a mesh leave them out, and the
        ternary layer never calls them occupied.
    """

    spec: VoxelSpec
    probability: NDArray[np.float64]
    variance: NDArray[np.float64] | None = None
    thresholds: tuple[float, float] = DEFAULT_THRESHOLDS
    info: dict[str, Any] = field(default_factory=dict)
    observed: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        self.probability = np.asarray(self.probability, dtype=float)
        if self.probability.shape != self.spec.shape:
            raise ValueError(f"probability has shape {self.probability.shape}; the voxel grid is {self.spec.shape}")
        if self.variance is not None:
            self.variance = np.asarray(self.variance, dtype=float)
            if self.variance.shape != self.spec.shape:
                raise ValueError(f"variance has shape {self.variance.shape}; the voxel grid is {self.spec.shape}")
        if self.observed is not None:
            self.observed = np.asarray(self.observed, dtype=bool)
            if self.observed.shape != self.spec.shape:
                raise ValueError(f"observed has shape {self.observed.shape}; the voxel grid is {self.spec.shape}")
        lo, hi = (float(t) for t in self.thresholds)
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"thresholds must satisfy 0 <= free <= occupied <= 1, got ({lo}, {hi})")
        self.thresholds = (lo, hi)

    @property
    def seen(self) -> NDArray[np.bool_]:
        """:attr:`observed`, or every voxel when it is not known, shape (nz, ny, nx)."""
        return np.ones(self.spec.shape, dtype=bool) if self.observed is None else self.observed

    @property
    def ternary(self) -> NDArray[np.int8]:
        """FREE (0) / OCCUPIED (1) / UNKNOWN (-1) per voxel, shape (nz, ny, nx); a voxel no ray
        went to is UNKNOWN where its probability is above the occupied threshold (the GP reaches
        behind surfaces, where nothing was seen)."""
        return ternary(self.probability, self.thresholds, None if self.observed is None else ~self.observed)

    def lookup(self, points: ArrayLike) -> NDArray[np.float64]:
        """Probability of the voxel holding each point (n, 3); 0.5 outside the grid. Shape (n,)."""
        k, j, i, inside = self.spec.index_of(points)
        return np.where(inside, self.probability[k, j, i], 0.5)
