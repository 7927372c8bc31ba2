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
#: (``grasper_qww`` for ``grasper_qw``: 0.95; ``gt_x_mm`` for ``gt_x_m``: 0.92). Below it, plausible extra columns of
#: a run without that group would be misread (``grasper_id`` 0.80, ``grasper_jaw`` 0.86, ``image_w`` 0.83, ``masked``
#: 0.80, ``gt_q`` 0.89).
NEAR_MISS_CUTOFF = 0.9
#: The lower ratio that suffices for a column of the same letters as a known one, swapped (``gt_wq`` for ``gt_qw``).
SWAPPED_LETTERS_CUTOFF = 0.8
#: The known columns a file column may carry a path suffix on (``mask_path`` for ``mask``).
PATH_COLUMNS = ("mask", "image")
PATH_SUFFIXES = ("_path", "_file")
#: The format's unit suffixes, and the unit each names (a column that drops one, ``tip_u`` for ``tip_u_px``, is a
#: near miss; a unit is never added to a column without one: ``occlusion_px`` is no ``occlusion``).
UNIT_SUFFIXES = {"_px": "pixels", "_m": "metres", "_s": "seconds"}

#: The names a path suffix away from a file column, or a unit suffix short of a known column, to that column; each
#: known column to itself (set last: ``t`` is ``t_s`` minus ``_s``, but ``t_s`` is a column of its own).
_SUFFIX_VARIANTS: dict[str, str] = {
    **{k + sfx: k for k in PATH_COLUMNS for sfx in PATH_SUFFIXES},
    **{k.removesuffix(sfx): k for k in KNOWN_COLUMNS for sfx in UNIT_SUFFIXES if k.endswith(sfx)},
    **{k: k for k in KNOWN_COLUMNS},
}


def _normal(name: str) -> str:
    return name.lower().replace("-", "_").replace(" ", "_")


def _closest_known(name: str) -> str | None:
    """The known column ``name`` most resembles, or None: equal up to case and ``-``/space for ``_`` first, then a
    suffix away (:data:`_SUFFIX_VARIANTS`), then the best ``difflib`` ratio of at least :data:`NEAR_MISS_CUTOFF`
    (:data:`SWAPPED_LETTERS_CUTOFF` for the same letters) among the known columns ``name`` does not extend by a word
    (``occlusion_s`` is not ``occlusion``). Two known columns tied at the best ratio: no suggestion
    (``grasper_qe`` is ``grasper_qw``, ``_qx``, ``_qy`` or ``_qz``), unless one alone has the same letters."""
    u = _normal(name)
    if u in _SUFFIX_VARIANTS:  # the known column itself (a case variant) or a suffix away from it
        return _SUFFIX_VARIANTS[u]
    matcher = difflib.SequenceMatcher()
    matcher.set_seq2(u)
    scored = []
    low = min(NEAR_MISS_CUTOFF, SWAPPED_LETTERS_CUTOFF)
    for k in KNOWN_COLUMNS:  # the cheap upper bounds first, as difflib.get_close_matches (a 20,000-column header)
        if u.startswith(k + "_"):  # a known name with a word added (occlusion_s, image_w): a column of its own
            continue
        matcher.set_seq1(k)
        if matcher.real_quick_ratio() >= low and matcher.quick_ratio() >= low:
            ratio, swapped = matcher.ratio(), sorted(u) == sorted(k)
            if ratio >= (SWAPPED_LETTERS_CUTOFF if swapped else NEAR_MISS_CUTOFF):
                scored.append((swapped, ratio, k))
    if not scored:
        return None
    scored.sort(reverse=True)
    if len(scored) > 1 and scored[0][:2] == scored[1][:2]:
        return None
    return scored[0][2]


def unit_of(column: str) -> str | None:
    """The unit a known column's name states (:data:`UNIT_SUFFIXES`), or None."""
    return next((unit for sfx, unit in UNIT_SUFFIXES.items() if column.endswith(sfx)), None)


def differs_in_unit(name: str, known: str) -> bool:
    """Whether the unknown column ``name`` does not end in the unit suffix of ``known`` (``gt_x_mm``, ``tip_u``)."""
    return unit_of(known) is not None and not _normal(name).endswith(known[known.rindex("_"):])


def suggestion(name: str, known: str) -> str:
    """``'known'``, and its unit when ``name`` does not state it (``'gt_x_m' (metres)`` for ``gt_x_mm``): a column
    renamed as suggested must hold values in the format's unit."""
    return f"{known!r} ({unit_of(known)})" if differs_in_unit(name, known) else repr(known)


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
