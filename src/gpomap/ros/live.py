"""A live map between a robot's messages and its published grids, free of any middleware.

:class:`LiveMap` holds what a mapping node does between its subscriptions and its publications:
laser scans wait until the pose of their frame is known at their stamp, then go to the streaming
mapper (:class:`gpomap.streaming.StreamingGPOM`) in the order they came; the map is sampled as
the three grid layers on request, and saved in the project's formats. With ``kind="cloud"`` it maps
``sensor_msgs/PointCloud2`` clouds in 3-D instead: the pose is the sensor's 4 x 4 matrix, the map
is read as a voxel map (:meth:`LiveMap.voxels`) and saved as the voxel output set. The ROS 1 node
(:mod:`gpomap.ros.node`) wires it to rospy and tf2; the ROS 2 node (:mod:`gpomap.ros2.node`) wires
the same object to rclpy. Every method may be called from any thread: a lock keeps the mapper to one caller at a time.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import InputFormatError
from gpomap.ros.messages import GridLayers, cloud_from_pointcloud2, grid_layers, scan_from_laserscan, stamp_seconds

__all__ = ["LiveMap", "PoseLookup"]

#: ``lookup(frame, seconds)``: the pose (x, y, yaw) of `frame` in the fixed frame at that time,
#: or None while it is not known (yet); (x, y, yaw, upside_down) for a frame that may be mounted
#: upside down (its beams are then mirrored: :func:`gpomap.ros.messages.is_upside_down`).
PoseLookup = Callable[[str, float], "tuple[float, float, float] | tuple[float, float, float, bool] | None"]


class LiveMap:
    """Scans in, occupancy grids out: a streaming mapper fed from a robot's messages.

    Parameters
    ----------
    mapper : StreamingGPOM
        The streaming mapper (anything with its ``add_scan``, ``ready_``, ``grid``, ``n_scans_``,
        ``hyperparameters_`` and ``summary``).
    resolution : float
        Cell side of the published and saved grids, metres.
    extent : (xmin, xmax, ymin, ymax), optional
        Region of the grids; default the data's (the grid grows with the map).
    time_offset : float
        Seconds added to each scan stamp before its pose is looked up (0.1 for Stage bags: see
        :data:`gpomap.io.rosbag.STAGE_TIME_OFFSET`).
    max_range : float, optional
        No-return threshold, metres; default each message's ``range_max``.
    pose_wait : float
        Seconds (of the `clock`) a scan may wait for its pose; after that it is dropped and
        counted in :meth:`status`.
    source : str
        The scan topic, for error messages.
    clock : callable
        Monotonic seconds (``time.monotonic``); tests pass their own.
    kind : {"scan", "cloud"}
        ``scan``: ``sensor_msgs/LaserScan`` messages, planar poses, a 2-D map. ``cloud``:
        ``sensor_msgs/PointCloud2`` messages, the lookup gives the sensor's pose as a 4 x 4 matrix,
        a 3-D map (`extent` then x, y only; the voxels span the data's height).
    """

    def __init__(
        self,
        mapper: Any,
        resolution: float,
        extent: tuple[float, float, float, float] | None = None,
        time_offset: float = 0.0,
        max_range: float | None = None,
        pose_wait: float = 1.0,
        source: str = "scan",
        clock: Callable[[], float] = time.monotonic,
        kind: str = "scan",
    ) -> None:
        if kind not in ("scan", "cloud"):
            raise ValueError(f"kind must be 'scan' or 'cloud', got {kind!r}")
        if not resolution > 0:
            raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
        if not pose_wait >= 0:
            raise ValueError(f"pose_wait must be >= 0 seconds, got {pose_wait}")
        self.mapper = mapper
        self.resolution = float(resolution)
        self.extent = extent
        self.time_offset = float(time_offset)
        self.max_range = max_range
        self.pose_wait = float(pose_wait)
        self.source = source
        self.clock = clock
        self.kind = kind
        #: The map's dimension: 2 for scans, 3 for clouds.
        self.dim = 3 if kind == "cloud" else 2
        # Corners of every valid cloud point and origin so far (3-D): the voxel map's default box.
        self._lower: np.ndarray | None = None
        self._upper: np.ndarray | None = None
        self._waiting: deque[tuple[Any, float]] = deque()
        self._lock = threading.Lock()
        self.n_received = 0
        self.n_dropped = 0
        self.n_rejected = 0
        self.last_error: str | None = None
        #: Stamp (seconds) of the newest scan given to the mapper; the published grids carry it.
        self.stamp: float | None = None
        self.n_used = 0
        # The latest scans' add_scan seconds: a bounded window, a robot runs for hours.
        self._latency: deque[float] = deque(maxlen=1000)

    # ------------------------------------------------------------------ in
    def receive(self, msg: Any) -> None:
        """Queue one ``sensor_msgs/LaserScan`` (cheap: called from the subscription's thread)."""
        self._waiting.append((msg, self.clock()))
        self.n_received += 1

    def process(self, lookup: PoseLookup, budget: float | None = None) -> int:
        """Give the mapper the waiting scans whose pose is known, in the order they came.

        A scan whose pose is not known yet stops the queue (those behind it are newer and tf
        arrives in time order); once it has waited `pose_wait` seconds it is dropped.

        Parameters
        ----------
        lookup : PoseLookup
        budget : float, optional
            Stop after this many seconds (of the `clock`) even if scans are left, so that a
            node keeps its publishing rate while it catches up; default: until none is left.

        Returns
        -------
        int
            Scans added to the map.
        """
        added = 0
        stop = None if budget is None else self.clock() + budget
        with self._lock:
            while self._waiting and (stop is None or added == 0 or self.clock() < stop):
                msg, arrived = self._waiting[0]
                stamp = stamp_seconds(msg.header.stamp)
                frame = str(msg.header.frame_id).lstrip("/")
                pose = lookup(frame, stamp + self.time_offset)
                if pose is None:
                    if self.clock() - arrived < self.pose_wait:
                        break
                    self._waiting.popleft()
                    self.n_dropped += 1
                    continue
                self._waiting.popleft()
                try:
                    scan: Any
                    if self.kind == "cloud":
                        scan = cloud_from_pointcloud2(msg, np.asarray(pose), self.max_range, source=self.source)
                        self._grow(scan)
                    else:
                        flipped = len(pose) == 4 and bool(pose[3])
                        scan = scan_from_laserscan(msg, pose[:3], self.max_range, source=self.source, upside_down=flipped)
                except InputFormatError as exc:
                    # One bad message must not stop a robot's map: count it, keep its reason.
                    self.n_rejected += 1
                    self.last_error = str(exc)
                    continue
                t = time.perf_counter()
                self.mapper.add_scan(scan)
                self._latency.append(time.perf_counter() - t)
                self.n_used += 1
                self.stamp = stamp
                added += 1
        return added

    def _grow(self, cloud: Any) -> None:
        pts = np.vstack([cloud.points[cloud.valid()], cloud.origin[None, :]])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        self._lower = lo if self._lower is None else np.minimum(self._lower, lo)
        self._upper = hi if self._upper is None else np.maximum(self._upper, hi)

    # ------------------------------------------------------------------ out
    @property
    def ready(self) -> bool:
        """Whether the mapper has learnt its hyperparameters (before that there is no map)."""
        return bool(getattr(self.mapper, "ready_", False))

    def _grid(self) -> Any:
        return self.mapper.grid(self.resolution, self.extent)

    def layers(self) -> GridLayers | None:
        """The trinary, probability and variance layers of the current map; None before it is ready (or in 3-D)."""
        if self.dim == 3:
            return None
        with self._lock:
            if not self.ready:
                return None
            occupancy_map = self._grid()
            prior = self.mapper.hyperparameters_.get("variance")
        return grid_layers(occupancy_map, prior)

    def voxel_bounds(self) -> tuple[Any, Any]:
        """Lower and upper corners (x, y, z), shape (3,) each, of the voxel map: the clouds' box grown
        by :data:`gpomap.lattice.EXTENT_MARGIN_CELLS` voxels, x and y from `extent` where given (as ``gpomap map``)."""
        from gpomap.lattice import EXTENT_MARGIN_CELLS

        if self._lower is None or self._upper is None:
            raise self._not_ready()
        pad = EXTENT_MARGIN_CELLS * self.resolution
        lo, hi = self._lower - pad, self._upper + pad
        if self.extent is not None:
            lo[:2], hi[:2] = (self.extent[0], self.extent[2]), (self.extent[1], self.extent[3])
        return lo, hi

    def voxels(self, memory_limit: int | None = None) -> Any:
        """The current 3-D map as a :class:`~gpomap.voxels.VoxelMap` at `resolution` over :meth:`voxel_bounds`.

        Raises
        ------
        NotFittedError
            Before the mapper is ready.
        MemoryLimitError
            The voxel grid would not fit in `memory_limit` (default :func:`gpomap.resources.memory_limit`'s).
        """
        with self._lock:
            return self._voxels(memory_limit)

    def _voxels(self, memory_limit: int | None = None) -> Any:
        from gpomap.lattice import bounds_extent
        from gpomap.resources import check_memory, voxel_grid_memory, voxel_shape
        from gpomap.resources import memory_limit as default_limit

        if self.dim != 3:
            raise ValueError("a voxel map needs clouds (kind='cloud')")
        self._require_ready()
        lo, hi = self.voxel_bounds()
        limit, source = (memory_limit, "the limit given") if memory_limit is not None else default_limit()
        nz, ny, nx = voxel_shape(lo, hi, self.resolution)
        what = f"a {nx} x {ny} x {nz} voxel grid at resolution {self.resolution:g} m"
        check_memory(voxel_grid_memory((nz, ny, nx)), limit, what, "set a coarser resolution or an x, y extent", source)
        self.mapper.refresh()
        return self.mapper.model_.grid(self.resolution, bounds_extent(lo, hi))

    def query(self, points: Any) -> tuple[Any, Any, Any]:
        """Occupancy probability, latent variance and ternary label at points, from the current map.

        Parameters
        ----------
        points : array-like of shape (m, 2), or (m, 3) for clouds
            x, y (z) in the fixed frame, metres.

        Returns
        -------
        probability, variance : ndarray of shape (m,)
            Outside the observed region the map's prior: 0.5 and the prior variance.
        ternary : ndarray of int8, shape (m,)
            The written map's call: 0 free, -1 unknown, 1 occupied (:meth:`gpomap.fitted.FittedMap.predict_ternary`).

        Raises
        ------
        NotFittedError
            Before the mapper is ready.
        """
        pts = np.asarray(points, dtype=float).reshape(-1, self.dim)
        with self._lock:
            self._require_ready()
            probability, variance = self.mapper.predict_proba(pts, return_var=True)
            ternary = self.mapper.predict_ternary(pts, refresh=False, probability=probability)
        return np.asarray(probability, dtype=float), np.asarray(variance, dtype=float), ternary

    def render(
        self, resolution: float, extent: tuple[float, float, float, float] | None = None, memory_limit: int | None = None
    ) -> GridLayers:
        """The map's layers on any grid: `resolution` over `extent` (default the data's).

        Parameters
        ----------
        resolution : float
            Cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
        memory_limit : int, optional
            Bytes; default :func:`gpomap.resources.memory_limit`'s. A grid that would need more
            is refused before any prediction.

        Returns
        -------
        GridLayers

        Raises
        ------
        NotFittedError
            Before the mapper is ready.
        MemoryLimitError
            The grid would not fit in `memory_limit`.
        """
        from gpomap.resources import check_memory, grid_memory, grid_shape
        from gpomap.resources import memory_limit as default_limit

        if not (np.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
        if self.dim == 3:
            raise ValueError("a planar render of a 3-D map: read its voxels (map_cloud) or query points")
        with self._lock:
            self._require_ready()
            if extent is None:
                extent = self.mapper.default_grid(resolution).extent
            limit, source = (memory_limit, "the limit given") if memory_limit is not None else default_limit()
            ny, nx = grid_shape(extent, resolution)
            what = f"a {nx} x {ny} grid ({nx * ny:.3g} cells) at resolution {resolution:g} m"
            check_memory(grid_memory((ny, nx)), limit, what, "ask for a coarser resolution or a smaller extent", source)
            occupancy_map = self.mapper.grid(resolution, extent)
            prior = self.mapper.hyperparameters_.get("variance")
        return grid_layers(occupancy_map, prior)

    def _require_ready(self) -> None:
        if not self.ready:
            raise self._not_ready()

    def _not_ready(self) -> Exception:
        from gpomap.errors import NotFittedError

        return NotFittedError(
            f"no map yet: {self.mapper.n_scans_} scans seen, the hyperparameters are learnt after the warm-up scans"
        )

    def save(self, directory: str | os.PathLike[str], pgm_mode: str = "trinary") -> list[Path]:
        """Write the current map as one set: ``map.yaml`` + ``map.pgm``, ``map.npz``, ``map.png``,
        and the fitted map itself, ``map.gpom`` (:mod:`gpomap.io.mapfile`: render, query, update later).

        In 3-D: the voxel output set of ``gpomap map`` (:func:`gpomap.io.voxel_outputs.write_voxel_outputs`:
        ``map.npz``, ``map.bt``, ``map.ply``, the two figures, ``map.gpom``).

        Parameters
        ----------
        directory : path-like
            Created if missing; the previous set there is replaced as a whole
            (:func:`gpomap.io.atomic.output_set`).
        pgm_mode : {"trinary", "scale"}

        Returns
        -------
        list of Path

        Raises
        ------
        NotFittedError
            Before the mapper is ready.
        """
        from gpomap.io.atomic import output_set
        from gpomap.io.export import write_map_files
        from gpomap.io.mapfile import FILENAME, save_fitted_map

        if self.dim == 3:
            import functools

            from gpomap.io.voxel_outputs import write_voxel_outputs

            with self._lock:
                # Under the lock: the model must not take a cloud while it is written.
                voxel_map = self._voxels()
                return write_voxel_outputs(
                    voxel_map,
                    directory,
                    title="gpomap: live map",
                    save_model=functools.partial(save_fitted_map, self.mapper.model_),
                )
        with self._lock, output_set(directory) as outputs:
            # Under the lock: the model must not take a scan while it is written.
            self._require_ready()
            occupancy_map = self._grid()
            staged = [save_fitted_map(self.mapper.model_, outputs.path / FILENAME)]
            staged += write_map_files(occupancy_map, outputs.path, pgm_mode=pgm_mode, title="gpomap: live map")
        return [outputs.final(p) for p in staged]

    def status(self) -> dict[str, Any]:
        """Counts, and the latency of the mapper's ``add_scan`` over the latest 1,000 scans (milliseconds)."""
        lat = np.asarray(self._latency, dtype=float)
        return {
            "ready": self.ready,
            "n_received": self.n_received,
            "n_used": self.n_used,
            "n_waiting": len(self._waiting),
            "n_dropped_no_pose": self.n_dropped,
            "n_rejected": self.n_rejected,
            "last_error": self.last_error,
            "stamp": self.stamp,
            "latency_ms": {
                "median": float(np.median(lat) * 1e3) if lat.size else None,
                "p95": float(np.percentile(lat, 95) * 1e3) if lat.size else None,
                "max": float(lat.max() * 1e3) if lat.size else None,
            },
        }
