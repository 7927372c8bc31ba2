"""Noise calibration (paper §V "Calibration", Table I): residual statistics at ground-truth poses.

For every frame of every run that has a ground-truth pose ``T_gt = cam_T_needle_gt`` each
residual of :mod:`factors.residuals` (the only copy of the maths) is evaluated *at the truth*:

* ``tip`` / ``tail``: ``pi(T_gt X) - z`` with ``z`` the recorded keypoint, undistorted
  (:func:`pinpoint_fg.observe.observe_frame`), pixels;
* ``conic``: the Sampson distance of every backbone pixel that
  :func:`~pinpoint_fg.observe.observe_frame` extracts from the frame's mask, pixels (one sample
  per pixel);
* ``grasp_position``: ``T_gt X_g - p_g`` (camera axes), metres;
* ``grasp_perpendicular``: ``z_g . (R_gt t_g)``, unitless;
* ``motion``: ``Log((D T_gt(k-1))^-1 T_gt(k))`` with ``D = cam_T_grasper(k) cam_T_grasper(k-1)^-1``
  from the recorded kinematics, for every pair of consecutive frames (frame indices differing
  by exactly one, so the statistic is per camera frame) that both have ground truth and
  kinematics; tangent ``[omega (rad); v (m)]``.

Per type the sample mean ``mu = (1/n) sum r_i`` and the unbiased sample covariance
``S = 1/(n-1) sum (r_i - mu)(r_i - mu)^T`` are returned as a :class:`~pinpoint_fg.noise.NoiseConfig`
(``count = n``). The tracker subtracts ``mu`` (a bias) and whitens with ``S``.

Choices the paper leaves open:

* A type with fewer than ``d + 1`` samples (``d`` its dimension) cannot give a full-rank
  covariance; it keeps its default (Table I) with ``count = 0``, and :func:`format_table` marks
  it as a default.
* A covariance that is numerically singular (e.g. perfect kinematics) has its eigenvalues
  floored at ``1e-12`` times the largest (and at ``1e-30`` absolutely) so it stays positive
  definite; nothing else is changed.
* Residuals whose error is a slowly varying bias (robot kinematics) are strongly correlated in
  time: the sampling error of their covariance is set by the number of *independent* stretches
  (run length / correlation time), not by the frame count. Calibrate on long, varied runs.
* A ground-truth pose whose needle would look far smaller than the frame's image measurements
  show it, or lie far from where they show it (:mod:`pinpoint_fg.eval.gt_scale`: a depth typed in the
  wrong unit, a metre typed for a millimetre in one cell, a failed board detection) does not describe
  that frame: its residuals are those of another pose. Such frames
  are left out and named (``skipped``); when every ground-truth frame of a run that it can test
  is, the run is refused (:class:`InputError` at its first such row, ``gt_z_m``). Three such frames among forty
  (depth 9.9 m) had given an anchor std of 2.6 m and a conic std of 11 px (1.2 px without them).
* The backbone residuals of one mask are correlated along the arc. With ``fit_correlation``
  (``calibrate --conic-correlation``) the correlation length ``ell`` of the Ornstein-Uhlenbeck
  model of :mod:`factors.conic_correlation` is fitted too, from the residuals' integrated
  autocorrelation along the arc (:func:`fit_conic_correlation`), and written to the noise file;
  without it the file keeps independent pixels (``ell = 0``), the paper's model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from factors import residuals as res
from factors.conic_correlation import arc_order
from pinpoint_fg.errors import InputError, path_list, refuse_repeated
from pinpoint_fg.eval.gt_scale import GtMismatch, gt_mismatch, left_out_note, refuse_all_left_out, seen_point_behind
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.likelihood import CONIC_DISTANCES
from pinpoint_fg.noise import RESIDUAL_DIMS, NoiseConfig, ResidualNoise
from pinpoint_fg.observation import Observation
from pinpoint_fg.observe import ignored_masks_note, observe_frame

#: Relative eigenvalue floor applied to a singular sample covariance.
COV_REL_FLOOR = 1e-12
#: Absolute eigenvalue floor (units of the residual squared).
COV_ABS_FLOOR = 1e-30


def _in_front(recording: Recording, rec: FrameRecord, T: np.ndarray, obs: Observation) -> None:
    """:class:`InputError` at the frame's ``gt_z_m`` when a needle point seen in its image lies at a depth <=
    :data:`factors.residuals.MIN_DEPTH_M` (:func:`~pinpoint_fg.eval.gt_scale.seen_point_behind`): the image
    residuals there are those of its mirror image (a conic cannot tell them apart), and calibrating on them
    silently inflated the noise (one such frame of eight: tip std 0.6 -> 42 px)."""
    behind = seen_point_behind(recording, T, obs.tip_px, obs.tail_px, obs.backbone_px)
    if behind is not None:
        raise InputError(f"the ground truth puts the needle's {behind.detail} at depth {behind.value:.3g} m, not in "
                         "front of the camera that sees it; correct the gt_* cells or clear them",
                         file=recording.csv_path, row=recording.row_of(rec), column="gt_z_m")



def residuals_at_truth(recording: Recording, conic_frames: list | None = None, conic_distance: str = "sampson",
                       skipped: list | None = None, ignored_masks: list | None = None) -> dict[str, np.ndarray]:
    """Every residual type evaluated at the ground-truth poses of one run.

    Returns ``{type: (n, d) array}`` for the types of :data:`pinpoint_fg.noise.RESIDUAL_DIMS` (``n`` may be 0).
    Frames without ground truth contribute nothing. ``conic_frames``: a list that receives each masked frame's
    ``(backbone pixels (M, 2), residuals (M,))``. ``conic_distance``: the backbone residual's, "sampson"
    (:func:`factors.residuals.conic_residual`) or "geometric" (:func:`factors.residuals.conic_geometric_residual`):
    calibrate with the one you track with. ``skipped``: a list that receives ``(frame record, why)`` of each
    ground-truth frame left out by the tests of :mod:`pinpoint_fg.eval.gt_scale`. ``ignored_masks``: a list that
    receives ``(frame, why)`` of each ground-truth frame whose mask :func:`~pinpoint_fg.observe.observe_frame`
    ignores (its backbone then adds nothing). Raises :class:`InputError` naming the run when no frame has ground
    truth, naming the row when a frame's ground truth puts a needle point its image shows behind the camera, and
    naming the first such row when those tests leave out every ground-truth frame that they could test.
    """
    if not recording.has_ground_truth:
        raise InputError("no frame has ground truth (gt_* columns): cannot calibrate", file=recording.root)
    if conic_distance not in CONIC_DISTANCES:
        raise ValueError(f"conic_distance must be one of {', '.join(CONIC_DISTANCES)}, got {conic_distance!r}")
    conic = res.conic_geometric_residual if conic_distance == "geometric" else res.conic_residual
    cam, nd = recording.info.camera, recording.info.needle
    K = cam.K
    out: dict[str, list[np.ndarray]] = {k: [] for k in RESIDUAL_DIMS}
    prev = None  # previous FrameRecord
    left_out: list[tuple[FrameRecord, GtMismatch]] = []
    passed = 0  # frames the gate could test and kept
    for rec in recording.frames:
        T = rec.cam_T_needle_gt
        if T is None:
            prev = None
            continue
        obs = observe_frame(recording, rec)
        _in_front(recording, rec, T, obs)
        why, tested = gt_mismatch(recording, T, obs.tip_px, obs.tail_px, obs.backbone_px)
        if why is not None:
            left_out.append((rec, why))
            prev = None  # nor the motion residuals that would pair it with its neighbours
            continue
        passed += tested
        if obs.mask_ignored is not None and ignored_masks is not None:  # a frame calibrated without its mask
            ignored_masks.append((int(rec.frame), obs.mask_ignored))
        if obs.tip_px is not None:
            out["tip"].append(res.keypoint_residual(T, K, nd.tip_m, obs.tip_px)[0])
        if obs.tail_px is not None:
            out["tail"].append(res.keypoint_residual(T, K, nd.tail_m, obs.tail_px)[0])
        if obs.backbone_px is not None:
            r = conic(T, K, nd.radius_m, obs.backbone_px, jacobian=False)[0].reshape(-1)
            out["conic"].append(r[:, None])
            if conic_frames is not None:
                conic_frames.append((obs.backbone_px, r))
        G = rec.cam_T_grasper
        if G is not None:
            out["grasp_position"].append(res.grasp_position_residual(T, nd.grasp_m, G[:3, 3])[0])
            perp = res.grasp_perpendicular_residual(T, nd.grasp_tangent, G[:3, 2])[0]
            out["grasp_perpendicular"].append(perp)
            if prev is not None and prev.cam_T_grasper is not None and rec.frame - prev.frame == 1:
                D = G @ np.linalg.inv(prev.cam_T_grasper)
                out["motion"].append(res.motion_residual(prev.cam_T_needle_gt, T, D)[0])
        prev = rec
    if left_out and passed == 0:
        refuse_all_left_out(recording, left_out)
    if skipped is not None:
        skipped.extend(left_out)
    return {k: (np.concatenate(v, axis=0) if v else np.zeros((0, RESIDUAL_DIMS[k]))) for k, v in out.items()}


def _floored_cov(samples: np.ndarray) -> np.ndarray:
    """Unbiased sample covariance ``(d, d)`` of ``samples`` ``(n, d)``, eigenvalues floored (see module)."""
    cov = np.atleast_2d(np.cov(samples, rowvar=False, ddof=1))
    cov = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(cov)
    floor = max(COV_REL_FLOOR * float(max(w[-1], 0.0)), COV_ABS_FLOOR)
    if w[0] > floor:
        return cov
    w = np.maximum(w, floor)
    return (V * w) @ V.T


def noise_from_residuals(samples: dict[str, np.ndarray]) -> NoiseConfig:
    """Sample mean and covariance per residual type (``{type: (n, d)}``) -> :class:`NoiseConfig`.

    Types with fewer than ``d + 1`` samples keep their defaults (``count = 0``).
    """
    fitted: dict[str, ResidualNoise] = {}
    for name, d in RESIDUAL_DIMS.items():
        r = np.asarray(samples.get(name, np.zeros((0, d))), dtype=float).reshape(-1, d)
        r = r[np.all(np.isfinite(r), axis=1)]
        if r.shape[0] < d + 1:
            continue
        fitted[name] = ResidualNoise(mean=r.mean(axis=0), cov=_floored_cov(r), count=int(r.shape[0]))
    return NoiseConfig(residuals=fitted)


#: Longest lag (pixels along the arc order) of the pooled autocorrelation :func:`fit_conic_correlation` sums.
CORRELATION_MAX_LAG = 400


def conic_autocorrelation(frames: list[tuple[np.ndarray, np.ndarray]], noise: ResidualNoise,
                          max_lag: int = CORRELATION_MAX_LAG) -> tuple[np.ndarray, float]:
    """Pooled autocorrelation ``rho (K + 1,)`` of the backbone residuals along the arc, by lag in pixels of the
    arc order (:func:`factors.conic_correlation.arc_order`), and the median step between consecutive pixels (px).

    ``frames``: per masked frame, pixels ``(M, 2)`` and residuals ``(M,)``. The residuals are centred on
    ``noise``'s mean (the calibrated bias, not each frame's own mean: a frame's common offset is correlated
    noise too); ``rho(k) = sum x_i x_{i+k} / n_k`` over all frames' pairs at lag ``k``, divided by ``rho(0)``.
    """
    mean = float(noise.mean[0])
    num = np.zeros(max_lag + 1)
    count = np.zeros(max_lag + 1)
    steps = []
    for points, r in frames:
        order = arc_order(points)
        x = np.asarray(r, dtype=float)[order] - mean
        q = np.asarray(points, dtype=float)[order]
        steps.append(np.sqrt(((q[1:] - q[:-1]) ** 2).sum(axis=1)))
        for k in range(min(max_lag, x.shape[0] - 1) + 1):
            num[k] += float(x[: x.shape[0] - k] @ x[k:])
            count[k] += x.shape[0] - k
    cov = num / np.maximum(count, 1.0)
    rho = np.where(count > 0, cov / cov[0], 0.0) if cov[0] > 0 else np.zeros(max_lag + 1)
    step = float(np.median(np.concatenate(steps))) if steps and sum(len(s) for s in steps) else 1.0
    return rho, step


def fit_conic_correlation(frames: list[tuple[np.ndarray, np.ndarray]], noise: ResidualNoise) -> float:
    """The backbone residuals' correlation length (px) for :mod:`factors.conic_correlation`'s model, matched to
    the residuals' integrated autocorrelation; 0 (independent pixels) when no frame has two pixels.

    What a correlated noise takes from the pose is its power at low spatial frequency: the spectral density at
    zero, ``sum_k rho(k)`` over all lags. The model's AR(1) coefficient per step ``a`` has
    ``sum_k rho(k) = (1 + a) / (1 - a)``; equating it to the measured sum ``tau = 1 + 2 sum_{k >= 1} rho(k)``
    (:func:`conic_autocorrelation`, lags up to the first one with ``rho <= 0``) gives ``a = (tau - 1) / (tau + 1)``
    and ``ell = -step / log a`` with the median step between pixels. A maximum-likelihood fit of the model instead
    is ruled by the residuals' small-scale roughness, which a smooth mask boundary does not have: on the
    simulator's runs (squared-exponential boundary noise, 20 px) it gave ~80 px where the integrated
    correlation is 21-44 px.
    """
    frames = [(p, r) for p, r in frames if len(r) >= 2 and np.isfinite(r).all()]
    if not frames:
        return 0.0
    rho, step = conic_autocorrelation(frames, noise)
    cut = int(np.argmax(rho[1:] <= 0.0)) + 1 if (rho[1:] <= 0.0).any() else rho.shape[0]
    tau = 1.0 + 2.0 * float(rho[1:cut].sum())
    a = (tau - 1.0) / (tau + 1.0)
    if a <= 0.0:
        return 0.0
    return float(-step / np.log(a))


def calibrate_runs(runs: list[Path], fit_correlation: bool = False, conic_distance: str = "sampson",
                   notes: list[str] | None = None) -> NoiseConfig:
    """Calibrated noise of every residual type from the ground truth of ``runs`` (module docstring); with
    ``fit_correlation`` also the backbone residuals' correlation length along the arc; ``conic_distance``: the
    backbone residual's (:func:`residuals_at_truth`). ``notes`` receives one line per run with ground-truth
    frames left out by the ground-truth tests (the count and the first rows), and one per run with masks ignored.

    Raises :class:`InputError` naming the run when a run cannot be read or has no ground truth, or is given twice.
    """
    runs = [Path(r) for r in path_list("runs", runs)]
    if not runs:
        raise InputError("calibration needs at least one recorded run")
    refuse_repeated(runs, "run")  # was counted twice: other statistics, a type's default replaced (count)
    pooled: dict[str, list[np.ndarray]] = {k: [] for k in RESIDUAL_DIMS}
    conic_frames: list[tuple[np.ndarray, np.ndarray]] = []
    for run in runs:
        recording = read_recording(run)
        skipped: list[tuple[FrameRecord, GtMismatch]] = []
        ignored: list[tuple[int, str]] = []
        samples = residuals_at_truth(recording, conic_frames if fit_correlation else None, conic_distance, skipped,
                                     ignored)
        if skipped and notes is not None:
            notes.append(left_out_note(recording, skipped))
        if ignored and notes is not None:
            notes.append(ignored_masks_note(run, ignored, fate="calibrated"))
        for k, v in samples.items():
            pooled[k].append(v)
    noise = noise_from_residuals({k: np.concatenate(v, axis=0) for k, v in pooled.items()})
    if noise["conic"].count > 0:  # the sigma describes this distance's residuals only (noise.py)
        noise = noise.with_conic_distance(conic_distance)
    if fit_correlation and noise["conic"].count > 0:
        noise = noise.with_conic_correlation(fit_conic_correlation(conic_frames, noise["conic"]))
    return noise


def _fmt(values: np.ndarray, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def format_table(noise: NoiseConfig) -> str:
    """The calibrated noise as a table shaped like the paper's Table I (std, bias, sample count).

    Rows: Anchor (x, y, z) mm, Perpendicular, Conic px, Keypoints (tip u, v; tail u, v) px, and
    the motion residual per frame: rotation (x, y, z) degrees and translation (x, y, z) mm
    (needle axes). ``default`` in the count column marks a type that kept its default.
    """
    r = noise.residuals

    def count(*names: str) -> str:
        cs = [r[n].count for n in names]
        if all(c == 0 for c in cs):
            return "default"
        return " / ".join(str(c) if c else "default" for c in cs)

    tip, tail = r["tip"], r["tail"]
    gp, perp, conic, mo = r["grasp_position"], r["grasp_perpendicular"], r["conic"], r["motion"]
    rows = [
        (
            "Anchor (x, y, z)",
            f"({_fmt(gp.sigma * 1e3, 2)}) mm",
            f"({_fmt(gp.mean * 1e3, 2)}) mm",
            count("grasp_position"),
        ),
        ("Perpendicular", f"{perp.sigma[0]:.3f}", f"{perp.mean[0]:.3f}", count("grasp_perpendicular")),
        ("Conic", f"{conic.sigma[0]:.3f} px", f"{conic.mean[0]:.3f} px", count("conic")),
        *([("Conic correlation length", f"{noise.conic_correlation_px:.1f} px", "-", count("conic"))]
          if noise.conic_correlation_px > 0 else []),
        (
            "Keypoints (tip u, v; tail u, v)",
            f"({_fmt(tip.sigma)}; {_fmt(tail.sigma)}) px",
            f"({_fmt(tip.mean)}; {_fmt(tail.mean)}) px",
            count("tip", "tail"),
        ),
        (
            "Motion rotation (x, y, z) per frame",
            f"({_fmt(np.degrees(mo.sigma[:3]))}) deg",
            f"({_fmt(np.degrees(mo.mean[:3]))}) deg",
            count("motion"),
        ),
        (
            "Motion translation (x, y, z) per frame",
            f"({_fmt(mo.sigma[3:] * 1e3)}) mm",
            f"({_fmt(mo.mean[3:] * 1e3)}) mm",
            count("motion"),
        ),
    ]
    header = ("Likelihood type", "Std. dev.", "Mean (bias)", "Count")
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(header)]

    def line(cells: tuple[str, ...]) -> str:
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    rule = "-" * len(line(header))
    return "\n".join([line(header), rule, *(line(row) for row in rows)])
