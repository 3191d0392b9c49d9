"""3-D scans for a map: which inputs hold them, reading and thinning clouds, the model and its voxel bounds.

``gpomap map`` on point clouds and depth frames (:mod:`gpomap.cli.map3d`) builds its model with
:func:`new_model`, and benchmarks build theirs through the command's own options
(:func:`gpomap.cli.map3d.unfitted_model`), so that both are the very model the command fits.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.errors import GpomapError
from gpomap.lattice import column_bounds

if TYPE_CHECKING:
    from gpomap.observations import Rays
    from gpomap.settings import MapSettings

__all__ = [
    "is_cloud_input",
    "select_clouds",
    "read_selected_clouds",
    "voxel_bounds",
    "enclosing_box",
    "labelled_box",
    "new_model",
]


def is_cloud_input(path: str | os.PathLike[str]) -> bool:
    """Whether `path` holds 3-D scans: a cloud format, or a bag with PointCloud2 and no LaserScan."""
    from gpomap.io import CLOUD_FORMATS, detect_format

    fmt = detect_format(path)
    if fmt in CLOUD_FORMATS:
        return True
    if fmt in ("rosbag1", "rosbag2"):
        from gpomap.io.pointcloud2 import bag_has_pointclouds_only

        return bag_has_pointclouds_only(path)
    return False


# --------------------------------------------------------------------------- reading and selecting
def select_clouds(
    clouds: Sequence[CloudScan],
    scan_range: tuple[int | None, int | None] | None = None,
    n_scans: int | None = None,
    n_rays: int | None = None,
    source: str = "input",
) -> list[CloudScan]:
    """A window of consecutive clouds, thinned to `n_scans` evenly spaced clouds of `n_rays` evenly spaced rays.

    Parameters
    ----------
    clouds : sequence of CloudScan
    scan_range : (first, last), optional
        Python slice bounds (last excluded; None open).
    n_scans, n_rays : int, optional
        Keep this many clouds / rays per cloud (all when there are fewer).
    source : str
        The input's name, for the message.

    Returns
    -------
    list of CloudScan

    Raises
    ------
    GpomapError
        The window selects no cloud.
    """
    out = list(clouds)
    if scan_range is not None:
        first, last = scan_range
        out = out[slice(first, last)]
        if not out:
            raise GpomapError(f"--range {first}:{last} selects no scans from {source}, which has {len(clouds)} scans")
    if n_scans is not None and n_scans < len(out):
        out = [out[i] for i in np.linspace(0, len(out) - 1, n_scans).round().astype(int)]
    if n_rays is not None:
        out = [_thin(c, n_rays) for c in out]
    return out


def _thin(cloud: CloudScan, n_rays: int) -> CloudScan:
    """`cloud` with `n_rays` evenly spaced rays (itself when it has no more)."""
    if cloud.n_points <= n_rays:
        return cloud
    keep = np.linspace(0, cloud.n_points - 1, n_rays).round().astype(int)
    hit = np.asarray(cloud.hit, dtype=bool)
    return CloudScan(cloud.origin, cloud.points[keep], hit[keep], cloud.max_range, cloud.time, dict(cloud.meta))


def read_selected_clouds(
    path: str,
    reader_options: dict[str, Any],
    scan_range: tuple[int | None, int | None] | None = None,
    n_scans: int | None = None,
    n_rays: int | None = None,
) -> list[CloudScan]:
    """Read the clouds of `path` (:func:`gpomap.io.read_clouds` with `reader_options`) and select them (:func:`select_clouds`).

    Parameters
    ----------
    path : str
        A cloud input (:data:`gpomap.io.CLOUD_FORMATS`, or a bag of PointCloud2 messages).
    reader_options : dict
        Keyword arguments of :func:`gpomap.io.read_clouds`.
    scan_range, n_scans, n_rays
        As for :func:`select_clouds`.

    Returns
    -------
    list of CloudScan

    Raises
    ------
    GpomapError
        What the reader refuses, a window selecting nothing, clouds without a valid ray.
    """
    from gpomap.io import read_clouds

    clouds = read_clouds(path, **reader_options)
    if not clouds:
        raise GpomapError(f"{path}: holds no 3-D scans")
    clouds = select_clouds(clouds, scan_range, n_scans, n_rays, path)
    if not any(c.valid().any() for c in clouds):
        raise GpomapError(f"{path}: no valid ray in {len(clouds)} scans (every point non-finite or at its sensor)")
    return clouds


# --------------------------------------------------------------------------- the model
def voxel_bounds(
    points: NDArray[np.float64],
    extent: tuple[float, float, float, float] | None,
    z_range: tuple[float, float] | None,
    resolution: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lower and upper corners (x, y, z), shape (3,) each, of the written voxel map.

    The observation points' bounding box grown by :data:`gpomap.lattice.EXTENT_MARGIN_CELLS`
    voxels of side `resolution` on every side (as a planar map's default extent: a surface hit on
    the box's edge reaches into the voxel past it), with x and y from `extent` and z from
    `z_range` where given, as they are.
    """
    from gpomap.lattice import EXTENT_MARGIN_CELLS

    pad = EXTENT_MARGIN_CELLS * float(resolution)
    lo = np.asarray(points, dtype=float).min(axis=0) - pad
    hi = np.asarray(points, dtype=float).max(axis=0) + pad
    if extent is not None:
        lo[:2], hi[:2] = (extent[0], extent[2]), (extent[1], extent[3])
    if z_range is not None:
        lo[2], hi[2] = z_range
    return lo, hi


def enclosing_box(clouds: Sequence[CloudScan], **model_options: Any) -> NDArray[np.float64]:
    """A box round every labelled point of `clouds` (:func:`labelled_box`'s or larger), from the
    rays alone: their hits, and the origin and the far end of each ray's free samples.

    The free samples of a ray lie on the segment between those two, so the box holds them all,
    whatever the clearance drops; working it out costs one pass over the rays, where the exact
    box asks every sample outside the hits' box about the clearance.

    Parameters
    ----------
    clouds : sequence of CloudScan
    **model_options
        The map settings (:class:`~gpomap.settings.MapSettings`).

    Returns
    -------
    ndarray of shape (2, 3)
        The lowest and the highest coordinates.

    Raises
    ------
    EmptyDataError
        As :func:`labelled_box`: no readings, or a class missing.
    """
    from gpomap.observations import Rays
    from gpomap.settings import MapSettings

    settings = MapSettings(**model_options)
    corners: list[NDArray[np.float64]] = []
    n_hits = n_free = 0
    for cloud in clouds:
        rays = Rays.of(cloud)
        hits = rays.ends[rays.hit]
        reach, counts = _free_samples_along(rays, settings)
        sampled = counts > 0
        n_hits, n_free = n_hits + hits.shape[0], n_free + int(sampled.sum())
        far = rays.origin + reach[sampled, None] * rays.directions[sampled]
        for part in (hits, far):
            if part.shape[0]:
                corners.extend(column_bounds(part))
        if sampled.any():
            corners.append(np.asarray(rays.origin, dtype=float))
    if n_hits == 0 or n_free == 0:
        return labelled_box(clouds, **model_options)  # its error: a class missing, or no readings
    return np.array([np.min(corners, axis=0), np.max(corners, axis=0)])


def _free_samples_along(rays: Rays, settings: MapSettings) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """How far along each ray its free samples may go (at least 0) and how many it holds (those at
    a step, two, ...: :func:`gpomap.observations.sample_counts`), each shape (b,)."""
    from gpomap.observations import sample_counts

    step = float(settings.free_step)
    margin = 0.5 * step if settings.hit_margin is None else float(settings.hit_margin)
    reach = np.maximum(rays.free_lengths(margin, settings.no_return_cap), 0.0)
    return reach, sample_counts(reach, step)


def labelled_box(clouds: Sequence[CloudScan], **model_options: Any) -> NDArray[np.float64]:
    """The bounding box of the labelled points of `clouds` (hits and the free samples the
    clearance keeps, :meth:`~gpomap.settings.MapSettings.make_observations`), without making them all.

    The clearance drops only free samples, and only those outside the hits' box can widen it;
    a sample's every coordinate is monotone along its ray (the same rounded products and sums as
    :func:`gpomap.observations.ray_free_points`), so a ray's samples inside the hits' box are one
    run of steps, checked at its two ends and skipped. The rest are asked about the clearance
    against every hit, as the whole's are: the box is the whole's to the bit. Where a scan's free
    samples are merged by cube (a depth frame's), each kept point is one of the samples the
    clearance keeps, so the box holds the merged points too, and may be wider by part of a cube.

    Parameters
    ----------
    clouds : sequence of CloudScan
    **model_options
        The map settings (:class:`~gpomap.settings.MapSettings`).

    Returns
    -------
    ndarray of shape (2, 3)
        The lowest and the highest coordinates.

    Raises
    ------
    EmptyDataError
        As :meth:`~gpomap.settings.MapSettings.make_observations`: no readings, or a class missing.
    """
    from gpomap.observations import Rays, free_near_hits
    from gpomap.settings import MapSettings

    settings = MapSettings(**model_options)
    step = float(settings.free_step)
    rays = [Rays.of(c) for c in clouds]
    hits = [r.ends[r.hit] for r in rays]
    counts = [_free_samples_along(r, settings)[1] for r in rays]
    n_hits = sum(len(h) for h in hits)
    if n_hits == 0 or not any(c.any() for c in counts):
        # make_observations' own error (a class missing, or no readings at all).
        obs = settings.make_observations(list(clouds))
        return np.array([obs.points.min(axis=0), obs.points.max(axis=0)])
    all_hits = np.concatenate(hits)
    box = np.array([all_hits.min(axis=0), all_hits.max(axis=0)])
    outside = [_samples_outside(r.origin, r.directions, k, step, box) for r, k in zip(rays, counts, strict=True)]
    free = np.concatenate(outside)
    if free.shape[0] == 0:
        return box
    clearance = settings.clearance(3)
    if clearance > 0:
        occupied = np.r_[np.zeros(free.shape[0], bool), np.ones(n_hits, bool)]
        free = free[~free_near_hits(np.concatenate([free, all_hits]), occupied, clearance)[: free.shape[0]]]
    if free.shape[0]:
        box = np.array([np.minimum(box[0], free.min(axis=0)), np.maximum(box[1], free.max(axis=0))])
    return box


def _samples_outside(
    origin: NDArray[np.float64], directions: NDArray[np.float64], counts: NDArray[np.intp], step: float, box: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The free samples (at ``step, 2 step, ..., counts[r] step`` along each ray, shape (b, 3) of
    `directions`) that may lie outside `box` (2, 3): each ray's but for a run, both of whose
    ends are inside the box, so every sample between is (its coordinates are monotone along it).

    Returns
    -------
    ndarray of shape (m, 3)
        The samples as :func:`gpomap.observations.ray_free_points` computes them.
    """
    o = np.asarray(origin, dtype=float)
    use = counts > 0
    d, n = directions[use], counts[use].astype(np.int64)
    # The steps where each ray is inside the box, estimated by the slab method, one step
    # inside either way ...
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (box[0] - o) / d, (box[1] - o) / d
        enter = np.nan_to_num(np.minimum(t0, t1), nan=-np.inf).max(axis=1)
        leave = np.nan_to_num(np.maximum(t0, t1), nan=np.inf).min(axis=1)
        first = np.clip(np.ceil(enter / step) + 1, 1, n + 1).astype(np.int64)
        last = np.clip(np.floor(leave / step) - 1, 0, n).astype(np.int64)
    # ... and skipped only where the samples at both ends are inside indeed.
    ok = first <= last
    for k in (first, last):
        at = o + (k * step)[:, None] * d
        ok &= ((at >= box[0]) & (at <= box[1])).all(axis=1)
    first, last = np.where(ok, first, n + 1), np.where(ok, last, n)
    before, m = first - 1, first - 1 + n - last  # steps 1..before, then last + 1..n
    ray = np.repeat(np.arange(n.size), m)
    j = np.arange(ray.size) - np.repeat(np.cumsum(m) - m, m)
    k = np.where(j < before[ray], j + 1, last[ray] + 1 + j - before[ray])
    return o + (k * step)[:, None] * d[ray]


def new_model(tile_options: dict[str, Any] | None = None, **model_options: Any) -> Any:
    """The unfitted 3-D model, :class:`~gpomap.mapping.AreaGPOM` with `tile_options` (tile_size, n_workers, ...) and the map settings."""
    from gpomap.mapping import AreaGPOM

    return AreaGPOM(**(tile_options or {}), **model_options)
