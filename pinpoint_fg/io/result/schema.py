"""Tracking results, format version 1 (``shared/RECORDING_FORMAT.md``, second half): file names, columns, records.

A result is a directory::

    OUT/
      result.json        method, settings, recording name/path, library version, flags
      estimates.csv      one row per frame: MAP pose, q95 uncertainties, bimodal, iterations, latency
      particles.npz      the particle set of every frame (np.load(allow_pickle=False))
      trajectory.tum     "t_s x y z qx qy qz qw" per frame (MAP pose)
      smoothed.csv       with a window L > 1: the fixed-lag smoothed pose per frame
      modes.csv          when the estimates carry modes: per frame up to 4 modes (pose, weight, covariance)
      particles.journal  only while writing / after a crash: append-only copy of the particles

``result.json`` keys (all required by :func:`read_result`; more keys are allowed):
``format`` = ``"pinpoint-result"``, ``version`` = 1, ``method`` (str), ``settings`` (object),
``recording_name`` (str), ``recording_path`` (str or null), ``library_version`` (str),
``weighted`` (bool: particles.npz has ``weight``), ``smoothed`` (bool: smoothed.csv exists),
``complete`` (bool: false until the writer was closed normally). The writer also records
``frames`` (count, at close) and ``particles`` (N, at close), and ``stopped`` (the exception's
class name) when the run ended with an exception; ``track`` adds ``recording_fingerprint``
(:mod:`pinpoint_fg.io.recording.fingerprint`).

Crash safety. Every CSV/TUM row is flushed as it is written. ``particles.npz`` cannot be
appended to (its arrays are stacked over frames), so it is rewritten whole, atomically
(temporary file + ``os.replace``), and therefore always loads. Rewriting it every frame costs
O(F N) per frame, O(F^2 N) per run (3000 particles x 300 frames would be ~10 GB of writes), so
once the arrays exceed ``npz_large_bytes`` (default 64 kB: 20 frames of 50 particles) it is
rewritten at most every ``npz_min_interval_s`` seconds of wall time, and always on close. (With
the earlier default of 8 MB, a 100-frame SVN run rewrote it on every frame: 1-2 ms per frame,
mostly the ``os.replace``, more than half of the writer's time in ``track``.) So that no
finished frame is lost in between, every frame's particles are also appended (one fixed-size binary record, flushed) to
``particles.journal``; :func:`read_result` reads the journal when it holds more frames than the
npz, so a result abandoned without ``close()`` still yields every finished frame. The journal is
deleted once the final npz is in place. Trade-off: after a crash an outside tool reading only
``particles.npz`` may miss the last <= ``npz_min_interval_s`` seconds of particle frames;
``estimates.csv`` and :func:`read_result` miss nothing.

Numbers are written with ``repr`` (shortest exact text); poses as ``x y z qw qx qy qz`` with a
unit quaternion (w >= 0), read back within ~1e-16 of the matrix written. NaN is allowed (written
``nan``) in ``q95_*``, ``latency_ms`` and extra columns, nowhere else; ``q95_*`` and ``latency_ms`` are never
negative, and ``q95_*`` at most :data:`MAX_RESULT_Q95` (``evaluate`` squares them; a duration has no such use, so
``latency_ms`` has no upper bound). Rows in error messages are
1-based data rows (header not counted); for particles.npz the row is the 1-based frame position.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pinpoint_fg.posterior.modes import Mode

RESULT_FORMAT = "pinpoint-result"
RESULT_VERSION = 1
RESULT_JSON = "result.json"
ESTIMATES_CSV = "estimates.csv"
PARTICLES_NPZ = "particles.npz"
TRAJECTORY_TUM = "trajectory.tum"
SMOOTHED_CSV = "smoothed.csv"
PARTICLES_JOURNAL = "particles.journal"
MODES_CSV = "modes.csv"
POSE_COLUMNS = ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")
#: The columns of estimates.csv, in order; extra columns follow.
ESTIMATE_COLUMNS = (
    "frame", "t_s", *POSE_COLUMNS, "q95_trans_m", "q95_rot_rad", "bimodal", "iterations", "latency_ms",
)
#: The columns of smoothed.csv.
SMOOTHED_COLUMNS = ("frame", "t_s", *POSE_COLUMNS)
#: Most modes a frame may have in modes.csv.
MAX_MODES = 4
#: Largest |x|, |y|, |z| (m) of any pose a result holds (estimates, smoothed, modes, particles). Far beyond any
#: camera (a diverged tracker's estimate is still written and scored) but bounded: a hand-edited ``1e300`` overflowed
#: the evaluation's squares (``evaluate``: LinAlgError traceback). The writer refuses what the reader refuses.
MAX_ABS_RESULT_METRES = 1e6
#: Largest ``q95_trans_m`` (m) and ``q95_rot_rad`` (rad) a result holds. Decision: refused by the reader (and the
#: writer) rather than scored: a hand-edited ``1e300`` overflowed the evaluation's squares (NumPy's RuntimeWarning on
#: stderr, then NLL-S ``inf`` in summary.csv). Bound far above any real spread: particles lie within
#: :data:`MAX_ABS_RESULT_METRES` (a spread of at most ~3.5e6 m, or a few radians), times a spread-scale factor <=
#: 1e6 (``track --spread-scale``), and low enough that evaluation's own scaling (another factor <= 1e6, mm / deg)
#: squares finitely.
MAX_RESULT_Q95 = 1e15
#: The 21 upper-triangle covariance columns ``cov_ij`` (0 <= i <= j <= 5) of modes.csv, row by row.
COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(6) for j in range(i, 6))
#: The columns of modes.csv.
MODE_COLUMNS = ("frame", "mode", "weight", *POSE_COLUMNS, *COV_COLUMNS)
#: Per frame, the mode weights must sum to 1 within this.
MODE_WEIGHT_SUM_TOL = 1e-6
#: Row and column indices of the upper-triangle covariance entries, in the order of :data:`COV_COLUMNS`.
COV_INDICES = np.triu_indices(6)


@dataclass(frozen=True, eq=False)
class ParticleHistory:
    """The particle sets of a result, stacked over frames."""

    frame: np.ndarray
    """Frame indices ``(F,)``."""
    cam_T_needle: np.ndarray
    """Particle poses ``(F, N, 4, 4)``."""
    log_posterior: np.ndarray
    """Log-posteriors ``(F, N)``."""
    weight: np.ndarray | None
    """Weights ``(F, N)`` for weighted methods, else None."""

    @property
    def T(self) -> np.ndarray:
        """Alias of :attr:`cam_T_needle`, ``(F, N, 4, 4)``."""
        return self.cam_T_needle


@dataclass(frozen=True, eq=False)
class Result:
    """A tracking result read back from disk; per-frame arrays have the frame axis first."""

    root: Path
    """The result directory."""
    info: dict
    """The contents of result.json."""
    frame: np.ndarray
    """Frame indices ``(F,)`` (int)."""
    t_s: np.ndarray
    """Time stamps ``(F,)``, seconds."""
    cam_T_needle: np.ndarray
    """MAP poses ``(F, 4, 4)``."""
    q95_trans_m: np.ndarray
    """``(F,)``, metres (NaN: unknown)."""
    q95_rot_rad: np.ndarray
    """``(F,)``, radians (NaN: unknown)."""
    bimodal: np.ndarray
    """``(F,)`` bool."""
    iterations: np.ndarray
    """``(F,)`` int."""
    latency_ms: np.ndarray
    """``(F,)``, milliseconds."""
    extra: dict[str, np.ndarray]
    """Numeric extra columns of estimates.csv, each ``(F,)`` (empty cell -> NaN)."""
    smoothed: tuple[np.ndarray, np.ndarray] | None
    """``(frames (F',), cam_T_needle (F', 4, 4))`` from smoothed.csv, None without smoothing."""
    particles: ParticleHistory | None
    """The particle sets; None when no frame has been written. After a crash without the journal
    it may hold fewer frames than the estimates (a prefix of them)."""

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @property
    def complete(self) -> bool:
        """True when the writer was closed normally."""
        return bool(self.info.get("complete"))

    @property
    def method(self) -> str:
        """The tracking method's name."""
        return str(self.info["method"])


@dataclass(frozen=True, eq=False)
class ModeHistory:
    """modes.csv read back: one entry per (frame, mode) row, in file order (frame, then mode)."""

    frame: np.ndarray
    """Frame index of each row ``(M,)``."""
    mode: np.ndarray
    """Mode index within its frame ``(M,)``, 0 = heaviest."""
    weight: np.ndarray
    """Mode weight ``(M,)``; the modes of a frame sum to 1."""
    cam_T_needle: np.ndarray
    """Peak poses ``(M, 4, 4)``."""
    cov_xi: np.ndarray
    """Covariances ``(M, 6, 6)`` in GTSAM's chart at the peak, [omega; v], rad / m (symmetric)."""

    @property
    def frames(self) -> np.ndarray:
        """The distinct frames that have modes, increasing ``(F',)``."""
        return np.unique(self.frame)

    def by_frame(self) -> dict[int, tuple[Mode, ...]]:
        """Frame -> its modes, dominant first."""
        out: dict[int, list[Mode]] = {}
        for i, f in enumerate(self.frame):
            out.setdefault(int(f), []).append(Mode(self.cam_T_needle[i], float(self.weight[i]), self.cov_xi[i]))
        return {f: tuple(m) for f, m in out.items()}

    def weights_at(self, frames: np.ndarray, k: int = MAX_MODES) -> np.ndarray:
        """Sorted mode weights ``(F, k)`` of ``frames`` (zero-padded); NaN rows for frames without modes."""
        frames = np.asarray(frames, dtype=np.int64)
        W = np.full((len(frames), k), np.nan)
        pos = {int(f): i for i, f in enumerate(frames)}
        seen = set()
        for f, m, w in zip(self.frame, self.mode, self.weight, strict=True):
            i = pos.get(int(f))
            if i is None or m >= k:
                continue
            if i not in seen:
                W[i] = 0.0
                seen.add(i)
            W[i, int(m)] = w
        return W
