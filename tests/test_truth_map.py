"""A ROS map as the true map: ``Truth.from_rosmap`` and ``gpomap evaluate --truth``."""

import json

import numpy as np
import pytest

from gpomap.cli import main
from gpomap.evaluation import Truth, evaluate
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.rosmap import read_rosmap, write_rosmap
from gpomap.simulate import paper_room, simulate_scans


def _write_truth(truth: Truth, path, unknown=None):
    """`truth` as a trinary ROS map (unknown where `unknown`, shape of the grid)."""
    p = np.where(truth.occupied, 1.0, 0.0)
    if unknown is not None:
        p[unknown] = np.nan
    write_rosmap(OccupancyMap(truth.grid, p), path)
    return path


def test_a_rosmap_at_its_own_resolution_is_the_same_truth(tmp_path):
    world = paper_room()[0]
    truth = Truth.from_world(world, 0.05)
    unknown = np.zeros(truth.grid.shape, bool)
    unknown[:10, :20] = True  # a corner the map does not know
    back = Truth.from_rosmap(read_rosmap(_write_truth(truth, tmp_path / "room.yaml", unknown)), 0.05)
    assert back.grid == truth.grid
    np.testing.assert_array_equal(back.known, ~unknown)
    np.testing.assert_array_equal(back.occupied, truth.occupied & ~unknown)


def test_a_coarser_cell_is_occupied_if_any_known_pixel_in_it_is(tmp_path):
    # 4 x 4 pixels of 0.1 m (rows from the lowest y), read at 0.2 m: 2 x 2 cells of 4 pixels each.
    occupied = np.zeros((4, 4), bool)
    occupied[0, 1] = True  # lower-left cell
    unknown = np.zeros((4, 4), bool)
    unknown[2:, 2:] = True  # the upper-right cell: all four unknown
    unknown[3, 0] = True  # one unknown pixel of the upper-left cell
    grid = GridSpec((1.0, 2.0), 0.1, (4, 4))
    back = Truth.from_rosmap(read_rosmap(_write_truth(Truth(grid, occupied), tmp_path / "m.yaml", unknown)), 0.2)
    assert back.grid.shape == (2, 2) and back.grid.origin == pytest.approx((1.0, 2.0))
    np.testing.assert_array_equal(back.occupied, [[True, False], [False, False]])
    np.testing.assert_array_equal(back.known, [[True, True], [True, False]])


def test_agreement_counts_hits_near_walls():
    grid = GridSpec((0.0, 0.0), 0.05, (20, 20))
    occupied = np.zeros(grid.shape, bool)
    occupied[:, 10] = True  # a wall at x = 0.50-0.55
    truth = Truth(grid, occupied)
    hits = np.array([[0.52, 0.3], [0.43, 0.3], [0.62, 0.5], [0.2, 0.5], [5.0, 5.0]])
    # Cells 0, 2 and 2 columns from the wall's are within 0.1 m; 6 columns and outside the grid are not.
    assert truth.agreement(hits) == pytest.approx(3 / 5)


@pytest.fixture
def room_log(tmp_path):
    """The paper's room seen by a 181-beam, 180-degree laser along its 31 poses, as a CARMEN log."""
    world, poses = paper_room()
    scans = simulate_scans(world, poses, 181, fov=np.pi, noise_std=0.0, seed=0)
    lines = []
    for k, s in enumerate(scans):
        x, y, t = s.pose
        ranges = " ".join(f"{r:.4f}" for r in s.ranges)
        lines.append(f"FLASER 181 {ranges} {x} {y} {t} {x} {y} {t} {k + 1.0} host {k + 1.0}")
    path = tmp_path / "room.log"
    path.write_text("\n".join(lines) + "\n")
    return path, world


def test_evaluate_truth_scores_against_the_map(tmp_path, room_log, capsys):
    log, world = room_log
    truth = Truth.from_world(world, 0.05)
    yaml = _write_truth(truth, tmp_path / "truth.yaml")
    assert main(["evaluate", str(log), "--truth", str(yaml), "--method", "ogm", "--json"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert "of the log's hits lie within 0.1 m of an occupied cell" in captured.err
    assert "warning" not in captured.err
    # The same as scoring against the room's geometry directly.
    from gpomap.io import read_scans

    direct = evaluate(read_scans(log), method="ogm", truth=truth)
    for key in ("auc", "iou", "observed_iou", "n_cells", "n_occupied_cells"):
        assert out["truth"]["points"][key] == pytest.approx(direct["truth"]["points"][key])


def test_evaluate_truth_in_another_frame_is_warned_of(tmp_path, room_log, capsys):
    log, world = room_log
    truth = Truth.from_world(world, 0.05)
    moved = Truth(GridSpec((truth.grid.origin[0] + 7.0, truth.grid.origin[1]), 0.05, truth.grid.shape), truth.occupied)
    yaml = _write_truth(moved, tmp_path / "moved.yaml")
    assert main(["evaluate", str(log), "--truth", str(yaml), "--method", "ogm", "--no-grid"]) == 0
    assert "same frame" in capsys.readouterr().err


def test_evaluate_truth_refusals(tmp_path, room_log, capsys):
    log, world = room_log
    truth = Truth.from_world(world, 0.05)
    assert main(["evaluate", "--demo", "--truth", str(_write_truth(truth, tmp_path / "t.yaml"))]) == 1
    assert "drop --truth" in capsys.readouterr().err
    empty = Truth(truth.grid, np.zeros(truth.grid.shape, bool))
    yaml = _write_truth(empty, tmp_path / "empty.yaml")
    assert main(["evaluate", str(log), "--truth", str(yaml), "--method", "ogm"]) == 1
    err = capsys.readouterr().err
    assert "empty.yaml" in err and "0 occupied" in err
    assert main(["evaluate", str(log), "--truth", str(tmp_path / "missing.yaml")]) == 1
    assert "missing.yaml" in capsys.readouterr().err
