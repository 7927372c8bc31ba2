"""SVN's per-frame evidence forgetting, 0.9 vs 1.0 (none): share of frames with a particle within 2 mm / 10 deg
of the truth, and the MAP particle's mean error, on every run of a directory (issue 9, item 2).

Usage: ``.venv/bin/python scripts/compare_forgetting.py RUNS_DIR`` (e.g. ``benchmark-output/runs`` after
``./run benchmark --quick``). Each run is tracked with its recording's ``suggested_disable``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config
from pinpoint_fg.trackers.svn import SvnSettings, SvnTracker


def main(root: Path) -> None:
    for run in sorted(p for p in root.iterdir() if (p / "recording.json").exists()):
        rec = read_recording(run)
        for gamma in (0.9, 1.0):
            tracker = SvnTracker(tracker_config(rec, "svn", disable=suggested_disable(run), seed=0),
                                 SvnSettings(forgetting=gamma))
            kept, err_t, err_r = [], [], []
            for frame in rec.frames:
                est = tracker.step(observe_frame(rec, frame))
                T = frame.cam_T_needle_gt
                if T is None:
                    continue
                e = pose_errors(est.particles, np.broadcast_to(T, est.particles.shape))
                kept.append(bool(np.any((e.trans_m < 2e-3) & (np.degrees(e.rot_rad) < 10.0))))
                m = pose_errors(est.cam_T_needle[None], T[None])
                err_t.append(m.trans_m[0])
                err_r.append(np.degrees(m.rot_rad[0]))
            print(f"{run.name:<16} forgetting {gamma}: truth kept {np.mean(kept):6.1%}  "
                  f"MAP {np.mean(err_t) * 1e3:5.2f} mm {np.mean(err_r):6.1f} deg", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmark-output/runs"))
