"""Write one occupancy map in every format gpomap offers: ROS map_server, NPZ and a PNG figure."""

from __future__ import annotations

import os
from pathlib import Path

from gpomap.grid import OccupancyMap
from gpomap.io.npz import save_map
from gpomap.io.rosmap import write_rosmap
from gpomap.plot import plot_map, save_figure


def write_map_outputs(
    occupancy_map: OccupancyMap,
    outdir: str | os.PathLike[str],
    stem: str = "map",
    pgm_mode: str = "trinary",
    title: str | None = None,
) -> list[Path]:
    """Write ``STEM.yaml`` + ``STEM.pgm`` (map_server), ``STEM.npz`` and ``STEM.png`` into `outdir`.

    Each file is written atomically (a temporary file renamed into place), so an interrupted run
    leaves the previous outputs whole.

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
        The files written.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    yaml_path, pgm_path = write_rosmap(occupancy_map, out / f"{stem}.yaml", mode=pgm_mode)
    npz_path = save_map(occupancy_map, out / f"{stem}.npz")
    fig = plot_map(occupancy_map, title=title)
    png_path = save_figure(fig, out / f"{stem}.png")
    return [Path(yaml_path), Path(pgm_path), Path(npz_path), Path(png_path)]
