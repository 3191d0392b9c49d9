"""The cell tree: free and occupied points grouped into axis-aligned rectangular cells.

One box is put round all points and split at the midpoint of its longest side, recursively
(the paper's Fig. 3). A box stops splitting when it holds only one class ("pure") and is no longer
than `max_cell`, or when its longest side is below `min_cell`. Empty boxes are dropped. A box that
reached `min_cell` still holding both classes is *ambiguous*: it is kept as two cells, one over its
hits and one over its free points, so neither class's evidence is lost or averaged away.

Nothing in the tree depends on the dimension: over 3-D points the boxes are cuboids and the
tree is octree-like (a cube splits into eight after three levels).

The tree is walked by compiled code when numba is there (:mod:`gpomap._compiled_cells`, the same
cells exactly); the Python walk below is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap import _compiled_cells
from gpomap.errors import EmptyDataError
from gpomap.lattice import column_bounds
from gpomap.supports import Supports

#: Box conventions: "node" is the tree node's box (the paper), "tight" the bounding box of the
#: cell's own points (never claims unobserved space).
BOX_MODES = ("node", "tight")


@dataclass(frozen=True)
class Cells:
    """The cells of a cell tree, each an axis-aligned box with a label and its member points.

    Attributes
    ----------
    lower, upper : ndarray of shape (n, d)
        The box of each cell (its GP support).
    node_lower, node_upper : ndarray of shape (n, d)
        The tree node each cell came from (equal to the box for ``box="node"``).
    occupied : ndarray of bool, shape (n,)
        Cell label: True for occupied cells, False for free.
    ambiguous : ndarray of bool, shape (n,)
        True for the two halves of a min-size cell that held both classes.
    member_offsets : ndarray of int, shape (n + 1,)
        Members of cell ``i`` are ``points[member_order[member_offsets[i]:member_offsets[i + 1]]]``.
    member_order : ndarray of int, shape (m,)
        Indices into the observation points, grouped by cell.
    points : ndarray of shape (m, d)
        The observation points the cells were built from.
    weights : ndarray of int32, shape (m,), optional
        How many samples each point stands for (merged free samples,
        :attr:`gpomap.observations.Observations.weight`); None: one each.
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    node_lower: NDArray[np.float64]
    node_upper: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    ambiguous: NDArray[np.bool_]
    member_offsets: NDArray[np.intp]
    member_order: NDArray[np.intp]
    points: NDArray[np.float64]
    weights: NDArray[np.int32] | None = None

    def __len__(self) -> int:
        return int(self.occupied.size)

    @property
    def counts(self) -> NDArray[np.intp]:
        """Number of samples per cell, ndarray of shape (n,): its member points, or the samples
        they stand for where they are weighted."""
        if self.weights is None:
            return np.diff(self.member_offsets)
        return np.add.reduceat(self.weights[self.member_order].astype(np.intp), self.member_offsets[:-1])

    @property
    def labels(self) -> NDArray[np.float64]:
        """GP targets: +1 occupied, -1 free, ndarray of shape (n,)."""
        return np.where(self.occupied, 1.0, -1.0)

    @property
    def boxes(self) -> NDArray[np.float64]:
        """Boxes as ndarray of shape (n, 2, d): ``[[xmin, ymin, ...], [xmax, ymax, ...]]`` per cell."""
        return np.stack([self.lower, self.upper], axis=1)

    def members(self, i: int) -> NDArray[np.float64]:
        """Member points of cell `i`, ndarray of shape (m_i, d)."""
        return self.points[self.member_order[self.member_offsets[i] : self.member_offsets[i + 1]]]

    def cell_of_point(self) -> NDArray[np.intp]:
        """Index of the cell holding each observation point, ndarray of shape (m,)."""
        out = np.empty(self.points.shape[0], dtype=np.intp)
        out[self.member_order] = np.repeat(np.arange(len(self)), self.counts)
        return out

    def to_supports(self) -> Supports:
        """The cells as GP inputs: boxes, member counts and member points."""
        return Supports(
            lower=self.lower,
            upper=self.upper,
            counts=self.counts.astype(float),
            member_points=self.points[self.member_order],
            member_offsets=self.member_offsets,
        )


def build_cells(
    points: NDArray[np.float64],
    occupied: NDArray[np.bool_],
    min_cell: float = 0.5,
    max_cell: float = 3.0,
    box: str = "node",
    weights: NDArray[np.int32] | None = None,
) -> Cells:
    """Group labelled points into cells with the longest-axis cell tree.

    Parameters
    ----------
    points : ndarray of shape (m, d)
        Any dimension d >= 1 (planar points, 3-D cloud samples).
    occupied : ndarray of bool, shape (m,)
    min_cell : float
        A box whose longest side is below this stops splitting, pure or not.
    max_cell : float
        A pure box whose longest side is above this splits on (keeps large free areas from
        being claimed by one cell).
    box : {"node", "tight"}
        The box a cell is given: the tree node's ("node", the paper's choice) or the bounding box
        of its own points ("tight"). Ambiguous halves always get the bounding box of their points.
    weights : ndarray of int32, shape (m,), optional
        How many samples each point stands for (:attr:`Cells.weights`): the tree is the points'
        alone, the cells' counts the samples'.

    Returns
    -------
    Cells
    """
    pts = np.asarray(points, dtype=float)
    occ = np.asarray(occupied, dtype=bool)
    if pts.ndim != 2 or pts.shape[1] < 1 or occ.shape != (pts.shape[0],):
        raise ValueError(f"points must have shape (m, d) and occupied (m,), got {pts.shape} and {occ.shape}")
    if pts.shape[0] == 0:
        raise EmptyDataError("no points to build cells from")
    if not (min_cell > 0 and max_cell >= min_cell):
        raise ValueError(f"need 0 < min_cell <= max_cell, got min_cell={min_cell}, max_cell={max_cell}")
    if box not in BOX_MODES:
        raise ValueError(f"box must be one of {BOX_MODES}, got {box!r}")
    if weights is not None and np.shape(weights) != (pts.shape[0],):
        raise ValueError(f"weights must have shape ({pts.shape[0]},), got {np.shape(weights)}")

    lo0, hi0 = column_bounds(pts)
    # A degenerate root (all points on a line or a plane) still needs an extent to split.
    hi0 = np.maximum(hi0, lo0 + 1e-9)
    if _compiled_cells.ENABLED:
        order, offsets, cell_box, node_box, cell_occ, cell_amb = _compiled_cells.cell_tree(
            pts, occ, lo0, hi0, min_cell, max_cell, box == "tight"
        )
        d = pts.shape[1]
        return Cells(
            lower=cell_box[:, :d].copy(),
            upper=cell_box[:, d:].copy(),
            node_lower=node_box[:, :d].copy(),
            node_upper=node_box[:, d:].copy(),
            occupied=cell_occ,
            ambiguous=cell_amb,
            member_offsets=offsets,
            member_order=order,
            points=pts,
            weights=weights,
        )

    # Boxes as tuples of Python floats: a node's few numbers cost less so than as small arrays,
    # and the arithmetic (sides, midpoints) is the same IEEE double arithmetic.
    Box = tuple[float, ...]
    out_lo: list[Box] = []
    out_hi: list[Box] = []
    node_lo: list[Box] = []
    node_hi: list[Box] = []
    out_occ: list[bool] = []
    out_amb: list[bool] = []
    out_members: list[NDArray[np.intp]] = []
    columns = [np.ascontiguousarray(pts[:, j]) for j in range(pts.shape[1])]

    def emit(idx: NDArray[np.intp], lo: Box, hi: Box, label: bool, amb: bool) -> None:
        if box == "tight" or amb:
            out_lo.append(tuple(float(c[idx].min()) for c in columns))
            out_hi.append(tuple(float(c[idx].max()) for c in columns))
        else:
            out_lo.append(lo)
            out_hi.append(hi)
        node_lo.append(lo)
        node_hi.append(hi)
        out_occ.append(label)
        out_amb.append(amb)
        out_members.append(idx)

    # Depth-first with an explicit stack: the tree can be deep for large maps.
    stack: list[tuple[NDArray[np.intp], Box, Box]] = [
        (np.arange(pts.shape[0], dtype=np.intp), tuple(lo0.tolist()), tuple(hi0.tolist()))
    ]
    while stack:
        idx, lo, hi = stack.pop()
        if idx.size == 0:
            continue  # empty cells carry no evidence
        n_occ = int(np.count_nonzero(occ[idx]))
        pure = n_occ == 0 or n_occ == idx.size
        side = [h - l for l, h in zip(lo, hi)]
        longest = max(side)
        if pure and longest <= max_cell:
            emit(idx, lo, hi, n_occ > 0, False)
            continue
        if longest < min_cell:
            if pure:
                emit(idx, lo, hi, n_occ > 0, False)
            else:
                o = occ[idx]
                emit(idx[o], lo, hi, True, True)
                emit(idx[~o], lo, hi, False, True)
            continue
        axis = side.index(longest)  # the first longest, as argmax
        mid = 0.5 * (lo[axis] + hi[axis])
        left = columns[axis][idx] < mid
        lo_r = (*lo[:axis], mid, *lo[axis + 1 :])
        hi_l = (*hi[:axis], mid, *hi[axis + 1 :])
        stack.append((idx[~left], lo_r, hi))
        stack.append((idx[left], lo, hi_l))

    counts = np.array([m.size for m in out_members], dtype=np.intp)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    return Cells(
        lower=np.array(out_lo, dtype=float),
        upper=np.array(out_hi, dtype=float),
        node_lower=np.array(node_lo, dtype=float),
        node_upper=np.array(node_hi, dtype=float),
        occupied=np.array(out_occ, dtype=bool),
        ambiguous=np.array(out_amb, dtype=bool),
        member_offsets=offsets,
        member_order=np.concatenate(out_members).astype(np.intp),
        points=pts,
        weights=weights,
    )
