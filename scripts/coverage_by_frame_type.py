"""q95 coverage split by frame type (with / without a segmentation mask), and what one spread factor per type buys.

Usage: ``.venv/bin/python scripts/coverage_by_frame_type.py FIT_ROOT SCORE_ROOT [SCORE_ROOT ...]
[--methods svn,mht,map] [--scenarios slow,normal,suturing,calibration,drive] [--gate-deg 30]`` where each ROOT is
a benchmark output for one seed (``runs/`` and ``results/<scenario>/<method>``; e.g. ``bench/seed-2`` to fit on
and ``bench bench/seed-3 bench/seed-4`` to score).

Prints, per method and run of the SCORE_ROOTs, the raw coverage (share of frames whose MAP error is within the
reported q95, translation / rotation) on mask and no-mask frames and their median q95 rotation bound; then the
spread factors fitted on FIT_ROOT's runs as ``calibrate-spread`` fits them
(:func:`~pinpoint_fg.eval.spread_calibration.scale_quantile`, frames within the mode gate), once pooled over all
frames and once per frame type, and each scored run's coverage under both, with the number of runs inside
issue 9's 90-98 % band on both parts. An analysis tool: the library's spread scale has one factor per method.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.spread_calibration import frame_errors, scale_quantile
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.io.result import read_result

BAND = (90.0, 98.0)


def _load(root: Path, scenario: str, method: str) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                           np.ndarray]:
    """``(run name, err_t (m), q95_t, err_r (rad), q95_r, has mask)`` per frame with truth and finite q95."""
    runs = sorted((root / "runs").glob(f"{scenario}-*"))
    if not runs:
        raise SystemExit(f"no run {scenario}-* in {root / 'runs'}")
    rec = read_recording(runs[0], inflate=False)
    res = read_result(root / "results" / scenario / method)
    fe = frame_errors(res, rec)
    has_mask = {int(r.frame): r.mask is not None for r in rec.frames}
    mask = np.array([has_mask[int(f)] for f in res.frame])
    ok = np.isfinite(fe.err_trans_m) & np.isfinite(fe.q95_trans_m) & np.isfinite(fe.q95_rot_rad)
    return runs[0].name, fe.err_trans_m[ok], fe.q95_trans_m[ok], fe.err_rot_rad[ok], fe.q95_rot_rad[ok], mask[ok]


def _factors(et: np.ndarray, qt: np.ndarray, er: np.ndarray, qr: np.ndarray, sel: np.ndarray) -> tuple[float, float]:
    """Translation and rotation spread factors fitted on the frames ``sel``."""
    return scale_quantile(et[sel], qt[sel]), scale_quantile(er[sel], qr[sel])


def _pct(x: np.ndarray) -> float:
    return 100.0 * float(np.mean(x)) if x.size else float("nan")


def _in_band(*c: float) -> bool:
    return all(BAND[0] <= v <= BAND[1] for v in c)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("fit_root", type=Path)
    ap.add_argument("score_roots", type=Path, nargs="+")
    ap.add_argument("--methods", default="svn,mht,map")
    ap.add_argument("--scenarios", default="slow,normal,suturing,calibration,drive")
    ap.add_argument("--gate-deg", type=float, default=30.0)
    a = ap.parse_args()
    scenarios = a.scenarios.split(",")
    gate = math.radians(a.gate_deg)
    for method in a.methods.split(","):
        fit = [_load(a.fit_root, sc, method) for sc in scenarios]
        et, qt, er, qr, mk = (np.concatenate([f[k] for f in fit]) for k in (1, 2, 3, 4, 5))
        g = er <= gate  # calibrate-spread's mode gate: frames in another mode say nothing about the spread

        pooled = _factors(et, qt, er, qr, g)
        split = {b: _factors(et, qt, er, qr, g & (mk == b)) for b in (True, False)}
        print(f"{method}: factors fitted on {a.fit_root} (t/r): pooled {pooled[0]:.2f}/{pooled[1]:.2f}, "
              f"mask frames {split[True][0]:.2f}/{split[True][1]:.2f}, no-mask {split[False][0]:.2f}/"
              f"{split[False][1]:.2f}")
        print(f"  {'run':16s} {'raw mask t/r':>13s} {'raw no-mask':>13s}  {'pooled t/r':>13s} {'per type t/r':>13s}")
        n = band_pooled = band_split = 0
        for root in a.score_roots:
            for sc in scenarios:
                name, t, q_t, r, q_r, m = _load(root, sc, method)
                kt = np.where(m, split[True][0], split[False][0])
                kr = np.where(m, split[True][1], split[False][1])
                cp = (_pct(t <= pooled[0] * q_t), _pct(r <= pooled[1] * q_r))
                cs = (_pct(t <= kt * q_t), _pct(r <= kr * q_r))
                n += 1
                band_pooled += _in_band(*cp)
                band_split += _in_band(*cs)
                print(f"  {name:16s} {_pct(t[m] <= q_t[m]):5.1f}/{_pct(r[m] <= q_r[m]):5.1f}   "
                      f"{_pct(t[~m] <= q_t[~m]):5.1f}/{_pct(r[~m] <= q_r[~m]):5.1f}   {cp[0]:5.1f}/{cp[1]:5.1f}   "
                      f"{cs[0]:5.1f}/{cs[1]:5.1f}")
        print(f"  runs inside {BAND[0]:g}-{BAND[1]:g} % on both parts: pooled {band_pooled} of {n}, "
              f"per type {band_split} of {n}")


if __name__ == "__main__":
    main()
