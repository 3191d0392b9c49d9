"""Benchmark converting a whole OctoMap tree (gpomap.convert.octree): time and peak memory by region size.

Each region, the tree's first WIDTH metres along x (all of y and z), or the whole tree, is
converted in a fresh process (so each peak resident memory is its own), tiled as
:class:`gpomap.convert.TiledOctreeModel` tiles it. Printed per region: known voxels, cells,
tiles (side, most cells in one, fitted), the agreement with the tree's known voxels, wall and CPU
seconds, the peak resident memory, and what of it the output holds (probability and variance,
8 bytes each per voxel). With ``--write`` the process also writes the output set of
``gpomap convert`` (NPZ, OctoMap, PLY mesh, figures), whose writers take memory of their own.

Run from the project root:
``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/convert_octree.py --resolution 0.08 --widths 10 20``
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def child(tree_path: Path, resolution: float, width: float | None, workers: int, write: bool) -> dict:
    """Convert one region in this process and measure it."""
    import numpy as np

    from gpomap.convert import convert_octree
    from gpomap.io.octomap import read_octree

    t0, c0 = time.perf_counter(), time.process_time()
    tree = read_octree(tree_path)
    lo = tree.extent()[0]
    upper = None if width is None else [float(lo[0]) + width, np.nan, np.nan]
    res = convert_octree(tree, resolution, upper=upper, n_workers=workers)
    written = 0
    if write:
        from gpomap.io.voxel_outputs import write_voxel_outputs

        with tempfile.TemporaryDirectory() as out:
            files = write_voxel_outputs(res.map, Path(out) / "o")
            written = sum(f.stat().st_size for f in files)
    r = res.report
    return {
        "width_m": width,
        "region": r["region"],
        "known_voxels": r["voxels"]["free"] + r["voxels"]["occupied"],
        "cells": r["cells"]["n"],
        "tiles": r.get("tiles"),
        "hyperparameters": r["hyperparameters"],
        "agreement": r["agreement"],
        "voxels": int(res.map.spec.n_voxels),
        "output_mb": 16 * res.map.spec.n_voxels / 2**20,
        "written_mb": written / 2**20,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", type=Path, default=DATA / "octomap" / "geb079.bt", help="OctoMap .bt / .ot file")
    ap.add_argument("--resolution", type=float, default=0.08, help="output voxel side, metres")
    ap.add_argument("--widths", type=float, nargs="*", default=[10.0, 20.0], help="regions: the first WIDTH m along x")
    ap.add_argument("--no-whole", action="store_true", help="skip the whole tree")
    ap.add_argument("--workers", type=int, default=1, help="tiles in flight")
    ap.add_argument("--write", action="store_true", help="also write the output set (its writers' memory counts)")
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    ap.add_argument("--child", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        width = None if args.child <= 0 else args.child
        print(json.dumps(child(args.tree, args.resolution, width, args.workers, args.write)))
        return 0
    rows = []
    for width in [*args.widths, *([] if args.no_whole else [0.0])]:
        cmd = [sys.executable, __file__, "--child", str(width), "--tree", str(args.tree)]
        cmd += ["--resolution", str(args.resolution), "--workers", str(args.workers)] + (["--write"] if args.write else [])
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        r = rows[-1]
        t = r["tiles"] or {}
        ag = r["agreement"]
        label = "whole tree" if r["width_m"] is None else f"first {r['width_m']:g} m"
        print(
            f"{label}: "
            f"{r['known_voxels']} known voxels, {r['cells']} cells, "
            f"tiles {t.get('tile_size', '-')} m ({t.get('tiles_fitted', '-')} fitted, at most {t.get('largest_tile_cells', '-')} cells); "
            f"{r['voxels']} output voxels ({r['output_mb']:.0f} MB); agreement {100 * ag.get('ternary', float('nan')):.2f} %, "
            f"AUC {ag.get('auc', float('nan')):.4f}; {r['wall_s']:.0f} s wall, {r['cpu_s']:.0f} s CPU; "
            f"peak {r['peak_rss_mb']:.0f} MB" + (f"; wrote {r['written_mb']:.0f} MB" if args.write else ""),
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
