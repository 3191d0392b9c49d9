"""A pinhole depth camera in a :class:`~gpomap.simulate3d.scene.Scene`: frames rendered by ray casting.

:func:`render_depth` renders one depth frame of a pinhole camera (:class:`PinholeCamera`, OpenCV
axes: x right, y down, z forward) by exact ray casting against every box, optionally with a depth
camera's noise (:class:`DepthNoise`); :func:`render_frames` renders one per pose, the written
poses carrying the noise's pose error. :func:`write_depth_frames` writes frames in the layout
``gpomap map`` reads (``camera-intrinsics.txt``, ``NAME.depth.png`` in millimetres,
``NAME.pose.txt`` camera-to-world), so simulated data goes through exactly the reader and the map
a user's frames go through; :func:`frame_clouds` gives the clouds that reader would return.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.clouds import CloudScan
from gpomap.simulate3d.scene import Scene

__all__ = [
    "PinholeCamera",
    "DepthNoise",
    "DepthFrames",
    "look_at",
    "render_depth",
    "render_frames",
    "write_depth_frames",
    "frame_clouds",
]


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
