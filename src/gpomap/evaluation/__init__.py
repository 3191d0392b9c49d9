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

The rooms, each with one job: :mod:`~gpomap.evaluation.splits` (windows and hold-out splits of
a log), :mod:`~gpomap.evaluation.points` (test points and the boundary mask),
:mod:`~gpomap.evaluation.reference` (where the training scans reached: observed cells, far
field, the robot's path), :mod:`~gpomap.evaluation.scoring` (metrics on points),
:mod:`~gpomap.evaluation.gridtruth` (a true map on a grid), :mod:`~gpomap.evaluation.methods`
(the registry of methods, by name), :mod:`~gpomap.evaluation.maps` (a method's model, its
written grid, lookups), :mod:`~gpomap.evaluation.data` (one split made
ready: :func:`prepare`) and :mod:`~gpomap.evaluation.driver` (:func:`run_method`,
:func:`evaluate`). Every name is importable from ``gpomap.evaluation`` itself.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gpomap.evaluation.data import EvalData, prepare
    from gpomap.evaluation.driver import evaluate, run_method
    from gpomap.evaluation.gridtruth import Truth, score_against_truth, score_truth
    from gpomap.evaluation.maps import (
        GRID_RESOLUTION,
        lookup,
        lookup_occupied,
        make_model,
        n_inputs,
        occupied_at,
        written_grid,
    )
    from gpomap.evaluation.methods import GP_METHODS, GRID_METHODS, METHODS, REGISTRY, Method, method_named
    from gpomap.evaluation.points import (
        BOUNDARY_RADIUS,
        NO_RETURN_CAP,
        TEST_FREE_STEP,
        TEST_HIT_MARGIN,
        near,
        protocol_points,
        test_points,
    )
    from gpomap.evaluation.reference import (
        FAR_DISTANCE,
        FAR_LATTICE,
        FAR_MAX_POINTS,
        PATH_STEP,
        REFERENCE_RESOLUTION,
        FarField,
        observed_at,
        path_points,
        reference_grid,
    )
    from gpomap.evaluation.scoring import path_occupied, score
    from gpomap.evaluation.splits import DEFAULT_BLOCK_PERIOD, SPLITS, check_split, holdout_split, resolve_split, scan_window

#: Each public name's module, imported when the name is first asked for (PEP 562), so that the
#: registry of methods (:mod:`~gpomap.evaluation.methods`) is read without loading the engine.
_HOMES: dict[str, str] = {
    "EvalData": "gpomap.evaluation.data",
    "prepare": "gpomap.evaluation.data",
    "evaluate": "gpomap.evaluation.driver",
    "run_method": "gpomap.evaluation.driver",
    "Truth": "gpomap.evaluation.gridtruth",
    "score_against_truth": "gpomap.evaluation.gridtruth",
    "score_truth": "gpomap.evaluation.gridtruth",
    "GRID_RESOLUTION": "gpomap.evaluation.maps",
    "lookup": "gpomap.evaluation.maps",
    "lookup_occupied": "gpomap.evaluation.maps",
    "make_model": "gpomap.evaluation.maps",
    "n_inputs": "gpomap.evaluation.maps",
    "occupied_at": "gpomap.evaluation.maps",
    "written_grid": "gpomap.evaluation.maps",
    "GP_METHODS": "gpomap.evaluation.methods",
    "GRID_METHODS": "gpomap.evaluation.methods",
    "METHODS": "gpomap.evaluation.methods",
    "REGISTRY": "gpomap.evaluation.methods",
    "Method": "gpomap.evaluation.methods",
    "method_named": "gpomap.evaluation.methods",
    "BOUNDARY_RADIUS": "gpomap.evaluation.points",
    "NO_RETURN_CAP": "gpomap.evaluation.points",
    "TEST_FREE_STEP": "gpomap.evaluation.points",
    "TEST_HIT_MARGIN": "gpomap.evaluation.points",
    "near": "gpomap.evaluation.points",
    "protocol_points": "gpomap.evaluation.points",
    "test_points": "gpomap.evaluation.points",
    "FAR_DISTANCE": "gpomap.evaluation.reference",
    "FAR_LATTICE": "gpomap.evaluation.reference",
    "FAR_MAX_POINTS": "gpomap.evaluation.reference",
    "PATH_STEP": "gpomap.evaluation.reference",
    "REFERENCE_RESOLUTION": "gpomap.evaluation.reference",
    "FarField": "gpomap.evaluation.reference",
    "observed_at": "gpomap.evaluation.reference",
    "path_points": "gpomap.evaluation.reference",
    "reference_grid": "gpomap.evaluation.reference",
    "path_occupied": "gpomap.evaluation.scoring",
    "score": "gpomap.evaluation.scoring",
    "DEFAULT_BLOCK_PERIOD": "gpomap.evaluation.splits",
    "SPLITS": "gpomap.evaluation.splits",
    "check_split": "gpomap.evaluation.splits",
    "holdout_split": "gpomap.evaluation.splits",
    "resolve_split": "gpomap.evaluation.splits",
    "scan_window": "gpomap.evaluation.splits",
}


def __getattr__(name: str) -> Any:
    """The public names of :data:`_HOMES`, imported from their module when first asked for."""
    if name in _HOMES:
        value = getattr(importlib.import_module(_HOMES[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gpomap.evaluation' has no attribute {name!r}")


__all__ = [
    "BOUNDARY_RADIUS",
    "DEFAULT_BLOCK_PERIOD",
    "FAR_DISTANCE",
    "FAR_LATTICE",
    "FAR_MAX_POINTS",
    "GP_METHODS",
    "GRID_METHODS",
    "GRID_RESOLUTION",
    "METHODS",
    "NO_RETURN_CAP",
    "PATH_STEP",
    "REFERENCE_RESOLUTION",
    "REGISTRY",
    "SPLITS",
    "TEST_FREE_STEP",
    "TEST_HIT_MARGIN",
    "EvalData",
    "FarField",
    "Method",
    "Truth",
    "check_split",
    "evaluate",
    "holdout_split",
    "lookup",
    "lookup_occupied",
    "make_model",
    "method_named",
    "n_inputs",
    "near",
    "observed_at",
    "occupied_at",
    "path_occupied",
    "path_points",
    "prepare",
    "protocol_points",
    "reference_grid",
    "resolve_split",
    "run_method",
    "scan_window",
    "score",
    "score_against_truth",
    "score_truth",
    "test_points",
    "written_grid",
]
