"""Evaluation of tracking results: metrics, the paper's tables, figures (``pinpoint-fg evaluate``).

:func:`evaluate` reads result directories (v1 format) and their recordings (the path stored in
``result.json`` unless one is given) and computes, per result, on the frames that have ground
truth:

* accuracy: translation / rotation errors, per camera axis, mean ± std
  (:func:`~pinpoint_fg.eval.metrics.summarize_errors`), latency median and 95th percentile;
* uncertainty: mean predicted q95, NLL-S and interval score from the result's q95 columns;
* bimodality, recomputed from the stored particles with the MAP and the truth
  (:func:`~pinpoint_fg.posterior.bimodality.assess_bimodality`; a set with fewer than six particles,
  e.g. the MAP method's single one, is never bimodal): the raw ``bimodal_share`` (all frames
  with particles), ``truth_in_dominant_share`` (bimodal frames with truth), and — judged
  against the truth about ambiguity (:mod:`pinpoint_fg.eval.ambiguity`) — the bimodal rate on
  *ambiguous* frames (sensitivity, ``bimodal_ambiguous_rate``) and on *clear* frames (the
  false-bimodal rate, ``bimodal_clear_rate``);
* the accuracy floor (per-frame MAP solved from the truth with the result's own likelihood:
  its switches and noise file) and the method's mean error as a multiple of it;
* occlusion breakdown of the mean errors (``none`` / ``partial`` / ``heavy``);
* posterior modes (:mod:`pinpoint_fg.eval.modes`): the share of frames the modes verdict calls
  bimodal (``bimodal_modes_share``), the truth kept by some mode / some particle, and — against a
  reference multi-hypothesis (MHT) result of the same recording, given with ``reference`` or found
  among the evaluated results (method ``mht``) — the bimodal rate of both verdicts on the frames
  the reference calls multimodal vs single-mode;
* fixed-lag smoothing (results tracked with a window L > 1): the smoothed poses' mean errors beside the
  filtered estimates' on the same frames (:func:`smoothed_accuracy`).

Ground truth that does not describe its frame (:mod:`pinpoint_fg.eval.gt_scale`: the needle it puts in
view several times smaller than the frame's keypoints and mask show it, e.g. a depth in centimetres, or far
from where they show it, e.g. a metre typed for a millimetre in one cell, or a seen point behind the camera) is
left out of every score, counted in ``gt_left_out_frames`` and named in one ``note:`` line of the text;
a recording whose every checkable ground-truth frame fails is refused (exit 2 from the CLI), before
``out`` is created.

The ΔNLL labels and the floor depend on the recording and the frame likelihood only (the
likelihood switches and the noise, not the method), so they are computed once per
(recording, switches without ``motion``, noise file) and shared by every result that uses them.

Files written to ``out``: ``summary.csv`` (one row per result), ``tables.md`` (Table II shaped
like the paper's; Table III when results carry ablation settings; a multimodality table), and
PNG figures (:mod:`pinpoint_fg.eval.plots`): ``errors.png``, ``error_time_<result>.png``,
``particle_cloud_<recording>.png``, ``ablation_<recording>.png``, ``modes_time_<recording>_<result>.png``
(mode weights over time, for results with modes).
"""

from __future__ import annotations

import csv
import hashlib
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from pinpoint_fg.errors import InputError, path_argument, path_list
from pinpoint_fg.eval import plots
from pinpoint_fg.eval.ambiguity import AmbiguityConfig, RecordingAmbiguity, analyse_recording
from pinpoint_fg.eval.gt_scale import left_out_frames, left_out_note
from pinpoint_fg.eval.metrics import PoseErrors, breakdown_by_label, pose_errors, summarize_errors
from pinpoint_fg.eval.modes import (
    ResultModes,
    mode_weight_calibration,
    modes_of_result,
    peaks_near_truth,
    reference_rates,
    truth_kept,
)
from pinpoint_fg.eval.spread_calibration import coverage, scaled_result
from pinpoint_fg.io.jsonfile import json_shown
from pinpoint_fg.io.outdir import prepare_output_dir
from pinpoint_fg.io.recording.fingerprint import recording_fingerprint
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.reader import (
    check_tracked_on,
    expand_result_dirs,
    read_result,
    recording_of,
    skipped_dir_note,
)
from pinpoint_fg.io.result.schema import MODES_CSV, Result
from pinpoint_fg.io.spread_scale import SpreadScale, recorded_scale
from pinpoint_fg.likelihood import CONIC_DISTANCES, MeasurementModel, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.posterior.bimodality import assess_bimodality, systematic_resample, tangent_at_map

#: The ablation matrix of the paper's Table III: (variant name, method, disabled switches, title).
ABLATION_VARIANTS: tuple[tuple[str, str, tuple[str, ...], str], ...] = (
    ("full", "svn", (), "All (full model)"),
    ("no-dense", "svn", ("dense",), "No dense image"),
    ("one-keypoint", "svn", ("tip",), "1 sparse keypoint"),
    ("no-keypoints", "svn", ("sparse",), "No sparse keypoints"),
    ("no-image", "svn", ("dense", "sparse"), "No image"),
    ("no-grasp-position", "svn", ("grasp-position",), "No robot position"),
    ("no-grasp-perpendicular", "svn", ("grasp-perpendicular",), "No robot orientation"),
    (
        "no-robot-no-motion", "svn", ("grasp-position", "grasp-perpendicular", "motion"),
        "No robot & no motion model",
    ),
    ("svgd", "svgd", (), "SVGD (no Hessian)"),
)

#: Columns of summary.csv, in order (the uncertainty/accuracy keys are those of summarize_errors).
SUMMARY_COLUMNS: tuple[str, ...] = (
    "method", "variant", "recording", "result", "complete", "frames",
    "trans_mean_mm", "trans_std_mm", "rot_mean_deg", "rot_std_deg",
    "trans_x_mean_mm", "trans_x_std_mm", "trans_y_mean_mm", "trans_y_std_mm",
    "trans_z_mean_mm", "trans_z_std_mm",
    "rot_x_mean_deg", "rot_x_std_deg", "rot_y_mean_deg", "rot_y_std_deg", "rot_z_mean_deg", "rot_z_std_deg",
    "trans_q95_mm", "rot_q95_deg", "nlls_trans", "nlls_rot", "is_trans", "is_rot", "coverage_trans", "coverage_rot",
    "uncertainty_frames_trans", "uncertainty_frames_rot",
    "bimodal_share", "truth_in_dominant_share", "bimodal_frames",
    "ambiguous_frames", "clear_frames", "bimodal_ambiguous_rate", "bimodal_clear_rate",
    "bimodal_modes_share", "truth_kept_modes_share", "truth_kept_particles_share",
    "minor_weight_mean", "truth_minor_share", "truth_mode_frames", "reference",
    "ref_multimodal_frames", "ref_single_frames", "bimodal_ref_multi_rate", "bimodal_ref_single_rate",
    "bimodal_modes_ref_multi_rate", "bimodal_modes_ref_single_rate",
    "floor_trans_mm", "floor_rot_deg", "trans_floor_multiple", "rot_floor_multiple",
    "trans_mm_none", "trans_mm_partial", "trans_mm_heavy", "rot_deg_none", "rot_deg_partial", "rot_deg_heavy",
    "latency_median_ms", "latency_p95_ms",
    "smoothed_frames", "smoothed_trans_mean_mm", "smoothed_rot_mean_deg", "filtered_trans_mean_mm_same",
    "filtered_rot_mean_deg_same", "gt_left_out_frames",
)


# --------------------------------------------------------------------------------------------
# identifying results


def normalized_disabled(disabled: Sequence[str]) -> tuple[str, ...]:
    """Canonical, sorted ``--disable`` names (``tip`` + ``tail`` -> ``sparse``)."""
    return tuple(sorted(Switches.from_disabled(tuple(disabled)).disabled()))


def variant_name(method: str, disabled: Sequence[str]) -> str:
    """Ablation variant of (method, disabled switches): an :data:`ABLATION_VARIANTS` name or a description."""
    key = normalized_disabled(disabled)
    for name, m, dis, _ in ABLATION_VARIANTS:
        if m == method and tuple(sorted(dis)) == key:
            return name
    if method == "svgd" and not key:
        return "svgd"
    return "full" if not key else "disable-" + "+".join(key)


def _variant_title(name: str) -> str:
    for v, _, _, title in ABLATION_VARIANTS:
        if v == name:
            return title
    return name


def _settings_of(res: Result) -> dict:
    s = res.info.get("settings")
    return s if isinstance(s, dict) else {}


def _disabled_of(res: Result) -> tuple[str, ...]:
    d = _settings_of(res).get("disabled") or ()
    if isinstance(d, str):
        d = [x for x in d.split(",") if x]
    if not isinstance(d, list | tuple):  # a hand-edited number was a TypeError traceback
        raise InputError(f'key "settings.disabled": must be a list of switch names, got {json_shown(d)}',
                         file=res.root / "result.json")
    try:
        return normalized_disabled(tuple(str(x) for x in d))
    except ValueError as exc:
        raise InputError(f'key "settings.disabled": {exc}', file=res.root / "result.json") from None


def _noise_of(res: Result) -> tuple[NoiseConfig, str | None]:
    path = _settings_of(res).get("noise_file")
    if not path:
        return NoiseConfig(), None
    where = res.root / "result.json"
    if not isinstance(path, str):
        raise InputError(f'key "settings.noise_file": must be a path or null, got {json_shown(path)}', file=where)
    p = Path(path)
    if not p.is_absolute() and not p.exists():
        p = res.root / p
    if not p.is_file():  # moved or deleted since tracking: say which result needs it
        raise InputError(f'key "settings.noise_file": the noise file it was tracked with, {p}, is not found',
                         file=where)
    return NoiseConfig.load(p), str(p.resolve())


def _conic_model_of(res: Result, noise: NoiseConfig) -> tuple[NoiseConfig, str]:
    """The noise with the result's ``settings.conic_correlation_px`` (when recorded) and its
    ``settings.conic_distance`` (default "sampson": results tracked before either existed)."""
    settings, where = _settings_of(res), res.root / "result.json"
    ell = settings.get("conic_correlation_px")
    if ell is not None:
        try:
            noise = noise.with_conic_correlation(ell)
        except ValueError as exc:
            raise InputError(f'key "settings.conic_correlation_px": {exc}', file=where) from None
    distance = settings.get("conic_distance", "sampson")
    if distance not in CONIC_DISTANCES:
        raise InputError(f'key "settings.conic_distance": must be one of {", ".join(CONIC_DISTANCES)}, got '
                         f"{json_shown(distance)}", file=where)
    return noise, distance


# --------------------------------------------------------------------------------------------
# per-result evaluation


@dataclass
class ResultEvaluation:
    """Everything computed for one result (arrays have the result's frame axis first)."""

    result: Result
    """The result read from disk."""
    recording: Recording
    """Its recording."""
    method: str
    """Tracking method."""
    variant: str
    """Ablation variant name (``full`` without disabled switches)."""
    label: str
    """Display name (unique among the evaluated results)."""
    T_gt: np.ndarray
    """(F, 4, 4) ground truth (NaN where unknown)."""
    has_gt: np.ndarray
    """(F,) bool."""
    errors: PoseErrors
    """Pose errors of the MAP estimates."""
    bimodal: np.ndarray
    """(F,) bool, recomputed from the particles (False where not assessed)."""
    assessed: np.ndarray
    """(F,) bool: frames whose particle set was assessed."""
    ashman_d: np.ndarray
    """(F,) Ashman's D of the two-component fit (NaN where not assessed / degenerate)."""
    labels: np.ndarray
    """(F,) ambiguity labels of the frames."""
    floor_errors: PoseErrors
    """Errors of the accuracy-floor poses at these frames."""
    occlusion: list
    """(F,) occlusion labels (None where unknown)."""
    row: dict = field(default_factory=dict)
    """The summary.csv row."""
    modes: ResultModes | None = None
    """The result's posterior modes (weights over time, peaks), None when not computed."""
    reference_method: str = ""
    """The method of the multi-hypothesis reference its modes rates were judged against ("" without one)."""


def _recording_for(res: Result, given: Recording | None, cache: dict[Path, Recording]) -> Recording:
    if given is None:
        return recording_of(res, cache, hint="pass the recording explicitly (--recording)")
    if str(res.info.get("recording_name")) != given.info.name:
        raise InputError(
            f"result is of recording {res.info.get('recording_name')!r}, the recording is {given.info.name!r}",
            file=res.root / "result.json", column="recording_name",
        )
    check_tracked_on(res, given)
    return given


def _refuse_namesakes(pairs: Sequence[tuple[Result, Recording]]) -> None:
    """:class:`InputError` naming ``result.json``'s ``recording_name`` when the result's recording shares its name with
    another recording of the evaluation but not its content (:func:`recording_fingerprint` with the ground truth).

    Tables, figures (their file names), labels and the multi-hypothesis reference are keyed by the recording's name:
    two scenes ``000001`` of two BOP datasets were mixed silently (the reference of one judged the other's frames,
    one figure overwrote the other). Copies of one recording (same content, other paths) are fine.
    """
    first: dict[str, Recording] = {}
    for res, rec in pairs:
        other = first.setdefault(rec.info.name, rec)
        if other is rec or os.path.realpath(other.root) == os.path.realpath(rec.root):
            continue
        if recording_fingerprint(other, truth=True) != recording_fingerprint(rec, truth=True):
            raise InputError(f"its recording {rec.root} and {other.root} (of another result here) are both named "
                             f"{rec.info.name!r} but differ; the evaluation keys tables, figures and the reference "
                             "by that name: evaluate them separately, or rename one (recording.json \"name\")",
                             file=res.root / "result.json", column="recording_name")


def _rows_in_recording(res: Result, recording: Recording) -> np.ndarray:
    pos = {int(r.frame): i for i, r in enumerate(recording.frames)}
    idx = np.array([pos.get(int(f), -1) for f in res.frame], dtype=int)
    if np.any(idx < 0):
        bad = int(res.frame[int(np.argmax(idx < 0))])
        raise InputError(f"frame {bad} is not in recording {recording.root}", file=res.root / "estimates.csv",
                         row=int(np.argmax(idx < 0)) + 1, column="frame")
    return idx


def _assess(res: Result, T_gt: np.ndarray, has_gt: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-frame bimodal (F,), assessed (F,), Ashman D (F,), truth-in-dominant (F,) float (NaN if n/a)."""
    F = len(res)
    bimodal = np.zeros(F, dtype=bool)
    assessed = np.zeros(F, dtype=bool)
    d = np.full(F, np.nan)
    tid = np.full(F, np.nan)
    P = res.particles
    if P is None:
        return bimodal, assessed, d, tid
    n_frames, n = P.cam_T_needle.shape[:2]
    assessed[:n_frames] = True
    if n < 6:
        return bimodal, assessed, d, tid
    with threadpool_limits(1):  # tiny EM problems: thread start-up would dominate
        for f in range(n_frames):
            v = assess_bimodality(
                P.cam_T_needle[f], res.cam_T_needle[f], weights=None if P.weight is None else P.weight[f],
                T_gt=T_gt[f] if has_gt[f] else None,
            )
            bimodal[f] = v.bimodal
            d[f] = v.ashman_d
            if v.truth_in_dominant is not None:
                tid[f] = float(v.truth_in_dominant)
    return bimodal, assessed, d, tid


def smoothed_accuracy(res: Result, T_gt: np.ndarray, has_gt: np.ndarray, errors: PoseErrors) -> dict[str, float]:
    """The fixed-lag smoothed poses (``smoothed.csv``, window L > 1) against the truth, beside the filtered estimate.

    A smoothed pose of frame k is the window's oldest pose once frame k + L - 1 was seen (the last L - 1
    frames' at the end of the run): it has seen more frames than the filtered estimate of k, so it is scored
    against the filtered estimate **of the same frames** (``filtered_*_same``) — frames with ground truth and
    both poses finite. ``T_gt``, ``has_gt``, ``errors``: per row of ``estimates.csv``. Keys: ``smoothed_frames``
    (0 and NaN means without smoothed poses), ``smoothed_trans_mean_mm``, ``smoothed_rot_mean_deg``,
    ``filtered_trans_mean_mm_same``, ``filtered_rot_mean_deg_same``.
    """
    out = {"smoothed_frames": 0, "smoothed_trans_mean_mm": float("nan"), "smoothed_rot_mean_deg": float("nan"),
           "filtered_trans_mean_mm_same": float("nan"), "filtered_rot_mean_deg_same": float("nan")}
    if res.smoothed is None or res.smoothed[0].size == 0:
        return out
    frames, T_s = res.smoothed
    pos = {int(f): i for i, f in enumerate(res.frame)}
    rows = np.array([pos.get(int(f), -1) for f in frames], dtype=int)
    if np.any(rows < 0):
        bad = int(np.argmax(rows < 0))
        raise InputError(f"smoothed frame {int(frames[bad])} has no row in estimates.csv",
                         file=res.root / "smoothed.csv", row=bad + 1, column="frame")
    e_s = pose_errors(T_s, T_gt[rows])
    use = has_gt[rows] & np.isfinite(e_s.trans_m) & np.isfinite(errors.trans_m[rows])
    out["smoothed_frames"] = int(use.sum())
    if use.any():
        out["smoothed_trans_mean_mm"] = 1e3 * float(np.mean(e_s.trans_m[use]))
        out["smoothed_rot_mean_deg"] = math.degrees(float(np.mean(e_s.rot_rad[use])))
        out["filtered_trans_mean_mm_same"] = 1e3 * float(np.mean(errors.trans_m[rows][use]))
        out["filtered_rot_mean_deg_same"] = math.degrees(float(np.mean(errors.rot_rad[rows][use])))
    return out


def _mean(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if x.size else float("nan")


#: A reference for the modes rates: (result path, frames (R,), sorted mode weights (R, K), its method).
Reference = tuple[str, np.ndarray, np.ndarray, str]


def _evaluate_one(
    res: Result, recording: Recording, amb: RecordingAmbiguity, variant: str, label: str,
    modes: ResultModes | None = None, reference: Reference | None = None, gt_left_out: set[int] | None = None,
) -> ResultEvaluation:
    """One result's metrics; ``gt_left_out``: frame numbers whose ground truth the tests of
    :mod:`~pinpoint_fg.eval.gt_scale` left out
    (:mod:`~pinpoint_fg.eval.gt_scale`), scored as frames without ground truth."""
    idx = _rows_in_recording(res, recording)
    F = len(res)
    T_gt = np.full((F, 4, 4), np.nan)
    gone = gt_left_out or set()
    for i, k in enumerate(idx):
        g = recording.frames[k].cam_T_needle_gt
        if g is not None and int(recording.frames[k].frame) not in gone:
            T_gt[i] = g
    has_gt = np.all(np.isfinite(T_gt), axis=(1, 2))
    errors = pose_errors(res.cam_T_needle, T_gt)
    summary = summarize_errors(errors, res.q95_trans_m, res.q95_rot_rad, mask=has_gt)
    bimodal, assessed, ashman, tid = _assess(res, T_gt, has_gt)

    aidx = amb.index_of(res.frame)
    labels = amb.labels[aidx]
    floor = PoseErrors(
        trans_m=amb.floor_errors.trans_m[aidx], rot_rad=amb.floor_errors.rot_rad[aidx],
        trans_axes_m=amb.floor_errors.trans_axes_m[aidx], rot_axes_rad=amb.floor_errors.rot_axes_rad[aidx],
    )
    occlusion = [recording.frames[k].occlusion for k in idx]

    row: dict = {
        "method": res.method, "variant": variant, "recording": recording.info.name, "result": str(res.root),
        "complete": int(res.complete),
    }
    row.update(summary)
    row["bimodal_share"] = float(np.mean(bimodal[assessed])) if assessed.any() else float("nan")
    row["bimodal_frames"] = int(bimodal.sum())
    row["truth_in_dominant_share"] = _mean(tid[bimodal & has_gt])
    amb_sel = assessed & (labels == "ambiguous")
    clear_sel = assessed & (labels == "clear")
    row["ambiguous_frames"] = int(amb_sel.sum())
    row["clear_frames"] = int(clear_sel.sum())
    row["bimodal_ambiguous_rate"] = float(np.mean(bimodal[amb_sel])) if amb_sel.any() else float("nan")
    row["bimodal_clear_rate"] = float(np.mean(bimodal[clear_sel])) if clear_sel.any() else float("nan")
    use = has_gt & np.isfinite(errors.trans_m) & np.isfinite(floor.trans_m)
    if use.any():
        ft, fr = float(np.mean(floor.trans_m[use])), float(np.mean(floor.rot_rad[use]))
        mt, mr = float(np.mean(errors.trans_m[use])), float(np.mean(errors.rot_rad[use]))
        row["floor_trans_mm"], row["floor_rot_deg"] = 1e3 * ft, math.degrees(fr)
        row["trans_floor_multiple"] = mt / ft if ft > 0 else float("inf")
        row["rot_floor_multiple"] = mr / fr if fr > 0 else float("inf")
    else:
        for k in ("floor_trans_mm", "floor_rot_deg", "trans_floor_multiple", "rot_floor_multiple"):
            row[k] = float("nan")
    by_t = breakdown_by_label(1e3 * errors.trans_m, occlusion, mask=has_gt)
    by_r = breakdown_by_label(np.degrees(errors.rot_rad), occlusion, mask=has_gt)
    for lab in ("none", "partial", "heavy"):
        row[f"trans_mm_{lab}"] = by_t.get(lab, float("nan"))
        row[f"rot_deg_{lab}"] = by_r.get(lab, float("nan"))
    modes = modes if modes is not None else modes_of_result(res)
    hm = modes.has_modes
    row["bimodal_modes_share"] = float(np.mean(modes.bimodal[hm])) if hm.any() else float("nan")
    near = peaks_near_truth(modes, T_gt, has_gt)
    row.update(truth_kept(res, modes, T_gt, has_gt, near))
    row.update(mode_weight_calibration(modes, T_gt, has_gt, near))
    if reference is not None:
        row["reference"] = reference[0]
        row.update(reference_rates(res.frame, bimodal, assessed, modes.bimodal, hm, reference[1], reference[2]))
    else:
        row["reference"] = ""
        row.update({"ref_multimodal_frames": 0, "ref_single_frames": 0})
        for k in ("bimodal_ref_multi_rate", "bimodal_ref_single_rate", "bimodal_modes_ref_multi_rate",
                  "bimodal_modes_ref_single_rate"):
            row[k] = float("nan")
    row.update(smoothed_accuracy(res, T_gt, has_gt, errors))
    lat = res.latency_ms[np.isfinite(res.latency_ms)]
    row["latency_median_ms"] = float(np.median(lat)) if lat.size else float("nan")
    row["latency_p95_ms"] = float(np.percentile(lat, 95)) if lat.size else float("nan")
    row["gt_left_out_frames"] = int(sum(int(recording.frames[k].frame) in gone for k in idx))
    return ResultEvaluation(
        result=res, recording=recording, method=res.method, variant=variant, label=label, T_gt=T_gt,
        has_gt=has_gt, errors=errors, bimodal=bimodal, assessed=assessed, ashman_d=ashman, labels=labels,
        floor_errors=floor, occlusion=occlusion, row=row, modes=modes,
        reference_method="" if reference is None else reference[3],
    )


# --------------------------------------------------------------------------------------------
# tables


def _f(x: float, digits: int = 2) -> str:
    if x is None or not np.isfinite(x):
        return "–"
    return f"{x:.{digits}f}" if abs(x) < 1e5 else f"{x:.2g}"


def _pm(mean: float, std: float, digits: int = 2) -> str:
    if not np.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f}±{std:.{digits}f}"


def _pct(x: float) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100.0 * x:.0f}%"


def _spread_share(r: dict, key: str) -> str:
    """`` @k%`` when the q95 (and the scores from it) of ``key`` ("trans" / "rot") cover only k % of the
    row's frames, the rest reporting none (NaN: a result written by other code, or a tracker that could not
    tell); "" when all do. Averaged over the frames that have one, a spread must say how many those are."""
    n, used = r.get("frames"), r.get(f"uncertainty_frames_{key}")
    if not n or used is None or used >= n:
        return ""
    return f" @{_pct(used / n)}"


def _md_cell(text: str) -> str:
    """``text`` as one Markdown table cell: ``|`` escaped, control characters shown as escapes (a recording named
    ``a|b`` shifted its row's values under the wrong headers, a newline in a name cut the row in two)."""
    return "".join(repr(c)[1:-1] if ord(c) < 32 or ord(c) == 127 else c for c in str(text)).replace("|", "\\|")


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_md_cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def table_ii(evals: Sequence[ResultEvaluation]) -> str:
    """Markdown table shaped like the paper's Table II (X/Y/Z/Total mean±std, Unc p95, NLL-S, IS, ×floor)."""
    rows = []
    for ev in evals:
        r = ev.row
        rows.append([
            ev.label, r["recording"], "Trans (mm)",
            *(_pm(r[f"trans_{a}_mean_mm"], r[f"trans_{a}_std_mm"]) for a in "xyz"),
            _pm(r["trans_mean_mm"], r["trans_std_mm"]), _f(r["trans_q95_mm"]) + _spread_share(r, "trans"),
            _f(r["nlls_trans"]), _f(r["is_trans"]), _f(r["trans_floor_multiple"], 1),
        ])
        rows.append([
            "", "", "Rot (deg)",
            *(_pm(r[f"rot_{a}_mean_deg"], r[f"rot_{a}_std_deg"]) for a in "xyz"),
            _pm(r["rot_mean_deg"], r["rot_std_deg"]), _f(r["rot_q95_deg"]) + _spread_share(r, "rot"),
            _f(r["nlls_rot"]), _f(r["is_rot"]), _f(r["rot_floor_multiple"], 1),
        ])
    header = ("Method", "Recording", "Metric", "X", "Y", "Z", "Total", "Unc (p95)", "NLL-S", "IS", "× floor")
    return _md_table(header, rows)


def table_multimodal(evals: Sequence[ResultEvaluation]) -> str:
    """Markdown table of the bimodality numbers, raw and judged against the ΔNLL labels."""
    rows = [[
        ev.label, ev.row["recording"], _pct(ev.row["bimodal_share"]), _pct(ev.row["truth_in_dominant_share"]),
        str(ev.row["ambiguous_frames"]), _pct(ev.row["bimodal_ambiguous_rate"]), str(ev.row["clear_frames"]),
        _pct(ev.row["bimodal_clear_rate"]),
    ] for ev in evals]
    header = ("Method", "Recording", "Bimodal (all frames)", "Truth in dominant mode", "Ambiguous frames",
              "Bimodal on ambiguous (sensitivity)", "Clear frames", "Bimodal on clear (false)")
    return _md_table(header, rows)


def table_smoothed(evals: Sequence[ResultEvaluation]) -> str:
    """Markdown table of the fixed-lag smoothed poses' errors beside the filtered ones ('' without any)."""
    rows = [[
        ev.label, ev.row["recording"], str(ev.row["smoothed_frames"]), _f(ev.row["smoothed_trans_mean_mm"]),
        _f(ev.row["smoothed_rot_mean_deg"]), _f(ev.row["filtered_trans_mean_mm_same"]),
        _f(ev.row["filtered_rot_mean_deg_same"]),
    ] for ev in evals if ev.row["smoothed_frames"] > 0]
    if not rows:
        return ""
    header = ("Method", "Recording", "Frames", "Smoothed trans (mm)", "Smoothed rot (deg)",
              "Filtered trans, same frames (mm)", "Filtered rot, same frames (deg)")
    return _md_table(header, rows)


def table_modes(evals: Sequence[ResultEvaluation]) -> str:
    """Markdown table of the modes numbers: both verdicts, truth kept, rates against the reference."""
    rows = [[
        ev.label, ev.row["recording"], _pct(ev.row["bimodal_share"]), _pct(ev.row["bimodal_modes_share"]),
        _pct(ev.row["truth_kept_modes_share"]), _pct(ev.row["truth_kept_particles_share"]),
        str(ev.row["ref_multimodal_frames"]), _pct(ev.row["bimodal_ref_multi_rate"]),
        _pct(ev.row["bimodal_modes_ref_multi_rate"]), str(ev.row["ref_single_frames"]),
        _pct(ev.row["bimodal_ref_single_rate"]), _pct(ev.row["bimodal_modes_ref_single_rate"]),
    ] for ev in evals]
    header = ("Method", "Recording", "Bimodal GMM", "Bimodal modes", "Truth kept (modes)",
              "Truth kept (particles)", "Ref. multimodal frames", "GMM on multi", "Modes on multi",
              "Ref. single frames", "GMM on single", "Modes on single")
    return _md_table(header, rows)


def _ablation_groups(evals: Sequence[ResultEvaluation]) -> dict[str, list[ResultEvaluation]]:
    """Recording name -> its SVN/SVGD results in Table III order (only recordings with an ablation)."""
    order = {v[0]: i for i, v in enumerate(ABLATION_VARIANTS)}
    groups: dict[str, list[ResultEvaluation]] = {}
    for ev in evals:
        if ev.method in ("svn", "svgd"):
            groups.setdefault(ev.recording.info.name, []).append(ev)
    out = {}
    for name, evs in groups.items():
        if any(ev.variant != "full" for ev in evs):
            out[name] = sorted(evs, key=lambda e: (order.get(e.variant, len(order)), e.label))
    return out


def table_iii(evals: Sequence[ResultEvaluation]) -> str:
    """Markdown tables shaped like the paper's Table III, one per recording with ablations ('' if none)."""
    parts = []
    for rec_name, evs in _ablation_groups(evals).items():
        rows = [[
            _variant_title(ev.variant),
            _pm(ev.row["trans_mean_mm"], ev.row["trans_std_mm"]), _f(ev.row["trans_q95_mm"]),
            _f(ev.row["nlls_trans"]), _f(ev.row["is_trans"]),
            _pm(ev.row["rot_mean_deg"], ev.row["rot_std_deg"]), _f(ev.row["rot_q95_deg"]),
            _f(ev.row["nlls_rot"]), _f(ev.row["is_rot"]), _f(ev.row["trans_floor_multiple"], 1),
        ] for ev in evs]
        header = ("Ablation", "Trans mean±std (mm)", "Unc", "NLL-S", "IS", "Rot mean±std (deg)", "Unc",
                  "NLL-S", "IS", "× floor (trans)")
        parts.append(f"### {rec_name}\n\n" + _md_table(header, rows))
    return "\n\n".join(parts)


def _per_result(evals: Sequence[ResultEvaluation], body: Callable[[dict], str]) -> list[str]:
    """One indented line per result: ``recording  label: body(row)``."""
    return [f"  {ev.row['recording']}  {ev.label}: {body(ev.row)}" for ev in evals]


def comparison_text(evals: Sequence[ResultEvaluation]) -> str:
    """The printable comparison: accuracy, uncertainty, floor and bimodality per result (fixed-width)."""
    header = ("recording", "method", "frames", "trans mm", "rot deg", "q95 mm/deg", "NLL-S t/r", "IS t/r",
              "x floor t/r", "bimodal", "on ambig.", "on clear", "truth dom.", "ms/frame")
    rows = []
    for ev in evals:
        r = ev.row
        rows.append((
            r["recording"], ev.label, str(r["frames"]), _pm(r["trans_mean_mm"], r["trans_std_mm"]),
            _pm(r["rot_mean_deg"], r["rot_std_deg"], 1),
            f"{_f(r['trans_q95_mm'])}/{_f(r['rot_q95_deg'], 1)}{_spread_share(r, 'rot')}",
            f"{_f(r['nlls_trans'])}/{_f(r['nlls_rot'])}", f"{_f(r['is_trans'])}/{_f(r['is_rot'], 1)}",
            f"{_f(r['trans_floor_multiple'], 1)}/{_f(r['rot_floor_multiple'], 1)}", _pct(r["bimodal_share"]),
            _pct(r["bimodal_ambiguous_rate"]), _pct(r["bimodal_clear_rate"]),
            _pct(r["truth_in_dominant_share"]), _f(r["latency_median_ms"], 1),
        ))
    widths = [max(len(h), *(len(x[i]) for x in rows)) if rows else len(h) for i, h in enumerate(header)]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    lines = [line(header), "-" * len(line(header)), *(line(x) for x in rows)]
    floors = {}
    for ev in evals:
        # the floor depends on the likelihood (its switches), not on the method: named as SVN's variant of them
        key = (ev.row["recording"], variant_name("svn", _disabled_of(ev.result)))
        if np.isfinite(ev.row["floor_trans_mm"]):
            floors.setdefault(key, (ev.row["floor_trans_mm"], ev.row["floor_rot_deg"]))
    if floors:
        lines.append("")
        lines.append("accuracy floor (per-frame MAP solved from the truth): " + "; ".join(
            f"{rec}{'' if var == 'full' else ' ' + var}: {t:.2f} mm / {r:.1f} deg"
            for (rec, var), (t, r) in floors.items()
        ))
    if any(ev.row.get("reference") for ev in evals) or any(np.isfinite(ev.row["bimodal_modes_share"])
                                                         for ev in evals):
        ref_methods = sorted({ev.reference_method for ev in evals if ev.reference_method}) or ["mht"]
        lines += ["", f"modes (second mode >= 0.1); rates on frames the reference {'/'.join(ref_methods).upper()} "
                  "calls multimodal / single-mode:"]
        lines += _per_result(evals, lambda r: (
            f"bimodal GMM {_pct(r['bimodal_share'])}, modes "
            f"{_pct(r['bimodal_modes_share'])}; truth kept modes {_pct(r['truth_kept_modes_share'])}, "
            f"particles {_pct(r['truth_kept_particles_share'])}; " + (
                f"vs reference: GMM {_pct(r['bimodal_ref_multi_rate'])} / {_pct(r['bimodal_ref_single_rate'])}, "
                f"modes {_pct(r['bimodal_modes_ref_multi_rate'])} / {_pct(r['bimodal_modes_ref_single_rate'])} "
                f"({r['ref_multimodal_frames']} / {r['ref_single_frames']} frames)" if r.get("reference") else
                "no reference")))
        if not all(ev.row.get("reference") for ev in evals):
            lines.append("  (no reference: neither an mht result of that recording among the inputs nor a --reference "
                         "of it)")
    smoothed = [ev for ev in evals if ev.row["smoothed_frames"] > 0]
    if smoothed:
        lines += ["", "fixed-lag smoothed poses (smoothed.csv) vs the filtered estimates of the same frames:"]
        lines += _per_result(smoothed, lambda r: (
            f"smoothed {_f(r['smoothed_trans_mean_mm'])} mm / {_f(r['smoothed_rot_mean_deg'])} deg, filtered "
            f"{_f(r['filtered_trans_mean_mm_same'])} mm / {_f(r['filtered_rot_mean_deg_same'])} deg "
            f"({r['smoothed_frames']} frames)"))
    lines.append("bimodal = raw share; on ambig./on clear = bimodal rate on frames whose second circle pose "
                 "is within 2.3 nats / beyond 10 nats of the truth's (ΔNLL)")
    if any(_spread_share(ev.row, "rot") for ev in evals):
        lines.append("q95 @k%: q95, NLL-S and IS over the k % of frames that report a spread (the others' q95 "
                     "cells are NaN, unknown)")
    return "\n".join(lines)


def coverage_text(evals: Sequence[ResultEvaluation], source: str) -> str:
    """q95 coverage per result before and after the spread scale ``source`` (rows need ``coverage_raw_*``)."""
    header = ("recording", "method", "kappa t/r", "raw cover t/r", "scaled cover t/r")
    rows = [(ev.row["recording"], ev.label, f"{ev.row['spread_kappa_trans']:.2f}/{ev.row['spread_kappa_rot']:.2f}",
             f"{_pct(ev.row['coverage_raw_trans'])}/{_pct(ev.row['coverage_raw_rot'])}",
             f"{_pct(ev.row['coverage_trans'])}/{_pct(ev.row['coverage_rot'])}") for ev in evals]
    widths = [max(len(x[k]) for x in (header, *rows)) for k in range(len(header))]  # columns under their heads
    lines = [f"q95 coverage (share of frames whose error is within q95), raw -> scaled by {source}:"]
    lines += ["  ".join(c.ljust(w) for c, w in zip(x, widths, strict=True)).rstrip() for x in (header, *rows)]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# figures


#: Longest file-name slug (:func:`_slug`): figure names stay far below the usual 255-byte file-name limit.
SLUG_MAX = 64


def _slug(text: str) -> str:
    """A file-name-safe form of ``text``: each run of other characters than ``A-Za-z0-9._-`` becomes ``_`` (empty:
    ``result``). A longer one than :data:`SLUG_MAX` keeps its head and a hash of the whole text, so two long names
    still differ (a 240-character recording name failed ``evaluate`` after half its files were written)."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "result"
    if len(slug) > SLUG_MAX:
        slug = f"{slug[:SLUG_MAX - 9]}-{hashlib.sha1(text.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"
    return slug


class _Stems:
    """Distinct file-name stems for distinct texts: :func:`_slug`, then ``-2``, ``-3``, ... in the order asked where
    two texts' slugs coincide (recordings named ``x y`` and ``x_y``; every all-non-ASCII name is ``result``), so that
    no figure overwrites another's file."""

    def __init__(self) -> None:
        self._of: dict[object, str] = {}
        self._taken: set[str] = set()

    def __call__(self, text: str, key: object = None) -> str:
        """The stem of ``text``; ``key`` (default ``text``) tells texts apart (a pair of names joined into one text
        can equal another pair's)."""
        key = text if key is None else key
        if key not in self._of:
            base = stem = _slug(text)
            k = 2
            while stem in self._taken:
                stem, k = f"{base}-{k}", k + 1
            self._of[key] = stem
            self._taken.add(stem)
        return self._of[key]


def _cloud_figure(evals: Sequence[ResultEvaluation], out: Path, stems: _Stems) -> list[Path]:
    paths = []
    by_rec: dict[str, list[ResultEvaluation]] = {}
    for ev in evals:
        P = ev.result.particles
        if P is not None and P.cam_T_needle.shape[1] >= 6:
            by_rec.setdefault(ev.recording.info.name, []).append(ev)
    for rec_name, evs in by_rec.items():
        # a frame every set has, ambiguous if possible, where most sets are bimodal and separation is largest
        common = set.intersection(*(set(ev.result.frame[ev.assessed & ev.has_gt].tolist()) for ev in evs))
        if not common:
            continue
        best, best_key = None, None
        for f in common:
            amb = sum(ev.labels[ev.result.frame == f][0] == "ambiguous" for ev in evs) > 0
            n_bi = sum(bool(ev.bimodal[ev.result.frame == f][0]) for ev in evs)
            d = max(np.nan_to_num(ev.ashman_d[ev.result.frame == f][0]) for ev in evs)
            key = (amb, n_bi, d)
            if best_key is None or key > best_key:
                best, best_key = f, key
        panels = []
        for ev in evs:
            i = int(np.nonzero(ev.result.frame == best)[0][0])
            P = ev.result.particles
            w = None if P.weight is None else P.weight[i]
            T_map = ev.result.cam_T_needle[i]
            v = assess_bimodality(P.cam_T_needle[i], T_map, weights=w, T_gt=ev.T_gt[i])
            X = tangent_at_map(T_map, P.cam_T_needle[i])
            if w is not None or X.shape[0] > 1000:
                X = X[systematic_resample(np.ones(X.shape[0]) if w is None else w, min(X.shape[0], 1000),
                                          np.random.default_rng(0))]
            panels.append(plots.CloudPanel(label=ev.label, scaled_xi=X, verdict=v))
        label = "ambiguous" if best_key[0] else "no ambiguous frame; most separated"
        title = f"{rec_name}, frame {best} ({label})"
        paths.append(plots.particle_cloud(panels, title, out / f"particle_cloud_{stems(rec_name)}.png"))
    return paths


def _figures(evals: Sequence[ResultEvaluation], out: Path) -> list[Path]:
    paths: list[Path] = []
    recs, labels, pairs = _Stems(), _Stems(), _Stems()  # file-name stems: distinct figures never share a file

    def pair(ev: ResultEvaluation) -> str:
        name = ev.recording.info.name
        return pairs(f"{recs(name)}_{labels(ev.label)}", key=(name, ev.label))

    groups: dict[str, list[plots.MethodErrors]] = {}
    for ev in evals:
        g = ev.has_gt & np.isfinite(ev.errors.trans_m)
        groups.setdefault(ev.recording.info.name, []).append(plots.MethodErrors(
            label=ev.label, trans_mm=1e3 * ev.errors.trans_m[g], rot_deg=np.degrees(ev.errors.rot_rad[g]),
            trans_axes_mm=1e3 * ev.errors.trans_axes_m[g], rot_axes_deg=np.degrees(ev.errors.rot_axes_rad[g]),
        ))
    paths.append(plots.error_distributions(list(groups.items()), out / "errors.png"))
    for ev in evals:
        res = ev.result
        paths.append(plots.error_over_time(
            res.t_s, 1e3 * ev.errors.trans_m, np.degrees(ev.errors.rot_rad), 1e3 * res.q95_trans_m,
            np.degrees(res.q95_rot_rad), ev.occlusion, f"{ev.label} on {ev.recording.info.name}",
            out / f"error_time_{pair(ev)}.png", bimodal=ev.bimodal,
            floor_trans_mm=1e3 * ev.floor_errors.trans_m, floor_rot_deg=np.degrees(ev.floor_errors.rot_rad),
        ))
    paths += _cloud_figure(evals, out, recs)
    for ev in evals:
        if ev.modes is not None and ev.modes.has_modes.any():
            paths.append(plots.mode_weights_over_time(
                ev.result.t_s, ev.modes.weights, f"mode weights: {ev.label} on {ev.recording.info.name}",
                out / f"modes_time_{pair(ev)}.png",
            ))
    for rec_name, evs in _ablation_groups(evals).items():
        names = [_variant_title(ev.variant) for ev in evs]
        ref = next((i for i, ev in enumerate(evs) if ev.variant == "full"), None)
        paths.append(plots.ablation_bars(
            names, [ev.row["trans_mean_mm"] for ev in evs], [ev.row["rot_mean_deg"] for ev in evs],
            f"Ablations on {rec_name}", out / f"ablation_{recs(rec_name)}.png", reference=ref,
        ))
    return paths


# --------------------------------------------------------------------------------------------
# entry points


@dataclass
class EvaluationReport:
    """What :func:`evaluate_results` computed and wrote."""

    evaluations: list[ResultEvaluation]
    """One per result, in the order given."""
    text: str
    """The printable comparison (:func:`comparison_text`)."""
    table_ii: str
    """Markdown Table II."""
    table_iii: str
    """Markdown Table III ('' without ablation results)."""
    files: list[Path]
    """Every file written (summary.csv, tables.md, figures)."""


def _write_summary(evals: Sequence[ResultEvaluation], path: Path) -> Path:
    extra = sorted({k for ev in evals for k in ev.row} - set(SUMMARY_COLUMNS))
    cols = [*SUMMARY_COLUMNS, *extra]
    with open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(cols)
        for ev in evals:
            cells = []
            for c in cols:
                v = ev.row.get(c, "")
                cells.append(repr(float(v)) if isinstance(v, float) else str(v))
            w.writerow(cells)
    return path


def evaluate_results(
    results: Sequence[Path | str],
    recording: Path | str | None = None,
    out: Path | str = Path("evaluation"),
    *,
    ambiguity: bool = True,
    figures: bool = True,
    config: AmbiguityConfig | None = None,
    progress: Callable[[str], None] | None = None,
    reference: Path | str | None = None,
    spread_scale: SpreadScale | None = None,
) -> EvaluationReport:
    """Evaluate result directories (module docstring); returns everything computed.

    A directory of results (``pinpoint-fg batch`` output) stands for its result sub-directories
    (:func:`~pinpoint_fg.io.result.expand_result_dirs`); each other sub-directory of it gets a ``note:`` line in the
    text (an empty one is what a failed batch run left: the evaluation is then not of the whole batch).
    ``ambiguity=False`` skips the ΔNLL labels (sensitivity / false-bimodal rates become NaN) but still computes
    the accuracy floor.
    ``progress(message)`` is called at each stage when given.
    ``reference``: a multi-hypothesis result (with modes.csv) whose per-frame modes judge the
    bimodal verdicts of the results of the same recording (a reference of none of their recordings is an
    :class:`InputError`, and so is a single-mode ``map`` result, which calls every frame single-mode; the text
    names the reference's method); without it, the first ``mht`` result of each recording among ``results`` is used.
    ``spread_scale`` (:mod:`pinpoint_fg.io.spread_scale`): every result's q95 columns are multiplied
    by its method's factors before any metric or figure uses them (the files are not changed); the rows gain
    ``spread_kappa_trans`` / ``_rot`` and the raw coverage ``coverage_raw_trans`` / ``_rot``, and the text a
    coverage table raw vs scaled. A result whose q95 were scaled when tracked (``settings.spread_scale``) is
    refused with ``spread_scale`` (no double scaling); without it, its recorded factors fill those columns
    (and the raw coverage is that of ``q95 / kappa``).
    """
    given_paths = path_list("results", results)
    skipped: list[Path] = []  # sub-directories of a batch directory that are not results: named in a note
    results = expand_result_dirs(given_paths, skipped)
    if not results:
        raise InputError("no results to evaluate")
    out = path_argument("out", out)  # None was pathlib's TypeError, naming no argument
    say = progress or (lambda _msg: None)
    given = read_recording(recording) if recording is not None else None
    cache: dict[Path, Recording] = {}
    loaded: list[tuple[Result, Recording, MeasurementModel, tuple]] = []
    kappas: list[tuple[float, float] | None] = []  # the factor each result's q95 are scaled by, None: raw
    raw_q95: list[tuple[np.ndarray, np.ndarray]] = []
    for p in results:
        res = read_result(p)
        recorded = recorded_scale(_settings_of(res), res.root / "result.json")
        if recorded is not None and spread_scale is not None:
            raise InputError("its q95 were already scaled when it was tracked (track --spread-scale); evaluate "
                             "it without --spread-scale", file=res.root / "result.json", column="settings.spread_scale")
        kt, kr = recorded if recorded is not None else (1.0, 1.0)
        raw_q95.append((res.q95_trans_m / kt, res.q95_rot_rad / kr))  # exact when not scaled at tracking time
        if spread_scale is not None:
            s = spread_scale.for_method(res.method)
            recorded = (s.kappa_trans, s.kappa_rot)
            res = scaled_result(res, spread_scale)
        kappas.append(recorded)
        rec = _recording_for(res, given, cache)
        noise, noise_key = _noise_of(res)
        noise, distance = _conic_model_of(res, noise)
        disabled = _disabled_of(res)
        sw = Switches.from_disabled(disabled)
        model = MeasurementModel(rec.info.camera, rec.info.needle, noise, sw, conic_distance=distance)
        key = (str(rec.root.resolve()), noise_key, noise.conic_correlation_px, distance,
               tuple(d for d in disabled if d != "motion"))
        loaded.append((res, rec, model, key))
    _refuse_namesakes([(res, rec) for res, rec, _, _ in loaded])

    refs: dict[str, Reference] = {}  # read before the long computations: a wrong one costs nothing
    if reference is not None:
        ref_res = read_result(reference)
        if not (ref_res.root / MODES_CSV).exists():
            raise InputError("the reference has no modes.csv (give a multi-hypothesis result)",
                             file=ref_res.root / MODES_CSV)
        ref_name = str(ref_res.info["recording_name"])
        names_evaluated = sorted({rec.info.name for _, rec, _, _ in loaded})
        if ref_name not in names_evaluated:  # it would judge nothing: every rate against it silently empty
            raise InputError(f"the reference is of recording {ref_name!r}, but the results are of "
                             f"{', '.join(map(repr, names_evaluated))}", file=ref_res.root / "result.json",
                             column="recording_name")
        check_tracked_on(ref_res, next(rec for _, rec, _, _ in loaded if rec.info.name == ref_name))
        if ref_res.method == "map":  # one mode per frame: every rate against it would read "single-mode"
            raise InputError("the reference is a single-mode MAP result, which calls every frame single-mode; give a "
                             "multi-hypothesis result (mht; or svn, svgd, pf)", file=ref_res.root / "result.json",
                             column="method")
        rm = modes_of_result(ref_res)
        refs[ref_name] = (str(ref_res.root), ref_res.frame, rm.weights, ref_res.method)

    say("modes")  # before the long computations too: a modes.csv that lacks frames is refused at once
    modes = [modes_of_result(res) for res, _, _, _ in loaded]
    # ground truth that does not describe its frame (gt_scale): checked before ``out`` exists, as it may refuse
    say("ground truth scale")
    recs = {rec.root: rec for _, rec, _, _ in loaded}
    frames_of: dict[Path, set[int]] = {root: set() for root in recs}
    for res, rec, _, _ in loaded:
        frames_of[rec.root].update(int(f) for f in res.frame)
    left_out = {root: left_out_frames(rec, frames_of[root]) for root, rec in recs.items()}
    # created only now that every input has been read: a refused one leaves no empty ``out`` behind
    # not into (or inside) a result, batch directory, recording or reference it reads, as the command line checks
    out = prepare_output_dir(out, True, "evaluation", inputs=[*given_paths, *results, *recs, *(
        p for p in (recording, reference) if p is not None)])

    # ΔNLL labels and floor: once per (recording, likelihood), on the union of the frames needed
    needed: dict[tuple, set[int]] = {}
    for res, rec, _, key in loaded:
        gone = {int(r.frame) for r, _ in left_out[rec.root]}
        needed.setdefault(key, set()).update(int(f) for f in res.frame if int(f) not in gone)
    analyses: dict[tuple, RecordingAmbiguity] = {}
    for _, rec, model, key in loaded:
        if key not in analyses:
            say(f"ambiguity and floor: {rec.info.name} ({len(needed[key])} frames)")
            analyses[key] = analyse_recording(
                rec, model, config or AmbiguityConfig(), alternatives=ambiguity, frames=needed[key]
            )

    if reference is None:
        for (res, rec, _, _), m in zip(loaded, modes, strict=True):
            if res.method == "mht" and m.source == "modes.csv" and rec.info.name not in refs:
                refs[rec.info.name] = (str(res.root), res.frame, m.weights, res.method)

    names: dict[str, int] = {}
    evals = []
    for (res, rec, _, key), res_modes in zip(loaded, modes, strict=True):
        disabled = _disabled_of(res)
        variant = variant_name(res.method, disabled)
        label = res.method if variant in ("full", "svgd") else f"{res.method} {variant}"
        window = _settings_of(res).get("window")
        if isinstance(window, int) and window > 1:
            label += f" L={window}"
        tag = (rec.info.name, label)
        names[str(tag)] = names.get(str(tag), 0) + 1
        if names[str(tag)] > 1:
            label += f" #{names[str(tag)]}"
        say(f"metrics: {label} on {rec.info.name}")
        evals.append(_evaluate_one(res, rec, analyses[key], variant, label, res_modes, refs.get(rec.info.name),
                                   {int(r.frame) for r, _ in left_out[rec.root]}))

    text_scaled = ""
    if any(k is not None for k in kappas):
        for ev, k, (qt, qr) in zip(evals, kappas, raw_q95, strict=True):
            ev.row["spread_kappa_trans"], ev.row["spread_kappa_rot"] = k if k is not None else (1.0, 1.0)
            ev.row["coverage_raw_trans"] = coverage(np.where(ev.has_gt, ev.errors.trans_m, np.nan), qt)
            ev.row["coverage_raw_rot"] = coverage(np.where(ev.has_gt, ev.errors.rot_rad, np.nan), qr)
        src = spread_scale.source if spread_scale is not None else None
        text_scaled = "\n\n" + coverage_text(evals, src or "the factors recorded when tracked")
    files = [_write_summary(evals, out / "summary.csv")]
    t2, t3, tm = table_ii(evals), table_iii(evals), table_multimodal(evals)
    md = ["# Evaluation", "", "## Tracking comparison (Table II)", "", t2, "", "## Multimodality", "", tm,
          "", "## Posterior modes", "", table_modes(evals)]
    if t3:
        md += ["", "## Ablations (Table III)", "", t3]
    ts = table_smoothed(evals)
    if ts:
        md += ["", "## Fixed-lag smoothing", "", ts]
    (out / "tables.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    files.append(out / "tables.md")
    if figures:
        say("figures")
        files += _figures(evals, out)
    text = (comparison_text(evals) + text_scaled + partial_text(evals, [(res, rec) for res, rec, _, _ in loaded])
            + no_truth_text(evals))
    notes = [skipped_dir_note(d) for d in skipped]
    notes += [left_out_note(recs[root], gone, " of the scores") for root, gone in left_out.items() if gone]
    # every tracker writes modes.csv; without it (an older result, or the file removed) the modes are the particles'
    notes += [f"note: {res.root} has no {MODES_CSV}: its modes are recomputed from its particles"
              for (res, _, _, _), m in zip(loaded, modes, strict=True) if m.source == "particles"]
    if notes:
        text += "\n\n" + "\n".join(notes)
    return EvaluationReport(evaluations=evals, text=text, table_ii=t2, table_iii=t3, files=files)


def partial_text(evals: Sequence[ResultEvaluation], pairs: Sequence[tuple[Result, Recording]]) -> str:
    """Lines naming every result that covers fewer frames than its recording: stopped early (``result.json``
    ``complete`` false: interrupted, or a located error) or tracked with ``--max-frames``. Its figures are over
    its own frames only, so a comparison with a complete result of the same run compares different frames."""
    lines = []
    for ev, (res, rec) in zip(evals, pairs, strict=True):
        if len(res) < len(rec.frames):
            why = "tracked with fewer frames" if res.complete else "stopped early (result.json: complete false)"
            lines.append(f"partial: {ev.label} on {rec.info.name} ({res.root}): {len(res)} of {len(rec.frames)} "
                         f"frames, {why}; its figures are over those frames only")
    return "\n\n" + "\n".join(lines) if lines else ""


def no_truth_text(evals: Sequence[ResultEvaluation]) -> str:
    """A line per result whose recording has no ground-truth pose on any frame (its table row reads "0 frames" and
    dashes, which alone looked like a failure): only its verdicts and timings are reported. Ground truth left out
    by :mod:`~pinpoint_fg.eval.gt_scale`'s tests has its own note (:func:`~pinpoint_fg.eval.gt_scale.left_out_note`)."""
    lines = [f"no ground truth: {ev.label} on {ev.recording.info.name} ({ev.result.root}): none of its "
             f"{len(ev.has_gt)} frames has a ground-truth pose (frames.csv gt_* cells), so its errors, q95 "
             "coverage and NLL are not scored; only its verdicts and timings are"
             for ev in evals if all(fr.cam_T_needle_gt is None for fr in ev.recording.frames)]
    return "\n\n" + "\n".join(lines) if lines else ""


def evaluate(results: list[Path], recording: Path | None = None, out: Path = Path("evaluation"),
             reference: Path | None = None, spread_scale: Path | None = None) -> str:
    """Evaluate results, write summary.csv, tables.md and figures to ``out``; return the printable summary.

    ``spread_scale``: a file of ``calibrate-spread`` whose factors scale the results' q95 (see
    :func:`evaluate_results`); it is read before anything is computed.
    """
    scale = SpreadScale.load(spread_scale) if spread_scale is not None else None
    return evaluate_results(results, recording, out, reference=reference, spread_scale=scale).text
