"""SVN's per-frame cost at window lengths L (and relinearisation thresholds) on the same frames of one run (issue 10).

Usage: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/svn_window_cost.py RUN [--particles 10 50]
[--windows 1 5] [--relin 0 0.05] [--skip 20]`` (RUN e.g. from ``pinpoint-fg simulate --scenario normal
--frames 150 --seed 1``). Every (N, L, relinearisation threshold) tracker is stepped in turn on each frame
(lock-step, one thread: machine load hits all alike), so the ratios between rows are what transfers between
machines, not the milliseconds. Prints per tracker the median step latency over all, mask and no-mask
frames (frames ``--skip``.. only: the first frames run twice the iterations), the median CPU time, the
ratio to L = 1 at the same N and threshold, the mean iterations and the MAP pose's mean errors (all frames).

``--relin`` sets :attr:`pinpoint_fg.window.Window.relin_threshold` (0: every term re-linearised exactly;
-1, the default: the tracker's own default, printed). With ``PYTHONPATH=<another tree>`` the same script
measures that tree (without ``--relin`` if it predates the setting): run both in turn for a before/after
comparison.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, tracker_config


def _errors(T: np.ndarray, T_gt: np.ndarray | None) -> tuple[float, float]:
    if T_gt is None:
        return float("nan"), float("nan")
    c = 0.5 * (np.trace(T_gt[:3, :3].T @ T[:3, :3]) - 1.0)
    return float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3])), float(np.arccos(np.clip(c, -1.0, 1.0)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--particles", type=int, nargs="+", default=[10, 50])
    ap.add_argument("--windows", type=int, nargs="+", default=[1, 5])
    ap.add_argument("--relin", type=float, nargs="+", default=[-1.0],
                    help="relinearisation thresholds (default -1: the tracker's own default)")
    ap.add_argument("--skip", type=int, default=20, help="latency statistics from this frame on")
    ap.add_argument("--frames", type=int, default=None, help="at most this many frames")
    args = ap.parse_args()
    rec = read_recording(args.run)
    frames = rec.frames if args.frames is None else rec.frames[: args.frames]
    obs = [observe_frame(rec, f, max_points=200) for f in frames]
    mask = np.array([o.backbone_px is not None for o in obs])
    specs = [(n, L, thr) for thr in args.relin for n in args.particles for L in args.windows]
    trackers = {}
    for n, L, thr in specs:
        t = make_tracker("svn", tracker_config(rec, "svn", n, L, seed=0))
        if thr >= 0:
            t.window.relin_threshold = thr  # a tree without the setting: its (exact) path only
        trackers[(n, L, thr)] = t
    F = len(frames)
    lat = {s: np.zeros(F) for s in specs}
    cpu = {s: np.zeros(F) for s in specs}
    its = {s: np.zeros(F) for s in specs}
    err = {s: np.zeros((F, 2)) for s in specs}
    for k, (f, o) in enumerate(zip(frames, obs, strict=True)):
        for s in specs:
            c0 = time.thread_time()
            est = trackers[s].step(o)
            cpu[s][k] = 1e3 * (time.thread_time() - c0)
            lat[s][k] = est.latency_ms
            its[s][k] = est.iterations
            err[s][k] = _errors(est.cam_T_needle, f.cam_T_needle_gt)
    sel = np.arange(F) >= args.skip
    print(f"{args.run}: {F} frames ({int(mask.sum())} with a mask), statistics over frames {args.skip}..")
    print(f"{'N':>4} {'L':>2} {'relin':>6} {'median':>7} {'mask':>7} {'nomask':>7} {'cpu':>7} {'vs L=1':>6} "
          f"{'iters':>5} {'trans mm':>8} {'rot deg':>7}")
    for n, L, thr in specs:
        s = (n, L, thr)
        base = np.median(lat[(n, min(args.windows), thr)][sel])
        used = getattr(trackers[s].window, "relin_threshold", 0.0)  # the threshold used (-1 asked for the default)
        med = np.median(lat[s][sel])
        print(f"{n:4d} {L:2d} {used:6.3f} {med:7.1f} {np.median(lat[s][sel & mask]):7.1f} "
              f"{np.median(lat[s][sel & ~mask]):7.1f} {np.median(cpu[s][sel]):7.1f} {med / base:6.2f} "
              f"{np.mean(its[s]):5.1f} {1e3 * np.nanmean(err[s][:, 0]):8.3f} "
              f"{np.degrees(np.nanmean(err[s][:, 1])):7.3f}")


if __name__ == "__main__":
    main()
