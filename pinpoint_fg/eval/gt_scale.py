"""Ground truth that does not describe its frame: the needle it puts in view is far smaller than the image shows.

A depth typed in the wrong unit or a failed board detection gives a pose whose needle projects to a few
pixels while the frame's keypoints and mask span a hundred. Residuals (``calibrate``) and errors
(``evaluate``) measured against such a pose are those of another pose, so both leave the frame out and name
it. The test compares extents in undistorted pixels::

    ratio = min(|tip - tail|, diag(bbox(backbone))) / (diag(bbox(pi(T_gt arc))) + GT_SCALE_SLACK_PX)

and leaves a frame out when ``ratio > GT_SCALE_GATE``. The smaller measured extent is used so that one false
keypoint or a stray mask blob cannot trigger it. Only "too small" is tested: occlusion can hide most of a
needle, so an image extent far *below* the projected one is no evidence against the pose. Over the ~6000
ground-truth frames of 51 simulated runs the ratio is at most 0.96.
"""

from __future__ import annotations

import numpy as np

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.observe import observe_frame

#: A ground-truth frame is left out when its image measurements span more than this many times the needle's
#: projected extent at the ground truth (:func:`gt_scale_ratio`).
GT_SCALE_GATE = 3.0
#: Pixels added to the projected extent before the gate (a needle seen as a few pixels: detection noise).
GT_SCALE_SLACK_PX = 10.0


def gt_scale_ratio(recording: Recording, T: np.ndarray, tip_px: np.ndarray | None, tail_px: np.ndarray | None,
                   backbone_px: np.ndarray | None) -> float | None:
    """How many times larger the frame's image measurements are than the needle projected at ``T`` (None: the
    frame has no extent to compare, i.e. neither both keypoints nor a backbone; module docstring)."""
    extents = []
    if tip_px is not None and tail_px is not None:
        extents.append(float(np.linalg.norm(np.asarray(tip_px) - np.asarray(tail_px))))
    if backbone_px is not None and len(backbone_px) >= 2:
        b = np.asarray(backbone_px, dtype=float)
        extents.append(float(np.linalg.norm(b.max(axis=0) - b.min(axis=0))))
    if not extents:
        return None
    arc = recording.info.needle.arc_points(64) @ T[:3, :3].T + T[:3, 3]
    px = recording.info.camera.project(arc)
    projected = float(np.linalg.norm(px.max(axis=0) - px.min(axis=0)))
    return min(extents) / (projected + GT_SCALE_SLACK_PX)


def left_out_frames(recording: Recording, frames: set[int]) -> list[tuple[FrameRecord, float]]:
    """``(frame record, ratio)`` of the ground-truth frames among ``frames`` (frame numbers) that the gate
    leaves out, in recording order. Refuses the run (:func:`refuse_all_left_out`) when it leaves out every
    frame it can test (a frame with neither both keypoints nor a backbone cannot be tested). Observes each
    such frame once (its mask decoded).
    """
    out: list[tuple[FrameRecord, float]] = []
    passed = 0
    for rec in recording.frames:
        if rec.cam_T_needle_gt is None or int(rec.frame) not in frames:
            continue
        obs = observe_frame(recording, rec)
        ratio = gt_scale_ratio(recording, rec.cam_T_needle_gt, obs.tip_px, obs.tail_px, obs.backbone_px)
        if ratio is not None and ratio > GT_SCALE_GATE:
            out.append((rec, ratio))
        elif ratio is not None:
            passed += 1
    if out and passed == 0:
        refuse_all_left_out(recording, out)
    return out


def refuse_all_left_out(recording: Recording, left_out: list[tuple[FrameRecord, float]]) -> None:
    """:class:`InputError` at the first left-out frame's row (``gt_z_m``), for a run whose every ground-truth frame
    that could be tested failed the gate: the whole column is in another unit, not one cell wrong (the frames
    that cannot be tested then hold the same wrong unit)."""
    rec, ratio = left_out[0]
    raise InputError(f"the ground truth of every frame that can be checked puts the needle {ratio:.3g}x "
                     f"smaller than its image shows it (here at depth {rec.cam_T_needle_gt[2, 3]:.4g} m): "
                     "metres expected; correct the gt_* cells", file=recording.csv_path,
                     row=recording.row_of(rec), column="gt_z_m")


def left_out_note(recording: Recording, left_out: list[tuple[FrameRecord, float]], what: str = "") -> str:
    """The one ``note:`` line naming the frames the gate left out (count and first rows, with their ratios) of
    ``what`` (e.g. " of the scores"; empty: of everything)."""
    first = ", ".join(f"{recording.row_of(r)} (x{ratio:.3g})" for r, ratio in left_out[:3])
    return (f"note: {recording.csv_path}: {len(left_out)} ground-truth frame(s) left out{what}: the needle would "
            f"look several times smaller there than its image shows it (rows {first}"
            f"{', ...' if len(left_out) > 3 else ''}); check their gt_* cells")
