"""Score one tracker on one recording frame by frame: mean MAP errors, truth kept, modes verdict.

The development comparisons (``scripts/compare_svn_map_mht.py``, ``scripts/compare_forgetting.py``) step a
tracker in this process and score it with the evaluation's own definitions: "kept" is
:func:`pinpoint_fg.eval.modes.near_truth` of some particle (2 mm and 10 deg), "bimodal" the modes verdict
(:func:`pinpoint_fg.posterior.summary.bimodal_from_modes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.eval.modes import near_truth
from pinpoint_fg.io.recording import Recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.summary import bimodal_from_modes, modes_of_estimate
from pinpoint_fg.trackers.base import Tracker


@dataclass(frozen=True)
class RunScore:
    """A tracker's scores over the frames of one recording that have ground truth."""

    trans_mm: float
    """Mean translation error of the MAP pose, millimetres."""
    rot_deg: float
    """Mean rotation error of the MAP pose, degrees."""
    kept: float
    """Share of frames with some particle within the truth-kept thresholds."""
    bimodal: float
    """Share of frames the modes verdict calls bimodal."""


def score_run(recording: Recording, tracker: Tracker) -> RunScore:
    """Step ``tracker`` through every frame of ``recording`` and score the frames with ground truth."""
    err_t, err_r, kept, bimodal = [], [], [], []
    for frame in recording.frames:
        est = tracker.step(observe_frame(recording, frame))
        T = frame.cam_T_needle_gt
        if T is None:
            continue
        kept.append(bool(np.any(near_truth(est.particles, T))))
        m = pose_errors(est.cam_T_needle[None], T[None])
        err_t.append(m.trans_m[0] * 1e3)
        err_r.append(np.degrees(m.rot_rad[0]))
        bimodal.append(bimodal_from_modes(modes_of_estimate(est)))
    return RunScore(float(np.mean(err_t)), float(np.mean(err_r)), float(np.mean(kept)), float(np.mean(bimodal)))
