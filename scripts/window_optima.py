"""SVN's own window scored at another tracker's pose: a search failure or a model preference? (issue 9).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/window_optima.py RUN OTHER_RESULT FRAME
[FRAME ...] [--polish 20]``, e.g. ``/tmp/bench/runs/drive-01 /tmp/bench/results/drive/mht 57 58``.

SVN (default settings, N = 50, L = 1, the run's suggested switches, seed 0 -- what ``track`` runs with the
``--disable`` its note suggests) is stepped
through the run. At each FRAME, after its step, the window of SVN's MAP hypothesis is evaluated at three newest
poses: SVN's own, ``OTHER_RESULT``'s estimate of that frame, and the ground truth. Each is then polished on that
window (``--polish`` Levenberg-Marquardt steps, :func:`pinpoint_fg.trackers.svn_modes.polish`). Printed per pose:
the window's negative log-posterior before and after the polish, the Laplace log-evidence after it, and the
rotation error (deg) after it. If the other pose polishes to a lower cost than SVN's, SVN's posterior prefers that
pose and SVN's transport and proposals did not find it (a search failure). If it polishes back to SVN's optimum,
or to a higher cost, the two trackers' models differ (their priors).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.io.result import read_result
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config
from pinpoint_fg.trackers.svn_modes import laplace_terms, polish


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("other", type=Path, help="a result directory of the same run (e.g. an mht result)")
    ap.add_argument("frames", type=int, nargs="+")
    ap.add_argument("--polish", type=int, default=20)
    args = ap.parse_args()
    rec = read_recording(args.run)
    other = read_result(args.other)
    other_pose = dict(zip(other.frame.tolist(), other.cam_T_needle, strict=True))
    tracker = make_tracker("svn", tracker_config(rec, "svn", disable=suggested_disable(args.run), seed=0))
    wanted = set(args.frames)
    print(f"{'frame':>5}  {'pose':6} {'cost':>9} {'polished':>9} {'log Z':>9} {'rot deg':>7}")
    for frame in rec.frames[: max(wanted) + 1]:
        tracker.step(observe_frame(rec, frame))
        k = frame.frame
        if k not in wanted:
            continue
        if k not in other_pose or frame.cam_T_needle_gt is None:
            print(f"{k:5d}  (no estimate of the other result or no ground truth)")
            continue
        window = tracker.window.subset([tracker._last_map] * 3)
        window.poses[-1, 1] = other_pose[k]
        window.poses[-1, 2] = frame.cam_T_needle_gt
        lin = window.linearize()
        before = lin.value + window.evidence
        lin = polish(window, lin, args.polish)
        _, _, log_z = laplace_terms(lin, window.evidence)
        rot = np.degrees(pose_errors(window.newest, np.broadcast_to(frame.cam_T_needle_gt, (3, 4, 4))).rot_rad)
        for i, name in enumerate(("svn", "other", "truth")):
            print(f"{k:5d}  {name:6} {before[i]:9.1f} {lin.value[i] + window.evidence[i]:9.1f} {log_z[i]:9.1f} "
                  f"{rot[i]:7.2f}")


if __name__ == "__main__":
    main()
