"""No-return codes found from the readings themselves, and the max range each scan reader uses.

Many lasers write "no return" as a fixed code instead of leaving the beam empty: 81.83 / 81.91 m
(SICK, 80 m family), 50.0 m, 51.05 / 51.1 m, 32.767 / 32.76 m, 5.0 / 5.6 m. Such a code sits at the
top of the range distribution and is repeated far more often than any real range near it: thousands
of readings on the code, against one or two per centimetre among the real ranges below it. A few
stray readings may lie above it, and a code may be smeared over a few centimetres (51.05-51.12 m) with tens of strays
above: then the densest 0.1 m near the top of the data is the code when it stands out as one.
A header value (CARMEN ``PARAM robot_front_laser_max``, the ``max_range`` field of ``ROBOTLASER1``,
a LaserScan's ``range_max``) may be missing, or say something else than the data
(``PARAM robot_front_laser_max 10`` in a log with real returns out to 50 m), so the readers decide:

1. an explicit ``max_range`` from the caller always wins;
2. otherwise the header value is kept when the data agree with it (the same readings are no-return
   with the header's threshold as with the code found in the data, up to a few readings);
3. otherwise the data wins: readings at or above the found code (minus :data:`TOLERANCE`) are
   no-return, or, with no code in the data, none are (the threshold is just above the largest
   reading); the disagreement is reported.

:func:`decide_max_range` returns a :class:`NoReturnDecision`; readers put its threshold in
``Scan.max_range`` (so ``Scan.no_return()`` and every free-ray cap use it) and the decision, as a
dict, in ``Scan.meta["no_return"]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.scans import usable_ranges

__all__ = ["NoReturnCode", "NoReturnDecision", "detect_no_return_code", "decide_max_range", "TOLERANCE"]

#: Readings at or above ``code - TOLERANCE`` (metres) are no-return once a code is found.
TOLERANCE = 0.01
# Twin codes (81.83 / 81.91, 51.05 / 51.1) lie within this many metres of the top code.
_WINDOW = 0.1
# Width (metres) of the bins in which the background density of real ranges is counted: the
# range resolution of the CARMEN logs (they print centimetres).
_BIN = 0.01
# A code holds at least this many readings, and this many times the real readings of a bin.
_MIN_COUNT = 8
_RATIO = 10.0
# Real readings just below the codes used to estimate the background density.
_NEIGHBOURS = 50
# Real ranges vary: below the codes there must be at least this many distinct values, else a log
# of two constant walls (1 m and 2 m) would make the farther one a code.
_MIN_DISTINCT = 20
# Readings are grouped into values to the millimetre (float32 bags store 32.767 as 32.76699829).
_DECIMALS = 3
# A code smeared over centimetres is looked for this far (m) below the largest reading ...
_SPREAD_REACH = 0.5
# ... against the real readings of this much range (m) below it.
_SPREAD_BACKGROUND = 1.0
# A header threshold that would turn real-looking readings into no-returns is contradicted only by
# this fraction of the valid readings (and at least _MIN_COUNT readings).
_MIN_FRACTION = 0.001


@dataclass(frozen=True)
class NoReturnCode:
    """A no-return code found in the data.

    Attributes
    ----------
    values : tuple of float
        The code value(s), metres, ascending (two for twin codes such as 81.83 and 81.91).
    counts : tuple of int
        Readings at each value.
    threshold : float
        ``min(values) - TOLERANCE``: readings at or above it are no-return.
    background : float
        Real readings per centimetre just below the code, the density the codes stand out from.
    strays : int
        Readings above the highest code (fewer than a code holds), no-return too.
    """

    values: tuple[float, ...]
    counts: tuple[int, ...]
    threshold: float
    background: float
    strays: int = 0


@dataclass
class NoReturnDecision:
    """How the no-return threshold of a set of scans was decided.

    Attributes
    ----------
    max_range : float
        The threshold: valid readings at or above it are no-return. Goes to ``Scan.max_range``.
    source : str
        ``"user"`` (the caller's ``max_range``), ``"header"`` (the header value, agreeing with the
        data), ``"data"`` (a code found in the readings) or ``"none found"`` (no code and no usable
        header: no reading is no-return).
    header_name : str or None
        What the header value is (``"PARAM robot_front_laser_max"``, ``"ROBOTLASER1 max_range"``,
        ``"LaserScan range_max"``).
    header_value : float or None
        The header's value, if any.
    code : NoReturnCode or None
        The code found in the data, if any.
    n_readings : int
        Valid readings (finite, positive) looked at.
    n_no_return : int
        Valid readings at or above `max_range`.
    contradiction : str or None
        Set when the header (or the caller's value) and the data disagree, saying how.
    notes : list of str
        Human-readable lines: what was decided and why.
    """

    max_range: float
    source: str
    header_name: str | None = None
    header_value: float | None = None
    code: NoReturnCode | None = None
    n_readings: int = 0
    n_no_return: int = 0
    contradiction: str | None = None
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """Plain-data view (JSON-serialisable) for ``Scan.meta`` and ``describe()``."""
        return {
            "max_range": self.max_range,
            "source": self.source,
            "header": None if self.header_name is None else {"name": self.header_name, "value": self.header_value},
            "code": None if self.code is None else list(self.code.values),
            "code_counts": None if self.code is None else list(self.code.counts),
            "n_readings": self.n_readings,
            "n_no_return": self.n_no_return,
            "contradiction": self.contradiction,
            "notes": list(self.notes),
        }


def _valid(ranges: ArrayLike) -> NDArray[np.float64]:
    r = np.asarray(ranges, dtype=float).reshape(-1)
    return r[usable_ranges(r)]


def _rounded(r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Readings rounded to the codes' precision; one near the float limit (1e308), which
    overflows when rounded, keeps its own value."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.round(r, _DECIMALS)
    return np.where(np.isfinite(out), out, r)


def _code_below(r: NDArray[np.float64], top_index: int) -> NoReturnCode | None:
    """The code whose highest value is ``r[top_index]`` (r sorted ascending), or None."""
    top = r[top_index]
    lo = int(np.searchsorted(r, top - _WINDOW, side="left"))
    window = r[lo : top_index + 1]
    # Background: the real readings just below the window, as readings per bin.
    k = min(_NEIGHBOURS, lo)
    if k < _MIN_COUNT:
        # Nothing (or almost nothing) else to compare with: a constant wall looks the same.
        return None
    below = _rounded(r[:lo])  # sorted, so distinct values are where it steps
    if np.count_nonzero(np.diff(below)) + 1 < _MIN_DISTINCT:
        return None
    span = max(float(top - _WINDOW - r[lo - k]), _BIN)
    background = k * _BIN / span
    values, counts = np.unique(_rounded(window), return_counts=True)
    spike = (counts >= _MIN_COUNT) & (counts >= _RATIO * background)
    if not spike[-1]:
        return None
    codes = values[spike]
    # Values between the lowest code and the top are no-return as well; count them with the codes.
    # Rounded so that 81.91 - 0.01 prints as 81.9, not 81.89999999999999.
    threshold = round(float(codes.min()) - TOLERANCE, 9)
    return NoReturnCode(
        values=tuple(float(v) for v in codes),
        counts=tuple(int(c) for c in counts[spike]),
        threshold=threshold,
        background=float(background),
    )


def detect_no_return_code(ranges: ArrayLike) -> NoReturnCode | None:
    """Find the no-return code in a set of readings, if there is one.

    A code is a value (to the millimetre) within 0.1 m of the top of the distribution that holds at
    least 8 readings and at least 10 times the readings per centimetre of the real ranges just below
    it (estimated from the 50 readings below the 0.1 m window). Several such values in the window
    (81.83 and 81.91) are all codes. The highest code must be the largest reading or lie under
    fewer than 8 readings (a sensor reports next to nothing beyond its code; those strays are
    no-return too), and the readings below must look like real ranges (at least 20 distinct
    values), else nothing is found.

    Parameters
    ----------
    ranges : array_like
        Readings, metres; non-finite and non-positive values are ignored.

    Returns
    -------
    NoReturnCode or None
    """
    r = np.sort(_valid(ranges))
    values = _rounded(r)
    # A sensor reports next to nothing beyond its own code: the code is the largest reading, or
    # lies under fewer stray readings than a code holds (logs where it does: docs/choices.md,
    # "Measured for the code").
    for strays in range(min(_MIN_COUNT, r.size)):
        top_index = r.size - 1 - strays
        if strays and values[top_index] == values[top_index + 1]:
            continue  # readings above it of its own value: not the top of a value
        code = _code_below(r, top_index)
        if code is not None:
            return replace(code, strays=strays)
    return _spread_code(r)


def _spread_code(r: NDArray[np.float64]) -> NoReturnCode | None:
    """A code smeared over a few centimetres (a SICK's 51.05-51.12 m), under more strays than one
    value's rule allows: the densest :data:`_WINDOW` within :data:`_SPREAD_REACH` of the top, when it
    holds a code's share of the readings, :data:`_RATIO` times the real readings of a window just
    below it, and :data:`_RATIO` times the readings above it (r sorted ascending)."""
    if r.size < _MIN_COUNT:
        return None
    top = float(r[-1])
    # Windows ending at each reading near the top: the densest one is the candidate.
    near = np.flatnonzero(r >= top - _SPREAD_REACH)
    starts = np.searchsorted(r, r[near] - _WINDOW, side="left")
    counts = near - starts + 1
    best = int(np.argmax(counts))
    hi_index, lo_index, count = int(near[best]), int(starts[best]), int(counts[best])
    while hi_index + 1 < r.size and r[hi_index + 1] == r[hi_index]:
        hi_index += 1  # the window's last value whole
    count = hi_index - lo_index + 1
    above = r.size - 1 - hi_index
    lo_value = float(r[lo_index])
    if np.unique(_rounded(r[:lo_index])).size < _MIN_DISTINCT:
        return None  # constant walls, not a code over real ranges
    below = r[(r >= lo_value - _SPREAD_BACKGROUND) & (r < lo_value)]
    background = below.size * _WINDOW / _SPREAD_BACKGROUND
    share = count >= max(_MIN_COUNT, int(np.ceil(_MIN_FRACTION * r.size)))
    if not (share and count >= _RATIO * max(background, 1.0) and count >= _RATIO * above):
        return None
    codes = _rounded(r[lo_index : hi_index + 1])
    return NoReturnCode(
        values=(float(codes.min()), float(codes.max())),
        counts=(count,),
        threshold=round(float(codes.min()) - TOLERANCE, 9),
        background=float(background * _BIN / _WINDOW),
        strays=above,
    )


def _fmt(x: float) -> str:
    return f"{x:.6g}"


def _disagreement(r: NDArray[np.float64], header: float, data_threshold: float) -> tuple[int, str]:
    """Readings the header and the data classify differently, and which way."""
    if header < data_threshold:
        # The header calls these no-return; the data says they are real returns. Readings right at
        # the header value are its own (undetected) code, not a disagreement.
        n = int(np.count_nonzero((r >= header + TOLERANCE) & (r < data_threshold)))
        return n, "real returns at or above"
    n = int(np.count_nonzero((r >= data_threshold) & (r < header)))
    return n, "no-return codes below"


def decide_max_range(
    ranges: ArrayLike,
    header: float | None = None,
    header_name: str | None = None,
    user: float | None = None,
) -> NoReturnDecision:
    """Decide the no-return threshold of a set of scans from the caller, the header and the data.

    Parameters
    ----------
    ranges : array_like
        All readings of the scans that share the sensor, metres.
    header : float, optional
        The max range the file states (None when it states none, or states a non-positive value).
    header_name : str, optional
        What `header` is, for the report (``"PARAM robot_front_laser_max"``, ...).
    user : float, optional
        The caller's max range; always wins.

    Returns
    -------
    NoReturnDecision
        See the module notes for the rules.
    """
    r = _valid(ranges)
    code = detect_no_return_code(r)
    top = float(r.max()) if r.size else 0.0
    # "No reading is no-return": just above the largest one (1 mm keeps the printed value tidy).
    none_threshold = top + 0.001 if r.size else 1.0
    data_threshold = code.threshold if code is not None else none_threshold
    if code is not None:
        found = (
            f"code {', '.join(_fmt(v) for v in code.values)} m found in the data "
            f"({', '.join(str(c) for c in code.counts)} readings, against {code.background:.2g} per cm below it"
            + (f"; {code.strays} stray readings above it, no-return too)" if code.strays else ")")
        )
    else:
        found = f"no no-return code in the data (largest reading {_fmt(top)} m)"
    if header is not None and not (np.isfinite(header) and header > 0):
        header = None
    name = header_name or "header max range"

    notes: list[str] = []
    contradiction: str | None = None
    if user is not None:
        threshold, source = float(user), "user"
        notes.append(f"max range {_fmt(threshold)} m given by the caller (--max-range); {found}")
        n, how = _disagreement(r, threshold, data_threshold)
        if code is not None and n >= _MIN_COUNT:
            contradiction = (
                f"the given max range {_fmt(threshold)} m disagrees with the data ({n} {how} it); the given value wins"
            )
    elif header is not None:
        n, how = _disagreement(r, header, data_threshold)
        limit = _MIN_COUNT if header > data_threshold else max(_MIN_COUNT, int(np.ceil(_MIN_FRACTION * r.size)))
        if n < limit:
            threshold, source = float(header), "header"
            at_header = int(np.count_nonzero(np.abs(r - header) <= TOLERANCE))
            if code is None and at_header:
                # Too few to stand out as a code on their own, but where the header says.
                found += f"; {at_header} readings at the header's {_fmt(header)} m"
            notes.append(f"{name} {_fmt(header)} m agrees with the data: {found}")
        else:
            threshold = data_threshold
            source = "data" if code is not None else "none found"
            share = 100.0 * n / max(r.size, 1)
            contradiction = f"{name} is {_fmt(header)} m but the data has {n} {how} it ({share:.3g} % of {r.size} readings); " + (
                f"using the code found in the data ({found})"
                if code is not None
                else f"the data wins: {found}, no reading is no-return"
            )
            notes.append(contradiction)
    elif code is not None:
        threshold, source = data_threshold, "data"
        notes.append(f"no max range in the file; {found}")
    else:
        threshold, source = none_threshold, "none found"
        notes.append(f"no max range in the file and {found}: no reading is no-return")

    n_no_return = int(np.count_nonzero(r >= threshold))
    return NoReturnDecision(
        max_range=float(threshold),
        source=source,
        header_name=header_name if header is not None else None,
        header_value=float(header) if header is not None else None,
        code=code,
        n_readings=int(r.size),
        n_no_return=n_no_return,
        contradiction=contradiction,
        notes=notes,
    )
