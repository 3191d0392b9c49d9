"""A scan's calibration points made a run or a few at a time: the same as made whole."""

from __future__ import annotations

import numpy as np
import pytest

import gpomap.heldout as heldout
from gpomap.clouds import CloudScan
from gpomap.heldout import CALIBRATION_HIT_MARGIN, CalibrationPoints, calibration_points, draw_calibration_points
from gpomap.observations import Rays, natural_subsample, ray_free_points
from gpomap.scans import Scan
from gpomap.simulate import paper_room_scans
from tests.world3d import ORIGINS, lidar_clouds


def _awkward_scan() -> Scan:
    """Beams whose free stretch ends exactly on a step (a sample on its limit), shorter than one
    step (no free point), invalid, and no-return ones (capped)."""
    step = 0.1
    ranges = np.array(
        [1.0 + CALIBRATION_HIT_MARGIN, 0.3 + CALIBRATION_HIT_MARGIN, 0.05, np.nan, -1.0, 8.0, 2.37, 0.0, 8.0, 3.0 * step]
    )
    angles = np.linspace(-1.5, 1.5, ranges.size)
    return Scan(pose=np.array([0.3, -0.2, 0.4]), angles=angles, ranges=ranges, max_range=8.0)


def _scans() -> list[Scan | CloudScan]:
    clouds = lidar_clouds(ORIGINS[:2], n_rays=200)
    invalid = CloudScan(np.zeros(3), np.full((4, 3), np.nan))
    return [_awkward_scan(), *paper_room_scans(n_beams=90, seed=0)[:2], *clouds, invalid]


@pytest.mark.parametrize("cap", [None, 2.0])
@pytest.mark.parametrize("k", range(6))
def test_runs_and_draws_are_the_whole_scans_points(k: int, cap: float | None) -> None:
    scan = _scans()[k]
    want, occ = calibration_points(scan, 0.1, cap)
    held = CalibrationPoints(scan, 0.1, cap)
    assert (held.size, held.n_free, held.n_occupied) == (occ.size, int((~occ).sum()), int(occ.sum()))
    if k == 0:
        # The awkward beams: a sample exactly at 1.0 m and at 0.3 m, none on the 0.05 m beam.
        assert held.n_occupied == 5 and held.n_free > 0
    for max_points in (1, 7, 50, 10**6):
        spans = held.spans(max_points)
        # Back to back, from the first point to the last.
        assert [a for a, _ in spans[1:]] == [b for _, b in spans[:-1]]
        assert (spans[0][0], spans[-1][1]) == (0, held.size) if spans else held.size == 0
        made = [held.between(a, b) for a, b in spans]
        got = np.concatenate([p for p, _ in made]) if made else np.zeros((0, want.shape[1]))
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.concatenate([o for _, o in made]) if made else occ, occ)
    rng = np.random.default_rng(k)
    for _ in range(5):
        # Any stretch (across rays and the hits), and any sorted draw.
        a, b = np.sort(rng.integers(0, held.size + 1, 2))
        p, o = held.between(int(a), int(b))
        np.testing.assert_array_equal(p, want[a:b])
        np.testing.assert_array_equal(o, occ[a:b])
        index = np.sort(rng.choice(held.size, min(held.size, 37), replace=False))
        p, o = held.take(index)
        np.testing.assert_array_equal(p, want[index])
        np.testing.assert_array_equal(o, occ[index])
        assert p.dtype == np.float64
    p, o = held.take(np.arange(held.size))
    np.testing.assert_array_equal(p, want)
    np.testing.assert_array_equal(o, occ)


def test_runs_hold_whole_rays_of_at_most_so_many_points() -> None:
    scan = paper_room_scans(n_beams=90, seed=0)[0]
    held = CalibrationPoints(scan, 0.1)
    rays = Rays.of(scan)
    lengths = rays.free_lengths(CALIBRATION_HIT_MARGIN, None)
    use = lengths > 0
    _, ray = ray_free_points(np.broadcast_to(rays.origin, (int(use.sum()), 2)), rays.directions[use], lengths[use], 0.1)
    longest = int(np.bincount(ray).max())
    for max_points in (1, longest, 3 * longest):
        for a, b in held.spans(max_points):
            if b <= held.n_free:
                # A run begins and ends at a ray's border, and is one ray when that is over the bound.
                assert a == 0 or ray[a] != ray[a - 1]
                assert b == held.n_free or ray[b] != ray[b - 1]
                assert b - a <= max_points or ray[a] == ray[b - 1]
            else:
                assert a >= held.n_free and b - a <= max_points


@pytest.mark.parametrize("run_points", [10**9, 100], ids=["counted-kept", "made-again"])
def test_points_drawn_by_number_are_those_drawn_from_all(run_points: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whether the counted scans are kept for the draw or made again, the draw is the uniform draw
    from every scan's points concatenated in scan order, each point with its scan."""
    monkeypatch.setattr(heldout, "RUN_POINTS", run_points)
    scans = paper_room_scans(n_beams=90, seed=0)[:6]
    parts = [calibration_points(s, 0.1, 2.0) for s in scans]
    pts, occ = np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])
    scan = np.repeat(np.arange(len(scans)), [o.size for _, o in parts])
    keep = natural_subsample(occ.size, 300, 4)
    drawn = draw_calibration_points(scans, 300, 4, 0.1, 2.0)
    assert (drawn.total, drawn.n_occupied) == (occ.size, int(occ.sum())) and keep.size == 300
    np.testing.assert_array_equal(drawn.points, pts[keep])
    np.testing.assert_array_equal(drawn.occupied, occ[keep])
    np.testing.assert_array_equal(drawn.scan, scan[keep])
