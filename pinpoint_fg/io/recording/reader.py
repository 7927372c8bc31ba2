"""Reading a recorded run: :func:`read_recording` (validated, or one ``InputError``) and its text summary."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from pinpoint_fg.io.recording.columns import near_miss_columns, suggestion
from pinpoint_fg.io.recording.schema import OCCLUSION_LABELS, Recording, shown
from pinpoint_fg.io.recording.validator import validate_run


def read_recording(path: str | Path, inflate: bool = True) -> Recording:
    """Read and validate a run directory; raise the first :class:`InputError` found.

    ``inflate`` False: PNGs' compressed data is checked only when decoded (:func:`validate_run`)."""
    recording, errors = validate_run(path, inflate)
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


def time_order_note(rec: Recording, frames: list | None = None) -> str | None:
    """One line for the user when ``t_s`` does not increase from row to row (None otherwise).

    The format orders frames by ``frame`` and does not require ``t_s`` to increase (schema's decisions), so such a
    run is valid and is tracked (a time step <= 0 gets one reference frame's process noise,
    :func:`pinpoint_fg.kinematics_check.elapsed_scale`); but ``trajectory.tum`` is then not in time order, which tools
    that read TUM files (evo) assume.
    """
    frames = rec.frames if frames is None else frames
    back = [(a, b) for a, b in zip(frames, frames[1:], strict=False) if not b.t_s > a.t_s]
    if not back:
        return None
    a, b = back[0]
    return (f"note: {Path(rec.root) / 'frames.csv'}: t_s does not increase at {len(back)} frame(s) (first: frame "
            f"{b.frame} at {b.t_s:g} s after frame {a.frame} at {a.t_s:g} s); they are tracked in frame order "
            "(such a step gets one reference frame's process noise), and trajectory.tum will not be in time order")


def no_image_evidence_note(rec: Recording, frames: list | None = None) -> str | None:
    """One line for the user when no frame has a tip, a tail or a mask (None otherwise): such a run is valid and
    is tracked, but every pose then comes from the first frame's prior and the kinematics alone."""
    frames = rec.frames if frames is None else frames
    if not frames or any(f.tip_px is not None or f.tail_px is not None or f.mask is not None for f in frames):
        return None
    return (f"note: {Path(rec.root) / 'frames.csv'}: none of the {len(frames)} frames has a tip, a tail or a mask; "
            "the poses come from the prior and the kinematics (where present) alone")


#: How many near-miss columns the note names before "and N more" (a generated header can hold thousands).
SHOWN_NEAR_MISSES = 3


def unknown_columns_note(rec: Recording) -> str | None:
    """One line for the user naming the unknown frames.csv columns that look like a misspelt known one (absent from
    the header) and the columns they most likely meant (:func:`near_miss_columns`; each once, with its unit when the
    look-alike does not state it); None when there are none. At most :data:`SHOWN_NEAR_MISSES` of each are named."""
    near = near_miss_columns(rec.columns)
    if not near:
        return None

    def listed(items: list[str]) -> str:
        more = len(items) - SHOWN_NEAR_MISSES
        return ", ".join(items[:SHOWN_NEAR_MISSES]) + (f" and {more} more" if more > 0 else "")

    names = listed([shown(c, 40) for c in near])
    meant = listed(list(dict.fromkeys(suggestion(c, k) for c, k in near.items())))
    verb = "column {} is" if len(near) == 1 else "columns {} are"
    return (f"note: {Path(rec.root) / 'frames.csv'}: {verb.format(names)} not in the format and "
            f"{'is' if len(near) == 1 else 'are'} ignored (did you mean {meant}?)")
