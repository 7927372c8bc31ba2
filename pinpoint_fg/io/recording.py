"""Recorded runs, format version 1 (``shared/RECORDING_FORMAT.md``): data model, reader, writer.

A run is a directory with ``recording.json``, ``frames.csv`` and optional ``masks/`` and
``images/``. Readers validate everything and raise :class:`pinpoint_fg.errors.InputError`
naming the file, the row and the column; extra columns/keys are ignored.

Conventions of the error reports (fixed here, used by every reader in this module):

* ``row`` is the **1-based data row** of ``frames.csv``: the header is not counted and
  fully blank lines are skipped, so row 1 is the first record. Every row message also says
  ``(frame F, file line L)`` with the frame index (when it parsed) and the physical file line,
  so the number cannot be mistaken for a frame index.
* ``column`` is the CSV column name, or the JSON key path (``"camera.fx"``) in
  ``recording.json``. Header problems carry no row and start with ``header:``.
* Problems with a mask or image file are reported against ``frames.csv`` (its row and the
  ``mask``/``image`` column) and the message names the PNG file.

Decisions the format leaves open (stated here so readers and writers agree):

* Every key shown in the format's ``recording.json`` example is required, with the JSON
  type shown (integers for ``width``/``height``/``version``; numbers otherwise, booleans
  are not numbers). ``fx``, ``fy``, ``frame_rate_hz``, ``radius_m``, ``wire_diameter_m``
  must be > 0; ``distortion`` has 4, 5, 8, 12 or 14 OpenCV coefficients.
* Numeric cells are plain decimal numbers (``1``, ``-0.5``, ``1e-3``); ``nan``/``inf`` and
  anything else are rejected. ``frame`` is a non-negative integer, strictly increasing.
  ``t_s`` is not required to increase (only ``frame`` is, per the format).
* Every number must also lie in a finite, physically possible range (a cell like ``1e300``
  parses but would overflow the maths): pixel cells within :data:`PIXEL_RANGE_FACTOR` image
  sizes of the image (``-10 W <= u <= 11 W``), metres within :data:`MAX_ABS_METRES` of the
  camera, ``frame`` at most ``2**63 - 1`` (int64), ``|t_s| <=`` :data:`MAX_ABS_TIME_S`; in
  recording.json ``width``/``height`` at most :data:`MAX_IMAGE_SIDE_PX`, ``fx``/``fy`` at most
  :data:`MAX_FOCAL_PX`, ``cx``/``cy`` in the pixel range, ``|distortion| <=``
  :data:`MAX_ABS_DISTORTION`, ``frame_rate_hz <=`` :data:`MAX_FRAME_RATE_HZ`, needle lengths at
  most :data:`MAX_NEEDLE_M` and angles within ``±``:data:`MAX_ABS_ANGLE_RAD`. recording.json is
  parsed by :func:`pinpoint_fg.io.jsonfile.loads_json` (bounded nesting, no huge integers).
* A quaternion is accepted when ``| ||q|| - 1 | <= QUAT_NORM_TOL`` (1 %) and normalised;
  anything farther from unit length is a typo or a swapped column, not rounding.
* Paths use ``/``, are relative, contain no ``..`` component, no backslash and no control
  character (NUL included), are at most :data:`MAX_PATH_CHARS` characters with components of at
  most 255 bytes, and must resolve (symlinks followed) inside the run directory.
* Masks must be PNG (lossless: a JPEG's noise would become backbone pixels). Images may be
  any format OpenCV decodes. Both must be exactly ``camera.width x camera.height``. PNGs are
  checked at validation time by :func:`check_png`: structure (signature, IHDR, every chunk's
  CRC, an IDAT, an IEND) *and* the compressed data (the IDAT zlib stream is inflated in Python
  and must be complete, of exactly the size the header implies, with valid row filter bytes),
  which catches truncated, bit-flipped and corrupt-but-CRC-valid files before libpng sees them
  (libpng would print its complaint to stderr). Every decode goes through
  :func:`_decode_image`, which runs the same check before ``cv2.imdecode``.
* Keypoints outside the image are not rejected (a detector's business, not the format's).
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import tempfile
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import cv2
import numpy as np

from factors.geometry import NeedleModel, PinholeCamera, pose_from_xyz_quat, xyz_quat_from_pose
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import load_json

FORMAT_NAME = "pinpoint-recording"
FORMAT_VERSION = 1

#: Column groups of frames.csv: within a group the cells are all present or all empty.
COLUMN_GROUPS: dict[str, tuple[str, ...]] = {
    "required": ("frame", "t_s"),
    "tip": ("tip_u_px", "tip_v_px"),
    "tail": ("tail_u_px", "tail_v_px"),
    "mask": ("mask",),
    "kinematics": (
        "grasper_x_m", "grasper_y_m", "grasper_z_m", "grasper_qw", "grasper_qx", "grasper_qy", "grasper_qz",
    ),
    "ground_truth": ("gt_x_m", "gt_y_m", "gt_z_m", "gt_qw", "gt_qx", "gt_qy", "gt_qz"),
    "image": ("image",),
    "occlusion": ("occlusion",),
}

OCCLUSION_LABELS = ("none", "partial", "heavy")

#: Largest accepted deviation of a quaternion's norm from 1 (relative); within it, q is normalised.
QUAT_NORM_TOL = 1e-2

#: Pixel cells must lie in ``[-F * side, (F + 1) * side]`` for the image side (width for u, height for v).
PIXEL_RANGE_FACTOR = 10
#: Largest accepted |coordinate| of a position cell (``*_m``), metres.
MAX_ABS_METRES = 10.0
#: Largest accepted |t_s|, seconds (~317 years: Unix time stamps fit).
MAX_ABS_TIME_S = 1e10
#: Largest accepted frame index (int64).
MAX_FRAME_INDEX = 2**63 - 1
#: Largest accepted image width/height, pixels.
MAX_IMAGE_SIDE_PX = 65535
#: Largest accepted focal length, pixels.
MAX_FOCAL_PX = 1e7
#: Largest accepted |distortion coefficient|.
MAX_ABS_DISTORTION = 1e6
#: Largest accepted frame rate, Hz.
MAX_FRAME_RATE_HZ = 1e6
#: Largest accepted needle radius / wire diameter, metres.
MAX_NEEDLE_M = 1.0
#: Largest accepted |needle arc angle|, radians.
MAX_ABS_ANGLE_RAD = 100.0
#: Longest accepted mask/image path, characters.
MAX_PATH_CHARS = 1024

#: All frames.csv columns this version knows, in the order the writer emits them.
KNOWN_COLUMNS: tuple[str, ...] = tuple(c for cols in COLUMN_GROUPS.values() for c in cols)

RECORDING_JSON = "recording.json"
FRAMES_CSV = "frames.csv"


@dataclass(frozen=True)
class RecordingInfo:
    """The contents of ``recording.json``."""

    name: str
    """Run name."""
    frame_rate_hz: float
    """Camera frame rate, Hz."""
    camera: PinholeCamera
    """Intrinsics, image size and distortion."""
    needle: NeedleModel
    """Needle geometry."""
    extra: dict = field(default_factory=dict)
    """Keys of recording.json this version does not know (kept, not interpreted)."""


@dataclass(frozen=True)
class FrameRecord:
    """One row of ``frames.csv``; None means the cell group was empty (not observed)."""

    frame: int
    """Frame index (strictly increasing in a run)."""
    t_s: float
    """Time stamp, seconds."""
    tip_px: np.ndarray | None = None
    """Detected tip ``(2,)``, distorted image pixels as recorded."""
    tail_px: np.ndarray | None = None
    """Detected tail ``(2,)``, distorted image pixels as recorded."""
    mask: str | None = None
    """Mask PNG path relative to the run directory."""
    cam_T_grasper: np.ndarray | None = None
    """Kinematic grasper pose ``(4, 4)``."""
    cam_T_needle_gt: np.ndarray | None = None
    """Ground-truth needle pose ``(4, 4)``."""
    image: str | None = None
    """Camera image path relative to the run directory."""
    occlusion: str | None = None
    """``none``, ``partial`` or ``heavy`` where known."""


# --------------------------------------------------------------------------------------------
# PNG structure and image files
# --------------------------------------------------------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


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


def check_png(data: bytes, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """``(width, height)`` of a sound PNG held in ``data``; ``ValueError(reason)`` otherwise.

    Walks every chunk and checks its CRC-32, requires a valid IHDR first, at least one IDAT and
    a final IEND; when ``size = (width, height)`` is given the header must match it (checked
    before any inflating, so a huge declared image costs nothing); then inflates the IDAT zlib
    stream in Python (in 1 MB pieces) and requires it to be complete, exactly as long as the
    header implies, with every row's filter byte in 0..4. Pixels are not un-filtered.
    """
    w, h, depth, colour, interlaced, idat = _png_chunks(data)
    if size is not None and (w, h) != tuple(size):
        raise ValueError(f"image is {w}x{h} px but the camera is {size[0]}x{size[1]} px (width x height)")
    _check_png_data(idat, _png_rows(w, h, _PNG_CHANNELS[colour] * depth, interlaced))
    return w, h


def png_size(data: bytes) -> tuple[int, int]:
    """``(width, height)`` of a sound PNG held in ``data`` (:func:`check_png` without a size)."""
    return check_png(data)


def _png_chunks(data: bytes) -> tuple[int, int, int, int, bool, list[memoryview]]:
    """Structural walk: ``(width, height, bit depth, colour type, interlaced, IDAT payloads)``."""
    if not data.startswith(_PNG_SIGNATURE):
        raise ValueError("not a PNG file (bad signature)")
    view = memoryview(data)
    pos, n = len(_PNG_SIGNATURE), len(data)
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


def _image_file_problem(path: Path, width: int | None, height: int | None, png_only: bool) -> str | None:
    """The reason ``path`` is not a usable image of ``width x height``, or None when it is."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    if data.startswith(_PNG_SIGNATURE):
        try:
            w, h = check_png(data, None if width is None or height is None else (width, height))
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


def _decode_image(path: Path, width: int | None, height: int | None, png_only: bool) -> np.ndarray:
    """Read and decode an image file; ``ValueError(reason)`` when unreadable, corrupt or mis-sized.

    The one place that hands image bytes to OpenCV: a PNG passes :func:`check_png` first.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    if data.startswith(_PNG_SIGNATURE):
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


def _path_problem(cell: str) -> str | None:
    """Why a mask/image cell is not an acceptable relative path (lexical checks only), or None."""
    bad = [c for c in cell if ord(c) < 32 or ord(c) == 127]
    if bad:
        return f"path {_shown(cell)} contains a control character ({bad[0]!r}); paths must be plain text"
    if len(cell) > MAX_PATH_CHARS:
        return f"path {_shown(cell)} has {len(cell)} characters (at most {MAX_PATH_CHARS} accepted)"
    try:
        too_long = [p for p in cell.split("/") if len(p.encode("utf-8")) > 255]
    except UnicodeEncodeError:
        return f"path {_shown(cell)} is not valid Unicode text"
    if too_long:
        return f"path {_shown(cell)} has a component of {len(too_long[0].encode())} bytes (at most 255 accepted)"
    if "\\" in cell:
        return f"path {_shown(cell)} contains a backslash; use '/' as the separator"
    win = PureWindowsPath(cell)
    if PurePosixPath(cell).is_absolute() or win.is_absolute() or win.drive:
        return f"path {_shown(cell)} is absolute; paths must be relative to the run directory"
    if ".." in PurePosixPath(cell).parts:
        return f"path {_shown(cell)} contains '..'; paths must stay inside the run directory"
    return None


def _shown(cell: str, limit: int = 80) -> str:
    """``repr`` of a cell, shortened to ``limit`` characters (a 4000-character path is not echoed whole)."""
    text = repr(cell)
    return text if len(text) <= limit else f"{text[: limit - 20]}...{text[-12:]} ({len(cell)} characters)"


def _resolve_inside(root_resolved: Path, cell: str) -> tuple[Path | None, str | None]:
    """``(resolved file, None)`` when ``cell`` names an existing file inside the run, else ``(None, why)``."""
    reason = _path_problem(cell)
    if reason is not None:
        return None, reason
    try:
        target = (root_resolved / cell).resolve()
        if not target.is_relative_to(root_resolved):
            return None, f"path {_shown(cell)} resolves to {target}, outside the run directory (symlink)"
        if not target.is_file():
            return None, f"no such file: {root_resolved / cell}"
    except (OSError, ValueError, RuntimeError) as exc:  # ELOOP, ENAMETOOLONG, ... from the file system
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        return None, f"path {_shown(cell)} cannot be used: {why}"
    return target, None


# --------------------------------------------------------------------------------------------
# The recording
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Recording:
    """A validated recorded run: its directory, ``recording.json`` and the rows of ``frames.csv``."""

    root: Path
    """The run directory (mask/image paths are relative to it)."""
    info: RecordingInfo
    """The contents of recording.json."""
    frames: tuple[FrameRecord, ...]
    """The rows of frames.csv in file order (frame strictly increasing)."""
    _row_by_frame: dict[int, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "_row_by_frame", {f.frame: i + 1 for i, f in enumerate(self.frames)})

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[FrameRecord]:
        return iter(self.frames)

    @property
    def has_ground_truth(self) -> bool:
        """True when at least one frame has a ground-truth pose."""
        return any(f.cam_T_needle_gt is not None for f in self.frames)

    @property
    def csv_path(self) -> Path:
        """The run's ``frames.csv``."""
        return self.root / FRAMES_CSV

    def row_of(self, rec: FrameRecord) -> int | None:
        """The 1-based data row of ``rec`` in frames.csv (None if its frame is not in this run)."""
        return self._row_by_frame.get(int(rec.frame))

    def mask_path(self, rec: FrameRecord) -> Path | None:
        """Absolute-or-root-relative path of the frame's mask PNG, None when it has none."""
        return None if rec.mask is None else self.root / rec.mask

    def image_path(self, rec: FrameRecord) -> Path | None:
        """Path of the frame's camera image, None when it has none."""
        return None if rec.image is None else self.root / rec.image

    def _load(self, rec: FrameRecord, column: str, png_only: bool) -> np.ndarray | None:
        rel = rec.mask if column == "mask" else rec.image
        if rel is None:
            return None
        row = self.row_of(rec)
        where = f"(frame {rec.frame})"
        reason = _path_problem(rel)
        if reason is None:
            try:
                root = self.root.resolve()
                target = (root / rel).resolve()
                if not target.is_relative_to(root):
                    reason = f"path {_shown(rel)} resolves to {target}, outside the run directory (symlink)"
            except (OSError, ValueError, RuntimeError) as exc:
                reason = f"path {_shown(rel)} cannot be used: {exc}"
        if reason is not None:
            raise InputError(f"{reason} {where}", file=self.csv_path, row=row, column=column)
        cam = self.info.camera
        try:
            return _decode_image(self.root / rel, cam.width, cam.height, png_only)
        except ValueError as exc:
            msg = f"{column} file {exc} {where}"
            raise InputError(msg, file=self.csv_path, row=row, column=column) from None

    def load_mask(self, rec: FrameRecord) -> np.ndarray | None:
        """The frame's segmentation as a boolean ``(height, width)`` array (True = needle backbone).

        A pixel is True where the PNG is nonzero; for colour PNGs, where any colour channel is
        nonzero (an alpha channel is ignored). None when the frame has no mask. An unreadable,
        corrupt or wrongly sized PNG raises :class:`InputError` naming frames.csv, the row,
        the ``mask`` column and the PNG file.
        """
        img = self._load(rec, "mask", png_only=True)
        if img is None:
            return None
        if img.ndim == 3:
            channels = img.shape[2]
            img = img[..., :1] if channels == 2 else img[..., : min(channels, 3)]
            return np.any(img != 0, axis=2)
        return img != 0

    def load_image(self, rec: FrameRecord) -> np.ndarray | None:
        """The frame's camera image as OpenCV decodes it, unchanged: ``(H, W)`` or ``(H, W, 3|4)`` BGR(A).

        None when the frame has no image; errors as in :meth:`load_mask`.
        """
        return self._load(rec, "image", png_only=False)


# --------------------------------------------------------------------------------------------
# Reading and validating
# --------------------------------------------------------------------------------------------

_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_INTEGER = re.compile(r"\d+")

_KNOWN_KEYS = ("format", "version", "name", "frame_rate_hz", "camera", "needle")
_CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")
_NEEDLE_KEYS = ("radius_m", "tail_angle_rad", "tip_angle_rad", "grasp_angle_rad", "wire_diameter_m")


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _json_shown(v: Any, limit: int = 60) -> str:
    """A JSON value as text for an error message, shortened to ``limit`` characters."""
    text = json.dumps(v)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _pixel_bounds(side_px: int) -> tuple[float, float]:
    """Accepted range of a pixel coordinate along an image side of ``side_px`` pixels."""
    return (-PIXEL_RANGE_FACTOR * side_px, (PIXEL_RANGE_FACTOR + 1) * side_px)


def _parse_info(json_path: Path, errors: list[InputError]) -> RecordingInfo | None:
    """Validate ``recording.json``; append every problem to ``errors``; the info when there were none."""
    n_before = len(errors)

    def err(msg: str, key: str | None = None) -> None:
        errors.append(InputError(msg, file=json_path, column=key))

    try:
        doc = load_json(json_path, missing="file not found (a run needs recording.json)")
    except InputError as exc:
        errors.append(exc)
        return None
    if not isinstance(doc, dict):
        err(f"the top level must be a JSON object, got {type(doc).__name__}")
        return None

    def get(obj: dict, key: str, path: str) -> Any:
        if key not in obj:
            err("missing required key", path)
            return None
        return obj[key]

    def number(obj: dict, key: str, path: str, positive: bool = False,
               bounds: tuple[float, float] | None = None) -> float | None:
        v = get(obj, key, path)
        if v is None and key not in obj:
            return None
        if not _is_number(v):
            err(f"must be a number, got {_json_shown(v)}", path)
            return None
        if not math.isfinite(v):
            err(f"must be finite, got {v}", path)
            return None
        if positive and v <= 0:
            err(f"must be > 0, got {v}", path)
            return None
        if bounds is not None and not bounds[0] <= v <= bounds[1]:
            err(f"out of range: {v:g} (accepted {bounds[0]:g} .. {bounds[1]:g})", path)
            return None
        return float(v)

    def positive_int(obj: dict, key: str, path: str) -> int | None:
        v = get(obj, key, path)
        if v is None and key not in obj:
            return None
        if not isinstance(v, int) or isinstance(v, bool):
            err(f"must be an integer, got {_json_shown(v)}", path)
            return None
        if v <= 0 or v > MAX_IMAGE_SIDE_PX:
            err(f"must be in 1 .. {MAX_IMAGE_SIDE_PX}, got {v}", path)
            return None
        return v

    fmt = get(doc, "format", "format")
    if "format" in doc and fmt != FORMAT_NAME:
        err(f"must be {FORMAT_NAME!r}, got {_json_shown(fmt)}", "format")
    version = get(doc, "version", "version")
    if "version" in doc:
        if not isinstance(version, int) or isinstance(version, bool):
            err(f"must be the integer {FORMAT_VERSION}, got {_json_shown(version)}", "version")
        elif version != FORMAT_VERSION:
            err(f"unsupported version {version} (this reader knows version {FORMAT_VERSION})", "version")
    name = get(doc, "name", "name")
    if "name" in doc and (not isinstance(name, str) or not name.strip()):
        err(f"must be a non-empty string, got {_json_shown(name)}", "name")
    rate = number(doc, "frame_rate_hz", "frame_rate_hz", positive=True, bounds=(0.0, MAX_FRAME_RATE_HZ))

    cam_vals: dict[str, Any] = {}
    cam = get(doc, "camera", "camera")
    if "camera" in doc and not isinstance(cam, dict):
        err(f"must be a JSON object, got {_json_shown(cam)}", "camera")
    elif isinstance(cam, dict):
        cam_vals["width"] = positive_int(cam, "width", "camera.width")
        cam_vals["height"] = positive_int(cam, "height", "camera.height")
        for key in ("fx", "fy"):
            cam_vals[key] = number(cam, key, f"camera.{key}", positive=True, bounds=(0.0, MAX_FOCAL_PX))
        for key, side in (("cx", "width"), ("cy", "height")):
            n_px = cam_vals[side] if cam_vals[side] is not None else MAX_IMAGE_SIDE_PX
            cam_vals[key] = number(cam, key, f"camera.{key}", bounds=_pixel_bounds(n_px))
        dist = get(cam, "distortion", "camera.distortion")
        if "distortion" in cam:
            if not isinstance(dist, list) or not all(_is_number(c) for c in dist):
                err(f"must be a list of numbers, got {_json_shown(dist)}", "camera.distortion")
            elif len(dist) not in (4, 5, 8, 12, 14):
                err(f"must have 4, 5, 8, 12 or 14 OpenCV coefficients, got {len(dist)}", "camera.distortion")
            elif not all(math.isfinite(c) for c in dist):
                err("contains NaN or infinite values", "camera.distortion")
            elif not all(abs(c) <= MAX_ABS_DISTORTION for c in dist):
                err(f"has a coefficient beyond ±{MAX_ABS_DISTORTION:g}", "camera.distortion")
            else:
                cam_vals["distortion"] = tuple(float(c) for c in dist)

    needle_vals: dict[str, Any] = {}
    needle = get(doc, "needle", "needle")
    if "needle" in doc and not isinstance(needle, dict):
        err(f"must be a JSON object, got {_json_shown(needle)}", "needle")
    elif isinstance(needle, dict):
        for key in _NEEDLE_KEYS:
            positive = key in ("radius_m", "wire_diameter_m")
            bounds = (0.0, MAX_NEEDLE_M) if positive else (-MAX_ABS_ANGLE_RAD, MAX_ABS_ANGLE_RAD)
            needle_vals[key] = number(needle, key, f"needle.{key}", positive=positive, bounds=bounds)

    if len(errors) > n_before:
        return None
    try:
        camera = PinholeCamera(**cam_vals)
    except ValueError as exc:
        err(str(exc), "camera")
        return None
    try:
        needle_model = NeedleModel(**needle_vals)
    except ValueError as exc:
        err(str(exc), "needle")
        return None
    extra = {k: v for k, v in doc.items() if k not in _KNOWN_KEYS}
    return RecordingInfo(name=name, frame_rate_hz=rate, camera=camera, needle=needle_model, extra=extra)


class _RowContext:
    """Error reporting for one frames.csv row."""

    def __init__(self, csv_path: Path, row: int, line: int, errors: list[InputError]) -> None:
        self.csv_path, self.row, self.line, self.errors = csv_path, row, line, errors
        self.frame: int | None = None
        self.failed = False

    def err(self, msg: str, column: str | None) -> None:
        line = f"file line {self.line}"
        where = f"frame {self.frame}, {line}" if self.frame is not None else line
        self.errors.append(InputError(f"{msg} ({where})", file=self.csv_path, row=self.row, column=column))
        self.failed = True

    def number(self, cell: str, column: str, bounds: tuple[float, float] | None = None) -> float | None:
        if _DECIMAL.fullmatch(cell):
            x = float(cell)
            if not math.isfinite(x):
                self.err(f"number {_shown(cell, 40)} overflows to infinity", column)
                return None
            if bounds is not None and not bounds[0] <= x <= bounds[1]:
                self.err(f"out of range: {x:g} (accepted {bounds[0]:g} .. {bounds[1]:g})", column)
                return None
            return x
        if _NONFINITE.fullmatch(cell):
            self.err(f"NaN or infinite value {_shown(cell, 40)}; leave the cell empty when not observed", column)
        else:
            self.err(f"not a number: {_shown(cell, 40)}", column)
        return None


def _parse_pose(ctx: _RowContext, cols: tuple[str, ...], values: list[float]) -> np.ndarray | None:
    q = np.asarray(values[3:7], dtype=float)
    # components clipped to ±2 (a unit quaternion's are within ±1): huge cells cannot overflow
    norm = float(np.sqrt(np.sum(np.square(np.clip(q, -2.0, 2.0)))))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        ctx.err(
            f"quaternion ({', '.join(cols[3:7])}) has norm {norm:.6g}{'+' if norm >= 2 else ''}; "
            f"it must be 1 within {QUAT_NORM_TOL:g}",
            cols[3],
        )
        return None
    return pose_from_xyz_quat(np.asarray(values[:3], dtype=float), q / norm)


def _parse_frames(
    root: Path, csv_path: Path, info: RecordingInfo | None, errors: list[InputError]
) -> list[FrameRecord] | None:
    """Validate ``frames.csv`` (and the files it names); append every problem to ``errors``."""
    n_before = len(errors)
    try:
        fh = open(csv_path, encoding="utf-8-sig", newline="")
    except FileNotFoundError:
        errors.append(InputError("file not found (a run needs frames.csv)", file=csv_path))
        return None
    except OSError as exc:
        errors.append(InputError(f"cannot read: {exc}", file=csv_path))
        return None
    width = info.camera.width if info is not None else None
    height = info.camera.height if info is not None else None
    try:
        root_resolved = root.resolve()
    except OSError:
        root_resolved = root.absolute()
    file_checked: dict[tuple[Path, bool], str | None] = {}
    records: list[FrameRecord] = []
    with fh:
        reader = csv.reader(fh)
        header: list[str] | None = None
        col: dict[str, int] = {}
        groups: dict[str, tuple[str, ...]] = {}
        prev_frame: tuple[int, int] | None = None
        data_row = 0
        try:
            for cells in reader:
                if not cells or all(not c.strip() for c in cells):
                    continue
                if header is None:
                    header = [c.strip() for c in cells]
                    for i, name in enumerate(header):
                        if name in col:
                            errors.append(
                                InputError(f"header: duplicate column {_shown(name)}", file=csv_path, column=name)
                            )
                        else:
                            col[name] = i
                    for gname, gcols in COLUMN_GROUPS.items():
                        missing = [c for c in gcols if c not in col]
                        if gname == "required" or (missing and len(missing) < len(gcols)):
                            for c in missing:
                                errors.append(
                                    InputError(
                                        f"header: required column missing (group {gname!r} needs "
                                        f"{', '.join(gcols)})",
                                        file=csv_path,
                                        column=c,
                                    )
                                )
                        if not missing:
                            groups[gname] = gcols
                    continue
                data_row += 1
                ctx = _RowContext(csv_path, data_row, reader.line_num, errors)
                if len(cells) != len(header):
                    ctx.err(f"has {len(cells)} cells but the header has {len(header)}", None)
                    continue
                cell = {name: cells[i].strip() for name, i in col.items()}
                rec = _parse_row(ctx, cell, groups, root_resolved, width, height, file_checked)
                if ctx.frame is not None:
                    if prev_frame is not None and ctx.frame <= prev_frame[0]:
                        ctx.err(
                            f"frame {ctx.frame} is not greater than frame {prev_frame[0]} of row "
                            f"{prev_frame[1]}; frames must be strictly increasing",
                            "frame",
                        )
                    prev_frame = (ctx.frame, data_row)
                if rec is not None and not ctx.failed:
                    records.append(rec)
        except csv.Error as exc:
            errors.append(InputError(f"malformed CSV at line {reader.line_num}: {exc}", file=csv_path))
        except UnicodeDecodeError as exc:
            errors.append(InputError(f"not UTF-8 text: {exc}", file=csv_path))
        if header is None and len(errors) == n_before:
            errors.append(InputError("empty file: no header row", file=csv_path))
    if len(errors) > n_before:
        return None
    return records


def _cell_bounds(column: str, width: int | None, height: int | None) -> tuple[float, float] | None:
    """Accepted range of a numeric frames.csv cell (None: checked otherwise, e.g. quaternion norm)."""
    if column.endswith("_u_px"):
        return _pixel_bounds(width if width is not None else MAX_IMAGE_SIDE_PX)
    if column.endswith("_v_px"):
        return _pixel_bounds(height if height is not None else MAX_IMAGE_SIDE_PX)
    if column.endswith("_m"):
        return (-MAX_ABS_METRES, MAX_ABS_METRES)
    return None


def _parse_row(
    ctx: _RowContext,
    cell: dict[str, str],
    groups: dict[str, tuple[str, ...]],
    root_resolved: Path,
    width: int | None,
    height: int | None,
    file_checked: dict[tuple[Path, bool], str | None],
) -> FrameRecord | None:
    """One data row -> FrameRecord (None when a required cell is unusable); problems go to ``ctx``."""
    frame: int | None = None
    t_s: float | None = None
    if "frame" in cell:
        c = cell["frame"]
        if c == "":
            ctx.err("empty; every row needs a frame index", "frame")
        elif _INTEGER.fullmatch(c):
            if len(c.lstrip("0")) > 19 or int(c) > MAX_FRAME_INDEX:
                ctx.err(f"frame index {_shown(c, 40)} is beyond int64 (at most {MAX_FRAME_INDEX})", "frame")
            else:
                frame = int(c)
                ctx.frame = frame
        else:
            ctx.err(f"not a non-negative integer: {_shown(c, 40)}", "frame")
    if "t_s" in cell:
        c = cell["t_s"]
        if c == "":
            ctx.err("empty; every row needs a time stamp", "t_s")
        else:
            t_s = ctx.number(c, "t_s", (-MAX_ABS_TIME_S, MAX_ABS_TIME_S))

    values: dict[str, Any] = {}
    for gname, gcols in groups.items():
        if gname == "required":
            continue
        present = [c for c in gcols if cell[c] != ""]
        if not present:
            continue
        if len(present) < len(gcols):
            empty = [c for c in gcols if cell[c] == ""]
            ctx.err(
                f"empty while {', '.join(present)} {'is' if len(present) == 1 else 'are'} filled; "
                f"the cells of group {gname!r} are all present or all empty (empty: {', '.join(empty)})",
                empty[0],
            )
            continue
        if gname in ("tip", "tail", "kinematics", "ground_truth"):
            nums = [ctx.number(cell[c], c, _cell_bounds(c, width, height)) for c in gcols]
            if any(v is None for v in nums):
                continue
            if gname in ("tip", "tail"):
                values[gname] = np.asarray(nums, dtype=float)
            else:
                pose = _parse_pose(ctx, gcols, nums)
                if pose is not None:
                    values[gname] = pose
        elif gname in ("mask", "image"):
            rel = cell[gname]
            target, reason = _resolve_inside(root_resolved, rel)
            if reason is None:
                key = (target, gname == "mask")
                if key not in file_checked:
                    file_checked[key] = _image_file_problem(target, width, height, png_only=gname == "mask")
                reason = file_checked[key]
                if reason is not None:
                    reason = f"{gname} file {reason}"
            if reason is not None:
                ctx.err(reason, gname)
            else:
                values[gname] = rel
        elif gname == "occlusion":
            label = cell["occlusion"]
            if label not in OCCLUSION_LABELS:
                allowed = ", ".join(OCCLUSION_LABELS)
                ctx.err(f"unknown occlusion label {_shown(label, 40)}; expected one of {allowed}", gname)
            else:
                values[gname] = label
    if frame is None or t_s is None:
        return None
    return FrameRecord(
        frame=frame,
        t_s=t_s,
        tip_px=values.get("tip"),
        tail_px=values.get("tail"),
        mask=values.get("mask"),
        cam_T_grasper=values.get("kinematics"),
        cam_T_needle_gt=values.get("ground_truth"),
        image=values.get("image"),
        occlusion=values.get("occlusion"),
    )


def validate_run(path: str | Path) -> tuple[Recording | None, list[InputError]]:
    """Check a run directory against format v1 and collect **every** problem.

    Returns ``(recording, [])`` for a valid run and ``(None, errors)`` otherwise, errors in
    file order (recording.json first, then frames.csv row by row).
    """
    root = Path(path)
    errors: list[InputError] = []
    try:
        is_dir = root.is_dir()
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        errors.append(InputError(f"cannot be used as a run directory: {why}", file=root))
        return None, errors
    if not is_dir:
        errors.append(InputError("not a directory (a run is a directory with recording.json and frames.csv)",
                                 file=root))
        return None, errors
    info = _parse_info(root / RECORDING_JSON, errors)
    frames = _parse_frames(root, root / FRAMES_CSV, info, errors)
    if errors or info is None or frames is None:
        return None, errors
    return Recording(root=root, info=info, frames=tuple(frames)), errors


def read_recording(path: str | Path) -> Recording:
    """Read and validate a run directory; raise the first :class:`InputError` found."""
    recording, errors = validate_run(path)
    if errors:
        raise errors[0]
    assert recording is not None
    return recording


def summarize_recording(rec: Recording) -> str:
    """A short human-readable summary: name, frames, duration, rates, and what each frame carries."""
    info, frames = rec.info, rec.frames
    n = len(frames)
    cam = info.camera
    lines = [f"run {info.name!r} ({rec.root})"]
    if n == 0:
        lines.append("  frames       0")
    else:
        duration = frames[-1].t_s - frames[0].t_s
        measured = f", {(n - 1) / duration:.3f} Hz measured" if n > 1 and duration > 0 else ""
        lines.append(
            f"  frames       {n} (index {frames[0].frame}..{frames[-1].frame}), duration {duration:.3f} s, "
            f"{info.frame_rate_hz:g} Hz declared{measured}"
        )
    lines.append(
        f"  camera       {cam.width}x{cam.height} px, fx {cam.fx:g}, fy {cam.fy:g}, "
        f"distortion {'yes' if cam.has_distortion else 'none'}"
    )
    lines.append(
        f"  needle       radius {info.needle.radius_m * 1e3:g} mm, arc {info.needle.tail_angle_rad:.4g}.."
        f"{info.needle.tip_angle_rad:.4g} rad, grasp at {info.needle.grasp_angle_rad:.4g} rad"
    )

    def share(count: int) -> str:
        return f"{count:6d}  ({100.0 * count / n:5.1f} %)" if n else f"{count:6d}"

    lines.append(f"  tip          {share(sum(f.tip_px is not None for f in frames))}")
    lines.append(f"  tail         {share(sum(f.tail_px is not None for f in frames))}")
    lines.append(f"  mask         {share(sum(f.mask is not None for f in frames))}")
    lines.append(f"  kinematics   {share(sum(f.cam_T_grasper is not None for f in frames))}")
    lines.append(f"  ground truth {share(sum(f.cam_T_needle_gt is not None for f in frames))}")
    lines.append(f"  image        {share(sum(f.image is not None for f in frames))}")
    occ = Counter(f.occlusion for f in frames)
    occ_text = ", ".join(f"{label} {occ.get(label, 0)}" for label in OCCLUSION_LABELS)
    lines.append(f"  occlusion    {occ_text}, unlabelled {occ.get(None, 0)}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _num_cell(x: float) -> str:
    """Shortest text that parses back to exactly the same float (Python's repr)."""
    return repr(float(x))


def _check_pose(name: str, T: Any) -> np.ndarray:
    a = np.asarray(T, dtype=float)
    if a.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite values")
    R = a[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} rotation block is not a proper rotation (R^T R = I, det R = +1)")
    if np.max(np.abs(a[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > 0:
        raise ValueError(f"{name} last row must be [0, 0, 0, 1]")
    return a


def _pose_cells(T: np.ndarray) -> list[str]:
    """``x y z qw qx qy qz`` cells of a pose (quaternion with w >= 0)."""
    xyz, q = xyz_quat_from_pose(T)
    return [_num_cell(v) for v in xyz] + [_num_cell(v) for v in q]


def _row_cells(rec: FrameRecord) -> dict[str, str]:
    """The frames.csv cells of ``rec`` (validating it; ``ValueError`` on bad values)."""
    frame = rec.frame
    if isinstance(frame, bool) or not isinstance(frame, int | np.integer) or frame < 0:
        raise ValueError(f"FrameRecord.frame must be a non-negative integer, got {frame!r}")
    if not math.isfinite(float(rec.t_s)):
        raise ValueError(f"frame {frame}: t_s must be finite, got {rec.t_s!r}")
    cells = {c: "" for c in KNOWN_COLUMNS}
    cells["frame"] = str(int(frame))
    cells["t_s"] = _num_cell(rec.t_s)
    for name, cols in (("tip_px", COLUMN_GROUPS["tip"]), ("tail_px", COLUMN_GROUPS["tail"])):
        v = getattr(rec, name)
        if v is not None:
            a = np.asarray(v, dtype=float)
            if a.shape != (2,) or not np.all(np.isfinite(a)):
                raise ValueError(f"frame {frame}: {name} must be a finite (2,) array, got {a!r}")
            cells.update(zip(cols, (_num_cell(x) for x in a), strict=True))
    for name, cols in (("cam_T_grasper", COLUMN_GROUPS["kinematics"]),
                       ("cam_T_needle_gt", COLUMN_GROUPS["ground_truth"])):
        v = getattr(rec, name)
        if v is not None:
            cells.update(zip(cols, _pose_cells(_check_pose(f"frame {frame}: {name}", v)), strict=True))
    for name in ("mask", "image"):
        v = getattr(rec, name)
        if v is not None:
            reason = _path_problem(str(v)) if str(v) else "empty path (use None for 'not observed')"
            if reason is not None:
                raise ValueError(f"frame {frame}: {name}: {reason}")
            cells[name] = str(v)
    if rec.occlusion is not None:
        if rec.occlusion not in OCCLUSION_LABELS:
            raise ValueError(
                f"frame {frame}: occlusion must be one of {OCCLUSION_LABELS}, got {rec.occlusion!r}"
            )
        cells["occlusion"] = rec.occlusion
    return cells


def _info_to_json(info: RecordingInfo) -> dict[str, Any]:
    cam, needle = info.camera, info.needle
    if cam.width is None or cam.height is None:
        raise ValueError("the camera must have a width and a height to be recorded")
    doc: dict[str, Any] = {k: v for k, v in info.extra.items() if k not in _KNOWN_KEYS}
    doc.update({
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": info.name,
        "frame_rate_hz": float(info.frame_rate_hz),
        "camera": {
            "width": int(cam.width), "height": int(cam.height),
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "distortion": [float(c) for c in (cam.distortion if cam.distortion is not None else (0.0,) * 5)],
        },
        "needle": {k: float(getattr(needle, k)) for k in _NEEDLE_KEYS},
    })
    return doc


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory and ``os.replace``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _mask_to_png_array(mask: Any, width: int, height: int, frame: int) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != (height, width):
        raise ValueError(
            f"frame {frame}: mask must have shape (height, width) = {(height, width)}, got {m.shape}"
        )
    return np.where(m != 0, 255, 0).astype(np.uint8)


def _image_to_png_array(image: Any, width: int, height: int, frame: int) -> np.ndarray:
    a = np.asarray(image)
    ok_shape = a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3, 4))
    if not ok_shape or a.shape[:2] != (height, width):
        raise ValueError(
            f"frame {frame}: image must have shape ({height}, {width}) or ({height}, {width}, 1|3|4), "
            f"got {a.shape}"
        )
    if a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frame {frame}: image must be uint8 or uint16, got {a.dtype}")
    return a


class RecordingWriter:
    """Incremental writer of a v1 run; a context manager.

    ``recording.json`` is written (atomically) when the writer is created, ``frames.csv``'s
    header at once, then one row per :meth:`add`, flushed as written, so a run stopped half-way
    leaves a valid run of the frames written so far. Floats are written with ``repr`` (shortest
    exact text), so scalars read back bit-identically; poses go through a unit quaternion
    (``w >= 0``) and read back within ~1e-16 of the matrix written. The header holds every
    column of this version; an empty cell means "not observed".
    """

    def __init__(self, run_dir: str | Path, info: RecordingInfo) -> None:
        self.run_dir = Path(run_dir)
        self.info = info
        doc = _info_to_json(info)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write_text(self.run_dir / RECORDING_JSON, json.dumps(doc, indent=2) + "\n")
        self._fh = open(self.run_dir / FRAMES_CSV, "w", encoding="utf-8", newline="")
        self._csv = csv.writer(self._fh, lineterminator="\n")
        self._csv.writerow(KNOWN_COLUMNS)
        self._fh.flush()
        self._last_frame: int | None = None
        self.frames_written = 0

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._fh.closed

    def add(
        self, frame: FrameRecord, mask: np.ndarray | None = None, image: np.ndarray | None = None
    ) -> FrameRecord:
        """Append one frame; returns the record as written (with ``mask``/``image`` paths set).

        ``mask`` (``(height, width)``, nonzero = backbone) is written as ``masks/NNNNNN.png``
        (0/255, 6-digit frame index) and ``image`` (``(height, width[, 1|3|4])`` uint8/uint16,
        OpenCV channel order) as ``images/NNNNNN.png``; the files are written before the row.
        Raises ``ValueError`` for a frame index not above the previous one or malformed values.
        """
        if self.closed:
            raise ValueError("RecordingWriter is closed")
        if self._last_frame is not None and int(frame.frame) <= self._last_frame:
            raise ValueError(f"frame {frame.frame} is not greater than the previous frame {self._last_frame}")
        width, height = int(self.info.camera.width), int(self.info.camera.height)
        cells = _row_cells(frame)  # validate before writing any file
        todo = (("mask", mask, _mask_to_png_array), ("image", image, _image_to_png_array))
        for name, array, convert in todo:
            if array is None:
                continue
            rel = f"{name}s/{int(frame.frame):06d}.png"
            png = convert(array, width, height, int(frame.frame))
            (self.run_dir / f"{name}s").mkdir(exist_ok=True)
            if not cv2.imwrite(str(self.run_dir / rel), png):
                raise OSError(f"cv2.imwrite failed for {self.run_dir / rel}")
            frame = replace(frame, **{name: rel})
            cells[name] = rel
        self._csv.writerow([cells[c] for c in KNOWN_COLUMNS])
        self._fh.flush()
        self._last_frame = int(frame.frame)
        self.frames_written += 1
        return frame

    def close(self) -> None:
        """Close frames.csv (idempotent)."""
        if not self._fh.closed:
            self._fh.close()


def write_recording(
    run_dir: str | Path,
    info: RecordingInfo,
    frames: Iterable[FrameRecord],
    masks: dict[int, np.ndarray] | None = None,
    images: dict[int, np.ndarray] | None = None,
) -> Path:
    """Write a whole run; ``masks``/``images`` map frame index -> array (written as PNGs). Returns run_dir."""
    frames = list(frames)
    masks = masks or {}
    images = images or {}
    indices = {int(f.frame) for f in frames}
    stray = sorted((set(masks) | set(images)) - indices)
    if stray:
        raise ValueError(f"masks/images given for frames not in the run: {stray[:10]}")
    with RecordingWriter(run_dir, info) as writer:
        for f in frames:
            writer.add(f, masks.get(int(f.frame)), images.get(int(f.frame)))
    return Path(run_dir)


def replace_ground_truth(run_dir: str | Path, gt_by_frame: dict[int, np.ndarray | None]) -> None:
    """Rewrite the ``gt_*`` cells of ``frames.csv``: ``gt_by_frame[frame]`` is the new ``cam_T_needle``.

    A frame mapped to None gets empty gt cells; frames not in the mapping keep theirs. Every
    other cell, including unknown extra columns, is kept as text, unchanged; missing gt columns
    are appended to the header. The file is replaced atomically (temporary file + ``os.replace``).
    Raises :class:`InputError` when frames.csv cannot be parsed far enough to find the rows, and
    ``ValueError`` for a frame that is not in the run or a malformed pose.
    """
    csv_path = Path(run_dir) / FRAMES_CSV
    gt_cols = COLUMN_GROUPS["ground_truth"]
    new_cells = {
        int(k): (None if v is None else _pose_cells(_check_pose(f"ground truth of frame {k}", v)))
        for k, v in gt_by_frame.items()
    }
    try:
        with open(csv_path, encoding="utf-8-sig", newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except FileNotFoundError:
        raise InputError("file not found (a run needs frames.csv)", file=csv_path) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read: {exc}", file=csv_path) from None
    if not rows:
        raise InputError("empty file: no header row", file=csv_path)
    header = [c.strip() for c in rows[0]]
    if "frame" not in header:
        raise InputError("header: required column missing", file=csv_path, column="frame")
    n_cols = len(header)
    for c in gt_cols:
        if c not in header:
            header.append(c)
    idx = {c: header.index(c) for c in header}
    body: list[list[str]] = []
    seen: set[int] = set()
    for r, cells in enumerate(rows[1:], start=1):
        if len(cells) != n_cols:
            raise InputError(f"has {len(cells)} cells but the header has {n_cols}", file=csv_path, row=r)
        cells = cells + [""] * (len(header) - n_cols)
        fcell = cells[idx["frame"]].strip()
        if not _INTEGER.fullmatch(fcell):
            raise InputError(f"not a non-negative integer: {_shown(fcell, 40)}", file=csv_path, row=r, column="frame")
        frame = int(fcell)
        seen.add(frame)
        if frame in new_cells:
            values = new_cells[frame] or [""] * len(gt_cols)
            for c, v in zip(gt_cols, values, strict=True):
                cells[idx[c]] = v
        body.append(cells)
    unknown = sorted(set(new_cells) - seen)
    if unknown:
        raise ValueError(f"ground truth given for frames not in {csv_path}: {unknown[:10]}")
    fd, tmp = tempfile.mkstemp(dir=csv_path.parent, prefix=f".{csv_path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as out:
            w = csv.writer(out, lineterminator="\n")
            w.writerow(header)
            w.writerows(body)
        os.replace(tmp, csv_path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
