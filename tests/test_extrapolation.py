"""The squash's variance scale, fitted on held-out stretches of the log (gpomap.extrapolation)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.special import ndtr

import gpomap.extrapolation as ex
import gpomap.heldout as heldout
import gpomap.observations as observations
from gpomap.mapping import AreaGPOM
from gpomap.simulate import paper_room, paper_room_scans, simulate_scans
from gpomap.squash import ProbitSquash


def test_holdout_stretches_by_hand():
    kept, held = heldout.holdout_stretches(20)
    # Ten stretches of two scans; the 2nd, 5th and 8th are held out.
    assert held.tolist() == [2, 3, 8, 9, 14, 15]
    assert sorted(kept.tolist() + held.tolist()) == list(range(20))
    # Nine scans: one per stretch.
    assert heldout.holdout_stretches(9)[1].tolist() == [1, 4, 7]
    # Too short to hold anything out.
    assert heldout.holdout_stretches(2)[1].size == 0


class _Fixed:
    """A stand-in for the held-in GP: latent moments from a given function of the points."""

    def __init__(self, moments):
        self.moments = moments

    def fit(self, obs):
        return self

    def predict(self, points, return_var=False):
        return self.moments(points)


SETTINGS = AreaGPOM().base


def _points(scans):
    """The map's points before the clearance: what each pattern's held-in points are cut from."""
    return SETTINGS.make_observations(scans, clearance=False)


def _fit(scans, moments, **kw):
    return ex.fit_variance_scale(
        scans,
        {"alpha": 30.0, "beta": 0.0},
        _points(scans),
        SETTINGS.clearance(2),
        _Fixed(moments).fit,
        centre=np.zeros(2),
        region_half=50.0,
        margin=0.0,
        **kw,
    )


def _room_scans():
    scans = paper_room_scans(n_beams=90, seed=0)
    # Drop the first third of the beams of the kept stretches' scans, so the held-out stretches
    # see space no kept beam went (as when a robot enters a room only later).
    kept, _ = heldout.holdout_stretches(len(scans))
    for i in kept:
        s = scans[i]
        keep = np.arange(s.n_beams) >= s.n_beams // 3
        scans[i] = type(s)(s.pose, s.angles[keep], s.ranges[keep], max_range=s.max_range)
    return scans


def _truth(scans):
    hits = cKDTree(np.concatenate([s.hits() for s in scans]))

    def occupied(points):
        # Each point's distance to its nearest hit, by a k-d tree: all pairs at once took most of
        # these tests' time (8 s of one test's 11).
        d, _ = hits.query(points, distance_upper_bound=1e-6)
        return d < 1e-9

    return occupied


def test_a_perfect_predictor_gets_the_sharpest_scale_and_a_coin_a_very_soft_one():
    scans = _room_scans()
    occupied = _truth(scans)
    kappa, report = _fit(scans, lambda p: (np.where(occupied(p), 1.0, -1.0), np.ones(len(p))))
    assert report["n_points"] >= ex.MIN_POINTS_PER_CLASS
    assert kappa == pytest.approx(ex.VARIANCE_SCALE_BOUNDS[0], rel=1e-3)
    rng = np.random.default_rng(0)
    kappa, _ = _fit(scans, lambda p: (rng.choice([-1.0, 1.0], len(p)), np.ones(len(p))))
    # A coin's likelihood is best at p = 1/2, where kappa is infinite; the sample's few points
    # more right than wrong stop the fit short of that, but far above 1.
    assert kappa > 100


def test_the_fitted_scale_is_the_likelihoods_best_by_brute_force():
    scans = _room_scans()
    occupied = _truth(scans)
    rng = np.random.default_rng(1)

    # Right four times in five, with a latent variance of 1/4: over-sure at kappa = 1.
    def moments(p):
        sign = np.where(occupied(p), 1.0, -1.0) * np.where(rng.random(len(p)) < 0.8, 1.0, -1.0)
        return 0.5 * sign, np.full(len(p), 0.25)

    state = rng.bit_generator.state
    kappa, report = _fit(scans, moments, seed=3)
    # The same points and moments again, scored on a fine grid of kappa.
    rng.bit_generator.state = state
    pts = []
    model = _Fixed(lambda p: pts.append(p) or moments(p))
    _, again = ex.fit_variance_scale(
        scans, {"alpha": 30.0, "beta": 0.0}, _points(scans), SETTINGS.clearance(2), model.fit, np.zeros(2), 50.0, 0.0, seed=3
    )
    assert again["kappa"] == pytest.approx(kappa)
    rng.bit_generator.state = state
    mu, var = moments(pts[0])
    y = occupied(pts[0])

    def scored(grid):
        p = ndtr(30.0 * mu[None, :] / np.sqrt(1.0 + 900.0 * grid[:, None] * var[None, :]))
        return -np.mean(np.where(y[None, :], np.log(p), np.log1p(-p)), axis=1)

    # Every 2.3 % over the bounds, then every 0.01 % within two steps either side of the best.
    coarse = np.exp(np.linspace(np.log(0.1), np.log(1e4), 501))
    best = int(np.argmin(scored(coarse)))
    grid = np.exp(np.linspace(np.log(coarse[max(best - 2, 0)]), np.log(coarse[min(best + 2, 500)]), 401))
    nll = scored(grid)
    alone = ex.VarianceScale.fit(mu, var, y, 30.0, 0.0).kappa
    assert alone == pytest.approx(grid[np.argmin(nll)], rel=0.01)
    assert ex._nll(alone, mu, var, y, 30.0, 0.0) == pytest.approx(nll.min(), abs=1e-4)
    assert report["log_loss"] == pytest.approx(nll.min(), abs=1e-4)
    assert report["log_loss"] <= report["log_loss_at_1"] + 1e-12


def test_region_observations_equal_the_kept_scans_observed_alone():
    scans = paper_room_scans(n_beams=90, seed=0)
    # A clearance wider than the square's 0.1 m gap to the outer wall, so hits outside it clear points inside.
    settings = AreaGPOM(free_clearance=0.3).base
    whole = settings.make_observations(scans, clearance=False)
    kept, _ = heldout.holdout_stretches(len(scans))
    # A square cutting through the room: hits just outside it clear free points just inside.
    lo, hi = np.array([0.1, 2.0]), np.array([12.0, 9.5])  # the outer wall x = 0 just outside
    got = ex.region_observations(whole, kept, lo, hi, settings.clearance(2))
    alone = settings.make_observations([scans[i] for i in kept])  # with the clearance
    inside = np.all((alone.points >= lo) & (alone.points <= hi), axis=1)
    np.testing.assert_array_equal(got.points, alone.points[inside])
    np.testing.assert_array_equal(got.occupied, alone.occupied[inside])
    np.testing.assert_array_equal(got.scan_index, kept[alone.scan_index[inside]])
    # The clearance was applied, and near the square's edge it took hits from outside.
    unclear = ex.region_observations(whole, kept, lo, hi, 0.0)
    assert unclear.n_free > got.n_free and unclear.n_occupied == got.n_occupied
    cut = np.all((whole.points >= lo) & (whole.points <= hi), axis=1) & np.isin(whole.scan_index, kept)
    from gpomap.observations import free_near_hits

    inside_only = whole.points[cut][~free_near_hits(whole.points[cut], whole.occupied[cut], settings.clearance(2))]
    assert len(inside_only) > len(got.points)


@pytest.mark.parametrize("made", [False, True], ids=["held", "made again"])
def test_the_kept_region_made_part_by_part_is_region_observations(monkeypatch, made):
    # Each pattern's held-in points, cut from the scans' points made again a few scans at a
    # time (or from the points held), are region_observations of every point at once.
    from gpomap.observations import ScanPoints

    monkeypatch.setattr(observations, "PART_POINTS", 500)
    world, poses = paper_room()
    scans = simulate_scans(world, poses, 90, max_range=3.0, seed=0)  # short beams: not all reach the square
    settings = AreaGPOM().base
    whole = settings.make_observations(scans, clearance=False)
    how = (settings.free_step, settings.hit_margin, settings.no_return_cap)
    source = ScanPoints(scans, *how) if made else ex._HeldPoints(whole)
    lo, hi = poses[12, :2] - 2.0, poses[12, :2] + 3.0
    answers = set()
    for first in heldout.FOLD_STARTS:
        kept, _ = heldout.holdout_stretches(len(scans), first)
        got = ex._kept_region(source, kept, lo, hi, settings.clearance(2))
        want = ex.region_observations(whole, kept, lo, hi, settings.clearance(2))
        for a in ("points", "occupied", "scan_index"):
            np.testing.assert_array_equal(getattr(got, a), getattr(want, a))
        assert want.n_free > 0 and want.n_occupied > 0
        # Which patterns' kept scans observed both classes in the square.
        inside = np.all((whole.points >= lo) & (whole.points <= hi), axis=1)
        for some in (kept, kept[:3], kept[-2:]):
            occupied = whole.occupied[inside & np.isin(whole.scan_index, some)]
            answers.add(ex._observes_both(source, len(scans), lo, hi)(some))
            assert ex._observes_both(source, len(scans), lo, hi)(some) == (occupied.any() and not occupied.all())
    assert answers == {True, False}
    if made:
        meets = np.all((source.scan_lower[:, :2] <= hi) & (source.scan_upper[:, :2] >= lo), axis=1)
        assert meets.any() and not meets.all()


def _unseen_by_hand(kept_scans, held_scans, lo, hi, margin, cap):
    """The held-out scans' points in the square shrunk by `margin` where no kept beam went, every
    point made whole: points and classes."""
    from gpomap.evidence import RayEvidence, lattice_grid
    from gpomap.heldout import calibration_points
    from gpomap.lattice import bounds_extent, column_bounds, flat_index, in_box

    parts = [calibration_points(s, no_return_cap=cap) for s in held_scans]
    pts, occ = np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])
    sel = in_box(pts, lo + margin, hi - margin)
    pts, occ = pts[sel], occ[sel]
    grid = lattice_grid(bounds_extent(*column_bounds(pts)), ex.UNSEEN_RESOLUTION[pts.shape[1]])
    cell, ok = flat_index(grid, pts)
    seen = ok & RayEvidence.from_scans(kept_scans, cap).seen(grid).reshape(-1)[cell]
    return pts[~seen], occ[~seen]


# (bytes of points kept between the two passes, points a run): all kept, none kept in runs of
# whole rays shorter than a scan, some kept.
BUDGETS = [(ex.POINT_MEMORY, None), (0, 50), (3000, 7)]


@pytest.mark.parametrize(("memory", "run"), BUDGETS)
def test_unseen_points_pass_over_only_scans_that_cannot_reach_the_square(monkeypatch, memory, run):
    # Short beams (3 m) round the paper room, and a square round one pose: most scans cannot
    # reach it, and skipping them changes nothing.
    from gpomap.observations import beams_reach

    if run is not None:
        monkeypatch.setattr(heldout, "RUN_POINTS", run)
    world, poses = paper_room()
    scans = simulate_scans(world, poses, 90, max_range=3.0, seed=0)
    kept, held = heldout.holdout_stretches(len(scans))
    # A square round a held-out pose, most of the room away from it.
    lo, hi, margin = poses[held[0], :2] - 2.0, poses[held[0], :2] + 3.0, 0.25
    kept_scans, held_scans = [scans[i] for i in kept], [scans[i] for i in held]
    unseen = ex._unseen_points(kept_scans, held_scans, lo, hi, margin, 10.0, memory=memory)
    got_pts, got_occ = unseen.take(np.arange(unseen.size))
    # By hand, every scan looked at, every point made at once.
    pts, occ = _unseen_by_hand(kept_scans, held_scans, lo, hi, margin, 10.0)
    np.testing.assert_array_equal(got_pts, pts)
    np.testing.assert_array_equal(got_occ, occ)
    assert unseen.n_occupied == occ.sum() and occ.any() and not occ.all()
    # A draw of a few: those of the whole.
    index = np.sort(np.random.default_rng(0).choice(unseen.size, 40, replace=False))
    got_pts, got_occ = unseen.take(index)
    np.testing.assert_array_equal(got_pts, pts[index])
    np.testing.assert_array_equal(got_occ, occ[index])
    reach = [beams_reach(s, lo, hi, 10.0) for s in scans]
    assert any(reach) and not all(reach)  # the test passes some scans over


@pytest.mark.parametrize(("memory", "run"), BUDGETS)
def test_unseen_points_of_point_clouds(monkeypatch, memory, run):
    from tests.world3d import ORIGINS, lidar_clouds

    if run is not None:
        monkeypatch.setattr(heldout, "RUN_POINTS", run)
    clouds = lidar_clouds(np.tile(ORIGINS, (2, 1)), n_rays=150)
    kept, held = heldout.holdout_stretches(len(clouds))
    kept_scans, held_scans = [clouds[i] for i in kept], [clouds[i] for i in held]
    lo, hi = np.array([0.5, 0.0]), np.array([5.0, 3.5])
    unseen = ex._unseen_points(kept_scans, held_scans, lo, hi, 0.1, None, memory=memory)
    pts, occ = _unseen_by_hand(kept_scans, held_scans, lo, hi, 0.1, None)
    got_pts, got_occ = unseen.take(np.arange(unseen.size))
    np.testing.assert_array_equal(got_pts, pts)
    np.testing.assert_array_equal(got_occ, occ)
    assert pts.shape[1] == 3 and occ.any() and not occ.all()


@pytest.mark.parametrize(("memory", "run"), BUDGETS)
def test_the_scale_is_fitted_on_a_draw_from_all_patterns_unseen_points(monkeypatch, memory, run):
    # Each pattern's held-in GP is asked about its own points of one uniform draw from every
    # pattern's unseen points in turn, as if all were made at once.
    if run is not None:
        monkeypatch.setattr(heldout, "RUN_POINTS", run)
    unseen_points = ex._unseen_points
    monkeypatch.setattr(ex, "_unseen_points", lambda *a: unseen_points(*a, memory=memory))
    scans = _room_scans()
    lo, hi = np.full(2, -50.0), np.full(2, 50.0)
    by_hand = []
    for first in heldout.FOLD_STARTS[:2]:
        kept, held = heldout.holdout_stretches(len(scans), first)
        by_hand.append(
            _unseen_by_hand([scans[i] for i in kept], [scans[i] for i in held], lo, hi, 0.0, ex.MapConfig.no_return_cap)
        )
    # The first pattern alone holds too few of a class, the first two pooled enough: two GPs.
    fewest = int(min(by_hand[0][1].sum(), (~by_hand[0][1]).sum()))
    monkeypatch.setattr(ex, "MIN_POINTS_PER_CLASS", fewest + 1)
    pts = np.concatenate([p for p, _ in by_hand])
    occ = np.concatenate([o for _, o in by_hand])
    assert min(occ.sum(), (~occ).sum()) > fewest + 1
    monkeypatch.setattr(ex, "MAX_POINTS", len(pts) // 3)
    asked = []

    class Recorder(_Fixed):
        def predict(self, points, return_var=False):
            asked.append(points)
            return np.zeros(len(points)), np.ones(len(points))

    _, report = ex.fit_variance_scale(
        scans,
        {"alpha": 30.0, "beta": 0.0},
        _points(scans),
        SETTINGS.clearance(2),
        Recorder(None).fit,
        np.zeros(2),
        50.0,
        0.0,
        seed=4,
    )
    assert report["n_patterns"] == 2 and report["n_points"] == len(pts) // 3
    keep = observations.natural_subsample(len(pts), len(pts) // 3, 4)
    fold_of = np.repeat([0, 1], [len(p) for p, _ in by_hand])[keep]
    assert len(asked) == 2 and (fold_of == 0).any() and (fold_of == 1).any()
    for k in (0, 1):
        np.testing.assert_array_equal(asked[k], pts[keep][fold_of == k])


def test_beams_reach_by_hand():
    from gpomap.observations import beams_reach
    from gpomap.scans import Scan

    # One beam of 2 m along +x from (0, 0).
    scan = Scan(pose=np.array([0.0, 0.0, 0.0]), angles=np.array([0.0]), ranges=np.array([2.0]), max_range=5.0)
    assert beams_reach(scan, [1.9, -1.0], [3.0, 1.0])  # the box begins within 2 m
    assert beams_reach(scan, [-3.0, 1.0], [-1.0, 3.0])  # sqrt(2) m away, behind: reach is a radius
    assert not beams_reach(scan, [2.1, -1.0], [3.0, 1.0])
    assert not beams_reach(scan, [1.5, 1.5], [3.0, 3.0])  # corner 2.12 m away
    # A no-return beam (at the max range, 5 m) reaches as far as the cap allows.
    far = Scan(pose=np.array([0.0, 0.0, 0.0]), angles=np.array([0.0]), ranges=np.array([5.0]), max_range=5.0)
    assert beams_reach(far, [4.5, -1.0], [6.0, 1.0]) and beams_reach(far, [4.5, -1.0], [6.0, 1.0], no_return_cap=4.6)
    assert not beams_reach(far, [4.5, -1.0], [6.0, 1.0], no_return_cap=4.0)
    assert beams_reach(scan, [1.9, -1.0], [3.0, 1.0], no_return_cap=1.0)  # a hit is not capped


def test_too_few_unseen_points_leave_the_scale_at_one():
    # A robot standing still: every held-out beam is a kept one, nothing is unseen.
    scans = paper_room_scans(n_beams=90, seed=0)[:1] * 20
    kappa, report = _fit(scans, lambda p: (np.zeros(len(p)), np.ones(len(p))))
    assert kappa == 1.0 and "reason" in report


@pytest.fixture(scope="module")
def fitted_room() -> AreaGPOM:
    """One fit for the two tests below, which only read it.

    A 0.3 m free clearance: on these thin scans the planar 0.1 m learns a 5 m length scale and fits
    10x slower, its scale at the lower bound; at 0.3 m the scale is fitted inside its bounds.
    """
    return AreaGPOM(min_cell=0.5, max_cell=1.0, free_clearance=0.3).fit(_room_scans())


def test_a_fitted_map_carries_its_scale_and_stays_unknown_far_away(fitted_room: AreaGPOM) -> None:
    model = fitted_room
    kappa = model.hyperparameters_["variance_scale"]
    assert kappa == model.extrapolation_["kappa"] == model.summary()["variance_scale_fit"]["kappa"]
    assert ex.VARIANCE_SCALE_BOUNDS[0] <= kappa <= ex.VARIANCE_SCALE_BOUNDS[1]
    # beta is 0, so far from the data the map is unknown whatever kappa is.
    assert model.predict_proba(np.array([[500.0, 500.0]]))[0] == pytest.approx(0.5, abs=1e-9)


def test_the_scale_applies_only_where_no_beam_went(fitted_room: AreaGPOM) -> None:
    model = fitted_room
    hyp = model.hyperparameters_
    squash = ProbitSquash(hyp["alpha"], hyp["beta"], hyp["variance_scale"])
    assert squash.variance_scale != 1  # a scale was fitted, so the formula below is told apart from the GP's own
    rng = np.random.default_rng(0)
    lo, hi = (corner + shift for corner, shift in zip(model.bounds_, (-2.0, 2.0)))
    pts = rng.uniform(lo, hi, (4000, 2))
    h, m, _ = model.evidence_.counts_at(pts)
    empty = (h == 0) & (m == 0)
    assert 100 < empty.sum() < len(pts) - 100
    mean, var = model.predict(pts, return_var=True)
    p = model.predict_proba(pts)
    # Cells some beam crossed: the counts on top of the GP's own (leave-one-out) probability.
    seen = model.evidence_.calibration(squash(mean, var), h, m)
    np.testing.assert_allclose(p[~empty], seen[~empty], rtol=0, atol=1e-12)
    # Cells none did: the probit with the latent variance scaled by kappa, by hand; nothing near a
    # surface or behind one moves it.
    a, kappa = squash.alpha, squash.variance_scale
    z = a * mean[empty] / np.sqrt(1 + a * a * kappa * var[empty])
    np.testing.assert_allclose(p[empty], 0.005 + 0.99 * ndtr(z), rtol=0, atol=1e-9)


def test_point_clouds_fit_the_variance_scale() -> None:
    from tests.world3d import ORIGINS, lidar_clouds

    clouds = lidar_clouds(np.tile(ORIGINS, (4, 1)), n_rays=300)
    # Held-out rays' points where no kept ray went, enough of each class to fit kappa on (the
    # GP's moments have no say in finding them).
    moments = _Fixed(lambda p: (np.zeros(len(p)), np.ones(len(p))))
    _, report = ex.fit_variance_scale(
        clouds,
        {"alpha": 1.0, "beta": 0.0},
        SETTINGS.make_observations(clouds, clearance=False),
        0.0,
        moments.fit,
        np.zeros(2),
        50.0,
        0.0,
    )
    assert report["n_points"] >= ex.MIN_POINTS_PER_CLASS


def test_a_voxel_map_keeps_the_gps_own_variance(monkeypatch: pytest.MonkeyPatch) -> None:
    # The clouds the test above fits kappa on: a voxel map leaves it at 1 (the GP's own variance);
    # asked to (the profile's flag), the same map fits it.
    from tests.world3d import ORIGINS, lidar_clouds

    clouds = lidar_clouds(np.tile(ORIGINS, (4, 1)), n_rays=300)
    model = AreaGPOM(n_workers=1).fit(clouds)
    assert model.hyperparameters_["variance_scale"] == 1.0
    assert "voxel maps" in model.extrapolation_["reason"]
    monkeypatch.setitem(ex.FIT_VARIANCE_SCALE, 3, True)
    fitted = AreaGPOM(n_workers=1).fit(clouds).extrapolation_
    assert "reason" not in fitted and fitted["n_points"] >= ex.MIN_POINTS_PER_CLASS


def test_a_region_with_too_few_unseen_points_gives_way_to_the_wider_one(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ex, "REGION_POINTS_PER_CLASS", 200)  # the whole room holds 384 a class
    scans = _room_scans()
    occupied = _truth(scans)
    model = _Fixed(lambda p: (np.where(occupied(p), 0.5, -0.5), np.full(len(p), 0.25)))
    obs = _points(scans)

    def fit(centre, half, wider=None):
        return ex.fit_variance_scale(
            scans, {"alpha": 30.0, "beta": 0.0}, obs, SETTINGS.clearance(2), model.fit, centre, half, 0.0, wider=wider
        )[1]

    small = fit(np.array([3.0, 3.0]), 1.5)
    assert small.get("n_points", 0) < ex.REGION_POINTS_PER_CLASS  # a corner of the room holds few
    wide = fit(np.zeros(2), 50.0)
    assert wide["n_points"] >= ex.REGION_POINTS_PER_CLASS
    # Too few in the first region: the wider one is taken, as if it had been given alone.
    got = fit(np.array([3.0, 3.0]), 1.5, wider=(np.zeros(2), 50.0, 0.0))
    assert got["region_half"] == 50.0 and got["kappa"] == wide["kappa"] and got["n_points"] == wide["n_points"]
    # Enough in the first: it is kept.
    assert fit(np.zeros(2), 50.0, wider=(np.zeros(2), 80.0, 0.0))["region_half"] == 50.0


def test_new_ground_centre_by_hand() -> None:
    # 20 scans: the first pattern holds out scans 2, 3, 8, 9, 14 and 15 (scan 0 is kept).
    wall = np.c_[np.arange(0.0, 10.0, 0.5), np.zeros(20)]  # kept hits in the square (0, 0) of 20 m
    rows = [
        (wall, True, 0),
        (wall[:5] + np.array([0.0, 0.9]), True, 2),  # held out, within 1 m of a kept hit: not new
        (np.array([[5.0, 5.0]]), False, 0),  # a kept free point in (0, 0)
        (np.array([[35.0, 15.0]]), True, 0),  # the square (1, 0): a kept hit ...
        (np.array([[30.0, 10.0]]), False, 0),  # ... a kept free point ...
        (np.array([[25.0, 5.0], [26.0, 5.0], [27.0, 6.0]]), True, 8),  # ... and three new hits
        (np.array([[45.0, 45.0]]), True, 0),  # the square (2, 2): a kept hit, no kept free point ...
        (np.array([[50.0, 50.0], [51.0, 50.0], [52.0, 50.0], [53.0, 50.0]]), True, 14),  # ... four new hits
    ]
    points = np.concatenate([r[0] for r in rows])
    occupied = np.concatenate([np.full(len(r[0]), r[1]) for r in rows])
    scan_index = np.concatenate([np.full(len(r[0]), r[2]) for r in rows])
    obs = ex.Observations(points, occupied, scan_index)
    # The square (2, 2) has more new hits, but a held-in GP there would have no free point.
    np.testing.assert_allclose(ex.new_ground_centre(obs, 20, 20.0), [30.0, 10.0])
    # Without the kept free point of (1, 0), no square will do; nor without held-out hits.
    no_free = ~np.all(points == [30.0, 10.0], axis=1)
    assert ex.new_ground_centre(ex.Observations(points[no_free], occupied[no_free], scan_index[no_free]), 20, 20.0) is None
    kept = np.isin(scan_index, [0])
    assert ex.new_ground_centre(ex.Observations(points[kept], occupied[kept], scan_index[kept]), 20, 20.0) is None


def test_square_lattice_marks_what_a_set_of_squares_holds(monkeypatch: pytest.MonkeyPatch) -> None:
    # Against the squares found one point at a time, in chunks smaller than the points.
    monkeypatch.setattr(ex._SquareLattice, "CHUNK", 7)
    rng = np.random.default_rng(3)
    pts = rng.uniform([-31.0, -12.0], [44.0, 9.0], size=(200, 2))
    mask = rng.random(200) < 0.3
    lattice = ex._SquareLattice(pts, 10.0)
    got = {tuple(lattice.centre(int(k))) for k in np.flatnonzero(lattice.holding(pts, mask))}
    want = {tuple((np.floor(p / 10.0) + 0.5) * 10.0) for p in pts[mask]}
    assert got == want
    # Squares are numbered x-major: equal counts go to the least x, then the least y.
    k = lattice.index(np.array([[-25.0, 5.0], [-25.0, -5.0], [15.0, -5.0]]))
    counts = np.bincount(k, minlength=lattice.size)
    np.testing.assert_allclose(lattice.centre(int(np.argmax(counts))), [-25.0, -5.0])


def _visit_scans():
    """The paper's room, the robot in its left part (x < 12) but for the second of ten stretches
    of the log, when it drives up the right part: the first pattern holds that stretch out, and
    its held-out scans alone see most of the right part."""
    world, _ = paper_room()
    n = 5  # scans per stretch
    left = np.c_[np.linspace(2.0, 10.0, n), np.full(n, 7.5), np.zeros(n)]  # sees through the doorway
    right = np.c_[np.full(n, 14.0), np.linspace(3.0, 14.0, n), np.full(n, np.pi / 2)]
    poses = [right if k == 1 else left for k in range(heldout.N_STRETCHES)]
    return simulate_scans(world, np.concatenate(poses), n_beams=180, seed=0)


def test_too_few_in_both_regions_tries_where_held_out_stretches_saw_new_ground(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ex, "REGION_POINTS_PER_CLASS", 200)
    scans = _visit_scans()
    occupied = _truth(scans)
    model = _Fixed(lambda p: (np.where(occupied(p), 0.5, -0.5), np.full(len(p), 0.25)))
    obs = _points(scans)
    corner, outside = np.array([3.0, 3.0]), np.array([-30.0, -30.0])

    def fit(centre, wider=None):
        return ex.fit_variance_scale(
            scans, {"alpha": 30.0, "beta": 0.0}, obs, SETTINGS.clearance(2), model.fit, centre, 3.0, 0.0, wider=wider
        )[1]

    ground = ex.new_ground_centre(obs, len(scans), 6.0)
    assert ground is not None and ground[0] > 12.0  # in the right part
    alone = {name: fit(c).get("n_points", 0) for name, c in [("corner", corner), ("outside", outside), ("ground", ground)]}
    assert alone["ground"] > max(alone["corner"], alone["outside"])
    got = fit(corner, wider=(outside, 3.0, 0.0))
    np.testing.assert_allclose(got["region_centre"], ground)
    assert got["n_points"] == alone["ground"] and got["region_half"] == 3.0
    # The same from the points made again a few scans at a time (never all held): to the bit.
    monkeypatch.setattr(observations, "PART_POINTS", 3000)
    again = observations.ScanPoints(scans, SETTINGS.free_step, SETTINGS.hit_margin, SETTINGS.no_return_cap)
    np.testing.assert_array_equal(ex.new_ground_centre(again, len(scans), 6.0), ground)
    redo = ex.fit_variance_scale(
        scans,
        {"alpha": 30.0, "beta": 0.0},
        again,
        SETTINGS.clearance(2),
        model.fit,
        corner,
        3.0,
        0.0,
        wider=(outside, 3.0, 0.0),
    )[1]
    assert redo == got


def test_the_unseen_probit_by_hand() -> None:
    """``unseen_probit``: kappa scales the variance, num / sqrt(1 + kappa den)."""
    from gpomap.squash import unseen_probit

    num = np.array([-2.0, -0.5, 1.0])
    den = np.array([0.0, 3.0, 1.5])
    # -2 with no variance; -0.5 / sqrt(1 + 2 * 3) = -0.5 / sqrt(7); 1 / sqrt(1 + 2 * 1.5) = 0.5.
    np.testing.assert_allclose(unseen_probit(num, den, 2.0), [-2.0, -0.5 / np.sqrt(7.0), 0.5], rtol=0, atol=1e-15)
