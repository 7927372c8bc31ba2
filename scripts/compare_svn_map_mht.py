"""SVN vs single-mode MAP vs MHT on every run of a directory: mean errors, truth kept, modes verdict (issue 9).

Usage: ``.venv/bin/python scripts/compare_svn_map_mht.py RUNS_DIR`` (e.g. the runs of ``pinpoint-fg simulate``
for each scenario with another ``--seed`` than the benchmark's). Each run is tracked as ``track`` would (the
recording's ``suggested_disable``, seed 0), one method after the other, in this process; "kept" = some particle
within 2 mm / 10 deg of the truth, "bimodal" = the modes verdict (second mode >= 0.1).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.summary import bimodal_from_modes, modes_of_estimate
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config


def main(root: Path) -> None:
    print(f"{'run':<16} {'method':<6} {'trans mm':>8} {'rot deg':>8} {'kept':>6} {'bimodal':>8}")
    for run in sorted(p for p in root.iterdir() if (p / "recording.json").exists()):
        rec = read_recording(run)
        for method in ("svn", "map", "mht"):
            tracker = make_tracker(method, tracker_config(rec, method, disable=suggested_disable(run), seed=0))
            err_t, err_r, kept, bimodal = [], [], [], []
            for frame in rec.frames:
                est = tracker.step(observe_frame(rec, frame))
                T = frame.cam_T_needle_gt
                if T is None:
                    continue
                e = pose_errors(est.particles, np.broadcast_to(T, est.particles.shape))
                kept.append(bool(np.any((e.trans_m < 2e-3) & (np.degrees(e.rot_rad) < 10.0))))
                m = pose_errors(est.cam_T_needle[None], T[None])
                err_t.append(m.trans_m[0] * 1e3)
                err_r.append(np.degrees(m.rot_rad[0]))
                bimodal.append(bimodal_from_modes(modes_of_estimate(est)))
            print(f"{run.name:<16} {method:<6} {np.mean(err_t):8.2f} {np.mean(err_r):8.1f} {np.mean(kept):6.1%} "
                  f"{np.mean(bimodal):8.1%}", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
