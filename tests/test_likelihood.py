"""The batched frame likelihood equals the sum of its GTSAM factors, biases and full covariances included."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.conventions import matrix_to_pose3
from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, Switches
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.observation import Observation

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()


def _obs(T: np.ndarray, rng: np.random.Generator) -> Observation:
    R, t = T[:3, :3], T[:3, 3]
    G = np.eye(4)
    G[:3, 3] = R @ NEEDLE.grasp_m + t + rng.normal(size=3) * 3e-4
    G[:3, :3] = se3_exp(np.r_[rng.normal(size=3), 0, 0, 0])[:3, :3]
    return Observation(0, 0.0, tip_px=CAM.project(R @ NEEDLE.tip_m + t) + rng.normal(size=2),
                       tail_px=CAM.project(R @ NEEDLE.tail_m + t) + rng.normal(size=2),
                       backbone_px=CAM.project(NEEDLE.arc_points(30) @ R.T + t) + rng.normal(size=(30, 2)),
                       cam_T_grasper=G)


def _biased_noise() -> NoiseConfig:
    """Noise with biases, a correlated grasp-position covariance and a scalar conic noise."""
    cov3 = np.array([[2.0, 0.3, 0.1], [0.3, 1.5, 0.0], [0.1, 0.0, 4.0]]) * 1e-7
    return NoiseConfig({
        "tip": ResidualNoise(np.r_[0.2, -0.1], np.array([[1.0, 0.2], [0.2, 1.1]])),
        "conic": ResidualNoise(np.r_[0.15], np.array([[1.5]])),
        "grasp_position": ResidualNoise(np.r_[1e-4, 0.0, -2e-4], cov3),
        "grasp_perpendicular": ResidualNoise(np.r_[0.02], np.array([[0.02]])),
    })


def test_likelihood_equals_gtsam_factor_errors_with_biases() -> None:
    rng = np.random.default_rng(0)
    noise = _biased_noise()
    T = se3_exp(np.r_[0.3, -0.2, 0.1, 0.002, -0.001, 0.045])
    lik = FrameLikelihood(_obs(T, rng), MeasurementModel(CAM, NEEDLE, noise, Switches()))
    assert lik.term_names == ("tip", "tail", "conic", "grasp_position", "grasp_perpendicular")
    poses = T @ se3_exp(rng.normal(size=(10, 6)) * np.r_[[0.05] * 3, [5e-4] * 3])
    nll = lik.nll(poses)
    for i in range(10):
        g = gtsam.NonlinearFactorGraph()
        for f in lik.gtsam_factors(0):
            g.add(f)
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(poses[i]))
        np.testing.assert_allclose(g.error(v), nll[i], rtol=1e-10)
    # and the value-only path equals the Jacobian path
    e1, _ = lik.whitened(poses, jacobian=False)
    e2, _ = lik.whitened(poses, jacobian=True)
    np.testing.assert_array_equal(e1, e2)


def test_switches_from_disabled_round_trip() -> None:
    for names in [(), ("dense",), ("sparse",), ("tip",), ("grasp-position", "grasp-perpendicular", "motion")]:
        assert Switches.from_disabled(names).disabled() == tuple(names)
    assert not Switches.from_disabled(("sparse",)).tip and not Switches.from_disabled(("sparse",)).tail


def test_term_losses_are_the_parts_of_the_robust_loss_and_each_matches_its_gtsam_factor() -> None:
    """Summed in order from zero, the terms give ``irls``'s loss bit for bit; each equals its own GTSAM factor's
    error (the default robust losses on, so the parts are robust ones)."""
    rng = np.random.default_rng(1)
    T = se3_exp(np.r_[-0.4, 0.3, 0.2, -0.003, 0.002, 0.05])
    lik = FrameLikelihood(_obs(T, rng), MeasurementModel(CAM, NEEDLE, NoiseConfig(), Switches()))
    poses = T @ se3_exp(rng.normal(size=(8, 6)) * np.r_[[0.2] * 3, [2e-3] * 3])
    parts = lik.term_losses(poses)
    assert tuple(parts) == lik.term_names
    total = np.zeros(8)
    for v in parts.values():
        assert v.shape == (8,)
        total += v
    np.testing.assert_array_equal(total, lik.irls(poses, jacobian=False)[0])
    # the likelihood-only path (no Jacobian built for any term) gives the loss and rows of the full one, bitwise
    loss, e, none = lik.irls(poses, jacobian=False)
    full = lik.irls(poses)
    assert none is None
    np.testing.assert_array_equal(loss, full[0])
    np.testing.assert_array_equal(e, full[1])
    np.testing.assert_array_equal(lik.nll(poses), full[0] + lik.cheirality(poses)[0])
    fs = lik.gtsam_factors(0)  # tip, tail, one robust factor per conic pixel, grasp position, perpendicularity
    assert len(fs) == 4 + 30
    groups = {"tip": fs[:1], "tail": fs[1:2], "conic": fs[2:-2], "grasp_position": fs[-2:-1],
              "grasp_perpendicular": fs[-1:]}
    for i in range(8):
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(poses[i]))
        for name, group in groups.items():
            np.testing.assert_allclose(sum(f.error(v) for f in group), parts[name][i], rtol=1e-10, err_msg=name)


def test_residuals_are_what_whitened_multiplies_by_each_terms_square_root_information() -> None:
    """``residuals`` (r - mean, unwhitened, (N, d) per term) times each term's ``W`` is ``whitened``, to round-off;
    with biases, a correlated covariance and a scalar conic noise."""
    rng = np.random.default_rng(2)
    noise = _biased_noise()
    T = se3_exp(np.r_[0.3, -0.2, 0.1, 0.002, -0.001, 0.045])
    lik = FrameLikelihood(_obs(T, rng), MeasurementModel(CAM, NEEDLE, noise, Switches()))
    poses = T @ se3_exp(rng.normal(size=(6, 6)) * np.r_[[0.05] * 3, [5e-4] * 3])
    r = lik.residuals(poses)
    assert tuple(r) == lik.term_names
    assert {k: v.shape for k, v in r.items()} == {"tip": (6, 2), "tail": (6, 2), "conic": (6, 30),
                                                   "grasp_position": (6, 3), "grasp_perpendicular": (6, 1)}
    parts = []
    for name, v in r.items():
        W = noise[name].sqrt_information
        parts.append(v * W[0, 0] if name == "conic" else v @ W.T)
    np.testing.assert_allclose(np.concatenate(parts, axis=1), lik.whitened(poses, jacobian=False)[0],
                               rtol=1e-12, atol=1e-12)
