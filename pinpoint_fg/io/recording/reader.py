"""Reading a recorded run: :func:`read_recording` (validated, or one ``InputError``) and its text summary."""

from __future__ import annotations

import difflib
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from pinpoint_fg.io.recording.schema import KNOWN_COLUMNS, OCCLUSION_LABELS, Recording, shown
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


#: ``difflib`` similarity ratio at or above which an unknown frames.csv column is taken for a misspelt known one
#: (``grasper_qww``, ``gt_wq`` for ``gt_qw``: 0.8; ``image_exposure_ms`` to ``image``: 0.45).
NEAR_MISS_CUTOFF = 0.8
#: Suffixes that alone separate an unknown column from a known one (``mask_path`` for ``mask``, ``tip_u`` for
#: ``tip_u_px``, ``gt_x`` for ``gt_x_m``).
NEAR_MISS_SUFFIXES = ("_path", "_file", "_px", "_m", "_s")


#: Every name a suffix of :data:`NEAR_MISS_SUFFIXES` away from a known column (added or removed), to that column;
#: each known column to itself (set last: ``t`` is ``t_s`` minus ``_s``, but ``t_s`` is a column of its own).
_SUFFIX_VARIANTS: dict[str, str] = {
    **{k + sfx: k for k in KNOWN_COLUMNS for sfx in NEAR_MISS_SUFFIXES},
    **{k.removesuffix(sfx): k for k in KNOWN_COLUMNS for sfx in NEAR_MISS_SUFFIXES if k.endswith(sfx)},
    **{k: k for k in KNOWN_COLUMNS},
}


def _normal(name: str) -> str:
    return name.lower().replace("-", "_").replace(" ", "_")


def _closest_known(name: str) -> str | None:
    """The known column ``name`` most resembles, or None: equal up to case and ``-``/space for ``_`` first, then
    equal but for a suffix of :data:`NEAR_MISS_SUFFIXES`, then the best ``difflib`` ratio of at least
    :data:`NEAR_MISS_CUTOFF` (a tie goes to a column of the same letters: ``gt_wq`` is ``gt_qw``, not ``gt_qx``)."""
    u = _normal(name)
    if u in _SUFFIX_VARIANTS:  # the known column itself (a case variant) or a suffix away from it
        return _SUFFIX_VARIANTS[u]
    matcher = difflib.SequenceMatcher()
    matcher.set_seq2(u)
    scored = []
    for k in KNOWN_COLUMNS:  # the cheap upper bounds first, as difflib.get_close_matches (a 20,000-column header)
        matcher.set_seq1(k)
        if (matcher.real_quick_ratio() >= NEAR_MISS_CUTOFF and matcher.quick_ratio() >= NEAR_MISS_CUTOFF
                and matcher.ratio() >= NEAR_MISS_CUTOFF):
            scored.append((matcher.ratio(), sorted(u) == sorted(k), k))
    return max(scored)[2] if scored else None


def near_miss_columns(columns: Sequence[str]) -> dict[str, str]:
    """The unknown columns of the header ``columns`` that look like a misspelt known column which the header lacks,
    each mapped to that column, in header order.

    Decision: extra columns stay allowed and ignored (the format's forward compatibility); but a renamed known column
    (``mask_path`` for ``mask``, ``Tip_U_px``) gave a valid run tracked without that data, silently. An unknown
    column counts only when the known column it most resembles (:func:`_closest_known`) is absent: beside ``mask``,
    a ``mask_path`` column is the user's own. Unrelated extras (``surgeon_comment``, ``image_exposure_ms``) resemble
    no known column closely enough.
    """
    present = set(columns)
    near: dict[str, str] = {}
    for name in columns:
        if name in KNOWN_COLUMNS or name in near:
            continue
        known = _closest_known(name)
        if known is not None and known not in present:
            near[name] = known
    return near


def unknown_columns_note(rec: Recording) -> str | None:
    """One line for the user naming the unknown frames.csv columns that look like a misspelt known one (absent from
    the header) and the column each most likely meant (:func:`near_miss_columns`); None when there are none."""
    near = near_miss_columns(rec.columns)
    if not near:
        return None
    names = ", ".join(shown(c, 40) for c in near)
    meant = ", ".join(repr(k) for k in near.values())
    verb = "column {} is" if len(near) == 1 else "columns {} are"
    return (f"note: {Path(rec.root) / 'frames.csv'}: {verb.format(names)} not in the format and "
            f"{'is' if len(near) == 1 else 'are'} ignored (did you mean {meant}?)")
