"""score_run: the development comparisons' per-run scores, by the evaluation's own definitions."""

from __future__ import annotations

import numpy as np

from pinpoint_fg.estimate import Estimate
from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.experiments.compare import score_run
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.sim.scenarios import simulate
from pinpoint_fg.track import make_tracker, tracker_config


class _Truth:
    """A 'tracker' that reports the ground truth (one particle) or, with ``flip``, the truth turned by 180 deg."""

    def __init__(self, recording, flip: bool) -> None:
        self.gt = {f.frame: f.cam_T_needle_gt for f in recording.frames}
        self.flip = flip

    def step(self, obs):
        T = self.gt[obs.frame].copy()
        if self.flip:
            T[:3, :2] = -T[:3, :2]  # rotation by pi about the needle's z axis
        return Estimate(frame=obs.frame, t_s=obs.t_s, cam_T_needle=T, q95_trans_m=0.0, q95_rot_rad=0.0,
                        iterations=1, latency_ms=0.0, particles=T[None], log_posterior=np.zeros(1))


def test_score_run_counts_the_truth_as_kept_and_a_flip_as_lost(tmp_path) -> None:
    rec = read_recording(simulate("normal", 8, seed=3, out=tmp_path / "run"))
    exact = score_run(rec, _Truth(rec, flip=False))
    assert exact.trans_mm == 0.0 and exact.rot_deg < 1e-6 and exact.kept == 1.0 and exact.bimodal == 0.0
    flipped = score_run(rec, _Truth(rec, flip=True))
    T = rec.frames[0].cam_T_needle_gt
    F = T.copy()
    F[:3, :2] = -F[:3, :2]
    assert abs(flipped.rot_deg - 180.0) < 1e-6 and flipped.kept == 0.0
    assert abs(flipped.trans_mm - pose_errors(F[None], T[None]).trans_m[0] * 1e3) < 1e-9


def test_score_run_of_a_real_tracker_matches_its_estimates(tmp_path) -> None:
    rec = read_recording(simulate("normal", 6, seed=3, out=tmp_path / "run"))
    sc = score_run(rec, make_tracker("map", tracker_config(rec, "map")))
    ests = []
    tr = make_tracker("map", tracker_config(rec, "map"))
    for f in rec.frames:
        ests.append(pose_errors(tr.step(observe_frame(rec, f)).cam_T_needle[None], f.cam_T_needle_gt[None]))
    assert abs(sc.rot_deg - np.mean([np.degrees(e.rot_rad[0]) for e in ests])) < 1e-9
    assert abs(sc.trans_mm - np.mean([e.trans_m[0] * 1e3 for e in ests])) < 1e-9
