"""3-D scenes of boxes, a depth camera ray-cast inside them, and the truth to score a map against.

The 3-D counterpart of :mod:`gpomap.simulate`, in four parts:

- :mod:`gpomap.simulate3d.scene`: a :class:`Scene` is a set of solid axis-aligned boxes (walls,
  floors, table tops and legs, shelf boards); its occupied space is the union of the boxes, and
  rays are cast against it exactly (the slab method).
- :mod:`gpomap.simulate3d.depth`: :func:`render_depth` renders one depth frame of a pinhole camera
  (:class:`PinholeCamera`, OpenCV axes: x right, y down, z forward) by that ray casting, optionally
  with a depth camera's noise (:class:`DepthNoise`); :func:`write_depth_frames` writes frames in
  the layout ``gpomap map`` reads (``camera-intrinsics.txt``, ``NAME.depth.png`` in millimetres,
  ``NAME.pose.txt`` camera-to-world), so simulated data goes through exactly the reader and the map
  a user's frames go through.
- :mod:`gpomap.simulate3d.truth`: the lattice points some ray came near, labelled occupied (inside
  a box) and boundary (near one) (:func:`truth_points`), as the 2-D rule of :mod:`gpomap.truth`.
- :mod:`gpomap.simulate3d.worlds`: :func:`office_scene` and :func:`office_poses` build three rooms
  on a corridor of doorways, with tables, shelves, a cabinet, a sofa and a pillar, and ten camera
  poses inside them; :func:`storeroom_scene` and :func:`storeroom_poses` a store room.

Every name is importable from here.
"""

from __future__ import annotations

from gpomap.simulate3d.depth import (
    DepthFrames,
    DepthNoise,
    PinholeCamera,
    frame_clouds,
    look_at,
    render_depth,
    render_frames,
    write_depth_frames,
)
from gpomap.simulate3d.scene import BOUNDARY_RADIUS, Scene
from gpomap.simulate3d.truth import OBSERVED_RADIUS, TRUTH_LATTICE, TruthVolume, observed_cells, truth_points
from gpomap.simulate3d.worlds import SCENE_OFFSET, office_poses, office_scene, storeroom_poses, storeroom_scene

__all__ = [
    "Scene",
    "PinholeCamera",
    "DepthNoise",
    "DepthFrames",
    "TruthVolume",
    "look_at",
    "render_depth",
    "render_frames",
    "write_depth_frames",
    "frame_clouds",
    "truth_points",
    "observed_cells",
    "office_scene",
    "office_poses",
    "storeroom_scene",
    "storeroom_poses",
    "TRUTH_LATTICE",
    "OBSERVED_RADIUS",
    "BOUNDARY_RADIUS",
    "SCENE_OFFSET",
]
