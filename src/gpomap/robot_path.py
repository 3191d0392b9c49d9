"""The robot's own path: the steps between consecutive scans it drove, and its body round them.

Space the robot drove through was free when it did. :func:`path_steps` keeps the steps between
consecutive scans that were driving, not jumps in the log (a new session, a relocalisation, a
held-out stretch whose ends face each other across a wall); the ray counts
(:meth:`gpomap.evidence.RayEvidence.path_passes`) count the cells within :data:`PATH_RADIUS` of
them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.observations import Rays, ScanData, sensor_positions
from gpomap.scans import Scan

#: Longest step between consecutive scans' poses taken as the robot driving (metres); longer
#: steps are jumps in the log (a new session, a relocalisation), not a path. Logs thinned by
#: distance keep a scan about every metre, and a scan lost or held out doubles a step there:
#: with a lower limit such steps were jumps, and the path had a gap at each. A longer step is
#: driving only where the robot drove straight along it (:data:`STRAIGHT_STEP_STRAY`). The logs'
#: steps: docs/choices.md, "The robot's body round its path" and "Measured for the code".
MAX_PATH_STEP: float = 2.5

#: Longest step (metres) taken as driving where the robot drove straight along it: twice
#: :data:`MAX_PATH_STEP`. Longer gaps, such as a held-out block of scans, may hide a detour
#: whatever the ends' headings (docs/choices.md, "The robot's body round its path").
MAX_STRAIGHT_STEP: float = 2 * MAX_PATH_STEP

#: Steps up to this long (metres) are the robot's path as they are. A longer one may not be
#: where the robot drove (a loop in a held-out stretch whose ends face each other across a
#: wall): it is the path only where the robot drove straight along it
#: (:data:`STRAIGHT_STEP_ANGLE`) or neither end's scan has a hit within :data:`PATH_RADIUS` of it
#: (a straight step may pass close to a hit the robot then drove through: a person, a door).
#: Measured in docs/choices.md, "The robot's body round its path".
SURE_PATH_STEP: float = 1.5

#: A planar scan's step is straight driving when both ends' headings lie within this many degrees
#: of the step's direction, forward or backward: between the few degrees of straight steps over a
#: held-out scan and the tens of degrees of turns (docs/choices.md, "The robot's body round its
#: path" and "Measured for the code").
STRAIGHT_STEP_ANGLE: float = 30.0

#: How far (metres) the robot may have strayed from a straight step. An arc that leaves and
#: reaches a step of length L at an angle a to it lies at most (L / 2) tan(a / 2) from it; this
#: is that distance for :data:`MAX_PATH_STEP` and the angle above, so a longer straight step
#: holds its ends' headings closer to it.
STRAIGHT_STEP_STRAY: float = MAX_PATH_STEP / 2 * float(np.tan(np.radians(STRAIGHT_STEP_ANGLE) / 2))

#: The robot's body round its path (metres): the cells the path crosses, shifted by up to this
#: much, count its steps (:meth:`RayEvidence.path_passes`). Any robot that carries a planar lidar
#: is wider than twice this, so these cells were inside it; few held-out hits lie this close to a
#: training path (docs/choices.md, "The robot's body round its path").
PATH_RADIUS: float = 0.1


def path_steps(scans: ScanData) -> NDArray[np.float64]:
    """The robot's path between consecutive scans, as segments (x0, y0, x1, y1), shape (k, 2 d).

    A step up to :data:`SURE_PATH_STEP` long is the path. A longer one is, when the robot drove
    straight along it (planar scans whose headings both lie within :data:`STRAIGHT_STEP_ANGLE` of
    it, and close enough that an arc between them strays at most :data:`STRAIGHT_STEP_STRAY`) and
    it is at most :data:`MAX_STRAIGHT_STEP` long, or, up to :data:`MAX_PATH_STEP`, when neither
    end's scan has a hit within :data:`PATH_RADIUS` of it (it could not have driven through what it
    saw); other steps are jumps.

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
        In log order.
    """
    scans = list(scans)
    if not scans:
        return np.zeros((0, 4))
    poses = sensor_positions(scans)
    d = poses.shape[1]
    steps = np.column_stack([poses[:-1], poses[1:]])
    lengths = np.sqrt(((steps[:, d:] - steps[:, :d]) ** 2).sum(axis=1))
    keep = lengths <= SURE_PATH_STEP
    for k in np.flatnonzero((lengths > SURE_PATH_STEP) & (lengths <= MAX_STRAIGHT_STEP)):
        if _drives_straight(scans[k], scans[k + 1]):
            keep[k] = True
            continue
        if lengths[k] > MAX_PATH_STEP:
            continue
        ends = [Rays.of(s) for s in (scans[k], scans[k + 1])]
        hits = np.concatenate([r.ends[r.hit] for r in ends]).reshape(-1, d)
        keep[k] = not (hits.size and _segment_distances(hits, steps[k, :d], steps[k, d:]).min() <= PATH_RADIUS)
    return steps[keep]


def _drives_straight(first: Scan | CloudScan, second: Scan | CloudScan) -> bool:
    """Whether two planar scans' headings both lie within :data:`STRAIGHT_STEP_ANGLE` of the step
    between them, forward or backward, and within the angle at which an arc between them strays
    :data:`STRAIGHT_STEP_STRAY` from it (point clouds carry no heading: False)."""
    if not (isinstance(first, Scan) and isinstance(second, Scan)):
        return False
    step = second.pose[:2] - first.pose[:2]
    direction = np.arctan2(step[1], step[0])
    # Off the step's line, forward or backward: the heading's difference folded into [0, pi/2].
    off = np.abs(np.angle(np.exp(2j * (np.array([first.pose[2], second.pose[2]]) - direction)))) / 2.0
    # The arc's stray (L / 2) tan(a / 2) solved for a.
    arc = 2.0 * np.arctan(2.0 * STRAIGHT_STEP_STRAY / max(float(np.hypot(*step)), 1e-12))
    return bool(np.all(off <= min(np.radians(STRAIGHT_STEP_ANGLE), arc)))


def _segment_distances(points: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance from each point (n, d) to the segment a-b, shape (n,)."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.sqrt(((points - (a + t[:, None] * ab)) ** 2).sum(axis=1))
