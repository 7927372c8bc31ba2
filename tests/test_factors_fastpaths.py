"""Every fast path pinned to its reference: restructured kernels and memoised evaluations."""

from __future__ import annotations

import numpy as np
import pytest

from factors import residuals as res
from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import cross, se3_exp
from factors.robust import RobustLoss
from pinpoint_fg import stein
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, gauss_newton_frames
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.observation import Observation
from pinpoint_fg.stein import SteinConfig, _median, floor_hessians, quantile_rows, stein_step
from tests.poses import KINDS, sample_poses
from tests.reference_kernels import conic_residual_reference, floor_hessians_reference, stein_step_reference

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()


def _edge_tilt(T: np.ndarray) -> np.ndarray:
    """|sin| of the angle between the needle plane and the viewing ray through its centre."""
    ray = T[:, :3, 3] / np.linalg.norm(T[:, :3, 3], axis=1, keepdims=True)
    return np.abs(np.einsum("ni,ni->n", ray, T[:, :3, 2]))


@pytest.mark.parametrize("kind", KINDS)
def test_conic_residual_equals_reference(kind: str) -> None:
    rng = np.random.default_rng(11)
    T = sample_poses(kind, 200, rng)
    pts = rng.uniform(0, 1080, size=(150, 2))
    r0, J0 = conic_residual_reference(T, CAM.K, NEEDLE.radius_m, pts)
    r1, J1 = res.conic_residual(T, CAM.K, NEEDLE.radius_m, pts)
    r2, none = res.conic_residual(T, CAM.K, NEEDLE.radius_m, pts, jacobian=False)
    assert none is None
    np.testing.assert_allclose(r2, r1, rtol=1e-12, atol=1e-12)
    # per pose, relative to the pose's largest entry (pixels and px/rad, px/m mix scales)
    err_r = np.max(np.abs(r1 - r0), axis=1) / np.maximum(np.max(np.abs(r0), axis=1), 1.0)
    err_J = np.max(np.abs(J1 - J0), axis=(1, 2)) / np.max(np.abs(J0), axis=(1, 2))
    tol = np.full(T.shape[0], 1e-9)
    if kind == "edge_on":
        # Within 1e-3 rad of edge-on the conic degenerates towards a double line and the Sampson
        # distance grows ill-conditioned: two summation orders then differ by round-off times a
        # condition ~ 1/tilt (measured 3e-6 at 2e-7 rad). There the bound is 1e-12 / tilt (1e-9 at 1e-3 rad).
        tilt = _edge_tilt(T)
        assert (tilt < 1e-5).sum() > 20 and (tilt >= 1e-3).sum() > 20
        tol = np.maximum(tol, 1e-12 / tilt)
    assert np.all(err_r < tol), np.max(err_r / tol)
    assert np.all(err_J < tol), np.max(err_J / tol)


def test_conic_residual_without_pixels_and_single_pose() -> None:
    T = sample_poses("uniform", 1, np.random.default_rng(2))[0]
    r, J = res.conic_residual(T, CAM.K, NEEDLE.radius_m, np.zeros((0, 2)))
    assert r.shape == (1, 0) and J.shape == (1, 0, 6)
    pts = np.array([[500.0, 400.0]])
    r0, J0 = conic_residual_reference(T, CAM.K, NEEDLE.radius_m, pts)
    r1, J1 = res.conic_residual(T, CAM.K, NEEDLE.radius_m, pts)
    np.testing.assert_allclose(r1, r0, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(J1, J0, rtol=1e-9, atol=1e-9 * np.abs(J0).max())


def _frame(rng: np.random.Generator) -> tuple[FrameLikelihood, np.ndarray]:
    T = sample_poses("uniform", 1, rng)[0]
    R, t = T[:3, :3], T[:3, 3]
    obs = Observation(0, 0.0, tip_px=CAM.project(R @ NEEDLE.tip_m + t) + rng.normal(size=2),
                      tail_px=CAM.project(R @ NEEDLE.tail_m + t) + rng.normal(size=2),
                      backbone_px=CAM.project(NEEDLE.arc_points(80) @ R.T + t) + rng.normal(size=(80, 2)),
                      cam_T_grasper=T)
    poses = T @ se3_exp(rng.normal(size=(30, 6)) * np.array([0.05] * 3 + [1e-3] * 3))
    return FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE)), poses


def test_gauss_newton_memo_is_bitwise_the_uncached_evaluation() -> None:
    rng = np.random.default_rng(5)
    lik, poses = _frame(rng)
    first = lik.gauss_newton(poses)
    other = lik.gauss_newton(poses @ se3_exp(np.full((30, 6), 1e-4)))  # evicts the memo
    again = lik.gauss_newton(poses.copy())
    fresh = FrameLikelihood(lik.observation, lik.model).gauss_newton(poses)
    for a, b, c in zip(first, again, fresh, strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c)
    first[2][:] = 0.0  # callers get copies: writing to one cannot corrupt the memo
    assert np.array_equal(lik.gauss_newton(poses)[2], fresh[2])
    assert not np.array_equal(other[0], again[0])
    np.testing.assert_allclose(lik.nll(poses), first[0], rtol=1e-12)


@pytest.mark.parametrize("options", [
    {}, {"normalise": "n"}, {"hessian": "kernel-average"}, {"hessian": "own"}, {"floor_each": False},
    {"hessian": "kernel-average", "floor_each": False}, {"preconditioner": "newton-alg1"},
    {"preconditioner": "none", "isotropic": True, "step_size": 1e-3},
])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stein_step_equals_reference(options: dict, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, d = 50, 6
    scale = np.array([0.09] * 3 + [1e-3] * 3)
    xi = rng.normal(size=(n, d)) * scale * rng.uniform(0.1, 3.0)
    g = rng.normal(size=(n, d)) / scale
    A = rng.normal(size=(n, d, d)) / scale[None, :, None]
    H = np.swapaxes(A, 1, 2) @ A * rng.uniform(0.1, 10.0, size=(n, 1, 1))
    H[0] = np.diag(1.0 / scale**2) * np.r_[1e-6, 1.0, 1.0, 1.0, 1.0, 1.0]  # ill-conditioned: the floor binds
    H[1] = 0.0  # no information: the fallback
    H[2, 0, 0] = np.nan  # non-finite: the fallback
    g[3] = np.inf  # non-finite gradient: zeroed
    cfg = SteinConfig(scale=tuple(scale), bandwidth_floor=1e-3, **options)
    ref = stein_step_reference(xi, g, H, cfg)
    new = stein_step(xi, g, H, cfg)
    assert new.bandwidth == pytest.approx(ref.bandwidth, rel=1e-14)
    np.testing.assert_allclose(new.kernel, ref.kernel, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(new.velocity, ref.velocity, rtol=1e-9, atol=1e-9 * np.abs(ref.velocity).max())
    err = np.max(np.abs(new.step - ref.step) / scale, axis=1)
    assert np.all(err < 1e-9 * (1.0 + np.max(np.abs(ref.step) / scale, axis=1)))


def test_floor_hessians_equals_reference() -> None:
    rng = np.random.default_rng(4)
    A = rng.normal(size=(40, 6, 6))
    H = A @ np.swapaxes(A, 1, 2)
    H[:10] -= 3.0 * np.eye(6)  # indefinite
    H[10] = 0.0
    fb = np.arange(1.0, 7.0)
    for a, b in zip(floor_hessians(H, 1e-2, fb), floor_hessians_reference(H, 1e-2, fb), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


@pytest.mark.parametrize("kind", KINDS)
def test_motion_residual_without_jacobian_is_the_same_residual(kind: str) -> None:
    rng = np.random.default_rng(12)
    Tp, Tc = sample_poses(kind, 100, rng), sample_poses(kind, 100, rng)
    D = se3_exp(rng.normal(size=(100, 6)) * 0.1)
    r, Jp, Jc = res.motion_residual(Tp, Tc, D)
    r0, none_p, none_c = res.motion_residual(Tp, Tc, D, jacobian=False)
    assert none_p is None and none_c is None and Jp.shape == Jc.shape == (100, 6, 6)
    np.testing.assert_array_equal(r0, r)


def test_grasp_perpendicular_with_one_axis_per_pose_equals_per_pose_calls() -> None:
    rng = np.random.default_rng(13)
    T = sample_poses("uniform", 40, rng)
    z = rng.normal(size=(40, 3))
    r, J = res.grasp_perpendicular_residual(T, NEEDLE.grasp_tangent, z)
    for i in range(40):
        ri, Ji = res.grasp_perpendicular_residual(T[i], NEEDLE.grasp_tangent, z[i] * 3.0)  # unnormalised
        np.testing.assert_allclose(r[i], ri[0], rtol=0, atol=1e-14)
        np.testing.assert_allclose(J[i], Ji[0], rtol=0, atol=1e-14)


def test_gauss_newton_frames_equals_per_frame_evaluation() -> None:
    # several frames with different term sets (no mask, no tip, no kinematics), batched, equal
    # a fresh per-frame evaluation; a frame of another noise model is grouped on its own
    rng = np.random.default_rng(14)
    frames, poses = [], []
    for k in range(6):
        lik, T = _frame(rng)
        o = lik.observation
        if k == 1:
            o = Observation(0, 0.0, tip_px=o.tip_px, tail_px=o.tail_px, cam_T_grasper=o.cam_T_grasper)
        if k == 2:
            o = Observation(0, 0.0, tail_px=o.tail_px, backbone_px=o.backbone_px)
        model = MeasurementModel(CAM, NEEDLE)  # a new, equal model per frame (as trackers build them)
        if k == 4:
            model = MeasurementModel(CAM, NEEDLE, NoiseConfig().with_robust({"tip": RobustLoss("cauchy", 2.0)}))
        frames.append(FrameLikelihood(o, model))
        poses.append(T[: 10 + k])
    frames[3].gauss_newton(poses[3])  # a memo hit inside the batch
    got = gauss_newton_frames(frames, poses)
    for f, T, g in zip(frames, poses, got, strict=True):
        ref = FrameLikelihood(f.observation, f.model).gauss_newton(T)
        for a, b in zip(g, ref, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
        memo = f.gauss_newton(T)  # the batch filled every frame's memo
        for a, b in zip(memo, g, strict=True):
            assert np.array_equal(a, b)


def test_quantile_rows_is_bitwise_np_quantile() -> None:
    """The Stein transport's stopping quantile: numpy's order statistics and interpolation, every bit."""
    rng = np.random.default_rng(21)
    for n in (1, 2, 3, 7, 20, 21, 50, 51, 1440):
        for q in (0.0, 0.25, 0.5, 0.95, 1.0):
            for case in range(6):
                x = rng.exponential(size=(2, n)) * 10.0 ** rng.uniform(-6, 0)
                if case == 1:
                    x[1] = 0.0
                elif case == 2:
                    x = np.round(x * 1e5)  # ties
                elif case == 3:
                    x[0, n // 2] = np.nan
                with np.errstate(invalid="ignore"):
                    ref = np.quantile(x, q, axis=1)
                assert np.array_equal(quantile_rows(x, q), ref, equal_nan=True), (n, q, case)


def test_median_is_bitwise_np_median() -> None:
    """The bandwidth's median (odd and even counts, ties, NaN) equals ``np.median`` exactly."""
    rng = np.random.default_rng(22)
    for n in (1, 2, 3, 4, 190, 1225, 1226):
        for case in range(4):
            v = rng.exponential(size=n) * 10.0 ** rng.uniform(-8, 3)
            if case == 1:
                v = np.round(v)
            elif case == 2:
                v[n // 2] = np.nan
            ref = float(np.median(v))
            got = _median(v)
            assert (np.isnan(ref) and np.isnan(got)) or got == ref, (n, case)


def test_cross_is_bitwise_np_cross() -> None:
    """``factors.lie.cross`` (used by the conic kernel and the SE(3) log) is ``np.cross``'s elementwise formula."""
    rng = np.random.default_rng(23)
    a = rng.normal(size=(50, 3, 3)) * 10.0 ** rng.uniform(-9, 3, size=(50, 3, 1))
    b = rng.normal(size=(50, 3, 3)) * 10.0 ** rng.uniform(-9, 3, size=(50, 3, 1))
    got = cross(a, b)
    assert np.array_equal(got, np.cross(a, b)) and got.flags["C_CONTIGUOUS"]
    assert np.array_equal(cross(a[0, 0], b[:, 1]), np.cross(a[0, 0], b[:, 1]))  # broadcast


def test_conic_pixel_basis_memo_is_bitwise_a_fresh_evaluation() -> None:
    """Alternating pixel sets (the memo keeps the last one) gives every evaluation its own pixels' result exactly."""
    rng = np.random.default_rng(24)
    T = sample_poses("uniform", 20, rng)
    sets = [rng.uniform(0, 1080, size=(60, 2)), rng.uniform(0, 1080, size=(60, 2)), rng.uniform(0, 1080, size=(30, 2))]
    sets.append(sets[2].reshape(60, 1)[:, 0].reshape(30, 2)[::-1].copy())  # the same values in another order
    first = [res.conic_residual(T, CAM.K, NEEDLE.radius_m, p) for p in sets]
    for p, (r0, J0) in zip(sets[::-1] + sets, first[::-1] + first, strict=True):
        r, J = res.conic_residual(T, CAM.K, NEEDLE.radius_m, p.copy())
        assert np.array_equal(r, r0) and np.array_equal(J, J0)
    # and against the reference kernel (to round-off: it sums in another order)
    r_ref, J_ref = conic_residual_reference(T, CAM.K, NEEDLE.radius_m, sets[0])
    np.testing.assert_allclose(first[0][0], r_ref, rtol=1e-9, atol=1e-9 * np.abs(r_ref).max())
    np.testing.assert_allclose(first[0][1], J_ref, rtol=1e-9, atol=1e-9 * np.abs(J_ref).max())


def test_floor_hessians_without_unusable_rows_equals_reference() -> None:
    """The branch that skips the fallback replacement (every row finite and informative) is the same floor."""
    rng = np.random.default_rng(25)
    A = rng.normal(size=(40, 6, 6))
    H = A @ np.swapaxes(A, 1, 2)
    H[:10] -= 3.0 * np.eye(6)  # indefinite, still informative
    fb = np.arange(1.0, 7.0)
    for a, b in zip(floor_hessians(H, 1e-2, fb), floor_hessians_reference(H, 1e-2, fb), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


def test_likelihood_conic_whitening_in_place_equals_the_products() -> None:
    """The conic's Jacobian whitened and IRLS-reweighted in place: ``J W sqrt(w)``, as new arrays would give."""
    rng = np.random.default_rng(26)
    lik, poses = _frame(rng)
    lik = FrameLikelihood(lik.observation, MeasurementModel(CAM, NEEDLE, NoiseConfig().with_robust(
        {"conic": RobustLoss("huber", 1.345)})))
    pts = lik._data["conic"]
    r, J = res.conic_residual(poses, CAM.K, NEEDLE.radius_m, pts)
    n, W = lik._noise["conic"], lik._W["conic"][0, 0]
    e, Jw = (r - n.mean[0]) * W, J * W
    d = np.abs(e)
    sw = np.sqrt(lik._loss["conic"].weight(d))
    loss, e_irls, J_irls = lik._robust("conic", *lik._whiten("conic", *res.conic_residual(poses, CAM.K,
                                                                                         NEEDLE.radius_m, pts)))
    assert np.array_equal(loss, lik._loss["conic"].loss(d).sum(axis=1))
    assert np.array_equal(e_irls, e * sw) and np.array_equal(J_irls, Jw * sw[:, :, None])


def test_sqrt_information_is_kept_per_covariance_value() -> None:
    """The whitening: computed once per covariance value, handed out as copies, recomputed after an in-place change."""
    n = ResidualNoise(np.zeros(2), np.array([[4.0, 0.5], [0.5, 1.0]]))
    ref = np.linalg.inv(np.linalg.cholesky(n.cov))
    a, b = n.sqrt_information, n.sqrt_information
    assert np.array_equal(a, ref) and np.array_equal(b, ref) and a is not b
    a[:] = 0.0  # a caller's copy: the kept one is untouched
    assert np.array_equal(n.sqrt_information, ref)
    n.cov[:] = 4.0 * n.cov
    assert np.array_equal(n.sqrt_information, np.linalg.inv(np.linalg.cholesky(n.cov)))


@pytest.mark.parametrize("kind", KINDS)
def test_point_and_small_residuals_filled_in_place_equal_their_concatenated_forms(kind: str) -> None:
    """point_jacobian, the grasp-perpendicularity Jacobian and the prior / motion residuals, bitwise their
    earlier forms (np.concatenate, per-call normalisation, separate log and inverse right Jacobian)."""
    from factors.lie import se3_inverse, se3_log, se3_right_jacobian_inv, skew

    rng = np.random.default_rng(14)
    for n in (1, 7, 60):
        T = sample_poses(kind, n, rng)
        R = T[:, :3, :3]
        for X in (NEEDLE.tip_m, NEEDLE.grasp_m, rng.normal(size=3) * 0.01):
            p, J = res.point_jacobian(T, X)
            np.testing.assert_array_equal(p, R @ X + T[:, :3, 3])
            np.testing.assert_array_equal(J, np.concatenate([-R @ skew(X), R], axis=2))
        for z in (rng.normal(size=3), rng.normal(size=(n, 3))):
            r, J = res.grasp_perpendicular_residual(T, NEEDLE.grasp_tangent, z)
            tg = NEEDLE.grasp_tangent / np.linalg.norm(NEEDLE.grasp_tangent)
            zg = z / np.linalg.norm(z, axis=-1, keepdims=True)
            np.testing.assert_array_equal(r[:, 0], ((R @ tg) * zg).sum(axis=-1))
            Jw = -np.einsum("i,nij->nj" if z.ndim == 1 else "ni,nij->nj", zg, R @ skew(tg))
            np.testing.assert_array_equal(J, np.concatenate([Jw, np.zeros((n, 3))], axis=1)[:, None, :])
        M = sample_poses(kind, n, rng)
        r, J = res.pose_prior_residual(T, M)
        r0 = se3_log(se3_inverse(M) @ T)
        np.testing.assert_array_equal(r, r0)
        np.testing.assert_array_equal(J, se3_right_jacobian_inv(r0))
        D = se3_exp(rng.normal(size=(n, 6)) * 0.1)
        r, Jp, Jc = res.motion_residual(M, T, D)
        E = se3_inverse(D @ M) @ T
        r0 = se3_log(E)
        np.testing.assert_array_equal(r, r0)
        np.testing.assert_array_equal(Jc, se3_right_jacobian_inv(r0))


@pytest.mark.parametrize("kind", KINDS)
def test_small_residuals_without_jacobian_are_bitwise_the_same_residuals(kind: str) -> None:
    """``jacobian=False`` (the particle filter's likelihood-only path) skips the Jacobian and returns None for it;
    the residual is bit for bit the one computed with it, and so is every likelihood built on them."""
    rng = np.random.default_rng(16)
    for n in (1, 7, 60):
        T = sample_poses(kind, n, rng)
        for X in (NEEDLE.tip_m, NEEDLE.grasp_m):
            p, none = res.point_jacobian(T, X, jacobian=False)
            assert none is None
            np.testing.assert_array_equal(p, res.point_jacobian(T, X)[0])
            z = rng.uniform(0, 1080, size=2)
            r, none = res.keypoint_residual(T, CAM.K, X, z, jacobian=False)
            assert none is None
            np.testing.assert_array_equal(r, res.keypoint_residual(T, CAM.K, X, z)[0])
        pg = rng.normal(size=3) * 0.02
        r, none = res.grasp_position_residual(T, NEEDLE.grasp_m, pg, jacobian=False)
        assert none is None
        np.testing.assert_array_equal(r, res.grasp_position_residual(T, NEEDLE.grasp_m, pg)[0])
        for zg in (rng.normal(size=3), rng.normal(size=(n, 3))):
            r, none = res.grasp_perpendicular_residual(T, NEEDLE.grasp_tangent, zg, jacobian=False)
            assert none is None
            np.testing.assert_array_equal(r, res.grasp_perpendicular_residual(T, NEEDLE.grasp_tangent, zg)[0])


def test_conic_residual_is_bitwise_its_earlier_form() -> None:
    """conic_residual with its constants built once (Q, skew(e_k)) and dh/dxi filled in place: the same bits as
    the per-call construction (its whole earlier body, restated here as the reference)."""
    from factors.lie import skew

    rng = np.random.default_rng(15)
    for kind in KINDS:
        T = sample_poses(kind, 40, rng)
        pts = rng.uniform(0, 1080, size=(120, 2))
        r, J = res.conic_residual(T, CAM.K, NEEDLE.radius_m, pts)
        K = CAM.K
        R, t = T[:, :3, :3], T[:, :3, 3]
        KR = K @ R
        h1, h2, h3 = KR[:, :, 0], KR[:, :, 1], t @ K.T
        A = cross(np.stack([h2, h3, h1], axis=1), np.stack([h3, h1, h2], axis=1))
        scale = 1.0 / np.maximum(np.sqrt(np.add.reduce(A * A, axis=(1, 2))), 1e-300)
        A = A * scale[:, None, None]
        _, sc, P, phi = res._pixel_basis(pts)
        Q = np.diag([1.0, 1.0, -(float(NEEDLE.radius_m) ** 2)])
        AP = A @ P
        QAP = Q @ AP
        C = np.swapaxes(AP, 1, 2) @ QAP
        cn = 1.0 / np.maximum(np.sqrt(np.add.reduce(C * C, axis=(1, 2))), 1e-300)
        C = C * cn[:, None, None]
        e, zero3 = np.eye(3), np.zeros((40, 3, 3))
        Dh1 = np.concatenate([-KR @ skew(e[0]), zero3], axis=2)
        Dh2 = np.concatenate([-KR @ skew(e[1]), zero3], axis=2)
        Dh3 = np.concatenate([zero3, KR], axis=2)
        S1, S2, S3 = skew(h1), skew(h2), skew(h3)
        DA = np.stack([-S3 @ Dh2 + S2 @ Dh3, -S1 @ Dh3 + S3 @ Dh1, -S2 @ Dh1 + S1 @ Dh2], axis=1)
        DAd = np.moveaxis(DA * scale[:, None, None, None], 3, 1) @ P
        dC = np.swapaxes(DAd, 2, 3) @ QAP[:, None]
        dC = (dC + np.swapaxes(dC, 2, 3)) * cn[:, None, None, None]
        Call = np.concatenate([C[:, None], dC], axis=1)
        flat = np.concatenate([Call.reshape(40, 7, 9), np.zeros((40, 7, 1))], axis=2)
        coef = flat[:, :, res._CONIC_COEF_INDEX] * res._CONIC_COEF_MULT
        out = (coef.reshape(-1, 6) @ phi).reshape(40, 7, 3, 120)
        f, g1, g2 = out[:, 0, 0], out[:, 0, 1], out[:, 0, 2]
        g2s = g1 * g1 + g2 * g2
        gn = np.sqrt(g2s)
        f2d = (f * sc / res.SAMPSON_MAX_PX) ** 2
        den = g2s + f2d
        ok = den > 0
        iden = 1.0 / den if ok.all() else np.where(ok, 1.0 / np.where(ok, den, 1.0), 0.0)
        np.testing.assert_array_equal(r, sc * f * gn * iden)
        c_f = sc * gn * (1.0 - 2.0 * f2d * iden) * iden
        c_g = sc * f * (1.0 - 2.0 * g2s * iden) * iden
        pos = gn > 0
        q = c_g / gn if pos.all() else np.where(pos, c_g / np.where(pos, gn, 1.0), 0.0)
        J0 = out[:, 1:, 0] * c_f[:, None] + out[:, 1:, 1] * (g1 * q)[:, None]
        J0 += out[:, 1:, 2] * (g2 * q)[:, None]
        np.testing.assert_array_equal(J, np.swapaxes(J0, 1, 2))


@pytest.mark.parametrize("eps", [1e-2, 1e-6, 1e-9])
@pytest.mark.parametrize("spread", [1e-3, 1.0, 1e6])
def test_floor_hessians_skips_the_eigen_decomposition_only_where_no_floor_binds(eps: float, spread: float) -> None:
    """Information whose eigenvalues all lie above the floor takes the Cholesky/LU path: the same matrices as the
    eigen-decomposition to round-off. One binding row sends the whole batch down the eigen path (the reference's
    own, pinned exactly), as do rows without information or with non-finite entries (the fallback)."""
    rng = np.random.default_rng(27)
    Q = np.linalg.qr(rng.normal(size=(50, 6, 6)))[0]
    w = spread * np.exp(rng.uniform(np.log(10 * eps), 0.0, size=(50, 6)))  # cond < 0.1 / eps: no floor binds
    H = (Q * w[:, None, :]) @ np.swapaxes(Q, 1, 2)
    H[:, 0, 1] += 1e-9 * np.abs(H[:, 0, 1]).max()  # slightly asymmetric: symmetrised first
    fb = np.ones(6)
    assert stein._unfloored(H, eps, fb, 1e-12) is not None
    (H_fl, H_inv), (H_ref, inv_ref) = floor_hessians(H, eps), floor_hessians_reference(H, eps)
    np.testing.assert_allclose(H_fl, H_ref, rtol=0, atol=1e-14 * np.abs(H_ref).max())
    # inverses of matrices with condition number c agree to ~c * 1e-16 (either method's own error)
    cond = (w.max(axis=1) / w.min(axis=1))[:, None, None]
    assert np.all(np.abs(H_inv - inv_ref) <= 1e-13 * cond * np.abs(inv_ref).max(axis=(1, 2), keepdims=True))
    np.testing.assert_allclose(H_inv @ (0.5 * (H + np.swapaxes(H, 1, 2))), np.broadcast_to(np.eye(6), H.shape),
                               rtol=0, atol=1e-14 * cond.max())
    binding = H.copy()
    binding[7] = spread * np.diag(np.r_[0.1 * eps, np.ones(5)])
    assert stein._unfloored(binding, eps, fb, 1e-12) is None
    for a, b in zip(floor_hessians(binding, eps), floor_hessians_reference(binding, eps), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    for bad in (0.0, np.nan):
        unusable = H.copy()
        unusable[3] = bad
        assert stein._unfloored(unusable, eps, fb, 1e-12) is None


@pytest.mark.parametrize("scale", [1e-150, 1e-3, 1.0, 1e6, 1e150])
def test_spectral_bound_lies_between_the_largest_eigenvalue_and_d_to_the_eighth_times_it(scale: float) -> None:
    rng = np.random.default_rng(31)
    Q = np.linalg.qr(rng.normal(size=(200, 6, 6)))[0]
    w = rng.normal(size=(200, 6)) * np.exp(rng.uniform(-12, 0, size=(200, 6)))  # indefinite, any spread
    w[:20] = np.abs(w[:20]).max(axis=1, keepdims=True)  # equal eigenvalues: the bound's loosest case
    w[20:40, 1:] = 0.0  # rank one: exact
    Hs = scale * (Q * w[:, None, :]) @ np.swapaxes(Q, 1, 2)
    Hs = 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
    lam = np.abs(np.linalg.eigvalsh(Hs)).max(axis=1)
    bound = stein._spectral_bound(Hs, np.sqrt(np.einsum("nij,nij->n", Hs, Hs)))
    assert np.all(np.isfinite(bound))
    assert np.all(bound >= lam * (1 - 1e-13)) and np.all(bound <= lam * 6 ** 0.125 * (1 + 1e-13))
    np.testing.assert_allclose(bound[20:40], lam[20:40], rtol=1e-13)
    np.testing.assert_allclose(bound[:20], lam[:20] * 6 ** 0.125, rtol=1e-13)


def test_floor_hessians_proves_no_floor_binds_where_the_frobenius_bound_could_not() -> None:
    """Eigenvalues just above the floor with a dominant one: ``eps ||H||_F`` exceeds the smallest eigenvalue, the
    sharper bound does not, and the Cholesky/LU path gives the reference's matrices."""
    rng = np.random.default_rng(5)
    eps = 1e-2
    Q = np.linalg.qr(rng.normal(size=(50, 6, 6)))[0]
    w = np.tile(np.r_[1.0, 0.5, 0.4, 0.3, 0.2, 1.05 * eps], (50, 1)) * rng.uniform(0.5, 2.0, size=(50, 1))
    H = (Q * w[:, None, :]) @ np.swapaxes(Q, 1, 2)
    fro = np.sqrt(np.einsum("nij,nij->n", H, H))
    assert np.all(w[:, -1] < eps * fro)  # the Frobenius test would fail every row
    assert stein._unfloored(H, eps, np.ones(6), 1e-12) is not None
    (H_fl, H_inv), (H_ref, inv_ref) = floor_hessians(H, eps), floor_hessians_reference(H, eps)
    np.testing.assert_allclose(H_fl, H_ref, rtol=0, atol=1e-14 * np.abs(H_ref).max())
    np.testing.assert_allclose(H_inv, inv_ref, rtol=0, atol=1e-12 * np.abs(inv_ref).max())


def test_stein_step_inverts_an_unfloored_svn_block_without_a_second_eigendecomposition(monkeypatch) -> None:  # noqa: ANN001
    """The kernel-weighted SVN block of well-spread particles needs no floor: one eigen-decomposition (each
    particle's own block) per step, and the step equals the reference's to round-off."""
    rng = np.random.default_rng(11)
    n, d = 50, 6
    scale = np.array([0.09] * 3 + [1e-3] * 3)
    xi = rng.normal(size=(n, d)) * scale
    g = rng.normal(size=(n, d)) / scale
    A = rng.normal(size=(n, d, d)) / scale[None, :, None]
    H = np.swapaxes(A, 1, 2) @ A
    cfg = SteinConfig(scale=tuple(scale), bandwidth_floor=1e-3)
    calls = []
    eig = stein._floor_eig
    monkeypatch.setattr(stein, "_floor_eig", lambda *a, **k: calls.append(k.get("want")) or eig(*a, **k))
    new = stein_step(xi, g, H, cfg)
    assert calls == ["floored"]
    ref = stein_step_reference(xi, g, H, cfg)
    err = np.max(np.abs(new.step - ref.step) / scale, axis=1)
    assert np.all(err < 1e-9 * (1.0 + np.max(np.abs(ref.step) / scale, axis=1)))
