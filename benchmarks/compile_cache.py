"""numba's compilation on a first ``gpomap map`` and its cache on the next: CPU per compiled function.

Runs ``gpomap map LOG -o OUT -q`` (through :func:`gpomap.cli.main`) twice in fresh processes
sharing a new, empty ``NUMBA_CACHE_DIR``: the first compiles every compiled function the map
uses, the second should load them all from the cache. For each run it prints the process's CPU,
the CPU numba spent compiling each of gpomap's functions (its ``numba:compile`` events, the
functions it compiles for them included), and each function's cache hits and misses. Usage::

    .venv/bin/python benchmarks/compile_cache.py                       # Belgioioso, the default map
    .venv/bin/python benchmarks/compile_cache.py --map-option=--kernel --map-option=se
    PYTHONPATH=/path/to/other/checkout/src .venv/bin/python benchmarks/compile_cache.py   # another version
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from module_bytecode import write_bytecode

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DEFAULT_LOG = DATA / "belgioioso" / "belgioioso-corrected.log.gz"


def child(log: str, out: str, options: list[str]) -> dict[str, Any]:
    """One ``gpomap map`` in this process, with numba's compilations timed per top-level function."""
    from numba.core import event
    from numba.core.registry import CPUDispatcher

    stack: list[tuple[str, float]] = []
    compile_cpu: dict[str, float] = {}

    class Listener(event.Listener):
        def on_start(self, ev: Any) -> None:
            f = ev.data["dispatcher"].py_func
            stack.append((f"{f.__module__}.{f.__qualname__}", time.process_time()))

        def on_end(self, ev: Any) -> None:
            name, t0 = stack.pop()
            if not stack:  # a top-level compilation: what it compiled inside is counted in it
                compile_cpu[name] = compile_cpu.get(name, 0.0) + time.process_time() - t0

    event.register("numba:compile", Listener())
    from gpomap import cli

    code = cli.main(["map", log, "-o", out, "-q", *options])
    if code != 0:
        raise SystemExit(f"gpomap map exited with {code}")
    cache: dict[str, list[int]] = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith("gpomap") or module is None:
            continue
        for attr, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == name and value.signatures:
                stats = value.stats
                cache[f"{name}.{attr}"] = [sum(stats.cache_hits.values()), sum(stats.cache_misses.values())]
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"compile_cpu": compile_cpu, "cache": cache, "cpu": usage.ru_utime + usage.ru_stime}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", type=Path, default=DEFAULT_LOG, help="the log to map (default: Belgioioso)")
    parser.add_argument("--map-option", action="append", default=[], help="an option for gpomap map (repeatable)")
    parser.add_argument("--child", nargs=2, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(*args.child, args.map_option)))
        return
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    write_bytecode()
    import gpomap

    print(
        f"# numba's compile cache (commit {commit}; gpomap from {Path(gpomap.__file__).parent}; {args.log.name} {' '.join(args.map_option)})"
    )
    runs = []
    with tempfile.TemporaryDirectory(prefix="gpomap-compile-cache-") as scratch:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(scratch) / "cache"))
        for _ in range(2):
            out = Path(scratch) / "out"
            shutil.rmtree(out, ignore_errors=True)
            cmd = [sys.executable, __file__, "--child", str(args.log), str(out)] + [f"--map-option={o}" for o in args.map_option]
            done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise SystemExit(f"gpomap map failed:\n{done.stderr}")
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    first, second = runs
    print(f"\nprocess CPU s: first run {first['cpu']:.1f}, second run {second['cpu']:.1f}\n")
    print(
        "| compiled function | first run: compile CPU s | first run: cache hits / misses | second run: compile CPU s | second run: cache hits / misses |"
    )
    print("|---|---|---|---|---|")
    names = sorted(set(first["cache"]) | set(first["compile_cpu"]), key=lambda n: -first["compile_cpu"].get(n, 0.0))
    for name in names:
        h1, m1 = first["cache"].get(name, [0, 0])
        h2, m2 = second["cache"].get(name, [0, 0])
        print(
            f"| {name} | {first['compile_cpu'].get(name, 0.0):.2f} | {h1} / {m1} | {second['compile_cpu'].get(name, 0.0):.2f} | {h2} / {m2} |"
        )
    print(f"| all | {sum(first['compile_cpu'].values()):.2f} | | {sum(second['compile_cpu'].values()):.2f} | |")


if __name__ == "__main__":
    main()
