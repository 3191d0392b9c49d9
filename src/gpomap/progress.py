"""Progress of long stages: a bar with an estimate on a terminal, plain lines otherwise, or nothing.

Every stage that can take more than a few seconds (tiled fit, grid prediction, reading a large
log) reports through :func:`progress`, so a user can tell a slow run from a hung one. The mode is
set once per process by the command line (``--quiet``) or by the API user:

- ``"auto"`` (default): a tqdm bar when stderr is a terminal, else one line per ~10 % step of a
  stage that has run for :data:`LINES_AFTER_SECONDS` (a log holds no lines for the many stages
  that take a fraction of a second);
- ``"lines"``: always line-based (logs, CI), after the same delay;
- ``"quiet"``: nothing.

tqdm is imported only when a bar is shown, so ``gpomap --help`` stays light.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

__all__ = ["Progress", "progress", "set_progress_mode", "get_progress_mode"]

Mode = Literal["auto", "lines", "quiet"]
_MODES: tuple[Mode, ...] = ("auto", "lines", "quiet")
_mode: Mode = "auto"
_open = 0  # stages open: a stage within another reports nothing, the outer one speaks for both
#: In line mode a stage says nothing until it has run this long, seconds.
LINES_AFTER_SECONDS: float = 1.0


def set_progress_mode(mode: Mode) -> None:
    """Choose how progress is shown for the rest of the process (see the module docstring)."""
    global _mode
    if mode not in _MODES:
        raise ValueError(f"progress mode must be one of {_MODES}, got {mode!r}")
    _mode = mode


def get_progress_mode() -> Mode:
    """The current progress mode."""
    return _mode


class Progress:
    """A counter of finished work items with an estimate of the time left.

    Parameters
    ----------
    total : int
        Number of items the stage will finish.
    desc : str
        What the stage does, shown before the count ("fitting tiles").
    unit : str
        Name of one item ("tile", "row", "scan").
    """

    def __init__(self, total: int, desc: str, unit: str = "item") -> None:
        self.total = max(int(total), 0)
        self.desc = desc
        self.unit = unit
        self.n = 0
        self._t0 = time.perf_counter()
        self._next_tenth = 1  # the next line is due when this many tenths of the work are done
        self._bar = None
        self._mode: Mode = "quiet" if _open else _mode
        if self._mode == "auto" and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, leave=False, file=sys.stderr)
        elif self._mode == "auto":
            self._mode = "lines"

    def update(self, n: int = 1) -> None:
        """Mark `n` more items done."""
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        # Tenths in integers: n / total >= k / 10 exactly, without a float's drift.
        elif self._mode == "lines" and 0 < self.n < self.total and 10 * self.n >= self._next_tenth * self.total:
            elapsed = time.perf_counter() - self._t0
            if elapsed < LINES_AFTER_SECONDS:
                return  # the next update past the delay prints the line
            left = elapsed * (self.total - self.n) / self.n
            print(
                f"  {self.desc}: {self.n}/{self.total} {self.unit}s, {elapsed:.0f} s elapsed, ~{left:.0f} s left",
                file=sys.stderr,
                flush=True,
            )
            self._next_tenth = 10 * self.n // self.total + 1

    def close(self) -> None:
        """End the stage (removes the bar; line mode prints nothing more)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None


@contextmanager
def progress(total: int, desc: str, unit: str = "item") -> Iterator[Progress]:
    """Report progress of a stage of `total` items: ``with progress(n, "fitting tiles") as bar: bar.update()``.

    Stages opened within it report nothing: a map built in bands of rows says which band it is
    at, not how far each band's tiles are (18 bands of 20 lines each on a large map).
    """
    global _open
    bar = Progress(total, desc, unit)
    _open += 1
    try:
        yield bar
    finally:
        _open -= 1
        bar.close()
