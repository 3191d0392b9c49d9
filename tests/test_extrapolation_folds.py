"""The variance scale's held-out patterns: pooled when one pattern finds too little unseen space."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import gpomap.extrapolation as ex
import gpomap.heldout as heldout
from gpomap.mapping import AreaGPOM
from gpomap.simulate import paper_room_scans
from tests.test_extrapolation import _room_scans, _truth


def test_the_three_patterns_by_hand():
    held = {first: heldout.holdout_stretches(20, first)[1].tolist() for first in heldout.FOLD_STARTS}
    # Ten stretches of two scans: the 2nd, 5th, 8th; the 3rd, 6th, 9th; the 1st, 4th, 7th, 10th.
    assert held[1] == [2, 3, 8, 9, 14, 15]
    assert held[2] == [4, 5, 10, 11, 16, 17]
    assert held[0] == [0, 1, 6, 7, 12, 13, 18, 19]
    # Together they hold out every scan once.
    assert sorted(held[0] + held[1] + held[2]) == list(range(20))


class _Fixed:
    """The held-in GP's stand-in: latent moments from a function of the points, and the fits it saw."""

    def __init__(self, moments):
        self.moments = moments
        self.fits = 0

    def fit(self, obs):
        self.fits += 1
        return self

    def predict(self, points, return_var=False):
        return self.moments(points)


def _only_one_stretch_moves():
    """A robot standing at its first pose, except during the 3rd of ten stretches of the log.

    The first pattern (stretches 2, 5, 8 held out) keeps that stretch and holds out only copies
    of the standing scan, which the kept copies saw; the second holds the moving stretch out,
    and what it saw is the only space no kept beam went.
    """
    tour = paper_room_scans(n_beams=90, seed=0)
    moving = set(np.array_split(np.arange(len(tour)), heldout.N_STRETCHES)[2].tolist())
    scans = [tour[i] if i in moving else tour[0] for i in range(len(tour))]
    return scans, _truth(scans)


def _fit(scans, stand_in):
    settings = AreaGPOM(ray_evidence=False).base
    points = settings.make_observations(scans, clearance=False)
    return ex.fit_variance_scale(
        scans, {"alpha": 30.0, "beta": 0.0}, points, settings.clearance(2), stand_in.fit, np.zeros(2), 50.0, 0.0
    )


def test_a_second_pattern_is_pooled_when_the_first_finds_nothing_unseen():
    scans, occupied = _only_one_stretch_moves()
    perfect = _Fixed(lambda p: (np.where(occupied(p), 1.0, -1.0), np.ones(len(p))))
    kappa, report = _fit(scans, perfect)
    assert report["n_patterns"] == 2 and report["n_points"] >= ex.MIN_POINTS_PER_CLASS
    # Only the second pattern had points, so only its held-in GP was fitted.
    assert perfect.fits == 1
    assert kappa == pytest.approx(ex.VARIANCE_SCALE_BOUNDS[0], rel=1e-3)
    rng = np.random.default_rng(0)
    kappa, _ = _fit(scans, _Fixed(lambda p: (rng.choice([-1.0, 1.0], len(p)), np.ones(len(p)))))
    assert kappa > 100


def test_one_pattern_is_enough_when_it_finds_enough():
    # The first pattern's kept scans miss a third of their beams: its held-out scans alone see there.
    scans = _room_scans()
    stand_in = _Fixed(lambda p: (np.zeros(len(p)), np.ones(len(p))))
    _, report = _fit(scans, stand_in)
    assert report["n_patterns"] == 1 and stand_in.fits == 1


def test_a_robot_that_never_moves_leaves_the_scale_at_one_after_every_pattern():
    scans = paper_room_scans(n_beams=90, seed=0)[:1] * 20
    stand_in = _Fixed(lambda p: (np.zeros(len(p)), np.ones(len(p))))
    kappa, report = _fit(scans, stand_in)
    assert kappa == 1.0 and "3 patterns" in report["reason"] and stand_in.fits == 0


def test_a_pattern_whose_kept_scans_never_saw_the_region_is_passed_over():
    # The robot stands in the room but for the 2nd of ten stretches, which tours a copy of the
    # room 100 m away. The first pattern holds that stretch out: its kept scans saw nothing of
    # the copy, so it has no GP there and is passed over (it used to end the fit, the scale at 1);
    # the other two keep the stretch and hold out nothing that reaches the copy.
    tour = paper_room_scans(n_beams=90, seed=0)
    away = set(np.array_split(np.arange(len(tour)), heldout.N_STRETCHES)[1].tolist())
    scans = [
        dataclasses.replace(tour[i], pose=tour[i].pose + np.array([100.0, 0.0, 0.0])) if i in away else tour[0]
        for i in range(len(tour))
    ]
    assert set(heldout.holdout_stretches(len(scans), heldout.FOLD_STARTS[0])[1].tolist()) >= away
    settings = AreaGPOM(ray_evidence=False).base
    points = settings.make_observations(scans, clearance=False)
    stand_in = _Fixed(lambda p: (np.zeros(len(p)), np.ones(len(p))))
    centre = np.mean([s.pose[:2] for s in (scans[i] for i in away)], axis=0)
    kappa, report = ex.fit_variance_scale(
        scans, {"alpha": 30.0, "beta": 0.0}, points, settings.clearance(2), stand_in.fit, centre, 15.0, 0.0
    )
    assert kappa == 1.0 and report["reason"].endswith("in 2 patterns of held-out stretches") and stand_in.fits == 0
