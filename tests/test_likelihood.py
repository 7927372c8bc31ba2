"""The batched frame likelihood equals the sum of its GTSAM factors, biases and full covariances included."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.conventions import matrix_to_pose3
from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, Switches, gauss_newton_rows
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
    # nll is gauss_newton's nll bit for bit (the seeding scores its last trial by nll alone), also where the
    # cheirality penalty is on (poses too near or behind the camera)
    near = poses.copy()
    near[:4, 2, 3] = [1e-3, 0.0, -0.02, 2e-3]
    fresh = FrameLikelihood(_obs(T, np.random.default_rng(1)), MeasurementModel(CAM, NEEDLE, NoiseConfig(), Switches()))
    np.testing.assert_array_equal(lik.nll(near), fresh.gauss_newton(near)[0])
    assert np.all(lik.cheirality(near)[0][:3] > 0)
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


@pytest.mark.parametrize("kind", ["uniform", "edge-on"])
def test_gauss_newton_rows_evaluates_only_the_changed_rows_and_equals_a_full_evaluation(kind: str) -> None:
    # The SVN safeguard's halvings re-evaluate the particles whose step they shortened (issue 10): the merged
    # result must be a full evaluation's, to round-off, and the memo must then hold it for the merged poses.
    rng = np.random.default_rng(31)
    truth = se3_exp(np.r_[0.3, -0.2, 0.1, 0.002, -0.001, 0.05])
    if kind == "edge-on":  # the needle plane through the optical centre: the conic degenerates to a line
        truth = se3_exp(np.r_[0.0, np.pi / 2 - 1e-4, 0.0, 0.0, 0.0, 0.05])
    f = FrameLikelihood(_obs(truth, rng), MeasurementModel(CAM, NEEDLE, NoiseConfig()))
    before = truth @ se3_exp(rng.normal(size=(12, 6)) * np.r_[[0.05] * 3, [1e-3] * 3])
    f.gauss_newton(before)
    rows = np.array([2, 7, 11])
    after = before.copy()
    after[rows] = before[rows] @ se3_exp(rng.normal(size=(3, 6)) * np.r_[[0.02] * 3, [3e-4] * 3])
    sizes = []
    irls = f.irls
    f.irls = lambda T, jacobian=True: (sizes.append(T.shape[0]), irls(T, jacobian))[1]
    merged = gauss_newton_rows(f, after, rows, before)
    assert sizes == [3]
    reference = FrameLikelihood(f.observation, f.model).gauss_newton(after)
    for a, b in zip(merged, reference, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    assert f._gn_memo[0] == after.tobytes()  # a later full call at the merged poses is free
    again = f.gauss_newton(after)
    assert sizes == [3] and all(np.array_equal(a, b) for a, b in zip(again, merged, strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(gauss_newton_rows(f, after, np.zeros(0, int), after), merged,
                                                     strict=True)) and sizes == [3]  # no rows: the memo answers
    # poses that differ outside rows, or a memo of other poses: a full evaluation, never a wrong merge
    other = after.copy()
    other[0] = before[0] @ se3_exp(np.r_[0.01, 0, 0, 0, 0, 0])
    sizes.clear()
    full = gauss_newton_rows(f, other, rows, after)
    assert sizes == [12]
    for a, b in zip(full, FrameLikelihood(f.observation, f.model).gauss_newton(other), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
