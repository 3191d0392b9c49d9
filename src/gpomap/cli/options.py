"""What every option of the commands stands on: numeric argument types, and defaults stated once.

An option's default is a :class:`Default` naming a config field (:mod:`gpomap.config`) or a
library value; :func:`resolve_library_defaults` puts the values in place after parsing and records
which options were left out, so a command can tell a default from the same value given. The
option groups the commands share are in :mod:`~gpomap.cli.input_options` (what is read),
:mod:`~gpomap.cli.model_options` (the model and its tiles) and :mod:`~gpomap.cli.output_options`
(the written map); an option of one command alone is declared in that command's module.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any

__all__ = [
    "number",
    "positive",
    "non_negative",
    "Default",
    "signature_default",
    "module_default",
    "resolve_library_defaults",
    "given",
    "flag",
]


# --------------------------------------------------------------------------- argument types
def number(kind: type, low: float | None = None, strict: bool = True) -> Callable[[str], Any]:
    """An argparse type: a finite `kind` (int or float), above `low` (or at least `low` if not `strict`).

    nan and inf are refused: ``float("nan") <= 0`` is false, so a plain sign test lets nan through.
    """
    if low is None:
        expected = "a finite number"
    elif low == 0:
        expected = "a positive number" if strict else "a number >= 0"
    else:
        expected = f"a number {'>' if strict else '>='} {low:g}"
    if kind is int:
        expected = expected.replace("number", "integer")

    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not math.isfinite(v) or (low is not None and (v <= low if strict else v < low)):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v

    return parse


def positive(kind: type) -> Callable[[str], Any]:
    """An argparse type: a finite number > 0."""
    return number(kind, 0.0)


def non_negative(kind: type) -> Callable[[str], Any]:
    """An argparse type: a finite number >= 0."""
    return number(kind, 0.0, strict=False)


# --------------------------------------------------------------------------- defaults
class Default:
    """An option's default, stated in one place: a config field (:mod:`gpomap.config`) or a library module.

    argparse keeps a default that is not a string as it is, so an option still holding a
    ``Default`` after parsing was not given: :func:`resolve_library_defaults` replaces it by its
    value and names it in ``args.library_defaults`` (a 3-D map replaces some of them,
    :func:`gpomap.cli.map3d.apply_3d_defaults`). A default found in a module that imports SciPy
    is looked up only when shown or used (`lookup`), so that ``gpomap --help`` stays fast.

    Parameters
    ----------
    value : object, optional
        The default itself.
    lookup : callable, optional
        Returns the default (instead of `value`).
    show : callable, optional
        Formats the value for ``--help`` (default: ``str``).
    """

    def __init__(self, value: Any = None, lookup: Callable[[], Any] | None = None, show: Callable[[Any], str] = str) -> None:
        self._value, self._lookup, self._show = value, lookup, show

    @property
    def value(self) -> Any:
        """The default's value (looked up now, if it is looked up)."""
        return self._lookup() if self._lookup is not None else self._value

    def __str__(self) -> str:
        return self._show(self.value)


def signature_default(module: str, name: str, parameter: str) -> Default:
    """The default of `parameter` of the function or class `name` in `module`, looked up when needed."""

    def lookup() -> Any:
        return inspect.signature(getattr(importlib.import_module(module), name)).parameters[parameter].default

    return Default(lookup=lookup)


def module_default(module: str, name: str, convert: Callable[[Any], Any] | None = None) -> Default:
    """The constant `name` of `module` (through `convert`, if given), looked up when needed."""

    def lookup() -> Any:
        value = getattr(importlib.import_module(module), name)
        return value if convert is None else convert(value)

    return Default(lookup=lookup)


def resolve_library_defaults(args: argparse.Namespace) -> None:
    """Replace each :class:`Default` by its value; ``args.library_defaults`` names the options left at one."""
    defaulted = {name for name, value in vars(args).items() if isinstance(value, Default)}
    for name in defaulted:
        setattr(args, name, getattr(args, name).value)
    args.library_defaults = frozenset(defaulted)


def given(args: argparse.Namespace, dests: Sequence[str]) -> list[str]:
    """Which of `dests` the command line set (a default is a :class:`Default` or None)."""
    return [d for d in dests if d not in args.library_defaults and getattr(args, d) is not None]


def flag(dest: str) -> str:
    """The command-line spelling of the option stored as `dest`."""
    return {
        "ray_evidence": "--no-ray-evidence",
        "fit_revisit": "--no-revisit",
        "scan_range": "--range",
        "test_points": "--test-points",
    }.get(dest, "--" + dest.replace("_", "-"))
