"""PCD point clouds (PCL's format; ascii, binary and binary_compressed) as :class:`CloudScan`.

The data are decoded by pypcd4. The header is checked here first, line by line, so a bad file
gets a message naming the line and what was expected, and so that sizes announced by the
header (``POINTS``, the compressed block's lengths) are compared with what the file holds before
anything is allocated.

Pose. ``VIEWPOINT tx ty tz qw qx qy qz`` is the sensor pose. By default the points are taken as
already in the map frame and the rays start at the viewpoint's position (``points_frame="map"``):
simulated benchmark scans are often stored so (their ``VIEWPOINT`` rotation the identity and the
points world coordinates). With ``points_frame="sensor"`` the points are transformed by the
viewpoint pose first. A `pose` given by the caller (a row of a poses file) replaces the
viewpoint, and the points are then in the sensor frame.

Max range. With `max_range`, a point farther than that from the origin is a no-return ray: free
up to `max_range` along its direction, never a hit (OctoMap's ``insertPointCloud`` treats such
rays the same way). Points with a non-finite coordinate (PCL's NaN for "no reading") are kept as
invalid rays.
"""

from __future__ import annotations

import os
import struct

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan, cloud_from_points
from gpomap.errors import InputFormatError
from gpomap.extras import require
from gpomap.io.checks import regular_file
from gpomap.io.poses import pose_from_viewpoint, transform_points

__all__ = ["read_pcd", "is_pcd", "PCD_KEYS", "MAX_PCD_BYTES"]

#: Header keys, in the order PCD v0.7 requires them.
PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_ENCODINGS = ("ascii", "binary", "binary_compressed")
#: Most bytes of decoded point data (a compressed block can announce any size).
MAX_PCD_BYTES = 1 << 31
_MAX_HEADER_LINES = 64


def is_pcd(head: bytes) -> bool:
    """Whether the start of a file looks like a PCD header."""
    text = head[:512].decode("latin-1")
    return text.startswith("# .PCD") or text.startswith("VERSION") or ("\nFIELDS " in text and "\nDATA " in text)


def _header(path: str) -> tuple[dict[str, list[str]], int]:
    """The header's values by key (line numbers checked) and the byte offset of the data."""
    values: dict[str, list[str]] = {}
    offset = 0
    with open(path, "rb") as f:
        for lineno in range(1, _MAX_HEADER_LINES + 1):
            raw = f.readline(4096)
            if not raw:
                raise InputFormatError(f"file ends in the header after {lineno - 1} lines; expected a DATA line", path=path)
            offset += len(raw)
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise InputFormatError(
                    "header line is not text; expected a PCD header (VERSION, FIELDS, ... DATA)", path=path, line=lineno
                ) from None
            if not line or line.startswith("#"):
                continue
            key, *rest = line.split()
            if key not in PCD_KEYS:
                raise InputFormatError(
                    f"unknown header key {key!r}; expected one of {', '.join(PCD_KEYS)}", path=path, line=lineno
                )
            if key in values:
                raise InputFormatError(f"second {key} line", path=path, line=lineno)
            values[key] = rest
            values[f"_line_{key}"] = [str(lineno)]
            if key == "DATA":
                break
        else:
            raise InputFormatError(f"no DATA line in the first {_MAX_HEADER_LINES} lines; expected a PCD header", path=path)
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "POINTS", "DATA"):
        if key not in values:
            raise InputFormatError(f"header has no {key} line; expected {', '.join(PCD_KEYS)}", path=path)
    return values, offset


def _line(values: dict[str, list[str]], key: str) -> int:
    return int(values[f"_line_{key}"][0])


def _ints(values: dict[str, list[str]], key: str, path: str, n: int | None = None) -> list[int]:
    try:
        out = [int(v) for v in values[key]]
    except ValueError:
        raise InputFormatError(
            f"{key} values must be integers, got {' '.join(values[key])!r}", path=path, line=_line(values, key)
        ) from None
    if (n is not None and len(out) != n) or any(v < 0 for v in out):
        want = f"{n} non-negative integers" if n is not None else "non-negative integers"
        raise InputFormatError(f"{key} has {' '.join(values[key])!r}; expected {want}", path=path, line=_line(values, key))
    return out


def _check_header(values: dict[str, list[str]], data_offset: int, path: str) -> tuple[int, NDArray[np.float64]]:
    """Check the header against itself and the file size; return (points, viewpoint (7,))."""
    fields = values["FIELDS"]
    n_fields = len(fields)
    for name in ("x", "y", "z"):
        if name not in fields:
            raise InputFormatError(
                f"FIELDS {' '.join(fields)!r} has no {name!r}; expected x y z among them", path=path, line=_line(values, "FIELDS")
            )
    sizes = _ints(values, "SIZE", path, n_fields)
    counts = _ints(values, "COUNT", path, n_fields) if "COUNT" in values else [1] * n_fields
    types = values["TYPE"]
    if len(types) != n_fields or any(t not in ("F", "I", "U") for t in types):
        raise InputFormatError(
            f"TYPE {' '.join(types)!r}; expected one of F, I, U per field ({n_fields})", path=path, line=_line(values, "TYPE")
        )
    for name in ("x", "y", "z"):
        i = fields.index(name)
        if types[i] != "F" or sizes[i] not in (4, 8) or counts[i] != 1:
            raise InputFormatError(
                f"field {name!r} is TYPE {types[i]} SIZE {sizes[i]} COUNT {counts[i]}; expected a float (F, 4 or 8 bytes, count 1)",
                path=path,
                line=_line(values, "TYPE"),
            )
    (n_points,) = _ints(values, "POINTS", path, 1)
    width = _ints(values, "WIDTH", path, 1)[0]
    height = _ints(values, "HEIGHT", path, 1)[0] if "HEIGHT" in values else 1
    if width * height != n_points:
        raise InputFormatError(
            f"POINTS {n_points} but WIDTH x HEIGHT = {width} x {height}; expected equal", path=path, line=_line(values, "POINTS")
        )
    encoding = values["DATA"][0].lower() if values["DATA"] else ""
    if encoding not in _ENCODINGS:
        raise InputFormatError(
            f"DATA {' '.join(values['DATA'])!r}; expected ascii, binary or binary_compressed",
            path=path,
            line=_line(values, "DATA"),
        )
    viewpoint = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    if "VIEWPOINT" in values:
        try:
            viewpoint = np.array([float(v) for v in values["VIEWPOINT"]])
            pose_from_viewpoint(viewpoint)
        except ValueError as exc:
            raise InputFormatError(
                f"VIEWPOINT {' '.join(values['VIEWPOINT'])!r}: {exc}", path=path, line=_line(values, "VIEWPOINT")
            ) from None
    row = sum(s * c for s, c in zip(sizes, counts))
    n_bytes = n_points * row
    if n_bytes > MAX_PCD_BYTES:
        raise InputFormatError(
            f"POINTS {n_points} of {row} bytes each is {n_bytes:,} bytes; at most {MAX_PCD_BYTES:,} are read", path=path
        )
    remaining = os.stat(path).st_size - data_offset
    if encoding == "binary" and remaining < n_bytes:
        raise InputFormatError(
            f"binary data is {remaining:,} bytes; POINTS {n_points} x {row} bytes per point needs {n_bytes:,} (truncated file?)",
            path=path,
        )
    if encoding == "binary_compressed" and n_points:
        with open(path, "rb") as f:
            f.seek(data_offset)
            sizes_raw = f.read(8)
        if len(sizes_raw) < 8:
            raise InputFormatError("binary_compressed data ends before its two size words", path=path)
        compressed, uncompressed = struct.unpack("<II", sizes_raw)
        if uncompressed != n_bytes or compressed > remaining - 8:
            raise InputFormatError(
                f"binary_compressed block announces {compressed:,} compressed bytes ({remaining - 8:,} in the file) and "
                f"{uncompressed:,} uncompressed; expected {n_bytes:,} uncompressed (POINTS {n_points} x {row} bytes)",
                path=path,
            )
    return n_points, viewpoint


def read_pcd(
    path: str | os.PathLike[str],
    pose: NDArray[np.float64] | None = None,
    points_frame: str = "map",
    max_range: float | None = None,
    time: float | None = None,
) -> CloudScan:
    """Read one PCD file as a :class:`~gpomap.clouds.CloudScan`.

    Parameters
    ----------
    path : path-like
    pose : ndarray of shape (4, 4), optional
        Sensor-to-map pose replacing the file's ``VIEWPOINT``; the points are then in the sensor
        frame and are transformed by it.
    points_frame : {"map", "sensor"}
        With the ``VIEWPOINT`` pose: whether the stored points are already in the map frame (the
        default, as simulated benchmark scans often are) or in the sensor frame.
    max_range : float, optional
        Points farther than this from the sensor become no-return rays ending at `max_range`.
    time : float, optional
        Stamp of the cloud.

    Returns
    -------
    CloudScan
        ``meta`` holds ``path``, ``fields``, ``encoding`` and ``viewpoint`` (7,).

    Raises
    ------
    InputFormatError
        Not a regular file; a header line that is not ``KEY values``, a missing or repeated key,
        no x, y or z float fields, sizes that disagree (WIDTH x HEIGHT against POINTS, the data
        against POINTS); a VIEWPOINT that is not 7 numbers with a unit quaternion; data pypcd4
        cannot decode (bad ascii numbers, a corrupt compressed block).
    """
    PointCloud = require("pypcd4", "reading PCD files").PointCloud

    if points_frame not in ("map", "sensor"):
        raise ValueError(f"points_frame must be 'map' or 'sensor', got {points_frame!r}")
    p = regular_file(path, "PCD point cloud")
    spath = str(p)
    try:
        values, offset = _header(spath)
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc})", path=spath) from None
    n_points, viewpoint = _check_header(values, offset, spath)
    try:
        cloud = PointCloud.from_path(p)
        data = cloud.pc_data
    except InputFormatError:
        raise
    except Exception as exc:  # pypcd4 raises ValueError, RuntimeError, lzf and pydantic errors on bad data
        raise InputFormatError(f"cannot decode the PCD data ({type(exc).__name__}: {str(exc)[:200]})", path=spath) from None
    if data.shape[0] != n_points:
        raise InputFormatError(f"data holds {data.shape[0]} points; POINTS says {n_points}", path=spath)
    xyz = np.column_stack([np.asarray(data[k], dtype=float) for k in ("x", "y", "z")]).reshape(-1, 3)
    sensor_pose = pose_from_viewpoint(viewpoint) if pose is None else np.asarray(pose, dtype=float)
    if pose is not None or points_frame == "sensor":
        xyz = transform_points(sensor_pose, xyz)
    return cloud_from_points(
        sensor_pose[:3, 3],
        xyz,
        max_range=max_range,
        time=time,
        meta={"path": spath, "fields": list(values["FIELDS"]), "encoding": values["DATA"][0].lower(), "viewpoint": viewpoint},
    )
