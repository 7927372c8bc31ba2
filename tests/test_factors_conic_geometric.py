"""The exact geometric distance of backbone pixels to the image ellipse (factors.residuals.conic_geometric_residual)."""

from __future__ import annotations

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from factors.residuals import conic_geometric_residual, conic_residual
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, Switches
from pinpoint_fg.noise import NoiseConfig, parse_robust_spec
from pinpoint_fg.observation import Observation
from tests.likelihood_checks import assert_equals_its_gtsam_factors

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()
DENSE = np.linspace(0.0, 2.0 * np.pi, 400_000, endpoint=False)


def _pose(view_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A needle 6-9 cm in front of the camera whose plane is ``view_deg`` from containing the viewing ray."""
    T = se3_exp(np.r_[np.deg2rad(90.0 - view_deg), 0.0, 0.0, 0.0, 0.0, 0.0])
    T = se3_exp(np.r_[0.0, 0.0, rng.uniform(-np.pi, np.pi), 0.0, 0.0, 0.0]) @ T
    T[:3, 3] = np.r_[rng.normal(size=2) * 0.004, rng.uniform(0.06, 0.09)]
    return T


def _brute_force(T: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Distance (px) from each pixel to 400 000 projected points of the circle (spacing well under 0.01 px)."""
    P = np.c_[NEEDLE.radius_m * np.cos(DENSE), NEEDLE.radius_m * np.sin(DENSE), np.zeros_like(DENSE)]
    q = CAM.project(P @ T[:3, :3].T + T[:3, 3])
    return np.array([np.sqrt(((q - p) ** 2).sum(axis=1)).min() for p in px])


@pytest.mark.parametrize("view_deg", [60.0, 20.0, 5.0, 1.0, 0.3])
def test_geometric_distance_equals_brute_force(view_deg: float) -> None:
    """Pixels along the arc with 2 px noise, and pixels scattered up to 15 px inside and outside: |r| is the
    distance to the nearest point of the projected circle, to 1e-3 px (the reference's own sampling limit)."""
    rng = np.random.default_rng(int(view_deg * 10))
    T = _pose(view_deg, rng)
    arc = CAM.project(NEEDLE.arc_points(60) @ T[:3, :3].T + T[:3, 3])
    px = np.concatenate([arc + rng.normal(size=arc.shape) * 2.0, arc + rng.uniform(-15, 15, size=arc.shape)])
    r, _ = conic_geometric_residual(T, CAM.K, NEEDLE.radius_m, px)
    np.testing.assert_allclose(np.abs(r[0]), _brute_force(T, px), atol=1e-3)
    # the sign is the Sampson distance's (the side of the conic)
    s, _ = conic_residual(T, CAM.K, NEEDLE.radius_m, px)
    assert np.array_equal(np.sign(r[0][np.abs(r[0]) > 1e-6]), np.sign(s[0][np.abs(r[0]) > 1e-6]))


def test_sampson_overstates_a_thin_ellipse_and_agrees_near_a_round_one() -> None:
    """Why it exists. Seen within a degree of edge-on, pixels scattered within 3 px (per axis) of the projected
    circle are at most ~4 px from the thin ellipse, and Sampson reads over 4 times that (near its pointed ends);
    on a round ellipse, within 0.05 px of it, the two agree."""
    rng = np.random.default_rng(3)
    for view_deg in (1.0, 0.5):
        T = _pose(view_deg, rng)
        ring = NEEDLE.point(np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False))
        px = CAM.project(ring @ T[:3, :3].T + T[:3, 3]) + rng.uniform(-3, 3, size=(400, 2))
        r, _ = conic_geometric_residual(T, CAM.K, NEEDLE.radius_m, px)
        s, _ = conic_residual(T, CAM.K, NEEDLE.radius_m, px)
        np.testing.assert_allclose(np.abs(r[0]), _brute_force(T, px), atol=1e-3)
        assert np.abs(r).max() < 4.3 and np.abs(s).max() > 4.0 * np.abs(r).max()
    T = _pose(60.0, rng)
    arc = CAM.project(NEEDLE.arc_points(80) @ T[:3, :3].T + T[:3, 3])
    px = arc + rng.normal(size=arc.shape) * 0.05
    r, _ = conic_geometric_residual(T, CAM.K, NEEDLE.radius_m, px)
    s, _ = conic_residual(T, CAM.K, NEEDLE.radius_m, px)
    np.testing.assert_allclose(r, s, atol=1e-3)


def test_batches_value_only_and_the_fallback_rows() -> None:
    """Rows of a batch equal single evaluations; ``jacobian=False`` gives the same r; a pose whose circle crosses
    the camera's principal plane (its image conic a hyperbola) falls back to the Sampson distance, bit for bit."""
    rng = np.random.default_rng(4)
    T = _pose(30.0, rng)
    px = CAM.project(NEEDLE.arc_points(40) @ T[:3, :3].T + T[:3, 3]) + rng.normal(size=(40, 2))
    crossing = T.copy()
    crossing[2, 3] = 0.3 * NEEDLE.radius_m  # the circle's plane is steep: part of it lies behind the camera
    crossing[:3, :3] = se3_exp(np.r_[np.pi / 2 - 0.2, 0, 0, 0, 0, 0])[:3, :3]
    batch = np.stack([T, crossing, T @ se3_exp(rng.normal(size=6) * 0.01)])
    r, J = conic_geometric_residual(batch, CAM.K, NEEDLE.radius_m, px)
    r0, _ = conic_geometric_residual(batch, CAM.K, NEEDLE.radius_m, px, jacobian=False)
    np.testing.assert_array_equal(r, r0)
    for i in (0, 2):
        ri, Ji = conic_geometric_residual(batch[i], CAM.K, NEEDLE.radius_m, px)
        np.testing.assert_allclose(ri[0], r[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(Ji[0], J[i], rtol=1e-10, atol=1e-10 * np.abs(J[i]).max())
    s, Js = conic_residual(crossing, CAM.K, NEEDLE.radius_m, px)
    np.testing.assert_array_equal(r[1], s[0])
    np.testing.assert_array_equal(J[1], Js[0])
    assert np.isfinite(r).all() and np.isfinite(J).all()


@pytest.mark.parametrize("robust", [True, False])
def test_likelihood_with_the_geometric_distance_equals_its_gtsam_factors(robust: bool) -> None:
    rng = np.random.default_rng(5)
    T = _pose(3.0, rng)
    px = CAM.project(NEEDLE.arc_points(50) @ T[:3, :3].T + T[:3, 3]) + rng.normal(size=(50, 2))
    obs = Observation(0, 0.0, tip_px=None, tail_px=None, backbone_px=px, cam_T_grasper=None)
    noise = NoiseConfig() if robust else NoiseConfig().with_robust(parse_robust_spec("none"))
    lik = FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE, noise, Switches(), conic_distance="geometric"))
    poses = T @ se3_exp(rng.normal(size=(4, 6)) * np.r_[[0.01] * 3, [3e-4] * 3])
    factors = assert_equals_its_gtsam_factors(lik, poses)
    assert len(factors) == (50 if robust else 1)
    with pytest.raises(ValueError, match="conic_distance"):
        MeasurementModel(CAM, NEEDLE, conic_distance="euclid")
