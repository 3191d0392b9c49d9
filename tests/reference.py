"""Slow, obviously-correct reference computations that the fast kernels are checked against.

Nothing here is used by gpomap itself: these are brute-force sums and integrals that share no code
with the closed forms and quadrature rules under test.
"""

from __future__ import annotations

import numpy as np


def midpoint_nodes(lower, upper, n):
    """Midpoint-rule nodes and equal weights (summing to one) over a box; one node for a point."""
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    axes = []
    for lo, hi in zip(lower, upper):
        if hi == lo:
            axes.append(np.array([lo]))
        else:
            axes.append(lo + (np.arange(n) + 0.5) * (hi - lo) / n)
    grid = np.meshgrid(*axes, indexing="ij")
    nodes = np.column_stack([g.ravel() for g in grid])
    return nodes, np.full(nodes.shape[0], 1.0 / nodes.shape[0])


def box_average(point_kernel, lower_a, upper_a, lower_b, upper_b, n=60):
    """The point kernel averaged over two boxes by a fine midpoint rule."""
    pa, wa = midpoint_nodes(lower_a, upper_a, n)
    pb, wb = midpoint_nodes(lower_b, upper_b, n)
    return float(wa @ point_kernel(pa, pb) @ wb)


def summed_by_loops(point_kernel, members_a, members_b):
    """The paper's eq. 13 with explicit loops: sum over all member pairs."""
    total = 0.0
    for x in members_a:
        for y in members_b:
            total += float(point_kernel(np.asarray(x)[None, :], np.asarray(y)[None, :])[0, 0])
    return total
