"""The ROS 2 node's requests, free of any ROS library: render a region, query points.

Custom service types need a colcon build, which ``pip install`` cannot do, so the node uses
types from the PyPI message packages:

- render: ``nav_msgs/srv/LoadMap``, whose response is an ``OccupancyGrid``; its request's one
  field, ``map_url``, carries the region as text (:func:`parse_render_request`);
- query: a topic pair of ``sensor_msgs/PointCloud2``: points (fields x, y) in, the same points with
  ``probability``, ``variance`` and ``ternary`` (the written map's call: 0 free, -1 unknown, 1
  occupied) out, under the request's header (:func:`points_from_cloud`, :func:`result_cloud_data`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError

__all__ = [
    "RenderRequest",
    "LAYERS",
    "parse_render_request",
    "points_from_cloud",
    "RESULT_FIELDS",
    "RESULT_POINT_STEP",
    "result_cloud_data",
]

#: The layers a render can return, as ``OccupancyGrid`` data (see :class:`gpomap.ros.messages.GridLayers`).
LAYERS = ("probability", "trinary", "variance")

#: ``sensor_msgs/PointField`` datatypes: FLOAT32 and FLOAT64.
_FLOAT_TYPES = {7: "f4", 8: "f8"}
#: The result cloud's fields: (name, byte offset); all FLOAT64, little-endian, 40 bytes a point.
RESULT_FIELDS = (("x", 0), ("y", 8), ("probability", 16), ("variance", 24), ("ternary", 32))
RESULT_POINT_STEP = 40


@dataclass(frozen=True)
class RenderRequest:
    """A region to render: cell side (None: the node's resolution), extent (None: the data's), layer."""

    resolution: float | None = None
    extent: tuple[float, float, float, float] | None = None
    layer: str = "probability"


def _float(key: str, text: str, request: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise InputFormatError(f"render request {request!r}: {key} must be a finite number, got {text!r}")
    return v


def parse_render_request(text: str) -> RenderRequest:
    """Read a render request: ``key=value`` items separated by ``&``, ``;`` or spaces.

    Keys: ``resolution`` (metres, > 0), ``extent`` (``xmin,xmax,ymin,ymax`` in metres) and
    ``layer`` (one of :data:`LAYERS`); each optional. Anything up to a ``?`` is ignored, so a
    URL such as ``gpomap:render?resolution=0.01&extent=0,2,0,1`` reads as its query part. An
    empty request renders the whole map at the node's resolution.

    Parameters
    ----------
    text : str

    Returns
    -------
    RenderRequest

    Raises
    ------
    InputFormatError
        An unknown key, a value that is not a number, a resolution <= 0, an extent that is not
        four numbers with xmin < xmax and ymin < ymax, or an unknown layer; naming the item.
    """
    body = text.split("?", 1)[1] if "?" in text else text
    resolution: float | None = None
    extent: tuple[float, float, float, float] | None = None
    layer = "probability"
    for item in (s for s in re.split(r"[&;\s]+", body.strip()) if s):
        key, sep, value = item.partition("=")
        key = key.strip().lower()
        if not sep:
            raise InputFormatError(f"render request {text!r}: item {item!r} is not key=value (keys: resolution, extent, layer)")
        if key == "resolution":
            resolution = _float("resolution", value, text)
            if resolution <= 0:
                raise InputFormatError(f"render request {text!r}: resolution must be > 0 metres, got {value!r}")
        elif key == "extent":
            parts = [p for p in value.split(",") if p.strip()]
            if len(parts) != 4:
                raise InputFormatError(f"render request {text!r}: extent must be xmin,xmax,ymin,ymax in metres, got {value!r}")
            e = [_float("extent", p, text) for p in parts]
            if not (e[0] < e[1] and e[2] < e[3]):
                raise InputFormatError(f"render request {text!r}: extent must have xmin < xmax and ymin < ymax, got {value!r}")
            extent = (e[0], e[1], e[2], e[3])
        elif key == "layer":
            layer = value.strip().lower()
            if layer not in LAYERS:
                raise InputFormatError(f"render request {text!r}: layer must be one of {', '.join(LAYERS)}, got {value!r}")
        else:
            raise InputFormatError(f"render request {text!r}: unknown key {key!r} (keys: resolution, extent, layer)")
    return RenderRequest(resolution, extent, layer)


def points_from_cloud(msg: Any, source: str = "query", dim: int = 2) -> NDArray[np.float64]:
    """The x, y (and z with `dim` 3) of a ``sensor_msgs/PointCloud2``'s points (other fields ignored).

    Parameters
    ----------
    msg : PointCloud2-like
        ``fields`` (name, offset, datatype), ``is_bigendian``, ``point_step``, ``row_step``,
        ``height``, ``width``, ``data``.
    source : str
        The topic, for error messages.
    dim : {2, 3}
        Read x, y or x, y, z.

    Returns
    -------
    ndarray of shape (height * width, dim)

    Raises
    ------
    InputFormatError
        No x or y field, a field that is not FLOAT32 or FLOAT64, or data shorter than the header says.
    """
    fields = {f.name: f for f in msg.fields}
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    axes = ("x", "y", "z")[:dim]
    for k in axes:
        if k not in fields:
            raise InputFormatError(
                f"{source}: PointCloud2 has no field {k!r} (fields: {', '.join(fields) or '(none)'}); expected {', '.join(axes)}"
            )
        f = fields[k]
        if f.datatype not in _FLOAT_TYPES:
            raise InputFormatError(
                f"{source}: PointCloud2 field {k!r} has datatype {f.datatype}; expected FLOAT32 (7) or FLOAT64 (8)"
            )
        names.append(k)
        formats.append(order + _FLOAT_TYPES[f.datatype])
        offsets.append(int(f.offset))
    step, row, h, w = int(msg.point_step), int(msg.row_step), int(msg.height), int(msg.width)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    fits = step > 0 and all(o + np.dtype(f).itemsize <= step for o, f in zip(offsets, formats))
    if not fits or row < w * step or data.size < h * row:
        raise InputFormatError(
            f"{source}: PointCloud2 of {data.size} data bytes for height {h}, width {w}, point_step {step}, row_step {row}, "
            f"fields {', '.join(axes)} at offsets {', '.join(map(str, offsets))}; expected height x row_step bytes and fields inside each point"
        )
    if h * w == 0:
        return np.empty((0, dim))
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rows = data[: h * row].reshape(h, row)[:, : w * step]
    pts = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype)
    return np.column_stack([pts[k] for k in axes]).astype(float)


def result_cloud_data(
    points: NDArray[np.float64], probability: NDArray[np.float64], variance: NDArray[np.float64], ternary: NDArray[np.int8]
) -> bytes:
    """The data bytes of the query result cloud: :data:`RESULT_FIELDS`, one point of 40 bytes each.

    Parameters
    ----------
    points : ndarray of shape (m, 2), or (m, 3) for a 3-D map (then z follows y and every field moves 8 bytes on)
    probability, variance : ndarray of shape (m,)
    ternary : ndarray of int, shape (m,)
        0 free, -1 unknown, 1 occupied; written as float64 like the other fields.

    Returns
    -------
    bytes
        ``m * RESULT_POINT_STEP`` bytes (8 more a point in 3-D), little-endian float64.
    """
    pts = np.asarray(points, float)
    pts = pts.reshape(-1, pts.shape[-1] if pts.ndim == 2 else 2)
    table = np.column_stack([pts, np.ravel(probability), np.ravel(variance), np.ravel(ternary)])
    return np.ascontiguousarray(table, dtype="<f8").tobytes()
