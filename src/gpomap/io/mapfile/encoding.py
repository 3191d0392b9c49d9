"""A fitted map's state as JSON and arrays, and back: the encoding of :mod:`gpomap.io.mapfile`.

:class:`_Writer` encodes the model's attributes (numbers, strings, arrays, tagged tuples, sets and
dicts, dataclasses, the objects of :func:`saved_classes`) and hands each array to the archive;
:class:`_Reader` makes them again, checking each class and each dataclass's fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
import weakref
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.resources import POINT_MEMORY

#: The archive member that holds the JSON header (no array of the state takes this name).
_HEADER = "header"

#: Attributes that are caches or belong to the running process, not to the map: not saved, and set
#: to these values on loading (by class name). A map loaded runs its tiles locally (``scheduler``).
NOT_SAVED: dict[str, dict[str, Any]] = {
    "gpomap.tiles.TiledGPOM": {"_client": None, "scheduler": None, "_kept_bounds": None},
    # A layer counted only at given points (a map asked at a few points while fitting) is never saved.
    "gpomap.fusion.EvidenceLayer": {
        "_at_surface": None,
        "_joined": None,
        "_grid_cache": None,
        "_asked_at": None,
        "_cells": None,
        "_counted_in_place": None,
    },
    "gpomap.gp.GPPosterior": {"precision": None},
    # Block points made again from the scans are filed with their runs again (_restore_points),
    # when first read (_PointsFromScans).
    "gpomap.tiles._BlockPoints": {"_runs": None, "_restore": None, "_restore_count": None},
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
        from gpomap.tiles.points import _SpilledPart

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
                    # Only their number is written: counted by part, never read back from the spill file
                    # (nor made from the scans, for a block of a map read from its file and not yet read).
                    n = value._restore_count if value._restore is not None else None
                    if n is None:
                        n = sum(p.shape[0] if isinstance(p, _SpilledPart) else len(p[0]) for p in v)
                    state[attr] = {"$from_scans": int(n)}
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
    def __init__(self, arrays: dict[str, NDArray[Any]], path: str = "") -> None:
        self.arrays = arrays
        self.path = path  # the file's, named by the errors of points made again later
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
                _PointsFromScans.wait(obj, [(bp, n) for m, bp, n in self._points if m is obj], self.path)
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


class _PointsFromScans:
    """Makes a map's labelled points again from its scans and files them under its blocks
    (:func:`_restore_points`), once, when one of its blocks is first read or added to.

    A map read to be rendered or queried never reads its points: on a log of a few thousand scans
    they are tens of millions, most of the time and memory a load took.
    """

    def __init__(self, model: Any, path: str) -> None:
        # Weakly: the model holds its blocks, which hold this; a map let go must go at once, not at
        # the next garbage collection (a written map's grid is put together after its model goes).
        self.model, self.path = weakref.ref(model), path

    @classmethod
    def wait(cls, model: Any, blocks: list[tuple[Any, int]], path: str) -> None:
        """Leave `blocks` (each with its saved count of points) to be filled when first read."""
        if not blocks:
            return
        restore = cls(model, path)
        for block, n in blocks:
            block._restore, block._restore_count = restore, n

    def __call__(self) -> None:
        from gpomap.errors import InputFormatError

        model = self.model()
        if model is None:
            raise RuntimeError("the map these block points belong to is gone")
        blocks = [(b, int(b._restore_count)) for b in model._block_points.values() if b._restore is self]
        for block, _ in blocks:
            block._restore = block._restore_count = None  # filled below, once
        try:
            _restore_points(model, blocks)
        except _StateError as exc:
            raise InputFormatError(f"map file state: {exc}", path=self.path) from None


def _restore_points(model: Any, blocks: list[tuple[Any, int]]) -> None:
    """The labelled points of a map fitted on scans, recomputed from them and filed as the fit filed them."""
    if not blocks:
        return
    from gpomap.observations import observation_parts
    from gpomap.tiles.blocks import PointFiling
    from gpomap.tiles.points import _HeldParts

    b = model.base

    def filed() -> tuple[int, int, set[int], int, int]:
        return (
            model._n_points,
            model._n_occupied_points,
            set(model._tiles_with_points),
            len(model._block_points),
            model._n_free_samples,
        )

    saved = filed()
    lower, upper = model._lower, model._upper
    model._n_points = model._n_occupied_points = model._n_free_samples = 0
    # Made a part at a time and filed as the fit files them, past POINT_MEMORY in a spill file: a
    # log of thousands of scans gives tens of millions of points.
    held = _HeldParts(POINT_MEMORY)
    filing = PointFiling(model, held, settled=True)
    for part in observation_parts(model._scans, b.free_step, b.hit_margin, b.no_return_cap, free_cube=b.free_cube(model._dim)):
        filing(part)
    held.close()
    model._lower, model._upper = lower, upper
    now = filed()
    if now != saved or any(bp.arrays()[0].shape[0] != n for bp, n in blocks):
        raise _StateError(
            f"the scans saved give {now[0]} labelled points in {now[3]} blocks; the map was fitted on {saved[0]} in {saved[3]}"
        )
