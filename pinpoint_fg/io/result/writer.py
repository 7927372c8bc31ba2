"""Writing a tracking result frame by frame: :class:`ResultWriter` (the files and their crash safety: see schema)."""

from __future__ import annotations

import csv
import dataclasses
import enum
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

import pinpoint_fg
from factors.geometry import xyz_quat_from_pose
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.recording.fingerprint import FINGERPRINT_KEY
from pinpoint_fg.io.recording.writer import atomic_write_text, check_pose
from pinpoint_fg.io.result.particles import ParticleWriter
from pinpoint_fg.io.result.schema import (
    COV_INDICES,
    ESTIMATE_COLUMNS,
    ESTIMATES_CSV,
    MAX_ABS_RESULT_METRES,
    MAX_MODES,
    MAX_RESULT_Q95,
    MODE_COLUMNS,
    MODE_WEIGHT_SUM_TOL,
    MODES_CSV,
    PARTICLES_JOURNAL,
    PARTICLES_NPZ,
    RESULT_FORMAT,
    RESULT_JSON,
    RESULT_VERSION,
    SMOOTHED_COLUMNS,
    SMOOTHED_CSV,
    TRAJECTORY_TUM,
)
from pinpoint_fg.posterior.modes import Mode


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


def _result_pose(name: str, T: Any) -> np.ndarray:
    """:func:`check_pose`, and within :data:`MAX_ABS_RESULT_METRES` of the camera (the reader refuses more)."""
    a = check_pose(name, T)
    _check_reach(name, a[:3, 3])
    return a


def _check_reach(name: str, xyz: np.ndarray) -> None:
    """``ValueError`` when a position of ``xyz`` (..., 3) lies beyond :data:`MAX_ABS_RESULT_METRES` of the camera."""
    reach = float(np.max(np.abs(xyz))) if np.size(xyz) else 0.0
    if reach > MAX_ABS_RESULT_METRES:
        raise ValueError(f"{name} lies {reach:.3g} m from the camera, beyond the result format's "
                         f"{MAX_ABS_RESULT_METRES:g} m (a diverged estimate)")


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
        _result_pose(f"{where}: mode {k} cam_T_needle", m.cam_T_needle)
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
        recording_fingerprint: str | None = None,
        npz_large_bytes: int = 64_000,
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
        if recording_fingerprint is not None:  # the recording's identity beyond its name (io.recording.fingerprint)
            self._info[FINGERPRINT_KEY] = str(recording_fingerprint)
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
        self._particles = ParticleWriter(self.out_dir, self.weighted, self.npz_large_bytes, self.npz_min_interval_s)
        self._last_frame: int | None = None
        self._last_smoothed: int | None = None
        self._closed = False

    # -- context manager -------------------------------------------------------------------
    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        self._finish(stopped=None if exc_type is None else exc_type.__name__)

    @property
    def frames_written(self) -> int:
        """Number of frames written so far."""
        return len(self._particles.frames)

    def _write_info(self) -> None:
        text = json.dumps(self._info, indent=2, allow_nan=False) + "\n"
        atomic_write_text(self.out_dir / RESULT_JSON, text)

    # -- per frame -------------------------------------------------------------------------
    def _check(self, est: Estimate) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        if isinstance(est.frame, bool) or not isinstance(est.frame, int | np.integer) or est.frame < 0:
            raise ValueError(f"frame must be a non-negative integer, got {est.frame!r}")
        f = int(est.frame)
        if self._last_frame is not None and f <= self._last_frame:
            raise ValueError(f"frame {f} is not greater than the previous frame {self._last_frame}")
        _scalar(f"frame {f}: t_s", est.t_s, allow_nan=False)
        _result_pose(f"frame {f}: cam_T_needle", est.cam_T_needle)
        for name in ("q95_trans_m", "q95_rot_rad", "latency_ms"):
            value = _scalar(f"frame {f}: {name}", getattr(est, name), allow_nan=True)
            if value < 0:  # the reader refuses it
                raise ValueError(f"frame {f}: {name} must not be negative, got {getattr(est, name)!r}")
            if name != "latency_ms" and value > MAX_RESULT_Q95:  # the reader refuses it (MAX_RESULT_Q95)
                raise ValueError(f"frame {f}: {name} {value:.3g} is beyond the result format's {MAX_RESULT_Q95:g}")
        if not isinstance(est.bimodal, bool | np.bool_) and est.bimodal not in (0, 1):
            raise ValueError(f"frame {f}: bimodal must be a bool, got {est.bimodal!r}")
        it = est.iterations
        if isinstance(it, bool) or not isinstance(it, int | np.integer) or it < 0:
            raise ValueError(f"frame {f}: iterations must be a non-negative integer, got {est.iterations!r}")
        P = np.asarray(est.particles, dtype=float)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] < 1:
            raise ValueError(f"frame {f}: particles must have shape (N, 4, 4) with N >= 1, got {P.shape}")
        n = P.shape[0]
        if self._particles.n is not None and n != self._particles.n:
            raise ValueError(f"frame {f}: {n} particles, but this run has N = {self._particles.n} (N is fixed per run)")
        if not np.all(np.isfinite(P)):
            raise ValueError(f"frame {f}: particles contain NaN or infinite values")
        R = P[:, :3, :3]
        ortho = np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)), axis=(1, 2))
        if np.any(ortho > 1e-6) or np.any(np.linalg.det(R) <= 0):
            raise ValueError(f"frame {f}: particles have rotation blocks that are not proper rotations")
        _check_reach(f"frame {f}: a particle", P[:, :3, 3])
        logp = np.asarray(est.log_posterior, dtype=float)
        if logp.shape != (n,):
            raise ValueError(f"frame {f}: log_posterior must have shape ({n},), got {logp.shape}")
        if np.any(np.isnan(logp)) or np.any(logp == np.inf):
            raise ValueError(f"frame {f}: log_posterior contains NaN or +inf")
        w = None
        if self.weighted:
            if est.weights is None:
                raise ValueError(f"frame {f}: this result is weighted but the estimate has no weight")
            w = np.asarray(est.weights, dtype=float)
            if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError(f"frame {f}: weight must be a finite non-negative ({n},) array")
        elif est.weights is not None:
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

    def write(self, est: Estimate) -> None:
        """Append one frame to every file (particles first, then the rows), each flushed."""
        if self._closed:
            raise ValueError("ResultWriter is closed")
        P, logp, w, T = self._check(est)
        f = int(est.frame)
        modes = None if est.modes is None else _check_modes(f"frame {f}", est.modes)
        xyz, quat = xyz_quat_from_pose(P)
        self._particles.append(f, xyz, quat, logp, w)
        self._last_frame = f
        self._particles.maybe_write_npz()

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
                                      *(_cell(v) for v in C[COV_INDICES])])
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
        T = _result_pose(f"smoothed frame {f}: cam_T_needle", cam_T_needle)
        self._smooth_csv.writerow([str(f), _cell(t_s), *_pose_cells(T)])
        self._smooth.flush()
        self._last_smoothed = f

    def _open_estimates(self) -> None:
        assert self._extra_keys is not None
        self._est = open(self.out_dir / ESTIMATES_CSV, "w", encoding="utf-8", newline="")
        self._est_csv = csv.writer(self._est, lineterminator="\n")
        self._est_csv.writerow([*ESTIMATE_COLUMNS, *self._extra_keys])
        self._est.flush()

    # -- closing ---------------------------------------------------------------------------
    def _finish(self, stopped: str | None) -> None:
        if self._closed:
            return
        self._closed = True
        self._particles.write_npz()
        if self._est is None:
            self._extra_keys = ()
            self._open_estimates()
        for fh in (self._est, self._tum, self._smooth):
            if fh is not None:
                fh.close()
        self._particles.close_journal()
        if self._modes is not None:
            self._modes.close()
        self._info["complete"] = stopped is None
        self._info["frames"] = len(self._particles.frames)
        self._info["particles"] = self._particles.n
        if stopped is not None:
            self._info["stopped"] = stopped
        self._write_info()
        self._particles.remove_journal()

    def close(self) -> None:
        """Write the final particles.npz, close every file, mark result.json complete (idempotent)."""
        self._finish(stopped=None)
