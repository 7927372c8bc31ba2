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


@pytest.mark.parametrize(("fields", "problem"), [
    ({"tip_angle_rad": 7.0}, "full circle"),                                 # the wire overlaps itself
    ({"tail_angle_rad": -3.2, "tip_angle_rad": 3.1}, "full circle"),
    ({"grasp_angle_rad": 3.0}, "not on the arc"),                             # past the tip
    ({"grasp_angle_rad": -0.5}, "not on the arc"),                            # behind the tail
    ({"tail_angle_rad": 0.0, "tip_angle_rad": -2.0, "grasp_angle_rad": 1.0}, "not on the arc"),
    ({"wire_diameter_m": 0.009}, "twice radius_m"),
    ({"radius_m": 4.5e-6, "wire_diameter_m": 4e-7}, "radius_m 4.5e-06 is below"),  # um typed as m
    ({"wire_diameter_m": 4e-10}, "wire_diameter_m 4e-10 is below"),
])
def test_impossible_needles_are_refused(fields: dict, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        NeedleModel(**fields)


@pytest.mark.parametrize("fields", [
    {"grasp_angle_rad": 0.0}, {"grasp_angle_rad": 3 * np.pi / 4},             # the arc's ends
    {"grasp_angle_rad": np.pi / 4 + 2 * np.pi}, {"grasp_angle_rad": -1e-12},  # mod 2 pi; round-off at the tail
    {"tail_angle_rad": 0.0, "tip_angle_rad": -2.0, "grasp_angle_rad": -1.0},  # an arc the other way round
    {"tail_angle_rad": 5.5, "tip_angle_rad": 7.0, "grasp_angle_rad": 0.1},    # crossing 2 pi
])
def test_possible_needles_are_accepted(fields: dict) -> None:
    NeedleModel(**fields)


def test_pose_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    xyz = rng.normal(size=(50, 3))
    T = pose_from_xyz_quat(xyz, q)
    xyz2, q2 = xyz_quat_from_pose(T)
    np.testing.assert_allclose(xyz2, xyz)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q2 * qn, axis=1)), 1.0, atol=1e-12)
