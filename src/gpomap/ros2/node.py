"""The ROS 2 node: ``sensor_msgs/LaserScan`` and ``nav_msgs/Odometry`` in, ``nav_msgs/OccupancyGrid`` out.

A thin rclpy adapter over :class:`gpomap.ros.live.LiveMap` (which holds the streaming mapper),
as :mod:`gpomap.ros.node` is for rospy: the subscriptions queue scans and record poses, the
node's main loop feeds the mapper and publishes the map at ``publish_rate`` (Hz of wall time).

Poses come from ``nav_msgs/Odometry`` (:class:`gpomap.ros2.poses.PoseBuffer`), not tf: neither
tf2_ros nor tf2_msgs is on PyPI. The laser's mounting on the robot is the ``sensor_pose``
parameter.

Topics (relative names, remap them as usual):

- subscribed: ``scan_topic`` (``scan``), ``odom_topic`` (``odom``), ``~/query``
  (``sensor_msgs/PointCloud2``, fields x, y);
- published (reliable, transient local: a late subscriber gets the last map): ``map`` (trinary:
  0 free, 100 occupied, -1 unknown), ``map_probability`` (occupancy in percent, 0..100),
  ``map_variance`` (latent variance in percent of the prior variance, 100 = nothing known), and
  ``~/status`` (``std_msgs/String``, JSON: scans used, dropped, latency);
- ``~/query_result`` (``sensor_msgs/PointCloud2``): the answer to each ``~/query`` message, under
  its header, fields x, y, probability, variance, ternary (FLOAT64; the ternary is the written map's
  call, 0 free, -1 unknown, 1 occupied; NaN probability and variance, unknown, before the first map).

Services: ``~/save_map`` (``std_srvs/Trigger``) writes ``map.yaml`` + ``map.pgm``, ``map.npz``,
``map.png`` and the fitted map ``map.gpom`` into ``save_directory`` as one set; ``~/render`` (``nav_msgs/LoadMap``) returns the map
on any grid, the request's ``map_url`` holding ``resolution=R extent=xmin,xmax,ymin,ymax
layer=probability|trinary|variance`` (:func:`gpomap.ros2.queries.parse_render_request`).

3-D (``cloud_topic`` set): the node subscribes to ``sensor_msgs/PointCloud2`` on ``cloud_topic``
instead of the scans, takes the odometry's full 6-DoF pose (:class:`gpomap.ros2.poses.PoseBuffer3D`;
``sensor_pose`` then [x, y, z, roll, pitch, yaw], or [x, y, yaw]), maps with the 3-D defaults of
``gpomap map`` (:data:`gpomap.config.VOXEL_MAP_DEFAULTS` where a parameter is unset, 3-D tiles),
and publishes the occupied voxel centres on ``map_cloud`` (``sensor_msgs/PointCloud2``, FLOAT32
x, y, z, probability) in place of the grids; ``~/save_map`` writes the voxel output set,
``~/query`` takes x, y, z and answers x, y, z, probability, variance, ternary; ``~/render`` is refused.

Parameters: those of the ROS 1 node (:func:`gpomap.ros.node.settings_from_params`, checked by the
same code) and :data:`ROS2_DEFAULTS`; AreaGPOM options as ``model.<option>``.
"""

from __future__ import annotations

import array
import contextlib
import json
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from gpomap.errors import GpomapError, InputFormatError, NotFittedError
from gpomap.ros.node import NodeSettings, make_live_map, settings_from_params

__all__ = ["Ros2Settings", "ROS2_DEFAULTS", "PARAMETERS", "ros2_settings", "main"]

_INSTALL = 'pip install "gpomap[ros2]"'

#: The ROS 2 node's own parameters and their defaults.
ROS2_DEFAULTS: dict[str, Any] = {
    "odom_topic": "odom",
    "cloud_topic": "",
    "sensor_pose": [0.0, 0.0, 0.0],
    "sensor_upside_down": False,
    "sensor_qos": "best_effort",
}
#: Every parameter the node reads (besides ``model.<option>``), with its default (None: unset).
PARAMETERS: dict[str, Any] = {
    **{f.name: getattr(NodeSettings(), f.name) for f in fields(NodeSettings) if f.name != "model"},
    **ROS2_DEFAULTS,
}
#: Parameters every rclpy node has.
_RCLPY_PARAMETERS = ("use_sim_time", "start_type_description_service")


@dataclass(frozen=True)
class Ros2Settings:
    """The node's parameters, checked: the ROS 1 node's and the ROS 2 node's own (see :func:`ros2_settings`)."""

    node: NodeSettings
    odom_topic: str = "odom"
    sensor_pose: tuple[float, ...] = (0.0, 0.0, 0.0)
    sensor_upside_down: bool = False
    sensor_qos: str = "best_effort"
    #: The PointCloud2 topic; empty: map LaserScan messages in 2-D.
    cloud_topic: str = ""


def ros2_settings(get: Callable[[str, Any], Any], model: dict[str, Any] | None = None) -> Ros2Settings:
    """Read and check the node's parameters.

    Parameters
    ----------
    get : callable
        ``get(name, default)``: a parameter's value, or `default` when it is not set.
    model : dict, optional
        AreaGPOM options (the ``model.<option>`` parameters).

    Returns
    -------
    Ros2Settings
        ``node``: :func:`gpomap.ros.node.settings_from_params`'s settings; ``odom_topic``
        (``odom``), ``sensor_pose`` ([x, y, yaw] of the laser in the odometry's child frame,
        metres and radians; [0, 0, 0]; with ``cloud_topic``, [x, y, z, roll, pitch, yaw] or
        [x, y, yaw], always returned as six values), ``cloud_topic`` (empty: 2-D), ``sensor_upside_down`` (false), ``sensor_qos``
        (``best_effort``, which receives from any publisher, or ``reliable``, which loses no
        message but does not hear best-effort publishers).

    Raises
    ------
    GpomapError
        A value of the wrong type or out of range, naming the parameter.
    """
    try:
        node = settings_from_params(lambda name, default: (model or {}) if name == "model" else get(name, default))
    except GpomapError as exc:
        # The shared checks name parameters the ROS 1 way (~name); ROS 2 has no ~ in a parameter's name.
        raise GpomapError(str(exc).replace("parameter ~", "parameter ", 1)) from None
    cloud_topic = str(get("cloud_topic", "") or "")
    pose = get("sensor_pose", ROS2_DEFAULTS["sensor_pose"])
    sizes = (3, 6) if cloud_topic else (3,)
    if isinstance(pose, str) or not isinstance(pose, Sequence) or len(pose) not in sizes:
        expected = "[x, y, z, roll, pitch, yaw] or [x, y, yaw]" if cloud_topic else "[x, y, yaw]"
        raise GpomapError(f"parameter sensor_pose must be {expected} (metres, radians), got {pose!r}")
    try:
        values = [float(v) for v in pose]
    except (TypeError, ValueError):
        values = [math.nan]
    if not all(math.isfinite(v) for v in values):
        expected = "six finite numbers [x, y, z, roll, pitch, yaw]" if len(pose) == 6 else "three finite numbers [x, y, yaw]"
        raise GpomapError(f"parameter sensor_pose must be {expected}, got {pose!r}")
    if cloud_topic:
        if len(values) == 3:
            values = [values[0], values[1], 0.0, 0.0, 0.0, values[2]]
        node = _with_3d_defaults(node, get, model or {})
    upside_down = get("sensor_upside_down", False)
    if not isinstance(upside_down, bool):
        raise GpomapError(f"parameter sensor_upside_down must be true or false, got {upside_down!r}")
    qos = str(get("sensor_qos", ROS2_DEFAULTS["sensor_qos"])).lower()
    if qos not in ("best_effort", "reliable"):
        raise GpomapError(f"parameter sensor_qos must be best_effort or reliable, got {qos!r}")
    return Ros2Settings(
        node=node,
        odom_topic=str(get("odom_topic", ROS2_DEFAULTS["odom_topic"])),
        sensor_pose=tuple(values),
        sensor_upside_down=upside_down,
        sensor_qos=qos,
        cloud_topic=cloud_topic,
    )


def _with_3d_defaults(node: NodeSettings, get: Callable[[str, Any], Any], model: dict[str, Any]) -> NodeSettings:
    """`node` with ``gpomap map``'s 3-D defaults where the parameter is unset: resolution, cells, 3-D tiles."""
    import dataclasses

    from gpomap.config import VOXEL_MAP_DEFAULTS
    from gpomap.tiles import DEFAULT_TILE_SIZE

    unset = object()
    changes: dict[str, Any] = {}
    if get("resolution", unset) is unset:
        changes["resolution"] = VOXEL_MAP_DEFAULTS["resolution"]
    if get("tile_size", unset) is unset:
        changes["tile_size"] = DEFAULT_TILE_SIZE[3]
    cells = {k: v for k, v in VOXEL_MAP_DEFAULTS.items() if k != "resolution" and k not in model}
    if cells:
        changes["model"] = {**node.model, **cells}
    return dataclasses.replace(node, **changes)


def read_settings(node: Any) -> Ros2Settings:
    """Declare the parameters on an rclpy node (made with ``automatically_declare_parameters_from_overrides``) and read them.

    Raises
    ------
    GpomapError
        An unknown parameter name (a typo would otherwise be ignored), or a bad value.
    """
    from rcl_interfaces.msg import ParameterDescriptor

    given = set(node.list_parameters([], 0).names)
    unknown = sorted(
        n for n in given if n not in PARAMETERS and n not in _RCLPY_PARAMETERS and not n.startswith(("model.", "qos_overrides."))
    )
    if unknown:
        raise GpomapError(
            f"unknown parameter(s) {', '.join(unknown)}; the node's parameters: {', '.join(PARAMETERS)}, model.<option>"
        )
    for name, default in PARAMETERS.items():
        if name not in given:
            # Dynamic typing: `-p resolution:=1` (an integer) is as good as 0.05; None declares it unset.
            node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True))

    def get(name: str, default: Any) -> Any:
        if name not in given:
            # Unset: the caller's default (the 3-D defaults differ from the declared 2-D ones).
            return default
        value = node.get_parameter(name).value
        if value is None:
            return default
        return list(value) if isinstance(value, array.array | tuple) else value

    model = {k: p.value for k, p in node.get_parameters_by_prefix("model").items()}
    return ros2_settings(get, model)


def _time(seconds: float) -> Any:
    """A ``builtin_interfaces/Time`` of `seconds`."""
    from builtin_interfaces.msg import Time

    sec = math.floor(seconds)
    nanosec = min(round((seconds - sec) * 1e9), 999_999_999)
    return Time(sec=int(sec), nanosec=int(nanosec))


class Ros2Node:
    """The rclpy wiring of a :class:`~gpomap.ros.live.LiveMap` (see the module's docstring)."""

    def __init__(self, node: Any, settings: Ros2Settings) -> None:
        from nav_msgs.msg import OccupancyGrid, Odometry
        from nav_msgs.srv import LoadMap
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import LaserScan, PointCloud2, PointField
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from gpomap.ros2.poses import PoseBuffer

        self.node = node
        self.settings = settings
        s = settings.node
        self._grid_type, self._string_type, self._cloud_type, self._field_type = OccupancyGrid, String, PointCloud2, PointField
        self._load_map = LoadMap
        self.three_d = bool(settings.cloud_topic)
        self.scan_topic = node.resolve_topic_name(settings.cloud_topic or s.scan_topic)
        self.poses: Any
        if self.three_d:
            from gpomap.ros2.poses import PoseBuffer3D

            self.live = make_cloud_map(s, source=self.scan_topic)
            self.poses = PoseBuffer3D(settings.sensor_pose)
        else:
            self.live = make_live_map(s, source=self.scan_topic)
            p = settings.sensor_pose
            self.poses = PoseBuffer((p[0], p[1], p[2]), settings.sensor_upside_down)
        self.n_odometry = 0
        self.n_odometry_rejected = 0
        self._wake = threading.Event()
        latched = QoSProfile(
            depth=1,
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        reliability = ReliabilityPolicy.RELIABLE if settings.sensor_qos == "reliable" else ReliabilityPolicy.BEST_EFFORT
        # A deep queue: the callbacks only append, the main loop drains it.
        sensor = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=reliability)
        layers = () if self.three_d else ("map", "map_probability", "map_variance")
        self.publishers = {name: node.create_publisher(OccupancyGrid, name, latched) for name in layers}
        self.cloud_publisher = node.create_publisher(PointCloud2, "map_cloud", latched) if self.three_d else None
        self.status_publisher = node.create_publisher(String, "~/status", latched)
        self.query_publisher = node.create_publisher(PointCloud2, "~/query_result", 10)
        self.subscriptions = [
            node.create_subscription(PointCloud2, settings.cloud_topic, self._on_scan, sensor)
            if self.three_d
            else node.create_subscription(LaserScan, s.scan_topic, self._on_scan, sensor),
            node.create_subscription(Odometry, settings.odom_topic, self._on_odometry, sensor),
            node.create_subscription(PointCloud2, "~/query", self._on_query, 10),
        ]
        self.services = [
            node.create_service(Trigger, "~/save_map", self._on_save),
            node.create_service(LoadMap, "~/render", self._on_render),
        ]
        self._published: tuple[int, ...] = ()
        self._published_scans = -1

    # ------------------------------------------------------------------ in
    def _on_scan(self, msg: Any) -> None:
        self.live.receive(msg)
        self._wake.set()

    def _on_odometry(self, msg: Any) -> None:
        from gpomap.ros.messages import pose_from_transform, stamp_seconds

        frame = str(msg.header.frame_id).lstrip("/")
        if frame and frame != self.settings.node.fixed_frame:
            # Poses in another frame would put the scans in the wrong place: count, keep the reason.
            self.n_odometry_rejected += 1
            self.live.last_error = f"odometry in frame {frame!r}, expected fixed_frame {self.settings.node.fixed_frame!r}"
            return
        pose = msg.pose.pose
        if self.three_d:
            p, q = pose.position, pose.orientation
            self.poses.add(stamp_seconds(msg.header.stamp), (p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
        else:
            self.poses.add(stamp_seconds(msg.header.stamp), *pose_from_transform(pose.position, pose.orientation))
        self.n_odometry += 1
        self._wake.set()

    # ------------------------------------------------------------------ out
    def _grid_message(self, layers: Any, data: Any, stamp: Any) -> Any:
        msg = self._grid_type()
        msg.header.frame_id = self.settings.node.fixed_frame
        msg.header.stamp = stamp
        msg.info.map_load_time = stamp
        msg.info.resolution = float(layers.grid.resolution)
        msg.info.width = int(layers.width)
        msg.info.height = int(layers.height)
        msg.info.origin.position.x, msg.info.origin.position.y = (float(v) for v in layers.grid.origin)
        msg.info.origin.orientation.w = 1.0
        msg.data = array.array("b", np.ascontiguousarray(data, dtype=np.int8).tobytes())
        return msg

    def status(self) -> dict[str, Any]:
        """The live map's status and the odometry counts."""
        status = self.live.status()
        status["n_odometry"] = self.n_odometry
        status["n_odometry_rejected"] = self.n_odometry_rejected
        return status

    def publish(self) -> bool:
        """Publish the three grids if the map changed, and the status if any count did; returns whether a map went out."""
        status = self.status()
        counts = tuple(status[k] for k in ("n_received", "n_used", "n_dropped_no_pose", "n_rejected", "n_waiting"))
        if counts == self._published:
            return False
        self._published = counts
        if status["n_used"] == self._published_scans or not status["ready"]:
            self.status_publisher.publish(self._string_type(data=json.dumps(status)))
            return False
        t = time.perf_counter()
        if self.three_d:
            return self._publish_voxels(status, t)
        layers = self.live.layers()
        if layers is None:
            return False
        stamp = _time(self.live.stamp or 0.0)
        for name, data in (("map", layers.trinary), ("map_probability", layers.probability), ("map_variance", layers.variance)):
            self.publishers[name].publish(self._grid_message(layers, data, stamp))
        self._published_scans = status["n_used"]
        status["publish_seconds"] = time.perf_counter() - t
        status["width"], status["height"] = layers.width, layers.height
        self.status_publisher.publish(self._string_type(data=json.dumps(status)))
        return True

    def _publish_voxels(self, status: dict[str, Any], t: float) -> bool:
        from gpomap.grid import OCCUPIED

        try:
            voxels = self.live.voxels()
        except GpomapError as exc:
            # A voxel grid over the memory limit: say so on the status, keep mapping.
            self.live.last_error = str(exc)
            self.status_publisher.publish(self._string_type(data=json.dumps(self.status())))
            return False
        occupied = (voxels.ternary == OCCUPIED).ravel()
        table = np.column_stack([voxels.spec.centres()[occupied], voxels.probability.ravel()[occupied]])
        out = self._cloud_type()
        out.header.frame_id = self.settings.node.fixed_frame
        out.header.stamp = _time(self.live.stamp or 0.0)
        out.height, out.width = 1, len(table)
        out.fields = [
            self._field_type(name=name, offset=4 * i, datatype=7, count=1)
            for i, name in enumerate(("x", "y", "z", "probability"))
        ]
        out.is_bigendian = False
        out.point_step = 16
        out.row_step = 16 * len(table)
        out.data = array.array("B", np.ascontiguousarray(table, dtype="<f4").tobytes())
        out.is_dense = True
        assert self.cloud_publisher is not None
        self.cloud_publisher.publish(out)
        self._published_scans = status["n_used"]
        status["publish_seconds"] = time.perf_counter() - t
        status["n_occupied_voxels"] = len(table)
        status["voxel_shape"] = list(voxels.spec.shape)
        self.status_publisher.publish(self._string_type(data=json.dumps(status)))
        return True

    # ------------------------------------------------------------------ requests
    def _on_save(self, request: Any, response: Any) -> Any:
        try:
            files = self.live.save(self.settings.node.save_directory)
        except (GpomapError, OSError, ValueError) as exc:
            response.success, response.message = False, str(exc)
            return response
        response.success, response.message = True, "wrote " + ", ".join(str(f) for f in files)
        return response

    def _on_render(self, request: Any, response: Any) -> Any:
        from gpomap.ros2.queries import parse_render_request

        codes = self._load_map.Response
        try:
            req = parse_render_request(str(request.map_url))
            layers = self.live.render(req.resolution or self.settings.node.resolution, req.extent)
        except InputFormatError as exc:
            response.result = codes.RESULT_INVALID_MAP_METADATA
            self.node.get_logger().warning(f"render: {exc}")
            return response
        except NotFittedError as exc:
            response.result = codes.RESULT_MAP_DOES_NOT_EXIST
            self.node.get_logger().warning(f"render: {exc}")
            return response
        except (GpomapError, MemoryError, ValueError) as exc:
            response.result = codes.RESULT_UNDEFINED_FAILURE
            self.node.get_logger().warning(f"render: {exc}")
            return response
        response.map = self._grid_message(layers, getattr(layers, req.layer), _time(self.live.stamp or 0.0))
        response.result = codes.RESULT_SUCCESS
        return response

    def _on_query(self, msg: Any) -> None:
        from gpomap.ros2.queries import RESULT_FIELDS, RESULT_POINT_STEP, points_from_cloud, result_cloud_data

        source = self.node.resolve_topic_name("~/query")
        frame = str(msg.header.frame_id).lstrip("/")
        try:
            if frame and frame != self.settings.node.fixed_frame:
                raise InputFormatError(
                    f"{source}: points in frame {frame!r}, expected fixed_frame {self.settings.node.fixed_frame!r}"
                )
            points = points_from_cloud(msg, source, dim=self.live.dim)
        except InputFormatError as exc:
            # The answer still goes out, empty, so that a caller waiting for it is not left hanging.
            self.node.get_logger().warning(str(exc))
            points = np.empty((0, self.live.dim))
        try:
            if len(points):
                probability, variance, ternary = self.live.query(points)
            else:
                probability, variance, ternary = np.empty(0), np.empty(0), np.empty(0, dtype=np.int8)
        except NotFittedError:
            probability = variance = np.full(len(points), np.nan)
            ternary = np.full(len(points), -1, dtype=np.int8)
        out = self._cloud_type()
        out.header = msg.header
        out.height, out.width = 1, len(points)
        names = ("x", "y", "z")[: self.live.dim] + tuple(name for name, _ in RESULT_FIELDS[2:])
        step = RESULT_POINT_STEP + 8 * (self.live.dim - 2)
        out.fields = [self._field_type(name=name, offset=8 * i, datatype=8, count=1) for i, name in enumerate(names)]
        out.is_bigendian = False
        out.point_step = step
        out.row_step = step * len(points)
        out.data = array.array("B", result_cloud_data(points, probability, variance, ternary))
        out.is_dense = bool(np.isfinite(probability).all())
        self.query_publisher.publish(out)

    # ------------------------------------------------------------------ loop
    def spin(self, ok: Callable[[], bool]) -> None:
        """Feed the mapper and publish until `ok()` turns false (ROS shuts down)."""
        period = 1.0 / self.settings.node.publish_rate
        next_publish = time.monotonic() + period
        while ok():
            self._wake.wait(timeout=max(0.0, min(0.05, next_publish - time.monotonic())))
            self._wake.clear()
            # Catch up on scans only until the next map is due: the map goes out at its rate.
            self.live.process(self.poses.lookup, budget=max(0.0, next_publish - time.monotonic()))
            if time.monotonic() >= next_publish:
                self.publish()
                next_publish = time.monotonic() + period


def make_cloud_map(settings: NodeSettings, source: str) -> Any:
    """The :class:`~gpomap.ros.live.LiveMap` of clouds over a new 3-D streaming mapper with these settings."""
    from gpomap.ros.live import LiveMap
    from gpomap.streaming import StreamingGPOM

    mapper = StreamingGPOM(
        warmup_scans=settings.warmup_scans,
        max_refits=settings.max_refits,
        tile_size=settings.tile_size,
        n_workers=1,
        thresholds=settings.thresholds,
        **settings.model,
    )
    return LiveMap(
        mapper,
        settings.resolution,
        extent=settings.extent,
        time_offset=settings.time_offset,
        max_range=settings.max_range,
        pose_wait=settings.pose_wait,
        source=source,
        kind="cloud",
    )


def _usage() -> str:
    lines = [
        "usage: gpomap-ros2 [--ros-args -p NAME:=VALUE ... -r FROM:=TO ...]",
        "",
        "gpomap's ROS 2 mapping node (docs/ros2.md). Parameters and their defaults:",
    ]
    lines += [f"  {name}: {json.dumps(default)}" for name, default in PARAMETERS.items()]
    lines.append("  model.<option>: AreaGPOM options, e.g. model.kernel:=se")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node (``gpomap-ros2`` or ``python -m gpomap.ros2``); returns the exit code."""
    args = list(sys.argv if argv is None else [sys.argv[0], *argv])
    if "--ros-args" not in args and any(a in ("-h", "--help") for a in args[1:]):
        print(_usage())
        return 0
    try:
        import rclpy
        from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
        from rclpy.utilities import remove_ros_args
    except ImportError as exc:
        print(f"gpomap-ros2: error: rclpy is not importable ({exc}); install it with {_INSTALL}", file=sys.stderr)
        return 1
    try:
        extra = remove_ros_args(args)[1:]
    except Exception as exc:  # rclpy's RCLInvalidROSArgsError: a --ros-args rcl could not parse
        print(f"gpomap-ros2: error: {str(exc).split(', at ')[0]}", file=sys.stderr)
        return 1
    if extra:
        print(f"gpomap-ros2: error: unexpected argument(s) {' '.join(extra)}; settings are ROS 2 parameters:", file=sys.stderr)
        print(_usage(), file=sys.stderr)
        return 2
    from gpomap.progress import set_progress_mode

    rclpy.init(args=args)
    # No progress bars in a node's log: the ~/status topic says how it goes.
    set_progress_mode("quiet")
    node = rclpy.create_node("gpomap", automatically_declare_parameters_from_overrides=True)
    try:
        settings = read_settings(node)
        adapter = Ros2Node(node, settings)
    except (GpomapError, ImportError, TypeError, ValueError) as exc:
        # TypeError / ValueError: a model.<option> AreaGPOM does not take, or a value it refuses.
        if isinstance(exc, ImportError):
            message = f"{exc}; install the message packages with {_INSTALL}"
        else:
            message = f"model.<option> parameters: {exc}" if isinstance(exc, TypeError) else str(exc)
        print(f"gpomap-ros2: error: {message}", file=sys.stderr)
        node.destroy_node()
        rclpy.try_shutdown()
        return 1
    s = settings.node
    node.get_logger().info(
        f"mapping {adapter.scan_topic} with poses from {node.resolve_topic_name(settings.odom_topic)} in frame {s.fixed_frame} "
        f"at {s.resolution:g} m, publishing at {s.publish_rate:g} Hz"
    )
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def serve() -> None:
        with contextlib.suppress(ExternalShutdownException):
            executor.spin()

    thread = threading.Thread(target=serve, name="gpomap-ros2-executor", daemon=True)
    thread.start()
    try:
        # SIGINT: rclpy shuts its context down and passes the signal on; end as on SIGTERM.
        with contextlib.suppress(KeyboardInterrupt):
            adapter.spin(rclpy.ok)
    finally:
        if s.save_on_shutdown and adapter.live.ready:
            files = adapter.live.save(s.save_directory)
            print("gpomap-ros2: saved " + ", ".join(str(f) for f in files), file=sys.stderr)
        executor.shutdown(timeout_sec=5)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
