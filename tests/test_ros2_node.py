"""The ROS 2 node for real: ``python -m gpomap.ros2``, a player and a client, three rclpy processes on loopback.

The player replays the first 20 s of the Stage arena bag (its first 200 scans): its ``/base_scan``
LaserScan messages and, as ``nav_msgs/Odometry``, its tf edge odom -> base_footprint (the laser
sits 0.225 m ahead of it: the node's ``sensor_pose``), the odometry ending at the last scan's stamp
as the bag's does. The client records every message on ``/map``, ``/map_probability``,
``/map_variance`` and ``/gpomap/status``; once the node has used every scan it calls
``/gpomap/save_map``, ``/gpomap/render`` (five requests) and ``/gpomap/query``, and writes what it
got as JSON. The test checks the node used the scans the batch reader uses; the messages are well
formed; the saved set is the published map, its map file answers the queries as the node did and
gives the render at a finer resolution; the published map, that render and the queried points score
against the arena's true floor plan at least as the batch map of the same scans (``gpomap map``)
does, minus 0.01 AUC; a bad render request and one over the memory limit are refused with
LoadMap's codes.

Each run uses its own ROS_DOMAIN_ID and discovery on localhost only. Skipped, with the reason,
where rclpy (``pip install "gpomap[ros2]"``) or the shared bag is missing.
"""

from __future__ import annotations

import base64
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ARENA = ROOT.parent / "shared" / "data" / "stage-arena"
BAG = ARENA / "robot1.bag"
#: LaserScan messages replayed: the bag's first 200 of 433 on /base_scan (20 s of its 43 s).
N_MESSAGES = 200
RESOLUTION = 0.05
#: base_footprint -> base_link -> base_laser_link in the bag's tf: the laser 0.225 m ahead, level.
SENSOR_POSE = [0.225, 0.0, 0.0]
FINE = 0.025


def _why_skip() -> str | None:
    if not BAG.exists():
        return f"shared Stage arena bag not present ({BAG})"
    missing = [m for m in ("rclpy", "nav_msgs", "sensor_msgs", "std_srvs") if importlib.util.find_spec(m) is None]
    if missing:
        return f"ROS 2 Python packages not importable ({', '.join(missing)}): pip install -e '.[ros2]'"
    return None


_SKIP = _why_skip()
needs_ros2 = pytest.mark.skipif(_SKIP is not None, reason=_SKIP or "")
needs_bag = pytest.mark.skipif(not BAG.exists(), reason=f"shared Stage arena bag not present ({BAG})")

# Replays the bag's first N scans and the odometry up to the last one's stamp at 10x once the client
# is ready (the file it names exists) and the node listens; exits when all are acknowledged.
PLAYER = r"""
import sys, time
import rclpy
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
from pathlib import Path
from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan

bag, n_scans, ready, rate = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]), 10.0
events = []
with AnyReader([bag]) as reader:
    for c, t, raw in reader.messages(connections=[c for c in reader.connections if c.topic in ("/base_scan", "/tf")]):
        m = reader.deserialize(raw, c.msgtype)
        if c.topic == "/base_scan":
            msg = LaserScan(angle_min=float(m.angle_min), angle_max=float(m.angle_max), angle_increment=float(m.angle_increment),
                            time_increment=float(m.time_increment), scan_time=float(m.scan_time), range_min=float(m.range_min),
                            range_max=float(m.range_max), ranges=[float(r) for r in m.ranges])
            msg.header.stamp = Time(sec=m.header.stamp.sec, nanosec=m.header.stamp.nanosec)
            msg.header.frame_id = m.header.frame_id.lstrip("/")
            events.append((t, "scan", msg, (m.header.stamp.sec, m.header.stamp.nanosec)))
            continue
        for tr in m.transforms:
            if (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")) != ("odom", "base_footprint"):
                continue
            msg = Odometry(child_frame_id="base_footprint")
            msg.header.stamp = Time(sec=tr.header.stamp.sec, nanosec=tr.header.stamp.nanosec)
            msg.header.frame_id = "odom"
            p, q = tr.transform.translation, tr.transform.rotation
            msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = p.x, p.y, p.z
            o = msg.pose.pose.orientation
            o.x, o.y, o.z, o.w = q.x, q.y, q.z, q.w
            events.append((t, "odom", msg, (tr.header.stamp.sec, tr.header.stamp.nanosec)))

# The stretch ends as the bag does: no odometry after the last scan's stamp, so that scan (its pose
# looked up 0.1 s later) has none and the node drops it.
end = [stamp for _, kind, _, stamp in events if kind == "scan"][n_scans - 1]
events = [e for e in events if e[3] <= end]
rclpy.init()
node = rclpy.create_node("gpomap_test_player")
qos = QoSProfile(depth=5000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
pubs = {"scan": node.create_publisher(LaserScan, "/base_scan", qos), "odom": node.create_publisher(Odometry, "/odom", qos)}
deadline = time.monotonic() + 90
while not ready.exists():
    assert time.monotonic() < deadline, "the client never got ready"
    time.sleep(0.05)
deadline = time.monotonic() + 60
while any(p.get_subscription_count() == 0 for p in pubs.values()):
    assert time.monotonic() < deadline, "the node never subscribed"
    time.sleep(0.05)
start, t0 = time.monotonic(), events[0][0]
for t, kind, msg, _ in events:
    time.sleep(max(0.0, start + (t - t0) * 1e-9 / rate - time.monotonic()))
    pubs[kind].publish(msg)
for p in pubs.values():
    assert p.wait_for_all_acked(Duration(seconds=60)), "messages not acknowledged"
print(sum(e[1] == "scan" for e in events), "scans", sum(e[1] == "odom" for e in events), "odometry")
node.destroy_node()
rclpy.shutdown()
"""

# Records the node's grids and status; when every scan is used, calls the services and writes it all as JSON.
CLIENT = r"""
import base64, json, sys, time
import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from nav_msgs.msg import OccupancyGrid
from nav_msgs.srv import LoadMap
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import String
from std_srvs.srv import Trigger

out_path, ready_path, n_messages = sys.argv[1], sys.argv[2], int(sys.argv[3])
requests, points = json.loads(sys.argv[4]), np.load(sys.argv[5])
rclpy.init()
node = rclpy.create_node("gpomap_test_client")
latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
grids, statuses, answers = [], [], {}

def grid(m, topic=None):
    p, o = m.info.origin.position, m.info.origin.orientation
    return {"topic": topic, "frame_id": m.header.frame_id, "stamp": m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
            "load_time": m.info.map_load_time.sec + 1e-9 * m.info.map_load_time.nanosec, "resolution": m.info.resolution,
            "width": m.info.width, "height": m.info.height, "origin": [p.x, p.y, p.z], "orientation": [o.x, o.y, o.z, o.w],
            "data": base64.b64encode(bytes(m.data)).decode()}

subs = [node.create_subscription(OccupancyGrid, t, (lambda t: lambda m: grids.append(grid(m, t)))(t), latched)
        for t in ("/map", "/map_probability", "/map_variance")]
subs.append(node.create_subscription(String, "/gpomap/status", lambda m: statuses.append(json.loads(m.data)), latched))

def on_answer(m):
    answers[m.header.stamp.sec] = {"frame_id": m.header.frame_id, "fields": [(f.name, f.offset, f.datatype) for f in m.fields],
                                   "point_step": m.point_step, "width": m.width, "data": base64.b64encode(bytes(m.data)).decode()}

subs.append(node.create_subscription(PointCloud2, "/gpomap/query_result", on_answer, 10))
query = node.create_publisher(PointCloud2, "/gpomap/query", 10)
deadline = time.monotonic() + 60
while any(s.get_publisher_count() == 0 for s in subs) or query.get_subscription_count() == 0:
    assert time.monotonic() < deadline, "the node's topics never matched"
    rclpy.spin_once(node, timeout_sec=0.1)
open(ready_path, "w").close()

def settled():
    if not statuses or statuses[-1]["n_received"] != n_messages or statuses[-1]["n_waiting"]:
        return False
    final = statuses[-1]["n_used"]
    return any("width" in s and s["n_used"] == final for s in statuses)

deadline = time.monotonic() + 240
while not settled():
    assert time.monotonic() < deadline, f"no final map; last status {statuses[-1:]}"
    rclpy.spin_once(node, timeout_sec=0.1)
# The last map's grids may trail its status by a few callbacks: wait for those of its stamp.
last = statuses[-1]["stamp"]
deadline = time.monotonic() + 60
while not all(any(g["topic"] == t and abs(g["stamp"] - last) < 1e-6 for g in grids) for t in ("/map", "/map_probability", "/map_variance")):
    assert time.monotonic() < deadline, f"the grids of the last map (stamp {last}) never came"
    rclpy.spin_once(node, timeout_sec=0.1)

def call(client, request):
    assert client.wait_for_service(timeout_sec=30), client.srv_name
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=120)
    assert future.done(), f"{client.srv_name} did not answer"
    return future.result()

save = call(node.create_client(Trigger, "/gpomap/save_map"), Trigger.Request())
render = node.create_client(LoadMap, "/gpomap/render")
renders = []
for text in requests:
    r = call(render, LoadMap.Request(map_url=text))
    renders.append({"request": text, "result": r.result, "map": grid(r.map) if r.result == 0 else None})

def ask(stamp, pts):
    m = PointCloud2(height=1, width=len(pts), is_bigendian=False, point_step=12, row_step=12 * len(pts), is_dense=True)
    m.header.stamp.sec, m.header.frame_id = stamp, "odom"
    m.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    m.data = np.column_stack([pts, np.zeros(len(pts))]).astype("<f4").tobytes()
    query.publish(m)
    deadline = time.monotonic() + 60
    while stamp not in answers:
        assert time.monotonic() < deadline, "no query result"
        rclpy.spin_once(node, timeout_sec=0.1)

ask(1, points)
ask(2, np.array([[100.0, 100.0], [-100.0, 50.0]]))
with open(out_path, "w") as f:
    json.dump({"grids": grids, "statuses": statuses, "save": {"success": save.success, "message": save.message},
               "renders": renders, "answers": answers}, f)
node.destroy_node()
rclpy.shutdown()
"""


# --------------------------------------------------------------------------- processes
def _stop(proc: subprocess.Popen) -> None:
    """SIGINT to the process group it leads (rclpy shuts down cleanly on it), then SIGKILL."""
    if proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGINT, 15), (signal.SIGKILL, 10)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


@pytest.fixture
def ros2_env(tmp_path: Path) -> dict[str, str]:
    """A DDS domain of this run's own, discovery on localhost only, logs in tmp_path."""
    return dict(
        os.environ,
        ROS_DOMAIN_ID=str(10 + os.getpid() % 90),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
        ROS_HOME=str(tmp_path / "ros"),
        ROS_LOG_DIR=str(tmp_path / "ros" / "log"),
        OMP_NUM_THREADS="1",
        PYTHONUNBUFFERED="1",
    )


@pytest.fixture
def start(tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen]]:
    """Start processes in their own groups, logging to tmp_path; all are stopped at the end."""
    started: list[subprocess.Popen] = []

    def run(name: str, args: list[str], env: dict[str, str]) -> subprocess.Popen:
        log = open(tmp_path / f"{name}.log", "w")  # noqa: SIM115 - closed when the process is stopped
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path, start_new_session=True)
        proc.log = log  # type: ignore[attr-defined]
        started.append(proc)
        return proc

    yield run
    for proc in reversed(started):
        _stop(proc)
        proc.log.close()  # type: ignore[attr-defined]


def _wait(what: str, condition: Callable[[], Any], timeout: float, procs: tuple[subprocess.Popen, ...], logs: Path) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        for p in procs:
            if p.poll() is not None:
                log = "".join(
                    (logs / f"{n}.log").read_text()[-3000:] for n in ("node", "client", "player") if (logs / f"{n}.log").exists()
                )
                raise AssertionError(f"{p.args[:3]} exited with {p.returncode} while waiting for {what}:\n{log}")
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _layer(m: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(base64.b64decode(m["data"]), dtype=np.int8).reshape(m["height"], m["width"])


def _stage_truth() -> Any:
    from PIL import Image

    from gpomap.evaluation import Truth

    img = np.asarray(Image.open(ARENA / "mrl_arena.pgm"))
    # The data README: Stage stretches the 406 x 460 bitmap to 4.06 m x 4.55 m centred at (1, 1).
    return Truth.from_plan(img < 128, (-1.03, -1.275), (0.0100, 0.009891), RESOLUTION)


# --------------------------------------------------------------------------- the test
@needs_ros2
@pytest.mark.slow
def test_ros2_node_maps_the_stage_arena_and_answers_its_services(ros2_env, start, tmp_path):
    from gpomap.evaluation import lookup, make_model, score_truth, written_grid
    from gpomap.grid import GridSpec
    from gpomap.io.npz import load_map
    from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
    from gpomap.io.rosmap import read_rosmap

    truth = _stage_truth()
    # The fine render's cells centred on the truth's (half a fine cell in from its edges): each
    # truth cell is scored at the fine cell at its centre, not at a corner four cells share.
    xmin, xmax, ymin, ymax = (e + d for e, d in zip(truth.grid.extent, (FINE / 2, -FINE / 2) * 2))
    points = truth.grid.centres()
    np.save(tmp_path / "points.npy", points)
    requests = [
        "",  # the whole map at the node's resolution: the published map
        f"gpomap:render?resolution={FINE}&extent={xmin},{xmax},{ymin},{ymax}&layer=probability",
        "resolution=0.05 layer=trinary",
        "resolution=0.05 extent=0,1,1,0",  # xmax < xmin
        "resolution=0.00001 extent=-1000,1000,-1000,1000",  # 4e16 cells: over any memory limit
    ]
    saved = tmp_path / "saved"
    node = start(
        "node",
        [
            sys.executable,
            "-m",
            "gpomap.ros2",
            "--ros-args",
            "-r",
            "scan:=/base_scan",
            "-p",
            f"time_offset:={STAGE_TIME_OFFSET}",
            "-p",
            f"resolution:={RESOLUTION}",
            "-p",
            "publish_rate:=2.0",
            "-p",
            f"sensor_pose:={json.dumps(SENSOR_POSE)}",
            "-p",
            "sensor_qos:=reliable",
            "-p",
            "pose_wait:=3.0",  # a loaded machine may run the odometry callback late; the last scan waits this long
            "-p",
            f"save_directory:={saved}",
            "-p",
            "save_on_shutdown:=true",
        ],
        ros2_env,
    )
    out, ready = tmp_path / "client.json", tmp_path / "client.ready"
    client_args = [str(out), str(ready), str(N_MESSAGES), json.dumps(requests), str(tmp_path / "points.npy")]
    (tmp_path / "client.py").write_text(CLIENT)
    client = start("client", [sys.executable, str(tmp_path / "client.py"), *client_args], ros2_env)
    # The player reads the bag and finds the node while the client starts; it plays once the client is ready.
    (tmp_path / "player.py").write_text(PLAYER)
    player = start("player", [sys.executable, str(tmp_path / "player.py"), str(BAG), str(N_MESSAGES), str(ready)], ros2_env)
    _wait("the client's subscriptions", ready.exists, 90, (node, client, player), tmp_path)
    assert player.wait(300) == 0, (tmp_path / "player.log").read_text()[-3000:]
    _wait("the client's report", lambda: client.poll() is not None, 300, (node,), tmp_path)
    assert client.returncode == 0, (tmp_path / "client.log").read_text()[-3000:]
    report = json.loads(out.read_text())

    # The scans: every one the batch reader gives of the stretch, and the last (no later pose) dropped after its wait.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the batch reader warns about the bag's last scan
        scans = read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)[: N_MESSAGES - 1]
    status = report["statuses"][-1]
    assert status["n_used"] == len(scans) == N_MESSAGES - 1
    assert status["n_dropped_no_pose"] == 1 and status["n_rejected"] == 0
    assert status["n_odometry"] > 0 and status["n_odometry_rejected"] == 0
    assert status["latency_ms"]["median"] > 0

    # Every grid message well formed; the three layers go out together, in time order.
    grids = ("/map", "/map_probability", "/map_variance")
    by_topic = {t: [m for m in report["grids"] if m["topic"] == t] for t in grids}
    n = len(by_topic["/map"])
    assert n >= 2 and all(len(v) == n for v in by_topic.values())
    for t, messages in by_topic.items():
        for m in messages:
            assert m["frame_id"] == "odom" and m["resolution"] == pytest.approx(RESOLUTION, rel=1e-6)
            assert m["origin"][2] == 0.0 and m["orientation"] == [0.0, 0.0, 0.0, 1.0] and m["load_time"] == m["stamp"]
            values = set(np.unique(_layer(m)).tolist())
            assert values <= {-1, 0, 100} if t == "/map" else (min(values) >= 0 and max(values) <= 100)
    for i in range(n):
        assert len({(by_topic[t][i]["stamp"], by_topic[t][i]["width"], by_topic[t][i]["height"]) for t in grids}) == 1
    stamps = [m["stamp"] for m in by_topic["/map"]]
    assert stamps == sorted(stamps) and stamps[-1] == pytest.approx(scans[-1].time, abs=1e-6)
    final = by_topic["/map_probability"][-1]
    grid = GridSpec(tuple(final["origin"][:2]), RESOLUTION, (final["height"], final["width"]))
    published = _layer(final) / 100.0
    trinary = _layer(by_topic["/map"][-1])
    assert (trinary == 0).any() and (trinary == 100).any()
    assert (_layer(by_topic["/map_variance"][-1]) > 0).any()

    # ~/save_map wrote the published map, and the fitted map beside it.
    assert report["save"]["success"], report["save"]["message"]
    assert {"map.gpom", "map.yaml", "map.pgm", "map.npz", "map.png"} <= {p.name for p in saved.iterdir()}
    saved_map = load_map(saved / "map.npz")
    assert saved_map.grid.shape == grid.shape and np.allclose(saved_map.grid.origin, grid.origin)
    assert np.abs(saved_map.probability - published).max() <= 0.005 + 1e-9
    rosmap = read_rosmap(saved / "map.yaml")
    assert np.array_equal(np.where(rosmap.occupied, 100, np.where(rosmap.free, 0, -1)), trinary)

    # ~/render: the empty request is the published map; a bad region and a huge grid are refused.
    whole, fine, tri, bad, huge = report["renders"]
    assert whole["result"] == 0 and np.array_equal(_layer(whole["map"]), _layer(final))
    assert whole["map"]["origin"] == final["origin"] and whole["map"]["stamp"] == final["stamp"]
    assert tri["result"] == 0 and np.array_equal(_layer(tri["map"]), trinary)
    assert bad["result"] == 3 and huge["result"] == 255
    assert fine["result"] == 0 and fine["map"]["resolution"] == pytest.approx(FINE, rel=1e-6)
    fine_grid = GridSpec(tuple(fine["map"]["origin"][:2]), FINE, (fine["map"]["height"], fine["map"]["width"]))
    assert fine_grid.shape == (round((ymax - ymin) / FINE), round((xmax - xmin) / FINE))
    assert np.allclose(fine_grid.origin, (xmin, ymin))

    # ~/query: one answer per point, under the request's header; outside the map the prior.
    answer = report["answers"]["1"]
    assert answer["frame_id"] == "odom" and answer["width"] == len(points) and answer["point_step"] == 40
    assert [f[0] for f in answer["fields"]] == ["x", "y", "probability", "variance", "ternary"]
    table = np.frombuffer(base64.b64decode(answer["data"]), dtype="<f8").reshape(-1, 5)
    assert np.allclose(table[:, :2], points.astype(np.float32), atol=0)
    assert ((table[:, 2] >= 0) & (table[:, 2] <= 1)).all() and (table[:, 3] > 0).all()
    far = np.frombuffer(base64.b64decode(report["answers"]["2"]["data"]), dtype="<f8").reshape(-1, 5)
    assert np.array_equal(far[:, 2], [0.5, 0.5]) and far[0, 3] == far[1, 3] >= table[:, 3].max()
    assert np.array_equal(far[:, 4], [-1, -1])  # the prior: unknown

    # The saved map file is the node's model: it answers the queries as the node did, to the bit.
    from gpomap.io.mapfile import load_fitted_map

    loaded = load_fitted_map(saved / "map.gpom")
    probability, variance = loaded.predict_proba(table[:, :2], return_var=True)
    assert np.array_equal(probability, table[:, 2]) and np.array_equal(variance, table[:, 3])
    assert np.array_equal(loaded.predict_ternary(table[:, :2]), table[:, 4])
    # ... and the fine render is its map on that grid, in percent.
    fine_map = loaded.grid(FINE, (xmin, xmax, ymin, ymax))
    assert fine_map.grid.shape == fine_grid.shape and np.allclose(fine_map.grid.origin, fine_grid.origin)
    assert np.array_equal(_layer(fine["map"]), np.rint(100 * fine_map.probability).astype(np.int8))

    # SIGINT: the node saves the map once more and exits cleanly.
    (saved / "map.npz").unlink()
    node.send_signal(signal.SIGINT)
    assert node.wait(60) == 0, (tmp_path / "node.log").read_text()[-3000:]
    assert "gpomap-ros2: saved" in (tmp_path / "node.log").read_text()
    assert np.array_equal(load_map(saved / "map.npz").probability, saved_map.probability)

    # Against the true floor plan, each at least the batch map's AUC (gpomap map, same scans) minus
    # 0.01: the published map (as saved), the fine render (unrounded: the 1 % steps of an
    # OccupancyGrid tie the many fine cells near 0 and 1), and the queried points (the batch
    # model's own points).
    batch = make_model("msk", n_workers=1).fit(scans)
    scores = {
        "published": score_truth(truth, lookup(saved_map, points))["auc"],
        "render": score_truth(truth, lookup(fine_map, points))["auc"],
        "query": score_truth(truth, table[:, 2])["auc"],
    }
    reference = {
        "published": score_truth(truth, lookup(written_grid(batch, RESOLUTION), points))["auc"],
        "render": score_truth(truth, lookup(batch.grid(FINE, (xmin, xmax, ymin, ymax)), points))["auc"],
        "query": score_truth(truth, batch.predict_proba(table[:, :2]))["auc"],
    }
    print(
        "truth AUC, node / batch: " + ", ".join(f"{k} {scores[k]:.4f} / {reference[k]:.4f}" for k in scores) + f"; {n} publishes"
    )
    for k in scores:
        assert scores[k] >= reference[k] - 0.01, k


# --------------------------------------------------------------------------- without rclpy
def _bag_odometry() -> list[tuple[float, tuple[float, float, float]]]:
    """The bag's tf edge odom -> base_footprint as (stamp, (x, y, yaw)), in bag order."""
    from rosbags.highlevel import AnyReader

    from gpomap.ros.messages import pose_from_transform, stamp_seconds

    out = []
    with AnyReader([BAG]) as reader:
        for c, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic == "/tf"]):
            for tr in reader.deserialize(raw, c.msgtype).transforms:
                if (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")) == ("odom", "base_footprint"):
                    out.append(
                        (stamp_seconds(tr.header.stamp), pose_from_transform(tr.transform.translation, tr.transform.rotation))
                    )
    return out


@needs_bag
def test_pose_buffer_gives_the_bag_readers_laser_poses():
    """Odometry (the tf edge odom -> base_footprint) plus sensor_pose: the poses `gpomap map` takes from the whole tf tree."""
    from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
    from gpomap.ros2.poses import PoseBuffer

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scans = read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)
    buffer = PoseBuffer(tuple(SENSOR_POSE))
    for t, pose in _bag_odometry():
        buffer.add(t, *pose)
    got = np.array([buffer.lookup("base_laser_link", s.time + STAGE_TIME_OFFSET)[:3] for s in scans])
    want = np.array([s.pose for s in scans])
    assert np.abs(got[:, :2] - want[:, :2]).max() < 1e-9
    assert np.abs(np.angle(np.exp(1j * (got[:, 2] - want[:, 2])))).max() < 1e-9
    # The bag's last scan: no odometry after its stamp, so no pose (the node drops it after pose_wait).
    assert buffer.lookup("base_laser_link", scans[-1].time + 0.2) is None


def test_pose_buffer_interpolates_along_the_shorter_arc_and_forgets_old_poses():
    from gpomap.ros2.poses import PoseBuffer

    buffer = PoseBuffer((1.0, 0.0, np.pi / 2), upside_down=True, cache_seconds=10.0)
    assert buffer.lookup("laser", 0.0) is None
    buffer.add(1.0, 0.0, 0.0, 3.0)
    buffer.add(3.0, 2.0, 4.0, -3.0)  # 0.283 rad on from 3.0 through pi, not 6 rad back
    x, y, yaw, flipped = buffer.lookup("laser", 2.0)
    # Robot at (1, 2) heading pi; the laser 1 m ahead of it, turned a quarter left.
    assert (x, y) == pytest.approx((0.0, 2.0)) and yaw == pytest.approx(-np.pi / 2) and flipped
    assert buffer.robot_pose(1.5) == pytest.approx((0.5, 1.0, 3.0 + (2 * np.pi - 6.0) / 4))
    assert buffer.lookup("laser", 0.5) is None and buffer.lookup("laser", 3.5) is None
    buffer.add(2.0, 9.0, 9.0, 0.0)  # out of order: filed by its stamp
    assert buffer.robot_pose(2.0) == pytest.approx((9.0, 9.0, 0.0))
    buffer.add(12.5, 0.0, 0.0, 0.0)  # 10 s of cache: the poses at 1 and 2 s are forgotten
    assert len(buffer) == 2 and buffer.robot_pose(2.5) is None and buffer.robot_pose(3.0) is not None
    with pytest.raises(ValueError, match="sensor_pose"):
        PoseBuffer((0.0, float("nan"), 0.0))


def test_render_requests_are_read_or_refused_naming_the_item():
    from gpomap.errors import InputFormatError
    from gpomap.ros2.queries import RenderRequest, parse_render_request

    assert parse_render_request("") == RenderRequest()
    assert parse_render_request("gpomap:render?resolution=0.01&extent=0,2,-1,1.5&layer=Trinary") == RenderRequest(
        0.01, (0.0, 2.0, -1.0, 1.5), "trinary"
    )
    assert parse_render_request(" resolution=0.1 ; layer=variance ") == RenderRequest(0.1, None, "variance")
    for text, what in (
        ("resolution=0", "resolution must be > 0"),
        ("resolution=abc", "resolution must be a finite number"),
        ("resolution=nan", "resolution must be a finite number"),
        ("extent=0,1,2", "extent must be xmin,xmax,ymin,ymax"),
        ("extent=1,0,0,1", "xmin < xmax"),
        ("layer=heat", "layer must be one of probability, trinary, variance"),
        ("size=3", "unknown key 'size'"),
        ("resolution", "is not key=value"),
    ):
        with pytest.raises(InputFormatError, match=what):
            parse_render_request(text)


def _cloud(fields: list[tuple[str, int, int]], step: int, rows: np.ndarray, big: bool = False, h: int = 1) -> Any:
    from types import SimpleNamespace

    data = rows.tobytes()
    w = len(rows) // h
    return SimpleNamespace(
        fields=[SimpleNamespace(name=n, offset=o, datatype=d) for n, o, d in fields],
        is_bigendian=big,
        point_step=step,
        row_step=step * w,
        height=h,
        width=w,
        data=data,
    )


def test_query_clouds_are_read_whatever_their_layout_and_answered_as_a_table():
    from gpomap.errors import InputFormatError
    from gpomap.ros2.queries import RESULT_FIELDS, RESULT_POINT_STEP, points_from_cloud, result_cloud_data

    xy = np.array([[0.5, -1.25], [3.0, 2.0], [-7.5, 0.125], [1.0, 1.0]])
    # x, y, z FLOAT32 and an intensity, as a laser driver's cloud; two rows of two points.
    table = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4")])
    table["x"], table["y"], table["z"] = xy[:, 0], xy[:, 1], 9.0
    cloud = _cloud([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)], 16, table, h=2)
    assert np.array_equal(points_from_cloud(cloud), xy)
    # y before x, FLOAT64, big-endian.
    table64 = np.zeros(4, dtype=[("y", ">f8"), ("x", ">f8")])
    table64["x"], table64["y"] = xy[:, 0], xy[:, 1]
    assert np.array_equal(points_from_cloud(_cloud([("y", 0, 8), ("x", 8, 8)], 16, table64, big=True)), xy)
    assert points_from_cloud(_cloud([("x", 0, 7), ("y", 4, 7)], 8, np.zeros(0, "<f4"))).shape == (0, 2)
    with pytest.raises(InputFormatError, match="no field 'y'"):
        points_from_cloud(_cloud([("x", 0, 7)], 4, table["x"]))
    with pytest.raises(InputFormatError, match="datatype 2"):
        points_from_cloud(_cloud([("x", 0, 2), ("y", 4, 7)], 8, table[["x", "y"]]))
    short = _cloud([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)], 16, table)
    short.data = short.data[:-1]
    with pytest.raises(InputFormatError, match="63 data bytes"):
        points_from_cloud(short)
    data = result_cloud_data(
        xy, np.array([0.1, 0.2, 0.5, 0.9]), np.array([1.0, 0.5, 0.25, 0.125]), np.array([0, 0, -1, 1], dtype=np.int8)
    )
    fields = [f for f, _ in RESULT_FIELDS]
    assert len(data) == 4 * RESULT_POINT_STEP and fields == ["x", "y", "probability", "variance", "ternary"]
    back = np.frombuffer(data, "<f8").reshape(4, 5)
    assert np.array_equal(back[:, :2], xy) and np.array_equal(back[:, 3], [1.0, 0.5, 0.25, 0.125])
    assert np.array_equal(back[:, 4], [0, 0, -1, 1])


def test_a_render_over_the_memory_limit_is_refused_before_any_prediction():
    from types import SimpleNamespace

    from gpomap.errors import NotFittedError
    from gpomap.resources import MemoryLimitError
    from gpomap.ros.live import LiveMap

    def no_prediction(*args: Any) -> Any:
        raise AssertionError("predicted")

    mapper = SimpleNamespace(ready_=True, n_scans_=50, grid=no_prediction, predict_proba=no_prediction)
    live = LiveMap(mapper, 0.05)
    with pytest.raises(
        MemoryLimitError,
        match=r"a 20000 x 10000 grid .* at resolution 0.001 m would need about .* limit of 1.0 GB \(the limit given\)",
    ):
        live.render(0.001, (0.0, 20.0, 0.0, 10.0), memory_limit=10**9)
    with pytest.raises(ValueError, match="resolution must be a positive number"):
        live.render(0.0)
    with pytest.raises(NotFittedError, match="3 scans seen"):
        LiveMap(SimpleNamespace(ready_=False, n_scans_=3), 0.05).query(np.zeros((1, 2)))


def test_ros2_settings_are_the_ros1_nodes_checks_plus_its_own():
    from gpomap.errors import GpomapError
    from gpomap.ros2.node import PARAMETERS, ros2_settings

    d = ros2_settings(lambda name, default: default)
    assert d.node.resolution == 0.05 and d.node.fixed_frame == "odom" and d.odom_topic == "odom"
    assert d.sensor_pose == (0.0, 0.0, 0.0) and not d.sensor_upside_down and d.sensor_qos == "best_effort"
    given = {"resolution": 1, "extent": [0.0, 4.0, -1.0, 1.0], "sensor_pose": [0.2, 0, 0.5], "sensor_qos": "RELIABLE"}
    s = ros2_settings(lambda name, default: given.get(name, default), model={"kernel": "se"})
    assert s.node.resolution == 1.0 and s.node.extent == (0.0, 4.0, -1.0, 1.0) and s.node.model == {"kernel": "se"}
    assert s.sensor_pose == (0.2, 0.0, 0.5) and s.sensor_qos == "reliable"
    for name, value, what in (
        ("resolution", -1, "parameter resolution must be a finite number > 0"),
        ("warmup_scans", 0.5, "parameter warmup_scans must be an integer"),
        ("sensor_pose", [1.0, 2.0], "parameter sensor_pose must be"),
        ("sensor_pose", [1.0, "a", 2.0], "parameter sensor_pose must be three finite numbers"),
        ("sensor_upside_down", "yes", "parameter sensor_upside_down must be true or false"),
        ("sensor_qos", "fast", "parameter sensor_qos must be best_effort or reliable"),
    ):
        with pytest.raises(GpomapError, match=what):
            ros2_settings(lambda n, default, name=name, value=value: value if n == name else default)
    assert set(PARAMETERS) >= {"scan_topic", "publish_rate", "save_on_shutdown", "odom_topic", "sensor_pose"}


def _quaternion_z(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a turn by `yaw` about z."""
    return (0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2)))


def test_a_pointcloud2_becomes_a_cloud_at_the_interpolated_6dof_sensor_pose():
    from types import SimpleNamespace

    from gpomap.errors import InputFormatError
    from gpomap.ros.messages import cloud_from_pointcloud2
    from gpomap.ros2.poses import PoseBuffer3D

    # Robot at x 0 then 2 (t = 0, 2 s), z 0.5, facing +y; the sensor 0.2 m ahead and 0.3 m up,
    # pitched 90 degrees (its x axis points down, its z axis forward).
    poses = PoseBuffer3D((0.2, 0.0, 0.3, 0.0, np.pi / 2, 0.0))
    poses.add(0.0, (0.0, 2.0, 0.5), _quaternion_z(np.pi / 2))
    poses.add(2.0, (2.0, 2.0, 0.5), _quaternion_z(np.pi / 2))
    assert poses.lookup("lidar", 2.5) is None
    pose = poses.lookup("lidar", 1.0)
    assert pose is not None
    # x, y, z FLOAT32 and an intensity: 16 bytes a point; a NaN point and one 5 m away.
    rows = np.array([[1, 0, 0, 7], [0, 1, 0, 7], [0, 0, 2, 7], [np.nan, 0, 0, 7], [0, 0, 5, 7]], dtype="<f4")
    msg = _cloud([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)], 16, rows)
    msg.header = SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=0), frame_id="lidar")
    cloud = cloud_from_pointcloud2(msg, pose, max_range=3.0, source="/points")
    # By hand: sensor (a, b, c) -> mount (c + 0.2, b, -a + 0.3) -> robot turned +90 deg at (1, 2, 0.5).
    np.testing.assert_allclose(cloud.origin, [1.0, 2.2, 0.8], atol=1e-12)
    np.testing.assert_allclose(cloud.points[[0, 1, 2]], [[1.0, 2.2, -0.2], [0.0, 2.2, 0.8], [1.0, 4.2, 0.8]], atol=1e-6)
    assert np.isnan(cloud.points[3]).any() and not cloud.valid()[3]
    # Beyond max_range: a no-return ray ending 3 m from the sensor, along its beam.
    np.testing.assert_allclose(cloud.points[4], [1.0, 5.2, 0.8], atol=1e-6)
    assert cloud.hit.tolist() == [True, True, True, True, False]
    assert cloud.time == 1.0 and cloud.meta["frame_id"] == "lidar"
    msg.fields = msg.fields[:2]
    with pytest.raises(InputFormatError, match=r"/points.*no field z"):
        cloud_from_pointcloud2(msg, pose, source="/points")


def _cloud_message(points: np.ndarray, stamp: float, frame: str = "lidar") -> Any:
    """A PointCloud2-like message of `points` (n, 3) in the sensor frame: FLOAT64 x, y, z, big-endian."""
    from types import SimpleNamespace

    msg = _cloud([("x", 0, 8), ("y", 8, 8), ("z", 16, 8)], 24, np.asarray(points, dtype=">f8"), big=True)
    sec = int(stamp)
    msg.header = SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=round((stamp - sec) * 1e9)), frame_id=frame)
    return msg


def test_the_live_map_of_clouds_finds_the_room_and_saves_the_voxel_set(tmp_path):
    import gpomap
    from gpomap.config import VOXEL_MAP_DEFAULTS
    from gpomap.grid import OCCUPIED
    from gpomap.ros2.node import make_cloud_map, ros2_settings
    from gpomap.ros2.poses import PoseBuffer3D
    from tests.world3d import ORIGINS, ROOM, lidar_clouds, occupied

    settings = ros2_settings(lambda name, default: {"cloud_topic": "points", "warmup_scans": 3}.get(name, default))
    # gpomap map's 3-D defaults where the parameters are unset.
    assert settings.node.resolution == VOXEL_MAP_DEFAULTS["resolution"]
    assert settings.node.model["min_cell"] == VOXEL_MAP_DEFAULTS["min_cell"] and settings.sensor_pose == (0.0,) * 6
    live = make_cloud_map(settings.node, source="/points")
    poses = PoseBuffer3D((0.0, 0.0, 0.1, 0.0, 0.0, 0.0))
    clouds = lidar_clouds(ORIGINS, n_rays=300)
    for t, cloud in enumerate(clouds):
        # Odometry puts the robot 0.1 m below the sensor, turned 30 degrees; the message is in the sensor frame.
        yaw = np.pi / 6
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        poses.add(float(t), tuple(cloud.origin - [0, 0, 0.1]), _quaternion_z(yaw))
        live.receive(_cloud_message((cloud.points - cloud.origin) @ rot, float(t)))
    assert live.process(poses.lookup) == len(clouds) and live.n_rejected == 0
    voxels = live.voxels()
    centres = voxels.spec.centres()
    lo, hi = live.voxel_bounds()
    # The room's box, by the margin of gpomap map's voxel bounds.
    assert np.all(lo <= ROOM[0] + 1e-9) and np.all(hi >= ROOM[1] - 1e-9)
    taken = (voxels.ternary == OCCUPIED).ravel()
    assert taken.sum() > 50
    # Occupied voxels lie on the walls, floor, ceiling or pillar (within a voxel and a half of one)
    # as often as in gpomap map's batch voxel map of the same clouds, on the same voxels.
    from gpomap.cli.map import default_model
    from gpomap.lattice import bounds_extent

    batch, resolution = default_model(workers=1)
    assert resolution == settings.node.resolution
    batch_voxels = batch.fit(clouds).grid(resolution, bounds_extent(lo, hi))
    batch_taken = (batch_voxels.ternary == OCCUPIED).ravel()
    on_surface = occupied(centres[taken], thickness=0.15).mean()
    assert on_surface > 0.8 and on_surface >= occupied(centres[batch_taken], thickness=0.15).mean() - 0.05
    # Queries in 3-D, and the saved map file answers them as the live map does.
    pts = np.array([[3.0, 2.0, 1.2], [0.0, 2.0, 1.2], [5.9, 3.9, 2.4]])
    probability, variance, ternary = live.query(pts)
    assert probability[0] < 0.5 and variance.shape == (3,)
    assert np.array_equal(ternary, live.mapper.model_.predict_ternary(pts))
    files = {f.name for f in live.save(tmp_path / "saved")}
    assert {"map.npz", "map.bt", "map.ply", "map.gpom"} <= files
    np.testing.assert_allclose(gpomap.load_map(tmp_path / "saved" / "map.gpom").predict_proba(pts), probability, atol=1e-12)
    with pytest.raises(ValueError, match="3-D map"):
        live.render(0.1)


def test_ros2_settings_in_3d_take_six_numbers_and_keep_what_is_set():
    from gpomap.errors import GpomapError
    from gpomap.ros2.node import ros2_settings

    given = {"cloud_topic": "points", "resolution": 0.2, "sensor_pose": [0.1, 0.0, 0.3, 0.0, 0.1, 0.2]}
    s = ros2_settings(lambda name, default: given.get(name, default), {"min_cell": 0.5})
    assert s.cloud_topic == "points" and s.sensor_pose == (0.1, 0.0, 0.3, 0.0, 0.1, 0.2)
    # Set values stay; unset ones take gpomap map's 3-D defaults.
    assert s.node.resolution == 0.2 and s.node.model == {"min_cell": 0.5, "max_cell": 1.0} and s.node.tile_size == 3.0
    assert ros2_settings(lambda n, d: {"cloud_topic": "p", "sensor_pose": [1, 2, 3]}.get(n, d)).sensor_pose == (1, 2, 0, 0, 0, 3)
    for pose, what in (([0.0] * 6, "must be \\[x, y, yaw\\]"), ([0.0] * 4, "x, y, z, roll, pitch, yaw")):
        topic = "" if len(pose) == 6 else "points"
        with pytest.raises(GpomapError, match=what):
            ros2_settings(lambda n, d, pose=pose, topic=topic: {"cloud_topic": topic, "sensor_pose": pose}.get(n, d))
    with pytest.raises(GpomapError, match="six finite numbers"):
        ros2_settings(lambda n, d: {"cloud_topic": "p", "sensor_pose": [0, 0, 0, 0, "a", 0]}.get(n, d))


# Publishes the simulated room's six lidar clouds (sensor frame, FLOAT32 with an intensity) and their
# odometry once the client is ready (the file it names exists) and the node listens.
PLAYER_3D = r"""
import os, sys, time
import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField

sys.path.insert(0, sys.argv[1])
from tests.world3d import ORIGINS, lidar_clouds

yaw, ready = float(sys.argv[2]), sys.argv[3]
rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
rclpy.init()
node = rclpy.create_node("gpomap_test_cloud_player")
qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
odom, points = node.create_publisher(Odometry, "/odom", qos), node.create_publisher(PointCloud2, "/points", qos)
deadline = time.monotonic() + 90
while not os.path.exists(ready):
    assert time.monotonic() < deadline, "the client never got ready"
    time.sleep(0.05)
deadline = time.monotonic() + 60
while odom.get_subscription_count() == 0 or points.get_subscription_count() == 0:
    assert time.monotonic() < deadline, "the node never subscribed"
    time.sleep(0.05)
for t, cloud in enumerate(lidar_clouds(ORIGINS, n_rays=300), start=1):
    o = Odometry(child_frame_id="base_link")
    o.header.stamp, o.header.frame_id = Time(sec=t), "odom"
    p = cloud.origin - [0.0, 0.0, 0.1]
    o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = (float(v) for v in p)
    o.pose.pose.orientation.z, o.pose.pose.orientation.w = float(np.sin(yaw / 2)), float(np.cos(yaw / 2))
    odom.publish(o)
    table = np.column_stack([(cloud.points - cloud.origin) @ rot, np.full(cloud.n_points, 7.0)]).astype("<f4")
    m = PointCloud2(height=1, width=len(table), is_bigendian=False, point_step=16, row_step=16 * len(table), is_dense=True)
    m.header.stamp, m.header.frame_id = Time(sec=t), "lidar"
    m.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate(("x", "y", "z", "intensity"))]
    m.data = table.tobytes()
    points.publish(m)
    time.sleep(0.05)
for p in (odom, points):
    assert p.wait_for_all_acked(Duration(seconds=60)), "messages not acknowledged"
node.destroy_node()
rclpy.shutdown()
"""

# Records map_cloud and the status; once every cloud is used and mapped, saves, queries x, y, z, writes JSON.
CLIENT_3D = r"""
import base64, json, sys, time
import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from nav_msgs.srv import LoadMap
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import String
from std_srvs.srv import Trigger

out_path, ready_path, n_clouds, pts = sys.argv[1], sys.argv[2], int(sys.argv[3]), np.array(json.loads(sys.argv[4]))
rclpy.init()
node = rclpy.create_node("gpomap_test_cloud_client")
latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
clouds, statuses, answers = [], [], {}

def cloud(m):
    return {"frame_id": m.header.frame_id, "stamp": m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
            "fields": [(f.name, f.offset, f.datatype) for f in m.fields], "point_step": m.point_step, "width": m.width,
            "data": base64.b64encode(bytes(m.data)).decode()}

subs = [node.create_subscription(PointCloud2, "/map_cloud", lambda m: clouds.append(cloud(m)), latched),
        node.create_subscription(String, "/gpomap/status", lambda m: statuses.append(json.loads(m.data)), latched),
        node.create_subscription(PointCloud2, "/gpomap/query_result", lambda m: answers.update({1: cloud(m)}), 10)]
query = node.create_publisher(PointCloud2, "/gpomap/query", 10)
deadline = time.monotonic() + 60
while any(s.get_publisher_count() == 0 for s in subs) or query.get_subscription_count() == 0:
    assert time.monotonic() < deadline, "the node's topics never matched"
    rclpy.spin_once(node, timeout_sec=0.1)
open(ready_path, "w").close()
deadline = time.monotonic() + 120
while not (statuses and statuses[-1]["n_used"] == n_clouds and "n_occupied_voxels" in statuses[-1]):
    assert time.monotonic() < deadline, f"no final map; last status {statuses[-1:]}"
    rclpy.spin_once(node, timeout_sec=0.1)
# The last map may trail its status by a few callbacks: wait for the cloud of its stamp.
last = statuses[-1]["stamp"]
while not any(abs(c["stamp"] - last) < 1e-6 for c in clouds):
    assert time.monotonic() < deadline, f"the map cloud of the last map (stamp {last}) never came"
    rclpy.spin_once(node, timeout_sec=0.1)
client = node.create_client(Trigger, "/gpomap/save_map")
assert client.wait_for_service(timeout_sec=30)
future = client.call_async(Trigger.Request())
rclpy.spin_until_future_complete(node, future, timeout_sec=120)
save = future.result()
render = node.create_client(LoadMap, "/gpomap/render")
assert render.wait_for_service(timeout_sec=30)
future = render.call_async(LoadMap.Request(map_url="resolution=0.1"))
rclpy.spin_until_future_complete(node, future, timeout_sec=60)
render_result = future.result().result
m = PointCloud2(height=1, width=len(pts), is_bigendian=False, point_step=24, row_step=24 * len(pts), is_dense=True)
m.header.stamp.sec, m.header.frame_id = 1, "odom"
m.fields = [PointField(name=n, offset=8 * i, datatype=PointField.FLOAT64, count=1) for i, n in enumerate("xyz")]
m.data = pts.astype("<f8").tobytes()
query.publish(m)
deadline = time.monotonic() + 60
while 1 not in answers:
    assert time.monotonic() < deadline, "no query result"
    rclpy.spin_once(node, timeout_sec=0.1)
with open(out_path, "w") as f:
    json.dump({"clouds": clouds, "statuses": statuses, "save": {"success": save.success, "message": save.message},
               "render": render_result, "answer": answers[1]}, f)
node.destroy_node()
rclpy.shutdown()
"""


@needs_ros2
@pytest.mark.slow
def test_ros2_node_maps_pointclouds_in_3d_and_answers_its_services(ros2_env, start, tmp_path):
    import gpomap
    from gpomap.cli.map import default_model
    from gpomap.grid import OCCUPIED
    from gpomap.lattice import bounds_extent
    from gpomap.ros.live import LiveMap
    from tests.world3d import ORIGINS, lidar_clouds, occupied

    yaw = np.pi / 6
    saved = tmp_path / "saved"
    args = ["cloud_topic:=points", "warmup_scans:=3", "publish_rate:=5.0", "sensor_qos:=reliable", "pose_wait:=3.0"]
    args += ["sensor_pose:=[0.0, 0.0, 0.1, 0.0, 0.0, 0.0]", f"save_directory:={saved}"]
    node = start("node", [sys.executable, "-m", "gpomap.ros2", "--ros-args", *(x for a in args for x in ("-p", a))], ros2_env)
    pts = [[3.0, 2.0, 1.2], [0.0, 2.0, 1.2], [5.9, 3.9, 2.4], [100.0, 100.0, 1.0]]
    out, ready = tmp_path / "client.json", tmp_path / "client.ready"
    (tmp_path / "client.py").write_text(CLIENT_3D)
    client_args = [str(out), str(ready), str(len(ORIGINS)), json.dumps(pts)]
    client = start("client", [sys.executable, str(tmp_path / "client.py"), *client_args], ros2_env)
    # The player starts and finds the node while the client starts; it plays once the client is ready.
    (tmp_path / "player.py").write_text(PLAYER_3D)
    player = start("player", [sys.executable, str(tmp_path / "player.py"), str(ROOT), repr(yaw), str(ready)], ros2_env)
    _wait("the client's subscriptions", ready.exists, 90, (node, client, player), tmp_path)
    assert player.wait(120) == 0, (tmp_path / "player.log").read_text()[-3000:]
    _wait("the client's report", lambda: client.poll() is not None, 180, (node,), tmp_path)
    assert client.returncode == 0, (tmp_path / "client.log").read_text()[-3000:]
    report = json.loads(out.read_text())

    status = report["statuses"][-1]
    assert status["n_used"] == len(ORIGINS) and status["n_rejected"] == 0 and status["n_dropped_no_pose"] == 0
    last = report["clouds"][-1]
    assert last["frame_id"] == "odom" and last["point_step"] == 16
    assert last["fields"] == [["x", 0, 7], ["y", 4, 7], ["z", 8, 7], ["probability", 12, 7]]
    table = np.frombuffer(base64.b64decode(last["data"]), dtype="<f4").reshape(-1, 4).astype(float)
    assert len(table) == status["n_occupied_voxels"] > 50 and np.all(table[:, 3] >= 0.5)
    # The published voxels lie on the room's surfaces as often as gpomap map's batch voxels of the
    # same clouds (same voxels: the node's box, the 3-D defaults' resolution).
    clouds = lidar_clouds(ORIGINS, n_rays=300)
    live = LiveMap(None, 0.1, kind="cloud")
    for c in clouds:
        live._grow(c)
    batch, resolution = default_model(workers=1)
    voxels = batch.fit(clouds).grid(resolution, bounds_extent(*live.voxel_bounds()))
    batch_centres = voxels.spec.centres()[(voxels.ternary == OCCUPIED).ravel()]
    on_surface = occupied(table[:, :3], thickness=0.15).mean()
    batch_on_surface = occupied(batch_centres, thickness=0.15).mean()
    print(
        f"occupied voxels on a surface, node / batch: {on_surface:.3f} / {batch_on_surface:.3f} ({len(table)} / {len(batch_centres)})"
    )
    assert on_surface > 0.8 and on_surface >= batch_on_surface - 0.05
    # The saved voxel set, and its map file answers the x, y, z query as the node did.
    assert report["save"]["success"], report["save"]["message"]
    assert {"map.npz", "map.bt", "map.ply", "map.gpom"} <= {p.name for p in saved.iterdir()}
    answer = report["answer"]
    fields = ["x", "y", "z", "probability", "variance", "ternary"]
    assert [f[0] for f in answer["fields"]] == fields and answer["width"] == len(pts)
    result = np.frombuffer(base64.b64decode(answer["data"]), dtype="<f8").reshape(-1, 6)
    np.testing.assert_array_equal(result[:, :3], pts)
    saved_map = gpomap.load_map(saved / "map.gpom")
    np.testing.assert_allclose(saved_map.predict_proba(np.array(pts)), result[:, 3], rtol=0, atol=1e-12)
    assert result[3, 3] == 0.5 and result[3, 5] == -1  # far outside: the prior, unknown
    assert np.array_equal(saved_map.predict_ternary(np.array(pts)), result[:, 5])
    # A planar render of a 3-D map is refused with LoadMap's undefined-failure code.
    assert report["render"] == 255
