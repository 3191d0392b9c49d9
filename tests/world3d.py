"""A small 3-D world for the tests: a closed room with a pillar, and a lidar ray-cast inside it.

Exact ray-box intersections (the slab method), so the hits lie on the true surfaces and the tests
can judge a 3-D map against the geometry itself.
"""

from __future__ import annotations

import numpy as np

from gpomap.clouds import CloudScan

ROOM = (np.array([0.0, 0.0, 0.0]), np.array([6.0, 4.0, 2.5]))
PILLAR = (np.array([3.5, 1.5, 0.0]), np.array([4.3, 2.3, 2.5]))


def _slab(origin, dirs, lo, hi):
    """Entry and exit distances of rays against an axis-aligned box, each of shape (n,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / dirs
        t2 = (hi - origin) / dirs
    return np.nanmax(np.minimum(t1, t2), axis=1), np.nanmin(np.maximum(t1, t2), axis=1)


def occupied(points, thickness=0.0):
    """Whether points lie within `thickness` of a surface (outside the room or inside the pillar)."""
    p = np.asarray(points, float)
    lo, hi = ROOM
    outside = np.any((p < lo + thickness) | (p > hi - thickness), axis=1)
    plo, phi = PILLAR
    in_pillar = np.all((p > plo - thickness) & (p < phi + thickness), axis=1)
    return outside | in_pillar


def lidar_clouds(origins, n_rays=600, max_range=4.0, seed=0):
    """One cloud per origin: rays uniform on the sphere, endpoints on the first surface.

    Rays longer than `max_range` are no-return rays ending at it.
    """
    rng = np.random.default_rng(seed)
    clouds = []
    for o in np.asarray(origins, float):
        d = rng.normal(size=(n_rays, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        _, t_room = _slab(o, d, *ROOM)  # leaving the room from inside
        t_in, t_out = _slab(o, d, *PILLAR)
        t = np.where((t_out >= np.maximum(t_in, 0)) & (t_in > 0), np.minimum(t_in, t_room), t_room)
        hit = t <= max_range
        t = np.minimum(t, max_range)
        clouds.append(CloudScan(o, o + t[:, None] * d, hit, max_range=max_range))
    return clouds


ORIGINS = np.array([[1.0, 1.0, 1.2], [2.0, 3.0, 1.0], [5.0, 1.0, 1.4], [5.2, 3.2, 1.1], [1.5, 2.2, 0.8], [2.8, 0.7, 1.6]])
