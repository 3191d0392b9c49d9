"""OctoMap ScanGraph reader: spherical_scan.graph known values, a written two-node graph, truncations."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.io import detect_format, read_clouds
from gpomap.io.scangraph import read_scangraph

SPHERICAL = Path("../shared/data/octomap/spherical_scan.graph")


def test_spherical_scan_known_values():
    (cloud,) = read_scangraph(SPHERICAL)
    assert cloud.n_points == 10201
    np.testing.assert_allclose(cloud.origin, [1.0, 0.0, -0.5])
    # Independent parse: the first point's three float64 after "1 node, 10201 points, int32 3".
    first = struct.unpack_from("<3d", SPHERICAL.read_bytes(), 12)
    np.testing.assert_allclose(cloud.points[0], np.add(first, [1.0, 0.0, -0.5]))
    assert detect_format(SPHERICAL) == "scangraph"


def _node(points: np.ndarray, t: tuple[float, float, float], q: tuple[float, float, float, float], node_id: int) -> bytes:
    out = struct.pack("<I", len(points))
    for p in points:
        out += struct.pack("<i3d", 3, *p)
    return out + struct.pack("<i3di4dI", 3, *t, 4, *q, node_id)


def test_two_node_graph_round_trip(tmp_path):
    c = np.sqrt(0.5)
    data = struct.pack("<I", 2)
    data += _node(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 7)
    data += _node(np.array([[1.0, 0.0, 0.0]]), (2.0, 3.0, 1.0), (c, 0.0, 0.0, c), 8)  # 90 degrees about z
    data += struct.pack("<I", 0)
    path = tmp_path / "g.graph"
    path.write_bytes(data)
    a, b = read_clouds(path)
    np.testing.assert_allclose(a.points, [[1, 0, 0], [0, 0, 2]])
    np.testing.assert_allclose(b.origin, [2, 3, 1])
    np.testing.assert_allclose(b.points, [[2, 4, 1]], atol=1e-12)
    assert (a.meta["id"], b.meta["id"]) == (7, 8)
    # The same bytes cut inside the second node's pose, and inside the edge count.
    path.write_bytes(data[:-40])
    with pytest.raises(InputFormatError, match="inside node 1's pose"):
        read_scangraph(path)
    path.write_bytes(data[:-2])
    with pytest.raises(InputFormatError, match="inside the edge count"):
        read_scangraph(path)


def test_wrong_element_count_and_bad_quaternion(tmp_path):
    path = tmp_path / "g.graph"
    path.write_bytes(struct.pack("<II", 1, 1) + struct.pack("<i3d", 4, 0, 0, 0))
    with pytest.raises(InputFormatError, match="node 0, point 0: element count 4; expected 3"):
        read_scangraph(path)
    path.write_bytes(struct.pack("<I", 1) + _node(np.zeros((1, 3)), (0, 0, 0), (2.0, 0, 0, 0), 0) + struct.pack("<I", 0))
    with pytest.raises(InputFormatError, match=r"node 0's pose: quaternion .* norm 2"):
        read_scangraph(path)
