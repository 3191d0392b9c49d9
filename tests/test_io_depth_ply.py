"""Depth frames (3DMatch layout) and PLY clouds: known pixels, the shipped frames, bad inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData, PlyElement

from gpomap.errors import InputFormatError
from gpomap.io import detect_format, read_clouds
from gpomap.io.depth import read_depth_frames
from gpomap.io.ply import read_ply

MATCH = Path("../shared/data/3dmatch")


def _frame_dir(tmp_path: Path, depth: np.ndarray, pose: str = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n") -> Path:
    (tmp_path / "camera-intrinsics.txt").write_text("100 0 2\n0 100 1\n0 0 1\n")
    Image.fromarray(depth.astype(np.uint16)).save(tmp_path / "frame-000000.depth.png")
    (tmp_path / "frame-000000.pose.txt").write_text(pose)
    return tmp_path


def test_known_pixels(tmp_path):
    depth = np.zeros((3, 5), dtype=np.uint16)
    depth[1, 2] = 2000  # the principal point, 2 m
    depth[0, 4] = 1000  # (u, v) = (4, 0), 1 m
    d = _frame_dir(tmp_path, depth, "1 0 0 10\n0 1 0 20\n0 0 1 30\n0 0 0 1\n")
    assert detect_format(d) == "depth-directory"
    (cloud,) = read_clouds(d)
    assert cloud.n_points == 15 and cloud.valid().sum() == 2  # 0 pixels are no reading, not free space
    np.testing.assert_allclose(cloud.origin, [10, 20, 30])
    np.testing.assert_allclose(cloud.points[1 * 5 + 2], [10, 20, 32])
    np.testing.assert_allclose(cloud.points[4], [10 + 0.02, 20 - 0.01, 31])  # x = (4-2)*1/100, y = (0-1)*1/100
    (far,) = read_clouds(d, max_range=1.5)
    assert far.hit[4] and not far.hit[7]


def test_shipped_frames_and_stride():
    clouds = read_depth_frames(MATCH, stride=4)
    assert len(clouds) == 5
    raw = np.asarray(Image.open(MATCH / "frame-000000.depth.png"))[::4, ::4]
    assert clouds[0].n_points == raw.size == 160 * 120
    assert int(clouds[0].valid().sum()) == int((raw > 0).sum())
    np.testing.assert_allclose(clouds[0].origin, [1.973046, 1.125734, 0.30982])


def test_bad_depth_inputs(tmp_path):
    d = _frame_dir(tmp_path, np.ones((2, 2)))
    (d / "frame-000000.pose.txt").write_text("1 0 0\n")
    with pytest.raises(InputFormatError, match="has 1 lines of numbers; expected 4 lines of 4"):
        read_depth_frames(d)
    (d / "frame-000000.pose.txt").unlink()
    with pytest.raises(InputFormatError, match=r"has no pose file frame-000000\.pose\.txt"):
        read_depth_frames(d)
    (d / "frame-000000.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    Image.fromarray(np.zeros((2, 2), dtype=np.uint8)).save(d / "frame-000000.depth.png")
    with pytest.raises(InputFormatError, match="image mode 'L'; expected a 16-bit"):
        read_depth_frames(d)
    (d / "camera-intrinsics.txt").write_text("100 0 2\n0 -1 1\n0 0 1\n")
    with pytest.raises(InputFormatError, match="is not \\[\\[fx, 0, cx\\]"):
        read_depth_frames(d)


@pytest.mark.parametrize("text", [True, False])
def test_ply_round_trip_with_poses(tmp_path, text):
    v = np.array([(1.0, 0.0, 0.0), (0.0, 1.0, 0.5)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    for i in range(2):
        PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(tmp_path / f"c{i}.ply"))
    poses = tmp_path / "poses.txt"
    poses.write_text("1 0 0 0  0 1 0 0  0 0 1 0\n0 -1 0 1  1 0 0 2  0 0 1 3\n")  # KITTI 3x4 rows; 2nd: 90 deg about z
    a, b = read_clouds(tmp_path, poses=poses)
    np.testing.assert_allclose(a.points, [[1, 0, 0], [0, 1, 0.5]], atol=1e-7)
    np.testing.assert_allclose(b.origin, [1, 2, 3])
    np.testing.assert_allclose(b.points, [[1, 3, 3], [0, 2, 3.5]], atol=1e-7)


def test_ply_needs_a_pose_and_vertices(tmp_path):
    v = np.array([(1.0,)], dtype=[("x", "f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "c.ply"))
    with pytest.raises(InputFormatError, match="PLY files carry no sensor pose"):
        read_clouds(tmp_path / "c.ply")
    with pytest.raises(InputFormatError, match="vertex element has no y, z"):
        read_ply(tmp_path / "c.ply", origin=np.zeros(3))
    (tmp_path / "c.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n\x00"
    )
    with pytest.raises(InputFormatError, match="cannot read as a PLY file"):
        read_ply(tmp_path / "c.ply", origin=np.zeros(3))
