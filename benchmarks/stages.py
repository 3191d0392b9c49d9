"""What each stage of the map's calibration is worth: every stage switched off in turn, the rest kept.

Each row is gpomap's written map (``gpomap map``'s defaults, 0.05 m) with one stage off, scored
as ``benchmarks/quality.py`` scores it, at natural frequencies:

- against the true plan of each simulated world (the Stage arena, the sim-worlds cave and
  hospital section, the synthetic room): every plan pixel the log observed (:mod:`gpomap.truth`);
  the map is fitted on the whole log;
- on held-out scans of the real logs (blocks of 40, every 5th held out; every 10th): held-out
  hits and free points every 0.1 m along held-out beams, uniformly subsampled.

A stage earns its place when switching it off makes the scores worse. Each map is fitted in a
process of its own with the stage's module constants set (a stage is off when its fitted part
is held at the value that leaves the map as it was without it). Run from the repository root::

    .venv/bin/python benchmarks/stages.py                       # every stage, every dataset
    .venv/bin/python benchmarks/stages.py --stages base,revisit --datasets cave,intel:blocks
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: Stage name: (what switching it off means, module constants to set, estimator options).
STAGES: dict[str, tuple[str, dict[str, Any], dict[str, Any]]] = {
    "base": ("every stage on (the defaults)", {}, {}),
    "shares": (
        "a scan's hit wins its whole update of a cell (OctoMap's rule)",
        {"gpomap.evidence.SHARED_UPDATES": False},
        {},
    ),
    "revisit": ("no later-visit recalibration", {}, {"fit_revisit": False}),
    "variance_scale": (
        "no variance scale for unseen space (the GP's own variance)",
        {"gpomap.extrapolation.MIN_POINTS_PER_CLASS": 10**9},
        {},
    ),
    "surface": ("surface misses weigh as misses", {"gpomap.fusion.calibration.FIT_SURFACE_WEIGHT": {2: False}}, {}),
    "near": (
        "near misses weigh as misses, and as no hit",
        {"gpomap.fusion.calibration.CALIBRATION_BOUNDS": "near"},
        {},
    ),
    "path": ("the robot's path is no evidence", {"gpomap.fusion.calibration.PATH_HITS": 0.0}, {}),
    "weights": (
        "the counting grid's weights (one hit = one miss, the GP worth two)",
        {"gpomap.fusion.calibration.CALIBRATION_BOUNDS": "fixed"},
        {},
    ),
    # Not stages: the GP's cells made finer. The tree splits a box on below max_cell (0.5 m) only
    # while it holds both classes, so a smaller min_cell alone makes cells finer at surfaces only.
    "min_cell_0.25": ("GP cells holding both classes split down to 0.25 m (pure ones stay 0.5 m)", {}, {"min_cell": 0.25}),
    "min_cell_0.125": ("GP cells holding both classes split down to 0.125 m (pure ones stay 0.5 m)", {}, {"min_cell": 0.125}),
    "cells_0.25": ("GP cells of 0.25 m everywhere", {}, {"min_cell": 0.25, "max_cell": 0.25}),
    # Free points are dropped within free_clearance of a hit (0.1 m in a plane), so the boxes at
    # surfaces hold both classes, and min_cell splits them; a wider clearance leaves few such boxes.
    "clearance_0.3": ("free points kept from 0.3 m of a hit (not 0.1 m)", {}, {"free_clearance": 0.3}),
    "clearance_0.2": ("free points kept from 0.2 m of a hit (not 0.1 m)", {}, {"free_clearance": 0.2}),
    "clearance_0.05": ("free points kept from 0.05 m of a hit (not 0.1 m)", {}, {"free_clearance": 0.05}),
    # A second draw of the map's own randomness (its hyperparameter sample, its calibration points),
    # to tell a variant's gain from one fit's luck.
    "seed_1": ("the map's seed 1 (not 0)", {}, {"seed": 1}),
    "clearance_0.3_seed_1": ("free points kept from 0.3 m of a hit, the map's seed 1", {}, {"free_clearance": 0.3, "seed": 1}),
    # Not a stage: a hit's weight bounded at 4 misses (its search bound is 1,000). On worlds
    # simulated without range noise the fitted weight runs to about 19, on the real logs below 1.
    "hit_weight_4": (
        "a hit weighs at most 4 misses",
        {"gpomap.fusion.calibration.CALIBRATION_BOUNDS": "hit_4"},
        {},
    ),
    "surface_0.125": (
        "free points kept from 0.1 m of a hit, and cells holding both classes split down to 0.125 m",
        {},
        {"free_clearance": 0.1, "min_cell": 0.125},
    ),
}
TRUTH_WORLDS = ("stage-arena", "cave", "hospital_section", "room")
HELD_OUT = ("intel:blocks", "intel:every", "fr079:blocks", "csail:blocks", "belgioioso:blocks")
TEST_POINTS = 40_000


def _bounds(kind: str) -> tuple[tuple[float, float], ...]:
    from gpomap.fusion.calibration import CALIBRATION_BOUNDS

    b = list(CALIBRATION_BOUNDS)
    if kind == "hit_4":
        b[0] = (b[0][0], np.log(4.0))
    elif kind == "near":
        b[2] = (0.0, 0.0)
        b[3] = (b[3][0], b[3][0])
    else:  # the counting grid's: hit 1, prior 2, near miss a miss, no near hit, surface miss a miss
        b = [(0.0, 0.0), (np.log(2.0), np.log(2.0)), (0.0, 0.0), (b[3][0], b[3][0]), (0.0, 0.0)]
    return tuple(b)


def _apply(patches: dict[str, Any]) -> None:
    for key, value in patches.items():
        module, attr = key.rsplit(".", 1)
        target = importlib.import_module(module)
        if not hasattr(target, attr):  # a stage renamed or removed: say so, not a run of the defaults
            raise AttributeError(f"{key} does not exist; update STAGES")
        if key.endswith("CALIBRATION_BOUNDS"):
            value = _bounds(value)
        setattr(target, attr, value)


def held_out_split(dataset: str) -> Any:
    """The split a held-out dataset ``log:split`` names, its training scans and test points, as
    ``benchmarks/quality.py`` makes it (:class:`gpomap.evaluation.EvalData`). Imports gpomap, so a
    stage's patches go first."""
    from gpomap.evaluation import prepare

    sys.path.insert(0, str(Path(__file__).parent))
    import quality

    log, split = dataset.split(":")
    scans, _ = quality.load(log)
    return prepare(scans, split, scan_step=quality.LOGS[log].get("scan_step", 1), seed=0, max_test_points=TEST_POINTS)


def child(stage: str, dataset: str) -> dict[str, Any]:
    """Score one dataset with one stage off (in this process)."""
    _, patches, given = STAGES[stage]
    _apply(patches)
    options = dict(given)
    seed = int(options.pop("seed", 0))  # make_model's own argument
    from gpomap.evaluation import lookup, lookup_occupied, make_model, score, written_grid
    from gpomap.truth import TruthPoints, score_plan

    sys.path.insert(0, str(Path(__file__).parent))
    import quality

    t = time.process_time()
    if ":" in dataset:
        data = held_out_split(dataset)
        model = make_model("msk", None, seed, 0.05, None, **options).fit(data.train)
        fit_cpu = time.process_time() - t
        scores = score(data.labels, lookup(written_grid(model, 0.05), data.points), {"boundary": data.masks["boundary"]})
        return {**{k: scores[k] for k in ("log_loss", "brier", "ece", "auc", "boundary_auc")}, "fit_cpu": fit_cpu}
    scans, plan = quality.load(dataset)
    assert plan is not None, f"{dataset} has no true plan"
    model = make_model("msk", None, seed, 0.05, None, **options).fit(scans)
    fit_cpu = time.process_time() - t
    truth = TruthPoints.of(plan, scans)
    written = written_grid(model, 0.05)
    return {**score_plan(truth, lookup(written, truth.points), lookup_occupied(written, truth.points)), "fit_cpu": fit_cpu}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stages", default=",".join(STAGES), help="comma-separated (default: all)")
    ap.add_argument("--datasets", default=",".join(TRUTH_WORLDS + HELD_OUT), help="comma-separated (default: all)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--child", nargs=2, metavar=("STAGE", "DATASET"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child)))
        return 0
    stages, datasets = args.stages.split(","), args.datasets.split(",")
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        ap.error(f"unknown stage(s) {', '.join(unknown)}; expected some of {', '.join(STAGES)}")
    results: dict[str, dict[str, Any]] = {}
    for stage in stages:
        results[stage] = {}
        for ds in datasets:
            out = subprocess.run([sys.executable, __file__, "--child", stage, ds], capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{stage} on {ds} failed:\n{out.stderr[-2000:]}", file=sys.stderr)
                continue
            results[stage][ds] = json.loads(out.stdout.strip().splitlines()[-1])
            r = results[stage][ds]
            print(f"{stage:16s} {ds:20s} " + " ".join(f"{k} {v:.4f}" for k, v in r.items() if isinstance(v, float)), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    print("\n## Each stage switched off (written map, natural frequencies)\n")
    truth = [d for d in datasets if ":" not in d]
    held = [d for d in datasets if ":" in d]
    for title, group, keys in (
        ("truth", truth, ("log_loss", "auc", "boundary_auc", "iou")),
        ("held out", held, ("log_loss", "ece", "auc", "boundary_auc")),
    ):
        if not group:
            continue
        head = ["stage off", *(f"{d}: {' / '.join(keys)}" for d in group), "fit CPU s (sum)"]
        print(f"### {title}\n")
        print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
        for stage in stages:
            row = [f"{stage} ({STAGES[stage][0]})"]
            for d in group:
                r = results[stage].get(d)
                row.append(" / ".join(f"{r[k]:.4f}" if r.get(k) is not None else "-" for k in keys) if r else "failed")
            row.append(f"{sum(results[stage][d]['fit_cpu'] for d in group if d in results[stage]):.0f}")
            print("| " + " | ".join(row) + " |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
