"""Local tile workers: one, threads, or processes, on the quality benchmark's logs.

MSK-GPOM as ``gpomap map`` builds it (:func:`gpomap.evaluation.make_model`) is fitted on the
training scans of a log and split of ``benchmarks/quality.py`` and writes its 0.05 m map, once
per way of running the tiles: in this process (one worker), on two threads (the default), and
on two forked processes (``worker_processes=True``). Printed: CPU seconds of this process and
its finished children, wall seconds, and the model's stages (wall). A warm-up fit on a few scans
first loads numba's compiled code, so no row pays for compiling it.

Run from the repository root::

    .venv/bin/python benchmarks/workers.py                       # Intel and CSAIL, both splits
    .venv/bin/python benchmarks/workers.py --logs fr079 --splits blocks
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import quality
from gpomap.evaluation import make_model, prepare

#: (label, n_workers, worker_processes)
VARIANTS: tuple[tuple[str, int, bool], ...] = (("1 worker", 1, False), ("2 threads", 2, False), ("2 processes", 2, True))
STAGES = ("cells", "hyperparameters", "variance_scale", "tile_fits", "evidence", "grid")


def _cpu() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def run(log: str, split: str) -> list[dict[str, Any]]:
    """Every variant on one log and split."""
    scans, plan = quality.load(log)
    step = quality.LOGS[log].get("scan_step", 1)
    data = prepare(scans, split, scan_step=step, max_test_points=quality.MAX_TEST_POINTS, plan=plan)
    make_model("msk", n_workers=1).fit(data.train[:50])  # numba's compiled code loaded
    rows = []
    for label, n_workers, processes in VARIANTS:
        c0, w0 = _cpu(), time.perf_counter()
        model = make_model("msk", n_workers=n_workers, worker_processes=processes)
        model.fit(data.train)
        t = time.perf_counter()
        model.grid(quality.GRID_RESOLUTION)
        stages = {**model.timings_, "grid": time.perf_counter() - t}
        row = {"log": log, "split": split, "workers": label, "cpu_s": _cpu() - c0, "wall_s": time.perf_counter() - w0}
        row.update({s: float(stages.get(s, 0.0)) for s in STAGES})
        rows.append(row)
        print(
            f"| {log} | {split} | {label} | {row['cpu_s']:.1f} | {row['wall_s']:.1f} | "
            + " | ".join(f"{row[s]:.2f}" for s in STAGES)
            + " |",
            flush=True,
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--logs", default="intel,csail", help=f"comma-separated, of {', '.join(quality.LOGS)}")
    parser.add_argument("--splits", default="blocks,every", help="comma-separated, of blocks, every")
    args = parser.parse_args(argv)
    header = "| log | split | workers | CPU s | wall s | " + " | ".join(f"{s} s" for s in STAGES) + " |"
    print(header)
    print("|" + "---|" * header.count(" | ") + "---|")
    for log in args.logs.split(","):
        for split in args.splits.split(","):
            run(log, split)
    return 0


if __name__ == "__main__":
    sys.exit(main())
