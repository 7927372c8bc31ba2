"""Where two or more results part: the frames whose rotation error exceeds a threshold, and what the model says there.

Usage: ``.venv/bin/python scripts/frames_apart.py RUN RESULT [RESULT ...] [--beyond-deg 30] [--from-frame 10]``
(e.g. a benchmark's ``runs/kinfault-04`` with its ``results/kinfault/{svn,map,mht}``).

Prints per result its mean rotation error over all frames and from ``--from-frame`` on, and the frames where its
error exceeds ``--beyond-deg``; then, for every such frame of any result, each result's pose's negative log-likelihood
under that frame's measurements alone (``FrameLikelihood.nll`` with the run's suggested switches, as ``track`` tracks it
with the ``--disable`` its note suggests; no motion prior) next to the truth's. A lower value for a pose far from the
truth means the frame itself prefers the wrong mode: a tracker that picks it follows the model, and one that does not is
held back by its history or its start.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.spread_calibration import frame_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.io.result import read_result
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("results", type=Path, nargs="+")
    ap.add_argument("--beyond-deg", type=float, default=30.0)
    ap.add_argument("--from-frame", type=int, default=10)
    a = ap.parse_args()
    rec = read_recording(a.run)
    model = tracker_config(rec, "map", disable=suggested_disable(a.run)).model
    by_frame = {int(f.frame): f for f in rec.frames}
    results = [read_result(p) for p in a.results]
    apart: set[int] = set()
    poses: list[dict[int, np.ndarray]] = []
    for path, res in zip(a.results, results, strict=True):
        rot = np.rad2deg(frame_errors(res, rec).err_rot_rad)
        late = res.frame >= a.from_frame
        far = [int(f) for f, r in zip(res.frame, rot, strict=True) if r > a.beyond_deg]
        apart.update(far)
        poses.append({int(f): T for f, T in zip(res.frame, res.cam_T_needle, strict=True)})
        print(f"{path}: mean rotation error {np.nanmean(rot):.2f} deg, from frame {a.from_frame} on "
              f"{np.nanmean(rot[late]):.2f} deg; frames beyond {a.beyond_deg:g} deg: {far}")
    if not apart:
        return
    names = [p.name or str(p) for p in a.results]
    print("\neach pose's negative log-likelihood under that frame's measurements alone")
    print(f"{'frame':<8}" + "  ".join(f"{n:>10}" for n in names) + f"  {'truth':>10}")
    for f in sorted(apart):
        lik = FrameLikelihood(observe_frame(rec, by_frame[f]), model)
        cells = [f"{float(lik.nll(p[f][None])[0]):10.2f}" if f in p else f"{'-':>10}" for p in poses]
        gt = by_frame[f].cam_T_needle_gt
        truth = f"{float(lik.nll(gt[None])[0]):10.2f}" if gt is not None else f"{'-':>10}"
        print(f"{f:<8}" + "  ".join(cells) + "  " + truth)


if __name__ == "__main__":
    main()
