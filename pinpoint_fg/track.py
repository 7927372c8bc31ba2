"""Track a recorded run with one method and write the v1 result format, frame by frame.

``track_recording(RUN, method, OUT)`` reads and validates the recording, turns each frame into
an :class:`~pinpoint_fg.observation.Observation` (undistorted keypoints, backbone pixels from the
mask, kinematics), steps the tracker, judges bimodality of the particle set, and appends the
frame to the result (flushed, so a run stopped half-way leaves every finished frame readable).
``latency_ms`` is the tracker's own step time; reading masks and the bimodality verdict are not
part of it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.bimodality import assess_bimodality
from pinpoint_fg.io.recording import Recording, read_recording
from pinpoint_fg.io.result import FrameEstimate, ResultWriter
from pinpoint_fg.likelihood import SWITCH_NAMES, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.trackers.base import Estimate, Tracker, TrackerConfig

METHODS = ("svn", "svgd", "pf", "map")
DEFAULT_PARTICLES = {"svn": 50, "svgd": 50, "pf": 3000, "map": 1}


def make_tracker(method: str, config: TrackerConfig) -> Tracker:
    """The tracker of ``method`` (svn, svgd, pf, map) with ``config``."""
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


def to_frame_estimate(est: Estimate, T_gt: np.ndarray | None = None) -> FrameEstimate:
    """Result row of an estimate, with the bimodality verdict of its particle set."""
    if est.particles.shape[0] >= 6:
        verdict = assess_bimodality(est.particles, est.cam_T_needle, weights=est.weights)
        bimodal = bool(verdict.bimodal)
    else:
        bimodal = False
    extra = {"reseeded": float(est.reseeded)}
    extra.update({k: float(v) for k, v in est.extra.items()})
    return FrameEstimate(
        frame=est.frame, t_s=est.t_s, cam_T_needle=est.cam_T_needle, q95_trans_m=est.q95_trans_m,
        q95_rot_rad=est.q95_rot_rad, bimodal=bimodal, iterations=est.iterations, latency_ms=est.latency_ms,
        particles_T=est.particles, log_posterior=est.log_posterior, weight=est.weights,
        smoothed=est.smoothed, extra=extra,
    )


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
) -> Path:
    """Track ``run`` with ``method`` and write the result directory ``out``; returns ``out``.

    ``progress`` None shows a bar only on a terminal. ``max_frames`` stops after that many frames.
    """
    recording = read_recording(run)
    noise = NoiseConfig.load(noise_file) if noise_file is not None else None
    config = tracker_config(recording, method, particles, window, noise, disable, seed)
    tracker = make_tracker(method, config)
    frames = recording.frames if max_frames is None else recording.frames[: int(max_frames)]
    if not frames:
        raise InputError("the recording has no frames", file=Path(run) / "frames.csv")
    settings = tracker.settings()
    settings["noise_file"] = None if noise_file is None else str(noise_file)
    show = sys.stderr.isatty() if progress is None else bool(progress)
    out = Path(out)
    with ResultWriter(out, method, settings, recording.info.name, str(Path(run).resolve()),
                      weighted=(method == "pf"), smoothed=config.window > 1) as writer:
        for rec in tqdm(frames, desc=f"{method} {recording.info.name}", unit="frame", disable=not show):
            obs = observe_frame(recording, rec, max_points=max_points)
            est = tracker.step(obs)
            writer.write(to_frame_estimate(est))
        final = getattr(tracker, "final_smoothed", None)
        if config.window > 1 and callable(final):
            for f, t, T in final():
                writer.write_smoothed(f, t, T)
    return out
