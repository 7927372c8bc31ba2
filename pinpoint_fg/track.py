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
from pathlib import Path

import numpy as np
from tqdm import tqdm

from factors.robust import RobustLoss
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.outdir import prepare_output_dir
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.likelihood import SWITCH_NAMES, Switches
from pinpoint_fg.noise import NoiseConfig
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


def _worker_init(parent_pid: int) -> None:
    """Worker initializer: one BLAS / OpenMP thread, scikit-learn loaded and warmed up, and an exit as soon as
    the tracking process is gone (e.g. SIGKILL), so no orphan keeps running or keeps the caller's pipes open.

    One thread: the worker shares the cores with the tracker; with its default pools (one thread per
    core) both processes' spinning BLAS threads fought for 2 cores, the tracker's steps took up to 3x
    longer and the worker fell behind (measured: 13.7 s of steps instead of 3.7 s, 6.8 s waiting for
    verdicts at the end of a 100-frame run).
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    # warm-up during the first steps: the first fit imports scikit-learn's mixture and k-means++
    rng = np.random.default_rng(0)
    cloud = np.tile(np.eye(4), (12, 1, 1))
    cloud[:, :3, 3] = 1e-3 * rng.normal(size=(12, 3))
    bimodality_verdict(cloud, np.eye(4), None)


class _Verdicts:
    """Per-frame summaries off the tracking thread: a worker process turns frame k's estimate into its result
    row (:func:`to_frame_estimate`: GMM verdict, mode clustering, weak direction) while the tracker steps k+1.

    The summaries (scikit-learn GMM fits, 20-30 ms) are not part of a tracker's step; computed
    inline they made ``track`` take 2x the step latencies it reported. With ``workers = 0`` they run
    inline. Rows are written in frame order either way, and are identical (seeded fits with one
    BLAS thread, deterministic clustering). The worker's start-up (spawn, imports, warm-up fit) overlaps
    the first steps; rows are collected without waiting until the last frame.
    """

    def __init__(self, workers: int) -> None:
        self.pool = None
        if workers > 0:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # spawn: the worker never inherits GTSAM state or BLAS locks; it imports scikit-learn while we track
            self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                            initializer=_worker_init, initargs=(os.getpid(),))
            self.pool.submit(os.getpid)  # workers start on the first submit: start them now
        self.pending: list = []

    def submit(self, est: Estimate) -> None:
        if self.pool is None or est.particles.shape[0] < 6:
            self.pending.append(to_frame_estimate(est))
        else:
            self.pending.append(self.pool.submit(to_frame_estimate, est))

    def ready(self, wait: bool = False) -> list[Estimate]:
        """Rows whose summaries are in, in frame order (all of them with ``wait``)."""
        out = []
        while self.pending:
            row = self.pending[0]
            if not isinstance(row, Estimate):
                if not (wait or row.done()):
                    break
                row = row.result()
            out.append(row)
            self.pending.pop(0)
        return out

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)


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
    with ResultWriter(out, method, settings, recording.info.name, str(Path(run).resolve()),
                      weighted=(method in WEIGHTED_METHODS), smoothed=config.window > 1) as writer:
        verdicts = _Verdicts(verdict_workers)
        try:
            for rec in tqdm(frames, desc=f"{method} {recording.info.name}", unit="frame", disable=not show):
                obs = observe_frame(recording, rec, max_points=max_points)
                verdicts.submit(tracker.step(obs))
                for row in verdicts.ready():
                    writer.write(row)
            for row in verdicts.ready(wait=True):
                writer.write(row)
        finally:
            verdicts.close()
        final = getattr(tracker, "final_smoothed", None)
        if config.window > 1 and callable(final):
            for f, t, T in final():
                writer.write_smoothed(f, t, T)
    return out
