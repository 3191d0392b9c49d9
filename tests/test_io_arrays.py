"""Tests of labelled-point files (CSV and NPZ)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.io.arrays import read_points, write_points
from gpomap.observations import Observations


def _obs() -> Observations:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(25, 2))
    occ = rng.random(25) < 0.4
    return Observations(points=pts, occupied=occ, scan_index=np.zeros(25, dtype=np.intp))


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    obs = _obs()
    path = tmp_path / f"points{suffix}"
    write_points(path, obs)
    assert path.exists()
    back = read_points(path)
    np.testing.assert_array_equal(back.points, obs.points)
    np.testing.assert_array_equal(back.occupied, obs.occupied)
    assert back.scan_index.dtype == np.intp and not back.scan_index.any()


def test_csv_true_false_any_column_order(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_text("occupied, y ,x,note\ntrue,2,1,a\nFalse,4.5,3,b\n\n1,0,0,c\n")
    obs = read_points(path)
    np.testing.assert_array_equal(obs.points, [[1, 2], [3, 4.5], [0, 0]])
    assert obs.occupied.tolist() == [True, False, True]


def test_csv_missing_column(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_text("x,y\n1,2\n")
    with pytest.raises(InputFormatError, match=r"p\.csv, line 1: missing column\(s\) occupied"):
        read_points(path)


def test_csv_non_numeric_value(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_text("x,y,occupied\n1,2,0\n1,abc,1\n")
    with pytest.raises(InputFormatError, match=r"line 3: non-numeric coordinate 'abc'"):
        read_points(path)


def test_csv_bad_label(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_text("x,y,occupied\n1,2,maybe\n")
    with pytest.raises(InputFormatError, match=r"line 2: occupied value 'maybe'; expected 0/1 or true/false"):
        read_points(path)


def test_csv_short_row_and_empty(tmp_path: Path) -> None:
    path = tmp_path / "p.csv"
    path.write_text("x,y,occupied\n1,2\n")
    with pytest.raises(InputFormatError, match=r"line 2: 2 fields, expected 3"):
        read_points(path)
    path.write_text("")
    with pytest.raises(InputFormatError, match="empty file"):
        read_points(path)
    path.write_text("x,y,occupied\n")
    with pytest.raises(InputFormatError, match="no data rows"):
        read_points(path)


def test_npz_missing_array_and_bad_shapes(tmp_path: Path) -> None:
    path = tmp_path / "p.npz"
    np.savez(path, points=np.zeros((3, 2)))
    with pytest.raises(InputFormatError, match=r"missing array\(s\) occupied"):
        read_points(path)
    np.savez(path, points=np.zeros((3, 3)), occupied=np.zeros(3, bool))
    with pytest.raises(InputFormatError, match=r"'points' has shape \(3, 3\); expected \(n, 2\)"):
        read_points(path)
    np.savez(path, points=np.zeros((3, 2)), occupied=np.zeros(4, bool))
    with pytest.raises(InputFormatError, match=r"'occupied' has shape \(4,\); expected \(3,\)"):
        read_points(path)
    np.savez(path, points=np.zeros((3, 2)), occupied=np.array([0, 1, 2]))
    with pytest.raises(InputFormatError, match="boolean or 0/1"):
        read_points(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match="no such file"):
        read_points(tmp_path / "none.csv")


# --- hostile input ------------------------------------------------------------------------------


def test_csv_invalid_utf8_nul_and_non_finite(tmp_path):
    from gpomap.io.arrays import read_points

    p = tmp_path / "bad.csv"
    p.write_bytes(b"x,y,occupied\n1,2,1\n3,\xff\xfe,0\n")
    with pytest.raises(InputFormatError, match=r"bad\.csv, line 3: not UTF-8 text"):
        read_points(p)
    p.write_bytes(b"x,y,occupied\n1,2\x00,1\n")
    with pytest.raises(InputFormatError, match=r"bad\.csv, line 2: non-numeric coordinate '2\\x00'"):
        read_points(p)
    p.write_text('x,y,occupied\n1,2,1\n"' + "7" * 200_000 + '",1,1\n')  # above csv's field size limit
    with pytest.raises(InputFormatError, match=r"bad\.csv, line 3: malformed CSV \(field larger than field limit"):
        read_points(p)
    for value in ("nan", "inf", "1e400", "9" * 5000):
        p.write_text(f"x,y,occupied\n1,2,1\n{value},2,0\n")
        with pytest.raises(InputFormatError, match=r"bad\.csv, line 3: non-finite coordinate"):
            read_points(p)


def test_npz_object_complex_truncated_and_lying_headers(tmp_path):
    import io
    import zipfile

    from gpomap.io.arrays import read_points

    p = tmp_path / "bad.npz"
    np.savez(p, points=np.array([[1, 2]], dtype=object), occupied=np.array([1]))
    with pytest.raises(InputFormatError, match=r"bad\.npz: array 'points' holds Python objects"):
        read_points(p)
    np.savez(p, points=np.array([[1 + 1j, 2]]), occupied=np.array([1]))
    with pytest.raises(InputFormatError, match=r"'points' has dtype complex128; expected real numbers"):
        read_points(p)
    np.savez(p, points=np.array([[1.0, np.nan]]), occupied=np.array([1]))
    with pytest.raises(InputFormatError, match=r"'points' row 0 is \[1.0, nan\]; expected finite"):
        read_points(p)
    np.savez(p, points=np.zeros((100, 2)), occupied=np.zeros(100, dtype=bool))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFormatError, match=r"bad\.npz: not a readable points \.npz file"):
        read_points(p)
    # A 128-byte .npy header announcing a terabyte must not be allocated.
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (10**11, 2)})
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("points.npy", buf.getvalue() + bytes(64))
        z.writestr("occupied.npy", buf.getvalue())
    with pytest.raises(InputFormatError, match=r"array 'points' announces shape \(100000000000, 2\)"):
        read_points(p)
