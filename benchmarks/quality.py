"""Map quality on every shared log and simulated world: gpomap as ``gpomap map`` builds it against the standard grids.

For each log and each of the protocol's two splits (``blocks``: blocks of 40 consecutive scans,
every 5th held out; ``every``: every 10th scan held out), every method is fitted on the training
scans only and scored on the same test points from the held-out scans, at their natural
frequencies (:mod:`gpomap.evaluation`: every held-out hit and free points every 0.1 m along the
held-out beams, uniformly subsampled: a few per cent are hits): its exact-point predictions and
its written map (``grid(0.05)`` then a cell lookup; a grid's written map is itself). Where the
log comes with its true plan (the Stage arena, the simulated worlds of ``sim-worlds/``, the
synthetic room), the written maps are also scored against it, pixel by pixel where the log
looked (:mod:`gpomap.truth`). Methods:

- ``msk``: gpomap with the library's defaults, built exactly as ``gpomap map`` builds it (local
  GPs in tiles of 5 m, on every core: :func:`gpomap.evaluation.make_model`);
- ``ogm-logodds-0.05``, ``ogm-logodds-0.1``: OctoMap's log-odds grid at 0.05 and 0.1 m;
- ``ogm-counting-0.05``: the counting grid at 0.05 m.

Logs: Intel, FR079 (every 3rd of its 4,791 scans), CSAIL, Belgioioso, the Stage arena bag, the
simulated cave and hospital section, and a simulated tour of the synthetic room of
:mod:`gpomap.simulate`. Each method runs in a forked child process
(:func:`gpomap.comparison.run_apart`) so its peak memory is its own.

Run from the repository root::

    .venv/bin/python benchmarks/quality.py                    # everything (an hour or two on 2 cores)
    .venv/bin/python benchmarks/quality.py --quick            # a smoke run: a few scans per log
    .venv/bin/python benchmarks/quality.py --logs intel,cave --splits every --json out.json
    .venv/bin/python benchmarks/quality.py --log-file robot.log.gz --log-file lab.bag   # your own logs

``--log-file`` scores any log or bag :func:`gpomap.io.read_scans` reads (a CARMEN log, a ROS bag
with one laser topic) the same way, named by its file; given alone, only those logs are run.

In each table '*' marks the best value of a metric among the rows of that log and split
(exact points and written grids together). An occupancy grid's exact-point prediction is a
lookup in its own grid, which is also its written map: one row ("own grid").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.comparison import GPOMAP, METHODS, TARGET_NAMES, format_value, run_apart, score_curves, table, tally, targets
from gpomap.evaluation import prepare, resolve_split
from gpomap.truth import PlanTruth

DATA = Path("..") / "shared" / "data"
LOGS: dict[str, dict[str, Any]] = {
    "intel": {"path": DATA / "intel" / "intel-corrected.log.gz", "title": "Intel Research Lab"},
    "fr079": {"path": DATA / "fr079" / "freiburg-079-corrected.log.gz", "scan_step": 3, "title": "Freiburg 079 (every 3rd scan)"},
    "csail": {"path": DATA / "csail-robotlaser1" / "csail.log.gz", "title": "MIT CSAIL"},
    "belgioioso": {"path": DATA / "belgioioso" / "belgioioso-corrected.log.gz", "title": "Belgioioso castle"},
    "stage-arena": {"path": DATA / "stage-arena" / "robot1.bag", "title": "Stage arena (true plan)"},
    "cave": {"path": DATA / "sim-worlds" / "cave" / "cave.log.gz", "title": "simulated cave (true plan)"},
    "hospital_section": {
        "path": DATA / "sim-worlds" / "hospital_section" / "hospital_section.log.gz",
        "title": "simulated hospital section (true plan)",
    },
    "room": {"path": None, "title": "synthetic room, 400 scans x 180 beams, 2 cm noise (true geometry)"},
}
SPLIT_NAMES = ("blocks", "every")
#: Test points per log and split (a seeded uniform subsample at natural frequencies; the same for every method).
MAX_TEST_POINTS = 40000
GRID_RESOLUTION = 0.05
#: The synthetic room's walls drawn one pixel thick at this pixel size (m), as the other plans' are.
ROOM_PLAN_PIXEL = 0.01
QUICK = {"scan_range": "0:120", "n_scans": 30, "n_beams": 90, "max_test_points": 2000, "grid_resolution": 0.2}


# ------------------------------------------------------------------------------ data
def _room(seed: int = 0) -> list[Any]:
    """The synthetic room's simulated tour: 400 poses along the paper's 31-pose tour (evenly by
    arc length), heading along the path."""
    from gpomap.simulate import paper_room, simulate_scans

    world, poses = paper_room()
    xy = poses[:, :2]
    arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
    s = np.linspace(0.0, arc[-1], 400)
    dense = np.column_stack([np.interp(s, arc, xy[:, 0]), np.interp(s, arc, xy[:, 1])])
    step = np.gradient(dense, axis=0)
    dense = np.column_stack([dense, np.arctan2(step[:, 1], step[:, 0])])
    return simulate_scans(world, dense, 180, noise_std=0.02, seed=seed)


def load(name: str) -> tuple[list[Any], PlanTruth | None]:
    """The scans of a log and its true plan (None for real logs)."""
    spec = LOGS[name]
    if name == "room":
        from gpomap.simulate import paper_room

        return _room(), PlanTruth.from_world(paper_room()[0], ROOM_PLAN_PIXEL)
    if name == "stage-arena":
        from PIL import Image

        from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the last scan has no later pose and is dropped, with a warning
            scans = read_rosbag(spec["path"], time_offset=STAGE_TIME_OFFSET)
        img = np.asarray(Image.open(DATA / "stage-arena" / "mrl_arena.pgm"))
        # The data README: Stage stretches the 406 x 460 bitmap to 4.06 m x 4.55 m centred at (1, 1).
        return scans, PlanTruth(img < 128, (-1.03, -1.275), (0.0100, 0.009891))
    from gpomap.io import read_scans

    scans = read_scans(spec["path"])
    folder = Path(spec["path"]).parent
    if folder.parent.name == "sim-worlds":
        # The worlds' README: square pixels of `resolution`, lower-left corner at `origin`, 0 = occupied.
        meta = json.loads((folder / f"{name}.json").read_text())
        return scans, PlanTruth.from_image(folder / f"{name}.truth.png", meta["resolution"], meta["origin"])
    return scans, None


# ------------------------------------------------------------------------------ tables
def _title(log: str) -> str:
    """A log's title; a --log-file log's (read back from JSON) is its name."""
    return str(LOGS[log]["title"]) if log in LOGS else log


def summary_table(results: list[dict[str, Any]]) -> list[str]:
    """One line per log and split: gpomap's written map against the best grid for each metric.

    "Best grid" is the best of the grid methods for that metric (higher AUC, lower log loss, Brier
    and ECE; against the true plan the same, higher IoU); CPU is gpomap's fit plus its written map
    against the log-odds grid at 0.05 m.
    """
    held = (("auc", True), ("boundary_auc", True), ("log_loss", False), ("brier", False), ("ece", False))
    plan = (("auc", True), ("boundary_auc", True), ("log_loss", False), ("iou", True), ("ternary_iou", True))
    head = [
        "log, split",
        "held out: AUC / boundary AUC / log loss / Brier / ECE (gpomap | best grid)",
        "true plan: AUC / boundary AUC / log loss / IoU p>0.5 / IoU ternary (gpomap | best grid)",
        "path cells occupied",
        "fit + map CPU s, gpomap / log-odds 0.05",
    ]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for log, split in dict.fromkeys((r["log"], r["split"]) for r in results):
        rows = {r["name"]: r for r in results if (r["log"], r["split"]) == (log, split)}
        if GPOMAP not in rows:
            continue
        msk = rows[GPOMAP]
        grids = [r for n, r in rows.items() if n != GPOMAP]

        def pair(
            where: str, metrics: tuple[tuple[str, bool], ...], msk: dict[str, Any] = msk, grids: list[dict[str, Any]] = grids
        ) -> str:
            if not msk.get(where):
                return "-"
            mine, best = [], []
            for key, higher in metrics:
                vals = [g[where][key] for g in grids if g.get(where) and g[where].get(key) is not None]
                mine.append(format_value(msk[where].get(key)))
                best.append(format_value((max(vals) if higher else min(vals)) if vals else None))
            return f"{' / '.join(mine)} \\| {' / '.join(best)}"

        path = msk["path"]["grid"]
        lo = rows.get("ogm-logodds-0.05")
        cpu = f"{msk['cpu_seconds']['fit'] + msk['cpu_seconds'].get('grid', 0):.0f}"
        cpu += f" / {lo['cpu_seconds']['fit']:.0f}" if lo else ""
        line = [
            f"{_title(log)}: {resolve_split(split)}",
            pair("grid", held),
            pair("plan", plan),
            f"{path['n_occupied']} of {path['n_cells']}",
            cpu,
        ]
        out.append("| " + " | ".join(line) + " |")
    return out


def criteria_table(results: list[dict[str, Any]]) -> tuple[list[str], int, int]:
    """One line per log and split: which targets MSK-GPOM's written map meets
    (:func:`gpomap.comparison.targets`). A target met reads "yes"; one missed, the two values;
    one not checked (no grid, no truth), "-".

    Returns
    -------
    lines : list of str
        The markdown table.
    met, checked : int
        Targets met and targets checked.
    """
    head = ["log, split", *TARGET_NAMES, "met"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    met = checked = 0
    for log, split in dict.fromkeys((r["log"], r["split"]) for r in results):
        rows = [r for r in results if (r["log"], r["split"]) == (log, split)]
        if not any(r["name"] == GPOMAP for r in rows):
            continue
        found = targets(rows)
        n_met, n_checked = tally(found)
        met, checked = met + n_met, checked + n_checked
        line = [f"{_title(log)}: {resolve_split(split)}", *(t.cell() for t in found), f"{n_met} of {n_checked}"]
        out.append("| " + " | ".join(line) + " |")
    return out, met, checked


def reliability_figure(results: list[dict[str, Any]], log: str, path: Path) -> None:
    """Reliability diagrams of one log: a panel per split, a curve per method and prediction."""
    from gpomap.plot import plot_evaluation

    splits = [s for s in SPLIT_NAMES if any(r["log"] == log and r["split"] == s for r in results)]
    if splits:
        panels = [
            (
                f"{_title(log)}: {resolve_split(split)}",
                score_curves([r for r in results if r["log"] == log and r["split"] == split]),
            )
            for split in splits
        ]
        plot_evaluation(panels, path)


def print_summary(results: list[dict[str, Any]]) -> None:
    """Print the summary table and the targets met, from a run's results (or its --json file)."""
    cells = {r["settings"]["grid_resolution"] for r in results if r["name"] == GPOMAP}
    written = f"written {cells.pop():g} m map" if len(cells) == 1 else "written map"
    print(f"\n## Summary ({written} against the best grid variant for each metric)\n")
    print("\n".join(summary_table(results)))
    lines, met, checked = criteria_table(results)
    print(f"\n## Targets met by the written map: {met} of {checked}\n")
    print("\n".join(lines))


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", help=f"comma-separated (default: {','.join(LOGS)}; none when --log-file is given)")
    ap.add_argument(
        "--log-file",
        type=Path,
        action="append",
        default=[],
        metavar="PATH",
        help="also score this log (CARMEN log or ROS bag), named by its file (repeatable)",
    )
    ap.add_argument("--scan-step", type=int, default=1, metavar="N", help="every Nth scan of each --log-file (default: 1)")
    ap.add_argument("--splits", default=",".join(SPLIT_NAMES), help="comma-separated (default: %(default)s)")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated (default: %(default)s)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke run: scans {QUICK['scan_range']} of each log, {QUICK['n_scans']} training scans of "
        f"{QUICK['n_beams']} beams, {QUICK['max_test_points']} test points, written grids at {QUICK['grid_resolution']} m",
    )
    ap.add_argument("--max-test-points", type=int, default=MAX_TEST_POINTS)
    ap.add_argument("--figures", type=Path, help="write reliability diagrams reliability-<log>.png here")
    ap.add_argument("--json", type=Path, metavar="OUT", help="write every result (without the models) as JSON")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--fit-surprise-rate",
        action="store_true",
        help="gpomap with its surprise rate fitted on each log's own scans (gpomap map --fit-surprise-rate)",
    )
    ap.add_argument(
        "--summary-from", type=Path, metavar="JSON", help="print the summary and the targets met of a --json file and stop"
    )
    args = ap.parse_args(argv)
    if args.summary_from:
        print_summary(json.loads(args.summary_from.read_text()))
        return 0
    gpomap_options = {"fit_surprise_rate": True} if args.fit_surprise_rate else {}
    for path in args.log_file:
        if not path.exists():
            ap.error(f"--log-file {path}: no such file")
        name = path.name.split(".")[0]
        LOGS[name] = {"path": path, "title": path.name, "scan_step": args.scan_step, "own": True}
    default_logs = "" if args.log_file else ",".join(k for k, v in LOGS.items() if not v.get("own"))
    chosen = args.logs if args.logs is not None else default_logs
    logs = [n for n in chosen.split(",") if n] + [p.name.split(".")[0] for p in args.log_file]
    splits, methods = (a.split(",") for a in (args.splits, args.methods))
    for given, known, what in ((logs, LOGS, "log"), (methods, METHODS, "method")):
        bad = sorted(set(given) - set(known))
        if bad:
            ap.error(f"unknown {what}(s) {', '.join(bad)}; expected some of {', '.join(known)}")
    grid_res = QUICK["grid_resolution"] if args.quick else GRID_RESOLUTION
    print(
        f"# Map quality (commit {_commit()}, {os.cpu_count()} CPUs; {' '.join(['benchmarks/quality.py'] + (argv or sys.argv[1:]))})"
    )
    print(
        f"Written grids at {grid_res} m; at most {QUICK['max_test_points'] if args.quick else args.max_test_points} "
        "test points per log and split, at their natural frequencies; far p = predictions on lattice points > 5 m from "
        "any training beam; path occ = cells (0.05 m) of the robot's own path (training and held-out poses) the map's "
        "ternary map calls occupied (gpomap: p > 0.5, never a cell beams saw through; the grids: p > 0.66), of all "
        "path cells. Against a true plan: every plan pixel the whole log observed (gpomap.truth), the written map "
        "fitted on the training scans; the grids' ternary map as map_server reads it (occupied above 0.65).",
        flush=True,
    )
    results: list[dict[str, Any]] = []
    for log in logs:
        spec = LOGS[log]
        if spec["path"] is not None and not Path(spec["path"]).exists():
            print(f"\nskipping {log}: {spec['path']} not found", flush=True)
            continue
        t = time.perf_counter()
        scans, plan = load(log)
        read_s = time.perf_counter() - t
        for split in splits:
            kw: dict[str, Any] = {
                "scan_step": spec.get("scan_step", 1),
                "seed": args.seed,
                "plan": plan,
                "max_test_points": args.max_test_points,
            }
            if args.quick:
                kw.update(
                    scan_range=QUICK["scan_range"],
                    n_scans=QUICK["n_scans"],
                    n_beams=QUICK["n_beams"],
                    max_test_points=QUICK["max_test_points"],
                )
            data = prepare(scans, split, **kw)
            rows = []
            for name in methods:
                r = run_apart(data, name, args.seed, grid_res, **gpomap_options)
                r.update(log=log, split=split)
                rows.append(r)
                results.append(r)
            m = data.masks
            print(f"\n## {spec['title']}: {resolve_split(split)} ({len(scans)} scans in the log, read in {read_s:.1f} s)\n")
            print(
                f"Training {len(data.train)} scans, {len(data.test)} held out; {data.labels.size} test points "
                f"({int(m['boundary'].sum())} boundary, {int(m['observed'].sum())} in observed cells, "
                f"{int(m['unobserved'].sum())} not; {int(data.far_test.sum())} > 5 m from the data); MSK-GPOM "
                + (f"in {rows[0]['settings']['tiles']} tiles, " if methods[0] == GPOMAP and rows[0]["settings"]["tiles"] else "")
                + (
                    f"{rows[0]['n_inputs']} cells, ternary map occupied above {rows[0]['occupied_threshold']:.3f}.\n"
                    if methods[0] == GPOMAP
                    else "\n"
                )
            )
            print("\n".join(table(rows, plan is not None)), flush=True)
        if args.figures:
            args.figures.mkdir(parents=True, exist_ok=True)
            reliability_figure(results, log, args.figures / f"reliability-{log}.png")
    print_summary(results)
    if args.json:
        args.json.write_text(json.dumps(results, default=str, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
