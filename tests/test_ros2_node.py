"""The ROS 2 node for real: ``python -m gpomap.ros2``, a player and a client, three rclpy processes on loopback.

The player replays the Stage arena bag: its ``/base_scan`` LaserScan messages and, as
``nav_msgs/Odometry``, its tf edge odom -> base_footprint (the laser sits 0.225 m ahead of it:
the node's ``sensor_pose``). The client records every message on ``/map``, ``/map_probability``,
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
#: LaserScan messages on /base_scan in the bag.
N_MESSAGES = 433
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
pytestmark = pytest.mark.skipif(_SKIP is not None, reason=_SKIP or "")

# Replays the bag's scans and odometry at 10x once the node listens; exits when all are acknowledged.
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

bag, rate = Path(sys.argv[1]), 10.0
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
            events.append((t, "scan", msg))
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
            events.append((t, "odom", msg))

rclpy.init()
node = rclpy.create_node("gpomap_test_player")
qos = QoSProfile(depth=5000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
pubs = {"scan": node.create_publisher(LaserScan, "/base_scan", qos), "odom": node.create_publisher(Odometry, "/odom", qos)}
deadline = time.monotonic() + 60
while any(p.get_subscription_count() == 0 for p in pubs.values()):
    assert time.monotonic() < deadline, "the node never subscribed"
    time.sleep(0.05)
start, t0 = time.monotonic(), events[0][0]
for t, kind, msg in events:
    time.sleep(max(0.0, start + (t - t0) * 1e-9 / rate - time.monotonic()))
    pubs[kind].publish(msg)
for p in pubs.values():
    assert p.wait_for_all_acked(Duration(seconds=60)), "messages not acknowledged"
print(sum(k == "scan" for _, k, _ in events), "scans", sum(k == "odom" for _, k, _ in events), "odometry")
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
for _ in range(10):  # the last grids may trail their status by a few callbacks
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
                log = "".join((logs / f"{n}.log").read_text()[-3000:] for n in ("node", "client") if (logs / f"{n}.log").exists())
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
    _wait("the client's subscriptions", ready.exists, 90, (node, client), tmp_path)

    (tmp_path / "player.py").write_text(PLAYER)
    play = subprocess.run(
        [sys.executable, str(tmp_path / "player.py"), str(BAG)],
        env=ros2_env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert play.returncode == 0, play.stdout + play.stderr[-3000:]
    _wait("the client's report", lambda: client.poll() is not None, 300, (node,), tmp_path)
    assert client.returncode == 0, (tmp_path / "client.log").read_text()[-3000:]
    report = json.loads(out.read_text())

    # The scans: every one the batch reader gives, and the last (no later pose) dropped after its wait.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the batch reader warns about that last scan too
        scans = read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)
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
    assert answer["frame_id"] == "odom" and answer["width"] == len(points) and answer["point_step"] == 32
    assert [f[0] for f in answer["fields"]] == ["x", "y", "probability", "variance"]
    table = np.frombuffer(base64.b64decode(answer["data"]), dtype="<f8").reshape(-1, 4)
    assert np.allclose(table[:, :2], points.astype(np.float32), atol=0)
    assert ((table[:, 2] >= 0) & (table[:, 2] <= 1)).all() and (table[:, 3] > 0).all()
    far = np.frombuffer(base64.b64decode(report["answers"]["2"]["data"]), dtype="<f8").reshape(-1, 4)
    assert np.array_equal(far[:, 2], [0.5, 0.5]) and far[0, 3] == far[1, 3] >= table[:, 3].max()

    # The saved map file is the node's model: it answers the queries as the node did, to the bit.
    from gpomap.io.mapfile import load_fitted_map

    loaded = load_fitted_map(saved / "map.gpom")
    probability, variance = loaded.predict_proba(table[:, :2], return_var=True)
    assert np.array_equal(probability, table[:, 2]) and np.array_equal(variance, table[:, 3])
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
