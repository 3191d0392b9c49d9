"""ROS map_server maps: a YAML file plus a PGM or PNG image.

The YAML keys (as ROS 1 ``map_server`` and ROS 2 ``nav2_map_server`` read them):

``image``
    Image file, relative to the YAML's directory (or absolute).
``resolution``
    Metres per pixel.
``origin``
    ``[x, y, yaw]``: pose of the lower-left pixel's lower-left corner. Only ``yaw = 0`` is supported.
``occupied_thresh``, ``free_thresh``
    Pixels with occupancy probability above / below these are occupied / free.
``negate``
    0: white is free, black occupied (p = (255 - v) / 255). 1: the reverse (p = v / 255).
``mode`` (optional)
    ``trinary`` (default): p > occupied_thresh occupied, p < free_thresh free, otherwise unknown.
    ``scale``: as trinary at the two ends, but the values between are kept as a graded occupancy;
    transparent pixels (alpha < 255, PNG only) are unknown.
    ``raw``: the pixel value *is* the occupancy in percent: v in 0..100 gives p = v / 100, and any other
    value (map_server writes 255; 101..254 are invalid) is unknown, with probability NaN here. ``negate``
    is ignored, as map_server ignores it.

Colour images are averaged over their colour channels, as ROS 1 map_server does. Row 0 of an image is
the top of the map; arrays here have row 0 at the lowest y, so readers and writers flip. The image
itself is read by :mod:`gpomap.io.mapimage`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.grid import FREE, OCCUPIED, GridSpec, OccupancyMap
from gpomap.io.atomic import atomic_write_group
from gpomap.io.checks import file_kind, regular_file
from gpomap.io.mapimage import MAX_PIXELS, read_map_image

__all__ = ["RosMap", "read_rosmap", "write_rosmap", "read_map_image", "MAX_PIXELS", "MAX_YAML_BYTES"]

#: Largest map YAML read, bytes (real ones are a few hundred).
MAX_YAML_BYTES = 1 << 20
# Longest run of digits accepted in the YAML (PyYAML's int() of 5,000 digits raises ValueError).
_MAX_DIGITS = 100
# Deepest nesting of [ / { accepted in the YAML before parsing (PyYAML recurses per level).
_MAX_YAML_DEPTH = 50

MODES = ("trinary", "scale", "raw")
REQUIRED_KEYS = ("image", "resolution", "origin", "occupied_thresh", "free_thresh", "negate")

#: Pixel values map_saver writes in trinary mode (negate 0).
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
PIXEL_UNKNOWN = 205

# Only yaw exactly 0 is supported; this tolerance forgives "-0.000000" and float noise.
_YAW_TOLERANCE = 1e-9


@dataclass
class RosMap:
    """A ROS map_server map as map_server interprets it.

    Parameters
    ----------
    grid : GridSpec
        Geometry: origin = lower-left corner, pixel side = resolution, shape = (rows, cols).
    probability : ndarray of float64, shape (ny, nx)
        Occupancy probability per pixel before thresholding, row 0 at the lowest y:
        ``(255 - v) / 255`` (negate 0) or ``v / 255`` (negate 1); in raw mode ``v / 100``, and NaN
        where the pixel is unknown.
    free : ndarray of bool, shape (ny, nx)
        Known free: ``probability < free_thresh`` (and not transparent / not raw-unknown).
    occupied : ndarray of bool, shape (ny, nx)
        Known occupied: ``probability > occupied_thresh`` (and not transparent / not raw-unknown).
    unknown : ndarray of bool, shape (ny, nx)
        Unknown to map_server: between the thresholds in trinary mode, transparent pixels in scale
        mode, values outside 0..100 in raw mode.
    pixels : ndarray of uint8, shape (ny, nx)
        The grey values read from the image (colour averaged), flipped to row 0 = lowest y.
    occupied_thresh, free_thresh : float
        The YAML's thresholds.
    negate : bool
        The YAML's ``negate``.
    mode : {"trinary", "scale", "raw"}
        The YAML's ``mode`` ("trinary" when absent).
    yaw : float
        Third element of ``origin``, radians; always 0 since rotated maps are rejected.
    yaml_path, image_path : Path
        Where the map was read from.
    """

    grid: GridSpec
    probability: NDArray[np.float64]
    free: NDArray[np.bool_]
    occupied: NDArray[np.bool_]
    unknown: NDArray[np.bool_]
    pixels: NDArray[np.uint8]
    occupied_thresh: float
    free_thresh: float
    negate: bool
    mode: str
    yaw: float
    yaml_path: Path
    image_path: Path

    @property
    def ternary(self) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) per pixel, ndarray of int8, shape (ny, nx).

        Scale-mode pixels between the thresholds are neither known free nor known occupied: unknown.
        """
        out = np.full(self.grid.shape, -1, dtype=np.int8)
        out[self.free] = FREE
        out[self.occupied] = OCCUPIED
        return out

    def to_occupancy_map(self) -> OccupancyMap:
        """This map as an :class:`~gpomap.grid.OccupancyMap` (thresholds = the YAML's).

        Probability is NaN where the map is unknown outside trinary mode (raw values outside 0..100,
        transparent scale pixels), so that the OccupancyMap's ternary labels are those of map_server.
        """
        p = self.probability.copy()
        if self.mode != "trinary":
            p[self.unknown] = np.nan
        info = {"source": "ros_map_server", "yaml": str(self.yaml_path), "mode": self.mode}
        return OccupancyMap(self.grid, p, thresholds=(self.free_thresh, self.occupied_thresh), info=info)


# --------------------------------------------------------------------------------------------------
# Reading images


def _read_yaml_text(path: str) -> str:
    """The map YAML's text, refused when too large, too deeply nested or not UTF-8."""
    p = Path(path)
    try:
        regular_file(p, "map YAML file")
    except InputFormatError as exc:
        if not p.exists():
            raise InputFormatError("map YAML file not found", path=path) from None
        raise exc from None
    try:
        size = p.stat().st_size
        if size > MAX_YAML_BYTES:
            raise InputFormatError(
                f"map YAML is {size:,} bytes; expected a small text file (at most {MAX_YAML_BYTES:,} bytes)", path=path
            )
        raw = p.read_bytes()[: MAX_YAML_BYTES + 1]
    except OSError as exc:
        raise InputFormatError(f"cannot read the map YAML ({exc})", path=path) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise InputFormatError(
            "map YAML file is not UTF-8 text (is it the image rather than the YAML?)", path=path, line=line
        ) from None
    long_number = re.search(rf"\d{{{_MAX_DIGITS},}}", text)
    if long_number:
        line = text.count("\n", 0, long_number.start()) + 1
        key = text.splitlines()[line - 1].split(":", 1)[0].strip()[:40]
        raise InputFormatError(
            f"'{key}' holds a number of {len(long_number.group())} digits; expected an ordinary number",
            path=path,
            line=line,
        )
    depth = deepest = 0
    for ch in text:
        # Flow collections nest by brackets; block nesting by indentation is bounded by the size.
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    if deepest > _MAX_YAML_DEPTH:
        raise InputFormatError(
            f"map YAML nests {deepest} levels of [ ] / {{ }}; expected a flat mapping (at most {_MAX_YAML_DEPTH})",
            path=path,
        )
    return text


def _key_lines(text: str) -> dict[str, int]:
    """1-based line of each top-level key in a YAML mapping, for error messages."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except (yaml.YAMLError, RecursionError, ValueError):
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {str(k.value): k.start_mark.line + 1 for k, _ in node.value}


def _number(config: dict[str, Any], key: str, path: str, lines: dict[str, int]) -> float:
    """A finite number from `config[key]`; numeric strings are accepted (PyYAML reads ``1e-3`` as a string)."""
    value = config[key]
    if isinstance(value, bool):
        value = None  # ``yes`` is not a number
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int of 400 digits
        number = math.nan
    if not math.isfinite(number):
        shown = repr(config[key])
        shown = shown if len(shown) <= 40 else shown[:40] + "..."
        raise InputFormatError(f"'{key}' must be a finite number, got {shown}", path=path, line=lines.get(key))
    return number


def read_rosmap(yaml_path: str | os.PathLike[str]) -> RosMap:
    """Read a ROS map_server map (YAML + PGM/PNG image).

    Parameters
    ----------
    yaml_path : str or path-like
        The map's YAML file. Its ``image`` is looked up relative to the YAML's directory.

    Returns
    -------
    RosMap
        Arrays flipped so that row 0 is the lowest y.

    Raises
    ------
    InputFormatError
        The YAML is missing, unparsable or not a mapping; a required key is missing (the message names
        it); a value is invalid (resolution not a positive number, thresholds outside 0..1, unknown
        mode, origin not ``[x, y, yaw]``); the origin has a non-zero yaw (rotated maps are not
        supported); the image is missing or not an 8-bit PGM / PNG.
    """
    path = str(yaml_path)
    text = _read_yaml_text(path)
    try:
        config = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise InputFormatError(f"invalid YAML: {getattr(exc, 'problem', None) or exc}", path=path, line=line) from None
    except (RecursionError, ValueError, OverflowError) as exc:
        # ValueError: PyYAML's int() of a 5,000-digit number; RecursionError: deep nesting.
        raise InputFormatError(f"YAML cannot be read ({type(exc).__name__}: {str(exc)[:200]})", path=path) from None
    if not isinstance(config, dict):
        raise InputFormatError(
            f"map YAML must be a mapping of keys (image, resolution, origin, ...), got {type(config).__name__}", path=path
        )
    lines = _key_lines(text)
    for key in REQUIRED_KEYS:
        if key not in config:
            raise InputFormatError(f"map YAML is missing the required key '{key}'", path=path)

    resolution = _number(config, "resolution", path, lines)
    if resolution <= 0:
        raise InputFormatError(
            f"'resolution' must be positive, got {config['resolution']!r}", path=path, line=lines.get("resolution")
        )

    origin = config["origin"]
    if not isinstance(origin, (list, tuple)) or len(origin) != 3:
        raise InputFormatError(f"'origin' must be a list [x, y, yaw], got {origin!r}", path=path, line=lines.get("origin"))
    x0, y0, yaw = (_number({"origin": v}, "origin", path, lines) for v in origin)
    if abs(yaw) > _YAW_TOLERANCE:
        raise InputFormatError(
            f"'origin' has yaw {yaw} rad (its third element): rotated maps are not supported, only yaw 0",
            path=path,
            line=lines.get("origin"),
        )

    occ_th = _number(config, "occupied_thresh", path, lines)
    free_th = _number(config, "free_thresh", path, lines)
    for key, value in (("occupied_thresh", occ_th), ("free_thresh", free_th)):
        if not 0.0 <= value <= 1.0:
            raise InputFormatError(f"'{key}' must be between 0 and 1, got {value}", path=path, line=lines.get(key))
    if free_th > occ_th:
        raise InputFormatError(
            f"'free_thresh' ({free_th}) must not exceed 'occupied_thresh' ({occ_th})", path=path, line=lines.get("free_thresh")
        )

    negate_raw = config["negate"]
    if isinstance(negate_raw, bool) or negate_raw in (0, 1):
        negate = bool(negate_raw)
    else:
        raise InputFormatError(f"'negate' must be 0 or 1, got {negate_raw!r}", path=path, line=lines.get("negate"))

    mode = config.get("mode", "trinary")
    if mode not in MODES:
        raise InputFormatError(f"'mode' must be one of {', '.join(MODES)}, got {mode!r}", path=path, line=lines.get("mode"))

    image = config["image"]
    if not isinstance(image, str) or not image.strip():
        raise InputFormatError(f"'image' must be a file name, got {image!r}", path=path, line=lines.get("image"))
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = Path(path).parent / image_path
    shown = image if len(image) <= 80 else image[:80] + "..."
    try:
        found = image_path.is_file()
    except (OSError, ValueError) as exc:  # name too long, NUL byte
        raise InputFormatError(
            f"image file {shown!r} named by 'image' cannot be looked up ({type(exc).__name__}: {str(exc)[:80]})",
            path=path,
            line=lines.get("image"),
        ) from None
    if not found and image_path.exists():
        kind = file_kind(os.stat(image_path).st_mode)
        raise InputFormatError(
            f"image {shown!r} named by 'image' is {kind}; expected a PGM or PNG file", path=path, line=lines.get("image")
        )
    if not found:
        raise InputFormatError(
            f"image file {shown!r} named by 'image' not found (looked for {image_path})", path=path, line=lines.get("image")
        )

    top_down, transparent = read_map_image(image_path)
    pixels = np.flipud(top_down).copy()
    transparent = None if transparent is None else np.flipud(transparent).copy()
    v = pixels.astype(np.float64)

    if mode == "raw":
        unknown = pixels > 100
        probability = np.where(unknown, np.nan, v / 100.0)
        free = (v / 100.0 < free_th) & ~unknown
        occupied = (v / 100.0 > occ_th) & ~unknown
    else:
        probability = v / 255.0 if negate else (255.0 - v) / 255.0
        hidden = transparent if (mode == "scale" and transparent is not None) else np.zeros(pixels.shape, dtype=bool)
        free = (probability < free_th) & ~hidden
        occupied = (probability > occ_th) & ~hidden
        unknown = ~(free | occupied) if mode == "trinary" else hidden

    try:
        grid = GridSpec((x0, y0), resolution, pixels.shape)
    except ValueError as exc:  # e.g. a resolution so small the extent underflows
        raise InputFormatError(f"map geometry is unusable: {exc}", path=path) from None
    return RosMap(
        grid=grid,
        probability=probability,
        free=free,
        occupied=occupied,
        unknown=unknown,
        pixels=pixels,
        occupied_thresh=occ_th,
        free_thresh=free_th,
        negate=negate,
        mode=mode,
        yaw=float(yaw),
        yaml_path=Path(path),
        image_path=image_path,
    )


# --------------------------------------------------------------------------------------------------
# Writing


def _yaml_float(x: float) -> str:
    """Shortest text that reads back as exactly `x`, and that YAML 1.1 (PyYAML) reads as a float."""
    text = repr(float(x))
    if "e" in text:
        mantissa, exponent = text.split("e")
        if "." not in mantissa:
            mantissa += ".0"  # YAML 1.1 reads "1e-05" as a string, "1.0e-05" as a float
        text = f"{mantissa}e{exponent}"
    return text


def _trinary_thresholds(thresholds: tuple[float, float]) -> tuple[float, float]:
    """Thresholds for the YAML that decode 0 / 254 / 205 back to occupied / free / unknown.

    The map's own thresholds are kept when they already do; otherwise they are moved just enough:
    free_thresh must lie in (1/255, 50/255] (254 is free, 205 is not) and occupied_thresh in
    [50/255, 1) (0 is occupied, 205 is not).
    """
    lo, hi = thresholds
    free_th = min(max(lo, 0.01), 0.196)
    occ_th = max(min(hi, 0.99), 0.197)
    return free_th, occ_th


def write_rosmap(
    occupancy_map: OccupancyMap,
    yaml_path: str | os.PathLike[str],
    mode: str = "trinary",
) -> tuple[Path, Path]:
    """Write a map as a ROS map_server YAML + binary PGM (P5), both atomically, as one group.

    Parameters
    ----------
    occupancy_map : OccupancyMap
        The map; its grid gives resolution and origin (yaw 0), its probability (ny, nx) the pixels.
    yaml_path : str or path-like
        The YAML to write. The image goes beside it with the same stem: ``map.yaml`` -> ``map.pgm``.
    mode : {"trinary", "scale"}
        ``trinary``: the map's ternary labels as 0 (occupied), 254 (free), 205 (unknown), the values
        ROS map_saver writes; the YAML's thresholds are the map's, moved only if needed so that
        map_server decodes these three values back to the same labels (see Notes).
        ``scale``: the probability as ``v = round(255 * (1 - p))`` (negate 0), and the map's
        thresholds in the YAML; NaN probabilities are written as the midpoint of the thresholds, a
        value map_server reads as neither free nor occupied.

    Returns
    -------
    yaml_path, image_path : Path

    Notes
    -----
    Value 205 means p = 50/255 = 0.196 to map_server, so in trinary mode ``free_thresh`` is capped
    at 0.196 and ``occupied_thresh`` raised to at least 0.197; with the paper's (0.33, 0.66) the
    YAML holds (0.196, 0.66). The map's own thresholds are recorded in a YAML comment.

    Reading the result with :func:`read_rosmap` gives back the grid geometry exactly, and the ternary
    labels exactly (trinary) or the probability to within 1/510 (scale).
    """
    if mode not in ("trinary", "scale"):
        raise ValueError(f"write_rosmap mode must be 'trinary' or 'scale', got {mode!r}")
    yaml_path = Path(yaml_path)
    if yaml_path.suffix == ".pgm":
        raise ValueError(f"yaml_path must be the YAML file, got the image name {yaml_path}")
    image_path = yaml_path.with_suffix(".pgm")
    grid = occupancy_map.grid

    if mode == "trinary":
        labels = occupancy_map.ternary
        image = np.full(grid.shape, PIXEL_UNKNOWN, dtype=np.uint8)
        image[labels == FREE] = PIXEL_FREE
        image[labels == OCCUPIED] = PIXEL_OCCUPIED
        free_th, occ_th = _trinary_thresholds(occupancy_map.thresholds)
    else:
        free_th, occ_th = occupancy_map.thresholds
        p = np.asarray(occupancy_map.probability, dtype=np.float64)
        p = np.where(np.isfinite(p), np.clip(p, 0.0, 1.0), 0.5 * (free_th + occ_th))
        image = np.rint(255.0 * (1.0 - p)).astype(np.uint8)

    ny, nx = grid.shape
    header = f"P5\n# CREATOR: gpomap {grid.resolution:.3f} m/pix\n{nx} {ny}\n255\n".encode("ascii")
    lo, hi = occupancy_map.thresholds
    text = (
        f"# gpomap map, {mode} mode; map thresholds (free below, occupied above): {lo}, {hi}\n"
        f"image: {image_path.name}\n"
        f"mode: {mode}\n"
        f"resolution: {_yaml_float(grid.resolution)}\n"
        f"origin: [{_yaml_float(grid.origin[0])}, {_yaml_float(grid.origin[1])}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {_yaml_float(occ_th)}\n"
        f"free_thresh: {_yaml_float(free_th)}\n"
    )
    # The image is renamed first, so the YAML never names an image that is not complete.
    with atomic_write_group([image_path, yaml_path], mode=["wb", "w"]) as (f_img, f_yaml):
        f_img.write(header)
        f_img.write(np.ascontiguousarray(np.flipud(image)).tobytes())
        f_yaml.write(text)
    return yaml_path, image_path
