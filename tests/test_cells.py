"""The cell tree: partition, purity, size thresholds, ambiguous cells."""

import numpy as np
import pytest

from gpomap.cells import build_cells
from gpomap.errors import EmptyDataError
from gpomap.observations import observations_from_scans
from gpomap.simulate import paper_room_scans
from tests.world3d import ORIGINS, lidar_clouds


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def room(request):
    # The paper's room from planar scans, and a 3-D room from lidar clouds (cuboid cells).
    data = paper_room_scans() if request.param == 2 else lidar_clouds(ORIGINS, n_rays=400)
    obs = observations_from_scans(data, free_step=0.2)
    cells = build_cells(obs.points, obs.occupied, min_cell=0.5, max_cell=3.0)
    assert cells.lower.shape == (len(cells), request.param)
    return obs, cells


def test_every_point_in_exactly_one_cell(room):
    obs, cells = room
    order = np.sort(cells.member_order)
    np.testing.assert_array_equal(order, np.arange(len(obs.points)))
    owner = cells.cell_of_point()
    for i in range(0, len(cells), 37):
        np.testing.assert_array_equal(
            np.flatnonzero(owner == i), np.sort(cells.member_order[cells.member_offsets[i] : cells.member_offsets[i + 1]])
        )


def test_cells_are_pure_and_hold_their_points(room):
    obs, cells = room
    for i in range(len(cells)):
        idx = cells.member_order[cells.member_offsets[i] : cells.member_offsets[i + 1]]
        assert idx.size > 0, "empty cells are dropped"
        assert np.all(obs.occupied[idx] == cells.occupied[i])
        pts = obs.points[idx]
        assert np.all(pts >= cells.lower[i] - 1e-12) and np.all(pts <= cells.upper[i] + 1e-12)


def test_size_thresholds(room):
    _, cells = room
    side = (cells.node_upper - cells.node_lower).max(axis=1)
    assert side.max() <= 3.0 + 1e-9, "pure cells above max_cell split on"
    # Only cells that stopped on size may be ambiguous, and those are below min_cell.
    assert np.all(side[cells.ambiguous] < 0.5)
    # A min-size cell holding both classes becomes two cells over the same node, one per class.
    amb = np.flatnonzero(cells.ambiguous)
    assert amb.size > 0 and amb.size % 2 == 0
    pairs = cells.node_lower[amb].round(9)
    _, counts = np.unique(pairs, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_hand_made_case():
    # Four free points on the left, two hits on the right of a 4 x 1 box: one split separates them.
    pts = np.array([[0.0, 0.0], [0.5, 1.0], [1.0, 0.5], [1.5, 0.2], [3.0, 0.5], [4.0, 1.0]])
    occ = np.array([False, False, False, False, True, True])
    cells = build_cells(pts, occ, min_cell=0.1, max_cell=10.0)
    assert len(cells) == 2
    left = int(np.argmin(cells.lower[:, 0]))
    np.testing.assert_allclose(cells.lower[left], [0.0, 0.0])
    np.testing.assert_allclose(cells.upper[left], [2.0, 1.0])
    assert not cells.occupied[left] and cells.occupied[1 - left]
    tight = build_cells(pts, occ, min_cell=0.1, max_cell=10.0, box="tight")
    np.testing.assert_allclose(tight.upper[np.argmin(tight.lower[:, 0])], [1.5, 1.0])


def test_hand_made_case_in_3d():
    # Free points low, hits high in a 1 x 1 x 4 column: the longest axis (z) is split once.
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.5], [0.5, 0.2, 1.5], [0.3, 0.9, 3.0], [1.0, 0.0, 4.0]])
    occ = np.array([False, False, False, True, True])
    cells = build_cells(pts, occ, min_cell=0.1, max_cell=10.0)
    assert len(cells) == 2
    low = int(np.argmin(cells.lower[:, 2]))
    np.testing.assert_allclose(cells.lower[low], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(cells.upper[low], [1.0, 1.0, 2.0])
    np.testing.assert_allclose(cells.lower[1 - low], [0.0, 0.0, 2.0])
    assert not cells.occupied[low] and cells.occupied[1 - low]


def test_bad_arguments():
    with pytest.raises(EmptyDataError):
        build_cells(np.zeros((0, 2)), np.zeros(0, bool))
    with pytest.raises(ValueError, match="min_cell <= max_cell"):
        build_cells(np.zeros((2, 2)), np.zeros(2, bool), min_cell=2.0, max_cell=1.0)


FIELDS = ("lower", "upper", "node_lower", "node_upper", "occupied", "ambiguous", "member_offsets", "member_order")


def _both_paths(monkeypatch, *args):
    import gpomap._compiled_cells as compiled_cells

    monkeypatch.setattr(compiled_cells, "ENABLED", True)
    fast = build_cells(*args)
    monkeypatch.setattr(compiled_cells, "ENABLED", False)
    return fast, build_cells(*args)


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("box", ["node", "tight"])
@pytest.mark.parametrize("sizes", [(0.5, 0.5), (0.5, 3.0), (1.0, 1.0)])
def test_compiled_tree_is_the_python_tree(monkeypatch, dim, box, sizes):
    import gpomap._compiled_cells as compiled_cells

    if not compiled_cells.AVAILABLE:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(dim)
    n = {1: 60, 2: 1500, 3: 6000}[dim]  # some boxes pure, some ambiguous, in every dimension
    pts = rng.uniform(-3.0, 17.0, size=(n, dim))
    pts[: n // 30] = np.round(pts[: n // 30])  # on split planes, and repeated
    occ = rng.random(n) < 0.2
    fast, slow = _both_paths(monkeypatch, pts, occ, *sizes, box)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
    assert slow.ambiguous.any() and not slow.ambiguous.all()  # both kinds of cell occur


@pytest.mark.parametrize("limit", [1, 3, 40])
def test_compiled_tree_below_a_cut_forced_top(monkeypatch, limit):
    """The compiled tree sorts the points into its forced top's frontier in one pass; cut short
    (a few frontier nodes still to split), the walk below it splits them as the Python tree does."""
    import gpomap._compiled_cells as compiled_cells

    if not compiled_cells.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(compiled_cells, "FORCED_NODES", limit)
    rng = np.random.default_rng(7)
    pts = rng.uniform(-2.0, 9.0, size=(4000, 3))
    occ = rng.random(4000) < 0.3
    fast, slow = _both_paths(monkeypatch, pts, occ, 1.0, 1.0, "node")
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)


def test_compiled_tree_on_degenerate_inputs(monkeypatch):
    import gpomap._compiled_cells as compiled_cells

    if not compiled_cells.AVAILABLE:
        pytest.skip("numba is not installed")
    line = np.column_stack([np.linspace(0.0, 5.0, 50), np.full(50, 2.0)])  # a flat root
    cases = [
        (np.array([[1.0, 2.0]]), np.array([True])),  # one point
        (line, np.ones(50, bool)),  # one class
        (line, np.arange(50) % 2 == 0),  # both classes on a line
        (np.zeros((30, 2)), np.arange(30) % 3 == 0),  # every point at one place
    ]
    for pts, occ in cases:
        fast, slow = _both_paths(monkeypatch, pts, occ, 0.5, 3.0, "node")
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)


@pytest.mark.parametrize("compiled", [True, False])
def test_weighted_points_give_the_points_cells_counting_the_samples_they_stand_for(monkeypatch, compiled):
    from gpomap import _compiled_cells

    monkeypatch.setattr(_compiled_cells, "ENABLED", compiled)
    rng = np.random.default_rng(5)
    points = rng.uniform(0.0, 4.0, (600, 3))
    occupied = points[:, 0] > 3.2
    weights = rng.integers(1, 6, 600).astype(np.int32)
    plain = build_cells(points, occupied, 0.5, 1.0)
    weighted = build_cells(points, occupied, 0.5, 1.0, weights=weights)
    np.testing.assert_array_equal(weighted.lower, plain.lower)
    np.testing.assert_array_equal(weighted.member_order, plain.member_order)
    by_hand = [
        sum(int(weights[j]) for j in plain.member_order[a:b]) for a, b in zip(plain.member_offsets[:-1], plain.member_offsets[1:])
    ]
    np.testing.assert_array_equal(weighted.counts, by_hand)
    np.testing.assert_array_equal(weighted.to_supports().counts, np.array(by_hand, dtype=float))
    with pytest.raises(ValueError, match="weights must have shape"):
        build_cells(points, occupied, 0.5, 1.0, weights=weights[:-1])
