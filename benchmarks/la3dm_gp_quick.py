"""Quick check of the 3-D GP map against the 3-D grid baseline on a la3dm world.

Every 4th scan held out; test points are the held-out hits (occupied) and free points every 0.1 m
along each held-out ray up to 0.1 m short of its hit, classes balanced (seeded). Scored: the GP
map's exact-point probability, the voxel map it writes (lookup at 0.1 m), and the project's
occupancy grids on the same scans (OctoMap's log-odds model, and counting) at 0.1 m.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/la3dm_gp_quick.py [--world sim_structured] [--cell 1.0] [--kernel se]
        [--clearance 0.3] [--box node] [--tile-size M]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from gpomap.baselines.ogm import OccupancyGridMapper
from gpomap.cells import build_cells
from gpomap.heldout import calibration_points
from gpomap.io import read_clouds
from gpomap.mapping import AreaGPOM
from gpomap.metrics import roc_auc
from gpomap.tiles import TiledGPOM


def log_loss(occ: np.ndarray, p: np.ndarray) -> float:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return float(-np.mean(np.where(occ, np.log(p), np.log1p(-p))))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--world", default="sim_structured")
    ap.add_argument("--cell", type=float, default=1.0, help="min_cell = max_cell of the cell tree")
    ap.add_argument("--kernel", default="se")
    ap.add_argument("--resolution", type=float, default=0.1)
    ap.add_argument("--clearance", type=float, default=0.3, help="free_clearance of the GP's observations")
    ap.add_argument("--box", default="node", choices=["node", "tight"], help="cell_box of the cell tree")
    ap.add_argument("--tile-size", type=float, default=None, help="map in x, y tiles of local GPs (TiledGPOM, one worker)")
    args = ap.parse_args()
    clouds = read_clouds(f"../shared/data/la3dm-sim/{args.world}", max_range=8.0)
    train = [c for i, c in enumerate(clouds) if i % 4 != 3]
    test = [c for i, c in enumerate(clouds) if i % 4 == 3]
    pts, occ = zip(*(calibration_points(c, 0.1, 10.0) for c in test), strict=True)
    P, O = np.concatenate(pts), np.concatenate(occ)
    rng = np.random.default_rng(0)
    i_occ, i_free = np.flatnonzero(O), np.flatnonzero(~O)
    n = min(i_occ.size, i_free.size)
    keep = np.concatenate([rng.choice(i_occ, n, replace=False), rng.choice(i_free, n, replace=False)])
    P, O = P[keep], O[keep]
    print(f"{args.world}: {len(train)} training scans, {len(test)} held out, {O.size} balanced test points")

    rows = []
    for name, model in [
        ("grid log-odds", OccupancyGridMapper(args.resolution, sensor_model="logodds")),
        ("grid counting", OccupancyGridMapper(args.resolution, sensor_model="counting", update="scan")),
    ]:
        t = time.process_time()
        model.fit(train)
        p = model.predict_proba(P)
        rows.append((f"{name} {args.resolution} m", roc_auc(O, p), log_loss(O, p), time.process_time() - t))

    settings = {
        "kernel": args.kernel,
        "min_cell": args.cell,
        "max_cell": args.cell,
        "free_clearance": args.clearance,
        "cell_box": args.box,
    }
    gp: Any = AreaGPOM(**settings) if args.tile_size is None else TiledGPOM(tile_size=args.tile_size, n_workers=1, **settings)
    obs = AreaGPOM(**settings).make_observations(train)
    default_cells = build_cells(obs.points, obs.occupied, 0.5, 0.5)
    print(f"observations: {obs.n_free} free, {obs.n_occupied} hits; cells at the 2-D default 0.5 m: {len(default_cells)}")
    t = time.process_time()
    gp.fit(train)
    fit_cpu = time.process_time() - t
    print(
        f"GP: {gp.n_inputs_} cells of {args.cell} m, {gp.hyperparameters_}, evidence {gp.evidence_.summary() if gp.evidence_ else None}"
    )
    print("GP stage timings (wall s):", {k: round(v, 2) for k, v in gp.timings_.items()})
    t = time.process_time()
    p = gp.predict_proba(P)
    pg = gp.predict_proba_gp(P)
    pred_cpu = time.process_time() - t
    rows.append((f"GP {args.kernel} exact points", roc_auc(O, p), log_loss(O, p), fit_cpu + pred_cpu))
    rows.append((f"GP {args.kernel} alone (no ray evidence)", roc_auc(O, pg), log_loss(O, pg), fit_cpu + pred_cpu))
    t = time.process_time()
    vm = gp.grid(args.resolution)
    pv = vm.lookup(P)
    grid_cpu = time.process_time() - t
    rows.append((f"GP voxel map {args.resolution} m {vm.probability.shape}", roc_auc(O, pv), log_loss(O, pv), fit_cpu + grid_cpu))
    print(f"{'method':45s} {'AUC':>7s} {'log loss':>9s} {'CPU s':>7s}")
    for name, auc, ll, cpu in rows:
        print(f"{name:45s} {auc:7.4f} {ll:9.4f} {cpu:7.1f}")


if __name__ == "__main__":
    main()
