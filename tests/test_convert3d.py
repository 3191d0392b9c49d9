"""Tests of gpomap.convert.octree: OctoMap trees to continuous maps, one GP or tiles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpomap.convert import TiledOctreeModel, convert_octree
from gpomap.errors import GpomapError
from gpomap.grid import OCCUPIED
from gpomap.io.octomap import read_octree, write_octree
from gpomap.voxels import VoxelMap, VoxelSpec

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GEB079 = DATA / "octomap" / "geb079.bt"
HYPER = ("variance", "length_scale", "noise", "alpha", "beta")


@pytest.fixture(scope="module")
def geb079():
    if not GEB079.exists():
        pytest.skip("shared OctoMap sample geb079.bt not available")
    return read_octree(GEB079)


REGION = ([5.0, -1.0, 0.0], [6.5, 0.5, 2.0])


@pytest.fixture(scope="module")
def one_gp(geb079):
    """A 1.5 x 1.5 m stretch of the FR-079 corridor, every height (1,681 cells), by one GP."""
    return convert_octree(geb079, 0.08, *REGION, max_cells=None)


def test_tiled_agrees_with_one_gp_on_a_real_region(geb079, one_gp):
    # The same stretch in tiles of 0.75 m (9 columns blended) with the one GP's hyperparameters.
    # The tiles see the cells within 1.5 length scales of their squares, so their maps differ
    # from the one GP's only where a cell beyond that would have moved them: measured, |dp|
    # 0.006 on average and 0.08 at most, one voxel in 1,300 of another class.
    one = one_gp
    assert "tiles" not in one.report
    given = {k: one.report["hyperparameters"][k] for k in HYPER}
    tiled = convert_octree(geb079, 0.08, *REGION, tile_size=0.75, hyperparameters=given)
    assert isinstance(tiled.model, TiledOctreeModel)
    t = tiled.report["tiles"]
    assert t["tile_size"] == 0.75 and t["tiles_fitted"] >= 4 and t["largest_tile_cells"] < one.report["cells"]["n"]
    assert tiled.map.spec == one.map.spec
    d = np.abs(tiled.map.probability - one.map.probability)
    assert d.mean() < 0.01 and d.max() < 0.15, (d.mean(), d.max())
    assert (tiled.map.ternary == one.map.ternary).mean() > 0.998
    # At the known voxels (predicted exactly, not read off the grid) both keep the tree's labels.
    a1, a2 = one.report["agreement"], tiled.report["agreement"]
    assert a2["n_checked"] == a1["n_checked"] > 8000
    assert abs(a2["ternary"] - a1["ternary"]) < 0.002 and a2["auc"] > 0.999
    # Two tiles in flight on threads: the same map (the tiles are added in the same order).
    two = convert_octree(geb079, 0.08, *REGION, tile_size=0.75, hyperparameters=given, n_workers=2)
    np.testing.assert_allclose(two.map.probability, tiled.map.probability, rtol=0, atol=1e-12)
    # The model answers anywhere by fitting the tiles it needs again: the voxels' own numbers.
    pts = np.array([[5.5, -0.3, 1.0], [6.1, 0.2, 0.4]])
    np.testing.assert_allclose(tiled.model.predict_proba(pts), tiled.map.lookup(pts), atol=0.05)


def test_more_cells_than_one_gp_holds_converts_in_tiles(geb079, one_gp):
    # The same stretch with at most 600 cells a GP (it has 1,681): converted in tiles whose GPs
    # each hold at most that many, with hyperparameters of their own learning, at 0.04 m (the
    # variance predicted on the tree's 0.08 m pitch and interpolated); the tree's known voxels
    # keep their labels as with one GP.
    res = convert_octree(geb079, 0.04, *REGION, max_cells=600)
    t = res.report["tiles"]
    assert t["largest_tile_cells"] <= 600 and t["tile_size"] < 3.0
    a1, a2 = one_gp.report["agreement"], res.report["agreement"]
    assert abs(a2["ternary"] - a1["ternary"]) < 0.01 and a2["auc"] > 0.999, (a1, a2)
    assert res.map.spec.resolution == 0.04 and np.isfinite(res.map.variance).all()
    assert (res.map.variance > 0).all() and (res.map.variance <= res.report["hyperparameters"]["variance"] + 1e-9).all()
    # Read at the 0.08 m grid's voxel centres, the two maps mostly agree on the class.
    centres = one_gp.map.spec.centres()
    k, j, i, inside = res.map.spec.index_of(centres)
    assert inside.mean() > 0.9
    same = res.map.ternary[k, j, i][inside] == one_gp.map.ternary.ravel()[inside]
    assert same.mean() > 0.98, same.mean()


def test_tiles_weights_sum_to_one_and_empty_tiles_predict_the_prior(tmp_path):
    # A tree of 2 x 1 x 0.4 m of 0.1 m voxels with a wall at x 1.2..1.4, converted over x 0..4 m in
    # tiles of 0.5 m: those beyond x 2.2 hold no cell in their reach and predict the prior (latent
    # mean 0, variance 1, p 0.5); the blend runs between them and the tiles with data.
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 10, 20))
    x = spec.centres()[:, 0].reshape(spec.shape)
    path = tmp_path / "slab.bt"
    write_octree(VoxelMap(spec, np.where((x > 1.2) & (x < 1.4), 0.97, 0.12)), path)
    tree = read_octree(path)
    res = convert_octree(tree, 0.1, [0.0, 0.0, 0.0], [4.0, 1.0, 0.4], tile_size=0.5)
    m = res.map
    wall = m.lookup(np.array([[1.3, 0.5, 0.2]]))
    free = m.lookup(np.array([[0.6, 0.5, 0.2]]))
    far = m.lookup(np.array([[3.5, 0.5, 0.2]]))
    assert wall[0] > 0.66 and free[0] < 0.33 and abs(far[0] - 0.5) < 1e-6
    assert m.ternary[:, :, 12:14].min() == OCCUPIED


def test_the_tiled_model_answers_through_its_fitted_map_in_one_pass_over_the_columns(tmp_path, monkeypatch):
    # The slab of the test above in columns of 0.5 m: the conversion's voxels are the fitted map's
    # voxels; the points scored beside them are predicted in the same pass, each column fitted
    # once, as a pass for the points alone predicts them; and every answer is the fitted map's.
    from gpomap.convert import ColumnsField, octree_tiling
    from gpomap.fitted import FittedMap

    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 10, 20))
    x = spec.centres()[:, 0].reshape(spec.shape)
    path = tmp_path / "slab.bt"
    write_octree(VoxelMap(spec, np.where((x > 1.2) & (x < 1.4), 0.97, 0.12)), path)
    box = ([0.0, 0.0, 0.0], [3.0, 1.0, 0.4])
    res = convert_octree(read_octree(path), 0.1, *box, tile_size=0.5)
    model = res.model
    assert isinstance(model, TiledOctreeModel) and isinstance(model.map_.field, ColumnsField)
    extent = (0.0, 3.0, 0.0, 1.0, 0.0, 0.4)
    again = model.voxels(0.1, extent)
    np.testing.assert_array_equal(again.probability, res.map.probability)
    np.testing.assert_array_equal(again.variance, res.map.variance)
    assert again.thresholds == res.map.thresholds == model.thresholds_

    fitted_keys = []
    fit = octree_tiling.fit_tile_task
    monkeypatch.setattr(octree_tiling, "fit_tile_task", lambda task: fitted_keys.append(task.key) or fit(task))
    pts = np.array([[1.25, 0.55, 0.15], [0.65, 0.45, 0.25], [2.05, 0.95, 0.05]])  # voxel centres
    vm, p = model.map_.voxels_and_points(0.1, extent, pts)
    assert len(fitted_keys) == len(set(fitted_keys)) == model.last_prediction_["tiles_fitted"] > 4
    np.testing.assert_array_equal(vm.probability, res.map.probability)
    np.testing.assert_allclose(p, model.predict_proba(pts), rtol=0, atol=1e-12)
    # At voxel centres of a grid on the tree's pitch (the variance predicted there, not
    # interpolated) the points are the grid's voxels.
    np.testing.assert_allclose(p, vm.lookup(pts), rtol=0, atol=1e-12)
    assert p[0] > 0.66 and p[1] < 0.33

    def quarter(self, points, return_var=False):
        return np.full(len(points), 0.25)

    monkeypatch.setattr(FittedMap, "predict_proba", quarter)
    np.testing.assert_array_equal(model.predict_proba(pts), [0.25, 0.25, 0.25])


def test_a_column_denser_than_the_limit_is_refused(geb079):
    with pytest.raises(GpomapError, match=r"densest 0.5 m column .* more than one GP holds \(50\)"):
        convert_octree(geb079, 0.08, [5.0, -1.0, 0.0], [6.0, 0.0, 2.0], max_cells=50)
