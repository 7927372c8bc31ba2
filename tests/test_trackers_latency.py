"""Every tracker's reported ``latency_ms`` covers its whole step, the uncertainty summary included (issue 10).

The benchmark compares methods by these latencies, so a step that timed itself before summarising its particles
would look cheaper than the others. No wall-clock time is asserted: each tracker module's clock is replaced by a
fake one that advances only while the method's summary function runs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, tracker_config

#: Every function that summarises a tracker's uncertainty, by (module, name) where the trackers call it.
SUMMARIES = (
    ("pinpoint_fg.trackers.base", "tangent_spread"),  # in summarize (pf; svn before this test)
    ("pinpoint_fg.trackers.svn", "tangent_spread"),
    ("pinpoint_fg.trackers.map", "gaussian_q95"),
    ("pinpoint_fg.trackers.mht", "mixture_spread"),
)
METHODS = ("svn", "pf", "map", "mht")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("latency") / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "3", "--seed", "2", "--out", str(out)]) == 0
    return out


def _timed(f: Callable, clock: list[float], calls: list[int]) -> Callable:
    """``f``, counting its calls and advancing the fake ``clock`` by one second per call."""

    def timed(*args: object, **kwargs: object) -> object:
        calls[0] += 1
        out = f(*args, **kwargs)
        clock[0] += 1.0
        return out

    return timed


@pytest.mark.parametrize("method", METHODS)
def test_latency_includes_the_uncertainty_summary(method: str, run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [0.0]
    calls = [0]
    for module_name, name in SUMMARIES:
        module = importlib.import_module(module_name)
        monkeypatch.setattr(module, name, _timed(getattr(module, name), clock, calls))
    tracker_module = importlib.import_module(f"pinpoint_fg.trackers.{method}")
    monkeypatch.setattr(tracker_module.time, "perf_counter", lambda: clock[0])
    rec = read_recording(run)
    tracker = make_tracker(method, tracker_config(rec, method, particles=8 if method == "svn" else None, seed=0))
    for frame in rec.frames:
        before = calls[0]
        est = tracker.step(observe_frame(rec, frame))
        assert calls[0] > before, "the step summarised its uncertainty"
        assert est.latency_ms == pytest.approx(1e3 * (calls[0] - before)), "every summary inside the timed step"
