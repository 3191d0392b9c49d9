"""OctoMap trees: geb079.bt known values, .bt / .ot round trips through pyoctomap, corrupt files refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.io import describe, detect_format
from gpomap.io.octomap import check_octree_file, read_octree, write_octree
from gpomap.voxels import VoxelMap, VoxelSpec

GEB079 = Path("../shared/data/octomap/geb079.bt")
STRUCTURED = Path("../shared/data/la3dm-sim/sim_structured/map.bt")


def test_geb079_known_values():
    # The header says 532,566 nodes at 0.08 m; the walk of the stream must agree before pyoctomap reads it.
    assert check_octree_file(GEB079) == ("bt", 0.08, 532566)
    tree = read_octree(GEB079)
    assert tree.resolution == pytest.approx(0.08)
    assert tree.n_leaves == 428144 and int(tree.occupied.sum()) == 143729
    # Pruned leaves are the resolution times a power of two.
    assert sorted(np.unique(tree.sizes.round(4))) == [0.08, 0.16, 0.32, 0.64]
    # A .bt keeps only occupied / free: the probabilities are the clamping bounds.
    np.testing.assert_allclose(np.unique(tree.probability), [0.1192, 0.971], atol=1e-6)
    lower, upper = tree.extent()
    np.testing.assert_allclose(lower, [-8.0, -7.52, -0.32], atol=1e-6)
    np.testing.assert_allclose(upper, [30.96, 7.44, 2.8], atol=1e-6)


def test_la3dm_world_tree_and_describe():
    assert detect_format(STRUCTURED) == "octomap"
    info = describe(STRUCTURED)
    assert info["resolution"] == pytest.approx(0.1)
    assert info["n_leaves"] == info["n_occupied"] + info["n_free"] == 138477
    assert info["extent"][5] == pytest.approx(4.3)  # the world's z bound, as the dataset's yaml says


def _map() -> VoxelMap:
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 5, 6))
    p = np.full(spec.shape, 0.5)
    p[0] = 0.2  # a free floor (30 voxels, prunable into blocks)
    p[2, 1:3, 1:4] = 0.9  # an occupied block
    p[3, 4, 5] = 0.7
    return VoxelMap(spec, p)


@pytest.mark.parametrize("suffix", [".bt", ".ot"])
def test_write_then_read_round_trip(tmp_path, suffix):
    m = _map()
    path = write_octree(m, tmp_path / f"m{suffix}")
    tree = read_octree(path)
    centres = m.spec.centres()
    occ = m.probability.reshape(-1) > 0.66
    free = m.probability.reshape(-1) < 0.33

    def as_set(a: np.ndarray) -> set[tuple[int, ...]]:
        return {tuple(v) for v in np.round(a / 0.05).astype(int)}

    assert as_set(tree.voxel_centres(True)) == as_set(centres[occ])
    assert as_set(tree.voxel_centres(False)) == as_set(centres[free])
    if suffix == ".ot":  # probabilities kept, clamped to OctoMap's bounds [0.1192, 0.971]
        got = {round(float(v), 3) for v in tree.probability}
        assert got == {0.2, 0.9, 0.7}


def _bt(size: int, data: bytes, res: str = "0.1") -> bytes:
    return f"# Octomap OcTree binary file\nid OcTree\nsize {size}\nres {res}\ndata\n".encode() + data


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"# not an octree\n", r"line 1: first line is .*expected '# Octomap OcTree binary file'"),
        (_bt(9, b"\x01\x00"), r"tree data hold 2 nodes; the header's size says 9"),
        (_bt(5, b"\x03\x00"), r"corrupt tree: tree data ends after 2 bytes"),
        (_bt(5, b"\xff\xff" * 40), r"an inner node at depth 16"),  # would recurse past 16 levels
        (_bt(2, b"\x01\x00", res="-1"), r"line 4: res '-1'; expected a positive number"),
        (_bt(2, b"\x01\x00").replace(b"size 2", b"size two"), r"line 3: size 'two'"),
        (b"# Octomap OcTree file\nid ColorOcTree\nsize 1\nres 0.1\ndata\n", r"line 2: tree type 'ColorOcTree'"),
        (
            b"# Octomap OcTree file\nsize 3\nres 0.1\ndata\n" + b"\x00\x00\x00\x00\x03",
            r"corrupt tree: tree data ends after 5 bytes",
        ),
    ],
)
def test_corrupt_trees_are_refused_before_octomap_reads_them(tmp_path, content, message):
    path = tmp_path / "bad.bt"
    path.write_bytes(content)
    with pytest.raises(InputFormatError, match=message):
        read_octree(path)


def test_smallest_valid_bt_reads(tmp_path):
    path = tmp_path / "one.bt"
    path.write_bytes(_bt(2, b"\x02\x00"))  # root with one occupied child leaf (bit 1: child 0 occupied)
    tree = read_octree(path)
    assert tree.n_leaves == 1 and tree.occupied.all()
    assert tree.sizes[0] == pytest.approx(0.1 * 2**15)  # a child of the root spans half the tree
    path.write_bytes(_bt(2, b"\x01\x00"))  # bit 0: child 0 free
    assert not read_octree(path).occupied.any()
