"""Exact ray traversal of grid cells (Amanatides & Woo), shared by the grids and the ray evidence."""

from __future__ import annotations

from gpomap.baselines.ogm import traverse

__all__ = ["traverse"]
