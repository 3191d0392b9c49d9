import numpy as np
import pytest

import gpomap.observations as observations
from gpomap.clouds import CloudScan
from gpomap.errors import EmptyDataError, InputFormatError
from gpomap.observations import free_near_hits, observations_from_scans, reading_counts, sensor_positions
from gpomap.scans import Scan, evenly_spaced, select_scans
from tests.world3d import ORIGINS, lidar_clouds


def test_hit_free_and_no_return_beams():
    # Beam 0 hits at 1.0 m; beam 1 is a no-return at max range 5; beam 2 is NaN; beam 3 is negative.
    scan = Scan([1.0, 2.0, 0.0], [0.0, np.pi / 2, 1.0, 2.0], [1.0, 5.0, np.nan, -1.0], 5.0)
    obs = observations_from_scans([scan], free_step=0.2, no_return_cap=3.0)
    assert obs.n_invalid == 2
    assert obs.n_no_return == 1
    hits = obs.points[obs.occupied]
    np.testing.assert_allclose(hits, [[2.0, 2.0]])
    free = obs.points[~obs.occupied]
    along_x = free[np.isclose(free[:, 1], 2.0)]
    # Samples at 0.2 .. 0.8: the 0.1 m margin keeps them short of the hit at 1.0.
    np.testing.assert_allclose(np.sort(along_x[:, 0]) - 1.0, [0.2, 0.4, 0.6, 0.8])
    along_y = free[np.isclose(free[:, 0], 1.0)]
    # The no-return beam gives free points up to the cap and no hit.
    assert along_y[:, 1].max() == pytest.approx(2.0 + 3.0)
    assert len(along_y) == 15


def test_cloud_hit_and_no_return_rays():
    # From (1, 2, 3): a hit 1 m up, a no-return ray 5 m along x, a NaN point and one at the origin.
    origin = np.array([1.0, 2.0, 3.0])
    pts = origin + np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]])
    cloud = CloudScan(origin, pts, hit=[True, False, True, True], max_range=5.0)
    obs = observations_from_scans([cloud], free_step=0.2, no_return_cap=3.0)
    assert obs.dim == 3 and obs.n_invalid == 2 and obs.n_no_return == 1
    np.testing.assert_allclose(obs.points[obs.occupied], [[1.0, 2.0, 4.0]])
    free = obs.points[~obs.occupied]
    up = free[np.isclose(free[:, 0], 1.0)]
    # Samples at 0.2 .. 0.8 above the origin: the 0.1 m margin keeps them short of the hit.
    np.testing.assert_allclose(np.sort(up[:, 2]) - 3.0, [0.2, 0.4, 0.6, 0.8])
    np.testing.assert_allclose(up[:, :2], np.tile([1.0, 2.0], (4, 1)))
    along_x = free[np.isclose(free[:, 2], 3.0)]
    # The no-return ray: free points to the 3 m cap, never a hit; with no cap, to its endpoint.
    assert len(along_x) == 15 and along_x[:, 0].max() == pytest.approx(4.0)
    uncapped = observations_from_scans([cloud], free_step=0.2)
    assert (~uncapped.occupied).sum() == 4 + 25
    assert observations_from_scans([cloud], free_step=0.2, no_return_cap=0.0).n_free == 4
    np.testing.assert_allclose(sensor_positions([cloud, cloud]), [origin, origin])


def test_cloud_observations_lie_on_their_rays():
    clouds = lidar_clouds(ORIGINS[:2], n_rays=50)
    obs = observations_from_scans(clouds, free_step=0.25)
    for i, c in enumerate(clouds):
        mine = obs.points[obs.scan_index == i]
        # Every point is on one of the cloud's rays (zero distance to the line), within its length.
        d = c.points - c.origin
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
        rel = mine - c.origin
        along = rel @ u.T  # (m, rays)
        off = np.linalg.norm(rel[:, None, :] - along[:, :, None] * u[None], axis=2)
        ray = np.argmin(off, axis=1)
        assert off[np.arange(len(mine)), ray].max() < 1e-9
        assert np.all(along[np.arange(len(mine)), ray] <= np.linalg.norm(d, axis=1)[ray] + 1e-9)


def test_twelve_lidar_clouds_of_la3dm_size_are_sampled_at_once():
    # Tests assert no wall time; la3dm-sized input (12 x 3,500 rays) is vectorised, not looped.
    clouds = lidar_clouds(np.tile(ORIGINS, (2, 1)), n_rays=3500, max_range=8.0)
    obs = observations_from_scans(clouds, free_step=0.2)
    assert obs.n_occupied == sum(int(c.hit.sum()) for c in clouds) and obs.n_free > 100_000


def test_free_near_hits_by_hand():
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.29], [0.5, 0.0], [0.0, 0.31]])
    occ = np.array([True, False, False, False, False])
    np.testing.assert_array_equal(free_near_hits(pts, occ, 0.3), [False, True, True, False, False])
    assert not free_near_hits(pts, occ, 0.0).any()
    assert not free_near_hits(pts, np.zeros(5, bool), 0.3).any()
    # The same in 3-D, the offsets along z: distance is Euclidean in every dimension.
    pts3 = np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.1], [0.0, 0.0, 0.29], [0.2, 0.2, 0.2], [0.0, 0.0, 0.31]])
    np.testing.assert_array_equal(free_near_hits(pts3, occ, 0.3), [False, True, True, False, False])


def test_free_clearance_drops_samples_of_a_beam_grazing_a_wall():
    # Beam 0 hits a wall at x = 2 head on; beam 1 runs along the wall 0.1 m from it, to a far
    # hit at y = 3. Only beam 1's samples beside beam 0's hit and its own last ones are near a hit.
    scan = Scan([0.0, 0.0, 0.0], [0.0, np.arctan2(3.0, 1.9)], [2.0, np.hypot(1.9, 3.0)], 10.0)
    kept = observations_from_scans([scan], free_step=0.2, free_clearance=0.3)
    every = observations_from_scans([scan], free_step=0.2)
    dropped = free_near_hits(every.points, every.occupied, 0.3)
    assert kept.n_cleared == int(dropped.sum()) > 0
    np.testing.assert_array_equal(kept.points, every.points[~dropped])
    hits = every.points[every.occupied]
    free = kept.points[~kept.occupied]
    assert np.min(np.linalg.norm(free[:, None] - hits[None], axis=2)) >= 0.3


def test_no_usable_readings_is_a_clear_error():
    scan = Scan([0, 0, 0], [0.0], [np.nan], 5.0)
    with pytest.raises(EmptyDataError, match="no usable readings"):
        observations_from_scans([scan])


def test_scan_rejects_mismatched_beams():
    with pytest.raises(InputFormatError, match="2 beam angles but 3 ranges"):
        Scan([0, 0, 0], [0.0, 1.0], [1.0, 2.0, 3.0], 5.0)


def test_paper_subselection_counts():
    scans = [Scan([i, 0, 0], np.linspace(-np.pi / 2, np.pi / 2, 361), np.ones(361), 80.0) for i in range(395)]
    chosen = select_scans(scans, 52, 37)
    assert len(chosen) == 52 and all(s.n_beams == 37 for s in chosen)
    assert chosen[0].pose[0] == 0 and chosen[-1].pose[0] == 394
    # Beams symmetric about the heading: first, middle and last kept.
    np.testing.assert_allclose(chosen[0].angles[[0, 18, 36]], [-np.pi / 2, 0.0, np.pi / 2])
    assert list(evenly_spaced(5, None)) == [0, 1, 2, 3, 4]


def test_points_made_a_part_at_a_time_are_the_whole_logs(monkeypatch):
    # observation_parts and ScanPoints against observations_from_scans: the same points, labels
    # and scans in the same order; a square's points as the whole's cut to it; counts and bounds.
    import gpomap.observations as observations
    from gpomap.lattice import in_box
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans(n_beams=72)
    scans = [*scans[:5], Scan(scans[5].pose, scans[5].angles, np.full(72, np.nan), 30.0), *scans[6:]]  # one without points
    whole = observations_from_scans(scans, 0.3, None, 5.0)
    monkeypatch.setattr(observations, "PART_POINTS", 500)
    parts = list(observations.observation_parts(scans, 0.3, None, 5.0))
    assert len(parts) > 5 and all(p.occupied.size >= 500 for p in parts[:-1])
    for name in ("points", "occupied", "scan_index"):
        joined = np.concatenate([getattr(p, name) for p in parts])
        assert joined.dtype == getattr(whole, name).dtype and joined.tobytes() == getattr(whole, name).tobytes()
    assert sum(p.n_invalid for p in parts) == whole.n_invalid == 72
    assert sum(p.n_no_return for p in parts) == whole.n_no_return
    made = observations.ScanPoints(scans, 0.3, None, 5.0)
    assert (made.n_free, made.n_occupied, made.n_scans) == (whole.n_free, whole.n_occupied, len(scans))
    np.testing.assert_array_equal(made.lower, whole.points.min(axis=0))
    np.testing.assert_array_equal(made.upper, whole.points.max(axis=0))
    assert np.isinf(made.scan_lower[5]).all()
    lo, hi = np.array([3.0, 2.0]), np.array([9.0, 6.5])
    square = made.square(lo, hi, 0.3)
    inside = in_box(whole.points, lo - 0.3, hi + 0.3)
    for name in ("points", "occupied", "scan_index"):
        assert getattr(square, name).tobytes() == getattr(whole, name)[inside].tobytes()


def test_planar_beams_are_each_scans_rays_joined_to_the_bit(monkeypatch):
    # Invalid readings (NaN, inf, 0, negative), no-returns at and past the maximum range, a scan
    # with no usable beam and scans of different beam counts and maximum ranges: the beams of all
    # scans at once are Rays.of of each, in order, and from_scans' ray evidence is built from them.
    from gpomap.evidence import RayEvidence
    from gpomap.observations import PlanarBeams, Rays

    rng = np.random.default_rng(5)
    scans = []
    for k, n in enumerate((181, 7, 360, 5)):
        ranges = rng.uniform(0.2, 12.0, n)
        if k == 1:
            ranges[:] = np.nan
        else:
            ranges[:4] = [np.nan, np.inf, 0.0, -1.0]
            ranges[4] = 10.0 if k != 2 else 8.0
        angles = np.linspace(-np.pi / 2, np.pi / 2, n)
        scans.append(Scan(rng.uniform(-5, 5, 3), angles, ranges, 10.0 if k != 2 else 8.0))
    beams = PlanarBeams.of(scans)
    rays = [Rays.of(s) for s in scans]
    assert rays[1].hit.size == 0 and np.any(~rays[0].hit)
    for name in ("directions", "lengths", "ends", "hit"):
        np.testing.assert_array_equal(getattr(beams, name), np.concatenate([getattr(r, name) for r in rays]))
    np.testing.assert_array_equal(beams.origins, np.concatenate([np.tile(r.origin, (r.hit.size, 1)) for r in rays]))
    np.testing.assert_array_equal(beams.scan, np.repeat(np.arange(4), [r.hit.size for r in rays]))
    evidence = RayEvidence.from_scans(scans, no_return_cap=3.0)
    capped = [np.where(r.hit, r.lengths, np.minimum(r.lengths, 3.0)) for r in rays]
    np.testing.assert_array_equal(
        evidence.ends,
        np.concatenate(
            [np.where((c == r.lengths)[:, None], r.ends, r.origin + c[:, None] * r.directions) for r, c in zip(rays, capped)]
        ),
    )
    np.testing.assert_array_equal(evidence.scan, beams.scan)
    np.testing.assert_array_equal(evidence.hit, beams.hit)
    # A few scans' beams at a time: the same beams (runs of scans cut at 200 beams, the scan
    # without a usable beam among them).
    import gpomap.evidence

    monkeypatch.setattr(gpomap.evidence, "BEAMS_AT_ONCE", 200)
    in_runs = RayEvidence.from_scans(scans, no_return_cap=3.0)
    for name in ("starts", "ends", "hit", "scan"):
        np.testing.assert_array_equal(getattr(in_runs, name), getattr(evidence, name))
    # The readings counted from the ranges alone: 4 invalid in each of three scans and all 7 of
    # the second; a no-return at the maximum range in three.
    assert reading_counts(scans) == (19, sum(r.n_no_return for r in rays)) and sum(r.n_no_return for r in rays) >= 3


def _by_cube(samples, origin, cube):
    """Brute force: each cube's first sample (in order) and how many samples it holds, by a dict."""
    first, count = {}, {}
    for i, p in enumerate(samples):
        key = tuple(np.floor((p - origin) / cube).astype(int).tolist())
        first.setdefault(key, i)
        count[key] = count.get(key, 0) + 1
    keys = sorted(first, key=first.get)
    return samples[[first[k] for k in keys]], np.array([count[k] for k in keys])


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("dim", [2, 3])
def test_merged_free_points_are_the_first_sample_of_each_cube_weighted_by_its_samples(monkeypatch, dim, compiled):
    from gpomap import _compiled_raycast
    from gpomap.observations import merged_ray_free_points, ray_free_points

    rng = np.random.default_rng(dim)
    directions = rng.normal(size=(300, dim))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origin = rng.normal(size=dim)
    lengths = rng.uniform(0.0, 3.0, 300)
    samples, _ = ray_free_points(np.broadcast_to(origin, directions.shape), directions, lengths, 0.2)
    want_points, want_weight = _by_cube(samples, origin, 0.1)
    monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", samples.shape[0])
    points, weight = merged_ray_free_points(origin, directions, lengths, 0.2, 0.1)
    np.testing.assert_array_equal(points, want_points)
    np.testing.assert_array_equal(weight, want_weight)
    assert weight.dtype == np.int32 and weight.sum() == samples.shape[0] and points.shape[0] < samples.shape[0]


def test_one_rays_samples_never_share_a_cube_of_half_the_step_and_far_reaching_rays_are_kept_whole(monkeypatch):
    from gpomap.observations import merged_ray_free_points, ray_free_points

    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0)
    direction = np.array([[1.0, 1.0, 1.0]]) / np.sqrt(3.0)
    points, weight = merged_ray_free_points(np.zeros(3), direction, np.array([5.0]), 0.2, 0.1)
    np.testing.assert_array_equal(points, ray_free_points(np.zeros((1, 3)), direction, np.array([5.0]), 0.2)[0])
    assert np.all(weight == 1)
    # Two rays along the same line: every sample shared, each point weighing two.
    points, weight = merged_ray_free_points(np.zeros(3), np.repeat(direction, 2, axis=0), np.array([5.0, 5.0]), 0.2, 0.1)
    assert points.shape == (25, 3) and np.all(weight == 2)
    # Cubes too small to index from the origin: every sample kept, one each.
    points, weight = merged_ray_free_points(np.zeros(3), np.repeat(direction, 2, axis=0), np.array([5.0, 5.0]), 0.2, 1e-7)
    assert points.shape == (50, 3) and np.all(weight == 1)
    # No ray at all, and a scan of fewer samples than MERGE_MIN_SAMPLES: every sample kept, one each.
    points, weight = merged_ray_free_points(np.zeros(3), np.zeros((0, 3)), np.zeros(0), 0.2, 0.1)
    assert points.shape == (0, 3) and weight.shape == (0,)
    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 51)
    points, weight = merged_ray_free_points(np.zeros(3), np.repeat(direction, 2, axis=0), np.array([5.0, 5.0]), 0.2, 0.1)
    assert points.shape == (50, 3) and np.all(weight == 1)


def test_voxel_maps_merge_free_samples_and_planar_maps_keep_them(monkeypatch):
    from gpomap.settings import MapSettings

    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0)
    settings = MapSettings()
    clouds = lidar_clouds(ORIGINS[:2], n_rays=400)
    merged = settings.make_observations(clouds, clearance=False)
    whole = observations_from_scans(clouds, settings.free_step)
    assert merged.weight is not None and merged.n_occupied == whole.n_occupied
    assert int(merged.weight[~merged.occupied].sum()) == whole.n_free and merged.n_free < whole.n_free
    assert np.all(merged.weight[merged.occupied] == 1)
    assert settings.free_cube(3) == pytest.approx(0.5 * settings.free_step) and settings.free_cube(2) is None


@pytest.mark.parametrize("compiled", [True, False])
def test_a_clouds_valid_rays_are_its_finite_endpoints_away_from_the_origin(monkeypatch, compiled):
    # Checked ray by ray against the rule, both paths: NaN and infinite coordinates, endpoints
    # at the origin, and one a distance whose square underflows (numpy's norm is 0 there too).
    from gpomap import _compiled_clouds

    monkeypatch.setattr(_compiled_clouds, "ENABLED", compiled)
    rng = np.random.default_rng(4)
    origin = np.array([0.0, -2.0, 0.5])
    n = 3 * _compiled_clouds.MIN_ROWS
    points = origin + rng.normal(size=(n, 3))
    points[rng.choice(n, 300, replace=False), rng.integers(0, 3, 300)] = np.nan
    points[rng.choice(n, 300, replace=False), rng.integers(0, 3, 300)] = -np.inf
    points[rng.choice(n, 300, replace=False)] = origin
    points[7] = origin + np.array([1e-170, 0.0, 0.0])
    want = [bool(np.isfinite(p).all() and float(np.sum((p - origin) ** 2)) > 0.0) for p in points]
    np.testing.assert_array_equal(CloudScan(origin, points).valid(), want)
    assert points[7, 0] != origin[0] and not want[7] and sum(want) < n - 600
    if compiled:
        assert _compiled_clouds.valid_rays(points, origin) is not None
        assert _compiled_clouds.valid_rays(points[:10], origin) is None  # a few rays: numpy's answer


@pytest.mark.parametrize("compiled", [True, False])
def test_a_clouds_rays_are_its_valid_endpoints_their_directions_and_lengths(monkeypatch, compiled):
    # Checked ray by ray against the geometry written out (math.hypot-free: the squares summed x
    # first, as both paths do), on a cloud with invalid rows between the valid ones: both paths
    # give the same bits.
    import math

    from gpomap import _compiled_clouds
    from gpomap.observations import Rays

    monkeypatch.setattr(_compiled_clouds, "ENABLED", compiled)
    rng = np.random.default_rng(5)
    origin = np.array([0.5, -1.0, 1.5])
    n = 2 * _compiled_clouds.MIN_ROWS
    points = origin + 3.0 * rng.normal(size=(n, 3))
    points[rng.choice(n, 200, replace=False), 1] = np.nan
    points[rng.choice(n, 200, replace=False)] = origin
    hit = rng.random(n) < 0.9
    rays = Rays.of(CloudScan(origin, points, hit))
    valid = [i for i, p in enumerate(points) if np.isfinite(p).all() and np.any(p != origin)]
    assert rays.lengths.size == len(valid) and rays.n_invalid == n - len(valid)
    for j in range(0, len(valid), 97):
        i = valid[j]
        d = [float(points[i, a] - origin[a]) for a in range(3)]
        length = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        assert rays.lengths[j] == length
        assert list(rays.directions[j]) == [v / length for v in d]
        assert list(rays.ends[j]) == list(points[i]) and rays.hit[j] == hit[i]
    if compiled:
        assert _compiled_clouds.ray_geometry(points, origin, CloudScan(origin, points).valid()) is not None
        assert _compiled_clouds.ray_geometry(points[:10], origin, np.ones(10, bool)) is None  # numpy's answer


def test_observations_selected_and_joined_keep_labels_scans_and_weights():
    from gpomap.observations import Observations

    pts = np.arange(12.0).reshape(6, 2)
    a = Observations(
        pts, np.array([0, 1, 0, 0, 1, 0], bool), np.array([0, 0, 1, 1, 2, 2]), 3, 1, weight=np.arange(1, 7, dtype=np.int32)
    )
    part = a.selected(np.array([True, False, True, True, False, False]))
    np.testing.assert_array_equal(part.points, pts[[0, 2, 3]])
    np.testing.assert_array_equal(part.weight, [1, 3, 4])
    np.testing.assert_array_equal(part.scan_index, [0, 1, 1])
    assert part.n_invalid == 3 and part.n_no_return == 1
    both = Observations.joined([part, a.selected(np.array([5]))], 2)
    np.testing.assert_array_equal(both.points, pts[[0, 2, 3, 5]])
    np.testing.assert_array_equal(both.weight, [1, 3, 4, 6])
    np.testing.assert_array_equal(both.occupied, [False, False, False, False])
    unweighted = Observations(pts[:1], np.array([True]), np.array([7]))
    assert Observations.joined([part, unweighted], 2).weight is None
    empty = Observations.joined([], 3)
    assert empty.points.shape == (0, 3) and empty.weight is None
