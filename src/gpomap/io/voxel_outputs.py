"""Outputs of a 3-D map (:class:`~gpomap.voxels.VoxelMap`): NPZ voxel grid, OctoMap, PLY mesh, PNG figures.

NPZ (:func:`save_voxels` / :func:`load_voxels`; no pickles):

=================  ======================  ==================================================
key                shape / dtype           meaning
=================  ======================  ==================================================
``format``         () str                  ``"gpomap-voxel-map"``
``version``        () int64                layout version, currently 1
``probability``    (nz, ny, nx) float64    occupancy probability, ``[z, y, x]`` order
``origin``         (3,) float64            lower corner (x, y, z) of voxel [0, 0, 0], metres
``resolution``     () float64              voxel side, metres
``thresholds``     (2,) float64            free-below, occupied-above
``ternary``        (nz, ny, nx) int8       FREE 0 / OCCUPIED 1 / UNKNOWN -1 (recomputed on load)
``variance``       (nz, ny, nx) float64    optional: latent variance
``info``           () str                  optional: the map's ``info`` as JSON
=================  ======================  ==================================================

The mesh (:func:`write_mesh`) is the p = 0.5 iso-surface of the probability by marching cubes
(scikit-image), vertices in map coordinates (voxel centres are the sample points), written as a
binary PLY through plyfile. The figures, drawn by :mod:`gpomap.plot`: :func:`~gpomap.plot.plot_slices`
(horizontal slices at chosen heights, one panel each, metres on the axes, probability on a colour
bar) and :func:`~gpomap.plot.plot_3d` (the occupied voxels' centres coloured by height).
:func:`write_voxel_outputs` writes them all as one output set (:func:`gpomap.io.atomic.output_set`).
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import InputFormatError
from gpomap.extras import require
from gpomap.io.atomic import atomic_write, file_written, output_set
from gpomap.io.checks import load_npz, regular_file
from gpomap.io.members import write_npz
from gpomap.voxels import VoxelMap, VoxelSpec

__all__ = ["save_voxels", "load_voxels", "write_mesh", "write_voxel_outputs", "FORMAT"]

FORMAT = "gpomap-voxel-map"
VERSION = 1


def save_voxels(voxel_map: VoxelMap, path: str | os.PathLike[str]) -> Path:
    """Write `voxel_map` to `path` as an ``.npz`` (its arrays deflated where that pays), atomically
    (no suffix is appended)."""
    m = voxel_map
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, dtype=np.int64),
        "probability": m.probability,
        "origin": np.asarray(m.spec.origin, dtype=np.float64),
        "resolution": np.array(m.spec.resolution),
        "thresholds": np.asarray(m.thresholds, dtype=np.float64),
        "ternary": m.ternary,
        **({} if m.observed is None else {"observed": m.observed}),
        "info": np.array(json.dumps(m.info, default=str)),
    }
    if m.variance is not None:
        arrays["variance"] = m.variance
    target = Path(path)
    write_npz(target, arrays)
    return target


def load_voxels(path: str | os.PathLike[str]) -> VoxelMap:
    """Read a map written by :func:`save_voxels`.

    Raises
    ------
    InputFormatError
        Not an ``.npz`` (or not a gpomap voxel map), a required array missing, shapes that
        disagree (origin not (3,), probability not 3-D, variance not its shape), a newer version.
    """
    name = str(path)
    data = load_npz(regular_file(path, "gpomap voxel map (.npz)"), "NumPy .npz voxel map")
    if "format" in data and str(data["format"]) != FORMAT:
        raise InputFormatError(f"not a gpomap voxel map: format is {str(data['format'])!r}", path=name)
    missing = [k for k in ("probability", "origin", "resolution", "thresholds") if k not in data]
    if missing:
        raise InputFormatError(f"voxel map is missing the required array(s) {', '.join(map(repr, missing))}", path=name)
    if "version" in data and int(data["version"]) > VERSION:
        raise InputFormatError(f"voxel map version {int(data['version'])} is newer than this gpomap reads ({VERSION})", path=name)
    p = np.asarray(data["probability"], dtype=float)
    if p.ndim != 3:
        raise InputFormatError(f"array 'probability' must have shape (nz, ny, nx), got {p.shape}", path=name)
    if data["origin"].shape != (3,):
        raise InputFormatError(f"array 'origin' must have shape (3,), got {data['origin'].shape}", path=name)
    try:
        info = json.loads(str(data["info"])) if "info" in data else {}
        o = data["origin"].astype(float)
        spec = VoxelSpec((o[0], o[1], o[2]), float(data["resolution"]), (p.shape[0], p.shape[1], p.shape[2]))
        variance = np.asarray(data["variance"], dtype=float) if "variance" in data else None
        lo, hi = (float(t) for t in data["thresholds"])
        observed = np.asarray(data["observed"], dtype=bool) if "observed" in data else None
        return VoxelMap(
            spec, p, variance=variance, thresholds=(lo, hi), info=info if isinstance(info, dict) else {}, observed=observed
        )
    except (ValueError, TypeError) as exc:
        raise InputFormatError(str(exc), path=name) from None


def write_mesh(voxel_map: VoxelMap, path: str | os.PathLike[str], level: float = 0.5) -> tuple[Path, int, int]:
    """The ``p = level`` iso-surface through the observed voxels (:attr:`VoxelMap.observed`) as a
    binary PLY mesh, atomically.

    Parameters
    ----------
    voxel_map : VoxelMap
    path : path-like
    level : float
        Probability of the surface (0.5: occupied inside, free outside).

    Returns
    -------
    path : Path
    n_vertices, n_faces : int
        Zero and zero when no voxel crosses `level` (an empty mesh is still written).
    """
    plyfile = require("plyfile", "writing map.ply")
    PlyData, PlyElement = plyfile.PlyData, plyfile.PlyElement
    marching_cubes = require("skimage.measure", "writing map.ply").marching_cubes

    p = voxel_map.probability
    r = voxel_map.spec.resolution
    # Padded with "free" so surfaces close at the grid's border instead of being left open.
    padded = np.pad(p, 1, constant_values=min(0.0, level - 1e-3))
    # Only where rays went: no surface across unseen space (the GP's guess there wraps it whole).
    seen = np.pad(voxel_map.seen, 1, constant_values=True)
    if padded[seen].min() < level < padded[seen].max():
        verts, faces, _, _ = marching_cubes(padded, level=level, spacing=(r, r, r), mask=seen)
        # (z, y, x) sample coordinates of the padded grid to map (x, y, z): the first sample is a centre.
        xyz = verts[:, ::-1] + voxel_map.spec.lower + r / 2 - r
    else:
        xyz, faces = np.empty((0, 3)), np.empty((0, 3), dtype=np.int32)
    vertex = np.array([tuple(v) for v in xyz], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    face = np.array([(list(f),) for f in faces], dtype=[("vertex_indices", "i4", (3,))])
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")]).write(buf)
    target = Path(path)
    with atomic_write(target, "wb") as f:
        f.write(buf.getvalue())
    return target, len(xyz), len(faces)


def write_voxel_outputs(
    voxel_map: VoxelMap,
    outdir: str | os.PathLike[str],
    stem: str = "map",
    heights: Sequence[float] | None = None,
    title: str | None = None,
    save_model: Callable[[Path], Path] | None = None,
) -> list[Path]:
    """Write ``STEM.npz``, ``STEM.bt``, ``STEM.ply`` (mesh), ``STEM-slices.png`` and ``STEM-3d.png`` as one set,
    with ``STEM.gpom`` written by `save_model` when it is given (the fitted map:
    ``functools.partial(gpomap.io.mapfile.save_fitted_map, model)``; a writer of grids knows no model).

    Returns
    -------
    list of Path
        The files written, in `outdir`.
    """
    from gpomap.io.octomap import write_octree
    from gpomap.plot import plot_3d, plot_slices, save_figure  # matplotlib only when the figures are drawn

    with output_set(outdir) as outputs:
        out = outputs.path
        staged = [save_voxels(voxel_map, out / f"{stem}.npz")]
        file_written()
        staged.append(write_octree(voxel_map, out / f"{stem}.bt"))
        file_written()
        staged.append(write_mesh(voxel_map, out / f"{stem}.ply")[0])
        file_written()
        staged.append(Path(save_figure(plot_slices(voxel_map, heights, title), out / f"{stem}-slices.png")))
        file_written()
        staged.append(Path(save_figure(plot_3d(voxel_map, title), out / f"{stem}-3d.png")))
        file_written()
        if save_model is not None:
            staged.append(save_model(out / f"{stem}.gpom"))
            file_written()
    return [outputs.final(p) for p in staged]
