"""Scoring against a true plan (:mod:`gpomap.truth`): which pixels a log observed, and the metrics."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from gpomap.evaluation import lookup, lookup_occupied
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.metrics import brier_score
from gpomap.scans import Scan
from gpomap.truth import PlanTruth, TruthPoints, score_plan


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.hypot(*(points - (a + t[:, None] * ab)).T)


def test_a_plan_image_puts_its_pixels_where_the_worlds_readme_says(tmp_path) -> None:
    img = np.full((3, 4), 255, np.uint8)
    img[0, 3] = 0  # top right
    img[2, 0] = 0  # bottom left
    Image.fromarray(img).save(tmp_path / "plan.png")
    plan = PlanTruth.from_image(tmp_path / "plan.png", 0.5, (10.0, 20.0))
    centres = plan.centres().reshape(3, 4, 2)
    # Pixel (row, col) has its centre at origin + ((col + 0.5) res, (H - row - 0.5) res).
    np.testing.assert_allclose(centres[0, 3], [10.0 + 3.5 * 0.5, 20.0 + 2.5 * 0.5])
    np.testing.assert_allclose(centres[2, 0], [10.25, 20.25])
    assert plan.occupied[0, 3] and plan.occupied[2, 0] and plan.occupied.sum() == 2


def test_the_observed_pixels_are_those_near_the_beams() -> None:
    plan = PlanTruth(np.zeros((100, 100), bool), (0.0, 0.0), (0.01, 0.01))
    # Two beams from (0.2, 0.5): one ends at 0.8 m (a hit at (1.0, 0.5) is off the plan), one
    # straight up to a hit at (0.2, 0.9).
    scan = Scan([0.2, 0.5, 0.0], np.array([0.0, np.pi / 2]), np.array([0.8, 0.4]), max_range=5.0)
    seen = plan.observed([scan])
    centres = plan.centres()
    sensor = np.array([0.2, 0.5])
    d = np.minimum(
        _segment_distance(centres, sensor, np.array([1.0, 0.5])), _segment_distance(centres, sensor, np.array([0.2, 0.9]))
    )
    # Brute force: within the radius of the beams (sampled every 0.01 m: at most 0.005 m off
    # them, and 0.0035 m more where the points are merged) observed, beyond it not.
    assert seen[d <= 0.025 - 0.009].all()
    assert not seen[d > 0.025 + 0.009].any()
    assert seen.sum() > 0.9 * (d <= 0.025).sum()


def test_unknown_pixels_of_a_plan_are_never_scored() -> None:
    known = np.ones((20, 20), bool)
    known[:, 10:] = False
    plan = PlanTruth(np.zeros((20, 20), bool), (0.0, 0.0), (0.05, 0.05), known)
    scan = Scan([0.05, 0.5, 0.0], np.array([0.0]), np.array([0.9]), max_range=5.0)
    points = TruthPoints.of(plan, [scan])
    assert points.points.size and (points.points[:, 0] < 0.5).all()


def test_boundary_pixels_lie_within_a_tenth_of_a_metre_of_a_wall() -> None:
    occupied = np.zeros((1, 50), bool)
    occupied[0, 25] = True  # centre at x = 0.255
    plan = PlanTruth(occupied, (0.0, 0.0), (0.01, 0.01))
    x = plan.centres()[:, 0]
    np.testing.assert_array_equal(plan.boundary(), np.abs(x - 0.255) <= 0.1 + 1e-9)


def test_score_plan_by_hand() -> None:
    truth = TruthPoints(np.zeros((4, 2)), np.array([True, False, False, True]), np.array([True, True, False, False]))
    p = np.array([0.9, 0.2, 0.4, 0.6])
    out = score_plan(truth, p, occupied=np.array([True, False, True, False]))
    assert out["log_loss"] == pytest.approx(-np.mean(np.log([0.9, 0.8, 0.6, 0.6])))
    assert out["brier"] == pytest.approx((0.01 + 0.04 + 0.16 + 0.16) / 4)
    assert out["auc"] == 1.0 and out["boundary_auc"] == 1.0
    assert out["iou"] == 1.0  # p > 0.5 is exactly the occupied pixels
    assert out["ternary_iou"] == pytest.approx(1 / 3)  # one of three pixels either calls occupied
    assert (out["n_points"], out["n_occupied"]) == (4, 2)


def test_a_written_map_is_read_at_the_pixels_cells() -> None:
    grid = GridSpec((0.0, 0.0), 0.5, (2, 2))
    om = OccupancyMap(grid, np.array([[0.1, 0.9], [0.3, 0.7]]), thresholds=(0.2, 0.5))
    points = np.array([[0.1, 0.1], [0.9, 0.1], [0.2, 0.8], [5.0, 5.0]])
    prob, called = lookup(om, points), lookup_occupied(om, points)
    np.testing.assert_allclose(prob, [0.1, 0.9, 0.3, 0.5])  # outside the map: a coin
    np.testing.assert_array_equal(called, [False, True, False, False])


def test_brier_score_by_hand() -> None:
    assert brier_score([True, False], [1.0, 0.0]) == 0.0
    assert brier_score([True, False, True], [0.5, 0.5, 0.5]) == pytest.approx(0.25)
    assert brier_score([True, False], [0.8, 0.4]) == pytest.approx((0.04 + 0.16) / 2)
    with pytest.raises(ValueError):
        brier_score([True], [1.5])


def test_a_world_drawn_as_a_plan_marks_every_pixel_its_geometry_says_is_occupied() -> None:
    from matplotlib.path import Path

    from gpomap.simulate import World

    # Walls at odd angles and a solid triangle; a pixel is occupied within half a pixel of a wall
    # (measured to every wall) or inside the triangle (matplotlib's point-in-polygon test).
    triangle = np.array([(2.0, 2.2), (2.8, 2.4), (2.3, 2.9)])
    world = World(segments=[(0.0, 0.0, 3.0, 0.4), (0.3, 2.9, 2.7, 1.1), (1.5, 0.0, 1.5, 3.0)], obstacles=[triangle])
    plan = PlanTruth.from_world(world, 0.01)
    centres = plan.centres()
    expected = (world.distance_to_walls(centres) <= 0.005) | Path(triangle).contains_points(centres)
    assert expected.sum() > 1000
    np.testing.assert_array_equal(plan.occupied.ravel(), expected)
