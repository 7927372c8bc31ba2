"""Hand-checked cases for pinpoint_fg.eval.metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.lie import so3_exp, so3_log
from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.metrics import (
    SIGMA_FLOOR,
    Z_975,
    PoseErrors,
    accuracy_multiple,
    breakdown_by_label,
    interval_score,
    nll_score,
    pose_errors,
    scores_from_q95,
    sigma_from_q95,
    summarize_errors,
)


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rx(a: float) -> np.ndarray:
    return so3_exp(np.array([a, 0.0, 0.0]))


def _rz(a: float) -> np.ndarray:
    return so3_exp(np.array([0.0, 0.0, a]))


# ----------------------------------------------------------------------------- pose errors


def test_pose_errors_hand_cases() -> None:
    T_gt = np.stack([_pose(np.eye(3), [1.0, 1.0, 1.0]), _pose(np.eye(3), [0.0, 0.0, 0.0])])
    T_est = np.stack([_pose(np.eye(3), [4.0, 5.0, 1.0]), _pose(_rz(np.pi / 2), [0.0, 0.0, 0.0])])
    e = pose_errors(T_est, T_gt)
    assert isinstance(e, PoseErrors)
    np.testing.assert_allclose(e.trans_m, [5.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(e.trans_axes_m, [[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], atol=1e-15)
    np.testing.assert_allclose(e.rot_rad, [0.0, np.pi / 2], atol=1e-14)
    np.testing.assert_allclose(e.rot_axes_rad, [[0, 0, 0], [0, 0, np.pi / 2]], atol=1e-14)


def test_rotation_axes_are_camera_axes() -> None:
    # truth rotated 90 deg about x; estimate = extra 30 deg about the CAMERA z axis (left perturbation).
    R_gt = _rx(np.pi / 2)
    R = _rz(np.pi / 6) @ R_gt
    e = pose_errors(_pose(R, [0, 0, 0.1])[None], _pose(R_gt, [0, 0, 0.1])[None])
    np.testing.assert_allclose(e.rot_axes_rad[0], [0.0, 0.0, np.pi / 6], atol=1e-14)
    np.testing.assert_allclose(e.rot_rad[0], np.pi / 6, atol=1e-14)
    # in the needle (body) frame the same error is about +y: the camera-frame convention matters
    np.testing.assert_allclose(so3_log(R_gt.T @ R), [0.0, np.pi / 6, 0.0], atol=1e-14)


def test_rotation_angle_matches_arccos_and_is_accurate_when_small_or_near_pi() -> None:
    rng = np.random.default_rng(3)
    w = rng.normal(size=(50, 3))
    w *= (rng.uniform(0.1, 3.0, size=50) / np.linalg.norm(w, axis=1))[:, None]
    R_gt = so3_exp(rng.normal(size=(50, 3)))
    R = R_gt @ so3_exp(w)
    T_est, T_gt = np.tile(np.eye(4), (50, 1, 1)), np.tile(np.eye(4), (50, 1, 1))
    T_est[:, :3, :3], T_gt[:, :3, :3] = R, R_gt
    e = pose_errors(T_est, T_gt)
    tr = np.trace(np.swapaxes(R_gt, 1, 2) @ R, axis1=1, axis2=2)
    np.testing.assert_allclose(e.rot_rad, np.arccos(np.clip((tr - 1) / 2, -1, 1)), atol=1e-9)
    np.testing.assert_allclose(e.rot_rad, np.linalg.norm(w, axis=1), atol=1e-12)
    # per-axis norm equals the angle for every size (conjugate rotations)
    np.testing.assert_allclose(np.linalg.norm(e.rot_axes_rad, axis=1), e.rot_rad, atol=1e-12)
    # tiny angle: arccos would return 0
    tiny = pose_errors(_pose(_rz(1e-9), [0, 0, 0]), np.eye(4))
    assert tiny.rot_rad == pytest.approx(1e-9, rel=1e-6)
    # exactly pi
    flip = pose_errors(_pose(_rx(np.pi), [0, 0, 0]), np.eye(4))
    assert flip.rot_rad == pytest.approx(np.pi, abs=1e-12)


def test_frames_without_truth_give_nan() -> None:
    T_gt = np.stack([np.eye(4), np.full((4, 4), np.nan)])
    T_est = np.stack([_pose(np.eye(3), [0, 0, 0.002]), np.eye(4)])
    e = pose_errors(T_est, T_gt)
    assert e.trans_m[0] == pytest.approx(0.002)
    assert np.isnan(e.trans_m[1]) and np.isnan(e.rot_rad[1])
    assert np.all(np.isnan(e.trans_axes_m[1])) and np.all(np.isnan(e.rot_axes_rad[1]))


def test_pose_errors_bad_shapes() -> None:
    with pytest.raises(InputError):
        pose_errors(np.eye(3), np.eye(4))
    with pytest.raises(InputError):
        pose_errors(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (2, 1, 1)))


# ----------------------------------------------------------------------------- scoring rules


def test_nll_score_hand_values() -> None:
    # 0.5 log(2 pi) + 1/2
    assert nll_score(1.0, 1.0) == pytest.approx(1.4189385332046727, abs=1e-15)
    # 0.5 log(8 pi), err = 0
    assert nll_score(0.0, 2.0) == pytest.approx(1.6120857137646180, abs=1e-15)
    # 0.5 log(2 pi 4) + 9 / 8
    np.testing.assert_allclose(nll_score(np.array([1.0, 3.0]), 2.0), [1.7370857137646180, 2.7370857137646180])
    # zero spread: floored, finite
    assert SIGMA_FLOOR == 1e-2
    # 0.5 log(2 pi 1e-4) = 0.5 (log 2 pi - 9.210340371976184)
    assert nll_score(0.0, 0.0) == pytest.approx(0.5 * (math.log(2 * math.pi) - 9.210340371976184), abs=1e-12)
    assert nll_score(1.0, 0.0) == pytest.approx(0.5 * (math.log(2 * math.pi) - 9.210340371976184) + 5000.0)


def test_interval_score_hand_values() -> None:
    np.testing.assert_allclose(
        interval_score(np.array([0.5, 1.5, -1.0, 1.0]), 0.0, 1.0, alpha=0.05), [1.0, 21.0, 41.0, 1.0]
    )
    assert interval_score(3.0, 1.0, 2.0, alpha=0.1) == pytest.approx(1.0 + 20.0)
    with pytest.raises(InputError):
        interval_score(1.0, 2.0, 1.0)
    with pytest.raises(InputError):
        interval_score(1.0, 0.0, 1.0, alpha=0.0)


def test_sigma_from_q95_and_scores() -> None:
    assert Z_975 == pytest.approx(1.959963984540054, abs=1e-15)
    assert sigma_from_q95(Z_975 * 2.0) == pytest.approx(2.0)
    nll, isc = scores_from_q95(np.array([1.0, 5.0]), Z_975 * 2.0)  # q95 = 3.92: inside, outside
    np.testing.assert_allclose(nll, nll_score(np.array([1.0, 5.0]), 2.0))
    np.testing.assert_allclose(isc, [Z_975 * 2.0, Z_975 * 2.0 + 40.0 * (5.0 - Z_975 * 2.0)])


# ----------------------------------------------------------------------------- summaries


def _errors(trans_m, rot_rad, trans_axes_m, rot_axes_rad) -> PoseErrors:
    return PoseErrors(*(np.asarray(x, dtype=float) for x in (trans_m, rot_rad, trans_axes_m, rot_axes_rad)))


def test_summarize_errors_hand_case() -> None:
    d = np.deg2rad
    e = _errors(
        [0.001, 0.003, np.nan, 0.010],
        [d(10.0), d(20.0), np.nan, d(50.0)],
        [[0.001, 0, 0], [0, 0.003, 0], [np.nan] * 3, [0.01, 0, 0]],
        [[d(10.0), 0, 0], [0, 0, d(20.0)], [np.nan] * 3, [0, 0, d(50.0)]],
    )
    q95_t = np.array([0.002, 0.002, 0.002, 0.002])
    q95_r = np.array([d(15.0), np.nan, d(15.0), d(15.0)])
    mask = np.array([True, True, True, False])  # frame 3 excluded, frame 2 has no truth
    s = summarize_errors(e, q95_t, q95_r, mask=mask)
    assert s["frames"] == 2
    assert s["trans_mean_mm"] == pytest.approx(2.0)
    assert s["trans_std_mm"] == pytest.approx(1.0)  # population std of {1, 3}
    assert s["rot_mean_deg"] == pytest.approx(15.0)
    assert s["rot_std_deg"] == pytest.approx(5.0)
    assert s["trans_x_mean_mm"] == pytest.approx(0.5) and s["trans_x_std_mm"] == pytest.approx(0.5)
    assert s["trans_y_mean_mm"] == pytest.approx(1.5) and s["trans_z_mean_mm"] == 0.0
    assert s["rot_x_mean_deg"] == pytest.approx(5.0) and s["rot_z_mean_deg"] == pytest.approx(10.0)
    assert s["rot_y_std_deg"] == 0.0
    # uncertainty: translation q95 = 2 mm on both frames; IS = width 2 + 40 * miss {0, 1} -> (2 + 42) / 2
    assert s["trans_q95_mm"] == pytest.approx(2.0)
    assert s["is_trans"] == pytest.approx(22.0)
    sig = 2.0 / Z_975
    nll = [0.5 * math.log(2 * math.pi * sig**2) + x**2 / (2 * sig**2) for x in (1.0, 3.0)]
    assert s["nlls_trans"] == pytest.approx(np.mean(nll))
    assert s["coverage_trans"] == pytest.approx(0.5)  # 1 mm within 2, 3 mm not
    # rotation q95 is missing on frame 1: only frame 0 (10 deg inside [0, 15]) -> IS = 15
    assert s["uncertainty_frames_rot"] == 1
    assert s["rot_q95_deg"] == pytest.approx(15.0)
    assert s["is_rot"] == pytest.approx(15.0)
    assert s["coverage_rot"] == 1.0
    # without q95 the uncertainty keys are NaN, accuracy keys unchanged
    s0 = summarize_errors(e, mask=mask)
    assert math.isnan(s0["nlls_rot"]) and math.isnan(s0["is_trans"]) and math.isnan(s0["coverage_rot"])
    assert s0["trans_mean_mm"] == pytest.approx(2.0)
    for key in ("trans_z_std_mm", "rot_x_std_deg", "rot_q95_deg", "nlls_trans"):
        assert key in s0
    with pytest.raises(InputError):
        summarize_errors(e, q95_t[:2])


def test_breakdown_and_accuracy_multiple() -> None:
    v = np.array([1.0, 2.0, 3.0, 4.0, 10.0, np.nan])
    labels = ["none", "heavy", None, "heavy", "none", "partial"]
    assert breakdown_by_label(v, labels) == {"heavy": 3.0, "none": 5.5}
    mask = np.array([1, 1, 1, 0, 1, 1], dtype=bool)
    assert breakdown_by_label(v, labels, mask=mask) == {"heavy": 2.0, "none": 5.5}
    with pytest.raises(InputError):
        breakdown_by_label(v, labels[:3])
    assert accuracy_multiple(3.0, 1.5) == pytest.approx(2.0)
    np.testing.assert_allclose(accuracy_multiple(np.array([1.0, 4.0]), np.array([2.0, 1.0])), [0.5, 4.0])
    assert accuracy_multiple(1.0, 0.0) == math.inf
