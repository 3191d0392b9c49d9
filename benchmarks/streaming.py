"""Streaming rate: a log replayed one scan at a time through StreamingGPOM.

Prints, per log: the warm-up fit, the latency of adding one scan (median / 95th percentile), the
rate at which scans are absorbed (ray counts current, GP as last refreshed), the latency of a
refresh every ``--refresh-every`` scans and the sustained rate with those refreshes, the final
``finish()`` (every tile exact, calibration refitted), the largest difference of the final map
from the batch map of the same scans on a 0.1 m grid (``--compare-batch``), and peak memory.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/streaming.py --log intel --refresh-every 10 --compare-batch
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np

from gpomap.io import read_scans
from gpomap.progress import set_progress_mode
from gpomap.streaming import DEFAULT_WARMUP_SCANS, StreamingGPOM
from gpomap.tiles import TiledGPOM

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
LOGS = {
    "intel": DATA / "intel" / "intel-corrected.log.gz",
    "fr079": DATA / "fr079" / "freiburg-079-corrected.log.gz",
    "csail": DATA / "csail-robotlaser1" / "csail.log.gz",
    "belgioioso": DATA / "belgioioso" / "belgioioso-corrected.log.gz",
}


def _ms(v: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(v) * 1e3, q)) if v else float("nan")


def run(name: str, scans: list, refresh_every: int, max_refits: int | None, compare: bool, options: dict) -> dict:
    stream = StreamingGPOM(warmup_scans=DEFAULT_WARMUP_SCANS, max_refits=max_refits, **options)
    add: list[float] = []
    refresh: list[float] = []
    pending: list[int] = []
    t_start = None
    cpu_start = 0.0
    for i, scan in enumerate(scans):
        t = time.perf_counter()
        stream.add_scan(scan)
        dt = time.perf_counter() - t
        if not stream.ready_:
            continue
        if t_start is None:  # the warm-up fit has just run: the streaming clock starts now
            t_start, cpu_start = time.perf_counter(), time.process_time()
            continue
        add.append(dt)
        if (i + 1) % refresh_every == 0:
            t = time.perf_counter()
            stream.refresh()
            refresh.append(time.perf_counter() - t)
            pending.append(stream.pending_tiles_)
    assert t_start is not None
    wall = time.perf_counter() - t_start
    cpu = time.process_time() - cpu_start
    t = time.perf_counter()
    stream.finish()
    finish = time.perf_counter() - t
    row = {
        "log": name,
        "scans": len(scans),
        "warmup_s": stream.stats()["warmup_seconds"],
        "add_median_ms": _ms(add, 50),
        "add_p95_ms": _ms(add, 95),
        "absorb_rate": len(add) / max(sum(add), 1e-12),
        "refresh_median_s": _ms(refresh, 50) / 1e3,
        "refresh_p95_s": _ms(refresh, 95) / 1e3,
        "sustained_rate": len(add) / wall,
        "cpu_per_scan_ms": 1e3 * cpu / max(len(add), 1),
        "pending_median": float(np.median(pending)) if pending else 0.0,
        "pending_max": int(max(pending)) if pending else 0,
        "finish_s": finish,
        "tiles": len(stream.model_.tiles_) if stream.model_ is not None else 0,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "max_diff": float("nan"),
    }
    if compare:
        # The same settings as the stream's (its tile size included), fitted on every scan at once.
        batch = TiledGPOM(**stream.options).fit(scans, hyperparameters=stream.hyperparameters_)
        spec = stream.default_grid(0.1)
        a = stream.grid(0.1, spec.extent).probability
        b = batch.grid(0.1, spec.extent).probability
        row["max_diff"] = float(np.max(np.abs(a - b)))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--log", choices=sorted(LOGS), nargs="+", default=["intel"])
    parser.add_argument("--scans", type=int, default=None, help="first N scans only")
    parser.add_argument("--refresh-every", type=int, default=10, help="refresh the GP every N scans")
    parser.add_argument("--max-refits", type=int, default=None, help="cap on tile refits per refresh")
    parser.add_argument("--compare-batch", action="store_true", help="also fit the batch map and report the difference")
    parser.add_argument("--tile-size", type=float, default=None, help="tile side, metres (default TiledGPOM's)")
    args = parser.parse_args()
    set_progress_mode("quiet")
    rows = []
    for name in args.log:
        scans = read_scans(LOGS[name])[: args.scans]
        options = {} if args.tile_size is None else {"tile_size": args.tile_size}
        rows.append(run(name, scans, args.refresh_every, args.max_refits, args.compare_batch, options))
    cols = [
        ("log", "{}"),
        ("scans", "{}"),
        ("warmup_s", "{:.1f}"),
        ("add_median_ms", "{:.1f}"),
        ("add_p95_ms", "{:.1f}"),
        ("absorb_rate", "{:.0f}"),
        ("refresh_median_s", "{:.2f}"),
        ("refresh_p95_s", "{:.2f}"),
        ("sustained_rate", "{:.1f}"),
        ("cpu_per_scan_ms", "{:.0f}"),
        ("pending_median", "{:.0f}"),
        ("pending_max", "{}"),
        ("finish_s", "{:.1f}"),
        ("tiles", "{}"),
        ("peak_mb", "{:.0f}"),
        ("max_diff", "{:.1e}"),
    ]
    print(
        f"refresh every {args.refresh_every} scans, max refits {args.max_refits or 'all'}, "
        f"tile size {args.tile_size or 'default'}; rates in scans/s"
    )
    print("| " + " | ".join(c for c, _ in cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f.format(r[c]) for c, f in cols) + " |")


if __name__ == "__main__":
    main()
