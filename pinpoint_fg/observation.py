"""What a tracker sees of one camera frame, after undistortion and mask processing.

This is the unit fed to ``tracker.step(observation)``; it is built from a recorded frame by
:func:`pinpoint_fg.observe.observe_frame`, or directly by a program that has its own
detector and kinematics (e.g. inside a SLAM pipeline). Every image quantity is in
*undistorted* (ideal pinhole) pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Observation:
    """One frame's evidence; ``None`` means "not observed this frame"."""

    frame: int
    """Frame index in the recording."""
    t_s: float
    """Time stamp, seconds."""
    tip_px: np.ndarray | None = None
    """Tip keypoint ``(2,)``, undistorted pixels."""
    tail_px: np.ndarray | None = None
    """Tail keypoint ``(2,)``, undistorted pixels."""
    backbone_px: np.ndarray | None = None
    """Backbone centre-line pixels ``(M, 2)``, undistorted; None when the frame has no mask, an empty one or one
    that is ignored (``mask_ignored``); M >= 1 otherwise."""
    cam_T_grasper: np.ndarray | None = None
    """Grasper pose from kinematics ``(4, 4)``: origin = grasp point, z axis = grasper axis."""
    mask_ignored: str | None = None
    """Why the frame's mask is ignored (:func:`pinpoint_fg.observe.centre_line_misfit`: not one thin curve, or
    mostly nonzero); None otherwise. For the user's note only: trackers read ``backbone_px``."""

    def __post_init__(self) -> None:
        for name, shape in (("tip_px", (2,)), ("tail_px", (2,)), ("cam_T_grasper", (4, 4))):
            v = getattr(self, name)
            if v is None:
                continue
            a = np.asarray(v, dtype=float)
            if a.shape != shape:
                raise ValueError(f"Observation.{name} must have shape {shape}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Observation.{name} contains NaN or infinite values")
            object.__setattr__(self, name, a)
        if self.backbone_px is not None:
            b = np.asarray(self.backbone_px, dtype=float)
            if b.ndim != 2 or b.shape[1] != 2:
                raise ValueError(f"Observation.backbone_px must have shape (M, 2), got {b.shape}")
            if not np.all(np.isfinite(b)):
                raise ValueError("Observation.backbone_px contains NaN or infinite values")
            object.__setattr__(self, "backbone_px", b if b.shape[0] > 0 else None)

    @property
    def has_image_evidence(self) -> bool:
        """True when any keypoint or backbone pixel is present."""
        return self.tip_px is not None or self.tail_px is not None or self.backbone_px is not None
