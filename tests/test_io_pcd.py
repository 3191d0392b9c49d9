"""PCD reader: the la3dm scans (known values), pypcd4 round trips in every encoding, bad headers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from gpomap.errors import InputFormatError
from gpomap.io import detect_format, read_clouds
from gpomap.io.pcd import read_pcd
from gpomap.io.poses import quaternion_matrix

LA3DM = Path("../shared/data/la3dm-sim/sim_structured")


def _raw_la3dm(path: Path) -> np.ndarray:
    """The float32 x y z intensity rows after the header, read without pypcd4."""
    data = path.read_bytes()
    start = data.index(b"DATA binary\n") + len(b"DATA binary\n")
    return np.frombuffer(data[start : start + 3500 * 16], dtype="<f4").reshape(-1, 4)


def test_la3dm_scan_known_values():
    path = LA3DM / "sim_structured_1.pcd"
    cloud = read_pcd(path, max_range=8.0)
    raw = _raw_la3dm(path)
    assert cloud.n_points == 3500 == len(raw)
    np.testing.assert_allclose(cloud.origin, [0.999982, 1.00002, 0.0997627])
    # Points are world coordinates already (identity VIEWPOINT rotation): hits equal the raw rows.
    r = np.linalg.norm(raw[:, :3] - cloud.origin, axis=1)
    assert int((~cloud.hit).sum()) == int((r > 8.0).sum()) > 0
    np.testing.assert_allclose(cloud.points[cloud.hit], raw[r <= 8.0, :3], atol=1e-6)
    far = cloud.points[~cloud.hit]
    np.testing.assert_allclose(np.linalg.norm(far - cloud.origin, axis=1), 8.0)
    assert cloud.meta["encoding"] == "binary"


def test_la3dm_directory_in_natural_order():
    clouds = read_clouds(LA3DM)
    assert detect_format(LA3DM) == "pcd-directory"
    assert [Path(c.meta["path"]).name for c in clouds][:3] == [
        "sim_structured_1.pcd",
        "sim_structured_2.pcd",
        "sim_structured_3.pcd",
    ]
    assert len(clouds) == 12 and all(c.n_points == 3500 for c in clouds)
    np.testing.assert_allclose(clouds[9].origin, [2.99999, 8.00001, 0.0997705])  # sim_structured_10


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
def test_pypcd4_round_trip(tmp_path, encoding):
    rng = np.random.default_rng(1)
    pts = rng.uniform(-5, 5, size=(200, 3)).astype(np.float32)
    pts[7] = np.nan  # PCL's no-reading point
    cloud = PointCloud.from_xyz_points(pts)
    path = tmp_path / "c.pcd"
    cloud.save(path, encoding=encoding)
    got = read_pcd(path)
    np.testing.assert_array_equal(got.points[~np.isnan(pts[:, 0])], pts[~np.isnan(pts[:, 0])])
    assert not got.valid()[7] and got.valid().sum() == 199
    np.testing.assert_array_equal(got.origin, [0, 0, 0])


def _write_with_viewpoint(path: Path, pts: np.ndarray, viewpoint: str) -> None:
    PointCloud.from_xyz_points(pts.astype(np.float32)).save(path, encoding=Encoding.ASCII)
    text = path.read_text().replace("VIEWPOINT 0.0 0.0 0.0 1.0 0.0 0.0 0.0", f"VIEWPOINT {viewpoint}")
    path.write_text(text)


def test_sensor_frame_points_are_moved_by_the_viewpoint(tmp_path):
    path = tmp_path / "v.pcd"
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)  # 90 degrees about z: qw = qz = sqrt(1/2)
    _write_with_viewpoint(path, np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 1.0]]), f"1 2 3 {c} 0 0 {s}")
    as_map = read_pcd(path)
    np.testing.assert_allclose(as_map.points, [[1, 0, 0], [0, 2, 1]], atol=1e-6)
    sensor = read_pcd(path, points_frame="sensor")
    np.testing.assert_allclose(sensor.origin, [1, 2, 3])
    np.testing.assert_allclose(sensor.points, [[1, 3, 3], [-1, 2, 4]], atol=1e-6)


def test_poses_file_replaces_the_viewpoint(tmp_path):
    for i in range(2):
        PointCloud.from_xyz_points(np.array([[1.0, 0, 0]], dtype=np.float32)).save(tmp_path / f"s_{i}.pcd")
    poses = tmp_path / "poses.txt"
    poses.write_text("# tx ty tz qw qx qy qz\n0 0 0 1 0 0 0\n5 0 1 0 0 0 1\n")
    clouds = read_clouds(tmp_path, poses=poses)
    np.testing.assert_allclose(clouds[1].origin, [5, 0, 1])
    np.testing.assert_allclose(clouds[1].points, [[4, 0, 1]], atol=1e-12)  # 180 degrees about z
    poses.write_text("0 0 0 1 0 0 0\n")
    with pytest.raises(InputFormatError, match="holds 1 poses for 2 PCD files"):
        read_clouds(tmp_path, poses=poses)


HEADER = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA {}\n"


@pytest.mark.parametrize(
    ("header", "body", "message"),
    [
        (HEADER.replace("FIELDS x y z", "FIELDS x y w"), b"", r"line 2: FIELDS 'x y w' has no 'z'"),
        (
            HEADER.replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 0 0 0 2 0 0 0"),
            b"",
            r"line 8: VIEWPOINT .*norm 2; expected a unit quaternion",
        ),
        (HEADER.replace("WIDTH 2", "WIDTH 3"), b"", r"line 9: POINTS 2 but WIDTH x HEIGHT = 3 x 1"),
        (HEADER.replace("TYPE F F F", "TYPE F F U"), b"", r"field 'z' is TYPE U"),
        (HEADER.replace("COUNT", "COLOUR"), b"", r"line 5: unknown header key 'COLOUR'"),
        (HEADER.format("binary").format(), b"\x00" * 20, r"binary data is 20 bytes; POINTS 2 x 12 bytes per point needs 24"),
        (
            HEADER.format("binary_compressed"),
            b"\x10\x00\x00\x00\x00\x00\x00\x40",
            r"announces 16 compressed bytes .* expected 24 uncompressed",
        ),
        (HEADER.format("ascii"), b"1 2 3\n4 five 6\n", r"cannot decode the PCD data"),
        (HEADER.format("lzma"), b"", r"line 10: DATA 'lzma'; expected ascii, binary or binary_compressed"),
        ("VERSION 0.7\nFIELDS x y z\n", b"", r"file ends in the header after 2 lines"),
    ],
)
def test_malformed_headers_say_where(tmp_path, header, body, message):
    path = tmp_path / "bad.pcd"
    path.write_bytes(header.format("ascii").encode() + body if "{}" in header else header.encode() + body)
    with pytest.raises(InputFormatError, match=message) as err:
        read_pcd(path)
    assert str(path) in str(err.value)


def test_not_a_regular_file(tmp_path):
    with pytest.raises(InputFormatError, match="file not found"):
        read_pcd(tmp_path / "missing.pcd")
    with pytest.raises(InputFormatError, match="is a directory"):
        read_pcd(tmp_path)


def test_quaternion_matrix_known_rotation():
    c = np.sqrt(0.5)
    np.testing.assert_allclose(quaternion_matrix(c, 0, 0, c), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
