"""OctoMap octrees (``.bt`` binary and ``.ot`` full files), read and written through pyoctomap.

Reading gives every leaf of the tree: its centre, its side (a pruned leaf covers 2^d voxels of
the tree's resolution along each axis), its occupancy probability and whether OctoMap counts it
occupied (probability above the tree's occupancy threshold). A ``.bt`` file keeps only
occupied / free per leaf, so its probabilities are the tree's clamping bounds (0.971 and 0.1192 by
default); a ``.ot`` file keeps each leaf's log-odds.

Why the file is walked here before pyoctomap reads it: OctoMap's readers trust the stream. They
print an error and return a partial tree on a size mismatch, and they recurse into whatever child
bits they read, without a depth limit or an end-of-file check, so a corrupt file can recurse past
the tree's 16 levels. :func:`check_octree_file` parses the header (line numbers in messages) and
walks the node records (2 bytes per inner node in ``.bt``; a 4-byte log-odds and a 1-byte child
mask per node in ``.ot``), refusing a tree deeper than 16 levels, a truncated stream and a node
count other than the header's ``size``. Only then does pyoctomap read it.

Writing (:func:`write_octree`) puts each known voxel of a :class:`~gpomap.voxels.VoxelMap` into an
OctoMap tree of the same resolution with its log-odds (clamped by OctoMap to its bounds); unknown
voxels stay unknown. ``.bt`` keeps occupied / free (OctoMap makes the tree maximum-likelihood and
prunes it before writing), ``.ot`` the probabilities. The bytes go through
:func:`gpomap.io.atomic.atomic_write`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.extras import require
from gpomap.grid import UNKNOWN
from gpomap.io.atomic import atomic_write
from gpomap.io.checks import regular_file
from gpomap.voxels import VoxelMap

__all__ = ["Octree", "read_octree", "check_octree_file", "write_octree", "is_octree_file", "BT_MAGIC", "OT_MAGIC", "TREE_DEPTH"]

BT_MAGIC = b"# Octomap OcTree binary file"
OT_MAGIC = b"# Octomap OcTree file"
#: Levels of an OctoMap tree: leaves at depth 16 at most.
TREE_DEPTH = 16
_MAX_HEADER_LINES = 64

# Per byte of a .bt child record (4 children x 2 bits, child i in bits 2i and 2i+1: neither = no
# child, bit 2i alone = free leaf, bit 2i+1 alone = occupied leaf, both = inner node): how many
# children exist and how many are inner nodes.
_BT_CHILDREN = np.array([sum(((b >> (2 * i)) & 3) != 0 for i in range(4)) for b in range(256)])
_BT_INNER = np.array([sum(((b >> (2 * i)) & 3) == 3 for i in range(4)) for b in range(256)])
_POPCOUNT = np.array([bin(b).count("1") for b in range(256)])


def is_octree_file(head: bytes) -> bool:
    """Whether the start of a file is an OctoMap header (``.bt`` or ``.ot``)."""
    return head.startswith(BT_MAGIC) or head.startswith(OT_MAGIC)


@dataclass
class Octree:
    """The leaves of an OctoMap tree.

    Attributes
    ----------
    centres : ndarray of shape (n, 3)
        Leaf centres, metres.
    sizes : ndarray of shape (n,)
        Leaf sides, metres (the resolution times a power of two).
    probability : ndarray of shape (n,)
        Occupancy probability of each leaf.
    occupied : ndarray of bool, shape (n,)
        OctoMap's decision (probability above `occupancy_threshold`).
    resolution : float
        Side of the smallest voxel, metres.
    kind : str
        ``"bt"`` or ``"ot"``.
    n_nodes : int
        Nodes in the tree (inner and leaves), the header's ``size``.
    params : dict
        The tree's sensor model: ``prob_hit``, ``prob_miss``, ``clamping_min``, ``clamping_max``,
        ``occupancy_threshold``.
    """

    centres: NDArray[np.float64]
    sizes: NDArray[np.float64]
    probability: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    resolution: float
    kind: str
    n_nodes: int
    params: dict[str, float] = field(default_factory=dict)

    @property
    def n_leaves(self) -> int:
        """Number of leaves."""
        return len(self.sizes)

    def extent(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper corners (x, y, z) of the box holding every leaf, shape (3,) each."""
        half = self.sizes[:, None] / 2
        return (self.centres - half).min(axis=0), (self.centres + half).max(axis=0)

    def voxel_centres(self, occupied: bool) -> NDArray[np.float64]:
        """Centres of every resolution-sized voxel inside the occupied (or free) leaves, shape (m, 3)."""
        sel = self.occupied == occupied
        out = []
        for size in np.unique(self.sizes[sel]):
            c = self.centres[sel & (self.sizes == size)]
            n = max(1, round(size / self.resolution))
            offs = (np.arange(n) - (n - 1) / 2) * self.resolution
            grid = np.stack(np.meshgrid(offs, offs, offs, indexing="ij"), axis=-1).reshape(-1, 3)
            out.append((c[:, None, :] + grid[None]).reshape(-1, 3))
        return np.concatenate(out) if out else np.empty((0, 3))


def _parse_header(path: str) -> tuple[str, dict[str, str], int]:
    """Kind (``"bt"`` / ``"ot"``), header values (id, size, res) and the data offset."""
    with open(path, "rb") as f:
        first = f.readline(256)
        if first.rstrip(b"\r\n") == BT_MAGIC:
            kind = "bt"
        elif first.rstrip(b"\r\n") == OT_MAGIC:
            kind = "ot"
        else:
            raise InputFormatError(
                f"first line is {first[:60]!r}; expected {BT_MAGIC.decode()!r} (.bt) or {OT_MAGIC.decode()!r} (.ot)",
                path=path,
                line=1,
            )
        offset = len(first)
        values: dict[str, str] = {}
        for lineno in range(2, _MAX_HEADER_LINES):
            raw = f.readline(256)
            if not raw:
                raise InputFormatError(
                    "file ends in the header; expected id, size, res and a 'data' line", path=path, line=lineno
                )
            offset += len(raw)
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise InputFormatError(
                    "header line is not text; expected id, size, res or data", path=path, line=lineno
                ) from None
            if not line or line.startswith("#"):
                continue
            key, _, value = line.partition(" ")
            if key == "data":
                break
            if key not in ("id", "size", "res"):
                raise InputFormatError(f"unknown header key {key!r}; expected id, size, res or data", path=path, line=lineno)
            values[key] = value.strip()
            values[f"line_{key}"] = str(lineno)
        else:
            raise InputFormatError(f"no 'data' line in the first {_MAX_HEADER_LINES} lines", path=path)
    for key in ("size", "res"):
        if key not in values:
            raise InputFormatError(f"header has no {key!r} line; expected id, size, res, data", path=path)
    if kind == "ot" and values.get("id", "OcTree") != "OcTree":
        raise InputFormatError(f"tree type {values['id']!r}; this reader takes id OcTree", path=path, line=int(values["line_id"]))
    return kind, values, offset


def _walk_bt(data: bytes) -> int:
    """Nodes in a .bt node stream (checked: depth, truncation); raises ValueError."""
    pos = 0
    nodes = 1
    depths = [0]
    while depths:
        depth = depths.pop()
        if pos + 2 > len(data):
            raise ValueError(f"tree data ends after {pos:,} bytes, inside a node at depth {depth}")
        b0, b1 = data[pos], data[pos + 1]
        pos += 2
        nodes += int(_BT_CHILDREN[b0] + _BT_CHILDREN[b1])
        inner = int(_BT_INNER[b0] + _BT_INNER[b1])
        if inner and depth + 1 >= TREE_DEPTH:
            raise ValueError(f"an inner node at depth {depth + 1} (byte {pos - 2:,}); OctoMap trees have {TREE_DEPTH} levels")
        depths.extend([depth + 1] * inner)
    return nodes


def _walk_ot(data: bytes) -> int:
    """Nodes in a .ot node stream (4-byte log-odds + child mask each); raises ValueError."""
    pos = 0
    nodes = 0
    depths = [0]
    while depths:
        depth = depths.pop()
        if pos + 5 > len(data):
            raise ValueError(f"tree data ends after {pos:,} bytes, inside a node at depth {depth}")
        mask = data[pos + 4]
        pos += 5
        nodes += 1
        if mask and depth >= TREE_DEPTH:
            raise ValueError(f"a node at depth {depth} has children (byte {pos - 5:,}); OctoMap trees have {TREE_DEPTH} levels")
        depths.extend([depth + 1] * int(_POPCOUNT[mask]))
    return nodes


def check_octree_file(path: str | os.PathLike[str]) -> tuple[str, float, int]:
    """Check an OctoMap file's header and node stream without building the tree.

    Returns
    -------
    kind : str
        ``"bt"`` or ``"ot"``.
    resolution : float
    n_nodes : int

    Raises
    ------
    InputFormatError
        Not a regular file; a first line other than OctoMap's; a header without ``size``,
        ``res`` or ``data``, or with values that are not numbers; a stream that ends early, goes
        deeper than 16 levels, or holds another number of nodes than ``size``.
    """
    p = regular_file(path, "OctoMap file (.bt or .ot)")
    spath = str(p)
    try:
        kind, values, offset = _parse_header(spath)
        with open(p, "rb") as f:
            f.seek(offset)
            data = f.read()
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc})", path=spath) from None
    try:
        size = int(values["size"])
        if size < 0:
            raise ValueError
    except ValueError:
        raise InputFormatError(
            f"size {values['size']!r}; expected a non-negative integer", path=spath, line=int(values["line_size"])
        ) from None
    try:
        res = float(values["res"])
        if not (np.isfinite(res) and res > 0):
            raise ValueError
    except ValueError:
        raise InputFormatError(
            f"res {values['res']!r}; expected a positive number (metres)", path=spath, line=int(values["line_res"])
        ) from None
    if size == 0:
        return kind, res, 0
    try:
        n = _walk_bt(data) if kind == "bt" else _walk_ot(data)
    except ValueError as exc:
        raise InputFormatError(f"corrupt tree: {exc}", path=spath) from None
    if n != size:
        raise InputFormatError(f"tree data hold {n:,} nodes; the header's size says {size:,}", path=spath)
    return kind, res, n


def _params(tree: Any) -> dict[str, float]:
    return {
        "prob_hit": float(tree.getProbHit()),
        "prob_miss": float(tree.getProbMiss()),
        "clamping_min": float(tree.getClampingThresMin()),
        "clamping_max": float(tree.getClampingThresMax()),
        "occupancy_threshold": float(tree.getOccupancyThres()),
    }


def load_pyoctomap_tree(path: str | os.PathLike[str]) -> tuple[Any, str, int]:
    """The file as a ``pyoctomap.OcTree`` (after :func:`check_octree_file`), its kind and node count."""
    pyoctomap = require("pyoctomap", "reading OctoMap trees")

    kind, res, n = check_octree_file(path)
    spath = str(path)
    if kind == "bt":
        tree = pyoctomap.OcTree(res)
        if n and not tree.readBinary(spath):
            raise InputFormatError("OctoMap could not read the binary tree", path=spath)
    else:
        tree = pyoctomap.OcTree(res).read(spath) if n else pyoctomap.OcTree(res)
        if tree is None:
            raise InputFormatError("OctoMap could not read the tree", path=spath)
    if int(tree.size()) != n:
        raise InputFormatError(f"OctoMap read {tree.size():,} nodes; the file holds {n:,}", path=spath)
    return tree, kind, n


def read_octree(path: str | os.PathLike[str]) -> Octree:
    """Read the leaves of an OctoMap ``.bt`` or ``.ot`` file.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    Octree

    Raises
    ------
    InputFormatError
        See :func:`check_octree_file`.
    """
    tree, kind, n = load_pyoctomap_tree(path)
    centres, sizes, values = [], [], []
    params = _params(tree)
    for leaf in tree.begin_leafs():
        centres.append(leaf.getCoordinate())
        sizes.append(leaf.getSize())
        # A .bt leaf is occupied or free, nothing more: asking OctoMap that is faster than
        # fetching the node's value.
        values.append(tree.isNodeOccupied(leaf) if kind == "bt" else leaf.current_node.getOccupancy())
    if kind == "bt":
        occ = np.asarray(values, dtype=bool)
        p = np.where(occ, params["clamping_max"], params["clamping_min"])
    else:
        p = np.asarray(values, dtype=float)
        occ = p > params["occupancy_threshold"]
    return Octree(
        centres=np.asarray(centres, dtype=float).reshape(-1, 3),
        sizes=np.asarray(sizes, dtype=float),
        probability=p,
        occupied=occ,
        resolution=float(tree.getResolution()),
        kind=kind,
        n_nodes=n,
        params=params,
    )


def octree_from_voxels(voxel_map: VoxelMap) -> Any:
    """A ``pyoctomap.OcTree`` at the map's resolution holding its known voxels' log-odds: those
    neither unknown in the ternary map nor unobserved (no ray went there: left unknown in the tree)."""
    pyoctomap = require("pyoctomap", "writing map.bt")

    tree = pyoctomap.OcTree(voxel_map.spec.resolution)
    known = (voxel_map.ternary != UNKNOWN) & voxel_map.seen
    p = np.clip(voxel_map.probability[known], 1e-6, 1 - 1e-6)
    log_odds = np.log(p / (1 - p))
    for c, lo in zip(voxel_map.spec.centres()[known.reshape(-1)], log_odds):
        tree.updateNode(c, float(lo), True)  # lazy: the inner nodes are updated once at the end
    tree.updateInnerOccupancy()
    return tree


def write_octree(voxel_map: VoxelMap, path: str | os.PathLike[str]) -> Path:
    """Write the known voxels of `voxel_map` as an OctoMap ``.bt`` or ``.ot`` file, atomically.

    Parameters
    ----------
    voxel_map : VoxelMap
        Voxels whose ternary value is unknown are left out (unknown in the tree).
    path : path-like
        Ending in ``.bt`` (occupied / free) or ``.ot`` (probabilities).

    Returns
    -------
    Path
        `path`.
    """
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in (".bt", ".ot"):
        raise ValueError(f"an OctoMap file name ends in .bt or .ot, got {target.name!r}")
    tree = octree_from_voxels(voxel_map)
    data = tree.writeBinary() if suffix == ".bt" else tree.write()
    if data is False:
        raise RuntimeError(f"OctoMap could not serialise the tree for {target}")
    with atomic_write(target, "wb") as f:
        f.write(bytes(data))
    return target
