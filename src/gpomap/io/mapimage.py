"""A map image, PGM or PNG, read as map_server reads it: its size checked from the header before
decoding, its pixels as an array (row 0 the image's top), and a PNG's alpha as transparency.
"""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.io.checks import regular_file

__all__ = ["read_map_image", "MAX_PIXELS", "MAX_PLAIN_PIXELS"]

#: Largest map image read, pixels (width x height), checked from the image header before decoding:
#: a 20000 x 20000 image would need gigabytes once converted to probabilities.
MAX_PIXELS = 200_000_000
#: Plain (ASCII, P2) PGMs cost tens of bytes a pixel while parsed: a lower limit.
MAX_PLAIN_PIXELS = 20_000_000

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# A PGM header (with comments) must fit in this many bytes.
_HEADER_BYTES = 65536


def _describe_magic(head: bytes) -> str:
    """Say what kind of file starts with `head`, for error messages."""
    known = {
        b"P1": "a plain PBM (bitmap) file",
        b"P4": "a binary PBM (bitmap) file",
        b"P3": "a plain PPM (colour) file",
        b"P6": "a binary PPM (colour) file",
        b"P7": "a PAM file",
        b"\xff\xd8\xff": "a JPEG file",
        b"GIF8": "a GIF file",
        b"BM": "a BMP file",
        b"II*\x00": "a TIFF file",
        b"MM\x00*": "a TIFF file",
        b"%PDF": "a PDF file",
    }
    for magic, what in known.items():
        if head.startswith(magic):
            return what
    if not head:
        return "an empty file"
    return f"a file starting with bytes {head[:8]!r}"


def _pgm_tokens(data: bytes, start: int, count: int, path: str) -> tuple[list[int], int]:
    """Read `count` whitespace-separated integers from a PGM header, skipping ``#`` comments.

    Returns the integers and the offset just past the last one.
    """
    values: list[int] = []
    i, n = start, len(data)
    while len(values) < count:
        while i < n and data[i : i + 1].isspace():
            i += 1
        if i < n and data[i : i + 1] == b"#":
            while i < n and data[i : i + 1] not in (b"\n", b"\r"):
                i += 1
            continue
        j = i
        while j < n and not data[j : j + 1].isspace() and data[j : j + 1] != b"#":
            j += 1
        if j == i:
            raise InputFormatError("PGM header ends early (expected width, height and maxval)", path=path)
        word = data[i:j]
        if not word.isdigit() or len(word) > 12:
            line = data.count(b"\n", 0, i) + 1
            raise InputFormatError(f"PGM header: expected a number, found {word[:20]!r}", path=path, line=line)
        values.append(int(word))
        i = j
    return values, i


def _check_size(width: int, height: int, limit: int, path: str) -> None:
    """Refuse an image larger than `limit` pixels, from its header, before decoding it."""
    if width * height > limit:
        raise InputFormatError(
            f"map image is {width} x {height} = {width * height:,} pixels; at most {limit:,} are read "
            "(the size comes from the image header)",
            path=path,
        )


def _png_size(head: bytes, path: str) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk (bytes 16..24)."""
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise InputFormatError("PNG file without an IHDR header chunk (truncated or corrupt)", path=path)
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _read_pgm(data: bytes, path: str) -> NDArray[np.uint8]:
    """Decode an 8-bit PGM (P5 binary or P2 ASCII); ndarray of uint8, shape (height, width), row 0 = top."""
    magic = data[:2]
    (width, height, maxval), end = _pgm_tokens(data, 2, 3, path)
    if width <= 0 or height <= 0:
        raise InputFormatError(f"PGM size must be positive, got {width} x {height}", path=path)
    if not 0 < maxval <= 255:
        raise InputFormatError(f"only 8-bit PGM images are supported (maxval 1..255), got maxval {maxval}", path=path)
    count = width * height
    _check_size(width, height, MAX_PIXELS if magic == b"P5" else MAX_PLAIN_PIXELS, path)
    if magic == b"P5":
        # Exactly one whitespace byte separates maxval from the raster.
        raster = data[end + 1 : end + 1 + count]
        if len(raster) < count:
            raise InputFormatError(
                f"PGM raster is truncated: {len(raster)} bytes for {width} x {height} = {count} pixels", path=path
            )
        pixels = np.frombuffer(raster, dtype=np.uint8).reshape(height, width)
    else:
        words = data[end:].split()
        if len(words) < count:
            raise InputFormatError(f"plain PGM has {len(words)} values for {width} x {height} = {count} pixels", path=path)
        try:
            values = np.array([int(w) for w in words[:count]], dtype=np.int64)
        except ValueError:
            raise InputFormatError("plain PGM raster holds a value that is not an integer", path=path) from None
        if values.min() < 0 or values.max() > maxval:
            raise InputFormatError(f"plain PGM value outside 0..{maxval}", path=path)
        pixels = values.astype(np.uint8).reshape(height, width)
    if maxval != 255:
        # Stretch to 0..255, as image loaders do, so thresholds mean the same thing.
        pixels = np.rint(pixels.astype(np.float64) * (255.0 / maxval)).astype(np.uint8)
    return pixels


def _read_png(path: str) -> tuple[NDArray[np.uint8], NDArray[np.bool_] | None]:
    """Decode a PNG to grey values (colour channels averaged) and a transparency mask (or None)."""
    from PIL import Image

    try:
        # The size was checked against MAX_PIXELS already; Pillow's own bomb warning adds nothing.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            img_file = Image.open(path)
        with img_file:
            img: Image.Image = img_file
            img.load()
            if img.mode in ("I", "I;16", "I;16B", "I;16L", "F"):
                raise InputFormatError(f"only 8-bit PNG images are supported, got Pillow mode {img.mode!r}", path=path)
            if img.mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            elif img.mode not in ("L", "LA", "RGB", "RGBA"):
                img = img.convert("RGBA" if "A" in img.mode else "L")
            arr = np.asarray(img)
            mode = img.mode
    except InputFormatError:
        raise
    except Image.DecompressionBombError as exc:
        raise InputFormatError(f"PNG image refused as too large by Pillow ({exc})", path=path) from None
    except Exception as exc:  # Pillow raises several types for corrupt files
        raise InputFormatError(f"cannot decode PNG image: {exc}", path=path) from None
    if arr.ndim == 2:
        return arr.astype(np.uint8), None
    has_alpha = mode in ("LA", "RGBA")
    colour = arr[..., :-1] if has_alpha else arr
    grey = np.rint(colour.astype(np.float64).mean(axis=-1)).astype(np.uint8)
    transparent = arr[..., -1] < 255 if has_alpha else None
    return grey, transparent


def read_map_image(image_path: str | os.PathLike[str]) -> tuple[NDArray[np.uint8], NDArray[np.bool_] | None]:
    """Read a map image (8-bit PGM P5/P2, or PNG) as it is stored: row 0 = top of the map.

    Parameters
    ----------
    image_path : str or path-like

    Returns
    -------
    pixels : ndarray of uint8, shape (height, width)
        Grey values, colour channels averaged.
    transparent : ndarray of bool, shape (height, width), or None
        Pixels with alpha < 255, for PNGs with an alpha channel; None otherwise.

    Raises
    ------
    InputFormatError
        The file is missing, is neither a PGM nor a PNG (the message says what it is), or is malformed.
    """
    path = str(image_path)
    p = regular_file(path, "map image (PGM or PNG)")
    try:
        with p.open("rb") as f:
            head = f.read(_HEADER_BYTES)
            if head[:2] in (b"P5", b"P2"):
                # Size from the header first: the raster is read only if it is not absurd.
                width, height = _pgm_size(head, path)
                _check_size(width, height, MAX_PIXELS if head[:2] == b"P5" else MAX_PLAIN_PIXELS, path)
                data = head + f.read()
            else:
                data = head
    except OSError as exc:
        raise InputFormatError(f"cannot read the map image ({exc})", path=path) from None
    if data[:2] in (b"P5", b"P2"):
        return _read_pgm(data, path), None
    if data.startswith(_PNG_MAGIC):
        _check_size(*_png_size(data, path), MAX_PIXELS, path)
        return _read_png(path)
    raise InputFormatError(f"map image must be a PGM (P5 or P2) or PNG file, found {_describe_magic(data[:16])}", path=path)


def _pgm_size(head: bytes, path: str) -> tuple[int, int]:
    """Width and height from the first bytes of a PGM, so the header can be checked alone."""
    try:
        (width, height, _), _ = _pgm_tokens(head, 2, 3, path)
    except InputFormatError:
        if len(head) >= _HEADER_BYTES:
            raise InputFormatError(
                f"PGM header (width, height, maxval) not complete within its first {_HEADER_BYTES} bytes", path=path
            ) from None
        raise
    return width, height


# --------------------------------------------------------------------------------------------------
# Reading the YAML
