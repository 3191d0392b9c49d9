"""The fitted map as a file: its size, the time to save and load it, and a grid read from it against the fit.

For each log, the map ``gpomap map LOG`` fits (its defaults; ``--workers`` local workers, 1 by
default) is fitted, saved to ``map.gpom`` and loaded back; then the loaded map's grid is taken at
``--resolution`` (over the whole map, as ``gpomap render MAP.gpom --resolution R`` does) and its
files written. Prints the fit's seconds, the file's size (and what takes it: the tiles' factors,
the scans, the rest), save and load seconds, the grid's cells and seconds, the seconds a loaded
map takes to make its labelled points from its scans when first read (as ``gpomap update`` reads
them; a render or query never does), each the least of ``--repeat`` runs (the machine may be
shared), and checks that the loaded map predicts as the live one to the bit.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mapfile.py --log stage-arena --resolution 0.01
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mapfile.py --log intel --resolution 0.05
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mapfile.py --log fr079 --resolution 0.05
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np

from gpomap.cli import build_parser
from gpomap.cli.map import model as _model
from gpomap.cli.options import resolve_library_defaults as _resolve_library_defaults
from gpomap.io.export import write_map_files
from gpomap.io.mapfile import load_fitted_map, save_fitted_map
from gpomap.progress import set_progress_mode

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
LOGS = {
    "stage-arena": (DATA / "stage-arena" / "robot1.bag", ["--topic", "/base_scan", "--time-offset", "0.1"]),
    "intel": (DATA / "intel" / "intel-corrected.log.gz", []),
    "belgioioso": (DATA / "belgioioso" / "belgioioso-corrected.log.gz", []),
    "fr079": (DATA / "fr079" / "freiburg-079-corrected.log.gz", []),
}


def _timed(fn, repeat: int = 1):
    """`fn()`'s result, and the least wall and CPU seconds of `repeat` calls (this machine is shared)."""
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        best = (min(best[0], time.perf_counter() - t), min(best[1], time.process_time() - c))
    return out, best[0], best[1]


def _sizes(path: Path) -> dict[str, int]:
    """Bytes in the archive by what they hold."""
    out = {"tile factors (L)": 0, "scans": 0, "other": 0}
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.filename.endswith("/L.npy"):
                out["tile factors (L)"] += info.compress_size
            elif "/_scans/" in info.filename:
                out["scans"] += info.compress_size
            else:
                out["other"] += info.compress_size
    return out


def run(name: str, resolution: float, workers: int, repeat: int, directory: Path) -> None:
    from gpomap.cli.common import load_scans as _load_scans

    log, options = LOGS[name]
    args = build_parser().parse_args(["map", str(log), *options, "-o", str(directory / "out"), "--workers", str(workers)])
    _resolve_library_defaults(args)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scans = _load_scans(args)
    model = _model(args)
    _, fit_wall, fit_cpu = _timed(lambda: model.fit(scans))
    path = directory / "map.gpom"
    _, save_wall, save_cpu = _timed(lambda: save_fitted_map(model, path), repeat)
    size = path.stat().st_size
    lo, hi = model.bounds_
    points = np.random.default_rng(0).uniform(lo - 1.0, hi + 1.0, size=(100_000, 2))
    p1, v1 = model.predict_proba(points, return_var=True)
    out = directory / "render"
    out.mkdir(exist_ok=True)
    # Each run on a map loaded afresh: a map's second grid or query reuses what its first formed.
    runs = []
    for _ in range(repeat):
        loaded, load_wall, load_cpu = _timed(lambda: load_fitted_map(path))
        (p2, v2), query_wall, query_cpu = _timed(lambda m=loaded: m.predict_proba(points, return_var=True))
        fresh = load_fitted_map(path)
        grid, grid_wall, grid_cpu = _timed(lambda m=fresh: m.grid(resolution))
        _, write_wall, write_cpu = _timed(lambda g=grid: write_map_files(g, out))
        shape = grid.grid.shape
        del fresh, grid
        _, points_wall, points_cpu = _timed(lambda m=loaded: m.training_points())
        runs.append(
            (load_wall, load_cpu, query_wall, query_cpu, grid_wall, grid_cpu, write_wall, write_cpu, points_wall, points_cpu)
        )
        del loaded
    load_wall, load_cpu, query_wall, query_cpu, grid_wall, grid_cpu, write_wall, write_cpu, points_wall, points_cpu = np.min(
        runs, axis=0
    )
    same = bool(np.array_equal(p1, p2) and np.array_equal(v1, v2))
    ny, nx = shape
    parts = ", ".join(f"{k} {v / 1e6:.2f}" for k, v in _sizes(path).items())
    print(f"{name}: {len(scans)} scans, {len(model.tiles_)} tiles, {model.n_inputs_} cells, {workers} worker(s)")
    print(f"  fit                  {fit_wall:.2f} s wall, {fit_cpu:.2f} s CPU")
    print(f"  map.gpom             {size / 1e6:.2f} MB ({parts} MB)")
    print(f"  save                 {save_wall:.2f} s wall, {save_cpu:.2f} s CPU")
    print(f"  load                 {load_wall:.2f} s wall, {load_cpu:.2f} s CPU")
    print(f"  query 100,000 points {query_wall:.2f} s wall, {query_cpu:.2f} s CPU; the live map's answers to the bit: {same}")
    print(
        f"  grid at {resolution:g} m        {nx} x {ny} cells ({nx * ny / 1e6:.2f} M) in {grid_wall:.2f} s wall, "
        f"{grid_cpu:.2f} s CPU; its files written in {write_wall:.2f} s wall, {write_cpu:.2f} s CPU"
    )
    print(f"  points from scans    {points_wall:.2f} s wall, {points_cpu:.2f} s CPU (when first read, as by an update)")
    total = (load_wall + grid_wall + write_wall, load_cpu + grid_cpu + write_cpu)
    print(
        f"  load + grid + files  {total[0]:.2f} s wall, {total[1]:.2f} s CPU; the fit: {fit_wall:.2f} s wall, {fit_cpu:.2f} s CPU"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--log", choices=sorted(LOGS), action="append", help="a shared log (repeatable; default: stage-arena)")
    p.add_argument("--resolution", type=float, default=0.01, help="the grid read from the loaded map, m")
    p.add_argument("--workers", type=int, default=1, help="local workers of the map")
    p.add_argument("--repeat", type=int, default=3, help="timed runs of each step after the fit; the least is printed")
    a = p.parse_args()
    set_progress_mode("quiet")
    for name in a.log or ["stage-arena"]:
        with tempfile.TemporaryDirectory() as d:
            run(name, a.resolution, a.workers, a.repeat, Path(d))


if __name__ == "__main__":
    main()
