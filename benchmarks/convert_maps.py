"""Benchmark grid-to-GP conversion (gpomap.convert) on the shared maps.

(a) The TurtleBot3 world map (384 x 384, 0.05 m): agreement with the input on known pixels, whether
    small gaps between wall pixels are closed, how uncertain the large unknown regions stay.
(b) The Stage arena's true plan ``mrl_arena.pgm`` (406 x 460 px, occupied = value < 128, everything
    else free). Its YAML is wrong and Stage really stretches it to 4.06 m x 4.55 m (0.0100 m x
    0.009891 m pixels); for simplicity we treat it as a square-pixel 0.01 m grid (4.06 m x 4.60 m,
    lower-left corner (-1.03, -1.275)). It is down-sampled to a coarse grid as occupancy grids are
    made (``--pooling``: a coarse pixel occupied if any of its fine pixels is, if most are, or the
    occupied share as its probability; the width is padded with free pixels to a whole number of
    coarse pixels), converted back to 0.01 m, and compared with the true fine plan, alongside
    nearest-neighbour and bilinear up-sampling of the coarse grid (scipy.ndimage.zoom, orders 0 and
    1, ``grid_mode=True`` so pixel edges line up). Measures on the 406 x 460 true pixels: ROC AUC of
    the score (probability / interpolated occupancy) against true occupancy, and accuracy and IoU of
    occupied pixels with "occupied" = score > 0.5 (for the GP also = ternary occupied, p > 0.66).
(c) The end-to-end time of converting the 384 x 384 map (read, fit, predict the whole grid).

Run from the project root:  ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/convert_maps.py``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gpomap.convert import convert_grid
from gpomap.grid import FREE, OCCUPIED, UNKNOWN, GridSpec, OccupancyMap
from gpomap.io.rosmap import read_map_image, read_rosmap
from gpomap.metrics import roc_auc

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ARENA_ORIGIN = (-1.03, -1.275)
ARENA_RESOLUTION = 0.01


def _table(title: str, header: list[str], rows: list[list[str]]) -> None:
    """Print a plain-text table with right-aligned columns."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print(f"\n{title}")
    line = "  ".join(h.rjust(w) for h, w in zip(header, widths))
    print(line)
    print("-" * len(line))
    for r in rows:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))


def gap_pixels(occupied: NDArray[np.bool_], unknown: NDArray[np.bool_], reach: int = 2) -> NDArray[np.bool_]:
    """Unknown pixels lying between two occupied pixels within `reach` pixels.

    Parameters
    ----------
    occupied, unknown : ndarray of bool, shape (ny, nx)
    reach : int
        A pixel u counts when occupied pixels sit at u + d and u - d for some offset d with
        Chebyshev length 1..reach (so on opposite sides of u, at most 2 * reach pixels apart).

    Returns
    -------
    ndarray of bool, shape (ny, nx)
    """
    ny, nx = occupied.shape
    pad = np.pad(occupied, reach)
    out = np.zeros_like(occupied)
    for dy in range(-reach, reach + 1):
        for dx in range(0, reach + 1):
            if (dx == 0 and dy <= 0) or max(abs(dx), abs(dy)) == 0:
                continue  # each opposite pair once
            plus = pad[reach + dy : reach + dy + ny, reach + dx : reach + dx + nx]
            minus = pad[reach - dy : reach - dy + ny, reach - dx : reach - dx + nx]
            out |= plus & minus
    return out & unknown


def bench_turtlebot(path: Path) -> dict[str, float]:
    """Part (a) and (c): convert the TurtleBot3 map and measure it."""
    src = read_rosmap(path)
    t = time.perf_counter()
    res = convert_grid(path)
    total = time.perf_counter() - t
    rep = res.report
    m = res.map
    lab = m.ternary
    print(f"TurtleBot3 map {path}: {src.grid.shape[0]} x {src.grid.shape[1]} px at {src.grid.resolution} m")
    print(
        f"pixels: {rep['pixels']['free']} free, {rep['pixels']['occupied']} occupied, {rep['pixels']['unknown']} unknown; "
        f"{rep['cells']['n']} cells ({rep['cells']['occupied']} occupied, {rep['cells']['ambiguous']} ambiguous)"
    )
    hp = rep["hyperparameters"]
    print("hyperparameters: " + ", ".join(f"{k} {v:.4g}" for k, v in hp.items()))
    ag = rep["agreement"]
    _table(
        "(a) agreement with the input on known pixels",
        ["measure", "value"],
        [
            ["ternary label matches (all known)", f"{ag['ternary']:.4f}"],
            ["  free pixels labelled free", f"{ag['free']:.4f}"],
            ["  occupied pixels labelled occupied", f"{ag['occupied']:.4f}"],
            ["AUC of p vs known labels", f"{ag['auc']:.4f}"],
        ],
    )

    gaps = gap_pixels(src.occupied, src.unknown, reach=2)
    gaps1 = gap_pixels(src.occupied, src.unknown, reach=1)
    rows = []
    for name, mask in (("between occupied within 1 px", gaps1), ("between occupied within 2 px", gaps)):
        n = int(mask.sum())
        rows.append(
            [
                name,
                str(n),
                f"{(lab[mask] == OCCUPIED).mean():.3f}" if n else "-",
                f"{(lab[mask] == UNKNOWN).mean():.3f}" if n else "-",
                f"{m.probability[mask].mean():.3f}" if n else "-",
            ]
        )
    _table("(a) gaps: unknown pixels between two occupied pixels", ["unknown pixels", "n", "occupied", "unknown", "mean p"], rows)

    # Distance (pixels) of every unknown pixel to the nearest known one.
    dist = ndimage.distance_transform_edt(src.unknown)
    bands = [(0.5, 2.5, "1-2 px"), (2.5, 10.5, "3-10 px"), (10.5, 20.5, "11-20 px"), (20.5, np.inf, "> 20 px (1 m)")]
    rows = []
    for lo, hi, name in bands:
        mask = src.unknown & (dist > lo) & (dist <= hi)
        n = int(mask.sum())
        rows.append(
            [
                name,
                str(n),
                f"{m.variance[mask].mean():.3f}",
                f"{(lab[mask] == UNKNOWN).mean():.3f}",
                f"{(lab[mask] == FREE).mean():.3f}",
                f"{(lab[mask] == OCCUPIED).mean():.3f}",
                f"{m.probability[mask].mean():.3f}",
            ]
        )
    _table(
        "(a) unknown pixels by distance to the nearest known pixel (prior variance = 1)",
        ["distance", "n", "mean var", "unknown", "free", "occupied", "mean p"],
        rows,
    )
    tm = rep["timings"]
    _table(
        "(c) time, 384 x 384 map at 0.05 m (seconds)",
        ["stage", "s"],
        [
            ["read + observations", f"{tm['read'] + tm['observations']:.2f}"],
            ["cells", f"{tm['fit_stages'].get('cells', 0.0):.2f}"],
            ["fit (hyperparameters, factorisation, squash)", f"{tm['fit'] - tm['fit_stages'].get('cells', 0.0):.2f}"],
            ["predict 147,456 pixels", f"{tm['prediction']:.2f}"],
            ["agreement", f"{tm['agreement']:.2f}"],
            ["total", f"{total:.2f}"],
        ],
    )
    return {"total": total}


def read_arena(path: Path) -> NDArray[np.bool_]:
    """True occupancy of the arena plan, ndarray of bool, shape (460, 406), row 0 = lowest y."""
    top_down, _ = read_map_image(path)
    return np.flipud(top_down < 128).copy()


#: How a coarse pixel is made from the fine pixels it holds, as occupancy grids are made: occupied
#: if any is, if most are, or the occupied share as its probability.
POOLING = {
    "any": lambda block: block.any(axis=(1, 3)).astype(float),
    "majority": lambda block: (block.mean(axis=(1, 3)) > 0.5).astype(float),
    "mean": lambda block: block.mean(axis=(1, 3)),
}


def bench_arena(path: Path, coarse_resolutions: list[float], poolings: list[str]) -> None:
    """Part (b): down-sample the true plan, convert back to 0.01 m, compare with interpolation."""
    truth = read_arena(path)
    ny, nx = truth.shape
    rows = []
    for coarse_res, pooling in ((c, p) for c in coarse_resolutions for p in poolings):
        k = round(coarse_res / ARENA_RESOLUTION)
        if not np.isclose(k * ARENA_RESOLUTION, coarse_res):
            raise SystemExit(f"coarse resolution {coarse_res} is not a whole number of 0.01 m pixels")
        cy, cx = -(-ny // k), -(-nx // k)
        fine = np.zeros((cy * k, cx * k), dtype=bool)  # padding is free
        fine[:ny, :nx] = truth
        coarse = POOLING[pooling](fine.reshape(cy, k, cx, k))
        cmap = OccupancyMap(GridSpec(ARENA_ORIGIN, coarse_res, coarse.shape), coarse)
        t = time.perf_counter()
        res = convert_grid(cmap, resolution=ARENA_RESOLUTION)
        t_gp = time.perf_counter() - t
        assert res.map.grid.origin == ARENA_ORIGIN and res.map.grid.shape == fine.shape
        p_gp = res.map.probability[:ny, :nx]
        scores = {}
        times = {}
        for order, name in ((0, "nearest (zoom order 0)"), (1, "bilinear (zoom order 1)")):
            t = time.perf_counter()
            up = ndimage.zoom(coarse.astype(float), k, order=order, grid_mode=True, mode="nearest")
            times[name] = time.perf_counter() - t
            scores[name] = up[:ny, :nx]
        scores["GP (convert_grid)"] = p_gp
        times["GP (convert_grid)"] = t_gp
        for name, s in scores.items():
            pred = s > 0.5
            report = res.report if name.startswith("GP") else None
            rows.append(_arena_row(f"{coarse_res:g} m, {pooling}", name, truth, s, pred, times[name], report))
        pred = res.map.ternary[:ny, :nx] == OCCUPIED
        rows.append(_arena_row(f"{coarse_res:g} m, {pooling}", "GP, occupied = p > 0.66", truth, p_gp, pred, t_gp, None))
    _table(
        f"(b) Stage arena plan {nx} x {ny} px (square 0.01 m pixels assumed), coarse -> 0.01 m; "
        "occupied = score > 0.5 unless stated",
        ["coarse, pooling", "method", "AUC", "accuracy", "IoU occ", "occ frac", "s", "GP cells / l"],
        rows,
    )
    print(f"true occupied fraction: {truth.mean():.4f}")


def _arena_row(coarse, name, truth, score, pred, seconds, report) -> list[str]:
    inter = int((pred & truth).sum())
    union = int((pred | truth).sum())
    extra = "-"
    if report is not None:
        extra = f"{report['cells']['n']} / {report['hyperparameters']['length_scale']:.3f} m"
    return [
        coarse,
        name,
        f"{roc_auc(truth.ravel(), score.ravel()):.4f}",
        f"{(pred == truth).mean():.4f}",
        f"{inter / union:.4f}",
        f"{pred.mean():.4f}",
        f"{seconds:.2f}",
        extra,
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--turtlebot", type=Path, default=DATA / "turtlebot3-world-map" / "map.yaml", help="ROS map YAML")
    ap.add_argument("--arena", type=Path, default=DATA / "stage-arena" / "mrl_arena.pgm", help="arena plan PGM")
    ap.add_argument("--coarse", type=float, nargs="+", default=[0.05], help="coarse resolutions for (b), metres")
    ap.add_argument("--pooling", nargs="+", choices=list(POOLING), default=list(POOLING), help="how (b)'s coarse grids are made")
    ap.add_argument("--skip-turtlebot", action="store_true")
    ap.add_argument("--skip-arena", action="store_true")
    args = ap.parse_args(argv)
    if not args.skip_turtlebot:
        bench_turtlebot(args.turtlebot)
    if not args.skip_arena:
        bench_arena(args.arena, args.coarse, args.pooling)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
