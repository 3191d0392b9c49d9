"""A 3-D scene of solid axis-aligned boxes: what is inside, how far, and where a ray first meets one.

A :class:`Scene` is a set of boxes (walls, floors, table tops and legs, shelf boards); its occupied
space is their union. It answers the questions the simulated sensor and the truth ask of it:
points inside (:meth:`Scene.contains`), distance to the nearest box (:meth:`Scene.distance`), both
at every cell of a voxel grid (:meth:`Scene.rasterise`), and the exact distance along rays to the
first box (:meth:`Scene.cast`, the slab method).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.voxels import VoxelSpec

__all__ = ["Scene", "BOUNDARY_RADIUS"]

#: Boundary points: within this distance (m) of a box (inside one included), as in 2-D.
BOUNDARY_RADIUS: float = 0.1

# Rays x boxes pairs per chunk of the ray caster: bounds its temporary arrays to tens of MB.
_PAIRS_PER_CHUNK: int = 1 << 20


def _boxes(lower: ArrayLike, upper: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least and greatest corners as arrays of shape (n, 3), checked: at least one box, finite, lower < upper."""
    lo = np.asarray(lower, dtype=float).reshape(-1, 3)
    hi = np.asarray(upper, dtype=float).reshape(-1, 3)
    if lo.shape != hi.shape or len(lo) == 0:
        raise ValueError(f"a scene needs at least one box, lower and upper of shape (n, 3), got {lo.shape} and {hi.shape}")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
        raise ValueError("every box needs finite corners with lower < upper on each axis")
    return lo, hi


@dataclass(frozen=True)
class Scene:
    """Solid axis-aligned boxes; occupied space is their union.

    Parameters
    ----------
    lower, upper : array_like of shape (n, 3)
        Each box's least and greatest corner (x, y, z), metres.
    names : tuple of str, optional
        What each box is (for figures and messages).
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    names: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        lo, hi = _boxes(self.lower, self.upper)
        names = tuple(self.names) if self.names else tuple(f"box {i}" for i in range(len(lo)))
        if len(names) != len(lo):
            raise ValueError(f"{len(names)} names for {len(lo)} boxes")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "names", names)

    @classmethod
    def from_boxes(cls, boxes: Sequence[tuple[str, ArrayLike, ArrayLike]], offset: ArrayLike = (0.0, 0.0, 0.0)) -> Scene:
        """A scene from ``(name, lower, upper)`` triples, every box moved by `offset` (x, y, z)."""
        shift = np.asarray(offset, dtype=float).reshape(3)
        return cls(
            np.array([np.asarray(lo, dtype=float) for _, lo, _ in boxes]) + shift,
            np.array([np.asarray(hi, dtype=float) for _, _, hi in boxes]) + shift,
            tuple(name for name, _, _ in boxes),
        )

    @property
    def n_boxes(self) -> int:
        """Number of boxes."""
        return len(self.lower)

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Least and greatest corner of all boxes, shape (3,) each."""
        return self.lower.min(axis=0), self.upper.max(axis=0)

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether each point (n, 3) lies inside a box (faces included), shape (n,)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        out = np.zeros(len(p), dtype=bool)
        for lo, hi in zip(self.lower, self.upper):
            out |= np.all((p >= lo) & (p <= hi), axis=1)
        return out

    def distance(self, points: ArrayLike) -> NDArray[np.float64]:
        """Euclidean distance (m) from each point (n, 3) to the nearest box, 0 inside one; shape (n,)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        best = np.full(len(p), np.inf)
        for lo, hi in zip(self.lower, self.upper):
            gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
            np.minimum(best, np.sqrt(np.einsum("ij,ij->i", gap, gap)), out=best)
        return best

    def rasterise(self, spec: VoxelSpec, radius: float = BOUNDARY_RADIUS) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """:meth:`contains` and ``distance <= radius`` at every cell centre of `spec`, box by box.

        Returns
        -------
        inside, near : ndarray of bool, shape ``spec.shape`` each
        """
        centres = [spec.axis_centres(a) for a in "xyz"]
        inside = np.zeros(spec.shape, dtype=bool)
        near = np.zeros(spec.shape, dtype=bool)
        for lo, hi in zip(self.lower, self.upper):
            # The centres within the box grown by `radius`, per axis; inside and near there.
            span = [np.flatnonzero((c >= lo[a] - radius - 1e-9) & (c <= hi[a] + radius + 1e-9)) for a, c in enumerate(centres)]
            if any(s.size == 0 for s in span):
                continue
            block = tuple(slice(int(s[0]), int(s[-1]) + 1) for s in span[::-1])
            gap = [np.maximum(np.maximum(lo[a] - centres[a][span[a]], centres[a][span[a]] - hi[a]), 0.0) for a in range(3)]
            d2 = gap[2][:, None, None] ** 2 + gap[1][None, :, None] ** 2 + gap[0][None, None, :] ** 2
            inside[block] |= d2 == 0.0
            near[block] |= d2 <= radius**2 + 1e-12
        return inside, near

    def cast(self, origins: ArrayLike, directions: ArrayLike, max_range: float = np.inf) -> NDArray[np.float64]:
        """Distance along each ray to the first box it meets (the slab method), exact.

        Parameters
        ----------
        origins : array_like of shape (n, 3) or (3,)
            Ray starts (one for all rays, or one each).
        directions : array_like of shape (n, 3)
            Unit directions.
        max_range : float
            Boxes farther than this are not met.

        Returns
        -------
        ndarray of shape (n,)
            The distance (0 for a ray starting inside a box), ``inf`` where no box lies within
            `max_range`.
        """
        d = np.asarray(directions, dtype=float).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
        out = np.full(len(d), np.inf)
        per = max(1, _PAIRS_PER_CHUNK // self.n_boxes)
        for s in range(0, len(d), per):
            out[s : s + per] = self._cast_chunk(o[s : s + per], d[s : s + per])
        out[out > max_range] = np.inf
        return out

    def _cast_chunk(self, o: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
        o3, d3 = o[:, None, :], d[:, None, :]
        lo, hi = self.lower[None], self.upper[None]
        parallel = d3 == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - o3) / d3
            t2 = (hi - o3) / d3
        # A ray parallel to a slab is inside it for every t, or for none.
        inside = (o3 >= lo) & (o3 <= hi)
        near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        t_in, t_out = near.max(axis=2), far.min(axis=2)
        meets = (t_in <= t_out) & (t_out >= 0.0)
        t = np.where(meets, np.maximum(t_in, 0.0), np.inf)
        return np.asarray(t.min(axis=1), dtype=float)
