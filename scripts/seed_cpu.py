"""Thread-CPU milliseconds of one seeding (``pinpoint_fg.init.seed_particles``) on each run's first frame.

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/seed_cpu.py RUN [RUN ...] [--repeats 3]
[--frame 0]``. To compare two commits, run it from a checkout of each (``git worktree add``) with ``PYTHONPATH``
set to that checkout, alternating them.

Every tracker seeds its first frame this way (and re-seeds a frame it finds implausible): the candidates
(1440 with a mask and kinematics: the fitted ellipse's two circle poses and the grasp's, swept over angles) are
polished by a few batched Gauss-Newton steps and the distinct modes kept (:mod:`pinpoint_fg.init`). Prints per run
the candidate count and the best of ``--repeats`` (a fresh frame likelihood each time, so no memo answers).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pinpoint_fg import init
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frame", type=int, default=0, help="index of the frame to seed (default the first)")
    args = ap.parse_args()
    for run in args.runs:
        rec = read_recording(run)
        config = tracker_config(rec, "svn", None, 1, disable=suggested_disable(rec), seed=0)
        obs = observe_frame(rec, rec.frames[args.frame])
        cfg = init.InitConfig()
        probe = FrameLikelihood(obs, config.model)
        n = sum(c.shape[0] for c in (init.ellipse_candidates(probe, cfg.angle_steps),
                                     init.grasp_candidates(probe, cfg.angle_steps)))
        best = np.inf
        for _ in range(args.repeats):
            lik = FrameLikelihood(obs, config.model)
            t0 = time.thread_time()
            init.seed_particles(lik, 50, np.random.default_rng(0), cfg)
            best = min(best, time.thread_time() - t0)
        print(f"{run.name} frame {args.frame}: {n} candidates, seeding {1e3 * best:.0f} ms (best of {args.repeats})",
              flush=True)


if __name__ == "__main__":
    main()
