"""3-D scenes of boxes, a depth camera ray-cast inside them, and the truth to score a map against.

The 3-D counterpart of :mod:`gpomap.simulate`. A :class:`Scene` is a set of solid axis-aligned
boxes (walls, floors, table tops and legs, shelf boards); its occupied space is the union of the
boxes. :func:`render_depth` renders one depth frame of a pinhole camera (:class:`PinholeCamera`,
OpenCV axes: x right, y down, z forward) by exact ray casting against every box (the slab
method), optionally with a depth camera's noise (:class:`DepthNoise`). :func:`write_depth_frames`
writes frames in the layout ``gpomap map`` reads (``camera-intrinsics.txt``, ``NAME.depth.png`` in
millimetres, ``NAME.pose.txt`` camera-to-world), so simulated data goes through exactly the
reader and the map a user's frames go through.

:func:`office_scene` and :func:`office_poses` build three rooms on a corridor of doorways, with
tables, shelves, a cabinet, a sofa and a pillar, and ten camera poses inside them.

Truth (:func:`truth_points`), as the 2-D rule of :mod:`gpomap.truth`: the points of a fine lattice
(:data:`TRUTH_LATTICE`, a quarter of a 0.1 m voxel) whose cell lies within :data:`OBSERVED_RADIUS`
(half a 0.1 m voxel) of a lattice cell some ray passed through (from the sensor to its end point,
:func:`gpomap.raycast.traverse`) are scored, each once; a point is occupied when it lies inside a
box; "boundary" points lie within :data:`BOUNDARY_RADIUS` of a box. Space no ray came near is
never scored, and a surface scores as thick as it is: a map that smears surfaces over free space
pays for it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.clouds import CloudScan
from gpomap.voxels import VoxelSpec

__all__ = [
    "Scene",
    "PinholeCamera",
    "DepthNoise",
    "DepthFrames",
    "TruthVolume",
    "look_at",
    "render_depth",
    "render_frames",
    "write_depth_frames",
    "frame_clouds",
    "truth_points",
    "observed_cells",
    "office_scene",
    "office_poses",
    "storeroom_scene",
    "storeroom_poses",
    "TRUTH_LATTICE",
    "OBSERVED_RADIUS",
    "BOUNDARY_RADIUS",
]

#: Side (m) of the truth lattice: 64 points per 0.1 m voxel, each nested in one voxel of a
#: grid whose faces lie on multiples of 0.1 m (OctoMap's and gpomap's voxel maps).
TRUTH_LATTICE: float = 0.025
#: A truth point is scored if its lattice cell lies this close (m, centre to centre) to a cell a
#: ray passed through: half a 0.1 m voxel, as the 2-D rule takes half a 0.05 m cell.
OBSERVED_RADIUS: float = 0.05
#: Boundary points: within this distance (m) of a box (inside one included), as in 2-D.
BOUNDARY_RADIUS: float = 0.1

# Rays x boxes pairs per chunk of the ray caster: bounds its temporary arrays to tens of MB.
_PAIRS_PER_CHUNK: int = 1 << 20


def _boxes(lower: ArrayLike, upper: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
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


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole depth camera: image size and intrinsics (pixels; OpenCV's convention, pixel
    (0, 0) the top-left one, integer coordinates at pixel centres).

    Parameters
    ----------
    width, height : int
    fx, fy, cx, cy : float
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov: float) -> PinholeCamera:
        """A camera of square pixels whose image spans `horizontal_fov` degrees, centred."""
        f = (width / 2) / np.tan(np.radians(horizontal_fov) / 2)
        return cls(width, height, float(f), float(f), (width - 1) / 2, (height - 1) / 2)

    @property
    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def directions(self) -> NDArray[np.float64]:
        """Every pixel's ray in the camera frame scaled to depth 1 (z = 1), shape (height * width, 3),
        row by row (image order)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        return np.column_stack([((u - self.cx) / self.fx).ravel(), ((v - self.cy) / self.fy).ravel(), np.ones(u.size)])


def look_at(position: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> NDArray[np.float64]:
    """The camera-to-world pose (4, 4) of a camera at `position` looking at `target`, OpenCV axes
    (x right, y down, z forward), its image upright with respect to `up`."""
    p = np.asarray(position, dtype=float).reshape(3)
    forward = np.asarray(target, dtype=float).reshape(3) - p
    if not np.linalg.norm(forward) > 0:
        raise ValueError("the camera's target must differ from its position")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=float))
    if not np.linalg.norm(right) > 1e-9:
        raise ValueError("the camera cannot look straight along its up direction")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = p
    return pose


@dataclass(frozen=True)
class DepthNoise:
    """A structured-light depth camera's errors.

    Parameters
    ----------
    axial : (float, float, float)
        Depth noise sigma(z) = a + b (z - c)^2 metres at depth z: Nguyen, Izadi and Lovell's
        Kinect model (3DIMPVT 2012), 1.2 mm at 0.4 m, 6 mm at 2 m, 26 mm at 4 m.
    dropout : float
        Share of pixels that read no depth at random.
    pose_position, pose_angle : float
        Sigma of the error (m, rad) of the pose written with a frame against the pose its
        rays were cast from, as a SLAM front end's.
    """

    axial: tuple[float, float, float] = (0.0012, 0.0019, 0.4)
    dropout: float = 0.01
    pose_position: float = 0.01
    pose_angle: float = 0.005

    def sigma(self, depth: ArrayLike) -> NDArray[np.float64]:
        """Depth noise sigma (m) at each depth (m), the shape of `depth`."""
        a, b, c = self.axial
        return a + b * (np.asarray(depth, dtype=float) - c) ** 2


def render_depth(
    scene: Scene,
    camera: PinholeCamera,
    pose: NDArray[np.float64],
    min_depth: float = 0.3,
    max_depth: float = 6.0,
    noise: DepthNoise | None = None,
    rng: np.random.Generator | None = None,
) -> NDArray[np.float64]:
    """A depth image of `scene` from a camera at `pose` (camera to world, 4x4).

    Parameters
    ----------
    scene : Scene
    camera : PinholeCamera
    pose : ndarray of shape (4, 4)
    min_depth, max_depth : float
        The sensor's range (m, along the optical axis): nearer or farther surfaces read 0.
    noise : DepthNoise, optional
        Depth noise and dropped pixels (the pose error is :func:`render_frames`'); None: exact.
    rng : numpy Generator, optional
        For the noise.

    Returns
    -------
    ndarray of shape (height, width)
        Depth along the optical axis (m), 0 where there is no reading.
    """
    rays = camera.directions()
    scale = np.linalg.norm(rays, axis=1)  # metres along a ray per metre of depth
    world = (rays / scale[:, None]) @ np.asarray(pose, dtype=float)[:3, :3].T
    t = scene.cast(pose[:3, 3], world, max_range=float(max_depth * scale.max()))
    depth = t / scale
    if noise is not None:
        gen = rng if rng is not None else np.random.default_rng(0)
        finite = np.isfinite(depth)
        depth[finite] += gen.normal(size=int(finite.sum())) * noise.sigma(depth[finite])
        depth[gen.random(depth.size) < noise.dropout] = np.inf
    depth[~((depth >= min_depth) & (depth <= max_depth))] = 0.0
    return depth.reshape(camera.height, camera.width)


def _rotation(axis_angle: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(axis_angle))
    if angle == 0.0:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.asarray(np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx)


@dataclass(frozen=True)
class DepthFrames:
    """Rendered frames with their poses.

    Attributes
    ----------
    camera : PinholeCamera
    depths : ndarray of shape (k, height, width)
        Depth (m), 0 = no reading.
    poses : ndarray of shape (k, 4, 4)
        The poses written with the frames (camera to world).
    true_poses : ndarray of shape (k, 4, 4)
        The poses the rays were cast from (equal to `poses` without pose noise).
    """

    camera: PinholeCamera
    depths: NDArray[np.float64]
    poses: NDArray[np.float64]
    true_poses: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.depths)


def render_frames(
    scene: Scene,
    camera: PinholeCamera,
    poses: Sequence[NDArray[np.float64]],
    min_depth: float = 0.3,
    max_depth: float = 6.0,
    noise: DepthNoise | None = None,
    seed: int = 0,
) -> DepthFrames:
    """One depth frame per pose (:func:`render_depth`); with `noise`, the written poses carry its pose error."""
    rng = np.random.default_rng(seed)
    depths, written = [], []
    for pose in poses:
        depths.append(render_depth(scene, camera, pose, min_depth, max_depth, noise, rng))
        p = np.array(pose, dtype=float)
        if noise is not None:
            p[:3, :3] = _rotation(rng.normal(size=3) * noise.pose_angle) @ p[:3, :3]
            p[:3, 3] += rng.normal(size=3) * noise.pose_position
        written.append(p)
    return DepthFrames(camera, np.array(depths), np.array(written), np.array([np.asarray(p, float) for p in poses]))


def write_depth_frames(frames: DepthFrames, directory: str | os.PathLike[str], depth_scale: float = 1000.0) -> Path:
    """Write `frames` as ``gpomap map`` reads depth frames (:mod:`gpomap.io.depth`).

    ``camera-intrinsics.txt``, and per frame ``frame-NNNNNN.depth.png`` (16-bit, `depth_scale`
    units per metre, rounded; 0 = no reading) and ``frame-NNNNNN.pose.txt`` (camera to world).

    Returns
    -------
    Path
        `directory` (created if missing).
    """
    from PIL import Image

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    np.savetxt(out / "camera-intrinsics.txt", frames.camera.matrix, fmt="%.10g")
    for i, (depth, pose) in enumerate(zip(frames.depths, frames.poses)):
        units = np.rint(depth * depth_scale)
        if units.max(initial=0) > 65535:
            raise ValueError(f"frame {i}: depth {depth.max():.3f} m does not fit 16 bits at {depth_scale:g} units per metre")
        Image.fromarray(units.astype(np.uint16)).save(out / f"frame-{i:06d}.depth.png")
        np.savetxt(out / f"frame-{i:06d}.pose.txt", pose, fmt="%.10f")
    return out


def frame_clouds(frames: DepthFrames, depth_scale: float = 1000.0) -> list[CloudScan]:
    """The frames as clouds, as :func:`gpomap.io.read_depth_frames` reads what
    :func:`write_depth_frames` writes (depths rounded to the image's units, written poses)."""
    from gpomap.clouds import cloud_from_points
    from gpomap.io.poses import transform_points

    rays = frames.camera.directions()
    out = []
    for depth, pose in zip(frames.depths, frames.poses):
        d = np.rint(depth.reshape(-1) * depth_scale) / depth_scale
        d[d == 0] = np.nan
        out.append(cloud_from_points(pose[:3, 3], transform_points(pose, rays * d[:, None])))
    return out


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


# --------------------------------------------------------------------------- scenes
def _wall_with_door(
    name: str,
    axis: str,
    at: tuple[float, float],
    span: tuple[float, float],
    door: tuple[float, float],
    height: float,
    door_height: float,
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """A wall `at` (its two faces) across `axis` ("x": the wall's faces are x = const), running
    along the other horizontal axis over `span`, with a doorway over `door` up to `door_height`."""

    def box(a: tuple[float, float], b: tuple[float, float], z: tuple[float, float]) -> tuple[ArrayLike, ArrayLike]:
        if axis == "x":
            return (a[0], b[0], z[0]), (a[1], b[1], z[1])
        return (b[0], a[0], z[0]), (b[1], a[1], z[1])

    out: list[tuple[str, ArrayLike, ArrayLike]] = []
    for part, (s0, s1), (z0, z1) in (
        ("left", (span[0], door[0]), (0.0, height)),
        ("right", (door[1], span[1]), (0.0, height)),
        ("lintel", door, (door_height, height)),
    ):
        if s1 > s0 and z1 > z0:
            out.append((f"{name} {part}", *box(at, (s0, s1), (z0, z1))))
    return out


def _table(
    name: str, x: tuple[float, float], y: tuple[float, float], height: float = 0.75
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """A table: a 4 cm top at `height` on four 5 cm legs."""
    out: list[tuple[str, ArrayLike, ArrayLike]] = [(f"{name} top", (x[0], y[0], height - 0.04), (x[1], y[1], height))]
    for lx in (x[0] + 0.03, x[1] - 0.08):
        for ly in (y[0] + 0.03, y[1] - 0.08):
            out.append((f"{name} leg", (lx, ly, 0.0), (lx + 0.05, ly + 0.05, height - 0.04)))
    return out


def _shelf(
    name: str, x: tuple[float, float], y: tuple[float, float], height: float, boards: int, back: str
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """An open shelf: two 3 cm side panels along its longer side's ends, `boards` 3 cm boards, a
    2 cm back panel on the side `back` ("x-", "x+", "y-", "y+")."""
    along_x = (x[1] - x[0]) >= (y[1] - y[0])
    out: list[tuple[str, ArrayLike, ArrayLike]] = []
    if along_x:
        out += [(f"{name} side", (x[0], y[0], 0.0), (x[0] + 0.03, y[1], height))]
        out += [(f"{name} side", (x[1] - 0.03, y[0], 0.0), (x[1], y[1], height))]
    else:
        out += [(f"{name} side", (x[0], y[0], 0.0), (x[1], y[0] + 0.03, height))]
        out += [(f"{name} side", (x[0], y[1] - 0.03, 0.0), (x[1], y[1], height))]
    for z in np.linspace(0.08, height - 0.03, boards):
        out.append((f"{name} board", (x[0], y[0], float(z)), (x[1], y[1], float(z) + 0.03)))
    bx = {
        "x-": ((x[0], x[0] + 0.02), y),
        "x+": ((x[1] - 0.02, x[1]), y),
        "y-": (x, (y[0], y[0] + 0.02)),
        "y+": (x, (y[1] - 0.02, y[1])),
    }
    (bx0, bx1), (by0, by1) = bx[back]
    out.append((f"{name} back", (bx0, by0, 0.0), (bx1, by1, height)))
    return out


#: Moves every box of the built-in scenes off the 0.1 m lattice (m), as a real building is.
SCENE_OFFSET: tuple[float, float, float] = (0.037, 0.061, 0.013)


def office_scene() -> Scene:
    """Three rooms in a row (9.2 x 6.3 m inside, 2.65 m high) joined by doorways, furnished.

    Room A (x 0-3): a table, a shelf against the west wall, a box on the floor; room B (x 3.12-6.1):
    a desk, a cabinet, a chair; room C (x 6.22-9.2): a sofa, two shelves, a pillar, a half-height
    partition. 20 cm outer walls, 12 cm inner ones, a floor and a ceiling slab; every box moved by
    :data:`SCENE_OFFSET`.
    """
    H = 2.65
    boxes: list[tuple[str, ArrayLike, ArrayLike]] = [
        ("floor", (-0.2, -0.2, -0.2), (9.4, 6.5, 0.0)),
        ("ceiling", (-0.2, -0.2, H), (9.4, 6.5, H + 0.2)),
        ("wall west", (-0.2, -0.2, 0.0), (0.0, 6.5, H)),
        ("wall east", (9.2, -0.2, 0.0), (9.4, 6.5, H)),
        ("wall south", (0.0, -0.2, 0.0), (9.2, 0.0, H)),
        ("wall north", (0.0, 6.3, 0.0), (9.2, 6.5, H)),
    ]
    boxes += _wall_with_door("wall AB", "x", (3.0, 3.12), (0.0, 6.3), (1.0, 1.9), H, 2.05)
    boxes += _wall_with_door("wall BC", "x", (6.1, 6.22), (0.0, 6.3), (4.3, 5.2), H, 2.05)
    # Room A.
    boxes += _table("table A", (0.8, 2.2), (3.6, 4.5))
    boxes += _shelf("shelf A", (0.0, 0.4), (0.6, 1.8), 1.9, 5, "x-")
    boxes += [("crate A", (2.1, 0.3, 0.0), (2.7, 0.8, 0.45))]
    # Room B.
    boxes += _table("desk B", (3.6, 5.2), (0.2, 0.9), 0.76)
    boxes += [("cabinet B", (4.2, 5.7, 0.0), (5.0, 6.3, 1.1))]
    boxes += [("chair B seat", (4.1, 1.1, 0.42), (4.55, 1.55, 0.47)), ("chair B column", (4.28, 1.28, 0.0), (4.37, 1.37, 0.42))]
    boxes += [("chair B back", (4.1, 1.51, 0.47), (4.55, 1.55, 0.95))]
    # Room C.
    boxes += [("sofa C seat", (6.6, 5.5, 0.0), (8.4, 6.3, 0.45)), ("sofa C back", (6.6, 6.1, 0.45), (8.4, 6.3, 0.85))]
    boxes += _shelf("shelf C1", (9.2 - 0.35, 9.2), (3.4, 4.6), 2.0, 6, "x+")
    boxes += _shelf("shelf C2", (6.4, 7.6), (0.0, 0.35), 1.2, 3, "y-")
    boxes += [("pillar C", (7.7, 1.4, 0.0), (8.0, 1.7, H)), ("partition C", (7.9, 3.0, 0.0), (9.2, 3.1, 1.3))]
    return Scene.from_boxes(boxes, SCENE_OFFSET)


def office_poses() -> list[NDArray[np.float64]]:
    """Ten camera poses in :func:`office_scene` (camera to world), three or four a room, some
    looking through a doorway."""
    shift = np.asarray(SCENE_OFFSET)
    views = [
        ((1.5, 1.0, 1.5), (1.0, 5.0, 0.6)),
        ((2.5, 5.6, 1.4), (0.3, 1.2, 0.9)),
        ((0.6, 3.0, 1.6), (3.1, 1.4, 1.0)),
        ((4.6, 2.5, 1.5), (4.6, 6.3, 0.5)),
        ((5.6, 4.5, 1.3), (3.6, 0.5, 0.7)),
        ((3.5, 3.3, 1.6), (6.5, 4.7, 1.1)),
        ((7.0, 4.0, 1.5), (9.0, 6.0, 0.5)),
        ((8.8, 0.6, 1.4), (6.5, 3.0, 0.8)),
        ((6.6, 2.0, 1.6), (9.2, 2.0, 1.2)),
        ((8.5, 4.6, 1.3), (6.3, 0.3, 0.6)),
    ]
    return [look_at(np.asarray(p) + shift, np.asarray(t) + shift) for p, t in views]


def storeroom_scene() -> Scene:
    """A store room 8 x 5 m inside, 3 m high: three rows of tall shelves with aisles between
    them, a workbench, crates on the floor, and an office behind a wall with a doorway."""
    H = 3.0
    boxes: list[tuple[str, ArrayLike, ArrayLike]] = [
        ("floor", (-0.2, -0.2, -0.2), (8.2, 5.2, 0.0)),
        ("ceiling", (-0.2, -0.2, H), (8.2, 5.2, H + 0.2)),
        ("wall west", (-0.2, -0.2, 0.0), (0.0, 5.2, H)),
        ("wall east", (8.0, -0.2, 0.0), (8.2, 5.2, H)),
        ("wall south", (0.0, -0.2, 0.0), (8.0, 0.0, H)),
        ("wall north", (0.0, 5.0, 0.0), (8.0, 5.2, H)),
    ]
    boxes += _wall_with_door("wall office", "x", (5.6, 5.72), (0.0, 5.0), (3.6, 4.5), H, 2.1)
    for n, y0 in enumerate((0.9, 2.1, 3.3)):
        boxes += _shelf(f"rack {n}", (0.9, 4.1), (y0, y0 + 0.5), 2.2, 5, "y-")
    boxes += _table("bench", (0.2, 1.6), (4.3, 4.95), 0.9)
    boxes += [("crate 1", (4.5, 0.2, 0.0), (5.1, 0.8, 0.6)), ("crate 2", (4.6, 0.25, 0.6), (5.0, 0.7, 0.95))]
    boxes += [("crate 3", (4.4, 4.2, 0.0), (5.2, 4.9, 0.7))]
    boxes += _table("office desk", (6.3, 7.9), (0.1, 0.8), 0.75)
    boxes += [("office cabinet", (7.4, 3.9, 0.0), (7.95, 4.95, 1.9))]
    return Scene.from_boxes(boxes, SCENE_OFFSET)


def storeroom_poses() -> list[NDArray[np.float64]]:
    """Eight camera poses in :func:`storeroom_scene`: down the aisles, across the room, into the office."""
    shift = np.asarray(SCENE_OFFSET)
    views = [
        ((0.4, 0.45, 1.6), (4.5, 0.6, 0.8)),
        ((4.7, 1.85, 1.4), (0.5, 1.8, 0.9)),
        ((0.5, 3.05, 1.5), (4.5, 3.0, 0.7)),
        ((4.9, 4.1, 1.7), (0.3, 4.6, 0.6)),
        ((5.1, 2.5, 1.8), (0.5, 0.5, 0.5)),
        ((2.5, 4.3, 1.6), (5.5, 0.3, 0.4)),
        ((4.8, 3.5, 1.5), (7.9, 4.5, 0.9)),
        ((7.6, 2.5, 1.4), (6.0, 0.3, 0.6)),
    ]
    return [look_at(np.asarray(p) + shift, np.asarray(t) + shift) for p, t in views]
