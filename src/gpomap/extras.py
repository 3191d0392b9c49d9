"""Optional dependencies: imported where they are needed, and a one-line error naming the extra when missing.

gpomap's core reads CARMEN logs, bags, labelled points, map_server maps and depth frames; point
clouds, OctoMap trees, PLY meshes and Dask clusters need the packages of an extra
(``pyproject.toml``'s ``[project.optional-dependencies]``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from gpomap.errors import MissingExtraError

#: Each optional module: the extra that installs it.
EXTRA_OF: dict[str, str] = {
    "pypcd4": "3d",
    "pyoctomap": "3d",
    "plyfile": "3d",
    "skimage": "3d",
    "skimage.measure": "3d",
    "distributed": "distributed",
}


def require(module: str, purpose: str) -> ModuleType:
    """Import `module`, or raise :class:`~gpomap.errors.MissingExtraError` naming its extra.

    Parameters
    ----------
    module : str
        A key of :data:`EXTRA_OF`.
    purpose : str
        What needs it, as the message starts ("reading PCD files").

    Returns
    -------
    module
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        extra = EXTRA_OF[module]
        raise MissingExtraError(
            f'{purpose} needs {module.split(".")[0]}, from gpomap\'s [{extra}] extra: pip install "gpomap[{extra}]"'
        ) from None
