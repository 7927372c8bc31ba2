"""Writing a recorded run: :class:`RecordingWriter` (frame by frame), :func:`write_recording`, and
:func:`replace_ground_truth` (rewrites only the ``gt_*`` cells). Every file is written atomically; values
are checked before anything is written (``ValueError``), so a writer never produces a run the reader rejects.
"""

from __future__ import annotations

import csv
import json
import math
import tempfile
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from factors.geometry import xyz_quat_from_pose
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.atomic import atomic_write
from pinpoint_fg.io.recording.schema import (
    COLUMN_GROUPS,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES_CSV,
    INFO_KEYS,
    INTEGER_CELL,
    KNOWN_COLUMNS,
    MAX_ABS_METRES,
    MAX_ABS_TIME_S,
    NEEDLE_KEYS,
    OCCLUSION_LABELS,
    RECORDING_JSON,
    FrameRecord,
    RecordingInfo,
    gt_depth_problem,
    path_problem,
    shown,
)
from pinpoint_fg.io.recording.validator import _cell_bounds, _parse_info


def _num_cell(x: float) -> str:
    """Shortest text that parses back to exactly the same float (Python's repr)."""
    return repr(float(x))


def check_pose(name: str, T: Any) -> np.ndarray:
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


def _recordable_pose(name: str, T: Any, column: str) -> np.ndarray:
    """:func:`check_pose`, and within the format's :data:`MAX_ABS_METRES` of the camera (the reader refuses
    more: ``groundtruth`` with a 1e300 m mount rewrote a run into one that no longer validated)."""
    a = check_pose(name, T)
    if float(np.max(np.abs(a[:3, 3]))) > MAX_ABS_METRES:
        raise InputError(f"{name} lies beyond the format's {MAX_ABS_METRES:g} m of the camera", column=column)
    return a


def _recordable_gt(name: str, T: Any) -> np.ndarray:
    """:func:`_recordable_pose` of a ground-truth pose, in front of the camera
    (:func:`~pinpoint_fg.io.recording.schema.gt_depth_problem`): :class:`InputError` at ``gt_z_m`` otherwise."""
    a = _recordable_pose(name, T, "gt_x_m")
    problem = gt_depth_problem(a)
    if problem is not None:
        raise InputError(f"{name}: {problem}", column="gt_z_m")
    return a


def _pose_cells(T: np.ndarray) -> list[str]:
    """``x y z qw qx qy qz`` cells of a pose (quaternion with w >= 0)."""
    xyz, q = xyz_quat_from_pose(T)
    return [_num_cell(v) for v in xyz] + [_num_cell(v) for v in q]


def frame_cells(rec: FrameRecord, width: int | None, height: int | None) -> dict[str, str]:
    """The frames.csv cells of ``rec``, checked as the reader will check them (``ValueError``/:class:`InputError`
    naming the column): a keypoint outside the image's accepted range (``import-bag`` of a tip at 1e308 px) was
    written, exit 0, into a run the reader then refused."""
    cells = _row_cells(rec)
    for column, cell in cells.items():
        bounds = _cell_bounds(column, width, height) if cell else None
        if bounds is not None and not bounds[0] <= float(cell) <= bounds[1]:
            raise InputError(f"frame {rec.frame}: {float(cell):g} is outside the accepted {bounds[0]:g} .. "
                             f"{bounds[1]:g}", column=column)
    return cells


def _row_cells(rec: FrameRecord) -> dict[str, str]:
    """The frames.csv cells of ``rec`` (validating it; ``ValueError`` on bad values)."""
    frame = rec.frame
    if isinstance(frame, bool) or not isinstance(frame, int | np.integer) or frame < 0:
        raise ValueError(f"FrameRecord.frame must be a non-negative integer, got {frame!r}")
    if not math.isfinite(float(rec.t_s)):
        raise ValueError(f"frame {frame}: t_s must be finite, got {rec.t_s!r}")
    if abs(float(rec.t_s)) > MAX_ABS_TIME_S:  # the reader refuses it (an importer's --fps 1e-300 wrote 7e300)
        raise InputError(f"frame {frame}: {float(rec.t_s):g} s is beyond the format's +-{MAX_ABS_TIME_S:g} s",
                         column="t_s")
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
            where = f"frame {frame}: {name}"
            T = _recordable_gt(where, v) if name == "cam_T_needle_gt" else _recordable_pose(where, v, cols[0])
            cells.update(zip(cols, _pose_cells(T), strict=True))
    for name in ("mask", "image"):
        v = getattr(rec, name)
        if v is not None:
            reason = path_problem(str(v)) if str(v) else "empty path (use None for 'not observed')"
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
    doc: dict[str, Any] = {k: v for k, v in info.extra.items() if k not in INFO_KEYS}
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
        "needle": {k: float(getattr(needle, k)) for k in NEEDLE_KEYS},
    })
    return doc


def _check_info_doc(doc: dict[str, Any], target: Path) -> None:
    """Refuse a ``recording.json`` the reader would refuse, before anything is written: the reader's own
    checks on a temporary copy; the first problem as an :class:`InputError` naming ``target`` and the key.
    (Importers wrote ``--fps 1e308`` or a 1e308 m needle and exited 0 with a run that did not validate.)"""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / RECORDING_JSON
        path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        errors: list[InputError] = []
        _parse_info(path, errors)
    if errors:
        raise InputError(errors[0].reason, file=target, column=errors[0].column)


def check_recording_info(info: RecordingInfo, target: Path, camera_source: tuple[Path, str] | None = None) -> None:
    """:class:`InputError` naming ``target`` and the key when the reader would refuse ``info`` as recording.json
    (:func:`_check_info_doc`); nothing is written. Importers call it before they create their output, to name
    their own input instead (a bag's camera_info with fx = 1e300 left a half-written run behind):
    ``camera_source`` ``(file, field)`` is named instead of ``target`` for a ``camera.*`` value."""
    try:
        _check_info_doc(_info_to_json(info), target)
    except InputError as exc:
        if camera_source is None or not str(exc.column).startswith("camera"):
            raise
        raise InputError(f"{exc.reason} ({exc.column})", file=camera_source[0], column=camera_source[1]) from None


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory and ``os.replace``."""
    with atomic_write(path) as f:
        f.write(text)


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
        _check_info_doc(doc, self.run_dir / RECORDING_JSON)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.run_dir / RECORDING_JSON, json.dumps(doc, indent=2) + "\n")
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
        try:
            cells = frame_cells(frame, width, height)  # validate before writing any file
        except InputError as exc:
            raise InputError(exc.reason, file=self.run_dir / FRAMES_CSV, column=exc.column) from None
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
        int(k): (None if v is None else _pose_cells(_recordable_gt(f"ground truth of frame {k}", v)))
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
        if not INTEGER_CELL.fullmatch(fcell):
            raise InputError(f"not a non-negative integer: {shown(fcell, 40)}", file=csv_path, row=r, column="frame")
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
    with atomic_write(csv_path) as out:
        w = csv.writer(out, lineterminator="\n")
        w.writerow(header)
        w.writerows(body)
