"""Residual values against independent computations, and the factors against the batched functions."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest

from factors import residuals as res
from factors.conventions import matrix_to_pose3
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import (
    ConicFactor,
    GraspPerpendicularFactor,
    GraspPositionFactor,
    KeypointFactor,
    MotionFactor,
)
from factors.lie import se3_exp
from tests.poses import sample_poses

CAM = PinholeCamera(905.0, 912.0, 540.2, 538.9, 1080, 1080)
NEEDLE = NeedleModel()


def test_keypoint_residual_matches_cv2_project_points() -> None:
    rng = np.random.default_rng(0)
    T = sample_poses("uniform", 100, rng)
    z = rng.uniform(0, 1080, size=2)
    r, _ = res.keypoint_residual(T, CAM.K, NEEDLE.tip_m, z)
    for i in range(len(T)):
        rvec, _ = cv2.Rodrigues(T[i, :3, :3])
        px, _ = cv2.projectPoints(NEEDLE.tip_m[None], rvec, T[i, :3, 3], CAM.K, np.zeros(5))
        np.testing.assert_allclose(r[i], px.reshape(2) - z, rtol=0, atol=1e-8)


def _fitted_ellipse(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV's ellipse through the projected circle: centre, semi-axes, axis directions."""
    P = NEEDLE.point(np.linspace(0, 2 * np.pi, 400, endpoint=False))
    px = CAM.project(P @ T[:3, :3].T + T[:3, 3])
    (cx, cy), (w, h), ang = cv2.fitEllipseDirect(px.astype(np.float32))
    a = np.deg2rad(ang)
    axes = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    return np.array([cx, cy]), np.array([w / 2, h / 2]), axes


@pytest.mark.parametrize("seed", range(6))
def test_conic_residual_against_opencv_ellipse(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = sample_poses("uniform", 1, rng)[0]
    # keep views that are not close to edge-on, where an ellipse fit is well defined
    while abs(T[:3, 2] @ T[:3, 3]) / np.linalg.norm(T[:3, 3]) < 0.3:
        T = sample_poses("uniform", 1, rng)[0]
    centre, semi, axes = _fitted_ellipse(T)
    # points on OpenCV's ellipse (independent of our conic): the residual vanishes there
    phi = rng.uniform(0, 2 * np.pi, 40)
    on = centre + (semi[0] * np.cos(phi))[:, None] * axes[0] + (semi[1] * np.sin(phi))[:, None] * axes[1]
    r_on, _ = res.conic_residual(T, CAM.K, NEEDLE.radius_m, on)
    assert np.abs(r_on).max() < 2e-3  # float32 fit of 400 points
    # move along OpenCV's ellipse normal by d: the residual reads d (outward positive)
    normal = (np.cos(phi) / semi[0])[:, None] * axes[0] + (np.sin(phi) / semi[1])[:, None] * axes[1]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    rho_min = semi.min() ** 2 / semi.max()  # smallest radius of curvature of the ellipse, px
    for d in (-0.5, -0.2, 0.3, 0.6):
        r_d, _ = res.conic_residual(T, CAM.K, NEEDLE.radius_m, on + d * normal)
        # Sampson is first order: its error is bounded by d^2 / rho_min, plus the fit's error
        np.testing.assert_allclose(r_d[0], d, atol=2e-3 + d * d / rho_min)
        assert np.all(np.sign(r_d[0]) == np.sign(d))


def test_conic_residual_finite_when_edge_on_or_behind_camera() -> None:
    rng = np.random.default_rng(3)
    T = sample_poses("edge_on", 50, rng)
    T[:, :3, :3] = T[:, :3, :3]
    # exactly edge-on: normal perpendicular to the ray through the centre
    Te = T.copy()
    ray = Te[:, :3, 3] / np.linalg.norm(Te[:, :3, 3], axis=1, keepdims=True)
    n = np.cross(ray, rng.normal(size=(50, 3)))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    x = np.cross(n, ray)
    Te[:, :3, :3] = np.stack([x, np.cross(n, x), n], axis=2)
    behind = T.copy()
    behind[:, 2, 3] *= -1
    pts = rng.uniform(0, 1080, size=(100, 2))
    for poses in (T, Te, behind):
        r, J = res.conic_residual(poses, CAM.K, NEEDLE.radius_m, pts)
        assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))
        assert np.abs(r).max() <= res.SAMPSON_MAX_PX / 2 + 1
    # behind the camera the conic is the same: the residual cannot tell (documented)
    flipped = T.copy()
    flipped[:, :3, :] *= -1  # the point reflection through the camera centre maps the circle to itself
    flipped[:, :3, :3] = T[:, :3, :3] @ np.diag([1.0, -1.0, -1.0]) * -1
    r1, _ = res.conic_residual(T, CAM.K, NEEDLE.radius_m, pts)
    r2, _ = res.conic_residual(flipped, CAM.K, NEEDLE.radius_m, pts)
    np.testing.assert_allclose(r1, r2, rtol=1e-6, atol=1e-6)


def test_keypoint_behind_camera_and_in_camera_plane_finite() -> None:
    T = np.eye(4)
    T[2, 3] = -0.03
    r, J = res.keypoint_residual(T, CAM.K, NEEDLE.tip_m, [500, 500])
    assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))
    T[2, 3] = 0.0
    r, J = res.keypoint_residual(T, CAM.K, np.zeros(3), [500, 500])
    assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))


def test_grasp_and_perpendicular_values() -> None:
    rng = np.random.default_rng(5)
    T = sample_poses("uniform", 30, rng)
    p = rng.normal(size=3)
    r, _ = res.grasp_position_residual(T, NEEDLE.grasp_m, p)
    np.testing.assert_allclose(r, T[:, :3, :3] @ NEEDLE.grasp_m + T[:, :3, 3] - p, atol=1e-15)
    z = rng.normal(size=3)
    r, _ = res.grasp_perpendicular_residual(T, NEEDLE.grasp_tangent * 3.0, z)
    expected = (T[:, :3, :3] @ NEEDLE.grasp_tangent) @ (z / np.linalg.norm(z))
    np.testing.assert_allclose(r[:, 0], expected, atol=1e-15)


def test_motion_residual_is_zero_for_exact_grasper_motion_and_matches_gtsam() -> None:
    rng = np.random.default_rng(6)
    Tp = sample_poses("uniform", 20, rng)
    D = se3_exp(rng.normal(size=6) * 0.2)
    r, _, _ = res.motion_residual(Tp, D @ Tp, D)
    assert np.abs(r).max() < 1e-12
    xi = rng.normal(size=6) * 0.5
    Tc = D @ Tp[0] @ se3_exp(xi)
    r, _, _ = res.motion_residual(Tp[0], Tc, D)
    g = gtsam.Pose3.Logmap(matrix_to_pose3(D @ Tp[0]).between(matrix_to_pose3(Tc)))
    np.testing.assert_allclose(r[0], g, atol=1e-9)


def _factors_and_functions(T: np.ndarray, rng: np.random.Generator):
    R, t = T[:3, :3], T[:3, 3]
    tip = CAM.project(R @ NEEDLE.tip_m + t) + rng.normal(size=2)
    pts = CAM.project(NEEDLE.arc_points(30) @ R.T + t) + rng.normal(size=(30, 2))
    pg = R @ NEEDLE.grasp_m + t + rng.normal(size=3) * 1e-3
    zg = rng.normal(size=3)
    cov3 = np.array([[1.0, 0.2, 0.0], [0.2, 2.0, 0.1], [0.0, 0.1, 3.0]]) * 1e-6
    return [
        (
            KeypointFactor(0, CAM, NEEDLE.tip_m, tip, gtsam.noiseModel.Diagonal.Sigmas([1.006, 1.012])),
            lambda X: res.keypoint_residual(X, CAM.K, NEEDLE.tip_m, tip),
            np.diag([1 / 1.006, 1 / 1.012]),
        ),
        (
            ConicFactor(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(30, 1.235)),
            lambda X: res.conic_residual(X, CAM.K, NEEDLE.radius_m, pts),
            np.eye(30) / 1.235,
        ),
        (
            GraspPositionFactor(0, NEEDLE.grasp_m, pg, gtsam.noiseModel.Gaussian.Covariance(cov3)),
            lambda X: res.grasp_position_residual(X, NEEDLE.grasp_m, pg),
            np.linalg.inv(np.linalg.cholesky(cov3)),
        ),
        (
            GraspPerpendicularFactor(0, NEEDLE.grasp_tangent, zg, gtsam.noiseModel.Isotropic.Sigma(1, 0.138)),
            lambda X: res.grasp_perpendicular_residual(X, NEEDLE.grasp_tangent, zg),
            np.eye(1) / 0.138,
        ),
    ]


def test_batched_functions_equal_factor_linearize() -> None:
    rng = np.random.default_rng(7)
    for T in sample_poses("uniform", 25, rng):
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(T))
        for f, fn, W in _factors_and_functions(T, rng):
            A, b = f.linearize(v).jacobian()
            r, J = fn(T[None])
            r, J = r.reshape(-1), J.reshape(-1, 6)
            # GTSAM whitens with an upper-triangular R (R^T R = inv(cov)); compare A^T A and A^T b,
            # which do not depend on the choice of square root, then the diagonal cases exactly.
            np.testing.assert_allclose(A.T @ A, J.T @ W.T @ W @ J, rtol=1e-10, atol=1e-10 * np.abs(A.T @ A).max())
            np.testing.assert_allclose(A.T @ b, -J.T @ W.T @ W @ r, rtol=1e-10, atol=1e-10 * np.abs(A.T @ b).max())
            if np.allclose(W, np.diag(np.diag(W))):
                np.testing.assert_allclose(A, W @ J, rtol=1e-10, atol=1e-12)
                np.testing.assert_allclose(b, -W @ r, rtol=1e-10, atol=1e-12)
    # the motion factor, two keys
    Tp, Tc = sample_poses("uniform", 2, rng)
    D = se3_exp(rng.normal(size=6) * 0.1)
    f = MotionFactor(0, 1, matrix_to_pose3(D), gtsam.noiseModel.Isotropic.Sigma(6, 0.5))
    v = gtsam.Values()
    v.insert(0, matrix_to_pose3(Tp))
    v.insert(1, matrix_to_pose3(Tc))
    A, b = f.linearize(v).jacobian()
    r, Jp, Jc = res.motion_residual(Tp, Tc, D)
    np.testing.assert_allclose(A, np.hstack([Jp[0], Jc[0]]) / 0.5, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b, -r[0] / 0.5, rtol=1e-10, atol=1e-12)


def test_small_graph_levenberg_marquardt_recovers_true_pose() -> None:
    rng = np.random.default_rng(8)
    worst_t = worst_r = 0.0
    for _ in range(20):
        T = sample_poses("uniform", 1, rng)[0]
        while abs(T[:3, 2] @ T[:3, 3]) / np.linalg.norm(T[:3, 3]) < 0.2:
            T = sample_poses("uniform", 1, rng)[0]
        R, t = T[:3, :3], T[:3, 3]
        zg = np.cross(R @ NEEDLE.grasp_tangent, rng.normal(size=3))  # a grasper axis perpendicular in truth
        g = gtsam.NonlinearFactorGraph()
        g.add(
            KeypointFactor(
                0, CAM, NEEDLE.tip_m, CAM.project(R @ NEEDLE.tip_m + t), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
            )
        )
        g.add(
            KeypointFactor(
                0, CAM, NEEDLE.tail_m, CAM.project(R @ NEEDLE.tail_m + t), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
            )
        )
        pts = CAM.project(NEEDLE.arc_points(40) @ R.T + t)
        g.add(ConicFactor(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(40, 1.235)))
        g.add(
            GraspPositionFactor(
                0, NEEDLE.grasp_m, R @ NEEDLE.grasp_m + t, gtsam.noiseModel.Diagonal.Sigmas([4.1e-4, 4.4e-4, 1e-3])
            )
        )
        g.add(GraspPerpendicularFactor(0, NEEDLE.grasp_tangent, zg, gtsam.noiseModel.Isotropic.Sigma(1, 0.138)))
        init = gtsam.Values()
        # ~1.7 deg / 1 mm off. From ~6 deg off, ~1 start in 4 lands in a local minimum of the
        # full-circle Sampson cost (measured 22/30 converge): the reason trackers keep hypotheses.
        start = T @ se3_exp(np.r_[rng.normal(size=3) * 0.03, rng.normal(size=3) * 1e-3])
        init.insert(0, matrix_to_pose3(start))
        params = gtsam.LevenbergMarquardtParams()
        params.setDiagonalDamping(True)  # the conic's px/m and px/rad columns differ by ~1e3
        params.setlambdaUpperBound(1e12)
        params.setRelativeErrorTol(1e-14)
        params.setAbsoluteErrorTol(1e-20)
        params.setMaxIterations(200)
        est = gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize().atPose3(0).matrix()
        worst_t = max(worst_t, np.linalg.norm(est[:3, 3] - t))
        worst_r = max(worst_r, np.linalg.norm(cv2.Rodrigues(est[:3, :3] @ R.T)[0]))
    assert worst_t < 1e-7 and worst_r < 1e-6, (worst_t, worst_r)


@pytest.mark.parametrize(
    "make, arg",
    [
        (lambda: KeypointFactor(0, CAM, [0, 0], [1, 2], gtsam.noiseModel.Isotropic.Sigma(2, 1)), "needle_point_m"),
        (
            lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, [np.nan, 2], gtsam.noiseModel.Isotropic.Sigma(2, 1)),
            "measured_px",
        ),
        (lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, [1, 2], gtsam.noiseModel.Isotropic.Sigma(3, 1)), "noise"),
        (lambda: KeypointFactor("x", CAM, NEEDLE.tip_m, [1, 2], gtsam.noiseModel.Isotropic.Sigma(2, 1)), "key"),
        (lambda: ConicFactor(0, CAM, 0.0045, np.zeros((0, 2)), gtsam.noiseModel.Isotropic.Sigma(1, 1)), "points_px"),
        (lambda: ConicFactor(0, CAM, 0.0045, np.zeros((3, 3)), gtsam.noiseModel.Isotropic.Sigma(3, 1)), "points_px"),
        (lambda: ConicFactor(0, CAM, -1.0, np.zeros((3, 2)), gtsam.noiseModel.Isotropic.Sigma(3, 1)), "radius_m"),
        (lambda: ConicFactor(0, np.eye(2), 0.0045, np.zeros((3, 2)), gtsam.noiseModel.Isotropic.Sigma(3, 1)), "camera"),
        (
            lambda: GraspPositionFactor(0, NEEDLE.grasp_m, [0, np.inf, 0], gtsam.noiseModel.Isotropic.Sigma(3, 1)),
            "measured_cam_m",
        ),
        (
            lambda: GraspPerpendicularFactor(0, [0, 0, 0], [0, 0, 1], gtsam.noiseModel.Isotropic.Sigma(1, 1)),
            "needle_tangent",
        ),
        (lambda: MotionFactor(0, 0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1)), "key_prev"),
        (lambda: MotionFactor(0, 1, np.full((4, 4), np.nan), gtsam.noiseModel.Isotropic.Sigma(6, 1)), "cam_delta"),
        (lambda: MotionFactor(0, 1, gtsam.Pose3(), "noise"), "noise"),
        (lambda: PinholeCamera(-1, 900, 0, 0), "fx"),
        (lambda: PinholeCamera(900, 900, 0, np.nan), "cy"),
        (lambda: NeedleModel(radius_m=0), "radius_m"),
    ],
)
def test_constructors_reject_bad_input_naming_the_argument(make, arg: str) -> None:
    with pytest.raises(ValueError, match=arg):
        make()


def test_factor_survives_in_graph_after_python_object_dropped_and_lm_on_edge_on_start() -> None:
    """No interpreter crash: factor objects dropped, an edge-on start, a start behind the camera."""
    import gc

    T = np.eye(4)
    T[:3, 3] = [0, 0, 0.04]
    pts = CAM.project(NEEDLE.arc_points(20) @ T[:3, :3].T + T[:3, 3])
    g = gtsam.NonlinearFactorGraph()
    g.add(ConicFactor(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(20, 1.0)))
    g.add(
        GraspPositionFactor(
            0, NEEDLE.grasp_m, T[:3, :3] @ NEEDLE.grasp_m + T[:3, 3], gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
        )
    )
    gc.collect()
    for start in (se3_exp(np.r_[np.pi / 2, 0, 0, 0, 0, 0.04]), se3_exp(np.r_[0, 0, 0, 0, 0, -0.04])):
        init = gtsam.Values()
        init.insert(0, matrix_to_pose3(start))
        out = gtsam.LevenbergMarquardtOptimizer(g, init).optimize()
        assert np.all(np.isfinite(out.atPose3(0).matrix()))


def test_exception_in_a_factor_callback_is_safe_to_inspect() -> None:
    """A user error inside a callback (a Point3 under the pose key) raises, and printing the
    traceback with every frame's locals (what pytest and IPython do) does not crash."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import traceback, gtsam, numpy as np
        from factors.gtsam_factors import GraspPositionFactor, MotionFactor
        for f in (GraspPositionFactor(0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.05], gtsam.noiseModel.Isotropic.Sigma(3, 1.0)),
                  MotionFactor(0, 1, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1.0))):
            v = gtsam.Values(); v.insert(0, gtsam.Point3(0, 0, 1)); v.insert(1, gtsam.Point3(0, 0, 1))
            try:
                f.linearize(v)
            except Exception as exc:
                for frame, _ in traceback.walk_tb(exc.__traceback__):
                    [repr(x) for x in frame.f_locals.values()]
                print(type(exc).__name__, "caught")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.count("caught") == 2
