"""Whether two versions of gpomap write the same maps, array by array, to the bit.

Two steps: ``write`` runs ``gpomap map LOG -o DIR/NAME`` (its defaults, plus each log's own
options) for a list of logs, and ``compare`` reads ``map.npz`` of each log from two such
directories and compares every array (``probability``, ``variance``, ``ternary``,
``seen_through``, ``path``, ...) for exact equality, NaNs in the same places counting as equal;
``info`` (timings, peak memory) is left out, being different every run. The map file
``map.gpom`` is compared too: the predictions it gives on a fixed set of points of each map, to
the bit. Exit status 1 when anything differs. Usage::

    .venv/bin/python benchmarks/identical_maps.py write /tmp/maps-before          # at one commit
    .venv/bin/python benchmarks/identical_maps.py write /tmp/maps-after           # at another
    .venv/bin/python benchmarks/identical_maps.py compare /tmp/maps-before /tmp/maps-after
    .venv/bin/python benchmarks/identical_maps.py write /tmp/m --logs intel --option=--resolution=0.1
    .venv/bin/python benchmarks/identical_maps.py write /tmp/m --logs sim_structured,3dmatch-stride4   # 3-D inputs
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# The shared data sits beside the project: ../shared/data from the repository's root.
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: Each log and the options it needs beyond the defaults.
LOGS: dict[str, tuple[Path, list[str]]] = {
    "intel": (DATA / "intel" / "intel-corrected.log.gz", []),
    "stage-arena": (DATA / "stage-arena" / "robot1.bag", ["--topic", "/base_scan", "--time-offset", "0.1"]),
    "belgioioso": (DATA / "belgioioso" / "belgioioso-corrected.log.gz", []),
    "csail": (DATA / "csail-robotlaser1" / "csail.log.gz", []),
    "fr079": (DATA / "fr079" / "freiburg-079-corrected.log.gz", []),
    "cave": (DATA / "sim-worlds" / "cave" / "cave.log.gz", []),
    "hospital_section": (DATA / "sim-worlds" / "hospital_section" / "hospital_section.log.gz", []),
    # 3-D inputs, at the voxel maps' defaults: a point cloud directory and depth frames.
    "sim_structured": (DATA / "la3dm-sim" / "sim_structured", ["--max-range", "8"]),
    "3dmatch-stride4": (DATA / "3dmatch", ["--stride", "4"]),
    "3dmatch": (DATA / "3dmatch", []),  # every pixel: 1.3 M rays, a minute or two
}
DEFAULT_LOGS = "intel,stage-arena"


def _gpomap() -> list[str]:
    script = Path(sys.executable).with_name("gpomap")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from gpomap.cli import console; sys.exit(console())"]


def write(outdir: Path, names: list[str], extra: list[str]) -> None:
    """``gpomap map`` of each log into ``outdir/NAME``."""
    outdir.mkdir(parents=True, exist_ok=True)
    for name in names:
        log, options = LOGS[name]
        t = time.perf_counter()
        cmd = [*_gpomap(), "map", str(log), "-o", str(outdir / name), "-q", *options, *extra]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr}")
        print(f"wrote {outdir / name} in {time.perf_counter() - t:.1f} s", flush=True)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype.kind == "f":
        return bool(np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b)))
    return bool(np.array_equal(a, b))


def _query_points(probability_shape: tuple[int, ...], origin: np.ndarray, resolution: float) -> np.ndarray:
    """A fixed set of points over a map (planar or voxel): 2,000 drawn uniformly over its extent (seed 0)."""
    rng = np.random.default_rng(0)
    return origin + rng.uniform(0, 1, size=(2000, len(probability_shape))) * np.array(probability_shape[::-1]) * resolution


def _format_version(path: Path) -> int:
    """The format version a map file's header names (read as it is: gpomap refuses other versions)."""
    with np.load(path, allow_pickle=False) as archive:
        return int(json.loads(str(archive["header"]))["version"])


def compare(first: Path, second: Path, names: list[str]) -> bool:
    """Print each log's arrays that differ (or "identical"); True when all are the same."""
    ok = True
    for name in names:
        a_path, b_path = first / name / "map.npz", second / name / "map.npz"
        if not a_path.exists() or not b_path.exists():
            print(f"{name}: missing {a_path if not a_path.exists() else b_path}")
            ok = False
            continue
        with np.load(a_path) as a, np.load(b_path) as b:
            keys = sorted((set(a.files) | set(b.files)) - {"info"})
            differ = []
            for k in keys:
                if k not in a.files or k not in b.files:
                    differ.append(f"{k} (in one only)")
                elif not _same(a[k], b[k]):
                    x, y = a[k], b[k]
                    if x.shape == y.shape and x.dtype.kind in "fiub":
                        n = int(np.sum(~((x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind == "f" else (x == y))))
                        differ.append(f"{k} ({n} of {x.size} values)")
                    else:
                        differ.append(f"{k} (shape {x.shape} / {y.shape}, dtype {x.dtype} / {y.dtype})")
            shape, origin, resolution = a["probability"].shape, a["origin"], float(a["resolution"])
        note = ""
        if (first / name / "map.gpom").exists() and (second / name / "map.gpom").exists():
            from gpomap import load_map
            from gpomap.io.mapfile import VERSION

            versions = {_format_version(d / name / "map.gpom") for d in (first, second)}
            if versions != {VERSION}:
                # A map file of another format version is refused by this gpomap: the grids alone are compared.
                note = f" (map.gpom not compared: format versions {sorted(versions)}, this gpomap reads {VERSION})"
            else:
                pts = _query_points(shape, origin, resolution)
                pa, va = load_map(first / name / "map.gpom").predict_proba(pts, return_var=True)
                pb, vb = load_map(second / name / "map.gpom").predict_proba(pts, return_var=True)
                if not (_same(pa, pb) and _same(va, vb)):
                    differ.append("map.gpom's predictions")
        print(f"{name}: " + ("identical" if not differ else "DIFFER: " + ", ".join(differ)) + note, flush=True)
        ok &= not differ
    return ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    w = sub.add_parser("write", help="gpomap map of each log into DIR/NAME")
    w.add_argument("outdir", type=Path)
    w.add_argument("--option", action="append", default=[], help="an extra gpomap map argument (repeatable; --option=--x=1)")
    c = sub.add_parser("compare", help="compare the maps of two directories")
    c.add_argument("first", type=Path)
    c.add_argument("second", type=Path)
    for p in (w, c):
        p.add_argument("--logs", default=DEFAULT_LOGS, help="comma-separated: " + ", ".join(LOGS) + f" (default: {DEFAULT_LOGS})")
    args = parser.parse_args()
    names = args.logs.split(",")
    unknown = [n for n in names if n not in LOGS]
    if unknown:
        raise SystemExit(f"unknown log(s) {', '.join(unknown)}: --logs takes {', '.join(LOGS)}")
    if args.command == "write":
        write(args.outdir, names, args.option)
        return
    sys.exit(0 if compare(args.first, args.second, names) else 1)


if __name__ == "__main__":
    main()
