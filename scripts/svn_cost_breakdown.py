"""Where SVN's step time goes: per-frame CPU milliseconds of its parts, over frames 20.. of one run (issue 10).

Usage: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/svn_cost_breakdown.py RUN [--particles 50] [--window 1]
[--frames mask|nomask|all] [--relin 0.5]`` (RUN e.g. from ``pinpoint-fg simulate --scenario normal --frames 150
--seed 1``). The run is tracked with the factors it asks to switch off switched off (``suggested_disable``: the
grasp factors on symmetric), as ``track``, ``demo`` and ``benchmark`` track it.
Each part is wrapped with a thread-CPU timer (nested calls of one part are counted once; parts overlap:
``linearize`` inside the polish is also in ``polish``). CPU time of this thread, so other load on the machine
matters less than for wall time. Slower than an unwrapped run by the wrappers' own cost (~1 %).
"""

from __future__ import annotations

import argparse
import collections
import time
from pathlib import Path

import numpy as np

from pinpoint_fg import relinearize as relinearize_module
from pinpoint_fg import window as window_module
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config
from pinpoint_fg.trackers import svn as svn_module
from pinpoint_fg.trackers import svn_modes

PARTS = (
    (svn_module.SvnTracker, "step", "step (total)"), (svn_module.SvnTracker, "_transport", "transport"),
    (svn_module.SvnTracker, "_propose", "mode proposals"), (svn_module, "settle", "settle (polish modes)"),
    (svn_modes, "polish", "polish"), (svn_module.SvnTracker, "_prune", "prune"),
    (window_module.Window, "push", "push + marginalise"), (window_module.Window, "linearize", "linearize"),
    (window_module.Window, "newest_value", "newest_value (trial)"),
    (relinearize_module.ChainAnchor, "_evaluate", "older part re-linearised"),
    (window_module.Window, "move_newest", "move_newest"),
    (svn_module, "stein_step", "stein_step"), (svn_module, "local", "local (chart)"),
    (svn_module, "se3_right_jacobian", "se3_right_jacobian"), (svn_module, "floor_hessians", "floor_hessians (svn)"),
    (svn_module, "tangent_spread", "tangent_spread (summary, modes)"),
    (svn_module, "FrameLikelihood", "FrameLikelihood()"),
    (np, "quantile", "np.quantile"),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--particles", type=int, default=50)
    ap.add_argument("--window", type=int, default=1)
    ap.add_argument("--frames", choices=("all", "mask", "nomask"), default="all")
    ap.add_argument("--relin", type=float, default=0.0, help="Window.relin_threshold (0: exact)")
    args = ap.parse_args()
    spent: collections.Counter = collections.Counter()
    depth: collections.Counter = collections.Counter()
    active = [False]

    def wrap(owner: object, name: str, tag: str) -> None:
        f = getattr(owner, name)

        def timed(*a: object, **k: object) -> object:
            if not active[0] or depth[tag]:
                return f(*a, **k)
            depth[tag] += 1
            t0 = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                spent[tag] += time.thread_time() - t0
                depth[tag] -= 1

        setattr(owner, name, timed)

    for owner, name, tag in PARTS:
        wrap(owner, name, tag)
    rec = read_recording(args.run)
    tracker = make_tracker("svn", tracker_config(rec, "svn", args.particles, args.window, seed=0,
                                                   disable=suggested_disable(rec)))
    tracker.window.relin_threshold = args.relin
    n = 0
    for k, frame in enumerate(rec.frames):
        obs = observe_frame(rec, frame, max_points=200)
        mask = obs.backbone_px is not None
        active[0] = k >= 20 and (args.frames == "all" or (args.frames == "mask") == mask)
        n += active[0]
        tracker.step(obs)
    print(f"svn N={args.particles} L={args.window}, {n} frames ({args.frames}): CPU ms per frame")
    for tag, s in sorted(spent.items(), key=lambda x: -x[1]):
        print(f"  {tag:24s} {1e3 * s / max(n, 1):7.2f}")


if __name__ == "__main__":
    main()
