"""3-D speed: ``gpomap map`` on the shared 3-D data against OctoMap's insertion of the same points.

For each case (la3dm ``sim_structured`` and ``sim_unstructured`` with ``--max-range 8``; the five
3DMatch depth frames at full pixel resolution, 640 x 480, and every 4th pixel, ``--stride 4``;
the simulated office's ten depth frames rendered at 640 x 480 and 160 x 120, ``office-vga`` and
``office``, written to a depth folder first, as ``benchmarks/quality3d.py`` renders them),
two kinds of fresh process, alternated, ``--repeat`` times each:

- **gpomap**: the command itself, ``gpomap map INPUT -o OUT -q [options]`` with every default
  (voxels of 0.1 m, the 3-D profile), run through :func:`gpomap.cli.main` with its CPU split by
  phase where the command calls them: ``read`` (the clouds read and selected), ``fit`` (the model
  planned, its memory checked, and fitted: :func:`gpomap.cli.map3d._plan` and ``model.fit``),
  ``voxels`` (the voxel map predicted, ``model.grid``) and ``write`` (the files written, the
  fitted map ``map.gpom`` among them). The stage timings are the wall seconds ``gpomap map``
  records in ``map.npz``.
- **octomap**: OctoMap through pyoctomap (:class:`gpomap.baselines.octomap.OctoMapBaseline`:
  ``insertPointCloud`` with ray casting, OctoMap's default sensor model) at the same resolution,
  inserting the very clouds ``gpomap map`` reads (read by the same function, from the same
  command line, so the same points and max range); ``insert`` is the CPU of the insertion alone.

CPU seconds are user + system time of the whole process (every thread) and of each phase
(:func:`time.process_time`, every thread); peak MB is the process's peak resident set. The ratios
are gpomap's over OctoMap's, medians of the runs of the same sitting: "fit / insert" is the
issue's target (at most 3x), "fit + voxels / insert" counts the map gpomap writes too, and the
peak memory ratio (target at most 4x) is of the whole processes. Both processes import gpomap's
command-line reader; "base MB" is each one's resident set once its clouds are read, before
fitting or inserting.

numba's cache is a fresh directory (``NUMBA_CACHE_DIR``) filled by an untimed ``gpomap map`` run
on each case before its timed ones (the cases take different paths: a depth frame's free samples
are merged, a lidar scan's are not), so every timed run loads compiled code as a user's second
run does (``benchmarks/compile_cache.py`` measures the first run's compiling); gpomap's modules
are compiled to bytecode first, as an install leaves them (:mod:`module_bytecode`).

Usage, from the repository's root::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed3d.py                         # every case, one run each
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed3d.py --cases sim_structured --repeat 3
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed3d.py --option=--workers=1    # an extra gpomap map option
    .venv/bin/python benchmarks/speed3d.py --json speed3d.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from module_bytecode import write_bytecode
from whole_logs import DATA, _gpomap_command, _map_info, _timed_process

#: Each case: the input and the ``gpomap map`` options it needs beyond the defaults.
CASES: dict[str, list[str]] = {
    "sim_structured": [str(DATA / "la3dm-sim" / "sim_structured"), "--max-range", "8"],
    "sim_unstructured": [str(DATA / "la3dm-sim" / "sim_unstructured"), "--max-range", "8"],
    "3dmatch": [str(DATA / "3dmatch")],
    "3dmatch-stride4": [str(DATA / "3dmatch"), "--stride", "4"],
    "office-vga": [],
    "office": [],
}
#: The cases whose input is a simulated scene's depth frames, rendered into the run's scratch
#: folder first (:func:`quality3d.rendered_frames`); their command is that folder.
RENDERED = ("office-vga", "office")
TARGET_CPU = 3.0
TARGET_MEMORY = 4.0


def _cpu() -> float:
    return time.process_time()


def _parsed(command: list[str], out: str) -> argparse.Namespace:
    """The options of ``gpomap map COMMAND -o OUT -q``, resolved as the command resolves them for 3-D inputs."""
    from gpomap import cli
    from gpomap.cli.map3d import apply_3d_defaults
    from gpomap.cli.options import resolve_library_defaults

    args = cli.build_parser().parse_args(["map", *command, "-o", out, "-q"])
    resolve_library_defaults(args)
    apply_3d_defaults(args)
    return args


def _once(obj: Any, name: str, f: Any) -> Any:
    """`f`, which deletes the instance attribute `name` of `obj` (itself) when called."""

    def call(*args: Any, **kwargs: Any) -> Any:
        del obj.__dict__[name]
        return f(*args, **kwargs)

    return call


def map_child(command: list[str], out: str) -> dict[str, Any]:
    """``gpomap map COMMAND -o OUT -q`` through :func:`gpomap.cli.main` in this process, its CPU by phase."""
    c0 = _cpu()
    from gpomap import cli
    from gpomap.cli import map3d
    from gpomap.io import voxel_outputs
    from gpomap.resources import rss_mb

    phases = {"import": _cpu() - c0, "read": 0.0, "fit": 0.0, "voxels": 0.0, "write": 0.0}
    memory: dict[str, float] = {}

    def timed(name: str, f: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t = _cpu()
            try:
                return f(*args, **kwargs)
            finally:
                phases[name] += _cpu() - t

        return wrapper

    read, plan = map3d.load_clouds, map3d._plan

    def load_clouds(args: argparse.Namespace) -> Any:
        clouds = timed("read", read)(args)
        memory["base"] = rss_mb() or 0.0
        return clouds

    def planned(args: argparse.Namespace, clouds: Any) -> Any:
        planned = timed("fit", plan)(args, clouds)  # the unfitted model first, with what the checks need
        model = planned[0]
        # The command calls each once on the model it planned; the timed method is let go after
        # its call, so the map saved (map.gpom) holds the model's own state only.
        for method, phase in (("fit", "fit"), ("grid", "voxels")):
            setattr(model, method, _once(model, method, timed(phase, getattr(model, method))))
        return planned

    map3d.load_clouds = load_clouds
    map3d._plan = planned
    voxel_outputs.write_voxel_outputs = timed("write", voxel_outputs.write_voxel_outputs)
    code = cli.main(["map", *command, "-o", out, "-q"])
    if code != 0:
        raise SystemExit(f"gpomap map {' '.join(command)} exited with {code}")
    phases["other"] = _cpu() - c0 - sum(phases.values())
    return {"phases": phases, "base_mb": memory.get("base", 0.0)}


def octomap_child(command: list[str], resolution: float) -> dict[str, Any]:
    """OctoMap's insertion of the clouds ``gpomap map COMMAND`` reads, at `resolution`, its CPU by phase."""
    c0 = _cpu()
    from gpomap.baselines.octomap import OctoMapBaseline
    from gpomap.cli.map3d import load_clouds
    from gpomap.resources import rss_mb

    c1 = _cpu()
    args = _parsed(command, "unused")
    clouds = load_clouds(args)
    c2 = _cpu()
    base = rss_mb() or 0.0
    tree = OctoMapBaseline(resolution, max_range=args.max_range).fit(clouds)
    c3 = _cpu()
    return {
        "phases": {"import": c1 - c0, "read": c2 - c1, "insert": c3 - c2},
        "base_mb": base,
        "rays": int(tree.n_rays_),
        "leaves": int(tree.tree_.getNumLeafNodes()),
    }


def _resolution(command: list[str]) -> float:
    """The voxel side ``gpomap map COMMAND`` writes (its 3-D default unless given)."""
    return float(_parsed(command, "unused").resolution)


def case_runs(name: str, command: list[str], repeat: int, scratch: Path, env: dict[str, str]) -> dict[str, Any]:
    """OctoMap's and gpomap's processes on one case, alternated, `repeat` runs each."""
    out = scratch / "out"
    resolution = _resolution(command)
    me = [sys.executable, str(Path(__file__).resolve())]
    runs: dict[str, Any] = {"name": name, "command": command, "resolution": resolution, "gpomap": [], "octomap": []}
    for _ in range(repeat):
        r = _timed_process([*me, "--octomap-child", json.dumps(command), str(resolution)], env, scratch)
        r.update(json.loads(r.pop("stdout").strip().splitlines()[-1]))
        runs["octomap"].append(r)
        shutil.rmtree(out, ignore_errors=True)
        r = _timed_process([*me, "--map-child", json.dumps(command), str(out)], env, scratch)
        r.update(json.loads(r.pop("stdout").strip().splitlines()[-1]))
        with np.load(out / "map.npz") as z:
            info = json.loads(str(z["info"]))
        r.update(_map_info(out), points=int(info.get("n_points", 0)), cells=int(info.get("n_cells", 0)))
        runs["gpomap"].append(r)
        print(
            f"{name}: octomap {runs['octomap'][-1]['cpu']:.1f} CPU s, gpomap map {r['cpu']:.1f} CPU s",
            file=sys.stderr,
            flush=True,
        )
    shutil.rmtree(out, ignore_errors=True)
    return runs


def _med(runs: list[dict[str, Any]], key: str, phase: str | None = None) -> float:
    return statistics.median(float(r["phases"][phase] if phase else r[key]) for r in runs)


def print_tables(results: list[dict[str, Any]], repeat: int) -> None:
    print()
    print(
        "| case | rays | voxel m | gpomap fit CPU s | + voxels | OctoMap insert CPU s | fit / insert | fit + voxels / insert "
        "| process CPU s gpomap / OctoMap | peak MB gpomap / OctoMap (base) | peak ratio |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        g, o = r["gpomap"], r["octomap"]
        fit, vox, ins = _med(g, "", "fit"), _med(g, "", "voxels"), _med(o, "", "insert")
        gp_peak, oc_peak = _med(g, "peak_mb"), _med(o, "peak_mb")
        print(
            f"| {r['name']} | {o[0]['rays']:,} | {r['resolution']:g} | {fit:.2f} | {vox:.2f} | {ins:.2f} | {fit / ins:.1f}x "
            f"| {(fit + vox) / ins:.1f}x | {_med(g, 'cpu'):.1f} / {_med(o, 'cpu'):.1f} "
            f"| {gp_peak:.0f} ({_med(g, 'base_mb'):.0f}) / {oc_peak:.0f} ({_med(o, 'base_mb'):.0f}) | {gp_peak / oc_peak:.1f}x |"
        )
    print()
    print(f"Targets: fit / insert at most {TARGET_CPU:g}x, peak ratio at most {TARGET_MEMORY:g}x; medians of {repeat} run(s).")
    print()
    for r in results:
        fastest = min(r["gpomap"], key=lambda w: w["cpu"])
        phases = ", ".join(f"{k} {v:.2f}" for k, v in fastest["phases"].items())
        stages = ", ".join(f"{k} {v:.2f}" for k, v in fastest["timings"].items())
        octo = min(r["octomap"], key=lambda w: w["cpu"])
        print(
            f"{r['name']}: gpomap map ({fastest['cpu']:.1f} CPU s, {fastest['wall']:.1f} wall s, {fastest['points']:,} points, "
            f"{fastest['cells']:,} cells): CPU s by phase: {phases}; wall s by stage: {stages}"
        )
        o_phases = ", ".join(f"{k} {v:.2f}" for k, v in octo["phases"].items())
        print(f"{r['name']}: OctoMap ({octo['cpu']:.1f} CPU s, {octo['leaves']:,} leaves): CPU s by phase: {o_phases}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated: " + ", ".join(CASES))
    parser.add_argument("--repeat", type=int, default=1, help="runs of each process per case (default: 1)")
    parser.add_argument(
        "--option", action="append", default=[], help="an extra gpomap map argument for every case (repeatable; --option=--x=1)"
    )
    parser.add_argument("--json", type=Path, help="also write the runs here")
    parser.add_argument("--map-child", nargs=2, metavar=("COMMAND", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--octomap-child", nargs=2, metavar=("COMMAND", "RESOLUTION"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.map_child:
        print(json.dumps(map_child(json.loads(args.map_child[0]), args.map_child[1])))
        return
    if args.octomap_child:
        print(json.dumps(octomap_child(json.loads(args.octomap_child[0]), float(args.octomap_child[1]))))
        return
    if args.repeat < 1:
        raise SystemExit(f"--repeat must be at least 1, got {args.repeat}")
    names = [n for n in args.cases.split(",") if n]
    unknown = [n for n in names if n not in CASES]
    if unknown:
        raise SystemExit(f"unknown case(s) {', '.join(unknown)}: --cases takes {', '.join(CASES)}")
    threads = os.environ.get("OMP_NUM_THREADS", "unset")
    extra = " ".join(args.option)
    import gpomap

    # The commit of the checkout gpomap is imported from (a worktree on PYTHONPATH, say), not of the directory run in.
    where = Path(gpomap.__file__).parent
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=where).stdout.strip()
    write_bytecode()

    print(
        f"# 3-D: gpomap map against OctoMap's insertion (commit {commit}, gpomap from {Path(gpomap.__file__).parent}, "
        f"{os.cpu_count()} CPUs, OMP_NUM_THREADS {threads})"
    )
    results = []
    with tempfile.TemporaryDirectory(prefix="gpomap-speed3d-") as tmp:
        scratch = Path(tmp)
        env = dict(os.environ, NUMBA_CACHE_DIR=str(scratch / "numba-cache"))
        for name in names:
            if name in RENDERED:
                from quality3d import rendered_frames  # the children never import it: their bases stay the same

                source = [str(rendered_frames(name, scratch)[3])]
            else:
                source = CASES[name]
            command = [*source, *args.option]
            warm = _timed_process([*_gpomap_command(), "map", *command, "-o", str(scratch / f"warm-{name}"), "-q"], env, scratch)
            print(f"numba's cache filled by an untimed gpomap map on {name} ({warm['cpu']:.1f} CPU s)", file=sys.stderr)
            results.append(case_runs(name, command, args.repeat, scratch, env))
    print(f"\n## gpomap map INPUT -o OUT -q {extra} (defaults) against OctoMap's insertion, whole processes".replace("  ", " "))
    print_tables(results, args.repeat)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
