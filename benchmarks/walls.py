"""Where a written map's walls lose ranking against a true plan: the plan's pixels by what the
counting grid's cell saw.

For each simulated world with a true plan (the Stage arena, the sim-worlds cave and hospital
section, the synthetic room), gpomap's written map (``gpomap map``'s defaults, 0.05 m) and the
counting grid ``(hits + 1) / (hits + misses + 2)`` at 0.05 m are fitted on the whole log and
looked up at every plan pixel the log observed (:mod:`gpomap.truth`, as ``benchmarks/quality.py``
and ``benchmarks/stages.py`` score a plan). The pixels are sorted by the counting grid's cell:

- **no count**: no beam crossed or ended in it;
- **misses only**: beams crossed it, none ended in it; split into cells that only beams with no
  return crossed (taken free to 10 m by both maps, as ``gpomap map`` and the truth's rule take
  them) and cells a beam that returned crossed too;
- **hits only**: beams ended in it, none crossed it;
- **hits and misses**: both.

Two tables per world: for each kind, its share of the pixels and of the boundary pixels (within
0.1 m of a true wall), the occupied share, each map's mean probability, its part of the log loss
and its boundary AUC within the kind; then the map's truth AUC and boundary AUC with the counting
grid's probability taken in place of its own in one kind of cell at a time (how much of the gap to
the grid each kind holds). Each world is fitted in a process of its own. Usage, from the
repository's root::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/walls.py                       # every world
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/walls.py --worlds hospital_section
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
from quality import load
from stages import TRUTH_WORLDS

RESOLUTION = 0.05
KINDS = ("no count", "misses only", "of them, no-return beams only", "hits only", "hits and misses")


def _kinds(
    hits: NDArray[np.int64], misses: NDArray[np.int64], returned_misses: NDArray[np.int64]
) -> dict[str, NDArray[np.bool_]]:
    """Each kind of counting-grid cell as a mask over the pixels (matching shapes);
    `returned_misses` counts only the beams that returned."""
    return {
        "no count": (hits == 0) & (misses == 0),
        "misses only": (hits == 0) & (misses > 0),
        "of them, no-return beams only": (hits == 0) & (misses > 0) & (returned_misses == 0),
        "hits only": (hits > 0) & (misses == 0),
        "hits and misses": (hits > 0) & (misses > 0),
    }


def _auc(labels: NDArray[np.bool_], scores: NDArray[np.float64]) -> float | None:
    """ROC AUC, or None where the pixels hold one class only."""
    return roc_auc(labels, scores) if 0 < labels.sum() < labels.size else None


def child(world: str) -> dict[str, Any]:
    """Both maps of one world at its plan's observed pixels, and the breakdown (in this process)."""
    scans, plan = load(world)
    if plan is None:
        raise SystemExit(f"{world} has no true plan")
    truth = TruthPoints.of(plan, scans)
    gpomap_map = written_grid(make_model("msk", None, 0, RESOLUTION, None).fit(scans), RESOLUTION)
    counting = make_model("ogm-counting", None, 0, RESOLUTION, None).fit(scans)
    assert isinstance(counting, OccupancyGridMapper)
    p_map = lookup(gpomap_map, truth.points)
    grid_map = written_grid(counting, RESOLUTION)  # its own grid, that of its counts
    assert grid_map.probability.shape == counting.hits_.shape
    p_grid = lookup(grid_map, truth.points)
    # The same counts on the same grid without the beams that returned nothing.
    returned = make_model("ogm-counting", None, 0, RESOLUTION, None, max_range_free=0.0, extent=counting.grid_).fit(scans)
    assert isinstance(returned, OccupancyGridMapper)
    rows, cols, inside = grid_map.grid.index_of(truth.points)
    hits, misses, returned_misses = (np.zeros(len(p_map), dtype=np.int64) for _ in range(3))
    hits[inside] = counting.hits_[rows[inside], cols[inside]]
    misses[inside] = counting.misses_[rows[inside], cols[inside]]
    returned_misses[inside] = returned.misses_[rows[inside], cols[inside]]
    y, boundary, n = truth.occupied, truth.boundary, len(p_map)
    kinds: dict[str, Any] = {}
    for name, mask in _kinds(hits, misses, returned_misses).items():
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
    return {"pixels": n, "scores": scores, "kinds": kinds}


def _f(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def print_world(world: str, r: dict[str, Any]) -> None:
    """The two tables of one world."""
    s = r["scores"]
    print(
        f"\n### {world}: {r['pixels']} pixels; truth AUC / boundary AUC / log loss: gpomap "
        f"{s['map']['auc']:.4f} / {s['map']['boundary_auc']:.4f} / {s['map']['log_loss']:.4f}, counting grid "
        f"{s['grid']['auc']:.4f} / {s['grid']['boundary_auc']:.4f} / {s['grid']['log_loss']:.4f}\n"
    )
    print(
        "| counting grid's cell | share of pixels / of boundary pixels | occupied | mean p gpomap / grid "
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
    print("\n| gpomap with the grid's p in | truth AUC | boundary AUC |\n|---|---|---|")
    print(f"| (no cell: gpomap as it is) | {s['map']['auc']:.4f} | {s['map']['boundary_auc']:.4f} |")
    for name in KINDS:
        w = r["kinds"][name]["swapped"]
        print(f"| {name} | {w['auc']:.4f} | {w['boundary_auc']:.4f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default=",".join(TRUTH_WORLDS), help="comma-separated (default: %(default)s)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return 0
    worlds = [w for w in args.worlds.split(",") if w]
    unknown = sorted(set(worlds) - set(TRUTH_WORLDS))
    if unknown:
        ap.error(f"unknown world(s) {', '.join(unknown)}; expected some of {', '.join(TRUTH_WORLDS)}")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"# Walls against the true plans (commit {commit}; gpomap map's defaults and the counting grid, {RESOLUTION} m)")
    results: dict[str, Any] = {}
    for world in worlds:
        out = subprocess.run([sys.executable, __file__, "--child", world], capture_output=True, text=True)
        if out.returncode != 0:
            print(f"{world} failed:\n{out.stderr[-2000:]}", file=sys.stderr)
            continue
        results[world] = json.loads(out.stdout.strip().splitlines()[-1])
        print_world(world, results[world])
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0 if len(results) == len(worlds) else 1


if __name__ == "__main__":
    sys.exit(main())
