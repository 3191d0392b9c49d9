"""The ROS 1 node for real: roscore, ``python -m gpomap.ros`` and ``rosbag play`` of the Stage arena's first 20 s.

A collector node (run with the same Python as gpomap's node) records every message published on
``/map``, ``/map_probability``, ``/map_variance`` and ``/gpomap/status``; the test checks each one
is well formed, that the node used the scans the batch reader uses, that ``~save_map`` writes
the published map, and scores the last published map against the arena's true floor plan: its
AUC must be at least the batch map's of the same scans minus 0.01.

rospy is Debian's (``/usr/bin/python3``); the node runs from a venv made from that Python with
``--system-site-packages`` and gpomap installed in it (``.venv/ros``, built on first use), as
the README tells robot users to do. Skipped, with the reason, where ROS 1 is not installed.
"""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import warnings
import xmlrpc.client
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ARENA = ROOT.parent / "shared" / "data" / "stage-arena"
BAG = ARENA / "robot1.bag"
SYSTEM_PYTHON = "/usr/bin/python3"
ROS_IMPORTS = "import rospy, tf2_ros, nav_msgs.msg, sensor_msgs.msg, std_msgs.msg, std_srvs.srv"
APT = "apt-get install ros-core python3-rospy python3-tf2-ros python3-nav-msgs python3-sensor-msgs python3-std-srvs"
#: Seconds of the bag played: its first 20 (of 43). Its messages come in steps of 0.1 s, so the cut
#: falls between two; the last scan played (stamp 26.1) has no tf 0.1 s later, as the bag's last has none.
PLAY_SECONDS = 20.05
#: LaserScan messages on /base_scan in those seconds (of 433 in the bag).
N_MESSAGES = 202
RESOLUTION = 0.05


def _imports_ros(python: str) -> bool:
    try:
        return subprocess.run([python, "-c", ROS_IMPORTS], capture_output=True, timeout=60).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _why_skip() -> str | None:
    if not BAG.exists():
        return f"shared Stage arena bag not present ({BAG})"
    missing = [tool for tool in ("roscore", "rosbag", "rosservice") if shutil.which(tool) is None]
    if missing:
        return f"ROS 1 not installed ({', '.join(missing)} not on PATH): {APT}"
    if not (_imports_ros(sys.executable) or (Path(SYSTEM_PYTHON).exists() and _imports_ros(SYSTEM_PYTHON))):
        return f"ROS 1 Python packages not importable from {sys.executable} or {SYSTEM_PYTHON}: {APT}"
    return None


_SKIP = _why_skip()
pytestmark = pytest.mark.skipif(_SKIP is not None, reason=_SKIP or "")

# Records every message of the node's topics as one JSON line (grids' data base64 int8).
COLLECTOR = r"""
import base64, json, sys
import rospy
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import String

out = open(sys.argv[1], "a", buffering=1)

def on_grid(topic):
    def callback(m):
        p, o = m.info.origin.position, m.info.origin.orientation
        out.write(json.dumps({
            "topic": topic, "frame_id": m.header.frame_id, "stamp": m.header.stamp.to_sec(),
            "load_time": m.info.map_load_time.to_sec(), "resolution": m.info.resolution,
            "width": m.info.width, "height": m.info.height, "origin": [p.x, p.y, p.z],
            "orientation": [o.x, o.y, o.z, o.w], "n_data": len(m.data),
            "data": base64.b64encode(bytes(bytearray(v & 0xFF for v in m.data))).decode(),
        }) + "\n")
    return callback

def on_status(m):
    out.write(json.dumps({"topic": "/gpomap/status", "status": json.loads(m.data)}) + "\n")

rospy.init_node("gpomap_test_collector")
for topic in ("/map", "/map_probability", "/map_variance"):
    rospy.Subscriber(topic, OccupancyGrid, on_grid(topic), queue_size=100)
rospy.Subscriber("/gpomap/status", String, on_status, queue_size=100)
rospy.spin()
"""


# --------------------------------------------------------------------------- processes
@pytest.fixture(scope="session")
def ros_python() -> str:
    """A Python that imports both rospy and this checkout's gpomap."""
    probe = [sys.executable, "-c", f"{ROS_IMPORTS}, gpomap"]
    if subprocess.run(probe, capture_output=True).returncode == 0:
        return sys.executable
    venv = ROOT / ".venv" / "ros"
    python = venv / "bin" / "python"
    stamp = venv / ".installed"
    key = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if not (python.exists() and stamp.exists() and stamp.read_text() == key):
        venv.parent.mkdir(parents=True, exist_ok=True)
        # This Python's pip installs into the venv (``pip --python``), without compiling every module
        # of the dependencies ahead: no pip of its own to put in the venv, and the install about a
        # third of the CPU time. Only a Python without pip installs with the venv's own.
        own_pip = importlib.util.find_spec("pip") is None
        make = [SYSTEM_PYTHON, "-m", "venv", "--clear", "--system-site-packages", str(venv)]
        subprocess.run(make if own_pip else [*make, "--without-pip"], check=True)
        pip = [str(python), "-m", "pip"] if own_pip else [sys.executable, "-m", "pip", "--python", str(python)]
        r = subprocess.run(
            [*pip, "install", "--quiet", "--disable-pip-version-check", "--no-compile", "-e", str(ROOT)],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        assert r.returncode == 0, f"installing gpomap into {venv} failed:\n{r.stderr[-3000:]}"
        stamp.write_text(key)
    return str(python)


def _stop(proc: subprocess.Popen) -> None:
    """SIGINT to the process group it leads (a ROS node shuts down cleanly on it), then SIGKILL."""
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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(what: str, condition: Callable[[], Any], timeout: float, procs: tuple[subprocess.Popen, ...] = ()) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for p in procs:
            assert p.poll() is None, f"{p.args[:3]} exited with {p.returncode} while waiting for {what}"
        try:
            value = condition()
        except (OSError, xmlrpc.client.Error):
            value = None
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture
def ros_master(start: Callable[..., subprocess.Popen], tmp_path: Path) -> tuple[dict[str, str], Any]:
    """A roscore on a free port with /use_sim_time set; the environment to reach it and its XML-RPC proxy."""
    port = _free_port()
    env = dict(
        os.environ,
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_IP="127.0.0.1",
        ROS_HOME=str(tmp_path / "ros"),
        ROS_LOG_DIR=str(tmp_path / "ros" / "log"),
        OMP_NUM_THREADS="1",
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_HOSTNAME", None)
    core = start("roscore", ["roscore", "-p", str(port)], env)
    master = xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"])
    _wait("roscore", lambda: master.getSystemState("/pytest")[0] == 1, 60, (core,))
    # The bag's clock drives ROS time: scans, tf and the published stamps all use it.
    master.setParam("/pytest", "/use_sim_time", True)
    return env, master


def _subscribed(master: Any, node: str, topics: tuple[str, ...]) -> bool:
    _, _, (_, subscribers, _) = master.getSystemState("/pytest")
    have = {topic for topic, nodes in subscribers if node in nodes}
    return all(t in have for t in topics)


def _records(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


# --------------------------------------------------------------------------- the test
def _batch_auc(scans: list, truth: Any) -> float:
    """Truth AUC of the map ``gpomap map`` makes of the same scans at the same resolution."""
    from gpomap.evaluation import lookup, make_model, score_truth, written_grid

    model = make_model("msk", n_workers=1).fit(scans)
    return float(score_truth(truth, lookup(written_grid(model, RESOLUTION), truth.grid.centres()))["auc"])


def _stage_truth() -> Any:
    from PIL import Image

    from gpomap.evaluation import Truth

    img = np.asarray(Image.open(ARENA / "mrl_arena.pgm"))
    # The data README: Stage stretches the 406 x 460 bitmap to 4.06 m x 4.55 m centred at (1, 1).
    return Truth.from_plan(img < 128, (-1.03, -1.275), (0.0100, 0.009891), 0.05)


@pytest.mark.slow
def test_node_maps_the_stage_arena_bag_on_a_real_roscore(ros_python, ros_master, start, tmp_path):
    from gpomap.evaluation import lookup, score_truth
    from gpomap.grid import GridSpec, OccupancyMap
    from gpomap.io.npz import load_map
    from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
    from gpomap.io.rosmap import read_rosmap

    env, master = ros_master
    saved = tmp_path / "saved"
    node = start(
        "node",
        [
            ros_python,
            "-m",
            "gpomap.ros",
            "_scan_topic:=/base_scan",
            "_fixed_frame:=odom",
            f"_time_offset:={STAGE_TIME_OFFSET}",
            f"_resolution:={RESOLUTION}",
            "_publish_rate:=2.0",
            f"_save_directory:={saved}",
        ],
        env,
    )
    collected = tmp_path / "messages.jsonl"
    script = tmp_path / "collector.py"
    script.write_text(COLLECTOR)
    collector = start("collector", [ros_python, str(script), str(collected)], env)
    procs = (node, collector)
    _wait("the node's subscriptions", lambda: _subscribed(master, "/gpomap", ("/base_scan", "/tf")), 60, procs)
    grids = ("/map", "/map_probability", "/map_variance")
    _wait("the collector's subscriptions", lambda: _subscribed(master, "/gpomap_test_collector", grids), 60, procs)

    # 20 s of recording at 10x; --wait-for-subscribers: no scan is published before the node listens.
    play_args = ["-q", "--clock", "--wait-for-subscribers", "-r", "10", "-u", str(PLAY_SECONDS), str(BAG)]
    play = subprocess.run(
        ["rosbag", "play", *play_args, "--topics", "/base_scan", "/tf"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert play.returncode == 0, play.stderr[-2000:]

    def settled() -> dict[str, Any] | None:
        """The last status once every scan is used or dropped and a map of all of them went out."""
        records = _records(collected)
        statuses = [r["status"] for r in records if r["topic"] == "/gpomap/status"]
        if not statuses or statuses[-1]["n_received"] != N_MESSAGES or statuses[-1]["n_waiting"]:
            return None
        final = statuses[-1]
        published = any("width" in s and s["n_used"] == final["n_used"] for s in statuses)
        return final if published else None

    status = _wait("the last map", settled, 120, procs)

    # ~save_map writes what was published (no scan came after it).
    r = subprocess.run(["rosservice", "call", "/gpomap/save_map"], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "success: True" in r.stdout, r.stdout + r.stderr
    records = _records(collected)

    # The scans: every one the batch reader gives of those played, and the last (no later pose) dropped after its wait.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the batch reader warns about the bag's last scan
        scans = read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)[: N_MESSAGES - 1]
    assert status["n_used"] == len(scans) == N_MESSAGES - 1
    assert status["n_dropped_no_pose"] == 1 and status["n_rejected"] == 0
    assert status["latency_ms"]["median"] > 0

    # Every grid message well formed.
    messages = [m for m in records if m["topic"] in grids]
    assert {m["topic"] for m in messages} == set(grids)
    layers: dict[str, list[np.ndarray]] = {t: [] for t in grids}
    for m in messages:
        assert m["frame_id"] == "odom"
        assert m["resolution"] == pytest.approx(RESOLUTION, rel=1e-6)  # float32 on the wire
        assert m["width"] > 0 and m["height"] > 0
        assert m["n_data"] == m["width"] * m["height"]
        assert m["origin"][2] == 0.0 and m["orientation"] == [0.0, 0.0, 0.0, 1.0]
        assert m["load_time"] == m["stamp"]
        data = np.frombuffer(base64.b64decode(m["data"]), dtype=np.int8)
        assert data.size == m["n_data"]
        values = set(np.unique(data).tolist())
        if m["topic"] == "/map":
            assert values <= {-1, 0, 100}
        else:
            assert min(values) >= 0 and max(values) <= 100
        layers[m["topic"]].append(data)
    # The three layers go out together, with the same geometry and stamp, in time order.
    n = len(layers["/map"])
    assert n >= 2 and all(len(v) == n for v in layers.values())
    by_topic = {t: [m for m in messages if m["topic"] == t] for t in grids}
    for i in range(n):
        geometry = {(m["stamp"], m["width"], m["height"], tuple(m["origin"])) for m in (by_topic[t][i] for t in grids)}
        assert len(geometry) == 1
        # Trinary and probability agree (a calibrated map: free below 0.196, occupied above 0.5;
        # probabilities rounded to 1 %).
        trinary, prob = layers["/map"][i], layers["/map_probability"][i]
        assert (prob[trinary == 100] >= 50).all() and (prob[trinary == 0] <= 20).all()
    stamps = [m["stamp"] for m in by_topic["/map"]]
    assert stamps == sorted(stamps) and stamps[-1] == pytest.approx(scans[-1].time, abs=1e-6)
    final = by_topic["/map_probability"][-1]
    assert (
        final["width"] * final["height"] >= by_topic["/map_probability"][0]["width"] * by_topic["/map_probability"][0]["height"]
    )
    final_trinary = layers["/map"][-1]
    assert (final_trinary == 0).any() and (final_trinary == 100).any()
    assert (layers["/map_variance"][-1] > 0).any()

    # The saved set is the published map.
    grid = GridSpec(tuple(final["origin"][:2]), RESOLUTION, (final["height"], final["width"]))
    saved_map = load_map(saved / "map.npz")
    assert saved_map.grid.shape == grid.shape and np.allclose(saved_map.grid.origin, grid.origin)
    published = layers["/map_probability"][-1].reshape(grid.shape) / 100.0
    assert np.abs(saved_map.probability - published).max() <= 0.005 + 1e-9
    rosmap = read_rosmap(saved / "map.yaml")
    expected = np.where(final_trinary == 100, 1, np.where(final_trinary == 0, 0, -1)).reshape(grid.shape)
    assert np.array_equal(np.where(rosmap.occupied, 1, np.where(rosmap.free, 0, -1)), expected)

    # Against the true floor plan: the node's last map (saved above, published to the 1 %
    # rounding of OccupancyGrid) at least the batch map's AUC minus 0.01. The percent layer
    # itself is scored too, for the record: its rounding ties the many cells near 0 and 1.
    truth = _stage_truth()
    live = score_truth(truth, lookup(saved_map, truth.grid.centres()))["auc"]
    percent = score_truth(truth, lookup(OccupancyMap(grid, published), truth.grid.centres()))["auc"]
    batch = _batch_auc(scans, truth)
    print(f"truth AUC: node's map {live:.4f} (its 1 % layer {percent:.4f}), batch map {batch:.4f}; {n} publishes")
    assert live >= batch - 0.01
