"""Bimodality verdicts judged in a worker process equal the inline ones, row for row."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.sim.scenarios import simulate
from pinpoint_fg.track import track_recording


def test_verdict_worker_matches_inline(tmp_path: Path) -> None:
    run = simulate("rotation", n_frames=10, seed=3, out=tmp_path / "run")
    inline = read_result(track_recording(run, "svn", tmp_path / "inline", particles=12, verdict_workers=0))
    worker = read_result(track_recording(run, "svn", tmp_path / "worker", particles=12, verdict_workers=1))
    assert list(worker.frame) == list(inline.frame) == list(range(10))
    assert np.array_equal(worker.bimodal, inline.bimodal)
    assert np.array_equal(worker.cam_T_needle, inline.cam_T_needle)
    assert worker.complete and inline.complete
