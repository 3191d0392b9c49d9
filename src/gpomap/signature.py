"""An estimator's ``__init__`` derived from its config: the parameters are the fields of a frozen
dataclass of :mod:`gpomap.config`, so their names, order, types and defaults are written once.

:class:`~gpomap.tiles.TiledGPOM` takes :class:`~gpomap.config.TiledConfig`'s fields and
:class:`~gpomap.mapping.AreaGPOM` :class:`~gpomap.config.EstimatorConfig`'s, each through
:func:`init_from`.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Concatenate, ParamSpec, TypeVar

__all__ = ["init_from"]

_P = ParamSpec("_P")
_S = TypeVar("_S")
_C = TypeVar("_C")


def init_from(config: Callable[_P, _C]) -> Callable[[Callable[[_S, _C], None]], Callable[Concatenate[_S, _P], None]]:
    """An ``__init__`` whose parameters are the fields of `config`, a frozen dataclass: the decorated
    function is handed the arguments bound into one config, defaults applied.

    A type checker reads the parameters from the dataclass's own ``__init__`` (the ParamSpec), and
    ``inspect``, ``help`` and scikit-learn from ``__signature__``; so the names, types and defaults
    are written once, as the config's fields. (A dataclass estimator inheriting the fields cannot
    be: the config is frozen, the estimator is not.)

    Parameters
    ----------
    config : type
        The frozen dataclass whose fields are the parameters.

    Returns
    -------
    callable
        A decorator of ``configure(self, params)``, `params` a `config`, making it the ``__init__``
        that takes the fields as arguments (positional in the fields' order, or by name).
    """
    fields = inspect.signature(config, eval_str=True)
    self = inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY)
    signature = fields.replace(parameters=[self, *fields.parameters.values()], return_annotation=None)

    def decorate(configure: Callable[[_S, _C], None]) -> Callable[Concatenate[_S, _P], None]:
        def __init__(self: _S, /, *args: _P.args, **kwargs: _P.kwargs) -> None:
            try:
                bound = fields.bind(*args, **kwargs)
            except TypeError as exc:  # named as Python names a plain __init__'s wrong arguments
                raise TypeError(f"{configure.__qualname__}() {exc}") from None
            configure(self, config(*bound.args, **bound.kwargs))

        for name in ("__module__", "__name__", "__qualname__", "__doc__"):
            setattr(__init__, name, getattr(configure, name))
        __init__.__signature__ = signature  # type: ignore[attr-defined]
        return __init__

    return decorate
