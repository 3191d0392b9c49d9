"""PointCloud2 from ROS 1 and ROS 2 bags: written bags with a moving robot and a tilted lidar, known points."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gpomap.errors import InputFormatError
from gpomap.io import describe, read_clouds
from tests.test_io_rosbag import _header, _tf, _write_bag


def _cloud(types, t: float, frame: str, pts: np.ndarray):
    field = types["sensor_msgs/msg/PointField"]
    # x y z float32 at offsets 0, 4, 8 and 4 bytes of padding: point_step 16.
    fields = [field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    data = np.zeros((len(pts), 4), dtype="<f4")
    data[:, :3] = pts
    return types["sensor_msgs/msg/PointCloud2"](
        header=_header(types, t, frame),
        height=1,
        width=len(pts),
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(pts),
        data=data.view(np.uint8).reshape(-1),
        is_dense=False,
    )


def _tilted(types, t: float):
    """base_link -> lidar: 1 m up, pitched down 90 degrees about y (the lidar's x axis points to -z)."""
    q = types["geometry_msgs/msg/Quaternion"](x=0.0, y=math.sin(math.pi / 4), z=0.0, w=math.cos(math.pi / 4))
    tr = types["geometry_msgs/msg/Transform"](translation=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=1.0), rotation=q)
    ts = types["geometry_msgs/msg/TransformStamped"](header=_header(types, t, "base_link"), child_frame_id="lidar", transform=tr)
    return types["tf2_msgs/msg/TFMessage"](transforms=[ts])


def _write(path: Path, ros2: bool) -> Path:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    types = store.types
    ser = store.serialize_cdr if ros2 else store.serialize_ros1
    pts = np.array([[0.5, 0.0, 0.0], [1.0, 0.0, 2.0], [np.nan, np.nan, np.nan]])
    msgs = [(0.0, "/tf_static", "tf2_msgs/msg/TFMessage", _tilted(types, 0.0))]
    msgs += [
        (t, "/tf", "tf2_msgs/msg/TFMessage", _tf(types, t, "odom", "base_link", 2.0 * t, 0.0, t * math.pi / 2))
        for t in (0.0, 1.0)
    ]
    msgs += [(t, "/points", "sensor_msgs/msg/PointCloud2", _cloud(types, t, "lidar", pts)) for t in (0.5, 2.0)]
    msgs.sort(key=lambda m: m[0])
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2

    writer: Writer1 | Writer2 = Writer2(path, version=9) if ros2 else Writer1(path)
    with writer:
        conns = {}
        for _, topic, msgtype, _m in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
        for t, topic, msgtype, m in msgs:
            writer.write(conns[topic], int(t * 1e9) + 1, ser(m, msgtype))
    return path


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_clouds_in_the_odom_frame(tmp_path, ros2):
    path = _write(tmp_path / ("b2" if ros2 else "b1.bag"), ros2)
    with pytest.warns(UserWarning, match="dropped 1 of 2 clouds"):  # t = 2 s is after the last pose
        (cloud,) = read_clouds(path)
    # At t = 0.5 s the robot is at x = 1 m, turned 45 degrees; the lidar 1 m above, looking down.
    np.testing.assert_allclose(cloud.origin, [1.0, 0.0, 1.0], atol=1e-9)
    # lidar (0.5, 0, 0) -> base (0, 0, 1 - 0.5); lidar (1, 0, 2) -> base (2, 0, 0); then the 45-degree turn.
    c = math.sqrt(0.5)
    np.testing.assert_allclose(cloud.points[:2], [[1.0, 0.0, 0.5], [1.0 + 2 * c, 2 * c, 0.0]], atol=1e-6)
    assert cloud.valid().tolist() == [True, True, False]
    with pytest.warns(UserWarning, match="dropped 1 of 2 clouds"):
        assert describe(path)["n_scans"] == 1


def test_bag_without_clouds_lists_topics(tmp_path):
    path = _write_bag(tmp_path / "scan.bag")
    with pytest.raises(InputFormatError, match=r"no PointCloud2 topic; topics in the bag: .*/scan \(sensor_msgs/msg/LaserScan\)"):
        read_clouds(path)
