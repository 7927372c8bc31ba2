"""Tracking jobs of the experiments: simulate a set of runs, track many runs in worker processes.

Workers receive only paths and strings (GTSAM objects cannot be pickled) and build everything
themselves.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm import tqdm

if TYPE_CHECKING:
    from pinpoint_fg.sim.config import SimConfig


@dataclass(frozen=True)
class TrackJob:
    """One tracking run for a worker process (paths and strings only)."""

    run: str
    """Recording directory."""
    method: str
    """svn, svgd, pf, map or mht."""
    out: str
    """Result directory."""
    seed: int = 0
    """Tracker seed."""
    disable: tuple[str, ...] = ()
    """Likelihood switches turned off (the recording's ``suggested_disable``)."""


#: True in a pool worker once it received SIGINT (:func:`_worker_init`): it starts no further job.
_interrupted = False
#: True in a pool worker while it runs a job.
_running = False


def _on_sigint(signum: int, frame: Any) -> None:
    global _interrupted
    _interrupted = True
    if _running:  # an idle worker only remembers it (raised in its queue wait, it printed a traceback)
        raise KeyboardInterrupt


def _worker_init() -> None:
    """Pool worker initializer: Ctrl-C stops the running job (KeyboardInterrupt, as by default) and every job the
    worker is handed afterwards (a worker outlives its job's exception and would otherwise run the queued ones)."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # a caller that ignores Ctrl-C keeps ignoring it
        signal.signal(signal.SIGINT, _on_sigint)


def _guarded(fn: Callable[..., Any], *args: Any) -> Any:
    global _running
    _running = True
    try:
        if _interrupted:  # checked after _running is set: an interrupt in between is raised by the handler
            raise KeyboardInterrupt
        return fn(*args)
    finally:
        _running = False


@contextmanager
def interruptible_pool(workers: int, mp_context: Any = None) -> Iterator[Callable[..., Future]]:
    """Worker processes for jobs that stop at Ctrl-C; yields ``submit(fn, *args) -> Future``.

    A plain :class:`ProcessPoolExecutor` left by a KeyboardInterrupt waits for **every** pending job (its
    ``shutdown(wait=True)``), so an interrupted ``demo`` kept tracking the remaining runs for minutes. Here the
    pending jobs are cancelled and a worker that saw the interrupt starts no other job; the jobs already running
    stop at the same SIGINT (a terminal sends it to the whole process group) and keep their finished frames.
    """
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp_context, initializer=_worker_init)
    try:
        yield lambda fn, *args: pool.submit(_guarded, fn, *args)
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _track(job: TrackJob) -> tuple[str, float]:
    from pinpoint_fg.track import track_recording

    t0 = time.perf_counter()
    # job.out lies under the demo's/benchmark's OUT, which run_demo/run_benchmark checked (overwrite or empty)
    track_recording(job.run, job.method, job.out, seed=job.seed, disable=job.disable, progress=False,
                    overwrite=True)
    return job.out, time.perf_counter() - t0


def run_tracking(jobs: list[TrackJob], workers: int, desc: str = "tracking") -> dict[str, float]:
    """Run tracking jobs in ``workers`` processes with a progress bar; returns wall seconds per result."""
    show = sys.stderr.isatty()
    seconds: dict[str, float] = {}
    if workers <= 1:
        for job in tqdm(jobs, desc=desc, disable=not show):
            out, dt = _track(job)
            seconds[out] = dt
        return seconds
    # one BLAS thread per worker: the workers already use every core
    env = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    for k in env:
        os.environ[k] = "1"
    try:
        with interruptible_pool(workers) as submit:
            futures = [submit(_track, job) for job in jobs]
            for fut in tqdm(as_completed(futures), total=len(futures), desc=desc, disable=not show):
                out, dt = fut.result()
                seconds[out] = dt
    finally:
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return seconds


def simulate_runs(scenarios: tuple[str, ...], frames: int, seed: int, root: Path,
                  config: SimConfig | None = None) -> dict[str, Path]:
    """Simulate each scenario at ``seed`` into ``root/runs/<scenario>-<seed>`` (``config``: the simulator's
    settings, default the paper's geometry and noise); returns the run directories by scenario."""
    from pinpoint_fg.sim.scenarios import simulate

    runs = {}
    for sc in scenarios:
        runs[sc] = simulate(sc, n_frames=frames, seed=seed, out=root / "runs" / f"{sc}-{seed:02d}", config=config)
    return runs
