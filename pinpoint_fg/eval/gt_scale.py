"""Ground truth that does not describe its frame: the needle it puts in view is not the one the image shows.

A depth typed in the wrong unit, a metre typed for a millimetre in one cell, or a failed board detection gives a
pose whose needle projects to a few pixels, or thousands of pixels away, while the frame's keypoints and mask show
the needle where it is. Residuals (``calibrate``) and errors (``evaluate``) measured against such a pose are those
of another pose, so both leave the frame out and name it (:func:`gt_mismatch`). Three tests, in undistorted
pixels, on the frame's measurements (tip and tail keypoints, mask backbone):

* **behind** — a needle point the image shows (the tip or tail where that keypoint is detected, the needle
  frame's origin where a mask is) lies at a depth <= :data:`factors.residuals.MIN_DEPTH_M`: the image residuals
  there would be those of its mirror image. ``calibrate`` refuses such a run at the row (its statistics were
  inflated silently: one such frame of eight gave a tip std of 42 px instead of 0.6); ``evaluate`` leaves the
  frame out.
* **small** — ``ratio = min(|tip - tail|, diag(bbox(backbone))) / (diag(bbox(pi(T_gt arc))) + GT_SCALE_SLACK_PX)``
  above :data:`GT_SCALE_GATE`. The smaller measured extent is used so that one false keypoint or a stray mask
  blob cannot trigger it. Only "too small" is tested by extent: occlusion can hide most of a needle, so an
  image extent far *below* the projected one is no evidence against the pose. Over the ~6000 ground-truth
  frames of 51 simulated runs the ratio is at most 0.96.
* **elsewhere** — every measurement lies far from the projected arc: ``d = min(d_tip, d_tail,
  median_i d(backbone_i))``, each the distance to the nearest of 256 projected arc points, exceeds both
  :data:`GT_OFFSET_GATE` times the measurements' own extent (``diag(bbox(tip, tail, backbone))`` plus the slack)
  and :data:`GT_OFFSET_MIN_PX`. The smallest group distance is used so that one false detection cannot
  trigger it, and the measurements' extent so that a pose placed too near (a huge projected arc) is caught as
  well as one placed beside the needle. Over 10,751 ground-truth frames of 72 simulated runs (seeds 1-8 of
  every scenario) ``d`` is at most 3.4 px and ``d / extent`` at most 0.34; a 0.5 m typed for 0.5 mm in
  ``gt_x_m`` gives ~10,000 px (54 extents), ``gt_z_m`` five times too small 253 px (1.4 extents).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from factors.residuals import MIN_DEPTH_M
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.observe import observe_frame

#: A ground-truth frame is left out when its image measurements span more than this many times the needle's
#: projected extent at the ground truth (:func:`gt_scale_ratio`).
GT_SCALE_GATE = 3.0
#: Pixels added to the projected extent before the gate (a needle seen as a few pixels: detection noise).
GT_SCALE_SLACK_PX = 10.0
#: ... or when every measurement lies farther than this many times the measurements' own extent from the
#: projected arc (:func:`gt_offset`; module docstring).
GT_OFFSET_GATE = 1.0
#: ... and farther than this many pixels (a needle seen as a dot: detection noise alone is a few pixels).
GT_OFFSET_MIN_PX = 50.0
#: Arc points projected for the offset test (their spacing, ~1 px for a 200 px needle, bounds its error).
ARC_SAMPLES = 256


class GtMismatch(NamedTuple):
    """Why a frame's ground truth was left out (module docstring)."""

    kind: str
    """``behind``, ``small`` or ``elsewhere``."""
    value: float
    """behind: the depth (m) of the point; small: the extent ratio; elsewhere: the distance in measured extents."""
    detail: str = ""
    """behind: which point (tip, tail, centre)."""


def seen_point_behind(recording: Recording, T: np.ndarray, tip_px: np.ndarray | None, tail_px: np.ndarray | None,
                      backbone_px: np.ndarray | None) -> GtMismatch | None:
    """The first needle point the frame's image shows that ``T`` puts at a depth <= ``MIN_DEPTH_M`` (module
    docstring, *behind*), or None."""
    nd = recording.info.needle
    for name, p_needle, seen in (("tip", nd.tip_m, tip_px), ("tail", nd.tail_m, tail_px),
                                 ("centre", np.zeros(3), backbone_px)):
        z = float(T[2, :3] @ p_needle + T[2, 3])
        if seen is not None and z <= MIN_DEPTH_M:
            return GtMismatch("behind", z, name)
    return None


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


def gt_offset(recording: Recording, T: np.ndarray, tip_px: np.ndarray | None, tail_px: np.ndarray | None,
              backbone_px: np.ndarray | None) -> tuple[float, float] | None:
    """``(d px, d / (measured extent + slack))``: how far the frame's measurements lie from the needle projected at
    ``T`` (module docstring, *elsewhere*); None without measurements or without an arc point in front."""
    groups = [np.asarray(p, dtype=float).reshape(1, 2) for p in (tip_px, tail_px) if p is not None]
    if backbone_px is not None and len(backbone_px) >= 1:
        groups.append(np.asarray(backbone_px, dtype=float).reshape(-1, 2))
    if not groups:
        return None
    arc = recording.info.needle.arc_points(ARC_SAMPLES) @ T[:3, :3].T + T[:3, 3]
    arc = arc[arc[:, 2] > MIN_DEPTH_M]
    if arc.shape[0] == 0:
        return None
    px = recording.info.camera.project(arc)
    dists = []
    for g in groups:
        d = np.sqrt(np.min(np.sum((g[:, None, :] - px[None]) ** 2, axis=-1), axis=1))
        dists.append(float(np.median(d)))
    pts = np.concatenate(groups)
    extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    d = min(dists)
    return d, d / (extent + GT_SCALE_SLACK_PX)


def gt_mismatch(recording: Recording, T: np.ndarray, tip_px: np.ndarray | None, tail_px: np.ndarray | None,
                backbone_px: np.ndarray | None) -> tuple[GtMismatch | None, bool]:
    """``(why the frame's ground truth ``T`` is left out or None, whether the frame could be tested)``: the three
    tests of the module docstring, in order; a frame with no measurement cannot be tested."""
    behind = seen_point_behind(recording, T, tip_px, tail_px, backbone_px)
    if behind is not None:
        return behind, True
    ratio = gt_scale_ratio(recording, T, tip_px, tail_px, backbone_px)
    if ratio is not None and ratio > GT_SCALE_GATE:
        return GtMismatch("small", ratio), True
    offset = gt_offset(recording, T, tip_px, tail_px, backbone_px)
    if offset is not None and offset[0] > GT_OFFSET_MIN_PX and offset[1] > GT_OFFSET_GATE:
        return GtMismatch("elsewhere", offset[1]), True
    return None, ratio is not None or offset is not None


def left_out_frames(recording: Recording, frames: set[int]) -> list[tuple[FrameRecord, GtMismatch]]:
    """``(frame record, why)`` of the ground-truth frames among ``frames`` (frame numbers) that the tests leave
    out, in recording order. Refuses the run (:func:`refuse_all_left_out`) when they leave out every frame they
    can test (a frame without measurements cannot be tested). Observes each such frame once (its mask decoded).
    """
    out: list[tuple[FrameRecord, GtMismatch]] = []
    passed = 0
    for rec in recording.frames:
        if rec.cam_T_needle_gt is None or int(rec.frame) not in frames:
            continue
        obs = observe_frame(recording, rec)
        why, tested = gt_mismatch(recording, rec.cam_T_needle_gt, obs.tip_px, obs.tail_px, obs.backbone_px)
        if why is not None:
            out.append((rec, why))
        elif tested:
            passed += 1
    if out and passed == 0:
        refuse_all_left_out(recording, out)
    return out


def _what(why: GtMismatch) -> str:
    if why.kind == "behind":
        return f"its {why.detail} at depth {why.value:.3g} m, behind the camera that sees it"
    if why.kind == "small":
        return f"the needle {why.value:.3g}x smaller than its image shows it"
    return f"the needle {why.value:.3g} times its image's size away from where its image shows it"


def refuse_all_left_out(recording: Recording, left_out: list[tuple[FrameRecord, GtMismatch]]) -> None:
    """:class:`InputError` at the first left-out frame's row (``gt_z_m``), for a run whose every ground-truth frame
    that could be tested failed: the whole column is in another unit or convention, not one cell wrong (the frames
    that cannot be tested then hold the same error)."""
    rec, why = left_out[0]
    unit = "metres expected; " if why.kind == "small" else ""
    raise InputError(f"the ground truth of every frame that can be checked puts {_what(why)} (here at depth "
                     f"{rec.cam_T_needle_gt[2, 3]:.4g} m): {unit}correct the gt_* cells", file=recording.csv_path,
                     row=recording.row_of(rec), column="gt_z_m")


def left_out_note(recording: Recording, left_out: list[tuple[FrameRecord, GtMismatch]], what: str = "") -> str:
    """The one ``note:`` line naming the frames the tests left out (count and first rows, with why) of ``what``
    (e.g. " of the scores"; empty: of everything)."""
    tags = {"small": lambda w: f"x{w.value:.3g} smaller", "elsewhere": lambda w: f"{w.value:.3g} sizes away",
            "behind": lambda w: f"{w.detail} behind the camera"}
    first = ", ".join(f"{recording.row_of(r)} ({tags[w.kind](w)})" for r, w in left_out[:3])
    return (f"note: {recording.csv_path}: {len(left_out)} ground-truth frame(s) left out{what}: the needle would "
            f"not be where its image shows it, or several times smaller (rows {first}"
            f"{', ...' if len(left_out) > 3 else ''}); check their gt_* cells")
