"""Record a tracker's per-frame outputs, compare two recordings bit for bit, and time steps (issue 10, fourth round).

A speed-up that must not change a number is checked by recording every frame's outputs with the old tree and
with the new one and comparing them (the ambiguous runs are chaotic: one changed bit can flip a later decision,
so the comparison is exact, with the largest absolute difference printed when it is not).

Usage (from a worktree, one thread)::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 PYTHONPATH=<old tree> .venv/bin/python scripts/step_outputs.py \\
        record svn /tmp/ref RUN [RUN ...]
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/step_outputs.py record svn /tmp/new RUN ...
    .venv/bin/python scripts/step_outputs.py compare /tmp/ref /tmp/new
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 [PYTHONPATH=<tree>] .venv/bin/python scripts/step_outputs.py time svn RUN

``record`` steps ``make_tracker(method, tracker_config(rec, method, disable=suggested_disable(run), seed=0))``
over every frame of each run directory and saves per frame ``cam_T_needle``, the particles, their
log-posteriors and the modes' weights and poses (``<out>/<method>_<run name>.npz``). ``compare`` prints per
file "bitwise" or "DIFF" with the largest absolute difference per field. ``time`` prints the median CPU and
wall milliseconds per step over mask frames (a backbone observed) and no-mask frames (interleave the trees'
runs on a shared machine and repeat; ``--save`` keeps the per-frame CPU times, e.g. to take each frame's
minimum over repeats, which other load on the machine can only raise).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

MAX_MODES = 8  # modes stored per frame (NaN-padded)


def _tracker(method: str, run: Path):
    rec = read_recording(run)
    return rec, make_tracker(method, tracker_config(rec, method, disable=suggested_disable(run), seed=0))


def _stack(arrays: list[np.ndarray]) -> np.ndarray:
    """One array when every frame has the same shape, else an object array (a re-seeding changes N)."""
    if len({a.shape for a in arrays}) == 1:
        return np.array(arrays)
    out = np.empty(len(arrays), dtype=object)
    out[:] = arrays
    return out


def record(method: str, out: Path, runs: list[Path]) -> None:
    """Save every frame's outputs of ``method`` on each run."""
    out.mkdir(parents=True, exist_ok=True)
    for run in runs:
        rec, tracker = _tracker(method, run)
        pose, particles, logp, mode_w, mode_pose = [], [], [], [], []
        for frame in rec.frames:
            est = tracker.step(observe_frame(rec, frame))
            pose.append(est.cam_T_needle)
            particles.append(np.asarray(est.particles))
            logp.append(np.asarray(est.log_posterior))
            modes = est.modes or ()
            w = np.full(MAX_MODES, np.nan)
            P = np.full((MAX_MODES, 4, 4), np.nan)
            for k, m in enumerate(modes[:MAX_MODES]):
                w[k], P[k] = m.weight, m.cam_T_needle
            mode_w.append(w)
            mode_pose.append(P)
        np.savez(out / f"{method}_{run.name}.npz", pose=np.array(pose), particles=_stack(particles),
                 logp=_stack(logp), mode_w=np.array(mode_w), mode_pose=np.array(mode_pose))
        print(f"{method} {run.name}: {len(pose)} frames recorded", flush=True)


def _max_abs(a: np.ndarray, b: np.ndarray) -> float:
    if a.dtype == object:
        return max((_max_abs(np.asarray(x, float), np.asarray(y, float)) for x, y in zip(a, b, strict=True)),
                   default=0.0)
    if a.shape != b.shape:
        return float("inf")
    d = np.abs(a - b)
    d = d[~(np.isnan(a) & np.isnan(b))]
    return float(d.max()) if d.size else 0.0


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype == object:
        return len(a) == len(b) and all(np.array_equal(np.asarray(x, float), np.asarray(y, float), equal_nan=True)
                                        for x, y in zip(a, b, strict=True))
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


def compare(ref: Path, new: Path) -> float:
    """Print per recording whether it is bitwise the reference; return the largest absolute difference."""
    worst = 0.0
    for f in sorted(ref.glob("*.npz")):
        g = new / f.name
        if not g.exists():
            print(f"{f.stem}: missing in {new}")
            continue
        a, b = np.load(f, allow_pickle=True), np.load(g, allow_pickle=True)
        diffs = {k: _max_abs(a[k], b[k]) for k in a.files}
        same = all(_equal(a[k], b[k]) for k in a.files)
        worst = max(worst, *diffs.values())
        print(f"{f.stem}: {'bitwise' if same else 'DIFF'} " + " ".join(f"{k}={v:.3g}" for k, v in diffs.items()))
    print(f"largest absolute difference: {worst:.3g}")
    return worst


def time_steps(method: str, run: Path, save: Path | None = None) -> None:
    """Median CPU / wall ms per step over mask and no-mask frames (``save``: per-frame CPU ms and mask flags)."""
    rec, tracker = _tracker(method, run)
    obs = [observe_frame(rec, f) for f in rec.frames]
    cpu: dict[bool, list[float]] = {True: [], False: []}
    wall: dict[bool, list[float]] = {True: [], False: []}
    per_frame = []
    for o in obs:
        c0, w0 = time.process_time(), time.perf_counter()
        tracker.step(o)
        c1, w1 = time.process_time(), time.perf_counter()
        mask = o.backbone_px is not None
        cpu[mask].append(1e3 * (c1 - c0))
        wall[mask].append(1e3 * (w1 - w0))
        per_frame.append((1e3 * (c1 - c0), mask))
    if save is not None:
        np.savez(save, cpu_ms=np.array([c for c, _ in per_frame]), mask=np.array([m for _, m in per_frame]))

    def med(a: list[float]) -> float:
        return float(np.median(a)) if a else float("nan")

    print(f"{run.name} {method}: mask n={len(cpu[True])} cpu {med(cpu[True]):.2f} wall {med(wall[True]):.2f} ms | "
          f"no-mask n={len(cpu[False])} cpu {med(cpu[False]):.2f} wall {med(wall[False]):.2f} ms | "
          f"total cpu {sum(cpu[True]) + sum(cpu[False]):.0f} ms")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("method")
    r.add_argument("out", type=Path)
    r.add_argument("runs", type=Path, nargs="+")
    c = sub.add_parser("compare")
    c.add_argument("ref", type=Path)
    c.add_argument("new", type=Path)
    t = sub.add_parser("time")
    t.add_argument("method")
    t.add_argument("run", type=Path)
    t.add_argument("--save", type=Path, default=None, help="write per-frame CPU ms and mask flags (.npz)")
    a = p.parse_args()
    if a.cmd == "record":
        record(a.method, a.out, a.runs)
    elif a.cmd == "compare":
        compare(a.ref, a.new)
    else:
        time_steps(a.method, a.run, a.save)


if __name__ == "__main__":
    main()
