"""Seeded fuzzing of every reader, a fixed number of mutants each: a mutant either reads or raises a GpomapError.

Valid small inputs (a CARMEN log, the first 50 lines of the Intel log when present, a map_server
YAML + PGM, points CSV and NPZ, a gpomap NPZ map, a ROS1 bag) are mutated by byte flips, token
replacement (nan, inf, 1e400, -1, 5,000 digits, empty), line truncation and line duplication.
Any other exception fails the test and shows the mutant.
"""

from __future__ import annotations

import gzip
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import GpomapError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io import read_scans
from gpomap.io.arrays import read_points
from gpomap.io.npz import load_map, save_map
from gpomap.io.rosmap import read_rosmap

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEED = 20240614
TOKENS = [b"nan", b"inf", b"-inf", b"1e400", b"-1", b"9" * 5000, b"", b"0", b"1e-400", b"\xff\xfe", b"[[[["]


def _mutate(data: bytes, rng: np.random.Generator, text: bool) -> bytes:
    """One random mutation of `data` (tokens and lines only make sense for text inputs)."""
    kind = int(rng.integers(0, 5 if text else 2))
    buf = bytearray(data)
    if kind == 0 or not buf:  # flip a few bytes
        for _ in range(int(rng.integers(1, 8))):
            if buf:
                buf[int(rng.integers(0, len(buf)))] = int(rng.integers(0, 256))
        return bytes(buf)
    if kind == 1:  # cut the file short
        return bytes(buf[: int(rng.integers(0, len(buf)))])
    lines = data.split(b"\n")
    i = int(rng.integers(0, len(lines)))
    if kind == 2:  # replace a token of one line
        words = lines[i].replace(b",", b" , ").split(b" ")
        if words:
            words[int(rng.integers(0, len(words)))] = TOKENS[int(rng.integers(0, len(TOKENS)))]
        lines[i] = b" ".join(words).replace(b" , ", b",")
    elif kind == 3:  # truncate one line
        lines[i] = lines[i][: int(rng.integers(0, len(lines[i]) + 1))]
    else:  # duplicate a line
        lines.insert(i, lines[i])
    return b"\n".join(lines)


def _fuzz(tmp_path: Path, name: str, original: bytes, read: Callable[[Path], object], iterations: int, text: bool = True) -> int:
    """Run `iterations` mutants through `read`, every one whatever the machine's speed; return how many ran."""
    rng = np.random.default_rng([SEED, sum(name.encode())])
    path = tmp_path / name
    done = 0
    for k in range(iterations):
        mutant = _mutate(original, rng, text)
        path.write_bytes(mutant)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read(path)
        except GpomapError:
            pass
        except Exception as exc:
            shown = mutant if len(mutant) <= 600 else mutant[:600] + b"..."
            pytest.fail(f"mutant {k} of {name} raised {type(exc).__name__}: {exc}\nmutant bytes: {shown!r}")
        done += 1
    return done


def _carmen_log() -> bytes:
    r = " ".join(["1.5"] * 178 + ["81.83", "0.0"])
    lines = ["# test log", "PARAM robot_frontlaser_offset -0.04 nohost 0", "PARAM robot_front_laser_max 80.99 nohost 0"]
    for k in range(4):
        lines.append(f"FLASER 180 {r} {k} 1 0.1 {k} 1 0.1 {k + 1.0} host {k + 1.0}")
        lines.append("ODOM 0 0 0 0 0 0 0 host 0")
    lines.append("ROBOTLASER1 0 -0.5 1.0 0.5 4.0 0.01 0 3 5.0 1.0 2.0 1 7.0 1.0 1.0 0.0 0.0 0.0 0.0 0 0 0 0 0 9.5 host 1.0")
    return ("\n".join(lines) + "\n").encode()


def test_fuzz_carmen(tmp_path: Path) -> None:
    assert _fuzz(tmp_path, "small.log", _carmen_log(), read_scans, 300) == 300
    intel = DATA / "intel" / "intel-corrected.log.gz"
    if intel.exists():
        with gzip.open(intel, "rb") as f:
            head = b"".join(f.readline() for _ in range(50))
        assert _fuzz(tmp_path, "intel-head.log", head, read_scans, 150) == 150
        # Gzipped mutants: the decompressor's errors must become InputFormatError too.
        assert _fuzz(tmp_path, "intel-head.log.gz", gzip.compress(head), read_scans, 100, text=False) == 100


def test_fuzz_rosmap(tmp_path: Path) -> None:
    pgm = b"P5\n# c\n4 3\n255\n" + bytes([0, 0, 0, 0, 205, 205, 205, 205, 254, 254, 254, 128])
    (tmp_path / "map.pgm").write_bytes(pgm)
    yml = (
        b"image: map.pgm\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\nnegate: 0\n"
        b"occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: trinary\n"
    )
    assert _fuzz(tmp_path, "map.yaml", yml, read_rosmap, 300) == 300
    # The image itself, read through an intact YAML that names it.
    (tmp_path / "img.yaml").write_bytes(yml.replace(b"map.pgm", b"fuzz.pgm"))
    assert _fuzz(tmp_path, "fuzz.pgm", pgm, lambda _: read_rosmap(tmp_path / "img.yaml"), 200) == 200


def test_fuzz_points(tmp_path: Path) -> None:
    csv = b"x,y,occupied\n0.5,1.0,1\n-2.0,3.25,0\n1e-3,7,true\n"
    assert _fuzz(tmp_path, "p.csv", csv, read_points, 300) == 300
    npz_path = tmp_path / "src.npz"
    np.savez(npz_path, points=np.array([[0.5, 1.0], [2.0, 3.0]]), occupied=np.array([True, False]))
    assert _fuzz(tmp_path, "p.npz", npz_path.read_bytes(), read_points, 200, text=False) == 200


def test_fuzz_map_npz(tmp_path: Path) -> None:
    grid = GridSpec((-1.0, 0.5), 0.1, (3, 4))
    m = OccupancyMap(grid, np.linspace(0, 1, 12).reshape(3, 4), variance=np.ones((3, 4)), info={"a": [1, 2]})
    original = save_map(m, tmp_path / "src.npz").read_bytes()
    assert _fuzz(tmp_path, "m.npz", original, load_map, 200, text=False) == 200


def test_fuzz_rosbag(tmp_path: Path) -> None:
    from tests.test_io_rosbag import _write_bag

    original = _write_bag(tmp_path / "src.bag").read_bytes()
    assert _fuzz(tmp_path, "f.bag", original, read_scans, 60, text=False) == 60
