"""The v1 recording format (``shared/RECORDING_FORMAT.md``) as data: names, columns, bounds, the records.

A run is a directory with ``recording.json``, ``frames.csv`` and optional ``masks/`` and ``images/``;
:class:`Recording` is a validated run in memory (masks and images load on demand).

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
  recording.json ``width``/``height`` at most :data:`MAX_IMAGE_SIDE_PX`, ``fx``/``fy`` between
  :data:`MIN_FOCAL_PX` and :data:`MAX_FOCAL_PX`, ``cx``/``cy`` in the pixel range, ``|distortion| <=``
  :data:`MAX_ABS_DISTORTION`, ``frame_rate_hz <=`` :data:`MAX_FRAME_RATE_HZ`, needle lengths at
  least :data:`MIN_NEEDLE_M` (0.1 mm radius, 1 um wire) and at most :data:`MAX_NEEDLE_M` and angles
  within ``±``:data:`MAX_ABS_ANGLE_RAD`. recording.json is
  parsed by :func:`pinpoint_fg.io.jsonfile.loads_json` (bounded nesting, no huge integers).
* A quaternion is accepted when ``| ||q|| - 1 | <= QUAT_NORM_TOL`` (1 %) and normalised;
  anything farther from unit length is a typo or a swapped column, not rounding.
* Paths use ``/``, are relative, contain no ``..`` component, no backslash and no control
  character (NUL included), are at most :data:`MAX_PATH_CHARS` characters with components of at
  most 255 bytes, and must resolve (symlinks followed) inside the run directory.
* Masks must be PNG (lossless: a JPEG's noise would become backbone pixels). Images may be
  any format OpenCV decodes. Both must be exactly ``camera.width x camera.height``. PNGs are
  checked at validation time by :func:`~pinpoint_fg.io.recording.png.check_png`: structure (signature, IHDR,
  every chunk's CRC, an IDAT, an IEND) *and* the compressed data (the IDAT zlib stream is inflated in Python
  and must be complete, of exactly the size the header implies, with valid row filter bytes),
  which catches truncated, bit-flipped and corrupt-but-CRC-valid files before libpng sees them
  (libpng would print its complaint to stderr). Every decode goes through
  :func:`pinpoint_fg.io.recording.png.decode_image`, which runs the same check before ``cv2.imdecode``.
  ``track`` reads a run without inflating (``read_recording(run, inflate=False)``): it decodes every mask it
  uses that way, so data corrupt under valid CRCs is reported at its frame, with the frames before it written.
* Keypoints outside the image are not rejected (a detector's business, not the format's).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from factors.geometry import MIN_NEEDLE_RADIUS_M, MIN_WIRE_DIAMETER_M, NeedleModel, PinholeCamera
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.png import decode_image

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
def gt_depth_problem(cam_T_needle: np.ndarray) -> str | None:
    """Why a ground-truth pose is impossible for the camera it is recorded with, or None.

    Decision: ground truth (``cam_T_needle``) whose needle centre lies at or behind the camera's image plane
    (``gt_z_m <= 0``) is refused by the reader and the writer. The camera cannot have recorded such a needle, and
    scoring an estimate against it was a silently wrong number (one mirrored frame of eight turned a 0.2 mm mean
    error into 10.7 mm, exit 0). The rule is the centre's depth only: whether the needle points a frame's image
    shows are in front is ``calibrate``'s finer check. Estimates are not checked (a diverged tracker's pose is a
    result, scored as it is).
    """
    z = float(cam_T_needle[2, 3])
    if z > 0.0:
        return None
    return f"the needle centre is at depth {z:.6g} m, not in front of the camera (ground truth must be)"


#: Largest accepted |t_s|, seconds (~317 years: Unix time stamps fit).
MAX_ABS_TIME_S = 1e10
#: Largest accepted frame index (int64).
MAX_FRAME_INDEX = 2**63 - 1
#: Largest accepted image width/height, pixels.
MAX_IMAGE_SIDE_PX = 65535
#: Largest accepted focal length, pixels.
MAX_FOCAL_PX = 1e7
#: Smallest accepted focal length, pixels: below one pixel per radian a pinhole camera's field of view is within
#: a fraction of a degree of 180 deg. (``fx = 1e-300`` made every projected keypoint infinite.)
MIN_FOCAL_PX = 1.0
#: Largest accepted |distortion coefficient|.
MAX_ABS_DISTORTION = 1e6
#: Largest accepted frame rate, Hz.
MAX_FRAME_RATE_HZ = 1e6
#: Largest accepted needle radius / wire diameter, metres.
MAX_NEEDLE_M = 1.0
#: Smallest accepted needle radius / wire diameter, metres (:class:`factors.geometry.NeedleModel`'s floors).
MIN_NEEDLE_M = {"radius_m": MIN_NEEDLE_RADIUS_M, "wire_diameter_m": MIN_WIRE_DIAMETER_M}
#: Largest accepted |needle arc angle|, radians.
MAX_ABS_ANGLE_RAD = 100.0
#: Longest accepted mask/image path, characters.
MAX_PATH_CHARS = 1024
#: All frames.csv columns this version knows, in the order the writer emits them.
KNOWN_COLUMNS: tuple[str, ...] = tuple(c for cols in COLUMN_GROUPS.values() for c in cols)
RECORDING_JSON = "recording.json"
FRAMES_CSV = "frames.csv"
INFO_KEYS = ("format", "version", "name", "frame_rate_hz", "camera", "needle")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")
NEEDLE_KEYS = ("radius_m", "tail_angle_rad", "tip_angle_rad", "grasp_angle_rad", "wire_diameter_m")
INTEGER_CELL = re.compile(r"\d+", re.ASCII)  # ASCII: \d alone also matched "٤" (int() reads it)


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


def path_problem(cell: str) -> str | None:
    """Why a mask/image cell is not an acceptable relative path (lexical checks only), or None."""
    bad = [c for c in cell if ord(c) < 32 or ord(c) == 127]
    if bad:
        return f"path {shown(cell)} contains a control character ({bad[0]!r}); paths must be plain text"
    if len(cell) > MAX_PATH_CHARS:
        return f"path {shown(cell)} has {len(cell)} characters (at most {MAX_PATH_CHARS} accepted)"
    try:
        too_long = [p for p in cell.split("/") if len(p.encode("utf-8")) > 255]
    except UnicodeEncodeError:
        return f"path {shown(cell)} is not valid Unicode text"
    if too_long:
        return f"path {shown(cell)} has a component of {len(too_long[0].encode())} bytes (at most 255 accepted)"
    if "\\" in cell:
        return f"path {shown(cell)} contains a backslash; use '/' as the separator"
    win = PureWindowsPath(cell)
    if PurePosixPath(cell).is_absolute() or win.is_absolute() or win.drive:
        return f"path {shown(cell)} is absolute; paths must be relative to the run directory"
    if ".." in PurePosixPath(cell).parts:
        return f"path {shown(cell)} contains '..'; paths must stay inside the run directory"
    return None


def shown(cell: str, limit: int = 80) -> str:
    """``repr`` of a cell, shortened to ``limit`` characters (a 4000-character path is not echoed whole)."""
    text = repr(cell)
    return text if len(text) <= limit else f"{text[: limit - 20]}...{text[-12:]} ({len(cell)} characters)"


@dataclass(frozen=True, eq=False)
class Recording:
    """A validated recorded run: its directory, ``recording.json`` and the rows of ``frames.csv``."""

    root: Path
    """The run directory (mask/image paths are relative to it)."""
    info: RecordingInfo
    """The contents of recording.json."""
    frames: tuple[FrameRecord, ...]
    """The rows of frames.csv in file order (frame strictly increasing)."""
    columns: tuple[str, ...] = ()
    """The header of frames.csv as read (each name stripped), in file order, unknown columns included. Decision:
    kept so that an unknown column that looks like a misspelt known one can be named on a ``note:`` line
    (:func:`~pinpoint_fg.io.recording.reader.unknown_columns_note`); empty for a Recording built in memory."""
    _row_by_frame: dict[int, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "columns", tuple(self.columns))
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
        reason = path_problem(rel)
        if reason is None:
            try:
                root = self.root.resolve()
                target = (root / rel).resolve()
                if not target.is_relative_to(root):
                    reason = f"path {shown(rel)} resolves to {target}, outside the run directory (symlink)"
            except (OSError, ValueError, RuntimeError) as exc:
                reason = f"path {shown(rel)} cannot be used: {exc}"
        if reason is not None:
            raise InputError(f"{reason} {where}", file=self.csv_path, row=row, column=column)
        cam = self.info.camera
        try:
            return decode_image(self.root / rel, cam.width, cam.height, png_only)
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
