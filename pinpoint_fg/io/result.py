"""Tracking results, format version 1 (``shared/RECORDING_FORMAT.md``, second half): writer and reader.

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
class name) when the run ended with an exception.

Crash safety. Every CSV/TUM row is flushed as it is written. ``particles.npz`` cannot be
appended to (its arrays are stacked over frames), so it is rewritten whole, atomically
(temporary file + ``os.replace``), and therefore always loads. Rewriting it every frame costs
O(F N) per frame, O(F^2 N) per run (3000 particles x 300 frames would be ~10 GB of writes), so
once the arrays exceed ``npz_large_bytes`` it is rewritten at most every ``npz_min_interval_s``
seconds of wall time, and always on close. So that no finished frame is lost in between, every
frame's particles are also appended (one fixed-size binary record, flushed) to
``particles.journal``; :func:`read_result` reads the journal when it holds more frames than the
npz, so a result abandoned without ``close()`` still yields every finished frame. The journal is
deleted once the final npz is in place. Trade-off: after a crash an outside tool reading only
``particles.npz`` may miss the last <= ``npz_min_interval_s`` seconds of particle frames;
``estimates.csv`` and :func:`read_result` miss nothing.

Numbers are written with ``repr`` (shortest exact text); poses as ``x y z qw qx qy qz`` with a
unit quaternion (w >= 0), read back within ~1e-16 of the matrix written. NaN is allowed (written
``nan``) in ``q95_*``, ``latency_ms`` and extra columns, nowhere else. Rows in error messages are
1-based data rows (header not counted); for particles.npz the row is the 1-based frame position.
"""

from __future__ import annotations

import csv
import dataclasses
import enum
import io
import json
import math
import os
import re
import tempfile
import time
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import pinpoint_fg
from factors.geometry import pose_from_xyz_quat, xyz_quat_from_pose
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import load_json
from pinpoint_fg.io.recording.schema import MAX_FRAME_INDEX, QUAT_NORM_TOL, json_shown, shown
from pinpoint_fg.io.recording.writer import atomic_write_text, check_pose
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
#: The 21 upper-triangle covariance columns ``cov_ij`` (0 <= i <= j <= 5) of modes.csv, row by row.
COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(6) for j in range(i, 6))
#: The columns of modes.csv.
MODE_COLUMNS = ("frame", "mode", "weight", *POSE_COLUMNS, *COV_COLUMNS)
#: Per frame, the mode weights must sum to 1 within this.
MODE_WEIGHT_SUM_TOL = 1e-6
_IU = np.triu_indices(6)

_JOURNAL_MAGIC = b"PPFGJRN1"
_JOURNAL_HEADER_BYTES = 32  # magic (8) + N (int64) + weighted (int64) + reserved (int64)


def _journal_dtype(n: int, weighted: bool) -> np.dtype:
    fields: list[tuple[Any, ...]] = [
        ("frame", "<i8"),
        ("xyz_m", "<f8", (n, 3)),
        ("quat_wxyz", "<f8", (n, 4)),
        ("log_posterior", "<f8", (n,)),
    ]
    if weighted:
        fields.append(("weight", "<f8", (n,)))
    return np.dtype(fields)


@dataclass(frozen=True, eq=False)
class FrameEstimate:
    """What a tracker reports for one frame (one row of every result file)."""

    frame: int
    """Frame index in the recording."""
    t_s: float
    """Time stamp, seconds."""
    cam_T_needle: np.ndarray
    """MAP pose ``(4, 4)``."""
    q95_trans_m: float
    """95th percentile of the particles' translation distance to the MAP, metres (NaN: unknown)."""
    q95_rot_rad: float
    """95th percentile of the particles' rotation angle to the MAP, radians (NaN: unknown)."""
    bimodal: bool
    """Bimodality verdict of the particle set."""
    iterations: int
    """Transport / optimiser iterations spent on this frame."""
    latency_ms: float
    """Wall time of the frame's update, milliseconds."""
    particles_T: np.ndarray
    """Particle poses ``cam_T_needle``, ``(N, 4, 4)`` (N fixed for a run)."""
    log_posterior: np.ndarray
    """Unnormalised log-posterior of each particle, ``(N,)``."""
    weight: np.ndarray | None = None
    """Importance weights ``(N,)`` for weighted methods (PF), else None."""
    smoothed: tuple[int, float, np.ndarray] | None = None
    """Fixed-lag estimate ``(frame, t_s, cam_T_needle (4, 4))`` of frame k - L + 1, when available."""
    extra: dict[str, float] = field(default_factory=dict)
    """More numeric columns for estimates.csv (e.g. ``{"reseeded": 1.0}``)."""
    modes: tuple[Mode, ...] | None = None
    """Posterior modes of the frame (written to modes.csv, dominant first), None: no modes.csv rows."""


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


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _jsonable(obj: Any, path: str = "settings") -> Any:
    """Convert settings to plain JSON values (numpy scalars/arrays, paths, tuples, dataclasses, enums)."""
    if obj is None or isinstance(obj, bool | str):
        return obj
    if isinstance(obj, enum.Enum):
        return _jsonable(obj.value, path)
    if isinstance(obj, np.generic):
        return _jsonable(obj.item(), path)
    if isinstance(obj, int):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else repr(obj)
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist(), path)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name), f"{path}.{f.name}") for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v, f"{path}.{k}") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v, f"{path}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, set | frozenset):
        return sorted(_jsonable(v, path) for v in obj)
    raise ValueError(f"{path}: {type(obj).__name__} is not JSON serialisable")


def _cell(x: float) -> str:
    return repr(float(x))


def _pose_cells(T: np.ndarray) -> list[str]:
    xyz, q = xyz_quat_from_pose(T)
    return [_cell(v) for v in xyz] + [_cell(v) for v in q]


def _scalar(name: str, v: Any, allow_nan: bool) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}") from None
    if math.isinf(x) or (math.isnan(x) and not allow_nan):
        raise ValueError(f"{name} must be finite{' or NaN' if allow_nan else ''}, got {x!r}")
    return x


def _check_modes(where: str, modes: Any) -> tuple[Mode, ...]:
    """Validated modes, sorted by decreasing weight (stable); ``ValueError`` naming ``where`` otherwise."""
    modes = tuple(modes)
    if not 1 <= len(modes) <= MAX_MODES:
        raise ValueError(f"{where}: modes must hold 1 to {MAX_MODES} modes, got {len(modes)}")
    for k, m in enumerate(modes):
        check_pose(f"{where}: mode {k} cam_T_needle", m.cam_T_needle)
        wk = _scalar(f"{where}: mode {k} weight", m.weight, allow_nan=False)
        if not 0.0 <= wk <= 1.0:
            raise ValueError(f"{where}: mode {k} weight must lie in [0, 1], got {wk!r}")
        C = np.asarray(m.cov_xi, dtype=float)
        if C.shape != (6, 6) or not np.all(np.isfinite(C)):
            raise ValueError(f"{where}: mode {k} cov_xi must be a finite (6, 6) array")
        if np.max(np.abs(C - C.T)) > 1e-9 * max(float(np.max(np.abs(C))), 1e-300):
            raise ValueError(f"{where}: mode {k} cov_xi is not symmetric")
    total = math.fsum(float(m.weight) for m in modes)
    if abs(total - 1.0) > MODE_WEIGHT_SUM_TOL:
        raise ValueError(f"{where}: mode weights sum to {total!r}, not 1 (tolerance {MODE_WEIGHT_SUM_TOL:g})")
    return tuple(sorted(modes, key=lambda m: -float(m.weight)))


class ResultWriter:
    """Writes a v1 result frame by frame; a context manager (see the module docstring for the files).

    ``result.json`` is written at creation with ``"complete": false`` and rewritten on
    :meth:`close` with ``true``. Each :meth:`write` appends (and flushes) the frame's particles to
    the journal, then its row of estimates.csv, its line of trajectory.tum and, when it carries
    one, its smoothed row. particles.npz is rewritten atomically after every frame while its
    arrays are smaller than ``npz_large_bytes``, afterwards at most every ``npz_min_interval_s``
    seconds, and always on close. N (particles) is fixed for a run; a change raises ValueError.
    Existing result files in ``out_dir`` are replaced. A frame that carries ``modes`` also gets its
    rows in modes.csv (opened at the first such frame, flushed per frame; ``frame, mode, weight``,
    the peak pose, the 21 upper-triangle ``cov_ij``): 1 to :data:`MAX_MODES` modes, weights in
    [0, 1] summing to 1 within 1e-6, written by decreasing weight; :func:`read_modes` reads them.
    """

    def __init__(
        self,
        out_dir: str | Path,
        method: str,
        settings: dict,
        recording_name: str,
        recording_path: str | None = None,
        weighted: bool = False,
        smoothed: bool = False,
        *,
        npz_large_bytes: int = 8_000_000,
        npz_min_interval_s: float = 2.0,
    ) -> None:
        self.out_dir = Path(out_dir)
        self.weighted = bool(weighted)
        self.smoothed = bool(smoothed)
        self.npz_large_bytes = int(npz_large_bytes)
        self.npz_min_interval_s = float(npz_min_interval_s)
        self._info: dict[str, Any] = {
            "format": RESULT_FORMAT,
            "version": RESULT_VERSION,
            "method": str(method),
            "settings": _jsonable(settings),
            "recording_name": str(recording_name),
            "recording_path": None if recording_path is None else str(recording_path),
            "library_version": pinpoint_fg.__version__,
            "weighted": self.weighted,
            "smoothed": self.smoothed,
            "complete": False,
        }
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for name in (ESTIMATES_CSV, PARTICLES_NPZ, TRAJECTORY_TUM, SMOOTHED_CSV, PARTICLES_JOURNAL, MODES_CSV):
            (self.out_dir / name).unlink(missing_ok=True)
        self._write_info()
        self._tum = open(self.out_dir / TRAJECTORY_TUM, "w", encoding="utf-8")
        self._est: Any = None  # estimates.csv, opened at the first frame (its header needs the extra keys)
        self._est_csv: Any = None
        self._extra_keys: tuple[str, ...] | None = None
        self._smooth: Any = None
        self._smooth_csv: Any = None
        if self.smoothed:
            self._smooth = open(self.out_dir / SMOOTHED_CSV, "w", encoding="utf-8", newline="")
            self._smooth_csv = csv.writer(self._smooth, lineterminator="\n")
            self._smooth_csv.writerow(SMOOTHED_COLUMNS)
            self._smooth.flush()
        self._modes: Any = None  # modes.csv, opened at the first frame with modes
        self._modes_csv: Any = None
        self._journal: Any = None
        self._journal_dtype: np.dtype | None = None
        self._n: int | None = None
        self._frames: list[int] = []
        self._xyz: list[np.ndarray] = []
        self._quat: list[np.ndarray] = []
        self._logp: list[np.ndarray] = []
        self._weight: list[np.ndarray] = []
        self._last_frame: int | None = None
        self._last_smoothed: int | None = None
        self._npz_frames = 0
        self._npz_time = -math.inf
        self._closed = False

    # -- context manager -------------------------------------------------------------------
    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        self._finish(stopped=None if exc_type is None else exc_type.__name__)

    @property
    def frames_written(self) -> int:
        """Number of frames written so far."""
        return len(self._frames)

    def _write_info(self) -> None:
        text = json.dumps(self._info, indent=2, allow_nan=False) + "\n"
        atomic_write_text(self.out_dir / RESULT_JSON, text)

    # -- per frame -------------------------------------------------------------------------
    def _check(self, est: FrameEstimate) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        if isinstance(est.frame, bool) or not isinstance(est.frame, int | np.integer) or est.frame < 0:
            raise ValueError(f"frame must be a non-negative integer, got {est.frame!r}")
        f = int(est.frame)
        if self._last_frame is not None and f <= self._last_frame:
            raise ValueError(f"frame {f} is not greater than the previous frame {self._last_frame}")
        _scalar(f"frame {f}: t_s", est.t_s, allow_nan=False)
        check_pose(f"frame {f}: cam_T_needle", est.cam_T_needle)
        for name in ("q95_trans_m", "q95_rot_rad", "latency_ms"):
            _scalar(f"frame {f}: {name}", getattr(est, name), allow_nan=True)
        if not isinstance(est.bimodal, bool | np.bool_) and est.bimodal not in (0, 1):
            raise ValueError(f"frame {f}: bimodal must be a bool, got {est.bimodal!r}")
        it = est.iterations
        if isinstance(it, bool) or not isinstance(it, int | np.integer) or it < 0:
            raise ValueError(f"frame {f}: iterations must be a non-negative integer, got {est.iterations!r}")
        P = np.asarray(est.particles_T, dtype=float)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] < 1:
            raise ValueError(f"frame {f}: particles_T must have shape (N, 4, 4) with N >= 1, got {P.shape}")
        n = P.shape[0]
        if self._n is not None and n != self._n:
            raise ValueError(f"frame {f}: {n} particles, but this run has N = {self._n} (N is fixed per run)")
        if not np.all(np.isfinite(P)):
            raise ValueError(f"frame {f}: particles_T contains NaN or infinite values")
        R = P[:, :3, :3]
        ortho = np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)), axis=(1, 2))
        if np.any(ortho > 1e-6) or np.any(np.linalg.det(R) <= 0):
            raise ValueError(f"frame {f}: particles_T has rotation blocks that are not proper rotations")
        logp = np.asarray(est.log_posterior, dtype=float)
        if logp.shape != (n,):
            raise ValueError(f"frame {f}: log_posterior must have shape ({n},), got {logp.shape}")
        if np.any(np.isnan(logp)) or np.any(logp == np.inf):
            raise ValueError(f"frame {f}: log_posterior contains NaN or +inf")
        w = None
        if self.weighted:
            if est.weight is None:
                raise ValueError(f"frame {f}: this result is weighted but the estimate has no weight")
            w = np.asarray(est.weight, dtype=float)
            if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError(f"frame {f}: weight must be a finite non-negative ({n},) array")
        elif est.weight is not None:
            raise ValueError(f"frame {f}: weight given, but the writer was created with weighted=False")
        if est.smoothed is not None and not self.smoothed:
            raise ValueError(f"frame {f}: smoothed estimate given, but the writer has smoothed=False")
        for k, v in est.extra.items():
            if not isinstance(k, str) or k in ESTIMATE_COLUMNS or not k:
                raise ValueError(f"frame {f}: extra key {k!r} is empty, not a string, or a standard column")
            _scalar(f"frame {f}: extra[{k!r}]", v, allow_nan=True)
        if self._extra_keys is not None:
            new = [k for k in est.extra if k not in self._extra_keys]
            if new:
                raise ValueError(
                    f"frame {f}: extra keys {new} were not among the first frame's extras "
                    f"{list(self._extra_keys)}"
                )
        return P, logp, w, np.asarray(est.cam_T_needle, dtype=float)

    def write(self, est: FrameEstimate) -> None:
        """Append one frame to every file (particles first, then the rows), each flushed."""
        if self._closed:
            raise ValueError("ResultWriter is closed")
        P, logp, w, T = self._check(est)
        f = int(est.frame)
        modes = None if est.modes is None else _check_modes(f"frame {f}", est.modes)
        xyz, quat = xyz_quat_from_pose(P)
        if self._n is None:
            self._n = P.shape[0]
            self._open_journal()
        assert self._journal_dtype is not None
        rec = np.zeros((), dtype=self._journal_dtype)
        rec["frame"], rec["xyz_m"], rec["quat_wxyz"], rec["log_posterior"] = f, xyz, quat, logp
        if w is not None:
            rec["weight"] = w
        self._journal.write(rec.tobytes())
        self._journal.flush()
        self._frames.append(f)
        self._xyz.append(xyz)
        self._quat.append(quat)
        self._logp.append(logp.copy())
        if w is not None:
            self._weight.append(w.copy())
        self._last_frame = f
        self._maybe_write_npz()

        if self._est is None:
            self._extra_keys = tuple(est.extra)
            self._open_estimates()
        assert self._extra_keys is not None
        row = [str(f), _cell(est.t_s), *_pose_cells(T), _cell(est.q95_trans_m), _cell(est.q95_rot_rad),
               "1" if bool(est.bimodal) else "0", str(int(est.iterations)), _cell(est.latency_ms)]
        row += [_cell(est.extra[k]) if k in est.extra else "" for k in self._extra_keys]
        self._est_csv.writerow(row)
        self._est.flush()
        xyz_t, q = xyz_quat_from_pose(T)
        self._tum.write(" ".join(_cell(v) for v in (est.t_s, *xyz_t, q[1], q[2], q[3], q[0])) + "\n")
        self._tum.flush()
        if modes is not None:
            self._write_modes(f, modes)
        if est.smoothed is not None:
            self.write_smoothed(*est.smoothed)

    def _write_modes(self, frame: int, modes: tuple[Mode, ...]) -> None:
        if self._modes is None:
            self._modes = open(self.out_dir / MODES_CSV, "w", encoding="utf-8", newline="")
            self._modes_csv = csv.writer(self._modes, lineterminator="\n")
            self._modes_csv.writerow(MODE_COLUMNS)
        for k, m in enumerate(modes):
            C = np.asarray(m.cov_xi, dtype=float)
            self._modes_csv.writerow([str(frame), str(k), _cell(m.weight), *_pose_cells(np.asarray(m.cam_T_needle)),
                                      *(_cell(v) for v in C[_IU])])
        self._modes.flush()

    def write_smoothed(self, frame: int, t_s: float, cam_T_needle: np.ndarray) -> None:
        """Append a smoothed estimate (also for the last L-1 frames when the run ends); flushed."""
        if self._closed:
            raise ValueError("ResultWriter is closed")
        if not self.smoothed:
            raise ValueError("smoothed estimate given, but the writer was created with smoothed=False")
        f = int(frame)
        if self._last_smoothed is not None and f <= self._last_smoothed:
            raise ValueError(f"smoothed frame {f} is not greater than the previous one {self._last_smoothed}")
        _scalar(f"smoothed frame {f}: t_s", t_s, allow_nan=False)
        T = check_pose(f"smoothed frame {f}: cam_T_needle", cam_T_needle)
        self._smooth_csv.writerow([str(f), _cell(t_s), *_pose_cells(T)])
        self._smooth.flush()
        self._last_smoothed = f

    def _open_journal(self) -> None:
        assert self._n is not None
        self._journal_dtype = _journal_dtype(self._n, self.weighted)
        self._journal = open(self.out_dir / PARTICLES_JOURNAL, "wb")
        header = _JOURNAL_MAGIC + np.array([self._n, int(self.weighted), 0], dtype="<i8").tobytes()
        assert len(header) == _JOURNAL_HEADER_BYTES
        self._journal.write(header)

    def _open_estimates(self) -> None:
        assert self._extra_keys is not None
        self._est = open(self.out_dir / ESTIMATES_CSV, "w", encoding="utf-8", newline="")
        self._est_csv = csv.writer(self._est, lineterminator="\n")
        self._est_csv.writerow([*ESTIMATE_COLUMNS, *self._extra_keys])
        self._est.flush()

    def _maybe_write_npz(self) -> None:
        n = self._n or 0
        nbytes = len(self._frames) * n * (3 + 4 + 1 + int(self.weighted)) * 8
        if nbytes <= self.npz_large_bytes or time.monotonic() - self._npz_time >= self.npz_min_interval_s:
            self._write_npz()

    def _write_npz(self) -> None:
        n = self._n or 0
        F = len(self._frames)
        arrays: dict[str, np.ndarray] = {
            "frame": np.asarray(self._frames, dtype=np.int64),
            "xyz_m": np.stack(self._xyz) if F else np.zeros((0, n, 3)),
            "quat_wxyz": np.stack(self._quat) if F else np.zeros((0, n, 4)),
            "log_posterior": np.stack(self._logp) if F else np.zeros((0, n)),
        }
        if self.weighted:
            arrays["weight"] = np.stack(self._weight) if F else np.zeros((0, n))
        path = self.out_dir / PARTICLES_NPZ
        fd, tmp = tempfile.mkstemp(dir=self.out_dir, prefix=f".{PARTICLES_NPZ}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        self._npz_frames = F
        self._npz_time = time.monotonic()

    # -- closing ---------------------------------------------------------------------------
    def _finish(self, stopped: str | None) -> None:
        if self._closed:
            return
        self._closed = True
        self._write_npz()
        if self._est is None:
            self._extra_keys = ()
            self._open_estimates()
        for fh in (self._est, self._tum, self._smooth, self._journal, self._modes):
            if fh is not None:
                fh.close()
        self._info["complete"] = stopped is None
        self._info["frames"] = len(self._frames)
        self._info["particles"] = self._n
        if stopped is not None:
            self._info["stopped"] = stopped
        self._write_info()
        (self.out_dir / PARTICLES_JOURNAL).unlink(missing_ok=True)

    def close(self) -> None:
        """Write the final particles.npz, close every file, mark result.json complete (idempotent)."""
        self._finish(stopped=None)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NAN = re.compile(r"[+-]?nan", re.IGNORECASE)
_INTEGER = re.compile(r"\d+")


#: Largest accepted particle count N of a journal header (a corrupt header must not allocate terabytes).
MAX_PARTICLES = 10_000_000


def _read_info(root: Path) -> dict:
    path = root / RESULT_JSON
    doc = load_json(path, missing="file not found (a result needs result.json)")
    if not isinstance(doc, dict):
        raise InputError("the top level must be a JSON object", file=path)
    types: dict[str, tuple[type, ...]] = {
        "format": (str,), "version": (int,), "method": (str,), "settings": (dict,), "recording_name": (str,),
        "recording_path": (str, type(None)), "library_version": (str,), "weighted": (bool,),
        "smoothed": (bool,), "complete": (bool,),
    }
    for key, allowed in types.items():
        if key not in doc:
            raise InputError("missing required key", file=path, column=key)
        v = doc[key]
        if not isinstance(v, allowed) or (bool not in allowed and isinstance(v, bool)):
            names = " or ".join("null" if t is type(None) else t.__name__ for t in allowed)
            raise InputError(f"must be {names}, got {json_shown(v)}", file=path, column=key)
    if doc["format"] != RESULT_FORMAT:
        raise InputError(f"must be {RESULT_FORMAT!r}, got {json_shown(doc['format'])}", file=path, column="format")
    if doc["version"] != RESULT_VERSION:
        raise InputError(
            f"unsupported version {doc['version']} (this reader knows {RESULT_VERSION})",
            file=path,
            column="version",
        )
    return doc


def _read_csv_rows(
    path: Path, required: tuple[str, ...], complete: bool
) -> tuple[list[str], list[list[str]]]:
    """Header and data rows (blank lines skipped). For an incomplete result a torn last line is dropped."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: {exc.reason} at byte {exc.start}", file=path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", file=path) from None
    if not complete and text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]  # the writer was stopped mid-line: drop the partial row
    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and any(c.strip() for c in r)]
    except csv.Error as exc:
        raise InputError(f"malformed CSV: {exc}", file=path) from None
    if not rows:
        raise InputError("empty file: no header row", file=path)
    header = [c.strip() for c in rows[0]]
    seen: set[str] = set()
    for c in header:
        if c in seen:
            raise InputError(f"header: duplicate column {c!r}", file=path, column=c)
        seen.add(c)
    for c in required:
        if c not in seen:
            raise InputError("header: required column missing", file=path, column=c)
    for r, cells in enumerate(rows[1:], start=1):
        if len(cells) != len(header):
            raise InputError(f"has {len(cells)} cells but the header has {len(header)}", file=path, row=r)
    return header, [[c.strip() for c in cells] for cells in rows[1:]]


def _num(path: Path, r: int, column: str, cell: str, allow_nan: bool) -> float:
    """A numeric cell: finite (what the writer writes), or NaN/empty where ``allow_nan``."""
    if _DECIMAL.fullmatch(cell):
        x = float(cell)
        if math.isfinite(x):
            return x
        raise InputError(f"number {shown(cell)} overflows to infinity", file=path, row=r, column=column)
    if allow_nan and (_NAN.fullmatch(cell) or cell == ""):
        return math.nan
    what = "number" if allow_nan else "finite number"
    raise InputError(f"not a {what}: {shown(cell)}", file=path, row=r, column=column)


def _int(path: Path, r: int, column: str, cell: str) -> int:
    """A non-negative integer cell that fits int64 (frame indices, iterations)."""
    if not _INTEGER.fullmatch(cell):
        raise InputError(f"not a non-negative integer: {shown(cell)}", file=path, row=r, column=column)
    if len(cell.lstrip("0")) > 19 or int(cell) > MAX_FRAME_INDEX:
        raise InputError(f"{shown(cell)} is beyond int64 (at most {MAX_FRAME_INDEX})", file=path, row=r,
                         column=column)
    return int(cell)


def _parse_frames_and_poses(
    path: Path, header: list[str], rows: list[list[str]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """frame ``(F,)``, t_s ``(F,)`` and poses ``(F, 4, 4)`` of a result CSV, validated."""
    idx = {c: i for i, c in enumerate(header)}
    F = len(rows)
    frames = np.zeros(F, dtype=np.int64)
    t_s = np.zeros(F)
    vals = np.zeros((F, 7))
    prev: int | None = None
    for r, cells in enumerate(rows, start=1):
        frames[r - 1] = _int(path, r, "frame", cells[idx["frame"]])
        if prev is not None and frames[r - 1] <= prev:
            raise InputError(
                f"frame {frames[r - 1]} is not greater than the previous row's frame {prev}",
                file=path, row=r, column="frame",
            )
        prev = int(frames[r - 1])
        t_s[r - 1] = _num(path, r, "t_s", cells[idx["t_s"]], allow_nan=False)
        for j, c in enumerate(POSE_COLUMNS):
            vals[r - 1, j] = _num(path, r, c, cells[idx[c]], allow_nan=False)
        q = vals[r - 1, 3:]
        # components clipped to ±2 (a unit quaternion's are within ±1): huge cells cannot overflow
        norm = float(np.sqrt(np.sum(np.square(np.clip(q, -2.0, 2.0)))))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise InputError(
                f"quaternion (qw, qx, qy, qz) has norm {norm:.6g}{'+' if norm >= 2 else ''}; "
                f"it must be 1 within {QUAT_NORM_TOL:g} "
                f"(frame {frames[r - 1]})",
                file=path, row=r, column="qw",
            )
    poses = pose_from_xyz_quat(vals[:, :3], vals[:, 3:]) if F else np.zeros((0, 4, 4))
    return frames, t_s, poses


def _check_particle_arrays(path: Path, arrays: dict[str, np.ndarray], weighted: bool) -> ParticleHistory:
    keys = ["frame", "xyz_m", "quat_wxyz", "log_posterior"] + (["weight"] if weighted else [])
    for k in keys:
        if k not in arrays:
            raise InputError("missing required array", file=path, column=k)
    frame = arrays["frame"]
    if frame.ndim != 1 or not np.issubdtype(frame.dtype, np.integer):
        msg = f"must be a 1-D integer array, got {frame.dtype} {frame.shape}"
        raise InputError(msg, file=path, column="frame")
    F = frame.shape[0]
    xyz = arrays["xyz_m"]
    if xyz.ndim != 3 or xyz.shape[0] != F or xyz.shape[2] != 3:
        raise InputError(f"must have shape (F={F}, N, 3), got {xyz.shape}", file=path, column="xyz_m")
    N = xyz.shape[1]
    shapes = {"quat_wxyz": (F, N, 4), "log_posterior": (F, N), "weight": (F, N)}
    for k in keys[2:]:
        a = arrays[k]
        if a.shape != shapes[k] or not np.issubdtype(a.dtype, np.floating):
            msg = f"must be a float array of shape {shapes[k]}, got {a.dtype} {a.shape}"
            raise InputError(msg, file=path, column=k)

    def first_bad(bad: np.ndarray) -> int:
        return int(np.argmax(bad.reshape(F, -1).any(axis=1))) + 1

    if np.any(np.diff(frame) <= 0):
        r = int(np.argmax(np.diff(frame) <= 0)) + 2
        raise InputError("frames are not strictly increasing", file=path, row=r, column="frame")
    for k, bad in (
        ("xyz_m", ~np.isfinite(xyz)),
        ("quat_wxyz", ~np.isfinite(arrays["quat_wxyz"])),
        ("log_posterior", np.isnan(arrays["log_posterior"]) | (arrays["log_posterior"] == np.inf)),
    ):
        if np.any(bad):
            raise InputError("contains NaN or infinite values", file=path, row=first_bad(bad), column=k)
    # components clipped to ±2 (a unit quaternion's are within ±1): huge cells cannot overflow
    norm = np.sqrt(np.sum(np.square(np.clip(arrays["quat_wxyz"], -2.0, 2.0)), axis=-1))
    bad = np.abs(norm - 1.0) > QUAT_NORM_TOL
    if np.any(bad):
        raise InputError(f"quaternion norm far from 1 (tolerance {QUAT_NORM_TOL:g})", file=path,
                         row=first_bad(bad), column="quat_wxyz")
    weight = None
    if weighted:
        weight = np.asarray(arrays["weight"], dtype=float)
        bad = ~np.isfinite(weight) | (weight < 0)
        if np.any(bad):
            raise InputError("contains negative, NaN or infinite weights", file=path, row=first_bad(bad),
                             column="weight")
    if F:
        T = pose_from_xyz_quat(xyz.astype(float), arrays["quat_wxyz"].astype(float))
    else:
        T = np.zeros((0, N, 4, 4))
    return ParticleHistory(frame=frame.astype(np.int64), cam_T_needle=T,
                           log_posterior=np.asarray(arrays["log_posterior"], dtype=float), weight=weight)


def _npz_declared_sizes_ok(path: Path) -> None:
    """Refuse an npz whose members declare more array data than they hold, or object arrays.

    ``np.load`` allocates the declared shape before reading, so a corrupt header would otherwise
    allocate whatever it claims. Raises :class:`InputError`; zip/format errors are left to np.load.
    """
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                else:
                    shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            if dtype.hasobject:
                raise InputError(f"member {info.filename!r} holds Python objects, which "
                                 "np.load(allow_pickle=False) refuses", file=path)
            count = 1
            for n in shape:
                count *= int(n)
            if count * dtype.itemsize > info.file_size:
                raise InputError(f"member {info.filename!r} declares shape {shape} of {dtype}, more than its "
                                 f"{info.file_size} bytes", file=path)


def _read_npz(path: Path, weighted: bool) -> ParticleHistory:
    try:
        _npz_declared_sizes_ok(path)
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of the zip/npy parsers on these bytes is bad input
        raise InputError(
            f"cannot load with np.load(allow_pickle=False): {type(exc).__name__}: {shown(str(exc), 120)}", file=path
        ) from None
    return _check_particle_arrays(path, arrays, weighted)


def _read_journal(path: Path, weighted: bool) -> ParticleHistory | None:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", file=path) from None
    if len(data) < _JOURNAL_HEADER_BYTES:
        return None  # stopped before the first record
    if not data.startswith(_JOURNAL_MAGIC):
        raise InputError("not a pinpoint particle journal (bad magic)", file=path)
    n, w_flag, _ = (int(x) for x in np.frombuffer(data, dtype="<i8", count=3, offset=len(_JOURNAL_MAGIC)))
    if not 1 <= n <= MAX_PARTICLES:
        raise InputError(f"header says N={n}; a result has 1 .. {MAX_PARTICLES} particles", file=path)
    if w_flag not in (0, 1) or bool(w_flag) != weighted:
        raise InputError(f"header says N={n}, weighted={bool(w_flag)}; result.json says weighted={weighted}",
                         file=path)
    dt = _journal_dtype(int(n), weighted)
    count = (len(data) - _JOURNAL_HEADER_BYTES) // dt.itemsize  # a torn last record is ignored
    rec = np.frombuffer(data, dtype=dt, count=count, offset=_JOURNAL_HEADER_BYTES)
    arrays = {k: np.array(rec[k]) for k in dt.names}
    return _check_particle_arrays(path, arrays, weighted)


def expand_result_dirs(paths: Iterable[str | Path]) -> list[Path]:
    """Result directories named by ``paths``: a result directory itself, or a directory of results.

    A path holding ``result.json`` is a result. A directory without one whose immediate
    sub-directories hold ``result.json`` (the output of ``pinpoint-fg batch``) stands for those
    sub-directories, in name order. Anything else is passed through unchanged, so
    :func:`read_result` reports it. Order is kept and duplicates are dropped.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir() and not (p / RESULT_JSON).exists():
            subs = sorted(d for d in p.iterdir() if d.is_dir() and (d / RESULT_JSON).is_file())
            out.extend(subs or [p])
        else:
            out.append(p)
    seen: set[Path] = set()
    unique = []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            unique.append(p)
    return unique


def read_result(out_dir: str | Path) -> Result:
    """Read and validate a result directory; bad content raises :class:`InputError` (file, row, column).

    Works on a result whose writer never closed (crash): every frame whose estimates row was
    written is returned (particles from the journal when it is ahead of particles.npz).
    """
    root = Path(out_dir)
    try:
        is_dir = root.is_dir()
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputError(f"cannot be used as a result directory: {why}", file=root) from None
    if not is_dir:
        raise InputError("not a directory (a result is a directory with result.json)", file=root)
    info = _read_info(root)
    complete = info["complete"]
    weighted = info["weighted"]

    est_path = root / ESTIMATES_CSV
    extra: dict[str, np.ndarray] = {}
    if est_path.exists():
        header, rows = _read_csv_rows(est_path, ESTIMATE_COLUMNS, complete)
    elif complete:
        raise InputError("file not found", file=est_path)
    else:
        header, rows = list(ESTIMATE_COLUMNS), []
    idx = {c: i for i, c in enumerate(header)}
    frame, t_s, poses = _parse_frames_and_poses(est_path, header, rows)
    F = len(rows)
    q95_t, q95_r, lat = np.zeros(F), np.zeros(F), np.zeros(F)
    bimodal = np.zeros(F, dtype=bool)
    iters = np.zeros(F, dtype=np.int64)
    for r, cells in enumerate(rows, start=1):
        q95_t[r - 1] = _num(est_path, r, "q95_trans_m", cells[idx["q95_trans_m"]], allow_nan=True)
        q95_r[r - 1] = _num(est_path, r, "q95_rot_rad", cells[idx["q95_rot_rad"]], allow_nan=True)
        lat[r - 1] = _num(est_path, r, "latency_ms", cells[idx["latency_ms"]], allow_nan=True)
        b = cells[idx["bimodal"]]
        if b not in ("0", "1"):
            raise InputError(f"must be 0 or 1, got {shown(b)}", file=est_path, row=r, column="bimodal")
        bimodal[r - 1] = b == "1"
        iters[r - 1] = _int(est_path, r, "iterations", cells[idx["iterations"]])
    for c in header:
        if c in ESTIMATE_COLUMNS:
            continue
        cells = [row[idx[c]] for row in rows]
        if all(_DECIMAL.fullmatch(x) or _NAN.fullmatch(x) or x == "" for x in cells):
            values = np.array([float(x) if x else math.nan for x in cells])
            if not np.any(np.isinf(values)):  # the writer never writes inf: such a column is not ours
                extra[c] = values
        # a non-numeric extra column is allowed and ignored

    smoothed = None
    if info["smoothed"]:
        sm_path = root / SMOOTHED_CSV
        if sm_path.exists():
            sh, srows = _read_csv_rows(sm_path, SMOOTHED_COLUMNS, complete)
            sf, _, sT = _parse_frames_and_poses(sm_path, sh, srows)
            smoothed = (sf, sT)
        elif complete:
            raise InputError("file not found (result.json says smoothed)", file=sm_path)
        else:
            smoothed = (np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))

    npz_path, journal_path = root / PARTICLES_NPZ, root / PARTICLES_JOURNAL
    particles = _read_npz(npz_path, weighted) if npz_path.exists() else None
    src = npz_path
    if journal_path.exists():
        journal = _read_journal(journal_path, weighted)
        if journal is not None and (particles is None or len(journal.frame) > len(particles.frame)):
            particles, src = journal, journal_path
    if particles is None and F > 0 and complete:
        raise InputError("file not found", file=npz_path)
    if particles is not None:
        P = len(particles.frame)
        if P > F:  # particles of a frame whose rows were not written before a crash
            if complete:
                msg = f"{P} particle frames but estimates.csv has {F} rows"
                raise InputError(msg, file=src, column="frame")
            particles = ParticleHistory(particles.frame[:F], particles.cam_T_needle[:F],
                                        particles.log_posterior[:F],
                                        None if particles.weight is None else particles.weight[:F])
            P = F
        if complete and P != F:
            raise InputError(f"{P} particle frames but estimates.csv has {F} rows", file=src, column="frame")
        mismatch = np.nonzero(particles.frame != frame[:P])[0]
        if mismatch.size:
            r = int(mismatch[0]) + 1
            raise InputError(
                f"frame {particles.frame[r - 1]} but estimates.csv row {r} is frame {frame[r - 1]}",
                file=src, row=r, column="frame",
            )
        if P == 0:
            particles = None
    return Result(
        root=root, info=info, frame=frame, t_s=t_s, cam_T_needle=poses, q95_trans_m=q95_t,
        q95_rot_rad=q95_r, bimodal=bimodal, iterations=iters, latency_ms=lat, extra=extra,
        smoothed=smoothed, particles=particles,
    )


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


def read_modes(out_dir: str | Path) -> ModeHistory:
    """Read and validate ``modes.csv`` of a result directory; bad content raises :class:`InputError`.

    Checks (each error names file, 1-based data row and column): integer ``frame`` non-decreasing
    and ``mode`` = 0, 1, ... within a frame (at most :data:`MAX_MODES`), weights finite in [0, 1],
    non-increasing within a frame and summing to 1 within :data:`MODE_WEIGHT_SUM_TOL`, unit
    quaternions, finite covariance entries with a positive semi-definite matrix (smallest eigenvalue
    >= -1e-9 times the largest magnitude). For a result whose writer never closed, a torn last line
    and a last frame whose rows are incomplete (weights not summing to 1) are dropped.
    """
    root = Path(out_dir)
    path = root / MODES_CSV
    if not path.exists():
        raise InputError("file not found", file=path)
    complete = bool(_read_info(root)["complete"])
    header, rows = _read_csv_rows(path, MODE_COLUMNS, complete)
    idx = {c: i for i, c in enumerate(header)}
    M = len(rows)
    frame = np.zeros(M, dtype=np.int64)
    mode = np.zeros(M, dtype=np.int64)
    weight = np.zeros(M)
    pose = np.zeros((M, 7))
    cov = np.zeros((M, 6, 6))
    for r, cells in enumerate(rows, start=1):
        for c, arr in (("frame", frame), ("mode", mode)):
            x = cells[idx[c]]
            if not _INTEGER.fullmatch(x):
                raise InputError(f"not a non-negative integer: {x!r}", file=path, row=r, column=c)
            arr[r - 1] = int(x)
        f, k = int(frame[r - 1]), int(mode[r - 1])
        if r > 1 and f < frame[r - 2]:
            raise InputError(f"frame {f} is smaller than the previous row's frame {frame[r - 2]}",
                             file=path, row=r, column="frame")
        want = int(mode[r - 2]) + 1 if r > 1 and f == frame[r - 2] else 0
        if k != want:
            raise InputError(f"mode {k} of frame {f}; expected {want} (modes count 0, 1, ... per frame)",
                             file=path, row=r, column="mode")
        if k >= MAX_MODES:
            raise InputError(f"frame {f} has more than {MAX_MODES} modes", file=path, row=r, column="mode")
        wk = _num(path, r, "weight", cells[idx["weight"]], allow_nan=False)
        if not 0.0 <= wk <= 1.0:
            raise InputError(f"weight {wk!r} is outside [0, 1]", file=path, row=r, column="weight")
        if k > 0 and wk > weight[r - 2]:
            raise InputError(f"weight {wk!r} exceeds the previous mode's {weight[r - 2]!r} (modes are sorted by "
                             "decreasing weight)", file=path, row=r, column="weight")
        weight[r - 1] = wk
        for j, c in enumerate(POSE_COLUMNS):
            pose[r - 1, j] = _num(path, r, c, cells[idx[c]], allow_nan=False)
        norm = float(np.linalg.norm(pose[r - 1, 3:]))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise InputError(f"quaternion (qw, qx, qy, qz) has norm {norm:.6g}; it must be 1 within "
                             f"{QUAT_NORM_TOL:g}", file=path, row=r, column="qw")
        vals = np.array([_num(path, r, c, cells[idx[c]], allow_nan=False) for c in COV_COLUMNS])
        C = np.zeros((6, 6))
        C[_IU] = vals
        C = C + np.triu(C, 1).T
        for i in range(6):
            if C[i, i] < 0:
                raise InputError(f"variance {C[i, i]!r} is negative", file=path, row=r, column=f"cov_{i}{i}")
        eig = np.linalg.eigvalsh(C)
        if eig[0] < -1e-9 * max(float(np.max(np.abs(eig))), 1e-300):
            raise InputError(f"covariance is not positive semi-definite (smallest eigenvalue {eig[0]:.3g})",
                             file=path, row=r, column="cov_00")
        cov[r - 1] = C
    # per-frame weight sums (the row named is the frame's last row)
    keep = M
    ends = [i for i in range(M) if i == M - 1 or frame[i + 1] != frame[i]]
    start = 0
    for end in ends:
        total = math.fsum(weight[start:end + 1])
        if abs(total - 1.0) > MODE_WEIGHT_SUM_TOL:
            if not complete and end == M - 1:
                keep = start  # the writer stopped in the middle of this frame's rows
                break
            raise InputError(f"the weights of frame {frame[end]} sum to {total!r}, not 1 (tolerance "
                             f"{MODE_WEIGHT_SUM_TOL:g})", file=path, row=end + 1, column="weight")
        start = end + 1
    T = pose_from_xyz_quat(pose[:keep, :3], pose[:keep, 3:]) if keep else np.zeros((0, 4, 4))
    return ModeHistory(frame=frame[:keep], mode=mode[:keep], weight=weight[:keep], cam_T_needle=T,
                       cov_xi=cov[:keep])
