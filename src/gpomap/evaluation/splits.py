"""Hold-out splits of a log: which scans train a map and which test it, never both.

The protocol's two splits (:data:`SPLITS`) are ``"blocks"`` (blocks of 40 consecutive scans,
every 5th block held out: whole stretches of the trajectory unseen) and ``"every"`` (every 10th
scan); any ``"every:K"`` or ``"blocks:LEN[:K]"`` works too (:func:`holdout_split`).
:func:`scan_window` picks the part of the log used before any split.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError

#: Fraction held out by "blocks:LEN" without K: one block in five.
DEFAULT_BLOCK_PERIOD = 5
#: The protocol's two splits, by name.
SPLITS = {"blocks": "blocks:40:5", "every": "every:10"}


def resolve_split(split: str) -> str:
    """The hold-out spec a split name stands for ("blocks", "every"); other specs unchanged."""
    return SPLITS.get(str(split), str(split))


def _parse_holdout(holdout: str) -> tuple[str, int, int]:
    parts = str(holdout).split(":")
    try:
        if parts[0] == "every" and len(parts) == 2:
            return "every", int(parts[1]), 1
        if parts[0] == "blocks" and len(parts) in (2, 3):
            return "blocks", int(parts[1]), int(parts[2]) if len(parts) == 3 else DEFAULT_BLOCK_PERIOD
    except ValueError:
        pass
    raise ValueError(f"holdout must be 'every:K', 'blocks:LEN' or 'blocks:LEN:K' with integers, got {holdout!r}")


def check_split(split: str) -> str:
    """The hold-out spec of a split name or spec (see :func:`holdout_split`), checked before any work.

    Raises
    ------
    ValueError
        Not "blocks", "every", ``every:K`` or ``blocks:LEN[:K]`` with integers K >= 2, LEN >= 1.
    """
    spec = resolve_split(split)
    mode, size, period = _parse_holdout(spec)
    if mode == "every" and size < 2:
        raise ValueError(f"'every:K' needs K >= 2, got {spec!r}")
    if size < 1 or (mode == "blocks" and period < 2):
        raise ValueError(f"hold-out sizes must be >= 1 and periods >= 2, got {spec!r}")
    return spec


def holdout_split(n_scans: int, holdout: str = "every:5", seed: int = 0) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Split scan indices into training and held-out (test) scans; the two never overlap.

    Parameters
    ----------
    n_scans : int
        Number of scans (at least 2).
    holdout : str
        A split name ("blocks", "every": :data:`SPLITS`) or spec.
        ``"every:K"``: hold out every K-th scan, starting at a seeded phase in ``[0, K)``
        (about 1/K of the scans). ``"blocks:LEN"`` / ``"blocks:LEN:K"``: cut the sequence into
        consecutive blocks of LEN scans (the first block shortened by a seeded offset in
        ``[0, LEN)``) and hold out every K-th block (default K = 5, so about a fifth), starting at
        a seeded block phase. Held-out blocks keep whole stretches of the trajectory unseen, which
        tests extrapolation more than every-K-th interleaving does.
    seed : int

    Returns
    -------
    train_idx, test_idx : ndarray of int
        Sorted, disjoint, together ``arange(n_scans)``; both non-empty.
    """
    mode, size, period = _parse_holdout(check_split(holdout))
    if n_scans < 2:
        raise EmptyDataError(f"a hold-out split needs at least 2 scans, got {n_scans}")
    rng = np.random.default_rng(seed)
    idx = np.arange(n_scans)
    if mode == "every":
        phase = int(rng.integers(size))
        test = (idx - phase) % size == 0
    else:
        offset = int(rng.integers(size))
        phase = int(rng.integers(period))
        block = (idx + offset) // size
        test = block % period == phase
    # Tiny logs: guarantee both sides are non-empty without breaking disjointness.
    if not test.any():
        test[int(rng.integers(n_scans))] = True
    if test.all():
        test[int(rng.integers(n_scans))] = False
    return np.flatnonzero(~test), np.flatnonzero(test)


def scan_window(scan_range: str | tuple[int | None, int | None] | None) -> slice:
    """The slice of a log that `scan_range` ("FIRST:LAST", a pair, or None) names."""
    if scan_range is None:
        return slice(None)
    if isinstance(scan_range, str):
        try:
            first, last = (int(v) if v.strip() else None for v in scan_range.split(":"))
        except ValueError:
            raise ValueError(f"scan_range must be 'FIRST:LAST' with integers, got {scan_range!r}") from None
    else:
        first, last = scan_range
    return slice(first, last)
