"""Which measurement makes SVN prefer its pose to single-mode MAP's? Per-term costs at both and at the truth (issue 9).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/frame_terms.py RUN [--frames 12]
[--every 1]``, e.g. ``/tmp/runs/drive-08`` (``pinpoint-fg simulate --scenario drive --frames 150 --seed 8``).

SVN and MAP (default settings, the run's suggested switches, seed 0: what ``track`` runs with the
``--disable`` its note suggests) are stepped in turn
through the first ``--frames`` frames. For every ``--every``-th frame it prints each tracker's rotation error
and, at SVN's pose, MAP's pose and the ground truth, each term's robust cost in nats
(:meth:`pinpoint_fg.likelihood.FrameLikelihood.term_losses`; the motion prior is not included). Last, the
mean per-frame cost of each term at each pose over the printed frames. A term that is cheaper at SVN's pose
on frame after frame, while the truth pays more than its noise model expects, is the measurement whose error
the model gets wrong: each frame is counted as independent evidence for the side that fits it better.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

POSES = ("svn", "map", "truth")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--every", type=int, default=1)
    args = ap.parse_args()
    rec = read_recording(args.run)
    switches = suggested_disable(args.run)
    trackers = {m: make_tracker(m, tracker_config(rec, m, disable=switches, seed=0)) for m in ("svn", "map")}
    sums: dict[tuple[str, str], float] = defaultdict(float)
    counts: dict[tuple[str, str], int] = defaultdict(int)
    for k, frame in enumerate(rec.frames[: args.frames]):
        obs = observe_frame(rec, frame)
        poses = {m: t.step(obs).cam_T_needle for m, t in trackers.items()}
        if frame.cam_T_needle_gt is None or k % args.every:
            continue
        poses["truth"] = frame.cam_T_needle_gt
        lik = FrameLikelihood(obs, trackers["svn"].config.model)
        rot = {m: float(np.degrees(pose_errors(poses[m][None], frame.cam_T_needle_gt[None]).rot_rad[0]))
               for m in ("svn", "map")}
        cells = []
        for who in POSES:
            parts = lik.term_losses(poses[who][None])
            for name, v in parts.items():
                sums[who, name] += float(v[0])
                counts[who, name] += 1
            cells.append(f"{who}: " + " ".join(f"{name}={float(v[0]):.2f}" for name, v in parts.items()))
        print(f"frame {frame.frame:4d}  rot svn {rot['svn']:6.1f} map {rot['map']:6.1f} deg | " + " | ".join(cells),
              flush=True)
    names = sorted({name for _, name in sums}, key=lambda n: [name for _, name in sums].index(n))
    print("mean per frame (nats; frames where the term is present)")
    print(f"{'term':22s}" + "".join(f"{who:>9s}" for who in POSES))
    for name in names:
        print(f"{name:22s}" + "".join(f"{sums[who, name] / max(counts[who, name], 1):9.2f}" for who in POSES))


if __name__ == "__main__":
    main()
