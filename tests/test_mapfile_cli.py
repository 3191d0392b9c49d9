"""gpomap map -> map.gpom -> gpomap render / query / update, and gpomap stream --save-state / --resume, in-process."""

from __future__ import annotations

import json
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import gpomap
from gpomap.cli import main
from gpomap.io.atomic import MANIFEST
from gpomap.io.mapfile import VERSION
from gpomap.io.npz import load_map as load_grid
from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
from gpomap.io.voxel_outputs import load_voxels
from gpomap.lattice import EXTENT_MARGIN_CELLS
from tests import world3d
from tests.test_map3d_cli import FAST, write_pcd
from tests.test_mapfile import _rewrite_header

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BAG = DATA / "stage-arena" / "robot1.bag"
pytestmark = pytest.mark.skipif(not BAG.exists(), reason="shared Stage arena bag not present")
ARENA = [str(BAG), "--topic", "/base_scan", "--time-offset", str(STAGE_TIME_OFFSET)]
GRID_ARRAYS = ("probability", "variance", "ternary", "seen_through", "origin", "resolution", "thresholds")


def same_grid_files(a: Path, b: Path) -> None:
    """Two written maps (map.npz) hold the same cells, to the bit."""
    with np.load(a) as x, np.load(b) as y:
        for key in GRID_ARRAYS:
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def manifest(outdir: Path) -> list[str]:
    return sorted(json.loads((outdir / MANIFEST).read_text())["files"])


def one_line_error(capsys, code: int) -> str:
    """The error of a run that failed: one line, no traceback (a reader's warnings aside)."""
    err = "".join(line for line in capsys.readouterr().err.splitlines(keepends=True) if not line.startswith("warning: "))
    assert code == 1 and err.startswith("gpomap: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.fixture(scope="module")
def scans():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("arena") / "map"
    assert main(["map", *ARENA, "--range", "0:40", "--resolution", "0.1", "-o", str(out), "-q"]) == 0
    return out


def test_map_puts_the_fitted_map_in_its_output_set(mapped):
    assert manifest(mapped) == ["map.gpom", "map.npz", "map.pgm", "map.png", "map.yaml"]
    # The map written is the loaded map's grid, to the bit: the file holds the model that wrote it.
    model = gpomap.load_map(mapped / "map.gpom")
    written, again = load_grid(mapped / "map.npz"), model.grid(0.1)
    assert written.grid == again.grid and written.thresholds == again.thresholds
    for key in ("probability", "variance", "ternary", "seen_through"):
        np.testing.assert_array_equal(getattr(written, key), getattr(again, key))


def test_render_writes_the_map_again_at_any_resolution(mapped, tmp_path, capsys):
    same = tmp_path / "same"
    assert main(["render", str(mapped / "map.gpom"), "-o", str(same), "--resolution", "0.1", "-q"]) == 0
    assert manifest(same) == ["map.npz", "map.pgm", "map.png", "map.yaml"]
    same_grid_files(same / "map.npz", mapped / "map.npz")
    assert (same / "map.pgm").read_bytes() == (mapped / "map.pgm").read_bytes()
    fine = tmp_path / "fine"
    extent = (0.0, 1.0, -0.5, 0.5)
    code = main(["render", str(mapped / "map.gpom"), "-o", str(fine), "--resolution", "0.01", "--extent", "0,1,-0.5,0.5"])
    printed = capsys.readouterr().out
    assert code == 0 and f"wrote        {fine / 'map.npz'}" in printed
    expected = gpomap.load_map(mapped / "map.gpom").grid(0.01, extent)
    got = load_grid(fine / "map.npz")
    assert got.grid == expected.grid and got.grid.shape == (100, 100)
    np.testing.assert_array_equal(got.probability, expected.probability)
    np.testing.assert_array_equal(got.variance, expected.variance)


def test_render_refuses_a_grid_too_large_before_loading_the_map(mapped, tmp_path, capsys):
    code = main(["render", str(mapped / "map.gpom"), "-o", str(tmp_path / "huge"), "--resolution", "0.0001"])
    err = one_line_error(capsys, code)
    assert "grid" in err and "would need about" in err and "--resolution" in err
    assert not (tmp_path / "huge").exists()


def test_render_into_the_output_set_holding_the_map_is_refused(mapped, tmp_path, capsys):
    own = tmp_path / "own"
    shutil.copytree(mapped, own)
    code = main(["render", str(own / "map.gpom"), "-o", str(own), "--resolution", "0.05", "-q"])
    assert "its output set holds map.gpom, the map being rendered" in one_line_error(capsys, code)
    assert (own / "map.gpom").exists() and manifest(own) == manifest(mapped)


def test_query_prints_or_writes_probability_and_variance(mapped, tmp_path, capsys):
    model = gpomap.load_map(mapped / "map.gpom")
    points = np.array([[0.5, 0.5], [1.2, 2.0], [-0.3, 1.1], [500.0, -300.0]])
    p, v = model.predict_proba(points, return_var=True)
    # Far from the data the map says what its prior says: 1/2 (its offset beta is 0) and the kernel's variance.
    assert model.hyperparameters_["beta"] == 0.0
    assert p[-1] == 0.5 and v[-1] == pytest.approx(model.hyperparameters_["variance"], rel=1e-12)
    csv = tmp_path / "points.csv"
    csv.write_text("x,y\n" + "\n".join(f"{float(x)!r},{float(y)!r}" for x, y in points) + "\n")
    assert main(["query", str(mapped / "map.gpom"), str(csv), "-q"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "x,y,probability,variance,ternary" and len(lines) == 5
    table = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    t = model.predict_ternary(points)
    assert t[-1] == -1  # the prior's 1/2 is neither free nor occupied
    np.testing.assert_array_equal(table, np.column_stack([points, p, v, t]))  # exact: 17 significant digits
    # No header, and an NPZ in and out.
    bare = tmp_path / "bare.csv"
    bare.write_text("\n".join(f"{float(x)!r}, {float(y)!r}" for x, y in points))
    out_csv = tmp_path / "answers.csv"
    assert main(["query", str(mapped / "map.gpom"), str(bare), "-o", str(out_csv), "-q"]) == 0
    assert out_csv.read_text().splitlines() == lines
    npz = tmp_path / "points.npz"
    np.savez(npz, points=points)
    out_npz = tmp_path / "answers.npz"
    assert main(["query", str(mapped / "map.gpom"), str(npz), "-o", str(out_npz), "-q"]) == 0
    with np.load(out_npz) as answers:
        np.testing.assert_array_equal(answers["probability"], p)
        np.testing.assert_array_equal(answers["variance"], v)
        np.testing.assert_array_equal(answers["points"], points)
        np.testing.assert_array_equal(answers["ternary"], t)
    # Points written out on the command line, mixed with a file, in the order given (after --,
    # as one begins with a minus sign).
    written = [f"{float(x)!r},{float(y)!r}" for x, y in points[2:]]
    assert main(["query", str(mapped / "map.gpom"), "-q", "--", written[0], str(npz), written[1]]) == 0
    mixed = capsys.readouterr().out.splitlines()
    assert mixed[0] == lines[0] and mixed[1:] == [lines[3], *lines[1:], lines[4]]


def test_query_points_of_the_wrong_dimension_or_not_numbers_are_one_line_errors(mapped, tmp_path, capsys):
    three = tmp_path / "xyz.csv"
    three.write_text("x,y,z\n1,2,3\n")
    code = main(["query", str(mapped / "map.gpom"), str(three)])
    err = one_line_error(capsys, code)
    assert f"{three}: points have 3 coordinates per row; {mapped / 'map.gpom'} is a 2-D map: expected x,y" in err
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2\n3,oops\n")
    err = one_line_error(capsys, main(["query", str(mapped / "map.gpom"), str(bad)]))
    assert f"{bad}, line 2: expected numbers separated by commas" in err
    err = one_line_error(capsys, main(["query", str(mapped / "map.gpom"), "1,2,3"]))
    assert f"point '1,2,3' has 3 coordinates; {mapped / 'map.gpom'} is a 2-D map: expected x,y" in err
    assert "is not finite" in one_line_error(capsys, main(["query", str(mapped / "map.gpom"), "1,inf"]))
    err = one_line_error(capsys, main(["query", str(mapped / "map.gpom"), "1;2"]))
    assert "1;2: file not found" in err and "or a point written out as x,y" in err
    with pytest.raises(SystemExit) as usage:
        main(["query", str(mapped / "map.gpom"), str(bad), "-o", str(tmp_path / "answers.txt")])
    assert usage.value.code == 2 and "must end in .csv or .npz" in capsys.readouterr().err


def test_update_adds_the_new_scans_to_the_saved_map(mapped, scans, tmp_path, capsys):
    out = tmp_path / "updated"
    code = main(["update", str(mapped / "map.gpom"), *ARENA, "--range", "40:50", "-o", str(out), "--resolution", "0.1"])
    printed = capsys.readouterr().out
    assert code == 0 and "update       10 scans added to 40" in printed and "scans        50" in printed
    assert manifest(out) == ["map.gpom", "map.npz", "map.pgm", "map.png", "map.yaml"]
    # The library's update of the same saved map, to the bit (tests/test_mapfile.py: that is the
    # batch map of the 60 scans with the saved hyperparameters).
    model = gpomap.load_map(mapped / "map.gpom")
    model.update(scans[40:50])
    expected = model.grid(0.1)
    got = load_grid(out / "map.npz")
    np.testing.assert_array_equal(got.probability, expected.probability)
    np.testing.assert_array_equal(got.variance, expected.variance)
    updated = gpomap.load_map(out / "map.gpom")
    assert updated._n_scans == 50 and updated.hyperparameters_ == model.hyperparameters_
    # Updating in place: the set in the map's own directory, the map file with it, is replaced; scans
    # the map holds already are said to count twice.
    own = tmp_path / "own"
    shutil.copytree(mapped, own)
    assert main(["update", str(own / "map.gpom"), *ARENA, "--range", "37:45", "-o", str(own), "-q"]) == 0
    err = capsys.readouterr().err
    warned = re.search(r"warning: (\d+) of the 8 new scans are already in .*own/map.gpom", err)
    assert warned and int(warned.group(1)) >= 3  # 37, 38 and 39 at least (the simulated robot also stands still)
    assert "laser" not in err and gpomap.load_map(own / "map.gpom")._n_scans == 48
    # New scans of another laser (here the same one thinned to 90 beams) are said to be so.
    laser = (
        f"{scans[0].angles.size} beams over {np.degrees(np.ptp(scans[0].angles)):.1f} degrees, max range {scans[0].max_range:g} m"
    )
    assert (
        main(["update", str(mapped / "map.gpom"), *ARENA, "--range", "50:52", "--beams", "90", "-o", str(tmp_path / "o"), "-q"])
        == 0
    )
    err = capsys.readouterr().err
    assert "warning: the new scans' laser (90 beams over " in err and f"is not the one of {mapped / 'map.gpom'} ({laser})" in err


def test_update_relearn_is_gpomap_map_of_every_scan(mapped, tmp_path):
    relearnt, mapped_all = tmp_path / "relearnt", tmp_path / "all"
    assert main(["update", str(mapped / "map.gpom"), *ARENA, "--range", "40:60", "-o", str(relearnt), "--relearn", "-q"]) == 0
    assert main(["map", *ARENA, "--range", "0:60", "-o", str(mapped_all), "-q"]) == 0
    same_grid_files(relearnt / "map.npz", mapped_all / "map.npz")


def test_stream_saved_and_resumed_ends_as_an_uninterrupted_run(tmp_path, capsys):
    # A map written at the end only (each written map costs a figure): the mapper absorbs scan by scan meanwhile.
    replay = [*ARENA, "--resolution", "0.1", "--rate", "0", "--every", "1000", "--warmup", "10", "-q"]
    whole, first, rest = tmp_path / "whole", tmp_path / "first", tmp_path / "rest"
    states = {name: tmp_path / f"{name}.gpom" for name in ("whole", "first", "rest")}
    assert main(["stream", *replay, "--range", "0:24", "-o", str(whole), "--save-state", str(states["whole"])]) == 0
    # The same replay stopped after 16 scans (its state saved when the log ended), then resumed.
    assert main(["stream", *replay, "--range", "0:16", "-o", str(first), "--save-state", str(states["first"])]) == 0
    capsys.readouterr()
    resume = ["--resume", str(states["first"]), "--save-state", str(states["rest"])]
    assert main(["stream", *replay, "--range", "0:24", "-o", str(rest), *resume]) == 0
    printed = capsys.readouterr().out
    assert (
        f"scans        24 of 24 (16 from {states['first']})" in printed and f"state        {states['rest']}: 24 scans" in printed
    )
    # The last map (gpomap map's of the 24 scans) and the streaming mapper before it, to the bit.
    same_grid_files(whole / "map.npz", rest / "map.npz")
    from gpomap.io.mapfile import load_streaming_state

    a, b = load_streaming_state(states["whole"]), load_streaming_state(states["rest"])
    assert a.n_scans_ == b.n_scans_ == 24 and a.version_ == b.version_
    points = np.random.default_rng(0).uniform(-1.5, 3.5, size=(4000, 2))
    pa, va = a.predict_proba(points, return_var=True, refresh=False)
    pb, vb = b.predict_proba(points, return_var=True, refresh=False)
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(va, vb)
    # Another log, or other settings, are refused before any work.
    code = main(
        ["stream", *replay, "--range", "0:24", "--beams", "90", "-o", str(tmp_path / "x"), "--resume", str(states["first"])]
    )
    assert "scan 0 of" in one_line_error(capsys, code)
    code = main(
        ["stream", *replay, "--range", "0:24", "-o", str(tmp_path / "x"), "--resume", str(states["first"]), "--max-cell", "1"]
    )
    assert "the state was saved with --max-cell its default; this command line gives 1.0" in one_line_error(capsys, code)


@pytest.fixture(scope="module")
def voxel_map(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("room3d")
    for i, c in enumerate(world3d.lidar_clouds(world3d.ORIGINS[:3], n_rays=400, max_range=4.0)):
        write_pcd(folder / f"scan_{i}.pcd", c, beyond=6.0)
    out = folder / "map"
    assert main(["map", str(folder), "-o", str(out), "--max-range", "4", *FAST]) == 0
    return out


def test_a_3d_map_is_rendered_and_queried(voxel_map, tmp_path, capsys):
    assert "map.gpom" in manifest(voxel_map)
    model = gpomap.load_map(voxel_map / "map.gpom")
    assert model.dim_ == 3
    out = tmp_path / "render"
    code = main(["render", str(voxel_map / "map.gpom"), "-o", str(out), "--resolution", "0.2", "--z-range", "0.5,1.5", "-q"])
    assert code == 0 and manifest(out) == ["map-3d.png", "map-slices.png", "map.bt", "map.npz", "map.ply"]
    # x and y: the data's box grown by the default's margin of cells; z: --z-range as given.
    lo, hi = model.bounds_
    pad = EXTENT_MARGIN_CELLS * 0.2
    expected = model.grid(0.2, (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad, 0.5, 1.5))
    got = load_voxels(out / "map.npz")
    assert got.spec == expected.spec
    np.testing.assert_array_equal(got.probability, expected.probability)
    capsys.readouterr()
    points = tmp_path / "xyz.csv"
    points.write_text("1,1,1\n3.9,1.9,1.0\n")
    assert main(["query", str(voxel_map / "map.gpom"), str(points), "-q"]) == 0
    table = np.loadtxt(capsys.readouterr().out.splitlines()[1:], delimiter=",")
    p = model.predict_proba(np.array([[1, 1, 1], [3.9, 1.9, 1.0]]))
    np.testing.assert_array_equal(table[:, 3], p)
    assert table[1, 3] > 0.5 > table[0, 3]  # in the pillar; in the open room
    # Free in the open room; inside the pillar, where no ray went, unknown whatever the GP says
    # (the written voxel map's rule, and OctoMap's: only voxels rays reached are known).
    np.testing.assert_array_equal(table[:, 5], [0, -1])
    flat = tmp_path / "xy.csv"
    flat.write_text("1,1\n")
    err = one_line_error(capsys, main(["query", str(voxel_map / "map.gpom"), str(flat)]))
    assert "is a 3-D map: expected x,y,z" in err


@pytest.mark.parametrize("command", ["render", "query", "update"])
def test_bad_map_files_are_one_line_errors(mapped, tmp_path, capsys, command):
    points = tmp_path / "p.csv"
    points.write_text("0,0\n")
    cut = tmp_path / "cut.gpom"
    cut.write_bytes((mapped / "map.gpom").read_bytes()[:5000])
    other = tmp_path / "v9.gpom"
    shutil.copy(mapped / "map.gpom", other)
    _rewrite_header(other, lambda h: h.update(version=9))
    cases = [
        (cut, "truncated or corrupt"),
        (other, "map file format version 9"),
        (mapped / "map.npz", "a written grid: gpomap.io.npz.load_map reads it"),
        (points, "not a gpomap map file: a file starting with b'0,0"),
    ]
    for path, message in cases:
        tail = {"render": ["-o", str(tmp_path / "o")], "query": [str(points)], "update": [*ARENA, "-o", str(tmp_path / "o")]}
        err = one_line_error(capsys, main([command, str(path), *tail[command]]))
        assert f"gpomap: error: {path}: " in err and message in err, err
        assert "expected" in err or f"this gpomap reads version {VERSION}" in err, err
    assert not (tmp_path / "o").exists()


def test_info_describes_a_fitted_map_from_its_header(mapped, capsys):
    path = mapped / "map.gpom"
    assert main(["info", str(path)]) == 0
    lines = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    model = gpomap.load_map(path)
    assert lines["format"] == f"gpomap fitted map (map.gpom, version {VERSION})" and lines["kind"] == "map"
    assert lines["model"] == "AreaGPOM, 2-D" and lines["n_scans"] == "40" and lines["scans_kept"] == "True"
    assert int(lines["n_cells"]) == model.n_inputs_ and int(lines["n_tiles"]) == len(model.tiles_)
    (x0, y0), (x1, y1) = model.bounds_
    assert lines["extent"] == f"{x0:.3f}, {x1:.3f}, {y0:.3f}, {y1:.3f}"
    assert lines["ray_counts"] == "on 0.05 m cells" and lines["thresholds"] == "0.196, 0.500"
    said = dict(pair.rsplit(" ", 1) for pair in lines["hyperparameters"].split(", "))
    assert {k: float(v) for k, v in said.items()} == pytest.approx(model.hyperparameters_, rel=5e-4)
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_cells"] == model.n_inputs_


def test_info_on_a_map_file_it_cannot_read_is_one_line(mapped, tmp_path, capsys):
    old = tmp_path / "old.gpom"
    shutil.copy(mapped / "map.gpom", old)
    _rewrite_header(old, lambda h: h.update(version=VERSION - 1))
    assert f"map file format version {VERSION - 1}" in one_line_error(capsys, main(["info", str(old)]))
    cut = tmp_path / "cut.gpom"
    cut.write_bytes((mapped / "map.gpom").read_bytes()[:5000])
    assert "truncated or corrupt" in one_line_error(capsys, main(["info", str(cut)]))


def test_info_counts_a_written_grids_classes(tmp_path, capsys):
    from gpomap.grid import GridSpec, OccupancyMap
    from gpomap.io.npz import save_map

    # 4 x 5 cells of 0.1 m from (1, -2): 3 occupied (p > 0.5), 15 free (p < 0.196), 2 unknown.
    p = np.full((4, 5), 0.05)
    p[0, :3] = 0.9
    p[3, 3:] = 0.3
    save_map(OccupancyMap(GridSpec((1.0, -2.0), 0.1, (4, 5)), p, thresholds=(0.196, 0.5)), tmp_path / "map.npz")
    assert main(["info", str(tmp_path / "map.npz")]) == 0
    lines = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert lines["format"] == "gpomap written grid (map.npz)" and lines["cells"] == "5 x 4"
    assert lines["extent"] == "1.000, 1.500, -2.000, -1.600"
    assert (lines["free"], lines["occupied"], lines["unknown"]) == ("15 (75.0 %)", "3 (15.0 %)", "2 (10.0 %)")
    assert lines["probability"] == "0.050, 0.900" and lines["thresholds"] == "0.196, 0.500"
    assert lines["variance"] == "False" and lines["robot_path"] == "none"
    # An origin a hair below zero (arithmetic on the data's box) prints as 0, not -0.
    save_map(OccupancyMap(GridSpec((-1e-13, -0.5), 0.1, (4, 5)), p), tmp_path / "map.npz")
    assert main(["info", str(tmp_path / "map.npz")]) == 0
    lines = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert lines["extent"] == "0.000, 0.500, -0.500, -0.100"


def test_info_counts_a_written_voxel_maps_classes(tmp_path, capsys):
    from gpomap.io.voxel_outputs import save_voxels
    from gpomap.voxels import VoxelMap, VoxelSpec

    # 2 x 3 x 4 voxels of 0.25 m from (0, 0, -1): 6 occupied, 18 free, none unknown.
    p = np.full((2, 3, 4), 0.1)
    p[1, :, :2] = 0.8
    save_voxels(VoxelMap(VoxelSpec((0.0, 0.0, -1.0), 0.25, (2, 3, 4)), p), tmp_path / "map.npz")
    assert main(["info", str(tmp_path / "map.npz")]) == 0
    lines = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert lines["format"] == "gpomap written voxel map (map.npz)" and lines["cells"] == "4 x 3 x 2"
    assert lines["extent"] == "0.000, 1.000, 0.000, 0.750, -1.000, -0.500"
    assert (lines["free"], lines["occupied"], lines["unknown"]) == ("18 (75.0 %)", "6 (25.0 %)", "0 (0.0 %)")
