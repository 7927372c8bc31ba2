"""pinpoint_fg.kinematic_bias: the Kalman filter's sequence likelihood equals the joint Gaussian's, exactly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from pinpoint_fg.kinematic_bias import BiasFilter, BiasModel, gaussian_nll, sequence_nll


def _spd(rng: np.random.Generator, d: int) -> np.ndarray:
    A = rng.normal(size=(d, d))
    return A @ A.T + d * np.eye(d)


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize(("tau_s", "white_share"), [(5.0, 0.01), (0.05, 0.3), (1.0, 1.0)])
def test_sequence_nll_is_the_joint_gaussian_of_the_ou_bias_plus_white_noise(d: int, tau_s: float,
                                                                          white_share: float) -> None:
    """Stacked over K frames at uneven times, ``r`` is Gaussian with ``Cov(r_i, r_j) = exp(-|t_i - t_j| / tau)
    (1 - f) C + [i = j] f C``; the filter's prediction-error sum equals its NLL for every sequence."""
    rng = np.random.default_rng(d)
    K, N = 7, 5
    C = _spd(rng, d) * 1e-6
    t = np.cumsum(rng.uniform(0.0, 0.5, size=K))
    model = BiasModel(tau_s, white_share)
    lag = np.exp(-np.abs(t[:, None] - t[None, :]) / tau_s)
    joint = np.kron(lag, (1.0 - white_share) * C) + np.kron(np.eye(K), white_share * C)
    r = rng.multivariate_normal(np.zeros(K * d), joint, size=N).reshape(N, K, d).transpose(1, 0, 2)  # (K, N, d)
    expected = -multivariate_normal(np.zeros(K * d), joint).logpdf(r.transpose(1, 0, 2).reshape(N, K * d))
    np.testing.assert_allclose(sequence_nll(r, t, C, model), expected, rtol=1e-10)


def test_all_white_is_the_white_model() -> None:
    """``white_share = 1``: no bias, ``S = C``, the same NLL as independent frames (to round-off)."""
    rng = np.random.default_rng(3)
    C = _spd(rng, 3)
    r = rng.normal(size=(6, 4, 3))
    t = np.arange(6) / 30.0
    np.testing.assert_allclose(sequence_nll(r, t, C, BiasModel(5.0, 1.0)), sequence_nll(r, t, C, None), rtol=1e-12)
    white = sum(-multivariate_normal(np.zeros(3), C).logpdf(rk) for rk in r)
    np.testing.assert_allclose(sequence_nll(r, t, C, None), white, rtol=1e-12)


def test_a_persistent_offset_is_paid_once_under_the_bias_model_and_on_every_frame_under_the_white_one() -> None:
    """The diagnosis in numbers: a constant 2-sigma offset over 150 frames at 30 Hz costs the white model 2 nats
    a frame; the bias model (tau 5 s, 1 % white) learns it, and the cost after the first frames is the filter's
    near-perfect predictions."""
    C = np.eye(1)
    t = np.arange(150) / 30.0
    r = np.full((150, 1), 2.0)
    model = BiasModel(5.0, 0.01)
    white = float(sequence_nll(r, t, C, None)[0] - sequence_nll(np.zeros_like(r), t, C, None)[0])
    bias = float(sequence_nll(r, t, C, model)[0] - sequence_nll(np.zeros_like(r), t, C, model)[0])
    assert white == pytest.approx(150 * 2.0)
    assert 0.0 < bias < 5.0


def test_filter_rows_update_and_predict() -> None:
    """One-dimensional update against the textbook gain; rows are copies with the shared covariance; predict decays
    the mean by ``a`` and moves the covariance toward the stationary one."""
    model = BiasModel(2.0, 0.25)
    C = np.array([[4.0]])
    f = BiasFilter.stationary(3, C, model)
    np.testing.assert_allclose(f.cov, [[3.0]])
    r = np.array([[1.0], [2.0], [-1.0]])
    g = f.update(r, C, model)
    gain = 3.0 / (3.0 + 1.0)
    np.testing.assert_allclose(g.mean, gain * r)
    np.testing.assert_allclose(g.cov, [[3.0 - gain * 3.0]])
    sub = g.rows([2, 0])
    np.testing.assert_array_equal(sub.mean, g.mean[[2, 0]])
    sub.mean[0] = 9.0
    assert g.mean[2, 0] != 9.0
    a = np.exp(-0.5 / 2.0)
    p = g.predict(0.5, C, model)
    np.testing.assert_allclose(p.mean, a * g.mean)
    np.testing.assert_allclose(p.cov, a * a * g.cov + (1 - a * a) * 3.0)
    np.testing.assert_allclose(gaussian_nll(np.zeros((2, 1)), C), 0.5 * np.log(2 * np.pi * 4.0))


@pytest.mark.parametrize(("tau_s", "white_share"), [(0.0, 0.5), (-1.0, 0.5), (float("nan"), 0.5), (float("inf"), 0.5),
                                                    (1.0, 0.0), (1.0, 1.5), (1.0, float("nan"))])
def test_bias_model_refuses_bad_settings(tau_s: float, white_share: float) -> None:
    with pytest.raises(ValueError):
        BiasModel(tau_s, white_share)


@pytest.mark.parametrize("dt_s", [-0.1, float("nan"), float("inf")])
def test_decay_refuses_bad_time_steps(dt_s: float) -> None:
    with pytest.raises(ValueError):
        BiasModel().decay(dt_s)
