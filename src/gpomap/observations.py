"""From beams to labelled points: free samples along each beam and the hits at their ends.

A beam that returned says two things: the space between the sensor and the end point is free,
and something is at the end point. A no-return beam (range at or beyond the sensor's maximum)
says only the first, and only up to where we trust it (`no_return_cap`).

The same holds for the rays of a 3-D point cloud (:class:`~gpomap.clouds.CloudScan`): one ray
from the sensor origin to each endpoint, a hit or a no-return ray. Planar scans and clouds go
through one sampler (:func:`ray_free_points`), in their own dimension.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from gpomap import _compiled_clearance, _compiled_clouds, _compiled_raycast
from gpomap.clouds import CloudScan
from gpomap.config import MapConfig
from gpomap.errors import EmptyDataError
from gpomap.lattice import box_index, box_shape, column_bounds, in_box, rows
from gpomap.scans import Scan, beyond_range, usable_ranges

#: What the map is made from: planar scans (2-D) or point clouds (3-D), one kind at a time.
ScanData = Sequence[Scan | CloudScan]


@dataclass(frozen=True)
class Observations:
    """Labelled points from a set of scans.

    Attributes
    ----------
    points : ndarray of shape (n, d)
        Map-frame positions (d = 2 for planar scans, 3 for point clouds).
    occupied : ndarray of bool, shape (n,)
        True for hits, False for free samples.
    scan_index : ndarray of int, shape (n,)
        Which scan (position in the input sequence) each point came from (int32 from scans: a
        whole log has tens of millions of points).
    n_invalid : int
        Readings dropped as NaN, inf or non-positive (rays with a non-finite endpoint, or one
        at the sensor origin, for clouds).
    n_no_return : int
        Valid readings at or beyond max range (free space only, never a hit).
    n_cleared : int
        Free samples dropped for lying too close to a hit (``free_clearance``).
    weight : ndarray of int32, shape (n,), optional
        How many samples each point stands for, where a scan's free samples were merged by cube
        (:func:`merged_ray_free_points`); None: one each.
    """

    points: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    scan_index: NDArray[np.integer[Any]]
    n_invalid: int = 0
    n_no_return: int = 0
    n_cleared: int = 0
    weight: NDArray[np.int32] | None = None

    @property
    def dim(self) -> int:
        """Number of spatial dimensions of the points."""
        return int(self.points.shape[1])

    @property
    def n_free(self) -> int:
        """Number of free points."""
        return int((~self.occupied).sum())

    @property
    def n_occupied(self) -> int:
        """Number of occupied points (hits)."""
        return int(self.occupied.sum())

    @property
    def labels(self) -> NDArray[np.float64]:
        """GP targets: +1 for occupied, -1 for free, ndarray of shape (n,)."""
        return np.where(self.occupied, 1.0, -1.0)

    @classmethod
    def joined(cls, parts: Sequence[Observations], dim: int) -> Observations:
        """The points of `parts` one after another, with their labels, scans and weights (none
        unless every part has them); empty points of `dim` dimensions without parts."""
        if not parts:
            return cls(np.zeros((0, dim)), np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int32))
        weights = [p.weight for p in parts]
        return cls(
            np.concatenate([p.points for p in parts]),
            np.concatenate([p.occupied for p in parts]),
            np.concatenate([p.scan_index for p in parts]),
            weight=None if any(w is None for w in weights) else np.concatenate(weights),  # type: ignore[arg-type]
        )

    def selected(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> Observations:
        """The points `keep` selects (a mask of shape (n,) or indices), with their labels, scans
        and weights; the reading counts kept."""
        return dataclasses.replace(
            self,
            points=rows(self.points, keep),
            occupied=self.occupied[keep],
            scan_index=self.scan_index[keep],
            weight=None if self.weight is None else self.weight[keep],
        )


def beam_free_points(
    origins: NDArray[np.float64],
    angles: NDArray[np.float64],
    lengths: NDArray[np.float64],
    step: float,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Points every `step` along planar beams, from `step` out to at most `lengths`.

    Parameters
    ----------
    origins : ndarray of shape (b, 2)
        Beam start points.
    angles : ndarray of shape (b,)
        Beam directions in the map frame, radians.
    lengths : ndarray of shape (b,)
        How far along each beam free points may go (inclusive).
    step : float
        Spacing of the samples along a beam.

    Returns
    -------
    points : ndarray of shape (m, 2)
    beam : ndarray of int, shape (m,)
        Index of the beam each point lies on.
    """
    a = np.asarray(angles, dtype=float)
    return ray_free_points(origins, np.column_stack([np.cos(a), np.sin(a)]), lengths, step)


def sample_counts(lengths: ArrayLike, step: float) -> NDArray[np.intp]:
    """How many free samples each ray holds: those at ``step, 2 step, ...`` up to its length,
    shape (b,) of `lengths` (b,); a negative length holds none.

    A tiny slack keeps a sample that lands exactly on the limit despite rounding."""
    return np.floor(np.maximum(np.asarray(lengths, dtype=float), 0.0) / step + 1e-9).astype(np.intp)


def ray_free_points(
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    lengths: NDArray[np.float64],
    step: float,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Points every `step` along rays in any dimension, from `step` out to at most `lengths`.

    Parameters
    ----------
    origins : ndarray of shape (b, d)
        Ray start points.
    directions : ndarray of shape (b, d)
        Unit direction of each ray.
    lengths : ndarray of shape (b,)
        How far along each ray free points may go (inclusive).
    step : float
        Spacing of the samples along a ray.

    Returns
    -------
    points : ndarray of shape (m, d)
    ray : ndarray of int, shape (m,)
        Index of the ray each point lies on.
    """
    if not step > 0:
        raise ValueError(f"free-point step must be positive, got {step}")
    lengths = np.maximum(np.asarray(lengths, dtype=float), 0.0)
    counts = sample_counts(lengths, step)
    if _compiled_raycast.ENABLED:
        return _compiled_raycast.free_samples(np.asarray(origins, dtype=float), np.asarray(directions, dtype=float), counts, step)
    total = int(counts.sum())
    ray = np.repeat(np.arange(lengths.size, dtype=np.intp), counts)
    # Position of each sample within its ray: 1, 2, ..., count.
    starts = np.cumsum(counts) - counts
    k = np.arange(total, dtype=np.intp) - np.repeat(starts, counts) + 1
    dist = k * step
    u = np.asarray(directions, dtype=float)[ray]
    o = np.asarray(origins, dtype=float)[ray]
    return o + dist[:, None] * u, ray


def merge_by_cube(
    points: NDArray[np.float64], cube: float, reference: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """The first of `points` in each cube of side `cube` (a lattice through `reference`), in
    their order, and how many of them fell in that cube.

    Parameters
    ----------
    points : ndarray of shape (m, d)
    cube : float
    reference : ndarray of shape (d,)

    Returns
    -------
    points : ndarray of shape (u, d)
    weight : ndarray of int32, shape (u,)
    """
    index = np.floor((points - reference) / cube).astype(np.int64)
    _, first, inverse = np.unique(index, axis=0, return_index=True, return_inverse=True)
    weight = np.bincount(inverse.ravel(), minlength=first.size)
    order = np.argsort(first)
    return rows(points, first[order]), weight[order].astype(np.int32)


#: Fewest free samples a scan must make for :func:`merged_ray_free_points` to merge them: a depth
#: frame's (millions, its rays crowding near the camera). Below it the exact samples cost little,
#: and merged they moved the maps of sparse lidar scans more than those of depth frames
#: (docs/3d.md, "Free samples merged by cube").
MERGE_MIN_SAMPLES: int = 1 << 20


def merged_ray_free_points(
    origins: NDArray[np.float64], directions: NDArray[np.float64], lengths: NDArray[np.float64], step: float, cube: float
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """:func:`ray_free_points` of one scan's rays merged by cube (:func:`merge_by_cube`, on a
    lattice through the first ray's origin): each kept point stands for the samples in its cube.

    With a cube of at most ``step / sqrt(d)``, one ray's own samples never share a cube: only where
    rays crowd (a depth camera's, near the sensor) are samples merged. A scan of fewer than
    :data:`MERGE_MIN_SAMPLES` samples, and rays reaching over ``2**20 - 1`` cubes, keep every
    sample (each of weight 1).

    Parameters
    ----------
    origins, directions, lengths, step
        As :func:`ray_free_points`'.
    cube : float
        Side of the cubes, metres.

    Returns
    -------
    points : ndarray of shape (u, d)
    weight : ndarray of int32, shape (u,)
    """
    lengths = np.maximum(np.asarray(lengths, dtype=float), 0.0)
    origins = np.broadcast_to(np.asarray(origins, dtype=float), np.shape(directions))
    counts = sample_counts(lengths, step)
    few = lengths.size == 0 or int(counts.sum()) < MERGE_MIN_SAMPLES
    if few or float(lengths.max()) / cube >= _compiled_raycast._CUBE_OFFSET - 1:
        points, _ = ray_free_points(origins, directions, lengths, step)
        return points, np.ones(points.shape[0], dtype=np.int32)
    if _compiled_raycast.ENABLED:
        return _compiled_raycast.merged_free_samples(origins, np.asarray(directions, dtype=float), counts, step, cube)
    points, _ = ray_free_points(origins, directions, lengths, step)
    return merge_by_cube(points, cube, origins[0])


#: Most boxes of the lattice :func:`free_near_hits` lays over the points (its distance
#: transform holds 8 bytes per box, and as much again while it runs) ...
MAX_CLEARANCE_BOXES: int = 4_000_000
#: ... and most boxes per clearance, by dimension: finer boxes leave a thinner band of points to
#: ask the tree about (about 2 sqrt(d) boxes wide round the clearance's distance), but the
#: distance transform grows with the cube in 3-D, so voxel maps take coarser boxes
#: (docs/choices.md, "Measured for the code").
CLEARANCE_SUBDIVISIONS: dict[int, int] = {2: 10, 3: 2}


def _subdivisions(span: NDArray[np.float64], clearance: float) -> int:
    """Boxes per clearance for a lattice over `span` (d,) metres within the box budget; 0 if none fits."""
    for k in range(CLEARANCE_SUBDIVISIONS.get(span.size, 2), 0, -1):
        if math.prod(float(v) for v in np.floor(span * (k / clearance)) + 2) <= MAX_CLEARANCE_BOXES:
            return k
    return 0


def free_near_hits(points: NDArray[np.float64], occupied: NDArray[np.bool_], clearance: float) -> NDArray[np.bool_]:
    """Which points are free and closer than `clearance` to a hit, ndarray of bool, shape (n,).

    A beam that grazes a wall at a shallow angle leaves free samples centimetres from the wall's
    surface; taken as evidence they mark the wall itself free, and a later scan's hit on that wall
    is then predicted free with confidence. Space this close to a surface is what the range and
    pose errors blur anyway, so such samples are better dropped than trusted.

    A compiled pass over boxes of hits (:mod:`gpomap._compiled_clearance`, when numba is there
    and its table of boxes fits :data:`MAX_CLEARANCE_BOXES`); else a distance transform over a
    lattice of boxes settles most samples and a k-d tree the rest. Both give the same answer.

    Parameters
    ----------
    points : ndarray of shape (n, d)
        Any dimension (planar points, or 3-D cloud samples).
    occupied : ndarray of bool, shape (n,)
    clearance : float
        Metres; 0 marks nothing.
    """
    out = np.zeros(occupied.shape, dtype=bool)
    if clearance <= 0 or not occupied.any() or occupied.all():
        return out
    points = np.asarray(points, dtype=float)
    if _compiled_clearance.ENABLED:
        # Every point handed over, the hits skipped: no copy of the free ones (most of a block).
        near = _compiled_clearance.near_hits(points, rows(points, occupied), clearance, MAX_CLEARANCE_BOXES, skip=occupied)
        if near is not None:
            return near
    free = np.flatnonzero(~occupied)
    # Boxes of side s = clearance / k: a point is within sqrt(d) s / 2 of its box's centre, so a
    # free point whose box centre is D boxes from the nearest hit box's centre is within
    # (D + sqrt(d)) s of a hit and farther than (D - sqrt(d)) s from every hit. Points sure
    # either way are settled by the distance transform; only the band between goes to the tree.
    dim = points.shape[1]
    lo, hi = column_bounds(points)
    k = _subdivisions(hi - lo, clearance)
    if k:
        shape = box_shape(lo, hi, k / clearance)
        flat = box_index(points, lo, k / clearance, shape)
        no_hit = np.ones(shape, dtype=bool)
        no_hit.ravel()[flat[occupied]] = False
        boxes_away = distance_transform_edt(no_hit).ravel()[flat[free]]
        diagonal = math.sqrt(dim)  # two half diagonals, in boxes
        # With a margin either way: a point on a box border may have been floored into either box.
        out[free[boxes_away + diagonal < k - 1e-6]] = True
        candidates = free[np.abs(boxes_away - k) <= diagonal + 1e-6]
    else:
        candidates = free  # a sparse, very wide map: ask the tree about every free point
    if candidates.size:
        dist, _ = cKDTree(rows(points, occupied)).query(rows(points, candidates), distance_upper_bound=clearance)
        out[candidates[dist < clearance]] = True
    return out


@dataclass(frozen=True)
class Rays:
    """The usable rays of one scan, in its own dimension, ready to be sampled.

    Attributes
    ----------
    origin : ndarray of shape (d,)
        Sensor position.
    directions : ndarray of shape (b, d)
        Unit direction of each valid ray.
    lengths : ndarray of shape (b,)
        Distance to each ray's endpoint (a no-return ray's recorded range).
    ends : ndarray of shape (b, d)
        Each ray's endpoint.
    hit : ndarray of bool, shape (b,)
        True where the ray ended on a surface, False for a no-return ray.
    no_return_limit : float
        Farthest a no-return ray is trusted by default (the planar scan's max range; infinite
        for a cloud, whose no-return endpoints the reader placed at the sensor's range).
    n_invalid : int
        Readings that gave no ray.
    """

    origin: NDArray[np.float64]
    directions: NDArray[np.float64]
    lengths: NDArray[np.float64]
    ends: NDArray[np.float64]
    hit: NDArray[np.bool_]
    no_return_limit: float
    n_invalid: int

    @classmethod
    def of(cls, scan: Scan | CloudScan) -> Rays:
        """The rays of a planar scan or of a point cloud."""
        if isinstance(scan, CloudScan):
            valid = scan.valid()
            hit = np.asarray(scan.hit, dtype=bool)[valid]
            made = _compiled_clouds.ray_geometry(scan.points, scan.origin, valid) if _compiled_clouds.ENABLED else None
            if made is None:
                ends = rows(scan.points, valid)
                vec = ends - scan.origin
                length = np.sqrt((vec * vec).sum(axis=1))
                made = ends, vec / length[:, None], length
            ends, directions, length = made
            return cls(scan.origin, directions, length, ends, hit, np.inf, int((~valid).sum()))
        # Scan.valid's, endpoints' and no_return's numbers, each worked out once: a fit asks for
        # every scan's rays in several passes.
        valid = scan.valid()
        r = scan.ranges[valid]
        directions, ends = _beam_geometry(scan.pose[0], scan.pose[1], scan.pose[2] + scan.angles[valid], r)
        return cls(
            scan.pose[:2],
            directions,
            r,
            ends,
            ~beyond_range(r, scan.max_range),
            scan.max_range,
            int(valid.size - np.count_nonzero(valid)),
        )

    @property
    def n_no_return(self) -> int:
        """Rays that gave no return."""
        return int(self.hit.size - np.count_nonzero(self.hit))

    def free_lengths(self, hit_margin: float, no_return_cap: float | None) -> NDArray[np.float64]:
        """How far along each ray free space is taken: `hit_margin` short of a hit; a no-return
        ray to `no_return_cap` (None: to its default limit), never beyond its recorded range."""
        cap = self.no_return_limit if no_return_cap is None else float(no_return_cap)
        return np.where(self.hit, self.lengths - hit_margin, np.minimum(np.minimum(cap, self.no_return_limit), self.lengths))


def _beam_geometry(
    x: float | NDArray[np.float64], y: float | NDArray[np.float64], heading: NDArray[np.float64], r: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit directions (b, 2) and endpoints (b, 2) of planar beams from (`x`, `y`) at world angles
    `heading` (b,) and ranges `r` (b,). Directions from the angles (not from the endpoints) keep
    the planar samples exact."""
    cos, sin = np.cos(heading), np.sin(heading)
    return np.column_stack([cos, sin]), np.column_stack([x + r * cos, y + r * sin])


@dataclass(frozen=True)
class PlanarBeams:
    """The usable beams of many planar scans at once: :meth:`Rays.of` of each scan, joined in order.

    Attributes
    ----------
    origins, directions, ends : ndarray of shape (b, 2)
        Each beam's sensor position, unit direction and endpoint.
    lengths : ndarray of shape (b,)
    hit : ndarray of bool, shape (b,)
    scan : ndarray of int, shape (b,)
        The place of each beam's scan in the scans given, non-decreasing.
    """

    origins: NDArray[np.float64]
    directions: NDArray[np.float64]
    lengths: NDArray[np.float64]
    ends: NDArray[np.float64]
    hit: NDArray[np.bool_]
    scan: NDArray[np.intp]

    @classmethod
    def of(cls, scans: Sequence[Scan]) -> PlanarBeams:
        """Every usable beam of `scans`, worked out in one pass over the log's beams instead of a
        pass per scan (the same numbers: the same arithmetic on each beam)."""
        sizes = np.array([s.ranges.size for s in scans], dtype=np.intp)
        poses = np.array([s.pose for s in scans], dtype=float).reshape(-1, 3)
        ranges = np.concatenate([s.ranges for s in scans]) if scans else np.zeros(0)
        angles = np.concatenate([s.angles for s in scans]) if scans else np.zeros(0)
        valid = usable_ranges(ranges)
        scan = np.repeat(np.arange(len(scans), dtype=np.intp), sizes)[valid]
        r = ranges[valid]
        x, y, theta = (poses[:, k][scan] for k in range(3))
        directions, ends = _beam_geometry(x, y, theta + angles[valid], r)
        hit = ~beyond_range(r, np.array([s.max_range for s in scans], dtype=float)[scan])
        return cls(np.column_stack([x, y]), directions, r, ends, hit, scan)


def beams_reach(scan: Scan | CloudScan, lower: ArrayLike, upper: ArrayLike, no_return_cap: float | None = None) -> bool:
    """Whether any beam of `scan` can come within the box `lower`..`upper` (its first k axes).

    A beam runs from the sensor at most as far as its recorded range, a no-return beam at most
    `no_return_cap` (None: its recorded range), as :meth:`Rays.free_lengths` and the ray counts
    (:meth:`gpomap.evidence.RayEvidence.from_scans`) take them; so a scan whose sensor is farther
    from the box than its longest beam sees nothing of it. A scan without usable beams reaches
    nothing.
    """
    if isinstance(scan, CloudScan):
        rays = Rays.of(scan)
        origin, lengths, hit = rays.origin, rays.lengths, rays.hit
    else:  # from the ranges alone: a whole log asks this of every scan
        valid = scan.valid()
        origin, lengths, hit = scan.pose[:2], scan.ranges[valid], ~scan.no_return()[valid]
    if lengths.size == 0:
        return False
    if no_return_cap is not None:
        lengths = np.where(hit, lengths, np.minimum(lengths, no_return_cap))
    lo, hi = np.ravel(lower), np.ravel(upper)
    origin = origin[: lo.size]
    gap = np.maximum(np.maximum(lo - origin, origin - hi), 0.0)
    return bool(math.sqrt(float(gap @ gap)) <= float(lengths.max()))


def labelled_observations(
    data: ScanData | Observations,
    free_step: float,
    hit_margin: float | None,
    no_return_cap: float | None,
    free_clearance: float = 0.0,
    free_cube: float | None = None,
) -> Observations:
    """:func:`observations_from_scans` of scans, or `data` itself when it already is labelled points.

    What an estimator fits on: given points are taken as they are (no clearance); both classes
    are required.

    Raises
    ------
    EmptyDataError
        When either class is missing.
    """
    obs = (
        data
        if isinstance(data, Observations)
        else observations_from_scans(data, free_step, hit_margin, no_return_cap, free_clearance, free_cube)
    )
    if obs.n_occupied == 0 or obs.n_free == 0:
        raise EmptyDataError(f"need both free and occupied observations, got {obs.n_free} free and {obs.n_occupied} occupied")
    return obs


def observations_from_scans(
    scans: ScanData,
    free_step: float = MapConfig.free_step,
    hit_margin: float | None = None,
    no_return_cap: float | None = None,
    free_clearance: float = 0.0,
    free_cube: float | None = None,
) -> Observations:
    """Free and occupied points from planar scans (2-D points) or point clouds (3-D points).

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
    free_step : float
        Spacing of free samples along each beam, metres.
    hit_margin : float, optional
        Free samples stop this far short of a hit, so a free point never sits on the obstacle
        that stopped the beam. Defaults to half of `free_step`.
    no_return_cap : float, optional
        A no-return beam gives free points out to this distance (and no hit). Defaults to the
        scan's max range (a cloud's no-return rays: to their endpoints); 0 ignores no-return beams.
    free_clearance : float
        Free samples closer than this to any hit of these scans are dropped (see
        :func:`free_near_hits`); 0 keeps them all.
    free_cube : float, optional
        Each scan's free samples merged by cubes of this side (:func:`merged_ray_free_points`),
        the points weighted; None keeps every sample.

    Returns
    -------
    Observations
    """
    pts_all: list[NDArray[np.float64]] = []
    occ_all: list[NDArray[np.bool_]] = []
    idx_all: list[NDArray[np.int32]] = []
    weight_all: list[NDArray[np.int32]] = []
    n_invalid = 0
    n_no_return = 0
    for i, scan in enumerate(scans):
        fp, fw, hp, invalid, no_return = _scan_points(scan, free_step, hit_margin, no_return_cap, free_cube)
        n_invalid += invalid
        n_no_return += no_return
        pts_all += [fp, hp]
        occ_all += [np.zeros(len(fp), bool), np.ones(len(hp), bool)]
        idx_all.append(np.full(len(fp) + len(hp), i, dtype=np.int32))
        if fw is not None:
            weight_all += [fw, np.ones(len(hp), dtype=np.int32)]
    if not pts_all or sum(len(p) for p in pts_all) == 0:
        raise EmptyDataError(f"no usable readings in {len(scans)} scan(s) ({n_invalid} invalid): nothing to map")
    points, occupied, scan_index = np.concatenate(pts_all, axis=0), np.concatenate(occ_all), np.concatenate(idx_all)
    weight = np.concatenate(weight_all) if free_cube is not None else None
    del pts_all, occ_all, idx_all, weight_all
    keep = ~free_near_hits(points, occupied, free_clearance)
    n_cleared = int(keep.size - keep.sum())
    obs = Observations(
        points=points,
        occupied=occupied,
        scan_index=scan_index,
        n_invalid=n_invalid,
        n_no_return=n_no_return,
        n_cleared=n_cleared,
        weight=weight,
    )
    # Only then a copy: a whole log's points are hundreds of megabytes.
    return obs.selected(keep) if n_cleared else obs


def _scan_points(
    scan: Scan | CloudScan, free_step: float, hit_margin: float | None, no_return_cap: float | None, free_cube: float | None
) -> tuple[NDArray[np.float64], NDArray[np.int32] | None, NDArray[np.float64], int, int]:
    """One scan's free points and their weights (None unless merged by `free_cube`), its hits
    (:func:`observations_from_scans`' per scan), its invalid readings and its no-return ones."""
    if hit_margin is None:
        hit_margin = 0.5 * free_step
    rays = Rays.of(scan)
    free_len = rays.free_lengths(hit_margin, no_return_cap)
    use = free_len > 0
    origins = np.broadcast_to(rays.origin, (int(use.sum()), rays.origin.size))
    fw: NDArray[np.int32] | None = None
    if free_cube is None:
        fp, _ = ray_free_points(origins, rows(rays.directions, use), free_len[use], free_step)
    else:
        fp, fw = merged_ray_free_points(origins, rows(rays.directions, use), free_len[use], free_step, free_cube)
    return fp, fw, rows(rays.ends, rays.hit), rays.n_invalid, rays.n_no_return


#: Most points a part of :func:`observation_parts` holds (whole scans are added until it is
#: reached): about 70 MB of planar points with their labels and scans.
PART_POINTS: int = 1 << 22


def observation_parts(
    scans: ScanData,
    free_step: float = MapConfig.free_step,
    hit_margin: float | None = None,
    no_return_cap: float | None = None,
    indices: Sequence[int] | None = None,
    free_cube: float | None = None,
) -> Iterator[Observations]:
    """:func:`observations_from_scans` (without a clearance) a part at a time, never all at once.

    Each part holds the points of consecutive whole scans, at least :data:`PART_POINTS` of them
    but for the last: joined, the parts are the whole's points, the same numbers in the same
    order. Only the last part may be empty, holding the counts of scans without points.

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
    free_step, hit_margin, no_return_cap : float
        As :func:`observations_from_scans`'.
    indices : sequence of int, optional
        The number each scan's points take as ``scan_index`` (default: its place in `scans`).
    free_cube : float, optional
        As :func:`observations_from_scans`'.

    Yields
    ------
    Observations
        With its scans' ``n_invalid`` and ``n_no_return``.
    """
    parts: list[tuple[NDArray[np.float64], NDArray[np.int32] | None, NDArray[np.float64], int]] = []
    held = n_invalid = n_no_return = 0
    for i, scan in enumerate(scans):
        fp, fw, hp, invalid, no_return = _scan_points(scan, free_step, hit_margin, no_return_cap, free_cube)
        n_invalid += invalid
        n_no_return += no_return
        if len(fp) + len(hp):
            parts.append((fp, fw, hp, i if indices is None else int(indices[i])))
            held += len(fp) + len(hp)
        if held >= PART_POINTS or (i == len(scans) - 1 and (parts or n_invalid or n_no_return)):
            d = parts[0][0].shape[1] if parts else (3 if isinstance(scan, CloudScan) else 2)
            # Each scan's free points, then its hits: the labels and scans repeated run by run.
            runs = np.array([(len(fp), len(hp)) for fp, _, hp, _ in parts], dtype=np.int64).reshape(-1, 2)
            weight = None
            if free_cube is not None:
                ones = np.ones(0, dtype=np.int32)
                weight = np.concatenate([ones, *(a for fp, fw, hp, _ in parts for a in (fw, np.ones(len(hp), np.int32)))])
            yield Observations(
                np.concatenate([a for fp, _, hp, _ in parts for a in (fp, hp)], axis=0) if parts else np.zeros((0, d)),
                np.repeat(np.tile(np.array([False, True]), len(parts)), runs.reshape(-1)),
                np.repeat(np.array([k for _, _, _, k in parts], dtype=np.int32), runs.sum(axis=1)),
                n_invalid,
                n_no_return,
                weight=weight,
            )
            parts, held, n_invalid, n_no_return = [], 0, 0, 0


class ScanPoints:
    """The labelled points of a log (:func:`observations_from_scans`, no clearance), known by
    their counts and bounds and made again where asked, never all held at once.

    A building's log gives tens of millions of points (a gigabyte with their labels and scans);
    what a fit asks of them besides filing them (its variance scale's squares, its new ground) is
    answered by making the points of the scans concerned again, the same numbers in the same
    order as the whole log's. One pass over the log (:func:`observation_parts`) counts them; each
    part is handed to `each_part` as it is made.

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
    free_step, hit_margin, no_return_cap : float
        As :func:`observations_from_scans`'.
    each_part : callable, optional
        Called with every part of the first pass, in order.
    free_cube : float, optional
        As :func:`observations_from_scans`'.

    Attributes
    ----------
    n_free, n_occupied, n_invalid, n_no_return : int
    n_scans : int
        One past the last scan with a point (0 without points).
    lower, upper : ndarray of shape (d,)
        Bounds of every point (NaN without points).
    scan_lower, scan_upper : ndarray of shape (len(scans), d)
        Bounds of each scan's points (+inf / -inf for a scan without points).
    """

    def __init__(
        self,
        scans: ScanData,
        free_step: float,
        hit_margin: float | None,
        no_return_cap: float | None,
        each_part: Callable[[Observations], None] | None = None,
        free_cube: float | None = None,
    ) -> None:
        self.scans = scans
        self._how = (free_step, hit_margin, no_return_cap)
        self._free_cube = free_cube
        d = data_dim(scans) if len(scans) else 2
        self.scan_lower = np.full((len(scans), d), np.inf)
        self.scan_upper = np.full((len(scans), d), -np.inf)
        self.n_free = self.n_occupied = self.n_invalid = self.n_no_return = self.n_scans = 0
        for part in self.parts():
            self.n_invalid += part.n_invalid
            self.n_no_return += part.n_no_return
            if part.occupied.size == 0:
                continue
            self.n_occupied += int(part.occupied.sum())
            self.n_free += int(part.occupied.size) - int(part.occupied.sum())
            self.n_scans = int(part.scan_index[-1]) + 1
            # A part's points are in scan order: each scan's points one run of it.
            first = np.flatnonzero(np.concatenate([[True], part.scan_index[1:] != part.scan_index[:-1]]))
            which = part.scan_index[first]
            self.scan_lower[which] = np.minimum.reduceat(part.points, first, axis=0)
            self.scan_upper[which] = np.maximum.reduceat(part.points, first, axis=0)
            if each_part is not None:
                each_part(part)
        seen = np.isfinite(self.scan_lower[:, 0])
        self.lower = self.scan_lower[seen].min(axis=0) if seen.any() else np.full(d, np.nan)
        self.upper = self.scan_upper[seen].max(axis=0) if seen.any() else np.full(d, np.nan)

    def parts(self, indices: Sequence[int] | None = None) -> Iterator[Observations]:
        """The points of every scan (or of the scans at `indices`, in their order), a part at a time."""
        scans = self.scans if indices is None else [self.scans[i] for i in indices]
        return observation_parts(scans, *self._how, indices=indices, free_cube=self._free_cube)

    def square(self, lower: ArrayLike, upper: ArrayLike, grow: float = 0.0) -> Observations:
        """The points inside the box `lower`..`upper` (its first axes; x, y for a square) grown by
        `grow`, in the log's order: the scans whose points reach it, made again and cut."""
        lo = np.ravel(np.asarray(lower, dtype=float)) - grow
        hi = np.ravel(np.asarray(upper, dtype=float)) + grow
        k = lo.size
        meets = np.flatnonzero(np.all((self.scan_lower[:, :k] <= hi) & (self.scan_upper[:, :k] >= lo), axis=1))
        # Each part cut as it is made and let go: only what lies inside is held, never the scans' whole points.
        cut: list[Observations] = []
        for p in self.parts(meets.tolist()) if meets.size else ():
            inside = in_box(p.points, lo, hi)
            cut.append(p.selected(inside))
            del p, inside
        return Observations.joined(cut, self.scan_lower.shape[1])


def natural_subsample(n_points: int, n: int, seed: int) -> NDArray[np.intp]:
    """Sorted indices of at most `n` of `n_points` points drawn uniformly without replacement by a
    generator seeded with `seed`: each class keeps the share it has in the data.

    Every calibration is fitted on such a sample, so that its probabilities are right at the
    frequencies a robot meets (along beams, a few per cent of points are hits), not at balanced classes.

    Parameters
    ----------
    n_points : int
    n : int
    seed : int

    Returns
    -------
    ndarray of int, shape (min(n, n_points),)
    """
    if n_points <= n:
        return np.arange(n_points)
    return np.sort(np.random.default_rng(seed).choice(n_points, n, replace=False))


def reading_counts(scans: ScanData) -> tuple[int, int]:
    """The invalid readings and the no-return ones of `scans`, as :class:`ScanPoints` counts them."""
    n_invalid = n_no_return = 0
    for scan in scans:
        if isinstance(scan, Scan):
            # From the ranges alone (Scan's own rules, as Rays.of counts them).
            n_invalid += int(scan.n_beams - np.count_nonzero(scan.valid()))
            n_no_return += int(np.count_nonzero(scan.no_return()))
            continue
        rays = Rays.of(scan)
        n_invalid += rays.n_invalid
        n_no_return += rays.n_no_return
    return n_invalid, n_no_return


def sensor_positions(scans: ScanData) -> NDArray[np.float64]:
    """Where the sensor was for each scan, ndarray of shape (k, d): a planar pose's (x, y), a cloud's origin."""
    return np.array([s.origin if isinstance(s, CloudScan) else s.pose[:2] for s in scans], dtype=float)


def data_dim(scans: ScanData) -> int:
    """Dimension of the map `scans` make: 3 for point clouds, 2 for planar scans."""
    return 3 if any(isinstance(s, CloudScan) for s in scans[:1]) else 2
