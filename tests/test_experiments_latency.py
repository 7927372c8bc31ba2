"""Lock-step latency runs (:mod:`pinpoint_fg.experiments.latency`): the trackers run on the model the accuracy
tables score."""

from __future__ import annotations

from pathlib import Path

import pytest

from pinpoint_fg import track
from pinpoint_fg.experiments.latency import TrackerSpec, lockstep
from pinpoint_fg.sim.scenarios import simulate


@pytest.mark.parametrize(("disable", "expected"), [
    (None, ("grasp-perpendicular", "grasp-position")),  # the recording's suggested_disable, as benchmark tracks it
    ((), ()),
])
def test_lockstep_tracks_with_the_recordings_suggested_switches_unless_told(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, disable: tuple[str, ...] | None,
        expected: tuple[str, ...]) -> None:
    run = simulate("symmetric", 3, 1, out=tmp_path / "run")
    seen = []
    real = track.make_tracker

    def spy(method: str, config: track.TrackerConfig):  # noqa: ANN202 - the tracker, as make_tracker returns it
        seen.append((method, config.switches))
        return real(method, config)

    monkeypatch.setattr(track, "make_tracker", spy)
    res = lockstep(run, [TrackerSpec("svn", "svn", 4), TrackerSpec("map", "map")], disable=disable)
    assert [m for m, _ in seen] == ["svn", "map"]
    on = {"grasp-position": "grasp_position", "grasp-perpendicular": "grasp_perpendicular"}
    for _, switches in seen:
        assert {name for name, attr in on.items() if not getattr(switches, attr)} == set(expected)
    assert sorted(res.disabled) == sorted(expected)
    assert res.latency_ms["svn"].shape == (3,) and res.latency_ms["map"].shape == (3,)


def test_track_wall_times_each_run_in_a_fresh_process(tmp_path: Path) -> None:
    """Each run of ``track_wall`` is a command-line-like ``track`` in a process of its own: this process neither
    tracks nor loads what a run loads (scikit-learn for the verdicts), so no run finds it loaded by the one before."""
    import sys

    from pinpoint_fg.experiments import latency
    from pinpoint_fg.io.result.reader import read_result

    run = simulate("normal", 8, 2, out=tmp_path / "run")
    loaded_before = "sklearn.mixture" in sys.modules
    res = latency.track_wall(run, tmp_path / "wall", frames=6, repeats=2)
    assert ("sklearn.mixture" in sys.modules) == loaded_before
    assert len(res["runs"]) == 2 and res["ratios"] == [r["ratio"] for r in res["runs"]]
    for k, r in enumerate(res["runs"], start=1):
        assert r["ratio"] == pytest.approx(r["wall_s"] / r["step_sum_s"]) and r["wall_s"] > 0
        got = read_result(tmp_path / "wall" / f"repeat-{k}")
        assert list(got.frame) == list(range(6)) and got.complete
    with pytest.raises(latency.InputError):
        latency.track_wall(run, tmp_path / "none", frames=6, repeats=0)


def test_track_wall_reports_each_process_cpu_and_the_bound_their_work_gives(tmp_path: Path) -> None:
    """The CPU split says whether ``track``'s wall is bound by work or by its schedule: the worker's CPU (its
    start-up, with scikit-learn, and the verdicts) is counted, and the bound follows from the two figures."""
    from pinpoint_fg.experiments import latency

    run = simulate("normal", 8, 2, out=tmp_path / "run")
    res = latency.track_wall(run, tmp_path / "wall", frames=8, repeats=1)
    (r,) = res["runs"]
    # a spawned worker that imports scikit-learn and fits mixtures cannot cost less than a tenth of a second
    assert r["cpu_worker_s"] > 0.1 and r["cpu_tracker_s"] > 0
    assert r["cpu_bound"] == pytest.approx(max(r["cpu_tracker_s"], (r["cpu_tracker_s"] + r["cpu_worker_s"]) / 2)
                                           / r["step_sum_s"])
