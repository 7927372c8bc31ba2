"""SVN vs single-mode MAP vs MHT on every run of a directory: mean errors, truth kept, modes verdict (issue 9).

Usage: ``.venv/bin/python scripts/compare_svn_map_mht.py RUNS_DIR`` (e.g. the runs of ``pinpoint-fg simulate``
for each scenario with another ``--seed`` than the benchmark's). Each run is tracked as ``track`` would (the
recording's ``suggested_disable``, seed 0), one method after the other, in this process; "kept" = some particle
within 2 mm / 10 deg of the truth, "bimodal" = the modes verdict (second mode >= 0.1).
"""

from __future__ import annotations

import sys
from pathlib import Path

from pinpoint_fg.experiments.compare import score_run
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config


def main(root: Path) -> None:
    print(f"{'run':<16} {'method':<6} {'trans mm':>8} {'rot deg':>8} {'kept':>6} {'bimodal':>8}")
    for run in sorted(p for p in root.iterdir() if (p / "recording.json").exists()):
        rec = read_recording(run)
        for method in ("svn", "map", "mht"):
            config = tracker_config(rec, method, disable=suggested_disable(run), seed=0)
            sc = score_run(rec, make_tracker(method, config))
            print(f"{run.name:<16} {method:<6} {sc.trans_mm:8.2f} {sc.rot_deg:8.1f} {sc.kept:6.1%} {sc.bimodal:8.1%}",
                  flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
