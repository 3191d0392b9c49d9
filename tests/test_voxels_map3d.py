"""The voxel map gpomap map writes on depth frames: its extent, and its surfaces against a scene's true boxes."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap import simulate3d as s3
from gpomap.apps.map3d import enclosing_box, labelled_box, voxel_bounds
from gpomap.cli import main
from gpomap.grid import OCCUPIED
from gpomap.io.voxel_outputs import load_voxels


def test_voxel_bounds_grow_the_data_box_by_two_voxels():
    points = np.array([[0.03, -1.0, 0.2], [2.5, 1.07, 1.3], [1.0, 0.0, 0.5]])
    lo, hi = voxel_bounds(points, None, None, 0.1)
    assert lo == pytest.approx([0.03 - 0.2, -1.2, 0.0]) and hi == pytest.approx([2.7, 1.27, 1.5])
    # Given bounds are kept as they are.
    lo, hi = voxel_bounds(points, (0.0, 1.0, -0.5, 0.5), (0.1, 0.9), 0.1)
    assert lo.tolist() == [0.0, -0.5, 0.1] and hi.tolist() == [1.0, 0.5, 0.9]


def _half_sphere_clouds(seed=3):
    """Two clouds of rays in every direction of x >= 0, hits and no-returns between 0.2 and 3 m:
    their free samples reach past the hits' box, and the clearance drops some of those."""
    from gpomap.clouds import CloudScan

    rng = np.random.default_rng(seed)
    clouds = []
    for origin in ([0.0, 0.0, 0.0], [0.5, -0.3, 0.2]):
        d = rng.normal(size=(300, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        d[:, 0] = np.abs(d[:, 0])
        ends = np.array(origin) + d * rng.uniform(0.2, 3.0, 300)[:, None]
        clouds.append(CloudScan(np.array(origin), ends, rng.uniform(size=300) > 0.2, 3.0))
    return clouds


@pytest.mark.parametrize("options", [{}, {"free_clearance": 0.0}, {"free_clearance": 0.4, "free_step": 0.07}])
def test_labelled_box_is_the_labelled_points_box_to_the_bit(options):
    # The extent gpomap map takes without making every labelled point is theirs exactly, where
    # free samples widen the hits' box and where the clearance drops the farthest of them.
    from gpomap.settings import MapSettings

    frames = s3.render_frames(s3.office_scene(), s3.PinholeCamera.from_fov(48, 36, 60), s3.office_poses()[:3])
    for clouds in (_half_sphere_clouds(), s3.frame_clouds(frames)):
        points = MapSettings(**options).make_observations(clouds).points
        np.testing.assert_array_equal(labelled_box(clouds, **options), [points.min(axis=0), points.max(axis=0)])
    # The first case is one the hits' box, or the box before the clearance, would get wrong.
    settings = MapSettings(**options)
    obs, unclear = (
        settings.make_observations(_half_sphere_clouds()),
        settings.make_observations(_half_sphere_clouds(), clearance=False),
    )
    hits = obs.points[obs.occupied]
    assert (obs.points.min(axis=0) < hits.min(axis=0)).any() or (obs.points.max(axis=0) > hits.max(axis=0)).any()
    if settings.clearance(3) > 0:
        assert not np.array_equal(unclear.points.min(axis=0), obs.points.min(axis=0)) or not np.array_equal(
            unclear.points.max(axis=0), obs.points.max(axis=0)
        )


@pytest.mark.parametrize("options", [{}, {"free_clearance": 0.4, "free_step": 0.07}])
def test_the_enclosing_box_holds_every_free_sample_within_a_step(options):
    # The box gpomap map checks the voxel grid's memory over before fitting: round every sample
    # the clearance might keep, and at most a step wider than all of them (the origin and a
    # ray's far end are within a step of its first and last samples).
    from gpomap.settings import MapSettings

    settings = MapSettings(**options)
    step = settings.free_step
    frames = s3.render_frames(s3.office_scene(), s3.PinholeCamera.from_fov(48, 36, 60), s3.office_poses()[:3])
    for clouds in (_half_sphere_clouds(), s3.frame_clouds(frames)):
        box = enclosing_box(clouds, **options)
        every = settings.make_observations(clouds, clearance=False).points
        lo, hi = every.min(axis=0), every.max(axis=0)
        assert (box[0] <= lo).all() and (box[1] >= hi).all()
        assert (box[0] >= lo - step - 1e-9).all() and (box[1] <= hi + step + 1e-9).all()
        exact = labelled_box(clouds, **options)
        assert (box[0] <= exact[0]).all() and (box[1] >= exact[1]).all()


def test_a_fitted_voxel_maps_kept_bounds_are_its_labelled_points_box(tmp_path):
    # The voxel map's extent after the fit: the labelled points without those the clearance
    # dropped, as the whole computation finds them; a map read from its file finds them again.
    from gpomap.apps.map3d import new_model
    from gpomap.io.mapfile import load_fitted_map, save_fitted_map

    clouds = _half_sphere_clouds()
    options = {"kernel": "se", "min_cell": 1.0, "max_cell": 1.0}
    model = new_model({"n_workers": 1}, **options).fit(clouds)
    np.testing.assert_array_equal(np.array(model.kept_bounds_), labelled_box(clouds, **options))
    save_fitted_map(model, tmp_path / "map.gpom")
    np.testing.assert_array_equal(np.array(load_fitted_map(tmp_path / "map.gpom").kept_bounds_), labelled_box(clouds, **options))


def test_the_exact_box_decides_where_the_enclosing_one_is_over_the_memory_limit(office_frames, tmp_path, monkeypatch):
    # A box round the rays too large for --memory-limit is not the map's: the labelled points'
    # box is asked, and the map is written over it as it would be without the larger box.
    import gpomap.cli.map3d as cli3d

    args = ["--kernel", "se", "--min-cell", "1.0", "--max-cell", "1.0", "--memory-limit", "0.5", "-q"]
    assert main(["map", str(office_frames), "-o", str(tmp_path / "a"), *args]) == 0
    monkeypatch.setattr(cli3d, "enclosing_box", lambda clouds, **options: np.array([[-1e4] * 3, [1e4] * 3]))
    assert main(["map", str(office_frames), "-o", str(tmp_path / "b"), *args]) == 0
    a, b = load_voxels(tmp_path / "a" / "map.npz"), load_voxels(tmp_path / "b" / "map.npz")
    assert a.spec == b.spec
    np.testing.assert_array_equal(a.probability, b.probability)


@pytest.fixture(scope="module")
def office_frames(tmp_path_factory):
    """Four 48 x 36 depth frames of the simulated office's first room, written as gpomap map reads them."""
    frames = s3.render_frames(s3.office_scene(), s3.PinholeCamera.from_fov(48, 36, 60), s3.office_poses()[:3])
    return s3.write_depth_frames(frames, tmp_path_factory.mktemp("office"))


def test_written_map_covers_every_hit_and_its_surfaces_hold_boxes(office_frames, tmp_path):
    out = tmp_path / "out"
    assert main(["map", str(office_frames), "-o", str(out), "--kernel", "se", "-q"]) == 0
    m = load_voxels(out / "map.npz")
    clouds = s3.frame_clouds(s3.render_frames(s3.office_scene(), s3.PinholeCamera.from_fov(48, 36, 60), s3.office_poses()[:3]))
    hits = np.concatenate([c.points[c.valid()] for c in clouds])
    # Every hit's voxel and the voxel beyond it (inside the wall it hit) are in the map.
    assert (m.spec.lower <= hits.min(axis=0) - m.spec.resolution).all()
    assert (m.spec.upper >= hits.max(axis=0) + m.spec.resolution).all()
    # The voxels map.bt calls occupied (occupied where rays went) each hold part of a box: no
    # surface grows into free space a ray saw.
    occupied = ((m.ternary == OCCUPIED) & m.seen).reshape(-1)
    centres = m.spec.centres()[occupied]
    scene = s3.office_scene()
    half = m.spec.resolution / 2
    holds = np.zeros(len(centres), dtype=bool)
    for lo, hi in zip(scene.lower, scene.upper):
        holds |= np.all((centres + half > lo) & (centres - half < hi), axis=1)
    assert occupied.sum() > 100 and holds.all()
