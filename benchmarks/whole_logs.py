"""Whole logs as ``gpomap map`` makes them, against the project's log-odds grid on the same log.

For each shared log, two fresh processes (so each peak RSS is its own): MSK-GPOM with the
defaults of ``gpomap map LOG -o OUT --resolution 0.05 --workers W`` (the model the command builds
from those options, fitted and sampled at 0.05 m), and OctoMap's log-odds grid at 0.05 m
(:class:`gpomap.baselines.ogm.OccupancyGridMapper`, its defaults). Each process reads the log,
fits, and builds the map it would write; CPU seconds include every thread of the process. The
ratio is the GP's fit + map CPU over the grid's, from the same run. Usage::

    .venv/bin/python benchmarks/whole_logs.py                 # intel, fr079, csail, belgioioso
    .venv/bin/python benchmarks/whole_logs.py --logs fr079 --workers 1
    .venv/bin/python benchmarks/whole_logs.py --logs none --log-file robot.log.gz   # your own logs
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

# The shared data sits beside the project: ../shared/data from the repository's root.
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LOGS = {
    "intel": DATA / "intel" / "intel-corrected.log.gz",
    "fr079": DATA / "fr079" / "freiburg-079-corrected.log.gz",
    "csail": DATA / "csail-robotlaser1" / "csail.log.gz",
    "belgioioso": DATA / "belgioioso" / "belgioioso-corrected.log.gz",
}
METHODS = ("ogm-logodds", "gpomap")
RESOLUTION = 0.05


def _clock() -> tuple[float, float]:
    """Wall and CPU seconds of this process (every thread)."""
    return time.perf_counter(), time.process_time()


def child(log: str, method: str, workers: int) -> dict[str, Any]:
    """One method on one whole log in this process; the results as a flat dict."""
    from gpomap import cli
    from gpomap.baselines.ogm import OccupancyGridMapper
    from gpomap.io import read_scans

    w0, c0 = _clock()
    scans = read_scans(log)
    w1, c1 = _clock()
    if method == "gpomap":
        argv = ["map", log, "-o", "unused", "--resolution", str(RESOLUTION), "--workers", str(workers)]
        args = cli.build_parser().parse_args(argv)
        cli._resolve_library_defaults(args)
        model: Any = cli._model(args)
    else:
        model = OccupancyGridMapper(resolution=RESOLUTION, sensor_model="logodds")
    model.fit(scans)
    w2, c2 = _clock()
    occupancy_map = model.grid(RESOLUTION)
    w3, c3 = _clock()
    stages = {k: float(v) for k, v in getattr(model, "timings_", {}).items() if k != "total_fit"}
    return {
        "log": Path(log).name,
        "method": method,
        "scans": len(scans),
        "read": [w1 - w0, c1 - c0],
        "fit": [w2 - w1, c2 - c1],
        "map": [w3 - w2, c3 - c2],
        "grid_shape": list(occupancy_map.grid.shape),
        "cells": int(getattr(model, "n_inputs_", 0)),
        "stages": stages,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", default=",".join(LOGS), help="comma-separated: " + ", ".join(LOGS) + ", or none")
    parser.add_argument(
        "--log-file",
        type=Path,
        action="append",
        default=[],
        metavar="PATH",
        help="also any log gpomap reads (repeatable), named by its file",
    )
    parser.add_argument("--workers", type=int, default=2, help="gpomap map --workers (default: 2)")
    parser.add_argument("--child", nargs=2, metavar=("LOG", "METHOD"), help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1], args.workers)))
        return
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"# Whole logs (commit {commit}, {os.cpu_count()} CPUs, gpomap map --resolution {RESOLUTION} --workers {args.workers})")
    results = []
    names = [] if args.logs == "none" else args.logs.split(",")
    unknown = [n for n in names if n not in LOGS]
    if unknown:
        raise SystemExit(f"unknown log(s) {', '.join(unknown)}: --logs takes {', '.join(LOGS)} or none")
    chosen = [(n, LOGS[n]) for n in names] + [(p.name, p) for p in args.log_file]
    for name, path in chosen:
        if not path.exists():
            print(f"skipping {name}: {path} not found", flush=True)
            continue
        for method in METHODS:
            cmd = [sys.executable, __file__, "--child", str(path), method, "--workers", str(args.workers)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                raise SystemExit(f"{name} {method} failed:\n{out.stderr}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            r["name"] = name
            results.append(r)
            print(f"done {name} {method}: fit + map {r['fit'][1] + r['map'][1]:.1f} CPU s", file=sys.stderr, flush=True)
    print()
    print(
        "| log | scans | method | read CPU s | fit CPU / wall s | map CPU / wall s | fit + map CPU s | / log-odds grid | peak MB | largest stage |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        grid = next(g for g in results if g["name"] == r["name"] and g["method"] == "ogm-logodds")
        total = r["fit"][1] + r["map"][1]
        ratio = total / (grid["fit"][1] + grid["map"][1])
        largest = max(r["stages"].items(), key=lambda kv: kv[1]) if r["stages"] else None
        print(
            f"| {r['name']} | {r['scans']} | {r['method']} | {r['read'][1]:.1f} | {r['fit'][1]:.1f} / {r['fit'][0]:.1f} "
            f"| {r['map'][1]:.1f} / {r['map'][0]:.1f} | {total:.1f} | {ratio:.2f}x | {r['peak_mb']:.0f} | "
            + (f"{largest[0]} {largest[1]:.1f} s" if largest else "-")
            + " |"
        )
    print()
    for r in results:
        if r["stages"]:
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
            print(f"{r['name']} {r['method']}: {r['cells']} cells, wall s per stage: {stages}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
