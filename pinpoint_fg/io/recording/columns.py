"""Near misses of frames.csv column names: an unknown column that looks like a misspelt known one.

The format allows extra columns and ignores them (forward compatibility), so a renamed known column (``mask_path`` for
``mask``, ``Tip_U_px``) would otherwise give a valid run tracked without that data, silently. The reader names such
columns on a ``note:`` line (:func:`pinpoint_fg.io.recording.reader.unknown_columns_note`) and the validator beside
a required column it misses (``grasper_wq`` for ``grasper_qw``).
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence

from pinpoint_fg.io.recording.schema import KNOWN_COLUMNS

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
