"""Seeding: closed-form circle poses, and every plausible mode gets particles."""

from __future__ import annotations

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.conic_fit import fit_conic
from pinpoint_fg.init import circle_poses_from_conic, seed_particles
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.observation import Observation

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()


@pytest.mark.parametrize("seed", range(8))
def test_one_closed_form_circle_pose_is_the_truth(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = se3_exp(np.r_[rng.normal(size=3) * 0.7, rng.uniform(-0.01, 0.01, 2), rng.uniform(0.03, 0.08)])
    if abs(T[:3, 2] @ T[:3, 3]) / np.linalg.norm(T[:3, 3]) < 0.2:
        pytest.skip("construction: too close to edge-on for a clean ellipse")
    px = CAM.project(NEEDLE.point(np.linspace(0, 2 * np.pi, 100)) @ T[:3, :3].T + T[:3, 3])
    sols = circle_poses_from_conic(fit_conic(px), CAM.K, NEEDLE.radius_m)
    assert len(sols) == 2
    n_true = T[:3, 2] * np.sign(T[2, 2])
    best = min(sols, key=lambda cn: np.linalg.norm(cn[0] - T[:3, 3]))
    assert np.linalg.norm(best[0] - T[:3, 3]) < 1e-9
    assert abs(best[1] @ n_true) > 1 - 1e-9
    # the other solution projects to the same conic: its circle points lie on the image ellipse
    c, n = [cn for cn in sols if cn is not best][0]
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    th = np.linspace(0, 2 * np.pi, 50)
    P = c + NEEDLE.radius_m * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * v)
    from factors.residuals import conic_residual

    r, _ = conic_residual(T, CAM.K, NEEDLE.radius_m, CAM.project(P))
    assert np.abs(r).max() < 1e-6


def test_seed_with_fewer_particles_than_modes_and_without_evidence() -> None:
    T = se3_exp(np.r_[0.9, 0.4, 0.3, 0.002, -0.001, 0.06])
    arc = CAM.project(NEEDLE.arc_points(60) @ T[:3, :3].T + T[:3, 3])
    lik = FrameLikelihood(Observation(0, 0.0, backbone_px=arc), MeasurementModel(CAM, NEEDLE))
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 50):
        P, modes = seed_particles(lik, n, rng)
        assert P.shape == (n, 4, 4) and np.all(np.isfinite(P))
    P, _ = seed_particles(FrameLikelihood(Observation(0, 0.0), MeasurementModel(CAM, NEEDLE)), 10, rng)
    assert P.shape == (10, 4, 4) and np.all(P[:, 2, 3] > 0)
