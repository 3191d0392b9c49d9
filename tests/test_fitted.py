"""The fitted map: the one object that answers for a fitted GP map.

A field made by hand (a probability known in closed form at every point) checks what the fitted
map makes of a field: grids at cell centres, in bands or whole, supersampled cells, voxels,
thresholds and the ternary map. The estimators' answers are their fitted map's, and a map loaded
from its file answers as the one saved.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from gpomap import fitted
from gpomap.fitted import FittedMap, GPHyperparameters
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.squash import ProbitSquash


class SlopeField:
    """A field whose probability rises along x: p = x / 10 clipped to [0, 1], variance y."""

    def __init__(self, dim: int = 2) -> None:
        self.dim = dim
        self.hyperparameters = GPHyperparameters(1.0, 0.5, 0.01)
        self.squash = ProbitSquash()
        self.blended = None
        self.forgotten: list[float] = []
        self.asked = 0

    def latent(self, points: NDArray[np.float64], return_var: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        return points[:, 0].copy(), points[:, 1].copy() if return_var else None

    def gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        self.asked += 1
        p = np.clip(points[:, 0] / 10.0, 0.0, 1.0)
        return p, points[:, 1].copy(), np.full(len(points), 0.5)

    def limited(self) -> contextlib.AbstractContextManager[Any]:
        return contextlib.nullcontext()

    def forget_below(self, y: float) -> None:
        self.forgotten.append(y)

    def grid_done(self) -> None:
        pass


def _map(field: SlopeField, thresholds: tuple[float, float] | None = None) -> FittedMap:
    lower = np.zeros(field.dim)
    upper = np.full(field.dim, 4.0)
    return FittedMap(field, None, thresholds, lower, upper, None, lambda: {"method": "slope"}, {})


def test_a_grid_is_the_field_at_each_cell_centre_and_its_extent_the_data_grown_by_two_cells() -> None:
    om = _map(SlopeField()).grid(0.5)
    # The data's box [0, 4] grown by two cells of 0.5 m on each side.
    assert om.grid.origin == pytest.approx((-1.0, -1.0))
    assert om.grid.shape == (12, 12)
    x = -1.0 + 0.25 + 0.5 * np.arange(12)
    np.testing.assert_allclose(om.probability, np.tile(np.clip(x / 10, 0, 1), (12, 1)))
    np.testing.assert_allclose(om.variance, np.tile(x[:, None], (1, 12)))  # variance = y at the centre
    assert om.thresholds == DEFAULT_THRESHOLDS


def test_a_supersampled_cell_takes_its_largest_probability_and_its_mean_variance() -> None:
    om = _map(SlopeField()).grid(1.0, extent=(0.0, 2.0, 0.0, 1.0), supersample=4)
    # Four samples across each 1 m cell, at 0.125, 0.375, 0.625, 0.875 of it: the largest x is
    # the cell's left edge + 0.875; the mean y is the cell's centre.
    np.testing.assert_allclose(om.probability, [[0.0875, 0.1875]])
    np.testing.assert_allclose(om.variance, [[0.5, 0.5]])


def test_a_large_grid_is_made_in_bands_of_rows_with_the_same_values(monkeypatch: pytest.MonkeyPatch) -> None:
    whole_field = SlopeField()
    whole = _map(whole_field).grid(0.1, extent=(0.0, 3.0, 0.0, 2.0))
    assert whole_field.asked == 1
    monkeypatch.setattr(fitted, "WRITTEN_BAND_CELLS", 150)  # five rows of 30 cells a band
    banded_field = SlopeField()
    banded = _map(banded_field).grid(0.1, extent=(0.0, 3.0, 0.0, 2.0))
    assert banded_field.asked == 4
    # A band's centres are its own rows' (the same points up to the round-off of their coordinates).
    np.testing.assert_allclose(banded.probability, whole.probability, rtol=0, atol=1e-12)
    np.testing.assert_allclose(banded.variance, whole.variance, rtol=0, atol=1e-12)
    # Each band lets go of what lies below its top, then everything once the grid is made.
    assert banded_field.forgotten == pytest.approx([0.5, 1.0, 1.5, 2.0, np.inf])


def test_a_voxel_map_is_the_field_at_each_voxel_centre() -> None:
    vm = _map(SlopeField(dim=3)).grid(1.0, extent=(0.0, 2.0, 0.0, 1.0, 0.0, 3.0))
    assert vm.probability.shape == (3, 1, 2)  # (nz, ny, nx)
    np.testing.assert_allclose(vm.probability, np.broadcast_to([0.05, 0.15], (3, 1, 2)))
    with pytest.raises(ValueError, match="supersample is for 2-D maps"):
        _map(SlopeField(dim=3)).grid(1.0, supersample=2)
    with pytest.raises(ValueError, match="use grid"):
        _map(SlopeField()).voxels(1.0)


class PassField(SlopeField):
    """A 3-D field that makes its voxels in a pass of its own: p = 0.3 and variance z there, the
    points' p = 0.7 and variance 2 (not what :meth:`gp_probabilities` says anywhere)."""

    def __init__(self) -> None:
        super().__init__(dim=3)
        self.passes: list[tuple[Any, int]] = []

    def voxel_probabilities(
        self, spec: Any, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        self.passes.append((spec, len(points)))
        z = spec.centres()[:, 2].reshape(spec.shape)
        return np.full(spec.shape, 0.3), z, np.full(len(points), 0.7), np.full(len(points), 2.0)


def test_a_field_with_a_voxel_pass_makes_the_voxels_and_the_points_beside_them_in_it() -> None:
    box = (0.0, 2.0, 0.0, 1.0, 0.0, 3.0)
    pts = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 2.5]])
    field = PassField()
    assert isinstance(field, fitted.VoxelPass) and not isinstance(SlopeField(dim=3), fitted.VoxelPass)
    m = _map(field)
    vm, p = m.voxels_and_points(1.0, box, pts)
    assert "grid" in m.timings and "prediction" not in m.timings
    assert len(field.passes) == 1 and field.passes[0][1] == 2 and field.asked == 0
    assert field.passes[0][0].shape == (3, 1, 2)
    np.testing.assert_array_equal(vm.probability, np.full((3, 1, 2), 0.3))
    np.testing.assert_array_equal(vm.variance, np.broadcast_to([[[0.5]], [[1.5]], [[2.5]]], (3, 1, 2)))
    np.testing.assert_array_equal(p, [0.7, 0.7])
    # voxels() is the same pass without points.
    np.testing.assert_array_equal(_map(field).voxels(1.0, box).probability, vm.probability)
    assert field.passes[-1][1] == 0 and field.asked == 0
    # A field without one: the voxels at their centres, then the points by predict_proba.
    plain = SlopeField(dim=3)
    vm, p = _map(plain).voxels_and_points(1.0, box, pts)
    np.testing.assert_allclose(vm.probability, np.broadcast_to([0.05, 0.15], (3, 1, 2)))
    np.testing.assert_allclose(p, [0.05, 0.15])
    assert plain.asked == 2
    assert _map(plain).voxels_and_points(1.0, box)[1].shape == (0,)


def test_points_ternary_and_thresholds() -> None:
    m = _map(SlopeField(), thresholds=(0.2, 0.7))
    pts = np.array([[1.0, 0.0], [5.0, 3.0], [9.0, 1.0]])
    np.testing.assert_allclose(m.predict_proba(pts), [0.1, 0.5, 0.9])
    p, var = m.predict_proba(pts, return_var=True)
    np.testing.assert_allclose(p, [0.1, 0.5, 0.9])
    np.testing.assert_allclose(var, [0.0, 3.0, 1.0])
    np.testing.assert_array_equal(m.predict_ternary(pts), [0, -1, 1])
    mean, var = m.predict(pts, return_var=True)
    np.testing.assert_allclose(mean, pts[:, 0])
    assert "prediction" in m.timings
    with pytest.raises(ValueError, match=r"shape \(m, 2\)"):
        m.predict_proba(np.zeros((3, 3)))


def test_every_estimator_answers_through_its_fitted_map(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tiled map and the dense baselines make no answer of their own: a fitted map that
    answers 0.25 everywhere makes every estimator answer 0.25."""
    from gpomap import AreaGPOM
    from gpomap.baselines.gpom import GPOM
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans()[::8]
    for model in (AreaGPOM(kernel="se", length_scale=0.5, optimise=False).fit(scans), GPOM(free_step=1.0).fit(scans)):
        pts = np.array([[2.0, 2.0], [5.0, 4.0]])
        before = model.predict_proba(pts)
        assert np.array_equal(before, model.map_.predict_proba(pts))
        om = model.grid(0.5)
        np.testing.assert_array_equal(om.probability, model.map_.grid(0.5).probability)

        def quarter(self: FittedMap, points: NDArray[np.float64], return_var: bool = False) -> Any:
            return np.full(len(points), 0.25)

        with monkeypatch.context() as patch:
            patch.setattr(FittedMap, "predict_proba", quarter)
            np.testing.assert_array_equal(model.predict_proba(pts), [0.25, 0.25])


def test_the_fitted_map_holds_each_stage_as_typed_values() -> None:
    from gpomap import AreaGPOM
    from gpomap.fusion import EvidenceCalibration
    from gpomap.revisit import RevisitCalibration
    from gpomap.simulate import paper_room_scans

    model = AreaGPOM(kernel="se", length_scale=0.5, optimise=False).fit(paper_room_scans()[::4])
    m = model.map_
    h = model.hyperparameters_
    assert m.hyperparameters == GPHyperparameters(h["variance"], h["length_scale"], h["noise"])
    assert (m.squash.alpha, m.squash.beta, m.squash.variance_scale) == (h["alpha"], h["beta"], h["variance_scale"])
    assert isinstance(m.calibration, EvidenceCalibration)
    assert isinstance(m.revisit, RevisitCalibration)
    assert m.thresholds == model.thresholds_
