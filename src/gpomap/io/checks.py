"""Checks every reader makes before it opens a file, and a bounded ``.npz`` loader.

Opening a FIFO blocks until a writer appears, and reading a device (``/dev/zero``) never ends, so
readers refuse anything that is not a regular file before opening it, from :func:`os.stat` alone.
"""

from __future__ import annotations

import math
import os
import stat
import zipfile
import zlib
from pathlib import Path

import numpy as np

from gpomap.errors import InputFormatError

__all__ = ["regular_file", "ros2_bag_directory", "file_kind", "load_npz", "MAX_NPZ_ARRAY_BYTES"]


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
        raise InputFormatError(f"file not found (no such file); expected a {what}", path=str(p)) from None
    except (OSError, ValueError) as exc:  # permission, name too long, embedded NUL
        raise InputFormatError(f"cannot examine the file ({exc}); expected a {what}", path=str(p)) from None
    if not stat.S_ISREG(st.st_mode):
        raise InputFormatError(f"is {file_kind(st.st_mode)}, not a regular file; expected a {what}", path=str(p))
    return p


def ros2_bag_directory(path: str | os.PathLike[str], what: str) -> bool:
    """Whether `path` is a ROS2 bag directory; anything else must be a regular file.

    Parameters
    ----------
    path : path-like
    what : str
        What the path should be, for the message (``"ROS bag"``, ...).

    Raises
    ------
    InputFormatError
        The path does not exist or cannot be examined, is a directory without ``metadata.yaml``,
        or is a FIFO, device or socket.
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        raise InputFormatError("no such file or directory", path=str(p)) from None
    except (OSError, ValueError) as exc:
        raise InputFormatError(f"cannot examine the path ({exc})", path=str(p)) from None
    if stat.S_ISDIR(mode):
        if (p / "metadata.yaml").is_file():
            return True
        raise InputFormatError("directory without metadata.yaml; expected a ROS2 bag directory", path=str(p))
    if not stat.S_ISREG(mode):
        # Opening a FIFO would block, reading a device might never end.
        raise InputFormatError(f"is {file_kind(mode)}, not a regular file; expected a {what}", path=str(p))
    return False


#: Largest array read from an ``.npz`` member, bytes, checked from the member's header before the
#: data are read: a 12-byte header can announce an array of terabytes.
MAX_NPZ_ARRAY_BYTES = 1 << 31


def load_npz(path: str | os.PathLike[str], what: str = ".npz file") -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` archive, read without pickles and with each size checked first.

    Parameters
    ----------
    path : path-like
    what : str
        What the archive should be, for messages.

    Returns
    -------
    dict of str to ndarray
        Keyed by member name without ``.npy``.

    Raises
    ------
    InputFormatError
        Not a regular file, not a zip archive, truncated or corrupt archive, a member that is not
        a ``.npy`` array, an object array (it would need pickles), an array larger than
        :data:`MAX_NPZ_ARRAY_BYTES` or than its member's stored size.
    """
    p = regular_file(path, what)
    spath = str(p)
    fmt = np.lib.format
    arrays: dict[str, np.ndarray] = {}
    member = "(archive)"
    try:
        with zipfile.ZipFile(p) as zf:
            for info in zf.infolist():
                member = info.filename
                key = member[:-4] if member.endswith(".npy") else member
                with zf.open(info) as f:
                    version = fmt.read_magic(f)
                    if version == (1, 0):
                        shape, _, dtype = fmt.read_array_header_1_0(f)
                    elif version == (2, 0):
                        shape, _, dtype = fmt.read_array_header_2_0(f)
                    else:
                        raise InputFormatError(
                            f"array {key!r} uses .npy format version {version}; expected 1.0 or 2.0", path=spath
                        )
                    if dtype.hasobject:
                        raise InputFormatError(
                            f"array {key!r} holds Python objects ({dtype}), which would need pickles; "
                            "expected numbers or strings",
                            path=spath,
                        )
                    nbytes = math.prod(shape) * dtype.itemsize
                    if nbytes > MAX_NPZ_ARRAY_BYTES or nbytes > info.file_size:
                        raise InputFormatError(
                            f"array {key!r} announces shape {shape} of {dtype} ({nbytes:,} bytes) but the member "
                            f"stores {info.file_size:,} bytes (at most {MAX_NPZ_ARRAY_BYTES:,} are read)",
                            path=spath,
                        )
                with zf.open(info) as f:
                    arrays[key] = fmt.read_array(f, allow_pickle=False)
    except InputFormatError:
        raise
    except (
        ValueError,
        OSError,
        EOFError,
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        zlib.error,
        NotImplementedError,
        KeyError,
        TypeError,
        SyntaxError,
        RuntimeError,
    ) as exc:
        # read_magic / read_array_header raise ValueError; a bad CRC or cut stream BadZipFile /
        # EOFError / zlib.error; an unsupported compression NotImplementedError; the encryption
        # flag RuntimeError ("password required").
        where = "" if member == "(archive)" else f" (member {member!r})"
        raise InputFormatError(f"not a readable {what}{where}: {type(exc).__name__}: {str(exc)[:200]}", path=spath) from None
    return arrays
