"""Line segments as GP inputs (GPOMIK's beams), and the quadrature nodes along them.

A beam is a segment of free space from the sensor to its end; a hit, or any point, is a segment
of zero length (:class:`Segments`). A kernel that has no closed form along segments averages its
point kernel over composite Gauss-Legendre nodes along each (:func:`segment_nodes`: panels fixed
in metres, so the nodes never move with the hyperparameters). The kernel itself is
:class:`gpomap.kernels.line.LineKernel`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.kernels.nodes import NodeSet


@dataclass(frozen=True)
class Segments:
    """A set of GP inputs that are line segments; a zero-length segment is a point.

    Parameters
    ----------
    starts, ends : ndarray of shape (n, 2)
        Segment end points (equal for a point).
    counts : ndarray of shape (n,), optional
        Observations each input stands for (ones by default: one beam, one hit). Used by the
        GP's ``"per_count"`` noise model only; the ``"sum"`` normalisation weighs by length.
    """

    starts: NDArray[np.float64]
    ends: NDArray[np.float64]
    counts: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        s = np.asarray(self.starts, dtype=float).reshape(-1, 2)
        e = np.asarray(self.ends, dtype=float).reshape(-1, 2)
        if s.shape != e.shape:
            raise ValueError(f"starts and ends must have the same shape, got {s.shape} and {e.shape}")
        if not (np.isfinite(s).all() and np.isfinite(e).all()):
            raise ValueError("segment end points must be finite")
        c = np.ones(len(s)) if self.counts is None else np.asarray(self.counts, dtype=float).reshape(-1)
        if c.shape != (len(s),):
            raise ValueError(f"counts must have shape ({len(s)},), got {c.shape}")
        object.__setattr__(self, "starts", s)
        object.__setattr__(self, "ends", e)
        object.__setattr__(self, "counts", c)

    @classmethod
    def from_points(cls, points: NDArray[np.float64]) -> Segments:
        """Point inputs: zero-length segments.

        Parameters
        ----------
        points : ndarray of shape (n, 2)
        """
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        return cls(p, p.copy())

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    @property
    def dim(self) -> int:
        """Number of spatial dimensions (2)."""
        return 2

    @property
    def lengths(self) -> NDArray[np.float64]:
        """Segment lengths, ndarray of shape (n,)."""
        d = self.ends - self.starts
        return np.hypot(d[:, 0], d[:, 1])

    @property
    def is_point(self) -> NDArray[np.bool_]:
        """True for zero-length inputs, ndarray of shape (n,)."""
        return np.all(self.starts == self.ends, axis=1)

    @property
    def midpoints(self) -> NDArray[np.float64]:
        """Segment midpoints, ndarray of shape (n, 2)."""
        return 0.5 * (self.starts + self.ends)

    def subset(self, index: NDArray[np.intp] | slice | Sequence[int]) -> Segments:
        """The inputs at `index` (an integer array, a boolean mask or a slice)."""
        idx = np.arange(len(self))[index]
        assert self.counts is not None  # __post_init__ fills it in
        return Segments(self.starts[idx], self.ends[idx], self.counts[idx])


def concatenate_segments(parts: Sequence[Segments]) -> Segments:
    """Stack several segment sets into one (for example beams and hits)."""
    if not parts:
        raise ValueError("nothing to concatenate")
    return Segments(
        np.concatenate([p.starts for p in parts]),
        np.concatenate([p.ends for p in parts]),
        np.concatenate([p.counts for p in parts]),
    )


def as_segments(X: Segments | NDArray[np.float64] | object) -> Segments:
    """`X` as :class:`Segments`: segments as they are, an (n, 2) array or point Supports as points."""
    if isinstance(X, Segments):
        return X
    if hasattr(X, "lower") and hasattr(X, "upper"):
        if not np.all(np.asarray(X.lower) == np.asarray(X.upper)):
            raise ValueError("a line kernel takes segments or points; these Supports hold boxes")
        return Segments(X.lower, X.upper, getattr(X, "counts", None))
    return Segments.from_points(np.asarray(X, dtype=float))


def segment_nodes(X: Segments, order: int, max_panel: float | None = None) -> NodeSet:
    """Composite Gauss-Legendre nodes along each segment, weights summing to one per input.

    Parameters
    ----------
    X : Segments
        n inputs; a point gets one node of weight 1.
    order : int
        Nodes per panel (the rule integrates polynomials of degree ``2 order - 1`` exactly).
    max_panel : float, optional
        Longest panel, in the units of the inputs; a segment of length L gets
        ``ceil(L / max_panel)`` panels. None: one panel per segment.

    Returns
    -------
    NodeSet
    """
    if order < 1:
        raise ValueError(f"quadrature order must be at least 1, got {order}")
    if max_panel is not None and not max_panel > 0:
        raise ValueError(f"max_panel must be positive, got {max_panel}")
    x, w = np.polynomial.legendre.leggauss(int(order))
    L = X.lengths
    point = X.is_point
    panels = np.ones(len(X), dtype=np.intp)
    if max_panel is not None:
        panels = np.maximum(1, np.ceil(L / max_panel - 1e-9)).astype(np.intp)
    sizes = np.where(point, 1, panels * order)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
    owner = np.repeat(np.arange(len(X)), sizes)
    # Position of each node within its input: panel index and node index within the panel.
    k = np.arange(int(offsets[-1])) - offsets[owner]
    npan = panels[owner]
    pan, j = k // order, k % order
    t = (pan + 0.5 * (x[j] + 1.0)) / npan  # in [0, 1] along the segment
    wt = 0.5 * w[j] / npan
    is_pt = point[owner]
    t = np.where(is_pt, 0.0, t)
    wt = np.where(is_pt, 1.0, wt)
    nodes = X.starts[owner] + t[:, None] * (X.ends - X.starts)[owner]
    return NodeSet(nodes, wt, offsets)
