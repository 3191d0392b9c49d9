import numpy as np
import pytest
from scipy.spatial import cKDTree

from gpomap import simulate3d as s3
from gpomap.clouds import CloudScan
from gpomap.io.depth import read_depth_frames
from gpomap.voxels import VoxelSpec

UNIT_BOX = s3.Scene(np.array([[2.0, -1.0, -1.0]]), np.array([[3.0, 1.0, 1.0]]))


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_ray_straight_at_a_face_reads_the_distance():
    assert UNIT_BOX.cast([0.0, 0.0, 0.0], [[1.0, 0.0, 0.0]])[0] == pytest.approx(2.0)


def test_ray_at_an_angle_hand_computed():
    # From the origin along (1, 1, 0): the box [2, 3] x [2, 3] x [-1, 1] is entered at its
    # corner edge (2, 2, 0), 2 sqrt 2 away; along (2, 1, 0.5) the box of UNIT_BOX at x = 2,
    # where y = 1 and z = 0.5 (on the face's edge, faces included): 2 |(1, 0.5, 0.25)|.
    corner = s3.Scene(np.array([[2.0, 2.0, -1.0]]), np.array([[3.0, 3.0, 1.0]]))
    assert corner.cast(np.zeros(3), _unit([[1.0, 1.0, 0.0]]))[0] == pytest.approx(2 * np.sqrt(2))
    t = UNIT_BOX.cast(np.zeros(3), _unit([[2.0, 1.0, 0.5]]))[0]
    assert t == pytest.approx(np.linalg.norm([2.0, 1.0, 0.5]))


def test_misses_parallel_rays_and_range():
    origins = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [2.5, 0.0, 0.0]])
    dirs = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    t = UNIT_BOX.cast(origins, dirs, max_range=10.0)
    # Away from it; parallel to x outside its y slab; parallel and on its face y = 1 (a face
    # counts as the box); up, beside it; starting inside it.
    assert np.isinf(t[0]) and np.isinf(t[1]) and np.isinf(t[3])
    assert t[2] == pytest.approx(2.0) and t[4] == 0.0
    assert np.isinf(UNIT_BOX.cast(np.zeros(3), [[1.0, 0.0, 0.0]], max_range=1.9)[0])


def test_nearest_box_wins():
    scene = s3.Scene(np.array([[5.0, -1, -1], [2.0, -1, -1], [8.0, -1, -1]]), np.array([[6.0, 1, 1], [2.5, 1, 1], [9.0, 1, 1]]))
    assert scene.cast(np.zeros(3), [[1.0, 0.0, 0.0]])[0] == pytest.approx(2.0)


def test_cast_agrees_with_a_fine_march_in_the_office():
    # Brute force: step along each ray by 1 mm until a point lies in a box.
    scene = s3.office_scene()
    rng = np.random.default_rng(4)
    origin = np.array([1.5, 2.7, 1.3])
    dirs = _unit(rng.normal(size=(20, 3)))
    t = scene.cast(origin, dirs)
    steps = np.arange(0.0, 12.0, 1e-3)
    for d, ti in zip(dirs, t):
        inside = scene.contains(origin + steps[:, None] * d)
        first = steps[np.argmax(inside)] if inside.any() else np.inf
        assert first == pytest.approx(ti, abs=1.1e-3)


def test_distance_to_a_box_hand_computed():
    p = np.array([[4.0, 0.0, 0.0], [4.0, 2.0, 2.0], [2.5, 0.0, 0.0], [2.5, 0.0, 1.5]])
    assert UNIT_BOX.distance(p) == pytest.approx([1.0, np.sqrt(3.0), 0.0, 0.5])
    assert UNIT_BOX.contains(p).tolist() == [False, False, True, False]


def test_rasterise_agrees_with_contains_and_distance():
    scene = s3.office_scene()
    spec = VoxelSpec.from_extent([2.5, 0.5, 0.5], [3.7, 2.2, 2.3], 0.05)
    inside, near = scene.rasterise(spec, 0.1)
    c = spec.centres()
    assert np.array_equal(inside.reshape(-1), scene.contains(c))
    assert np.array_equal(near.reshape(-1), scene.distance(c) <= 0.1)
    assert inside.any() and (near & ~inside).any()


def test_camera_facing_a_wall_sees_it_at_its_depth():
    # A camera at (0, 0, 1) looking along +x at the wall x = 3: every pixel reads depth 3; a
    # pixel right of centre looks to -y (right of +x with z up) and one above centre to +z.
    wall = s3.Scene(np.array([[3.0, -10.0, -10.0]]), np.array([[3.2, 10.0, 10.0]]))
    cam = s3.PinholeCamera(8, 6, 4.0, 4.0, 3.5, 2.5)
    pose = s3.look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0])
    depth = s3.render_depth(wall, cam, pose, min_depth=0.3, max_depth=6.0)
    assert depth == pytest.approx(np.full((6, 8), 3.0))
    rays = cam.directions().reshape(6, 8, 3)
    right, top = pose[:3, :3] @ rays[2, 7], pose[:3, :3] @ rays[0, 3]
    assert right[1] == pytest.approx(-(7 - 3.5) / 4.0) and right[0] == 1.0
    assert top[2] == pytest.approx((2.5 - 0) / 4.0)
    # Out of range reads 0, no reading.
    assert (s3.render_depth(wall, cam, pose, max_depth=2.9) == 0).all()


def test_frames_written_are_read_back_by_the_depth_reader(tmp_path):
    scene = s3.office_scene()
    cam = s3.PinholeCamera.from_fov(32, 24, 60)
    poses = s3.office_poses()[:2]
    frames = s3.render_frames(scene, cam, poses)
    s3.write_depth_frames(frames, tmp_path)
    clouds = read_depth_frames(tmp_path)
    assert len(clouds) == 2
    for cloud, own, pose in zip(clouds, s3.frame_clouds(frames), poses):
        assert np.allclose(cloud.origin, pose[:3, 3])
        v = cloud.valid()
        assert np.array_equal(v, own.valid()) and v.mean() > 0.9
        assert np.allclose(cloud.points[v], own.points[v], atol=1e-9)
        # Each endpoint lies on a box, up to the millimetre rounding of the depth image.
        assert scene.distance(cloud.points[v]).max() < 2e-3


def test_depth_noise_has_its_sigma():
    wall = s3.Scene(np.array([[4.0, -20.0, -20.0]]), np.array([[4.2, 20.0, 20.0]]))
    cam = s3.PinholeCamera(200, 100, 400.0, 400.0, 99.5, 49.5)
    pose = s3.look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    noise = s3.DepthNoise(dropout=0.05)
    assert noise.sigma(2.0) == pytest.approx(0.0012 + 0.0019 * 1.6**2)
    depth = s3.render_depth(wall, cam, pose, noise=noise, rng=np.random.default_rng(0)).ravel()
    read = depth > 0
    assert (~read).mean() == pytest.approx(0.05, abs=0.01)
    # The wall's depth varies across the image (x = 4 everywhere): z-depth is 4 exactly.
    assert np.std(depth[read] - 4.0) == pytest.approx(float(noise.sigma(4.0)), rel=0.05)


def test_written_poses_carry_the_pose_error():
    noise = s3.DepthNoise(dropout=0.0)
    cam = s3.PinholeCamera.from_fov(8, 6, 60)
    frames = s3.render_frames(s3.office_scene(), cam, s3.office_poses(), noise=noise, seed=3)
    moved = np.linalg.norm(frames.poses[:, :3, 3] - frames.true_poses[:, :3, 3], axis=1)
    assert 0 < moved.mean() < 5 * noise.pose_position
    assert np.allclose(np.linalg.det(frames.poses[:, :3, :3]), 1.0)


def test_truth_points_are_the_lattice_points_near_crossed_cells():
    # Brute force: every lattice point within the radius of the centre of a lattice cell some
    # ray crossed (cells found by marching each ray in 0.1 mm steps).
    scene = s3.Scene(np.array([[1.0, -1.0, -1.0]]), np.array([[1.3, 1.0, 1.0]]))
    origin = np.array([0.01, 0.02, 0.03])
    dirs = _unit(np.array([[1.0, 0.0, 0.0], [1.0, 0.3, -0.2], [1.0, -0.4, 0.1]]))
    t = scene.cast(origin, dirs)
    cloud = CloudScan(origin, origin + t[:, None] * dirs)
    truth = s3.truth_points(scene, [cloud], lattice=0.025, radius=0.05)
    step = np.arange(0.0, 1.0, 1e-4)
    marched = np.concatenate([origin + np.outer(step * ti, d) for d, ti in zip(dirs, t)])
    crossed = np.unique(np.floor(marched / 0.025).astype(int), axis=0)
    centres = (crossed + 0.5) * 0.025
    box = VoxelSpec.from_extent([-0.2, -0.6, -0.6], [1.6, 0.6, 0.6], 0.025)
    lattice = box.centres()
    d, _ = cKDTree(centres).query(lattice)
    expected = lattice[d <= 0.05 + 1e-9]
    got = truth.points[np.lexsort(truth.points.T)]
    assert got.shape == expected.shape and np.allclose(got, expected[np.lexsort(expected.T)])
    assert truth.n_observed == len(expected)
    assert np.array_equal(truth.occupied, scene.contains(truth.points))
    assert np.array_equal(truth.boundary, scene.distance(truth.points) <= 0.1)
    # Points inside the box are only those the hits' cells reach: at most the radius deep.
    assert truth.occupied.any() and (truth.points[truth.occupied, 0] < 1.0 + 0.05 + 0.025).all()


def test_truth_subsample_is_uniform_and_seeded():
    scene = s3.office_scene()
    cam = s3.PinholeCamera.from_fov(16, 12, 60)
    clouds = s3.frame_clouds(s3.render_frames(scene, cam, s3.office_poses()[:1]))
    full = s3.truth_points(scene, clouds)
    part = s3.truth_points(scene, clouds, max_points=len(full.points) // 4, seed=1)
    assert len(part.points) == len(full.points) // 4 and part.n_observed == full.n_observed
    assert part.occupied.mean() == pytest.approx(full.occupied.mean(), abs=0.02)
    again = s3.truth_points(scene, clouds, max_points=len(full.points) // 4, seed=1)
    assert np.array_equal(part.points, again.points)


def test_scenes_are_well_formed():
    for scene, poses in ((s3.office_scene(), s3.office_poses()), (s3.storeroom_scene(), s3.storeroom_poses())):
        origins = np.array([p[:3, 3] for p in poses])
        # Every camera stands in free space, inside the building, at least 0.3 m from a surface.
        assert not scene.contains(origins).any() and (scene.distance(origins) > 0.3).all()
        lo, hi = scene.bounds
        assert ((origins > lo) & (origins < hi)).all()
        for p in poses:
            assert np.allclose(p[:3, :3].T @ p[:3, :3], np.eye(3)) and np.linalg.det(p[:3, :3]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="lower < upper"):
        s3.Scene(np.array([[0.0, 0, 0]]), np.array([[0.0, 1, 1]]))
