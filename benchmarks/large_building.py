"""Whole buildings: ``gpomap map`` on a log hundreds of metres across, against the numpy counting grid.

The case is a simulated building (:mod:`gpomap.simulate`): a grid of blocks, each split into
rooms with a door onto the corridor, corridors between the blocks, furniture in some rooms, walled
all round; a robot drives every east-west corridor in turn (a snake) and into one room of most
blocks, scanning with 181 beams over 180 degrees (30 m range, no return written as 30.000, range
noise 0.02 m, 0.5 % of returns dropped, the logged pose 2 cm / 0.005 rad off the true one, as the
shared simulated worlds). The log is written as a CARMEN file (cached in ``--data-dir``: the same
settings give the same file) and mapped as a user maps it:

- ``gpomap map LOG -o OUT --resolution 0.05 -q``, its defaults otherwise, as a whole process;
- a process that reads the same scans the same way, fits the numpy counting grid
  (:class:`gpomap.baselines.ogm.OccupancyGridMapper`, ``sensor_model="counting"``) at 0.05 m and
  writes the same four files (``map.yaml``, ``map.pgm``, ``map.npz``, ``map.png``).

Each process's CPU (user + system, every thread), wall time and peak RSS come from ``wait4``; the
stage timings are those ``gpomap map`` records in ``map.npz``; gpomap's modules are compiled to
bytecode first, as an install leaves them (:mod:`module_bytecode`). With ``--memory-phases`` (Linux),
``gpomap map`` runs without ``-q`` and its resident set is read from ``/proc`` every 0.2 s, and
the peak of each phase its progress lines mark is printed: reading the scans, the fit, the
written grid's prediction, and writing the files (``map.gpom`` last). Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/large_building.py                      # both cases
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/large_building.py --cases hospital    # 400 x 260 m, ~7,000 scans
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/large_building.py --cases none --shared all --repeat 3  # the shared logs
    .venv/bin/python benchmarks/large_building.py --cases none --log-file robot.log.gz  # your own log
    .venv/bin/python benchmarks/large_building.py --write-log hospital /tmp/b.log.gz    # just the log
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/large_building.py --cases hospital-dense --methods gpomap --memory-phases
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))
from module_bytecode import write_bytecode

RESOLUTION = 0.05

# The shared logs sit beside the project: ../shared/data from the repository's root.
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SHARED = {
    "intel": DATA / "intel" / "intel-corrected.log.gz",
    "fr079": DATA / "fr079" / "freiburg-079-corrected.log.gz",
    "csail": DATA / "csail-robotlaser1" / "csail.log.gz",
    "belgioioso": DATA / "belgioioso" / "belgioioso-corrected.log.gz",
    "stage-arena": DATA / "stage-arena" / "robot1.bag",
    "cave": DATA / "sim-worlds" / "cave" / "cave.log.gz",
    "hospital_section": DATA / "sim-worlds" / "hospital_section" / "hospital_section.log.gz",
}


@dataclass(frozen=True)
class Building:
    """A simulated building and the robot's tour of it.

    Parameters
    ----------
    blocks_x, blocks_y : int
        Blocks across and up; a block is ``pitch - corridor`` metres square.
    pitch : float
        Block plus corridor, metres.
    corridor : float
        Corridor width, metres.
    step : float
        Metres driven between scans.
    room_visits : float
        Fraction of blocks where the robot enters a room.
    """

    blocks_x: int = 17
    blocks_y: int = 11
    pitch: float = 23.5
    corridor: float = 3.0
    step: float = 1.0
    room_visits: float = 0.6
    beams: int = 181
    max_range: float = 30.0
    range_sigma: float = 0.02
    dropout: float = 0.005
    pose_sigma: tuple[float, float] = (0.02, 0.005)
    seed: int = 5


#: The cases: a hospital-sized building (about 400 x 260 m, a scan every metre: 7,500 scans, 1.4 M
#: beams), the same tour scanned every 0.3 m (25,000 scans, 4.6 M beams), and a small building
#: of 8 x 5 blocks (190 x 120 m) for a quick look.
CASES = {
    "small": Building(blocks_x=8, blocks_y=5),
    "hospital": Building(),
    "hospital-dense": Building(step=0.3),
}


def _door(a: float, b: float, width: float, rng: np.random.Generator) -> tuple[float, float]:
    """A door's span on a wall from `a` to `b` (a < b), kept a metre off the ends."""
    c = rng.uniform(a + 1.0 + width / 2, b - 1.0 - width / 2)
    return c - width / 2, c + width / 2


def _wall_with_gaps(p: tuple[float, float], q: tuple[float, float], gaps: list[tuple[float, float]]) -> list[list[float]]:
    """Segments of the straight wall p -> q (axis-aligned) with `gaps` (spans along it) left open."""
    axis = 0 if p[1] == q[1] else 1
    lo, hi = sorted((p[axis], q[axis]))
    cuts = [lo]
    for g0, g1 in sorted(gaps):
        cuts += [g0, g1]
    cuts.append(hi)
    out = []
    for s0, s1 in zip(cuts[::2], cuts[1::2], strict=True):
        if s1 - s0 > 1e-9:
            a = [s0, p[1]] if axis == 0 else [p[0], s0]
            b = [s1, p[1]] if axis == 0 else [p[0], s1]
            out.append(a + b)
    return out


def building_walls_and_path(b: Building) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The building's wall segments, shape (w, 4), and the tour's waypoints, shape (k, 2)."""
    rng = np.random.default_rng(b.seed)
    c, P = b.corridor, b.pitch
    W, H = b.blocks_x * P + c, b.blocks_y * P + c
    walls: list[list[float]] = [[0, 0, W, 0], [W, 0, W, H], [W, H, 0, H], [0, H, 0, 0]]
    # Block (i, j) spans [x0, x0 + s] x [y0, y0 + s]; corridors run between blocks and round them all.
    s = P - c
    doors: dict[tuple[int, int], list[tuple[float, float, float, float]]] = {}
    for i in range(b.blocks_x):
        for j in range(b.blocks_y):
            x0, y0 = c + i * P, c + j * P
            kind = rng.choice(["four", "two", "hall"], p=[0.6, 0.3, 0.1])
            bottom: list[tuple[float, float]] = []
            top: list[tuple[float, float]] = []
            entries = []  # (door centre x, wall y, room centre x, room centre y)
            if kind == "hall":
                g = _door(x0, x0 + s, 2.0, rng)
                bottom.append(g)
                top.append(_door(x0, x0 + s, 2.0, rng))
                entries.append((0.5 * sum(g), y0, x0 + s / 2, y0 + s / 2))
            else:
                halves = [(x0, x0 + s / 2), (x0 + s / 2, x0 + s)] if kind == "four" else [(x0, x0 + s)]
                mid = y0 + s / 2
                walls.append([x0, mid, x0 + s, mid])
                if kind == "four":
                    walls.append([x0 + s / 2, y0, x0 + s / 2, y0 + s])
                for a0, a1 in halves:
                    g = _door(a0, a1, 1.0, rng)
                    bottom.append(g)
                    entries.append((0.5 * sum(g), y0, 0.5 * (a0 + a1), y0 + s / 4))
                    top.append(_door(a0, a1, 1.0, rng))
            walls += _wall_with_gaps((x0, y0), (x0 + s, y0), bottom)
            walls += _wall_with_gaps((x0, y0 + s), (x0 + s, y0 + s), top)
            walls += [[x0, y0, x0, y0 + s], [x0 + s, y0, x0 + s, y0 + s]]
            # Furniture: a few boxes against the room walls, clear of the middle the robot visits.
            for _ in range(rng.integers(0, 6)):
                w, h = rng.uniform(0.4, 1.6, size=2)
                bx = rng.uniform(x0 + 0.3, x0 + s - 0.3 - w)
                by = rng.choice([rng.uniform(y0 + s / 2 + 0.3, y0 + s - 0.3 - h), rng.uniform(y0 + 0.3, y0 + 1.2)])
                if abs(bx + w / 2 - (x0 + s / 4)) < 2.0 or abs(bx + w / 2 - (x0 + 3 * s / 4)) < 2.0:
                    continue  # keeps the doors' approach clear
                walls += [[bx, by, bx + w, by], [bx + w, by, bx + w, by + h], [bx + w, by + h, bx, by + h], [bx, by + h, bx, by]]
            doors[i, j] = entries
    # The tour: east-west corridor j (centre y = j P + c / 2) in turn, a snake joined along the
    # outer north-south corridors, with a detour into a room of a block on the corridor's north.
    path: list[tuple[float, float]] = [(c / 2, c / 2)]
    for j in range(b.blocks_y + 1):
        yc = j * P + c / 2
        order = range(b.blocks_x) if j % 2 == 0 else range(b.blocks_x - 1, -1, -1)
        for i in order:
            if j < b.blocks_y and rng.uniform() < b.room_visits:
                dx, wy, rx, ry = doors[i, j][rng.integers(len(doors[i, j]))]
                path += [(dx, yc), (dx, wy + 0.8), (rx - 1.5, ry), (rx + 1.5, ry + 1.0), (dx, wy + 0.8), (dx, yc)]
        end = W - c / 2 if j % 2 == 0 else c / 2
        path.append((end, yc))
        if j < b.blocks_y:
            path.append((end, yc + P))
    return np.asarray(walls, dtype=float), np.asarray(path, dtype=float)


def _poses(waypoints: NDArray[np.float64], step: float) -> NDArray[np.float64]:
    """Poses every `step` metres along the polyline, heading along it, shape (n, 3)."""
    seg = np.diff(waypoints, axis=0)
    keep = np.hypot(seg[:, 0], seg[:, 1]) > 1e-9
    w = np.vstack([waypoints[:1], waypoints[1:][keep]])
    seg = np.diff(w, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    s = np.arange(0.0, cum[-1], step)
    xy = np.column_stack([np.interp(s, cum, w[:, 0]), np.interp(s, cum, w[:, 1])])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    return np.column_stack([xy, np.arctan2(seg[k, 1], seg[k, 0])])


def write_building_log(b: Building, path: Path) -> dict[str, Any]:
    """Simulate the tour of `b` and write it as a CARMEN log (FLASER lines, gzipped); what was written."""
    from gpomap.simulate import World, beam_angles

    rng = np.random.default_rng(b.seed + 1)
    walls, waypoints = building_walls_and_path(b)
    poses = _poses(waypoints, b.step)
    rel = beam_angles(b.beams, np.pi)
    lo_w = np.minimum(walls[:, :2], walls[:, 2:])
    hi_w = np.maximum(walls[:, :2], walls[:, 2:])
    chunk = 64  # poses cast together against the walls within range of them
    tmp = path.with_name(path.name + ".part")
    with gzip.open(tmp, "wt", compresslevel=3) as f:
        f.write(f"# gpomap benchmarks/large_building.py: {len(poses)} scans, {b.beams} beams, {asdict(b)}\n")
        for k0 in range(0, len(poses), chunk):
            p = poses[k0 : k0 + chunk]
            lo, hi = p[:, :2].min(axis=0) - b.max_range, p[:, :2].max(axis=0) + b.max_range
            near = np.flatnonzero(((hi_w >= lo) & (lo_w <= hi)).all(axis=1))
            world = World(segments=walls[near])
            angles = (p[:, 2:3] + rel[None, :]).ravel()
            ranges = world.cast(np.repeat(p[:, :2], b.beams, axis=0), angles, b.max_range).reshape(len(p), b.beams)
            hit = ranges < b.max_range
            ranges = np.where(hit, np.maximum(ranges + rng.normal(0.0, b.range_sigma, ranges.shape), 1e-3), ranges)
            ranges[hit & (rng.uniform(size=ranges.shape) < b.dropout)] = b.max_range
            ranges = np.minimum(ranges, b.max_range)
            logged = p + np.column_stack(
                [rng.normal(0.0, b.pose_sigma[0], (len(p), 2)), rng.normal(0.0, b.pose_sigma[1], len(p))]
            )
            for i in range(len(p)):
                r = " ".join(f"{v:.3f}" for v in ranges[i])
                x, y, t = logged[i]
                stamp = 0.1 * (k0 + i)
                f.write(f"FLASER {b.beams} {r} {x:.4f} {y:.4f} {t:.5f} {x:.4f} {y:.4f} {t:.5f} {stamp:.3f} sim {stamp:.3f}\n")
    tmp.replace(path)
    extent = walls[:, [0, 2]].max() - walls[:, [0, 2]].min(), walls[:, [1, 3]].max() - walls[:, [1, 3]].min()
    return {"scans": len(poses), "beams": len(poses) * b.beams, "walls": len(walls), "size_m": [float(e) for e in extent]}


def building_log(name: str, data_dir: Path) -> Path:
    """The case's log in `data_dir`, simulated and written if missing (its settings are in its name)."""
    b = CASES[name]
    key = _settings_key(b)
    path = data_dir / f"building-{name}-{key}.log.gz"
    if not path.exists():
        data_dir.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        info = write_building_log(b, path)
        print(f"simulated {name}: {info} in {time.perf_counter() - t:.0f} s -> {path}", file=sys.stderr, flush=True)
    return path


def _settings_key(b: Building) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(asdict(b), sort_keys=True).encode()).hexdigest()[:10]


# ----------------------------------------------------------------------------- processes


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
    return {
        "scans": len(scans),
        "beams": int(sum(s.n_beams for s in scans)),
        "grid": list(occupancy_map.grid.shape),
        "import": c1 - c0,
        "read": c2 - c1,
        "fit": c3 - c2,
        "write": c4 - c3,
    }


def _gpomap_command() -> list[str]:
    """``gpomap`` as a user runs it: the console script beside this Python, or the same entry point."""
    script = Path(sys.executable).with_name("gpomap")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from gpomap.cli import console; sys.exit(console())"]


#: The progress lines of ``gpomap map`` that start each phase after the first ("read").
PHASES: tuple[tuple[str, str], ...] = (
    ("fit", "fitting MSK-GPOM"),
    ("grid", " cells in "),
    ("write", " cells predicted in "),
)


def _resident_mb(pid: int) -> float | None:
    """The resident set of process `pid` in MB (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((int(line.split()[1]) / 1024.0 for line in f if line.startswith("VmRSS:")), None)
    except OSError:
        return None


def timed_process(cmd: list[str], env: dict[str, str], scratch: Path, phases: bool = False) -> dict[str, Any]:
    """Run `cmd` to the end; its CPU (user + system, every thread), wall and peak RSS, and its
    stdout; with `phases`, also the peak resident set of each of :data:`PHASES` (its stderr read
    as it comes, its resident set every 0.2 s)."""
    samples: list[tuple[float, float]] = []
    marks: list[tuple[float, str]] = []
    with open(scratch / "stdout", "w+") as out, open(scratch / "stderr", "w+") as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.PIPE if phases else err, text=True)
        threads = []
        if phases:

            def read_stderr() -> None:
                assert proc.stderr is not None
                for line in proc.stderr:
                    err.write(line)
                    marks.append((time.perf_counter() - t, line))

            def sample() -> None:
                while proc.poll() is None:
                    mb = _resident_mb(proc.pid)
                    if mb is not None:
                        samples.append((time.perf_counter() - t, mb))
                    time.sleep(0.2)

            threads = [threading.Thread(target=f, daemon=True) for f in (read_stderr, sample)]
            for th in threads:
                th.start()
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
        for th in threads:
            th.join()
        code = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if code != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({code}):\n{stderr[-4000:]}")
    result = {"cpu": usage.ru_utime + usage.ru_stime, "wall": wall, "peak_mb": usage.ru_maxrss / 1024.0, "stdout": stdout}
    if phases:
        result["phase_peak_mb"] = phase_peaks(samples, marks)
    return result


def phase_peaks(samples: list[tuple[float, float]], marks: list[tuple[float, str]]) -> dict[str, float]:
    """The largest resident set sampled in each phase: "read" until the first of :data:`PHASES`'
    lines, then each phase until the next one's line (a phase whose line never came is left out)."""
    starts = {"read": 0.0}
    for name, text in PHASES:
        starts[name] = next((at for at, line in marks if text in line and at >= max(starts.values())), float("inf"))
    order = sorted(starts.items(), key=lambda kv: kv[1])
    peaks: dict[str, float] = {}
    for (name, begin), (_, end) in zip(order, [*order[1:], ("end", float("inf"))]):
        inside = [mb for at, mb in samples if begin <= at < end]
        if inside:
            peaks[name] = max(inside)
    return peaks


def run_case(name: str, log: Path, scratch: Path, methods: list[str], repeat: int = 1, phases: bool = False) -> dict[str, Any]:
    """The counting grid and ``gpomap map`` on one log, each its own process, `repeat` times alternated."""
    env = dict(os.environ)
    out = scratch / "out"
    result: dict[str, Any] = {"name": name, "log": str(log), "grid_runs": [], "gpomap_runs": []}
    for _ in range(repeat):
        if "grid" in methods:
            r = timed_process([sys.executable, __file__, "--grid-child", str(log), str(out)], env, scratch)
            r.update(json.loads(r.pop("stdout").strip().splitlines()[-1]))
            result["grid_runs"].append(r)
            print(f"done {name} counting grid: {r['cpu']:.1f} CPU s, {r['peak_mb']:.0f} MB", file=sys.stderr, flush=True)
        if "gpomap" in methods:
            cmd = [*_gpomap_command(), "map", str(log), "-o", str(out), "--resolution", str(RESOLUTION)]
            r = timed_process(cmd if phases else [*cmd, "-q"], env, scratch, phases)
            r.pop("stdout")
            with np.load(out / "map.npz") as z:
                info = json.loads(str(z["info"]))
                r["grid_shape"] = list(z["probability"].shape)
            r["timings"] = info.get("timings", {})
            r["cells"] = info.get("n_cells")
            result["gpomap_runs"].append(r)
            print(f"done {name} gpomap map: {r['cpu']:.1f} CPU s, {r['peak_mb']:.0f} MB", file=sys.stderr, flush=True)
    # Each method's run of median CPU stands for it (the fastest of two).
    for method in ("grid", "gpomap"):
        runs = sorted(result[f"{method}_runs"], key=lambda r: r["cpu"])
        if runs:
            result[method] = runs[(len(runs) - 1) // 2]
    return result


def print_table(results: list[dict[str, Any]]) -> None:
    """The table and each case's stage timings."""
    print()
    print(
        "| log | scans | beams | map cells | counting grid CPU s / wall s / peak MB | gpomap map CPU s / wall s / peak MB | CPU / grid | peak / grid |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        g, m = r.get("grid"), r.get("gpomap")
        shape = (m or {}).get("grid_shape") or (g or {}).get("grid")
        cells = f"{shape[1]} x {shape[0]}" if shape else "-"
        gs = f"{g['cpu']:.1f} / {g['wall']:.1f} / {g['peak_mb']:.0f}" if g else "-"
        ms = f"{m['cpu']:.1f} / {m['wall']:.1f} / {m['peak_mb']:.0f}" if m else "-"
        ratio = f"{m['cpu'] / g['cpu']:.2f}x" if g and m else "-"
        peak = f"{m['peak_mb'] / g['peak_mb']:.2f}x" if g and m else "-"
        scans = g["scans"] if g else "-"
        beams = g["beams"] if g else "-"
        print(f"| {r['name']} | {scans} | {beams} | {cells} | {gs} | {ms} | {ratio} | {peak} |")
    print()
    for r in results:
        if "grid" in r:
            g = r["grid"]
            print(
                f"{r['name']}: counting grid CPU s: " + ", ".join(f"{k} {g[k]:.2f}" for k in ("import", "read", "fit", "write"))
            )
        if "gpomap" in r:
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r["gpomap"]["timings"].items())
            print(f"{r['name']}: gpomap map, wall s per stage: {stages}")
            if "phase_peak_mb" in r["gpomap"]:
                peaks = ", ".join(f"{k} {v:.0f}" for k, v in r["gpomap"]["phase_peak_mb"].items())
                print(f"{r['name']}: gpomap map, peak resident MB per phase: {peaks}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="hospital,hospital-dense", help="comma-separated: " + ", ".join(CASES) + ", or none")
    parser.add_argument("--log-file", type=Path, action="append", default=[], metavar="PATH", help="also any log gpomap reads")
    parser.add_argument(
        "--shared", default="none", help="also shared logs, comma-separated: " + ", ".join(SHARED) + ", all or none (default)"
    )
    parser.add_argument("--methods", default="grid,gpomap", help="comma-separated: grid, gpomap (default: both)")
    parser.add_argument(
        "--repeat", type=int, default=1, help="runs of each method, alternated; the one of median CPU is shown (default: 1)"
    )
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=Path(tempfile.gettempdir()) / "gpomap-large-building",
        help="where the simulated logs are kept (default: %(default)s)",
    )
    parser.add_argument("--write-log", nargs=2, metavar=("CASE", "PATH"), help="only simulate CASE's log into PATH")
    parser.add_argument("--grid-child", nargs=2, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument(
        "--memory-phases", action="store_true", help="also the peak resident set of each phase of gpomap map (Linux)"
    )
    args = parser.parse_args()
    if args.grid_child:
        print(json.dumps(grid_child(*args.grid_child)))
        return
    if args.write_log:
        name, dest = args.write_log
        print(write_building_log(CASES[name], Path(dest)))
        return
    names = [] if args.cases == "none" else args.cases.split(",")
    unknown = [n for n in names if n not in CASES]
    if unknown:
        raise SystemExit(f"unknown case(s) {', '.join(unknown)}: --cases takes {', '.join(CASES)} or none")
    methods = args.methods.split(",")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    write_bytecode()
    print(
        f"# Whole buildings (commit {commit}, {os.cpu_count()} CPUs, OMP_NUM_THREADS {os.environ.get('OMP_NUM_THREADS', 'unset')})"
    )
    shared = list(SHARED) if args.shared == "all" else [] if args.shared == "none" else args.shared.split(",")
    if any(n not in SHARED for n in shared):
        raise SystemExit(f"--shared takes some of {', '.join(SHARED)}, all or none, got {args.shared!r}")
    chosen = [(n, SHARED[n]) for n in shared] + [(n, building_log(n, args.data_dir)) for n in names]
    chosen += [(p.name, p) for p in args.log_file]
    results = []
    for name, log in chosen:
        with tempfile.TemporaryDirectory(prefix="gpomap-large-building-") as scratch:
            results.append(run_case(name, log, Path(scratch), methods, args.repeat, args.memory_phases))
    print(f"\n## gpomap map LOG -o OUT --resolution {RESOLUTION} against the counting grid, whole processes")
    print_table(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
