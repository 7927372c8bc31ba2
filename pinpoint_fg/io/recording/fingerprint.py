"""The identity of a recorded run's content, independent of its path and of how its numbers are spelled.

A recording's ``name`` (recording.json) is not unique: every BOP dataset has a scene ``000001``, and the same scenario
and seed simulated with other options is the same ``normal-01``. ``track`` records
:func:`recording_fingerprint` in ``result.json`` (key ``recording_fingerprint``) so that ``evaluate`` and
``calibrate-spread`` can tell the recording a result was tracked on from another of the same name; ``evaluate`` also
refuses two different recordings of one name among its inputs (it groups tables, figures and the reference by
name).

Decision: the fingerprint covers what the trackers read — camera, needle, and per frame the index, time, keypoints,
kinematics, mask path and the mask file's bytes — and, with ``truth``, the ground truth and the occlusion label too.
Without ``truth`` it leaves out what ``groundtruth`` rewrites after tracking, so a result stays evaluable against
improved ground truth; images (overlays only) and extra keys are never part of it. Values are hashed as parsed
(``0.5`` and ``5e-1`` are the same cell).
"""

from __future__ import annotations

import hashlib
import weakref
from typing import Any

import numpy as np

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.schema import NEEDLE_KEYS, Recording

#: result.json key holding the fingerprint of the recording a result was tracked on.
FINGERPRINT_KEY = "recording_fingerprint"

_CACHE: weakref.WeakKeyDictionary[Recording, dict[bool, str]] = weakref.WeakKeyDictionary()


def _values(x: Any) -> tuple | None:
    return None if x is None else tuple(float(v) for v in np.asarray(x, dtype=float).ravel())


def _mask_digest(rec: Recording, rel: str) -> bytes:
    path = rec.root / rel
    try:
        return hashlib.sha256(path.read_bytes()).digest()
    except OSError as exc:  # validated when read; gone since
        raise InputError(f"cannot read: {exc.strerror or exc}", file=path) from None


def recording_fingerprint(rec: Recording, truth: bool = False) -> str:
    """``"sha256:<hex>"`` of the recording's content (module docstring); computed once per recording and ``truth``."""
    known = _CACHE.setdefault(rec, {})
    if truth in known:
        return known[truth]
    cam, needle = rec.info.camera, rec.info.needle
    h = hashlib.sha256()
    h.update(repr((cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, _values(cam.distortion))).encode())
    h.update(repr(tuple(float(getattr(needle, k)) for k in NEEDLE_KEYS)).encode())
    for f in rec.frames:
        h.update(repr((int(f.frame), float(f.t_s), _values(f.tip_px), _values(f.tail_px), _values(f.cam_T_grasper),
                       f.mask)).encode())
        if f.mask is not None:
            h.update(_mask_digest(rec, f.mask))
        if truth:
            h.update(repr((_values(f.cam_T_needle_gt), f.occlusion)).encode())
    known[truth] = "sha256:" + h.hexdigest()
    return known[truth]
