"""Voxel grids and their outputs: geometry conventions, NPZ round trip, the mesh of a known sphere, figures."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData

from gpomap.errors import InputFormatError
from gpomap.io.octomap import read_octree
from gpomap.io.voxel_outputs import load_voxels, save_voxels, write_mesh, write_voxel_outputs
from gpomap.voxels import VoxelMap, VoxelSpec


def test_spec_conventions():
    spec = VoxelSpec.from_extent([0.03, -1.0, 0.0], [1.0, 0.0, 0.45], 0.1)
    assert spec.origin == pytest.approx((0.0, -1.0, 0.0))  # aligned to a multiple of the resolution
    assert spec.shape == (5, 10, 10)  # (nz, ny, nx)
    c = spec.centres()
    np.testing.assert_allclose(c[0], [0.05, -0.95, 0.05])
    np.testing.assert_allclose(c[1], [0.15, -0.95, 0.05])  # x fastest
    k, j, i, inside = spec.index_of([[0.15, -0.95, 0.25], [2.0, 0.0, 0.0], [0.1, -1.0, 0.0]])
    assert (k[0], j[0], i[0]) == (2, 0, 1) and inside.tolist() == [True, False, True]
    assert i[2] == 1  # a point on a face belongs to the upper voxel


def _sphere(radius: float = 0.6) -> VoxelMap:
    spec = VoxelSpec((-1.0, -1.0, -1.0), 0.05, (40, 40, 40))
    c = spec.centres()
    d = np.linalg.norm(c, axis=1).reshape(spec.shape)
    p = 1.0 / (1.0 + np.exp((d - radius) / 0.05))  # 0.5 exactly on the sphere
    return VoxelMap(spec, p, variance=np.full(spec.shape, 0.1), info={"method": "test"})


def test_npz_round_trip_and_refusals(tmp_path):
    m = _sphere()
    path = save_voxels(m, tmp_path / "m.npz")
    got = load_voxels(path)
    assert got.spec == m.spec and got.info == {"method": "test"}
    np.testing.assert_array_equal(got.probability, m.probability)
    np.testing.assert_array_equal(got.variance, m.variance)
    np.savez(tmp_path / "bad.npz", probability=np.zeros((2, 2)), origin=np.zeros(3), resolution=0.1, thresholds=[0.3, 0.6])
    with pytest.raises(InputFormatError, match=r"'probability' must have shape \(nz, ny, nx\), got \(2, 2\)"):
        load_voxels(tmp_path / "bad.npz")


def test_mesh_of_a_sphere_lies_on_it(tmp_path):
    m = _sphere(0.6)
    path, n_vertices, n_faces = write_mesh(m, tmp_path / "s.ply")
    ply = PlyData.read(str(path))
    v = np.column_stack([ply["vertex"][k] for k in "xyz"])
    assert len(v) == n_vertices > 500 and len(ply["face"]) == n_faces
    # Every vertex of the p = 0.5 surface on the sphere of radius 0.6, within a fraction of a voxel.
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.6, atol=0.01)


def test_output_set(tmp_path):
    m = _sphere()
    files = write_voxel_outputs(m, tmp_path / "out", heights=[0.0, 0.5])
    assert sorted(f.name for f in files) == ["map-3d.png", "map-slices.png", "map.bt", "map.npz", "map.ply"]
    assert all(f.stat().st_size > 0 for f in files)
    tree = read_octree(tmp_path / "out" / "map.bt")
    # The octree's occupied voxels are the map's (p > 0.66), voxel for voxel.
    assert len(tree.voxel_centres(True)) == int((m.probability > 0.66).sum())


def test_voxels_no_ray_went_to_are_left_out_of_the_tree_and_the_mesh(tmp_path):
    from gpomap.io.octomap import write_octree

    # Two occupied blocks on a free field; rays went only round the first (x below 1.2 m).
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (12, 12, 24))
    p = np.full(spec.shape, 0.1)
    p[3:8, 3:8, 3:8] = 0.9
    p[3:8, 3:8, 15:20] = 0.9
    observed = np.zeros(spec.shape, bool)
    observed[:, :, :12] = True
    m = VoxelMap(spec, p, thresholds=(0.3, 0.6), observed=observed)
    save_voxels(m, tmp_path / "m.npz")
    np.testing.assert_array_equal(load_voxels(tmp_path / "m.npz").observed, observed)
    tree = read_octree(write_octree(m, tmp_path / "m.bt"))
    occupied = tree.centres[tree.occupied]
    assert occupied.size and ((occupied > 0.3) & (occupied < 0.8)).all()  # the first block's voxels only
    assert tree.extent()[1][0] <= 1.2 + 1e-6  # the unobserved half is unknown: not in the tree
    _, n_vertices, _ = write_mesh(m, tmp_path / "m.ply")
    vertex = PlyData.read(tmp_path / "m.ply")["vertex"]
    assert n_vertices > 0 and float(np.max(vertex["x"])) < 1.25  # round the first block, nothing round the second
