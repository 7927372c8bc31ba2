"""Camera and needle models."""

from __future__ import annotations

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera, pose_from_xyz_quat, xyz_quat_from_pose

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080, distortion=(-0.08, 0.02, 0.001, -0.0005, 0.0))


def test_undistort_inverts_distort_to_subpixel_precision() -> None:
    rng = np.random.default_rng(0)
    ideal = rng.uniform(20, 1060, size=(500, 2))
    back = CAM.undistort_px(CAM.distort_px(ideal))
    assert np.abs(back - ideal).max() < 1e-6


def test_distortion_moves_points_and_none_is_identity() -> None:
    pts = np.array([[100.0, 120.0], [1000.0, 900.0]])
    assert np.abs(CAM.distort_px(pts) - pts).max() > 1.0
    plain = PinholeCamera(900.0, 900.0, 539.5, 539.5)
    np.testing.assert_array_equal(plain.undistort_px(pts), pts)


def test_undistort_rejects_bad_points() -> None:
    with pytest.raises(ValueError, match="points_px"):
        CAM.undistort_px(np.array([[np.nan, 1.0]]))
    with pytest.raises(ValueError, match="points_px"):
        CAM.undistort_px(np.zeros((3, 3)))


def test_needle_points_and_tangents() -> None:
    nd = NeedleModel()
    np.testing.assert_allclose(nd.tail_m, [0.0045, 0, 0])
    np.testing.assert_allclose(nd.tip_m, 0.0045 * np.array([np.cos(3 * np.pi / 4), np.sin(3 * np.pi / 4), 0]))
    th = np.linspace(0, 2 * np.pi, 7)
    np.testing.assert_allclose(np.sum(nd.point(th) * nd.tangent(th), axis=1), 0, atol=1e-18)
    np.testing.assert_allclose(np.linalg.norm(nd.tangent(th), axis=1), 1)
    with pytest.raises(ValueError, match="tip_angle_rad"):
        NeedleModel(tip_angle_rad=0.0)


def test_pose_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    xyz = rng.normal(size=(50, 3))
    T = pose_from_xyz_quat(xyz, q)
    xyz2, q2 = xyz_quat_from_pose(T)
    np.testing.assert_allclose(xyz2, xyz)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q2 * qn, axis=1)), 1.0, atol=1e-12)
