"""Mode proposals keep the ellipse exactly; Laplace evidence matches brute-force integration."""

from __future__ import annotations

import numpy as np
import pytest

from factors.lie import local, se3_exp
from factors.residuals import needle_image_conic
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.proposals import (
    arc_flips,
    dedupe,
    frame_ellipse_poses,
    gaussian_log_normaliser,
    laplace_log_evidence,
    mode_proposals,
    near,
    polish_with_prior,
    pose_on_circle,
    twin_poses,
)
from tests.test_trackers_pf import CAMERA, NEEDLE, observe, true_pose

K, R = CAMERA.K, NEEDLE.radius_m
TA, PA = NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad


def _poses(n: int, seed: int) -> np.ndarray:
    """Random oblique needle poses 35-70 mm in front of the camera."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = se3_exp(np.concatenate([rng.normal(size=(n, 3)) * 0.8, np.zeros((n, 3))], axis=1))[:, :3, :3]
    T[:, :3, 3] = np.stack([rng.uniform(-0.01, 0.01, n), rng.uniform(-0.01, 0.01, n), rng.uniform(0.035, 0.07, n)], 1)
    return T


def _conic_gap(T: np.ndarray, C_ref: np.ndarray) -> np.ndarray:
    return np.abs(needle_image_conic(T, K, R) - C_ref).max(axis=(1, 2))


def test_flips_keep_the_circle_and_move_the_arc() -> None:
    T = _poses(20, 0)
    F = arc_flips(T, TA, PA)
    assert F.shape == (20, 3, 4, 4)
    C = needle_image_conic(T, K, R)
    for j in range(3):
        assert np.all(_conic_gap(F[:, j], C) < 1e-9)
        assert np.allclose(F[:, j, :3, 3], T[:, :3, 3])  # same centre
        assert np.allclose(np.abs(np.sum(F[:, j, :3, 2] * T[:, :3, 2], axis=1)), 1.0)  # same plane
    # the midpoint flip swaps tip and tail in space; the tail flip keeps the tail, the tip flip the tip
    tip = lambda X: X[:, :3, :3] @ NEEDLE.tip_m + X[:, :3, 3]  # noqa: E731
    tail = lambda X: X[:, :3, :3] @ NEEDLE.tail_m + X[:, :3, 3]  # noqa: E731
    assert np.allclose(tip(F[:, 0]), tail(T), atol=1e-12) and np.allclose(tail(F[:, 0]), tip(T), atol=1e-12)
    assert np.allclose(tail(F[:, 1]), tail(T), atol=1e-12) and not np.allclose(tip(F[:, 1]), tip(T), atol=1e-4)
    assert np.allclose(tip(F[:, 2]), tip(T), atol=1e-12) and not np.allclose(tail(F[:, 2]), tail(T), atol=1e-4)


def test_twin_reproduces_the_modes_ellipse_and_its_arc_pixels() -> None:
    T = _poses(30, 1)
    tw = twin_poses(T, K, R, TA, PA)
    assert tw.shape[0] >= 25  # only near face-on / edge-on views lack a twin
    C = needle_image_conic(T, K, R)
    for X in tw:
        gap = _conic_gap(X[None], C)
        assert gap.min() < 1e-9
        i = int(np.argmin(gap))
        assert abs(X[:3, 2] @ T[i, :3, 2]) < np.cos(np.deg2rad(5.0))  # a different plane
        # the arc's midpoint projects onto the same pixel (carried along its ray), tip/tail nearby
        mid = NEEDLE.point(0.5 * (TA + PA))
        assert np.allclose(CAMERA.project(X[:3, :3] @ mid + X[:3, 3]), CAMERA.project(T[i, :3, :3] @ mid + T[i, :3, 3]),
                           atol=1e-6)


def test_frame_ellipse_poses_reproduce_the_fitted_conic() -> None:
    rng = np.random.default_rng(2)
    T = true_pose()
    obs = observe(T, rng)
    P, C = frame_ellipse_poses(obs.backbone_px, K, R, TA, PA)
    assert C is not None and P.shape[0] == 4
    Cs = C * np.sign(C[0, 0] + C[1, 1])
    assert np.all(_conic_gap(P, Cs) < 1e-9)
    # one of them is near the truth (the ellipse fit is noisy: a few degrees / millimetres)
    xi = local(P, np.broadcast_to(T, P.shape))
    assert np.min(np.linalg.norm(xi[:, :3], axis=1)) < np.deg2rad(10.0)


def test_mode_proposals_keep_the_ellipse_and_are_distinct() -> None:
    rng = np.random.default_rng(3)
    T = true_pose()
    lik = FrameLikelihood(observe(T, rng), MeasurementModel(CAMERA, NEEDLE))
    P = mode_proposals(T, lik, frame_ellipse=False)
    assert P.shape[0] == 7  # 3 flips, the twin and its 3 flips
    assert np.all(_conic_gap(P, needle_image_conic(T, K, R)) < 1e-9)
    allp = np.concatenate([T[None], P])
    assert dedupe(allp).tolist() == list(range(8))
    assert not near(P, T).any()
    # with the frame's ellipse: each proposal reproduces either the mode's or the frame's conic
    Pf = mode_proposals(T, lik)
    _, Cf = frame_ellipse_poses(lik.observation.backbone_px, K, R, TA, PA)
    Cf = Cf * np.sign(Cf[0, 0] + Cf[1, 1])
    gap = np.minimum(_conic_gap(Pf, needle_image_conic(T, K, R)), _conic_gap(Pf, Cf))
    assert Pf.shape[0] > P.shape[0] and np.all(gap < 1e-9)
    # existing modes are excluded
    assert mode_proposals(T, lik, existing=P[:2], frame_ellipse=False).shape[0] == 5


def test_pose_on_circle_rows_are_independent() -> None:
    # frame_ellipse_poses builds its four poses in one call: each row must be the one-row call's, bit for bit
    rng = np.random.default_rng(11)
    c, n, m = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    together = pose_on_circle(c, n, m, 0.7)
    one_by_one = np.stack([pose_on_circle(c[i], n[i], m[i], 0.7)[0] for i in range(6)])
    assert together.tobytes() == one_by_one.tobytes()


def _dedupe_one_by_one(T: np.ndarray, existing: np.ndarray) -> list[int]:
    """The reference: one :func:`near` call per pose against the existing poses and those kept so far."""
    kept: list[int] = []
    for i in range(T.shape[0]):
        ref = np.concatenate([existing, T[kept]])
        if ref.shape[0] and near(T[i], ref).any():
            continue
        kept.append(i)
    return kept


@pytest.mark.parametrize("seed", range(40))
def test_dedupe_equals_the_one_by_one_loop(seed: int) -> None:
    # clusters at the separation's scale (5 deg, 1 mm), so that chains of near pairs occur: a pose near a dropped
    # pose but not near a kept one must stay
    rng = np.random.default_rng(seed)
    base = true_pose()
    spread = rng.choice([0.03, 0.08, 0.5])
    T = base @ se3_exp(np.concatenate([rng.normal(size=(12, 3)) * spread, rng.normal(size=(12, 3)) * 1e-3 * spread
                                       / 0.08], axis=1))
    E = T[rng.choice(12, size=rng.integers(0, 3), replace=False)] @ se3_exp(rng.normal(size=6) * 1e-3)
    assert dedupe(T, E).tolist() == _dedupe_one_by_one(T, E.reshape(-1, 4, 4))
    assert dedupe(T).tolist() == _dedupe_one_by_one(T, np.zeros((0, 4, 4)))
    assert dedupe(T[:0]).tolist() == []


def test_gaussian_log_normaliser() -> None:
    P = np.diag([0.5, 2.0, 3.0])
    assert np.isclose(gaussian_log_normaliser(P), -0.5 * np.log(np.linalg.det(2 * np.pi * P)))
    assert laplace_log_evidence(1.0, -np.eye(2)) == -np.inf


@pytest.mark.parametrize("seed", [0, 1])
def test_laplace_evidence_matches_brute_force_on_a_slice(seed: int) -> None:
    """1-D slice through the polished peak of a real frame likelihood: Laplace vs trapezoid quadrature."""
    rng = np.random.default_rng(seed)
    T = true_pose()
    lik = FrameLikelihood(observe(T, rng, kinematics=False), MeasurementModel(CAMERA, NEEDLE))
    Tp, E, H = polish_with_prior(lik, T, iters=30)
    _, g, _ = lik.gauss_newton(Tp)
    assert np.linalg.norm(g) < 1e-3 * np.sqrt(np.trace(H[0]))  # at the peak
    for _ in range(3):
        u = rng.normal(size=6)
        u /= np.linalg.norm(u)
        h = float(u @ H[0] @ u)
        s = np.linspace(-8, 8, 2001) / np.sqrt(h)
        nll = lik.nll(Tp[0] @ se3_exp(s[:, None] * u))
        m = nll.min()
        brute = -m + np.log(np.trapezoid(np.exp(-(nll - m)), s))
        laplace = float(laplace_log_evidence(E[0], np.array([[h]])))
        assert abs(brute - laplace) < 0.1, (brute, laplace)


def test_polish_with_prior_is_pulled_towards_the_prior() -> None:
    rng = np.random.default_rng(4)
    T = true_pose()
    lik = FrameLikelihood(observe(T, rng), MeasurementModel(CAMERA, NEEDLE))
    mu = T @ se3_exp(np.r_[0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    free, E0, _ = polish_with_prior(lik, T, iters=20)
    weak, _, _ = polish_with_prior(lik, T, mu, np.eye(6) * 1e-6, iters=20)
    strong, E1, H1 = polish_with_prior(lik, T, mu, np.eye(6) * 1e8, iters=40)
    assert np.allclose(local(free, weak), 0.0, atol=1e-4)
    assert np.linalg.norm(local(strong, mu[None])) < 1e-3
    assert E1[0] > E0[0] and np.all(np.linalg.eigvalsh(H1[0]) > 1e7)
