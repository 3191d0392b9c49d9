"""``gpomap convert`` on a hand-made grid: ``--pooling`` reaches the conversion, bad values are usage errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gpomap.cli import main
from gpomap.convert import convert_grid
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.npz import load_map, save_map

PIXEL = 0.05
FINE = 0.01


def _room() -> np.ndarray:
    """20 x 20 pixels of 0s and 1s: a room's walls one pixel thick, edge to edge (any pooling's
    look), and a wall from the top one ending in the room."""
    v = np.zeros((20, 20))
    v[[1, 18], 1:19] = v[1:19, [1, 18]] = 1.0
    v[10:18, 9] = 1.0
    return v


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def room_npz(tmp_path_factory: pytest.TempPathFactory):
    path = tmp_path_factory.mktemp("grid") / "room.npz"
    return save_map(OccupancyMap(GridSpec((0.0, 0.0), PIXEL, (20, 20)), _room()), path)


def _convert(room_npz, out, pooling: str | None, capsys) -> tuple[dict, np.ndarray]:
    argv = ["convert", str(room_npz), "-o", str(out), "--resolution", str(FINE), "-q", "--json"]
    if pooling is not None:
        argv += ["--pooling", pooling]
    code, stdout, err = _run(argv, capsys)
    assert code == 0, err
    report = json.loads(stdout.split("\nwrote")[0])
    return report, load_map(out / "map.npz").probability


def test_pooling_reaches_the_conversion(room_npz, tmp_path, capsys):
    # The room's walls run edge to edge: read by itself (auto) it is any-pixel pooled, and a 0
    # beside a wall is wholly free. Told it was majority-pooled, a 0 beside a 1 may hold up to half
    # of a wall (taken as partly occupied) and a 1 holds more than half: the written map differs,
    # and is the library's for that pooling.
    auto, p_auto = _convert(room_npz, tmp_path / "auto", None, capsys)
    told_any, p_any = _convert(room_npz, tmp_path / "any", "any", capsys)
    majority, p_majority = _convert(room_npz, tmp_path / "majority", "majority", capsys)
    assert (auto["pooling"], told_any["pooling"], majority["pooling"]) == ("any", "any", "majority")
    np.testing.assert_array_equal(p_auto, p_any)
    library = convert_grid(room_npz, resolution=FINE, pooling="majority").map.probability
    np.testing.assert_allclose(p_majority, library, rtol=0, atol=1e-12)
    # The fine pixels of the free coarse pixels beside the walls (the room's inside ring): held
    # free when any-pooled, partly occupied when majority-pooled.
    k = round(PIXEL / FINE)
    ring = np.zeros((20, 20), dtype=bool)
    ring[2:17, 2] = True  # beside the left wall, inside the room
    beside = np.kron(ring, np.ones((k, k), dtype=bool))
    assert p_any[beside].max() < 1e-3
    assert p_majority[beside].mean() > 0.05
    # Majority-pooled, every 1 is at least half occupied in the map; any-pooled only somewhere.
    ones = np.kron(_room() == 1.0, np.ones((k, k), dtype=bool))
    share = (p_majority > 0.5).reshape(20, k, 20, k).mean(axis=(1, 3))
    assert (share[_room() == 1.0] > 0.5).all()
    assert ((p_any > 0.5) & ones).sum() < ((p_majority > 0.5) & ones).sum()


def test_a_bad_pooling_is_a_usage_error(room_npz, tmp_path, capsys):
    code, _, err = _run(["convert", str(room_npz), "-o", str(tmp_path / "out"), "--pooling", "median"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert lines[0].startswith("gpomap convert: error: argument --pooling: invalid choice: 'median'"), lines
    assert len(lines) == 2 and "--help" in lines[1]
    assert not (tmp_path / "out").exists()


def test_pooling_is_refused_for_an_octree(tmp_path, capsys):
    # An OctoMap tree has no pooling: the option is named, not ignored (before the tree is read).
    tree = tmp_path / "x.bt"
    tree.write_bytes(b"not read")
    code, _, err = _run(["convert", str(tree), "-o", str(tmp_path / "out"), "--pooling", "majority", "-q"], capsys)
    assert code == 1
    assert "--pooling is for grids" in err


def test_the_pooling_factor_reaches_the_conversion(tmp_path, capsys):
    # An any-pooled room whose right wall borders unknown space: told (or, untold, taking) the
    # factor of the output's resolution, its 1s beside unknown space are read as a wall's front.
    v = _room()
    v[:, 19] = np.nan
    path = save_map(OccupancyMap(GridSpec((0.0, 0.0), PIXEL, (20, 20)), v), tmp_path / "half.npz")
    k = round(PIXEL / FINE)
    runs = {}
    for name, extra in (("untold", []), ("told", ["--pooling-factor", str(k)]), ("other", ["--pooling-factor", "2"])):
        argv = ["convert", str(path), "-o", str(tmp_path / name), "--resolution", str(FINE), "-q", "--json", *extra]
        code, stdout, err = _run(argv, capsys)
        assert code == 0, err
        runs[name] = (json.loads(stdout.split("\nwrote")[0]), load_map(tmp_path / name / "map.npz").probability)
    assert [runs[n][0]["pooling_factor"] for n in ("untold", "told", "other")] == [k, k, 2]
    np.testing.assert_array_equal(runs["untold"][1], runs["told"][1])
    library = convert_grid(path, resolution=FINE, pooling_factor=2).map.probability
    np.testing.assert_allclose(runs["other"][1], library, rtol=0, atol=1e-12)
    assert np.abs(runs["other"][1] - runs["told"][1]).max() > 1e-3
    # No factor where the output's cell is not a whole part of the pixel.
    code, stdout, err = _run(["convert", str(path), "-o", str(tmp_path / "odd"), "--resolution", "0.03", "-q", "--json"], capsys)
    assert code == 0, err
    assert json.loads(stdout.split("\nwrote")[0])["pooling_factor"] is None
    code, _, err = _run(["convert", str(path), "-o", str(tmp_path / "bad"), "--pooling-factor", "0"], capsys)
    assert code == 2 and "--pooling-factor" in err
