"""Arrays written as zip members (gpomap.io.members): deflated where that pays, read back exactly."""

import io
import zipfile
import zlib

import numpy as np

from gpomap.io.members import DEFLATE_BELOW, SPREAD_FROM, deflates, write_member


def _whole_ratio(array):
    raw = np.ascontiguousarray(array).tobytes()
    return len(zlib.compress(raw, 1)) / len(raw)


def test_a_large_array_is_deflated_when_the_whole_of_it_shrinks():
    rng = np.random.default_rng(0)
    # A map plane: a corner of unknown space (its first bytes deflate), then values that do not.
    plane = rng.random(SPREAD_FROM // 8 + 4096)
    plane[:2_000] = 0.5
    # Counts over a building's lattice: zero but where beams went.
    counts = np.zeros(SPREAD_FROM // 4 * 2, dtype=np.float32)
    counts[rng.integers(0, counts.size, 20_000)] = rng.integers(1, 9, 20_000) / 256
    # Values of six decimals: they shrink by a fifth, not by a third (a written map's planes).
    rounded = np.round(rng.random(SPREAD_FROM // 8 + 4096), 6)
    rounded[:2_000] = 0.5
    assert 2 / 3 < _whole_ratio(rounded) < 0.8
    for array in (plane, counts, rounded):
        assert array.nbytes >= SPREAD_FROM
        assert deflates(array) == (_whole_ratio(array) < DEFLATE_BELOW)
    assert not deflates(plane) and deflates(counts) and not deflates(rounded)


def test_members_read_back_exactly_stored_or_deflated():
    rng = np.random.default_rng(1)
    arrays = {
        "plane": rng.random((1500, 1500)),
        "flags": rng.random((1500, 1500)) < 0.01,
        "tiny": np.array(3.5),
        "text": np.array('{"a": 1}'),
    }
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for key, array in arrays.items():
            write_member(zf, key, array)
    with zipfile.ZipFile(buffer) as zf:
        kinds = {i.filename: i.compress_type for i in zf.infolist()}
    assert kinds["plane.npy"] == zipfile.ZIP_STORED and kinds["flags.npy"] == zipfile.ZIP_DEFLATED
    buffer.seek(0)
    loaded = np.load(buffer)
    for key, array in arrays.items():
        assert loaded[key].dtype == array.dtype
        np.testing.assert_array_equal(loaded[key], array)
