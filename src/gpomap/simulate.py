"""2-D worlds of walls and a planar laser simulator.

A :class:`World` is a set of wall segments. It is built from free-standing segments and from
closed polygons; a polygon is either a *solid* obstacle (its inside is occupied) or a room
*outline* (only its edges are walls). The simulator casts beams against every wall at once with
numpy and returns :class:`~gpomap.scans.Scan` objects, so simulated data goes through exactly the
same pipeline as logged data. :func:`paper_room` rebuilds the synthetic room of the MSK-GPOM paper
(Fig. 4): about 20 x 16 units, 31 poses, 36 noiseless beams over 360 degrees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.grid import GridSpec
from gpomap.scans import Scan

#: Default sensor range for the simulated worlds: longer than any line across the paper room.
DEFAULT_MAX_RANGE: float = 30.0

# Beams x segments pairs evaluated per chunk: bounds temporary memory to a few tens of MB.
_PAIRS_PER_CHUNK: int = 1 << 20


def _as_polygon(vertices: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
        raise ValueError(f"a polygon needs at least 3 vertices given as (m, 2), got shape {v.shape}")
    # Accept an explicitly closed vertex list too: drop the repeated first vertex.
    if np.array_equal(v[0], v[-1]):
        v = v[:-1]
    return v


def _polygon_edges(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Edges of a closed polygon as segments, ndarray of shape (m, 4): x0, y0, x1, y1."""
    return np.column_stack([v, np.roll(v, -1, axis=0)])


@dataclass(frozen=True)
class World:
    """A planar world of walls.

    Parameters
    ----------
    segments : array_like of shape (s, 4) or (s, 2, 2), optional
        Free-standing walls, each ``(x0, y0, x1, y1)`` or ``((x0, y0), (x1, y1))``.
    obstacles : sequence of array_like of shape (m, 2), optional
        Solid polygons (closed implicitly): their edges are walls and their inside is occupied.
    outlines : sequence of array_like of shape (m, 2), optional
        Room outlines (closed implicitly): only their edges are walls.

    Attributes
    ----------
    walls : ndarray of shape (w, 4)
        Every wall segment, free-standing ones first, then outline edges, then obstacle edges.
    """

    segments: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    obstacles: tuple[NDArray[np.float64], ...] = ()
    outlines: tuple[NDArray[np.float64], ...] = ()
    walls: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        seg = np.asarray(self.segments, dtype=float).reshape(-1, 4)
        obstacles = tuple(_as_polygon(p) for p in self.obstacles)
        outlines = tuple(_as_polygon(p) for p in self.outlines)
        walls = np.concatenate([seg] + [_polygon_edges(p) for p in outlines + obstacles], axis=0)
        if len(walls) == 0:
            raise ValueError("a world needs at least one wall (segment, outline or obstacle)")
        if not np.isfinite(walls).all():
            raise ValueError("wall coordinates must be finite")
        object.__setattr__(self, "segments", seg)
        object.__setattr__(self, "obstacles", obstacles)
        object.__setattr__(self, "outlines", outlines)
        object.__setattr__(self, "walls", walls)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of all walls."""
        xs = self.walls[:, [0, 2]]
        ys = self.walls[:, [1, 3]]
        return (float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max()))

    def cast(self, origins: ArrayLike, angles: ArrayLike, max_range: float = DEFAULT_MAX_RANGE) -> NDArray[np.float64]:
        """Range to the first wall along each beam.

        Parameters
        ----------
        origins : array_like of shape (b, 2) or (2,)
            Beam start points (one shared point may be given as shape (2,)).
        angles : array_like of shape (b,)
            Beam directions in the world frame, radians.
        max_range : float
            Sensor range: a beam that hits nothing nearer returns exactly `max_range`.

        Returns
        -------
        ndarray of shape (b,)
            Distance along each beam to the nearest wall, at most `max_range`.
        """
        a = np.asarray(angles, dtype=float).reshape(-1)
        o = np.broadcast_to(np.asarray(origins, dtype=float), (a.size, 2))
        d = np.column_stack([np.cos(a), np.sin(a)])
        p0 = self.walls[:, :2]
        e = self.walls[:, 2:] - p0  # wall direction, (w, 2)
        out = np.full(a.size, float(max_range))
        chunk = max(1, _PAIRS_PER_CHUNK // len(self.walls))
        for lo in range(0, a.size, chunk):
            oc, dc = o[lo : lo + chunk, None, :], d[lo : lo + chunk, None, :]
            # Ray o + t d meets wall p0 + s e where (p0 - o) = t d - s e; Cramer's rule in 2-D.
            w = p0[None, :, :] - oc
            denom = dc[..., 0] * e[None, :, 1] - dc[..., 1] * e[None, :, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
                s = (w[..., 0] * dc[..., 1] - w[..., 1] * dc[..., 0]) / denom
            # A little slack on s so a beam aimed exactly at a corner cannot slip between the
            # two walls that meet there through rounding. Parallel walls (denom 0) never count.
            tol = 1e-10
            ok = (denom != 0) & (t >= 0) & (s >= -tol) & (s <= 1 + tol)
            t = np.where(ok, t, np.inf)
            out[lo : lo + chunk] = np.minimum(t.min(axis=1), max_range)
        return out

    def distance_to_walls(self, points: ArrayLike) -> NDArray[np.float64]:
        """Euclidean distance from each point to the nearest wall segment.

        Parameters
        ----------
        points : array_like of shape (n, 2)

        Returns
        -------
        ndarray of shape (n,)
        """
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        a = self.walls[:, :2]
        e = self.walls[:, 2:] - a
        ee = np.maximum((e * e).sum(axis=1), 1e-300)  # guards zero-length walls
        out = np.empty(len(p))
        chunk = max(1, _PAIRS_PER_CHUNK // len(self.walls))
        for lo in range(0, len(p), chunk):
            w = p[lo : lo + chunk, None, :] - a[None, :, :]
            # Closest point on each segment: projection clamped to the segment.
            s = np.clip((w * e[None]).sum(axis=2) / ee, 0.0, 1.0)
            r = w - s[..., None] * e[None]
            out[lo : lo + chunk] = np.sqrt((r * r).sum(axis=2).min(axis=1))
        return out

    def inside_obstacle(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether each point lies inside a solid obstacle (even-odd rule), shape (n,)."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        inside = np.zeros(len(p), dtype=bool)
        for poly in self.obstacles:
            # Only points in the polygon's bounding box can be inside it.
            lo, hi = poly.min(axis=0), poly.max(axis=0)
            box = np.flatnonzero(((p >= lo) & (p <= hi)).all(axis=1))
            if box.size == 0:
                continue
            v0, v1 = poly, np.roll(poly, -1, axis=0)
            x, y = p[box, 0:1], p[box, 1:2]
            # Count crossings of a ray to +x: edges straddling the point's y (half-open so a
            # vertex on the ray is counted once) whose crossing lies to the right of the point.
            straddle = (v0[None, :, 1] > y) != (v1[None, :, 1] > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                xc = v0[None, :, 0] + (y - v0[None, :, 1]) * (v1[None, :, 0] - v0[None, :, 0]) / (v1[None, :, 1] - v0[None, :, 1])
            crossings = (straddle & (x < xc)).sum(axis=1)
            inside[box] |= crossings % 2 == 1
        return inside

    def occupancy(self, points: ArrayLike, wall_thickness: float = 0.1) -> NDArray[np.bool_]:
        """True occupancy: within `wall_thickness / 2` of a wall, or inside a solid obstacle.

        Parameters
        ----------
        points : array_like of shape (n, 2)
        wall_thickness : float
            Walls are treated as bands of this width centred on their segments.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        if not wall_thickness >= 0:
            raise ValueError(f"wall_thickness must be non-negative, got {wall_thickness}")
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        return (self.distance_to_walls(p) <= 0.5 * wall_thickness) | self.inside_obstacle(p)

    def true_grid(self, grid: GridSpec, wall_thickness: float | None = None) -> NDArray[np.bool_]:
        """True occupancy of each cell, judged at the cell centre.

        Parameters
        ----------
        grid : GridSpec
        wall_thickness : float, optional
            Defaults to the grid resolution, so every cell whose centre is within half a cell of
            a wall is occupied (a wall crossing a cell near its corner may still leave it free).

        Returns
        -------
        ndarray of bool, shape (ny, nx)
            Row 0 at the lowest y, as everywhere in gpomap.
        """
        thick = grid.resolution if wall_thickness is None else float(wall_thickness)
        return self.occupancy(grid.centres(), thick).reshape(grid.shape)


def beam_angles(n_beams: int, fov: float = 2 * np.pi) -> NDArray[np.float64]:
    """Beam angles relative to the sensor heading.

    Parameters
    ----------
    n_beams : int
    fov : float
        Field of view, radians. For a full circle (2 pi) the beams are evenly spaced without
        repeating the endpoint: ``2 pi k / n``; otherwise ``linspace(-fov / 2, fov / 2, n)``.

    Returns
    -------
    ndarray of shape (n_beams,)
    """
    if n_beams <= 0:
        raise ValueError(f"n_beams must be positive, got {n_beams}")
    if not 0 < fov <= 2 * np.pi + 1e-12:
        raise ValueError(f"fov must be in (0, 2 pi], got {fov}")
    if np.isclose(fov, 2 * np.pi):
        return 2 * np.pi * np.arange(n_beams) / n_beams
    if n_beams == 1:
        return np.zeros(1)
    return np.linspace(-fov / 2, fov / 2, n_beams)


def simulate_scans(
    world: World,
    poses: ArrayLike,
    n_beams: int,
    fov: float = 2 * np.pi,
    max_range: float = DEFAULT_MAX_RANGE,
    noise_std: float = 0.0,
    seed: int | np.random.Generator | None = None,
) -> list[Scan]:
    """Simulate a planar laser at each pose.

    Parameters
    ----------
    world : World
    poses : array_like of shape (k, 3)
        Sensor poses (x, y, theta).
    n_beams : int
        Beams per scan.
    fov : float
        Field of view in radians (see :func:`beam_angles`).
    max_range : float
        Beams that hit nothing nearer read exactly `max_range` (a no-return).
    noise_std : float
        Standard deviation of additive Gaussian range noise on beams that hit a wall. No-return
        beams stay at `max_range`; noisy ranges are kept positive, and a hit pushed to or beyond
        `max_range` becomes a no-return, as a real sensor would report it.
    seed : int or numpy Generator, optional
        Seeds the noise; the same seed gives the same scans.

    Returns
    -------
    list of Scan
        One per pose, with ``meta={"simulated": True}``.
    """
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poses must have shape (k, 3), got {p.shape}")
    if not noise_std >= 0:
        raise ValueError(f"noise_std must be non-negative, got {noise_std}")
    rel = beam_angles(n_beams, fov)
    k = len(p)
    world_angles = (p[:, 2:3] + rel[None, :]).ravel()
    origins = np.repeat(p[:, :2], n_beams, axis=0)
    ranges = world.cast(origins, world_angles, max_range).reshape(k, n_beams)
    if noise_std > 0:
        rng = np.random.default_rng(seed)
        noise = rng.normal(0.0, noise_std, size=ranges.shape)
        hit = ranges < max_range
        # Floor at a small positive range: a reading <= 0 would be an invalid one.
        ranges = np.where(hit, np.maximum(ranges + noise, 1e-6), ranges)
    return [Scan(p[i], rel.copy(), ranges[i], max_range, meta={"simulated": True}) for i in range(k)]


# The paper room (Fig. 4 of the paper): an outer 20 x 16 room split by a partition with a
# doorway, a short stub wall and two box obstacles. Coordinates in the paper's arbitrary units.
_ROOM_OUTLINE = [(0.0, 0.0), (20.0, 0.0), (20.0, 16.0), (0.0, 16.0)]
_ROOM_WALLS = [
    (12.0, 0.0, 12.0, 6.0),  # partition, lower part
    (12.0, 9.0, 12.0, 16.0),  # partition, upper part: the doorway is y in (6, 9)
    (0.0, 11.0, 4.5, 11.0),  # stub wall from the left side
]
_ROOM_BOXES = [
    [(4.0, 3.0), (6.5, 3.0), (6.5, 5.5), (4.0, 5.5)],
    [(15.5, 11.0), (17.5, 11.0), (17.5, 13.0), (15.5, 13.0)],
]
# The robot tours the left room clockwise, goes through the doorway, loops round the right room.
_ROOM_WAYPOINTS = [
    (2.0, 2.0),
    (2.0, 8.5),
    (7.0, 8.5),
    (7.0, 13.5),
    (2.5, 13.5),
    (9.5, 13.0),
    (9.5, 7.5),
    (14.5, 7.5),
    (14.5, 2.5),
    (18.0, 2.5),
    (18.5, 9.0),
    (18.5, 14.5),
    (13.5, 14.5),
]


def _sample_path(waypoints: Sequence[tuple[float, float]], n: int) -> NDArray[np.float64]:
    """`n` poses evenly spaced by arc length along a polyline, heading along the path."""
    w = np.asarray(waypoints, dtype=float)
    seg = np.diff(w, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    s = np.linspace(0.0, cum[-1], n)
    xy = np.column_stack([np.interp(s, cum, w[:, 0]), np.interp(s, cum, w[:, 1])])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    theta = np.arctan2(seg[i, 1], seg[i, 0])
    return np.column_stack([xy, theta])


def paper_room() -> tuple[World, NDArray[np.float64]]:
    """The synthetic room of the paper (Fig. 4) and the robot's 31 poses.

    The room is a closed 20 x 16 rectangle (lower-left corner at the origin) with a vertical
    partition at x = 12 that has a doorway for y in (6, 9), a stub wall along y = 11 from the left
    side to x = 4.5, and two solid boxes. The poses follow a tour of both rooms; every one is at
    least 1 unit from any wall. Use with 36 beams over 360 degrees (:func:`paper_room_scans`).

    Returns
    -------
    world : World
    poses : ndarray of shape (31, 3)
        (x, y, theta), heading along the path.
    """
    world = World(
        segments=np.asarray(_ROOM_WALLS, dtype=float),
        obstacles=tuple(np.asarray(box, dtype=float) for box in _ROOM_BOXES),
        outlines=(np.asarray(_ROOM_OUTLINE, dtype=float),),
    )
    return world, _sample_path(_ROOM_WAYPOINTS, 31)


def paper_room_scans(n_beams: int = 36, noise_std: float = 0.0, seed: int | None = 0) -> list[Scan]:
    """Scans of :func:`paper_room`: 36 beams over 360 degrees at each of its 31 poses.

    Parameters
    ----------
    n_beams : int
    noise_std : float
        Gaussian range noise (the paper's data is noiseless).
    seed : int, optional

    Returns
    -------
    list of Scan
        31 scans; the room is closed, so every beam hits a wall.
    """
    world, poses = paper_room()
    return simulate_scans(world, poses, n_beams, 2 * np.pi, DEFAULT_MAX_RANGE, noise_std, seed)
