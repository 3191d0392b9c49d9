"""The ROS 1 node: ``sensor_msgs/LaserScan`` and tf in, ``nav_msgs/OccupancyGrid`` out.

A thin rospy adapter over :class:`gpomap.ros.live.LiveMap` (which holds the streaming mapper):
the scan subscription queues messages, tf2 gives each scan's laser pose in the fixed frame, and
the node's main loop feeds the mapper and publishes the map at ``~publish_rate`` (Hz of wall
time: the map costs the machine's time whatever the ROS clock, e.g. a bag played at 20x).

Topics (relative names, remap them as usual):

- subscribed: ``~scan_topic`` (``scan``), ``/tf``, ``/tf_static``;
- published (latched): ``map`` (trinary, map_server's 0 free / 100 occupied / -1 unknown),
  ``map_probability`` (occupancy in percent, 0..100), ``map_variance`` (latent variance in
  percent of the prior variance, 100 = nothing known), and ``~status`` (``std_msgs/String``,
  JSON: scans used, dropped, latency).

Service ``~save_map`` (``std_srvs/Trigger``): writes ``map.yaml`` + ``map.pgm``, ``map.npz``,
``map.png`` and the fitted map ``map.gpom`` into ``~save_directory`` as one set.

Parameters: see :func:`settings_from_params`. The settings are read and checked without rospy,
so a wrong value is one clear line and exit code 1 before any subscription.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from gpomap.errors import GpomapError
from gpomap.streaming import DEFAULT_TILE_SIZE, DEFAULT_WARMUP_SCANS

__all__ = ["NodeSettings", "settings_from_params", "main"]

_ROS_HELP = (
    "the ROS 1 Python packages (rospy, tf2_ros, nav_msgs, sensor_msgs, std_srvs) are not importable from this Python "
    "({exc}); on Debian: apt-get install ros-core python3-rospy python3-tf2-ros python3-nav-msgs python3-sensor-msgs "
    "python3-std-srvs, then run gpomap from a venv made with `/usr/bin/python3 -m venv --system-site-packages`"
)


@dataclass(frozen=True)
class NodeSettings:
    """The node's parameters, checked (see :func:`settings_from_params` for their meaning)."""

    scan_topic: str = "scan"
    fixed_frame: str = "odom"
    resolution: float = 0.05
    publish_rate: float = 1.0
    extent: tuple[float, float, float, float] | None = None
    time_offset: float = 0.0
    max_range: float | None = None
    pose_wait: float = 1.0
    warmup_scans: int = DEFAULT_WARMUP_SCANS
    max_refits: int | None = None
    tile_size: float = DEFAULT_TILE_SIZE
    thresholds: tuple[float, float] | None = None
    save_directory: str = "gpomap-map"
    save_on_shutdown: bool = False
    model: dict[str, Any] = field(default_factory=dict)


def _number(name: str, value: Any, low: float | None = None, strict: bool = True, optional: bool = False) -> float | None:
    if optional and value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise GpomapError(f"parameter ~{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or (low is not None and (v <= low if strict else v < low)):
        bound = "" if low is None else f" {'>' if strict else '>='} {low:g}"
        raise GpomapError(f"parameter ~{name} must be a finite number{bound}, got {value!r}")
    return v


def settings_from_params(get: Callable[[str, Any], Any]) -> NodeSettings:
    """Read and check the node's private parameters.

    Parameters
    ----------
    get : callable
        ``get(name, default)`` for a private parameter (``rospy.get_param("~" + name, default)``,
        or a dict's ``get`` in tests).

    Returns
    -------
    NodeSettings
        ``scan_topic`` (default ``scan``), ``fixed_frame`` (``odom``), ``resolution`` (m, 0.05),
        ``publish_rate`` (Hz of wall time, 1.0), ``extent`` ([xmin, xmax, ymin, ymax], default
        the data's), ``time_offset`` (s added to scan stamps before the tf lookup, 0),
        ``max_range`` (no-return threshold, default each message's ``range_max``),
        ``pose_wait`` (s a scan waits for its tf before it is dropped, 1.0), ``warmup_scans``
        (scans before the hyperparameters are learnt and the first map, 30), ``max_refits``
        (most tiles refitted per map published, oldest first; default no limit), ``tile_size`` (m,
        5), ``thresholds`` ([free, occupied]; default a calibrated map's, 0.196 and 0.5,
        :data:`gpomap.grid.CALIBRATED_THRESHOLDS`), ``save_directory`` (``gpomap-map``),
        ``save_on_shutdown`` (false), ``model`` (a dict of :class:`~gpomap.mapping.AreaGPOM`
        options, e.g. ``{kernel: se, free_step: 0.1}``).

    Raises
    ------
    GpomapError
        A value of the wrong type or out of range, naming the parameter.
    """
    d = NodeSettings()
    extent = get("extent", None)
    if extent is not None and extent != []:
        if not isinstance(extent, Sequence) or isinstance(extent, str) or len(extent) != 4:
            raise GpomapError(f"parameter ~extent must be [xmin, xmax, ymin, ymax] in metres, got {extent!r}")
        e = tuple(_number("extent", v) or 0.0 for v in extent)
        if not (e[0] < e[1] and e[2] < e[3]):
            raise GpomapError(f"parameter ~extent must have xmin < xmax and ymin < ymax, got {extent!r}")
        extent = (e[0], e[1], e[2], e[3])
    else:
        extent = None
    given = get("thresholds", None)
    thresholds: tuple[float, float] | None = None
    if given is not None and given != []:
        if not isinstance(given, Sequence) or isinstance(given, str) or len(given) != 2:
            raise GpomapError(f"parameter ~thresholds must be [free, occupied], got {given!r}")
        lo, hi = (_number("thresholds", v) or 0.0 for v in given)
        if not 0 <= lo <= hi <= 1:
            raise GpomapError(f"parameter ~thresholds must satisfy 0 <= free <= occupied <= 1, got {given!r}")
        thresholds = (lo, hi)
    model = get("model", {}) or {}
    if not isinstance(model, dict):
        raise GpomapError(f"parameter ~model must be a dict of AreaGPOM options, got {model!r}")
    warmup = get("warmup_scans", d.warmup_scans)
    if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 1:
        raise GpomapError(f"parameter ~warmup_scans must be an integer >= 1, got {warmup!r}")
    max_refits = get("max_refits", d.max_refits)
    if max_refits is not None and (isinstance(max_refits, bool) or not isinstance(max_refits, int) or max_refits < 1):
        raise GpomapError(f"parameter ~max_refits must be an integer >= 1 (or unset: no limit), got {max_refits!r}")
    save_on_shutdown = get("save_on_shutdown", d.save_on_shutdown)
    if not isinstance(save_on_shutdown, bool):
        raise GpomapError(f"parameter ~save_on_shutdown must be true or false, got {save_on_shutdown!r}")
    return NodeSettings(
        scan_topic=str(get("scan_topic", d.scan_topic)),
        fixed_frame=str(get("fixed_frame", d.fixed_frame)).lstrip("/"),
        resolution=float(_number("resolution", get("resolution", d.resolution), 0.0) or d.resolution),
        publish_rate=float(_number("publish_rate", get("publish_rate", d.publish_rate), 0.0) or d.publish_rate),
        extent=extent,
        time_offset=float(_number("time_offset", get("time_offset", d.time_offset)) or 0.0),
        max_range=_number("max_range", get("max_range", None), 0.0, optional=True),
        pose_wait=float(_number("pose_wait", get("pose_wait", d.pose_wait), 0.0, strict=False) or 0.0),
        warmup_scans=int(warmup),
        max_refits=max_refits,
        tile_size=float(_number("tile_size", get("tile_size", d.tile_size), 0.0) or d.tile_size),
        thresholds=thresholds,
        save_directory=str(get("save_directory", d.save_directory)),
        save_on_shutdown=save_on_shutdown,
        model=dict(model),
    )


def make_live_map(settings: NodeSettings, source: str) -> Any:
    """The :class:`~gpomap.ros.live.LiveMap` over a new streaming mapper with these settings."""
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
    )


class RosNode:
    """The rospy wiring of a :class:`~gpomap.ros.live.LiveMap` (see the module's docstring)."""

    def __init__(self, settings: NodeSettings) -> None:
        import rospy
        import tf2_ros
        from nav_msgs.msg import OccupancyGrid
        from sensor_msgs.msg import LaserScan
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        self.rospy = rospy
        self.settings = settings
        self._grid_type = OccupancyGrid
        self._string_type = String
        self.live = make_live_map(settings, source=rospy.resolve_name(settings.scan_topic))
        self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(60.0))
        self._tf_errors = (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException)
        self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        self._wake = threading.Event()
        self.publishers = {
            name: rospy.Publisher(name, OccupancyGrid, queue_size=1, latch=True)
            for name in ("map", "map_probability", "map_variance")
        }
        self.status_publisher = rospy.Publisher("~status", String, queue_size=1, latch=True)
        # A deep queue: the callback only appends, the main loop drains it.
        self.subscriber = rospy.Subscriber(settings.scan_topic, LaserScan, self._on_scan, queue_size=1000)
        self.service = rospy.Service("~save_map", Trigger, self._on_save)
        self._published: tuple[int, ...] = ()
        self._published_scans = -1

    def _on_scan(self, msg: Any) -> None:
        self.live.receive(msg)
        self._wake.set()

    def lookup(self, frame: str, seconds: float) -> tuple[float, float, float, bool] | None:
        """The laser frame's pose in the fixed frame at `seconds` and whether it is upside down,
        from tf2; None while unknown."""
        from gpomap.ros.messages import is_upside_down, pose_from_transform

        try:
            tr = self.tf_buffer.lookup_transform(self.settings.fixed_frame, frame, self.rospy.Time.from_sec(seconds))
        except self._tf_errors:
            return None
        return (*pose_from_transform(tr.transform.translation, tr.transform.rotation), is_upside_down(tr.transform.rotation))

    def _message(self, layers: Any, data: Any, stamp: Any) -> Any:
        msg = self._grid_type()
        msg.header.frame_id = self.settings.fixed_frame
        msg.header.stamp = stamp
        msg.info.map_load_time = stamp
        msg.info.resolution = layers.grid.resolution
        msg.info.width = layers.width
        msg.info.height = layers.height
        msg.info.origin.position.x, msg.info.origin.position.y = layers.grid.origin
        msg.info.origin.orientation.w = 1.0
        msg.data = data.tolist()
        return msg

    def publish(self) -> bool:
        """Publish the three grids if the map changed, and the status if any count did; returns whether a map went out."""
        status = self.live.status()
        counts = tuple(status[k] for k in ("n_received", "n_used", "n_dropped_no_pose", "n_rejected", "n_waiting"))
        if counts == self._published:
            return False
        self._published = counts
        if status["n_used"] == self._published_scans or not status["ready"]:
            self.status_publisher.publish(self._string_type(data=json.dumps(status)))
            return False
        t = time.perf_counter()
        layers = self.live.layers()
        if layers is None:
            return False
        stamp = self.rospy.Time.from_sec(self.live.stamp or 0.0)
        for name, data in (("map", layers.trinary), ("map_probability", layers.probability), ("map_variance", layers.variance)):
            self.publishers[name].publish(self._message(layers, data, stamp))
        self._published_scans = status["n_used"]
        status["publish_seconds"] = time.perf_counter() - t
        status["width"], status["height"] = layers.width, layers.height
        self.status_publisher.publish(self._string_type(data=json.dumps(status)))
        return True

    def _on_save(self, request: Any) -> Any:
        from std_srvs.srv import TriggerResponse

        try:
            files = self.live.save(self.settings.save_directory)
        except (GpomapError, OSError, ValueError) as exc:
            return TriggerResponse(success=False, message=str(exc))
        return TriggerResponse(success=True, message="wrote " + ", ".join(str(f) for f in files))

    def spin(self) -> None:
        """Feed the mapper and publish until ROS shuts down."""
        period = 1.0 / self.settings.publish_rate
        next_publish = time.monotonic() + period
        while not self.rospy.is_shutdown():
            self._wake.wait(timeout=max(0.0, min(0.05, next_publish - time.monotonic())))
            self._wake.clear()
            # Catch up on scans only until the next map is due: the map goes out at its rate.
            self.live.process(self.lookup, budget=max(0.0, next_publish - time.monotonic()))
            if time.monotonic() >= next_publish:
                self.publish()
                next_publish = time.monotonic() + period
        if self.settings.save_on_shutdown and self.live.ready:
            files = self.live.save(self.settings.save_directory)
            print("gpomap-ros: saved " + ", ".join(str(f) for f in files), file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the node (``gpomap-ros`` or ``python -m gpomap.ros``); returns the exit code."""
    try:
        import rospy
    except ImportError as exc:
        print(f"gpomap-ros: error: {_ROS_HELP.format(exc=exc)}", file=sys.stderr)
        return 1
    from gpomap.progress import set_progress_mode

    rospy.init_node("gpomap", argv=list(argv) if argv is not None else sys.argv, disable_signals=False)
    # No progress bars in a node's log: the ~status topic says how it goes.
    set_progress_mode("quiet")
    try:
        settings = settings_from_params(lambda name, default: rospy.get_param("~" + name, default))
        node = RosNode(settings)
    except (GpomapError, ImportError, TypeError, ValueError) as exc:
        # TypeError / ValueError: a ~model option AreaGPOM does not take, or a value it refuses.
        message = _ROS_HELP.format(exc=exc) if isinstance(exc, ImportError) else str(exc)
        print(f"gpomap-ros: error: {message}", file=sys.stderr)
        return 1
    rospy.loginfo(
        "gpomap: mapping %s in frame %s at %g m, publishing at %g Hz",
        rospy.resolve_name(settings.scan_topic),
        settings.fixed_frame,
        settings.resolution,
        settings.publish_rate,
    )
    node.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
