"""Would one temperature calibrate the mode weights? Fit ``w ∝ w_raw^(1/tau)`` on one seed, score others (issue 9).

Usage: ``.venv/bin/python scripts/mode_weight_temperature.py BENCH_OUT [--fit-seed 2] [--test-seeds 1 3 4]
[--methods svn mht]``, where ``BENCH_OUT`` is a ``./run benchmark --unseen-seeds ...`` output directory (the
seed-1 results in ``BENCH_OUT/results/SCENARIO/METHOD``, seed K's in ``BENCH_OUT/seed-K/results/...``).

Both multi-hypothesis trackers report overconfident mode weights where modes compete (snapshots: minor modes
weigh ~0.05 where the truth lies in one on ~20 % of the frames; README, *Modes*). A temperature is the one-parameter
recalibration (as ``calibrate-spread``'s factor is for q95): on the frames where some reported mode keeps the truth
(2 mm / 10 deg, :func:`pinpoint_fg.eval.modes.peaks_near_truth`) and at least two modes are reported, ``tau``
minimises the negative log-probability the tempered weights give the truth's mode(s) (``scipy``'s bounded scalar
minimiser on ``log tau`` in [log 0.1, log 100]). Printed per method: ``tau`` fitted on the fit seed's scenarios
pooled, then per scenario over the test seeds: the minor modes' mean weight beside the share of frames whose truth
is in a minor mode (:func:`pinpoint_fg.eval.modes.mode_weight_calibration`'s pair; equal when calibrated) and the
negative log-probability of the truth's mode, raw -> tempered, and the temperature that scenario alone would take.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from pinpoint_fg.eval.modes import modes_of_result, peaks_near_truth
from pinpoint_fg.io.recording import Recording
from pinpoint_fg.io.result.reader import read_result, recording_of

SCENARIOS = ("slow", "normal", "rotation", "suturing", "calibration", "symmetric", "drive", "kinfault", "snapshots")
#: (log weights of the reported modes (M,), which of them keep the truth (M,) bool) per scored frame.
Frame = tuple[np.ndarray, np.ndarray]


def competing_frames(result: Path, cache: dict[Path, Recording]) -> list[Frame]:
    """The frames of ``result`` with >= 2 reported modes, one of which keeps the truth."""
    res = read_result(result)
    truth = {f.frame: f.cam_T_needle_gt for f in recording_of(res, cache).frames}
    T_gt = np.stack([truth[int(f)] if truth[int(f)] is not None else np.eye(4) for f in res.frame])
    has_gt = np.array([truth[int(f)] is not None for f in res.frame])
    modes = modes_of_result(res)
    out = []
    for i, near in peaks_near_truth(modes, T_gt, has_gt).items():
        if near.any() and near.shape[0] > 1:
            out.append((np.log(np.maximum(modes.weights[i, : near.shape[0]], 1e-300)), near))
    return out


def tempered(log_w: np.ndarray, tau: float) -> np.ndarray:
    z = log_w / tau
    p = np.exp(z - z.max())
    return p / p.sum()


def nll(frames: list[Frame], tau: float) -> float:
    """Negative log-probability the tempered weights give the truth's mode(s), summed over ``frames``."""
    return float(-sum(np.log(max(tempered(lw, tau)[near].sum(), 1e-300)) for lw, near in frames))


def calibration(frames: list[Frame], tau: float) -> tuple[float, float]:
    """(minor modes' mean weight, share of frames whose truth is in a minor mode and not the dominant one)."""
    minor, in_minor = [], []
    for lw, near in frames:
        p = tempered(lw, tau)
        d = int(np.argmax(p))
        minor.append(1.0 - p[d])
        in_minor.append(not near[d])
    return float(np.mean(minor)), float(np.mean(in_minor))


def fit_tau(frames: list[Frame]) -> float:
    r = minimize_scalar(lambda lt: nll(frames, float(np.exp(lt))), bounds=(np.log(0.1), np.log(100.0)),
                        method="bounded")
    return float(np.exp(r.x))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path)
    ap.add_argument("--fit-seed", type=int, default=2)
    ap.add_argument("--test-seeds", type=int, nargs="+", default=[1, 3, 4])
    ap.add_argument("--methods", nargs="+", default=["svn", "mht"])
    args = ap.parse_args()

    def path(seed: int, scenario: str, method: str) -> Path:
        base = args.bench if seed == 1 else args.bench / f"seed-{seed}"
        return base / "results" / scenario / method

    cache: dict[Path, Recording] = {}
    for method in args.methods:
        seeds = [args.fit_seed, *args.test_seeds]
        frames = {(s, sc): competing_frames(path(s, sc, method), cache) for s in seeds for sc in SCENARIOS
                  if path(s, sc, method).is_dir()}
        train = [f for (s, _), fs in frames.items() if s == args.fit_seed for f in fs]
        if not train:
            print(f"{method}: no frame with two modes and the truth in one on seed {args.fit_seed}")
            continue
        tau = fit_tau(train)
        print(f"{method}: tau {tau:.2f} fitted on seed {args.fit_seed}'s {len(train)} frames with competing modes; "
              f"seeds {' '.join(map(str, args.test_seeds))}:")
        print(f"  {'scenario':<12} frames  minor w / truth minor, raw -> tempered    NLL raw -> tempered   own tau")
        for sc in SCENARIOS:
            test = [f for s in args.test_seeds for f in frames.get((s, sc), [])]
            if not test:
                continue
            (w0, t0), (w1, t1) = calibration(test, 1.0), calibration(test, tau)
            print(f"  {sc:<12} {len(test):6d}  {w0:.3f} / {t0:.3f} -> {w1:.3f} / {t1:.3f}"
                  f"          {nll(test, 1.0):7.1f} -> {nll(test, tau):7.1f}   {fit_tau(test):7.2f}")


if __name__ == "__main__":
    main()
