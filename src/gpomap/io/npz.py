"""Occupancy maps as NumPy ``.npz`` archives: everything an :class:`OccupancyMap` holds, losslessly.

Arrays in the archive (no pickles; it loads with ``allow_pickle=False``):

=================  ================  ===========================================================
key                shape / dtype     meaning
=================  ================  ===========================================================
``format``         () str            ``"gpomap-occupancy-map"``, to recognise the file
``version``        () int64          layout version, currently 1
``probability``    (ny, nx) float64  occupancy probability, row 0 at the lowest y
``origin``         (2,) float64      lower-left corner of the grid, metres
``resolution``     () float64        cell side, metres
``thresholds``     (2,) float64      free-below, occupied-above
``ternary``        (ny, nx) int8     FREE 0 / OCCUPIED 1 / UNKNOWN -1 (for other tools; recomputed on load)
``variance``       (ny, nx) float64  optional: latent variance
``seen_through``   (ny, nx) bool     optional: cells beams crossed and none ended in, never occupied
``path``           (k, 2) float64    optional: robot path
``info``           () str            optional: ``OccupancyMap.info`` as JSON
=================  ================  ===========================================================
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import InputFormatError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.checks import load_npz, regular_file
from gpomap.io.members import write_npz

__all__ = ["save_map", "load_map"]

FORMAT = "gpomap-occupancy-map"
VERSION = 1
REQUIRED = ("probability", "origin", "resolution", "thresholds")


def _json_default(value: Any) -> Any:
    """Make NumPy values and paths JSON-serialisable; anything else is an error."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def save_map(occupancy_map: OccupancyMap, path: str | os.PathLike[str]) -> Path:
    """Write `occupancy_map` to `path` as an ``.npz`` (its arrays deflated where that pays), atomically.

    Parameters
    ----------
    occupancy_map : OccupancyMap
    path : str or path-like
        Written exactly as given: unlike :func:`numpy.savez`, no ``.npz`` suffix is appended.

    Returns
    -------
    Path
        `path`.

    Raises
    ------
    ValueError
        ``occupancy_map.info`` cannot be written as JSON (it may hold numbers, strings, lists, dicts,
        NumPy scalars and arrays). Tuples come back as lists.
    """
    m = occupancy_map
    try:
        info_json = json.dumps(m.info, default=_json_default, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"map info cannot be saved as JSON: {exc}") from exc
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, dtype=np.int64),
        "probability": np.asarray(m.probability, dtype=np.float64),
        "origin": np.asarray(m.grid.origin, dtype=np.float64),
        "resolution": np.array(m.grid.resolution, dtype=np.float64),
        "thresholds": np.asarray(m.thresholds, dtype=np.float64),
        "ternary": m.ternary,
        "info": np.array(info_json),
    }
    if m.variance is not None:
        arrays["variance"] = np.asarray(m.variance, dtype=np.float64)
    if m.seen_through is not None:
        arrays["seen_through"] = np.asarray(m.seen_through, dtype=bool)
    if m.path is not None:
        arrays["path"] = np.asarray(m.path, dtype=np.float64)
    target = Path(path)
    write_npz(target, arrays)
    return target


def _shape_error(key: str, expected: str, got: tuple[int, ...], path: str) -> InputFormatError:
    return InputFormatError(f"array '{key}' must have shape {expected}, got {got}", path=path)


def _real(data: dict[str, np.ndarray], key: str, path: str) -> np.ndarray:
    """`data[key]` as float64, refusing strings, complex numbers and other non-real dtypes."""
    a = data[key]
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer) or a.dtype == bool):
        raise InputFormatError(f"array '{key}' has dtype {a.dtype}; expected real numbers", path=path)
    return np.asarray(a, dtype=np.float64)


def _flags(data: dict[str, np.ndarray], key: str, path: str) -> np.ndarray:
    """`data[key]` as bool, refusing any dtype but bool (a map's own flags are saved as bool)."""
    a = data[key]
    if a.dtype != bool:
        raise InputFormatError(f"array '{key}' has dtype {a.dtype}; expected bool", path=path)
    return np.asarray(a, dtype=bool)


def load_map(path: str | os.PathLike[str]) -> OccupancyMap:
    """Read a map written by :func:`save_map`.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    OccupancyMap
        With variance, seen-through cells, path and info when the file has them (``info`` is ``{}``
        otherwise).

    Raises
    ------
    InputFormatError
        The file is missing or not an ``.npz``; a required array (probability, origin, resolution,
        thresholds) is missing; shapes disagree (variance, ternary or seen_through not the
        probability's shape, origin not (2,), path not (k, 2)); seen_through is not bool;
        resolution or thresholds are invalid; info is not JSON.
    """
    name = str(path)
    p = regular_file(path, "gpomap .npz map file")
    try:
        with p.open("rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise InputFormatError(f"cannot read the map file ({exc})", path=name) from None
    # Check the zip signature first, to say what the file is instead.
    if not head.startswith(b"PK"):
        found = "a single-array .npy file" if head.startswith(b"\x93NUMPY") else f"a file starting with {head!r}"
        raise InputFormatError(f"not a NumPy .npz map file (a zip archive): found {found}", path=name)
    data = load_npz(p, "NumPy .npz map file")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise InputFormatError(f"map file is missing the required array(s) {', '.join(map(repr, missing))}", path=name)
    if "format" in data and str(data["format"]) != FORMAT:
        raise InputFormatError(f"not a gpomap map file: format is {str(data['format'])!r}", path=name)
    version = VERSION
    if "version" in data:
        v = data["version"]
        if v.shape != () or not np.issubdtype(v.dtype, np.integer):
            raise InputFormatError(f"array 'version' must be one integer, got {v.dtype} of shape {v.shape}", path=name)
        version = int(v)
    if version > VERSION:
        raise InputFormatError(f"map file version {version} is newer than this gpomap reads ({VERSION})", path=name)

    probability = _real(data, "probability", name)
    if probability.ndim != 2:
        raise _shape_error("probability", "(ny, nx)", probability.shape, name)
    origin = _real(data, "origin", name)
    if origin.shape != (2,):
        raise _shape_error("origin", "(2,)", origin.shape, name)
    resolution = _real(data, "resolution", name)
    if resolution.size != 1:
        raise _shape_error("resolution", "() (one number)", resolution.shape, name)
    thresholds = _real(data, "thresholds", name)
    if thresholds.shape != (2,):
        raise _shape_error("thresholds", "(2,)", thresholds.shape, name)
    for key in ("variance", "ternary", "seen_through"):
        if key in data and data[key].shape != probability.shape:
            raise _shape_error(key, f"{probability.shape} (the probability's)", data[key].shape, name)
    robot_path = None
    if "path" in data:
        robot_path = _real(data, "path", name)
        if robot_path.ndim != 2 or robot_path.shape[1] != 2:
            raise _shape_error("path", "(k, 2)", robot_path.shape, name)
    info: dict[str, Any] = {}
    if "info" in data:
        try:
            info = json.loads(str(data["info"]))
        except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError
            raise InputFormatError(f"array 'info' is not valid JSON: {str(exc)[:200]}", path=name) from None
        if not isinstance(info, dict):
            raise InputFormatError(f"array 'info' must hold a JSON object, got {type(info).__name__}", path=name)

    try:
        grid = GridSpec((origin[0], origin[1]), float(resolution.reshape(())), probability.shape)
        variance = _real(data, "variance", name) if "variance" in data else None
        seen_through = _flags(data, "seen_through", name) if "seen_through" in data else None
        lo, hi = (float(t) for t in thresholds)
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"thresholds must satisfy 0 <= free <= occupied <= 1, got ({lo}, {hi})")
        return OccupancyMap(
            grid, probability, variance=variance, thresholds=(lo, hi), path=robot_path, info=info, seen_through=seen_through
        )
    except (ValueError, TypeError) as exc:
        raise InputFormatError(str(exc), path=name) from None
