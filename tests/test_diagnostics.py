"""Honest reports: hyperparameters at their bounds, alpha at its cap, probability away from data, one-class maps."""

import math

import numpy as np
import pytest

from gpomap import diagnostics as d
from gpomap.mapping import AreaGPOM

BOUNDS = {"length_scale": (0.05, 20.0), "noise": (1e-4, 10.0), "alpha": (1e-3, 30.0), "shift": (-5.0, 5.0)}


def hp(**kw):
    base = {"variance": 1.0, "length_scale": 0.5, "noise": 0.1, "alpha": 2.0, "beta": 0.0}
    return {**base, **kw}


def test_nothing_to_say_about_a_healthy_fit():
    assert d.at_bounds(hp(), BOUNDS) == {}
    assert d.hyperparameter_warnings(hp(), BOUNDS) == []


def test_values_at_or_near_bounds():
    found = d.at_bounds(hp(length_scale=19.5, noise=1.04e-4, alpha=29.0, beta=-4.9 * 29.0), BOUNDS)
    assert found == {
        "length_scale": (19.5, "upper", 20.0),
        "noise": (1.04e-4, "lower", 1e-4),
        "alpha": (29.0, "upper", 30.0),
        "shift": (pytest.approx(-4.9), "lower", -5.0),
    }
    # 5 % is the tolerance: 19 m is more than 5 % below 20 m (20 / 1.05 = 19.05).
    assert d.at_bounds(hp(length_scale=19.0), BOUNDS) == {}
    assert d.at_bounds(hp(length_scale=19.1), BOUNDS)["length_scale"][1] == "upper"
    # A bound pair that pins a value (not searched) is never reported.
    assert d.at_bounds(hp(), {"shift": (0.0, 0.0)}) == {}


def test_warning_sentences():
    w = d.hyperparameter_warnings(hp(alpha=30.0, length_scale=0.05), BOUNDS)
    assert any(s.startswith("alpha 30 is at the upper bound 30 of its search (its cap)") for s in w)
    assert any(s.startswith("length_scale 0.05 is at the lower bound 0.05") for s in w)


def test_alpha_at_its_cap_is_no_warning_for_a_map_of_ray_counts():
    # With ray evidence the GP is the counts' prior: a capped alpha does not make the map hard.
    w = d.hyperparameter_warnings(hp(alpha=30.0, length_scale=0.05), BOUNDS, counted=True)
    assert not any(s.startswith("alpha") for s in w)
    assert any(s.startswith("length_scale 0.05 is at the lower bound 0.05") for s in w)
    # A fitted map: the same fit with and without its ray counts.
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans()[:6]
    with_counts = AreaGPOM(kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5).fit(scans)
    assert with_counts.evidence_ is not None
    hyper = {**with_counts.hyperparameters_, "alpha": 30.0}
    gp_only = AreaGPOM(kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5, ray_evidence=False).fit(
        scans, hyperparameters=hyper
    )
    with_counts = AreaGPOM(kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5).fit(scans, hyperparameters=hyper)
    assert gp_only.evidence_ is None
    assert any(s.startswith("alpha 30 is at the upper bound") for s in d.fit_warnings(gp_only))
    # Six scans leave no held-out stretch to fit the variance scale on: nothing tempers the GP
    # where no beam went, so a capped alpha is a warning with the counts too, saying what to do.
    assert "reason" in with_counts.extrapolation_
    alpha = [s for s in d.fit_warnings(with_counts) if s.startswith("alpha 30 is at the upper bound")]
    assert alpha and "read those parts as unknown, or add scans that see them" in alpha[0]
    assert not any(s.startswith("alpha") for s in d.hyperparameter_warnings(hyper, BOUNDS, counted=True, tempered=True))


def test_prior_probability_by_hand():
    # Phi(beta / sqrt(1 + alpha^2 v)): beta 1, alpha 0, v 1 -> Phi(1) = 0.8413.
    assert d.prior_probability(hp(alpha=0.0, beta=1.0)) == pytest.approx(0.841345, abs=1e-6)
    # alpha 3, beta 1.5, v 0.25: 1.5 / sqrt(1 + 2.25) = 0.832050 -> Phi = 0.797310.
    assert d.prior_probability(hp(alpha=3.0, beta=1.5, variance=0.25)) == pytest.approx(0.797310, abs=1e-6)
    assert d.prior_probability(hp(beta=0.0)) == 0.5
    # alpha 1, beta -1, v 0: Phi(-1) = 0.16.
    w = d.hyperparameter_warnings(hp(alpha=1.0, beta=-1.0, variance=0.0), BOUNDS)
    assert w == [
        "far from the data the map's probability is 0.16, not about 0.5 (alpha 1, beta -1): unexplored space "
        "will look free rather than unknown"
    ]
    # 0.5 +- 0.1 passes: Phi(0.25) = 0.599.
    assert d.hyperparameter_warnings(hp(alpha=1.0, beta=0.25, variance=0.0), BOUNDS) == []


def test_map_classes():
    # 1000 known cells: the band's edges, one wall cell in a thousand and half of them, pass.
    t = np.zeros((20, 100), dtype=np.int8)
    t[10:, :] = -1
    t[0, 0] = 1
    assert d.map_warnings(t) == []
    t[0, 0] = 0  # no wall cell at all
    assert d.map_warnings(t) == [
        "the map is almost all free: 0 of its 1000 known cells (0 %) are occupied; the walls the scans hit are mostly missing"
    ]
    t[:5, :] = 1  # 500 of 1000
    assert d.map_warnings(t) == []
    t[5, 0] = 1  # 501 of 1000
    assert d.map_warnings(t) == [
        "the map is mostly occupied: 50.1 % of its 1000 known cells; the space the beams crossed is not free in it"
    ]
    small = np.zeros(4000, dtype=np.int8)
    small[:3] = 1  # 3 in 4000: 0.075 %
    assert d.map_warnings(small) == [
        "the map is almost all free: 3 of its 4000 known cells (0.075 %) are occupied; the walls the scans hit are mostly missing"
    ]
    assert d.map_warnings(np.full((3, 3), -1)) == [
        "no cell of the 9-cell map is known (all between the thresholds): the map says nothing"
    ]


def test_a_voxel_maps_classes_are_counted_where_rays_went():
    from gpomap.grid import OCCUPIED, ternary
    from gpomap.voxels import VoxelMap, VoxelSpec

    # 10 x 10 x 10 voxels: rays went to the first two layers (150 free, 50 occupied: 25 %); the
    # GP calls the 800 voxels behind them occupied, which the OctoMap file leaves out.
    p = np.full((10, 10, 10), 0.9)
    p[:2] = 0.05
    p[1, :5, :] = 0.9
    observed = np.zeros(p.shape, dtype=bool)
    observed[:2] = True
    voxels = VoxelMap(VoxelSpec((0.0, 0.0, 0.0), 0.1, p.shape), p, observed=observed)
    assert d.map_warnings(ternary(p, voxels.thresholds)) == [
        "the map is mostly occupied: 85.0 % of its 1000 known cells; the space the beams crossed is not free in it"
    ]
    # The voxel map's own ternary layer leaves them unknown, and the warning counts where rays went.
    assert (voxels.ternary == OCCUPIED).sum() == 50
    assert d.map_warnings(voxels.ternary) == [] and d.map_warnings(voxels.ternary, observed=voxels.observed) == []
    p[1, 5:, :] = 0.9  # 100 of the 200 where rays went
    p[0, 0, 0] = 0.9
    assert d.map_warnings(VoxelMap(voxels.spec, p, observed=observed).ternary, observed=observed) == [
        "the map is mostly occupied: 50.5 % of its 200 known cells rays went to; the space the beams crossed is not free in it"
    ]


def test_search_bounds_follow_the_estimator():
    model = AreaGPOM(length_scale_bounds=(0.1, 5.0), noise_bounds=(1e-3, 1.0))
    b = d.search_bounds(model)
    assert b["length_scale"] == (0.1, 5.0) and b["noise"] == (1e-3, 1.0)
    assert b["alpha"][1] == pytest.approx(30.0)
    # A fixed length scale is not searched: nothing to be "at bound".
    assert "length_scale" not in d.search_bounds(AreaGPOM(optimise=False))


def test_a_real_tiny_fit():
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans()[:4]
    model = AreaGPOM(
        kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5, hyper_subset=100, length_scale_bounds=(0.05, 0.3)
    ).fit(scans)
    hyper = model.hyperparameters_
    warnings = d.fit_warnings(model, model.grid(1.0))
    found = d.at_bounds(hyper, d.search_bounds(model))
    # The room's length scale (~0.7 m) is above this search's 0.3 m: it must run to the bound and be said so.
    assert found["length_scale"][1] == "upper"
    assert any(w.startswith("length_scale") and "upper bound 0.3" in w for w in warnings)
    assert d.hyperparameter_source(model).startswith("at bound: length_scale")
    p0 = d.prior_probability(hyper)
    assert (any("far from the data" in w for w in warnings)) == (not 0.4 <= p0 <= 0.6)
    assert math.isfinite(p0)


def test_a_variance_scale_at_its_bound_is_named_not_warned():
    from gpomap.extrapolation import VARIANCE_SCALE_BOUNDS
    from gpomap.simulate import paper_room_scans

    # Forty scans of the room predict its held-out stretches' unseen points so well that the
    # variance scale runs to the lower end of its search.
    model = AreaGPOM(kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5, hyper_subset=100).fit(paper_room_scans()[:40])
    assert "reason" not in model.extrapolation_
    assert d.search_bounds(model)["variance_scale"] == tuple(VARIANCE_SCALE_BOUNDS)
    kappa = model.hyperparameters_["variance_scale"]
    assert kappa == pytest.approx(VARIANCE_SCALE_BOUNDS[0], rel=1e-3)
    assert "variance_scale" in d.hyperparameter_source(model)
    assert not any("variance_scale" in w for w in d.fit_warnings(model))
    # Given to the fit, it is not searched: no bound to be at.
    given = AreaGPOM(kernel="se", min_cell=1.0, max_cell=2.0, free_step=0.5).fit(
        paper_room_scans()[:40], hyperparameters=model.hyperparameters_
    )
    assert "variance_scale" not in d.search_bounds(given)
