import numpy as np
import pytest

import gpomap.baselines.ogm as ogm
import gpomap.raycast as raycast
from gpomap.baselines.ogm import L_HIT, L_MAX, L_MIN, L_MISS, OccupancyGridMapper
from gpomap.clouds import CloudScan
from gpomap.errors import NotFittedError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.raycast import traverse
from gpomap.scans import Scan
from gpomap.simulate import World, paper_room_scans, simulate_scans
from gpomap.voxels import VoxelMap, VoxelSpec
from tests.world3d import ORIGINS, lidar_clouds
from tests.world3d import occupied as room_occupied


def brute_force_cells(grid, start, end, n=300_001):
    # Fine enough to catch the small corner clips of these beams (checked at 2e6 samples too).
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = start + t * (end - start)
    *idx, inside = grid.index_of(pts)
    # Distinct cells in numpy first (flat indices): a Python set of every sample's tuple was half the time.
    flat = np.unique(np.ravel_multi_index(tuple(i[inside] for i in idx), grid.shape))
    return set(zip(*(i.tolist() for i in np.unravel_index(flat, grid.shape))))


# The same traversal on a 2-D grid and on a 3-D voxel lattice (arrays indexed x last in both).
GRIDS = {
    2: GridSpec((-1.0, -2.0), 0.25, (40, 40)),
    3: VoxelSpec((-1.0, -2.0, 0.0), 0.25, (12, 40, 40)),
}


@pytest.mark.parametrize("dim", [2, 3])
def test_traversal_matches_fine_sampling_on_random_beams(dim):
    grid = GRIDS[dim]
    rng = np.random.default_rng(42)
    starts = rng.uniform([-1, -2, 0][:dim], [9, 8, 3][:dim], size=(40, dim))
    ends = rng.uniform([-3, -4, -1][:dim], [11, 10, 4][:dim], size=(40, dim))  # some leave the grid
    beam, *idx = traverse(grid, starts, ends)
    assert len(idx) == dim and np.all(np.diff(beam) >= 0)
    for i in range(40):
        got = list(zip(*(j[beam == i].tolist() for j in idx)))
        assert len(got) == len(set(got)), "a beam visited a cell twice"
        assert set(got) == brute_force_cells(grid, starts[i], ends[i])


@pytest.mark.parametrize("dim", [2, 3])
def test_traversal_is_ordered_and_connected(dim):
    grid = GridSpec((0.0, 0.0), 1.0, (10, 10)) if dim == 2 else VoxelSpec((0.0, 0.0, 0.0), 1.0, (10, 10, 10))
    start, end = [9.3, 0.2, 0.6][:dim], [0.4, 8.9, 7.3][:dim]
    _beam, *idx = traverse(grid, [start], [end])
    cells = np.column_stack(idx)
    assert np.all(np.abs(np.diff(cells, axis=0)).sum(axis=1) == 1)  # face-connected: one cell at a time
    assert tuple(cells[0]) == tuple(int(v) for v in start[::-1]) and tuple(cells[-1]) == tuple(int(v) for v in end[::-1])


def test_diagonal_through_grid_corners_visits_only_the_diagonal():
    grid = GridSpec((0.0, 0.0), 1.0, (5, 5))
    _, rows, cols = traverse(grid, [[0.5, 0.5]], [[3.5, 3.5]])
    assert list(zip(rows, cols)) == [(0, 0), (1, 1), (2, 2), (3, 3)]
    # A beam along a grid line, and a start exactly on a line heading back across it.
    _, rows, cols = traverse(grid, [[2.0, 0.5]], [[0.5, 0.5]])
    assert list(zip(rows, cols)) == [(0, 1), (0, 0)]
    # In 3-D: through the voxel corners, and through the edges of a plane diagonal (z fixed).
    cube = VoxelSpec((0.0, 0.0, 0.0), 1.0, (5, 5, 5))
    _, iz, iy, ix = traverse(cube, [[0.5, 0.5, 0.5]], [[3.5, 3.5, 3.5]])
    assert list(zip(iz, iy, ix)) == [(0, 0, 0), (1, 1, 1), (2, 2, 2), (3, 3, 3)]
    _, iz, iy, ix = traverse(cube, [[0.5, 0.5, 2.5]], [[2.5, 2.5, 2.5]])
    assert list(zip(iz, iy, ix)) == [(2, 0, 0), (2, 1, 1), (2, 2, 2)]


@pytest.mark.parametrize("dim", [2, 3])
def test_traversal_in_chunks_matches_one_pass(monkeypatch, dim):
    grid = GridSpec((0.0, 0.0), 0.1, (100, 100)) if dim == 2 else VoxelSpec((0.0, 0.0, 0.0), 0.1, (30, 100, 100))
    rng = np.random.default_rng(1)
    s, e = rng.uniform(0, [10, 10, 3][:dim], (200, dim)), rng.uniform(0, [10, 10, 3][:dim], (200, dim))
    whole = traverse(grid, s, e)
    monkeypatch.setattr(raycast, "ENTRIES_PER_CHUNK", 50)
    for a, b in zip(whole, traverse(grid, s, e)):
        np.testing.assert_array_equal(a, b)


def wall_world():
    # A wall at x = 5 (cells of 1 m: the hit cell is column 5), the sensor in column 0.
    return World(segments=[(5.0, -10.0, 5.0, 10.0)])


def test_hit_cell_occupied_and_traversed_cells_free():
    scans = simulate_scans(wall_world(), np.tile([0.5, 0.5, 0.0], (20, 1)), 1, fov=0.1, max_range=30.0)
    m = OccupancyGridMapper(resolution=1.0, extent=(0.0, 8.0, 0.0, 2.0)).fit(scans)
    assert m.hits_[0, 5] == 20 and m.hits_.sum() == 20
    p = m.predict_proba([[5.5, 0.5], [2.5, 0.5], [0.5, 0.5], [4.5, 0.5]])
    assert p[0] == pytest.approx(0.971)  # clamped at OctoMap's upper bound
    np.testing.assert_allclose(p[1:], 0.1192)  # and at its lower one
    np.testing.assert_array_equal(m.observed_[0], [20, 20, 20, 20, 20, 20, 0, 0])
    # Beyond the wall and in the other row: never observed, exactly 0.5.
    assert m.predict_proba([[6.5, 0.5], [2.5, 1.5], [100.0, 0.0]]).tolist() == [0.5, 0.5, 0.5]


def test_octomap_default_constants():
    # OccupancyOcTreeBase's constructor: setProbHit(0.7), setProbMiss(0.4), clamping 0.1192 / 0.971.
    assert L_HIT == pytest.approx(np.log(0.7 / 0.3)) == pytest.approx(0.8473, abs=1e-4)
    assert pytest.approx(-0.4055, abs=1e-4) == L_MISS
    assert pytest.approx(-2.0000, abs=1e-4) == L_MIN and pytest.approx(3.5110, abs=1e-4) == L_MAX
    m = OccupancyGridMapper()
    assert (m.l_occ, m.l_free, m.l_min, m.l_max, m.max_range_free) == (L_HIT, L_MISS, L_MIN, L_MAX, 10.0)


def test_hand_computed_ray_through_a_small_grid():
    # From (0.5, 0.5) to (3.5, 2.5), slope 2/3, 1 m cells. The line crosses x = 1 at y = 0.83,
    # y = 1 at x = 1.25, x = 2 at y = 1.5, y = 2 at x = 2.75, x = 3 at y = 2.17: cells (row, col)
    # (0,0) (0,1) (1,1) (1,2) (2,2) (2,3), the last holding the end point.
    grid = GridSpec((0.0, 0.0), 1.0, (4, 4))
    _, rows, cols = traverse(grid, [[0.5, 0.5]], [[3.5, 2.5]])
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 0), (0, 1), (1, 1), (1, 2), (2, 2), (2, 3)]
    scan = Scan([0.5, 0.5, 0.0], [np.arctan2(2.0, 3.0)], [np.hypot(3.0, 2.0)], 10.0)
    m = OccupancyGridMapper(1.0, (0.0, 4.0, 0.0, 4.0)).fit([scan])
    expected = np.zeros((4, 4))
    expected[[0, 0, 1, 1, 2], [0, 1, 1, 2, 2]] = L_MISS
    expected[2, 3] = L_HIT
    np.testing.assert_allclose(m.log_odds_, expected)


def test_clamping_by_hand():
    # Ten scans hitting cell 2 (log-odds would be 8.47, clamped at 3.51), then two scans passing
    # through cell 2 to cell 3: 3.51 - 2 * 0.405 = 2.70, not 8.47 - 0.81. Cells 0, 1: twelve
    # misses, clamped at -2.0.
    hit2 = Scan([0.5, 0.5, 0.0], [0.0], [2.0], 10.0)
    hit3 = Scan([0.5, 0.5, 0.0], [0.0], [3.0], 10.0)
    m = OccupancyGridMapper(1.0, (0.0, 4.0, 0.0, 1.0)).fit([hit2] * 10 + [hit3] * 2)
    np.testing.assert_allclose(m.log_odds_[0], [L_MIN, L_MIN, L_MAX + 2 * L_MISS, 2 * L_HIT])
    assert m.log_odds_[0, 2] == pytest.approx(2.701, abs=1e-3)


def test_one_update_per_cell_per_scan_and_a_hit_wins():
    # One scan, three beams from (0.5, 0.5) along +x: ranges 1.0, 3.0 and 3.0 (cells 0..1, 0..3,
    # 0..3), plus one ending in cell 2 (range 2.0) while the others cross it.
    scan = Scan([0.5, 0.5, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 3.0, 3.0, 2.0], 10.0)
    m = OccupancyGridMapper(1.0, (0.0, 5.0, 0.0, 1.0)).fit([scan])
    # Log-odds (OctoMap): cell 0 one miss (not four), cell 1 hit by beam 0 and crossed by three:
    # a hit wins; cell 2 likewise; cell 3 one hit (two beams end there); cell 4 unseen.
    np.testing.assert_allclose(m.log_odds_[0], [L_MISS, L_HIT, L_HIT, L_HIT, 0.0])
    np.testing.assert_array_equal(m.observed_[0], [1, 1, 1, 1, 0])
    # Counting, per beam (GMapping): cell 0 four misses; cell 1 one hit, three misses; cell 2
    # one hit, two misses; cell 3 two hits.
    c = OccupancyGridMapper(1.0, (0.0, 5.0, 0.0, 1.0), "counting").fit([scan])
    np.testing.assert_array_equal(c.hits_[0], [0, 1, 1, 2, 0])
    np.testing.assert_array_equal(c.misses_[0], [4, 3, 2, 0, 0])
    np.testing.assert_allclose(c.predict_proba([[x + 0.5, 0.5] for x in range(5)]), [1 / 6, 2 / 6, 2 / 5, 3 / 4, 0.5])
    # Counting once per scan: the same sets as the log-odds grid.
    s = OccupancyGridMapper(1.0, (0.0, 5.0, 0.0, 1.0), "counting", update="scan").fit([scan])
    np.testing.assert_array_equal(s.hits_[0], [0, 1, 1, 1, 0])
    np.testing.assert_array_equal(s.misses_[0], [1, 0, 0, 0, 0])
    # Log-odds per beam instead: cell 0 four misses, cell 1 a hit and three misses.
    b = OccupancyGridMapper(1.0, (0.0, 5.0, 0.0, 1.0), update="beam").fit([scan])
    np.testing.assert_allclose(b.log_odds_[0, :2], [4 * L_MISS, L_HIT + 3 * L_MISS])


def test_counting_and_logodds_agree_on_streamed_chunks(monkeypatch):
    scans = paper_room_scans(n_beams=36)
    for kw in [{}, {"sensor_model": "counting"}, {"update": "beam"}]:
        whole = OccupancyGridMapper(0.25, **kw).fit(scans)
        monkeypatch.setattr(ogm, "ENTRIES_PER_CHUNK", 500)
        monkeypatch.setattr(raycast, "ENTRIES_PER_CHUNK", 500)
        parts = OccupancyGridMapper(0.25, **kw).fit(scans)
        monkeypatch.undo()
        np.testing.assert_allclose(parts.log_odds_, whole.log_odds_)
        np.testing.assert_array_equal(parts.hits_, whole.hits_)


def test_one_scan_updates_by_hand():
    scan = Scan([0.5, 0.5, 0.0], [0.0], [2.0], 10.0)  # hit at (2.5, 0.5): cells 0, 1 free
    m = OccupancyGridMapper(resolution=1.0, extent=(0.0, 4.0, 0.0, 1.0), l_occ=0.85, l_free=-0.4).fit([scan])
    np.testing.assert_allclose(m.log_odds_[0], [-0.4, -0.4, 0.85, 0.0])


def test_one_cloud_ray_updates_by_hand():
    # The 3-D grid baseline: a ray from (0.5, 0.5, 0.5) hitting at x = 2.5 (voxels 0, 1 free),
    # and a no-return ray up the z axis, free to the 2 m cap (voxels 0..2 of that column).
    cloud = CloudScan([0.5, 0.5, 0.5], [[2.5, 0.5, 0.5], [0.5, 0.5, 9.0]], hit=[True, False])
    m = OccupancyGridMapper(1.0, (0.0, 4.0, 0.0, 1.0, 0.0, 4.0), l_occ=0.85, l_free=-0.4, max_range_free=2.0).fit([cloud])
    assert m.log_odds_.shape == (4, 1, 4)
    np.testing.assert_allclose(m.log_odds_[0, 0], [-0.4, -0.4, 0.85, 0.0])  # voxel 0 once per scan
    np.testing.assert_allclose(m.log_odds_[:, 0, 0], [-0.4, -0.4, -0.4, 0.0])
    assert m.predict_proba([[2.7, 0.2, 0.9], [3.5, 0.5, 0.5]]).tolist() == pytest.approx([1 / (1 + np.exp(-0.85)), 0.5])
    vm = m.grid_map()
    assert isinstance(vm, VoxelMap) and vm.spec == m.grid_
    np.testing.assert_allclose(vm.probability.ravel(), m.predict_proba(m.grid_.centres()))


def test_3d_grid_on_lidar_clouds_agrees_with_the_room():
    clouds = lidar_clouds(ORIGINS, n_rays=1500, max_range=8.0)
    m = OccupancyGridMapper(resolution=0.2).fit(clouds)
    p = m.grid_map().probability.ravel()
    centres = m.grid_.centres()
    seen = m.observed_.ravel() > 0
    occ, free = (p > 0.66) & seen, (p < 0.33) & seen
    assert occ.sum() > 200 and free.sum() > 2000
    # Occupied voxels lie on the room's surfaces (within a voxel), free ones off them.
    assert room_occupied(centres[occ], thickness=0.2 + 1e-9).all()
    assert (~room_occupied(centres[free], thickness=0.0)).mean() > 0.99


def test_no_return_beam_never_marks_occupied():
    scan = Scan([0.5, 0.5, 0.0], [0.0, np.pi / 2], [10.0, 10.0], 10.0)
    m = OccupancyGridMapper(resolution=1.0, extent=(0.0, 20.0, 0.0, 20.0), max_range_free=4.0).fit([scan])
    assert m.hits_.sum() == 0 and (m.log_odds_ <= 0).all()
    # Free up to the cap: cells 0..4 along x (the 4 m cap ends at x = 4.5), nothing further.
    # Both beams start in cell 0: once per scan for log-odds, once per beam for counting.
    np.testing.assert_array_equal(m.observed_[0, :7], [1, 1, 1, 1, 1, 0, 0])
    c = OccupancyGridMapper(1.0, (0.0, 20.0, 0.0, 20.0), "counting", max_range_free=4.0).fit([scan])
    np.testing.assert_array_equal(c.misses_[0, :7], [2, 1, 1, 1, 1, 0, 0])
    assert c.hits_.sum() == 0


def test_unobserved_and_grid_map():
    scans = paper_room_scans()
    m = OccupancyGridMapper(resolution=0.25).fit(scans)
    gm = m.grid_map()
    assert isinstance(gm, OccupancyMap) and gm.grid == m.grid_
    never = m.observed_ == 0
    assert never.any() and (~never).any()
    assert np.all(gm.probability[never] == 0.5)
    np.testing.assert_allclose(gm.variance, gm.probability * (1 - gm.probability))
    p, v = m.predict(m.grid_.centres())
    np.testing.assert_allclose(p, gm.probability.ravel())
    np.testing.assert_allclose(v, p * (1 - p))
    # The default extent covers every pose and hit, with a margin.
    xmin, xmax, ymin, ymax = m.grid_.extent
    assert xmin < 0 and ymin < 0 and xmax > 20 and ymax > 16


def test_paper_room_map_agrees_with_truth():
    from gpomap.simulate import paper_room

    world, poses = paper_room()
    scans = simulate_scans(world, poses, 360, max_range=30.0)
    m = OccupancyGridMapper(resolution=0.2).fit(scans)
    # Walls lie on grid lines here, so a hit may mark the cell on either side: occupied cells
    # are judged against thick walls, free cells against thin ones.
    near_wall = world.true_grid(m.grid_, wall_thickness=2.5 * m.grid_.resolution)
    on_wall = world.true_grid(m.grid_, wall_thickness=0.1 * m.grid_.resolution)
    p = m.grid_map().probability
    seen = m.observed_ > 0
    occ = (p > 0.66) & seen
    free = (p < 0.33) & seen
    assert occ.sum() > 300 and free.sum() > 5000
    assert near_wall[occ].all()
    assert (~on_wall[free]).mean() > 0.99


def test_not_fitted_and_bad_parameters():
    with pytest.raises(NotFittedError):
        OccupancyGridMapper().predict_proba([[0.0, 0.0]])
    with pytest.raises(ValueError, match="l_min"):
        OccupancyGridMapper(l_min=1.0).fit(paper_room_scans())
    with pytest.raises(ValueError, match="sensor_model"):
        OccupancyGridMapper(sensor_model="bayes").fit(paper_room_scans())
