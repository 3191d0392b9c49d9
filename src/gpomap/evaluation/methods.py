"""The methods a map can be made with, by name: the one registry of them.

Evaluation (:func:`gpomap.evaluation.maps.make_model`), the comparison with the grids
(:mod:`gpomap.comparison`), the paper's benchmark (:mod:`gpomap.benchmark`) and the commands'
``--method`` read their names, labels and models from :data:`REGISTRY`. Each entry builds a
:class:`~gpomap.protocol.Mapper`; its estimator class is imported only when a model is built
(or its class asked for), so reading the names costs no import of the engine. A new method is
one entry here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from gpomap.protocol import Mapper


@dataclass(frozen=True)
class Method:
    """One way to make a map, as evaluation builds it.

    Attributes
    ----------
    name : str
        The name commands and results use (``--method``, ``result["method"]``).
    label : str
        How tables and figures name it.
    description : str
        One line for help texts.
    estimator : callable
        Returns the estimator class (imported when called): its constructor takes the options
        (``inspect.signature(m.estimator())`` lists them).
    own_grid : bool
        An occupancy grid: built with a cell side (the evaluation's ``resolution``), no kernel
        and no seed; the map it writes is its own cells. Otherwise a GP method: a kernel and a
        seed, and a written map at any resolution.
    fixed : mapping of str to object
        Constructor arguments the name itself fixes (the grids' sensor model).
    tiles : bool
        Fits in tiles on worker processes: takes ``n_workers``.
    """

    name: str
    label: str
    description: str
    estimator: Callable[[], Callable[..., Mapper]]
    own_grid: bool = False
    fixed: Mapping[str, Any] = field(default_factory=dict)
    tiles: bool = False

    def build(
        self, kernel: str | None = None, seed: int = 0, resolution: float = 0.1, n_workers: int | None = None, **options: Any
    ) -> Mapper:
        """The unfitted model, `options` passed to its constructor.

        Parameters
        ----------
        kernel : {"se", "matern32"}, optional
            Point kernel of a GP method (default: the method's own); a grid takes none.
        seed : int
            Seeds a GP method; a grid takes none.
        resolution : float
            A grid's cell side, metres; a GP method predicts anywhere.
        n_workers : int, optional
            Workers of a method fitted in tiles (default: the CPU count, as ``gpomap map``).
        **options
            Constructor arguments.

        Returns
        -------
        Mapper
        """
        cls = self.estimator()
        if self.own_grid:
            return cls(resolution=resolution, **self.fixed, **options)
        gp_options = dict(options, seed=seed, **({"kernel": kernel} if kernel is not None else {}))
        if self.tiles:
            return cls(n_workers=n_workers, **self.fixed, **gp_options)
        return cls(**self.fixed, **gp_options)


def _area_gpom() -> Callable[..., Mapper]:
    from gpomap.mapping import AreaGPOM

    return AreaGPOM


def _gpomik() -> Callable[..., Mapper]:
    from gpomap.baselines.gpomik import GPOMIK

    return GPOMIK


def _gpom() -> Callable[..., Mapper]:
    from gpomap.baselines.gpom import GPOM

    return GPOM


def _occupancy_grid() -> Callable[..., Mapper]:
    from gpomap.baselines.ogm import OccupancyGridMapper

    return OccupancyGridMapper


_METHODS = (
    Method(
        "msk",
        "MSK-GPOM",
        "gpomap: local GPs over cells in tiles, sharpened by each cell's ray counts (the map gpomap map writes)",
        _area_gpom,
        tiles=True,
    ),
    Method("gpomik", "GPOMIK", "the paper's baseline: one dense GP over beams with the integral kernel", _gpomik),
    Method("gpom", "GPOM", "the paper's baseline: one dense GP over hit and free points", _gpom),
    Method(
        "ogm",
        "OGM",
        "the log-odds occupancy grid, OctoMap's sensor model (the same as ogm-logodds)",
        _occupancy_grid,
        own_grid=True,
        fixed={"sensor_model": "logodds"},
    ),
    Method(
        "ogm-logodds",
        "OGM log-odds",
        "the log-odds occupancy grid, OctoMap's sensor model",
        _occupancy_grid,
        own_grid=True,
        fixed={"sensor_model": "logodds"},
    ),
    Method(
        "ogm-counting",
        "OGM counting",
        "the counting grid: (hits + 1) / (hits + misses + 2) per cell",
        _occupancy_grid,
        own_grid=True,
        fixed={"sensor_model": "counting"},
    ),
)
#: Every method by name, in the order commands list them.
REGISTRY: dict[str, Method] = {m.name: m for m in _METHODS}
#: The names (``gpomap evaluate --method`` takes one of these).
METHODS: tuple[str, ...] = tuple(REGISTRY)
#: The occupancy grids among them.
GRID_METHODS: tuple[str, ...] = tuple(name for name, m in REGISTRY.items() if m.own_grid)
#: The GP methods among them.
GP_METHODS: tuple[str, ...] = tuple(name for name, m in REGISTRY.items() if not m.own_grid)


def method_named(name: str) -> Method:
    """The registered method `name`.

    Raises
    ------
    ValueError
        No method of that name.
    """
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; expected one of {METHODS}") from None
