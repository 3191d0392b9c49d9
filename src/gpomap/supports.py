"""GP inputs with extent: boxes (cells) and points, side by side.

A point is a box of zero width. Every input also carries the points it stands for (its members)
and their count, which the summed area kernel and the ``"sum"`` normalisation need. Mixed sets of
cells and points (the paper's eq. 14) are just concatenated supports.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Supports:
    """A set of GP inputs, each an axis-aligned box (possibly of zero width) with member points.

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
        Box corners; ``lower == upper`` for a point.
    counts : ndarray of shape (n,)
        Number of observations each input stands for (1 for a point).
    member_points : ndarray of shape (m, d), optional
        The member points of all inputs, grouped by input.
    member_offsets : ndarray of int, shape (n + 1,), optional
        Members of input ``i`` are ``member_points[member_offsets[i]:member_offsets[i + 1]]``.
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    member_points: NDArray[np.float64] | None = None
    member_offsets: NDArray[np.intp] | None = None

    def __post_init__(self) -> None:
        lo = np.atleast_2d(np.asarray(self.lower, dtype=float))
        hi = np.atleast_2d(np.asarray(self.upper, dtype=float))
        if lo.shape != hi.shape:
            raise ValueError(f"lower and upper must have the same shape, got {lo.shape} and {hi.shape}")
        if np.any(hi < lo):
            raise ValueError("every box needs upper >= lower")
        counts = np.asarray(self.counts, dtype=float).reshape(-1)
        if counts.shape != (lo.shape[0],):
            raise ValueError(f"counts must have shape ({lo.shape[0]},), got {counts.shape}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "counts", counts)
        if (self.member_points is None) != (self.member_offsets is None):
            raise ValueError("member_points and member_offsets go together")
        if self.member_offsets is not None:
            off = np.asarray(self.member_offsets, dtype=np.intp)
            if off.shape != (lo.shape[0] + 1,):
                raise ValueError(f"member_offsets must have shape ({lo.shape[0] + 1},), got {off.shape}")
            object.__setattr__(self, "member_offsets", off)
            object.__setattr__(self, "member_points", np.asarray(self.member_points, dtype=float))

    @classmethod
    def from_points(cls, points: NDArray[np.float64]) -> Supports:
        """Point inputs: zero-width boxes, each its own single member.

        Parameters
        ----------
        points : ndarray of shape (n, d)
        """
        p = np.atleast_2d(np.asarray(points, dtype=float))
        return cls(p, p, np.ones(p.shape[0]), p, np.arange(p.shape[0] + 1, dtype=np.intp))

    @classmethod
    def from_boxes(
        cls, lower: NDArray[np.float64], upper: NDArray[np.float64], counts: NDArray[np.float64] | None = None
    ) -> Supports:
        """Box inputs without member points (for the exact and quadrature area kernels).

        Parameters
        ----------
        lower, upper : ndarray of shape (n, d)
        counts : ndarray of shape (n,), optional
            Observations per box, for the ``"sum"`` normalisation; ones by default.
        """
        lo = np.atleast_2d(np.asarray(lower, dtype=float))
        return cls(lo, upper, np.ones(lo.shape[0]) if counts is None else counts)

    def __len__(self) -> int:
        return int(self.lower.shape[0])

    @property
    def dim(self) -> int:
        """Number of spatial dimensions."""
        return int(self.lower.shape[1])

    @property
    def widths(self) -> NDArray[np.float64]:
        """Box side lengths, ndarray of shape (n, d)."""
        return self.upper - self.lower

    @property
    def centres(self) -> NDArray[np.float64]:
        """Box centres, ndarray of shape (n, d)."""
        return 0.5 * (self.lower + self.upper)

    @property
    def is_point(self) -> NDArray[np.bool_]:
        """True for zero-width inputs, ndarray of shape (n,)."""
        return np.all(self.upper == self.lower, axis=1)

    @property
    def has_members(self) -> bool:
        """Whether member points are known."""
        return self.member_offsets is not None

    def subset(self, index: NDArray[np.intp] | slice) -> Supports:
        """The inputs at `index` (an integer array or a slice), members included."""
        idx = np.arange(len(self))[index]
        off, members = self.member_offsets, self.member_points
        if off is None or members is None:  # no members (the two are set together)
            return Supports(self.lower[idx], self.upper[idx], self.counts[idx])
        sizes = off[idx + 1] - off[idx]
        starts = off[idx]
        take = np.repeat(starts - np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes) + np.arange(int(sizes.sum()))
        return Supports(
            self.lower[idx],
            self.upper[idx],
            self.counts[idx],
            members[take],
            np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp),
        )


def concatenate(parts: Sequence[Supports]) -> Supports:
    """Stack several input sets into one (for example cells and points, the paper's eq. 14)."""
    if not parts:
        raise ValueError("nothing to concatenate")
    lower = np.concatenate([p.lower for p in parts])
    upper = np.concatenate([p.upper for p in parts])
    counts = np.concatenate([p.counts for p in parts])
    members = [(p.member_points, p.member_offsets) for p in parts]
    if any(pts is None or off is None for pts, off in members):
        return Supports(lower, upper, counts)
    points: list[NDArray[np.float64]] = []
    offsets = [np.zeros(1, dtype=np.intp)]
    base = 0
    for pts, off in members:
        assert pts is not None and off is not None  # checked above
        points.append(pts)
        offsets.append(off[1:] + base)
        base += int(off[-1])
    return Supports(lower, upper, counts, np.concatenate(points), np.concatenate(offsets))
