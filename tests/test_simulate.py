import numpy as np
import pytest

from gpomap.grid import GridSpec
from gpomap.scans import Scan
from gpomap.simulate import World, beam_angles, paper_room, paper_room_scans, simulate_scans


def square_room(side: float = 10.0) -> World:
    return World(outlines=[[(0, 0), (side, 0), (side, side), (0, side)]])


def test_beam_perpendicular_to_wall_reads_the_distance():
    world = World(segments=[(5.0, -1.0, 5.0, 1.0)])
    r = world.cast([[1.0, 0.0]], [0.0], max_range=30.0)
    assert r[0] == pytest.approx(4.0)


def test_beam_at_an_angle_hand_computed():
    # Wall x = 5; from (1, 0) at 45 degrees the beam reaches it at (5, 4): range 4 sqrt 2.
    world = World(segments=[((5.0, -10.0), (5.0, 10.0))])
    r = world.cast(np.array([1.0, 0.0]), [np.pi / 4], max_range=30.0)
    assert r[0] == pytest.approx(4 * np.sqrt(2))


def test_miss_gives_exactly_max_range():
    world = World(segments=[(5.0, -1.0, 5.0, 1.0)])
    # Pointing away, pointing parallel, passing above the end of the wall, and a wall too far.
    origins = [[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [-30.0, 0.0]]
    angles = [np.pi, np.pi / 2, np.arctan2(1.5, 4.0), 0.0]
    r = world.cast(origins, angles, max_range=12.0)
    assert np.array_equal(r, np.full(4, 12.0))


def test_nearest_of_several_walls_wins():
    world = World(segments=[(5.0, -1.0, 5.0, 1.0), (3.0, -1.0, 3.0, 1.0), (8.0, -1, 8.0, 1)])
    assert world.cast([[0.0, 0.0]], [0.0], 30.0)[0] == pytest.approx(3.0)


def test_beam_into_a_corner_does_not_slip_through():
    world = square_room(10.0)
    r = world.cast([[5.0, 5.0], [2.0, 2.0]], [np.pi / 4, np.pi / 4], max_range=100.0)
    np.testing.assert_allclose(r, [5 * np.sqrt(2), 8 * np.sqrt(2)])
    r = world.cast([[5.0, 5.0]] * 4, [np.pi / 4, 3 * np.pi / 4, 5 * np.pi / 4, 7 * np.pi / 4], 100.0)
    np.testing.assert_allclose(r, np.full(4, 5 * np.sqrt(2)))


def test_cast_in_chunks_matches_small_batches(monkeypatch):
    import gpomap.simulate as sim

    world, poses = paper_room()
    rng = np.random.default_rng(3)
    a = rng.uniform(-np.pi, np.pi, 500)
    o = poses[rng.integers(0, len(poses), 500), :2]
    full = world.cast(o, a, 30.0)
    monkeypatch.setattr(sim, "_PAIRS_PER_CHUNK", 7)
    np.testing.assert_array_equal(world.cast(o, a, 30.0), full)


def test_endpoints_lie_on_walls():
    world, poses = paper_room()
    scans = simulate_scans(world, poses, 90, max_range=30.0)
    hits = np.concatenate([s.hits() for s in scans])
    assert len(hits) == 31 * 90
    assert world.distance_to_walls(hits).max() < 1e-9


def test_distance_to_walls_hand_computed():
    world = World(segments=[(0.0, 0.0, 4.0, 0.0)])
    d = world.distance_to_walls([[2.0, 3.0], [-3.0, 4.0], [4.0, 0.0], [7.0, -4.0]])
    np.testing.assert_allclose(d, [3.0, 5.0, 0.0, 5.0])


def test_occupancy_at_known_points():
    world = World(
        segments=[(0.0, 0.0, 10.0, 0.0)],
        obstacles=[[(4.0, 4.0), (6.0, 4.0), (6.0, 6.0), (4.0, 6.0)]],
        outlines=[[(-5.0, -5.0), (15.0, -5.0), (15.0, 15.0), (-5.0, 15.0)]],
    )
    pts = [
        [5.0, 0.04],  # within half the thickness of the free-standing wall
        [5.0, 0.06],  # just outside it
        [5.0, 5.0],  # inside the solid box
        [4.0, 5.0],  # on the box edge
        [2.0, 8.0],  # inside the room outline but not in anything solid: free
        [-5.0, 3.0],  # on the outline
    ]
    occ = world.occupancy(pts, wall_thickness=0.1)
    np.testing.assert_array_equal(occ, [True, False, True, True, False, True])


def test_true_grid_matches_cell_centres_and_orientation():
    world = World(obstacles=[[(0.0, 2.0), (4.0, 2.0), (4.0, 4.0), (0.0, 4.0)]])
    grid = GridSpec((0.0, 0.0), 1.0, (4, 4))
    truth = world.true_grid(grid, wall_thickness=0.0)
    # Rows are y ascending: the box covers the top two rows.
    np.testing.assert_array_equal(truth, [[False] * 4, [False] * 4, [True] * 4, [True] * 4])


def test_beam_angles():
    np.testing.assert_allclose(beam_angles(4), [0, np.pi / 2, np.pi, 3 * np.pi / 2])
    np.testing.assert_allclose(beam_angles(3, np.pi), [-np.pi / 2, 0, np.pi / 2])


def test_simulated_scan_geometry():
    world = square_room(10.0)
    scans = simulate_scans(world, [[2.0, 3.0, np.pi / 2]], 4, max_range=30.0)
    (s,) = scans
    assert isinstance(s, Scan)
    # Relative angles 0, 90, 180, 270 degrees from a heading of +y: up, left, down, right.
    np.testing.assert_allclose(s.ranges, [7.0, 2.0, 3.0, 8.0])
    np.testing.assert_allclose(s.hits(), [[2, 10], [0, 3], [2, 0], [10, 3]], atol=1e-12)


def test_noise_is_seeded_and_no_returns_stay_at_max_range():
    world = World(segments=[(5.0, -1.0, 5.0, 1.0)])
    poses = np.zeros((20, 3))
    a = simulate_scans(world, poses, 8, max_range=30.0, noise_std=0.05, seed=7)
    b = simulate_scans(world, poses, 8, max_range=30.0, noise_std=0.05, seed=7)
    c = simulate_scans(world, poses, 8, max_range=30.0, noise_std=0.05, seed=8)
    ra = np.array([s.ranges for s in a])
    np.testing.assert_array_equal(ra, [s.ranges for s in b])
    assert not np.array_equal(ra, [s.ranges for s in c])
    # Beam 0 hits the wall at 5 with noise; every other beam misses and reads exactly 30.
    assert np.std(ra[:, 0]) > 0.01 and abs(ra[:, 0].mean() - 5.0) < 0.05
    assert np.all(ra[:, 1:] == 30.0)


def test_paper_room_dimensions_and_free_poses():
    world, poses = paper_room()
    assert poses.shape == (31, 3)
    assert world.bounds == (0.0, 20.0, 0.0, 16.0)
    assert not world.occupancy(poses[:, :2], wall_thickness=0.1).any()
    assert world.distance_to_walls(poses[:, :2]).min() >= 1.0
    scans = paper_room_scans()
    assert len(scans) == 31 and all(s.n_beams == 36 for s in scans)
    # The room is closed: every beam returns, and the hits spread over the whole room.
    assert all(not s.no_return().any() for s in scans)
    hits = np.concatenate([s.hits() for s in scans])
    assert hits[:, 0].min() == pytest.approx(0.0) and hits[:, 0].max() == pytest.approx(20.0)
    assert hits[:, 1].min() == pytest.approx(0.0) and hits[:, 1].max() == pytest.approx(16.0)


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError, match="at least one wall"):
        World()
    with pytest.raises(ValueError, match="at least 3 vertices"):
        World(obstacles=[[(0, 0), (1, 1)]])
    with pytest.raises(ValueError, match="shape"):
        simulate_scans(square_room(), [[1.0, 1.0]], 4)
