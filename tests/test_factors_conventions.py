"""The tangent convention as executable statements, checked against GTSAM."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.conventions import (
    left_vw_to_right_jacobian,
    matrix_to_pose3,
    oplus,
    oplus_matrix,
    pose3_to_matrix,
    right_to_left_vw_jacobian,
)
from factors.lie import (
    se3_adjoint,
    se3_exp,
    se3_log,
    se3_right_jacobian,
    se3_right_jacobian_inv,
)
from factors.residuals import point_jacobian
from tests.poses import KINDS, sample_poses


def test_retract_is_right_exponential_with_rotation_first() -> None:
    rng = np.random.default_rng(0)
    for T in sample_poses("uniform", 20, rng):
        P = matrix_to_pose3(T)
        xi = rng.normal(size=6)
        xi[:3] *= 3.0 / max(3.0, np.linalg.norm(xi[:3]))  # |omega| < pi: inside Log's principal range
        np.testing.assert_allclose(P.retract(xi).matrix(), oplus(P, xi).matrix(), atol=1e-12)
        np.testing.assert_allclose(oplus_matrix(T, xi), P.retract(xi).matrix(), atol=1e-12)
        np.testing.assert_allclose(P.localCoordinates(P.retract(xi)), xi, atol=1e-9)
    # rotation first: [0,0,0.3,0,0,0] is a yaw, [0,0,0,1,2,3] a pure translation
    np.testing.assert_allclose(pose3_to_matrix(gtsam.Pose3.Expmap(np.r_[0, 0, 0, 1, 2, 3]))[:3, 3], [1, 2, 3])


def test_batched_lie_functions_match_gtsam() -> None:
    rng = np.random.default_rng(1)
    for kind in KINDS:
        for T in sample_poses(kind, 30, rng):
            P = matrix_to_pose3(T)
            xi = gtsam.Pose3.Logmap(P)
            # at angles within ~1e-2 of pi GTSAM may return the equivalent vector of angle > pi;
            # ours stays in [0, pi]. Both must map back to T.
            np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-9)
            assert np.linalg.norm(se3_log(T)[:3]) <= np.pi + 1e-12
            if np.linalg.norm(xi[:3]) < np.pi - 0.1:
                np.testing.assert_allclose(se3_log(T), xi, atol=1e-9)
            if np.linalg.norm(xi[:3]) < np.pi - 0.1:
                np.testing.assert_allclose(se3_exp(xi), P.matrix(), atol=1e-12)
            np.testing.assert_allclose(se3_right_jacobian(xi), gtsam.Pose3.ExpmapDerivative(xi), atol=1e-9)
            np.testing.assert_allclose(se3_right_jacobian_inv(xi), gtsam.Pose3.LogmapDerivative(xi), atol=1e-6)
            np.testing.assert_allclose(se3_adjoint(T), P.AdjointMap(), atol=1e-14)


def test_left_right_jacobian_conversion() -> None:
    rng = np.random.default_rng(2)
    X = rng.normal(size=3)
    for T in sample_poses("uniform", 10, rng):
        _, J_right = point_jacobian(T, X)
        p = T[:3, :3] @ X + T[:3, 3]
        skew_p = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        J_left_vw = np.hstack([np.eye(3), -skew_p])  # paper appendix: [I, -[p]x] for Exp([v; w]) T
        np.testing.assert_allclose(left_vw_to_right_jacobian(J_left_vw, T), J_right[0], atol=1e-12)
        np.testing.assert_allclose(right_to_left_vw_jacobian(J_right[0], T), J_left_vw, atol=1e-12)
