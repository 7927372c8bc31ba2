"""pinpoint_fg.offload: the work `track` moves off the tracking thread gives the same result files as inline.

A worker process observes frames ahead (mask check, decode, backbone) and summarises each estimate
(GMM verdict, modes, weak direction) behind the tracker; whatever it has not finished is computed
inline. These tests pin the worker's functions to the inline ones, and the whole run's files.
"""

from __future__ import annotations

import csv
import io
import multiprocessing as mp
import os
import sys
from concurrent.futures import BrokenExecutor, ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.offload import Offload, _keep, _observe, _worker_init, to_frame_estimate
from pinpoint_fg.sim.scenarios import simulate
from pinpoint_fg.track import make_tracker, track_recording, tracker_config


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # masks on every 3rd frame or so: observations with and without backbones
    return simulate("rotation", n_frames=12, seed=3, out=tmp_path_factory.mktemp("verdicts") / "run")


def _without_latency(path: Path) -> list[list[str]]:
    rows = list(csv.reader(io.StringIO(path.read_text())))
    j = rows[0].index("latency_ms")
    return [r[:j] + r[j + 1 :] for r in rows]


def test_verdict_worker_matches_inline(run: Path, tmp_path: Path) -> None:
    """The whole result (estimates.csv but latency_ms, modes.csv, particles.npz, trajectory) is the same."""
    inline = track_recording(run, "svn", tmp_path / "inline", particles=12, verdict_workers=0, progress=False)
    worker = track_recording(run, "svn", tmp_path / "worker", particles=12, verdict_workers=1, progress=False)
    a, b = read_result(inline), read_result(worker)
    assert list(a.frame) == list(b.frame) == list(range(12))
    assert a.complete and b.complete
    assert _without_latency(inline / "estimates.csv") == _without_latency(worker / "estimates.csv")
    for name in ("modes.csv", "trajectory.tum", "particles.npz"):
        assert (inline / name).read_bytes() == (worker / name).read_bytes(), name


def test_worker_functions_equal_inline(run: Path) -> None:
    """What the worker process returns (observations, result rows) equals the inline computation exactly."""
    recording = read_recording(run)
    frames = recording.frames
    pool = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                               initargs=(os.getpid(),))
    try:
        pool.submit(_keep, recording)
        observed = [pool.submit(_observe, rec, 200) for rec in frames]
        tracker = make_tracker("svn", tracker_config(recording, "svn", particles=12))
        ests = []
        for rec, fut in zip(frames, observed, strict=True):
            obs = fut.result()
            here = observe_frame(recording, rec, max_points=200)
            for k in ("frame", "t_s"):
                assert getattr(obs, k) == getattr(here, k)
            for k in ("tip_px", "tail_px", "backbone_px", "cam_T_grasper"):
                x, y = getattr(obs, k), getattr(here, k)
                assert (x is None) == (y is None) and (x is None or np.array_equal(x, y)), (rec.frame, k)
            ests.append(tracker.step(obs))
        assert any(o.result().backbone_px is not None for o in observed)  # mask frames were among them
        rows = [pool.submit(to_frame_estimate, e).result() for e in ests]
    finally:
        pool.shutdown()
    for est, row in zip(ests, rows, strict=True):
        ref = to_frame_estimate(est)
        assert row.bimodal == ref.bimodal and row.extra == ref.extra
        assert len(row.modes) == len(ref.modes)
        for m, n in zip(row.modes, ref.modes, strict=True):
            assert m.weight == n.weight
            assert np.array_equal(m.cam_T_needle, n.cam_T_needle) and np.array_equal(m.cov_xi, n.cov_xi)


def test_offload_writes_rows_in_frame_order_whoever_computes_them(run: Path) -> None:
    """Rows come back in submission order, whether the worker made them or (not started yet) this process."""
    recording = read_recording(run)
    offload = Offload(1, 200)
    try:
        tracker = make_tracker("svn", tracker_config(recording, "svn", particles=12))
        obs = list(offload.observations(recording, recording.frames))
        assert [o.frame for o in obs] == [r.frame for r in recording.frames]
        ests = [tracker.step(o) for o in obs]
        offload.pool.submit(os.getpid).result()  # the worker is up
        offload.submit(ests[0])
        offload.pending[0][1].result()  # the first row: made by the worker
        for e in ests[1:]:
            offload.submit(e)
        rows = offload.ready(wait=True)  # the rest: the worker's or, where it had not started, this process's
    finally:
        offload.close(failed=False)
    assert [r.frame for r in rows] == [e.frame for e in ests]
    assert [r.bimodal for r in rows] == [to_frame_estimate(e).bimodal for e in ests]
    assert offload.pending == []


@pytest.mark.parametrize("loaded", [False, True])
def test_the_end_of_a_run_leaves_a_short_backlog_to_the_worker_unless_scikit_learn_is_loaded_here(
        run: Path, loaded: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """At the end, rows the worker has not started are made here only when that costs no scikit-learn import
    (~0.35 s): without it a short backlog is waited for, not cancelled; the rows are the same either way."""
    import sklearn.mixture  # noqa: F401 - loaded, so that removing it from sys.modules below means "not loaded"

    recording = read_recording(run)
    tracker = make_tracker("svn", tracker_config(recording, "svn", particles=12))
    ests = [tracker.step(observe_frame(recording, r)) for r in recording.frames]
    expected = [to_frame_estimate(e).bimodal for e in ests]
    if not loaded:
        monkeypatch.delitem(sys.modules, "sklearn.mixture")
    offload = Offload(1, 200)
    try:
        for e in ests:
            offload.submit(e)
        futures = [row[1] for row in offload.pending]
        rows = offload.ready(wait=True)
    finally:
        offload.close(failed=False)
    assert len(futures) == len(ests)
    assert any(f.cancelled() for f in futures) == loaded  # the worker is still importing: nothing has started
    assert [r.bimodal for r in rows] == expected


def test_track_leaves_the_callers_thread_pools_alone(run: Path, tmp_path: Path) -> None:
    """``blas_threads`` limits the pools only while tracking."""
    before = [(p["filepath"], p["num_threads"]) for p in threadpool_info()]
    track_recording(run, "map", tmp_path / "map", max_frames=3, progress=False, blas_threads=1)
    assert [(p["filepath"], p["num_threads"]) for p in threadpool_info()][: len(before)] == before


def _track_through(offload: Offload, recording: Recording) -> tuple[list, list, list]:
    """Observe every frame through ``offload``, track them with a 12-particle svn, queue the estimates and wait for
    their rows: ``(observations, estimates, rows)``."""
    got = list(offload.observations(recording, recording.frames))
    tracker = make_tracker("svn", tracker_config(recording, "svn", particles=12))
    ests = [tracker.step(o) for o in got]
    for e in ests:
        offload.submit(e)
    return got, ests, offload.ready(wait=True)


def _assert_as_inline(recording: Recording, got: list, ests: list, rows: list) -> None:
    """The observations are the inline ones (frames, backbones) and the rows come in the estimates' order."""
    for rec, obs in zip(recording.frames, got, strict=True):
        here = observe_frame(recording, rec, max_points=200)
        assert obs.frame == here.frame
        x, y = obs.backbone_px, here.backbone_px
        assert (x is None) == (y is None) and (x is None or np.array_equal(x, y))
    assert [r.frame for r in rows] == [e.frame for e in ests]


def test_everything_falls_back_inline_when_the_workers_die(run: Path) -> None:
    """Dead workers (broken pools) only cost time: every observation and row is then made in this process, equal to
    the inline ones, and in order."""
    recording = read_recording(run)
    offload = Offload(1, 200)
    try:
        assert offload.observer is offload.pool  # one worker: one process observes and makes rows
        dead = offload.pool.submit(os._exit, 3)  # the worker process dies: the pool is broken
        assert isinstance(dead.exception(), BrokenExecutor)
        got, ests, rows = _track_through(offload, recording)
    finally:
        offload.close(failed=True)
    _assert_as_inline(recording, got, ests, rows)
    assert [r.extra for r in rows] == [to_frame_estimate(e).extra for e in ests]


@pytest.mark.parametrize("workers", [1, 2])
def test_one_worker_process_observes_and_makes_rows_more_get_an_observer_of_their_own(run: Path,
                                                                                      workers: int) -> None:
    """With one worker the observer is the row worker (one process to start beside the tracker, not two); with more,
    the observer is a process of its own (``_keep``'s copy of the recording lives in one process). Either way the
    observations and rows equal the inline ones."""
    recording = read_recording(run)
    offload = Offload(workers, 200)
    try:
        assert (offload.observer is offload.pool) == (workers == 1)
        pids = {offload.pool.submit(os.getpid).result() for _ in range(8)}
        pids |= {offload.observer.submit(os.getpid).result()}
        assert len(pids) <= workers + (workers > 1)
        got, ests, rows = _track_through(offload, recording)
    finally:
        offload.close(failed=False)
    _assert_as_inline(recording, got, ests, rows)
    assert all(np.array_equal(o.tip_px, observe_frame(recording, r, max_points=200).tip_px)
               for o, r in zip(got, recording.frames, strict=True))
    assert [r.bimodal for r in rows] == [to_frame_estimate(e).bimodal for e in ests]


def test_the_command_line_returns_after_the_worker_pools_it_stopped_have_shut_down(run: Path, tmp_path: Path) -> None:
    """``Offload.close`` does not wait for the workers after a successful run, so their pools are still shutting
    down when ``track_recording`` returns; ``main`` waits for them (``join_stopped_workers``), so the interpreter's
    exit hook has no pool to race with (``OSError: [Errno 9] Bad file descriptor`` after a finished run)."""
    import threading

    from pinpoint_fg.cli import main
    from pinpoint_fg.offload import _STOPPING

    before = set(threading.enumerate())
    track_recording(run, "svn", tmp_path / "api", particles=12, max_frames=3, verdict_workers=1, progress=False)
    left = [t for t in _STOPPING if t not in before]
    assert left, "the library call returned while its pools were still shutting down (nothing for main to wait for)"
    for t in left:
        t.join(30)
    _STOPPING.clear()
    code = main(["track", str(run), "--method", "svn", "--particles", "12",
                 "--out", str(tmp_path / "cli")])
    assert code == 0
    assert not _STOPPING
    assert [t for t in threading.enumerate() if t not in before and not t.daemon] == []
