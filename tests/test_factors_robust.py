"""Robust losses: the NumPy formulas equal GTSAM's mEstimators; per-pixel conic factors equal ConicFactor."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.conventions import matrix_to_pose3
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import ConicFactor, GraspPerpendicularFactor, conic_pixel_factors
from factors.lie import se3_exp
from factors.robust import RobustLoss

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()


@pytest.mark.parametrize("kind", ["huber", "cauchy", "gm"])
@pytest.mark.parametrize("k", [0.5, 1.0, 1.345, 3.0])
def test_loss_and_weight_equal_gtsam_mestimator(kind: str, k: float) -> None:
    rl = RobustLoss(kind, k)
    est = rl.gtsam_estimator()
    d = np.r_[0.0, 1e-9, 0.3, k * (1 - 1e-12), k, k * (1 + 1e-12), 1.7, 5.0, 37.0, 1e4]
    for x in d:
        assert abs(float(rl.loss(x)) - est.loss(x)) <= 1e-12 * max(1.0, est.loss(x))
        assert abs(float(rl.weight(x)) - est.weight(x)) <= 1e-12
    # vectorised calls equal the scalar ones and are even in d
    np.testing.assert_array_equal(rl.loss(d), [float(rl.loss(x)) for x in d])
    np.testing.assert_array_equal(rl.weight(-d), rl.weight(d))
    # w = rho'(d) / d (central differences of the loss)
    x = np.r_[0.4, 2.2, 6.0]
    h = 1e-6
    np.testing.assert_allclose((rl.loss(x + h) - rl.loss(x - h)) / (2 * h) / x, rl.weight(x), rtol=1e-7)


def test_none_is_the_gaussian_and_parse() -> None:
    rl = RobustLoss()
    d = np.r_[0.0, 2.0, 10.0]
    np.testing.assert_array_equal(rl.loss(d), 0.5 * d * d)
    np.testing.assert_array_equal(rl.weight(d), 1.0)
    base = gtsam.noiseModel.Isotropic.Sigma(2, 1.5)
    assert rl.gtsam_model(base) is base and rl.gtsam_estimator() is None and not rl.active
    assert RobustLoss.parse("huber") == RobustLoss("huber", 1.345)
    assert RobustLoss.parse("cauchy") == RobustLoss("cauchy", 1.0)
    assert RobustLoss.parse(" Cauchy:2.5 ") == RobustLoss("cauchy", 2.5)
    assert RobustLoss.parse("gm") == RobustLoss("gm", 1.0) and RobustLoss.parse("GM:3") == RobustLoss("gm", 3.0)
    assert str(RobustLoss("huber", 2.0)) == "huber:2" and str(rl) == "none"
    for bad in ["tukey:1", "huber:abc", "huber:-1", "cauchy:0", "huber:nan", None, 1.345]:
        with pytest.raises(ValueError):
            RobustLoss.parse(bad)


def test_robust_gtsam_factor_error_and_linearize_match_the_formula() -> None:
    """GTSAM's Robust(Huber) on a 1-D factor: error = rho(|e|), linearize = sqrt(w) * Gaussian linearisation."""
    T = se3_exp(np.r_[0.3, -0.2, 0.1, 0.002, -0.001, 0.045])
    z = np.r_[0.3, 0.9, 0.2]
    sigma = 0.05
    for rl in (RobustLoss("huber", 1.345), RobustLoss("cauchy", 1.0), RobustLoss("gm", 1.0)):
        plain = GraspPerpendicularFactor(0, NEEDLE.grasp_tangent, z, gtsam.noiseModel.Isotropic.Sigma(1, sigma))
        robust = GraspPerpendicularFactor(0, NEEDLE.grasp_tangent, z,
                                          rl.gtsam_model(gtsam.noiseModel.Isotropic.Sigma(1, sigma)))
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(T))
        r, J = plain.residual(T)
        d = abs(r[0]) / sigma
        assert d > rl.k  # the interesting (down-weighted) side
        np.testing.assert_allclose(robust.error(v), rl.loss(d), rtol=1e-12)
        A0, b0 = plain.linearize(v).jacobian()
        A1, b1 = robust.linearize(v).jacobian()
        sw = np.sqrt(rl.weight(d))
        np.testing.assert_allclose(A1, sw * A0, rtol=1e-12)
        np.testing.assert_allclose(b1, sw * b0, rtol=1e-12)


def test_conic_pixel_factors_equal_conic_factor_and_share_one_evaluation(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    T = se3_exp(np.r_[0.4, 0.3, -0.2, 0.003, 0.002, 0.05])
    R, t = T[:3, :3], T[:3, 3]
    pts = CAM.project(NEEDLE.arc_points(25) @ R.T + t) + rng.normal(size=(25, 2)) * 2.0
    sigma, bias = 1.3, 0.2
    whole = ConicFactor(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(25, sigma), bias=bias)
    pixels = conic_pixel_factors(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(1, sigma), bias=bias)
    assert len(pixels) == 25
    for dxi in rng.normal(size=(4, 6)) * np.r_[[0.05] * 3, [1e-3] * 3]:
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(T @ se3_exp(dxi)))
        np.testing.assert_allclose(sum(f.error(v) for f in pixels), whole.error(v), rtol=1e-12)
        A, b = whole.linearize(v).jacobian()
        Ap = np.vstack([f.linearize(v).jacobian()[0] for f in pixels])
        bp = np.concatenate([f.linearize(v).jacobian()[1] for f in pixels])
        np.testing.assert_allclose(Ap, A, rtol=1e-12, atol=1e-12 * np.abs(A).max())
        np.testing.assert_allclose(bp, b, rtol=1e-12, atol=1e-15)
    # a whole graph linearised at one pose evaluates the batched residual once
    import factors.residuals as res

    calls = []
    original = res.conic_residual

    def counting(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(res, "conic_residual", counting)
    g = gtsam.NonlinearFactorGraph()
    for f in conic_pixel_factors(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(1, sigma)):
        g.add(f)
    v = gtsam.Values()
    v.insert(0, matrix_to_pose3(T))
    g.linearize(v)
    g.error(v)
    assert len(calls) == 1
    v.update(0, matrix_to_pose3(T @ se3_exp(np.r_[0.01, 0, 0, 0, 0, 0])))
    g.error(v)
    assert len(calls) == 2
    with pytest.raises(ValueError, match="dimension"):
        conic_pixel_factors(0, CAM, NEEDLE.radius_m, pts, gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    with pytest.raises(ValueError, match="at least one"):
        conic_pixel_factors(0, CAM, NEEDLE.radius_m, np.zeros((0, 2)), gtsam.noiseModel.Isotropic.Sigma(1, 1.0))


def test_geman_mcclure_bounds_what_a_far_outlier_costs() -> None:
    """Geman-McClure redescends: its cost tends to k^2 / 2 and its pull ``rho'(d) = w d`` to 0 far out, where
    Cauchy's cost grows as log d and its pull decays only as 1/d (so a crowd of far pixels still pulls)."""
    gm, cauchy = RobustLoss("gm", 3.0), RobustLoss("cauchy", 3.0)
    d = np.r_[30.0, 300.0, 3000.0]
    assert np.all(gm.loss(d) < 0.5 * 9.0) and gm.loss(3000.0) > 0.5 * 9.0 * (1 - 1e-5)
    assert np.all(np.diff(cauchy.loss(d)) > 4.0)  # + log(10) * k^2 / 2 per decade
    pull_gm, pull_cauchy = gm.weight(d) * d, cauchy.weight(d) * d
    np.testing.assert_allclose(pull_cauchy * d, 9.0, rtol=1e-2)  # ~ k^2 / d
    np.testing.assert_allclose(pull_gm * d**3, 81.0, rtol=3e-2)  # ~ k^4 / d^3
