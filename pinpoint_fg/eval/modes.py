"""Evaluation of posterior modes: the modes verdict, truth kept, and bimodality judged against a reference.

Per result (frame axis first):

* **mode weights** ``(F, K)`` sorted per frame, zero-padded, NaN rows for frames without modes:
  from the result's ``modes.csv`` (:func:`pinpoint_fg.io.result.read_modes`), which must cover the frames of
  ``estimates.csv`` (:func:`~pinpoint_fg.io.result.reader.check_modes_cover`); a result written
  before modes.csv existed has them recomputed from its particles
  (:func:`pinpoint_fg.posterior.summary.modes_from_particles`; a single particle is one mode).
* **modes verdict** per frame: the second mode weighs at least 0.1
  (:data:`pinpoint_fg.posterior.summary.BIMODAL_MODE_WEIGHT`).
* **truth kept**: the share of frames with ground truth where some mode peak
  (``truth_kept_modes_share``), respectively some particle (``truth_kept_particles_share``), is
  within ``TRUTH_KEPT_TRANS_M`` = 2 mm AND ``TRUTH_KEPT_ROT_RAD`` = 10 deg of the truth.
* **mode weights against the truth** (:func:`mode_weight_calibration`): on the frames where some
  mode keeps the truth, the mean weight of the minor modes (``minor_weight_mean``: the probability the
  result gives to the truth *not* being in its dominant mode) beside the share of those frames where
  the truth is in a minor mode and not in the dominant one (``truth_minor_share``). Calibrated
  weights make the two equal; a "bimodal" verdict that the reference calls false can then be
  checked against the truth rather than against the reference.
* **reference rates**: a reference result (a multi-hypothesis tracker, MHT, on the same recording)
  calls a frame *multimodal* when its second mode weighs at least 0.1, else *single-mode*. On the
  frames both results have (the reference's frames with modes), the share of frames each verdict
  (GMM ``bimodal``, modes ``bimodal_modes``) calls bimodal is reported separately on the
  reference-multimodal frames (sensitivity; issue target >= 90 %) and on the reference-single-mode
  frames (false-bimodal rate; target <= 5 %). A rate over zero frames is NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.result.reader import check_modes_cover, read_modes
from pinpoint_fg.io.result.schema import MAX_MODES, MODES_CSV, ModeHistory, Result
from pinpoint_fg.posterior.summary import BIMODAL_MODE_WEIGHT, modes_from_particles

TRUTH_KEPT_TRANS_M = 2e-3
"""A mode / particle keeps the truth when within this translation (m) ..."""
TRUTH_KEPT_ROT_RAD = math.radians(10.0)
"""... and within this rotation (rad) of it."""


@dataclass(frozen=True)
class ResultModes:
    """The modes of one result, per frame of the result."""

    weights: np.ndarray
    """(F, K) sorted mode weights, zero-padded; NaN rows where the frame has no modes."""
    peaks: list
    """(F,) list of (M_f, 4, 4) mode peak poses (empty (0, 4, 4) where no modes)."""
    source: str
    """``"modes.csv"``, ``"particles"`` (recomputed; ``evaluate`` prints a ``note:`` line) or ``"none"``."""

    @property
    def has_modes(self) -> np.ndarray:
        """(F,) bool."""
        return np.isfinite(self.weights[:, 0])

    @property
    def bimodal(self) -> np.ndarray:
        """(F,) bool: the modes verdict (False where no modes)."""
        return np.nan_to_num(self.weights[:, 1]) >= BIMODAL_MODE_WEIGHT


def modes_of_result(res: Result, k: int = MAX_MODES) -> ResultModes:
    """The result's modes (module docstring: modes.csv, else recomputed from the particles)."""
    F = len(res)
    empty = np.zeros((0, 4, 4))
    if (res.root / MODES_CSV).exists():
        hist: ModeHistory = read_modes(res.root)
        check_modes_cover(hist, res)  # a frame without its modes was left out of the modes figures, silently
        pos = {int(f): i for i, f in enumerate(res.frame)}
        peaks = [empty] * F
        for f in hist.frames:
            if int(f) in pos:
                peaks[pos[int(f)]] = hist.cam_T_needle[hist.frame == f]
        return ResultModes(hist.weights_at(res.frame, k), peaks, "modes.csv")
    P = res.particles
    W = np.full((F, k), np.nan)
    peaks = [empty] * F
    if P is None:
        return ResultModes(W, peaks, "none")
    for i in range(len(P.frame)):
        modes = modes_from_particles(P.cam_T_needle[i], P.log_posterior[i], None if P.weight is None else P.weight[i],
                                     k_max=k)
        W[i] = 0.0
        W[i, :len(modes)] = [m.weight for m in modes]
        peaks[i] = np.stack([m.cam_T_needle for m in modes])
    return ResultModes(W, peaks, "particles")


def near_truth(T: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """(..., ) bool: poses T (..., 4, 4) within the truth-kept thresholds of T_gt (broadcast)."""
    e = pose_errors(T, T_gt)
    return (e.trans_m <= TRUTH_KEPT_TRANS_M) & (e.rot_rad <= TRUTH_KEPT_ROT_RAD)


def peaks_near_truth(modes: ResultModes, T_gt: np.ndarray, has_gt: np.ndarray) -> dict[int, np.ndarray]:
    """Per frame index with ground truth and modes: (M_f,) bool, which mode peaks are near the truth."""
    return {int(i): near_truth(modes.peaks[i], T_gt[i][None]) for i in np.nonzero(has_gt & modes.has_modes)[0]}


def truth_kept(res: Result, modes: ResultModes, T_gt: np.ndarray, has_gt: np.ndarray,
               near: dict[int, np.ndarray] | None = None) -> dict[str, float]:
    """``truth_kept_modes_share`` and ``truth_kept_particles_share`` (NaN when nothing to judge).

    ``near``: :func:`peaks_near_truth` when the caller has it already."""
    near = peaks_near_truth(modes, T_gt, has_gt) if near is None else near
    kept = [bool(m.any()) for m in near.values()]
    out = {"truth_kept_modes_share": float(np.mean(kept)) if kept else float("nan")}
    P = res.particles
    if P is None:
        out["truth_kept_particles_share"] = float("nan")
        return out
    n = len(P.frame)
    g = np.nonzero(has_gt[:n])[0]
    if g.size == 0:
        out["truth_kept_particles_share"] = float("nan")
        return out
    near = near_truth(P.cam_T_needle[g], T_gt[g][:, None])  # (G, N)
    out["truth_kept_particles_share"] = float(np.mean(np.any(near, axis=1)))
    return out


def mode_weight_calibration(modes: ResultModes, T_gt: np.ndarray, has_gt: np.ndarray,
                            near: dict[int, np.ndarray] | None = None) -> dict[str, float | int]:
    """``minor_weight_mean``, ``truth_minor_share`` and their frame count ``truth_mode_frames`` (module docstring).

    ``T_gt`` (F, 4, 4) and ``has_gt`` (F,) per frame of the result; the dominant mode is the heaviest
    (the first on ties). NaN when no mode keeps the truth on any frame. ``near``: :func:`peaks_near_truth`
    when the caller has it already.
    """
    near = peaks_near_truth(modes, T_gt, has_gt) if near is None else near
    minor_w, in_minor = [], []
    for i, is_near in near.items():
        if not is_near.any():
            continue
        w = modes.weights[i, : is_near.shape[0]]
        dom = int(np.argmax(w))
        minor_w.append(float(np.sum(w) - w[dom]) / float(np.sum(w)))
        in_minor.append(not bool(is_near[dom]))
    if not minor_w:
        return {"minor_weight_mean": float("nan"), "truth_minor_share": float("nan"), "truth_mode_frames": 0}
    return {"minor_weight_mean": float(np.mean(minor_w)), "truth_minor_share": float(np.mean(in_minor)),
            "truth_mode_frames": len(minor_w)}


def reference_rates(frames: np.ndarray, bimodal: np.ndarray, assessed: np.ndarray, bimodal_modes: np.ndarray,
                    has_modes: np.ndarray, ref_frames: np.ndarray, ref_weights: np.ndarray) -> dict[str, float | int]:
    """Bimodal rates of both verdicts on the reference's multimodal vs single-mode frames (module docstring).

    ``frames`` (F,) of the evaluated result with its GMM verdict ``bimodal`` (valid where
    ``assessed``) and modes verdict ``bimodal_modes`` (valid where ``has_modes``); ``ref_frames``
    (R,) and ``ref_weights`` (R, K) of the reference (NaN rows: no modes, ignored).
    """
    ref_ok = np.isfinite(ref_weights[:, 0])
    ref_multi = {int(f): bool(w[1] >= BIMODAL_MODE_WEIGHT)
                 for f, w, ok in zip(ref_frames, ref_weights, ref_ok, strict=True) if ok}
    label = np.array([ref_multi.get(int(f), None) for f in frames], dtype=object)
    multi = np.array([x is True for x in label])
    single = np.array([x is False for x in label])

    def rate(verdict: np.ndarray, valid: np.ndarray, on: np.ndarray) -> float:
        s = valid & on
        return float(np.mean(verdict[s])) if s.any() else float("nan")

    return {
        "ref_multimodal_frames": int(multi.sum()), "ref_single_frames": int(single.sum()),
        "bimodal_ref_multi_rate": rate(bimodal, assessed, multi),
        "bimodal_ref_single_rate": rate(bimodal, assessed, single),
        "bimodal_modes_ref_multi_rate": rate(bimodal_modes, has_modes, multi),
        "bimodal_modes_ref_single_rate": rate(bimodal_modes, has_modes, single),
    }
