"""Thread-CPU cost per call of the mode proposals' geometry on a run's mask frames (issue 10).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/proposal_cost.py RUN [--frames 30]
[--repeats 100]``. On the first ``--frames`` frames with a backbone, at the true pose, prints the mean microseconds
per call of :func:`pinpoint_fg.proposals.mode_proposals` (as SVN calls it for its best mode: with the frame's own
ellipse) and of its parts: ``twin_poses``, ``frame_ellipse_poses``, ``arc_flips`` and ``dedupe``. Compare two trees
by running it from each (``PYTHONPATH=<tree>``), alternately and more than once: thread CPU still moves with the
host's load.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pinpoint_fg import proposals as P
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config


def _per_call_us(f: Callable[[], object], repeats: int) -> float:
    f()
    t0 = time.thread_time()
    for _ in range(repeats):
        f()
    return (time.thread_time() - t0) / repeats * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=100)
    args = ap.parse_args()
    rec = read_recording(args.run)
    model = tracker_config(rec, "svn", disable=suggested_disable(rec)).model
    nd, K = model.needle, model.camera.K
    ta, pa = nd.tail_angle_rad, nd.tip_angle_rad
    cases = []
    for frame in rec.frames:
        obs = observe_frame(rec, frame, max_points=200)
        if obs.backbone_px is not None and frame.cam_T_needle_gt is not None:
            cases.append((FrameLikelihood(obs, model), frame.cam_T_needle_gt))
        if len(cases) == args.frames:
            break
    if not cases:
        raise SystemExit(f"{args.run}: no frame with a backbone and ground truth")
    total = dict.fromkeys(("mode_proposals", "twin_poses", "frame_ellipse_poses", "arc_flips", "dedupe"), 0.0)
    for lik, T in cases:
        px = lik.observation.backbone_px
        # the parts' inputs as mode_proposals builds them (its twin, the frame's circles, their flips), so that each
        # part is timed on what it gets there
        base = np.concatenate([T[None], P.twin_poses(T[None], K, nd.radius_m, ta, pa),
                               P.frame_ellipse_poses(px, K, nd.radius_m, ta, pa)[0]])
        cands = np.concatenate([base[1:], P.arc_flips(base, ta, pa).reshape(-1, 4, 4)])
        calls = {
            "mode_proposals": lambda lik=lik, T=T: P.mode_proposals(T, lik),
            "twin_poses": lambda T=T: P.twin_poses(T[None], K, nd.radius_m, ta, pa),
            "frame_ellipse_poses": lambda px=px: P.frame_ellipse_poses(px, K, nd.radius_m, ta, pa),
            "arc_flips": lambda base=base: P.arc_flips(base, ta, pa),
            "dedupe": lambda cands=cands, T=T: P.dedupe(cands, T[None]),
        }
        for name, f in calls.items():
            total[name] += _per_call_us(f, args.repeats)
    print(f"{args.run.name}: {len(cases)} mask frames, thread CPU per call (us)")
    for name, us in total.items():
        print(f"  {name:20s} {us / len(cases):8.1f}")


if __name__ == "__main__":
    main()
