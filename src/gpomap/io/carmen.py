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
robot pose, with the laser ``robot_frontlaser_offset`` ahead of it, or already the laser pose?
The data answers: the end points draw the sharpest walls (fewest 2 cm cells hit) with no offset
(docs/choices.md, "Measured for the code"). So by default the pose is used as the laser pose
(offset 0), and the PARAM value is kept in ``Scan.meta["frontlaser_offset_param"]``;
pass ``laser_offset="param"`` to apply it (for raw logs whose poses are robot poses) or a number.
``ROBOTLASER1`` carries the laser pose explicitly and rays are cast from it.

Scan order is line order. Time stamps (``ipc_timestamp`` / ``timestamp``) go to ``Scan.time``
only where they look usable: finite, not all equal and almost never repeated (stamps printed to
6 significant digits can all be the same number, and are then dropped).

No-return. The threshold (``Scan.max_range``) is decided per message type from the readings
(:mod:`gpomap.io.noreturn`): a log whose header states the range keeps it where the data agree
(the codes the shared logs carry: docs/choices.md, "Measured for the code"); a log whose code is 50 m and has no PARAM no longer turns every no-return into a
hit, and ``PARAM robot_front_laser_max 10`` in a log with real returns out to 50 m is overruled
(and the contradiction reported in ``Scan.meta["no_return"]``).
"""

from __future__ import annotations

import gzip
import io
import math
import os
import warnings
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.io.checks import regular_file
from gpomap.io.noreturn import NoReturnDecision, decide_max_range
from gpomap.scans import Scan

__all__ = ["read_carmen", "beam_angles", "is_carmen_text", "LASER_MESSAGES", "MAX_LINE_BYTES", "MAX_BEAMS"]

#: Longest line read, bytes: a 1,081-beam ROBOTLASER1 line with remissions is about 20 kB.
MAX_LINE_BYTES = 1 << 20

#: Largest beam or remission count accepted in a line (a count is checked before the line length).
MAX_BEAMS = 100_000

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
    ranges: NDArray[np.float64]
    pose: tuple[float, float, float]
    laser_pose_given: bool
    time: float
    angles: NDArray[np.float64] | None = None
    max_range: float | None = None


@dataclass
class _Parsed:
    """What one pass over a log gives."""

    lasers: list[_Laser]
    # PARAM name -> (value text, 1-based line); the last one in the file wins.
    params: dict[str, tuple[str, int]]
    n_lines: int
    any_text: bool
    # First line that is not text (NUL bytes or not UTF-8), for the "no laser lines" message.
    binary_line: int | None
    # Lines of the laser messages this reader does not take (RAWLASER, RLASER, ...), by name.
    other_lasers: dict[str, int]


#: Laser messages of CARMEN logs this reader does not take: RAWLASER1-4 carry no pose (a log
#: before SLAM corrected it), RLASER and ROBOTLASER2 are a second, rear laser.
_OTHER_LASERS: tuple[bytes, ...] = (b"RAWLASER", b"RLASER", b"ROBOTLASER2")


def _other_lasers_note(other: dict[str, int]) -> str:
    """What the "no laser lines" message adds about the laser lines a log has instead."""
    if not other:
        return ""
    found = ", ".join(f"{name} ({n} line{'s' if n != 1 else ''})" for name, n in sorted(other.items()))
    notes = []
    if any(name.startswith("RAWLASER") for name in other):
        notes.append(
            "RAWLASER lines carry no pose: correct the log with a SLAM first, such as GMapping, which writes FLASER lines with the corrected poses"
        )
    if any(name.startswith(("RLASER", "ROBOTLASER2")) for name in other):
        notes.append("RLASER and ROBOTLASER2 lines are a second (rear) laser, which gpomap does not read")
    return f" (found {found}; " + "; ".join(notes) + ")"


def _lines(path: Path) -> Iterator[tuple[int, bytes]]:
    """(1-based number, raw bytes) of each line of a plain or gzipped file, read as a stream.

    Gzip is recognised by its magic bytes. A line longer than :data:`MAX_LINE_BYTES` is refused,
    so a file without line breaks cannot fill the memory.
    """
    spath = str(path)
    with path.open("rb") as raw:
        gzipped = raw.read(2) == b"\x1f\x8b"
    number = 0
    try:
        with gzip.open(path, "rb") if gzipped else path.open("rb") as f:
            while True:
                line = f.readline(MAX_LINE_BYTES + 1)
                if not line:
                    return
                number += 1
                if len(line) > MAX_LINE_BYTES:
                    raise InputFormatError(
                        f"line longer than {MAX_LINE_BYTES} bytes; expected a text log with one message a line",
                        path=spath,
                        line=number,
                    )
                yield number, line
    except (EOFError, OSError, zlib.error) as exc:
        # gzip.BadGzipFile is an OSError; EOFError is a truncated stream.
        raise InputFormatError(
            f"corrupt or truncated {'gzip data' if gzipped else 'file'} ({exc})", path=spath, line=number + 1
        ) from None


def _decode(raw: bytes) -> str:
    # Host names in old logs may be Latin-1; numeric fields with such bytes fail as non-numeric.
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _is_binary(raw: bytes) -> bool:
    if b"\x00" in raw:
        return True
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError:
        return True
    return False


def _floats(tokens: list[str], path: str, line: int, first_field: int) -> list[float]:
    """Convert tokens to floats, naming the first bad field (1-based, counting the message name).

    ``nan``, ``inf`` and numbers too large for a float (``1e400``, 5,000 digits) are converted as
    Python does (to NaN / inf); callers check the fields that must be finite.
    """
    try:
        return list(map(float, tokens))
    except ValueError:
        for k, t in enumerate(tokens):
            try:
                float(t)
            except ValueError:
                shown = t if len(t) <= 40 else t[:40] + "..."
                raise InputFormatError(
                    f"non-numeric field {first_field + k} {shown!r}; expected a number", path=path, line=line
                ) from None
        raise InputFormatError("non-numeric field; expected numbers", path=path, line=line) from None


def _finite(values: Iterable[float], names: Iterable[str], first_field: int, kind: str, path: str, line: int) -> None:
    """Refuse NaN / inf in fields that must be finite (poses, beam geometry)."""
    for k, (v, name) in enumerate(zip(values, names)):
        if not math.isfinite(v):
            raise InputFormatError(
                f"{kind} field {first_field + k} ({name}) is {v}; expected a finite number", path=path, line=line
            )


def _count(tokens: list[str], index: int, what: str, path: str, line: int) -> int:
    """Read an integer count at `index`, or raise a truncation / format error."""
    kind = tokens[0]
    if len(tokens) <= index:
        raise InputFormatError(f"truncated {kind} line: it ends before the {what} (field {index + 1})", path=path, line=line)
    text = tokens[index]
    shown = text if len(text) <= 40 else text[:40] + "..."
    try:
        value = float(text)
    except ValueError:
        raise InputFormatError(
            f"non-numeric field {index + 1} {shown!r}; expected the {what} (an integer)", path=path, line=line
        ) from None
    # NaN, inf and 1e400 fail the first test (int() of them would raise ValueError / OverflowError).
    if not math.isfinite(value) or value < 0 or value != int(value):
        raise InputFormatError(
            f"field {index + 1} is {shown!r}; expected the {what} (a non-negative integer)", path=path, line=line
        )
    if value > MAX_BEAMS:
        raise InputFormatError(f"field {index + 1} is {shown!r}; expected the {what}, at most {MAX_BEAMS}", path=path, line=line)
    return int(value)


def _check_length(tokens: list[str], expected: int, formula: str, path: str, line: int) -> None:
    got = len(tokens)
    if got < expected:
        raise InputFormatError(f"truncated {tokens[0]} line: {got} fields, expected {expected} ({formula})", path=path, line=line)
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
    _finite(pose, ("odom_x", "odom_y", "odom_theta"), n + 6, "FLASER", path, line)
    return _Laser(line, "FLASER", np.array(values[:n], dtype=float), pose, laser_pose_given=False, time=stamp)


def _parse_robotlaser1(tokens: list[str], path: str, line: int) -> _Laser:
    n = _count(tokens, 8, "number of readings", path, line)
    m = _count(tokens, 9 + n, "number of remission values", path, line)
    _check_length(tokens, n + m + 24, f"n + m + 24 with n = {n}, m = {m}", path, line)
    head = _floats(tokens[2:8], path, line, first_field=3)
    start, _fov, res, max_range = head[0], head[1], head[2], head[3]
    _finite((start,), ("start_angle",), 3, "ROBOTLASER1", path, line)
    _finite((res,), ("angular_res",), 5, "ROBOTLASER1", path, line)
    ranges = _floats(tokens[9 : 9 + n], path, line, first_field=10)
    tail_at = 10 + n + m
    tail = _floats(tokens[tail_at : tail_at + 12], path, line, first_field=tail_at + 1)
    _finite(tail[:3], ("laser_x", "laser_y", "laser_theta"), tail_at + 1, "ROBOTLASER1", path, line)
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported just below
        angles = start + res * np.arange(n, dtype=float)
    if not np.isfinite(angles).all():
        raise InputFormatError(
            f"ROBOTLASER1 start_angle {start} and angular_res {res} give non-finite beam angles; expected angles in radians",
            path=path,
            line=line,
        )
    return _Laser(
        line,
        "ROBOTLASER1",
        np.array(ranges, dtype=float),
        (tail[0], tail[1], tail[2]),  # laser pose: rays start here
        laser_pose_given=True,
        time=tail[11],
        angles=angles,
        # A non-positive or non-finite field states no max range.
        max_range=max_range if math.isfinite(max_range) and max_range > 0 else None,
    )


def _usable_times(stamps: NDArray[np.float64]) -> bool:
    """Whether time stamps carry information: finite, not constant, rarely repeated."""
    if stamps.size == 0 or not np.isfinite(stamps).all():
        return False
    if stamps.size == 1:
        return True
    repeated = np.count_nonzero(np.diff(stamps) == 0)
    return bool(stamps.max() > stamps.min() and repeated <= _MAX_REPEATED_STAMPS * (stamps.size - 1))


def _parse_file(path: Path) -> _Parsed:
    """Laser lines and PARAM values of a CARMEN log, in one streaming pass."""
    spath = str(path)
    lasers: list[_Laser] = []
    params: dict[str, tuple[str, int]] = {}
    n_lines = 0
    any_text = False
    binary_line: int | None = None
    other_lasers: dict[str, int] = {}
    for i, raw in _lines(path):
        n_lines = i
        # Cheap first-token test on the bytes: most lines of a log are skipped ODOM / NEFF lines.
        if raw.startswith(b"FLASER"):
            tokens = _decode(raw).split()
            if tokens[0] == "FLASER":
                lasers.append(_parse_flaser(tokens, spath, i))
                continue
        elif raw.startswith(b"ROBOTLASER1"):
            tokens = _decode(raw).split()
            if tokens[0] == "ROBOTLASER1":
                lasers.append(_parse_robotlaser1(tokens, spath, i))
                continue
        elif raw.startswith(b"PARAM"):
            tokens = _decode(raw).split()
            if len(tokens) >= 3 and tokens[0] == "PARAM":
                params[tokens[1]] = (tokens[2], i)
        elif raw.startswith(_OTHER_LASERS):
            name = raw.split(maxsplit=1)[0].decode("ascii", "replace")
            other_lasers[name] = other_lasers.get(name, 0) + 1
        if binary_line is None and _is_binary(raw):
            binary_line = i
        if not any_text and raw.strip():
            any_text = True
    return _Parsed(lasers, params, n_lines, any_text or bool(lasers), binary_line, other_lasers)


def _param_float(params: dict[str, tuple[str, int]], name: str, path: str, positive: bool = False) -> float | None:
    if name not in params:
        return None
    text, line = params[name]
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or (positive and value <= 0):
        shown = text if len(text) <= 40 else text[:40] + "..."
        expected = "a positive number (metres)" if positive else "a finite number"
        raise InputFormatError(f"PARAM {name} is {shown!r}; expected {expected}", path=path, line=line)
    return value


def _decide(lasers: list[_Laser], kind: str, param_max: float | None, max_range: float | None) -> NoReturnDecision:
    """The no-return threshold of all `kind` lines of a log (one laser: one decision)."""
    ranges = np.concatenate([las.ranges for las in lasers]) if lasers else np.empty(0)
    header: float | None = None
    name: str | None = None
    notes: list[str] = []
    if kind == "ROBOTLASER1":
        fields = [las.max_range for las in lasers if las.max_range is not None]
        if fields:
            values, counts = np.unique(np.asarray(fields), return_counts=True)
            header, name = float(values[np.argmax(counts)]), "ROBOTLASER1 max_range"
            if len(values) > 1:
                notes.append(
                    f"ROBOTLASER1 max_range differs between lines ({', '.join(f'{v:g}' for v in values[:5])}); "
                    f"compared the most common, {header:g} m, with the data"
                )
    if header is None and param_max is not None:
        header, name = param_max, "PARAM robot_front_laser_max"
    decision = decide_max_range(ranges, header, name, user=max_range)
    decision.notes.extend(notes)
    return decision


def read_carmen(
    path: str | os.PathLike[str],
    angles: str = "gmapping",
    max_range: float | None = None,
    laser_offset: float | str | None = None,
) -> list[Scan]:
    """Read the laser scans of a CARMEN log (plain text or gzip).

    The file is read as a stream, one line at a time (gzip too), so memory grows with the scans
    kept, not with the ``ODOM`` and other lines skipped.

    Parameters
    ----------
    path : path-like
        The log file (``.log``, ``.log.gz``, ``.clf``, ...; gzip is recognised by content).
    angles : {"gmapping", "linspace"}
        Beam-angle convention for ``FLASER`` lines, which carry no angles (see
        :func:`beam_angles`). ``ROBOTLASER1`` lines carry their own start angle and resolution.
    max_range : float, optional
        No-return threshold, metres: readings at or above it become no-return beams; always wins.
        Default: decided from the data (:func:`gpomap.io.noreturn.decide_max_range`), separately
        for the ``FLASER`` and the ``ROBOTLASER1`` lines: the header value (the ``max_range``
        field of ``ROBOTLASER1`` lines, else ``PARAM robot_front_laser_max``) when the readings
        agree with it, else the no-return code found in the readings, else no reading is
        no-return.
    laser_offset : float or "param", optional
        Distance of the laser ahead of the ``FLASER`` pose along its heading, metres. Default 0:
        in corrected logs the pose already is the laser pose (see the module notes).
        ``"param"`` applies ``PARAM robot_frontlaser_offset`` (last value in the file; 0 if absent).

    Returns
    -------
    list of Scan
        In line order. ``Scan.meta`` holds ``line`` (1-based), ``message``, ``robot_pose``
        (ndarray of shape (3,), the pose read from the line), ``frontlaser_offset_param`` and
        ``no_return`` (the decision as a dict, shared by the scans of one message type: see
        :meth:`gpomap.io.noreturn.NoReturnDecision.as_dict`).

    Raises
    ------
    InputFormatError
        Missing, empty or non-regular file (directory, FIFO, device), corrupt gzip, no laser
        lines, truncated line, wrong field count, non-numeric field, NaN or inf in a pose or in
        the beam geometry, impossible beam count, non-numeric PARAM value; the message names the
        file and the 1-based line.
    """
    if max_range is not None and not (math.isfinite(max_range) and max_range > 0):
        raise ValueError(f"max_range must be a positive finite number of metres, got {max_range!r}")
    p = regular_file(path, "CARMEN log")
    spath = str(p)
    parsed = _parse_file(p)
    lasers = parsed.lasers
    if not parsed.any_text:
        raise InputFormatError("empty file; expected a CARMEN log with FLASER or ROBOTLASER1 lines", path=spath)
    if not lasers:
        binary = f" (line {parsed.binary_line} is binary data, not text)" if parsed.binary_line is not None else ""
        raise InputFormatError(
            f"no laser lines in {parsed.n_lines} lines{binary}; expected FLASER or ROBOTLASER1 messages"
            + _other_lasers_note(parsed.other_lasers),
            path=spath,
            line=parsed.binary_line,
        )

    param_max = _param_float(parsed.params, "robot_front_laser_max", spath, positive=True)
    param_offset = _param_float(parsed.params, "robot_frontlaser_offset", spath)
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

    decisions: dict[str, tuple[float, dict]] = {}
    for kind in LASER_MESSAGES:
        group = [las for las in lasers if las.kind == kind]
        if group:
            d = _decide(group, kind, param_max, max_range)
            if parsed.other_lasers:
                # Read beside FLASER / ROBOTLASER1, a rear laser's lines are left out: say so.
                left = ", ".join(f"{name} ({n})" for name, n in sorted(parsed.other_lasers.items()))
                d.notes.append(f"laser lines not read: {left}; gpomap reads FLASER and ROBOTLASER1 (the front laser)")
            info = d.as_dict()
            info["message"] = kind
            decisions[kind] = (d.max_range, info)

    _warn_odd_beam_counts(lasers, spath)
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
        mr, info = decisions[las.kind]
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
                ranges=las.ranges,
                max_range=mr,
                time=las.time if keep_time else None,
                meta={
                    "line": las.line,
                    "message": las.kind,
                    "robot_pose": robot,
                    "frontlaser_offset_param": param_offset,
                    "no_return": info,
                },
            )
        )
    return scans


def _warn_odd_beam_counts(lasers: list[_Laser], path: str) -> None:
    """Warn of FLASER lines whose beam count is not the log's usual one: such a line carries no
    angles, so its beams are spread over 180 degrees, which a truncated line's are not."""
    counts = np.array([len(las.ranges) for las in lasers if las.kind == "FLASER"])
    if counts.size == 0:
        return
    values, n = np.unique(counts, return_counts=True)
    usual = int(values[n == n.max()].max())  # the most common; of equals, the longest
    odd = [las for las in lasers if las.kind == "FLASER" and len(las.ranges) != usual]
    if odd:
        first = ", ".join(f"line {las.line}: {len(las.ranges)}" for las in odd[:3])
        more = f" and {len(odd) - 3} more" if len(odd) > 3 else ""
        warnings.warn(
            f"{path}: {len(odd)} FLASER line(s) with another beam count than the log's {usual} ({first}{more}); "
            "each is taken as a 180-degree sweep of its own beams (a truncated line is not: check the log)",
            stacklevel=3,
        )


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
