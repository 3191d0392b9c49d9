"""No-return codes found from the data: synthetic CARMEN logs and bags, the shared logs, the CLI report."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from gpomap.cli import main
from gpomap.io import describe, read_scans
from gpomap.io.carmen import read_carmen
from gpomap.io.noreturn import TOLERANCE, decide_max_range, detect_no_return_code

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

N_SCANS, N_BEAMS = 20, 181


def _real_ranges(rng: np.random.Generator, size: int, low: float = 0.3, high: float = 20.0) -> np.ndarray:
    """Indoor-like ranges to the centimetre, as the CARMEN logs print them."""
    return np.round(rng.uniform(low, high, size), 2)


def _with_codes(rng: np.random.Generator, ranges: np.ndarray, codes: list[float], fraction: float = 0.03) -> np.ndarray:
    """`ranges` with `fraction` of the readings replaced by the codes (in turn)."""
    out = ranges.copy()
    idx = rng.choice(out.size, int(fraction * out.size), replace=False)
    out[idx] = np.resize(np.asarray(codes, dtype=float), idx.size)
    return out


def _flaser_log(path: Path, ranges: np.ndarray, params: list[str] = ()) -> Path:
    lines = [f"PARAM {p} nohost 0" for p in params]
    for k, scan in enumerate(ranges.reshape(-1, N_BEAMS)):
        x, t = 0.1 * k, 0.01 * k
        r = " ".join(f"{v:.10g}" for v in scan)
        lines.append(f"FLASER {N_BEAMS} {r} {x} 0 {t} {x} 0 {t} {k + 1.0} host {k + 1.0}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _robotlaser_log(path: Path, ranges: np.ndarray, max_range: float) -> Path:
    lines = []
    for k, scan in enumerate(ranges.reshape(-1, N_BEAMS)):
        r = " ".join(f"{v:.10g}" for v in scan)
        lines.append(
            f"ROBOTLASER1 0 -1.5708 3.1416 0.017453 {max_range} 0.01 0 {N_BEAMS} {r} 0 "
            f"{0.1 * k} 0 0 {0.1 * k} 0 0 0 0 0 0 0 {k + 1.0} host {k + 1.0}"
        )
    path.write_text("\n".join(lines) + "\n")
    return path


def _count_at_or_above(ranges: np.ndarray, value: float) -> int:
    return int(np.count_nonzero(ranges >= value - TOLERANCE))


@pytest.mark.parametrize(
    "codes",
    [[50.0], [51.05, 51.1], [32.767, 32.76], [81.83, 81.91], [5.6]],
    ids=["50", "51.05+51.1", "32.767+32.76", "81.83+81.91", "5.6"],
)
def test_code_found_without_param(tmp_path: Path, codes: list[float]) -> None:
    rng = np.random.default_rng(1)
    high = min(codes) - 0.5  # real ranges end well below the code
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS, high=min(high, 20.0)), codes)
    scans = read_carmen(_flaser_log(tmp_path / "c.log", ranges))
    d = scans[0].meta["no_return"]
    assert d["source"] == "data" and d["header"] is None
    assert d["code"] == sorted(codes)
    assert scans[0].max_range == pytest.approx(min(codes) - TOLERANCE)
    n_code = int(np.isin(ranges, codes).sum())
    assert d["n_no_return"] == n_code == sum(int(s.no_return().sum()) for s in scans)
    # No code reading becomes a hit: no phantom walls at the code's distance.
    assert max(np.hypot(*(s.hits() - s.pose[:2]).T).max() for s in scans) < min(codes) - 0.4


def test_code_under_a_few_stray_readings(tmp_path: Path) -> None:
    # MIT's infinite corridor log: 3,720 readings at 51.06 m and 466 at 51.11 m under two at
    # 51.16 m. Before, the top reading had to be the code, so none was found and every no-return
    # became a hit 51 m out.
    rng = np.random.default_rng(9)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [51.06, 51.06, 51.11])
    strays = rng.choice(np.flatnonzero(ranges < 20.0), 2, replace=False)
    ranges[strays] = [51.16, 51.2]
    scans = read_carmen(_flaser_log(tmp_path / "s.log", ranges))
    d = scans[0].meta["no_return"]
    assert d["source"] == "data" and d["code"] == [51.06, 51.11]
    assert "2 stray readings above it, no-return too" in d["notes"][0]
    assert scans[0].max_range == pytest.approx(51.05)
    assert d["n_no_return"] == int((ranges > 51.0).sum()) == sum(int(s.no_return().sum()) for s in scans)
    assert max(np.hypot(*(s.hits() - s.pose[:2]).T).max() for s in scans) < 20.5
    # As many readings above the code as a code holds, at distinct values: real long returns
    # beyond a repeated range, so that range is not a code.
    over = np.r_[ranges[ranges < 51.0], np.full(500, 51.06), 51.2 + 0.1 * np.arange(8)]
    assert detect_no_return_code(over) is None
    assert detect_no_return_code(over[:-1]).values == (51.06,)


def test_50m_code_beats_an_80m_param_and_is_reported(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [50.0])
    path = _flaser_log(tmp_path / "p80.log", ranges, ["robot_front_laser_max 80.0"])
    info = describe(path)
    d = info["no_return"]
    assert d["source"] == "data" and d["code"] == [50.0] and info["max_range"] == pytest.approx(49.99)
    assert info["n_no_return"] == int((ranges == 50.0).sum())
    assert "PARAM robot_front_laser_max is 80 m" in d["contradiction"]
    assert d["contradiction"] in info["notes"]


def test_param_10_overruled_by_real_returns_beyond_it(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = N_SCANS * N_BEAMS
    # 35 % of the readings are real returns between 10 and 45 m; the sensor's code is 50 m.
    real = np.where(rng.random(n) < 0.35, _real_ranges(rng, n, 10.0, 45.0), _real_ranges(rng, n, 0.3, 9.9))
    ranges = _with_codes(rng, real, [50.0])
    scans = read_carmen(_flaser_log(tmp_path / "p10.log", ranges, ["robot_front_laser_max 10"]))
    d = scans[0].meta["no_return"]
    assert d["source"] == "data" and scans[0].max_range == pytest.approx(49.99)
    assert d["header"] == {"name": "PARAM robot_front_laser_max", "value": 10.0}
    assert "real returns at or above it" in d["contradiction"]
    hits = np.concatenate([np.hypot(*(s.hits() - s.pose[:2]).T) for s in scans])
    assert np.count_nonzero(hits > 10.0) == np.count_nonzero((ranges > 10.0) & (ranges < 50.0))
    # The same data without the code: nothing is no-return, and the PARAM is still overruled.
    scans = read_carmen(_flaser_log(tmp_path / "p10b.log", real, ["robot_front_laser_max 10"]))
    d = scans[0].meta["no_return"]
    assert d["source"] == "none found" and d["n_no_return"] == 0 and d["contradiction"]
    assert scans[0].max_range > real.max()


def test_param_that_agrees_is_kept(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [81.91])
    (s, *_) = read_carmen(_flaser_log(tmp_path / "ok.log", ranges, ["robot_front_laser_max 80.99"]))
    d = s.meta["no_return"]
    assert s.max_range == 80.99 and d["source"] == "header" and d["code"] == [81.91]
    assert d["contradiction"] is None and d["n_no_return"] == int((ranges == 81.91).sum())


def test_no_code_and_no_param_means_no_no_return(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    ranges = _real_ranges(rng, N_SCANS * N_BEAMS)
    scans = read_carmen(_flaser_log(tmp_path / "none.log", ranges))
    d = scans[0].meta["no_return"]
    assert d["source"] == "none found" and d["code"] is None and d["n_no_return"] == 0
    assert scans[0].max_range > ranges.max()
    assert sum(len(s.hits()) for s in scans) == ranges.size
    assert "no reading is no-return" in d["notes"][0]


def test_user_max_range_always_wins(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [50.0])
    path = _flaser_log(tmp_path / "u.log", ranges, ["robot_front_laser_max 80"])
    scans = read_carmen(path, max_range=10.0)
    d = scans[0].meta["no_return"]
    assert scans[0].max_range == 10.0 and d["source"] == "user" and d["code"] == [50.0]
    assert d["n_no_return"] == _count_at_or_above(ranges, 10.0 + TOLERANCE)
    assert "the given value wins" in d["contradiction"]


@pytest.mark.parametrize("field,source,threshold", [(80.0, "data", 49.99), (50.0, "header", 50.0)])
def test_robotlaser1_field_against_the_data(tmp_path: Path, field: float, source: str, threshold: float) -> None:
    rng = np.random.default_rng(7)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [50.0])
    scans = read_carmen(_robotlaser_log(tmp_path / "r1.log", ranges, field))
    d = scans[0].meta["no_return"]
    assert d["message"] == "ROBOTLASER1" and d["source"] == source
    assert scans[0].max_range == pytest.approx(threshold)
    assert d["n_no_return"] == int((ranges == 50.0).sum())
    assert (d["contradiction"] is not None) == (source == "data")


def test_detector_refuses_what_is_not_a_code() -> None:
    rng = np.random.default_rng(8)
    # Two constant walls: the farther is not a code (nothing shows what real ranges look like).
    assert detect_no_return_code(np.r_[np.full(500, 1.0), np.full(500, 2.0)]) is None
    # A few repeats at the top, as real ranges have near a dense band, are not a code.
    real = _real_ranges(rng, 5000, 0.3, 5.0)
    assert detect_no_return_code(np.r_[real, np.full(3, 5.0)]) is None
    # NaN, inf and non-positive readings are ignored; an empty set finds nothing.
    assert detect_no_return_code([np.nan, np.inf, -1.0, 0.0]) is None
    code = detect_no_return_code(np.r_[real, np.full(200, 32.767), [np.nan, np.inf]])
    assert code is not None and code.values == (32.767,) and code.counts == (200,)
    # The header's value shared by a few readings (Stage's 23 of 77,940 at range_max 5.0) is kept.
    below = _real_ranges(rng, 5000, 0.3, 4.9)
    d = decide_max_range(np.r_[below, np.full(5, 5.0)], header=5.0, header_name="LaserScan range_max")
    assert d.source == "header" and d.max_range == 5.0 and d.n_no_return == 5 and d.code is None
    assert "5 readings at the header's 5 m" in d.notes[0]


# --- bags -------------------------------------------------------------------------------------


def _write_scan_bag(path: Path, ranges: np.ndarray, range_max: float) -> Path:
    """ROS1 bag: /tf odom -> laser (robot still), one LaserScan of N_BEAMS per 0.1 s."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    T = store.types

    def header(t: float, frame: str):
        sec = int(t)
        return T["std_msgs/msg/Header"](
            seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9)), frame_id=frame
        )

    scans = ranges.reshape(-1, N_BEAMS)
    with Writer(path) as w:
        tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        sc = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for k in range(len(scans) + 1):
            t = 0.1 * k
            tr = T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            msg = T["tf2_msgs/msg/TFMessage"](
                transforms=[
                    T["geometry_msgs/msg/TransformStamped"](header=header(t, "odom"), child_frame_id="laser", transform=tr)
                ]
            )
            w.write(tf, int(t * 1e9) + 1, store.serialize_ros1(msg, "tf2_msgs/msg/TFMessage"))
            if k < len(scans):
                scan = T["sensor_msgs/msg/LaserScan"](
                    header=header(t, "laser"),
                    angle_min=-math.pi / 2,
                    angle_max=math.pi / 2,
                    angle_increment=math.pi / (N_BEAMS - 1),
                    time_increment=0.0,
                    scan_time=0.1,
                    range_min=0.05,
                    range_max=range_max,
                    ranges=scans[k].astype(np.float32),
                    intensities=np.zeros(0, dtype=np.float32),
                )
                w.write(sc, int(t * 1e9) + 2, store.serialize_ros1(scan, "sensor_msgs/msg/LaserScan"))
    return path


def test_bag_code_below_range_max(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    ranges = _with_codes(rng, np.round(rng.uniform(0.3, 25.0, 10 * N_BEAMS), 3), [32.767])
    scans = read_scans(_write_scan_bag(tmp_path / "b.bag", ranges, range_max=60.0))
    d = scans[0].meta["no_return"]
    assert d["source"] == "data" and d["code"] == [32.767] and d["topic"] == "/scan"
    assert "LaserScan range_max is 60 m" in d["contradiction"]
    assert d["n_no_return"] == int((ranges == 32.767).sum()) == sum(int(s.no_return().sum()) for s in scans)


def test_bag_range_max_that_agrees_is_kept(tmp_path: Path) -> None:
    rng = np.random.default_rng(10)
    ranges = _with_codes(rng, np.round(rng.uniform(0.3, 4.5, 10 * N_BEAMS), 3), [5.0])
    scans = read_scans(_write_scan_bag(tmp_path / "s.bag", ranges, range_max=5.0))
    d = scans[0].meta["no_return"]
    assert d["source"] == "header" and scans[0].max_range == 5.0 and d["code"] == [5.0]
    assert d["n_no_return"] == int((ranges == 5.0).sum())


# --- shared logs and the CLI ------------------------------------------------------------------

# (file, no-return readings, how decided, code): the counts `gpomap info` gave before detection.
SHARED = [
    ("intel/intel-corrected.log.gz", 4172, "data", [81.83]),
    ("belgioioso/belgioioso-corrected.log.gz", 699, "header", [81.91]),
    ("csail-robotlaser1/csail.log.gz", 6097, "header", [81.91]),
    ("stage-arena/robot1.bag", 23, "header", None),
]


@pytest.mark.parametrize("rel,count,source,code", SHARED, ids=[s[0].split("/")[0] for s in SHARED])
def test_shared_logs_keep_their_no_return_counts(rel: str, count: int, source: str, code: list | None) -> None:
    path = DATA / rel
    if not path.exists():
        pytest.skip(f"shared data file {path} not found")
    info = describe(path)
    assert info["n_no_return"] == count
    assert info["no_return_source"] == source and info["no_return_code"] == code
    assert info["no_return"]["contradiction"] is None


def test_info_prints_code_count_and_contradiction(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(11)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS), [50.0])
    path = _flaser_log(tmp_path / "cli.log", ranges, ["robot_front_laser_max 80"])
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    n = int((ranges == 50.0).sum())
    assert "no-return code  50 m (FLASER)" in out
    assert f"no-return count {n} of {ranges.size} readings (>= 49.99 m)" in out
    assert "decided by      data (PARAM robot_front_laser_max 80)" in out
    assert "contradiction   PARAM robot_front_laser_max is 80 m but the data has" in out
    assert main(["info", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["no_return_code"] == [50.0] and d["n_no_return"] == n
    assert main(["info", str(path), "--max-range", "30"]) == 0
    assert "decided by      user" in capsys.readouterr().out


def test_map_says_how_many_readings_returned_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The summary's count is the log's readings at the no-return code, counted here from the ranges written.
    rng = np.random.default_rng(12)
    ranges = _with_codes(rng, _real_ranges(rng, N_SCANS * N_BEAMS, high=8.0), [50.0])
    path = _flaser_log(tmp_path / "map.log", ranges)
    fast = ["--kernel", "se", "--min-cell", "1.0", "--max-cell", "1.0", "--resolution", "0.25", "--length-scale", "1"]
    assert main(["map", str(path), "-o", str(tmp_path / "out"), *fast]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("points "))
    n = _count_at_or_above(ranges, 50.0)
    assert n > 0 and line.endswith(f"occupied; {n} readings without a return (free space only, to --no-return-cap)")
    # A log whose every beam returned says nothing of them.
    path = _flaser_log(tmp_path / "all.log", _real_ranges(rng, N_SCANS * N_BEAMS, high=8.0))
    assert main(["map", str(path), "-o", str(tmp_path / "all"), *fast]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("points "))
    assert line.endswith(" occupied")


def test_the_ray_counts_line_states_the_silent_rule_when_it_moves_the_map() -> None:
    from gpomap.cli.common import ray_counts

    weights = {"hit_weight": 0.82, "surface_weight": 0.46, "near_weight": 0.35, "near_hit_weight": 0.001}
    summary = {**weights, "prior_weight": 0.22, "surprise_rate": 0.01, "silent_rate": 0.5, "silent_mix": 0.063}
    # (1 - 0.063) p + 0.063 * 0.5, by hand.
    assert ray_counts(summary).endswith("; where only beams without a return went, p -> 0.937 p + 0.0315")
    assert ray_counts({**summary, "silent_mix": 0.0}).endswith("surprise rate 0.01")


def test_a_reading_near_the_float_limit_leaks_no_overflow_warning() -> None:
    import warnings

    from gpomap.io.noreturn import detect_no_return_code

    ranges = np.r_[np.linspace(0.5, 20.0, 500), 1e308]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = detect_no_return_code(ranges)
    assert found is None or found.value < 1e300  # a lone absurd reading is no sensor's code


def test_a_bag_whose_range_max_hides_a_smeared_code_trusts_the_data(tmp_path: Path) -> None:
    # Built like a SICK bag seen in the wild: LaserScan range_max 80 m, but about 1 % of the
    # readings at 51.05-51.12 m (the laser's no-return code, smeared over centimetres as float32
    # and the sensor's jitter leave it) with a few strays above, to 51.22 m.
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from tests.test_io_rosbag import _scan, _tf

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    types = store.types
    rng = np.random.default_rng(7)
    path = tmp_path / "sick.bag"
    with Writer(path) as writer:
        tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for i in range(61):
            t = 0.1 * i
            msg = _tf(types, t, "odom", "laser", 0.01 * i, 0.0, 0.0)
            writer.write(tf, int(t * 1e9) + 1, store.serialize_ros1(msg, "tf2_msgs/msg/TFMessage"))
            if 0 < i < 60:
                ranges = np.round(rng.uniform(0.5, 30.0, 181), 3)
                code = rng.random(181) < 0.012
                ranges[code] = rng.uniform(51.05, 51.12, int(code.sum()))
                if i % 20 == 0:
                    ranges[0] = rng.uniform(51.13, 51.22)
                laser = _scan(types, t, "laser", ranges, angle_increment=math.pi / 180, range_max=80.0)
                writer.write(scan, int(t * 1e9) + 2, store.serialize_ros1(laser, "sensor_msgs/msg/LaserScan"))
    scans = read_scans(path)
    decision = scans[0].meta["no_return"]
    assert decision["source"] == "data" and 51.0 <= decision["max_range"] < 51.05
    assert decision["contradiction"] and "range_max is 80 m" in decision["contradiction"]
    # Every reading of the code, and the strays above it, is a no-return: none is a wall at 51 m.
    assert all(not (s.hits() - s.pose[:2] > 50).any() for s in scans) and sum(int(s.no_return().sum()) for s in scans) > 100
    info = describe(path)
    assert info["no_return_source"] == "data" and any("51.05" in n for n in info["notes"])
