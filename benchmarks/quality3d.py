"""3-D map quality: the voxel map ``gpomap map`` writes against OctoMap and a counting voxel grid.

Two kinds of case:

- **Against the truth** (simulated scenes of boxes, :mod:`gpomap.simulate3d`): depth frames of a
  pinhole camera (160 x 120 pixels, 60 degrees across, 0.3-6 m) rendered by exact ray casting
  inside the office (three rooms joined by doorways, furnished; 10 frames) and the store room
  (aisles of shelves and an office; 8 frames), noise-free, and the office again with a depth
  camera's noise (Kinect-like axial noise, 1 % dropped pixels, 1 cm / 0.005 rad pose error,
  :class:`gpomap.simulate3d.DepthNoise`), and the office at a depth camera's full resolution
  (``office-vga``: 640 x 480 pixels, whose free samples ``gpomap map`` merges by cube,
  :data:`gpomap.observations.MERGE_MIN_SAMPLES`). The frames are written as ``gpomap map`` reads depth
  frames (16-bit millimetre PNGs, intrinsics, camera-to-world poses) and read back by the CLI's
  own reader. Every map is built from all frames and scored on the truth lattice (0.025 m) where
  the rays went (:func:`gpomap.simulate3d.truth_points`: a point within 0.05 m of a lattice cell a
  ray crossed; occupied inside a box; boundary within 0.1 m of one), drawn uniformly (at most
  ``--max-truth`` points).
- **Held out** (the shared 3-D data): la3dm ``sim_structured`` and ``sim_unstructured`` (12 scans,
  ``--max-range 8``; every 4th scan held out), 3DMatch's five frames (``--stride 4``; the 4th,
  ``frame-000116``, held out; ``3dmatch-full``: every pixel, the free samples merged) and a 16-beam lidar simulated at 12 poses in OctoMap's ``geb079.bt``
  (``benchmarks/volume_quality.py``'s; every 4th held out; ``geb079-dense``: a 128-beam lidar, 1024
  azimuths, whose free samples are merged). Test points are the held-out rays' hits
  and free points every 0.1 m along them to 0.1 m short of the hit
  (:func:`gpomap.evaluation.test_points`), drawn uniformly (at most ``--max-test``): natural
  frequencies, never class-balanced. Boundary points lie within 0.5 m of a held-out hit.

Maps, each at ``--resolution`` (0.1 m, ``gpomap map``'s default), from the same training scans:

- ``gpomap``: read and built exactly as ``gpomap map INPUT -o OUT [options]`` does
  (:func:`gpomap.cli.map3d.load_clouds`, :func:`~gpomap.cli.map3d.unfitted_model`, its
  defaults), and the voxel map it writes over the fitted blocks' kept points (``map.npz``), looked up at the
  scored points: the map a user gets, not exact-point predictions. Its ternary map is the one
  ``map.bt`` holds: occupied where the ternary layer says so and a ray went
  (:attr:`gpomap.voxels.VoxelMap.observed`);
- ``octomap``: OctoMap through pyoctomap (:class:`gpomap.baselines.octomap.OctoMapBaseline`:
  ``insertPointCloud`` with ray casting, its default sensor model), the same points; a voxel it
  does not hold is 0.5, unknown; occupied is OctoMap's own (p > 0.5);
- ``counting``: the counting voxel grid ``(hits + 1) / (hits + misses + 2)``
  (:class:`gpomap.baselines.ogm.OccupancyGridMapper`), its ternary map at map_server's thresholds
  (free below 0.196, occupied above 0.65).

Metrics (:func:`gpomap.truth.score_plan`): ROC AUC, boundary AUC, log loss, Brier score, ECE
(10 bins), occupied IoU at p > 0.5 and of the ternary map's occupied class; and the sensor
positions the ternary map calls occupied. Each map is built in a forked child process: the fit
and map times (wall seconds; numba's compilation on a first run timed apart) and the memory the
child added to what it was forked with (peak resident MiB).

Then, to see where the scores come from: on the simulated scenes, the share of each map's
occupied voxels that hold no part of a box (surfaces grown into free space), with how many of
gpomap's occupied voxels lie where no ray went (map.npz's GP guess, left out of map.bt); and
per case, the scored points by what the training rays did in their voxel (no ray; misses only;
hits only; hits and misses, each scan counted once per voxel as gpomap's ray evidence counts
it), with each map's mean probability there and its part of the log loss.

Targets (issue 52, item 3, with OctoMap as the grid): log loss, Brier and ECE below OctoMap's;
AUC and boundary AUC at least OctoMap's; against the truth, occupied IoU at p > 0.5 and of the
ternary map at least OctoMap's; no sensor position occupied.

Run from the repository root::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/quality3d.py [--json q3d.json]   # every case
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/quality3d.py --quick             # a smoke run
    .venv/bin/python benchmarks/quality3d.py --cases office,sim_structured --resolution 0.05
    .venv/bin/python benchmarks/quality3d.py --cases office --frames frames   # keep frames/office
    .venv/bin/python benchmarks/quality3d.py --methods gpomap --set free_clearance=0.1   # another setting

``--set NAME=VALUE`` changes one of gpomap's options (a :class:`gpomap.config.MapConfig` field,
as ``gpomap map``'s option of that name would) to measure other settings than the defaults.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures as cf
import json
import multiprocessing
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.grid import OCCUPIED, ternary
from gpomap.truth import MAP_SERVER_THRESHOLDS, TruthPoints, score_plan

sys.path.insert(0, str(Path(__file__).resolve().parent))
from child_memory import fresh_peak, peak_mb

DATA = Path("..") / "shared" / "data"
#: The voxel side of ``gpomap map`` (and of the grids beside it), metres.
RESOLUTION: float = 0.1
#: Every held-out case holds out every 4th scan (the 4th, 8th, ...).
HOLDOUT_PERIOD: int = 4
SIM_CASES = ("office", "office-noisy", "storeroom", "office-vga")
HELD_OUT_CASES = ("sim_structured", "sim_unstructured", "3dmatch", "3dmatch-full", "geb079", "geb079-dense")
#: Pixels of the simulated scenes' frames: the usual cases', a depth camera's full resolution.
IMAGE = (160, 120)
VGA_IMAGE = (640, 480)
QUICK_CASES = ("office", "sim_structured", "3dmatch")
METHODS = ("gpomap", "octomap", "counting")
#: gpomap's options changed by ``--set NAME=VALUE`` (a field of :class:`gpomap.config.MapConfig` or
#: an option's destination), to measure other settings than the defaults.
OVERRIDES: dict[str, Any] = {}

# Metric, title, higher is better, truth cases only.
METRICS: tuple[tuple[str, str, bool, bool], ...] = (
    ("auc", "AUC", True, False),
    ("boundary_auc", "bnd AUC", True, False),
    ("log_loss", "log loss", False, False),
    ("brier", "Brier", False, False),
    ("ece", "ECE", False, False),
    ("iou", "IoU p>0.5", True, True),
    ("ternary_iou", "IoU ternary", True, True),
)


@dataclass
class Case:
    """One dataset: training scans, the ``gpomap map`` command line that reads them, the scored points."""

    name: str
    kind: str  # "truth" or "held out"
    command: list[str]
    train: list[CloudScan]
    points: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    boundary: NDArray[np.bool_]
    max_range: float | None
    info: dict[str, Any] = field(default_factory=dict)
    scene: Any = None  # the true boxes of a simulated case


# --------------------------------------------------------------------------- the CLI's reading
def cli_args(command: Sequence[str], resolution: float) -> argparse.Namespace:
    """The parsed options of ``gpomap map COMMAND -o OUT --resolution R``, defaults resolved as ``gpomap map`` resolves them."""
    from gpomap import cli
    from gpomap.cli.map3d import apply_3d_defaults
    from gpomap.cli.options import resolve_library_defaults

    args = cli.build_parser().parse_args(["map", *command, "-o", "unused", "--resolution", f"{resolution:g}"])
    resolve_library_defaults(args)
    apply_3d_defaults(args)
    for name, value in OVERRIDES.items():
        setattr(args, name, value)
    return args


def read_as_cli(command: Sequence[str], resolution: float) -> list[CloudScan]:
    """The clouds ``gpomap map COMMAND`` reads (:func:`gpomap.cli.map3d.load_clouds`)."""
    from gpomap.cli.map3d import load_clouds

    return load_clouds(cli_args(command, resolution))


def holdout(n: int, period: int = HOLDOUT_PERIOD) -> tuple[list[int], list[int]]:
    """Training and held-out indices: every `period`-th scan (the `period`-th, 2 `period`-th, ...) held out."""
    test = [i for i in range(n) if i % period == period - 1]
    return [i for i in range(n) if i not in test], test


# --------------------------------------------------------------------------- cases
def rendered_frames(name: str, workdir: Path, quick: bool = False) -> tuple[Any, Any, Any, Path]:
    """A simulated scene's depth frames rendered and written as ``gpomap map`` reads a depth folder.

    Returns the scene, the camera, whether the frames are noisy, and the folder (``workdir / name``).
    """
    from gpomap import simulate3d as s3

    scene, poses = (s3.storeroom_scene(), s3.storeroom_poses()) if name == "storeroom" else (s3.office_scene(), s3.office_poses())
    width, height = (80, 60) if quick else VGA_IMAGE if name == "office-vga" else IMAGE
    camera = s3.PinholeCamera.from_fov(width, height, 60)
    noise = s3.DepthNoise() if name.endswith("-noisy") else None
    frames = s3.render_frames(scene, camera, poses, min_depth=0.3, max_depth=6.0, noise=noise, seed=1)
    return scene, camera, noise, s3.write_depth_frames(frames, workdir / name)


def sim_case(name: str, workdir: Path, resolution: float, max_truth: int, quick: bool) -> Case:
    """A simulated scene rendered to depth frames, written, read back as ``gpomap map`` reads them, with its truth."""
    from gpomap import simulate3d as s3

    scene, camera, noise, folder = rendered_frames(name, workdir, quick)
    command = [str(folder)]
    clouds = read_as_cli(command, resolution)
    truth = s3.truth_points(scene, clouds, max_points=max_truth, seed=0)
    info = {
        "frames": len(clouds),
        "rays": int(sum(int(c.valid().sum()) for c in clouds)),
        "image": f"{camera.width}x{camera.height}",
        "noise": noise is not None,
        "n_observed_truth": truth.n_observed,
        "sensor_positions": [c.origin.tolist() for c in clouds],
    }
    return Case(name, "truth", command, clouds, truth.points, truth.occupied, truth.boundary, None, info, scene)


def _held_out_points(
    test: Sequence[CloudScan], max_test: int
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Natural-frequency test points of the held-out clouds and which lie within 0.5 m of a held-out hit."""
    from gpomap.evaluation import BOUNDARY_RADIUS, near, test_points

    points, occupied = test_points(list(test), seed=0, max_points=max_test)
    hits = np.concatenate([c.points[c.valid() & np.asarray(c.hit, dtype=bool)] for c in test])
    return points, occupied, near(points, hits, BOUNDARY_RADIUS)


def held_out_case(
    name: str, command: list[str], clouds: list[CloudScan], max_test: int, max_range: float | None, info: dict[str, Any]
) -> Case:
    tr, te = holdout(len(clouds))
    train, test = [clouds[i] for i in tr], [clouds[i] for i in te]
    points, occupied, boundary = _held_out_points(test, max_test)
    info = {
        **info,
        "train_scans": tr,
        "test_scans": te,
        "rays": int(sum(int(c.valid().sum()) for c in train)),
        "sensor_positions": [c.origin.tolist() for c in train],
    }
    return Case(name, "held out", command, train, points, occupied, boundary, max_range, info)


def la3dm_case(world: str, resolution: float, max_test: int) -> Case:
    command = [str(DATA / "la3dm-sim" / world), "--max-range", "8"]
    return held_out_case(world, command, read_as_cli(command, resolution), max_test, 8.0, {})


def match_case(name: str, resolution: float, max_test: int) -> Case:
    command = [str(DATA / "3dmatch"), "--stride", "1" if name == "3dmatch-full" else "4"]
    return held_out_case(name, command, read_as_cli(command, resolution), max_test, None, {})


#: The dense lidar of ``geb079-dense``: azimuths, beams and half the vertical field of view
#: (degrees) of a 128-beam sensor, whose sweeps make millions of free samples and are merged.
DENSE_LIDAR = (1024, 128, 22.5)


def geb079_case(max_test: int, workdir: Path, dense: bool = False) -> Case:
    """The simulated lidar in geb079.bt (``benchmarks/volume_quality.py``'s; with `dense`, a
    128-beam one, :data:`DENSE_LIDAR`), as in-memory clouds: no file format holds them, so the
    command line only sets the options (``--max-range 10``)."""
    from gpomap.io.octomap import load_pyoctomap_tree
    from volume_quality import corridor_poses, simulate_lidar

    tree, _, _ = load_pyoctomap_tree(DATA / "octomap" / "geb079.bt")
    n_az, n_el, fov = DENSE_LIDAR if dense else (360, 16, 15.0)
    clouds = [simulate_lidar(tree, p, n_az, n_el, fov) for p in corridor_poses(tree)]
    name = "geb079-dense" if dense else "geb079"
    return held_out_case(
        name, [str(workdir), "--max-range", "10"], clouds, max_test, 10.0, {"lidar": f"{n_az} x {n_el} beams, 10 m"}
    )


# --------------------------------------------------------------------------- the maps
Lookup = Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.bool_]]]


def _voxel_lookup(voxel_map: Any, occupied: NDArray[np.bool_]) -> Lookup:
    """Probability and ternary-occupied of the voxel holding each point (0.5 and not occupied outside)."""

    def lookup(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        k, j, i, inside = voxel_map.spec.index_of(points)
        return voxel_map.lookup(points), inside & occupied[k, j, i]

    return lookup


def build_gpomap(case: Case, resolution: float) -> tuple[Lookup, dict[str, Any]]:
    """The map ``gpomap map`` writes from the case's training scans, built as it builds it
    (:func:`gpomap.cli.map3d.run`: the model of its options, fitted, its voxel grid over the
    fitted blocks' kept points)."""
    from gpomap.apps.map3d import voxel_bounds
    from gpomap.cli.map3d import unfitted_model
    from gpomap.compiled import compile_time
    from gpomap.lattice import bounds_extent

    args = cli_args(case.command, resolution)
    with compile_time() as compiling:
        t0 = time.perf_counter()
        model = unfitted_model(args)
        model.fit(case.train)
        t1 = time.perf_counter()
        lo, hi = voxel_bounds(np.array(model.kept_bounds_), args.extent, args.z_range, args.resolution)
        voxel_map = model.grid(args.resolution, bounds_extent(lo, hi))
        t2 = time.perf_counter()
    # The ternary layer calls occupied only where a ray went (map.bt's voxels); the GP's own
    # classes reach behind the surfaces too.
    occupied = voxel_map.ternary == OCCUPIED
    n_occ = int((voxel_map.probability > voxel_map.thresholds[1]).sum())
    summary = model.summary()
    stats = {
        "fit_s": t1 - t0 - compiling[0],
        "map_s": t2 - t1,
        "compile_s": compiling[0],
        "voxels": int(voxel_map.probability.size),
        "occupied_voxels": n_occ,
        "occupied_unseen_share": (n_occ - int(occupied.sum())) / max(n_occ, 1),
        "occupied_observed_voxels": int(occupied.sum()),
        "thresholds": list(voxel_map.thresholds),
        "hyperparameters": summary["hyperparameters"],
        "evidence": summary["evidence"],
        "n_cells": summary["n_cells"],
    }
    return _voxel_lookup(voxel_map, occupied), stats


def build_octomap(case: Case, resolution: float) -> tuple[Lookup, dict[str, Any]]:
    """OctoMap (pyoctomap) on the same rays; its probabilities read voxel by voxel."""
    from gpomap.baselines.octomap import OctoMapBaseline

    t0 = time.perf_counter()
    tree = OctoMapBaseline(resolution, max_range=case.max_range).fit(case.train)
    t1 = time.perf_counter()

    def lookup(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        # OctoMap's voxel faces lie on multiples of its resolution: one query per voxel, not per point.
        keys, where = np.unique(np.floor(points / resolution).astype(np.int64), axis=0, return_inverse=True)
        p = tree.predict_proba((keys + 0.5) * resolution)[where.reshape(-1)]
        return p, p > 0.5

    return lookup, {"fit_s": t1 - t0, "map_s": 0.0, "leaves": int(tree.tree_.getNumLeafNodes())}


def build_counting(case: Case, resolution: float) -> tuple[Lookup, dict[str, Any]]:
    """The counting voxel grid on the same rays, its ternary map at map_server's thresholds."""
    from gpomap.baselines.ogm import OccupancyGridMapper

    t0 = time.perf_counter()
    grid = OccupancyGridMapper(resolution, sensor_model="counting", max_range_free=case.max_range or 10.0).fit(case.train)
    voxel_map = grid.grid_map()
    t1 = time.perf_counter()
    return _voxel_lookup(voxel_map, ternary(voxel_map.probability, MAP_SERVER_THRESHOLDS) == OCCUPIED), {
        "fit_s": t1 - t0,
        "map_s": 0.0,
    }


BUILDERS: dict[str, Callable[[Case, float], tuple[Lookup, dict[str, Any]]]] = {
    "gpomap": build_gpomap,
    "octomap": build_octomap,
    "counting": build_counting,
}


def false_surfaces(scene: Any, lookup: Lookup, resolution: float) -> dict[str, Any]:
    """The voxels (faces on multiples of `resolution`) over a scene that a map calls occupied (its
    ternary map), and the share of them that hold no part of a box: surfaces grown into free space."""
    from gpomap.voxels import VoxelSpec

    lo, hi = scene.bounds
    spec = VoxelSpec.from_extent(lo, hi, resolution)
    centres = spec.centres()
    occupied = lookup(centres)[1]
    half = resolution / 2
    holds = np.zeros(len(centres), dtype=bool)
    for lo_box, hi_box in zip(scene.lower, scene.upper):
        holds |= np.all((centres + half > lo_box) & (centres - half < hi_box), axis=1)
    n = int(occupied.sum())
    return {"occupied_in_scene": n, "false_surface_share": float(np.mean(~holds[occupied])) if n else 0.0}


def _method_in_child(method: str, case: Case, resolution: float) -> dict[str, Any]:
    """Build one map and look it up at the case's points and sensor positions (in a forked child)."""
    start = fresh_peak()
    lookup, stats = BUILDERS[method](case, resolution)
    t = time.perf_counter()
    p, occupied = lookup(case.points)
    stats["lookup_s"] = time.perf_counter() - t
    origins = np.array(case.info["sensor_positions"], dtype=float)
    stats["sensors_occupied"] = int(lookup(origins)[1].sum())
    if case.scene is not None:
        stats.update(false_surfaces(case.scene, lookup, resolution))
    stats["peak_mb"] = peak_mb() - start
    return {"p": p, "occupied": occupied, **stats}


def run_method(method: str, case: Case, resolution: float) -> dict[str, Any]:
    """:func:`_method_in_child` in a forked child, so its memory is its own; a failure is a row saying why."""
    ctx = multiprocessing.get_context("fork")
    try:
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
            return pool.submit(_method_in_child, method, case, resolution).result()
    except Exception as exc:  # a method that cannot run here is a row saying why
        return {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}


def score_case(case: Case, method: str, result: dict[str, Any]) -> dict[str, Any]:
    """The row of one method on one case: its metrics, times and memory."""
    row: dict[str, Any] = {"dataset": case.name, "kind": case.kind, "method": method}
    if "error" in result:
        return {**row, "error": result["error"]}
    truth = TruthPoints(case.points, case.occupied, case.boundary)
    scores = score_plan(truth, result["p"], result["occupied"])
    row.update({k: scores[k] for k, *_ in METRICS})
    row.update({k: v for k, v in result.items() if k not in ("p", "occupied")})
    return row


# --------------------------------------------------------------------------- where the scores come from
#: The voxels the scored points fall in, by what the training scans' rays did there, counted as
#: gpomap's ray evidence counts them (:meth:`gpomap.evidence.RayEvidence.counts`: each scan once
#: per voxel, a hit winning over a miss).
CATEGORIES = ("outside", "no ray", "misses only", "hits only", "hits and misses")


def voxel_categories(case: Case, resolution: float) -> NDArray[np.int8]:
    """Index into :data:`CATEGORIES` of each scored point's voxel (faces on multiples of `resolution`), shape (n,)."""
    from gpomap.evidence import RayEvidence
    from gpomap.voxels import VoxelSpec

    lo = np.minimum(case.points.min(axis=0), np.array([c.origin for c in case.train]).min(axis=0))
    hi = np.maximum(case.points.max(axis=0), np.array([c.origin for c in case.train]).max(axis=0))
    spec = VoxelSpec.from_extent(lo - resolution, hi + resolution, resolution)
    counts = RayEvidence.from_scans(case.train, case.max_range or 10.0).counts(spec)
    k, j, i, inside = spec.index_of(case.points)
    h, m = counts.hits[k, j, i] > 0, counts.misses[k, j, i] > 0
    out = np.select([~inside, ~h & ~m, ~h, ~m], [0, 1, 2, 3], 4)
    return out.astype(np.int8)


def breakdown(case: Case, category: NDArray[np.int8], results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Per voxel category: its share of the points, their occupied share, each map's mean
    probability there and its part of the map's log loss (summed over the category, divided by all points)."""
    from gpomap.metrics import log_loss

    n = len(case.occupied)
    rows = []
    for c, name in enumerate(CATEGORIES):
        sel = category == c
        if not sel.any():
            continue
        y = case.occupied[sel]
        row: dict[str, Any] = {"dataset": case.name, "voxels": name, "share": float(sel.mean()), "occupied": float(y.mean())}
        for method, r in results.items():
            if "error" in r:
                continue
            p = np.clip(np.asarray(r["p"])[sel], 0.0, 1.0)
            row[f"{method}_p"] = float(p.mean())
            row[f"{method}_log_loss"] = float(log_loss(y, p)) * int(sel.sum()) / n
        rows.append(row)
    return rows


def print_breakdown(rows: Sequence[dict[str, Any]], methods: Sequence[str]) -> None:
    print("\n### Where the log loss comes from (voxels by what the training rays did there, each scan counted once per voxel)\n")
    head = " | ".join(f"{m} p / log loss" for m in methods)
    print(f"| dataset | voxels | share of points | occupied | {head} |")
    print("|---|---|---|---|" + "---|" * len(methods))
    for r in rows:
        vals = " | ".join(f"{_fmt(r.get(f'{m}_p'), 3)} / {_fmt(r.get(f'{m}_log_loss'), 4)}" for m in methods)
        print(f"| {r['dataset']} | {r['voxels']} | {r['share']:.3f} | {r['occupied']:.3f} | {vals} |")


def print_surfaces(rows: Sequence[dict[str, Any]]) -> None:
    print(
        "\n### Occupied voxels: gpomap's where no ray went (map.npz) and where rays went (map.bt); every map's that hold no true box\n"
    )
    print(
        "| dataset | gpomap p > threshold | of them where no ray went | in map.bt | holding no box: gpomap / octomap / counting |"
    )
    print("|---|---|---|---|---|")
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        by = {r["method"]: r for r in rows if r["dataset"] == dataset and "error" not in r}
        g = by.get("gpomap")
        if g is None:
            continue
        false = " / ".join(
            f"{by[m]['false_surface_share']:.1%} of {by[m]['occupied_in_scene']:,}"
            if m in by and "false_surface_share" in by[m]
            else "-"
            for m in METHODS
        )
        print(
            f"| {dataset} | {g['occupied_voxels']:,} | {g['occupied_unseen_share']:.1%} | {g['occupied_observed_voxels']:,} | {false} |"
        )


# --------------------------------------------------------------------------- targets and tables
def targets(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """gpomap's map against OctoMap's on each case: each metric's target, met or missed."""
    out = []
    by = {(r["dataset"], r["method"]): r for r in rows if "error" not in r}
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        g, o = by.get((dataset, "gpomap")), by.get((dataset, "octomap"))
        if g is None or o is None:
            continue
        for key, title, higher, truth_only in METRICS:
            if truth_only and g["kind"] != "truth":
                continue
            a, b = g.get(key), o.get(key)
            if a is None or b is None:
                continue
            met = a >= b if higher else a < b
            out.append({"dataset": dataset, "metric": key, "title": title, "gpomap": a, "octomap": b, "met": bool(met)})
        out.append(
            {
                "dataset": dataset,
                "metric": "sensors_occupied",
                "title": "sensor positions occupied",
                "gpomap": g["sensors_occupied"],
                "octomap": o["sensors_occupied"],
                "met": g["sensors_occupied"] == 0,
            }
        )
    return out


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def print_tables(cases: Sequence[Case], rows: Sequence[dict[str, Any]]) -> None:
    for case in cases:
        n, occ = len(case.occupied), int(case.occupied.sum())
        what = "truth points" if case.kind == "truth" else "held-out test points"
        extra = f", {case.info['n_observed_truth']:,} observed" if "n_observed_truth" in case.info else ""
        print(
            f"\n### {case.name} ({case.kind}): {len(case.train)} training scans, {case.info['rays']:,} rays; "
            f"{n:,} {what}{extra}, {occ / n:.1%} occupied, {int(case.boundary.sum()):,} boundary"
        )
        print()
        cols = [t for _, t, _, _ in METRICS] + ["fit s", "map s", "peak MB", "sensors occ."]
        print("| method | " + " | ".join(cols) + " |")
        print("|---|" + "---|" * len(cols))
        for r in rows:
            if r["dataset"] != case.name:
                continue
            if "error" in r:
                print(f"| {r['method']} | not run: {r['error']} |" + " |" * (len(cols) - 1))
                continue
            vals = [_fmt(r.get(k)) for k, *_ in METRICS]
            vals += [_fmt(r["fit_s"], 2), _fmt(r["map_s"], 2), _fmt(r["peak_mb"], 0), str(r["sensors_occupied"])]
            print(f"| {r['method']} | " + " | ".join(vals) + " |")


def print_targets(found: Sequence[dict[str, Any]]) -> None:
    met = sum(t["met"] for t in found)
    print(f"\n### Targets against OctoMap: {met} of {len(found)} met\n")
    print("| dataset | missed (gpomap / OctoMap) |")
    print("|---|---|")
    for dataset in dict.fromkeys(t["dataset"] for t in found):
        mine = [t for t in found if t["dataset"] == dataset]
        missed = [f"{t['title']} {_fmt(t['gpomap'])} / {_fmt(t['octomap'])}" for t in mine if not t["met"]]
        print(f"| {dataset} ({sum(t['met'] for t in mine)} of {len(mine)} met) | {'; '.join(missed) or 'none'} |")


# --------------------------------------------------------------------------- main
def make_cases(names: Sequence[str], workdir: Path, resolution: float, max_truth: int, max_test: int, quick: bool) -> list[Case]:
    cases = []
    for name in names:
        t = time.perf_counter()
        if name in SIM_CASES:
            case = sim_case(name, workdir, resolution, max_truth, quick)
        elif name in ("sim_structured", "sim_unstructured"):
            case = la3dm_case(name, resolution, max_test)
        elif name in ("3dmatch", "3dmatch-full"):
            case = match_case(name, resolution, max_test)
        elif name in ("geb079", "geb079-dense"):
            case = geb079_case(max_test, workdir, dense=name == "geb079-dense")
        else:
            raise SystemExit(f"unknown case {name!r}; the cases are {', '.join(SIM_CASES + HELD_OUT_CASES)}")
        case.info["prepare_s"] = time.perf_counter() - t
        print(f"{name}: prepared in {case.info['prepare_s']:.1f} s", file=sys.stderr)
        cases.append(case)
    return cases


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", help=f"comma-separated cases (default: all: {','.join(SIM_CASES + HELD_OUT_CASES)})")
    ap.add_argument("--quick", action="store_true", help=f"a smoke run: {', '.join(QUICK_CASES)}, 80 x 60 frames, fewer points")
    ap.add_argument("--resolution", type=float, default=RESOLUTION, help="voxel side of every map, m (default: %(default)s)")
    ap.add_argument(
        "--max-truth", type=int, default=1_000_000, help="most truth points per simulated case (default: %(default)s)"
    )
    ap.add_argument("--max-test", type=int, default=50_000, help="most held-out test points per case (default: %(default)s)")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated maps (default: %(default)s)")
    ap.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="a gpomap option, as a Python literal (repeatable)"
    )
    ap.add_argument("--json", type=Path, help="also write the rows and targets as JSON")
    ap.add_argument(
        "--frames", type=Path, metavar="DIR", help="keep the simulated cases' depth frames in DIR/NAME (gpomap map reads them)"
    )
    args = ap.parse_args(argv)
    for item in args.set:
        name, _, text = item.partition("=")
        try:
            OVERRIDES[name.strip()] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            OVERRIDES[name.strip()] = text
    names = args.cases.split(",") if args.cases else list(QUICK_CASES if args.quick else SIM_CASES + HELD_OUT_CASES)
    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method(s) {', '.join(unknown)}; the methods are {', '.join(METHODS)}")
    max_truth, max_test = (200_000, 20_000) if args.quick else (args.max_truth, args.max_test)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="quality3d-") as tmp:
        workdir = args.frames if args.frames is not None else Path(tmp)
        cases = make_cases([n.strip() for n in names if n.strip()], workdir, args.resolution, max_truth, max_test, args.quick)
        rows: list[dict[str, Any]] = []
        parts: list[dict[str, Any]] = []
        for case in cases:
            results = {}
            for method in methods:
                results[method] = run_method(method, case, args.resolution)
                rows.append(score_case(case, method, results[method]))
                r = rows[-1]
                print(
                    f"{case.name}: {method} {'failed' if 'error' in r else 'in %.1f s' % (r['fit_s'] + r['map_s'])}",
                    file=sys.stderr,
                )
            parts += breakdown(case, voxel_categories(case, args.resolution), results)
    changed = "".join(f", {k}={v!r}" for k, v in OVERRIDES.items())
    print(f"# 3-D map quality at {args.resolution:g} m voxels{changed} ({time.perf_counter() - t0:.0f} s in all)")
    print_tables(cases, rows)
    found = targets(rows)
    print_targets(found)
    print_surfaces(rows)
    print_breakdown(parts, methods)
    if args.json:
        info = {c.name: {k: v for k, v in c.info.items() if k != "sensor_positions"} for c in cases}
        args.json.write_text(
            json.dumps(
                {
                    "resolution": args.resolution,
                    "overrides": OVERRIDES,
                    "cases": info,
                    "rows": rows,
                    "targets": found,
                    "breakdown": parts,
                },
                indent=1,
                default=float,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
