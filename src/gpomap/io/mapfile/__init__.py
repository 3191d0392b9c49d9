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

The package's rooms: :mod:`~gpomap.io.mapfile.encoding` turns the model's state into JSON and
arrays and back; :mod:`~gpomap.io.mapfile.files` writes and reads the archive, its header and
its version.
"""

from gpomap.io.mapfile.encoding import NOT_SAVED, saved_classes
from gpomap.io.mapfile.files import (
    FILENAME,
    FORMAT,
    VERSION,
    load_fitted_map,
    load_streaming_state,
    read_map_header,
    save_fitted_map,
    save_streaming_state,
)

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
