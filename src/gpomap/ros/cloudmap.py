"""The streaming mapper for 3-D clouds the live map uses: :class:`~gpomap.streaming.StreamingGPOM` on :class:`~gpomap.clouds.CloudScan`.

:class:`~gpomap.tiles.TiledGPOM` is dimension-generic (3-D tiles are x, y columns); the streaming
mapper's warm-up, refresh and calibration are too. Only its change record after the warm-up reads
a planar scan's pose, so this subclass records a cloud's x, y box instead.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from gpomap.clouds import CloudScan
from gpomap.streaming import StreamingGPOM

__all__ = ["CloudStreamingGPOM"]


class CloudStreamingGPOM(StreamingGPOM):
    """:class:`~gpomap.streaming.StreamingGPOM` for 3-D clouds (same parameters and attributes)."""

    def add_scans(self, scans: Sequence[Any]) -> None:
        """Add clouds, in the order the sensor took them (see :meth:`StreamingGPOM.add_scans`).

        Parameters
        ----------
        scans : sequence of CloudScan
        """
        clouds = list(scans)
        if not clouds or self.model_ is None:
            super().add_scans(clouds)
            return
        t0 = time.perf_counter()
        self.n_scans_ += len(clouds)
        self.model_.absorb(clouds)
        self._record_change(_xy_box(clouds))
        self._add_seconds.append((time.perf_counter() - t0) / len(clouds))


def _xy_box(clouds: Sequence[CloudScan]) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of the clouds' valid endpoints and origins."""
    pts = np.concatenate([c.points[c.valid(), :2] for c in clouds] + [np.array([c.origin[:2] for c in clouds])])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])
