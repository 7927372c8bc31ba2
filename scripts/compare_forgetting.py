"""SVN's per-frame evidence forgetting, 0.9 vs 1.0 (none): share of frames with a particle within 2 mm / 10 deg
of the truth, and the MAP particle's mean error, on every run of a directory (issue 9, item 2).

Usage: ``.venv/bin/python scripts/compare_forgetting.py RUNS_DIR`` (e.g. ``benchmark-output/runs`` after
``./run benchmark --quick``). Each run is tracked with its recording's ``suggested_disable``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pinpoint_fg.experiments.compare import score_run
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.track import suggested_disable, tracker_config
from pinpoint_fg.trackers.svn import SvnSettings, SvnTracker


def main(root: Path) -> None:
    for run in sorted(p for p in root.iterdir() if (p / "recording.json").exists()):
        rec = read_recording(run)
        for gamma in (0.9, 1.0):
            tracker = SvnTracker(tracker_config(rec, "svn", disable=suggested_disable(run), seed=0),
                                 SvnSettings(forgetting=gamma))
            sc = score_run(rec, tracker)
            print(f"{run.name:<16} forgetting {gamma}: truth kept {sc.kept:6.1%}  "
                  f"MAP {sc.trans_mm:5.2f} mm {sc.rot_deg:6.1f} deg", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "benchmark-output/runs"))
