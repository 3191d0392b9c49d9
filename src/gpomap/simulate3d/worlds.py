"""Built-in 3-D worlds: an office of three rooms and a store room, each with camera poses inside it.

:func:`office_scene` and :func:`office_poses` build three rooms on a corridor of doorways, with
tables, shelves, a cabinet, a sofa and a pillar, and ten camera poses inside them;
:func:`storeroom_scene` and :func:`storeroom_poses` a store room of tall shelves and aisles with an
office behind a doorway, and eight poses. Both are made of the pieces here (walls with doorways,
tables, open shelves) and moved off the 0.1 m lattice by :data:`SCENE_OFFSET`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.simulate3d.depth import look_at
from gpomap.simulate3d.scene import Scene

__all__ = ["office_scene", "office_poses", "storeroom_scene", "storeroom_poses", "SCENE_OFFSET"]


def _wall_with_door(
    name: str,
    axis: str,
    at: tuple[float, float],
    span: tuple[float, float],
    door: tuple[float, float],
    height: float,
    door_height: float,
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """A wall `at` (its two faces) across `axis` ("x": the wall's faces are x = const), running
    along the other horizontal axis over `span`, with a doorway over `door` up to `door_height`."""

    def box(a: tuple[float, float], b: tuple[float, float], z: tuple[float, float]) -> tuple[ArrayLike, ArrayLike]:
        if axis == "x":
            return (a[0], b[0], z[0]), (a[1], b[1], z[1])
        return (b[0], a[0], z[0]), (b[1], a[1], z[1])

    out: list[tuple[str, ArrayLike, ArrayLike]] = []
    for part, (s0, s1), (z0, z1) in (
        ("left", (span[0], door[0]), (0.0, height)),
        ("right", (door[1], span[1]), (0.0, height)),
        ("lintel", door, (door_height, height)),
    ):
        if s1 > s0 and z1 > z0:
            out.append((f"{name} {part}", *box(at, (s0, s1), (z0, z1))))
    return out


def _table(
    name: str, x: tuple[float, float], y: tuple[float, float], height: float = 0.75
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """A table: a 4 cm top at `height` on four 5 cm legs."""
    out: list[tuple[str, ArrayLike, ArrayLike]] = [(f"{name} top", (x[0], y[0], height - 0.04), (x[1], y[1], height))]
    for lx in (x[0] + 0.03, x[1] - 0.08):
        for ly in (y[0] + 0.03, y[1] - 0.08):
            out.append((f"{name} leg", (lx, ly, 0.0), (lx + 0.05, ly + 0.05, height - 0.04)))
    return out


def _shelf(
    name: str, x: tuple[float, float], y: tuple[float, float], height: float, boards: int, back: str
) -> list[tuple[str, ArrayLike, ArrayLike]]:
    """An open shelf: two 3 cm side panels along its longer side's ends, `boards` 3 cm boards, a
    2 cm back panel on the side `back` ("x-", "x+", "y-", "y+")."""
    along_x = (x[1] - x[0]) >= (y[1] - y[0])
    out: list[tuple[str, ArrayLike, ArrayLike]] = []
    if along_x:
        out += [(f"{name} side", (x[0], y[0], 0.0), (x[0] + 0.03, y[1], height))]
        out += [(f"{name} side", (x[1] - 0.03, y[0], 0.0), (x[1], y[1], height))]
    else:
        out += [(f"{name} side", (x[0], y[0], 0.0), (x[1], y[0] + 0.03, height))]
        out += [(f"{name} side", (x[0], y[1] - 0.03, 0.0), (x[1], y[1], height))]
    for z in np.linspace(0.08, height - 0.03, boards):
        out.append((f"{name} board", (x[0], y[0], float(z)), (x[1], y[1], float(z) + 0.03)))
    bx = {
        "x-": ((x[0], x[0] + 0.02), y),
        "x+": ((x[1] - 0.02, x[1]), y),
        "y-": (x, (y[0], y[0] + 0.02)),
        "y+": (x, (y[1] - 0.02, y[1])),
    }
    (bx0, bx1), (by0, by1) = bx[back]
    out.append((f"{name} back", (bx0, by0, 0.0), (bx1, by1, height)))
    return out


#: Moves every box of the built-in scenes off the 0.1 m lattice (m), as a real building is.
SCENE_OFFSET: tuple[float, float, float] = (0.037, 0.061, 0.013)


def office_scene() -> Scene:
    """Three rooms in a row (9.2 x 6.3 m inside, 2.65 m high) joined by doorways, furnished.

    Room A (x 0-3): a table, a shelf against the west wall, a box on the floor; room B (x 3.12-6.1):
    a desk, a cabinet, a chair; room C (x 6.22-9.2): a sofa, two shelves, a pillar, a half-height
    partition. 20 cm outer walls, 12 cm inner ones, a floor and a ceiling slab; every box moved by
    :data:`SCENE_OFFSET`.
    """
    H = 2.65
    boxes: list[tuple[str, ArrayLike, ArrayLike]] = [
        ("floor", (-0.2, -0.2, -0.2), (9.4, 6.5, 0.0)),
        ("ceiling", (-0.2, -0.2, H), (9.4, 6.5, H + 0.2)),
        ("wall west", (-0.2, -0.2, 0.0), (0.0, 6.5, H)),
        ("wall east", (9.2, -0.2, 0.0), (9.4, 6.5, H)),
        ("wall south", (0.0, -0.2, 0.0), (9.2, 0.0, H)),
        ("wall north", (0.0, 6.3, 0.0), (9.2, 6.5, H)),
    ]
    boxes += _wall_with_door("wall AB", "x", (3.0, 3.12), (0.0, 6.3), (1.0, 1.9), H, 2.05)
    boxes += _wall_with_door("wall BC", "x", (6.1, 6.22), (0.0, 6.3), (4.3, 5.2), H, 2.05)
    # Room A.
    boxes += _table("table A", (0.8, 2.2), (3.6, 4.5))
    boxes += _shelf("shelf A", (0.0, 0.4), (0.6, 1.8), 1.9, 5, "x-")
    boxes += [("crate A", (2.1, 0.3, 0.0), (2.7, 0.8, 0.45))]
    # Room B.
    boxes += _table("desk B", (3.6, 5.2), (0.2, 0.9), 0.76)
    boxes += [("cabinet B", (4.2, 5.7, 0.0), (5.0, 6.3, 1.1))]
    boxes += [("chair B seat", (4.1, 1.1, 0.42), (4.55, 1.55, 0.47)), ("chair B column", (4.28, 1.28, 0.0), (4.37, 1.37, 0.42))]
    boxes += [("chair B back", (4.1, 1.51, 0.47), (4.55, 1.55, 0.95))]
    # Room C.
    boxes += [("sofa C seat", (6.6, 5.5, 0.0), (8.4, 6.3, 0.45)), ("sofa C back", (6.6, 6.1, 0.45), (8.4, 6.3, 0.85))]
    boxes += _shelf("shelf C1", (9.2 - 0.35, 9.2), (3.4, 4.6), 2.0, 6, "x+")
    boxes += _shelf("shelf C2", (6.4, 7.6), (0.0, 0.35), 1.2, 3, "y-")
    boxes += [("pillar C", (7.7, 1.4, 0.0), (8.0, 1.7, H)), ("partition C", (7.9, 3.0, 0.0), (9.2, 3.1, 1.3))]
    return Scene.from_boxes(boxes, SCENE_OFFSET)


def office_poses() -> list[NDArray[np.float64]]:
    """Ten camera poses in :func:`office_scene` (camera to world), three or four a room, some
    looking through a doorway."""
    shift = np.asarray(SCENE_OFFSET)
    views = [
        ((1.5, 1.0, 1.5), (1.0, 5.0, 0.6)),
        ((2.5, 5.6, 1.4), (0.3, 1.2, 0.9)),
        ((0.6, 3.0, 1.6), (3.1, 1.4, 1.0)),
        ((4.6, 2.5, 1.5), (4.6, 6.3, 0.5)),
        ((5.6, 4.5, 1.3), (3.6, 0.5, 0.7)),
        ((3.5, 3.3, 1.6), (6.5, 4.7, 1.1)),
        ((7.0, 4.0, 1.5), (9.0, 6.0, 0.5)),
        ((8.8, 0.6, 1.4), (6.5, 3.0, 0.8)),
        ((6.6, 2.0, 1.6), (9.2, 2.0, 1.2)),
        ((8.5, 4.6, 1.3), (6.3, 0.3, 0.6)),
    ]
    return [look_at(np.asarray(p) + shift, np.asarray(t) + shift) for p, t in views]


def storeroom_scene() -> Scene:
    """A store room 8 x 5 m inside, 3 m high: three rows of tall shelves with aisles between
    them, a workbench, crates on the floor, and an office behind a wall with a doorway."""
    H = 3.0
    boxes: list[tuple[str, ArrayLike, ArrayLike]] = [
        ("floor", (-0.2, -0.2, -0.2), (8.2, 5.2, 0.0)),
        ("ceiling", (-0.2, -0.2, H), (8.2, 5.2, H + 0.2)),
        ("wall west", (-0.2, -0.2, 0.0), (0.0, 5.2, H)),
        ("wall east", (8.0, -0.2, 0.0), (8.2, 5.2, H)),
        ("wall south", (0.0, -0.2, 0.0), (8.0, 0.0, H)),
        ("wall north", (0.0, 5.0, 0.0), (8.0, 5.2, H)),
    ]
    boxes += _wall_with_door("wall office", "x", (5.6, 5.72), (0.0, 5.0), (3.6, 4.5), H, 2.1)
    for n, y0 in enumerate((0.9, 2.1, 3.3)):
        boxes += _shelf(f"rack {n}", (0.9, 4.1), (y0, y0 + 0.5), 2.2, 5, "y-")
    boxes += _table("bench", (0.2, 1.6), (4.3, 4.95), 0.9)
    boxes += [("crate 1", (4.5, 0.2, 0.0), (5.1, 0.8, 0.6)), ("crate 2", (4.6, 0.25, 0.6), (5.0, 0.7, 0.95))]
    boxes += [("crate 3", (4.4, 4.2, 0.0), (5.2, 4.9, 0.7))]
    boxes += _table("office desk", (6.3, 7.9), (0.1, 0.8), 0.75)
    boxes += [("office cabinet", (7.4, 3.9, 0.0), (7.95, 4.95, 1.9))]
    return Scene.from_boxes(boxes, SCENE_OFFSET)


def storeroom_poses() -> list[NDArray[np.float64]]:
    """Eight camera poses in :func:`storeroom_scene`: down the aisles, across the room, into the office."""
    shift = np.asarray(SCENE_OFFSET)
    views = [
        ((0.4, 0.45, 1.6), (4.5, 0.6, 0.8)),
        ((4.7, 1.85, 1.4), (0.5, 1.8, 0.9)),
        ((0.5, 3.05, 1.5), (4.5, 3.0, 0.7)),
        ((4.9, 4.1, 1.7), (0.3, 4.6, 0.6)),
        ((5.1, 2.5, 1.8), (0.5, 0.5, 0.5)),
        ((2.5, 4.3, 1.6), (5.5, 0.3, 0.4)),
        ((4.8, 3.5, 1.5), (7.9, 4.5, 0.9)),
        ((7.6, 2.5, 1.4), (6.0, 0.3, 0.6)),
    ]
    return [look_at(np.asarray(p) + shift, np.asarray(t) + shift) for p, t in views]
