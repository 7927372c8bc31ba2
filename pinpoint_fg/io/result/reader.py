"""Reading a tracking result back: :func:`read_result` (estimates, smoothed poses, particles) and :func:`read_modes`.

Every problem raises :class:`~pinpoint_fg.errors.InputError` naming the file, the 1-based data row and the column.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from factors.geometry import pose_from_xyz_quat
from pinpoint_fg.errors import InputError, path_argument, path_list
from pinpoint_fg.io.jsonfile import json_shown, load_json
from pinpoint_fg.io.outdir import path_text
from pinpoint_fg.io.recording.fingerprint import FINGERPRINT_KEY, recording_fingerprint
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import MAX_FRAME_INDEX, QUAT_NORM_TOL, Recording, shown
from pinpoint_fg.io.result.particles import read_journal, read_npz
from pinpoint_fg.io.result.schema import (
    COV_COLUMNS,
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
    POSE_COLUMNS,
    RESULT_FORMAT,
    RESULT_JSON,
    RESULT_VERSION,
    SMOOTHED_COLUMNS,
    SMOOTHED_CSV,
    ModeHistory,
    ParticleHistory,
    Result,
)

_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_NAN = re.compile(r"[+-]?nan", re.IGNORECASE)
_INTEGER = re.compile(r"\d+", re.ASCII)


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
    method, recorded = doc["method"], doc["settings"].get("method", doc["method"])
    if not method.strip() or method != recorded:  # hand-edited: evaluated, and spread-scaled, as another method
        why = ("must not be empty" if not method.strip()
               else f"is {method!r} but settings.method is {json_shown(recorded)}")
        raise InputError(why, file=path, column="method")
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


def _check_xyz(path: Path, r: int, xyz: np.ndarray) -> None:
    """A row's position (x_m, y_m, z_m) within :data:`MAX_ABS_RESULT_METRES` of the camera."""
    for c, x in zip(POSE_COLUMNS[:3], xyz, strict=False):
        if abs(x) > MAX_ABS_RESULT_METRES:
            raise InputError(f"{float(x)!r} m is beyond the result format's {MAX_ABS_RESULT_METRES:g} m of the camera",
                             file=path, row=r, column=c)


def _quat_norm(q: np.ndarray) -> float:
    """Norm of a quaternion whose components are clipped to ±2 (a unit one's are within ±1): huge cells cannot
    overflow (``1e200`` was "norm inf" after NumPy's overflow warning)."""
    return float(np.sqrt(np.sum(np.square(np.clip(q, -2.0, 2.0)))))


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
        _check_xyz(path, r, vals[r - 1, :3])
        norm = _quat_norm(vals[r - 1, 3:])
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise InputError(
                f"quaternion (qw, qx, qy, qz) has norm {norm:.6g}{'+' if norm >= 2 else ''}; "
                f"it must be 1 within {QUAT_NORM_TOL:g} "
                f"(frame {frames[r - 1]})",
                file=path, row=r, column="qw",
            )
    poses = pose_from_xyz_quat(vals[:, :3], vals[:, 3:]) if F else np.zeros((0, 4, 4))
    return frames, t_s, poses


def expand_result_dirs(paths: Iterable[str | Path], skipped: list[Path] | None = None) -> list[Path]:
    """Result directories named by ``paths``: a result directory itself, or a directory of results.

    A path holding ``result.json`` is a result. A directory without one whose immediate
    sub-directories hold ``result.json`` (the output of ``pinpoint-fg batch``) stands for those
    sub-directories, in name order. Anything else is passed through unchanged, so
    :func:`read_result` reports it. Order is kept and duplicates are dropped.

    ``skipped``, when given, receives the other sub-directories of such a directory of results (in name order;
    hidden ones, starting with ".", are not listed). Decision: they stay skipped, as a batch directory may hold
    anything beside its results, but the caller says so (:func:`skipped_dir_note`): silently, the empty directory a
    failed batch run left looked like a batch evaluated in full.
    """
    out: list[Path] = []
    for p in map(Path, path_list("paths", paths)):
        if p.is_dir() and not (p / RESULT_JSON).exists():
            dirs = sorted(d for d in p.iterdir() if d.is_dir())
            subs = [d for d in dirs if (d / RESULT_JSON).is_file()]
            out.extend(subs or [p])
            if subs and skipped is not None:
                skipped.extend(d for d in dirs if d not in subs and not d.name.startswith("."))
        else:
            out.append(p)
    seen: set[str] = set()
    unique = []
    for p in out:
        key = os.path.realpath(p)  # not Path.resolve: a symlink loop was its RuntimeError traceback
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def skipped_dir_note(path: Path) -> str:
    """The ``note:`` line for a sub-directory of a directory of results that :func:`expand_result_dirs` skipped."""
    try:
        empty = not any(path.iterdir())
    except OSError:
        empty = False
    why = ("empty, not a result (what a batch run that failed before writing anything left)" if empty
           else f"not a result (no {RESULT_JSON})")
    # a name with a newline must not break the one line
    return f"note: skipped {path_text(path)}: {why}, beside the results in {path_text(path.parent)}"


def read_result(out_dir: str | Path) -> Result:
    """Read and validate a result directory; bad content raises :class:`InputError` (file, row, column).

    Works on a result whose writer never closed (crash): every frame whose estimates row was
    written is returned (particles from the journal when it is ahead of particles.npz).
    """
    root = path_argument("out_dir", out_dir)
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
        for c, arr in (("q95_trans_m", q95_t), ("q95_rot_rad", q95_r), ("latency_ms", lat)):
            arr[r - 1] = _num(est_path, r, c, cells[idx[c]], allow_nan=True)
            if arr[r - 1] < 0:  # a radius and a duration: the writer never writes a negative one
                raise InputError(f"must not be negative, got {shown(cells[idx[c]])}", file=est_path, row=r, column=c)
            if c != "latency_ms" and arr[r - 1] > MAX_RESULT_Q95:  # its square overflowed in evaluate
                raise InputError(f"{shown(cells[idx[c]])} is beyond the result format's {MAX_RESULT_Q95:g}",
                                 file=est_path, row=r, column=c)
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
    particles = read_npz(npz_path, weighted) if npz_path.exists() else None
    src = npz_path
    if journal_path.exists():
        journal = read_journal(journal_path, weighted)
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


def read_modes(out_dir: str | Path) -> ModeHistory:
    """Read and validate ``modes.csv`` of a result directory; bad content raises :class:`InputError`.

    Checks (each error names file, 1-based data row and column): integer ``frame`` non-decreasing
    and ``mode`` = 0, 1, ... within a frame (at most :data:`MAX_MODES`), weights finite in [0, 1],
    non-increasing within a frame and summing to 1 within :data:`MODE_WEIGHT_SUM_TOL`, unit
    quaternions, finite covariance entries with a positive semi-definite matrix (smallest eigenvalue
    >= -1e-9 times the largest magnitude). For a result whose writer never closed, a torn last line
    and a last frame whose rows are incomplete (weights not summing to 1) are dropped.
    """
    root = path_argument("out_dir", out_dir)
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
            arr[r - 1] = _int(path, r, c, cells[idx[c]])  # int() into int64 was an OverflowError beyond it
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
        _check_xyz(path, r, pose[r - 1, :3])
        norm = _quat_norm(pose[r - 1, 3:])
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise InputError(f"quaternion (qw, qx, qy, qz) has norm {norm:.6g}{'+' if norm >= 2 else ''}; it must "
                             "be 1 within "
                             f"{QUAT_NORM_TOL:g}", file=path, row=r, column="qw")
        vals = np.array([_num(path, r, c, cells[idx[c]], allow_nan=False) for c in COV_COLUMNS])
        C = np.zeros((6, 6))
        C[COV_INDICES] = vals
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


def check_modes_cover(hist: ModeHistory, res: Result) -> None:
    """:class:`InputError` naming modes.csv's row and ``frame`` unless its frames are those of ``estimates.csv``.

    Decision (``RECORDING_FORMAT.md``: "one row per frame and mode", written frame by frame like
    ``estimates.csv``): every frame of the estimates has its modes, and modes.csv has no frame the estimates lack.
    A modes.csv missing frames was evaluated on the frames it had (the truth-kept and bimodal shares of a subset,
    exit 0). The writer appends a frame's modes after its estimates row, so a result whose writer never closed may
    lack the modes of its last estimates frame only; that frame is then left without modes.
    """
    path = res.root / MODES_CSV
    have = np.unique(hist.frame)
    frames = res.frame if res.complete or len(res.frame) == 0 else res.frame[:-1]
    extra = np.nonzero(~np.isin(hist.frame, res.frame))[0]
    if extra.size:
        pos = int(extra[0])
        raise InputError(f"frame {int(hist.frame[pos])} is not a frame of {ESTIMATES_CSV}", file=path,
                         row=pos + 1, column="frame")
    missing = frames[~np.isin(frames, have)]
    if missing.size:
        f = int(missing[0])
        later = np.nonzero(hist.frame > f)[0]
        row = int(later[0]) + 1 if later.size else len(hist.frame)
        where = "before this row" if later.size else "after the last row" if len(hist.frame) else "(no data rows)"
        raise InputError(f"frame {f} of {ESTIMATES_CSV} has no modes {where} (every frame has 1 to {MAX_MODES} "
                         f"modes; {missing.size} frame(s) missing)", file=path, row=row or None, column="frame")


def recording_of(res: Result, cache: dict[Path, Recording], hint: str = "") -> Recording:
    """The recording ``result.json`` names (``recording_path``; relative: to the result), read once per path.

    ``cache`` maps resolved paths to recordings already read. The recording's name must be the result's
    ``recording_name``. :class:`InputError` naming ``result.json`` otherwise, or when the path is empty or names
    no directory (with ``hint``, e.g. how to pass the recording instead, appended to the message).
    """
    path = res.info.get("recording_path")
    if not path:
        raise InputError(f'key "recording_path" is empty{": " + hint if hint else ""}',
                         file=res.root / "result.json", column="recording_path")
    p = Path(str(path))
    if not p.is_absolute() and not p.exists():
        p = res.root / p
    key = Path(os.path.realpath(p))
    if key not in cache and not p.is_dir():  # moved or deleted since tracking: say which result needs it
        raise InputError(f"the recording it was tracked on, {p}, is not found (moved or deleted?)"
                         f"{': ' + hint if hint else ''}", file=res.root / "result.json", column="recording_path")
    if key not in cache:
        cache[key] = read_recording(p)
    rec = cache[key]
    if str(res.info.get("recording_name")) != rec.info.name:
        raise InputError(f"result is of recording {res.info.get('recording_name')!r}, the recording is "
                         f"{rec.info.name!r}", file=res.root / "result.json", column="recording_name")
    check_tracked_on(res, rec)
    return rec


def _fingerprint_at_recorded_path(res: Result, rec: Recording) -> str | None:
    """The fingerprint of the recording ``res``'s ``recording_path`` names, when that is another readable directory
    than ``rec``'s (a result written before ``recording_fingerprint`` existed); else None."""
    text = res.info.get("recording_path")
    if not text:
        return None
    p = Path(str(text))
    if not p.is_absolute() and not p.exists():
        p = res.root / p
    if not p.is_dir() or os.path.realpath(p) == os.path.realpath(rec.root):
        return None
    try:
        return recording_fingerprint(read_recording(p))
    except InputError:  # moved, replaced or damaged since: the name is all there is to check
        return None


def check_tracked_on(res: Result, rec: Recording) -> None:
    """:class:`InputError` naming ``result.json``'s ``recording_fingerprint`` when ``rec`` is not the recording ``res``
    was tracked on: same name, other content (:mod:`pinpoint_fg.io.recording.fingerprint`; a run re-simulated with
    other options into the same directory, or another dataset's scene ``000001``). It was scored against that
    recording's ground truth, exit 0. A result written before the key existed is compared with the recording its
    ``recording_path`` names when that is another readable directory, else only its name is checked."""
    recorded, key = res.info.get(FINGERPRINT_KEY), FINGERPRINT_KEY
    if recorded is None:
        recorded, key = _fingerprint_at_recorded_path(res, rec), "recording_path"
        if recorded is None:
            return
    path = res.root / "result.json"
    if not isinstance(recorded, str):
        raise InputError(f"must be a string, got {json_shown(recorded)}", file=path, column=key)
    if recorded != recording_fingerprint(rec):
        raise InputError(f"the recording {rec.root} is named {rec.info.name!r} like the one this result was tracked "
                         "on, but its content differs (camera, needle, observations or masks)", file=path, column=key)
