"""The ROS adapter's middleware-free parts, without ROS: message conversion, the LiveMap core, the node's parameters.

The LaserScan messages are the Stage arena bag's, deserialised by rosbags (ROS 2 field names:
``stamp.sec`` / ``stamp.nanosec``), so the code the rospy node runs is checked on real messages.
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gpomap.errors import GpomapError, InputFormatError, NotFittedError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.mapfile import load_fitted_map
from gpomap.io.npz import load_map
from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
from gpomap.ros.live import LiveMap
from gpomap.ros.messages import grid_layers, is_upside_down, pose_from_transform, scan_from_laserscan, stamp_seconds
from gpomap.ros.node import NodeSettings, settings_from_params
from gpomap.streaming import StreamingGPOM

BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "stage-arena" / "robot1.bag"
needs_bag = pytest.mark.skipif(not BAG.exists(), reason="shared Stage arena bag not present")


def bag_messages() -> list:
    """The bag's /base_scan LaserScan messages, in order."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([BAG], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        conns = [c for c in reader.connections if c.topic == "/base_scan"]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]


def batch_scans() -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the last scan has no later pose and is dropped, with a warning
        return read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)


def laserscan(ranges, range_min=0.1, range_max=5.0, angle_min=-1.0, angle_increment=0.5, stamp=(3, 500_000_000)):
    header = SimpleNamespace(stamp=SimpleNamespace(secs=stamp[0], nsecs=stamp[1]), frame_id="/laser")
    return SimpleNamespace(
        header=header,
        ranges=list(ranges),
        range_min=range_min,
        range_max=range_max,
        angle_min=angle_min,
        angle_increment=angle_increment,
    )


# --------------------------------------------------------------------------- messages
def test_stamps_of_ros1_and_ros2():
    assert stamp_seconds(SimpleNamespace(secs=12, nsecs=250_000_000)) == 12.25
    assert stamp_seconds(SimpleNamespace(sec=12, nanosec=250_000_000)) == 12.25
    with pytest.raises(InputFormatError, match="secs/nsecs"):
        stamp_seconds(12.25)


def test_pose_from_transform_is_x_y_yaw():
    t = SimpleNamespace(x=1.0, y=-2.0, z=0.15)
    half = math.radians(30) / 2
    q = SimpleNamespace(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))
    assert pose_from_transform(t, q) == pytest.approx((1.0, -2.0, math.radians(30)))


def test_upside_down_laser_frames_mirror_their_beams():
    # z axis of the rotated frame: level (yaw only), rolled 180 degrees, pitched 180, rolled 60.
    yaw = SimpleNamespace(x=0.0, y=0.0, z=math.sin(0.3), w=math.cos(0.3))
    roll = SimpleNamespace(x=1.0, y=0.0, z=0.0, w=0.0)
    pitch = SimpleNamespace(x=0.0, y=1.0, z=0.0, w=0.0)
    tilt = SimpleNamespace(x=math.sin(math.radians(30)), y=0.0, z=0.0, w=math.cos(math.radians(30)))
    assert [is_upside_down(q) for q in (yaw, roll, pitch, tilt)] == [False, True, True, False]
    # A beam at +90 degrees of an upside-down laser heading along x points to -y.
    msg = laserscan([1.0, 2.0])  # beams at -1.0 and -0.5 rad
    scan = scan_from_laserscan(msg, (0.0, 0.0, 0.0), upside_down=True)
    np.testing.assert_allclose(scan.angles, [1.0, 0.5])
    np.testing.assert_allclose(scan.hits(), [[math.cos(1.0), math.sin(1.0)], [2 * math.cos(0.5), 2 * math.sin(0.5)]])


def test_laserscan_readings_follow_rep_117():
    msg = laserscan([1.0, math.inf, -math.inf, math.nan, 0.05, 5.0, 7.0])
    scan = scan_from_laserscan(msg, (1.0, 2.0, 0.5))
    assert scan.max_range == 5.0 and scan.time == 3.5 and scan.meta["frame_id"] == "laser"
    np.testing.assert_allclose(scan.angles, -1.0 + 0.5 * np.arange(7))
    # valid: 1.0, +inf (as the limit), 5.0 and 7.0; invalid: -inf, nan and below range_min.
    assert scan.valid().tolist() == [True, True, False, False, False, True, True]
    assert scan.no_return().tolist() == [False, True, False, False, False, True, True]
    assert scan.ranges[1] == 5.0
    # A threshold given wins over range_max.
    assert scan_from_laserscan(msg, (0, 0, 0), max_range=4.0).no_return().tolist()[0] is False


@pytest.mark.parametrize(
    ("change", "pose", "match"),
    [
        ({"range_max": 0.0}, (0, 0, 0), "scan_topic: range_max must be a positive number"),
        ({"range_max": math.nan}, (0, 0, 0), "range_max must be a positive number"),
        ({"angle_increment": math.inf}, (0, 0, 0), "angle_min -1.0 and angle_increment inf must be finite"),
        ({}, (0, math.nan, 0), "laser pose must be three finite numbers"),
        ({}, (0, 0), "laser pose must be three finite numbers"),
    ],
)
def test_bad_laserscans_are_refused_naming_the_field(change, pose, match):
    msg = laserscan([1.0, 2.0])
    for k, v in change.items():
        setattr(msg, k, v)
    with pytest.raises(InputFormatError, match=match):
        scan_from_laserscan(msg, pose, source="scan_topic")


@needs_bag
def test_bag_messages_convert_as_the_bag_reader_reads_them():
    scans = batch_scans()
    messages = bag_messages()[: len(scans)]
    for msg, ref in zip(messages, scans):
        scan = scan_from_laserscan(msg, ref.pose)
        assert scan.time == ref.time and scan.max_range == ref.max_range
        np.testing.assert_array_equal(scan.angles, ref.angles)
        np.testing.assert_array_equal(scan.ranges, ref.ranges)


def test_grid_layers_follow_the_occupancy_grid_conventions():
    spec = GridSpec((-1.0, 2.0), 0.5, (2, 3))
    prob = np.array([[0.0, 0.2, 0.5], [0.7, 0.996, np.nan]])
    var = np.array([[0.0, 0.5, 1.0], [2.0, 0.25, np.nan]])
    layers = grid_layers(OccupancyMap(spec, prob, var, thresholds=(0.33, 0.66)), prior_variance=1.0)
    assert (layers.width, layers.height) == (3, 2)
    # Row-major from the lower-left cell, as OccupancyGrid data.
    assert layers.trinary.tolist() == [0, 0, -1, 100, 100, -1]
    assert layers.probability.tolist() == [0, 20, 50, 70, 100, -1]
    assert layers.variance.tolist() == [0, 50, 100, 100, 25, -1]  # capped at the prior
    assert all(a.dtype == np.int8 for a in (layers.trinary, layers.probability, layers.variance))
    # Without a prior variance: relative to the largest one.
    assert grid_layers(OccupancyMap(spec, prob, var)).variance.tolist() == [0, 25, 50, 100, 12, -1]
    assert grid_layers(OccupancyMap(spec, prob)).variance.tolist() == [-1] * 6


# --------------------------------------------------------------------------- the LiveMap core
class Clock:
    """Seconds that move only when the test says."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_live_map_mirrors_the_scans_of_a_laser_the_lookup_says_is_upside_down():
    class Recorder:
        def __init__(self) -> None:
            self.scans: list = []

        def add_scan(self, scan) -> None:
            self.scans.append(scan)

    mapper = Recorder()
    live = LiveMap(mapper, 0.1)  # type: ignore[arg-type]
    live.receive(laserscan([1.0, 2.0]))
    live.receive(laserscan([1.0, 2.0], stamp=(4, 0)))
    poses = {3.5: (0.0, 0.0, 0.0), 4.0: (0.0, 0.0, 0.0, True)}
    assert live.process(lambda frame, t: poses[t]) == 2
    np.testing.assert_allclose(mapper.scans[0].angles, [-1.0, -0.5])
    np.testing.assert_allclose(mapper.scans[1].angles, [1.0, 0.5])


@needs_bag
def test_live_map_from_bag_messages_is_the_streaming_map_of_the_bag_reader(tmp_path):
    # The first 40 scans (20 of warm-up, 20 streamed after it) and the bag's last message, which
    # has no pose: the whole bag would only stream more of the same.
    scans = batch_scans()[:40]
    # The poses the bag reader found (tf interpolated 0.1 s after each stamp); the last scan has none.
    poses = {round(s.time + STAGE_TIME_OFFSET, 6): tuple(s.pose) for s in scans}
    lookups = []

    def lookup(frame: str, t: float):
        lookups.append(frame)
        return poses.get(round(t, 6))

    clock = Clock()
    live = LiveMap(
        StreamingGPOM(warmup_scans=20, n_workers=1),
        0.1,
        time_offset=STAGE_TIME_OFFSET,
        pose_wait=1.0,
        source="/base_scan",
        clock=clock,
    )
    assert live.layers() is None
    with pytest.raises(NotFittedError, match="0 scans seen"):
        live.save(tmp_path / "early")
    every = bag_messages()
    messages = [*every[: len(scans)], every[-1]]
    for msg in messages:
        live.receive(msg)
    # All but the last have a pose; the last waits, then is dropped once pose_wait has passed.
    assert live.process(lookup) == len(scans)
    assert live.status()["n_waiting"] == 1 and live.process(lookup) == 0
    clock.now = 1.5
    assert live.process(lookup) == 0
    status = live.status()
    assert status["n_received"] == len(messages) and status["n_used"] == len(scans)
    assert status["n_dropped_no_pose"] == 1 and status["n_waiting"] == 0 and status["ready"]
    assert status["latency_ms"]["median"] > 0 and status["stamp"] == scans[-1].time
    assert set(lookups) == {"base_laser_link"}

    reference = StreamingGPOM(warmup_scans=20, n_workers=1)
    for s in scans:
        reference.add_scan(s)
    expected = reference.grid(0.1)
    layers = live.layers()
    assert layers is not None and layers.grid == expected.grid
    assert np.array_equal(layers.trinary, grid_layers(expected).trinary)
    files = live.save(tmp_path / "saved")
    assert sorted(f.name for f in files) == ["map.gpom", "map.npz", "map.pgm", "map.png", "map.yaml"]
    np.testing.assert_allclose(load_map(tmp_path / "saved" / "map.npz").probability, expected.probability, atol=1e-12)
    # The fitted map saved beside the grids is the live model: the same grid, to the bit.
    fitted = load_fitted_map(tmp_path / "saved" / "map.gpom").grid(0.1, expected.grid.extent)
    assert np.array_equal(fitted.probability, expected.probability)


@needs_bag
def test_live_map_keeps_a_bad_message_out_and_goes_on():
    scans = batch_scans()
    poses = {round(s.time, 6): tuple(s.pose) for s in scans}
    live = LiveMap(StreamingGPOM(warmup_scans=5, n_workers=1), 0.1, source="/base_scan")
    messages = bag_messages()[:3]
    messages[1].range_max = -1.0
    for msg in messages:
        live.receive(msg)
    assert live.process(lambda frame, t: poses.get(round(t, 6))) == 2
    status = live.status()
    assert status["n_rejected"] == 1 and "/base_scan: range_max must be a positive number" in status["last_error"]


@needs_bag
def test_live_map_processing_stops_at_its_budget():
    clock = Clock()
    live = LiveMap(StreamingGPOM(warmup_scans=30, n_workers=1), 0.1, clock=clock)
    for msg in bag_messages()[:10]:
        live.receive(msg)

    def lookup(frame, t):
        clock.now += 0.4  # each scan costs 0.4 s of this clock
        return (0.0, 0.0, 0.0)

    # At least one scan per call, then none once the budget of 1 s is spent.
    assert live.process(lookup, budget=1.0) == 3
    assert live.process(lookup, budget=0.0) == 1
    assert live.process(lookup) == 6


# --------------------------------------------------------------------------- the node's parameters
def test_node_settings_defaults_and_values():
    assert settings_from_params(lambda name, default: default) == NodeSettings()
    given = {
        "scan_topic": "/base_scan",
        "fixed_frame": "/odom",
        "resolution": 0.1,
        "extent": [-1, 4, -2, 3],
        "thresholds": [0.2, 0.8],
        "max_range": 5.5,
        "warmup_scans": 10,
        "model": {"kernel": "se"},
        "save_on_shutdown": True,
    }
    s = settings_from_params(lambda name, default: given.get(name, default))
    assert s.fixed_frame == "odom" and s.extent == (-1.0, 4.0, -2.0, 3.0) and s.thresholds == (0.2, 0.8)
    assert s.max_range == 5.5 and s.warmup_scans == 10 and s.model == {"kernel": "se"} and s.save_on_shutdown


@pytest.mark.parametrize(
    ("name", "value", "match"),
    [
        ("resolution", 0, r"~resolution must be a finite number > 0, got 0"),
        ("resolution", "fine", r"~resolution must be a number, got 'fine'"),
        ("publish_rate", math.inf, r"~publish_rate must be a finite number > 0"),
        ("pose_wait", -1, r"~pose_wait must be a finite number >= 0"),
        ("max_range", 0, r"~max_range must be a finite number > 0"),
        ("extent", [0, 1, 2], r"~extent must be \[xmin, xmax, ymin, ymax\]"),
        ("extent", [1, 0, 0, 1], r"~extent must have xmin < xmax"),
        ("thresholds", [0.7, 0.3], r"~thresholds must satisfy 0 <= free <= occupied <= 1"),
        ("warmup_scans", 0, r"~warmup_scans must be an integer >= 1"),
        ("warmup_scans", 2.5, r"~warmup_scans must be an integer >= 1"),
        ("model", "se", r"~model must be a dict"),
        ("save_on_shutdown", "yes", r"~save_on_shutdown must be true or false"),
    ],
)
def test_bad_node_parameters_are_refused_naming_them(name, value, match):
    with pytest.raises(GpomapError, match=match):
        settings_from_params(lambda n, default: value if n == name else default)


def test_the_node_without_rospy_says_what_to_install():
    if importlib.util.find_spec("rospy") is not None:
        pytest.skip("rospy is importable here: the node would start (tests/test_ros_node.py runs it)")
    r = subprocess.run([sys.executable, "-m", "gpomap.ros"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.startswith("gpomap-ros: error: the ROS 1 Python packages (rospy, tf2_ros, nav_msgs, sensor_msgs, std_srvs)")
    assert "apt-get install ros-core python3-rospy" in r.stderr and "--system-site-packages" in r.stderr
