"""Checks every reader makes before it opens a file.

Opening a FIFO blocks until a writer appears, and reading a device (``/dev/zero``) never ends, so
readers refuse anything that is not a regular file before opening it, from :func:`os.stat` alone.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from gpomap.errors import InputFormatError

__all__ = ["regular_file", "file_kind"]


def file_kind(mode: int) -> str:
    """Name the kind of file `mode` (from :func:`os.stat`) describes, for messages."""
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def regular_file(path: str | os.PathLike[str], what: str = "input file") -> Path:
    """`path` as a Path, after checking that it names an existing regular file.

    Parameters
    ----------
    path : path-like
    what : str
        What the file should be, for the message (``"CARMEN log"``, ``"map image"``, ...).

    Returns
    -------
    Path

    Raises
    ------
    InputFormatError
        The path does not exist, cannot be examined, or is a directory, FIFO, device or socket.
    """
    p = Path(path)
    try:
        st = os.stat(p)  # follows symlinks: a link to a regular file is fine
    except FileNotFoundError:
        raise InputFormatError(f"no such file; expected a {what}", path=str(p)) from None
    except (OSError, ValueError) as exc:  # permission, name too long, embedded NUL
        raise InputFormatError(f"cannot examine the file ({exc}); expected a {what}", path=str(p)) from None
    if not stat.S_ISREG(st.st_mode):
        raise InputFormatError(f"is {file_kind(st.st_mode)}, not a regular file; expected a {what}", path=str(p))
    return p
