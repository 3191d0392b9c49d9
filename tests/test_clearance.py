"""Free samples near hits: the box pre-filter gives the brute-force answer exactly."""

import numpy as np
import pytest
from scipy.spatial.distance import cdist

import gpomap._compiled_clearance as compiled_clearance
import gpomap.observations as observations
from gpomap.observations import free_near_hits


def brute_force(points: np.ndarray, occupied: np.ndarray, clearance: float) -> np.ndarray:
    d = cdist(points[~occupied], points[occupied]).min(axis=1)
    out = np.zeros(len(points), bool)
    out[np.flatnonzero(~occupied)[d < clearance]] = True
    return out


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("clearance", [0.05, 0.3, 1.7])
@pytest.mark.parametrize("lattice", ["fine", "coarse", "none"])  # the most boxes per clearance, 1, no lattice
@pytest.mark.parametrize("compiled", [False, True])
def test_free_near_hits_equals_brute_force(dim: int, clearance: float, lattice: str, compiled: bool, monkeypatch) -> None:
    if compiled and not compiled_clearance.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(compiled_clearance, "ENABLED", compiled)
    rng = np.random.default_rng(dim * 10 + int(clearance * 10))
    # Negative and positive coordinates, and points on box borders (multiples of the clearance).
    pts = rng.uniform(-8.0, 12.0, size=(3000, dim)) * clearance * (2.0 if dim == 3 else 4.0)
    pts[:300] = np.round(pts[:300] / clearance) * clearance
    occ = rng.random(3000) < 0.1
    span = pts.max(axis=0) - pts.min(axis=0)
    if lattice != "fine":  # a budget of boxes that allows 1 per clearance, or none
        budget = int(np.prod(np.floor(span / clearance) + 2)) if lattice == "coarse" else 1
        monkeypatch.setattr(observations, "MAX_CLEARANCE_BOXES", budget)
    expected = {"fine": observations.CLEARANCE_SUBDIVISIONS[dim], "coarse": 1, "none": 0}[lattice]
    assert observations._subdivisions(span, clearance) == expected
    got = free_near_hits(pts, occ, clearance)
    np.testing.assert_array_equal(got, brute_force(pts, occ, clearance))
    assert got.any() and not got.all()  # both answers occur, so the comparison means something


@pytest.mark.parametrize("compiled", [False, True])
def test_free_near_hits_far_apart_and_degenerate(compiled: bool, monkeypatch) -> None:
    monkeypatch.setattr(compiled_clearance, "ENABLED", compiled and compiled_clearance.AVAILABLE)
    # Two clusters kilometres apart: boxes between them are never formed.
    occ = np.array([True, False, False, True, False])
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.5, 0.0], [5000.0, -3000.0], [5000.0, -2999.8]])
    np.testing.assert_array_equal(free_near_hits(pts, occ, 0.3), [False, True, False, False, True])
    assert not free_near_hits(pts, np.zeros(5, bool), 0.3).any()
    assert not free_near_hits(pts, np.ones(5, bool), 0.3).any()


@pytest.mark.skipif(not compiled_clearance.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_clearance_on_box_borders_and_its_budget(dim: int) -> None:
    # Samples and hits on a lattice one clearance apart, shifted by less than a rounding error:
    # pairs exactly a clearance apart are not near, pairs a hair closer are.
    clearance = 0.3
    rng = np.random.default_rng(dim)
    lattice = rng.integers(-20, 20, size=(2000, dim)) * clearance + 1e-12 * rng.standard_normal((2000, dim))
    hits, free = lattice[:200], lattice[200:]
    got = compiled_clearance.near_hits(free, hits, clearance, max_boxes=10**7)
    assert got is not None
    d = cdist(free, hits).min(axis=1)
    np.testing.assert_array_equal(got, d < clearance)
    assert got.any() and not got.all()
    # Scattered samples, negative coordinates, a clearance that is not a round number.
    pts = rng.uniform(-3.0, 7.0, size=(4000, dim))
    got = compiled_clearance.near_hits(pts[400:], pts[:400], 0.37, max_boxes=10**7)
    assert got is not None
    np.testing.assert_array_equal(got, cdist(pts[400:], pts[:400]).min(axis=1) < 0.37)
    # Past the budget of boxes it declines, and free_near_hits falls back on the numpy path.
    assert compiled_clearance.near_hits(free, hits, clearance, max_boxes=10) is None


@pytest.mark.skipif(not compiled_clearance.AVAILABLE, reason="numba is not installed")
def test_compiled_clearance_on_a_wall_scanned_again_and_again() -> None:
    # Hundreds of hits a box along a wall, free samples on both sides at all distances: the
    # boxes' bounding boxes skip or take whole boxes, and the answer is still brute force's.
    rng = np.random.default_rng(5)
    wall = np.column_stack([rng.uniform(0.0, 3.0, 20000), rng.normal(0.0, 0.01, 20000)])
    free = rng.uniform([-0.5, -1.0], [3.5, 1.0], size=(4000, 2))
    got = compiled_clearance.near_hits(free, wall, 0.3, max_boxes=10**7)
    assert got is not None
    np.testing.assert_array_equal(got, cdist(free, wall).min(axis=1) < 0.3)
    assert got.any() and not got.all()


@pytest.mark.skipif(not compiled_clearance.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("dense_hits", [np.inf, 0.0, 100.0])  # the coarsest boxes, the finest, as dense as the hits say
def test_compiled_clearance_at_every_box_size_on_a_dense_floor(dense_hits: float, monkeypatch) -> None:
    # A floor and a wall of a depth frame's density, free samples at all distances above and
    # beside them, more of them than hits (finer boxes are taken only then): every box size gives
    # brute force's answer.
    monkeypatch.setattr(compiled_clearance, "DENSE_HITS", dense_hits)
    rng = np.random.default_rng(8)
    floor = np.column_stack([rng.uniform(0.0, 1.2, 3000), rng.uniform(0.0, 1.2, 3000), rng.normal(0.0, 0.005, 3000)])
    wall = np.column_stack([rng.uniform(0.0, 1.2, 1000), rng.normal(1.2, 0.005, 1000), rng.uniform(0.0, 1.0, 1000)])
    hits = np.vstack([floor, wall])
    free = rng.uniform([-0.4, -0.4, -0.5], [1.6, 1.6, 1.2], size=(6000, 3))
    got = compiled_clearance.near_hits(free, hits, 0.3, max_boxes=10**7)
    assert got is not None
    np.testing.assert_array_equal(got, cdist(free, hits).min(axis=1) < 0.3)
    assert got.any() and not got.all()


@pytest.mark.skipif(not compiled_clearance.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_clearance_asked_of_every_point_with_the_hits_skipped(dim: int) -> None:
    # A block's points handed whole, its hits skipped: brute force's answer for its free points,
    # False for its hits, whether the hits widen the lattice's box or not.
    rng = np.random.default_rng(11 + dim)
    pts = rng.uniform(-2.0, 5.0, size=(3000, dim))
    pts[:5] = rng.uniform(-6.0, 9.0, size=(5, dim))  # some hits outside the free points' box
    occupied = np.zeros(3000, dtype=bool)
    occupied[:300] = True
    got = compiled_clearance.near_hits(pts, pts[occupied], 0.3, max_boxes=10**7, skip=occupied)
    assert got is not None
    want = np.zeros(3000, dtype=bool)
    want[~occupied] = cdist(pts[~occupied], pts[occupied]).min(axis=1) < 0.3
    np.testing.assert_array_equal(got, want)
    assert got.any() and not got[~occupied].all()


def test_hits_filed_by_box_keep_a_stable_argsorts_order() -> None:
    # The counting sort against numpy's stable argsort: boxes in any order, many hits a box,
    # boxes left empty.
    rng = np.random.default_rng(3)
    points = rng.normal(size=(5000, 3))
    box = rng.integers(0, 40, 5000) * 3  # every third box only
    starts = np.zeros(121, dtype=np.int64)
    np.cumsum(np.bincount(box, minlength=120), out=starts[1:])
    out = np.empty_like(points)
    compiled_clearance._filed_by_box(points, box.astype(np.int64), starts, out)
    np.testing.assert_array_equal(out, points[np.argsort(box, kind="stable")])
