"""Median thread-CPU milliseconds per frame of one tracker's ``step``, best of several repeats (issue 10).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/step_cpu.py RUN [RUN ...] [--method svn]
[--particles 50] [--window 1] [--frames 100] [--repeats 5]``. To compare two commits, run it from a checkout of
each (``git worktree add``) with ``PYTHONPATH`` set to that checkout, alternating them.

Each repeat tracks the run's first ``--frames`` frames afresh (the recording's suggested switches, seed 0; frames are
observed once, outside the timing) and takes the median over frames 10 on of ``time.thread_time()`` around
``step`` (the whole step: the uncertainty summary included), over all frames and over frames without a mask; the
best (lowest) repeat is printed: thread CPU is less sensitive to other load than wall time, and the minimum of
repeats less sensitive still.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--method", default="svn")
    ap.add_argument("--particles", type=int, default=None)
    ap.add_argument("--window", type=int, default=1)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    for run in args.runs:
        rec = read_recording(run)
        obs = [observe_frame(rec, f) for f in rec.frames[: args.frames]]
        best_all, best_nomask = np.inf, np.inf
        for _ in range(args.repeats):
            config = tracker_config(rec, args.method, args.particles, args.window,
                                    disable=suggested_disable(run), seed=0)
            tracker = make_tracker(args.method, config)
            every, nomask = [], []
            for k, o in enumerate(obs):
                t0 = time.thread_time()
                tracker.step(o)
                dt = 1e3 * (time.thread_time() - t0)
                if k >= 10:
                    every.append(dt)
                    if o.backbone_px is None:
                        nomask.append(dt)
            best_all = min(best_all, float(np.median(every)))
            best_nomask = min(best_nomask, float(np.median(nomask)) if nomask else np.nan)
        print(f"{run.name} {args.method} N={config.particles} L={args.window}: median {best_all:.2f} ms, "
              f"no-mask {best_nomask:.2f} ms (best of {args.repeats})", flush=True)


if __name__ == "__main__":
    main()
