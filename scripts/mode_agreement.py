"""SVN's mode weights against MHT's on the same recordings: log-odds offsets, the modes verdict, calibration (issue 9).

Usage: ``.venv/bin/python scripts/mode_agreement.py RESULTS_DIR RUN...``, where ``RESULTS_DIR`` holds
``NAME-svn`` and ``NAME-mht`` (``pinpoint-fg track`` outputs) for each recording ``RUN`` (a run directory whose
name is ``NAME``), e.g.::

    for m in svn mht; do .venv/bin/pinpoint-fg track runs/snapshots-01 --method $m --out res/snapshots-01-$m; done
    .venv/bin/python scripts/mode_agreement.py res runs/snapshots-01

(symmetric runs are tracked with their ``suggested_disable`` as ``--disable``). Per run, then pooled over the runs:

* ``log-odds |SVN - MHT|``: on the frames where both report the same two heaviest modes (each of SVN's two within
  1 scaled unit, 5 deg / 1 mm, of a distinct MHT mode), the median of ``|log(w1/w2)_svn - log(w1/w2)_mht|``;
* SVN's modes verdict (second mode >= 0.1) on the frames MHT calls multimodal / single-mode
  (:func:`pinpoint_fg.eval.modes.reference_rates`, as ``evaluate --reference``);
* each method's minor modes' mean weight beside the share of frames whose truth is in a minor mode
  (:func:`pinpoint_fg.eval.modes.mode_weight_calibration`; equal when the weights are calibrated).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.modes import ResultModes, mode_weight_calibration, modes_of_result, reference_rates
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.trackers.svn_modes import scaled_distance


def log_odds_offsets(svn: ResultModes, svn_frames: np.ndarray, mht: ResultModes, mht_frames: np.ndarray
                     ) -> list[float]:
    """``|log-odds_svn - log-odds_mht|`` of the two heaviest modes on the frames where both hold the same two.

    ``ResultModes`` list each frame's peaks dominant first, in the order of its sorted weights (modes.csv's order).
    """
    row = {int(f): i for i, f in enumerate(svn_frames)}
    out = []
    for j, f in enumerate(mht_frames):
        i = row.get(int(f))
        if i is None or svn.peaks[i].shape[0] < 2 or mht.peaks[j].shape[0] < 2:
            continue
        d0, d1 = (scaled_distance(svn.peaks[i][k][None], mht.peaks[j]) for k in (0, 1))
        j0, j1 = int(np.argmin(d0)), int(np.argmin(d1))
        if j0 == j1 or d0[j0] > 1.0 or d1[j1] > 1.0:
            continue
        wa, wb = svn.weights[i], mht.weights[j]
        odds_a = np.log(wa[0]) - np.log(max(wa[1], 1e-300))
        odds_b = np.log(wb[j0]) - np.log(max(wb[j1], 1e-300))
        out.append(abs(float(odds_a - odds_b)))
    return out


def main(results: Path, runs: list[Path]) -> None:
    pooled: dict[str, list] = {"offsets": [], "multi": [], "single": [], "svn": [], "mht": []}
    for run in runs:
        rec = read_recording(run)
        gt = {f.frame: f.cam_T_needle_gt for f in rec}
        res = {m: read_result(results / f"{run.name}-{m}") for m in ("svn", "mht")}
        modes = {m: modes_of_result(r) for m, r in res.items()}
        offsets = log_odds_offsets(modes["svn"], res["svn"].frame, modes["mht"], res["mht"].frame)
        svn = res["svn"]
        # only the modes verdict's rates are printed: it stands in for the GMM verdict's arguments too
        rates = reference_rates(svn.frame, modes["svn"].bimodal, modes["svn"].has_modes, modes["svn"].bimodal,
                                modes["svn"].has_modes, res["mht"].frame, modes["mht"].weights)
        cal = {}
        for m, r in res.items():
            T_gt = np.stack([gt[int(f)] if gt[int(f)] is not None else np.eye(4) for f in r.frame])
            has_gt = np.array([gt[int(f)] is not None for f in r.frame])
            cal[m] = mode_weight_calibration(modes[m], T_gt, has_gt)
            if cal[m]["truth_mode_frames"]:
                pooled[m].append((cal[m]["minor_weight_mean"], cal[m]["truth_minor_share"],
                                  cal[m]["truth_mode_frames"]))
        n_multi, n_single = rates["ref_multimodal_frames"], rates["ref_single_frames"]
        r_multi, r_single = rates["bimodal_modes_ref_multi_rate"], rates["bimodal_modes_ref_single_rate"]
        pooled["offsets"] += offsets
        pooled["multi"].append((r_multi, n_multi))
        pooled["single"].append((r_single, n_single))
        med = f"{np.median(offsets):6.3f}" if offsets else "     -"
        print(f"{run.name:<16} log-odds |SVN-MHT| median {med} ({len(offsets)} frames); SVN bimodal on MHT multi "
              f"{r_multi:6.1%} ({n_multi}) / single {r_single:6.1%} ({n_single}); minor weight / truth minor: "
              + ", ".join(f"{m} {c['minor_weight_mean']:.3f} / {c['truth_minor_share']:.3f}" for m, c in cal.items()))

    def pool(pairs: list) -> str:
        n = sum(k for r, k in pairs if k)
        return f"{sum(r * k for r, k in pairs if k) / n:.1%} ({n})" if n else "- (0)"

    def pool_cal(rows: list) -> str:
        n = sum(r[2] for r in rows)
        return (f"{sum(r[0] * r[2] for r in rows) / n:.3f} / {sum(r[1] * r[2] for r in rows) / n:.3f} ({n} frames)"
                if n else "-")

    offsets = pooled["offsets"]
    print(f"pooled: log-odds |SVN-MHT| median {np.median(offsets) if offsets else float('nan'):.3f} "
          f"({len(offsets)} frames); SVN bimodal on MHT multi {pool(pooled['multi'])} / single "
          f"{pool(pooled['single'])}; minor weight / truth minor: svn {pool_cal(pooled['svn'])}, "
          f"mht {pool_cal(pooled['mht'])}")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]])
