"""Track a recorded run with one method and write the v1 result format, frame by frame.

``track_recording(RUN, method, OUT)`` reads and validates the recording, turns each frame into
an :class:`~pinpoint_fg.observation.Observation` (undistorted keypoints, backbone pixels from the
mask, kinematics), steps the tracker, judges bimodality of the particle set, and appends the
frame to the result (flushed, so a run stopped half-way leaves every finished frame readable).
``latency_ms`` is the tracker's own step time; reading masks and the bimodality verdict are not
part of it. With a worker process (``pinpoint-fg track``) those run beside the tracker, so the
wall time stays close to the sum of the step latencies (README, *Latency*).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from factors.robust import RobustLoss
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.jsonfile import INT64_MAX
from pinpoint_fg.io.outdir import missing_dirs, prepare_output_dir, remove_empty_dirs
from pinpoint_fg.io.recording.fingerprint import recording_fingerprint
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.particles import MAX_PARTICLES
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.io.spread_scale import SpreadScale, scaled_cov_xi, settings_entry
from pinpoint_fg.likelihood import CONIC_DISTANCES, SWITCH_NAMES, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observe import ignored_masks_note, recording_notes
from pinpoint_fg.offload import Offload, bimodality_verdict, to_frame_estimate  # noqa: F401 - track's public names
from pinpoint_fg.posterior.summary import posterior_columns
from pinpoint_fg.trackers.base import Tracker, TrackerConfig

METHODS = ("svn", "svgd", "pf", "map", "mht")
DEFAULT_PARTICLES = {"svn": 50, "svgd": 50, "pf": 3000, "map": 1, "mht": 4}
#: Methods whose particles carry weights (particles.npz has ``weight``).
WEIGHTED_METHODS = ("pf", "mht")
#: Largest accepted seed: result.json records it, and its reader takes int64 (2**64 wrote an unreadable result).
MAX_SEED = INT64_MAX


def _whole(name: str, value: object, low: int, high: int = MAX_SEED) -> int:
    """``value`` as an int in ``[low, high]``, else ValueError naming it: a float is refused, not truncated
    (``particles=10.5`` tracked with 10), and NumPy's "expected non-negative integer" named no argument."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= int(value) <= high:
        where = f"in [{low}, {high}]" if name in ("seed", "particles") else f">= {low}"
        raise ValueError(f"{name} must be a whole number {where}, got {value!r}")
    return int(value)


def _disabled(disable: object) -> tuple[str, ...]:
    """``disable`` as a tuple of known switch names; a single string was split into its letters (``"tip"``: t, i,
    p), None was "'NoneType' object is not iterable", and an unknown name was refused only after ``out`` existed."""
    if isinstance(disable, str):
        raise ValueError(f"disable must be a list of switch names, got the string {disable!r} (write [{disable!r}])")
    try:
        names = tuple(disable)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"disable must be a list of switch names, got {type(disable).__name__}") from None
    Switches.from_disabled(names)  # ValueError naming the unknown ones and the choices
    return names


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
                   seed: int = 0, conic_distance: str | None = None) -> TrackerConfig:
    """A TrackerConfig for a recording (camera, needle) with the method's default particle count.

    ``conic_distance``: the backbone residual, "sampson" or "geometric"
    (:attr:`~pinpoint_fg.likelihood.MeasurementModel.conic_distance`); None: the one ``noise`` was calibrated for,
    else "sampson"; another one than ``noise``'s is refused (:func:`resolve_conic_distance`, as ``track``)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    n = DEFAULT_PARTICLES[method] if particles is None else _whole("particles", particles, 1)
    window = _whole("window", window, 1)
    seed = _whole("seed", seed, 0)
    return TrackerConfig(
        camera=recording.info.camera, needle=recording.info.needle, noise=noise or NoiseConfig(),
        switches=Switches.from_disabled(_disabled(disable)), particles=n, window=window, seed=seed,
        conic_distance=resolve_conic_distance(conic_distance, noise, None),
    )


def suggested_disable(run: str | Path | Recording) -> tuple[str, ...]:
    """The switches a recording asks to be tracked without (recording.json ``suggested_disable``, a list of
    ``--disable`` names; absent: none). ``demo`` and ``benchmark`` honour it; ``track`` uses its own ``--disable``.
    ``run``: the run's directory, or the :class:`Recording` already read from it (not read a second time)."""
    recording = run if isinstance(run, Recording) else read_recording(run)
    path = recording.root / "recording.json"
    value = recording.info.extra.get("suggested_disable", [])
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise InputError('key "suggested_disable" must be a list of switch names', file=path)
    unknown = [v for v in value if v not in SWITCH_NAMES]
    if unknown:
        choices = ", ".join(SWITCH_NAMES)
        raise InputError(f'key "suggested_disable": unknown switch(es) {unknown}; choose from {choices}', file=path)
    return tuple(value)


def suggestion_note(recording: Recording, disable: tuple[str, ...] | list[str]) -> str | None:
    """The ``note:`` line ``track`` prints when the recording asks to be tracked without switches (recording.json
    ``suggested_disable``) that ``disable`` keeps on; None otherwise.

    Decision: ``track`` does not apply the suggestion itself. The model is what the command line says, and a
    key outside the recording format (the simulator writes it: the ``symmetric`` scenario's grasp factors) must not
    change it silently. But neither should it be ignored silently: ``demo`` and ``benchmark`` honour it, so without
    the note a user's ``track`` of such a run scored another model than the benchmark's, with nothing to say so.
    A malformed key gets no note (``track`` does not use it; ``suggested_disable`` refuses it where it is used).
    """
    try:
        wanted = suggested_disable(recording)
    except InputError:
        return None
    missing = [name for name in wanted if name not in disable]
    if not missing:
        return None
    every = ",".join(dict.fromkeys([*disable, *wanted]))
    them = "them" if len(missing) > 1 else "it"
    return (f"note: {recording.root / 'recording.json'} suggests tracking without {', '.join(missing)} "
            f"(\"suggested_disable\", which demo and benchmark follow); this run keeps {them} (track applies only "
            f"--disable): add --disable {every} to follow it")


def _thread_limit(threads: int | None) -> AbstractContextManager:
    """Context limiting the process's BLAS / OpenMP pools to ``threads`` (None: no change)."""
    if threads is None:
        return nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(threads))


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
    spread_scale: str | Path | None = None,
    conic_correlation_px: float | None = None,
    conic_distance: str | None = None,
) -> Path:
    """Track ``run`` with ``method`` and write the result directory ``out``; returns ``out``.

    ``progress`` None shows a bar only on a terminal. ``max_frames`` stops after that many frames.
    ``out`` must be new or empty unless ``overwrite`` (:func:`pinpoint_fg.io.outdir.prepare_output_dir`);
    it is checked before the recording is read, so a refused ``out`` costs nothing. An ``out`` this call created is
    removed again if the call fails before writing anything into it.
    ``verdict_workers`` processes summarise each frame (GMM verdict, modes) behind the tracker and observe frames
    ahead of it (one worker does both, more get an observer process of their own:
    :class:`~pinpoint_fg.offload.Offload`; 0: all inline, same files; ``pinpoint-fg track`` uses 1; the workers are
    spawned, so a calling script needs the usual ``if __name__ == "__main__":`` guard).
    ``robust`` (from :func:`pinpoint_fg.noise.parse_robust_spec`) replaces the robust losses of the
    noise file or the defaults; ``conic_correlation_px`` likewise the backbone residuals' correlation length
    along the arc (:mod:`factors.conic_correlation`; 0: independent pixels, the default). ``conic_distance``:
    "sampson" or "geometric" (:attr:`~pinpoint_fg.likelihood.MeasurementModel.conic_distance`); None: the one the
    noise file was calibrated for, else "sampson". Another one than the noise file's is refused (:class:`InputError`
    naming the file's ``conic_distance``): its conic sigma describes the other distance's residuals.
    ``spread_scale``: a file of ``calibrate-spread`` (:mod:`pinpoint_fg.io.spread_scale`); the q95
    columns written are the tracker's bounds times the method's factors, the covariances of ``modes.csv``
    are scaled to match (:func:`~pinpoint_fg.io.spread_scale.scaled_cov_xi`: rotation block ``kappa_rot^2``,
    translation ``kappa_trans^2``, cross ``kappa_rot kappa_trans``; the ``weak_*`` columns are those of the
    scaled covariance), and ``result.json``'s ``settings.spread_scale`` records the file and the factors (the
    tracker itself, its poses, particles and mode weights are not affected). A method the file has no factor
    for is refused before tracking.
    ``blas_threads`` limits the BLAS / OpenMP thread pools while tracking (threadpoolctl; None: leave them).
    Default 1: a frame's matrices are small (6x6 blocks, N x M pixel products), so a second thread only
    spins; on the shared 2-core machine one thread made SVN's steps 2.3x, PF's and MAP's 1.2x faster.
    The files equal, bit for bit, those of a run with ``OPENBLAS_NUM_THREADS=1`` (what ``demo`` and
    ``benchmark`` use with ``--jobs`` > 1) on any core count; a threaded BLAS rounds some sums
    differently (SVN's poses moved by <= 1.2e-15 m over a 150-frame run; PF, MAP, MHT unchanged).
    """
    # the arguments first: a refused one leaves no output directory behind
    path_argument("run", run)
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    for name, value, low in (("particles", particles, 1), ("window", window, 1), ("seed", seed, 0),
                             ("max_frames", max_frames, 1), ("blas_threads", blas_threads, 1)):
        if value is not None or name in ("window", "seed"):
            # max_frames=-1 tracked all frames but the last (a slice), silently; particles beyond what a result
            # holds were NumPy's MemoryError traceback after the run had been read
            _whole(name, value, low, MAX_PARTICLES if name == "particles" else MAX_SEED)
    _disabled(disable)
    for name, value in (("noise_file", noise_file), ("spread_scale", spread_scale)):
        if value is not None:  # a number was pathlib's TypeError; "" read the current directory as the file
            path_argument(name, value)
    if conic_correlation_px is not None:
        NoiseConfig(conic_correlation_px=conic_correlation_px)  # refused here (ValueError), before any output
    if conic_distance is not None and conic_distance not in CONIC_DISTANCES:
        raise ValueError(f"conic_distance must be one of {', '.join(CONIC_DISTANCES)}, got {conic_distance!r}")
    # read once, here: a bad file, or one of another backbone distance, is refused before any output or reading
    noise = NoiseConfig.load(noise_file) if noise_file is not None else None
    if noise is not None:
        resolve_conic_distance(conic_distance, noise, noise_file)
    if robust is not None and not isinstance(robust, Mapping):
        raise ValueError(f"robust must be a dict {{residual name: RobustLoss}} (parse_robust_spec parses a --robust "
                         f"SPEC), got {type(robust).__name__}")  # a str was "dictionary update sequence element #0"
    # Decision: ``out`` (and the parents) created here is removed again when the run fails while it is still
    # empty (a recording refused on reading, a bad spread scale): an empty directory left behind was met later as
    # a result that is not one (in a batch output, by ``evaluate``). One holding files (a result cut short) stays.
    created = missing_dirs(out)
    out = prepare_output_dir(out, overwrite, "result", inputs=(run,))
    try:
        scale = None
        if spread_scale is not None:
            scale = settings_entry(SpreadScale.load(spread_scale), method)  # refused before any work
        offload = Offload(verdict_workers, max_points)  # first: the observer starts up while we read
        failed = True
        try:
            out = _track(run, method, out, particles, window, noise_file, noise, disable, seed, progress,
                         max_frames, robust, blas_threads, offload, scale, conic_correlation_px, conic_distance)
            failed = False
        finally:
            offload.close(failed)
    except BaseException:
        remove_empty_dirs(created)
        raise
    return out


def resolve_conic_distance(asked: str | None, noise: NoiseConfig | None, noise_file: str | Path | None) -> str:
    """The backbone distance to track with: ``asked``, else the noise file's, else "sampson"; a noise file
    calibrated for another distance than ``asked`` is refused (:func:`track_recording`)."""
    recorded = None if noise is None else noise.conic_distance
    if asked is None:
        return recorded or "sampson"
    if recorded is not None and recorded != asked:
        raise InputError(f'key "conic_distance": the noise file was calibrated for the {recorded} backbone distance, '
                         f"not {asked}: track with --conic-distance {recorded}, or calibrate again with "
                         f"--conic-distance {asked}", file=Path(noise_file) if noise_file is not None else None)
    return asked


def _numerical_failure(exc: Exception) -> bool:
    """True for a tracker's numerical breakdown on degenerate input, reported as one line instead of a traceback:
    GTSAM's indeterminate linear system (a ``RuntimeError``), or non-finite numbers or a pose beyond the format's
    reach (a diverged estimate) that the result writer refuses."""
    text = str(exc)
    if isinstance(exc, RuntimeError):
        return "Indeterminate linear system" in text
    return "NaN" in text or "infinite" in text or "beyond the result format's" in text


def _first_line(exc: Exception) -> str:
    lines = [s.strip() for s in str(exc).splitlines() if s.strip()]
    return lines[0] if lines else type(exc).__name__


def _track(run: str | Path, method: str, out: Path, particles: int | None, window: int,
           noise_file: str | Path | None, noise: NoiseConfig | None, disable: tuple[str, ...] | list[str], seed: int,
           progress: bool | None, max_frames: int | None, robust: dict[str, RobustLoss] | None,
           blas_threads: int | None, offload: Offload, scale: dict | None = None,
           conic_correlation_px: float | None = None, conic_distance: str | None = None) -> Path:
    """:func:`track_recording` once ``out`` is prepared and ``offload``'s observer started.

    ``noise``: the noise file ``noise_file`` as read and checked by :func:`track_recording` (None without one).
    ``scale``: :func:`~pinpoint_fg.io.spread_scale.settings_entry` of the spread scale, or None.
    """
    # every mask is decoded through decode_image, whose check inflates it first (in the observer, beside the
    # tracker): inflating all of them here too made reading ~0.3 s of a 100-frame run's 3 s (1080 x 1080 masks)
    recording = read_recording(run, inflate=False)
    if robust is not None:
        noise = (noise or NoiseConfig()).with_robust(robust)
    if conic_correlation_px is not None:
        noise = (noise or NoiseConfig()).with_conic_correlation(conic_correlation_px)
    config = tracker_config(recording, method, particles, window, noise, disable, seed, conic_distance)
    tracker = make_tracker(method, config)
    frames = recording.frames if max_frames is None else recording.frames[: int(max_frames)]
    if not frames:
        raise InputError("the recording has no frames", file=Path(run) / "frames.csv")
    for note in recording_notes(recording, frames):
        print(note, file=sys.stderr)
    note = suggestion_note(recording, disable)
    if note is not None:
        print(note, file=sys.stderr)
    settings = tracker.settings()
    # absolute, as the recording's path: `evaluate` reads it back from any directory (relative, it found another
    # noise.json in the caller's directory, or none)
    settings["noise_file"] = None if noise_file is None else str(Path(noise_file).absolute())
    if scale is not None:
        settings["spread_scale"] = scale

    def scaled(row: Estimate) -> Estimate:
        """The row with the method's factors applied to its q95, its covariance and its modes' (whose
        least-observable direction, the ``weak_*`` columns, is then that of the scaled covariance)."""
        if scale is None:
            return row
        kt, kr = scale["kappa_trans"], scale["kappa_rot"]
        cov = None if row.cov_xi is None else scaled_cov_xi(row.cov_xi, kt, kr)
        modes, extra = row.modes, row.extra
        if modes is not None:
            modes = tuple(replace(m, cov_xi=scaled_cov_xi(m.cov_xi, kt, kr)) for m in modes)
            extra = {**extra, **posterior_columns(modes, row.cam_T_needle)}
        return replace(row, q95_trans_m=kt * row.q95_trans_m, q95_rot_rad=kr * row.q95_rot_rad, cov_xi=cov,
                       modes=modes, extra=extra)
    show = sys.stderr.isatty() if progress is None else bool(progress)
    with _thread_limit(blas_threads), ResultWriter(out, method, settings, recording.info.name,
                                                   str(Path(run).resolve()), weighted=(method in WEIGHTED_METHODS),
                                                   smoothed=config.window > 1,
                                                   recording_fingerprint=recording_fingerprint(recording)) as writer:
        ignored: list[tuple[int, str]] = []
        try:
            for obs in tqdm(offload.observations(recording, frames), desc=f"{method} {recording.info.name}",
                            unit="frame", total=len(frames), disable=not show):
                if obs.mask_ignored is not None:
                    ignored.append((obs.frame, obs.mask_ignored))
                try:
                    offload.submit(tracker.step(obs))
                    for row in offload.ready():
                        writer.write(scaled(row))
                except (RuntimeError, ValueError) as exc:
                    if isinstance(exc, InputError) or not _numerical_failure(exc):
                        raise
                    raise InputError(f"frame {obs.frame}: {method} failed on this input ({_first_line(exc)}); the "
                                     f"frames before it are in {out}", file=Path(run) / "frames.csv") from exc
            for row in offload.ready(wait=True):
                writer.write(scaled(row))
        finally:  # also when a later frame stops the run: the frames written were tracked without those masks
            if ignored:
                print(ignored_masks_note(Path(run), ignored), file=sys.stderr)
        final = getattr(tracker, "final_smoothed", None)
        if config.window > 1 and callable(final):
            for f, t, T in final():
                writer.write_smoothed(f, t, T)
    return out
