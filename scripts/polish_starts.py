"""Where would each member of SVN's best mode end if polished? The settle's extra starts judged (issue 9).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/polish_starts.py RUN FRAME [FRAME ...]
[--polish 30]``, e.g. ``/tmp/bench/runs/drive-01 57``.

SVN (default settings, N = 50, L = 1, the run's suggested switches, seed 0 -- what ``track`` runs with the
``--disable`` its note suggests) is stepped
through the run. At each FRAME the inputs of its settle (:func:`pinpoint_fg.trackers.svn_modes.settle`: the window
after transport, its linearisation, the modes) are copied, and every member of the best mode is polished on its
own window for ``--polish`` Levenberg-Marquardt steps. Printed per member, by current cost: its window's cost now,
its Gauss-Newton-predicted peak's distance from the mode representative's (scaled units: 5 deg, 1 mm), its cost
and rotation error (deg) after the polish, and which members the settle's extra starts take
(:func:`~pinpoint_fg.trackers.svn_modes._extra_starts`, ``ModeSettings.start_spacing``) and which the rule before the
twelfth round took (the two lowest-cost members more than 0.5 unit from the representative's predicted peak). If a
member ends at a lower cost than the representative, the mode holds a better optimum than its representative's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config
from pinpoint_fg.trackers import svn as svn_module
from pinpoint_fg.trackers.svn_modes import _extra_starts, polish, scaled_distance


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("frames", type=int, nargs="+")
    ap.add_argument("--polish", type=int, default=30)
    args = ap.parse_args()
    rec = read_recording(args.run)
    tracker = make_tracker("svn", tracker_config(rec, "svn", disable=suggested_disable(args.run), seed=0))
    seen: dict = {}
    settle = svn_module.settle

    def copying_settle(window, lin, found, *a, **k):  # noqa: ANN001, ANN202 - settle's own signature
        seen["inputs"] = (window.subset(np.arange(window.newest.shape[0])), lin, found)
        return settle(window, lin, found, *a, **k)

    svn_module.settle = copying_settle
    wanted = set(args.frames)
    modes = tracker.svn.modes
    for frame in rec.frames[: max(wanted) + 1]:
        seen.clear()
        tracker.step(observe_frame(rec, frame))
        if frame.frame not in wanted:
            continue
        if "inputs" not in seen or frame.cam_T_needle_gt is None:
            print(f"frame {frame.frame}: no settle on this frame or no ground truth")
            continue
        window, lin, found = seen["inputs"]
        cost = lin.value + window.evidence
        mode = int(np.argmax(found.mode_log_evidence))
        rep = int(found.reps[mode])
        members = np.flatnonzero(found.labels == mode)
        new = _extra_starts(found, mode, rep, cost, modes.map_starts - 1, modes.start_spacing)
        others = members[members != rep]
        far = others[scaled_distance(found.peaks[rep], found.peaks[others]) > 0.5]
        old = far[np.argsort(cost[far], kind="stable")[: modes.map_starts - 1]].tolist()
        sub = window.subset(members)
        after = polish(sub, lin.subset(members), args.polish)
        final = after.value + sub.evidence
        rot = np.degrees(pose_errors(sub.newest, np.broadcast_to(frame.cam_T_needle_gt, sub.newest.shape)).rot_rad)
        dist = scaled_distance(found.peaks[rep], found.peaks[members])
        print(f"frame {frame.frame}: best mode's {members.size} members (rep {rep}); starts now {new}, before {old}")
        print(f"{'row':>4} {'cost':>10} {'peak dist':>9} {'polished':>10} {'rot deg':>7}  start")
        for k in np.argsort(cost[members], kind="stable"):
            j = int(members[k])
            tag = "rep" if j == rep else ("now+before" if j in new and j in old else
                                          "now" if j in new else "before" if j in old else "")
            print(f"{j:4d} {cost[j]:10.2f} {dist[k]:9.2f} {final[k]:10.2f} {rot[k]:7.2f}  {tag}")


if __name__ == "__main__":
    main()
