"""The evaluation protocol: hold out scans, test on their hits and free space, score what users get.

1. ``scan_range`` (a ``"FIRST:LAST"`` window, Python slice semantics: LAST excluded) picks the
   part of the log to use, and ``scan_step`` thins it (every k-th scan) before anything else.
2. :func:`holdout_split` holds out scans, never trained on. The protocol's two splits
   (:data:`SPLITS`): ``"blocks"`` = ``"blocks:40:5"``, blocks of 40 consecutive scans with every
   5th block held out (whole stretches of the trajectory unseen, as Hilbert maps does), and
   ``"every"`` = ``"every:10"``, every 10th scan held out. Any ``"every:K"`` /
   ``"blocks:LEN[:K]"`` works too.
3. The training scans may be thinned to ``n_scans`` scans of ``n_beams`` beams
   (:func:`gpomap.scans.select_scans`); the test scans are used whole.
4. :func:`test_points`: every held-out hit (occupied) and free points every 0.1 m along each
   held-out beam up to 0.1 m short of its hit, with **no** clearance round hits (the GP methods
   drop free samples near walls when they train; the test does not, so a map that blurs walls
   pays for it); no-return beams give free points to the 10 m cap. A seeded uniform subsample
   keeps each class at its natural frequency (a few per cent of the points are hits), and every
   method is scored on the same points.
5. :func:`run_method` fits a method and scores two predictions at those points: the exact-point
   one (``model.predict_proba(points)``) and the **written grid** (what ``gpomap map`` writes:
   ``model.grid(resolution)`` at the output resolution, 0.05 m by default, then a cell lookup of
   each point; an occupancy grid's written map is its own grid). Scores (:func:`score`): ROC
   AUC, boundary AUC (test points within 0.5 m of a held-out hit: wall sharpness), AUC on the
   points in cells the reference grid observed (cells any training beam crossed, from the
   counting grid at 0.05 m) and on the rest, FPR at TPR 95 %, log loss (probabilities clipped at
   1e-6), Brier score, expected calibration error (10 equal-width bins) and the reliability diagram's bins.
   Also what the map says far from all data (> 5 m from any cell a training beam crossed), how
   many cells of the robot's own path (training and held-out poses) it calls occupied, and,
   where a true map exists (:class:`Truth`), AUC and occupied-class IoU against it on its grid.
6. :func:`evaluate` does all of it for one method.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError
from gpomap.grid import DEFAULT_THRESHOLDS, OCCUPIED, GridSpec, OccupancyMap
from gpomap.metrics import (
    brier_score,
    expected_calibration_error,
    fpr_at_tpr,
    iou,
    log_loss,
    reliability_bins,
    roc_auc,
    roc_curve,
)
from gpomap.observations import natural_subsample, observations_from_scans
from gpomap.resources import peak_rss_mb
from gpomap.scans import Scan, select_scans
from gpomap.truth import MAP_SERVER_THRESHOLDS, PlanTruth, TruthPoints, score_plan

if TYPE_CHECKING:
    from gpomap.io.rosmap import RosMap

#: "ogm" is the log-odds grid (OctoMap's model); "ogm-counting" the counting grid.
METHODS = ("msk", "gpomik", "gpom", "ogm", "ogm-logodds", "ogm-counting")
GRID_METHODS = ("ogm", "ogm-logodds", "ogm-counting")

#: Fraction held out by "blocks:LEN" without K: one block in five.
DEFAULT_BLOCK_PERIOD = 5
#: The protocol's two splits, by name.
SPLITS = {"blocks": "blocks:40:5", "every": "every:10"}
#: Test points: free every TEST_FREE_STEP along a held-out beam, stopping TEST_HIT_MARGIN short.
TEST_FREE_STEP = 0.1
TEST_HIT_MARGIN = 0.1
#: No-return beams: free to this distance (never beyond the sensor's max range), never a hit.
NO_RETURN_CAP = 10.0
#: Boundary test points: within this distance (m) of a held-out hit.
BOUNDARY_RADIUS = 0.5
#: The reference grid telling observed cells from unobserved ones (counting grid, metres).
REFERENCE_RESOLUTION = 0.05
#: The written map's resolution (m) unless told otherwise.
GRID_RESOLUTION = 0.05
#: "Far from all data": farther than this (m) from any cell a training beam crossed.
FAR_DISTANCE = 5.0
#: Far-field lattice spacing (m) and most lattice points predicted.
FAR_LATTICE = 0.25
FAR_MAX_POINTS = 2000
#: The robot's path is checked every this many metres (half the reference cell: no cell skipped).
PATH_STEP = 0.025


def resolve_split(split: str) -> str:
    """The hold-out spec a split name stands for ("blocks", "every"); other specs unchanged."""
    return SPLITS.get(str(split), str(split))


def _parse_holdout(holdout: str) -> tuple[str, int, int]:
    parts = str(holdout).split(":")
    try:
        if parts[0] == "every" and len(parts) == 2:
            return "every", int(parts[1]), 1
        if parts[0] == "blocks" and len(parts) in (2, 3):
            return "blocks", int(parts[1]), int(parts[2]) if len(parts) == 3 else DEFAULT_BLOCK_PERIOD
    except ValueError:
        pass
    raise ValueError(f"holdout must be 'every:K', 'blocks:LEN' or 'blocks:LEN:K' with integers, got {holdout!r}")


def check_split(split: str) -> str:
    """The hold-out spec of a split name or spec (see :func:`holdout_split`), checked before any work.

    Raises
    ------
    ValueError
        Not "blocks", "every", ``every:K`` or ``blocks:LEN[:K]`` with integers K >= 2, LEN >= 1.
    """
    spec = resolve_split(split)
    mode, size, period = _parse_holdout(spec)
    if mode == "every" and size < 2:
        raise ValueError(f"'every:K' needs K >= 2, got {spec!r}")
    if size < 1 or (mode == "blocks" and period < 2):
        raise ValueError(f"hold-out sizes must be >= 1 and periods >= 2, got {spec!r}")
    return spec


def holdout_split(n_scans: int, holdout: str = "every:5", seed: int = 0) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Split scan indices into training and held-out (test) scans; the two never overlap.

    Parameters
    ----------
    n_scans : int
        Number of scans (at least 2).
    holdout : str
        A split name ("blocks", "every": :data:`SPLITS`) or spec.
        ``"every:K"``: hold out every K-th scan, starting at a seeded phase in ``[0, K)``
        (about 1/K of the scans). ``"blocks:LEN"`` / ``"blocks:LEN:K"``: cut the sequence into
        consecutive blocks of LEN scans (the first block shortened by a seeded offset in
        ``[0, LEN)``) and hold out every K-th block (default K = 5, so about a fifth), starting at
        a seeded block phase. Held-out blocks keep whole stretches of the trajectory unseen, which
        tests extrapolation more than every-K-th interleaving does.
    seed : int

    Returns
    -------
    train_idx, test_idx : ndarray of int
        Sorted, disjoint, together ``arange(n_scans)``; both non-empty.
    """
    mode, size, period = _parse_holdout(check_split(holdout))
    if n_scans < 2:
        raise EmptyDataError(f"a hold-out split needs at least 2 scans, got {n_scans}")
    rng = np.random.default_rng(seed)
    idx = np.arange(n_scans)
    if mode == "every":
        phase = int(rng.integers(size))
        test = (idx - phase) % size == 0
    else:
        offset = int(rng.integers(size))
        phase = int(rng.integers(period))
        block = (idx + offset) // size
        test = block % period == phase
    # Tiny logs: guarantee both sides are non-empty without breaking disjointness.
    if not test.any():
        test[int(rng.integers(n_scans))] = True
    if test.all():
        test[int(rng.integers(n_scans))] = False
    return np.flatnonzero(~test), np.flatnonzero(test)


def protocol_points(
    scans: Sequence[Scan],
    free_step: float = TEST_FREE_STEP,
    hit_margin: float | None = TEST_HIT_MARGIN,
    no_return_cap: float | None = NO_RETURN_CAP,
) -> Any:
    """Every candidate test point of held-out scans, before balancing (see :func:`test_points`).

    Returns
    -------
    gpomap.observations.Observations
        Hits (occupied) and free points every `free_step` from `free_step` out to `hit_margin`
        short of each hit (no-return beams: to `no_return_cap`); no clearance round hits.
    """
    return observations_from_scans(scans, free_step, hit_margin, no_return_cap, free_clearance=0.0)


def test_points(
    scans: Sequence[Scan],
    free_step: float = TEST_FREE_STEP,
    seed: int = 0,
    max_points: int | None = None,
    hit_margin: float | None = TEST_HIT_MARGIN,
    no_return_cap: float | None = NO_RETURN_CAP,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Labelled test points from held-out scans, at their natural frequencies.

    Parameters
    ----------
    scans : sequence of Scan
        The held-out scans.
    free_step : float
        Spacing of free points along the beams (0.1 m: the protocol).
    seed : int
        Seed of the subsampling.
    max_points : int, optional
        Most test points in all: a uniform, seeded subsample, so each class keeps its share (along
        beams, a few per cent of the points are hits).
    hit_margin : float, optional
        Free points stop this short of a hit (0.1 m: the protocol; None: half of `free_step`).
        No clearance round other hits: a free point next to a wall stays a test point.
    no_return_cap : float, optional
        No-return beams give free points out to this distance (and never beyond the sensor's
        max range), never a hit. None: the max range.

    Returns
    -------
    points : ndarray of shape (m, 2)
    labels : ndarray of bool, shape (m,)
        True for occupied (a hit).
    """
    obs = protocol_points(scans, free_step, hit_margin, no_return_cap)
    n_occ = int(np.count_nonzero(obs.occupied))
    if n_occ == 0 or n_occ == obs.occupied.size:
        raise EmptyDataError(f"held-out scans give {n_occ} hits and {obs.occupied.size - n_occ} free points; need both")
    keep = natural_subsample(obs.occupied.size, obs.occupied.size if max_points is None else int(max_points), seed)
    return obs.points[keep], obs.occupied[keep]


# Not a pytest test despite its name (the protocol's term).
test_points.__test__ = False  # type: ignore[attr-defined]


def near(points: NDArray[np.float64], targets: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
    """Which points lie within `radius` of any target, ndarray of bool, shape (n,).

    Parameters
    ----------
    points : ndarray of shape (n, 2)
    targets : ndarray of shape (t, 2)
    radius : float
    """
    from scipy.spatial import cKDTree

    if len(targets) == 0:
        return np.zeros(len(points), dtype=bool)
    d, _ = cKDTree(targets).query(points, distance_upper_bound=radius)
    return d <= radius


def scan_window(scan_range: str | tuple[int | None, int | None] | None) -> slice:
    """The slice of a log that `scan_range` ("FIRST:LAST", a pair, or None) names."""
    if scan_range is None:
        return slice(None)
    if isinstance(scan_range, str):
        try:
            first, last = (int(v) if v.strip() else None for v in scan_range.split(":"))
        except ValueError:
            raise ValueError(f"scan_range must be 'FIRST:LAST' with integers, got {scan_range!r}") from None
    else:
        first, last = scan_range
    return slice(first, last)


def make_model(
    method: str, kernel: str | None = None, seed: int = 0, resolution: float = 0.1, n_workers: int | None = None, **options: Any
) -> Any:
    """The estimator `method` names, with `options` passed to its constructor.

    Parameters
    ----------
    method : {"msk", "gpomik", "gpom", "ogm", "ogm-logodds", "ogm-counting"}
        "ogm" is "ogm-logodds".
    kernel : {"se", "matern32"}, optional
        Point kernel of the GP methods (default: each method's own default). Ignored by the grids.
    seed : int
        Ignored by the grids.
    resolution : float
        Cell side of the grids (the GP methods predict anywhere).
    n_workers : int, optional
        "msk": workers for its tiles (default: the CPU count, as ``gpomap map``).
    """
    gp_opts = dict(options, seed=seed, **({"kernel": kernel} if kernel is not None else {}))
    if method == "msk":
        from gpomap.mapping import AreaGPOM

        return AreaGPOM(n_workers=n_workers, **gp_opts)
    if method == "gpomik":
        from gpomap.baselines.gpomik import GPOMIK

        return GPOMIK(**gp_opts)
    if method == "gpom":
        from gpomap.baselines.gpom import GPOM

        return GPOM(**gp_opts)
    if method in GRID_METHODS:
        from gpomap.baselines.ogm import OccupancyGridMapper

        model = "counting" if method == "ogm-counting" else "logodds"
        return OccupancyGridMapper(resolution=resolution, sensor_model=model, **options)
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")


def n_inputs(model: Any) -> int:
    """GP inputs of a fitted model (cells, beams or points); for a grid, the cells it observed."""
    if hasattr(model, "n_inputs_"):
        return int(model.n_inputs_)
    # Occupancy grid: the cells it observed are its "inputs".
    return int((model.observed_ > 0).sum())


def written_grid(model: Any, resolution: float = GRID_RESOLUTION) -> OccupancyMap:
    """The map ``gpomap map`` writes for a fitted model, at `resolution` over the data's extent.

    MSK-GPOM and the GP baselines: ``grid(resolution)``; an occupancy grid: its own grid (it has
    no finer map to give).
    """
    from gpomap.baselines.ogm import OccupancyGridMapper

    if isinstance(model, OccupancyGridMapper):
        return model.grid_map()
    return model.grid(resolution)


def lookup(occupancy_map: OccupancyMap, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Probability of the written map's cell holding each point (0.5 outside the map), shape (n,)."""
    rows, cols, inside = occupancy_map.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.full(len(rows), 0.5)
    out[inside] = occupancy_map.probability[rows[inside], cols[inside]]
    return out


def lookup_occupied(occupancy_map: OccupancyMap, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether the written map's ternary map calls the cell holding each point occupied (False
    outside the map), shape (n,)."""
    rows, cols, inside = occupancy_map.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.zeros(len(rows), dtype=bool)
    out[inside] = occupancy_map.ternary[rows[inside], cols[inside]] == OCCUPIED
    return out


def occupied_at(model: Any, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether a fitted model's ternary map calls each point occupied, shape (n,): its own
    ``predict_ternary`` where it has one (MSK-GPOM's fitted threshold, cells beams saw through
    never occupied), else its probability above the paper's occupied threshold (the grids)."""
    if hasattr(model, "predict_ternary"):
        return np.asarray(model.predict_ternary(points)) == OCCUPIED
    return np.asarray(model.predict_proba(points), dtype=float) > DEFAULT_THRESHOLDS[1]


def reference_grid(train: Sequence[Scan], resolution: float = REFERENCE_RESOLUTION) -> Any:
    """The counting grid of the training scans: which cells any training beam crossed."""
    from gpomap.baselines.ogm import OccupancyGridMapper

    return OccupancyGridMapper(resolution, sensor_model="counting", max_range_free=NO_RETURN_CAP).fit(train)


def observed_at(reference: Any, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether each point lies in a cell the reference grid observed, shape (n,)."""
    rows, cols, inside = reference.grid_.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.zeros(len(rows), dtype=bool)
    out[inside] = reference.observed_[rows[inside], cols[inside]] > 0
    return out


def path_points(scans: Sequence[Scan], step: float = PATH_STEP) -> NDArray[np.float64]:
    """Points every `step` along the robot's path through `scans` (in log order), shape (n, 2).

    The path joins consecutive scans' sensor positions where the map takes the robot to have
    driven (:func:`gpomap.evidence.path_steps`); jumps in the log are left out.
    """
    from gpomap.evidence import path_steps
    from gpomap.observations import sensor_positions

    if len(scans) == 0:
        return np.zeros((0, 2))
    out = [sensor_positions(scans)]
    for a, b in zip(*np.split(path_steps(scans), 2, axis=1)):
        length = float(np.hypot(*(b - a)))
        if length > 0:
            t = np.arange(step, length, step) / length
            out.append(a + t[:, None] * (b - a))
    return np.concatenate(out)


def path_occupied(
    prob: NDArray[np.float64] | None,
    points: NDArray[np.float64],
    cell: float = REFERENCE_RESOLUTION,
    occupied: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """How much of the robot's own path a map calls occupied (ternary threshold).

    Parameters
    ----------
    prob : ndarray of shape (n,), or None
        The map's probability at `points` (None with `occupied`).
    points : ndarray of shape (n, 2)
        :func:`path_points`.
    cell : float
        Path points are counted per cell of this side (a lattice from the origin), so a long
        stretch of path in one cell counts once.
    occupied : ndarray of bool, shape (n,), optional
        Whether the map's ternary map calls each point occupied (:func:`occupied_at`,
        :func:`lookup_occupied`), in place of `prob` above the paper's occupied threshold.

    Returns
    -------
    dict
        ``n_cells`` on the path, ``n_occupied`` of them with a point the map calls occupied (the
        robot drove through them: they should be none), ``fraction``.
    """
    if occupied is None:
        if prob is None:
            raise ValueError("path_occupied needs the map's probability or its occupied class")
        occupied = np.asarray(prob) > DEFAULT_THRESHOLDS[1]
    keys = np.floor(np.asarray(points, dtype=float) / cell).astype(np.int64)
    _, cell_of = np.unique(keys, axis=0, return_inverse=True)
    cell_of = cell_of.ravel()
    n = int(cell_of.max()) + 1 if cell_of.size else 0
    occupied_cells = np.zeros(n, bool)
    np.logical_or.at(occupied_cells, cell_of, np.asarray(occupied, dtype=bool))
    return {"n_cells": n, "n_occupied": int(occupied_cells.sum()), "fraction": float(occupied_cells.mean()) if n else 0.0}


@dataclass(frozen=True)
class FarField:
    """Distance to the data on a coarse lattice round it.

    Attributes
    ----------
    grid : GridSpec
        The lattice: the reference grid's box padded by ``2 * FAR_DISTANCE``, cells of FAR_LATTICE.
    distance : ndarray of shape (ny, nx)
        Distance (m) from each lattice cell centre to the nearest lattice cell holding an
        observed reference cell (exact to about one lattice cell).
    """

    grid: GridSpec
    distance: NDArray[np.float64]

    @classmethod
    def from_reference(cls, reference: Any, spacing: float = FAR_LATTICE, pad: float = 2 * FAR_DISTANCE) -> FarField:
        """The lattice round a fitted reference grid (see :func:`reference_grid`)."""
        from scipy.ndimage import distance_transform_edt

        x0, x1, y0, y1 = reference.grid_.extent
        grid = GridSpec.from_extent((x0 - pad, x1 + pad, y0 - pad, y1 + pad), spacing)
        seen = np.zeros(grid.shape, dtype=bool)
        r, c = np.nonzero(reference.observed_ > 0)
        centres = np.column_stack(reference.grid_.origin) + (np.column_stack([c, r]) + 0.5) * reference.grid_.resolution
        rr, cc, inside = grid.index_of(centres)
        seen[rr[inside], cc[inside]] = True
        return cls(grid, distance_transform_edt(~seen) * spacing)

    def distance_at(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance to the data of each point (inf outside the lattice), shape (n,)."""
        rows, cols, inside = self.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
        out = np.full(len(rows), np.inf)
        out[inside] = self.distance[rows[inside], cols[inside]]
        return out

    def far_points(self, distance: float = FAR_DISTANCE, max_points: int = FAR_MAX_POINTS, seed: int = 0) -> NDArray[np.float64]:
        """Lattice cell centres farther than `distance` from the data, at most `max_points` (seeded)."""
        idx = np.flatnonzero(self.distance.ravel() > distance)
        if idx.size > max_points:
            idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
        return self.grid.centres()[idx]


@dataclass(frozen=True)
class Truth:
    """A true occupancy map on a grid.

    Attributes
    ----------
    grid : GridSpec
    occupied : ndarray of bool, shape (ny, nx)
    known : ndarray of bool, shape (ny, nx)
        Cells to score (all of them by default).
    """

    grid: GridSpec
    occupied: NDArray[np.bool_]
    known: NDArray[np.bool_] | None = None

    @classmethod
    def from_world(cls, world: Any, resolution: float = GRID_RESOLUTION, wall_thickness: float | None = None) -> Truth:
        """A simulated world's true grid over its bounds (:meth:`gpomap.simulate.World.true_grid`), on
        the written maps' lattice (see :meth:`from_plan`)."""
        grid = GridSpec.from_extent(world.bounds, resolution, align=True)
        return cls(grid, world.true_grid(grid, wall_thickness))

    @classmethod
    def from_plan(
        cls,
        occupied_pixels: NDArray[np.bool_],
        lower_left: tuple[float, float],
        pixel_size: tuple[float, float],
        resolution: float = GRID_RESOLUTION,
        known_pixels: NDArray[np.bool_] | None = None,
    ) -> Truth:
        """A floor-plan bitmap resampled to `resolution`: a cell is occupied if any pixel in it is.

        The cells are those of every map written at `resolution` (corners on multiples of it, as
        ``gpomap map`` and the occupancy grids place theirs), not cells from the bitmap's corner:
        a map is scored cell for cell. Off that lattice every map cell straddles two true cells,
        and a wall one cell thick in the map is scored as two half-right cells, which costs a
        grid a good part of its IoU (docs/choices.md, "Measured for the code").

        Parameters
        ----------
        occupied_pixels : ndarray of bool, shape (h, w)
            Row 0 at the top (image order).
        lower_left : (x, y)
            Map-frame position of the bitmap's lower-left corner.
        pixel_size : (sx, sy)
            Pixel width and height, metres.
        resolution : float
        known_pixels : ndarray of bool, shape (h, w), optional
            The pixels the plan knows (default: every one); a cell is scored if any known pixel is
            in it, and occupied if any known occupied pixel is.
        """
        h, w = occupied_pixels.shape
        x0, y0 = lower_left
        grid = GridSpec.from_extent((x0, x0 + w * pixel_size[0], y0, y0 + h * pixel_size[1]), resolution, align=True)
        rows, cols = np.indices((h, w))
        centres = np.column_stack([x0 + (cols.ravel() + 0.5) * pixel_size[0], y0 + (h - rows.ravel() - 0.5) * pixel_size[1]])
        r, c, inside = grid.index_of(centres)
        scored = inside if known_pixels is None else inside & np.asarray(known_pixels, dtype=bool).ravel()
        occ = np.zeros(grid.shape, dtype=bool)
        hit = scored & occupied_pixels.ravel()
        occ[r[hit], c[hit]] = True
        known = np.zeros(grid.shape, dtype=bool)
        known[r[scored], c[scored]] = True
        return cls(grid, occ, known)

    @classmethod
    def from_rosmap(cls, rosmap: RosMap, resolution: float = GRID_RESOLUTION) -> Truth:
        """A ROS map_server map as the truth, resampled to `resolution` (:meth:`from_plan`).

        Its pixels are read as map_server reads them (:func:`gpomap.io.rosmap.read_rosmap`):
        occupied above the YAML's ``occupied_thresh``, free below ``free_thresh``, the rest unknown
        and not scored.
        """
        g = rosmap.grid
        # RosMap's rows start at the lowest y; from_plan takes image order.
        return cls.from_plan(
            rosmap.occupied[::-1], g.origin, (g.resolution, g.resolution), resolution, known_pixels=~rosmap.unknown[::-1]
        )

    def agreement(self, points: NDArray[np.float64], within: float = 0.1) -> float:
        """Share of `points` on the true map's walls: their cell within `within` of an occupied cell.

        A log and its true map in one frame put most hits on the walls; in different frames
        (another origin, a map frame against odometry) few.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
            Hits, metres. Points outside the grid count as off the walls.
        within : float
            Largest distance between the centres of a point's cell and an occupied cell, metres.

        Returns
        -------
        float
            In [0, 1]; 0 without points or without an occupied cell.
        """
        from scipy import ndimage

        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if len(pts) == 0 or not self.occupied.any():
            return 0.0
        # Distance from each cell's centre to the nearest occupied cell's centre, metres.
        distance = ndimage.distance_transform_edt(~self.occupied) * self.grid.resolution
        r, c, inside = self.grid.index_of(pts)
        near = distance[r[inside], c[inside]] <= within + 1e-9
        return float(near.sum() / len(pts))


def score_truth(
    truth: Truth,
    prob: NDArray[np.float64],
    observed: NDArray[np.bool_] | None = None,
    threshold: float = DEFAULT_THRESHOLDS[1],
    occupied: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """Score probabilities at the truth grid's cell centres against it.

    Parameters
    ----------
    truth : Truth
    prob : ndarray of shape (ny * nx,)
        Predicted occupancy at ``truth.grid.centres()``.
    observed : ndarray of bool, shape (ny * nx,), optional
        Cells the training data observed: also scored alone.
    threshold : float
        Occupied above this (the map's ternary threshold): the IoU's predicted class.
    occupied : ndarray of bool, shape (ny * nx,), optional
        The IoU's predicted class itself, the map's ternary map (:func:`occupied_at`,
        :func:`lookup_occupied`), in place of `prob` above `threshold`.

    Returns
    -------
    dict
        ``auc``, ``iou``, ``observed_auc``, ``observed_iou`` (None without `observed`),
        ``n_cells``, ``n_occupied_cells``.
    """
    known = np.ones(truth.occupied.size, bool) if truth.known is None else truth.known.ravel()
    y = truth.occupied.ravel()
    called = prob > threshold if occupied is None else np.asarray(occupied, dtype=bool)
    out: dict[str, Any] = {
        "auc": _auc_or_none(y[known], prob[known]),
        "iou": iou(called[known], y[known]),
        "n_cells": int(known.sum()),
        "n_occupied_cells": int(y[known].sum()),
        "observed_auc": None,
        "observed_iou": None,
    }
    if observed is not None:
        sel = known & observed
        out["observed_auc"] = _auc_or_none(y[sel], prob[sel])
        out["observed_iou"] = iou(called[sel], y[sel])
        out["n_observed_cells"] = int(sel.sum())
    return out


def _auc_or_none(labels: NDArray[np.bool_], prob: NDArray[np.float64]) -> float | None:
    """ROC AUC, or None where a subset holds only one class (JSON null, '-' in tables)."""
    if labels.size == 0 or labels.all() or not labels.any():
        return None
    return roc_auc(labels, prob)


def score(
    labels: NDArray[np.bool_],
    prob: NDArray[np.float64],
    masks: dict[str, NDArray[np.bool_]] | None = None,
    n_bins: int = 10,
    roc: bool = False,
) -> dict[str, Any]:
    """Every protocol metric of one prediction at the test points.

    Parameters
    ----------
    labels : ndarray of bool, shape (n,)
    prob : ndarray of shape (n,)
        Predicted occupancy probabilities (clipped to [0, 1] first).
    masks : dict of str to ndarray of bool, shape (n,), optional
        Subsets scored alone by AUC, as ``<name>_auc`` with ``n_<name>`` (e.g. "boundary",
        "observed", "unobserved"); None where a subset lacks a class.
    n_bins : int
        Bins of the expected calibration error and the reliability diagram.
    roc : bool
        Also return the ROC curve.

    Returns
    -------
    dict
        ``auc``, ``fpr_at_tpr95``, ``log_loss``, ``brier``, ``ece``, the subset AUCs, ``reliability``
        (``mean_prob``, ``frac_pos``, ``counts`` per bin; empty bins None) and, with `roc`,
        ``roc`` (``fpr`` and ``tpr`` lists, one point per distinct probability).
    """
    p = np.clip(np.asarray(prob, dtype=float), 0.0, 1.0)
    mean_p, frac, counts = reliability_bins(labels, p, n_bins)
    out: dict[str, Any] = {
        "auc": roc_auc(labels, p),
        "fpr_at_tpr95": fpr_at_tpr(labels, p, 0.95),
        "log_loss": log_loss(labels, p),
        "brier": brier_score(labels, p),
        "ece": expected_calibration_error(labels, p, n_bins),
    }
    for name, m in (masks or {}).items():
        out[f"{name}_auc"] = _auc_or_none(labels[m], p[m])
        out[f"n_{name}"] = int(m.sum())
    out["reliability"] = {
        "mean_prob": [None if np.isnan(v) else float(v) for v in mean_p],
        "frac_pos": [None if np.isnan(v) else float(v) for v in frac],
        "counts": counts.tolist(),
    }
    if roc:
        fpr, tpr, _ = roc_curve(labels, p)
        out["roc"] = {"fpr": fpr.tolist(), "tpr": tpr.tolist()}
    return out


def _spread(values: NDArray[np.float64]) -> dict[str, Any]:
    """Count, mean and standard deviation (None when empty)."""
    if values.size == 0:
        return {"n": 0, "mean": None, "std": None}
    return {"n": int(values.size), "mean": float(values.mean()), "std": float(values.std())}


def _clock() -> tuple[float, float]:
    """Wall time and CPU time of this process and its reaped children (tile workers), seconds."""
    t = os.times()
    return time.perf_counter(), time.process_time() + t.children_user + t.children_system


@dataclass
class EvalData:
    """One split of one log, ready to score any method on (see :func:`prepare`).

    Attributes
    ----------
    train, test : list of Scan
        Training scans (thinned as asked) and held-out scans (whole).
    points : ndarray of shape (n, 2)
    labels : ndarray of bool, shape (n,)
        The test points (natural frequencies) and their classes.
    masks : dict of str to ndarray of bool, shape (n,)
        "boundary" (within BOUNDARY_RADIUS of a held-out hit), "observed" and "unobserved" (the
        reference grid's cells).
    far_test : ndarray of bool, shape (n,)
        Test points farther than FAR_DISTANCE from every cell a training beam crossed.
    far_points : ndarray of shape (f, 2)
        Lattice points that far from the data.
    reference : OccupancyGridMapper
        The counting grid of the training scans at REFERENCE_RESOLUTION.
    truth : Truth or None
    truth_observed : ndarray of bool, shape (ny * nx,) or None
        Truth cells the reference grid observed.
    path : ndarray of shape (p, 2)
        Points along the robot's path through the whole window, training and held-out scans
        (:func:`path_points`).
    plan : TruthPoints or None
        A true plan's pixels that the window's scans observed (:mod:`gpomap.truth`).
    settings, seconds : dict
    """

    train: list[Scan]
    test: list[Scan]
    points: NDArray[np.float64]
    labels: NDArray[np.bool_]
    masks: dict[str, NDArray[np.bool_]]
    far_test: NDArray[np.bool_]
    far_points: NDArray[np.float64]
    reference: Any
    truth: Truth | None = None
    truth_observed: NDArray[np.bool_] | None = None
    path: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    plan: TruthPoints | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def prepare(
    scans: Sequence[Scan],
    holdout: str = "every",
    scan_range: str | tuple[int | None, int | None] | None = None,
    scan_step: int = 1,
    n_scans: int | None = None,
    n_beams: int | None = None,
    seed: int = 0,
    test_free_step: float = TEST_FREE_STEP,
    max_test_points: int | None = None,
    truth: Truth | None = None,
    plan: PlanTruth | None = None,
) -> EvalData:
    """Split a log, make the test points and everything scored about them, once for all methods.

    Parameters
    ----------
    scans : sequence of Scan
        The whole log.
    holdout : str
        A split name ("blocks", "every": :data:`SPLITS`) or spec (see :func:`holdout_split`).
    scan_range : "FIRST:LAST" or (first, last), optional
        Window of the log (Python slice), applied first.
    scan_step : int
        Keep every `scan_step`-th scan of the window (before the split).
    n_scans, n_beams : int, optional
        Thin the training scans to this many evenly spaced scans of this many beams.
    seed : int
        Seeds the split and the test-point subsample.
    test_free_step : float
        Spacing of free test points (0.1 m: the protocol).
    max_test_points : int, optional
        Cap on test points, a seeded uniform subsample.
    truth : Truth, optional
        True map to score against, cell by cell.
    plan : PlanTruth, optional
        True plan to score the written maps against, pixel by pixel where the window's scans
        looked (:class:`gpomap.truth.TruthPoints`).

    Returns
    -------
    EvalData
    """
    spec = resolve_split(holdout)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    if scan_step < 1:
        raise ValueError(f"scan_step must be >= 1, got {scan_step}")
    window = list(scans)[scan_window(scan_range)][::scan_step]
    train_idx, test_idx = holdout_split(len(window), spec, seed)
    train = select_scans([window[i] for i in train_idx], n_scans, n_beams)
    test = [window[i] for i in test_idx]
    seconds["split"] = time.perf_counter() - t
    t = time.perf_counter()
    points, labels = test_points(test, test_free_step, seed, max_test_points)
    hits = np.concatenate([s.hits() for s in test])
    seconds["test_points"] = time.perf_counter() - t
    t = time.perf_counter()
    reference = reference_grid(train)
    observed = observed_at(reference, points)
    far = FarField.from_reference(reference)
    masks = {"boundary": near(points, hits, BOUNDARY_RADIUS), "observed": observed, "unobserved": ~observed}
    truth_observed = observed_at(reference, truth.grid.centres()) if truth is not None else None
    seconds["reference"] = time.perf_counter() - t
    t = time.perf_counter()
    plan_points = TruthPoints.of(plan, window) if plan is not None else None
    seconds["plan"] = time.perf_counter() - t
    settings = {
        "holdout": spec,
        "scan_range": scan_range if scan_range is None or isinstance(scan_range, str) else list(scan_range),
        "scan_step": scan_step,
        "n_scans_in_range": len(window),
        "n_scans": n_scans,
        "n_beams": n_beams,
        "seed": seed,
        "test_free_step": test_free_step,
        "test_hit_margin": TEST_HIT_MARGIN,
        "no_return_cap": NO_RETURN_CAP,
        "max_test_points": max_test_points,
        "test_scan_indices": [int(i) for i in test_idx],
    }
    return EvalData(
        train,
        test,
        points,
        labels,
        masks,
        far.distance_at(points) > FAR_DISTANCE,
        far.far_points(seed=seed),
        reference,
        truth,
        truth_observed,
        path_points(window),
        plan_points,
        settings,
        seconds,
    )


def run_method(
    data: EvalData,
    method: str = "msk",
    kernel: str | None = None,
    seed: int = 0,
    resolution: float = 0.1,
    grid_resolution: float = GRID_RESOLUTION,
    n_workers: int | None = None,
    return_roc: bool = False,
    score_grid: bool = True,
    **method_options: Any,
) -> dict[str, Any]:
    """Fit one method on ``data.train`` and score its exact-point and written-grid predictions.

    Parameters
    ----------
    data : EvalData
    method : {"msk", "gpomik", "gpom", "ogm", "ogm-logodds", "ogm-counting"}
    kernel : {"se", "matern32"}, optional
        Point kernel of the GP methods (default: the library's).
    seed : int
        Seeds the method.
    resolution : float
        Cell side of the occupancy grids.
    grid_resolution : float
        Resolution of the written map of the GP methods (0.05 m).
    n_workers : int, optional
        Worker processes for tiles (default: the CPU count).
    return_roc : bool
        Also return the ROC curves: each score's ``roc`` (:func:`score`), the exact points' also
        as ``roc``.
    score_grid : bool
        Also build and score the written grid.
    **method_options
        Passed to the method's constructor.

    Returns
    -------
    dict
        JSON-serialisable: ``points`` and ``grid`` (each :func:`score`'s dict, ``grid`` None
        without `score_grid`), ``auc``, ``fpr_at_tpr95``, ``log_loss`` (the exact-point ones),
        ``far`` (mean and spread of the predictions far from the data: at far test points and on
        the far lattice, for both predictions), ``path`` (:func:`path_occupied` of both), ``truth`` (:func:`score_truth` of both, or None),
        ``plan`` (the written map against ``data.plan``, :func:`gpomap.truth.score_plan`, or None),
        ``seconds`` and ``cpu_seconds`` (``fit``, ``predict``, ``grid``; the model's own stages),
        ``peak_rss_mb`` (this process's peak so far), ``n_inputs``, ``n_train_scans``,
        ``n_test_scans``, ``n_test_points``, ``hyperparameters`` (GP methods), ``evidence`` (the ray
        evidence's calibration, MSK-GPOM), ``settings``.
    """
    seconds: dict[str, float] = {}
    cpu: dict[str, float] = {}
    w0, c0 = _clock()
    model = make_model(method, kernel, seed, resolution, n_workers, **method_options)
    model.fit(data.train)
    w1, c1 = _clock()
    prob = np.asarray(model.predict_proba(data.points), dtype=float)
    w2, c2 = _clock()
    seconds["fit"], cpu["fit"] = w1 - w0, c1 - c0
    seconds["predict"], cpu["predict"] = w2 - w1, c2 - c1
    for stage, value in getattr(model, "timings_", {}).items():
        if stage != "prediction" and isinstance(value, (int, float)):
            seconds[stage] = float(value)
    points_score = score(data.labels, prob, data.masks, roc=return_roc)
    far_lattice = np.asarray(model.predict_proba(data.far_points), dtype=float) if len(data.far_points) else np.zeros(0)
    far = {"test_points": {"points": _spread(prob[data.far_test])}, "lattice": {"points": _spread(far_lattice)}}
    # Each map's own ternary map is judged (MSK-GPOM fits its occupied threshold).
    occupied_above = float(getattr(model, "thresholds_", DEFAULT_THRESHOLDS)[1])
    path = {"points": path_occupied(None, data.path, occupied=occupied_at(model, data.path))}
    truth_out: dict[str, Any] | None = None
    if data.truth is not None:
        centres = data.truth.grid.centres()
        truth_out = {
            "points": score_truth(
                data.truth,
                np.asarray(model.predict_proba(centres), dtype=float),
                data.truth_observed,
                occupied=occupied_at(model, centres),
            )
        }

    grid_score = None
    written_shape = None
    plan_out: dict[str, Any] | None = None
    if score_grid:
        w3, c3 = _clock()
        occupancy_map = written_grid(model, grid_resolution)
        w4, c4 = _clock()
        seconds["grid"], cpu["grid"] = w4 - w3, c4 - c3
        written_shape = list(occupancy_map.grid.shape)
        gprob = lookup(occupancy_map, data.points)
        grid_score = score(data.labels, gprob, data.masks, roc=return_roc)
        far["test_points"]["grid"] = _spread(gprob[data.far_test])
        far["lattice"]["grid"] = _spread(lookup(occupancy_map, data.far_points))
        path["grid"] = path_occupied(None, data.path, occupied=lookup_occupied(occupancy_map, data.path))
        if data.truth is not None and truth_out is not None:
            centres = data.truth.grid.centres()
            truth_out["grid"] = score_truth(
                data.truth,
                lookup(occupancy_map, centres),
                data.truth_observed,
                occupied=lookup_occupied(occupancy_map, centres),
            )
        if data.plan is not None:
            plan_prob = lookup(occupancy_map, data.plan.points)
            # A grid's ternary map as map_server reads it; gpomap's its own.
            grid_method = method in GRID_METHODS
            plan_occupied = (
                plan_prob > MAP_SERVER_THRESHOLDS[1] if grid_method else lookup_occupied(occupancy_map, data.plan.points)
            )
            plan_out = score_plan(data.plan, plan_prob, plan_occupied)
        del occupancy_map

    is_grid = method in GRID_METHODS
    result: dict[str, Any] = {
        "method": method,
        "occupied_threshold": occupied_above,
        "auc": points_score["auc"],
        "fpr_at_tpr95": points_score["fpr_at_tpr95"],
        "log_loss": points_score["log_loss"],
        "points": points_score,
        "grid": grid_score,
        "far": far,
        "path": path,
        "truth": truth_out,
        "plan": plan_out,
        "seconds": seconds,
        "cpu_seconds": cpu,
        "peak_rss_mb": peak_rss_mb(),
        "n_inputs": n_inputs(model),
        "n_train_scans": len(data.train),
        "n_test_scans": len(data.test),
        "n_test_points": int(data.labels.size),
        "settings": {
            **data.settings,
            "method": method,
            "kernel": None if is_grid else getattr(model, "kernel", getattr(getattr(model, "base", None), "kernel", kernel)),
            "resolution": resolution if is_grid else None,
            "grid_resolution": (resolution if is_grid else grid_resolution) if score_grid else None,
            "written_grid_shape": written_shape,
            "tiles": len(model.tiles_) if hasattr(model, "tiles_") else None,
            "method_options": _jsonable(method_options),
        },
    }
    if hasattr(model, "hyperparameters_"):
        result["hyperparameters"] = {k: float(v) for k, v in model.hyperparameters_.items()}
    if getattr(model, "evidence_", None) is not None:
        result["evidence"] = _jsonable(model.evidence_.summary())
    if return_roc:
        result["roc"] = points_score["roc"]
    return result


def evaluate(
    scans: Sequence[Scan],
    method: str = "msk",
    kernel: str | None = None,
    holdout: str = "every",
    n_scans: int | None = None,
    n_beams: int | None = None,
    scan_range: str | tuple[int | None, int | None] | None = None,
    seed: int = 0,
    resolution: float = 0.1,
    test_free_step: float = TEST_FREE_STEP,
    max_test_points: int | None = None,
    return_roc: bool = False,
    n_workers: int | None = None,
    grid_resolution: float = GRID_RESOLUTION,
    scan_step: int = 1,
    truth: Truth | None = None,
    score_grid: bool = True,
    plan: PlanTruth | None = None,
    **method_options: Any,
) -> dict[str, Any]:
    """Fit a method on training scans and score it on held-out scans (:func:`prepare` then
    :func:`run_method`; see them for the parameters).

    Returns
    -------
    dict
        :func:`run_method`'s, with ``seconds`` also holding ``split``, ``test_points``,
        ``reference`` and ``total``.
    """
    t = time.perf_counter()
    data = prepare(scans, holdout, scan_range, scan_step, n_scans, n_beams, seed, test_free_step, max_test_points, truth, plan)
    result = run_method(
        data, method, kernel, seed, resolution, grid_resolution, n_workers, return_roc, score_grid, **method_options
    )
    result["seconds"] = {**data.seconds, **result["seconds"], "total": time.perf_counter() - t}
    return result


def _jsonable(value: Any) -> Any:
    """`value` with tuples and numpy scalars / arrays turned into JSON types."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def score_against_truth(model: Any, world: Any, grid: GridSpec | float, wall_thickness: float | None = None) -> dict[str, Any]:
    """Score a fitted map against a simulated world's true occupancy on a grid.

    Parameters
    ----------
    model : fitted estimator
        Anything with ``predict_proba(points)``.
    world : gpomap.simulate.World
    grid : GridSpec or float
        The grid to score on; a float is a resolution over the world's bounds.
    wall_thickness : float, optional
        Width of the wall bands counted occupied (default the grid resolution, see
        :meth:`gpomap.simulate.World.true_grid`).

    Returns
    -------
    dict
        ``auc``, ``fpr_at_tpr95``, ``n_cells``, ``n_occupied_cells``, ``resolution``.
    """
    if not isinstance(grid, GridSpec):
        grid = GridSpec.from_extent(world.bounds, float(grid))
    truth = world.true_grid(grid, wall_thickness).ravel()
    prob = np.asarray(model.predict_proba(grid.centres()), dtype=float)
    return {
        "auc": roc_auc(truth, prob),
        "fpr_at_tpr95": fpr_at_tpr(truth, prob, 0.95),
        "n_cells": int(truth.size),
        "n_occupied_cells": int(truth.sum()),
        "resolution": grid.resolution,
    }
