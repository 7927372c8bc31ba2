"""Recorded runs, format version 1 (``shared/RECORDING_FORMAT.md``): data model, reader, writer.

A run is a directory with ``recording.json``, ``frames.csv`` and optional ``masks/`` and
``images/``. Readers validate everything and raise :class:`pinpoint_fg.errors.InputError`
naming the file, the row and the column; extra columns/keys are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from factors.geometry import NeedleModel, PinholeCamera

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
