"""A saved map and new scans: the unfitted map of the same settings, which new scans it holds already, and whether a new laser is not the map's.

``gpomap update`` (:mod:`gpomap.cli.update`) adds a new log's scans to a saved map with these; what
the updated map is, against a batch fit of all the scans, is in docs/mapfile.md.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["unfitted_like", "repeated_scans", "other_laser", "bounds_with"]


def unfitted_like(model: Any) -> Any:
    """An unfitted map of `model`'s class with its settings (its tiling as given, not as resolved
    by its fit): its constructor arguments read back (``get_params``), as scikit-learn's clone
    makes one, so no argument is named here."""
    return type(model)(**model.get_params())


def _scan_key(scan: Any) -> bytes:
    from gpomap.clouds import CloudScan

    if isinstance(scan, CloudScan):
        return scan.origin.tobytes() + scan.points.tobytes()
    return scan.pose.tobytes() + scan.ranges.tobytes()


def repeated_scans(saved: Sequence[Any], new: Sequence[Any]) -> int:
    """How many of the `new` scans are already among the `saved` ones (the same pose and readings)."""
    keys = {_scan_key(s) for s in saved}
    return sum(_scan_key(s) in keys for s in new)


def _laser(scan: Any) -> str:
    """A planar scan's laser in words: its beams, their span and its maximum range."""
    span = math.degrees(float(scan.angles.max() - scan.angles.min())) if scan.angles.size > 1 else 0.0
    return f"{scan.angles.size} beams over {span:.1f} degrees, max range {scan.max_range:g} m"


def other_laser(saved: Sequence[Any], new: Sequence[Any]) -> tuple[str, str] | None:
    """A laser among the `new` planar scans that none of the `saved` ones has, and the saved
    scans' most common one, in words (:func:`_laser`); None when every new laser is a saved one,
    or the scans are clouds (whose points vary from scan to scan)."""
    from gpomap.clouds import CloudScan

    if any(isinstance(s, CloudScan) for s in (*saved, *new)):
        return None
    known = Counter(_laser(s) for s in saved)
    other = next((d for d in (_laser(s) for s in new) if d not in known), None)
    return None if other is None else (other, known.most_common(1)[0][0])


def bounds_with(
    bounds: Sequence[Sequence[float]], scans: Sequence[Any], no_return_cap: float | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The box of a map's data grown over new scans: their sensors, hits, and no-return rays as far as they clear free space.

    Parameters
    ----------
    bounds : (lower, upper)
        The saved data's corners, shape (dim,) each.
    scans : sequence of Scan or CloudScan
    no_return_cap : float, optional
        How far a no-return ray clears free space (the map's ``no_return_cap``); None: its whole length.

    Returns
    -------
    lower, upper : ndarray of shape (dim,)
    """
    from gpomap.observations import Rays

    lo, hi = (np.asarray(b, dtype=float) for b in bounds)
    for s in scans:
        rays = Rays.of(s)
        lengths = (
            rays.lengths if no_return_cap is None else np.where(rays.hit, rays.lengths, np.minimum(rays.lengths, no_return_cap))
        )
        pts = np.concatenate([rays.origin.reshape(1, -1), rays.origin + lengths[:, None] * rays.directions])
        lo, hi = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
    return lo, hi
