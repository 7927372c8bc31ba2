"""Track a recorded run with one method and write the v1 result format, frame by frame.

``track_recording(RUN, method, OUT)`` reads and validates the recording, turns each frame into
an :class:`~pinpoint_fg.observation.Observation` (undistorted keypoints, backbone pixels from the
mask, kinematics), steps the tracker, judges bimodality of the particle set, and appends the
frame to the result (flushed, so a run stopped half-way leaves every finished frame readable).
``latency_ms`` is the tracker's own step time; reading masks and the bimodality verdict are not
part of it.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

import numpy as np
from tqdm import tqdm

from factors.robust import RobustLoss
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.outdir import prepare_output_dir
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.likelihood import SWITCH_NAMES, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observation import Observation
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.bimodality import assess_bimodality
from pinpoint_fg.posterior.summary import modes_of_estimate, posterior_columns
from pinpoint_fg.trackers.base import Tracker, TrackerConfig

METHODS = ("svn", "svgd", "pf", "map", "mht")
DEFAULT_PARTICLES = {"svn": 50, "svgd": 50, "pf": 3000, "map": 1, "mht": 4}
#: Methods whose particles carry weights (particles.npz has ``weight``).
WEIGHTED_METHODS = ("pf", "mht")


def make_tracker(method: str, config: TrackerConfig) -> Tracker:
    """The tracker of ``method`` (svn, svgd, pf, map, mht) with ``config``."""
    if method == "svn":
        from pinpoint_fg.trackers.svn import SvnTracker

        return SvnTracker(config)
    if method == "svgd":
        from pinpoint_fg.trackers.svn import SvgdTracker

        return SvgdTracker(config)
    if method == "pf":
        from pinpoint_fg.trackers.pf import ParticleFilterTracker

        return ParticleFilterTracker(config)
    if method == "map":
        from pinpoint_fg.trackers.map import MapTracker

        return MapTracker(config)
    if method == "mht":
        from pinpoint_fg.trackers.mht import MhtConfig, MhtTracker

        return MhtTracker(config, MhtConfig(max_branches=config.particles))
    raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")


def tracker_config(recording: Recording, method: str, particles: int | None = None, window: int = 1,
                   noise: NoiseConfig | None = None, disable: tuple[str, ...] | list[str] = (),
                   seed: int = 0) -> TrackerConfig:
    """A TrackerConfig for a recording (camera, needle) with the method's default particle count."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    n = DEFAULT_PARTICLES[method] if particles is None else int(particles)
    if n < 1:
        raise ValueError(f"particles must be >= 1, got {n}")
    if int(window) < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    return TrackerConfig(
        camera=recording.info.camera, needle=recording.info.needle, noise=noise or NoiseConfig(),
        switches=Switches.from_disabled(tuple(disable)), particles=n, window=int(window), seed=int(seed),
    )


def suggested_disable(run: str | Path) -> tuple[str, ...]:
    """The switches a recording asks to be tracked without (recording.json ``suggested_disable``, a list of
    ``--disable`` names; absent: none). ``demo`` and ``benchmark`` honour it; ``track`` uses its own ``--disable``."""
    path = Path(run) / "recording.json"
    value = read_recording(run).info.extra.get("suggested_disable", [])
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise InputError('key "suggested_disable" must be a list of switch names', file=path)
    unknown = [v for v in value if v not in SWITCH_NAMES]
    if unknown:
        choices = ", ".join(SWITCH_NAMES)
        raise InputError(f'key "suggested_disable": unknown switch(es) {unknown}; choose from {choices}', file=path)
    return tuple(value)


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


#: Frames whose observations the worker prepares ahead of the tracker.
OBSERVE_AHEAD = 3

_RECORDING: Recording | None = None  # the worker process's copy of the recording (set by _worker_init)


def _worker_init(parent_pid: int, recording: Recording | None) -> None:
    """Worker initializer: keep the recording, use one BLAS / OpenMP thread, and exit as soon as the tracking
    process is gone (e.g. SIGKILL), so no orphan keeps running or keeps the caller's pipes open. (scikit-learn
    is imported by the first verdict, so the worker can observe frames ~1 s sooner.)

    One thread: the worker shares the cores with the tracker; with its default pools (one thread per
    core) both processes' spinning BLAS threads fought for 2 cores, the tracker's steps took up to 3x
    longer and the worker fell behind (measured: 13.7 s of steps instead of 3.7 s, 6.8 s waiting for
    verdicts at the end of a 100-frame run).
    """
    global _RECORDING
    _RECORDING = recording

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _observe(rec: FrameRecord, max_points: int) -> Observation:
    """Worker task: :func:`observe_frame` of ``rec`` on the worker's copy of the recording."""
    assert _RECORDING is not None, "the worker was started without a recording"
    return observe_frame(_RECORDING, rec, max_points=max_points)


def _thread_limit(threads: int | None) -> AbstractContextManager:
    """Context limiting the process's BLAS / OpenMP pools to ``threads`` (None: no change)."""
    if threads is None:
        return nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(threads))


class _Offload:
    """The work around a tracker's step, off the tracking thread: a worker process reads and observes frames
    ahead (mask PNG check and decode, backbone) and turns frame k's estimate into its result row
    (:func:`to_frame_estimate`: GMM verdict, modes, weak direction) while the tracker steps.

    Neither is part of a step's latency; computed inline they made ``track`` take 2x the step
    latencies it reported (GMM fits 20-30 ms, mask frames 10 ms). With ``workers = 0`` everything
    runs inline. Whatever the worker has not finished when it is needed is computed here instead
    (its start-up, ~2 s, or when it falls behind; at the end, the rows it has not started): the
    results are the same either way (deterministic observation, seeded fits with one BLAS thread,
    deterministic clustering), and rows are written in frame order.
    """

    def __init__(self, workers: int, recording: Recording, max_points: int) -> None:
        self.recording, self.max_points = recording, max_points
        self.pool = None
        if workers > 0:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # spawn: the worker never inherits GTSAM state or BLAS locks; it imports scikit-learn while we track
            self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                            initializer=_worker_init, initargs=(os.getpid(), recording))
        self.pending: list = []

    def observations(self, frames: list[FrameRecord]) -> Iterator[Observation]:
        """The observations of ``frames``, in order (the worker's when it has finished them, else made here)."""
        if self.pool is None:
            for rec in frames:
                yield observe_frame(self.recording, rec, max_points=self.max_points)
            return
        ahead: deque = deque()
        for k, rec in enumerate(frames):
            while len(ahead) <= OBSERVE_AHEAD and k + len(ahead) < len(frames):
                ahead.append(self.pool.submit(_observe, frames[k + len(ahead)], self.max_points))
            fut = ahead.popleft()
            if fut.done() and fut.exception() is None:
                yield fut.result()
            else:  # not ready (or failed: the inline call raises the same error, from this process)
                fut.cancel()
                yield observe_frame(self.recording, rec, max_points=self.max_points)

    def submit(self, est: Estimate) -> None:
        if self.pool is None or est.particles.shape[0] < 6:
            self.pending.append(to_frame_estimate(est))
        else:
            self.pending.append((est, self.pool.submit(to_frame_estimate, est)))

    def ready(self, wait: bool = False) -> list[Estimate]:
        """Rows whose summaries are in, in frame order (all of them with ``wait``: those the worker has not
        started are computed here, alongside the one it is working on)."""
        if wait:
            self.pending = [to_frame_estimate(row[0]) if not isinstance(row, Estimate) and row[1].cancel() else row
                            for row in self.pending]
        out = []
        while self.pending:
            row = self.pending[0]
            if not isinstance(row, Estimate):
                if not (wait or row[1].done()):
                    break
                row = row[1].result()
            out.append(row)
            self.pending.pop(0)
        return out

    def close(self, failed: bool) -> None:
        """Stop the worker. After a failure wait for it; after success do not: every row is written, and its
        exit (interpreter clean-up, ~0.3 s) overlaps whatever the caller does next (an interpreter joins it
        at exit)."""
        if self.pool is not None:
            self.pool.shutdown(wait=failed, cancel_futures=True)


def track_recording(
    run: str | Path,
    method: str = "svn",
    out: str | Path = "out",
    particles: int | None = None,
    window: int = 1,
    noise_file: str | Path | None = None,
    disable: tuple[str, ...] | list[str] = (),
    seed: int = 0,
    progress: bool | None = None,
    max_frames: int | None = None,
    max_points: int = 200,
    overwrite: bool = False,
    verdict_workers: int = 0,
    robust: dict[str, RobustLoss] | None = None,
    blas_threads: int | None = 1,
) -> Path:
    """Track ``run`` with ``method`` and write the result directory ``out``; returns ``out``.

    ``progress`` None shows a bar only on a terminal. ``max_frames`` stops after that many frames.
    ``out`` must be new or empty unless ``overwrite`` (:func:`pinpoint_fg.io.outdir.prepare_output_dir`);
    it is checked before the recording is read, so a refused ``out`` costs nothing.
    ``verdict_workers`` processes summarise each frame (GMM verdict, modes) alongside the tracker
    (0: inline, same rows; ``pinpoint-fg track`` uses 1; the worker is spawned, so a calling script needs the usual
    ``if __name__ == "__main__":`` guard).
    ``robust`` (from :func:`pinpoint_fg.noise.parse_robust_spec`) replaces the robust losses of the
    noise file or the defaults.
    ``blas_threads`` limits the BLAS / OpenMP thread pools while tracking (threadpoolctl; None: leave them).
    Default 1: a frame's matrices are small (6x6 blocks, N x M pixel products), so a second thread only
    spins; on the shared 2-core machine one thread made SVN's steps 2.3x, PF's and MAP's 1.2x faster,
    with bitwise the same results (``estimates.csv`` apart from ``latency_ms``, ``modes.csv``, particles).
    """
    out = prepare_output_dir(out, overwrite, "result")
    recording = read_recording(run)
    noise = NoiseConfig.load(noise_file) if noise_file is not None else None
    if robust is not None:
        noise = (noise or NoiseConfig()).with_robust(robust)
    config = tracker_config(recording, method, particles, window, noise, disable, seed)
    tracker = make_tracker(method, config)
    frames = recording.frames if max_frames is None else recording.frames[: int(max_frames)]
    if not frames:
        raise InputError("the recording has no frames", file=Path(run) / "frames.csv")
    settings = tracker.settings()
    settings["noise_file"] = None if noise_file is None else str(noise_file)
    show = sys.stderr.isatty() if progress is None else bool(progress)
    with _thread_limit(blas_threads), ResultWriter(out, method, settings, recording.info.name,
                                                   str(Path(run).resolve()), weighted=(method in WEIGHTED_METHODS),
                                                   smoothed=config.window > 1) as writer:
        offload = _Offload(verdict_workers, recording, max_points)
        failed = True
        try:
            for obs in tqdm(offload.observations(frames), desc=f"{method} {recording.info.name}", unit="frame",
                            total=len(frames), disable=not show):
                offload.submit(tracker.step(obs))
                for row in offload.ready():
                    writer.write(row)
            for row in offload.ready(wait=True):
                writer.write(row)
            failed = False
        finally:
            offload.close(failed)
        final = getattr(tracker, "final_smoothed", None)
        if config.window > 1 and callable(final):
            for f, t, T in final():
                writer.write_smoothed(f, t, T)
    return out
