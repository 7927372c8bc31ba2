"""Ground truth from the checkerboard (paper §V-A): ``pinpoint-fg groundtruth RUN --board-to-needle FILE``.

For every frame with a camera image the board is detected (:func:`pinpoint_fg.checkerboard.detect_board`)
and the needle pose follows from the fixed, measured mount transform::

    cam_T_needle = cam_T_board · board_T_needle

The run's ``gt_*`` columns are then rewritten with these poses
(:func:`pinpoint_fg.io.recording.replace_ground_truth`): a frame without an image or without
a detection gets empty gt cells, so afterwards every gt cell of the run is checkerboard-derived. When the
board is detected in no image at all (a wrong board size, images without the board) nothing is rewritten:
an :class:`~pinpoint_fg.errors.InputError` names the board of the ``board_to_needle`` file instead.
When the run already had ground truth (the simulator writes it), the checkerboard poses
are compared with it first and the comparison is part of the returned statistics.

The ``board_to_needle`` file (JSON, written by :func:`write_board_to_needle`)::

    {
      "format": "pinpoint-board-to-needle",       optional; if present exactly this
      "version": 1,                               optional; if present 1
      "board_T_needle": [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]],
      "board": {"squares_x": 5, "squares_y": 4, "square_m": 0.001, "margin_m": 0.001}   optional
    }

Instead of ``board_T_needle`` the pose may be given as ``"xyz_m": [x, y, z]`` and
``"quat_wxyz": [w, x, y, z]`` (Hamilton; normalised, rejected if its norm is off by more
than 1 %). Metres (each translation component at most 10 m, the recording format's bound); the
board frame is the one of :mod:`pinpoint_fg.checkerboard` (origin at the board centre, z into the
board). A rotation block within 1e-3 of orthonormal is accepted and projected onto SO(3)
(hand-typed matrices carry rounding); anything else is an :class:`~pinpoint_fg.errors.InputError`
naming the file and the key.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from factors.geometry import pose_from_xyz_quat
from factors.lie import se3_inverse, so3_log
from pinpoint_fg.checkerboard import DEFAULT_NEEDLE_T_BOARD, BoardSpec, detect_board
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.jsonfile import load_json
from pinpoint_fg.io.recording.schema import MAX_ABS_METRES, gt_depth_problem

BOARD_TO_NEEDLE_FORMAT = "pinpoint-board-to-needle"
BOARD_TO_NEEDLE_VERSION = 1

#: The simulator's mount, as the ``board_T_needle`` a ``board_to_needle`` file would hold.
DEFAULT_BOARD_T_NEEDLE: np.ndarray = se3_inverse(np.asarray(DEFAULT_NEEDLE_T_BOARD))
DEFAULT_BOARD_T_NEEDLE.setflags(write=False)

_ORTHO_TOL = 1e-3
_QUAT_NORM_TOL = 1e-2


def write_board_to_needle(
    path: str | Path, board_T_needle: np.ndarray = DEFAULT_BOARD_T_NEEDLE, spec: BoardSpec | None = None
) -> Path:
    """Write a ``board_to_needle`` JSON file (format in the module docstring); returns the path."""
    T = np.asarray(board_T_needle, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"board_T_needle must be a finite (4, 4) pose, got shape {T.shape}")
    spec = spec or BoardSpec()
    doc = {
        "format": BOARD_TO_NEEDLE_FORMAT,
        "version": BOARD_TO_NEEDLE_VERSION,
        "board_T_needle": [[float(x) for x in row] for row in T],
        "board": {
            "squares_x": int(spec.squares_x),
            "squares_y": int(spec.squares_y),
            "square_m": float(spec.square_m),
            "margin_m": float(spec.margin_m),
        },
    }
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return p


def _project_rotation(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def _number_array(doc: dict, key: str, shape: tuple[int, ...], file: Path) -> np.ndarray:
    value = doc[key]
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"must be numbers with shape {shape}, got {value!r}", file=file, column=key) from None
    if a.shape != shape:
        raise InputError(f"must have shape {shape}, got {a.shape}", file=file, column=key)
    if not np.all(np.isfinite(a)):
        raise InputError("contains NaN or infinite values", file=file, column=key)
    if any(isinstance(x, bool) for x in np.asarray(value, dtype=object).ravel()):
        raise InputError("must hold numbers, not booleans", file=file, column=key)
    return a


def read_board_to_needle(path: str | Path) -> tuple[np.ndarray, BoardSpec]:
    """Read and validate a ``board_to_needle`` file -> (``board_T_needle`` (4, 4), :class:`BoardSpec`)."""
    file = path_argument("path", path)  # None was pathlib's TypeError; "" read the current directory
    doc: Any = load_json(file, missing="file not found (the board-to-needle transform)")
    if not isinstance(doc, dict):
        raise InputError("must be a JSON object", file=file)
    if "format" in doc and doc["format"] != BOARD_TO_NEEDLE_FORMAT:
        raise InputError(f"must be {BOARD_TO_NEEDLE_FORMAT!r}, got {doc['format']!r}", file=file, column="format")
    if "version" in doc and doc["version"] != BOARD_TO_NEEDLE_VERSION:
        raise InputError(
            f"unsupported version {doc['version']!r} (this reader knows {BOARD_TO_NEEDLE_VERSION})",
            file=file,
            column="version",
        )
    has_matrix = "board_T_needle" in doc
    has_xyzq = "xyz_m" in doc or "quat_wxyz" in doc
    if has_matrix == has_xyzq:
        raise InputError(
            "give the pose either as 'board_T_needle' (4x4) or as 'xyz_m' + 'quat_wxyz', exactly one of them",
            file=file,
        )
    if has_matrix:
        T = _number_array(doc, "board_T_needle", (4, 4), file)
        if np.max(np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > 1e-9:
            raise InputError("last row must be [0, 0, 0, 1]", file=file, column="board_T_needle")
        R = T[:3, :3]
        if np.max(np.abs(R.T @ R - np.eye(3))) > _ORTHO_TOL or np.linalg.det(R) <= 0:
            raise InputError(
                "rotation block is not a proper rotation (R^T R = I, det R = +1)", file=file, column="board_T_needle"
            )
        T = T.copy()
        T[:3, :3] = _project_rotation(R)
    else:
        for key in ("xyz_m", "quat_wxyz"):
            if key not in doc:
                raise InputError("missing (needed together with the other of 'xyz_m', 'quat_wxyz')", file=file,
                                 column=key)
        xyz = _number_array(doc, "xyz_m", (3,), file)
        q = _number_array(doc, "quat_wxyz", (4,), file)
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise InputError(f"quaternion norm {norm:.6g} is not 1", file=file, column="quat_wxyz")
        T = pose_from_xyz_quat(xyz, q / norm)
    offset_m = float(np.max(np.abs(T[:3, 3])))
    if offset_m > MAX_ABS_METRES:
        raise InputError(f"translation {offset_m:.6g} m is beyond {MAX_ABS_METRES:g} m (the mount is a few "
                         "millimetres; it would write gt_* cells the recording format refuses)", file=file,
                         column="board_T_needle" if has_matrix else "xyz_m")
    spec = BoardSpec()
    if "board" in doc:
        b = doc["board"]
        if not isinstance(b, dict):
            raise InputError("must be an object", file=file, column="board")
        allowed = {"squares_x", "squares_y", "square_m", "margin_m"}
        kwargs = {}
        for k, v in b.items():
            if k not in allowed:
                continue  # forward compatible: unknown keys are ignored
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise InputError(f"must be a number, got {v!r}", file=file, column=f"board.{k}")
            kwargs[k] = v
        try:
            spec = BoardSpec(**kwargs)
        except ValueError as exc:
            raise InputError(str(exc), file=file, column="board") from None
    return T, spec


def _summary(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"mean": math.nan, "median": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "mean": float(np.mean(values)),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(np.max(values)),
    }


@dataclass(frozen=True)
class GroundTruthStats:
    """What :func:`groundtruth_run` did, and how the checkerboard agrees with any earlier ground truth."""

    run: Path
    """The run directory."""
    frames: int
    """Frames in the run."""
    with_image: int
    """Frames with a camera image."""
    detected: int
    """Frames where the board was detected (these now have gt cells)."""
    compared_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    """Frame indices ``(C,)`` with both a detection and an earlier ground truth."""
    trans_err_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """``‖t_board − t_old‖`` of the needle origin ``(C,)``, millimetres."""
    rot_err_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Rotation angle between the checkerboard and the earlier needle orientation ``(C,)``, degrees."""

    @property
    def trans_summary_mm(self) -> dict[str, float]:
        """Mean, median, 95th percentile and max of :attr:`trans_err_mm` (NaN when nothing was compared)."""
        return _summary(self.trans_err_mm)

    @property
    def rot_summary_deg(self) -> dict[str, float]:
        """Mean, median, 95th percentile and max of :attr:`rot_err_deg` (NaN when nothing was compared)."""
        return _summary(self.rot_err_deg)

    def describe(self) -> str:
        """A few human-readable lines."""
        rate = 100.0 * self.detected / self.with_image if self.with_image else 0.0
        lines = [
            f"{self.run}: {self.frames} frames, {self.with_image} with images, board detected in "
            f"{self.detected} ({rate:.1f} %); gt columns rewritten ({self.frames - self.detected} frames left empty)",
        ]
        if self.trans_err_mm.size:
            t, r = self.trans_summary_mm, self.rot_summary_deg
            lines.append(f"checkerboard vs previous ground truth over {self.trans_err_mm.size} frames:")
            lines.append(
                f"  translation [mm]  mean {t['mean']:.3f}  median {t['median']:.3f}  p95 {t['p95']:.3f}  "
                f"max {t['max']:.3f}"
            )
            lines.append(
                f"  rotation   [deg]  mean {r['mean']:.3f}  median {r['median']:.3f}  p95 {r['p95']:.3f}  "
                f"max {r['max']:.3f}"
            )
        else:
            lines.append("no previous ground truth to compare with")
        return "\n".join(lines)


def groundtruth_run(run: str | Path, board_to_needle: str | Path) -> GroundTruthStats:
    """Rewrite a run's ``gt_*`` columns from the checkerboard in its images (module docstring).

    Raises :class:`InputError` for an unreadable run or transform file, when no frame
    of the run has an image, and when the board is detected in none of them (the run is left unchanged).
    """
    from pinpoint_fg.io.recording.reader import read_recording
    from pinpoint_fg.io.recording.writer import replace_ground_truth

    board_T_needle, spec = read_board_to_needle(board_to_needle)
    recording = read_recording(run)
    camera = recording.info.camera
    with_image = [rec for rec in recording.frames if rec.image is not None]
    if not with_image:
        raise InputError(
            "the run has no camera images (the 'image' column is empty): nothing to detect the checkerboard in",
            file=Path(run),
        )
    gt_by_frame: dict[int, np.ndarray | None] = {int(rec.frame): None for rec in recording.frames}
    compared, t_err, r_err = [], [], []
    for rec in with_image:
        image = recording.load_image(rec)
        cam_T_board = detect_board(image, camera, spec)
        if cam_T_board is None:
            continue
        cam_T_needle = cam_T_board @ board_T_needle
        behind = gt_depth_problem(cam_T_needle)
        if behind is not None:  # the run's reader would refuse it: name the mount, leave frames.csv as it is
            raise InputError(f"frame {rec.frame}: {behind}; {Path(run) / 'frames.csv'} is left unchanged",
                             file=Path(board_to_needle), column="board_T_needle")
        far = float(np.max(np.abs(cam_T_needle[:3, 3])))
        if far > MAX_ABS_METRES:  # the writer refused it naming no file ("error: column 'gt_x_m': ...")
            raise InputError(f"frame {rec.frame}: the board puts the needle {far:.6g} m from the camera, beyond the "
                             f"format's {MAX_ABS_METRES:g} m (is the board size right?); "
                             f"{Path(run) / 'frames.csv'} is left unchanged", file=Path(board_to_needle),
                             column="board")
        gt_by_frame[int(rec.frame)] = cam_T_needle
        old = rec.cam_T_needle_gt
        if old is not None:
            compared.append(int(rec.frame))
            t_err.append(1e3 * float(np.linalg.norm(cam_T_needle[:3, 3] - old[:3, 3])))
            r_err.append(math.degrees(float(np.linalg.norm(so3_log(old[:3, :3].T @ cam_T_needle[:3, :3])))))
    detected = sum(v is not None for v in gt_by_frame.values())
    if detected == 0:  # rewriting would empty every gt cell of the run (a wrong board size wiped the truth, exit 0)
        raise InputError(
            f"the {spec.squares_x} x {spec.squares_y} checkerboard of {spec.square_m * 1e3:g} mm squares was found "
            f"in none of the run's {len(with_image)} images; {Path(run) / 'frames.csv'} is left unchanged "
            "(is the board size right?)", file=Path(board_to_needle), column="board")
    replace_ground_truth(run, gt_by_frame)
    return GroundTruthStats(
        run=Path(run),
        frames=len(recording.frames),
        with_image=len(with_image),
        detected=detected,
        compared_frames=np.asarray(compared, dtype=int),
        trans_err_mm=np.asarray(t_err, dtype=float),
        rot_err_deg=np.asarray(r_err, dtype=float),
    )
