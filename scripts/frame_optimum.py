"""How far one masked frame's own likelihood pulls the pose from the truth, and how many nats it pays to (issue 9).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/frame_optimum.py RUN [--frames 40]
[--steps 50]``, e.g. ``/tmp/runs/symmetric-01`` (``pinpoint-fg simulate --scenario symmetric --frames 150 --seed 1``).

For every frame with a mask among the first ``--frames``, the frame's negative log-likelihood alone (its
measurement terms with the run's suggested switches; no motion prior, no window) is minimised from the true
pose by damped Gauss-Newton steps in the right chart (``T exp(step)``, the step halved until the NLL falls). It
prints the NLL at the truth and at that optimum, and the optimum's depth and rotation offsets from the truth; last,
their means. With independent pixels as the model assumes, a 6-DoF fit from the truth lowers the NLL by about
3 nats (half a chi-square with 6 degrees of freedom). Drops of tens of nats, with the optimum far along one
direction (depth on a far, oblique partial arc), mean the frame's pixels share an error the model counts as
independent evidence.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from factors.lie import se3_exp
from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config


def frame_optimum(lik: FrameLikelihood, start: np.ndarray, steps: int) -> np.ndarray:
    """``start (4, 4)`` moved by up to ``steps`` damped Gauss-Newton steps on ``lik``'s NLL alone."""
    T = start.copy()
    for _ in range(steps):
        value, grad, hess = lik.gauss_newton(T[None])
        step = -np.linalg.solve(hess[0] + 1e-9 * np.trace(hess[0]) * np.eye(6), grad[0])
        for _ in range(30):
            trial = T @ se3_exp(step)
            if lik.nll(trial[None])[0] < value[0]:
                T = trial
                break
            step = 0.5 * step
        else:
            break
    return T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--steps", type=int, default=50)
    args = ap.parse_args()
    rec = read_recording(args.run)
    model = tracker_config(rec, "svn", disable=suggested_disable(args.run)).model
    rows = []
    for frame in rec.frames[: args.frames]:
        obs = observe_frame(rec, frame)
        if obs.backbone_px is None or frame.cam_T_needle_gt is None:
            continue
        lik = FrameLikelihood(obs, model)
        gt = frame.cam_T_needle_gt
        T = frame_optimum(lik, gt, args.steps)
        at_truth, at_opt = float(lik.nll(gt[None])[0]), float(lik.nll(T[None])[0])
        depth_mm = 1e3 * float(T[2, 3] - gt[2, 3])
        rot_deg = float(np.degrees(pose_errors(T[None], gt[None]).rot_rad[0]))
        rows.append((at_truth - at_opt, depth_mm, rot_deg))
        print(f"frame {frame.frame:4d} ({', '.join(lik.term_names)}; {len(obs.backbone_px)} px): NLL truth "
              f"{at_truth:7.1f} -> optimum {at_opt:7.1f}; optimum depth {depth_mm:+7.2f} mm, "
              f"rotation {rot_deg:5.1f} deg")
    if rows:
        drop, depth, rot = np.asarray(rows).T
        print(f"{len(rows)} masked frames: mean NLL drop {drop.mean():.1f} nats (median {np.median(drop):.1f}); "
              f"depth offset mean {depth.mean():+.2f} mm, mean |.| {np.abs(depth).mean():.2f} mm; "
              f"rotation mean {rot.mean():.1f} deg")


if __name__ == "__main__":
    main()
