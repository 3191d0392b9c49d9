"""Where a written map's walls lose ranking against a true plan: the scored points by what the
counting grid's cell saw.

For each simulated world with a true plan (the Stage arena, the sim-worlds cave and hospital
section, the synthetic room), gpomap's written map (``gpomap map``'s defaults, 0.05 m) and the
counting grid ``(hits + 1) / (hits + misses + 2)`` at 0.05 m are fitted on the whole log and
looked up at every plan pixel the log observed (:mod:`gpomap.truth`, as ``benchmarks/quality.py``
and ``benchmarks/stages.py`` score a plan). A held-out dataset (``log:split``, as
``benchmarks/stages.py`` names them) fits both on the split's training scans and looks them up at
``benchmarks/quality.py``'s held-out test points, at their natural frequencies (boundary: within
0.5 m of a held-out hit). The points are sorted by the counting grid's cell:

- **no count**: no beam crossed or ended in it;
- **misses only**: beams crossed it, none ended in it; split into cells that only beams with no
  return crossed (taken free to 10 m by both maps, as ``gpomap map`` and the truth's rule take
  them) and cells a beam that returned crossed too;
- **hits only**: beams ended in it, none crossed it;
- **hits and misses**: both.

Three tables per dataset: for each kind, its share of the points and of the boundary points
(against a plan: within 0.1 m of a true wall), the occupied share, each map's mean probability,
its part of the log loss and its boundary AUC within the kind; then the map's AUC and boundary AUC
with the counting grid's probability taken in place of its own in one kind of cell at a time (how
much of the gap to the grid each kind holds); then the map's log loss and AUC with one constant
probability in the cells that only beams without a return crossed (what a rate fitted for those
cells could give). Each dataset is fitted in a process of its own. Usage, from the repository's
root::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/walls.py       # every world, and benchmarks/stages.py's held-out splits
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/walls.py --datasets hospital_section,intel:blocks
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.baselines.ogm import OccupancyGridMapper
from gpomap.evaluation import lookup, make_model, written_grid
from gpomap.metrics import log_loss, roc_auc
from gpomap.truth import TruthPoints

sys.path.insert(0, str(Path(__file__).resolve().parent))
from quality import LOGS, load
from stages import HELD_OUT, TRUTH_WORLDS, held_out_split

RESOLUTION = 0.05
NO_RETURN_ONLY = "of them, no-return beams only"
KINDS = ("no count", "misses only", NO_RETURN_ONLY, "hits only", "hits and misses")
#: Constant probabilities tried in the cells only beams without a return crossed.
CONSTANTS = (0.01, 0.02, 0.04, 0.08)


def _kinds(
    hits: NDArray[np.int64], misses: NDArray[np.int64], returned_misses: NDArray[np.int64]
) -> dict[str, NDArray[np.bool_]]:
    """Each kind of counting-grid cell as a mask over the scored points (matching shapes);
    `returned_misses` counts only the beams that returned."""
    return {
        "no count": (hits == 0) & (misses == 0),
        "misses only": (hits == 0) & (misses > 0),
        NO_RETURN_ONLY: (hits == 0) & (misses > 0) & (returned_misses == 0),
        "hits only": (hits > 0) & (misses == 0),
        "hits and misses": (hits > 0) & (misses > 0),
    }


def _auc(labels: NDArray[np.bool_], scores: NDArray[np.float64]) -> float | None:
    """ROC AUC, or None where the pixels hold one class only."""
    return roc_auc(labels, scores) if 0 < labels.sum() < labels.size else None


def _scored(dataset: str) -> tuple[list[Any], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """The scans both maps are fitted on, and the scored points (n, 2), their labels and
    boundary mask (n,): a world's observed plan pixels, or a held-out split's test points."""
    if ":" in dataset:
        data = held_out_split(dataset)
        return list(data.train), data.points, np.asarray(data.labels, dtype=bool), data.masks["boundary"]
    scans, plan = load(dataset)
    if plan is None:
        raise SystemExit(f"{dataset} has no true plan")
    truth = TruthPoints.of(plan, scans)
    return scans, truth.points, truth.occupied, truth.boundary


def child(dataset: str) -> dict[str, Any]:
    """Both maps of one dataset at its scored points, and the breakdown (in this process)."""
    scans, points, y, boundary = _scored(dataset)
    gpomap_map = written_grid(make_model("msk", None, 0, RESOLUTION, None).fit(scans), RESOLUTION)
    counting = make_model("ogm-counting", None, 0, RESOLUTION, None).fit(scans)
    assert isinstance(counting, OccupancyGridMapper)
    p_map = lookup(gpomap_map, points)
    grid_map = written_grid(counting, RESOLUTION)  # its own grid, that of its counts
    assert grid_map.probability.shape == counting.hits_.shape
    p_grid = lookup(grid_map, points)
    # The same counts on the same grid without the beams that returned nothing.
    returned = make_model("ogm-counting", None, 0, RESOLUTION, None, max_range_free=0.0, extent=counting.grid_).fit(scans)
    assert isinstance(returned, OccupancyGridMapper)
    rows, cols, inside = grid_map.grid.index_of(points)
    hits, misses, returned_misses = (np.zeros(len(p_map), dtype=np.int64) for _ in range(3))
    hits[inside] = counting.hits_[rows[inside], cols[inside]]
    misses[inside] = counting.misses_[rows[inside], cols[inside]]
    returned_misses[inside] = returned.misses_[rows[inside], cols[inside]]
    n = len(p_map)
    kinds: dict[str, Any] = {}
    masks = _kinds(hits, misses, returned_misses)
    for name, mask in masks.items():
        on_boundary = mask & boundary
        kinds[name] = {
            "share": float(mask.mean()),
            "boundary_share": float(on_boundary.sum() / boundary.sum()),
            "occupied": float(y[mask].mean()) if mask.any() else None,
        }
        for label, p in (("map", p_map), ("grid", p_grid)):
            kinds[name][label] = {
                "mean_p": float(p[mask].mean()) if mask.any() else None,
                # The kind's part of the log loss over every pixel: the four kinds' parts add up to it.
                "log_loss_part": log_loss(y[mask], p[mask]) * mask.sum() / n if mask.any() else 0.0,
                "boundary_auc": _auc(y[on_boundary], p[on_boundary]),
            }
        swapped = np.where(mask, p_grid, p_map)
        kinds[name]["swapped"] = {"auc": roc_auc(y, swapped), "boundary_auc": roc_auc(y[boundary], swapped[boundary])}
    scores = {
        label: {"auc": roc_auc(y, p), "boundary_auc": roc_auc(y[boundary], p[boundary]), "log_loss": log_loss(y, p)}
        for label, p in (("map", p_map), ("grid", p_grid))
    }
    constants = {}
    for c in CONSTANTS:
        p = np.where(masks[NO_RETURN_ONLY], c, p_map)
        constants[str(c)] = {"log_loss": log_loss(y, p), "auc": roc_auc(y, p), "boundary_auc": roc_auc(y[boundary], p[boundary])}
    what = "test points" if ":" in dataset else "pixels"
    return {"points": n, "what": what, "scores": scores, "kinds": kinds, "constants": constants}


def _f(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def print_dataset(dataset: str, r: dict[str, Any]) -> None:
    """The three tables of one dataset."""
    s, what = r["scores"], r["what"]
    against = "truth" if what == "pixels" else "held out"
    print(
        f"\n### {dataset}: {r['points']} {what}; {against} AUC / boundary AUC / log loss: gpomap "
        f"{s['map']['auc']:.4f} / {s['map']['boundary_auc']:.4f} / {s['map']['log_loss']:.4f}, counting grid "
        f"{s['grid']['auc']:.4f} / {s['grid']['boundary_auc']:.4f} / {s['grid']['log_loss']:.4f}\n"
    )
    print(
        f"| counting grid's cell | share of {what} / of boundary {what} | occupied | mean p gpomap / grid "
        "| log loss part gpomap / grid | boundary AUC within, gpomap / grid |"
    )
    print("|---|---|---|---|---|---|")
    for name in KINDS:
        k, m, g = r["kinds"][name], r["kinds"][name]["map"], r["kinds"][name]["grid"]
        print(
            f"| {name} | {k['share']:.3f} / {k['boundary_share']:.3f} | {_f(k['occupied'])} | "
            f"{_f(m['mean_p'])} / {_f(g['mean_p'])} | {m['log_loss_part']:.4f} / {g['log_loss_part']:.4f} | "
            f"{_f(m['boundary_auc'])} / {_f(g['boundary_auc'])} |"
        )
    print("\n| gpomap with the grid's p in | AUC | boundary AUC |\n|---|---|---|")
    print(f"| (no cell: gpomap as it is) | {s['map']['auc']:.4f} | {s['map']['boundary_auc']:.4f} |")
    for name in KINDS:
        w = r["kinds"][name]["swapped"]
        print(f"| {name} | {w['auc']:.4f} | {w['boundary_auc']:.4f} |")
    print(
        "\n| gpomap with p in the cells only beams without a return crossed | log loss | AUC | boundary AUC |\n|---|---|---|---|"
    )
    print(f"| (as it is) | {s['map']['log_loss']:.4f} | {s['map']['auc']:.4f} | {s['map']['boundary_auc']:.4f} |")
    for c, v in r["constants"].items():
        print(f"| {c} | {v['log_loss']:.4f} | {v['auc']:.4f} | {v['boundary_auc']:.4f} |")


def _known(dataset: str) -> bool:
    """A world with a true plan, or ``log:split`` of a log ``benchmarks/quality.py`` reads."""
    if ":" not in dataset:
        return dataset in TRUTH_WORLDS
    log, split = dataset.split(":", 1)
    return log in LOGS and split in ("blocks", "every")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--datasets",
        default=",".join(TRUTH_WORLDS + HELD_OUT),
        help="comma-separated worlds and log:split (blocks or every) (default: %(default)s)",
    )
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return 0
    datasets = [d for d in args.datasets.split(",") if d]
    unknown = [d for d in datasets if not _known(d)]
    if unknown:
        ap.error(
            f"unknown dataset(s) {', '.join(unknown)}; expected worlds of {', '.join(TRUTH_WORLDS)} or log:split of {', '.join(LOGS)}"
        )
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(
        f"# Walls, by what the counting grid's cell saw (commit {commit}; gpomap map's defaults and the counting grid, {RESOLUTION} m)"
    )
    results: dict[str, Any] = {}
    for dataset in datasets:
        out = subprocess.run([sys.executable, __file__, "--child", dataset], capture_output=True, text=True)
        if out.returncode != 0:
            print(f"{dataset} failed:\n{out.stderr[-2000:]}", file=sys.stderr)
            continue
        results[dataset] = json.loads(out.stdout.strip().splitlines()[-1])
        print_dataset(dataset, results[dataset])
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0 if len(results) == len(datasets) else 1


if __name__ == "__main__":
    sys.exit(main())
