"""Tests of the ROS bag reader: the Stage bag against its true floor plan, and synthetic bags."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.io import describe, detect_format, read_scans
from gpomap.io.rosbag import STAGE_TIME_OFFSET, load_rosbag, read_rosbag, yaw_from_quaternion

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STAGE = DATA / "stage-arena"


def _need_stage() -> Path:
    bag = STAGE / "robot1.bag"
    if not bag.exists() or not (STAGE / "mrl_arena.pgm").exists():
        pytest.skip(f"Stage arena data not found in {STAGE} (expected ../shared/data beside the project)")
    return bag


def _fraction_near_plan(hits: np.ndarray, tol: float = 0.03) -> float:
    """Fraction of hits within `tol` of an occupied pixel (as an area) of the true plan."""
    from PIL import Image
    from scipy.spatial import cKDTree

    img = np.asarray(Image.open(STAGE / "mrl_arena.pgm"))
    h, _ = img.shape
    # Stage stretches the bitmap to 4.06 m x 4.55 m; lower-left corner (-1.03, -1.275), row 0 on top.
    dx, dy = 0.0100, 0.009891
    rows, cols = np.nonzero(img < 128)
    centres = np.column_stack([-1.03 + (cols + 0.5) * dx, -1.275 + (h - rows - 0.5) * dy])
    _, idx = cKDTree(centres).query(hits, k=8)
    q = centres[idx]
    gx = np.maximum(np.abs(hits[:, None, 0] - q[..., 0]) - dx / 2, 0.0)
    gy = np.maximum(np.abs(hits[:, None, 1] - q[..., 1]) - dy / 2, 0.0)
    return float((np.hypot(gx, gy).min(axis=1) <= tol).mean())


def test_stage_bag_counts_and_geometry() -> None:
    result = load_rosbag(_need_stage())
    assert result.topic == "/base_scan"
    assert result.n_messages == 433 and len(result.scans) == 433 and result.n_dropped == 0
    assert result.laser_frames == ["base_laser_link"]
    s = result.scans[0]
    assert s.n_beams == 180 and s.max_range == 5.0
    assert s.angles[0] == pytest.approx(-math.pi / 2, abs=1e-6)
    assert s.angles[-1] == pytest.approx(math.pi / 2, abs=1e-6)
    # odom -> base_footprint (-0.607, 2.8, 0) composed with base_link -> base_laser_link (0.225, 0).
    np.testing.assert_allclose(s.pose, [-0.382, 2.8, 0.0], atol=1e-9)
    # No hit is ever placed at a no-return (range_max) reading.
    for sc in result.scans:
        assert np.all(np.hypot(*(sc.hits() - sc.pose[:2]).T) < 5.0)


def test_stage_bag_hits_lie_on_true_plan_with_time_offset() -> None:
    bag = _need_stage()
    shifted = load_rosbag(bag, time_offset=STAGE_TIME_OFFSET)
    # The last scan has no later pose to match.
    assert len(shifted.scans) == 432 and shifted.n_dropped == 1
    near = _fraction_near_plan(np.concatenate([s.hits() for s in shifted.scans]))
    same = _fraction_near_plan(np.concatenate([s.hits() for s in load_rosbag(bag).scans]))
    # Measured: 87.1 % with the 0.1 s offset, 76.8 % with the same-stamp pose.
    assert near >= 0.85
    assert near > same + 0.05


def test_stage_unknown_topic_lists_topics() -> None:
    with pytest.raises(InputFormatError, match=r"unknown topic '/scan'; LaserScan topics: /base_scan; topics in the bag: .*/tf"):
        read_rosbag(_need_stage(), topic="/scan")


def test_stage_unknown_frame_lists_frames() -> None:
    with pytest.raises(InputFormatError, match=r"unknown fixed frame 'world'; known tf frames: .*base_laser_link.*odom"):
        read_rosbag(_need_stage(), fixed_frame="world")


def test_stage_describe() -> None:
    info = describe(_need_stage(), time_offset=STAGE_TIME_OFFSET)
    assert info["format"] == "rosbag1" and info["n_scans"] == 432 and info["n_dropped"] == 1
    assert info["beams_per_scan"] == 180 and info["max_range"] == 5.0
    assert info["time_span"] > 40


# --- synthetic bags ---------------------------------------------------------------------------


def _quat(types, yaw: float):
    return types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def _header(types, t: float, frame: str):
    sec = math.floor(t)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))
    header = types["std_msgs/msg/Header"]
    if "seq" in header.__dataclass_fields__:  # ROS1 headers have a sequence number
        return header(seq=0, stamp=stamp, frame_id=frame)
    return header(stamp=stamp, frame_id=frame)


def _tf(types, t: float, parent: str, child: str, x: float, y: float, yaw: float, quaternion=None):
    """A TFMessage of one transform: a planar pose, or the rotation `quaternion` (x, y, z, w)."""
    rotation = _quat(types, yaw) if quaternion is None else types["geometry_msgs/msg/Quaternion"](*quaternion)
    tr = types["geometry_msgs/msg/Transform"](translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0), rotation=rotation)
    ts = types["geometry_msgs/msg/TransformStamped"](header=_header(types, t, parent), child_frame_id=child, transform=tr)
    return types["tf2_msgs/msg/TFMessage"](transforms=[ts])


def _scan(types, t: float, frame: str, ranges, angle_increment: float = math.pi / 2, range_max: float = 4.0):
    """A LaserScan from -90 to 90 degrees in steps of `angle_increment`."""
    return types["sensor_msgs/msg/LaserScan"](
        header=_header(types, t, frame),
        angle_min=-math.pi / 2,
        angle_max=math.pi / 2,
        angle_increment=angle_increment,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.05,
        range_max=range_max,
        ranges=np.asarray(ranges, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )


def _odometry(types, t: float, x: float, yaw: float):
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0), orientation=_quat(types, yaw)
    )
    twist = types["geometry_msgs/msg/Twist"](
        linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return types["nav_msgs/msg/Odometry"](
        header=_header(types, t, "odom"),
        child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def _write_bag(
    path: Path,
    ros2: bool = False,
    odom: bool = False,
    laser_quaternion=None,
    map_frame: bool = False,
    map_clock: float | None = None,
) -> Path:
    """Robot drives along x from 0 to 2 m over 2 s while turning 0 -> pi/2; laser 0.1 m ahead.

    Scans at t = -0.5 (before the poses, dropped), 0.5, 1.0 and 1.5 s, three beams at -90, 0 and 90
    degrees with ranges (1, 4 = max range, 0.01 = below range_min). The laser's rotation on the
    robot is `laser_quaternion` (x, y, z, w), or none; with `map_frame`, tf places odom in map
    (on /tf_static, or on /tf at the robot's stamps plus `map_clock` seconds when given).
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        # The Noetic store lacks tf2_msgs; its definition is one line.
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    types = store.types
    ser = store.serialize_cdr if ros2 else store.serialize_ros1
    messages = []
    # Frame names with leading slashes, as in ROS1 bags, must be normalised by the reader.
    laser = _tf(types, 0.0, "/base_link", "/laser", 0.1, 0.0, 0.0, laser_quaternion)
    messages.append((0.0, "/tf_static", "tf2_msgs/msg/TFMessage", laser))
    if map_frame and map_clock is None:
        messages.append((0.0, "/tf_static", "tf2_msgs/msg/TFMessage", _tf(types, 0.0, "/map", "/odom", 0.0, 0.0, 0.0)))
    elif map_frame:
        for t in (0.0, 1.0, 2.0):
            # A correction that moves (one published unchanged would count as static).
            messages.append((t, "/tf", "tf2_msgs/msg/TFMessage", _tf(types, t + map_clock, "/map", "/odom", 0.01 * t, 0.0, 0.0)))
    for t in (0.0, 1.0, 2.0):
        if odom:
            messages.append((t, "/odom", "nav_msgs/msg/Odometry", _odometry(types, t, t, t * math.pi / 4)))
        else:
            messages.append((t, "/tf", "tf2_msgs/msg/TFMessage", _tf(types, t, "/odom", "/base_link", t, 0.0, t * math.pi / 4)))
    for t in (-0.5, 0.5, 1.0, 1.5):
        messages.append((max(t, 0.0), "/scan", "sensor_msgs/msg/LaserScan", _scan(types, t, "laser", [1.0, 4.0, 0.01])))
    messages.sort(key=lambda m: m[0])
    if ros2:
        from rosbags.rosbag2 import Writer as Writer2

        writer = Writer2(path, version=9)
    else:
        from rosbags.rosbag1 import Writer as Writer1

        writer = Writer1(path)
    with writer:
        conns = {}
        for _, topic, msgtype, _msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
        for t, topic, msgtype, msg in messages:
            writer.write(conns[topic], int(t * 1e9) + 1, ser(msg, msgtype))
    return path


def _expected_pose(t: float) -> np.ndarray:
    yaw = t * math.pi / 4
    return np.array([t + 0.1 * math.cos(yaw), 0.1 * math.sin(yaw), yaw])


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_synthetic_bag_tf_round_trip(tmp_path: Path, ros2: bool) -> None:
    path = _write_bag(tmp_path / ("bag2" if ros2 else "bag1.bag"), ros2=ros2)
    assert detect_format(path) == ("rosbag2" if ros2 else "rosbag1")
    with pytest.warns(UserWarning, match="dropped 1 of 4 scans"):
        scans = read_scans(path)
    assert [s.time for s in scans] == pytest.approx([0.5, 1.0, 1.5])
    for s in scans:
        np.testing.assert_allclose(s.pose, _expected_pose(s.time), atol=1e-6)
        assert s.max_range == pytest.approx(4.0)
        assert s.valid().tolist() == [True, True, False]
        assert s.no_return().tolist() == [False, True, False]
        assert len(s.hits()) == 1
    # time_offset shifts the lookup, not the stamp.
    shifted = load_rosbag(path, time_offset=0.5)
    assert [s.time for s in shifted.scans] == pytest.approx([-0.5, 0.5, 1.0, 1.5])
    np.testing.assert_allclose(shifted.scans[0].pose, _expected_pose(0.0), atol=1e-6)


def test_synthetic_bag_odometry_topic(tmp_path: Path) -> None:
    path = _write_bag(tmp_path / "odom.bag", odom=True)
    result = load_rosbag(path, odom_topic="/odom")
    assert result.fixed_frame == "odom" and result.n_dropped == 1
    for s in result.scans:
        # The static base_link -> laser transform from /tf_static is still applied.
        np.testing.assert_allclose(s.pose, _expected_pose(s.time), atol=1e-6)
    with pytest.raises(InputFormatError, match="unknown Odometry topic '/wheel'"):
        load_rosbag(path, odom_topic="/wheel")


def test_synthetic_bag_unknown_topic(tmp_path: Path) -> None:
    path = _write_bag(tmp_path / "t.bag")
    with pytest.raises(InputFormatError, match=r"t\.bag: unknown topic '/base_scan'; LaserScan topics: /scan"):
        read_rosbag(path, topic="/base_scan")
    with pytest.raises(InputFormatError, match=r"is not a LaserScan topic '/tf'"):
        read_rosbag(path, topic="/tf")


def test_no_scans_in_pose_range(tmp_path: Path) -> None:
    path = _write_bag(tmp_path / "t.bag")
    with pytest.raises(InputFormatError, match="no scans left: all 4 scan stamps"):
        load_rosbag(path, time_offset=100.0)


def test_missing_bag(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match="no such file"):
        read_rosbag(tmp_path / "nothing.bag")


def test_yaw_from_quaternion() -> None:
    for yaw in (-3.0, -1.0, 0.0, 0.5, 3.1):
        assert yaw_from_quaternion(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)) == pytest.approx(yaw)


# --- bags the poses cannot come from ----------------------------------------------------------


def _write_tfless_bag(path: Path, with_odom: bool) -> Path:
    """A ROS1 bag with /scan (and optionally /odom) but no /tf at all."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    with Writer(path) as writer:
        scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        odom = writer.add_connection("/wheel_odom", "nav_msgs/msg/Odometry", typestore=store) if with_odom else None
        for k, t in enumerate((0.0, 0.5, 1.0)):
            writer.write(
                scan, k * 10 + 1, store.serialize_ros1(_scan(types, t, "laser", [1.0, 4.0, 2.0]), "sensor_msgs/msg/LaserScan")
            )
            if odom is not None:
                writer.write(odom, k * 10 + 2, store.serialize_ros1(_odometry(types, t, t, 0.0), "nav_msgs/msg/Odometry"))
    return path


def test_bag_without_tf_lists_topics(tmp_path: Path) -> None:
    path = _write_tfless_bag(tmp_path / "notf.bag", with_odom=False)
    with pytest.raises(
        InputFormatError,
        match=r"notf\.bag: no /tf or /tf_static messages to take the scan poses from; "
        r"topics in the bag: /scan \(sensor_msgs/msg/LaserScan\)$",
    ):
        read_rosbag(path)


def test_bag_without_tf_names_the_odometry_topic(tmp_path: Path) -> None:
    path = _write_tfless_bag(tmp_path / "odom.bag", with_odom=True)
    with pytest.raises(
        InputFormatError,
        match=r"use --odom-topic NAME \(odom_topic=\) with /wheel_odom; topics in the bag: .*nav_msgs/msg/Odometry",
    ):
        read_rosbag(path)
    with pytest.raises(
        InputFormatError, match=r"unknown Odometry topic '/odom'; Odometry topics: /wheel_odom; topics in the bag"
    ):
        read_rosbag(path, odom_topic="/odom")
    # With the right topic, the laser sits at the odometry's child frame.
    with pytest.warns(UserWarning, match="laser frame 'laser' not in tf"):
        scans = read_rosbag(path, odom_topic="/wheel_odom")
    assert [s.pose[0] for s in scans] == pytest.approx([0.0, 0.5, 1.0])


def test_fixed_frame_outside_the_poses_lists_frames_and_time_ranges(tmp_path: Path) -> None:
    path = _write_bag(tmp_path / "t.bag")
    with pytest.raises(InputFormatError, match=r"lie outside .*odom -> base_link: 0 \.\. 2 s.*tf frames: base_link, laser, odom"):
        load_rosbag(path, time_offset=100.0)
    with pytest.raises(InputFormatError, match=r"unknown fixed frame 'map'; known tf frames: base_link, laser, odom"):
        load_rosbag(path, fixed_frame="map")


def test_bag_that_is_not_a_regular_file(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "pipe.bag"
    os.mkfifo(fifo)
    with pytest.raises(InputFormatError, match=r"pipe\.bag: is a FIFO \(named pipe\), not a regular file"):
        read_rosbag(fifo)
    with pytest.raises(InputFormatError, match=r"directory without metadata\.yaml"):
        read_rosbag(tmp_path)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + bytes(200))
    with pytest.raises(InputFormatError, match=r"junk\.bag: cannot open as a ROS bag"):
        read_rosbag(junk)


def test_bag_whose_index_is_damaged_names_the_cause(tmp_path: Path) -> None:
    # A written ROS1 bag whose first index-data record (op 0x04) claims one entry more than its
    # 12-byte entries hold: the reader's own check fails with a bare AssertionError.
    path = _write_bag(tmp_path / "damaged.bag")
    data = bytearray(path.read_bytes())
    op = data.index(b"op=\x04")
    count = data.index(b"count=", op - 40) + len(b"count=")
    assert op - 40 < count < op + 40  # the same record's header
    (n,) = struct.unpack_from("<I", data, count)
    struct.pack_into("<I", data, count, n + 1)
    path.write_bytes(bytes(data))
    with pytest.raises(
        InputFormatError, match=r"damaged\.bag: cannot open as a ROS bag \(AssertionError in the bag reader: .*rosbag reindex"
    ):
        read_rosbag(path)


def test_bag_of_the_old_format_names_it_and_the_conversion(tmp_path: Path) -> None:
    # ROS bags before format 2.0 begin "#ROSRECORD V1.2" (a real one: CCNY's scan_tools demo).
    old = tmp_path / "old.bag"
    old.write_bytes(b"#ROSRECORD V1.2\n" + b"\x1e\x00\x00\x00" + bytes(60))
    with pytest.raises(
        InputFormatError, match=r"old\.bag: a ROS bag of the old format V1\.2 .*rosbag filter IN\.bag OUT\.bag True"
    ):
        detect_format(old)
    with pytest.raises(InputFormatError, match=r"old format V1\.2"):
        read_scans(old)


@pytest.mark.parametrize("quaternion", [(1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)], ids=["roll", "pitch"])
def test_upside_down_laser_mirrors_its_beams(tmp_path: Path, quaternion: tuple[float, ...]) -> None:
    # A laser on its back (rolled, or pitched and so facing backwards) turns clockwise seen from
    # above. Its beam at angle a in its own frame points along the world heading of its x axis
    # minus a (x axis: the robot's heading for a roll, the reverse for a pitch).
    path = _write_bag(tmp_path / "flipped.bag", laser_quaternion=quaternion)
    result = load_rosbag(path)
    assert result.n_dropped == 1
    assert any("upside down" in note for note in result.scans[0].meta["no_return"]["notes"])
    for s in result.scans:
        yaw = s.time * math.pi / 4
        laser = np.array([s.time + 0.1 * math.cos(yaw), 0.1 * math.sin(yaw)])
        heading = yaw + (math.pi if quaternion[1] else 0.0)
        # The one beam that returned: -90 degrees in the laser's frame, 1 m.
        expected = laser + np.array([math.cos(heading + math.pi / 2), math.sin(heading + math.pi / 2)])
        np.testing.assert_allclose(s.hits(), [expected], atol=1e-6)


def test_tilted_laser_is_warned_of(tmp_path: Path) -> None:
    # Pitched 20 degrees down: a planar map takes the scans as level, so the reader says so.
    half = math.radians(20.0) / 2
    path = _write_bag(tmp_path / "tilted.bag", laser_quaternion=(0.0, math.sin(half), 0.0, math.cos(half)))
    with pytest.warns(
        UserWarning, match=r"3 of 3 scans' laser planes are tilted more than 10 degrees from level in 'odom' \(up to 20\)"
    ):
        result = load_rosbag(path)
    assert not any("upside down" in note for note in result.scans[0].meta["no_return"]["notes"])
    level = load_rosbag(_write_bag(tmp_path / "level.bag"))
    assert not any("tilted" in note for note in level.scans[0].meta["no_return"]["notes"])


def test_frames_above_the_default_fixed_frame_are_named(tmp_path: Path) -> None:
    # A robot that ran SLAM while recording: tf has map -> odom; the default maps in odom, and says so.
    path = _write_bag(tmp_path / "slam.bag", map_frame=True)
    notes = load_rosbag(path).scans[0].meta["no_return"]["notes"]
    assert any("tf also places 'odom' in 'map'" in n and "--fixed-frame map" in n for n in notes)
    # Not when the fixed frame was chosen, nor when nothing is above it, nor when what is above
    # gives no pose at the scans' stamps (a SLAM stamping with the wall clock, as on the Stage bag).
    chosen = load_rosbag(path, fixed_frame="odom").scans[0].meta["no_return"]["notes"]
    plain = load_rosbag(_write_bag(tmp_path / "plain.bag")).scans[0].meta["no_return"]["notes"]
    wall = load_rosbag(_write_bag(tmp_path / "wall.bag", map_frame=True, map_clock=1e9)).scans[0]
    assert wall.meta["frames_above"] == []
    assert not any("tf also places" in n for n in chosen + plain + wall.meta["no_return"]["notes"])
    # The same at the robot's own stamps: suggested.
    same = load_rosbag(_write_bag(tmp_path / "same.bag", map_frame=True, map_clock=0.0)).scans[0]
    assert same.meta["frames_above"] == ["map"]


def test_map_command_says_where_a_corrected_frame_is(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from gpomap import cli
    from gpomap.cli.common import load_scans
    from gpomap.cli.options import resolve_library_defaults

    path = _write_bag(tmp_path / "slam.bag", map_frame=True)
    for argv, said in (
        (["map", str(path), "-o", "out"], True),
        (["map", str(path), "-o", "out", "--fixed-frame", "odom"], False),
    ):
        capsys.readouterr()
        args = cli.build_parser().parse_args(argv)
        resolve_library_defaults(args)
        with pytest.warns(UserWarning, match="dropped 1 of 4 scans"):
            scans = load_scans(args)
        assert scans[0].meta["frames_above"] == ["map"] and scans[0].meta["fixed_frame"] == "odom"
        err = capsys.readouterr().err
        assert ("poses in 'odom', which tf places in 'map': --fixed-frame map maps in that frame" in err) == said
