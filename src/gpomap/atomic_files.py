"""Files replaced atomically: a file is either the old one or the complete new one, never half-written.

Every writer in gpomap goes through :func:`atomic_write` (one file) or :func:`atomic_write_group`
(several files that belong together, such as a ROS ``map.yaml`` and its ``map.pgm``); a run's
whole set of outputs goes through :func:`gpomap.io.atomic.output_set`, built on them. They sit
below the readers and writers (:mod:`gpomap.io`) and the figures (:mod:`gpomap.plot`) alike, so
each can write a file without the other.

How: the new content goes to a temporary file in the *same directory* as the target (so the final
rename never crosses file systems), is flushed and fsynced, and only then renamed over the target
with :func:`os.replace`, which is atomic on POSIX and on Windows. If anything raises before the
rename, the temporary file is removed and the target is left untouched.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_write", "atomic_write_group"]

_MODES = {"w", "wt", "wb"}


def _open_temp(target: Path) -> tuple[int, Path]:
    """Create a new, empty temporary file beside `target`; return its descriptor and path."""
    for _ in range(100):
        tmp = target.with_name(f".{target.name}.{secrets.token_hex(6)}.tmp")
        try:
            # 0o666 filtered by the umask: the file ends up with the permissions a plain open() would
            # give it (mkstemp would make it 0o600, which surprises users of the output).
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        except FileExistsError:
            continue
        return fd, tmp
    raise FileExistsError(f"could not create a temporary file beside {target}")


def _fsync_dir(directory: Path) -> None:
    """Make a rename in `directory` durable (best effort: not every platform can open a directory)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove_quietly(path: Path) -> None:
    with suppress(FileNotFoundError):
        os.unlink(path)


class _Pending:
    """One temporary file waiting to be renamed over its target."""

    def __init__(self, target: str | os.PathLike[str], mode: str, encoding: str | None, newline: str | None) -> None:
        if mode not in _MODES:
            raise ValueError(f"atomic_write supports modes {sorted(_MODES)}, got {mode!r}")
        self.target = Path(target)
        if self.target.is_dir():
            raise IsADirectoryError(f"cannot write a file over the directory {self.target}")
        fd, self.tmp = _open_temp(self.target)
        try:
            if mode == "wb":
                self.file: IO[Any] = os.fdopen(fd, "wb")
            else:
                self.file = os.fdopen(fd, "w", encoding=encoding or "utf-8", newline=newline)
        except BaseException:
            os.close(fd)
            _remove_quietly(self.tmp)
            raise

    def finish(self) -> None:
        """Flush and fsync the content, then close (the rename is the caller's next step)."""
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()

    def discard(self) -> None:
        """Close and remove the temporary file; the target is not touched."""
        with suppress(Exception):
            self.file.close()
        _remove_quietly(self.tmp)


@contextmanager
def atomic_write(
    path: str | os.PathLike[str],
    mode: str = "wb",
    encoding: str | None = None,
    newline: str | None = None,
) -> Iterator[IO[Any]]:
    """Open `path` for writing so that it is replaced only if the ``with`` block succeeds.

    Parameters
    ----------
    path : str or path-like
        The file to create or replace. Its directory must exist.
    mode : {"wb", "w", "wt"}
        Binary or text.
    encoding : str, optional
        Text encoding (text modes only), UTF-8 when not given.
    newline : str, optional
        As for :func:`open` (text modes only).

    Yields
    ------
    file object
        Writes go to a temporary file beside `path`.

    Notes
    -----
    On leaving the block normally, the temporary file is fsynced and renamed over `path`. On any
    exception (including KeyboardInterrupt), it is removed, the exception propagates, and `path`
    keeps its previous content byte for byte (or stays absent).

    Examples
    --------
    >>> with atomic_write("out.txt", "w") as f:  # doctest: +SKIP
    ...     f.write("hello\\n")
    """
    with atomic_write_group([path], mode=mode, encoding=encoding, newline=newline) as (f,):
        yield f


@contextmanager
def atomic_write_group(
    paths: Sequence[str | os.PathLike[str]],
    mode: str | Sequence[str] = "wb",
    encoding: str | None = None,
    newline: str | None = None,
) -> Iterator[tuple[IO[Any], ...]]:
    """Write several files that belong together: all are replaced, or (on error) none is.

    Parameters
    ----------
    paths : sequence of str or path-like
        The files to create or replace, in the order they are renamed at the end. Put a file that
        refers to the others (a ROS map YAML naming its image) *last*, so that it never points at an
        image that is not there yet.
    mode : str or sequence of str
        ``"wb"``, ``"w"`` or ``"wt"``: one for all files, or one per file.
    encoding, newline : str, optional
        For the text-mode files, as in :func:`atomic_write`.

    Yields
    ------
    tuple of file objects
        One per path, in the same order.

    Notes
    -----
    All temporary files are written and fsynced first; only when every one is complete are they
    renamed over their targets. An error while writing any of them removes all the temporary files
    and leaves every target untouched. The renames themselves are individually atomic but not
    jointly: if the operating system fails one of them (a disk removed mid-way), the files renamed
    before it are new and the rest old; the remaining temporary files are still cleaned up.
    """
    targets = [Path(p) for p in paths]
    if not targets:
        raise ValueError("atomic_write_group needs at least one path")
    resolved = [os.path.abspath(t) for t in targets]
    if len(set(resolved)) != len(resolved):
        raise ValueError(f"atomic_write_group was given the same file twice: {[str(t) for t in targets]}")
    modes = [mode] * len(targets) if isinstance(mode, str) else list(mode)
    if len(modes) != len(targets):
        raise ValueError(f"{len(modes)} modes for {len(targets)} paths")

    pending: list[_Pending] = []
    try:
        for target, m in zip(targets, modes):
            pending.append(_Pending(target, m, encoding, newline))
        yield tuple(p.file for p in pending)
        for p in pending:
            p.finish()
        while pending:
            p = pending[0]
            os.replace(p.tmp, p.target)
            pending.pop(0)
    except BaseException:
        for p in pending:
            p.discard()
        raise
    for directory in {t.parent for t in targets}:
        _fsync_dir(directory)
