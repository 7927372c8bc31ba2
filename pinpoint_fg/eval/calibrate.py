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
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from factors import residuals as res
from pinpoint_fg.errors import InputError, path_list, refuse_repeated
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import FrameRecord, Recording
from pinpoint_fg.noise import RESIDUAL_DIMS, NoiseConfig, ResidualNoise
from pinpoint_fg.observe import observe_frame

#: Relative eigenvalue floor applied to a singular sample covariance.
COV_REL_FLOOR = 1e-12
#: Absolute eigenvalue floor (units of the residual squared).
COV_ABS_FLOOR = 1e-30


def _in_front(recording: Recording, rec: FrameRecord, T: np.ndarray, points: list) -> None:
    """:class:`InputError` at the frame's ``gt_z_m`` when a needle point seen in its image (``(name, point in the
    needle frame, observation or None)``) lies at a depth <= :data:`factors.residuals.MIN_DEPTH_M`: the image
    residuals there are those of its mirror image (a conic cannot tell them apart), and calibrating on them
    silently inflated the noise (one such frame of eight: tip std 0.6 -> 42 px)."""
    for name, p_needle, seen in points:
        z = float(T[2, :3] @ p_needle + T[2, 3])
        if seen is not None and z <= res.MIN_DEPTH_M:
            raise InputError(f"the ground truth puts the needle's {name} at depth {z:.3g} m, not in front of the "
                             "camera that sees it; correct the gt_* cells or clear them", file=recording.csv_path,
                             row=recording.row_of(rec), column="gt_z_m")


def residuals_at_truth(recording: Recording) -> dict[str, np.ndarray]:
    """Every residual type evaluated at the ground-truth poses of one run.

    Returns ``{type: (n, d) array}`` for the types of :data:`pinpoint_fg.noise.RESIDUAL_DIMS`
    (``n`` may be 0). Frames without ground truth contribute nothing. Raises
    :class:`InputError` naming the run when no frame has ground truth, and naming the row when a frame's
    ground truth puts a needle point its image shows behind the camera.
    """
    if not recording.has_ground_truth:
        raise InputError("no frame has ground truth (gt_* columns): cannot calibrate", file=recording.root)
    cam, nd = recording.info.camera, recording.info.needle
    K = cam.K
    out: dict[str, list[np.ndarray]] = {k: [] for k in RESIDUAL_DIMS}
    prev = None  # previous FrameRecord
    for rec in recording.frames:
        T = rec.cam_T_needle_gt
        if T is None:
            prev = None
            continue
        obs = observe_frame(recording, rec)
        _in_front(recording, rec, T, [("tip", nd.tip_m, obs.tip_px), ("tail", nd.tail_m, obs.tail_px),
                                      ("centre", np.zeros(3), obs.backbone_px)])
        if obs.tip_px is not None:
            out["tip"].append(res.keypoint_residual(T, K, nd.tip_m, obs.tip_px)[0])
        if obs.tail_px is not None:
            out["tail"].append(res.keypoint_residual(T, K, nd.tail_m, obs.tail_px)[0])
        if obs.backbone_px is not None:
            out["conic"].append(res.conic_residual(T, K, nd.radius_m, obs.backbone_px)[0].reshape(-1, 1))
        G = rec.cam_T_grasper
        if G is not None:
            out["grasp_position"].append(res.grasp_position_residual(T, nd.grasp_m, G[:3, 3])[0])
            perp = res.grasp_perpendicular_residual(T, nd.grasp_tangent, G[:3, 2])[0]
            out["grasp_perpendicular"].append(perp)
            if prev is not None and prev.cam_T_grasper is not None and rec.frame - prev.frame == 1:
                D = G @ np.linalg.inv(prev.cam_T_grasper)
                out["motion"].append(res.motion_residual(prev.cam_T_needle_gt, T, D)[0])
        prev = rec
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


def calibrate_runs(runs: list[Path]) -> NoiseConfig:
    """Calibrated noise of every residual type from the ground truth of ``runs`` (module docstring).

    Raises :class:`InputError` naming the run when a run cannot be read or has no ground truth, or is given twice.
    """
    runs = [Path(r) for r in path_list("runs", runs)]
    if not runs:
        raise InputError("calibration needs at least one recorded run")
    refuse_repeated(runs, "run")  # was counted twice: other statistics, a type's default replaced (count)
    pooled: dict[str, list[np.ndarray]] = {k: [] for k in RESIDUAL_DIMS}
    for run in runs:
        samples = residuals_at_truth(read_recording(run))
        for k, v in samples.items():
            pooled[k].append(v)
    return noise_from_residuals({k: np.concatenate(v, axis=0) for k, v in pooled.items()})


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
