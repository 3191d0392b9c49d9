"""Ray evidence (hit and miss counts per cell) and its fusion with the GP's probability."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest

from gpomap import _compiled_counts, fusion, lattice
from gpomap.clouds import CloudScan
from gpomap.evidence import NEAR_END, RayEvidence, lattice_grid, next_to_hits
from gpomap.fusion import (
    CALIBRATION_BOUNDS,
    SURPRISE_RATE,
    EvidenceCalibration,
    fit_calibration,
    gp_sampling_factor,
    surface_misses,
)
from gpomap.grid import GridSpec, coarse_grid, interpolate_to
from gpomap.heldout import calibration_points
from gpomap.mapping import AreaGPOM
from gpomap.robot_path import PATH_RADIUS
from gpomap.scans import Scan
from gpomap.simulate import paper_room_scans
from gpomap.voxels import VoxelSpec


def _scan(x: float, y: float, angles: list[float], ranges: list[float], max_range: float = 5.0) -> Scan:
    return Scan(pose=np.array([x, y, 0.0]), angles=np.array(angles), ranges=np.array(ranges), max_range=max_range)


GRID = GridSpec((0.0, 0.0), 0.1, (3, 20))
# The same row of cells in 3-D: voxels [iz, iy, ix], the rays run along x at y = 0.15, z = 0.25.
VOXELS = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 3, 20))


def _along_x(dim: int, ranges: list[float], max_range: float = 5.0, y: float = 0.15) -> Scan | CloudScan:
    """Beams (rays) from the centre of cell 0 along +x: a planar scan, or a cloud at z = 0.25."""
    if dim == 2:
        return _scan(0.05, y, [0.0] * len(ranges), ranges, max_range)
    o = np.array([0.05, y, 0.25])
    r = np.array(ranges)
    return CloudScan(o, o + np.column_stack([r, 0 * r, 0 * r]), hit=r < max_range, max_range=max_range)


@pytest.fixture(params=["compiled", "numpy"])
def counting(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test on both ways of counting: numba's pass over the entries and numpy's sorts."""
    if request.param == "compiled" and not _compiled_counts.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(_compiled_counts, "ENABLED", request.param == "compiled")
    return str(request.param)


def _row(a: np.ndarray, dim: int) -> np.ndarray:
    """The row of cells the rays run along (y index 1; z index 2 in 3-D)."""
    return a[1] if dim == 2 else a[2, 1]


@pytest.mark.parametrize("dim", [2, 3])
def test_counts_along_one_beam_by_hand(dim: int, counting: str) -> None:
    # From the centre of cell 0 along +x to x = 1.07: crosses cells 0..9 of the row, ends in 10.
    hits, misses, near, silent = RayEvidence.from_scans([_along_x(dim, [1.02])]).counts(GRID if dim == 2 else VOXELS)
    assert silent.sum() == 0  # its beam returned
    assert hits.sum() == 1 and _row(hits, dim)[10] == 1
    assert _row(misses, dim)[:10].tolist() == [1] * 10 and misses.sum() == 10
    # Near misses: cells whose centres lie within NEAR_END (0.2 m) of the end: cell 9 (centre
    # 0.95, 0.12 m away) and not cell 8 (0.85, 0.22 m).
    assert NEAR_END == 0.2
    assert np.flatnonzero(_row(near, dim)).tolist() == [9] and near.sum() == 1


@pytest.mark.parametrize("dim", [2, 3])
def test_a_scans_near_share_is_its_beams_that_end_near(dim: int, counting: str) -> None:
    # One beam ends at x = 0.57 (cell 5), another of the same scan at 0.64 (cell 6): cell 4
    # (centre 0.45) is within 0.2 m of both ends, so a whole near miss; cell 3 (0.35) of neither;
    # cell 5 is half the first beam's hit, half the second's near miss.
    grid = GRID if dim == 2 else VOXELS
    hits, misses, near, _ = RayEvidence.from_scans([_along_x(dim, [0.52, 0.59])]).counts(grid)
    assert np.flatnonzero(_row(near, dim)).tolist() == [4, 5] and _row(near, dim)[[4, 5]].tolist() == [1.0, 0.5]
    assert _row(hits, dim)[[5, 6]].tolist() == [0.5, 1.0] and _row(misses, dim)[[3, 4, 5]].tolist() == [1.0, 1.0, 0.5]
    # A third beam of the same scan going on to x = 1.57 sees through cells 4 to 6: a third of each
    # of cells 4 and 5's updates is a far miss; cell 14 is near its own end only.
    hits, misses, near, _ = RayEvidence.from_scans([_along_x(dim, [0.52, 0.59, 1.52])]).counts(grid)
    # (Shares are whole 256ths: a third is 85 of them.)
    np.testing.assert_array_equal(_row(hits, dim)[[4, 5, 6, 15]], [0, 85 / 256, 1 / 2, 1])
    np.testing.assert_array_equal(_row(misses, dim)[[4, 5, 6, 14]], [1, 171 / 256, 1 / 2, 1])
    np.testing.assert_array_equal(_row(near, dim)[[3, 4, 5, 6, 13, 14]], [0, 171 / 256, 85 / 256, 0, 0, 1])


@pytest.mark.parametrize("dim", [2, 3])
def test_one_update_per_cell_per_scan_shared_among_its_beams(dim: int, counting: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from gpomap import evidence

    # Two beams of one scan: one ends in cell 5, the other passes through it to cell 12.
    s = _along_x(dim, [0.5, 1.2])
    grid = GRID if dim == 2 else VOXELS
    hits, misses, *_ = RayEvidence.from_scans([s]).counts(grid)
    assert _row(hits, dim)[5] == 0.5 and _row(misses, dim)[5] == 0.5  # one beam of two ended there
    assert _row(hits, dim)[12] == 1
    assert _row(misses, dim)[0:5].tolist() == [1] * 5  # crossed by both beams, counted once
    np.testing.assert_array_equal((hits + misses)[(hits + misses) > 0], 1.0)  # one update a cell
    # The same scan twice: every count doubles.
    h2, m2, *_ = RayEvidence.from_scans([s, s]).counts(grid)
    np.testing.assert_array_equal(h2, 2 * hits)
    np.testing.assert_array_equal(m2, 2 * misses)
    # OctoMap's rule: the hit wins the whole update over the same scan's miss.
    monkeypatch.setattr(evidence, "SHARED_UPDATES", False)
    hits, misses, *_ = RayEvidence.from_scans([s]).counts(grid)
    assert _row(hits, dim)[5] == 1 and _row(misses, dim)[5] == 0 and _row(misses, dim)[0:5].tolist() == [1] * 5


@pytest.mark.parametrize("dim", [2, 3])
def test_no_return_beam_gives_misses_to_the_cap_and_no_hit(dim: int, counting: str) -> None:
    s = _along_x(dim, [5.0], max_range=5.0)
    hits, misses, near, silent = RayEvidence.from_scans([s], no_return_cap=0.7).counts(GRID if dim == 2 else VOXELS)
    assert hits.sum() == 0
    assert _row(misses, dim)[:8].tolist() == [1] * 8 and misses.sum() == 8
    assert near.sum() == 0  # a beam that did not return has no end to be near
    np.testing.assert_array_equal(silent, misses)  # and every update it made is a silent one


@pytest.mark.parametrize("dim", [2, 3])
def test_a_silent_update_is_a_scans_whose_beams_there_all_returned_nothing(dim: int, counting: str) -> None:
    from gpomap.fusion import only_silent

    grid = GRID if dim == 2 else VOXELS
    # Scan 1: a beam returned at x = 0.57 (cells 0 to 4 crossed, a hit in 5) and one returned
    # nothing, free to the cap 0.98 from x = 0.05 (cells 0 to 10). Scan 2: one beam returned at
    # x = 0.87 (cells 0 to 7 crossed, a hit in 8).
    first = _along_x(dim, [0.52, 5.0], max_range=5.0)
    second = _along_x(dim, [0.82])
    *_, silent = RayEvidence.from_scans([first], no_return_cap=0.98).counts(grid)
    # Cells 0 to 5 held the returned beam too; 6 to 10 the silent beam alone.
    assert _row(silent, dim)[:12].tolist() == [0] * 6 + [1] * 5 + [0] and silent.sum() == 5
    hits, misses, _, silent = RayEvidence.from_scans([first, second], no_return_cap=0.98).counts(grid)
    assert _row(silent, dim)[:12].tolist() == [0] * 6 + [1] * 5 + [0]
    # Cells 6 and 7 were crossed and cell 8 ended in by the second scan's returned beam: of the
    # silent cells only 9 and 10 are left to the silent beam alone.
    cells = _row(only_silent(hits, misses, silent), dim)
    assert np.flatnonzero(cells).tolist() == [9, 10]
    # The robot's path through a cell rules it out too.
    path = np.zeros(grid.shape, dtype=int)
    _row(path, dim)[9] = 1
    assert np.flatnonzero(_row(only_silent(hits, misses, silent, path), dim)).tolist() == [10]


def test_counts_add_over_scans_and_batches(monkeypatch: pytest.MonkeyPatch, counting: str) -> None:
    scans = paper_room_scans()[:6]
    ev = RayEvidence.from_scans(scans)
    grid = lattice_grid(ev.extent(), 0.05, margin=0.05)
    whole = ev.counts(grid)
    parts = [ev.counts(grid, scans=np.array([k])) for k in range(len(scans))]
    assert 0 < whole.near.sum() < whole.misses.sum() and np.all(whole.near <= whole.misses)
    for j in range(len(whole)):
        np.testing.assert_array_equal(whole[j], sum(p[j] for p in parts))
    # Tiny batches (one scan each) give the same counts as one batch.
    import gpomap.evidence as evidence

    monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", 1)
    for a, b in zip(ev.counts(grid), whole, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not _compiled_counts.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("budget", [1 << 22, 2000])
def test_compiled_counts_equal_numpys_and_keep_the_same_scans_cells(monkeypatch: pytest.MonkeyPatch, budget: int) -> None:
    import gpomap.evidence as evidence

    # The room's scans (most beams return) and 3-D clouds with no-returns, in one batch or many.
    rng = np.random.default_rng(3)
    clouds = []
    for _ in range(5):
        o = rng.uniform([0.5, 0.5, 0.2], [3.0, 2.0, 0.8])
        ends = o + rng.normal(0, 0.8, (80, 3))
        clouds.append(CloudScan(o, ends, hit=np.linalg.norm(ends - o, axis=1) < 1.2, max_range=1.2))
    room = paper_room_scans()[:8]
    monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", budget)
    for scans, res in ((room, 0.05), (clouds, 0.1)):
        got = {}
        for path in ("compiled", "numpy"):
            monkeypatch.setattr(_compiled_counts, "ENABLED", path == "compiled")
            ev = RayEvidence.from_scans(scans)
            grid = lattice_grid(ev.extent(), res, margin=res)
            got[path] = (ev.counts(grid, keep=np.array([1, 4])), dict(ev._kept))
        (c_counts, c_kept), (n_counts, n_kept) = got["compiled"], got["numpy"]
        assert c_counts.hits.sum() > 0 and 0 < c_counts.near.sum() < c_counts.misses.sum()
        for a, b in zip(c_counts, n_counts, strict=True):
            np.testing.assert_array_equal(a, b)
        assert sorted(k for _, k in c_kept) == sorted(k for _, k in n_kept) == [1, 4]
        for key, cells in c_kept.items():
            for a, b in zip(cells, n_kept[key], strict=True):
                np.testing.assert_array_equal(a, b)


def test_lattice_cells_do_not_depend_on_the_extent() -> None:
    a = lattice_grid((0.12, 3.0, -1.0, 2.0), 0.05)
    b = lattice_grid((-2.0, 3.0, -1.3, 2.0), 0.05)
    c = lattice_grid((0.12, 3.0, -1.0, 2.0, 0.33, 1.0), 0.05)
    assert isinstance(c, VoxelSpec) and c.shape[0] == 14
    for g in (a, b, c):
        k = np.array(g.origin) / 0.05
        np.testing.assert_allclose(k, np.round(k), atol=1e-9)


def test_calibration_formula_by_hand() -> None:
    cal = EvidenceCalibration(hit_weight=2.0, prior_weight=2.0, near_weight=0.25, near_hit_weight=0.5)
    # (2 * 1 + 2 * 0.5) / (2 * 1 + 1 + 2) = 0.6, then one surprise in a hundred: 0.005 + 0.99 * 0.6.
    assert cal.posterior_mean(np.array([0.5]), np.array([2.0]), np.array([1]))[0] == pytest.approx(0.6)
    assert SURPRISE_RATE == 1e-2
    assert cal(np.array([0.5]), np.array([2.0]), np.array([1]))[0] == pytest.approx(0.599)
    # A hundred scans saw through a cell and none ended there: not 1e-4 (the GP's 0.01 weighing 2
    # against 100), but 0.005 + 0.99 * 0.02 / 102.
    assert cal(np.array([0.01]), np.array([0]), np.array([100]))[0] == pytest.approx(0.005 + 0.99 * 0.02 / 102)
    # 3 hits of weight 2 and 4 near misses worth half a hit each: 6 + 2 = 8 weighted hits.
    assert cal.hits(np.array([3]), np.array([4]))[0] == pytest.approx(8.0)
    # 5 misses of which 4 near, and 3 steps of the path worth PATH_HITS = 10 hits of weight 2 each:
    # 1 + 4 * 0.25 + 3 * 10 * 2 = 62 weighted misses.
    assert cal.misses(np.array([5]), np.array([4]), np.array([3]))[0] == pytest.approx(62.0)
    # A cell crossed by 4 scans, each ending its beam just beyond it: 4 * 0.5 weighted hits against
    # 4 * 0.25 weighted misses, (2 + 2 * 0.5) / (2 + 1 + 2) = 0.6 from the GP's 0.5.
    h, m = cal.hits(np.array([0]), np.array([4])), cal.misses(np.array([4]), np.array([4]))
    assert cal.posterior_mean(np.array([0.5]), h, m)[0] == pytest.approx(0.6)
    # No counts: the GP's probability.
    assert cal.posterior_mean(np.array([0.8]), np.array([0]), np.array([0]))[0] == pytest.approx(0.8)
    # Surface misses worth a tenth of a miss: of 5 misses, 4 near (0.25 each) and the far one beside a
    # hit (0.1), 1.1 weighted misses; away from hits the far one is a whole miss, 2.0.
    walled = EvidenceCalibration(2.0, 2.0, 0.25, 0.5, surface_weight=0.1)
    beside = surface_misses(np.array([5, 5]), np.array([4, 4]), np.array([True, False]))
    np.testing.assert_array_equal(beside, [1.0, 0.0])
    np.testing.assert_allclose(walled.misses(np.array([5, 5]), np.array([4, 4]), surface=beside), [1.1, 2.0])
    # A fitted surprise rate of 0.1 instead: 0.05 + 0.9 * 0.6.
    surprised = EvidenceCalibration(2.0, 2.0, 0.25, 0.5, surprise_rate=0.1)
    assert surprised(np.array([0.5]), np.array([2.0]), np.array([1]))[0] == pytest.approx(0.59)
    # The defaults are the counting grid with the GP in place of its prior 1/2: (3 + 1) / (3 + 5 + 2),
    # a near miss a miss and no hit.
    default = EvidenceCalibration()
    assert default.posterior_mean(np.array([0.5]), default.hits(np.array([3]), np.array([2])), np.array([5]))[0] == pytest.approx(
        0.4
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_next_to_hits_by_hand(dim: int) -> None:
    # One hit in the middle of a 5^d block, one in a corner: each cell with a hit and the cells round it.
    hits = np.zeros((5,) * dim, dtype=np.int32)
    hits[(2,) * dim] = 3
    hits[(0,) * dim] = 1
    want = np.zeros(hits.shape, bool)
    want[(slice(1, 4),) * dim] = True
    want[(slice(0, 2),) * dim] = True
    np.testing.assert_array_equal(next_to_hits(hits), want)
    assert not next_to_hits(np.zeros((4,) * dim, dtype=np.int32)).any()


def test_calibration_points_follow_the_protocol() -> None:
    s = _scan(0.0, 0.0, [0.0, np.pi / 2], [1.0, 5.0], max_range=5.0)
    pts, occ = calibration_points(s, step=0.1, no_return_cap=0.5)
    free = pts[~occ]
    # Returned beam: free at 0.1 .. 0.9 (0.1 short of the hit), and the hit at 1.0.
    along_x = np.sort(free[np.abs(free[:, 1]) < 1e-9, 0])
    np.testing.assert_allclose(along_x, np.arange(1, 10) * 0.1)
    np.testing.assert_allclose(pts[occ], [[1.0, 0.0]], atol=1e-12)
    # No-return beam: free to the cap, no hit.
    along_y = np.sort(free[np.abs(free[:, 0]) < 1e-9, 1])
    np.testing.assert_allclose(along_y, np.arange(1, 6) * 0.1)


@pytest.mark.parametrize("dim", [2, 3])
def test_leave_one_scan_out_removes_the_scans_own_counts(dim: int) -> None:
    # Two scans from different poses; the calibration points of scan 0 must see scan 1's counts only.
    a = _along_x(dim, [1.0])
    b = _along_x(dim, [1.5], y=0.25)
    ev = RayEvidence.from_scans([a, b])
    seen = {}

    def predict_gp(points: np.ndarray) -> np.ndarray:
        seen["points"] = points
        return np.full(len(points), 0.5)

    _, report, _ = fit_calibration([a, b], ev, GRID if dim == 2 else VOXELS, predict_gp, n_scans=2, step=0.1)
    assert report["n_points"] > 0
    # The scans' beams run along different rows, so with only the other scan's counts no point
    # is counted, and the GP is asked nothing: a leaked count of a scan's own would make its
    # points counted (and its hits certain).
    assert report["n_predicted"] == 0 and "points" not in seen


@pytest.fixture(scope="module")
def half_room() -> tuple[AreaGPOM, list[Scan]]:
    """The room's even scans fitted (read, never changed, by the tests below); the odd ones held out.

    The length scale is fixed at 0.4 m, within what real logs learn, so the written grid samples
    the GP every third of it (two 0.05 m cells) whatever a search on half the room would find."""
    scans = paper_room_scans()
    return AreaGPOM(kernel="se", length_scale=0.4, optimise=False).fit(scans[::2]), scans[1::2]


def test_fused_map_scores_better_than_the_gp_and_half_far_away(half_room: tuple[AreaGPOM, list[Scan]]) -> None:
    model, test = half_room
    pts, occ = [], []
    for s in test:
        p, o = calibration_points(s, step=0.1)
        pts.append(p)
        occ.append(o)
    P, Y = np.concatenate(pts), np.concatenate(occ)
    from gpomap.metrics import log_loss, roc_auc

    # Held-out points at their own frequencies: the counts halve the GP's log loss (0.08 against
    # 0.16 when written) and rank about as well (a perfect simulation leaves the GP little to miss).
    fused, gp = model.predict_proba(P), model.predict_proba_gp(P)
    assert log_loss(Y, fused) < 0.7 * log_loss(Y, gp)
    assert roc_auc(Y, fused) > roc_auc(Y, gp) - 0.005
    # Far from every observation: no counts, zero latent mean, p = 0.5.
    assert model.predict_proba(np.array([[1e4, 1e4]]))[0] == pytest.approx(0.5, abs=1e-9)


def test_written_grid_uses_its_own_cells_counts(half_room: tuple[AreaGPOM, list[Scan]]) -> None:
    # Half the room's scans: the GP is still sampled coarsely (factor 2) and interpolated.
    model, _ = half_room
    om = model.grid(0.05, extent=(0.0, 10.0, 0.0, 8.0))  # a corner of the room, walls included
    hits, misses, _ = model.evidence_.grid_counts(om.grid)
    p_gp, _, p_unseen = (a.reshape(om.grid.shape) for a in model._gp_probabilities(om.grid.centres()))
    factor = gp_sampling_factor(model.hyperparameters_["length_scale"], 0.05)
    assert factor > 1  # the GP was sampled coarsely and interpolated
    # Cells no beam crossed take the GP's probability for unseen space (gpomap.extrapolation).
    exact = np.where((hits == 0) & (misses == 0), p_unseen, model.evidence_.calibration(p_gp, hits, misses))
    # Interpolating the GP a third of a length scale apart moves the written map little, and
    # only in cells next to walls with few counts (measured on Intel scans 0-300, every 10th
    # held out: the same held-out AUC and log loss, 0.9930 and 0.103, in a quarter of the time).
    diff = np.abs(om.probability - exact)
    assert diff.mean() < 0.01
    assert np.quantile(diff, 0.95) < 0.05


def test_bilinear_interpolation_is_exact_on_a_plane() -> None:
    fine = GridSpec((-1.0, 2.0), 0.05, (37, 53))
    coarse = coarse_grid(fine, 4)
    plane = lambda xy: 0.3 + 2.0 * xy[:, 0] - 0.7 * xy[:, 1]  # noqa: E731
    got = interpolate_to(plane(coarse.centres()).reshape(coarse.shape), coarse, fine)
    np.testing.assert_allclose(got.ravel(), plane(fine.centres()), atol=1e-12)
    assert coarse_grid(fine, 1) == fine
    # The dimension-free versions: the same in 2-D, and trilinear (exact on a plane) in 3-D.
    assert lattice.coarse(fine, 4) == coarse
    np.testing.assert_array_equal(lattice.grid_centres(fine), fine.centres())
    vox = VoxelSpec((-1.0, 2.0, 0.3), 0.05, (11, 37, 53))
    big = lattice.coarse(vox, 3)
    assert isinstance(big, VoxelSpec)
    plane3 = lambda p: 0.3 + 2.0 * p[:, 0] - 0.7 * p[:, 1] + 1.1 * p[:, 2]  # noqa: E731
    got3 = lattice.interpolate(plane3(big.centres()).reshape(big.shape), big, vox)
    np.testing.assert_allclose(got3.ravel(), plane3(vox.centres()), atol=1e-12)
    np.testing.assert_array_equal(lattice.grid_centres(vox), vox.centres())


def test_gp_sampling_factor() -> None:
    assert gp_sampling_factor(0.3, 0.05) == 2  # 0.1 m apart
    assert gp_sampling_factor(0.1, 0.05) == 1
    assert gp_sampling_factor(5.0, 0.05) == 4  # capped


def test_path_passes_in_3d_follow_the_sensor() -> None:
    # A sensor moved along x at y = 0.15, z = 0.25 in 0.25 m steps from x = 0.05 to 1.55: on
    # 0.1 m voxels the body's reach is one voxel, so the track's row (x from -0.05 to 1.65: ix
    # 0..16) and its four side rows (shifted by a voxel in y or z, not in x: ix 0..15).
    clouds = [CloudScan(o, o[None, :] + [0.0, 0.0, 0.1]) for o in (np.array([0.05 + 0.25 * k, 0.15, 0.25]) for k in range(7))]
    passes = RayEvidence.from_scans(clouds).path_passes(VOXELS)
    want = np.zeros(VOXELS.shape, dtype=bool)
    want[2, 1, :17] = True
    for iz, iy in ((1, 1), (3, 1), (2, 0), (2, 2)):
        want[iz, iy, :16] = True
    np.testing.assert_array_equal(passes > 0, want)


def test_path_passes_cover_the_robots_body_once_per_step() -> None:
    """One 0.5 m step along row 10 of a 5 cm grid: the cells it crosses shifted by up to
    PATH_RADIUS (2 cells: 0 or +-1, +-2 along x in the row itself, 0, +-1 one row off, 0 two
    rows off), each once; two steps count where both pass, and add up."""
    from gpomap.robot_path import PATH_RADIUS

    assert PATH_RADIUS == 0.1  # the cells below are worked out for it
    grid = GridSpec((0.0, 0.0), 0.05, (40, 40))
    a, b, c = (_scan(x, 0.52, [np.pi / 2], [0.1]) for x in (0.51, 1.01, 1.26))
    passes = RayEvidence.from_scans([a, b]).path_passes(grid)
    # x from 0.51 + k_x 0.05 to 1.01 + k_x 0.05 in row 10 + k_y, with k_x^2 + k_y^2 <= 4.
    want = np.zeros(grid.shape, dtype=np.int32)
    want[10, 8:23] = 1  # 0.41 .. 1.11 m
    want[[9, 11], 9:22] = 1  # 0.46 .. 1.06 m
    want[[8, 12], 10:21] = 1  # 0.51 .. 1.01 m
    np.testing.assert_array_equal(passes, want)
    two = RayEvidence.from_scans([a, b, c]).path_passes(grid)
    np.testing.assert_array_equal(two, passes + RayEvidence.from_scans([b, c]).path_passes(grid))
    assert two.max() == 2


def test_path_passes_follow_the_robot_and_skip_jumps() -> None:
    # Scan 0 at x = 0.05 sees a hit at x = 1.05 (a person); the robot then drives through it.
    first = _scan(0.05, 0.15, [0.0], [1.0])
    path = [_scan(0.05 + 0.25 * k, 0.15, [np.pi / 2], [0.1]) for k in range(1, 7)]
    scans = [first, *path]
    driven = RayEvidence.from_scans(scans).path_passes(GRID)
    assert driven[1, :16].min() >= 1 and driven[1, 17:].sum() == 0

    # A 2 m step (a log of 1 m strides that lost a scan) is driving: straight along the robot's
    # heading, or, turning, where its ends' scans saw nothing within the robot's body of it. A
    # sideways step past what an end saw (x = 1.05: the ends of a held-out loop, close across a
    # wall) is not; nor is a 3 m one unless the robot drove straight along it.
    def facing(x: float, heading: float, hit_x: float | None = None) -> Scan:
        if hit_x is None:  # one beam to +y, 0.5 m long
            return Scan(
                pose=np.array([x, 0.15, heading]), angles=np.array([np.pi / 2 - heading]), ranges=np.array([0.5]), max_range=5.0
            )
        return Scan(pose=np.array([x, 0.15, heading]), angles=np.array([-heading]), ranges=np.array([hit_x - x]), max_range=5.0)

    def passes(a: Scan, b: Scan) -> np.ndarray:
        return RayEvidence.from_scans([a, b]).path_passes(GRID)

    side = np.pi / 2
    assert passes(facing(0.05, side), facing(2.05, side))[1].min() == 1  # turning, nothing in the way
    assert passes(facing(0.05, side, hit_x=1.05), facing(2.05, side)).sum() == 0
    assert passes(facing(0.05, 0.0, hit_x=1.05), facing(2.05, np.pi))[1].min() == 1  # straight: drove through it
    assert passes(facing(0.05, side), facing(3.1, side)).sum() == 0  # 3 m sideways: a jump
    assert passes(facing(0.05, 0.0), facing(3.1, 0.0))[1].min() == 1  # 3 m straight: two scans lost

    # A long straight step holds its headings closer to it. An arc leaving and reaching a 2.5 m
    # step at 30 degrees strays 1.25 tan(15 deg) = 0.3349 m from it; one leaving and reaching a 4 m
    # step at 19.01 degrees as far, 2 tan(9.507 deg) = 0.3349 m, and a 3 m one at 25.17 degrees,
    # 1.5 tan(12.587 deg) = 0.3349 m.
    def steps(length: float, degrees: float) -> int:
        h = np.radians(degrees)
        return len(RayEvidence.from_scans([facing(0.05, h), facing(0.05 + length, h)]).path)

    assert steps(4.0, 18.5) == 1 and steps(4.0, 19.5) == 0
    assert steps(3.0, 24.9) == 1 and steps(3.0, 25.5) == 0
    # A hit just beyond the robot's body (0.1 m) of a sideways step does not stop it.
    gap = PATH_RADIUS + 0.01
    beside = Scan(
        pose=np.array([0.05, 0.15, side]),
        angles=np.array([np.arctan2(gap, 1.0) - side]),
        ranges=np.array([np.hypot(gap, 1.0)]),
        max_range=5.0,
    )
    assert RayEvidence.from_scans([beside, facing(2.05, side)]).path.shape == (1, 4)


def _calibration_scene() -> tuple[list[Scan], RayEvidence, GridSpec]:
    """Six scans of 12 beams of 0.5 m (a hit and four free calibration points each, misses near
    their ends and far from them), three of them close together (their points are counted by the
    others) and three far apart (never counted)."""
    poses = [(0.52, 0.51), (0.57, 0.53), (0.61, 0.47), (3.5, 0.5), (0.5, 3.5), (3.5, 3.5)]
    scans = [
        _scan(x, y, list(np.linspace(-np.pi, np.pi, 12, endpoint=False) + 0.3 * k), [0.5] * 12) for k, (x, y) in enumerate(poses)
    ]
    return scans, RayEvidence.from_scans(scans), GridSpec((0.0, 0.0), 0.05, (80, 80))


def _p_gp(points: np.ndarray) -> np.ndarray:
    return 0.2 + 0.6 / (1.0 + np.exp(-4.0 * (points[:, 0] - 0.55) + 3.0 * (points[:, 1] - 0.5)))


def _room_scene() -> tuple[list[Scan], RayEvidence, GridSpec]:
    """The paper room's first six scans on a 0.1 m lattice: far misses beside other scans' hits."""
    scans = paper_room_scans()[:6]
    return scans, RayEvidence.from_scans(scans), lattice_grid((-1.0, 11.0, -1.0, 11.0), 0.1)


@pytest.mark.parametrize("scene", [_calibration_scene, _room_scene], ids=["small scene", "room"])
def test_calibration_predicts_only_counted_points_and_matches_the_whole_sample_fit(scene: Callable[[], tuple]) -> None:
    from scipy.optimize import minimize

    scans, ev, grid = scene()
    asked: list[np.ndarray] = []

    def predict_gp(points: np.ndarray) -> np.ndarray:
        asked.append(points)
        return _p_gp(points)

    fitted, report, _ = fit_calibration(scans, ev, grid, predict_gp, n_scans=len(scans), step=0.1)
    # Truth by brute force: every scan's points with the other scans' counts taken directly (not
    # all counts minus its own), the GP at every point, the plain mean log loss minimised.
    # Surface misses: far misses of cells with one of those other scans' hits in their 3 x 3 block.
    pts, occ, h, m, n, sf = [], [], [], [], [], []
    for k, s in enumerate(scans):
        p, o = calibration_points(s, 0.1)
        hits, misses, near, _ = ev.counts(grid, scans=np.array([j for j in range(len(scans)) if j != k]))
        cell, inside = lattice.flat_index(grid, p)
        padded = np.pad(hits > 0, 1)
        block = np.zeros(hits.shape, bool)
        for dy in range(3):
            for dx in range(3):
                block |= padded[dy : dy + hits.shape[0], dx : dx + hits.shape[1]]
        pts.append(p)
        occ.append(o)
        h.append(np.where(inside, hits.reshape(-1)[cell], 0))
        m.append(np.where(inside, misses.reshape(-1)[cell], 0))
        n.append(np.where(inside, near.reshape(-1)[cell], 0))
        sf.append(np.where(inside & block.reshape(-1)[cell], (misses - near).reshape(-1)[cell], 0))
    P, O, H, M, N, S = (np.concatenate(a) for a in (pts, occ, h, m, n, sf))
    # The scene has points of both classes, counted and not, with near misses and far ones; the
    # room's far misses are at a surface and away from one.
    counted = (H + M) > 0
    assert 0 < counted.sum() < counted.size and 0 < N.sum() < M.sum()
    assert (0 < S.sum() < (M - N).sum()) == (scene is _room_scene)
    # The fit takes every point at its own frequency (these scenes hold fewer than the cap).
    assert O.size <= fusion.CALIBRATION_POINTS and report["n_points"] == O.size
    g = _p_gp(P)

    def loss(theta: np.ndarray) -> float:
        cal = EvidenceCalibration(*np.exp(theta))
        p = cal(g, cal.hits(H, N), cal.misses(M, N, surface=S))
        return float(-np.mean(np.where(O, np.log(p), np.log1p(-p))))

    best = minimize(
        loss,
        np.log([1.0, 2.0, 1.0, 1.0, 1.0]),
        method="L-BFGS-B",
        bounds=CALIBRATION_BOUNDS,
        options={"ftol": 1e-14, "gtol": 1e-10},
    )
    truth = np.exp(best.x)
    got = np.array([fitted.hit_weight, fitted.prior_weight, fitted.near_weight, fitted.near_hit_weight, fitted.surface_weight])
    # The same minimum. On this small scene the near miss's two weights lie on a ridge (the
    # near misses decide, so their ratio does, not their size): the loss and the ratio are compared.
    assert loss(np.log(got)) == pytest.approx(best.fun, rel=1e-5)
    np.testing.assert_allclose(got[[0, 1, 4]], truth[[0, 1, 4]], rtol=2e-3)
    assert got[3] / got[2] == pytest.approx(truth[3] / truth[2], rel=2e-3)
    # Where surface misses are, weighing them apart is a real degree of freedom: the fit moved it
    # off a miss's; where none are, it stays a miss's.
    assert (abs(np.log(fitted.surface_weight)) > 0.05) == (scene is _room_scene)
    # The GP was asked once, at exactly the counted points.
    assert len(asked) == 1 and len(asked[0]) == counted.sum() == report["n_predicted"]
    want = {tuple(np.round(q, 9)) for q in P[counted]}
    assert {tuple(np.round(q, 9)) for q in asked[0]} == want
    assert report["n_points"] == O.size


@pytest.mark.parametrize("dim", [2, 3])
def test_separable_interpolation_equals_the_point_by_point_one(dim: int) -> None:
    from scipy.interpolate import RegularGridInterpolator

    fine = GridSpec((-1.0, 2.0), 0.05, (37, 53)) if dim == 2 else VoxelSpec((-1.0, 2.0, 0.3), 0.05, (11, 37, 53))
    for factor in (2, 3, 4):
        big = lattice.coarse(fine, factor)
        values = np.random.default_rng(factor).uniform(size=big.shape)
        got = lattice.interpolate(values, big, fine)
        # Truth: scipy's interpolator at every fine centre (array order, x last).
        axes = [np.unique(big.centres()[:, k]) for k in reversed(range(dim))]
        want = RegularGridInterpolator(axes, values)(fine.centres()[:, ::-1]).reshape(fine.shape)
        np.testing.assert_allclose(got, want, atol=1e-12)
    # At the coarse centres themselves: the values (interpolating a lattice onto itself shifted by
    # whole cells), and a centre beyond the source is refused.
    inner = lattice.make_grid(np.asarray(big.origin) + big.resolution, big.resolution, np.array(big.shape[::-1]) - 2)
    np.testing.assert_allclose(lattice.interpolate(values, big, inner), values[(slice(1, -1),) * dim], atol=1e-12)
    outer = lattice.make_grid(np.asarray(big.origin) - big.resolution, big.resolution, np.array(big.shape[::-1]))
    with pytest.raises(ValueError, match="outside"):
        lattice.interpolate(values, big, outer)


@pytest.mark.parametrize("dim", [2, 3])
def test_seen_cells_and_one_scans_counts_at_cells_equal_the_whole_grid_counts(
    dim: int, monkeypatch: pytest.MonkeyPatch, counting: str
) -> None:
    from gpomap import evidence

    rng = np.random.default_rng(dim)
    grid = GridSpec((0.0, 0.0), 0.1, (30, 40)) if dim == 2 else VoxelSpec((0.0, 0.0, 0.0), 0.1, (10, 30, 40))
    scans = []
    for _ in range(4):
        o = rng.uniform(0.5, [3.5, 2.5, 0.9][:dim])
        ends = o + rng.normal(0, 1.0, (60, dim))
        if dim == 2:
            d = ends - o
            scans.append(_scan(o[0], o[1], list(np.arctan2(d[:, 1], d[:, 0])), list(np.hypot(d[:, 0], d[:, 1])), max_range=1.5))
        else:
            scans.append(CloudScan(o, ends, hit=np.linalg.norm(ends - o, axis=1) < 1.5, max_range=1.5))
    ev = RayEvidence.from_scans(scans)
    # Whether any scan counted a cell, against the whole counts (one batch and many).
    hits, misses, *_ = ev.counts(grid)
    assert 0 < np.count_nonzero(hits + misses) < hits.size
    for budget in (1 << 22, 50):
        monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", budget)
        np.testing.assert_array_equal(ev.seen(grid), (hits + misses) > 0)
    cells = rng.integers(0, int(np.prod(grid.shape)), 3000)
    for k in range(4):
        # Truth: the whole grid's counts of that scan alone, read at the cells.
        counts = ev.counts(grid, scans=np.array([k]))
        want = [a.reshape(-1)[cells] for a in counts]
        assert want[0].sum() > 0 and want[1].sum() > want[2].sum() > 0
        for budget in (1 << 22, 50):  # one batch, and a few beams a batch
            monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", budget)
            got = ev.scan_counts_at(grid, k, cells)
            for j in range(len(want)):
                np.testing.assert_array_equal(got[j], want[j])
        # The scan's update by brute force, beam by beam: each cell's share of hits is the scan's
        # beams that returned and ended in it over all its beams there, its near share those that
        # crossed it and ended their return within NEAR_END of its centre.
        lo, hi = np.searchsorted(ev.scan, [k, k + 1])
        tally: dict[int, list[int]] = {}
        for j in range(lo, hi):
            _, *idx = evidence.traverse(grid, ev.starts[j : j + 1], ev.ends[j : j + 1])
            end = tuple(np.floor((ev.ends[j] - np.asarray(grid.origin)) / grid.resolution).astype(int)[::-1])
            for cell in zip(*idx, strict=True):
                centre = np.asarray(grid.origin) + (np.array(cell[::-1]) + 0.5) * grid.resolution
                ended = bool(ev.hit[j]) and tuple(int(c) for c in cell) == end
                close = bool(ev.hit[j]) and not ended and float(np.linalg.norm(centre - ev.ends[j])) < NEAR_END
                t = tally.setdefault(int(np.ravel_multi_index(cell, grid.shape)), [0, 0, 0])
                t[0], t[1], t[2] = t[0] + 1, t[1] + ended, t[2] + close
        brute = np.zeros((3, int(np.prod(grid.shape))))
        for flat, (through, ended, close) in tally.items():
            brute[:, flat] = ended / through, (through - ended) / through, close / through
        for j in range(3):  # whole 256ths of the update: within half of one
            np.testing.assert_allclose(counts[j].reshape(-1), brute[j], rtol=0, atol=0.5 / evidence.SHARE_UNITS)
        np.testing.assert_array_equal((counts.hits + counts.misses).reshape(-1), brute[0] + brute[1])
    # The cells the whole counts kept (batches of whole scans, one or a few a batch) give the same.
    for budget in (1 << 22, 50):
        monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", budget)
        kept = RayEvidence.from_scans(scans)
        for a, b in zip(kept.counts(grid, keep=np.array([1, 3])), ev.counts(grid), strict=True):
            np.testing.assert_array_equal(a, b)
        assert sorted(k for _, k in kept._kept) == [1, 3]
        for k in range(4):
            got = kept.scan_counts_at(grid, k, cells)
            for g, a in zip(got, ev.counts(grid, scans=np.array([k])), strict=True):
                np.testing.assert_array_equal(g, a.reshape(-1)[cells])
        kept.forget()
        assert not kept._kept


def test_evidence_layer_calibrates_from_the_cells_its_counts_kept(monkeypatch: pytest.MonkeyPatch, counting: str) -> None:
    from gpomap.evidence import RayEvidence as RE
    from gpomap.fusion import EvidenceLayer

    scans, _, _ = _calibration_scene()
    # Truth: the calibration on evidence that kept nothing (every held-out scan traversed again).
    layer = EvidenceLayer(scans, 0.1, _p_gp, calibration_scans=len(scans))
    assert layer.lattice is not None
    want, report, _ = fit_calibration(scans, RE.from_scans(scans), layer.lattice, _p_gp, n_scans=len(scans), step=0.2)
    # The layer's own calibration never traverses a scan again, and drops the kept cells after.
    monkeypatch.setattr(RE, "_scan_updates", lambda *a: pytest.fail("a held-out scan was traversed again"))
    layer = EvidenceLayer(scans, 0.1, _p_gp, calibration_scans=len(scans))
    assert (layer.calibration, layer.report) == (want, report)
    assert not layer.evidence._kept


def test_written_grid_takes_the_variance_two_samples_apart(half_room: tuple[AreaGPOM, list[Scan]]) -> None:
    """The planar written map: the GP's mean at every sample, its variance at every second one,
    interpolated (checked against scipy's interpolator and the squash worked out here); the mean
    alone is the full prediction's mean to the bit."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.special import ndtr

    from gpomap.fusion import VARIANCE_STEP_SAMPLES

    model, _ = half_room
    om = model.grid(0.05, extent=(0.0, 10.0, 0.0, 8.0))
    sampled = lattice.coarse(om.grid, gp_sampling_factor(model.hyperparameters_["length_scale"], 0.05))
    apart = lattice.coarse(sampled, VARIANCE_STEP_SAMPLES)
    centres = lattice.grid_centres(sampled)
    num, no_den, mean, no_var = model.blended_moments(centres, variance=False)
    assert no_den is None and no_var is None
    full_num, _, full_mean, _ = model.blended_moments(centres)
    np.testing.assert_array_equal(num, full_num)
    np.testing.assert_array_equal(mean, full_mean)
    _, den_apart, _, var_apart = model.blended_moments(lattice.grid_centres(apart))
    axes = [np.asarray(apart.origin)[k] + apart.resolution * (np.arange(n) + 0.5) for k, n in zip((1, 0), apart.shape)]
    den = RegularGridInterpolator(axes, den_apart.reshape(apart.shape))(centres[:, ::-1])
    var = RegularGridInterpolator(axes, var_apart.reshape(apart.shape))(centres[:, ::-1])
    hp = model.hyperparameters_
    # Unseen space: the variance scaled by kappa.
    z = num / np.sqrt(1.0 + hp["variance_scale"] * den)
    p_gp, p_unseen = ndtr(num / np.sqrt(1.0 + den)), ndtr(z)
    hits, misses, _ = model.evidence_.grid_counts(om.grid)
    want = model.evidence_.grid_proba(
        om.grid, lattice.interpolate(p_gp, sampled, om.grid), lattice.interpolate(p_unseen, sampled, om.grid)
    )
    np.testing.assert_allclose(om.probability, want, atol=1e-12)
    np.testing.assert_allclose(om.variance, lattice.interpolate(var, sampled, om.grid), atol=1e-12)
    assert (hits + misses).max() > 0 and np.ptp(den) > 0  # counts and a variance that varies


def test_lattice_corners_by_hand() -> None:
    nodes, corner, weight = lattice.lattice_corners(np.array([[0.25, 0.5], [1.0, 0.0]]), 1.0)
    # The first point's cell has corners (0, 0), (0, 1), (1, 0), (1, 1), weighted by the opposite areas.
    got = {tuple(nodes[c]): w for c, w in zip(corner[0], weight[0])}
    assert got == {(0.0, 0.0): 0.375, (0.0, 1.0): 0.375, (1.0, 0.0): 0.125, (1.0, 1.0): 0.125}
    # A point on a node is that node's value alone; every node once.
    assert weight[1].max() == 1.0 and tuple(nodes[corner[1][weight[1].argmax()]]) == (1.0, 0.0)
    assert len({tuple(n) for n in nodes}) == len(nodes)
    # Multilinear interpolation is exact on a plane, in 3-D too.
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3.0, 3.0, size=(50, 3))
    nodes, corner, weight = lattice.lattice_corners(pts, 0.4)
    plane = lambda p: 0.3 + 2.0 * p[:, 0] - 0.7 * p[:, 1] + 1.1 * p[:, 2]  # noqa: E731
    np.testing.assert_allclose((weight * plane(nodes)[corner]).sum(axis=1), plane(pts), atol=1e-12)


def test_calibrations_take_the_gp_with_its_variance_as_a_written_map_does(half_room: tuple[AreaGPOM, list[Scan]]) -> None:
    """The GP the calibrations fit: its mean at each point, its variance interpolated from the
    corners of the point's cell of a lattice two GP samples apart (checked against scipy's
    interpolator and the squash worked out here); on a node, the GP's own probability."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.special import ndtr

    model, _ = half_room
    step = fusion.variance_step(model.hyperparameters_["length_scale"], model.base.evidence_resolution)
    assert step == pytest.approx(0.2)  # the GP sampled every 2 cells of 0.05 m, its variance every 2 samples
    pts = np.random.default_rng(3).uniform([1.0, 1.0], [5.5, 4.5], size=(1500, 2))
    assert model._variance_corners(pts) is not None  # points that share corners
    p, p_unseen = model._gp_proba_as_written(pts)
    # The tiles predict locally, leaving out covariances below 1e-6 of the variance, so another
    # set of queries moves a value by that much.
    xs, ys = (np.arange(np.floor(pts[:, k].min() / step) - 1, np.ceil(pts[:, k].max() / step) + 2) * step for k in (0, 1))
    nodes = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    _, den_nodes, _, _ = model.blended_moments(nodes)
    den = RegularGridInterpolator((xs, ys), den_nodes.reshape(xs.size, ys.size))(pts)
    num, _, _, _ = model.blended_moments(pts, variance=False)
    kappa = model.hyperparameters_["variance_scale"]
    np.testing.assert_allclose(p, ndtr(num / np.sqrt(1.0 + den)), atol=1e-6)
    np.testing.assert_allclose(p_unseen, ndtr(num / np.sqrt(1.0 + kappa * den)), atol=1e-6)
    assert np.ptp(den) > 0  # a variance that varies
    exact, _, exact_unseen = model._gp_probabilities(nodes)
    on_node = model._gp_proba_as_written(nodes)
    np.testing.assert_allclose(on_node[0], exact, atol=1e-6)
    np.testing.assert_allclose(on_node[1], exact_unseen, atol=1e-6)
    # Between nodes it moves the map's probability little.
    assert np.abs(model._proba_as_written(pts) - model.predict_proba(pts)).mean() < 0.01
    # Points too sparse to share corners (each its own cell's four) are asked as they are.
    sparse = 0.5 + np.arange(50)[:, None] * np.array([[0.17, 0.13]])
    assert model._variance_corners(sparse) is None
    np.testing.assert_allclose(model._gp_proba_as_written(sparse)[0], model._gp_probabilities(sparse)[0], atol=1e-6)


def test_a_voxel_maps_calibrations_take_the_gp_as_its_written_map_does_too() -> None:
    """In 3-D too: the mean at each point, the variance interpolated trilinearly from the corners
    of a lattice two GP samples apart on the voxels (checked against scipy's interpolator)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.special import ndtr

    from tests.world3d import ORIGINS, lidar_clouds

    model = AreaGPOM(n_workers=1).fit(lidar_clouds(ORIGINS, n_rays=300))
    step = fusion.variance_step(model.hyperparameters_["length_scale"], model.base.evidence_resolution_3d)
    pts = np.random.default_rng(4).uniform([1.0, 1.0, 0.5], [5.0, 3.0, 2.0], size=(3000, 3))
    assert model._variance_corners(pts) is not None
    p, _ = model._gp_proba_as_written(pts)
    axes = [np.arange(np.floor(pts[:, k].min() / step) - 1, np.ceil(pts[:, k].max() / step) + 2) * step for k in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    _, den_nodes, _, _ = model.blended_moments(nodes)
    den = RegularGridInterpolator(axes, den_nodes.reshape([a.size for a in axes]))(pts)
    num, _, _, _ = model.blended_moments(pts, variance=False)
    np.testing.assert_allclose(p, ndtr(num / np.sqrt(1.0 + den)), atol=1e-6)
    assert np.ptp(den) > 0


def test_a_voxel_maps_ternary_at_points_follows_its_written_rule() -> None:
    """In 3-D the map's ternary call at points follows its voxel map's rule: never occupied in a
    voxel no ray went to (the GP's guess behind the walls), whatever the probability there."""
    from tests.world3d import ORIGINS, lidar_clouds

    model = AreaGPOM(n_workers=1).fit(lidar_clouds(ORIGINS[:3], n_rays=200))
    voxels = model.grid(model.base.evidence_resolution_3d)  # on the counted lattice
    assert voxels.observed is not None
    # The voxels the written map puts above the threshold and every 10th of the others.
    pick = (voxels.probability.reshape(-1) > 0.4) | (np.arange(voxels.probability.size) % 10 == 0)
    centres = voxels.spec.centres()[pick]
    observed = voxels.observed.reshape(-1)[pick]
    p = model.predict_proba(centres)
    above = p > voxels.thresholds[1]
    assert (above & observed).any() and (above & ~observed).any()  # both cases among them
    called = model.predict_ternary(centres)
    np.testing.assert_array_equal(called == 1, above & observed)
    np.testing.assert_array_equal(called[above & ~observed], -1)
    np.testing.assert_array_equal(called == 0, p < voxels.thresholds[0])


def test_other_scans_counts_are_the_counts_without_each_points_own_scan() -> None:
    """The calibration's per-point counts equal the counts of every scan but the point's own, taken
    afresh (``counts(grid, scans=others)``) and read at the point's cell (0 off the grid)."""
    from gpomap.fusion import _other_scans_counts

    scans = paper_room_scans()[:6]
    ev = RayEvidence.from_scans(scans)
    grid = lattice_grid((-1.0, 11.0, -1.0, 11.0), 0.1)
    whole = ev.counts(grid)
    rng = np.random.default_rng(5)
    pts_all, scan_all = [], []
    for k in range(len(scans)):
        pts, _ = calibration_points(scans[k], 0.1)
        pick = rng.choice(len(pts), 400, replace=False)
        pts_all.append(pts[pick])
        scan_all.append(np.full(400, k))
    pts, scan_of = np.concatenate(pts_all), np.concatenate(scan_all)
    got = _other_scans_counts(ev, grid, whole, pts, scan_of)
    cell, inside = lattice.flat_index(grid, pts)
    assert 0 < inside.sum() < inside.size  # points on the grid and off it
    for k in range(len(scans)):
        others = ev.counts(grid, scans=np.array([j for j in range(len(scans)) if j != k]))
        sel = scan_of == k
        for mine, theirs in zip((*got[:3], got[4]), others, strict=True):
            np.testing.assert_array_equal(mine[sel], np.where(inside[sel], theirs.reshape(-1)[cell[sel]], 0))
        # Surface misses: the far misses of cells with one of the other scans' hits in their 3 x 3 block.
        padded = np.pad(others.hits > 0, 1)
        block = np.zeros(others.hits.shape, bool)
        for dy in range(3):
            for dx in range(3):
                block |= padded[dy : dy + block.shape[0], dx : dx + block.shape[1]]
        far = (others.misses - others.near).reshape(-1)[cell[sel]]
        np.testing.assert_array_equal(got[3][sel], np.where(inside[sel] & block.reshape(-1)[cell[sel]], far, 0))
    assert got[0].sum() > 0 and got[1].sum() > 0  # the room's scans overlap: the test sees counts
    assert 0 < got[3].sum() < (got[1] - got[2]).sum()  # and far misses beside hits and away from them


def _wall_scans(jitter: float, n: int = 30) -> list[Scan]:
    """Scans from the line x = 0.5 of a wall at x = 2.0 (beams over +-0.6 rad), the wall seen
    `jitter` metres nearer or farther in each scan (uniform: a pose error across scans)."""
    rng = np.random.default_rng(3)
    angles = np.linspace(-0.6, 0.6, 41)
    scans = []
    for k in range(n):
        y = 1.0 + 2.0 * k / n
        wall = 2.0 + rng.uniform(-jitter, jitter)
        scans.append(_scan(0.5, y, list(angles), list((wall - 0.5) / np.cos(angles))))
    return scans


def test_a_near_miss_counts_as_a_hit_only_where_surfaces_fall_in_such_cells(monkeypatch: pytest.MonkeyPatch) -> None:
    # Walls smeared across scans by pose error: a cell one scan nearly missed just before the
    # wall is another scan's hit, and the fit finds near misses worth hits. A wall seen in the same
    # place by every scan: the cells before it are never hit, and a near miss is worth no hit.
    import gpomap.fusion.calibration

    grid = GridSpec((0.0, 0.0), 0.05, (100, 60))

    def fit(scans: list[Scan]) -> tuple[EvidenceCalibration, float]:
        ev = RayEvidence.from_scans(scans)
        cal, report, _ = fit_calibration(scans, ev, grid, lambda p: np.full(len(p), 0.5), n_scans=len(scans), step=0.1)
        return cal, report["log_loss"]

    smeared, loss_smeared = fit(_wall_scans(0.12))
    steady, _ = fit(_wall_scans(0.0))
    floor = float(np.exp(CALIBRATION_BOUNDS[3][0]))
    # As a share of a hit: a tenth or more on the smeared wall, nothing on the steady one.
    assert smeared.near_hit_weight > 0.1 * smeared.hit_weight and smeared.near_hit_weight > 10 * floor
    assert steady.near_hit_weight < 10 * floor and steady.near_hit_weight < 1e-4 * steady.hit_weight
    # On the smeared wall the fourth weight is what lowers the held-out loss: the best fit with a
    # near miss worth no hit (its bounds pinned to the floor) is worse.
    low = CALIBRATION_BOUNDS[3][0]
    monkeypatch.setattr(
        gpomap.fusion.calibration, "CALIBRATION_BOUNDS", (*CALIBRATION_BOUNDS[:3], (low, low), *CALIBRATION_BOUNDS[4:])
    )
    pinned, loss_pinned = fit(_wall_scans(0.12))
    assert pinned.near_hit_weight == pytest.approx(floor)
    assert loss_smeared < loss_pinned - 5e-4


@pytest.mark.parametrize("x0", [-0.5, -0.513], ids=["on the counted lattice", "off it"])
def test_a_large_planar_written_grid_is_built_in_bands_and_is_the_same_map(
    half_room: tuple[AreaGPOM, list[Scan]], monkeypatch: pytest.MonkeyPatch, x0: float
) -> None:
    """Built in bands of rows (a shorter last one), the written map is the one built whole: each
    band samples the GP where the whole grid does, and reads the counts and the distances to hits
    of its own rows (off the counted lattice, from one count of the whole grid). Up to the local
    prediction's tolerance: a tile's blocks of queries, and so
    the covariances below `gpomap.gp.LOCAL_TOL` of the variance it leaves out, follow the queries
    it is given (2e-5 at most against the dense solve on the room's grid, docs/choices.md)."""
    from gpomap import fusion

    model, _ = half_room
    extent = (x0, 10.5, -0.5, 8.3)  # 176 rows of 220 cells (221 off the lattice)
    whole = model.grid(0.05, extent=extent)
    assert any(tile.posterior.precision is not None for tile in model.tiles_.values())
    bands: list[tuple[int, ...]] = []
    build = fusion.EvidenceLayer._written_block

    def counted(self: fusion.EvidenceLayer, grid: GridSpec, *args: object) -> tuple[np.ndarray, np.ndarray]:
        bands.append(grid.shape)
        return build(self, grid, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(fusion.written, "WRITTEN_BAND_CELLS", 5_000)
    monkeypatch.setattr(fusion.EvidenceLayer, "_written_block", counted)
    traversals: list[tuple[int, ...]] = []
    count = RayEvidence.counts

    def traversed(self: RayEvidence, grid: GridSpec, *args: object, **kwargs: object) -> object:
        traversals.append(grid.shape)
        return count(self, grid, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(RayEvidence, "counts", traversed)
    banded = model.grid(0.05, extent=extent)
    assert traversals == ([] if x0 == -0.5 else [(176, 221)])
    assert len(bands) == 9 and bands[-1][0] < bands[0][0] and sum(b[0] for b in bands) == 176
    np.testing.assert_allclose(banded.probability, whole.probability, rtol=0, atol=2e-5)
    assert banded.variance is not None and whole.variance is not None
    np.testing.assert_allclose(banded.variance, whole.variance, rtol=0, atol=2e-5)
    np.testing.assert_array_equal(banded.ternary, whole.ternary)
    # The tiles' K^-1, formed by the variance's prediction, is dropped as the bands pass them.
    assert all(tile.posterior.precision is None for tile in model.tiles_.values())
    assert np.ptp(whole.probability) > 0.9  # walls and free space, not a constant map


def test_a_grid_put_together_later_is_the_grid_and_lets_its_map_go(monkeypatch: pytest.MonkeyPatch) -> None:
    """``FittedMap.grid_later``: the bands wait in their file, the map and its model can be let
    go, and the grid put together afterwards is :meth:`grid`'s to the bit."""
    import gc
    import weakref

    from gpomap import fusion

    monkeypatch.setattr(fusion.written, "WRITTEN_BAND_CELLS", 5_000)
    model = AreaGPOM(kernel="se", length_scale=0.4, optimise=False).fit(paper_room_scans()[::2])
    extent = (-0.5, 10.5, -0.5, 8.3)
    whole = model.grid(0.05, extent=extent)
    later = model.map_.grid_later(0.05, extent=extent)
    assert later.grid == whole.grid
    gone = weakref.ref(model)
    del model
    gc.collect()
    assert gone() is None  # nothing the later grid holds keeps the model
    made = later()
    np.testing.assert_array_equal(made.probability, whole.probability)
    assert made.variance is not None and whole.variance is not None
    np.testing.assert_array_equal(made.variance, whole.variance)
    np.testing.assert_array_equal(made.ternary, whole.ternary)
    assert made.thresholds == whole.thresholds and made.info["method"] == whole.info["method"]


def test_grid_rows_are_a_band_of_the_same_cells() -> None:
    grid = GridSpec((1.0, -2.0), 0.1, (30, 7))
    band = grid.rows(10, 25)
    assert band.shape == (15, 7) and band.resolution == grid.resolution
    np.testing.assert_allclose(band.y_centres(), grid.y_centres()[10:25], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(band.x_centres(), grid.x_centres())
    with pytest.raises(ValueError, match="rows 5:31"):
        grid.rows(5, 31)
    from gpomap.grid import row_bands

    assert [(a, b, band.shape) for a, b, band in row_bands(grid, 12)] == [(0, 12, (12, 7)), (12, 24, (12, 7)), (24, 30, (6, 7))]


def test_the_gp_alone_grid_is_built_in_bands_of_the_same_values(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without ray evidence a large planar grid is predicted in bands of rows: each cell is still
    the blended GP's prediction at its centre (here against the prediction of every centre at
    once, to the local prediction's tolerance)."""
    from gpomap import fitted

    scans = paper_room_scans()[::4]
    model = AreaGPOM(kernel="se", length_scale=0.4, optimise=False, ray_evidence=False).fit(scans)
    monkeypatch.setattr(fitted, "WRITTEN_BAND_CELLS", 3_000)
    calls: list[int] = []
    predict = type(model)._predict_blended

    def counted(self: AreaGPOM, points: np.ndarray) -> tuple[np.ndarray, ...]:
        calls.append(len(points))
        return predict(self, points)

    monkeypatch.setattr(type(model), "_predict_blended", counted)
    om = model.grid(0.05, extent=(-0.5, 10.5, -0.5, 8.3))
    assert len(calls) == 14 and sum(calls) == om.probability.size  # 13 rows of 220 cells a band
    assert all(tile.posterior.precision is None for tile in model.tiles_.values())
    p, var = model.predict_proba_gp(om.grid.centres(), return_var=True)
    np.testing.assert_allclose(om.probability, p.reshape(om.grid.shape), rtol=0, atol=2e-5)
    assert om.variance is not None
    np.testing.assert_allclose(om.variance, var.reshape(om.grid.shape), rtol=0, atol=2e-5)
    assert np.ptp(om.probability) > 0.5


def test_a_map_built_in_bands_reports_its_bands_not_each_bands_tiles(
    half_room: tuple[AreaGPOM, list[Scan]], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from gpomap import fusion, progress
    from gpomap.progress import get_progress_mode, set_progress_mode

    monkeypatch.setattr(progress, "LINES_AFTER_SECONDS", 0.0)  # lines from the first step: the bands are quick
    model, _ = half_room
    monkeypatch.setattr(fusion.written, "WRITTEN_BAND_CELLS", 5_000)
    before = get_progress_mode()
    set_progress_mode("lines")
    try:
        capsys.readouterr()
        model.grid(0.05, extent=(-0.5, 10.5, -0.5, 8.3))  # 9 bands
        err = capsys.readouterr().err
        model.grid(0.5)  # one piece: its tiles report
        one_piece = capsys.readouterr().err
    finally:
        set_progress_mode(before)
    assert "building the map: 1/9 bands" in err and "building the map: 8/9 bands" in err
    assert "predicting tiles" not in err
    assert "predicting tiles" in one_piece and "building the map" not in one_piece


def test_a_calibrated_map_calls_occupied_what_is_more_likely_occupied_than_not():
    from gpomap.grid import CALIBRATED_THRESHOLDS, DEFAULT_THRESHOLDS, ternary
    from gpomap.mapping import AreaGPOM
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans(n_beams=36, noise_std=0.02)
    # A 0.3 m clearance: on these 31 thin scans the planar 0.1 m learns a 4 m length scale and
    # fits 14x slower (docs/choices.md, "Free clearance"); and the SE kernel's exact area kernel,
    # which fits them 2x faster than the default Matern 3/2's quadrature: the thresholds are the
    # subject here.
    clear = {"free_clearance": 0.3, "kernel": "se"}
    model = AreaGPOM(**clear).fit(scans)
    fitted = CALIBRATED_THRESHOLDS[1]
    assert model.thresholds_ == CALIBRATED_THRESHOLDS == (0.196, 0.5)
    assert model.grid(0.5).thresholds == model.thresholds_
    q = np.array([[1.0, 1.0], [5.0, 5.0], [8.0, 2.0]])
    # (5, 5) lies inside a box no beam entered: likely occupied, but no beam ended there, so unknown.
    no_hit = model.evidence_.seen_through_at(q)
    assert no_hit[1]
    np.testing.assert_array_equal(model.predict_ternary(q), ternary(model.predict_proba(q), CALIBRATED_THRESHOLDS, no_hit))
    assert model.predict_proba(q)[1] > 0.5 and model.predict_ternary(q)[1] == -1
    # Cells beams crossed and none ended in are never occupied: unknown where the map's p is above
    # the threshold (cells in front of the walls, beside their hits). By hand from the counts of a
    # grid off the counted lattice (the room's walls lie on cell borders of the lattice itself),
    # with a low occupied threshold a user may give, which some such cells pass.
    model = AreaGPOM(thresholds=(0.1, 0.2), **clear).fit(scans)
    assert model.thresholds_ == (0.1, 0.2)  # given thresholds are kept
    fitted = 0.2
    m = model.grid(0.05, extent=(-0.487, 10.513, -0.479, 8.521))
    hits, *_ = model.evidence_.evidence.counts(m.grid)
    seen = hits == 0  # beams or the path crossed it, or nothing reached it: no beam ended there
    np.testing.assert_array_equal(m.seen_through, seen)
    above = m.probability > fitted
    assert (above & seen).any() and (above & ~seen).any()
    np.testing.assert_array_equal(m.ternary == 1, above & ~seen)
    np.testing.assert_array_equal(m.ternary[above & seen], -1)
    # The same at points: those of the map written on the counted lattice, at its cell centres;
    # predicted at those the map puts above the threshold and every 9th of the others (all 133,000
    # took half the test's time).
    on = model.grid(0.05)
    centres = on.grid.centres()
    seen_at = model.evidence_.seen_through_at(centres)
    assert on.seen_through is not None and seen_at is not None
    np.testing.assert_array_equal(seen_at, on.seen_through.ravel())
    pick = (on.probability.ravel() > fitted) | (np.arange(len(centres)) % 9 == 0)
    p_at, occupied_at = model.predict_proba(centres[pick]), model.predict_ternary(centres[pick]) == 1
    assert occupied_at.any() and ((p_at > fitted) & seen_at[pick]).any()  # both cases among them
    np.testing.assert_array_equal(occupied_at, (p_at > fitted) & ~seen_at[pick])
    # Without ray evidence the GP alone is not calibrated: the paper's.
    assert AreaGPOM(ray_evidence=False, **clear).fit(scans).thresholds_ == DEFAULT_THRESHOLDS


def test_surprise_rate_by_hand():
    from gpomap.fusion import MAX_SURPRISE_RATE, fit_surprise_rate

    # 100 points the counts call certainly free (p = 0), 5 of them hits: the likelihood
    # 5 log(eps / 2) + 95 log(1 - eps / 2) is largest at eps / 2 = 5 / 100.
    p, y = np.zeros(100), np.arange(100) < 5
    assert fit_surprise_rate(p, y) == pytest.approx(0.1, rel=1e-9)
    # Every point right and sure: the floor; every point wrong and sure: the ceiling.
    assert fit_surprise_rate(p, np.zeros(100, bool)) == SURPRISE_RATE
    assert fit_surprise_rate(p, np.ones(100, bool)) == MAX_SURPRISE_RATE
    # 2 hits among the 100: 0.04, inside the bounds (1e-3, 0.3) but not those of the library.
    assert fit_surprise_rate(p, np.arange(100) < 2, bounds=(1e-3, 0.3)) == pytest.approx(0.04, rel=1e-9)
    assert fit_surprise_rate(p, np.arange(100) < 2, bounds=(0.05, 0.3)) == 0.05


def test_surprise_rate_is_the_brute_force_most_likely():
    from gpomap.fusion import fit_surprise_rate

    rng = np.random.default_rng(5)
    y = rng.random(2000) < 0.5
    q = np.where(y, rng.beta(6, 1, 2000), rng.beta(1, 6, 2000))
    flip = rng.random(2000) < 0.06  # surprises: labels the probabilities did not foresee
    y = y ^ flip

    def loglik(rates):
        p = rates[:, None] / 2 + (1 - rates[:, None]) * q[None, :]
        return np.where(y[None, :], np.log(p), np.log1p(-p)).sum(axis=1)

    # Every 2 % over the bounds, then every 0.01 % within two steps either side of the best (the
    # log-likelihood is concave in the rate: each point's is the log of a linear function of it).
    coarse = np.exp(np.linspace(np.log(1e-4), np.log(0.3), 401))
    i = int(np.argmax(loglik(coarse)))
    rates = np.exp(np.linspace(np.log(coarse[max(i - 2, 0)]), np.log(coarse[min(i + 2, 400)]), 401))
    best = rates[np.argmax(loglik(rates))]
    got = fit_surprise_rate(q, y, bounds=(1e-4, 0.3))
    assert got == pytest.approx(best, rel=1e-3) and 0.01 < got < 0.3


def test_calibration_fits_the_surprise_rate_against_a_gp_that_never_saw_the_held_out_scans() -> None:
    from gpomap.fusion import fit_surprise_rate

    scans, ev, grid = _calibration_scene()
    given: list[list[Scan]] = []

    def p_apart(points: np.ndarray) -> np.ndarray:
        return 1.0 - _p_gp(points)  # another GP than the map's, so that it shows where it is used

    def gp_apart(kept: list[Scan]):
        given.append(list(kept))
        return p_apart

    # Three of the six scans held out: the GP apart is fitted on the other three.
    fitted, report, _ = fit_calibration(scans, ev, grid, _p_gp, n_scans=3, step=0.1, gp_apart=gp_apart)
    held = [0, 2, 5]  # calibration_scans(6, 3)
    assert len(given) == 1 and [id(s) for s in given[0]] == [id(scans[k]) for k in (1, 3, 4)]
    # Truth: the held-out scans' points, each with the other scans' counts taken directly, all
    # of them; counted points at the fitted weights' posterior mean over the GP apart,
    # the others at the GP apart alone; the rate maximising their likelihood.
    pts, occ, h, m, n = [], [], [], [], []
    for k in held:
        pk, ok = calibration_points(scans[k], 0.1)
        hits, misses, near, _ = ev.counts(grid, scans=np.array([j for j in range(len(scans)) if j != k]))
        cell, inside = lattice.flat_index(grid, pk)
        pts.append(pk)
        occ.append(ok)
        for dest, a in zip((h, m, n), (hits, misses, near)):
            dest.append(np.where(inside, a.reshape(-1)[cell], 0))
    P, O, H, M, N = (np.concatenate(a) for a in (pts, occ, h, m, n))
    assert O.size <= fusion.CALIBRATION_POINTS  # every point, at its own frequency
    q = np.where(H + M > 0, fitted.posterior_mean(p_apart(P), fitted.hits(H, N), fitted.misses(M, N)), p_apart(P))
    assert fitted.surprise_rate == pytest.approx(fit_surprise_rate(q, O), rel=1e-9)
    assert report["surprise_rate"] == fitted.surprise_rate and fitted.surprise_rate >= SURPRISE_RATE
    # The weights are those fitted without it, at the prior rate.
    plain, _, _ = fit_calibration(scans, ev, grid, _p_gp, n_scans=3, step=0.1)
    assert plain.surprise_rate == SURPRISE_RATE
    assert (plain.hit_weight, plain.prior_weight) == (fitted.hit_weight, fitted.prior_weight)
    # More scans held out than kept: the GP apart would not be the map's GP, the prior stays.
    short, report, _ = fit_calibration(scans, ev, grid, _p_gp, n_scans=4, step=0.1, gp_apart=gp_apart)
    assert short.surprise_rate == SURPRISE_RATE and "surprise_rate" not in report and len(given) == 1


def test_a_map_fits_its_surprise_rate_when_asked_against_its_gp_fitted_on_the_other_scans_alone():
    from gpomap.mapping import AreaGPOM
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans(n_beams=36, noise_std=0.02)
    # A 0.3 m clearance and the SE kernel, as in the test above: at the planar 0.1 m these thin
    # scans learn a 4 m length scale and the three fits take 40 s instead of 3 (1.5 with the SE
    # kernel); the GP apart is the subject here.
    clear = {"free_clearance": 0.3, "kernel": "se"}
    # By default the prior: no GP apart, no rate fitted.
    plain = AreaGPOM(n_workers=1, calibration_scans=10, **clear).fit(scans)
    assert plain.evidence_.gp_apart is None and plain.evidence_.calibration.surprise_rate == SURPRISE_RATE
    assert "surprise_rate" not in plain.evidence_.report
    # Asked, with 10 of the 31 scans held out (the GP apart fitted on the other 21): a rate that
    # every probability of the map is mixed with, above the prior on these noisy scans.
    model = AreaGPOM(n_workers=1, calibration_scans=10, fit_surprise_rate=True, **clear).fit(scans)
    rate = model.evidence_.report["surprise_rate"]
    assert model.evidence_.calibration.surprise_rate == rate > SURPRISE_RATE
    assert model.get_params()["fit_surprise_rate"] is True
    kept = scans[::2]
    held = AreaGPOM(n_workers=1, **clear).fit(kept, hyperparameters=model.hyperparameters_)
    q = np.array([[1.0, 1.0], [5.0, 5.0], [8.0, 2.0], [3.0, 6.5]])
    np.testing.assert_allclose(model.evidence_.gp_apart(kept)(q), held._gp_proba_written(q), rtol=1e-12)
    # And it is not the map's own GP, which saw the other scans too.
    assert not np.allclose(model.evidence_.gp_apart(kept)(q), model._gp_proba_written(q))


def test_sixteen_bit_path_passes_are_the_thirty_two_bit_ones_and_widen_as_scans_add_up(monkeypatch: pytest.MonkeyPatch) -> None:
    # The lattice's path passes and silent updates by path_dtype: 16-bit for a log under
    # NARROW_COUNT_SCANS scans, widened to 32 bits when added scans reach it; every count the same
    # as 32-bit ones from the start. Every 7th beam's return dropped, so that there are silent updates.
    from gpomap import evidence

    room = []
    for scan in paper_room_scans(n_beams=72):
        ranges = scan.ranges.copy()
        ranges[::7] = scan.max_range
        room.append(dataclasses.replace(scan, ranges=ranges))
    monkeypatch.setattr(evidence, "NARROW_COUNT_SCANS", 0)  # 32-bit throughout: the reference
    wide = fusion.EvidenceLayer(room[:10], 0.1, _p_gp, calibration_scans=3)
    wide.add_scans(room[10:])
    monkeypatch.setattr(evidence, "NARROW_COUNT_SCANS", 12)
    narrow = fusion.EvidenceLayer(room[:10], 0.1, _p_gp, calibration_scans=3)
    assert narrow._path.dtype == narrow._silent.dtype == np.uint16 and narrow._hits.dtype == fusion.COUNT_DTYPE
    narrow.add_scans(room[10:])  # 31 scans: past 12
    assert narrow._path.dtype == wide._path.dtype == narrow._silent.dtype == np.int32
    for name in ("_hits", "_beam_misses", "_near_misses", "_silent", "_path"):
        np.testing.assert_array_equal(getattr(narrow, name), getattr(wide, name))
    assert wide._hits.max() > 1 and wide._path.max() > 0 and wide._silent.max() > 1
    pts = np.random.default_rng(0).uniform((0.0, 0.0), (20.0, 16.0), (4000, 2))
    grid = GridSpec.from_extent((0.0, 20.0, 0.0, 16.0), 0.1)
    monkeypatch.setattr(evidence, "NARROW_COUNT_SCANS", 0)
    # A whole log at once, its calibration fitted with 16-bit passes: the 32-bit layer's numbers.
    whole = fusion.EvidenceLayer(room, 0.1, _p_gp, calibration_scans=3)
    monkeypatch.setattr(evidence, "NARROW_COUNT_SCANS", 2**16 - 1)
    short = fusion.EvidenceLayer(room, 0.1, _p_gp, calibration_scans=3)
    assert short._path.dtype == short._silent.dtype == np.uint16 and whole._path.dtype == np.int32
    np.testing.assert_array_equal(short.proba(pts, _p_gp(pts)), whole.proba(pts, _p_gp(pts)))
    for x, y in zip(short.grid_counts(grid), whole.grid_counts(grid), strict=True):
        np.testing.assert_array_equal(x, y)
    assert short.summary() == whole.summary()


@pytest.mark.parametrize("dim", [2, 3])
def test_the_calibration_sample_is_a_draw_from_every_held_out_point(monkeypatch: pytest.MonkeyPatch, dim: int) -> None:
    # Only the points drawn are made (from their rays): they are those of the draw from every
    # held-out scan's points made whole, in the same order.
    import gpomap.fusion.calibration as calibration
    from gpomap.fusion import _other_scans_counts
    from gpomap.heldout import calibration_scans
    from gpomap.observations import natural_subsample
    from tests.world3d import ORIGINS, lidar_clouds

    if dim == 2:
        scans, ev, grid = _room_scene()
    else:
        scans = lidar_clouds(ORIGINS, n_rays=200)
        ev = RayEvidence.from_scans(scans)
        grid = lattice_grid((-1.0, 7.0, -1.0, 5.0, -1.0, 3.5), 0.1)
    picked = calibration_scans(len(scans), 4)
    parts = [calibration_points(scans[k], 0.1) for k in picked]
    pts = np.concatenate([p for p, _ in parts])
    occ = np.concatenate([o for _, o in parts])
    scan_of = np.repeat(picked, [len(o) for _, o in parts])
    n = len(pts) // 5
    monkeypatch.setattr(calibration, "CALIBRATION_POINTS", n)
    keep = natural_subsample(len(pts), n, 7)
    asked: list[np.ndarray] = []

    def predict_gp(points: np.ndarray) -> np.ndarray:
        asked.append(points)
        return _p_gp(points)

    _, report, sample = fit_calibration(scans, ev, grid, predict_gp, n_scans=4, step=0.1, seed=7)
    h, m, *_ = _other_scans_counts(ev, grid, ev.counts(grid), pts[keep], scan_of[keep], False)
    counted = (h > 0) | (m > 0)
    assert report["n_points"] == n and 0 < counted.sum() < n
    np.testing.assert_array_equal(asked[0], pts[keep][counted])
    np.testing.assert_array_equal(sample.occupied, occ[keep][counted])


def test_a_layer_set_aside_holds_nothing_and_comes_back_the_same() -> None:
    from gpomap.fusion import EvidenceLayer

    scans, _, _ = _calibration_scene()
    layer = EvidenceLayer(scans, 0.1, _p_gp, calibration_scans=len(scans))
    names = ("_hits", "_beam_misses", "_near_misses", "_path")
    before = {n: getattr(layer, n).copy() for n in names}
    assert all(a.size for a in before.values())
    P = np.random.default_rng(3).uniform(-1.0, 6.0, size=(500, 2))
    p_before, surface = layer.proba(P, _p_gp(P)), layer.at_surface().copy()
    with layer.set_aside():
        assert all(getattr(layer, n).size == 0 for n in names)
    for n in names:
        after = getattr(layer, n)
        assert after.dtype == before[n].dtype and np.array_equal(after, before[n])
    assert np.array_equal(layer.proba(P, _p_gp(P)), p_before)
    assert np.array_equal(layer.at_surface(), surface)


def test_the_silent_rate_is_the_likelihoods_maximum_found_by_brute_force() -> None:
    """fit_silent_rate against a search of the whole (mix, rate) square: a map's probabilities
    that say nothing of these cells' classes (drawn apart from them) are mixed towards their share."""
    from gpomap.fusion import SILENT_FIT_POINTS, fit_silent_rate

    rng = np.random.default_rng(3)
    n = 2000
    occupied = rng.random(n) < 0.15
    p = rng.uniform(0.0, 0.1, n)

    def loss(mix: float, rate: float) -> float:
        q = (1.0 - mix) * p + mix * rate
        return float(-np.mean(np.where(occupied, np.log(q), np.log1p(-q))))

    rate, mix = fit_silent_rate(p, occupied)
    mixes, rates = np.linspace(0.0, 1.0, 201), np.linspace(0.005, 0.5, 199)
    best = min(loss(m, r) for m in mixes for r in rates)
    assert loss(mix, rate) <= best + 1e-6
    # Probabilities drawn apart from the classes are worth nothing: all the rate, and the rate the
    # points' share of hits (a constant's likelihood is largest at the share).
    assert mix == pytest.approx(1.0, abs=1e-3) and rate == pytest.approx(occupied.mean(), abs=1e-3)
    # Too few points to fit: the probabilities as they are.
    assert fit_silent_rate(p[: SILENT_FIT_POINTS - 1], occupied[: SILENT_FIT_POINTS - 1]) == (0.0, 0.0)
