"""The map's fitted stages, one interface: the chain applied stage by stage is the map's prediction,
each stage is the formula it documents, and each stage's fit recovers the values that made its data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from gpomap.extrapolation import VarianceScale
from gpomap.fusion import SURPRISE_RATE, EvidenceCalibration
from gpomap.mapping import AreaGPOM
from gpomap.revisit import MIN_SCANS, WIDTH, RevisitCalibration
from gpomap.stages import CalibratedMoments, Counted, StageChain
from tests.test_revisit import _tour


@pytest.fixture(scope="module")
def tour_map() -> AreaGPOM:
    """A planar map with ray evidence and a later visit's recalibration (a log long enough for one)."""
    return AreaGPOM(kernel="se", min_cell=0.5, max_cell=1.0, free_step=0.3).fit(_tour(MIN_SCANS + 20))


def _points(model: AreaGPOM) -> np.ndarray:
    """Points over the map and beyond it (where no beam went), seed 0."""
    rng = np.random.default_rng(0)
    return np.vstack([rng.uniform([0.0, 0.0], [20.0, 16.0], (400, 2)), rng.uniform([-30.0, -30.0], [-10.0, -10.0], (50, 2))])


def test_the_chain_applied_stage_by_stage_is_the_maps_prediction(tour_map: AreaGPOM) -> None:
    model = tour_map
    chain = model.map_.stages
    # The stages in order, each the map's fitted value.
    assert isinstance(chain.squash, VarianceScale) and chain.squash.kappa == model.hyperparameters_["variance_scale"]
    assert chain.fusion is model.evidence_.calibration and chain.revisit is model.evidence_.revisit
    assert not model.evidence_.revisit.identity
    pts = _points(model)
    num, den, _, _ = model.blended_moments(pts)
    assert den is not None
    gp = chain.squash.apply(CalibratedMoments(num, den))
    hits, misses = model.evidence_.counts_at(pts)
    fused = chain.fusion.apply(Counted(gp.probability, gp.unseen, hits, misses))
    final = chain.revisit.apply(fused)
    # To the bit: the map's own prediction, and the chain applied at once.
    np.testing.assert_array_equal(final, model.predict_proba(pts))
    np.testing.assert_array_equal(chain.apply(CalibratedMoments(num, den), (hits, misses)), final)
    np.testing.assert_array_equal(gp.probability, model.predict_proba_gp(pts))
    # Each stage moves the probabilities: counted cells and cells no count reached, and the recalibration.
    counted = (hits > 0) | (misses > 0)
    assert counted.any() and (~counted).any()
    assert not np.array_equal(fused[counted], gp.probability[counted])
    assert not np.array_equal(final, fused)
    # The map of the GP alone: the chain ends at the squash.
    gp_only = model._gp_map().stages
    assert gp_only.fusion is None and gp_only.revisit is None
    np.testing.assert_array_equal(gp_only.apply(CalibratedMoments(num, den)), model._gp_map().predict_proba(pts))


def test_each_stage_is_the_formula_it_documents(tour_map: AreaGPOM) -> None:
    """Point by point in plain floats: Phi of the calibrated moments, the Beta update of the counts
    (the GP's probability for unseen space where a cell has none) mixed with the surprise rate,
    and the recalibration in log-odds."""
    model = tour_map
    chain = model.map_.stages
    cal, rev = model.evidence_.calibration, model.evidence_.revisit
    kappa = model.hyperparameters_["variance_scale"]
    pts = _points(model)[::15]
    num, den, _, _ = model.blended_moments(pts)
    assert den is not None
    hits, misses = model.evidence_.counts_at(pts)
    got = chain.apply(CalibratedMoments(num, den), (hits, misses))

    def phi(z: float) -> float:
        return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))

    assert ((hits == 0) & (misses == 0)).any() and (hits > 0).any()
    for k in range(len(pts)):
        p_gp = phi(num[k] / math.sqrt(1.0 + den[k]))
        p_unseen = phi(num[k] / math.sqrt(1.0 + kappa * den[k]))
        beta_update = (hits[k] + cal.prior_weight * p_gp) / (hits[k] + misses[k] + cal.prior_weight)
        q = p_unseen if hits[k] == 0 and misses[k] == 0 else beta_update
        p = cal.surprise_rate / 2 + (1.0 - cal.surprise_rate) * q
        z = math.log(p / (1.0 - p))
        want = 1.0 / (1.0 + math.exp(-(rev.slope * z + rev.shift * (1.0 - math.exp(-0.5 * (z / WIDTH) ** 2)))))
        assert got[k] == pytest.approx(want, rel=1e-9), k


def test_the_squash_stage_is_a_dense_gps_own_squash() -> None:
    """A dense GP squashes its latent moments through its ProbitSquash; the squash stage on the
    same moments calibrated gives its probabilities to the bit."""
    from gpomap.baselines.gpom import GPOM
    from gpomap.simulate import paper_room_scans

    model = GPOM(free_step=1.0).fit(paper_room_scans()[::8])
    pts = np.random.default_rng(1).uniform(-1.0, 11.0, (300, 2))
    mu, var = model.map_.predict(pts, return_var=True)
    sq = model.map_.squash
    moments = CalibratedMoments(sq.alpha * mu + sq.beta, sq.alpha**2 * var)
    np.testing.assert_array_equal(model.map_.stages.apply(moments), model.predict_proba(pts))
    np.testing.assert_array_equal(VarianceScale(sq.variance_scale).apply(moments).unseen, sq.unseen(mu, var))


def test_a_chain_with_fusion_needs_the_counts() -> None:
    chain = StageChain(VarianceScale(), EvidenceCalibration(), RevisitCalibration())
    with pytest.raises(ValueError, match="counts"):
        chain.apply(CalibratedMoments(np.zeros(2), np.ones(2)))


def test_the_variance_scale_fit_recovers_the_scale_its_points_were_drawn_with() -> None:
    rng = np.random.default_rng(2)
    n, alpha, beta, kappa = 200_000, 2.0, 0.0, 6.0
    mu = rng.normal(0.0, 1.0, n)
    var = rng.uniform(0.05, 1.0, n)
    occupied = rng.uniform(size=n) < ndtr((alpha * mu + beta) / np.sqrt(1.0 + alpha * alpha * kappa * var))
    got = VarianceScale.fit(mu, var, occupied, alpha, beta).kappa
    assert got == pytest.approx(kappa, rel=0.1)
    # Drawn at kappa = 1, the fit says so.
    again = rng.uniform(size=n) < ndtr((alpha * mu + beta) / np.sqrt(1.0 + alpha * alpha * var))
    assert VarianceScale.fit(mu, var, again, alpha, beta).kappa == pytest.approx(1.0, rel=0.1)


def test_the_fusion_fit_recovers_the_weights_its_points_were_drawn_with() -> None:
    rng = np.random.default_rng(3)
    n = 200_000
    truth = EvidenceCalibration(hit_weight=3.0, prior_weight=5.0, near_weight=0.3, near_hit_weight=0.8, surface_weight=0.2)
    p_gp = rng.uniform(0.02, 0.98, n)
    hits = rng.poisson(1.0, n).astype(float)
    near = rng.poisson(0.7, n).astype(float)
    misses = near + rng.poisson(1.5, n)  # near misses are counted among the misses
    surface = np.where(rng.uniform(size=n) < 0.5, misses - near, 0.0)  # far misses at a surface
    p = truth(p_gp, truth.hits(hits, near), truth.misses(misses, near, surface=surface))
    occupied = rng.uniform(size=n) < p
    got = EvidenceCalibration.fit(p_gp, hits, misses, near, surface, occupied)
    want = (truth.hit_weight, truth.prior_weight, truth.near_weight, truth.near_hit_weight, truth.surface_weight)
    have = (got.hit_weight, got.prior_weight, got.near_weight, got.near_hit_weight, got.surface_weight)
    np.testing.assert_allclose(have, want, rtol=0.15)
    assert got.surprise_rate == SURPRISE_RATE
    # Without surface misses weighed apart, theirs stays a miss's.
    assert EvidenceCalibration.fit(p_gp, hits, misses, near, surface, occupied, fit_surface=False).surface_weight == 1.0


def test_the_revisit_fit_recovers_the_recalibration_its_points_were_drawn_with() -> None:
    rng = np.random.default_rng(4)
    truth = RevisitCalibration(slope=1.3, shift=-0.6)
    p_later, p_among = rng.uniform(0.01, 0.99, 100_000), rng.uniform(0.01, 0.99, 100_000)
    y_later, y_among = rng.uniform(size=p_later.size) < truth(p_later), rng.uniform(size=p_among.size) < truth(p_among)
    got = RevisitCalibration.fit(p_later, y_later, p_among, y_among)
    assert got.slope == pytest.approx(truth.slope, abs=0.05)
    assert got.shift == pytest.approx(truth.shift, abs=0.1)
    # The stage's apply is the recalibration itself, 1/2 kept.
    q = np.array([0.1, 0.5, 0.8])
    np.testing.assert_array_equal(got.apply(q), got(q))
    assert got.apply(np.array([0.5]))[0] == pytest.approx(0.5, abs=1e-15)
