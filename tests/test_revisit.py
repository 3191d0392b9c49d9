"""The recalibration for a later visit: its map of probabilities, its fit, its held-out stretch, and a map that uses it."""

import math
from dataclasses import replace

import numpy as np
import pytest

from gpomap import revisit as rv
from gpomap.fusion import fit_silent_rate
from gpomap.grid import CALIBRATED_THRESHOLDS
from gpomap.heldout import calibration_points, holdout_stretches
from gpomap.mapping import AreaGPOM
from gpomap.observations import natural_subsample
from gpomap.simulate import paper_room, simulate_scans


def _by_hand(p: float, slope: float, shift: float) -> float:
    z = math.log(p / (1.0 - p))
    z2 = slope * z + shift * (1.0 - math.exp(-0.5 * (z / rv.WIDTH) ** 2))
    return 1.0 / (1.0 + math.exp(-z2))


def test_recalibration_by_hand_keeps_one_half_and_keeps_order():
    r = rv.RevisitCalibration(slope=0.8, shift=1.2)
    for p in (0.005, 0.1, 0.3, 0.7, 0.9, 0.995):
        assert r(p) == pytest.approx(_by_hand(p, 0.8, 1.2), rel=1e-12)
    # Far from all data the map says 1/2; so it does after.
    assert r(0.5) == pytest.approx(0.5, abs=1e-15)
    p = np.linspace(0.001, 0.999, 2001)
    # Every map the fit may return keeps the order of probabilities (the ternary map its classes).
    for slope in rv.SLOPE_BOUNDS:
        for shift in (-rv.MAX_SHIFT_RATIO * slope, rv.MAX_SHIFT_RATIO * slope):
            assert np.all(np.diff(rv.RevisitCalibration(slope, shift)(p)) > 0), (slope, shift)
    # Beyond the bound it would not: the fit's bound is needed.
    assert not np.all(np.diff(rv.RevisitCalibration(0.5, 3.0 * 0.5 * rv.MAX_SHIFT_RATIO)(p)) > 0)
    q = np.array([0.2, 0.6])
    np.testing.assert_array_equal(rv.RevisitCalibration()(q), q)
    assert rv.RevisitCalibration().identity and not r.identity


def _weighted_loss(slope, shift, p_l, y_l, p_a, y_a):
    total = 0.0
    for p, y in ((p_l, y_l), (p_a, y_a)):
        q = rv.RevisitCalibration(slope, shift)(p)
        total += 0.5 * np.mean(np.where(y, -np.log(q), -np.log1p(-q)))
    return total


def test_fit_is_the_brute_force_optimum_of_both_halves():
    rng = np.random.default_rng(3)
    # A later stretch more occupied than its map says, the points among the training scans as it says.
    p_l = rng.uniform(0.01, 0.99, 4000)
    y_l = rng.uniform(size=p_l.size) < rv.RevisitCalibration(0.8, 1.0)(p_l)
    p_a = rng.uniform(0.01, 0.99, 3000)
    y_a = rng.uniform(size=p_a.size) < p_a
    got = rv.RevisitCalibration.fit(p_l, y_l, p_a, y_a)
    slopes, shifts = np.linspace(0.6, 1.4, 81), np.linspace(-0.5, 1.5, 81)
    losses = np.array([[_weighted_loss(a, b, p_l, y_l, p_a, y_a) for b in shifts] for a in slopes])
    i, j = np.unravel_index(np.argmin(losses), losses.shape)
    assert got.slope == pytest.approx(slopes[i], abs=0.011)
    assert got.shift == pytest.approx(shifts[j], abs=0.026)
    assert _weighted_loss(got.slope, got.shift, p_l, y_l, p_a, y_a) <= losses.min() + 1e-9
    # Between the later half's truth (0.8, 1.0) and the identity the other half wants.
    assert 0.8 < got.slope < 1.0 and 0.0 < got.shift < 1.0


def test_fit_is_the_identity_when_a_half_lacks_a_class():
    p = np.array([0.2, 0.7, 0.9])
    both, occupied = np.array([True, False, True]), np.ones(3, bool)
    assert rv.RevisitCalibration.fit(p, occupied, p, both).identity
    assert rv.RevisitCalibration.fit(p, both, p, ~occupied).identity


def _tour(n: int, n_beams: int = 36):
    """`n` noisy scans along the paper room's tour."""
    world, poses = paper_room()
    xy = poses[:, :2]
    arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
    s = np.linspace(0.0, arc[-1], n)
    dense = np.column_stack([np.interp(s, arc, xy[:, 0]), np.interp(s, arc, xy[:, 1])])
    step = np.gradient(dense, axis=0)
    dense = np.column_stack([dense, np.arctan2(step[:, 1], step[:, 0])])
    return simulate_scans(world, dense, n_beams, noise_std=0.02, seed=0)


def test_later_visit_points_are_a_held_out_stretch_predicted_by_a_map_of_the_rest():
    scans = _tour(rv.MIN_SCANS)
    kept, held = holdout_stretches(len(scans))
    asked = {}

    def fit_rest(rest, points):
        asked["scans"] = rest
        asked["points"] = points
        return np.linspace(0.1, 0.9, len(points))

    p, occupied, report = rv.later_visit_points(scans, fit_rest, seed=1)
    assert [id(s) for s in asked["scans"]] == [id(scans[i]) for i in kept]
    # The held-out scans' points at their own frequencies: a uniform sample of the cap's size.
    parts = [calibration_points(scans[i], no_return_cap=10.0) for i in held]
    pts, occ = np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])
    assert occ.size > rv.POINTS
    assert report["n_points"] == rv.POINTS == occupied.size
    # Hits keep their share, within a binomial draw's four standard deviations.
    share = occ.mean()
    assert abs(occupied.mean() - share) < 4 * np.sqrt(share * (1 - share) / rv.POINTS)
    label = {tuple(np.round(q, 9)): o for q, o in zip(pts, occ)}
    assert [label[tuple(np.round(q, 9))] for q in asked["points"]] == occupied.tolist()
    np.testing.assert_array_equal(p, np.linspace(0.1, 0.9, rv.POINTS))


def test_the_points_drawn_by_number_are_those_drawn_from_all():
    """Only the points drawn are made, and they are the uniform draw from every held-out point
    concatenated in scan order."""
    scans = _tour(rv.MIN_SCANS)
    _, held = holdout_stretches(len(scans))
    parts = [calibration_points(scans[i], no_return_cap=10.0) for i in held]
    pts, occ = np.concatenate([p for p, _ in parts]), np.concatenate([o for _, o in parts])
    keep = natural_subsample(occ.size, rv.POINTS, 3)
    drawn = rv.drawn_points([scans[i] for i in held], 10.0, 3)
    assert drawn is not None
    np.testing.assert_array_equal(drawn[0], pts[keep])
    np.testing.assert_array_equal(drawn[1], occ[keep])


def test_short_logs_keep_the_identity():
    scans = _tour(rv.MIN_SCANS - 1)
    p, occupied, report = rv.later_visit_points(scans, lambda rest, points: None)
    assert p.size == 0 and occupied.size == 0 and "reason" in report


@pytest.fixture(scope="module")
def fitted_tour():
    scans = _tour(rv.MIN_SCANS + 20)
    return AreaGPOM(kernel="se", min_cell=0.5, max_cell=1.0, free_step=0.3).fit(scans)


def test_a_map_recalibrates_every_probability_it_gives_and_keeps_its_ternary_map(fitted_tour):
    model = fitted_tour
    ev = model.evidence_
    assert not ev.revisit.identity and model.summary()["revisit"]["n_points"] > 0
    rng = np.random.default_rng(0)
    pts = rng.uniform([0.0, 0.0], [20.0, 16.0], (500, 2))
    with_it, thresholds = model.predict_proba(pts), model.thresholds_
    grid = model.grid(0.1)
    revisit, ev.revisit = ev.revisit, rv.RevisitCalibration()
    try:
        without, plain_thresholds = model.predict_proba(pts), model.thresholds_
        plain_grid = model.grid(0.1)
    finally:
        ev.revisit = revisit
    np.testing.assert_allclose(with_it, revisit(without), rtol=1e-12)
    np.testing.assert_allclose(grid.probability, revisit(plain_grid.probability), rtol=1e-12)
    # The ternary thresholds hold on the probabilities the map gives, whatever recalibrated them.
    assert thresholds == plain_thresholds == CALIBRATED_THRESHOLDS
    np.testing.assert_array_equal(grid.ternary == 1, (grid.probability > thresholds[1]) & ~grid.seen_through)
    assert (grid.ternary == 1).any() and (grid.ternary == 0).any()


def test_the_map_of_the_rest_is_this_map_on_fewer_scans(fitted_tour):
    # The fold the recalibration was fitted on, refitted by hand (the map's settings, tiles,
    # hyperparameters and calibration of the ray counts): the same predictions at the held-out
    # stretch's points, so the stored recalibration is that fit's.
    model = fitted_tour
    scans = model._scans
    kept, _ = holdout_stretches(len(scans))
    rest = AreaGPOM(**{**model.get_params(), "fit_revisit": False, "tile_size": model.tile_size_, "origin": model.origin_})
    # Without a silent rate: it is fitted on these points.
    calibration = model.evidence_.calibration
    rest._given_calibration = replace(calibration, silent_rate=0.0, silent_mix=0.0)
    rest.fit([scans[i] for i in kept], hyperparameters=dict(model.hyperparameters_))
    assert rest.evidence_.calibration == rest._given_calibration and rest.evidence_.report == {"given": 1.0}
    p, occupied, _ = rv.later_visit_points(scans, lambda s, q: rest._proba_as_written(q), seed=model.base.seed)
    points = rv.drawn_points([scans[i] for i in holdout_stretches(len(scans))[1]], model.base.no_return_cap, model.base.seed)[0]
    silent = rest.evidence_.counts_at(points)[2]
    assert (calibration.silent_rate, calibration.silent_mix) == fit_silent_rate(p[silent], occupied[silent])
    sample = model.evidence_.sample
    among = calibration.with_silent(sample.probability, sample.silent)
    got = rv.RevisitCalibration.fit(calibration.with_silent(p, silent), occupied, among, sample.occupied)
    assert got.slope == pytest.approx(model.evidence_.revisit.slope, rel=1e-6)
    assert got.shift == pytest.approx(model.evidence_.revisit.shift, rel=1e-6, abs=1e-9)


def test_the_map_of_the_rest_fits_only_the_tiles_asked_and_answers_as_with_all(fitted_tour):
    # The later visit's map of the other stretches fits a tile when a prediction first needs it:
    # fewer tiles, the same probabilities to the bit as the map with every tile fitted up front.
    model = fitted_tour
    scans = model._scans
    kept, _ = holdout_stretches(len(scans))
    fixed = dict(model.hyperparameters_)
    eager = model._refit().unfitted(fit_revisit=False)
    eager._given_calibration = model.evidence_.calibration
    eager.fit([scans[i] for i in kept], hyperparameters=fixed)
    lazy = model._refit().unfitted(fit_revisit=False)
    lazy._tiles_when_asked = True
    lazy._given_calibration = model.evidence_.calibration
    lazy.fit([scans[i] for i in kept], hyperparameters=fixed)
    args = (model.base.no_return_cap, model.base.seed)
    p_eager, occ, _ = rv.later_visit_points(scans, lambda s, q: eager._proba_as_written(q), *args)
    p_lazy, occ_lazy, _ = rv.later_visit_points(scans, lambda s, q: lazy._proba_as_written(q), *args)
    np.testing.assert_array_equal(p_lazy, p_eager)
    np.testing.assert_array_equal(occ_lazy, occ)
    assert len(eager.tiles_) == len(lazy.tiles_) + len(lazy._waiting)
    # Counted only at the points asked: the same probabilities, without the lattice's arrays.
    pts = rv.drawn_points([scans[i] for i in holdout_stretches(len(scans))[1]], *args)[0]
    asked = model._refit().unfitted(fit_revisit=False)
    asked._tiles_when_asked = True
    asked._given_calibration = model.evidence_.calibration
    asked._asked_at = pts
    asked.fit([scans[i] for i in kept], hyperparameters=fixed)
    np.testing.assert_array_equal(asked._proba_as_written(pts), p_eager)
    assert asked.evidence_._hits.size == 0 < eager.evidence_._hits.size
    # Asked at a corner's points: only the tiles they need, and the blocks those gather cells
    # from, are made; the same answers.
    corner = pts[(pts[:, 0] < 6.0) & (pts[:, 1] < 6.0)]
    near = model._refit().unfitted(fit_revisit=False)
    near._tiles_when_asked = True
    near._given_calibration = model.evidence_.calibration
    near._asked_at = corner
    near.fit([scans[i] for i in kept], hyperparameters=fixed)
    np.testing.assert_array_equal(near._proba_as_written(corner), eager._proba_as_written(corner))
    assert corner.shape[0] > 100
    assert len(near._blocks) < len(eager._blocks)
    assert len(near.tiles_) + len(near._waiting) < len(eager.tiles_) // 2
    with pytest.raises(ValueError, match="only at the cells"):
        asked.predict_proba(pts[:1] + 3.0)
    # A layer saved before layers could be counted at given points (neither attribute in its
    # state) answers as before.
    old = type(eager.evidence_).__new__(type(eager.evidence_))
    old.__dict__.update({k: v for k, v in eager.evidence_.__dict__.items() if k not in ("_cells", "_asked_at")})
    np.testing.assert_array_equal(old.counts_at(pts), eager.evidence_.counts_at(pts))
    # What the map itself took for its recalibration.
    p_model, *_ = model._later_visit_points()
    np.testing.assert_array_equal(p_model, p_eager)
    # Without ray counts nothing is predicted while fitting: no tile is fitted until asked.
    gp = model._refit().unfitted(fit_revisit=False, ray_evidence=False)
    gp._tiles_when_asked = True
    gp.fit(scans, hyperparameters=fixed)
    assert len(gp.tiles_) == 0
    point = np.array([[6.0, 7.5]])
    whole = model._refit().unfitted(fit_revisit=False, ray_evidence=False).fit(scans, hyperparameters=fixed)
    np.testing.assert_array_equal(gp.predict_proba(point), whole.predict_proba(point))
    assert 1 <= len(gp.tiles_) <= 4 < len(whole.tiles_)


@pytest.mark.parametrize("updated", [False, True])
def test_the_map_of_the_rest_takes_this_maps_points_as_making_them_again_would(fitted_tour, updated):
    # The map of the other stretches files the fitted map's block points without the held-out
    # scans' (each block knows its points' scans), instead of making them from the scans: the
    # same points in the same order, so the same blocks, tiles, bounds and answers. A map updated
    # with later scans knows its new points' scans too.
    model = fitted_tour
    scans = model._scans
    if updated:
        model = AreaGPOM(**model.get_params()).fit(scans[:30]).update(scans[30:])
    kept, held = holdout_stretches(len(scans))
    rest = [scans[i] for i in kept]
    given = model._kept_points_of(rest)
    assert given is not None and np.array_equal(given.dropped, held)
    # Not this map's held-out stretches' others: made from the scans.
    assert model._kept_points_of(rest[1:]) is None and model._kept_points_of(rest[::-1]) is None
    fixed = dict(model.hyperparameters_)
    made, taken = (model._refit().unfitted(fit_revisit=False) for _ in range(2))
    taken._kept_points = given
    for m in (made, taken):
        m._given_calibration = model.evidence_.calibration
        m.fit(rest, hyperparameters=fixed)
    assert sorted(made._block_points) == sorted(taken._block_points)
    for k, block in made._block_points.items():
        for a, b in zip(block.arrays(), taken._block_points[k].arrays(), strict=True):
            np.testing.assert_array_equal(a, b)
    assert made._tiles_with_points == taken._tiles_with_points and sorted(made.tiles_) == sorted(taken.tiles_)
    np.testing.assert_array_equal(made._lower, taken._lower)
    np.testing.assert_array_equal(made._upper, taken._upper)
    untimed = [{k: v for k, v in m.summary().items() if k not in ("timings", "tile_fit_seconds")} for m in (made, taken)]
    assert untimed[0] == untimed[1]
    pts = np.random.default_rng(3).uniform([0.0, 0.0], [20.0, 16.0], (2000, 2))
    np.testing.assert_array_equal(made.predict_proba(pts), taken.predict_proba(pts))
    # What the map took for its recalibration is the map of the rest made from the scans.
    p_model, *_ = model._later_visit_points()
    p_made, _, _ = rv.later_visit_points(scans, lambda s, q: made._proba_as_written(q), model.base.no_return_cap, model.base.seed)
    np.testing.assert_array_equal(p_model, p_made)
