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
from gpomap.stages import CalibratedMoments, Counted, GPProbability, StageChain
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
    hits, misses, silent = model.evidence_.counts_at(pts)
    fused = chain.fusion.apply(Counted(gp.probability, gp.unseen, hits, misses, silent))
    final = chain.revisit.apply(fused)
    # To the bit: the map's own prediction, and the chain applied at once.
    np.testing.assert_array_equal(final, model.predict_proba(pts))
    np.testing.assert_array_equal(chain.apply(CalibratedMoments(num, den), (hits, misses, silent)), final)
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
    the silent rate where only beams without a return went, and the recalibration in log-odds."""
    model = tour_map
    chain = model.map_.stages
    cal, rev = model.evidence_.calibration, model.evidence_.revisit
    kappa = model.hyperparameters_["variance_scale"]
    pts = _points(model)[::15]
    num, den, _, _ = model.blended_moments(pts)
    assert den is not None
    hits, misses, silent = model.evidence_.counts_at(pts)
    got = chain.apply(CalibratedMoments(num, den), (hits, misses, silent))

    def phi(z: float) -> float:
        return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))

    assert ((hits == 0) & (misses == 0)).any() and (hits > 0).any()
    for k in range(len(pts)):
        p_gp = phi(num[k] / math.sqrt(1.0 + den[k]))
        p_unseen = phi(num[k] / math.sqrt(1.0 + kappa * den[k]))
        beta_update = (hits[k] + cal.prior_weight * p_gp) / (hits[k] + misses[k] + cal.prior_weight)
        q = p_unseen if hits[k] == 0 and misses[k] == 0 else beta_update
        p = cal.surprise_rate / 2 + (1.0 - cal.surprise_rate) * q
        if silent[k]:
            p = (1.0 - cal.silent_mix) * p + cal.silent_mix * cal.silent_rate
        z = math.log(p / (1.0 - p))
        want = 1.0 / (1.0 + math.exp(-(rev.slope * z + rev.shift * (1.0 - math.exp(-0.5 * (z / WIDTH) ** 2)))))
        assert got[k] == pytest.approx(want, rel=1e-9), k


def _phi(z: float) -> float:
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


@pytest.fixture
def squashed(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """How many values each call of the squash stage's apply squashed, in order."""
    sizes: list[int] = []
    apply = VarianceScale.apply

    def counted(self: VarianceScale, moments: CalibratedMoments) -> GPProbability:
        sizes.append(np.size(moments.mean))
        return apply(self, moments)

    monkeypatch.setattr(VarianceScale, "apply", counted)
    return sizes


def test_a_dense_gp_squashes_through_the_squash_stage(squashed: list[int]) -> None:
    """A dense GP's field squashes its latent moments, calibrated by its ProbitSquash, through the
    squash stage: its probabilities are the probit's own call's to the bit, and the formula's."""
    from gpomap.baselines.gpom import GPOM
    from gpomap.estimator import squash_latent
    from gpomap.simulate import paper_room_scans
    from gpomap.squash import ProbitSquash

    model = GPOM(free_step=1.0).fit(paper_room_scans()[::8])
    pts = np.random.default_rng(1).uniform(-1.0, 11.0, (300, 2))
    mu, var = model.map_.predict(pts, return_var=True)
    sq = model.map_.squash
    moments = CalibratedMoments(sq.alpha * mu + sq.beta, sq.alpha**2 * var)
    squashed.clear()
    p = model.predict_proba(pts)
    assert sum(squashed) == pts.shape[0]
    np.testing.assert_array_equal(p, sq(mu, var))
    np.testing.assert_array_equal(model.map_.stages.apply(moments), p)
    np.testing.assert_array_equal(VarianceScale(sq.variance_scale).apply(moments).unseen, sq.unseen(mu, var))
    for k in range(0, len(pts), 10):
        z = (sq.alpha * mu[k] + sq.beta) / math.sqrt(1.0 + sq.alpha**2 * var[k])
        assert p[k] == pytest.approx(_phi(z), rel=1e-12), k
    # A dense GP's probit of a variance scale of its own (kappa 3), where no beam went.
    scaled = ProbitSquash(sq.alpha, 0.2, 3.0)
    gp = squash_latent(scaled, mu, var)
    np.testing.assert_array_equal(gp.probability, scaled(mu, var))
    np.testing.assert_array_equal(gp.unseen, scaled.unseen(mu, var))
    for k in range(0, len(pts), 10):
        z = (sq.alpha * mu[k] + 0.2) / math.sqrt(1.0 + 3.0 * sq.alpha**2 * var[k])
        assert gp.unseen[k] == pytest.approx(_phi(z), rel=1e-12), k


def test_a_grid_conversion_squashes_through_the_squash_stage(squashed: list[int]) -> None:
    """A grid conversion's GP squashes through the squash stage too, in a known pixel at a pixel's
    variance: its probability before it is held to the pixels is the probit's own call's to the
    bit, and the formula's."""
    from gpomap.convert import convert_grid
    from tests.test_convert import _wall_map

    model = convert_grid(_wall_map()).model
    pts = np.random.default_rng(2).uniform(-0.5, 2.5, (200, 2))  # the 2 m map and beyond it
    mu, var = model.predict(pts, return_var=True)
    squashed.clear()
    p, _, pixel = model._pixel_proba(pts)
    assert sum(squashed) == pts.shape[0]
    assert (pixel >= 0).any() and (pixel < 0).any()
    v = np.where(pixel >= 0, model.pixel_variance_, var)
    sq = model.gp_.squash
    np.testing.assert_array_equal(p, sq(mu, v))
    for k in range(0, len(pts), 10):
        z = (sq.alpha * mu[k] + sq.beta) / math.sqrt(1.0 + sq.alpha**2 * v[k])
        assert p[k] == pytest.approx(_phi(z), rel=1e-12), k


def test_the_octree_columns_squash_through_the_squash_stage(tmp_path, squashed: list[int]) -> None:
    """The tiled octree conversion squashes its blended moments through the squash stage at
    variance scale 1, calibrated as the tiles calibrate theirs (alpha^2 as a * a): its voxels
    and points are the stage's, each once, and the formula's."""
    from gpomap.convert import convert_octree
    from gpomap.io.octomap import read_octree, write_octree
    from gpomap.voxels import VoxelMap, VoxelSpec

    # A slab of 2 x 1 x 0.4 m with a wall at x 1.2..1.4, in columns of 0.5 m.
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 10, 20))
    x = spec.centres()[:, 0].reshape(spec.shape)
    write_octree(VoxelMap(spec, np.where((x > 1.2) & (x < 1.4), 0.97, 0.12)), tmp_path / "slab.bt")
    res = convert_octree(read_octree(tmp_path / "slab.bt"), 0.1, [0.0, 0.0, 0.0], [3.0, 1.0, 0.4], tile_size=0.5)
    model, field = res.model, res.model.map_.field
    assert sum(squashed) >= res.map.probability.size
    a, b = model.hyperparameters_["alpha"], model.hyperparameters_["beta"]
    pts = np.random.default_rng(3).uniform([0.0, 0.0, 0.0], [3.0, 1.0, 0.4], (60, 3))
    mean, var = field.latent(pts, True)
    squashed.clear()
    p, _, unseen = field.gp_probabilities(pts)
    assert squashed == [len(pts)]
    np.testing.assert_array_equal(unseen, p)  # voxels are not rays: no unseen space apart
    np.testing.assert_array_equal(p, VarianceScale().apply(CalibratedMoments(a * mean + b, a * a * var)).probability)
    for k in range(0, len(pts), 6):
        assert p[k] == pytest.approx(_phi((a * mean[k] + b) / math.sqrt(1.0 + a * a * var[k])), rel=1e-12), k
    squashed.clear()
    again = model.voxels(0.1, (0.0, 3.0, 0.0, 1.0, 0.0, 0.4))
    assert sum(squashed) == again.probability.size  # every voxel once, in bands of layers
    np.testing.assert_array_equal(again.probability, res.map.probability)


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
