"""The kinematic terms' evidence for SVN's, MAP's and the true trajectory: white noise vs a slow bias (issue 9).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/kinematic_bias_evidence.py RUN
[--frames 30] [--tau-s 5] [--white-share 0.01]``, e.g. ``/tmp/runs/drive-09`` (``pinpoint-fg simulate --scenario
drive --frames 150 --seed 9``).

SVN and MAP (default settings, the run's suggested switches, seed 0) are stepped through the first ``--frames``
frames. For their trajectories and the true one, the sequence of grasp-position and grasp-perpendicularity
residuals (:meth:`pinpoint_fg.likelihood.FrameLikelihood.residuals`) is scored two ways, each as a negative
log-likelihood in nats (Gaussian: the robust losses are left out of both):

* **white**, the trackers' model: every frame independent, ``r_k ~ N(0, C)`` with the noise file's ``C``;
* **bias**, the simulator's model of kinematic error (``pinpoint_fg.sim.kinematics.ou_white_process``): ``r_k = b_k
  + w_k``, ``b`` an Ornstein-Uhlenbeck process with time constant ``--tau-s`` and variance ``(1 - f) C``, ``w``
  white with variance ``f C`` (``f = --white-share``), scored by its Kalman filter's prediction errors (the exact
  sequence likelihood; :func:`pinpoint_fg.kinematic_bias.sequence_nll`).

Where one trajectory leads under *white* and trails under *bias*, the tracker's evidence for it came from
counting one slowly varying kinematic error as fresh evidence on every frame. The trajectories are the trackers'
own (fitted under the white model), so this scores, not re-fits: a tracker with the bias model would move them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.kinematic_bias import BiasModel, sequence_nll
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

TERMS = ("grasp_position", "grasp_perpendicular")
WHO = ("svn", "map", "truth")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--tau-s", type=float, default=5.0, help="the simulator's kin_bias_tau_s")
    ap.add_argument("--white-share", type=float, default=0.01, help="the simulator's kin_white_var_fraction")
    args = ap.parse_args()
    rec = read_recording(args.run)
    switches = suggested_disable(args.run)
    trackers = {m: make_tracker(m, tracker_config(rec, m, disable=switches, seed=0)) for m in ("svn", "map")}
    model = trackers["svn"].config.model
    seq: dict[tuple[str, str], list[np.ndarray]] = {(w, t): [] for w in WHO for t in TERMS}
    rot: dict[str, list[float]] = {"svn": [], "map": []}
    times: list[float] = []
    for frame in rec.frames[: args.frames]:
        obs = observe_frame(rec, frame)
        poses = {m: t.step(obs).cam_T_needle for m, t in trackers.items()}
        if frame.cam_T_needle_gt is None or obs.cam_T_grasper is None:
            continue
        poses["truth"] = frame.cam_T_needle_gt
        for m in rot:
            rot[m].append(float(np.degrees(pose_errors(poses[m][None], frame.cam_T_needle_gt[None]).rot_rad[0])))
        lik = FrameLikelihood(obs, model)
        for who, T in poses.items():
            r = lik.residuals(T[None])
            for term in TERMS:
                if term in r:
                    seq[who, term].append(r[term][0])
        times.append(frame.t_s)
    if len(times) < 2:
        raise SystemExit("fewer than two frames with ground truth and kinematics")
    dt_s = float(np.median(np.diff(times)))
    model_bias = BiasModel(args.tau_s, args.white_share)
    print(f"{args.run.name}: {len(times)} frames, dt {dt_s * 1e3:.1f} ms; mean rotation error SVN "
          f"{np.mean(rot['svn']):.1f} deg, MAP {np.mean(rot['map']):.1f} deg; bias tau {args.tau_s} s, white share "
          f"{args.white_share}")
    print(f"{'term':22s}{'trajectory':>11s}{'white nll':>12s}{'bias nll':>12s}")
    for term in TERMS:
        for who in WHO:
            if not seq[who, term]:
                continue
            r, cov = np.asarray(seq[who, term]), model.noise[term].cov
            white, bias = (float(sequence_nll(r, times, cov, m)[0]) for m in (None, model_bias))
            print(f"{term:22s}{who:>11s}{white:12.1f}{bias:12.1f}")


if __name__ == "__main__":
    main()
