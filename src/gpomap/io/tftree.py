"""A tf tree: the 3-D transforms between a robot's frames over time, as a bag records them.

Each child frame has one parent edge (:class:`TfEdge`), a time series of transforms; an edge is
interpolated at any stamp, linearly in position and along the shorter arc in rotation, and a
static edge (from ``/tf_static``, or whose values never change) is constant. :class:`TfTree`
composes the edges between two frames through their common ancestor. Transforms are rows of
(x, y, z, qx, qy, qz, qw), ROS's quaternion order, so the same tree serves planar LaserScan poses
(:func:`planar` projects them to x, y, yaw) and 3-D clouds (:mod:`gpomap.io.pointcloud2`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError

__all__ = ["TfTree", "TfEdge", "planar", "planar_transform", "slerp", "yaw_from_quaternion", "up_component"]

# Stamps closer than this (seconds) count as equal when checking the pose time range.
_TIME_TOL = 1e-6


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about z) of a unit quaternion, radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def up_component(qx: Any, qy: Any) -> Any:
    """The z component of a frame's z axis rotated by the unit quaternion (qx, qy, qz, qw), in the
    parent frame: 1 level, 0 on its side, -1 upside down. Scalars or arrays."""
    return 1.0 - 2.0 * (np.square(qx) + np.square(qy))


def _qmul(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hamilton products of quaternions (k, 4) in (x, y, z, w) order."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.column_stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def _rotate(q: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectors (k, 3) rotated by unit quaternions (k, 4)."""
    u, w = q[:, :3], q[:, 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _compose(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pose `b` (expressed in frame `a`) in `a`'s parent frame; arrays of shape (k, 7)."""
    return np.column_stack([a[:, :3] + _rotate(a[:, 3:], b[:, :3]), _qmul(a[:, 3:], b[:, 3:])])


def _inverse(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse transforms, shape (k, 7)."""
    q = a[:, 3:] * np.array([-1.0, -1.0, -1.0, 1.0])
    return np.column_stack([-_rotate(q, a[:, :3]), q])


def slerp(q0: NDArray[np.float64], q1: NDArray[np.float64], f: NDArray[np.float64]) -> NDArray[np.float64]:
    """Spherical interpolation along the shorter arc between unit quaternions (k, 4), by f (k,)."""
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-9
    s = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - f, np.sin((1.0 - f) * theta) / s)
    w1 = np.where(small, f, np.sin(f * theta) / s)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def planar(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """3-D transforms (k, 7) projected to (x, y, yaw), shape (k, 3)."""
    x, y, z, w = pose[:, 3], pose[:, 4], pose[:, 5], pose[:, 6]
    return np.column_stack([pose[:, 0], pose[:, 1], np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))])


def planar_transform(x: float, y: float, yaw: float) -> tuple[float, ...]:
    """The 3-D transform (7 values) of a planar pose."""
    return (x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


class TfEdge:
    """Time series of one parent -> child transform.

    Transforms are collected with :meth:`add`, then :meth:`finish` sorts them into arrays.

    Parameters
    ----------
    parent, child : str
        Frame names (without a leading slash).
    static : bool
        Constant in time (``/tf_static``); :meth:`finish` also marks an edge static when its
        published values never change.

    Attributes
    ----------
    t : ndarray of shape (m,)
        Stamps (seconds), increasing, after :meth:`finish`.
    p : ndarray of shape (m, 7)
        Transforms at `t`, rows of (x, y, z, qx, qy, qz, qw), unit quaternions (NaN where the
        bag's was zero).
    """

    def __init__(self, parent: str, child: str, static: bool) -> None:
        self.parent = parent
        self.child = child
        self.static = static
        self._t: list[float] = []
        self._p: list[tuple[float, ...]] = []
        self.t: NDArray[np.float64] = np.empty(0)
        self.p: NDArray[np.float64] = np.empty((0, 7))

    def add(self, t: float, pose: tuple[float, ...]) -> None:
        """Record the transform `pose` (7 values, x, y, z, qx, qy, qz, qw) at stamp `t` (seconds)."""
        self._t.append(t)
        self._p.append(pose)

    def finish(self) -> None:
        """Sort the recorded transforms into :attr:`t` and :attr:`p`, quaternions normalised."""
        t = np.asarray(self._t, dtype=float)
        p = np.asarray(self._p, dtype=float).reshape(-1, 7)
        norm = np.linalg.norm(p[:, 3:], axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            p[:, 3:] = p[:, 3:] / norm  # a zero quaternion becomes NaN: that pose is unusable
        order = np.argsort(t, kind="stable")
        t, p = t[order], p[order]
        # Keep the last of equal stamps, so interpolation never divides by zero.
        last = np.append(np.diff(t) > 0, True)
        self.t, self.p = t[last], p[last]
        # A transform that is republished unchanged (e.g. base_link -> laser on ROS1 /tf) is static.
        if len(self.p) and np.ptp(self.p, axis=0).max() <= 1e-9:
            self.static = True

    def at(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Interpolated transforms at times `t` (k,): poses (k, 7) and a mask of times in range."""
        if self.static or len(self.t) == 1:
            return np.repeat(self.p[-1:], len(t), axis=0), np.ones(len(t), dtype=bool)
        ok = (t >= self.t[0] - _TIME_TOL) & (t <= self.t[-1] + _TIME_TOL)
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[i], self.t[i + 1]
        f = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
        p0, p1 = self.p[i], self.p[i + 1]
        xyz = p0[:, :3] + f[:, None] * (p1[:, :3] - p0[:, :3])
        return np.column_stack([xyz, slerp(p0[:, 3:], p1[:, 3:], f)]), ok


class TfTree:
    """A tf tree: each child frame has one parent edge; transforms are rows of (x, y, z, qx, qy, qz, qw).

    Attributes
    ----------
    edges : dict of str to TfEdge
        Each child frame's edge from its parent.
    """

    def __init__(self) -> None:
        self.edges: dict[str, TfEdge] = {}

    def add(self, parent: str, child: str, t: float, pose: tuple[float, ...], static: bool) -> None:
        """Record the transform `pose` (7 values) of `child` in `parent` at stamp `t` (seconds)."""
        edge = self.edges.get(child)
        if edge is None:
            edge = self.edges[child] = TfEdge(parent, child, static)
        elif edge.parent != parent:
            # tf allows one parent per frame; a second one would be a broken tree. Keep the first.
            return
        edge.add(t, pose)

    def finish(self) -> None:
        """Finish every edge (:meth:`TfEdge.finish`); call once all transforms are added."""
        for e in self.edges.values():
            e.finish()

    def frames(self) -> list[str]:
        """Every frame the tree names, sorted."""
        names = set(self.edges)
        names.update(e.parent for e in self.edges.values())
        return sorted(names)

    def chain(self, frame: str) -> list[str]:
        """`frame` and its ancestors, up to the root."""
        out = [frame]
        seen = {frame}
        while out[-1] in self.edges:
            parent = self.edges[out[-1]].parent
            if parent in seen:  # a cycle: stop rather than loop
                break
            out.append(parent)
            seen.add(parent)
        return out

    def _down(self, ancestor: str, frame: str, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Pose of `frame` in `ancestor` at times `t`, shape (k, 7)."""
        pose = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (len(t), 1))
        ok = np.ones(len(t), dtype=bool)
        for f in self.chain(frame):
            if f == ancestor:
                break
            p, m = self.edges[f].at(t)
            pose = _compose(p, pose)
            ok &= m
        return pose, ok

    def path_edges(self, fixed: str, target: str) -> list[TfEdge]:
        """The edges between `fixed` and `target` (through their common ancestor)."""
        up = self.chain(target)
        common = next((f for f in self.chain(fixed) if f in up), None)
        edges = []
        for start in (fixed, target):
            for f in self.chain(start):
                if f == common:
                    break
                edges.append(self.edges[f])
        return edges

    def lookup(self, fixed: str, target: str, t: NDArray[np.float64], path: str) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Pose of `target` in `fixed` at times `t` (k,): 3-D transforms (k, 7) and in-range mask (k,)."""
        known = self.frames()
        for name, what in ((fixed, "fixed frame"), (target, "laser frame")):
            if name not in known:
                raise InputFormatError(f"unknown {what} {name!r}; known tf frames: {', '.join(known) or '(none)'}", path=path)
        up = self.chain(target)
        common = next((f for f in self.chain(fixed) if f in up), None)
        if common is None:
            raise InputFormatError(
                f"no tf path from {fixed!r} to {target!r}: they are in different trees; known tf frames: {', '.join(known)}",
                path=path,
            )
        a, ok_a = self._down(common, fixed, t)
        b, ok_b = self._down(common, target, t)
        return _compose(_inverse(a), b), ok_a & ok_b
