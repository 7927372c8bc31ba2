"""PNG files of a run: structure and compressed-data checks before OpenCV decodes a mask or image.

A mask or image is checked by :func:`check_png` (signature, IHDR, every chunk's CRC, an IDAT, an IEND, and the
inflated scanline data: complete, of exactly the size the header implies, valid filter bytes) before
``cv2.imdecode`` sees it, so truncated, bit-flipped and corrupt-but-CRC-valid files become one-line errors.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np

#: The eight bytes every PNG file starts with.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
#: Adam7 passes: (x start, y start, x step, y step).
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
_INFLATE_PIECE = 1 << 20


def _png_rows(width: int, height: int, bits_per_pixel: int, interlaced: bool) -> list[tuple[int, int]]:
    """``(row count, bytes per row without the filter byte)`` of every (sub-)image of the scanline data."""
    if not interlaced:
        return [(height, (width * bits_per_pixel + 7) // 8)]
    out = []
    for x0, y0, dx, dy in _ADAM7:
        w = (width - x0 + dx - 1) // dx if width > x0 else 0
        h = (height - y0 + dy - 1) // dy if height > y0 else 0
        if w and h:
            out.append((h, (w * bits_per_pixel + 7) // 8))
    return out


def _check_png_data(idat: list[memoryview], rows: list[tuple[int, int]]) -> None:
    """Inflate the IDAT zlib stream piece by piece; it must hold exactly ``rows`` with filter bytes 0..4."""
    expected = sum(n * (1 + b) for n, b in rows)
    # the position of every filter byte, as (start, stride, count) runs over the inflated stream
    runs, pos = [], 0
    for n, b in rows:
        runs.append((pos, 1 + b, n))
        pos += n * (1 + b)
    d = zlib.decompressobj()
    total = 0

    def take(piece: bytes) -> None:
        nonlocal total
        if total + len(piece) > expected:
            raise ValueError(f"corrupt PNG (image data longer than the {expected} bytes the header implies)")
        arr = np.frombuffer(piece, dtype=np.uint8)
        for start, stride, count in runs:
            first = max(start, total)
            if first > start:
                first = start + -(-(first - start) // stride) * stride
            last = min(start + stride * count, total + len(piece))
            if first < last and np.any(arr[first - total : last - total : stride] > 4):
                raise ValueError("corrupt PNG (invalid row filter type in the image data)")
        total += len(piece)

    try:
        for i, chunk in enumerate(idat):
            buf = bytes(chunk)
            while buf and not d.eof:
                take(d.decompress(buf, _INFLATE_PIECE))
                buf = d.unconsumed_tail
            if d.eof:
                if d.unused_data or any(len(c) for c in idat[i + 1 :]):
                    raise ValueError("corrupt PNG (data after the end of the compressed image stream)")
                break
        while not d.eof:
            piece = d.decompress(b"", _INFLATE_PIECE)
            if not piece:
                break
            take(piece)
    except zlib.error as exc:
        raise ValueError(f"corrupt PNG (compressed image data: {exc})") from None
    if not d.eof:
        raise ValueError("corrupt PNG (compressed image data ends early)")
    if total != expected:
        raise ValueError(f"corrupt PNG (image data has {total} bytes, the header implies {expected})")


def check_png(data: bytes, size: tuple[int, int] | None = None, inflate: bool = True) -> tuple[int, int]:
    """``(width, height)`` of a sound PNG held in ``data``; ``ValueError(reason)`` otherwise.

    Walks every chunk and checks its CRC-32, requires a valid IHDR first, at least one IDAT and
    a final IEND; when ``size = (width, height)`` is given the header must match it (checked
    before any inflating, so a huge declared image costs nothing); then inflates the IDAT zlib
    stream in Python (in 1 MB pieces) and requires it to be complete, exactly as long as the
    header implies, with every row's filter byte in 0..4. Pixels are not un-filtered.
    ``inflate`` False stops before inflating (a 1080x1080 mask's data takes ~3 ms; the rest ~0.1 ms).
    """
    w, h, depth, colour, interlaced, idat = _png_chunks(data)
    if size is not None and (w, h) != tuple(size):
        raise ValueError(f"image is {w}x{h} px but the camera is {size[0]}x{size[1]} px (width x height)")
    if inflate:
        _check_png_data(idat, _png_rows(w, h, _PNG_CHANNELS[colour] * depth, interlaced))
    return w, h


def png_size(data: bytes) -> tuple[int, int]:
    """``(width, height)`` of a sound PNG held in ``data`` (:func:`check_png` without a size)."""
    return check_png(data)


def _png_chunks(data: bytes) -> tuple[int, int, int, int, bool, list[memoryview]]:
    """Structural walk: ``(width, height, bit depth, colour type, interlaced, IDAT payloads)``."""
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG file (bad signature)")
    view = memoryview(data)
    pos, n = len(PNG_SIGNATURE), len(data)
    size: tuple[int, int] | None = None
    idat: list[memoryview] = []
    while True:
        if pos + 12 > n:
            raise ValueError("truncated PNG (no IEND chunk)")
        length = int.from_bytes(view[pos : pos + 4], "big")
        ctype = bytes(view[pos + 4 : pos + 8]).decode("latin-1")
        end = pos + 12 + length
        if length > 0x7FFFFFFF or end > n:
            raise ValueError(f"truncated PNG (chunk {ctype!r} runs past the end of the file)")
        crc = int.from_bytes(view[end - 4 : end], "big")
        if zlib.crc32(view[pos + 4 : end - 4]) != crc:
            raise ValueError(f"corrupt PNG (CRC mismatch in chunk {ctype!r})")
        if size is None:
            if ctype != "IHDR" or length != 13:
                raise ValueError("corrupt PNG (first chunk is not a valid IHDR)")
            size = (
                int.from_bytes(view[pos + 8 : pos + 12], "big"),
                int.from_bytes(view[pos + 12 : pos + 16], "big"),
            )
            if size[0] == 0 or size[1] == 0 or size[0] > 0x7FFFFFFF or size[1] > 0x7FFFFFFF:
                raise ValueError("corrupt PNG (image size zero or beyond 2^31 - 1)")
            depth, colour, compression, filtering, interlace = bytes(view[pos + 16 : pos + 21])
            if colour not in _PNG_DEPTHS or depth not in _PNG_DEPTHS[colour]:
                raise ValueError(f"corrupt PNG (bit depth {depth} with colour type {colour})")
            if compression != 0 or filtering != 0 or interlace not in (0, 1):
                raise ValueError("corrupt PNG (unknown compression, filter or interlace method)")
        elif ctype == "IDAT":
            idat.append(view[pos + 8 : end - 4])
        elif ctype == "IEND":
            break
        pos = end
    if not idat:
        raise ValueError("corrupt PNG (no IDAT chunk)")
    return size[0], size[1], depth, colour, bool(interlace), idat


def image_file_problem(path: Path, width: int | None, height: int | None, png_only: bool,
                       inflate: bool = True) -> str | None:
    """The reason ``path`` is not a usable image of ``width x height``, or None when it is.

    ``inflate`` False: a PNG's compressed data is not inflated (:func:`check_png`)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    if not data:
        return f"{path}: empty file (0 bytes)"  # cv2.imdecode raises on an empty buffer instead of returning None
    if data.startswith(PNG_SIGNATURE):
        try:
            w, h = check_png(data, None if width is None or height is None else (width, height), inflate)
        except ValueError as exc:
            return f"{path}: {exc}"
    elif png_only:
        return f"{path}: not a PNG file (bad signature)"
    else:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            return f"{path}: not a readable image"
        h, w = img.shape[:2]
    if width is not None and height is not None and (w, h) != (width, height):
        return f"{path}: image is {w}x{h} px but the camera is {width}x{height} px (width x height)"
    return None


def decode_image(path: Path, width: int | None, height: int | None, png_only: bool) -> np.ndarray:
    """Read and decode an image file; ``ValueError(reason)`` when unreadable, corrupt or mis-sized.

    The one place that hands image bytes to OpenCV: a PNG passes :func:`check_png` first.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not data:
        raise ValueError(f"{path}: empty file (0 bytes)")
    if data.startswith(PNG_SIGNATURE):
        try:
            check_png(data, None if width is None or height is None else (width, height))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    elif png_only:
        raise ValueError(f"{path}: not a PNG file (bad signature)")
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image (decoding failed)")
    h, w = img.shape[:2]
    if width is not None and height is not None and (w, h) != (width, height):
        raise ValueError(
            f"{path}: image is {w}x{h} px but the camera is {width}x{height} px (width x height)"
        )
    return img
