"""The fitted continuous map as one file, ``map.gpom``: saved once, read later at any resolution, extended.

``gpomap map`` writes the grids it was asked for (``map.yaml`` / ``.pgm`` / ``.npz`` / ``.png``)
and, beside them, the fitted map itself in ``map.gpom``: :func:`save_fitted_map` writes one,
:func:`load_fitted_map` (``gpomap.load_map``) reads it back as the very model that was saved, a
:class:`~gpomap.tiles.TiledGPOM` whose ``predict_proba(points, return_var=True)`` and
``grid(resolution, extent)`` give the live model's answers to the bit, and whose ``update(scans)``
extends it. (``gpomap.io.npz.load_map`` reads a *written grid*, ``map.npz``: numbers on cells of
one resolution, not a model.)

The file is a zip archive of NumPy ``.npy`` arrays (``numpy.load(path, allow_pickle=False)``
opens it; nothing in it is a pickle): one array ``header``, a JSON string, and the arrays it names.
The header holds

- ``format``: ``"gpomap-fitted-map"``; ``version``: :data:`VERSION`, raised whenever what is saved
  changes; ``written_by``: the gpomap version;
- ``kind``: ``"map"`` (:func:`save_fitted_map`) or ``"stream"`` (:func:`save_streaming_state`: a
  :class:`~gpomap.streaming.StreamingGPOM` to resume);
- ``summary``: what a command checks before loading the map (dimension, bounds of the data,
  scans, tiles, largest tile, hyperparameters, thresholds);
- ``state``: the model's attributes, encoded generically: numbers, strings and lists as JSON;
  each NumPy array as ``{"$array": NAME}``, NAME the archive member; tuples, sets and dicts with
  other keys than strings tagged (``$tuple``, ``$set``, ``$items``); a dataclass as
  ``{"$dataclass": CLASS, "fields": {...}}`` with every init field; any other object of the map
  as ``{"$object": CLASS, "state": {...}}`` with every attribute but the caches of
  :data:`NOT_SAVED`. CLASS is one of :func:`saved_classes` (nothing else is made on loading).

So a field added to a calibration dataclass, or an attribute added to the model, is saved without
a change here; a dataclass whose fields are not those the file holds is refused on loading, naming
the class and the fields, and :data:`VERSION` is raised with any such change so that files of the
old layout are refused too (``tests/test_mapfile.py`` pins the layout and says so). Some things
are stored in a form of their own: each tile's Cholesky factor by its lower triangle (``$tril``),
the scans as arrays (``$scans``: poses, beam angles, ranges; a cloud's origin, points and hit
flags), and what follows from the scans is recomputed from them on loading instead of stored: the
labelled points along the beams
(:func:`gpomap.observations.observations_from_scans`, filed under their blocks as the fit filed
them, ``$from_scans``) and the beams of the ray counts (:meth:`gpomap.evidence.RayEvidence.from_scans`;
their scan indices and the robot's path between scans are stored, ``$rays``). Both are checked
against the counts saved with them. A map fitted on labelled points (no scans) stores its points.

Everything a refit needs is in the file (the scans and the settings), so a map can be extended
(``TiledGPOM.update``, ``gpomap update``) or refitted from scratch (``gpomap update --relearn``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import zipfile
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.atomic import atomic_write
from gpomap.io.checks import MAX_NPZ_ARRAY_BYTES, load_npz, regular_file

__all__ = [
    "FORMAT",
    "VERSION",
    "FILENAME",
    "NOT_SAVED",
    "save_fitted_map",
    "load_fitted_map",
    "save_streaming_state",
    "load_streaming_state",
    "read_map_header",
    "saved_classes",
]

FORMAT = "gpomap-fitted-map"
#: Raised whenever what a map file holds changes; a file of another version is refused.
VERSION = 2
#: The map file ``gpomap map`` writes beside its grids: ``.gpom``, not ``.npz``, so that it is never
#: taken for the written grid ``map.npz`` (though both are zip archives of NumPy arrays).
FILENAME = "map.gpom"
_HEADER = "header"
_WHAT = "gpomap map file (.gpom, written by gpomap map or save_fitted_map)"

#: Attributes that are caches or belong to the running process, not to the map: not saved, and set
#: to these values on loading (by class name). A map loaded runs its tiles locally (``scheduler``).
NOT_SAVED: dict[str, dict[str, Any]] = {
    "gpomap.tiles.TiledGPOM": {"_client": None, "scheduler": None},
    "gpomap.fusion.EvidenceLayer": {"_at_surface": None, "_joined": None, "_grid_cache": None},
    "gpomap.gp.GPPosterior": {"precision": None},
}


def _name(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def saved_classes() -> dict[str, type]:
    """The classes a map file may hold, by the name the file gives them (module and qualified name)."""
    from gpomap.fusion import CalibrationSample, EvidenceCalibration, EvidenceLayer
    from gpomap.gp import GPPosterior
    from gpomap.grid import GridSpec
    from gpomap.kernels.area import AreaKernel
    from gpomap.kernels.point import KERNELS
    from gpomap.mapping import AreaGPOM
    from gpomap.revisit import RevisitCalibration
    from gpomap.settings import MapSettings
    from gpomap.squash import ProbitSquash
    from gpomap.streaming import StreamingGPOM
    from gpomap.supports import Supports
    from gpomap.tiles import TiledGPOM, TileState, _BlockCells, _BlockPoints
    from gpomap.voxels import VoxelSpec

    classes: list[type] = [
        TiledGPOM,
        AreaGPOM,
        StreamingGPOM,
        MapSettings,
        TileState,
        GPPosterior,
        Supports,
        AreaKernel,
        *KERNELS.values(),
        ProbitSquash,
        _BlockCells,
        _BlockPoints,
        EvidenceLayer,
        EvidenceCalibration,
        RevisitCalibration,
        CalibrationSample,
        GridSpec,
        VoxelSpec,
    ]
    return {_name(c): c for c in classes}


def _not_saved(cls: type) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for base in reversed(cls.__mro__):
        out.update(NOT_SAVED.get(_name(base), {}))
    return out


def _is_namedtuple(value: Any) -> bool:
    return isinstance(value, tuple) and hasattr(type(value), "_fields")


# --------------------------------------------------------------------------- scans as arrays
def _scan_arrays(scans: Sequence[Any]) -> dict[str, NDArray[Any]]:
    """The scans of a list (all planar or all clouds) as a few arrays, exactly (their ``meta`` is not kept)."""
    from gpomap.clouds import CloudScan

    n = len(scans)
    clouds = n > 0 and isinstance(scans[0], CloudScan)
    if any(isinstance(s, CloudScan) != clouds for s in scans):
        raise TypeError("cannot save a list mixing planar scans and point clouds")
    times = np.array([math.nan if s.time is None else float(s.time) for s in scans], dtype=float)
    out: dict[str, NDArray[Any]] = {
        "time": times,
        "has_time": np.array([s.time is not None for s in scans], dtype=bool),
    }
    if clouds:
        sizes = [s.points.shape[0] for s in scans]
        out.update(
            origin=np.array([s.origin for s in scans], dtype=float).reshape(n, 3),
            points=np.concatenate([s.points for s in scans]).reshape(-1, 3) if n else np.zeros((0, 3)),
            hit=np.concatenate([np.asarray(s.hit, dtype=bool) for s in scans]) if n else np.zeros(0, bool),
            max_range=np.array([math.nan if s.max_range is None else s.max_range for s in scans], dtype=float),
            has_max_range=np.array([s.max_range is not None for s in scans], dtype=bool),
        )
    else:
        sizes = [s.ranges.size for s in scans]
        out.update(
            pose=np.array([s.pose for s in scans], dtype=float).reshape(n, 3),
            angles=np.concatenate([s.angles for s in scans]) if n else np.zeros(0),
            ranges=np.concatenate([s.ranges for s in scans]) if n else np.zeros(0),
            max_range=np.array([s.max_range for s in scans], dtype=float),
        )
    out["offsets"] = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).astype(np.int64)
    return out


def _scans_from_arrays(a: dict[str, NDArray[Any]], kind: str) -> list[Any]:
    from gpomap.clouds import CloudScan
    from gpomap.scans import Scan

    off = a["offsets"]
    times = [float(t) if has else None for t, has in zip(a["time"], a["has_time"], strict=True)]
    if kind == "clouds":
        ranges = [float(r) if has else None for r, has in zip(a["max_range"], a["has_max_range"], strict=True)]
        return [
            CloudScan(a["origin"][i], a["points"][off[i] : off[i + 1]], a["hit"][off[i] : off[i + 1]], ranges[i], times[i])
            for i in range(len(times))
        ]
    return [
        Scan(a["pose"][i], a["angles"][off[i] : off[i + 1]], a["ranges"][off[i] : off[i + 1]], float(a["max_range"][i]), times[i])
        for i in range(len(times))
    ]


# --------------------------------------------------------------------------- lower triangles
def _pack_lower(L: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The lower triangle of square `L`, row by row, shape (n (n + 1) / 2,); None when `L` has
    anything above its diagonal (it is then stored whole)."""
    n = L.shape[0]
    if L.ndim != 2 or L.shape[1] != n or L.dtype != np.float64:
        return None
    below = np.tri(n, dtype=bool)
    if L[~below].any():
        return None
    return L[below]  # row by row: the lower triangle's order


def _unpack_lower(packed: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    if packed.shape != (n * (n + 1) // 2,):
        raise ValueError(f"a packed lower triangle of {n} rows needs {n * (n + 1) // 2} numbers, got {packed.shape}")
    L = np.zeros((n, n))
    L[np.tri(n, dtype=bool)] = packed
    return L


# --------------------------------------------------------------------------- encoding
class _Writer:
    """Turns a model into JSON-able state and its arrays (the archive members), each handed to
    `sink` as it is met (written at once, so a map's tiles are never all in memory; kept in
    :attr:`arrays` without a sink)."""

    def __init__(self, sink: Callable[[str, NDArray[Any]], None] | None = None) -> None:
        self.arrays: dict[str, NDArray[Any]] = {}
        self._sink = sink
        self._keys: set[str] = set()
        self._scans: dict[tuple[int, ...], dict[str, Any]] = {}
        self._models: list[Any] = []  # the TiledGPOMs being encoded, innermost last
        self._classes = saved_classes()
        self._names = {c: n for n, c in self._classes.items()}

    def add(self, where: str, array: NDArray[Any]) -> str:
        key = where
        i = 1
        while key in self._keys or key == _HEADER:
            i += 1
            key = f"{where}~{i}"
        self._keys.add(key)
        if self._sink is not None:
            self._sink(key, np.ascontiguousarray(array))
        else:
            self.arrays[key] = np.ascontiguousarray(array)
        return key

    def scans(self, scans: list[Any] | None, where: str) -> Any:
        if scans is None:
            return None
        ids = tuple(id(s) for s in scans)
        if ids not in self._scans:  # the model's scans and its ray counts' are the same objects
            from gpomap.clouds import CloudScan

            kind = "clouds" if scans and isinstance(scans[0], CloudScan) else "planar"
            arrays = {k: self.add(f"{where}/{k}", v) for k, v in _scan_arrays(scans).items()}
            self._scans[ids] = {"kind": kind, "arrays": arrays}
        return {"$scans": self._scans[ids]}

    def encode(self, value: Any, where: str) -> Any:
        from gpomap.tiles import TileStore

        if value is None or isinstance(value, (bool, str)):
            return value
        if isinstance(value, np.bool_):
            return bool(value)
        if isinstance(value, (int, np.integer)):
            return int(value)
        if isinstance(value, (float, np.floating)):
            return float(value)
        if isinstance(value, np.ndarray):
            if value.dtype.hasobject:
                raise TypeError(f"cannot save an array of Python objects ({where})")
            return {"$array": self.add(where, value)}
        if isinstance(value, bytes):
            return {"$bytes": self.add(where, np.frombuffer(value, dtype=np.uint8))}
        cls = type(value)
        if _is_namedtuple(value):
            return {"$namedtuple": self._class_name(cls, where), "fields": self._fields(value, value._fields, where)}
        if isinstance(value, tuple):
            return {"$tuple": [self.encode(v, f"{where}/{i}") for i, v in enumerate(value)]}
        if isinstance(value, list):
            return [self.encode(v, f"{where}/{i}") for i, v in enumerate(value)]
        if isinstance(value, (set, frozenset)):
            return {"$set": [self.encode(v, f"{where}/{i}") for i, v in enumerate(sorted(value))]}
        if isinstance(value, TileStore):
            # Read back tile by tile, each let go once written (their factors are written as they come).
            return {
                "$items": [
                    [self.encode(k, f"{where}/{i}k"), self.encode(value.peek(k), f"{where}/{i}")] for i, k in enumerate(value)
                ]
            }
        if isinstance(value, dict):
            if all(isinstance(k, str) and not k.startswith("$") for k in value):
                return {k: self.encode(v, f"{where}/{k}") for k, v in value.items()}
            return {
                "$items": [
                    [self.encode(k, f"{where}/{i}k"), self.encode(v, f"{where}/{i}")] for i, (k, v) in enumerate(value.items())
                ]
            }
        name = self._class_name(cls, where)
        if dataclasses.is_dataclass(value):
            skip = _not_saved(cls)
            names = [f.name for f in dataclasses.fields(value) if f.init and f.name not in skip]
            return {"$dataclass": name, "fields": self._fields(value, names, where)}
        return self._object(value, name, where)

    def _class_name(self, cls: type, where: str) -> str:
        if cls not in self._names:
            raise TypeError(
                f"cannot save a {_name(cls)} ({where}): not a class a map file holds (gpomap.io.mapfile.saved_classes)"
            )
        return self._names[cls]

    def _fields(self, value: Any, names: Sequence[str], where: str) -> dict[str, Any]:
        from gpomap.gp import GPPosterior

        out = {}
        for n in names:
            v = getattr(value, n)
            if isinstance(value, GPPosterior) and n == "L":
                packed = _pack_lower(v)
                if packed is not None:
                    out[n] = {"$tril": self.add(f"{where}/L", packed), "n": int(v.shape[0])}
                    continue
            out[n] = self.encode(v, f"{where}/{n}")
        return out

    def _object(self, value: Any, name: str, where: str) -> dict[str, Any]:
        from gpomap.fusion import EvidenceLayer
        from gpomap.streaming import StreamingGPOM
        from gpomap.tiles import TiledGPOM, _BlockPoints

        skip = _not_saved(type(value))
        state: dict[str, Any] = {}
        if isinstance(value, TiledGPOM):
            self._models.append(value)
        try:
            for attr, v in vars(value).items():
                w = f"{where}/{attr}"
                if attr in skip:
                    continue
                scans = (TiledGPOM, "_scans"), (StreamingGPOM, "_buffer"), (EvidenceLayer, "_scans")
                if any(isinstance(value, c) and attr == a for c, a in scans):
                    state[attr] = self.scans(v, w)
                elif isinstance(value, EvidenceLayer) and attr == "_parts":
                    state[attr] = self._rays(value, w)
                elif isinstance(value, EvidenceLayer) and attr == "gp_apart":
                    state[attr] = self._gp_apart(v, w)
                elif isinstance(value, _BlockPoints) and attr == "_parts" and self._points_from_scans():
                    points, _ = value.arrays()
                    state[attr] = {"$from_scans": int(points.shape[0])}
                else:
                    state[attr] = self.encode(v, w)
        finally:
            if isinstance(value, TiledGPOM):
                self._models.pop()
        return {"$object": name, "state": state}

    def _points_from_scans(self) -> bool:
        """Whether the model being encoded can recompute its labelled points from its scans."""
        return bool(self._models) and getattr(self._models[-1], "_scans", None) is not None

    def _gp_apart(self, fn: Any, where: str) -> Any:
        if fn is None:
            return None
        model = self._models[-1] if self._models else None
        if model is not None and getattr(fn, "__self__", None) is model and getattr(fn, "__name__", "") == "_gp_apart":
            return {"$ref": "model._gp_apart"}
        raise TypeError(f"cannot save the ray evidence's gp_apart {fn!r} ({where}): only its own map's _gp_apart")

    def _rays(self, layer: Any, where: str) -> dict[str, Any]:
        """The ray counts' beams as their scan indices and the path; the beams themselves follow from the scans."""
        parts = layer._parts
        d = layer._dim
        if parts:
            # As EvidenceLayer.evidence joins them (without joining them here: saving changes nothing).
            offsets = np.cumsum([0] + [p.n_scans for p in parts[:-1]])
            scan = np.concatenate([p.scan + o for p, o in zip(parts, offsets, strict=True)]).astype(np.intp)
            path = np.concatenate([p.path for p in parts]).reshape(-1, 2 * d)
            n_beams = int(sum(p.hit.size for p in parts))
        else:
            scan, path, n_beams = np.zeros(0, np.intp), np.zeros((0, 2 * d)), 0
        return {
            "$rays": {
                "scan": self.add(f"{where}/scan", scan),
                "path": self.add(f"{where}/path", path),
                "n_beams": n_beams,
                "n_parts": len(parts),
            }
        }


# --------------------------------------------------------------------------- decoding
class _StateError(Exception):
    """The state is not what this gpomap writes (turned into an InputFormatError naming the file)."""


class _Reader:
    def __init__(self, arrays: dict[str, NDArray[Any]]) -> None:
        self.arrays = arrays
        self._classes = saved_classes()
        self._scans: dict[str, list[Any]] = {}
        self._models: list[Any] = []
        self._points: list[tuple[Any, Any, int]] = []  # (model, block points, saved count)

    def array(self, key: Any) -> NDArray[Any]:
        if not isinstance(key, str) or key not in self.arrays:
            raise _StateError(f"array {key!r} is missing (a truncated or altered file)")
        return self.arrays[key]

    def cls(self, name: Any) -> Any:
        if name not in self._classes:
            raise _StateError(f"class {name!r} is not one a map file holds")
        return self._classes[name]

    def decode(self, enc: Any) -> Any:
        if enc is None or isinstance(enc, (bool, int, float, str)):
            return enc
        if isinstance(enc, list):
            return [self.decode(v) for v in enc]
        if not isinstance(enc, dict):
            raise _StateError(f"unexpected {type(enc).__name__} in the state")
        tags = [k for k in enc if k.startswith("$")]
        if not tags:
            return {k: self.decode(v) for k, v in enc.items()}
        tag = tags[0]
        if tag == "$array":
            return self.array(enc["$array"])
        if tag == "$bytes":
            return self.array(enc["$bytes"]).tobytes()
        if tag == "$tril":
            return _unpack_lower(np.asarray(self.array(enc["$tril"]), dtype=np.float64), int(enc["n"]))
        if tag == "$tuple":
            return tuple(self.decode(v) for v in enc["$tuple"])
        if tag == "$set":
            return {self._hashable(self.decode(v)) for v in enc["$set"]}
        if tag == "$items":
            return {self._hashable(self.decode(k)): self.decode(v) for k, v in enc["$items"]}
        if tag == "$scans":
            return self._decode_scans(enc["$scans"])
        if tag == "$namedtuple":
            cls = self.cls(enc["$namedtuple"])
            return cls(**self._checked_fields(cls, list(cls._fields), enc["fields"]))
        if tag == "$dataclass":
            cls = self.cls(enc["$dataclass"])
            if not dataclasses.is_dataclass(cls):
                raise _StateError(f"{enc['$dataclass']} is not a dataclass")
            names = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in _not_saved(cls)]  # type: ignore[arg-type]
            return cls(**self._checked_fields(cls, names, enc["fields"]))  # type: ignore[arg-type, operator]
        if tag == "$object":
            return self._object(self.cls(enc["$object"]), enc["state"])
        if tag == "$ref":
            if enc["$ref"] != "model._gp_apart" or not self._models:
                raise _StateError(f"unknown reference {enc['$ref']!r}")
            return self._models[-1]._gp_apart
        if tag in ("$rays", "$from_scans"):
            return _Pending(tag, enc[tag])
        raise _StateError(f"unknown tag {tag!r}")

    @staticmethod
    def _hashable(value: Any) -> Any:
        if isinstance(value, list):
            raise _StateError("a list cannot be a set member or a dict key")
        return value

    def _checked_fields(self, cls: type, names: list[str], fields: Any) -> dict[str, Any]:
        if not isinstance(fields, dict) or sorted(fields) != sorted(names):
            have = sorted(fields) if isinstance(fields, dict) else fields
            raise _StateError(
                f"{_name(cls)} has the fields {sorted(names)} in this gpomap, the file holds {have}: "
                "written by another version of gpomap"
            )
        return {k: self.decode(v) for k, v in fields.items()}

    def _decode_scans(self, enc: Any) -> list[Any]:
        key = json.dumps(enc, sort_keys=True)
        if key not in self._scans:
            kind = enc["kind"]
            if kind not in ("planar", "clouds"):
                raise _StateError(f"unknown scan kind {kind!r}")
            self._scans[key] = _scans_from_arrays({k: self.array(v) for k, v in enc["arrays"].items()}, kind)
        return list(self._scans[key])

    def _object(self, cls: Any, state: Any) -> Any:
        from gpomap.fusion import EvidenceLayer
        from gpomap.tiles import TiledGPOM, TileStore, _BlockPoints

        if not isinstance(state, dict):
            raise _StateError(f"{_name(cls)}: its state must be an object")
        skip = _not_saved(cls)
        extra = sorted(set(state) & set(skip))
        if extra:
            raise _StateError(f"{_name(cls)}: {extra} are caches, never saved")
        obj = cls.__new__(cls)
        if isinstance(obj, TiledGPOM):
            self._models.append(obj)
        try:
            values = {k: self.decode(v) for k, v in state.items()}
            obj.__dict__.update(skip)
            obj.__dict__.update(values)
            if isinstance(obj, _BlockPoints) and isinstance(values.get("_parts"), _Pending):
                if not self._models:
                    raise _StateError("block points to recompute outside a map")
                obj._parts = []
                self._points.append((self._models[-1], obj, int(values["_parts"].value)))
            if isinstance(obj, EvidenceLayer) and isinstance(values.get("_parts"), _Pending):
                _restore_rays(obj, values["_parts"].value, self)
            if isinstance(obj, TiledGPOM):
                if isinstance(values.get("tiles_"), dict):
                    obj.tiles_ = TileStore(tiles=values["tiles_"])  # saved as a dict of its states
                _restore_points(obj, [(bp, n) for m, bp, n in self._points if m is obj])
                self._points = [p for p in self._points if p[0] is not obj]
        finally:
            if isinstance(obj, TiledGPOM):
                self._models.pop()
        return obj


@dataclasses.dataclass
class _Pending:
    """A value recomputed once its object's other attributes are loaded."""

    tag: str
    value: Any


def _restore_rays(layer: Any, enc: dict[str, Any], reader: _Reader) -> None:
    """The ray counts' beams, from their scans; their scan indices and path as saved."""
    from gpomap.evidence import RayEvidence

    scan = np.asarray(reader.array(enc["scan"]), dtype=np.intp)
    path = np.asarray(reader.array(enc["path"]), dtype=float)
    if int(enc["n_parts"]) == 0:
        layer._parts = []
        return
    full = RayEvidence.from_scans(layer._scans, layer.no_return_cap)
    if full.hit.size != int(enc["n_beams"]) or scan.shape != full.hit.shape:
        raise _StateError(f"the ray counts' {int(enc['n_beams'])} beams are not the {full.hit.size} of the scans saved with them")
    layer._parts = [RayEvidence(full.starts, full.ends, full.hit, scan, path)]


def _restore_points(model: Any, blocks: list[tuple[Any, int]]) -> None:
    """The labelled points of a map fitted on scans, recomputed from them and filed as the fit filed them."""
    if not blocks:
        return
    from gpomap.errors import EmptyDataError
    from gpomap.observations import observations_from_scans

    b = model.base
    saved = (model._n_points, model._n_occupied_points, set(model._tiles_with_points), len(model._block_points))
    lower, upper = model._lower, model._upper
    model._n_points = model._n_occupied_points = 0
    try:
        obs = observations_from_scans(model._scans, b.free_step, b.hit_margin, b.no_return_cap)
        points, occupied = np.asarray(obs.points, dtype=float), np.asarray(obs.occupied, dtype=bool)
    except EmptyDataError:
        points, occupied = np.zeros((0, model._dim)), np.zeros(0, dtype=bool)
    model._add_points(points, occupied)
    model._lower, model._upper = lower, upper
    now = (model._n_points, model._n_occupied_points, set(model._tiles_with_points), len(model._block_points))
    if now != saved or any(bp.arrays()[0].shape[0] != n for bp, n in blocks):
        raise _StateError(
            f"the scans saved give {now[0]} labelled points in {now[3]} blocks; the map was fitted on {saved[0]} in {saved[3]}"
        )


# --------------------------------------------------------------------------- the file
def _summary(model: Any) -> dict[str, Any]:
    lo, hi = model.bounds_
    from gpomap.tiles import light_tiles

    cells = [s.n_cells for s in light_tiles(model.tiles_)]
    return {
        "class": _name(type(model)),
        "dim": int(model.dim_),
        "bounds": [[float(v) for v in lo], [float(v) for v in hi]],
        "n_scans": int(model._n_scans),
        "scans_kept": model._scans is not None,
        "n_tiles": len(cells),
        "largest_tile_cells": int(max(cells)) if cells else 0,
        "n_cells": int(model.n_inputs_),
        "hyperparameters": {k: float(v) for k, v in model.hyperparameters_.items()},
        "thresholds": [float(t) for t in model.thresholds_],
        "ray_evidence": model.evidence_ is not None,
        "no_return_cap": model.base.no_return_cap,
        "evidence_resolution": float(model.base.evidence_resolution_3d if model.dim_ == 3 else model.base.evidence_resolution),
    }


#: Bytes of an array deflate is tried on before the whole array is (:func:`_deflates`): a building's
#: map file holds tens of thousands of arrays (each tile's factor, cells and weights).
_DEFLATE_SAMPLE = 1 << 13


def _deflates(array: NDArray[Any]) -> bool:
    """Whether to deflate `array`'s member: when its first bytes shrink by a fifth at least (ray
    counts, flags, offsets, beam angles repeated scan after scan, the header). Cholesky factors and
    ranges barely shrink, and deflating them would cost more time than it saves bytes."""
    raw = np.ascontiguousarray(array).view(np.uint8).reshape(-1)[:_DEFLATE_SAMPLE].tobytes()
    return len(raw) < 1024 or len(zlib.compress(raw, 1)) < 0.8 * len(raw)


def _write_member(zf: zipfile.ZipFile, key: str, array: NDArray[Any]) -> None:
    """One array as the member ``KEY.npy``, deflated where that pays (:func:`_deflates`)."""
    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED if _deflates(array) else zipfile.ZIP_STORED
    with zf.open(info, "w", force_zip64=array.nbytes > (1 << 30)) as member:
        np.lib.format.write_array(member, array, allow_pickle=False)


def _write(path: str | os.PathLike[str], obj: Any, where: str, header: Callable[[Any], dict[str, Any]]) -> Path:
    """The archive of `obj`: every array as the state is encoded, then the header (``header(state)``)."""
    target = Path(path)
    with atomic_write(target, "wb") as f, zipfile.ZipFile(f, "w", allowZip64=True) as zf:
        state = _Writer(lambda key, array: _write_member(zf, key, array)).encode(obj, where)
        text = json.dumps(header(state), allow_nan=True, separators=(",", ":"))
        _write_member(zf, _HEADER, np.array(text))
    return target


def save_fitted_map(model: Any, path: str | os.PathLike[str]) -> Path:
    """Write a fitted map to `path` (``map.gpom`` by convention), atomically.

    Parameters
    ----------
    model : TiledGPOM
        A fitted map (an :class:`~gpomap.mapping.AreaGPOM`, or a
        :class:`~gpomap.streaming.StreamingGPOM`'s ``model_``), 2-D or 3-D. Saved as it is,
        tiles waiting for a refresh included: the file predicts what the model predicts now.
        Not to be changed by another thread while it is saved.
    path : path-like
        Written exactly as given (no suffix is added).

    Returns
    -------
    Path

    Raises
    ------
    TypeError
        `model` is not a TiledGPOM, or holds something a map file cannot (see :func:`saved_classes`).
    NotFittedError
        `model` is not fitted.
    """
    from gpomap._version import __version__
    from gpomap.tiles import TiledGPOM

    if not isinstance(model, TiledGPOM):
        hint = (
            " (a StreamingGPOM: save its model_, or its whole state with save_streaming_state)"
            if hasattr(model, "model_")
            else ""
        )
        raise TypeError(f"save_fitted_map takes a fitted TiledGPOM or AreaGPOM, got {type(model).__name__}{hint}")
    model._check_fitted()
    summary = _summary(model)

    def header(state: Any) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "written_by": f"gpomap {__version__}",
            "kind": "map",
            "summary": summary,
            "state": state,
        }

    return _write(path, model, "map", header)


def save_streaming_state(mapper: Any, path: str | os.PathLike[str]) -> Path:
    """Write a :class:`~gpomap.streaming.StreamingGPOM`'s whole state to `path`, to resume it later.

    The file is a map file of kind ``"stream"``: :func:`load_streaming_state` gives the mapper
    back (scans absorbed, tiles waiting, statistics, the warm-up's scans if it is not over), and
    :func:`load_fitted_map` its map, once the warm-up is over.

    Parameters
    ----------
    mapper : StreamingGPOM
    path : path-like

    Returns
    -------
    Path
    """
    from gpomap._version import __version__
    from gpomap.streaming import StreamingGPOM

    if not isinstance(mapper, StreamingGPOM):
        raise TypeError(f"save_streaming_state takes a StreamingGPOM, got {type(mapper).__name__}")
    summary: dict[str, Any] = {"ready": mapper.model_ is not None, "n_scans_added": int(mapper.n_scans_)}
    if mapper.model_ is not None:
        summary.update(_summary(mapper.model_))
    else:
        summary["warmup"] = [len(mapper._buffer), mapper.warmup_scans]

    def header(state: Any) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "written_by": f"gpomap {__version__}",
            "kind": "stream",
            "summary": summary,
            "state": state,
        }

    return _write(path, mapper, "stream", header)


def _not_a_map(path: str, found: str) -> InputFormatError:
    return InputFormatError(f"not a gpomap map file: {found}; expected a {_WHAT}", path=path)


def read_map_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The header of a map file (format, version, kind, summary, state), read alone: cheap, whatever the map's size.

    Raises
    ------
    InputFormatError
        One line naming the file: not a file, not a zip archive, truncated or corrupt, not a
        gpomap map file (a written grid ``map.npz`` is named as such), another format version.
    """
    name = str(path)
    p = regular_file(path, _WHAT)
    try:
        with p.open("rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc}); expected a {_WHAT}", path=name) from None
    if not head.startswith(b"PK"):
        found = "a single NumPy array (.npy)" if head.startswith(b"\x93NUM") else f"a file starting with {head!r}"
        raise _not_a_map(name, found)
    try:
        with zipfile.ZipFile(p) as zf:
            names = zf.namelist()
            if f"{_HEADER}.npy" not in names:
                if "format.npy" in names:
                    with zf.open("format.npy") as m:
                        fmt = str(np.lib.format.read_array(m, allow_pickle=False))
                    grid = " (a written grid: gpomap.io.npz.load_map reads it)" if fmt == "gpomap-occupancy-map" else ""
                    raise _not_a_map(name, f"a file of format {fmt!r}{grid}")
                raise _not_a_map(name, "a zip archive without a 'header' array")
            info = zf.getinfo(f"{_HEADER}.npy")
            if info.file_size > MAX_NPZ_ARRAY_BYTES:
                raise _not_a_map(name, f"a header of {info.file_size:,} bytes")
            with zf.open(info) as m:
                header_array = np.lib.format.read_array(m, allow_pickle=False)
    except InputFormatError:
        raise
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        OSError,
        ValueError,
        KeyError,
        NotImplementedError,
        RuntimeError,
    ) as exc:
        raise InputFormatError(
            f"truncated or corrupt ({type(exc).__name__}: {str(exc)[:120]}); expected a {_WHAT}", path=name
        ) from None
    if header_array.shape != () or header_array.dtype.kind != "U":
        raise _not_a_map(name, f"a 'header' array of {header_array.dtype} with shape {header_array.shape}, not one JSON string")
    try:
        header = json.loads(str(header_array))
    except (ValueError, RecursionError):
        raise _not_a_map(name, "a 'header' that is not JSON") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        kind = header.get("format") if isinstance(header, dict) else None
        raise _not_a_map(name, f"a header of format {kind!r}, not {FORMAT!r}")
    version = header.get("version")
    if version != VERSION:
        raise InputFormatError(
            f"map file format version {version!r} (written by {header.get('written_by', 'an unknown gpomap')}); "
            f"this gpomap reads version {VERSION}: refit the map from its log, or use the gpomap that wrote it",
            path=name,
        )
    if header.get("kind") not in ("map", "stream") or not isinstance(header.get("summary"), dict):
        raise _not_a_map(name, f"a header of unknown kind {header.get('kind')!r}")
    return header


def _load_state(path: str | os.PathLike[str], header: dict[str, Any]) -> Any:
    arrays = load_npz(path, _WHAT)
    arrays.pop(_HEADER, None)
    try:
        return _Reader(arrays).decode(header["state"])
    except _StateError as exc:
        raise InputFormatError(f"map file state: {exc}", path=str(path)) from None
    except (GpomapError, KeyError, TypeError, ValueError, AttributeError, IndexError, ArithmeticError, RecursionError) as exc:
        raise InputFormatError(
            f"map file state is not what gpomap writes ({type(exc).__name__}: {str(exc)[:160]}): an altered file", path=str(path)
        ) from None


def load_fitted_map(path: str | os.PathLike[str]) -> Any:
    """Read the fitted map of a map file (``gpomap.load_map``).

    Parameters
    ----------
    path : path-like
        A file written by :func:`save_fitted_map` (``gpomap map``'s ``map.gpom``), or by
        :func:`save_streaming_state` once its warm-up was over (its map, as it stood).

    Returns
    -------
    TiledGPOM
        The model that was saved (an :class:`~gpomap.mapping.AreaGPOM` from ``gpomap map``):
        ``predict_proba(points, return_var=False)``, ``predict``, ``grid(resolution, extent=None)``
        (an :class:`~gpomap.grid.OccupancyMap`, or a :class:`~gpomap.voxels.VoxelMap` in 3-D),
        ``summary()``, and ``update(scans)`` to add scans. Its tiles run in this process or on
        local workers, as its ``n_workers`` says.

    Raises
    ------
    InputFormatError
        One line naming the file and what was expected (see :func:`read_map_header`), or a
        streaming state still in its warm-up (no map yet).
    """
    header = read_map_header(path)
    obj = _load_state(path, header)
    if header["kind"] == "stream":
        if obj.model_ is None:
            warm = header["summary"].get("warmup", ["?", "?"])
            raise InputFormatError(
                f"a streaming state still warming up ({warm[0]} of {warm[1]} scans): it holds no map yet", path=str(path)
            )
        return obj.model_
    return obj


def load_streaming_state(path: str | os.PathLike[str]) -> Any:
    """Read a :class:`~gpomap.streaming.StreamingGPOM` written by :func:`save_streaming_state`, to add scans to it.

    Raises
    ------
    InputFormatError
        As :func:`read_map_header`, or a map file of kind ``"map"`` (not a streaming state).
    """
    header = read_map_header(path)
    if header["kind"] != "stream":
        raise InputFormatError(
            "holds a fitted map, not a streaming state (written by gpomap stream --save-state or save_streaming_state)",
            path=str(path),
        )
    return _load_state(path, header)
