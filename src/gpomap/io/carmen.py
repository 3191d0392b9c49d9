"""CARMEN log reader: ``FLASER`` and ``ROBOTLASER1`` lines, plain or gzipped.

Line formats (fields separated by white space)::

    FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp
    ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode
        n r_1 ... r_n m rem_1 ... rem_m laser_x laser_y laser_theta robot_x robot_y robot_theta
        tv rv forward_safety side_safety turn_axis timestamp host logger_timestamp

``FLASER`` has ``n + 11`` fields, ``ROBOTLASER1`` has ``n + m + 24``. ``PARAM``, ``ODOM``,
``NEFF``, comments (``#``) and every other message type are skipped; ``PARAM
robot_frontlaser_offset`` and ``PARAM robot_front_laser_max`` are read (the last value in the file
wins, as with CARMEN's parameter server).

Poses. In the corrected logs this reader targets (GMapping outputs) both ``FLASER`` pose triples
hold the same corrected pose; we read the one at the end of the line (``odom_*``). Is that the
robot pose, with the laser ``robot_frontlaser_offset`` (-0.04 m in Belgioioso and FR079) ahead of
it, or already the laser pose? The data answers: counting the 2 cm cells hit by all end points
(fewer = sharper walls), FR079 gives 195,303 cells with offset 0 against 216,136 with -0.04 and
209,693 with +0.04; Belgioioso 65,345 against 70,207 / 70,187. So by default the pose is used as the
laser pose (offset 0), and the PARAM value is kept in ``Scan.meta["frontlaser_offset_param"]``;
pass ``laser_offset="param"`` to apply it (for raw logs whose poses are robot poses) or a number.
``ROBOTLASER1`` carries the laser pose explicitly and rays are cast from it.

Scan order is line order. Time stamps (``ipc_timestamp`` / ``timestamp``) go to ``Scan.time``
only where they look usable: finite, not all equal and almost never repeated (Belgioioso's, printed
to 6 significant digits, are all the same number and are dropped).
"""

from __future__ import annotations

import gzip
import io
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.scans import Scan

__all__ = ["read_carmen", "beam_angles", "is_carmen_text", "DEFAULT_MAX_RANGE", "LASER_MESSAGES"]

#: Max range assumed when neither the caller nor the log gives one: the SICK LMS range (its
#: no-return codes 81.83 / 81.91 then fall at or above it).
DEFAULT_MAX_RANGE = 80.0

#: Message types this reader turns into scans.
LASER_MESSAGES = ("FLASER", "ROBOTLASER1")

# Fraction of repeated consecutive time stamps above which the stamps are deemed too coarse.
_MAX_REPEATED_STAMPS = 0.01


def beam_angles(n: int, convention: str = "gmapping") -> NDArray[np.float64]:
    """Beam angles of an ``FLASER`` scan with `n` beams, relative to the laser heading.

    Parameters
    ----------
    n : int
        Number of beams.
    convention : {"gmapping", "linspace"}
        ``"gmapping"``: ``-pi/2 + i * step`` with step pi/180 for 180 or 181 beams, pi/360 for 360
        or 361 (and pi/(n-1) otherwise, i.e. a 180 degree sweep). ``"linspace"``:
        ``linspace(-pi/2, pi/2, n)``.

    Returns
    -------
    ndarray of shape (n,)
    """
    if convention == "gmapping":
        if n in (180, 181):
            step = math.pi / 180
        elif n in (360, 361):
            step = math.pi / 360
        else:
            step = math.pi / max(n - 1, 1)
        return -math.pi / 2 + step * np.arange(n, dtype=float)
    if convention == "linspace":
        return np.linspace(-math.pi / 2, math.pi / 2, n)
    raise ValueError(f"unknown beam-angle convention {convention!r}; expected 'gmapping' or 'linspace'")


@dataclass
class _Laser:
    """One parsed laser line, before max range and offsets are settled."""

    line: int
    kind: str
    ranges: list[float]
    pose: tuple[float, float, float]
    laser_pose_given: bool
    time: float
    angles: NDArray[np.float64] | None = None
    max_range: float | None = None


def _open_text(path: Path) -> list[str]:
    """All lines of a plain or gzipped text file (gzip detected by its magic bytes)."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputFormatError("no such file", path=str(path)) from None
    except IsADirectoryError:
        raise InputFormatError("is a directory, expected a CARMEN log file", path=str(path)) from None
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (EOFError, OSError, gzip.BadGzipFile) as exc:
            raise InputFormatError(f"corrupt or truncated gzip data ({exc})", path=str(path)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return text.splitlines()


def _floats(tokens: list[str], path: str, line: int, first_field: int) -> list[float]:
    """Convert tokens to floats, naming the first bad field (1-based, counting the message name)."""
    try:
        return list(map(float, tokens))
    except ValueError:
        for k, t in enumerate(tokens):
            try:
                float(t)
            except ValueError:
                raise InputFormatError(
                    f"non-numeric field {first_field + k} {t!r}; expected a number", path=path, line=line
                ) from None
        raise InputFormatError("non-numeric field; expected numbers", path=path, line=line) from None


def _count(tokens: list[str], index: int, what: str, path: str, line: int) -> int:
    """Read an integer count at `index`, or raise a truncation / format error."""
    kind = tokens[0]
    if len(tokens) <= index:
        raise InputFormatError(
            f"truncated {kind} line: it ends before the {what} (field {index + 1})", path=path, line=line
        )
    try:
        value = float(tokens[index])
    except ValueError:
        raise InputFormatError(
            f"non-numeric field {index + 1} {tokens[index]!r}; expected the {what} (an integer)",
            path=path,
            line=line,
        ) from None
    if value != int(value) or value < 0:
        raise InputFormatError(
            f"field {index + 1} is {tokens[index]!r}; expected the {what} (a non-negative integer)",
            path=path,
            line=line,
        )
    return int(value)


def _check_length(tokens: list[str], expected: int, formula: str, path: str, line: int) -> None:
    got = len(tokens)
    if got < expected:
        raise InputFormatError(
            f"truncated {tokens[0]} line: {got} fields, expected {expected} ({formula})", path=path, line=line
        )
    if got > expected:
        raise InputFormatError(
            f"wrong field count in {tokens[0]} line: {got} fields, expected {expected} ({formula})",
            path=path,
            line=line,
        )


def _parse_flaser(tokens: list[str], path: str, line: int) -> _Laser:
    n = _count(tokens, 1, "number of readings", path, line)
    _check_length(tokens, n + 11, f"n + 11 with n = {n}", path, line)
    values = _floats(tokens[2 : n + 8], path, line, first_field=3)
    # ipc_timestamp only: host (n + 9) is a name and logger_timestamp is not needed.
    stamp = _floats([tokens[n + 8]], path, line, first_field=n + 9)[0]
    # Pose from the end of the line (odom_x, odom_y, odom_theta): the robot pose.
    pose = (values[n + 3], values[n + 4], values[n + 5])
    return _Laser(line, "FLASER", values[:n], pose, laser_pose_given=False, time=stamp)


def _parse_robotlaser1(tokens: list[str], path: str, line: int) -> _Laser:
    n = _count(tokens, 8, "number of readings", path, line)
    m = _count(tokens, 9 + n, "number of remission values", path, line)
    _check_length(tokens, n + m + 24, f"n + m + 24 with n = {n}, m = {m}", path, line)
    head = _floats(tokens[2:8], path, line, first_field=3)
    start, _fov, res, max_range = head[0], head[1], head[2], head[3]
    ranges = _floats(tokens[9 : 9 + n], path, line, first_field=10)
    tail_at = 10 + n + m
    tail = _floats(tokens[tail_at : tail_at + 12], path, line, first_field=tail_at + 1)
    angles = start + res * np.arange(n, dtype=float)
    return _Laser(
        line,
        "ROBOTLASER1",
        ranges,
        (tail[0], tail[1], tail[2]),  # laser pose: rays start here
        laser_pose_given=True,
        time=tail[11],
        angles=angles,
        max_range=max_range if max_range > 0 else None,
    )


def _usable_times(stamps: NDArray[np.float64]) -> bool:
    """Whether time stamps carry information: finite, not constant, rarely repeated."""
    if stamps.size == 0 or not np.isfinite(stamps).all():
        return False
    if stamps.size == 1:
        return True
    repeated = np.count_nonzero(np.diff(stamps) == 0)
    return bool(stamps.max() > stamps.min() and repeated <= _MAX_REPEATED_STAMPS * (stamps.size - 1))


def _parse_lines(lines: Iterable[str], path: str) -> tuple[list[_Laser], dict[str, str]]:
    """Laser lines and the PARAM values of a CARMEN log."""
    lasers: list[_Laser] = []
    params: dict[str, str] = {}
    for i, text in enumerate(lines, start=1):
        # Cheap first-token test: most lines of a log are skipped ODOM / NEFF lines.
        if text.startswith("FLASER"):
            tokens = text.split()
            if tokens[0] == "FLASER":
                lasers.append(_parse_flaser(tokens, path, i))
        elif text.startswith("ROBOTLASER1"):
            tokens = text.split()
            if tokens[0] == "ROBOTLASER1":
                lasers.append(_parse_robotlaser1(tokens, path, i))
        elif text.startswith("PARAM"):
            tokens = text.split()
            if len(tokens) >= 3 and tokens[0] == "PARAM":
                params[tokens[1]] = tokens[2]
    return lasers, params


def _param_float(params: dict[str, str], name: str, path: str) -> float | None:
    if name not in params:
        return None
    try:
        return float(params[name])
    except ValueError:
        raise InputFormatError(f"PARAM {name} is {params[name]!r}; expected a number", path=path) from None


def read_carmen(
    path: str | os.PathLike[str],
    angles: str = "gmapping",
    max_range: float | None = None,
    laser_offset: float | str | None = None,
) -> list[Scan]:
    """Read the laser scans of a CARMEN log (plain text or gzip).

    Parameters
    ----------
    path : path-like
        The log file (``.log``, ``.log.gz``, ``.clf``, ...; gzip is recognised by content).
    angles : {"gmapping", "linspace"}
        Beam-angle convention for ``FLASER`` lines, which carry no angles (see
        :func:`beam_angles`). ``ROBOTLASER1`` lines carry their own start angle and resolution.
    max_range : float, optional
        Sensor maximum range, metres; readings at or above it become no-return beams. Default:
        ``PARAM robot_front_laser_max`` if the log has it (80.99 in Belgioioso and FR079), else the
        ``max_range`` field of ``ROBOTLASER1`` lines, else 80 m (:data:`DEFAULT_MAX_RANGE`). Either
        way the SICK no-return codes 81.83 / 81.91 m become no-return beams.
    laser_offset : float or "param", optional
        Distance of the laser ahead of the ``FLASER`` pose along its heading, metres. Default 0:
        in corrected logs the pose already is the laser pose (see the module notes, measured).
        ``"param"`` applies ``PARAM robot_frontlaser_offset`` (last value in the file; 0 if absent).

    Returns
    -------
    list of Scan
        In line order. ``Scan.meta`` holds ``line`` (1-based), ``message``, ``robot_pose``
        (ndarray of shape (3,), the pose read from the line) and ``frontlaser_offset_param``.

    Raises
    ------
    InputFormatError
        Missing or empty file, no laser lines, truncated line, wrong field count, non-numeric
        field; the message names the file and the 1-based line.
    """
    p = Path(path)
    spath = str(p)
    lines = _open_text(p)
    if not any(t.strip() for t in lines):
        raise InputFormatError("empty file; expected a CARMEN log with FLASER or ROBOTLASER1 lines", path=spath)
    lasers, params = _parse_lines(lines, spath)
    if not lasers:
        raise InputFormatError(
            f"no laser lines in {len(lines)} lines; expected FLASER or ROBOTLASER1 messages", path=spath
        )

    param_max = _param_float(params, "robot_front_laser_max", spath)
    param_offset = _param_float(params, "robot_frontlaser_offset", spath)
    if laser_offset is None:
        offset = 0.0
    elif laser_offset == "param":
        offset = param_offset or 0.0
    elif isinstance(laser_offset, str):
        raise ValueError(f"laser_offset must be a number, None or 'param', got {laser_offset!r}")
    else:
        offset = float(laser_offset)

    stamps = np.array([las.time for las in lasers])
    keep_time = _usable_times(stamps)

    angle_cache: dict[int, NDArray[np.float64]] = {}
    scans: list[Scan] = []
    for las in lasers:
        n = len(las.ranges)
        if las.angles is not None:
            beam = las.angles
        else:
            if n not in angle_cache:
                angle_cache[n] = beam_angles(n, angles)
            beam = angle_cache[n]
        if max_range is not None:
            mr = float(max_range)
        elif param_max is not None:
            mr = param_max
        elif las.max_range is not None:
            mr = las.max_range
        else:
            mr = DEFAULT_MAX_RANGE
        robot = np.array(las.pose, dtype=float)
        if las.laser_pose_given or offset == 0.0:
            sensor = robot
        else:
            c, s = math.cos(robot[2]), math.sin(robot[2])
            sensor = robot + np.array([offset * c, offset * s, 0.0])
        scans.append(
            Scan(
                pose=sensor,
                angles=beam,
                ranges=np.asarray(las.ranges, dtype=float),
                max_range=mr,
                time=las.time if keep_time else None,
                meta={
                    "line": las.line,
                    "message": las.kind,
                    "robot_pose": robot,
                    "frontlaser_offset_param": param_offset,
                },
            )
        )
    return scans


def is_carmen_text(head: bytes) -> bool:
    """Whether the first bytes of a (decompressed) file look like a CARMEN log."""
    text = head.decode("utf-8", errors="replace")
    for line in io.StringIO(text):
        word = line.split(maxsplit=1)[0] if line.strip() else ""
        if not word:
            continue
        if word.startswith("#"):
            continue
        return word in LASER_MESSAGES or word in ("PARAM", "ODOM", "NEFF", "SYNC", "RAWLASER1", "TRUEPOS")
    return False
