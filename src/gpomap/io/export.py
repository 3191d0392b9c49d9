"""Write one occupancy map in every format gpomap offers: ROS map_server, NPZ and a PNG figure."""

from __future__ import annotations

import os
from pathlib import Path

from gpomap.grid import OccupancyMap
from gpomap.io.atomic import file_written, output_set
from gpomap.io.npz import save_map
from gpomap.io.rosmap import write_rosmap

__all__ = ["write_map_files", "write_map_outputs"]


def write_map_files(
    occupancy_map: OccupancyMap,
    directory: str | os.PathLike[str],
    stem: str = "map",
    pgm_mode: str = "trinary",
    title: str | None = None,
) -> list[Path]:
    """Write ``STEM.yaml`` + ``STEM.pgm``, ``STEM.npz`` and ``STEM.png`` into an existing `directory`.

    Each file on its own is written atomically; to replace them together use
    :func:`write_map_outputs` (or write into an :func:`gpomap.io.atomic.output_set`'s ``path``).

    Parameters
    ----------
    occupancy_map : OccupancyMap
    directory : path-like
        Must exist.
    stem : str
        Base name of the files.
    pgm_mode : {"trinary", "scale"}
        map_server mode: the ternary map, or the probability as a grey level.
    title : str, optional
        Title of the figure.

    Returns
    -------
    list of Path
        The files written.
    """
    # matplotlib is imported only when a figure is drawn (gpomap --help stays light).
    from gpomap.plot import plot_map, save_figure

    out = Path(directory)
    yaml_path, pgm_path = write_rosmap(occupancy_map, out / f"{stem}.yaml", mode=pgm_mode)
    file_written()
    npz_path = save_map(occupancy_map, out / f"{stem}.npz")
    file_written()
    fig = plot_map(occupancy_map, title=title)
    png_path = save_figure(fig, out / f"{stem}.png")
    file_written()
    return [Path(yaml_path), Path(pgm_path), Path(npz_path), Path(png_path)]


def write_map_outputs(
    occupancy_map: OccupancyMap,
    outdir: str | os.PathLike[str],
    stem: str = "map",
    pgm_mode: str = "trinary",
    title: str | None = None,
) -> list[Path]:
    """Write ``STEM.yaml`` + ``STEM.pgm`` (map_server), ``STEM.npz`` and ``STEM.png`` into `outdir`, as one set.

    The files are written into a staging directory and then replace the previous set together
    (:func:`gpomap.io.atomic.output_set`): an error or an interrupt leaves `outdir` exactly as it
    was, and a success leaves only this run's files among gpomap's (files of the previous run that
    this one does not write are removed; the user's own files are kept).

    Parameters
    ----------
    occupancy_map : OccupancyMap
    outdir : path-like
        Created if missing.
    stem : str
        Base name of the files.
    pgm_mode : {"trinary", "scale"}
        map_server mode: the ternary map, or the probability as a grey level.
    title : str, optional
        Title of the figure.

    Returns
    -------
    list of Path
        The files written, in `outdir`.
    """
    with output_set(outdir) as outputs:
        staged = write_map_files(occupancy_map, outputs.path, stem=stem, pgm_mode=pgm_mode, title=title)
    return [outputs.final(p) for p in staged]
