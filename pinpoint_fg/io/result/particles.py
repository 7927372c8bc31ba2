"""The particle sets of a result: ``particles.npz`` (rewritten atomically) and its crash journal.

``particles.journal`` is a 32-byte header (magic, N, weighted, reserved; little-endian int64) and one
fixed-size record per frame (:func:`journal_dtype`), appended and flushed as each frame is written;
a torn last record is ignored on reading. Readers check every array (shapes, finiteness, unit
quaternions, non-negative weights with a positive, finite sum per frame) and refuse an npz whose headers
declare more data than it holds.
"""

from __future__ import annotations

import math
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from factors.geometry import pose_from_xyz_quat
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.atomic import atomic_write
from pinpoint_fg.io.recording.schema import QUAT_NORM_TOL, shown
from pinpoint_fg.io.result.schema import (
    MAX_ABS_RESULT_METRES,
    PARTICLES_JOURNAL,
    PARTICLES_NPZ,
    RESULT_JSON,
    ParticleHistory,
)

JOURNAL_MAGIC = b"PPFGJRN1"
JOURNAL_HEADER_BYTES = 32  # magic (8) + N (int64) + weighted (int64) + reserved (int64)
#: Largest accepted particle count N of a journal header (a corrupt header must not allocate terabytes).
MAX_PARTICLES = 10_000_000


def journal_dtype(n: int, weighted: bool) -> np.dtype:
    """One journal record: frame index and N particles (positions, wxyz quaternions, log-posteriors, weights)."""
    fields: list[tuple[Any, ...]] = [
        ("frame", "<i8"),
        ("xyz_m", "<f8", (n, 3)),
        ("quat_wxyz", "<f8", (n, 4)),
        ("log_posterior", "<f8", (n,)),
    ]
    if weighted:
        fields.append(("weight", "<f8", (n,)))
    return np.dtype(fields)


class ParticleWriter:
    """The particle side of a :class:`~pinpoint_fg.io.result.writer.ResultWriter`: journal and npz.

    :meth:`append` writes the frame's record to the journal (opened at the first frame, when N is
    known) and flushes it, keeps the arrays, and rewrites particles.npz atomically while its arrays
    are at most ``npz_large_bytes``, afterwards at most every ``npz_min_interval_s`` seconds.
    :meth:`write_npz` writes it now (the result writer does on close). The journal is removed by
    :meth:`remove_journal` once the final npz and result.json are in place.
    """

    def __init__(self, out_dir: Path, weighted: bool, npz_large_bytes: int, npz_min_interval_s: float) -> None:
        self.out_dir = out_dir
        self.weighted = weighted
        self.npz_large_bytes = npz_large_bytes
        self.npz_min_interval_s = npz_min_interval_s
        self.n: int | None = None
        """Particles per frame (fixed per run), None before the first frame."""
        self.frames: list[int] = []
        """Frames written so far."""
        self._journal: Any = None
        self._journal_dtype: np.dtype | None = None
        self._xyz: list[np.ndarray] = []
        self._quat: list[np.ndarray] = []
        self._logp: list[np.ndarray] = []
        self._weight: list[np.ndarray] = []
        self._npz_frames = 0
        self._npz_time = -math.inf

    def append(self, frame: int, xyz: np.ndarray, quat: np.ndarray, logp: np.ndarray, w: np.ndarray | None) -> None:
        """One frame's particles (positions (N, 3), quaternions wxyz (N, 4), log-posteriors, weights or None)."""
        if self.n is None:
            self.n = xyz.shape[0]
            self._open_journal()
        assert self._journal_dtype is not None
        rec = np.zeros((), dtype=self._journal_dtype)
        rec["frame"], rec["xyz_m"], rec["quat_wxyz"], rec["log_posterior"] = frame, xyz, quat, logp
        if w is not None:
            rec["weight"] = w
        self._journal.write(rec.tobytes())
        self._journal.flush()
        self.frames.append(frame)
        self._xyz.append(xyz)
        self._quat.append(quat)
        self._logp.append(logp.copy())
        if w is not None:
            self._weight.append(w.copy())

    def _open_journal(self) -> None:
        assert self.n is not None
        self._journal_dtype = journal_dtype(self.n, self.weighted)
        self._journal = open(self.out_dir / PARTICLES_JOURNAL, "wb")
        header = JOURNAL_MAGIC + np.array([self.n, int(self.weighted), 0], dtype="<i8").tobytes()
        assert len(header) == JOURNAL_HEADER_BYTES
        self._journal.write(header)

    def maybe_write_npz(self) -> None:
        """Rewrite particles.npz unless it is large and was rewritten less than ``npz_min_interval_s`` ago."""
        n = self.n or 0
        nbytes = len(self.frames) * n * (3 + 4 + 1 + int(self.weighted)) * 8
        if nbytes <= self.npz_large_bytes or time.monotonic() - self._npz_time >= self.npz_min_interval_s:
            self.write_npz()

    def write_npz(self) -> None:
        """Write particles.npz with every frame so far (temporary file + ``os.replace``)."""
        n = self.n or 0
        F = len(self.frames)
        arrays: dict[str, np.ndarray] = {
            "frame": np.asarray(self.frames, dtype=np.int64),
            "xyz_m": np.stack(self._xyz) if F else np.zeros((0, n, 3)),
            "quat_wxyz": np.stack(self._quat) if F else np.zeros((0, n, 4)),
            "log_posterior": np.stack(self._logp) if F else np.zeros((0, n)),
        }
        if self.weighted:
            arrays["weight"] = np.stack(self._weight) if F else np.zeros((0, n))
        path = self.out_dir / PARTICLES_NPZ
        with atomic_write(path, binary=True) as fh:
            np.savez(fh, **arrays)
        self._npz_frames = F
        self._npz_time = time.monotonic()

    def close_journal(self) -> None:
        """Close the journal file (it stays on disk until :meth:`remove_journal`)."""
        if self._journal is not None:
            self._journal.close()

    def remove_journal(self) -> None:
        """Delete particles.journal (the final npz holds every frame)."""
        (self.out_dir / PARTICLES_JOURNAL).unlink(missing_ok=True)


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
    # a float array like the others (strings or a record dtype were NumPy's isfinite TypeError, complex numbers
    # a ComplexWarning and their imaginary part dropped); at least one particle, as the writer and the journal have
    # (a result without frames is written with N = 0)
    if xyz.ndim != 3 or xyz.shape[0] != F or xyz.shape[2] != 3 or (F > 0 and xyz.shape[1] < 1) \
            or not np.issubdtype(xyz.dtype, np.floating):
        raise InputError(f"must be a float array of shape (F={F}, N >= 1, 3), got {xyz.dtype} {xyz.shape}", file=path,
                         column="xyz_m")
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
    bad = np.abs(xyz) > MAX_ABS_RESULT_METRES
    if np.any(bad):
        raise InputError(f"a position lies beyond the result format's {MAX_ABS_RESULT_METRES:g} m of the camera",
                         file=path, row=first_bad(bad), column="xyz_m")
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
        # Decision: a frame's weights must have a positive, finite sum, as the writer's normalised weights do. All
        # zero was "column 'weights'" from the bimodality test with no file or row; finite weights summing to inf
        # (every one 1e308) were NumPy's overflow warning there and a bimodal rate computed from NaNs, exit 0.
        with np.errstate(over="ignore"):
            total = weight.sum(axis=1)
        bad = ~(np.isfinite(total) & (total > 0))
        if np.any(bad):
            r = int(np.argmax(bad))
            why = "are all zero" if total[r] == 0 else "sum to infinity (too large to normalise)"
            raise InputError(f"the weights of frame {int(frame[r])} {why}; a frame's weights must have a positive, "
                             "finite sum", file=path, row=r + 1, column="weight")
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


def read_npz(path: Path, weighted: bool) -> ParticleHistory:
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
    _check_weighted_agrees(path, "weight" in arrays, weighted)
    return _check_particle_arrays(path, arrays, weighted)


def _check_weighted_agrees(path: Path, has_weight: bool, weighted: bool) -> None:
    """:class:`InputError` at ``result.json``'s ``weighted`` when it contradicts the particle file ``path``.

    Decision: the writer stores a weight per particle exactly when ``weighted`` is true, so a contradiction means one
    of the two files was edited or swapped; guessing was wrong either way (``false`` over a PF's weights evaluated its
    particles as equally weighted, bimodal rate 17 % -> 8 %, exit 0), so neither is trusted and both are named.
    """
    if has_weight == weighted:
        return
    held = "holds no per-particle weights" if weighted else "holds per-particle weights (a weighted result's)"
    raise InputError(f"is {str(weighted).lower()} but {path.name} {held}; the writer keeps the two in step, so one "
                     "of them was edited or replaced", file=path.parent / RESULT_JSON, column="weighted")


def read_journal(path: Path, weighted: bool) -> ParticleHistory | None:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", file=path) from None
    if len(data) < JOURNAL_HEADER_BYTES:
        return None  # stopped before the first record
    if not data.startswith(JOURNAL_MAGIC):
        raise InputError("not a pinpoint particle journal (bad magic)", file=path)
    n, w_flag, _ = (int(x) for x in np.frombuffer(data, dtype="<i8", count=3, offset=len(JOURNAL_MAGIC)))
    if not 1 <= n <= MAX_PARTICLES:
        raise InputError(f"header says N={n}; a result has 1 .. {MAX_PARTICLES} particles", file=path)
    if w_flag not in (0, 1):
        raise InputError(f"header says N={n}, weighted={w_flag}; the flag must be 0 or 1", file=path)
    _check_weighted_agrees(path, bool(w_flag), weighted)
    dt = journal_dtype(int(n), weighted)
    count = (len(data) - JOURNAL_HEADER_BYTES) // dt.itemsize  # a torn last record is ignored
    rec = np.frombuffer(data, dtype=dt, count=count, offset=JOURNAL_HEADER_BYTES)
    arrays = {k: np.array(rec[k]) for k in dt.names}
    return _check_particle_arrays(path, arrays, weighted)
