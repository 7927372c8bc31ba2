"""The GMM bimodality verdict's EM tolerance: verdicts and cost against a converged reference (issue 10).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/verdict_em_tol.py RUN... [--methods svn pf]
[--frames 100] [--tols 1e-3 3e-3 1e-2 3e-2] [--repeats 3]``.

Each run is tracked as ``track`` would (the recording's ``suggested_disable``, seed 0) with every method, and every
frame's particle set (with the PF's weights) is kept. Then each set gets the verdict of
:func:`pinpoint_fg.posterior.bimodality.assess_bimodality` with a converged reference fit (20 k-means++ starts,
``tol = 1e-6``, ``max_iter = 2000``) and with three starts at each ``--tols`` value. Printed per method and tolerance:
the share judged bimodal, the frames whose verdict differs from the reference's and from the first tolerance's, and
the runs they are on; last, the mean milliseconds a verdict took at each tolerance, the tolerances alternated
``--repeats`` times over every set (one thread; the machine's load moves single passes by 10-20 %).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.bimodality import EmSettings, assess_bimodality
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

REFERENCE = EmSettings(tol=1e-6, n_init=20, max_iter=2000)


def particle_sets(runs: list[Path], methods: list[str], frames: int) -> list[tuple[str, str, tuple]]:
    """``(run name, method, (particles, T_map, weights))`` for the first ``frames`` frames of every run and method."""
    out = []
    for run in runs:
        rec = read_recording(run)
        for method in methods:
            tracker = make_tracker(method, tracker_config(rec, method, disable=suggested_disable(rec), seed=0))
            for frame in rec.frames[:frames]:
                est = tracker.step(observe_frame(rec, frame))
                if est.particles.shape[0] >= 6:  # what ``track`` judges (offload.bimodality_verdict)
                    out.append((run.name, method, (est.particles, est.cam_T_needle, est.weights)))
    return out


def verdicts(sets: list[tuple[str, str, tuple]], em: EmSettings) -> tuple[np.ndarray, float]:
    """Every set's verdict under ``em`` and the seconds they took."""
    t0 = time.perf_counter()
    v = np.array([assess_bimodality(P, T, weights=w, em=em).bimodal for _, _, (P, T, w) in sets])
    return v, time.perf_counter() - t0


def main(runs: list[Path], methods: list[str], frames: int, tols: list[float], repeats: int) -> None:
    sets = particle_sets(runs, methods, frames)
    judged = [m for m in methods if any(sm == m for _, sm, _ in sets)]
    if len(judged) < len(methods):
        print(f"no verdicts for {', '.join(sorted(set(methods) - set(judged)))}: fewer than 6 particles a frame")
    if not sets:
        return
    methods = judged
    names = np.array([r for r, _, _ in sets])
    meth = np.array([m for _, m, _ in sets])
    reference, _ = verdicts(sets, REFERENCE)
    first = None
    print(f"{len(sets)} particle sets; reference: {REFERENCE}")
    for tol in tols:
        v, _ = verdicts(sets, EmSettings(tol=tol))
        first = v if first is None else first
        for m in methods:
            k = meth == m
            diff = v[k] != reference[k]
            where = {str(r): int(diff[names[k] == r].sum()) for r in np.unique(names[k]) if diff[names[k] == r].any()}
            print(f"tol {tol:<6g} {m:<4} sets {k.sum():5d}  bimodal {v[k].mean():6.1%}  differ from reference "
                  f"{diff.sum():3d}  from tol {tols[0]:g} {(v[k] != first[k]).sum():3d}  {where}")
    cost: dict[float, list[float]] = {t: [] for t in tols}
    for _ in range(repeats):
        for tol in tols:
            cost[tol].append(1e3 * verdicts(sets, EmSettings(tol=tol))[1] / len(sets))
    for tol in tols:
        print(f"tol {tol:<6g} ms per verdict: {' / '.join(f'{c:.2f}' for c in cost[tol])}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--methods", nargs="+", default=["svn", "pf"])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--tols", nargs="+", type=float, default=[1e-3, 3e-3, 1e-2, 3e-2])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    main(a.runs, a.methods, a.frames, a.tols, a.repeats)
