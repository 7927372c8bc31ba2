"""The along-arc Ornstein-Uhlenbeck whitening of the backbone residuals (factors/conic_correlation.py)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.conic_correlation import MIN_STEP_PX, ArcWhitening, arc_order
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import ConicFactor, conic_pixel_factors
from factors.lie import se3_exp
from factors.residuals import conic_residual
from factors.robust import NO_LOSS
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observation import Observation
from tests.likelihood_checks import assert_equals_its_gtsam_factors

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()


def _view(kind: str, rng: np.random.Generator) -> np.ndarray:
    """A needle pose 5-10 cm in front of the camera: tilted, face-on, or within a few degrees of edge-on."""
    tilt = {"face_on": 0.1, "tilted": 0.8, "edge_on": np.pi / 2 - rng.uniform(0.02, 0.08)}[kind]
    axis = np.r_[np.cos(rng.uniform(0, 2 * np.pi)), np.sin(rng.uniform(0, 2 * np.pi)), 0.0]
    T = se3_exp(np.r_[axis / np.linalg.norm(axis) * tilt, 0, 0, 0])
    T = se3_exp(np.r_[0, 0, rng.uniform(-np.pi, np.pi), 0, 0, 0]) @ T
    T[:3, 3] = np.r_[rng.normal(size=2) * 0.005, rng.uniform(0.05, 0.1)]
    return T


def _arc_pixels(T: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` pixels along the needle's 3/8 arc, in arc order (and their arc angles)."""
    angles = np.linspace(0.0, 0.75 * np.pi, count)
    return CAM.project(NEEDLE.point(angles) @ T[:3, :3].T + T[:3, 3]), angles


def _path(px: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(px, axis=0), axis=1).sum())


@pytest.mark.parametrize("kind", ["face_on", "tilted", "edge_on"])
def test_arc_order_recovers_the_arc_from_shuffled_pixels(kind: str) -> None:
    """Random order in, the arc's order out (either direction), for ten views of each kind. Within a few degrees
    of edge-on a 3/8 arc folds back on itself in the image, its two branches closer than the pixel noise, and no
    order from the pixels alone can tell them apart: there the order must be about as short a path as the arc's own
    (consecutive pixels are neighbours in the image, which is what the correlation model needs; within 10 %: the
    0.3 px noise lets other orders be a few per cent shorter or longer, while zig-zagging between the branches, as
    the principal axis and the ellipse angle both did on these views, is 30 % longer)."""
    rng = np.random.default_rng({"face_on": 1, "tilted": 2, "edge_on": 3}[kind])
    for _ in range(10):
        px, _ = _arc_pixels(_view(kind, rng), 60)
        px = px + rng.normal(size=px.shape) * 0.3
        shuffled = rng.permutation(60)
        got = shuffled[arc_order(px[shuffled])]  # back to indices along the arc
        if kind == "edge_on":
            assert _path(px[got]) <= 1.1 * _path(px)
        else:
            assert np.array_equal(got, np.arange(60)) or np.array_equal(got, np.arange(60)[::-1]), got


def test_arc_order_of_raster_order_pixels_and_small_sets() -> None:
    rng = np.random.default_rng(4)
    px, _ = _arc_pixels(_view("tilted", rng), 80)
    raster = np.lexsort((px[:, 0], np.round(px[:, 1])))  # rows, then columns: what a mask skeleton gives
    got = raster[arc_order(px[raster])]
    assert np.array_equal(got, np.arange(80)) or np.array_equal(got, np.arange(80)[::-1])
    assert np.array_equal(arc_order(np.zeros((0, 2))), np.zeros(0, dtype=int))
    assert np.array_equal(arc_order(np.array([[3.0, 4.0], [1.0, 1.0]])), [0, 1])
    assert sorted(arc_order(np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 0.0], [3.0, 0.0]]))) == [0, 1, 2, 3]
    for bad in (np.array([[np.nan, 1.0]] * 5), np.zeros((4, 3))):
        with pytest.raises(ValueError, match="points_px"):
            arc_order(bad)


@pytest.mark.parametrize("ell", [3.0, 20.0, 80.0])
def test_innovations_are_the_exact_whitening_of_the_ou_covariance(ell: float) -> None:
    """``e = chol(Sigma)^-1 r`` in arc order, ``Sigma_ij = exp(-|s_i - s_j| / ell)``, uneven steps and a gap."""
    rng = np.random.default_rng(5)
    px, _ = _arc_pixels(_view("tilted", rng), 50)
    px = np.delete(px, np.arange(20, 30), axis=0) + rng.normal(size=(40, 2)) * 0.2  # an occluded stretch
    w = ArcWhitening.from_points(px, ell)
    s = w.arc_length_px
    q = px[w.order]
    np.testing.assert_allclose(np.diff(s), np.maximum(np.linalg.norm(np.diff(q, axis=0), axis=1), MIN_STEP_PX),
                               rtol=1e-12)
    L = np.linalg.cholesky(np.exp(-np.abs(s[:, None] - s[None, :]) / ell))
    r = rng.normal(size=(3, 40))
    e, _ = w.apply(r)
    np.testing.assert_allclose(e, np.linalg.solve(L, r[:, w.order].T).T, rtol=1e-9, atol=1e-9)


def test_innovations_of_an_ou_sample_are_white() -> None:
    """Residuals drawn from the model give innovations of unit variance and no lag-1 correlation, where the
    residuals themselves are strongly correlated (seeded; 400 frames of 120 pixels)."""
    rng = np.random.default_rng(6)
    px, _ = _arc_pixels(_view("face_on", rng), 120)
    w = ArcWhitening.from_points(px, 20.0)
    s = w.arc_length_px
    cov = np.exp(-np.abs(s[:, None] - s[None, :]) / 20.0)
    x = rng.multivariate_normal(np.zeros(120), cov, size=400)  # in arc order
    r = np.empty_like(x)
    r[:, w.order] = x  # back to the pixels' own order
    e, _ = w.apply(r)

    def lag1(a: np.ndarray) -> float:
        return float(np.mean(a[:, 1:] * a[:, :-1]) / np.mean(a * a))

    assert lag1(x) > 0.8
    assert abs(lag1(e)) < 0.02
    assert abs(np.var(e) - 1.0) < 0.02


def test_a_vanishing_correlation_length_gives_the_independent_residuals_and_bad_lengths_are_refused() -> None:
    rng = np.random.default_rng(7)
    px, _ = _arc_pixels(_view("tilted", rng), 30)
    w = ArcWhitening.from_points(px, 1e-3)
    r, J = rng.normal(size=(2, 30)), rng.normal(size=(2, 30, 6))
    e, Je = w.apply(r, J)
    np.testing.assert_array_equal(e, r[:, w.order])
    np.testing.assert_array_equal(Je, J[:, w.order])
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="correlation length"):
            ArcWhitening.from_points(px, bad)


def test_duplicate_pixels_stay_finite() -> None:
    px = np.repeat(np.array([[100.0, 200.0], [101.0, 200.0], [102.0, 201.0]]), 2, axis=0)
    w = ArcWhitening.from_points(px, 20.0)
    e, _ = w.apply(np.arange(6.0)[None])
    assert np.isfinite(e).all() and np.all(w.a < 1.0)


def _obs(T: np.ndarray, rng: np.random.Generator) -> Observation:
    px, _ = _arc_pixels(T, 60)
    G = np.eye(4)
    G[:3, 3] = T[:3, :3] @ NEEDLE.grasp_m + T[:3, 3]
    return Observation(0, 0.0, tip_px=CAM.project(T[:3, :3] @ NEEDLE.tip_m + T[:3, 3]) + rng.normal(size=2),
                       tail_px=None, backbone_px=px[rng.permutation(60)] + rng.normal(size=(60, 2)),
                       cam_T_grasper=G)


@pytest.mark.parametrize("robust", [True, False])
def test_likelihood_with_correlation_equals_its_gtsam_factors(robust: bool) -> None:
    """The batched path (value, gradient, GN information) equals the GTSAM factors built from the same frame,
    with the default per-pixel Cauchy loss (one factor per innovation) and without (one ConicFactor)."""
    rng = np.random.default_rng(8)
    T = _view("tilted", rng)
    noise = NoiseConfig(robust={} if robust else {"conic": NO_LOSS}, conic_correlation_px=15.0)
    lik = FrameLikelihood(_obs(T, rng), MeasurementModel(CAM, NEEDLE, noise, Switches()))
    assert lik.arc_whitening is not None
    poses = T @ se3_exp(rng.normal(size=(5, 6)) * np.r_[[0.03] * 3, [5e-4] * 3])
    factors = assert_equals_its_gtsam_factors(lik, poses)
    assert len(factors) == (1 + 60 + 2 if robust else 1 + 1 + 2)


def test_correlation_discounts_a_smooth_offset_but_not_a_kink() -> None:
    """What the model is for: a smooth along-arc displacement of the mask (every pixel 1 px off) costs far less
    than under independence, while the same pixels with alternating signs cost about as much."""
    rng = np.random.default_rng(9)
    T = _view("face_on", rng)
    px, _ = _arc_pixels(T, 120)
    r_offset = np.ones((1, 120))
    r_kink = np.where(np.arange(120) % 2 == 0, 1.0, -1.0)[None]
    w = ArcWhitening.from_points(px, 20.0)
    cost = {name: {"independent": 0.5 * float((r * r).sum()), "correlated": 0.5 * float((w.apply(r)[0] ** 2).sum())}
            for name, r in (("offset", r_offset), ("kink", r_kink))}
    assert cost["offset"]["correlated"] < 0.1 * cost["offset"]["independent"]
    assert cost["kink"]["correlated"] > 0.9 * cost["kink"]["independent"]
    assert NoiseConfig().conic_correlation_px == 0.0  # the default stays the paper's independent pixels


def test_factor_whitening_must_match_the_pixels() -> None:
    rng = np.random.default_rng(10)
    px, _ = _arc_pixels(_view("tilted", rng), 20)
    other = ArcWhitening.from_points(px[:10], 10.0)
    noise = gtsam.noiseModel.Isotropic.Sigma(20, 1.0)
    with pytest.raises(ValueError, match="10 pixels"):
        ConicFactor(0, CAM, NEEDLE.radius_m, px, noise, whitening=other)
    with pytest.raises(ValueError, match="ArcWhitening"):
        conic_pixel_factors(0, CAM, NEEDLE.radius_m, px, gtsam.noiseModel.Isotropic.Sigma(1, 1.0), whitening="x")
    # the factor's residual is the whitening of the plain conic residual
    T = _view("tilted", rng)
    w = ArcWhitening.from_points(px, 10.0)
    r, J = ConicFactor(0, CAM, NEEDLE.radius_m, px, noise, bias=0.2, whitening=w).residual(T)
    r0, J0 = conic_residual(T[None], CAM.K, NEEDLE.radius_m, px)
    e, Je = w.apply(r0 - 0.2, J0)
    np.testing.assert_array_equal(r, e[0])
    np.testing.assert_array_equal(J, Je[0])
