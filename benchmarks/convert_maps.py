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
    The other plans (the sim-worlds plans, the TurtleBot3 map's known pixels) are scored the same
    way. The conversion is told how each coarse grid was made (``convert_grid(..., pooling=...,
    pooling_factor=...)``, "GP"); where the pooling it infers by itself (``pooling="auto"``,
    :func:`gpomap.convert.infer_pooling`) differs, that conversion is scored too ("GP, auto", still
    told the factor).
(c) The end-to-end time of converting the 384 x 384 map (read, fit, predict the whole grid).

The summary ends with the line of targets: in how many cases the conversion beats both nearest
and bilinear up-sampling in AUC and in occupied IoU, told the pooling and inferring it.

Run from the project root:  ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/convert_maps.py``
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gpomap.convert import convert_grid, infer_pooling
from gpomap.errors import EmptyDataError
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


@dataclass
class Plan:
    """A fine occupancy grid taken as the truth: pooled to a coarse grid, converted back, scored.

    Attributes
    ----------
    name : str
    occupied : ndarray of bool, shape (ny, nx)
        Row 0 = lowest y.
    known : ndarray of bool, shape (ny, nx)
        Pixels with a label (unknown ones are pooled as unknown and not scored).
    origin : (float, float)
        Lower-left corner, metres.
    resolution : float
        Fine pixel side, metres.
    factor : int
        Fine pixels per coarse pixel side, by default.
    """

    name: str
    occupied: NDArray[np.bool_]
    known: NDArray[np.bool_]
    origin: tuple[float, float]
    resolution: float
    factor: int


def load_plans(data: Path, names: list[str]) -> list[Plan]:
    """The fine grids scored: the Stage arena plan, the sim-worlds plans, the TurtleBot3 ROS map."""
    plans = []
    for name in names:
        if name == "arena":
            occ = read_arena(data / "stage-arena" / "mrl_arena.pgm")
            plans.append(Plan(name, occ, np.ones_like(occ), ARENA_ORIGIN, ARENA_RESOLUTION, 5))
        elif name in SIM_WORLDS:
            world = data / "sim-worlds" / name
            meta = json.loads((world / f"{name}.json").read_text())
            top_down, _ = read_map_image(world / f"{name}.truth.png")
            occ = np.flipud(top_down < 128).copy()
            res, (x0, y0) = float(meta["resolution"]), meta["origin"]
            # A plan wider than WINDOW_PIXELS is scored in windows that far apart (one GP each).
            n = -(-occ.shape[1] // WINDOW_PIXELS)
            cuts = np.linspace(0, occ.shape[1], n + 1).round().astype(int)
            for i, (c0, c1) in enumerate(itertools.pairwise(cuts)):
                part = f"{name} {i + 1}/{n}" if n > 1 else name
                plans.append(Plan(part, occ[:, c0:c1], np.ones((occ.shape[0], c1 - c0), dtype=bool), (x0 + c0 * res, y0), res, 5))
        elif name == "turtlebot":
            ros = read_rosmap(data / "turtlebot3-world-map" / "map.yaml")
            # Cropped to the known pixels and a coarse pixel or two round them.
            rows, cols = np.nonzero(~ros.unknown)
            r0, c0 = max(rows.min() - 4, 0), max(cols.min() - 4, 0)
            r1, c1 = rows.max() + 5, cols.max() + 5
            g = ros.grid
            origin = (g.origin[0] + c0 * g.resolution, g.origin[1] + r0 * g.resolution)
            plans.append(Plan(name, ros.occupied[r0:r1, c0:c1], ~ros.unknown[r0:r1, c0:c1], origin, g.resolution, 2))
        else:
            raise SystemExit(f"unknown plan {name!r}; expected one of {', '.join(PLANS)}")
    return plans


SIM_WORLDS = ("cave", "hospital_section")
#: The converter is one GP over its inputs: the hospital plan (1,086 pixels wide) is scored in
#: three windows of 362 pixels.
WINDOW_PIXELS = 400
PLANS = ("arena", *SIM_WORLDS, "turtlebot")


#: How a coarse pixel is made from the known fine pixels it holds, as occupancy grids are made:
#: occupied if any is, if most are, or the occupied share as its probability (NaN: none known).
POOLING = {
    "any": lambda occ, n: np.where(n > 0, occ > 0, np.nan),
    "majority": lambda occ, n: np.where(n > 0, occ > 0.5 * n, np.nan),
    "mean": lambda occ, n: np.where(n > 0, occ / np.maximum(n, 1), np.nan),
}


def pool(plan: Plan, k: int, pooling: str) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """The coarse grid of `plan`, cropped to whole coarse pixels (a partial one at the edge would
    stand for a sliver of the plan), and the fine truth and known mask cropped the same way."""
    cy, cx = plan.occupied.shape[0] // k, plan.occupied.shape[1] // k
    occ = plan.occupied[: cy * k, : cx * k] & plan.known[: cy * k, : cx * k]
    known = plan.known[: cy * k, : cx * k]
    n_occ = occ.reshape(cy, k, cx, k).sum(axis=(1, 3))
    n_known = known.reshape(cy, k, cx, k).sum(axis=(1, 3))
    with np.errstate(invalid="ignore"):
        coarse = POOLING[pooling](n_occ, n_known).astype(float)
    return coarse, occ, known


def bench_plans(plans: list[Plan], factors: list[int] | None, poolings: list[str], options: dict | None = None) -> list[dict]:
    """Part (b): pool each plan, convert back to its fine pixels, compare with interpolation.

    `options` are :func:`gpomap.convert.convert_grid` model options (a length in source pixels is
    given as ``length_scale_px``; ``pooling`` given there replaces the one the grid was made by)."""
    rows, records = [], []
    for plan in plans:
        for k in factors or [plan.factor]:
            for pooling in poolings:
                coarse, occ, known = pool(plan, k, pooling)
                cmap = OccupancyMap(GridSpec(plan.origin, plan.resolution * k, coarse.shape), coarse)
                opts = dict(options or {})
                if "length_scale_px" in opts:
                    opts["length_scale"] = float(opts.pop("length_scale_px")) * plan.resolution * k
                told = opts.pop("pooling", pooling)
                # The factor is part of how the grid was made (``--option pooling_factor=null``: not told).
                opts.setdefault("pooling_factor", k)
                inferred = infer_pooling(coarse)
                scores, times, results = {}, {}, {}
                # Interpolation reads an unknown coarse pixel as 0.5.
                filled = np.where(np.isfinite(coarse), coarse, 0.5)
                for order, name in ((0, "nearest"), (1, "bilinear")):
                    t = time.perf_counter()
                    scores[name] = ndimage.zoom(filled, k, order=order, grid_mode=True, mode="nearest")
                    times[name] = time.perf_counter() - t
                runs = [("GP", told)] + ([("GP, auto", "auto")] if inferred != told else [])
                for name, read in runs:
                    t = time.perf_counter()
                    try:
                        res = convert_grid(cmap, resolution=plan.resolution, pooling=read, **opts)
                    except EmptyDataError as e:
                        res = None  # scored as a map of p = 0.5 everywhere, and said
                        print(f"  GP refused: {e}", flush=True)
                    times[name] = time.perf_counter() - t
                    if res is not None:
                        assert res.map.grid.shape == occ.shape
                    scores[name] = res.map.probability if res is not None else np.full(occ.shape, 0.5)
                    results[name] = res
                label = f"{plan.name}, {plan.resolution * k:.3g} m, {pooling}"
                for name, score in scores.items():
                    rec = _scores(occ[known], score[known], score[known] > 0.5)
                    rec.update(plan=plan.name, coarse=plan.resolution * k, pooling=pooling, method=name, seconds=times[name])
                    records.append(rec)
                    extra = "-"
                    if name.startswith("GP"):
                        res = results[name]
                        rec["refused"] = res is None
                        rec["read_as"] = res.model.reading_.pooling if res is not None and res.model.reading_ else None
                        rec["inferred"] = inferred
                        if res is not None:
                            hp = res.report["hyperparameters"]
                            extra = f"{res.report['cells']['n']} / {hp['length_scale'] / (plan.resolution * k):.2f} px / {rec['read_as']}"
                        else:
                            extra = "refused"
                    rows.append(_row(label, name, rec, extra))
                res = results["GP"]
                if res is not None:
                    ternary_occ = (res.map.ternary == OCCUPIED)[known]
                    rec = _scores(occ[known], res.map.probability[known], ternary_occ)
                    rows.append(_row(label, "GP, occupied = p > 0.66", rec, "-"))
                gp = next(r for r in records[::-1] if r["method"] == "GP")
                print(f"  {label}: GP {gp['auc']:.4f} / {gp['iou']:.4f} ({times['GP']:.1f} s; inferred {inferred})", flush=True)
    _table(
        "(b) plans pooled to coarse grids and converted back to their fine pixels; occupied = score > 0.5 unless stated",
        ["plan, coarse, pooling", "method", "AUC", "IoU occ", "occ frac", "true frac", "s", "GP inputs / l / read as"],
        rows,
    )
    return records


def _scores(truth: NDArray[np.bool_], score: NDArray[np.float64], pred: NDArray[np.bool_]) -> dict:
    return {
        "auc": float(roc_auc(truth, score)),
        "iou": float((pred & truth).sum() / max((pred | truth).sum(), 1)),
        "occ_frac": float(pred.mean()),
        "true_frac": float(truth.mean()),
    }


def _row(label: str, name: str, rec: dict, extra: str) -> list[str]:
    return [
        label,
        name,
        f"{rec['auc']:.4f}",
        f"{rec['iou']:.4f}",
        f"{rec['occ_frac']:.4f}",
        f"{rec['true_frac']:.4f}",
        f"{rec.get('seconds', 0.0):.2f}",
        extra,
    ]


def summary(records: list[dict]) -> None:
    """Where the GP beats both interpolations, in AUC and in IoU, per plan and pooling, told the
    pooling and inferring it; then the line of targets met."""
    rows = []
    keys = list(dict.fromkeys((r["plan"], r["coarse"], r["pooling"]) for r in records))
    met = {"told": 0, "auto": 0}
    for key in keys:
        by = {r["method"]: r for r in records if (r["plan"], r["coarse"], r["pooling"]) == key}
        best_auc = max(by["nearest"]["auc"], by["bilinear"]["auc"])
        best_iou = max(by["nearest"]["iou"], by["bilinear"]["iou"])
        auto = by.get("GP, auto", by["GP"])  # the inferred pooling was the told one: the same map
        cells = []
        for name, gp in (("told", by["GP"]), ("auto", auto)):
            beats = gp["auc"] > best_auc and gp["iou"] > best_iou
            met[name] += beats
            score = "refused" if gp.get("refused") else f"{gp['auc']:.4f} / {gp['iou']:.4f}"
            cells += [score, "yes" if beats else "no"]
        rows.append(
            [
                f"{key[0]}, {key[1]:.3g} m, {key[2]}",
                f"{by['nearest']['auc']:.4f} / {by['nearest']['iou']:.4f}",
                f"{by['bilinear']['auc']:.4f} / {by['bilinear']['iou']:.4f}",
                *cells[:2],
                str(by["GP"].get("inferred")),
                *cells[2:],
            ]
        )
    _table(
        "summary: AUC / occupied IoU (p > 0.5); GP told how the grid was made, and GP inferring it (auto)",
        ["plan, coarse, pooling", "nearest", "bilinear", "GP told", "beats both", "inferred", "GP auto", "beats both"],
        rows,
    )
    n = len(keys)
    print(
        f"\ntargets met (beats nearest and bilinear in AUC and occupied IoU): told the pooling {met['told']} of {n}, "
        f"inferring it {met['auto']} of {n}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--turtlebot", type=Path, default=DATA / "turtlebot3-world-map" / "map.yaml", help="ROS map YAML")
    ap.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    ap.add_argument("--plans", nargs="+", choices=PLANS, default=list(PLANS), help="fine grids for (b)")
    ap.add_argument(
        "--factor", type=int, nargs="+", help="fine pixels per coarse pixel side for (b) (default: 5, the TurtleBot3 map 2)"
    )
    ap.add_argument("--pooling", nargs="+", choices=list(POOLING), default=list(POOLING), help="how (b)'s coarse grids are made")
    ap.add_argument("--skip-turtlebot", action="store_true", help="skip (a) and (c)")
    ap.add_argument("--skip-plans", action="store_true", help="skip (b)")
    ap.add_argument("--json", type=Path, help="also write (b)'s scores to this JSON file")
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a convert_grid model option for (b), VALUE as JSON (optimise=true, occupied_fraction=1.0, length_scale_px=3, "
        'pooling="auto", pooling_factor=null)',
    )
    args = ap.parse_args(argv)
    options = {}
    for item in args.option:
        name, _, value = item.partition("=")
        options[name] = json.loads(value)
    if not args.skip_turtlebot:
        bench_turtlebot(args.turtlebot)
    if not args.skip_plans:
        records = bench_plans(load_plans(args.data, args.plans), args.factor, args.pooling, options)
        summary(records)
        if args.json:
            args.json.write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
