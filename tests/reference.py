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


def _difference_axis(lo_a, hi_a, lo_b, hi_b, n):
    """Nodes and weights (summing to one) of u = s - t, s uniform on [lo_a, hi_a], t on [lo_b, hi_b].

    The density of u is the overlap length of [lo_a, hi_a] and [u + lo_b, u + hi_b] over the
    product of the widths (a trapezoid); a zero-width side makes it uniform over the other, two
    zero-width sides a single node.
    """
    wa, wb = hi_a - lo_a, hi_b - lo_b
    lo, hi = lo_a - hi_b, hi_a - lo_b
    if hi == lo:
        return np.array([lo]), np.array([1.0])
    u = lo + (np.arange(n) + 0.5) * (hi - lo) / n
    if wa == 0 or wb == 0:
        return u, np.full(n, 1.0 / n)
    overlap = np.clip(np.minimum(hi_a, u + hi_b) - np.maximum(lo_a, u + lo_b), 0.0, None)
    w = overlap / (wa * wb) * (hi - lo) / n
    return u, w


def box_average_by_difference(point_kernel, lower_a, upper_a, lower_b, upper_b, n=80):
    """The point kernel averaged over two boxes of any dimension, as a d-dimensional integral.

    For a stationary kernel the 2d-dimensional double average is E[k(a - b)], and a - b has,
    per axis, the trapezoid density of a difference of two uniforms; a midpoint rule on its
    support (n nodes per axis) integrates k against it. Nothing here uses a separable kernel, so
    it checks the Matern 3/2 quadrature as well as the squared exponential's closed form.
    """
    axes = [_difference_axis(la, ua, lb, ub, n) for la, ua, lb, ub in zip(lower_a, upper_a, lower_b, upper_b)]
    grid = np.meshgrid(*[u for u, _ in axes], indexing="ij")
    weights = np.meshgrid(*[w for _, w in axes], indexing="ij")
    u = np.column_stack([g.ravel() for g in grid])
    w = np.prod(np.column_stack([g.ravel() for g in weights]), axis=1)
    return float(w @ point_kernel(u, np.zeros((1, u.shape[1])))[:, 0])
