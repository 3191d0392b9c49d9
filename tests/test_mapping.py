"""The MSK-GPOM estimator end to end on the simulated room, whose true map is known."""

import numpy as np
import pytest

from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.grid import FREE, OCCUPIED
from gpomap.mapping import AreaGPOM
from gpomap.metrics import roc_auc
from gpomap.observations import observations_from_scans
from gpomap.scans import Scan
from gpomap.simulate import paper_room, paper_room_scans, simulate_scans


@pytest.fixture(scope="module")
def room():
    world, poses = paper_room()
    rng = np.random.default_rng(7)
    # Held-out data: other poses (the training path jittered), more beams; never trained on.
    test_poses = poses.copy()
    test_poses[:, :2] += rng.normal(0, 0.3, (len(poses), 2))
    test_poses = test_poses[world.distance_to_walls(test_poses[:, :2]) > 0.5]
    test = observations_from_scans(simulate_scans(world, test_poses, 90), free_step=0.2)
    # 1,000 held-out hits of the 2,790 and as many free points: the AUC's standard error is then
    # about 0.002, against a margin of 0.04 to the bound.
    occ = rng.choice(np.flatnonzero(test.occupied), 1000, replace=False)
    free = rng.choice(np.flatnonzero(~test.occupied), occ.size, replace=False)
    sel = np.concatenate([occ, free])
    return world, paper_room_scans(), test.points[sel], test.occupied[sel]


@pytest.fixture(scope="module", params=["se", "matern32"])
def fitted(request, room):
    _, scans, _, _ = room
    return AreaGPOM(kernel=request.param).fit(scans)


def test_held_out_auc_is_high(fitted, room):
    _, _, points, labels = room
    # Measured 0.996 / 0.996 (SE / Matern 3/2) with the defaults; chance is 0.5, the paper 0.93-0.94.
    assert roc_auc(labels, fitted.predict_proba(points)) > 0.95


def test_map_is_right_at_the_walls_and_in_open_space(fitted, room):
    world, scans, _, _ = room
    rng = np.random.default_rng(3)
    walls = world.walls
    t = rng.random(400)
    seg = walls[rng.integers(len(walls), size=400)]
    on_wall = seg[:, :2] + t[:, None] * (seg[:, 2:] - seg[:, :2])
    # Only wall points the robot saw: near some training hit.
    hits = np.concatenate([s.hits() for s in scans])
    seen = np.min(np.linalg.norm(on_wall[:, None] - hits[None], axis=2), axis=1) < 0.25
    p_wall = fitted.predict_proba(on_wall[seen])
    # Open floor at least a metre from every wall, inside the room.
    grid = rng.uniform([0.5, 0.5], [19.5, 15.5], (2000, 2))
    open_floor = grid[(world.distance_to_walls(grid) > 1.0) & ~world.inside_obstacle(grid)]
    p_floor = fitted.predict_proba(open_floor)
    assert np.mean(p_floor < 0.5) > 0.95
    # Walls rank above open floor almost without exception (measured 0.999 / 1.000 for SE /
    # Matern 3/2), and most seen wall points read occupied (measured 64 % / 79 %: SE's squash
    # leans free right at walls, where free cells lie 0.1 m away).
    labels = np.r_[np.ones(p_wall.size, bool), np.zeros(p_floor.size, bool)]
    assert roc_auc(labels, np.r_[p_wall, p_floor]) > 0.99
    assert np.mean(p_wall > 0.5) > 0.55


def test_grid_and_ternary(fitted):
    m = fitted.grid(0.5)
    # The room's 20 x 16 m box and two cells round it: its walls on the box's edges are drawn whole.
    assert m.grid.shape == (36, 44) and m.grid.extent == (-1.0, 21.0, -1.0, 17.0)
    assert np.all((m.probability >= 0) & (m.probability <= 1))
    assert np.all(m.variance >= 0)
    assert (m.ternary == FREE).sum() > (m.ternary == OCCUPIED).sum() > 0
    # The grid is the GP at the cell centres updated by each grid cell's own ray counts.
    # Cells with counts (those without any take the GP's probability for unseen space).
    hits, misses, _ = fitted.evidence_.grid_counts(m.grid)
    counted = np.flatnonzero((hits + misses).ravel() > 0)[:50]
    p, v = fitted.predict_proba_gp(m.grid.centres()[counted], return_var=True)
    fused = fitted.evidence_.calibration(p, hits.ravel()[counted], misses.ravel()[counted])
    np.testing.assert_allclose(fused, m.probability.ravel()[counted], atol=0.03)
    _, var = fitted.predict(m.grid.centres()[counted], return_var=True)
    np.testing.assert_allclose(var, v, rtol=0.05)
    summary = fitted.summary()
    assert summary["n_cells"] == fitted.n_inputs_ > 100
    assert set(summary["hyperparameters"]) == {
        "variance",
        "length_scale",
        "noise",
        "alpha",
        "beta",
        "variance_scale",
    }
    assert {"observations", "cells", "hyperparameters", "tile_fits", "prediction"} <= set(summary["timings"])


def test_fixed_hyperparameters_are_kept():
    # A third of the room's scans: the hyperparameters are kept whatever the data.
    m = AreaGPOM(kernel="se", length_scale=0.7, noise=0.05, optimise=False).fit(paper_room_scans()[:10])
    assert m.hyperparameters_["length_scale"] == 0.7 and m.hyperparameters_["noise"] == 0.05
    assert m.hyper_source_["evaluations"] == 0


def test_free_clearance_applies_to_scans_not_to_given_points():
    # A third of the room's scans still have beams grazing walls, whose free points get cleared.
    scans = paper_room_scans()[:10]
    m = AreaGPOM(kernel="se", length_scale=0.7, optimise=False, free_clearance=0.3)
    cleared = m.fit(scans).summary()["n_free_points_cleared"]
    _, occupied = m.training_points()
    given = observations_from_scans(scans, free_step=0.2, no_return_cap=10.0)
    assert cleared > 0 and np.sum(~occupied) + cleared == given.n_free
    _, occupied = m.fit(given).training_points()
    assert np.sum(~occupied) == given.n_free and m.summary()["n_free_points_cleared"] == 0


def test_errors_are_clear():
    with pytest.raises(NotFittedError, match="call fit"):
        AreaGPOM().predict_proba(np.zeros((1, 2)))
    only_free = [Scan([0, 0, 0], [0.0, 1.0], [5.0, 5.0], 5.0)]
    with pytest.raises(EmptyDataError, match="need both free and occupied"):
        AreaGPOM().fit(only_free)
    with pytest.raises(ValueError, match="shape"):
        AreaGPOM(kernel="se", optimise=False).fit(paper_room_scans()[:4]).predict(np.zeros(3))


def test_get_and_set_params():
    m = AreaGPOM(kernel="se", min_cell=0.3)
    assert m.get_params()["min_cell"] == 0.3
    assert m.set_params(max_cell=2.0).max_cell == 2.0
    with pytest.raises(ValueError, match="unknown parameter"):
        m.set_params(bogus=1)


@pytest.fixture(scope="module")
def room3d():
    from tests.world3d import ORIGINS, lidar_clouds

    train = lidar_clouds(ORIGINS, n_rays=300)
    # Held out: other sensor positions, other rays; the protocol's points (hits, free every 0.1 m).
    test = observations_from_scans(lidar_clouds(ORIGINS[:4] + np.array([0.4, -0.3, 0.2]), n_rays=200, seed=9), 0.1, 0.1)
    rng = np.random.default_rng(3)
    occ = np.flatnonzero(test.occupied)
    free = rng.choice(np.flatnonzero(~test.occupied), occ.size, replace=False)
    sel = np.concatenate([occ, free])
    return AreaGPOM(kernel="se").fit(train), test.points[sel], test.occupied[sel]


def test_3d_map_from_clouds(room3d):
    from gpomap.voxels import VoxelMap
    from tests.world3d import occupied

    model, points, labels = room3d
    assert model.dim_ == 3 and model.cell_boxes()[0].shape[1] == 3 and model.path_.shape == (6, 3)
    assert model.evidence_ is not None and model.evidence_.lattice.resolution == 0.1
    p, var = model.predict_proba(points, return_var=True)
    assert p.shape == var.shape == (len(points),)
    # Measured 0.990 (the GP alone 0.989) with these 6 x 300 rays.
    assert roc_auc(labels, p) > 0.95
    assert roc_auc(labels, model.predict_proba_gp(points)) > 0.95
    # Far from every observation: the GP's prior, unknown.
    assert model.predict_proba(np.array([[100.0, 100.0, 100.0]]))[0] == pytest.approx(0.5, abs=1e-9)
    vm = model.grid(0.25)
    assert isinstance(vm, VoxelMap) and vm.probability.shape == vm.spec.shape == vm.variance.shape
    # The voxel map against the true geometry (surfaces a voxel thick), on the room and its
    # walls (not the space beyond them, nor the pillar's core): measured 0.996.
    centres = vm.spec.centres()
    near = ~occupied(centres, thickness=-0.3)
    truth = occupied(centres, thickness=0.25)
    assert roc_auc(truth[near], vm.probability.ravel()[near]) > 0.95
    with pytest.raises(ValueError, match=r"shape \(m, 3\)"):
        model.predict_proba(np.zeros((2, 2)))
