"""Validating a recorded run: ``recording.json`` and every row of ``frames.csv``, all problems collected.

Conventions of the error reports (fixed here, used by every check of a run):

* ``row`` is the **1-based data row** of ``frames.csv``: the header is not counted and
  fully blank lines are skipped, so row 1 is the first record. Every row message also says
  ``(frame F, file line L)`` with the frame index (when it parsed) and the physical file line,
  so the number cannot be mistaken for a frame index.
* ``column`` is the CSV column name, or the JSON key path (``"camera.fx"``) in
  ``recording.json``. Header problems carry no row and start with ``header:``.
* Problems with a mask or image file are reported against ``frames.csv`` (its row and the
  ``mask``/``image`` column) and the message names the PNG file.

"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from factors.geometry import NeedleModel, PinholeCamera, pose_from_xyz_quat
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.jsonfile import json_shown, load_json
from pinpoint_fg.io.recording.columns import differs_in_unit, near_miss_columns, unit_of
from pinpoint_fg.io.recording.png import image_file_problem
from pinpoint_fg.io.recording.schema import (
    COLUMN_GROUPS,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES_CSV,
    INFO_KEYS,
    INTEGER_CELL,
    MAX_ABS_ANGLE_RAD,
    MAX_ABS_DISTORTION,
    MAX_ABS_METRES,
    MAX_ABS_TIME_S,
    MAX_FOCAL_PX,
    MAX_FRAME_INDEX,
    MAX_FRAME_RATE_HZ,
    MAX_IMAGE_SIDE_PX,
    MAX_NEEDLE_M,
    MIN_FOCAL_PX,
    MIN_NEEDLE_M,
    NEEDLE_KEYS,
    OCCLUSION_LABELS,
    PIXEL_RANGE_FACTOR,
    QUAT_NORM_TOL,
    RECORDING_JSON,
    FrameRecord,
    Recording,
    RecordingInfo,
    gt_depth_problem,
    path_problem,
    shown,
)

_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _pixel_bounds(side_px: int) -> tuple[float, float]:
    """Accepted range of a pixel coordinate along an image side of ``side_px`` pixels."""
    return (-PIXEL_RANGE_FACTOR * side_px, (PIXEL_RANGE_FACTOR + 1) * side_px)


def _resolve_inside(root_resolved: Path, cell: str) -> tuple[Path | None, str | None]:
    """``(resolved file, None)`` when ``cell`` names an existing file inside the run, else ``(None, why)``."""
    reason = path_problem(cell)
    if reason is not None:
        return None, reason
    try:
        target = (root_resolved / cell).resolve()
        if not target.is_relative_to(root_resolved):
            return None, f"path {shown(cell)} resolves to {target}, outside the run directory (symlink)"
        if not target.is_file():
            if target.exists():  # a directory, FIFO or device is there: "no such file" sent users looking for it
                return None, f"not a regular file: {root_resolved / cell}"
            return None, f"no such file: {root_resolved / cell}"
    except (OSError, ValueError, RuntimeError) as exc:  # ELOOP, ENAMETOOLONG, ... from the file system
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        return None, f"path {shown(cell)} cannot be used: {why}"
    return target, None


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
            err(f"must be a number, got {json_shown(v)}", path)
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
            err(f"must be an integer, got {json_shown(v)}", path)
            return None
        if v <= 0 or v > MAX_IMAGE_SIDE_PX:
            err(f"must be in 1 .. {MAX_IMAGE_SIDE_PX}, got {v}", path)
            return None
        return v

    fmt = get(doc, "format", "format")
    if "format" in doc and fmt != FORMAT_NAME:
        err(f"must be {FORMAT_NAME!r}, got {json_shown(fmt)}", "format")
    version = get(doc, "version", "version")
    if "version" in doc:
        if not isinstance(version, int) or isinstance(version, bool):
            err(f"must be the integer {FORMAT_VERSION}, got {json_shown(version)}", "version")
        elif version != FORMAT_VERSION:
            err(f"unsupported version {version} (this reader knows version {FORMAT_VERSION})", "version")
    name = get(doc, "name", "name")
    if "name" in doc and (not isinstance(name, str) or not name.strip()):
        err(f"must be a non-empty string, got {json_shown(name)}", "name")
    rate = number(doc, "frame_rate_hz", "frame_rate_hz", positive=True, bounds=(0.0, MAX_FRAME_RATE_HZ))

    cam_vals: dict[str, Any] = {}
    cam = get(doc, "camera", "camera")
    if "camera" in doc and not isinstance(cam, dict):
        err(f"must be a JSON object, got {json_shown(cam)}", "camera")
    elif isinstance(cam, dict):
        cam_vals["width"] = positive_int(cam, "width", "camera.width")
        cam_vals["height"] = positive_int(cam, "height", "camera.height")
        for key in ("fx", "fy"):
            cam_vals[key] = number(cam, key, f"camera.{key}", positive=True, bounds=(MIN_FOCAL_PX, MAX_FOCAL_PX))
        for key, side in (("cx", "width"), ("cy", "height")):
            n_px = cam_vals[side] if cam_vals[side] is not None else MAX_IMAGE_SIDE_PX
            cam_vals[key] = number(cam, key, f"camera.{key}", bounds=_pixel_bounds(n_px))
        dist = get(cam, "distortion", "camera.distortion")
        if "distortion" in cam:
            if not isinstance(dist, list) or not all(_is_number(c) for c in dist):
                err(f"must be a list of numbers, got {json_shown(dist)}", "camera.distortion")
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
        err(f"must be a JSON object, got {json_shown(needle)}", "needle")
    elif isinstance(needle, dict):
        for key in NEEDLE_KEYS:
            positive = key in MIN_NEEDLE_M
            bounds = (MIN_NEEDLE_M[key], MAX_NEEDLE_M) if positive else (-MAX_ABS_ANGLE_RAD, MAX_ABS_ANGLE_RAD)
            needle_vals[key] = number(needle, key, f"needle.{key}", positive=positive, bounds=bounds)

    if len(errors) > n_before:
        return None
    try:
        camera = PinholeCamera(**cam_vals)
    except ValueError as exc:
        err(str(exc), "camera")
        return None
    bad_px = _not_undistortable(camera)
    if bad_px is not None:
        err(f"cannot be inverted at pixel ({bad_px[0]:g}, {bad_px[1]:g}) of the image (OpenCV's undistortion gives "
            "NaN or inf there): not a usable lens model", "camera.distortion")
        return None
    try:
        needle_model = NeedleModel(**needle_vals)
    except ValueError as exc:
        err(str(exc), "needle")
        return None
    extra = {k: v for k, v in doc.items() if k not in INFO_KEYS}
    return RecordingInfo(name=name, frame_rate_hz=rate, camera=camera, needle=needle_model, extra=extra)


#: Pixels per image side at which :func:`_not_undistortable` tries the lens model (a grid, corners included).
UNDISTORT_GRID = 17


def _not_undistortable(camera: PinholeCamera) -> tuple[float, float] | None:
    """The first pixel of a ``UNDISTORT_GRID`` x ``UNDISTORT_GRID`` grid over the image (corners included) that
    ``camera.undistort_px`` maps to NaN or inf, or None. Coefficients within the accepted bounds can still make
    the model's inverse blow up (a rational-model ``k6 = 1e6``: NaN at almost every pixel): every keypoint and mask
    pixel would then be NaN, so the lens model is refused where it is read, not frame by frame."""
    if not camera.has_distortion:
        return None
    u = np.linspace(0.0, camera.width - 1.0, UNDISTORT_GRID)
    v = np.linspace(0.0, camera.height - 1.0, UNDISTORT_GRID)
    grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    with np.errstate(all="ignore"):
        out = camera.undistort_px(grid)
    bad = ~np.isfinite(out).all(axis=1)
    return (float(grid[bad][0, 0]), float(grid[bad][0, 1])) if bad.any() else None


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
                self.err(f"number {shown(cell, 40)} overflows to infinity", column)
                return None
            if bounds is not None and not bounds[0] <= x <= bounds[1]:
                self.err(f"out of range: {x:g} (accepted {bounds[0]:g} .. {bounds[1]:g})", column)
                return None
            return x
        if _NONFINITE.fullmatch(cell):
            self.err(f"NaN or infinite value {shown(cell, 40)}; leave the cell empty when not observed", column)
        else:
            self.err(f"not a number: {shown(cell, 40)}", column)
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


def _look_alikes(header: list[str]) -> dict[str, list[str]]:
    """Each known column the header lacks -> the header's unknown columns that look like it (:mod:`.columns`)."""
    meant: dict[str, list[str]] = {}
    for u, k in near_miss_columns(header).items():
        meant.setdefault(k, []).append(u)
    return meant


def _look_alike_hint(column: str, alikes: list[str]) -> str:
    """The tail of a "required column missing" error naming ``alikes`` (up to three), and ``column``'s unit when one
    of them states another ("" for none)."""
    if not alikes:
        return ""
    unit = f" ({column} is in {unit_of(column)})" if any(differs_in_unit(u, column) for u in alikes) else ""
    return (f"; the header's {', '.join(shown(u, 40) for u in alikes[:3])} look{'s' if len(alikes) == 1 else ''} "
            f"like it{unit}")


def _parse_frames(
    root: Path, csv_path: Path, info: RecordingInfo | None, errors: list[InputError], inflate: bool = True,
    header_out: list[str] | None = None,
) -> list[FrameRecord] | None:
    """Validate ``frames.csv`` (and the files it names); append every problem to ``errors``.

    ``inflate``: PNGs' compressed data is inflated and checked too (:func:`validate_run`). ``header_out``, when
    given, receives the header's column names (stripped), unknown ones included."""
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
                    if header_out is not None:
                        header_out[:] = header
                    for i, name in enumerate(header):
                        if name in col:
                            errors.append(
                                InputError(f"header: duplicate column {shown(name)}", file=csv_path, column=name)
                            )
                        else:
                            col[name] = i
                    meant: dict[str, list[str]] | None = None  # known column -> the header's look-alikes of it
                    for gname, gcols in COLUMN_GROUPS.items():
                        missing = [c for c in gcols if c not in col]
                        if gname == "required" or (missing and len(missing) < len(gcols)):
                            for c in missing:
                                meant = _look_alikes(header) if meant is None else meant  # for an error only
                                like = _look_alike_hint(c, meant.get(c, []))
                                errors.append(
                                    InputError(
                                        f"header: required column missing (group {gname!r} needs "
                                        f"{', '.join(gcols)}){like}",
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
                rec = _parse_row(ctx, cell, groups, root_resolved, width, height, file_checked, inflate)
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
    inflate: bool = True,
) -> FrameRecord | None:
    """One data row -> FrameRecord (None when a required cell is unusable); problems go to ``ctx``.
    ``inflate``: as in :func:`validate_run`."""
    frame: int | None = None
    t_s: float | None = None
    if "frame" in cell:
        c = cell["frame"]
        if c == "":
            ctx.err("empty; every row needs a frame index", "frame")
        elif INTEGER_CELL.fullmatch(c):
            if len(c.lstrip("0")) > 19 or int(c) > MAX_FRAME_INDEX:
                ctx.err(f"frame index {shown(c, 40)} is beyond int64 (at most {MAX_FRAME_INDEX})", "frame")
            else:
                frame = int(c)
                ctx.frame = frame
        else:
            ctx.err(f"not a non-negative integer: {shown(c, 40)}", "frame")
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
                problem = gt_depth_problem(pose) if pose is not None and gname == "ground_truth" else None
                if problem is not None:
                    ctx.err(problem, "gt_z_m")
                elif pose is not None:
                    values[gname] = pose
        elif gname in ("mask", "image"):
            rel = cell[gname]
            target, reason = _resolve_inside(root_resolved, rel)
            if reason is None:
                key = (target, gname == "mask")
                if key not in file_checked:
                    file_checked[key] = image_file_problem(target, width, height, png_only=gname == "mask",
                                                           inflate=inflate)
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
                ctx.err(f"unknown occlusion label {shown(label, 40)}; expected one of {allowed}", gname)
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


def validate_run(path: str | Path, inflate: bool = True) -> tuple[Recording | None, list[InputError]]:
    """Check a run directory against format v1 and collect **every** problem.

    Returns ``(recording, [])`` for a valid run and ``(None, errors)`` otherwise, errors in
    file order (recording.json first, then frames.csv row by row).
    ``inflate`` False skips one check of PNG masks and images: their compressed data is not inflated (structure,
    every chunk's CRC and the size are still checked; :func:`~pinpoint_fg.io.recording.png.check_png`). For
    callers that decode every image they use through :func:`~pinpoint_fg.io.recording.png.decode_image`,
    which runs the full check first: a file whose data is corrupt under valid CRCs is then reported, located,
    when its frame is decoded rather than here.
    """
    errors: list[InputError] = []
    try:
        root = path_argument("run", path)
    except InputError as exc:
        return None, [exc]
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
    header: list[str] = []
    frames = _parse_frames(root, root / FRAMES_CSV, info, errors, inflate, header)
    if errors or info is None or frames is None:
        return None, errors
    return Recording(root=root, info=info, frames=tuple(frames), columns=tuple(header)), errors
