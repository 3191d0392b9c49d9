"""Errors raised by gpomap.

Every error derives from :class:`GpomapError`, so callers (and the command line) can catch one type.
Messages say what was wrong, where (file, line, field), and what was expected.
"""

from __future__ import annotations


class GpomapError(Exception):
    """Base class of every error gpomap raises on purpose."""


class InputFormatError(GpomapError, ValueError):
    """An input file or array does not have the expected format.

    Parameters
    ----------
    message : str
        What was wrong and what was expected.
    path : str, optional
        The file that was being read.
    line : int, optional
        1-based line number in that file, where it applies.
    """

    def __init__(self, message: str, path: str | None = None, line: int | None = None) -> None:
        self.path = path
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}"
            if line is not None:
                where += f", line {line}"
            where += ": "
        super().__init__(where + message)


class NotFittedError(GpomapError, AttributeError):
    """An estimator was used before `fit`."""


class NumericalError(GpomapError, ArithmeticError):
    """A linear-algebra step failed (for example, a covariance matrix not positive definite)."""


class EmptyDataError(GpomapError, ValueError):
    """There is nothing to learn from: no valid observations, or only one class."""


class DistributedError(GpomapError, RuntimeError):
    """A Dask distributed scheduler could not be reached, or had no workers left to run the tiles."""


class MissingExtraError(GpomapError, ImportError):
    """An optional dependency is not installed; the message names the extra that brings it."""
