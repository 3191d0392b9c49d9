"""Tests of the CARMEN log reader: shared data sets, conventions and malformed input."""

from __future__ import annotations

import gzip
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io import describe, read_scans
from gpomap.io.carmen import beam_angles, read_carmen

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# (file, scans, beams, message type) as the data README gives them.
CARMEN_FILES = [
    ("intel/intel-corrected.log.gz", 910, 180, "FLASER"),
    ("belgioioso/belgioioso-corrected.log.gz", 395, 361, "FLASER"),
    ("fr079/freiburg-079-corrected.log.gz", 4791, 360, "FLASER"),
    ("csail-robotlaser1/csail.log.gz", 686, 361, "ROBOTLASER1"),
]


def _need(rel: str) -> Path:
    path = DATA / rel
    if not path.exists():
        pytest.skip(f"shared data file {path} not found (expected ../shared/data beside the project)")
    return path


def _flaser(ranges: list[float], pose=(1.0, 2.0, 0.5), stamp: float = 10.0) -> str:
    r = " ".join(f"{v:g}" for v in ranges)
    x, y, t = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {t} {x} {y} {t} {stamp} host {stamp}"


@pytest.mark.parametrize("rel,n_scans,n_beams,kind", CARMEN_FILES)
def test_shared_logs_load_with_readme_counts(rel: str, n_scans: int, n_beams: int, kind: str) -> None:
    scans = read_scans(_need(rel))
    assert len(scans) == n_scans
    assert {s.n_beams for s in scans} == {n_beams}
    assert {s.meta["message"] for s in scans} == {kind}
    # The SICK no-return codes are at or above max range in every file, so no hit lies there.
    for s in scans:
        assert s.max_range <= 81.83
        hit = s.valid() & ~s.no_return()
        assert not np.any(s.ranges[hit] >= 81.0)
        assert np.all(np.hypot(*(s.hits() - s.pose[:2]).T) < s.max_range)
    assert sum(int(s.no_return().sum()) for s in scans) > 0


def test_max_range_rules() -> None:
    # FR079 has PARAM robot_front_laser_max 80.99, which its 81.91 code agrees with: kept.
    fr = read_carmen(_need("fr079/freiburg-079-corrected.log.gz"))[0]
    assert fr.max_range == pytest.approx(80.99)
    assert fr.meta["no_return"]["source"] == "header" and fr.meta["no_return"]["code"] == [81.91]
    # Intel has no PARAM: the threshold is its code 81.83 less the 0.01 m tolerance.
    intel = _need("intel/intel-corrected.log.gz")
    s = read_carmen(intel)[0]
    assert s.max_range == pytest.approx(81.82)
    assert s.meta["no_return"]["source"] == "data" and s.meta["no_return"]["code"] == [81.83]
    user = read_carmen(intel, max_range=30.0)[0]
    assert user.max_range == 30.0 and user.meta["no_return"]["source"] == "user"


def test_time_stamps_kept_only_when_usable() -> None:
    assert all(s.time is None for s in read_carmen(_need("belgioioso/belgioioso-corrected.log.gz")))
    intel = read_carmen(_need("intel/intel-corrected.log.gz"))
    assert intel[0].time == pytest.approx(32.9068)


def test_beam_angle_conventions() -> None:
    a = beam_angles(180)
    assert a[0] == pytest.approx(-math.pi / 2)
    assert a[1] - a[0] == pytest.approx(math.pi / 180)
    assert beam_angles(361)[-1] == pytest.approx(math.pi / 2)
    assert beam_angles(360)[1] - beam_angles(360)[0] == pytest.approx(math.pi / 360)
    lin = beam_angles(180, "linspace")
    assert lin[-1] == pytest.approx(math.pi / 2)
    with pytest.raises(ValueError, match="convention"):
        beam_angles(10, "bogus")


def test_small_flaser_file_geometry_and_skipped_lines(tmp_path: Path) -> None:
    ranges = [1.0] * 180
    ranges[90] = 81.91  # no-return code
    ranges[91] = 0.0  # invalid
    text = "\n".join(
        [
            "# comment",
            "## another",
            "PARAM robot_frontlaser_offset -0.04 nohost 0",
            "PARAM robot_front_laser_max 80.99 nohost 0",
            "ODOM 0 0 0 0 0 0 0 host 0",
            "NEFF 12.5",
            "WHATEVER 1 2 3",
            _flaser(ranges, pose=(1.0, 2.0, 0.0), stamp=1.0),
            _flaser([2.0] * 180, pose=(1.5, 2.0, math.pi / 2), stamp=2.0),
        ]
    )
    path = tmp_path / "small.log"
    path.write_text(text + "\n")
    scans = read_carmen(path)
    assert len(scans) == 2
    s0, s1 = scans
    assert s0.meta["line"] == 8 and s1.meta["line"] == 9
    assert s0.time == 1.0 and s1.time == 2.0
    assert s0.max_range == pytest.approx(80.99)
    assert s0.no_return()[90] and not s0.valid()[91]
    assert len(s0.hits()) == 178
    # Beam 0 points to the robot's right (-pi/2) at 1 m.
    np.testing.assert_allclose(s0.hits()[0], [1.0, 1.0], atol=1e-12)
    # Default: the pose is the laser pose; the PARAM offset is recorded, applied on request.
    np.testing.assert_allclose(s1.pose, [1.5, 2.0, math.pi / 2])
    assert s1.meta["frontlaser_offset_param"] == pytest.approx(-0.04)
    moved = read_carmen(path, laser_offset="param")[1]
    np.testing.assert_allclose(moved.pose, [1.5, 1.96, math.pi / 2], atol=1e-12)


def test_gzipped_small_file(tmp_path: Path) -> None:
    path = tmp_path / "small.log.gz"
    with gzip.open(path, "wt") as f:
        f.write(_flaser([3.0] * 360, pose=(0.0, 0.0, 0.0)) + "\n")
    scans = read_scans(path)
    assert len(scans) == 1 and scans[0].n_beams == 360
    # Beam 180 of 360 (pi/360 steps) points straight ahead.
    np.testing.assert_allclose(scans[0].hits()[180], [3.0, 0.0], atol=1e-12)


def test_robotlaser1_uses_laser_pose(tmp_path: Path) -> None:
    n, m = 3, 1
    line = f"ROBOTLASER1 0 -0.5 1.0 0.5 4.0 0.01 0 {n} 5.0 1.0 2.0 {m} 7.0 1.0 1.0 0.0 0.0 0.0 0.0 0 0 0 0 0 123.5 host 1.0"
    path = tmp_path / "r1.log"
    path.write_text(line + "\n")
    (s,) = read_carmen(path)
    np.testing.assert_allclose(s.pose, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(s.angles, [-0.5, 0.0, 0.5])
    assert s.max_range == 4.0 and s.no_return().tolist() == [True, False, False]
    np.testing.assert_allclose(s.hits()[0], [2.0, 1.0])


def test_describe_small_file(tmp_path: Path) -> None:
    path = tmp_path / "d.clf"
    path.write_text(_flaser([1.0] * 180, stamp=1.0) + "\n" + _flaser([81.83] * 180, stamp=3.0) + "\n")
    info = describe(path)
    assert info["format"] == "carmen"
    assert info["n_scans"] == 2 and info["beams_per_scan"] == 180
    assert info["time_span"] == pytest.approx(2.0)


# --- malformed input: one test each --------------------------------------------------------


def test_truncated_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.log"
    good = _flaser([1.0] * 180)
    path.write_text(good + "\n" + good[: len(good) // 2] + "\n")
    with pytest.raises(InputFormatError, match=r"bad\.log, line 2: truncated FLASER line: \d+ fields, expected 191"):
        read_carmen(path)


def test_wrong_field_count(tmp_path: Path) -> None:
    path = tmp_path / "bad.log"
    path.write_text(_flaser([1.0] * 180) + " extra\n")
    with pytest.raises(InputFormatError, match=r"line 1: wrong field count in FLASER line: 192 fields, expected 191 \(n \+ 11"):
        read_carmen(path)


def test_non_numeric_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.log"
    path.write_text("# header\n" + _flaser([1.0] * 180).replace(" 1 1 1 ", " 1 oops 1 ", 1) + "\n")
    with pytest.raises(InputFormatError, match=r"line 2: non-numeric field \d+ 'oops'; expected a number"):
        read_carmen(path)


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.log"
    path.write_text("")
    with pytest.raises(InputFormatError, match=r"empty\.log: empty file"):
        read_carmen(path)


def test_file_without_laser_lines(tmp_path: Path) -> None:
    path = tmp_path / "nolaser.log"
    path.write_text("PARAM a 1 nohost 0\nODOM 0 0 0 0 0 0 0 host 0\n")
    with pytest.raises(GpomapError, match="no laser lines in 2 lines; expected FLASER or ROBOTLASER1"):
        read_carmen(path)


def test_file_with_only_lasers_the_reader_does_not_take_says_which(tmp_path: Path) -> None:
    # A raw log (RAWLASER1 and ODOM, before any SLAM corrected it) and a rear laser's RLASER lines.
    raw = tmp_path / "raw.log"
    raw.write_text(
        "ODOM 0 0 0 0 0 0 1.0 host 1.0\n"
        + "RAWLASER1 0 -1.5708 3.1416 0.0175 8.0 0.01 0 3 1.0 2.0 3.0 0 1.0 host 1.0\n" * 2
        + "RLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0\n"
    )
    with pytest.raises(
        InputFormatError,
        match=(
            r"no laser lines in 4 lines; .* \(found RAWLASER1 \(2 lines\), RLASER \(1 line\); "
            r"RAWLASER lines carry no pose: .*GMapping.*; RLASER and ROBOTLASER2 lines are a second \(rear\) laser"
        ),
    ):
        read_carmen(raw)
    # Beside front-laser lines, the others are left out and the decision's notes say so.
    both = tmp_path / "both.log"
    both.write_text("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0\n" + "RLASER 3 1.0 2.0 3.0 0 0 3.14 0 0 0 1.0 host 1.0\n")
    scans = read_carmen(both)
    assert len(scans) == 1
    assert (
        "laser lines not read: RLASER (1); gpomap reads FLASER and ROBOTLASER1 (the front laser)"
        in scans[0].meta["no_return"]["notes"]
    )


# --- hostile input: only InputFormatError, naming file and line ---------------------------------


@pytest.mark.parametrize(
    "count,expected",
    [
        ("inf", "'inf'; expected the number of readings"),
        ("nan", "'nan'"),
        ("1e400", "'1e400'"),
        ("1e18", "at most 100000"),
        ("9" * 5000, "expected the number of readings"),
        ("-3", "non-negative"),
        ("2.5", "non-negative integer"),
    ],
    ids=["inf", "nan", "1e400", "huge", "5000-digits", "negative", "fraction"],
)
def test_bad_beam_count(tmp_path: Path, count: str, expected: str) -> None:
    path = tmp_path / "bad.log"
    path.write_text(_flaser([1.0] * 180) + "\n" + f"FLASER {count} 1 2 3 0 0 0 0 0 0 1 host 1\n")
    with pytest.raises(InputFormatError, match=rf"bad\.log, line 2: field 2 is .*{expected}") as info:
        read_carmen(path)
    assert len(str(info.value)) < 300  # a 5,000-digit field is shortened in the message


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e400"])
def test_non_finite_pose(tmp_path: Path, value: str) -> None:
    path = tmp_path / "pose.log"
    tokens = _flaser([1.0] * 180).split()
    tokens[180 + 5] = value  # odom_x, the pose read
    path.write_text(" ".join(tokens) + "\n")
    with pytest.raises(InputFormatError, match=r"pose\.log, line 1: FLASER field 186 \(odom_x\) is .*expected a finite number"):
        read_carmen(path)


def test_non_finite_ranges_are_invalid_readings(tmp_path: Path) -> None:
    path = tmp_path / "r.log"
    path.write_text(_flaser([1.0] * 177 + [math.nan, math.inf, 7.0]).replace(" 7 ", " 1e400 ") + "\n")
    (s,) = read_carmen(path)
    # nan, inf and 1e400 (read as inf) are invalid readings, not errors and not hits.
    assert s.valid().sum() == 177 and len(s.hits()) == 177
    assert not s.valid()[177:].any()


def test_robotlaser1_non_finite_geometry(tmp_path: Path) -> None:
    path = tmp_path / "r1.log"
    path.write_text("ROBOTLASER1 0 nan 1.0 0.5 4.0 0.01 0 3 5.0 1.0 2.0 0 1.0 1.0 0.0 0.0 0.0 0.0 0 0 0 0 0 123.5 host 1.0\n")
    with pytest.raises(InputFormatError, match=r"line 1: ROBOTLASER1 field 3 \(start_angle\) is nan"):
        read_carmen(path)
    path.write_text("ROBOTLASER1 0 0 1.0 1e308 4.0 0.01 0 3 5.0 1.0 2.0 0 1.0 1.0 0.0 0.0 0.0 0.0 0 0 0 0 0 123.5 host 1.0\n")
    with pytest.raises(InputFormatError, match=r"line 1: .*non-finite beam angles"):
        read_carmen(path)


def test_binary_garbage_and_invalid_utf8(tmp_path: Path) -> None:
    path = tmp_path / "garbage.log"
    path.write_bytes(b"\x00\x01\xfe\xff" * 100 + b"\n" + bytes(range(11, 256)) + b"\n")
    with pytest.raises(InputFormatError, match=r"garbage\.log, line 1: no laser lines in 2 lines \(line 1 is binary data"):
        read_carmen(path)
    path.write_bytes((_flaser([1.0] * 180) + "\n").encode() + b"FLASER 180 \xff\xfe " + b"1 " * 188 + b"\n")
    with pytest.raises(InputFormatError, match=r"line 2: .*non-numeric field"):
        read_carmen(path)


def test_overlong_line_is_refused_without_reading_it_all(tmp_path: Path) -> None:
    path = tmp_path / "long.log.gz"
    with gzip.open(path, "wb") as f:
        f.write(b"# x\n" + b"7" * (2 << 20))  # no newline for 2 MB
    with pytest.raises(InputFormatError, match=r"long\.log\.gz, line 2: line longer than 1048576 bytes"):
        read_carmen(path)


def test_truncated_gzip(tmp_path: Path) -> None:
    path = tmp_path / "cut.log.gz"
    data = gzip.compress(("\n".join(_flaser([1.0] * 180) for _ in range(50)) + "\n").encode())
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFormatError, match=r"cut\.log\.gz, line \d+: corrupt or truncated gzip data"):
        read_carmen(path)


def test_bad_param_value_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "p.log"
    path.write_text("PARAM robot_front_laser_max nan nohost 0\n" + _flaser([1.0] * 180) + "\n")
    with pytest.raises(InputFormatError, match=r"p\.log, line 1: PARAM robot_front_laser_max is 'nan'; expected a positive"):
        read_carmen(path)


def test_directory_and_fifo_refused_before_opening(tmp_path: Path) -> None:
    import os

    with pytest.raises(InputFormatError, match="is a directory, not a regular file"):
        read_carmen(tmp_path)
    fifo = tmp_path / "pipe.log"
    os.mkfifo(fifo)
    # Opening a FIFO without a writer would block: the reader must refuse it from stat alone.
    with pytest.raises(InputFormatError, match=r"pipe\.log: is a FIFO \(named pipe\), not a regular file"):
        read_scans(fifo)
    with pytest.raises(InputFormatError, match="FIFO"):
        read_carmen(fifo)


def test_a_flaser_line_of_another_beam_count_is_warned_of(tmp_path: Path) -> None:
    log = tmp_path / "odd.log"
    log.write_text(_flaser([1.0] * 180) + "\n" + _flaser([1.0] * 10, stamp=11.0) + "\n" + _flaser([1.0] * 180, stamp=12.0) + "\n")
    with pytest.warns(
        UserWarning, match=r"odd\.log: 1 FLASER line\(s\) with another beam count than the log's 180 \(line 2: 10\)"
    ):
        scans = read_carmen(log)
    assert [s.n_beams for s in scans] == [180, 10, 180]
    # The usual count only: nothing to say.
    log.write_text(_flaser([1.0] * 180) + "\n" + _flaser([1.0] * 180, stamp=11.0) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_carmen(log)
