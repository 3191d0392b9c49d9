import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.npz import load_map, save_map


def _full_map():
    grid = GridSpec((-2.5, 1.25), 0.1, (6, 8))
    rng = np.random.default_rng(1)
    return OccupancyMap(
        grid,
        rng.uniform(0, 1, grid.shape),
        variance=rng.uniform(0, 2, grid.shape),
        thresholds=(0.3, 0.7),
        path=rng.normal(size=(5, 2)),
        info={"method": "gpom", "lengthscale": np.float64(0.25), "sizes": np.arange(3), "ok": True, "n": None},
        seen_through=rng.uniform(0, 1, grid.shape) < 0.5,
    )


def _rewrite(src, dst, drop=(), **replace):
    """Copy an npz, dropping or replacing arrays (to make malformed files)."""
    with np.load(src) as z:
        data = {k: z[k] for k in z.files if k not in drop}
    data.update(replace)
    with open(dst, "wb") as f:
        np.savez(f, **data)
    return dst


def test_round_trip_everything(tmp_path):
    m = _full_map()
    out = save_map(m, tmp_path / "map.npz")
    assert out == tmp_path / "map.npz"
    back = load_map(out)
    assert back.grid == m.grid
    np.testing.assert_array_equal(back.probability, m.probability)
    np.testing.assert_array_equal(back.variance, m.variance)
    np.testing.assert_array_equal(back.path, m.path)
    np.testing.assert_array_equal(back.seen_through, m.seen_through)
    np.testing.assert_array_equal(back.ternary, m.ternary)
    # The seen-through cells are what keeps some cells above the threshold out of the occupied class.
    assert ((m.probability > 0.7) & m.seen_through).any()
    assert (m.ternary != OccupancyMap(m.grid, m.probability, thresholds=m.thresholds).ternary).any()
    assert back.thresholds == (0.3, 0.7)
    assert back.info == {"method": "gpom", "lengthscale": 0.25, "sizes": [0, 1, 2], "ok": True, "n": None}
    with np.load(out) as z:
        np.testing.assert_array_equal(z["ternary"], m.ternary)


def test_round_trip_minimal_and_exact_name(tmp_path):
    m = OccupancyMap(GridSpec((0, 0), 1.0, (1, 1)), np.array([[np.nan]]))
    save_map(m, tmp_path / "plain")  # no suffix added
    back = load_map(tmp_path / "plain")
    assert back.variance is None and back.path is None and back.seen_through is None and back.info == {}
    assert np.isnan(back.probability[0, 0])


def test_unserialisable_info_is_a_clear_error(tmp_path):
    m = _full_map()
    m.info["model"] = object()
    with pytest.raises(ValueError, match="info cannot be saved as JSON"):
        save_map(m, tmp_path / "m.npz")
    assert list(tmp_path.iterdir()) == []


def test_missing_required_array(tmp_path):
    good = save_map(_full_map(), tmp_path / "good.npz")
    bad = _rewrite(good, tmp_path / "bad.npz", drop=("resolution",))
    with pytest.raises(InputFormatError, match=r"missing the required array.*'resolution'"):
        load_map(bad)


def test_variance_shape_disagrees(tmp_path):
    good = save_map(_full_map(), tmp_path / "good.npz")
    bad = _rewrite(good, tmp_path / "bad.npz", variance=np.zeros((3, 3)))
    with pytest.raises(InputFormatError, match=r"'variance' must have shape \(6, 8\).*got \(3, 3\)"):
        load_map(bad)


def test_seen_through_must_be_bool_of_the_probabilitys_shape(tmp_path):
    src = save_map(_full_map(), tmp_path / "m.npz")
    bad = _rewrite(src, tmp_path / "dtype.npz", seen_through=np.ones((6, 8)))
    with pytest.raises(InputFormatError, match="'seen_through' has dtype float64; expected bool"):
        load_map(bad)
    bad = _rewrite(src, tmp_path / "shape.npz", seen_through=np.ones((6, 7), bool))
    with pytest.raises(InputFormatError, match="seen_through"):
        load_map(bad)


def test_path_shape(tmp_path):
    good = save_map(_full_map(), tmp_path / "good.npz")
    bad = _rewrite(good, tmp_path / "bad.npz", path=np.zeros((4, 3)))
    with pytest.raises(InputFormatError, match=r"'path' must have shape \(k, 2\)"):
        load_map(bad)


def test_bad_resolution(tmp_path):
    good = save_map(_full_map(), tmp_path / "good.npz")
    bad = _rewrite(good, tmp_path / "bad.npz", resolution=np.array(-1.0))
    with pytest.raises(InputFormatError, match="resolution must be a positive number"):
        load_map(bad)


def test_not_an_npz(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(InputFormatError, match=r"not a NumPy \.npz map file.*found a file starting with b'hello'"):
        load_map(tmp_path / "x.npz")
    np.save(tmp_path / "y.npy", np.zeros(3))
    with pytest.raises(InputFormatError, match=r"single-array \.npy"):
        load_map(tmp_path / "y.npy")
    with pytest.raises(InputFormatError, match="not found"):
        load_map(tmp_path / "missing.npz")


def test_interrupted_save_keeps_previous_file(tmp_path, monkeypatch):
    target = save_map(_full_map(), tmp_path / "map.npz")
    before = target.read_bytes()

    # Fail after part of the archive went to the temporary file: its first member written whole.
    import gpomap.io.members as members

    real_write = members.write_member
    written = []

    def write_then_fail(zf, key, array):
        if written:
            raise OSError("simulated failure midway")
        written.append(key)
        real_write(zf, key, array)

    monkeypatch.setattr(members, "write_member", write_then_fail)
    bigger = OccupancyMap(GridSpec((0, 0), 0.5, (30, 30)), np.zeros((30, 30)))
    with pytest.raises(OSError, match="midway"):
        save_map(bigger, target)
    monkeypatch.setattr(members, "write_member", real_write)
    assert written
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]
    assert load_map(target).grid.shape == (6, 8)
