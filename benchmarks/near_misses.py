"""Near misses in the ray evidence: the calibration with and without them, and their distance.

:mod:`gpomap.evidence` counts a scan's miss of a cell as a near miss when its every beam through
the cell ended its return within :data:`gpomap.evidence.NEAR_END` of it, and
:mod:`gpomap.fusion` fits a weight of their own for them. This script fits MSK-GPOM once per log
and split (the defaults of ``gpomap map``, as ``benchmarks/quality.py`` builds it), then rebuilds
only the ray evidence for each variant:

- ``none``: no near misses (their weight held at 1, a miss like any other: the model before);
- ``0.1``, ``0.2``, ``0.3``: near misses within that many metres of the end, weight fitted.

For each it prints the fitted weights, the calibration's own leave-one-scan-out log loss (on the
training scans only), and the protocol's scores of the written 0.05 m map on the held-out scans
(:mod:`gpomap.evaluation`): AUC, boundary AUC, log loss, ECE, cells of the robot's path called
occupied, and on the Stage arena and the room the occupied-class IoU against the true map.

Run from the repository root::

    .venv/bin/python benchmarks/near_misses.py                       # every log, blocks split
    .venv/bin/python benchmarks/near_misses.py --logs intel --splits blocks,every
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import quality
from gpomap import evidence
from gpomap.evaluation import lookup, make_model, path_occupied, prepare, score, score_truth
from gpomap.fusion import calibration

VARIANTS: tuple[float | None, ...] = (None, 0.1, 0.2, 0.3)
GRID_RESOLUTION = 0.05


def _calibrate(model: Any, near_end: float | None) -> None:
    """Rebuild `model`'s ray evidence with near misses within `near_end` (None: no near misses)."""
    saved_end, saved_bounds = evidence.NEAR_END, calibration.CALIBRATION_BOUNDS
    try:
        if near_end is None:
            # A near miss weighs as a miss (its weight held at 1) and adds no hit (held at the floor).
            near_hit = (saved_bounds[3][0], saved_bounds[3][0])
            calibration.CALIBRATION_BOUNDS = (*saved_bounds[:2], (0.0, 0.0), near_hit, *saved_bounds[4:])
        else:
            evidence.NEAR_END = near_end
        model.evidence_ = model._make_evidence()
    finally:
        evidence.NEAR_END, calibration.CALIBRATION_BOUNDS = saved_end, saved_bounds


def run(log: str, split: str, seed: int = 0) -> list[dict[str, Any]]:
    """Every variant on one log and split."""
    scans, truth = quality.load(log, False)
    step = quality.LOGS[log].get("scan_step", 1)
    data = prepare(scans, split, scan_step=step, seed=seed, max_test_points=quality.MAX_TEST_POINTS, truth=truth)
    t = time.perf_counter()
    model = make_model("msk", seed=seed).fit(data.train)
    fit_s = time.perf_counter() - t
    rows = []
    for near_end in VARIANTS:
        t = time.perf_counter()
        _calibrate(model, near_end)
        occupancy_map = model.grid(GRID_RESOLUTION)
        seconds = time.perf_counter() - t
        prob = lookup(occupancy_map, data.points)
        s = score(data.labels, prob, data.masks)
        cal = model.evidence_.summary()
        row = {
            "log": log,
            "split": split,
            "near_end": near_end,
            "hit_weight": cal["hit_weight"],
            "near_weight": cal["near_weight"],
            "prior_weight": cal["prior_weight"],
            "loso_log_loss": cal.get("log_loss"),
            "auc": s["auc"],
            "boundary_auc": s["boundary_auc"],
            "log_loss": s["log_loss"],
            "ece": s["ece"],
            "path": path_occupied(lookup(occupancy_map, data.path), data.path)["n_occupied"],
            "iou": score_truth(truth, lookup(occupancy_map, truth.grid.centres()))["iou"] if truth is not None else None,
            "gp_fit_s": fit_s,
            "evidence_and_grid_s": seconds,
        }
        rows.append(row)
        print(_line(row), flush=True)
    return rows


HEADER = (
    "| log | split | near misses within | hit w | near w | prior w | LOSO log loss | AUC | boundary AUC "
    "| log loss | ECE | path cells | truth IoU | evidence + grid s |"
)


def _line(r: dict[str, Any]) -> str:
    near = "none" if r["near_end"] is None else f"{r['near_end']:.1f} m"
    iou = "" if r["iou"] is None else f"{r['iou']:.3f}"
    return (
        f"| {r['log']} | {r['split']} | {near} | {r['hit_weight']:.1f} | {r['near_weight']:.3f} | {r['prior_weight']:.2f} "
        f"| {r['loso_log_loss']:.4f} | {r['auc']:.4f} | {r['boundary_auc']:.4f} | {r['log_loss']:.4f} | {r['ece']:.4f} "
        f"| {r['path']} | {iou} | {r['evidence_and_grid_s']:.1f} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--logs", default=",".join(quality.LOGS), help=f"comma-separated, of {', '.join(quality.LOGS)}")
    parser.add_argument("--splits", default="blocks", help="comma-separated, of blocks, every")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(HEADER)
    print("|" + "---|" * HEADER.count(" | ") + "---|")
    for log in args.logs.split(","):
        for split in args.splits.split(","):
            run(log, split, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
