"""Scoring a map against a true floor plan, pixel by pixel, where the log looked.

A simulated log comes with the plan it was simulated over; a map is scored against it on the
plan's own pixels. The test points are every plan pixel whose centre lies within
:data:`OBSERVED_RADIUS` of a point the log observed (a hit, or a point sampled every
:data:`OBSERVED_STEP` along a beam; no-return beams to :data:`NO_RETURN_CAP`), each weighted
once; a pixel's label is the plan's, and a map's prediction there is the probability of the map
cell holding the pixel's centre. So space the robot never looked at is not scored, and a wall
scores as thick as the plan draws it: a map that smears walls over free space pays for it.

"Boundary" pixels lie within :data:`BOUNDARY_RADIUS` of a true occupied pixel: their AUC is the
map's wall sharpness.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from gpomap.metrics import brier_score, expected_calibration_error, iou, log_loss, roc_auc
from gpomap.observations import observations_from_scans
from gpomap.scans import Scan

#: A pixel is scored if its centre lies this close (m) to an observed point: half a 0.05 m map cell.
OBSERVED_RADIUS: float = 0.025
#: Spacing (m) of the points sampled along each beam.
OBSERVED_STEP: float = 0.01
#: No-return beams are observed free space to this distance (m).
NO_RETURN_CAP: float = 10.0
#: Boundary pixels: within this distance (m) of a true occupied pixel.
BOUNDARY_RADIUS: float = 0.1
#: Observed points are merged on a lattice this fine (m) before the distance query: a whole log
#: samples tens of millions of points along its beams, most of them repeats.
_MERGE: float = 0.005
#: map_server's default ternary thresholds (free below, occupied above): how a grid's users read it.
MAP_SERVER_THRESHOLDS: tuple[float, float] = (0.196, 0.65)
#: Most cells of the merge raster (bytes, as booleans): a larger plan merges on a coarser lattice.
_MAX_RASTER_CELLS: int = 200_000_000
#: Scans sampled at a time.
_CHUNK: int = 100

#: Side, in pixels, of the blocks :meth:`PlanTruth.from_world` screens for walls before it measures each pixel.
_WALL_BLOCK: int = 16


@dataclass(frozen=True)
class PlanTruth:
    """A true floor plan as pixels.

    Attributes
    ----------
    occupied : ndarray of bool, shape (h, w)
        Row 0 at the top (image order).
    lower_left : (float, float)
        Map-frame position of the plan's lower-left corner, metres.
    pixel_size : (float, float)
        Pixel width and height, metres.
    known : ndarray of bool, shape (h, w), optional
        Pixels the plan knows (default: every one); the others are never scored.
    """

    occupied: NDArray[np.bool_]
    lower_left: tuple[float, float]
    pixel_size: tuple[float, float]
    known: NDArray[np.bool_] | None = None

    @classmethod
    def from_image(cls, path: str | Path, resolution: float, origin: tuple[float, float] = (0.0, 0.0)) -> PlanTruth:
        """A plan image (dark = occupied, below 128) with square pixels of `resolution` metres."""
        from PIL import Image

        img = np.asarray(Image.open(path).convert("L"))
        return cls(img < 128, (float(origin[0]), float(origin[1])), (float(resolution), float(resolution)))

    @classmethod
    def from_world(cls, world: Any, resolution: float = 0.01) -> PlanTruth:
        """A simulated world (:class:`gpomap.simulate.World`) drawn at `resolution`, its walls one pixel thick."""
        x0, x1, y0, y1 = world.bounds
        w, h = int(np.ceil((x1 - x0) / resolution)), int(np.ceil((y1 - y0) / resolution))
        rows, cols = np.indices((h, w))
        centres = np.column_stack([x0 + (cols.ravel() + 0.5) * resolution, y0 + (h - rows.ravel() - 0.5) * resolution])
        # Walls are measured only in blocks whose centre lies near one: a pixel is at least its
        # block centre's distance less half the block's diagonal from every wall.
        block = _WALL_BLOCK
        brow, bcol = rows.ravel() // block, cols.ravel() // block
        nbc = (w + block - 1) // block
        bcx = x0 + (np.arange(nbc) + 0.5) * block * resolution
        nbr = (h + block - 1) // block
        bcy = y0 + h * resolution - (np.arange(nbr) + 0.5) * block * resolution
        bx, by = np.meshgrid(bcx, bcy)
        near = world.distance_to_walls(
            np.column_stack([bx.ravel(), by.ravel()])
        ) <= 0.5 * resolution + block * resolution * np.sqrt(0.5)
        candidates = np.flatnonzero(near[brow * nbc + bcol])
        occupied = world.inside_obstacle(centres)
        occupied[candidates] |= world.distance_to_walls(centres[candidates]) <= 0.5 * resolution
        return cls(occupied.reshape(h, w), (float(x0), float(y0)), (float(resolution), float(resolution)))

    @classmethod
    def from_rosmap(cls, rosmap: Any) -> PlanTruth:
        """A ROS map_server map (:func:`gpomap.io.rosmap.read_rosmap`) as the plan: occupied above
        its YAML's ``occupied_thresh``, its unknown pixels never scored."""
        g = rosmap.grid
        # RosMap's rows start at the lowest y; a plan's at the top.
        return cls(
            np.asarray(rosmap.occupied[::-1], dtype=bool),
            (float(g.origin[0]), float(g.origin[1])),
            (float(g.resolution), float(g.resolution)),
            ~np.asarray(rosmap.unknown[::-1], dtype=bool),
        )

    def centres(self) -> NDArray[np.float64]:
        """Every pixel's centre in the map frame, shape (h * w, 2), in image order."""
        h, w = self.occupied.shape
        rows, cols = np.indices((h, w))
        x = self.lower_left[0] + (cols.ravel() + 0.5) * self.pixel_size[0]
        y = self.lower_left[1] + (h - rows.ravel() - 0.5) * self.pixel_size[1]
        return np.column_stack([x, y])

    def boundary(self, radius: float = BOUNDARY_RADIUS) -> NDArray[np.bool_]:
        """Pixels within `radius` of a true occupied pixel, shape (h * w,)."""
        if not self.occupied.any():
            return np.zeros(self.occupied.size, dtype=bool)
        distance = distance_transform_edt(~self.occupied, sampling=(self.pixel_size[1], self.pixel_size[0]))
        return np.asarray(distance <= radius + 1e-9).ravel()

    def observed(self, scans: Sequence[Scan], radius: float = OBSERVED_RADIUS, step: float = OBSERVED_STEP) -> NDArray[np.bool_]:
        """Pixels whose centre lies within `radius` of a point `scans` observed, shape (h * w,)."""
        # Points on the merge lattice, as cells of a raster over the plan (grown by the radius); a
        # plan of a whole building merges coarser, so the raster stays within _MAX_RASTER_CELLS.
        h, w = self.occupied.shape
        width, height = w * self.pixel_size[0] + 2 * radius, h * self.pixel_size[1] + 2 * radius
        merge = max(_MERGE, float(np.sqrt(width * height / _MAX_RASTER_CELLS)))
        pad = radius + merge
        lo = np.asarray(self.lower_left) - pad
        shape = (int(np.ceil((width + 2 * merge) / merge)), int(np.ceil((height + 2 * merge) / merge)))
        seen = np.zeros(shape[0] * shape[1], dtype=bool)
        for start in range(0, len(scans), _CHUNK):
            obs = observations_from_scans(list(scans[start : start + _CHUNK]), step, step, NO_RETURN_CAP, free_clearance=0.0)
            q = np.floor((obs.points - lo) / merge).astype(np.int64)
            inside = (q >= 0).all(axis=1) & (q[:, 0] < shape[0]) & (q[:, 1] < shape[1])
            seen[q[inside, 0] * shape[1] + q[inside, 1]] = True
        flat = np.flatnonzero(seen)
        points = lo + (np.column_stack([flat // shape[1], flat % shape[1]]) + 0.5) * merge
        if points.size == 0:
            return np.zeros(self.occupied.size, dtype=bool)
        # The merge moves a point by at most half the lattice's diagonal: searched that much wider.
        reach = radius + merge * np.sqrt(0.5)
        d, _ = cKDTree(points).query(self.centres(), distance_upper_bound=reach)
        return np.asarray(d <= reach)


@dataclass(frozen=True)
class TruthPoints:
    """The scored pixels of a plan for one log (:meth:`PlanTruth.observed`).

    Attributes
    ----------
    points : ndarray of shape (n, 2)
        Pixel centres.
    occupied : ndarray of bool, shape (n,)
    boundary : ndarray of bool, shape (n,)
    """

    points: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    boundary: NDArray[np.bool_]

    @classmethod
    def of(cls, plan: PlanTruth, scans: Sequence[Scan]) -> TruthPoints:
        """The pixels of `plan` that `scans` observed."""
        seen = plan.observed(scans)
        if plan.known is not None:
            seen &= plan.known.ravel()
        return cls(plan.centres()[seen], plan.occupied.ravel()[seen], plan.boundary()[seen])


def score_plan(truth: TruthPoints, prob: NDArray[np.float64], occupied: NDArray[np.bool_] | None = None) -> dict[str, Any]:
    """Every truth metric of one map at the scored pixels.

    Parameters
    ----------
    truth : TruthPoints
    prob : ndarray of shape (n,)
        The map's probability at ``truth.points``.
    occupied : ndarray of bool, shape (n,), optional
        The map's ternary occupied class there (for ``ternary_iou``).

    Returns
    -------
    dict
        ``auc``, ``boundary_auc``, ``log_loss``, ``brier``, ``ece`` (10 bins), ``iou`` (occupied
        at p > 0.5), ``ternary_iou`` (None without `occupied`), ``n_points``, ``n_occupied``.
    """
    y = truth.occupied
    p = np.clip(np.asarray(prob, dtype=float), 0.0, 1.0)
    b = truth.boundary
    both = y.any() and not y.all()
    return {
        "auc": roc_auc(y, p) if both else None,
        "boundary_auc": roc_auc(y[b], p[b]) if y[b].any() and not y[b].all() else None,
        "log_loss": log_loss(y, p),
        "brier": brier_score(y, p),
        "ece": expected_calibration_error(y, p, 10),
        "iou": iou(p > 0.5, y),
        "ternary_iou": None if occupied is None else iou(np.asarray(occupied, dtype=bool), y),
        "n_points": int(y.size),
        "n_occupied": int(y.sum()),
    }
