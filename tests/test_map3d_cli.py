"""gpomap map and gpomap convert on 3-D inputs, in-process: the output set, its files read back, bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData

from gpomap.apps.map3d import is_cloud_input, select_clouds
from gpomap.cli import main
from gpomap.cli.map import default_model
from gpomap.clouds import CloudScan
from gpomap.grid import FREE, OCCUPIED
from gpomap.io.octomap import read_octree, write_octree
from gpomap.io.voxel_outputs import load_voxels
from gpomap.voxels import VoxelMap, VoxelSpec
from tests import world3d

OUTPUTS = ["map-3d.png", "map-slices.png", "map.bt", "map.npz", "map.ply"]
FAST = ["--kernel", "se", "--min-cell", "1.0", "--max-cell", "1.0", "--resolution", "0.25", "-q"]


def write_pcd(path, cloud: CloudScan, beyond: float) -> None:
    """An ASCII PCD of `cloud` with its origin in VIEWPOINT; no-return rays pushed out to `beyond` metres."""
    pts = cloud.points.copy()
    miss = ~np.asarray(cloud.hit, dtype=bool)
    d = pts[miss] - cloud.origin
    pts[miss] = cloud.origin + d / np.linalg.norm(d, axis=1, keepdims=True) * beyond
    o = cloud.origin
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT {o[0]} {o[1]} {o[2]} 1 0 0 0\nPOINTS {len(pts)}\nDATA ascii\n"
    )
    path.write_text(header + "\n".join(f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in pts) + "\n")


@pytest.fixture(scope="module")
def room_pcds(tmp_path_factory):
    """Three lidar scans of the test room (6 x 4 x 2.5 m with a pillar) as a directory of PCD files."""
    folder = tmp_path_factory.mktemp("room")
    for i, c in enumerate(world3d.lidar_clouds(world3d.ORIGINS[:3], n_rays=400, max_range=4.0)):
        write_pcd(folder / f"scan_{i}.pcd", c, beyond=6.0)
    return folder


def test_map_writes_the_3d_output_set_that_loads_back(room_pcds, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["map", str(room_pcds), "-o", str(out), "--max-range", "4", "--slices", "0.5,1.5", *FAST])
    printed = capsys.readouterr().out
    assert code == 0
    # gpomap map writes the fitted map too (map.gpom, gpomap.io.mapfile); gpomap convert does not.
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == sorted([*OUTPUTS, "map.gpom"])
    assert "scans        3" in printed and "voxels" in printed and "hyperparams" in printed
    assert "unseen space the GP's own variance (voxel maps do not fit it)" in printed
    # Not searched, so not listed with the learnt hyperparameters.
    hyper_line = next(line for line in printed.splitlines() if line.startswith("hyperparams"))
    assert "variance_scale" not in hyper_line and "length_scale" in hyper_line
    for name in [*OUTPUTS, "map.gpom"]:
        assert f"wrote        {out / name}" in printed
    m = load_voxels(out / "map.npz")
    assert m.spec.resolution == 0.25 and m.variance is not None
    # The written map against the room: voxels deep inside the free space are free, the pillar occupied.
    centres = m.spec.centres()
    t = m.ternary.reshape(-1)
    inside = world3d.occupied(centres, thickness=0.0) == 0
    clear = inside & ~world3d.occupied(centres, thickness=0.5)
    assert np.mean(t[clear] == FREE) > 0.8
    # The OctoMap file holds the known voxels with the npz's labels.
    tree = read_octree(out / "map.bt")
    assert tree.resolution == pytest.approx(0.25)
    label = m.lookup(tree.centres) > 0.5
    assert tree.n_leaves > 0 and np.mean(label == tree.occupied) > 0.99
    seen_occupied = ((t == OCCUPIED) & m.seen.reshape(-1)).sum()  # map.bt holds the voxels rays went to
    assert tree.occupied.sum() == pytest.approx(seen_occupied, rel=0.5)  # pruning merges some
    # The ternary layer, as map.bt, calls occupied only where rays went; the GP's guess behind the
    # walls is counted apart in the summary.
    guessed = int(((m.probability > m.thresholds[1]) & ~m.seen).sum())
    assert (t == OCCUPIED).sum() == seen_occupied and guessed > 0
    assert f"{seen_occupied} occupied, " in printed and f"({guessed} of them above the occupied threshold" in printed
    mesh = PlyData.read(str(out / "map.ply"))
    assert len(mesh["vertex"]) > 0 and len(mesh["face"]) > 0


def test_default_model_is_the_commands(room_pcds):
    clouds = select_clouds(world3d.lidar_clouds(world3d.ORIGINS[:2], n_rays=100), n_rays=50)
    assert [c.n_points for c in clouds] == [50, 50]
    model, resolution = default_model()
    # The command's engine with its options: 3-D cells, tiles of the default size, every core.
    assert resolution == 0.1 and type(model).__name__ == "AreaGPOM"
    assert (model.max_cell, model.tile_size, model.n_workers) == (None, None, None)  # None: the 3-D default
    assert model.base.cell_sides(3) == (1.0, 1.0) and model.base.cell_sides(2) == (0.5, 0.5)
    assert default_model(workers=1, tile_size=4.0)[0].get_params()["tile_size"] == 4.0
    assert is_cloud_input(room_pcds)


def test_the_library_applies_the_voxel_profile_as_the_command_does() -> None:
    # AreaGPOM() on clouds builds the map `gpomap map CLOUDS` builds: the same cells, bit for bit
    # the same probabilities; a planar profile's 0.5 m cells would give three times as many.
    from gpomap.mapping import AreaGPOM

    clouds = select_clouds(world3d.lidar_clouds(world3d.ORIGINS[:2], n_rays=300), n_rays=150)
    command, _ = default_model(workers=1)
    library = AreaGPOM(n_workers=1)
    command.fit(clouds)
    library.fit(clouds)
    q = np.random.default_rng(0).uniform(*command.bounds_, (500, 3))
    assert library.n_inputs_ == command.n_inputs_
    np.testing.assert_array_equal(library.predict_proba(q), command.predict_proba(q))
    planar_cells = AreaGPOM(n_workers=1, min_cell=0.5, max_cell=0.5).fit(clouds).n_inputs_
    assert planar_cells > 2 * library.n_inputs_


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--chunk-scans", "2"], "--chunk-scans is for 2-D inputs"),
        (["--stride", "2"], "--stride: not an option of pcd-directory input"),
        (["--range", "5:9"], "--range 5:9 selects no scans from"),
        (["--z-range", "9,10", "--memory-limit", "1e-6"], "voxel grid"),
    ],
)
def test_bad_3d_options_are_one_line_errors(room_pcds, tmp_path, capsys, extra, message):
    code = main(["map", str(room_pcds), "-o", str(tmp_path / "o"), *FAST, *extra])
    err = capsys.readouterr().err
    assert code == 1 and message in err and err.startswith("gpomap: error:"), err
    assert not (tmp_path / "o" / "map.npz").exists()


def test_bad_3d_inputs(tmp_path, capsys):
    ply = tmp_path / "scan.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n"
    )
    assert main(["map", str(ply), "-o", str(tmp_path / "o"), "-q"]) == 1
    assert "PLY files carry no sensor pose" in capsys.readouterr().err
    bad = tmp_path / "bad.pcd"
    bad.write_text(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n"
    )
    assert main(["map", str(bad), "-o", str(tmp_path / "o"), "-q"]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "FIELDS" in err and "no 'z'" in err
    # A 2-D log given a 3-D option: refused, not ignored.
    log = tmp_path / "a.log"
    log.write_text("FLASER 3 1.0 1.0 1.0 0 0 0 0 0 0 1.0 host 1.0\n")
    assert main(["map", str(log), "-o", str(tmp_path / "o"), "--poses", str(ply), "-q"]) == 1
    assert "--poses is for 3-D inputs" in capsys.readouterr().err


def _slab_octree(path) -> None:
    """A 2 x 2 x 1 m box of 0.1 m voxels: a wall at x 1.2..1.4 (occupied), free on both sides."""
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (10, 20, 20))
    x = spec.centres()[:, 0].reshape(spec.shape)
    p = np.where((x > 1.2) & (x < 1.4), 0.97, 0.12)
    write_octree(VoxelMap(spec, p), path)


def test_convert_octree(tmp_path, capsys):
    bt = tmp_path / "slab.bt"
    _slab_octree(bt)
    out = tmp_path / "conv"
    code = main(["convert", str(bt), "-o", str(out), "--resolution", "0.05", "--z-range", "0.2,0.8", "-q"])
    printed = capsys.readouterr().out
    assert code == 0
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == OUTPUTS
    # Every occupied voxel keeps its label; the free voxels touching the wall may blur (as in 2-D).
    agreement = float(printed.split("agreement    ")[1].split(" %")[0])
    assert agreement >= 90.0 and "occupied 100.00 %" in printed and "AUC 1.0000" in printed, printed
    m = load_voxels(out / "map.npz")
    assert m.spec.resolution == 0.05 and m.spec.lower[2] == pytest.approx(0.2) and m.spec.upper[2] == pytest.approx(0.8)
    # The wall is where the octree has it, to a voxel of the source.
    wall = m.lookup(np.array([[1.3, 1.0, 0.5], [0.5, 1.0, 0.5], [1.8, 1.0, 0.5]]))
    assert wall[0] > 0.66 and wall[1] < 0.33 and wall[2] < 0.33
    code = main(["convert", str(bt), "-o", str(out), "--max-cells", "10", "-q"])
    assert code == 1 and "more than one GP holds (10)" in capsys.readouterr().err
    truncated = tmp_path / "cut.bt"
    truncated.write_bytes(bt.read_bytes()[:-20])
    assert main(["convert", str(truncated), "-o", str(tmp_path / "c2"), "-q"]) == 1
    assert "corrupt tree" in capsys.readouterr().err


def test_info_reads_depth_frames_as_map_does_and_warns_of_depths_in_other_units(capsys):
    from pathlib import Path

    frames = Path(__file__).resolve().parents[2] / "shared" / "data" / "3dmatch"
    if not frames.exists():
        pytest.skip("shared 3DMatch frames not present")
    assert main(["info", str(frames), "--stride", "8"]) == 0
    out, err = capsys.readouterr()
    assert "points_per_scan 4800" in out  # 640 x 480 pixels, every 8th along both axes
    assert "warning" not in err
    # Read as if in units five times smaller (TUM's 5000 a metre read as millimetres, reversed): a room 20 m deep.
    assert main(["info", str(frames), "--stride", "8", "--depth-scale", "200"]) == 0
    err = capsys.readouterr().err
    assert "beyond a depth camera's reach" in err and "--depth-scale" in err
    # A 2-D input refuses them, naming the option.
    assert main(["info", str(frames.parent / "intel" / "intel-corrected.log.gz"), "--stride", "3"]) == 1
    assert "--stride is for 3-D inputs" in capsys.readouterr().err


def test_evaluate_on_3d_scans_says_in_one_line_it_scores_planar_maps(capsys):
    from pathlib import Path

    clouds = Path(__file__).resolve().parents[2] / "shared" / "data" / "la3dm-sim" / "sim_structured"
    if not clouds.exists():
        pytest.skip("shared la3dm data not present")
    assert main(["evaluate", str(clouds), "--method", "msk"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gpomap evaluate scores planar maps only" in err[0] and "quality3d.py" in err[0]


@pytest.mark.parametrize("merged", [False, True])
def test_the_summary_counts_the_free_samples_merged_points_stand_for(room_pcds, tmp_path, capsys, monkeypatch, merged):
    # Every free sample of the scans (made again here, none merged) is counted once, whether the
    # points stand for one each or were merged by cube.
    import gpomap.observations as observations
    from gpomap.apps.map3d import read_selected_clouds

    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0 if merged else observations.MERGE_MIN_SAMPLES)
    assert main(["map", str(room_pcds), "-o", str(tmp_path / "out"), "--max-range", "4", *FAST]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("points "))
    clouds = read_selected_clouds(str(room_pcds), {"poses": None, "max_range": 4.0})
    samples = observations.observations_from_scans(clouds, 0.2).n_free
    if merged:
        n_free = int(line.split()[1])
        assert n_free < samples and f"{n_free} free (standing for {samples} samples, merged by cube)" in line
    else:
        assert line.startswith(f"points       {samples} free, ") and "standing for" not in line
