"""Whole logs as ``gpomap map`` makes them, against the project's occupancy grids on the same log.

Two tables, each case in fresh processes (so each peak RSS and CPU figure is its own):

- **process**: the command itself, ``gpomap map LOG -o OUT -q`` with its defaults, timed as a
  whole process (imports, reading, numba's compilation or its cache, fitting, the written files),
  against a process that reads the same scans the same way, builds the numpy counting grid at the
  map's 0.05 m (:class:`gpomap.baselines.ogm.OccupancyGridMapper`, ``sensor_model="counting"``)
  and writes the same four files. ``gpomap map`` runs first with an empty numba cache
  (``NUMBA_CACHE_DIR`` a new directory: the first run after an install), then ``--repeat`` times
  with that cache filled, alternating with the grid's runs; the ratio is the median of the warm
  runs' CPU over the median of the grid's, from the same sitting, with the spread (min-max) beside.
  CPU seconds are the process's user + system time, every thread included; the stage timings are
  the wall seconds ``gpomap map`` records in ``map.npz``. gpomap's modules are compiled to bytecode
  first, as an install leaves them (:mod:`module_bytecode`).
- **fit**: MSK-GPOM with the defaults of ``gpomap map LOG -o OUT --resolution 0.05 --workers W``
  (the model the command builds from those options, fitted and sampled at 0.05 m) against OctoMap's
  log-odds grid at 0.05 m: each process reads the log, fits and builds the map it would write; the
  ratio is the GP's fit + map CPU over the grid's.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/whole_logs.py                  # every shared 2-D log, both tables
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/whole_logs.py --tables process --logs belgioioso,stage-arena
    .venv/bin/python benchmarks/whole_logs.py --tables fit --logs fr079 --workers 1
    .venv/bin/python benchmarks/whole_logs.py --logs none --log-file robot.log.gz   # your own logs
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from module_bytecode import write_bytecode

# The shared data sits beside the project: ../shared/data from the repository's root.
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LOGS = {
    "intel": DATA / "intel" / "intel-corrected.log.gz",
    "fr079": DATA / "fr079" / "freiburg-079-corrected.log.gz",
    "csail": DATA / "csail-robotlaser1" / "csail.log.gz",
    "belgioioso": DATA / "belgioioso" / "belgioioso-corrected.log.gz",
    "stage-arena": DATA / "stage-arena" / "robot1.bag",
    "cave": DATA / "sim-worlds" / "cave" / "cave.log.gz",
    "hospital_section": DATA / "sim-worlds" / "hospital_section" / "hospital_section.log.gz",
}
METHODS = ("ogm-logodds", "gpomap")
RESOLUTION = 0.05
TABLES = ("process", "fit")


def _clock() -> tuple[float, float]:
    """Wall and CPU seconds of this process (every thread)."""
    return time.perf_counter(), time.process_time()


def child(log: str, method: str, workers: int) -> dict[str, Any]:
    """One method on one whole log in this process; the results as a flat dict."""
    from gpomap import cli
    from gpomap.baselines.ogm import OccupancyGridMapper
    from gpomap.cli import map as map_command
    from gpomap.cli.options import resolve_library_defaults
    from gpomap.io import read_scans

    w0, c0 = _clock()
    scans = read_scans(log)
    w1, c1 = _clock()
    if method == "gpomap":
        argv = ["map", log, "-o", "unused", "--resolution", str(RESOLUTION), "--workers", str(workers)]
        args = cli.build_parser().parse_args(argv)
        resolve_library_defaults(args)
        model: Any = map_command.model(args)
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


def grid_child(log: str, out: str) -> dict[str, Any]:
    """The counting grid as a process: the scans read as ``gpomap map`` reads them, fitted, the four files written."""
    c0 = time.process_time()
    from gpomap import cli
    from gpomap.baselines.ogm import OccupancyGridMapper
    from gpomap.cli.common import load_scans
    from gpomap.cli.options import resolve_library_defaults
    from gpomap.io.export import write_map_outputs

    c1 = time.process_time()
    args = cli.build_parser().parse_args(["map", log, "-o", out, "-q"])
    resolve_library_defaults(args)
    scans = load_scans(args)
    c2 = time.process_time()
    occupancy_map = OccupancyGridMapper(resolution=RESOLUTION, sensor_model="counting").fit(scans).grid_map()
    c3 = time.process_time()
    write_map_outputs(occupancy_map, out, title=f"counting grid: {Path(log).name}")
    c4 = time.process_time()
    return {"scans": len(scans), "import": c1 - c0, "read": c2 - c1, "fit": c3 - c2, "write": c4 - c3}


def map_child(log: str, out: str) -> dict[str, Any]:
    """``gpomap map LOG -o OUT -q`` run through :func:`gpomap.cli.main` in this process, its CPU split by phase.

    The command's own steps are timed where they are called (reading the scans, fitting, writing
    the map), everything else (interpreter start excluded) is "other": argument parsing, the
    imports the command makes along the way, the summary.
    """
    c0 = time.process_time()
    from gpomap import cli

    c1 = time.process_time()
    phases = {"import gpomap.cli": c1 - c0, "read": 0.0, "fit": 0.0, "write": 0.0}

    def timed(name: str, f: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t = time.process_time()
            try:
                return f(*args, **kwargs)
            finally:
                phases[name] += time.process_time() - t

        return wrapper

    from gpomap.cli import map as map_command

    map_command.load_scans = timed("read", map_command.load_scans)
    map_command.fitted_model = timed("fit", map_command.fitted_model)
    map_command.write_map = timed("write", map_command.write_map)
    code = cli.main(["map", log, "-o", out, "-q"])
    if code != 0:
        raise SystemExit(f"gpomap map {log} exited with {code}")
    phases["other"] = time.process_time() - c1 - phases["read"] - phases["fit"] - phases["write"]
    return phases


def _gpomap_command() -> list[str]:
    """``gpomap`` as a user runs it: the console script beside this Python, or the same entry point."""
    script = Path(sys.executable).with_name("gpomap")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from gpomap.cli import console; sys.exit(console())"]


def _timed_process(cmd: list[str], env: dict[str, str], logs: Path) -> dict[str, Any]:
    """Run `cmd` to the end; its CPU (user + system, every thread), wall and peak RSS, and its stdout."""
    with open(logs / "stdout", "w+") as out, open(logs / "stderr", "w+") as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{stderr}")
    return {"cpu": usage.ru_utime + usage.ru_stime, "wall": wall, "peak_mb": usage.ru_maxrss / 1024.0, "stdout": stdout}


def _map_info(outdir: Path) -> dict[str, Any]:
    """The stage timings and cell size ``gpomap map`` recorded in its ``map.npz``."""
    import numpy as np

    with np.load(outdir / "map.npz") as z:
        info = json.loads(str(z["info"]))
        resolution = float(z["resolution"])
    return {"timings": info.get("timings", {}), "resolution": resolution}


def process_runs(name: str, path: Path, repeat: int, scratch: Path) -> dict[str, Any]:
    """``gpomap map`` (a cold numba cache, then `repeat` warm runs) and the counting grid (`repeat` runs), alternated."""
    cache = scratch / "numba-cache"
    shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    out = scratch / "out"
    gpomap_cmd = [*_gpomap_command(), "map", str(path), "-o", str(out), "-q"]
    grid_cmd = [sys.executable, __file__, "--grid-child", str(path), str(out)]

    def gpomap_run() -> dict[str, Any]:
        shutil.rmtree(out, ignore_errors=True)
        r = _timed_process(gpomap_cmd, env, scratch)
        r.update(_map_info(out))
        return r

    def grid_run() -> dict[str, Any]:
        shutil.rmtree(out, ignore_errors=True)
        r = _timed_process(grid_cmd, env, scratch)
        r.update(json.loads(r.pop("stdout").strip().splitlines()[-1]))
        return r

    runs: dict[str, Any] = {"name": name, "cold": gpomap_run(), "warm": [], "grid": []}
    for _ in range(repeat):
        runs["grid"].append(grid_run())
        runs["warm"].append(gpomap_run())
    # One more warm run through gpomap.cli.main, its CPU split by phase.
    shutil.rmtree(out, ignore_errors=True)
    split = _timed_process([sys.executable, __file__, "--map-child", str(path), str(out)], env, scratch)
    runs["phases"] = json.loads(split.pop("stdout").strip().splitlines()[-1])
    runs["phases_total"] = split["cpu"]
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(cache, ignore_errors=True)
    for r in [runs["cold"], *runs["warm"]]:
        r.pop("stdout", None)
    runs["scans"] = runs["grid"][0]["scans"]
    return runs


def _spread(values: list[float]) -> str:
    """``median (min-max)`` of a few timings, or the one value."""
    med = statistics.median(values)
    return f"{med:.1f}" if len(values) == 1 else f"{med:.1f} ({min(values):.1f}-{max(values):.1f})"


def print_process_table(results: list[dict[str, Any]]) -> None:
    """The process table and, per log, the warm run's stages."""
    print()
    print(
        "| log | scans | counting grid CPU s | gpomap map first run CPU s (of it compiling, wall s) | / grid | gpomap map later runs CPU s "
        "| / grid (min-max) | peak MB gpomap / grid |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        grid = [g["cpu"] for g in r["grid"]]
        warm = [w["cpu"] for w in r["warm"]]
        g_med = statistics.median(grid)
        cold = r["cold"]
        compiling = cold["timings"].get("compiling (first run)", 0.0)
        # The warm runs' ratio to the grid, each warm run against the grid run beside it.
        pair = [w / g for w, g in zip(warm, grid, strict=True)]
        print(
            f"| {r['name']} | {r['scans']} | {_spread(grid)} | {cold['cpu']:.1f} ({compiling:.1f}) | {cold['cpu'] / g_med:.1f}x "
            f"| {_spread(warm)} | {statistics.median(warm) / g_med:.1f}x ({min(pair):.1f}-{max(pair):.1f}) "
            f"| {statistics.median(w['peak_mb'] for w in r['warm']):.0f} / {statistics.median(g['peak_mb'] for g in r['grid']):.0f} |"
        )
    print()
    for r in results:
        g = r["grid"][0]
        grid_parts = ", ".join(f"{k} {g[k]:.2f}" for k in ("import", "read", "fit", "write"))
        fastest = min(r["warm"], key=lambda w: w["cpu"])
        stages = ", ".join(f"{k} {v:.2f}" for k, v in fastest["timings"].items())
        cold = ", ".join(f"{k} {v:.2f}" for k, v in r["cold"]["timings"].items())
        print(f"{r['name']}: counting grid CPU s: {grid_parts}")
        if "phases" in r:
            phases = ", ".join(f"{k} {v:.2f}" for k, v in r["phases"].items())
            print(
                f"{r['name']}: gpomap map's CPU s by phase (a further warm run, {r['phases_total']:.1f} CPU s in all): {phases}"
            )
        print(
            f"{r['name']}: gpomap map, fastest later run ({fastest['cpu']:.1f} CPU s, {fastest['wall']:.1f} wall s), wall s per stage: {stages}"
        )
        print(
            f"{r['name']}: gpomap map, first run ({r['cold']['cpu']:.1f} CPU s, {r['cold']['wall']:.1f} wall s), wall s per stage: {cold}"
        )


def fit_runs(name: str, path: Path, workers: int) -> list[dict[str, Any]]:
    """The fit table's two processes on one log: the log-odds grid and MSK-GPOM, fit + map timed inside."""
    results = []
    for method in METHODS:
        cmd = [sys.executable, __file__, "--child", str(path), method, "--workers", str(workers)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"{name} {method} failed:\n{out.stderr}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r["name"] = name
        results.append(r)
        print(f"done {name} {method}: fit + map {r['fit'][1] + r['map'][1]:.1f} CPU s", file=sys.stderr, flush=True)
    return results


def print_fit_table(results: list[dict[str, Any]]) -> None:
    """The fit table and, per log, MSK-GPOM's stages."""
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
    parser.add_argument("--tables", default=",".join(TABLES), help="comma-separated: " + ", ".join(TABLES) + " (default: both)")
    parser.add_argument(
        "--repeat", type=int, default=3, help="process table: warm gpomap map runs and grid runs per log (default: 3)"
    )
    parser.add_argument("--workers", type=int, default=2, help="fit table: gpomap map --workers (default: 2)")
    parser.add_argument("--child", nargs=2, metavar=("LOG", "METHOD"), help=argparse.SUPPRESS)
    parser.add_argument("--grid-child", nargs=2, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--map-child", nargs=2, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1], args.workers)))
        return
    if args.grid_child:
        print(json.dumps(grid_child(*args.grid_child)))
        return
    if args.map_child:
        print(json.dumps(map_child(*args.map_child)))
        return
    tables = args.tables.split(",")
    if not tables or any(t not in TABLES for t in tables):
        raise SystemExit(f"--tables takes some of {', '.join(TABLES)}, got {args.tables!r}")
    if args.repeat < 1:
        raise SystemExit(f"--repeat must be at least 1, got {args.repeat}")
    names = [] if args.logs == "none" else args.logs.split(",")
    unknown = [n for n in names if n not in LOGS]
    if unknown:
        raise SystemExit(f"unknown log(s) {', '.join(unknown)}: --logs takes {', '.join(LOGS)} or none")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    write_bytecode()
    threads = os.environ.get("OMP_NUM_THREADS", "unset")
    print(f"# Whole logs (commit {commit}, {os.cpu_count()} CPUs, OMP_NUM_THREADS {threads})")
    chosen = [(n, LOGS[n]) for n in names] + [(p.name, p) for p in args.log_file]
    process: list[dict[str, Any]] = []
    fit: list[dict[str, Any]] = []
    for name, path in chosen:
        if not path.exists():
            print(f"skipping {name}: {path} not found", flush=True)
            continue
        if "process" in tables:
            with tempfile.TemporaryDirectory(prefix="gpomap-whole-logs-") as scratch:
                process.append(process_runs(name, path, args.repeat, Path(scratch)))
            r = process[-1]
            print(
                f"done {name} processes: grid {_spread([g['cpu'] for g in r['grid']])}, gpomap map first "
                f"{r['cold']['cpu']:.1f}, later {_spread([w['cpu'] for w in r['warm']])} CPU s",
                file=sys.stderr,
                flush=True,
            )
        if "fit" in tables:
            fit += fit_runs(name, path, args.workers)
    if process:
        print(
            f"\n## gpomap map LOG -o OUT (defaults) against the counting grid at {RESOLUTION} m, whole processes, {args.repeat} runs each"
        )
        print_process_table(process)
    if fit:
        print(
            f"\n## Fit + map inside one process (gpomap map --resolution {RESOLUTION} --workers {args.workers}) against the log-odds grid"
        )
        print_fit_table(fit)
    if args.json:
        args.json.write_text(json.dumps({"process": process, "fit": fit}, indent=1))


if __name__ == "__main__":
    main()
