"""The paper's evaluation metrics (§V, "Evaluation Metrics"), as pure vectorised functions.

Poses are homogeneous ``cam_T_needle`` matrices; a batch of frames is ``(F, 4, 4)`` and a
batch of particle sets is ``(F, N, 4, 4)`` (frame axis first, particle axis next). Tangent
vectors follow GTSAM: ``xi = [omega; v]`` with ``T_i = T_ref · Exp(xi)``.

Units. The functions that take raw errors (:func:`nll_score`, :func:`interval_score`) are
unit-agnostic: ``err``, ``sigma``, ``low`` and ``upp`` must share one unit. :func:`summarize_errors`
reports translation in millimetres and rotation in degrees and evaluates NLL-S and the
interval score in those units, as the paper's Tables II and III do (the NLL-S value depends
on the unit through ``log sigma``; these units make our numbers comparable with the paper's).

Uncertainty -> Gaussian sigma (one convention, used everywhere here). The paper scores an
error magnitude ``err`` under ``err ~ N(0, sigma^2)`` with sigma "from the predicted
uncertainty", which is reported as the 95th percentile ``q95`` of the particles' error
magnitudes. We read ``q95`` as the 95 % point of ``|err|`` under that same one-dimensional
model, i.e. the half-width of a central 95 % interval of ``N(0, sigma^2)``:
``sigma = q95 / z_0.975 = q95 / 1.95996``. (The chi-distribution alternative, 2.796 for a
3-vector's norm, would model each axis separately; NLL-S as the paper writes it is
one-dimensional, so the one-dimensional quantile is the consistent choice.) The matching
prediction interval of a magnitude for the interval score is ``[0, q95]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.lie import so3_log
from pinpoint_fg.errors import InputError
from pinpoint_fg.posterior.spread import pose_array

Z_975 = 1.959963984540054
"""Standard-normal 97.5 % point: ``q95 = Z_975 · sigma`` for ``|err|`` with ``err ~ N(0, sigma^2)``."""

SIGMA_FLOOR = 1e-2
"""Smallest sigma used by :func:`nll_score`, in the unit of ``err`` — the reports use mm and degrees,
so 0.01 mm / 0.01 deg, far below anything this sensing resolves. A tracker claiming zero spread
(a collapsed particle filter, one hypothesis left after pruning) is then scored as claiming
0.01: still punished hard when wrong (err 1 mm -> NLL-S 5000), but a mean over frames stays
readable instead of being swamped by 1e17 from a few such frames."""

_AXES = ("x", "y", "z")


# ----------------------------------------------------------------------------- validation


def _finite_rows(T: np.ndarray) -> np.ndarray:
    """Mask ``(...)`` of poses whose 16 entries are all finite."""
    return np.all(np.isfinite(T), axis=(-2, -1))


#: Largest accepted ``max |R^T R - I|`` of a finite pose given to :func:`pose_errors`.
ROTATION_TOL = 1e-6


def _check_rigid(name: str, T: np.ndarray) -> None:
    """InputError naming ``name`` when a finite pose's rotation block is not a rotation: a scaled or zero block gave
    a rotation error of 0 (the quaternion of a scaled identity is the identity's), silently."""
    finite = _finite_rows(T)
    R = T[..., :3, :3][finite]
    if R.size and float(np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)))) > ROTATION_TOL:
        raise InputError(f"{name} holds a pose whose rotation block is not a rotation (max |R^T R - I| > "
                         f"{ROTATION_TOL:g})", column=name)


# ----------------------------------------------------------------------------- pose errors


@dataclass(frozen=True)
class PoseErrors:
    """Per-frame errors of estimated poses against ground truth; NaN where a pose is not finite."""

    trans_m: np.ndarray
    """(F,) ``||t - t_gt||`` in metres (error of the needle origin, the circle centre)."""
    rot_rad: np.ndarray
    """(F,) geodesic angle ``arccos((tr(R_gt^T R) - 1) / 2)`` in radians, in [0, pi]."""
    trans_axes_m: np.ndarray
    """(F, 3) ``|t - t_gt|`` per camera axis (x right, y down, z forward), metres."""
    rot_axes_rad: np.ndarray
    """(F, 3) ``|Log(R R_gt^T)|`` per camera axis, radians; its row norm equals ``rot_rad``."""


def pose_errors(T_est: np.ndarray, T_gt: np.ndarray) -> PoseErrors:
    """Translation and rotation errors of ``T_est`` (F, 4, 4) against ``T_gt`` (F, 4, 4).

    * ``trans_m = ||t - t_gt||`` and ``trans_axes_m = |t - t_gt|`` (camera axes).
    * ``rot_rad`` is the paper's ``arccos((tr(R_gt^T R) - 1) / 2)``, evaluated as the norm of
      ``Log(R_gt^T R)`` through the quaternion (``2 atan2(|q_v|, q_w)``). That is the same angle,
      but accurate everywhere: the arccos form loses all digits below ~1e-8 rad (its argument
      rounds to 1) and is ill-conditioned near pi.
    * ``rot_axes_rad = |Log(R R_gt^T)|``: the error rotation ``R = Exp(delta) R_gt`` written as a
      rotation vector ``delta`` in the CAMERA frame, component-wise absolute (the X/Y/Z rotation
      columns of the paper's Table II). ``R R_gt^T = R_gt (R_gt^T R) R_gt^T`` is conjugate to
      ``R_gt^T R``, so ``||delta|| = rot_rad`` exactly, for every angle.

    Either input may also be a single (4, 4) pose (broadcast). Frames where either pose has a
    non-finite entry (e.g. no ground truth) get NaN errors instead of an exception.
    """
    T_est = pose_array("T_est", T_est)
    T_gt = pose_array("T_gt", T_gt)
    try:
        shape = np.broadcast_shapes(T_est.shape, T_gt.shape)
    except ValueError:
        raise InputError(f"T_est {T_est.shape} and T_gt {T_gt.shape} hold different frame counts") from None
    T_est = np.broadcast_to(T_est, shape)
    T_gt = np.broadcast_to(T_gt, shape)
    for name, T in (("T_est", T_est), ("T_gt", T_gt)):
        _check_rigid(name, T)
    ok = _finite_rows(T_est) & _finite_rows(T_gt)
    eye = np.eye(4)
    T_est = np.where(ok[..., None, None], T_est, eye)
    T_gt = np.where(ok[..., None, None], T_gt, eye)

    dt = T_est[..., :3, 3] - T_gt[..., :3, 3]
    R, R_gt = T_est[..., :3, :3], T_gt[..., :3, :3]
    w_body = so3_log(np.swapaxes(R_gt, -1, -2) @ R)
    w_cam = so3_log(R @ np.swapaxes(R_gt, -1, -2))

    nan = np.where(ok, 0.0, np.nan)
    return PoseErrors(
        trans_m=np.linalg.norm(dt, axis=-1) + nan,
        rot_rad=np.linalg.norm(w_body, axis=-1) + nan,
        trans_axes_m=np.abs(dt) + nan[..., None],
        rot_axes_rad=np.abs(w_cam) + nan[..., None],
    )


# ----------------------------------------------------------------------------- scoring rules


def sigma_from_q95(q95: np.ndarray) -> np.ndarray:
    """Gaussian sigma of an error magnitude from its predicted 95th percentile: ``q95 / Z_975``.

    See the module docstring for why the one-dimensional 97.5 % point (1.95996) is used.
    """
    return np.asarray(q95, dtype=float) / Z_975


def nll_score(err: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """NLL-S: ``0.5 log(2 pi sigma^2) + err^2 / (2 sigma^2)``, element-wise (broadcast).

    ``sigma`` is floored at :data:`SIGMA_FLOOR` (0.01 in the unit of ``err``: mm or deg in reports), so a particle set
    with zero spread scores finitely (and very badly unless ``err`` is ~0 as well).
    """
    err = np.asarray(err, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    if np.any(sigma < 0):  # was floored to SIGMA_FLOOR like a zero spread: a silently "very confident" score
        raise InputError("nll_score: sigma must not be negative", column="sigma")
    sigma = np.maximum(sigma, SIGMA_FLOOR)
    return 0.5 * np.log(2.0 * np.pi * sigma**2) + err**2 / (2.0 * sigma**2)


def interval_score(err: np.ndarray, low: np.ndarray, upp: np.ndarray, alpha: float = 0.05) -> np.ndarray:
    """Interval score (Gneiting & Raftery) of the central ``1 - alpha`` interval ``[low, upp]``.

    ``IS = (upp - low) + 2/alpha · max(0, low - err) + 2/alpha · max(0, err - upp)``, element-wise.
    For an error magnitude with predicted 95th percentile ``q95`` the interval is ``[0, q95]``.
    """
    if not (isinstance(alpha, (int, float, np.number)) and 0.0 < alpha < 1.0):  # a str was a TypeError of '<'
        raise InputError(f"alpha must lie in (0, 1), got {alpha!r}", column="alpha")
    err = np.asarray(err, dtype=float)
    low = np.asarray(low, dtype=float)
    upp = np.asarray(upp, dtype=float)
    if np.any(low > upp):
        raise InputError("interval_score: low exceeds upp", column="low")
    return (
        (upp - low) + (2.0 / alpha) * np.maximum(0.0, low - err) + (2.0 / alpha) * np.maximum(0.0, err - upp)
    )


def scores_from_q95(err: np.ndarray, q95: np.ndarray, alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """``(NLL-S, IS)`` of error magnitudes ``err`` given predicted ``q95`` (same unit, broadcast).

    ``sigma = q95 / Z_975`` for NLL-S; interval ``[0, q95]`` for the interval score.
    """
    q95 = np.asarray(q95, dtype=float)
    return nll_score(err, sigma_from_q95(q95)), interval_score(err, np.zeros_like(q95), q95, alpha)


# ----------------------------------------------------------------------------- summaries


def _mean_std(x: np.ndarray) -> tuple[float, float]:
    """Mean and population standard deviation (ddof = 0); NaN for an empty array."""
    if x.size == 0:
        return float("nan"), float("nan")
    return float(np.mean(x)), float(np.std(x))


def summarize_errors(
    errors: PoseErrors,
    q95_trans_m: np.ndarray | None = None,
    q95_rot_rad: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    alpha: float = 0.05,
) -> dict[str, float]:
    """One row of the paper's Table II / III from per-frame errors and predicted q95 spreads.

    Frames used: ``mask`` (F,) bool (e.g. "has ground truth"; default all) AND finite errors.
    Accuracy keys (translation in mm, rotation in degrees; std is the population std, ddof=0):
    ``frames``, ``trans_mean_mm``, ``trans_std_mm``, ``rot_mean_deg``, ``rot_std_deg`` and per axis
    ``trans_{x,y,z}_{mean,std}_mm``, ``rot_{x,y,z}_{mean,std}_deg`` (camera axes, see
    :class:`PoseErrors`). Uncertainty keys, averaged over the used frames whose q95 is finite
    (``uncertainty_frames_trans`` / ``_rot`` count them; NaN when none or when q95 is ``None``):
    ``trans_q95_mm``, ``rot_q95_deg`` (mean predicted q95), ``nlls_trans``, ``nlls_rot`` (mean NLL-S
    with ``sigma = q95 / 1.96``, in mm / deg), ``is_trans``, ``is_rot`` (mean interval score of
    ``[0, q95]`` at ``alpha``, in mm / deg), ``coverage_trans``, ``coverage_rot`` (share of those frames
    whose error is within the predicted q95: 0.95 for a calibrated q95).
    """
    F = np.shape(errors.trans_m)[0] if np.ndim(errors.trans_m) else 1
    trans = np.reshape(np.asarray(errors.trans_m, dtype=float), (F,))
    rot = np.reshape(np.asarray(errors.rot_rad, dtype=float), (F,))
    t_ax = np.reshape(np.asarray(errors.trans_axes_m, dtype=float), (F, 3))
    r_ax = np.reshape(np.asarray(errors.rot_axes_rad, dtype=float), (F, 3))
    use = np.isfinite(trans) & np.isfinite(rot)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (F,):
            raise InputError(f"mask has shape {m.shape}, expected ({F},)", column="mask")
        if m.dtype != bool:  # strings (or any non-empty value) read as True: every frame kept, silently
            raise InputError(f"mask must be boolean, got dtype {m.dtype}", column="mask")
        use &= m.astype(bool)

    out: dict[str, float] = {"frames": int(use.sum())}
    out["trans_mean_mm"], out["trans_std_mm"] = _mean_std(1e3 * trans[use])
    out["rot_mean_deg"], out["rot_std_deg"] = _mean_std(np.degrees(rot[use]))
    for j, ax in enumerate(_AXES):
        out[f"trans_{ax}_mean_mm"], out[f"trans_{ax}_std_mm"] = _mean_std(1e3 * t_ax[use, j])
    for j, ax in enumerate(_AXES):
        out[f"rot_{ax}_mean_deg"], out[f"rot_{ax}_std_deg"] = _mean_std(np.degrees(r_ax[use, j]))

    for key, err, q95, scale, unit in (
        ("trans", trans, q95_trans_m, 1e3, "mm"),
        ("rot", rot, q95_rot_rad, np.degrees(1.0), "deg"),
    ):
        if q95 is None:
            sel = np.zeros(F, dtype=bool)
            q = np.full(F, np.nan)
        else:
            q = np.asarray(q95, dtype=float)
            if q.shape != (F,):
                raise InputError(f"q95_{key} has shape {q.shape}, expected ({F},)", column=f"q95_{key}")
            if np.any(q[np.isfinite(q)] < 0):
                raise InputError(f"q95_{key} must be non-negative", column=f"q95_{key}")
            sel = use & np.isfinite(q)
        out[f"uncertainty_frames_{key}"] = int(sel.sum())
        if sel.any():
            e, qq = scale * err[sel], scale * q[sel]
            nll, isc = scores_from_q95(e, qq, alpha)
            out[f"{key}_q95_{unit}"] = float(np.mean(qq))
            out[f"nlls_{key}"] = float(np.mean(nll))
            out[f"is_{key}"] = float(np.mean(isc))
            out[f"coverage_{key}"] = float(np.mean(e <= qq))
        else:
            out[f"{key}_q95_{unit}"] = float("nan")
            out[f"nlls_{key}"] = float("nan")
            out[f"is_{key}"] = float("nan")
            out[f"coverage_{key}"] = float("nan")
    return out


def breakdown_by_label(
    values: np.ndarray, labels: np.ndarray | list[str | None], mask: np.ndarray | None = None
) -> dict[str, float]:
    """Mean of ``values`` (F,) per label (F,) (e.g. occlusion ``none`` / ``partial`` / ``heavy``).

    Frames whose label is ``None`` or ``""`` (unknown), whose value is not finite, or that ``mask``
    (F,) excludes are skipped. Keys are the labels present, sorted; labels with no usable frame
    are absent.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    if isinstance(labels, str) or labels is None:  # a string was split into one label per character
        raise InputError(f"labels must be a list of labels, got {type(labels).__name__}", column="labels")
    lab = list(labels)
    if len(lab) != v.shape[0]:
        raise InputError(f"{len(lab)} labels for {v.shape[0]} values", column="labels")
    use = np.isfinite(v)
    if mask is not None:
        m = np.asarray(mask).reshape(-1)
        if m.shape != v.shape:
            raise InputError(f"mask has shape {m.shape}, expected {v.shape}", column="mask")
        use &= m.astype(bool)
    known = np.array([x is not None and str(x) != "" for x in lab], dtype=bool)
    use &= known
    names = np.array([str(x) if k else "" for x, k in zip(lab, known, strict=True)], dtype=object)
    out: dict[str, float] = {}
    for name in sorted(set(names[use].tolist())):
        out[name] = float(np.mean(v[use & (names == name)]))
    return out


def accuracy_multiple(method_mean: np.ndarray | float, floor_mean: np.ndarray | float) -> np.ndarray | float:
    """How many times the accuracy floor a method's mean error is: ``method_mean / floor_mean``.

    The floor is the mean error of the per-frame MAP solved from the truth (DESIGN.md
    §Evaluation): 1.0 means the method is as accurate as the model allows, larger is worse.
    Element-wise; a zero floor gives ``inf`` (or NaN for 0/0) rather than an exception.
    """
    m = np.asarray(method_mean, dtype=float)
    f = np.asarray(floor_mean, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = m / f
    return float(r) if r.ndim == 0 else r
