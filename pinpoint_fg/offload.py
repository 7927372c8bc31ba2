"""The work around a tracker's step that is not part of it: observing frames and completing estimates into rows.

:func:`to_frame_estimate` completes a tracker's :class:`~pinpoint_fg.estimate.Estimate` into the row a
result holds (GMM bimodality verdict, modes, summary columns). :class:`Offload` does that and the
frames' observations (:func:`pinpoint_fg.observe.observe_frame`: mask PNG check and decode,
backbone) either inline or in worker processes beside the tracker: observations ``OBSERVE_AHEAD``
frames ahead, rows behind. Whatever the worker has not finished when it is needed (its start-up,
or when it falls behind), or could not do, is computed inline instead, so the worker only ever
saves time: results are the same either way, and an error is raised from the tracking process.

This module imports neither the trackers nor scikit-learn (the first verdict does), so the
observer is ready ~0.5 s after it is spawned.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import BrokenExecutor, Executor, Future
from typing import Any

import numpy as np

from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.observation import Observation
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.bimodality import assess_bimodality
from pinpoint_fg.posterior.summary import modes_of_estimate, posterior_columns

#: Frames whose observations the worker prepares ahead of the tracker.
OBSERVE_AHEAD = 3
#: Rows left to the workers at the end of a run from which this process makes the unstarted ones itself even
#: though it has not loaded scikit-learn: the import (~0.35 s) costs about as much as the workers' backlog of
#: this many rows shared between two processes (a verdict took 20-30 ms when this was chosen; 8-12 ms since the
#: thirty-third round's EM tolerance, so the worker rarely leaves such a backlog on a clear run).
INLINE_BACKLOG = 30

#: Manager threads of worker pools :meth:`Offload.close` left shutting down (see :func:`join_stopped_workers`).
_STOPPING: list[threading.Thread] = []


def join_stopped_workers(timeout_s: float = 30.0) -> None:
    """Wait until the worker pools that :meth:`Offload.close` stopped without waiting have shut down.

    The command-line entry point calls this before returning. The interpreter waits for those pools at exit
    anyway. But its exit hook in ``concurrent.futures`` wakes each pool's manager thread through a pipe, and it
    does so without the pool's lock, while that thread may be closing the pipe. The run was then complete and
    on disk, but it printed an ``OSError: [Errno 9] Bad file descriptor`` traceback (seen once in ~40 runs; a
    known race: CPython gh-83279 / bpo-39098). After this call no pool of ours is left shutting down, so the
    exit hook has nothing to race with. It costs nothing: the process would wait for the same threads at exit.
    """
    deadline = time.monotonic() + timeout_s
    while _STOPPING:
        _STOPPING.pop().join(max(0.0, deadline - time.monotonic()))


def bimodality_verdict(particles: np.ndarray, T_map: np.ndarray, weights: np.ndarray | None) -> bool:
    """The GMM bimodality verdict of a particle set (False below 6 particles: nothing to judge)."""
    if particles.shape[0] < 6:
        return False
    return bool(assess_bimodality(particles, T_map, weights=weights).bimodal)


def to_frame_estimate(est: Estimate, T_gt: np.ndarray | None = None, bimodal: bool | None = None) -> Estimate:
    """Result row of an estimate: the GMM bimodality verdict of its particle set (computed unless given), its
    modes (modes.csv) and the extra columns ``bimodal_modes`` and ``weak_*`` (:mod:`pinpoint_fg.posterior.summary`)."""
    if bimodal is None:
        bimodal = bimodality_verdict(est.particles, est.cam_T_needle, est.weights)
    modes = modes_of_estimate(est)
    extra = {"reseeded": float(est.reseeded)}
    extra.update({k: float(v) for k, v in est.extra.items()})
    extra.update(posterior_columns(modes, est.cam_T_needle))
    return dataclasses.replace(est, bimodal=bimodal, extra=extra, modes=modes)


_RECORDING: Recording | None = None  # the observer process's copy of the recording (set by _keep)


def _worker_init(parent_pid: int) -> None:
    """Worker initializer: exit as soon as the tracking process is gone (e.g. SIGKILL), so no orphan keeps running
    or keeps the caller's pipes open; ignore Ctrl-C (the tracking process stops the workers); use one BLAS /
    OpenMP thread.

    One thread: the worker shares the cores with the tracker; with its default pools (one thread per
    core) both processes' spinning BLAS threads fought for 2 cores, the tracker's steps took up to 3x
    longer and the worker fell behind (measured: 13.7 s of steps instead of 3.7 s, then 6.8 s waiting
    for verdicts, on a 100-frame run).
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()
    # Ctrl-C is the tracking process's to handle (it stops the workers, :meth:`Offload.close`); a worker's own
    # KeyboardInterrupt printed a traceback of the queue it was waiting on
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _warm_up() -> None:
    """Row-worker task: one verdict on a fixed 12-particle cloud, so scikit-learn's mixture and k-means++ are loaded
    (~1 s) before the first row arrives rather than after it (the worker then starts that far behind)."""
    cloud = np.tile(np.eye(4), (12, 1, 1))
    cloud[:, :3, 3] = 1e-3 * np.random.default_rng(0).normal(size=(12, 3))
    bimodality_verdict(cloud, np.eye(4), None)


def _keep(recording: Recording) -> None:
    """Observer task: keep ``recording`` for the :func:`_observe` tasks that follow (one process, in order)."""
    global _RECORDING
    _RECORDING = recording


def _observe(rec: FrameRecord, max_points: int) -> Observation:
    """Observer task: :func:`observe_frame` of ``rec`` on the observer's copy of the recording."""
    if _RECORDING is None:
        raise RuntimeError("the observer has no recording")
    return observe_frame(_RECORDING, rec, max_points=max_points)


def _submit(pool: Executor | None, fn: Callable, *args: Any) -> Future | None:
    """``pool.submit(fn, *args)``; None without a pool or when it is broken (a worker died) or shut down."""
    if pool is None:
        return None
    try:
        return pool.submit(fn, *args)
    except (BrokenExecutor, RuntimeError):
        return None


def _done(fut: Future | None) -> bool:
    """Whether ``fut`` holds a result (not pending, cancelled or failed)."""
    return fut is not None and fut.done() and not fut.cancelled() and fut.exception() is None


class Offload:
    """Observations and result rows of a run, inline (``workers = 0``) or in spawned processes: ``workers`` for the
    rows, which with one worker also observes, and with more an observer of its own.

    Computed inline, the GMM fits (20-30 ms a frame then; 8-12 ms since the thirty-third round) and mask frames
    (~10 ms) made ``track`` take 2x the step latencies it reported. While a verdict cost about an SVN step, the
    worker's observations, queued behind the verdicts, were used for 0-16 of normal-01's 150 frames; with the
    cheaper verdicts, for 92-95. With two or more row workers the observations get a process of their own:
    they are on the tracker's path and rows are not, and queued behind GMM fits most of them were not ready in time
    and were made inline. With one worker (``pinpoint-fg track``'s default) they share it all the same: on two cores
    a third process cost more than it saved. Starting a worker (interpreter, imports) takes ~0.5 s of CPU, the
    row worker's scikit-learn ~0.6-0.9 s more, on a core the two workers shared while the tracker held the other;
    measured with fresh processes alternated (the twenty-ninth round, ``experiments.latency.track_wall``), one
    process for both took ``track``'s wall on normal-01 from 2.79-3.04 s to 2.24-2.68 s over 100 frames (8 of 8
    pairs faster) and from 9.49-9.82 s to 8.56-9.16 s over 500 frames (3 of 3), although more observations are
    then made inline. The workers are started at construction, so they import
    while the tracking process reads the recording (the observer is then sent it, not read twice;
    the row workers load scikit-learn: started with the first row instead, or with the first
    observation, a row worker began up to ~25 frames behind on a busy machine and the last rows were
    waited for, 0.4-1.7 s). Spawned: they inherit no
    GTSAM state or BLAS locks (a calling script needs the usual ``if __name__ == "__main__":``
    guard). Rows come out in submission order whoever made them.
    """

    def __init__(self, workers: int, max_points: int) -> None:
        self.max_points = max_points
        self.pool = self.observer = None
        self._managers: list[threading.Thread] = []
        if workers > 0:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            before = set(threading.enumerate())

            ctx = mp.get_context("spawn")
            self.pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                                            initargs=(os.getpid(),))
            for _ in range(workers):
                self.pool.submit(_warm_up)
            if workers == 1:
                self.observer = self.pool
            else:
                self.observer = ProcessPoolExecutor(1, mp_context=ctx, initializer=_worker_init,
                                                    initargs=(os.getpid(),))
                self.observer.submit(os.getpid)  # processes start on the first submit: start it now
            # the pools' manager threads (started by the first submit; their queue feeders are daemons), for
            # join_stopped_workers: found without the executors' private attributes
            self._managers = [t for t in threading.enumerate() if t not in before and not t.daemon]
        self.pending: list[Estimate | tuple[Estimate, Future]] = []

    def observations(self, recording: Recording, frames: list[FrameRecord]) -> Iterator[Observation]:
        """The observations of ``frames`` of ``recording``, in order: the observer's where it has finished them,
        else made here (and its copy cancelled if it has not started)."""
        _submit(self.observer, _keep, recording)
        ahead: deque[Future | None] = deque()
        for k, rec in enumerate(frames):
            while self.observer is not None and len(ahead) <= OBSERVE_AHEAD and k + len(ahead) < len(frames):
                ahead.append(_submit(self.observer, _observe, frames[k + len(ahead)], self.max_points))
            fut = ahead.popleft() if ahead else None
            if _done(fut):
                yield fut.result()
            else:  # inline; a failure the observer met is raised here, from this process
                if fut is not None:
                    fut.cancel()
                yield observe_frame(recording, rec, max_points=self.max_points)

    def submit(self, est: Estimate) -> None:
        """Queue ``est`` for its row (made inline without a worker or below 6 particles: no GMM to fit)."""
        fut = None if est.particles.shape[0] < 6 else _submit(self.pool, to_frame_estimate, est)
        self.pending.append(to_frame_estimate(est) if fut is None else (est, fut))

    def ready(self, wait: bool = False) -> list[Estimate]:
        """Rows that are in, in submission order. With ``wait`` all of them: those the workers have not started
        are made here, alongside the ones they are working on, when this process has scikit-learn loaded or the
        backlog is at least :data:`INLINE_BACKLOG` (otherwise the workers finish them: importing it here cost
        0.2-0.35 s per run for a backlog of a few rows); one a worker failed on is made again here."""
        if wait and ("sklearn.mixture" in sys.modules or sum(isinstance(r, tuple) for r in self.pending)
                     >= INLINE_BACKLOG):
            self.pending = [to_frame_estimate(row[0]) if isinstance(row, tuple) and row[1].cancel() else row
                            for row in self.pending]
        out = []
        while self.pending:
            row = self.pending[0]
            if isinstance(row, tuple):
                est, fut = row
                if not (wait or fut.done()):
                    break
                try:
                    row = fut.result()  # waits, with ``wait``
                except Exception:  # noqa: BLE001 - a worker failed or died: made here (its error raised from here)
                    row = to_frame_estimate(est)
            out.append(row)
            self.pending.pop(0)
        return out

    def close(self, failed: bool) -> None:
        """Stop the workers. After a failure wait for them; after success do not: every row is out, and their
        exit (interpreter clean-up, ~0.3 s) overlaps whatever the caller does next (an interpreter joins them
        at exit; :func:`join_stopped_workers` joins them earlier, as the command line does)."""
        # one worker observes too: the same pool, shut down once
        for pool in (self.pool,) if self.observer is self.pool else (self.observer, self.pool):
            if pool is not None:
                pool.shutdown(wait=failed, cancel_futures=True)
        _STOPPING.extend(t for t in self._managers if t.is_alive())
        self._managers = []
