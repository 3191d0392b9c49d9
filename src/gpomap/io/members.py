"""Arrays written as the members of a zip archive of NumPy arrays (``map.npz``, ``map.gpom``).

Each array is one ``.npy`` member, deflated only where that pays: a map's counts, flags and
offsets shrink many times over; its probabilities, variances and Cholesky factors barely, and
deflating them costs more time than it saves bytes. :func:`numpy.load` reads either kind.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.io.atomic import atomic_write

__all__ = ["DEFLATE_BELOW", "DEFLATE_LEVEL", "deflates", "write_member", "write_npz"]

#: zlib's level for the members deflated: the fastest. A map's counts and flags shrink nearly as
#: much as at zlib's default, in a fraction of its time (docs/choices.md, "Measured for the code").
DEFLATE_LEVEL: int = 1

#: Bytes of an array deflate is tried on before the whole array is (:func:`deflates`): a building's
#: map file holds tens of thousands of arrays (each tile's factor, cells and weights).
DEFLATE_SAMPLE: int = 1 << 13


#: Arrays of at least this many bytes are sampled in :data:`SPREAD_PIECES` pieces of
#: :data:`DEFLATE_SAMPLE` bytes spread evenly over them instead: a map's planes begin at a corner
#: of unknown space, whose first bytes deflate whatever the rest does.
SPREAD_FROM: int = 1 << 20
SPREAD_PIECES: int = 8

#: A member is deflated when its sample shrinks below this share of its size. A written map's
#: probability and variance planes shrink only to 0.73-0.88 of theirs, at about 20 ns a byte: more
#: time than the bytes saved are worth. Counts, flags and offsets shrink to a few percent.
DEFLATE_BELOW: float = 2.0 / 3.0


def deflates(array: NDArray[Any]) -> bool:
    """Whether to deflate `array`'s member: when its first :data:`DEFLATE_SAMPLE` bytes (a large
    array's pieces, :data:`SPREAD_FROM`) shrink below :data:`DEFLATE_BELOW` of their size, or it is small."""
    raw = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
    if raw.size < 1024:
        return True
    if raw.size < SPREAD_FROM:
        sample = raw[:DEFLATE_SAMPLE].tobytes()
    else:
        starts = np.linspace(0, raw.size - DEFLATE_SAMPLE, SPREAD_PIECES).astype(np.intp)
        sample = b"".join(raw[s : s + DEFLATE_SAMPLE].tobytes() for s in starts)
    return len(zlib.compress(sample, 1)) < DEFLATE_BELOW * len(sample)


def write_member(zf: zipfile.ZipFile, key: str, array: NDArray[Any]) -> None:
    """`array` as the member ``KEY.npy`` of `zf` (open for writing), deflated where that pays
    (:func:`deflates`), dated 1980 so that the same arrays give the same bytes."""
    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED if deflates(array) else zipfile.ZIP_STORED
    # zipfile reads a member's level from its ZipInfo: compress_level from Python 3.13, _compresslevel before.
    setattr(info, "compress_level" if hasattr(info, "compress_level") else "_compresslevel", DEFLATE_LEVEL)
    with zf.open(info, "w", force_zip64=array.nbytes > (1 << 30)) as member:
        np.lib.format.write_array(member, array, allow_pickle=False)


def write_npz(path: str | os.PathLike[str], arrays: dict[str, Any]) -> None:
    """`arrays` (array-likes by key) as an ``.npz`` at `path`, each through :func:`write_member`,
    written atomically (no suffix is appended)."""
    with atomic_write(path, "wb") as f, zipfile.ZipFile(f, "w", allowZip64=True) as zf:
        for key, array in arrays.items():
            write_member(zf, key, np.asarray(array))
