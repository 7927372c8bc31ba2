"""pinpoint_fg.kinematic_bias: the Kalman filter's sequence likelihood equals the joint Gaussian's, exactly; the
evidence book's corrections sum to the bias model's sequence likelihood less the white one's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from factors.robust import NO_LOSS, RobustLoss
from pinpoint_fg.kinematic_bias import (
    KINEMATIC_TERMS,
    BiasBook,
    BiasFilter,
    BiasModel,
    gaussian_nll,
    kinematic_correction,
    sequence_nll,
)


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


@pytest.mark.parametrize("terms", [(), ("grasp_position", "grasp_position"), ("tip",)])
def test_bias_model_refuses_bad_terms(terms: tuple[str, ...]) -> None:
    if not terms:
        assert BiasModel(terms=[]).terms == ()  # a list is kept as a tuple; no term: the white model
        return
    with pytest.raises(ValueError):
        BiasModel(terms=terms)


# ------------------------------------------------------------------------------------- the evidence book


def _sequence(rng: np.random.Generator, K: int, N: int, d: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    C = _spd(rng, d) * 1e-6
    t = np.cumsum(rng.uniform(0.01, 0.2, size=K))
    r = rng.multivariate_normal(np.zeros(d), C, size=(K, N))
    return C, t, r


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize(("tau_s", "white_share"), [(5.0, 0.01), (0.3, 0.3), (2.0, 1.0)])
def test_book_corrections_sum_to_the_bias_sequence_nll_less_the_white_one(d: int, tau_s: float,
                                                                          white_share: float) -> None:
    """With exact poses (no pose uncertainty) and Gaussian losses, a run of corrections turns the white count of a
    residual sequence into :func:`sequence_nll`'s bias-model likelihood (itself pinned to the joint Gaussian above)."""
    rng = np.random.default_rng(10 * d)
    K, N = 9, 4
    C, t, r = _sequence(rng, K, N, d)
    model = BiasModel(tau_s, white_share, terms=("grasp_position",))
    book = BiasBook.start(model)
    J, no_pose = np.zeros((N, d, 6)), np.zeros((N, 6, 6))
    total = sum(book.correct({"grasp_position": (r[k], J, C, NO_LOSS)}, no_pose, t[k]) for k in range(K))
    expected = sequence_nll(r, t, C, model) - sequence_nll(r, t, C, None)
    np.testing.assert_allclose(total, expected, rtol=1e-9, atol=1e-9)


def test_book_scores_are_predictive_of_the_uncertain_pose() -> None:
    """One frame, a pose with covariance Sigma: the correction is the NLL of ``r`` under ``N(b, S + J Sigma J^T)``
    less that under ``N(0, C + J Sigma J^T)`` (scipy's densities), per hypothesis; the update is the Kalman update
    with measurement noise ``f C + J Sigma J^T``."""
    rng = np.random.default_rng(7)
    N, d = 3, 3
    C = _spd(rng, d) * 1e-6
    model = BiasModel(5.0, 0.2, terms=("grasp_position",))
    book = BiasBook.start(model)
    book.correct({"grasp_position": (rng.normal(size=(N, d)) * 1e-3, np.zeros((N, d, 6)), C, NO_LOSS)},
                 np.zeros((N, 6, 6)), 0.0)
    b, P = book.means["grasp_position"].copy(), book.covs["grasp_position"].copy()
    a = np.exp(-(1 / 30) / 5.0)
    b, P = a * b, a * a * P + (1 - a * a) * 0.8 * C
    r = rng.normal(size=(N, d)) * 1e-3
    J = rng.normal(size=(N, d, 6)) * 1e-2
    Sigma = np.stack([_spd(rng, 6) * 1e-4 for _ in range(N)])
    out = book.correct({"grasp_position": (r, J, C, NO_LOSS)}, Sigma, 1 / 30)
    for i in range(N):
        A = J[i] @ Sigma[i] @ J[i].T
        bias = -multivariate_normal(b[i], P[i] + 0.2 * C + A).logpdf(r[i])
        white = -multivariate_normal(np.zeros(d), C + A).logpdf(r[i])
        assert out[i] == pytest.approx(bias - white, rel=1e-9, abs=1e-9)
        S = P[i] + 0.2 * C + A
        gain = P[i] @ np.linalg.inv(S)
        np.testing.assert_allclose(book.means["grasp_position"][i], b[i] + gain @ (r[i] - b[i]), rtol=1e-9)
        np.testing.assert_allclose(book.covs["grasp_position"][i], P[i] - gain @ P[i], rtol=1e-9, atol=1e-22)


def test_all_white_book_corrects_nothing_bit_for_bit() -> None:
    """``white_share = 1``: no bias, the two scores are the same numbers, every correction exactly 0 (robust loss and
    pose uncertainty included): a tracker with this model is the white one, bit for bit."""
    rng = np.random.default_rng(4)
    N = 5
    book = BiasBook.start(BiasModel(5.0, 1.0))
    for k in range(4):
        terms = {"grasp_position": (rng.normal(size=(N, 3)), rng.normal(size=(N, 3, 6)), _spd(rng, 3), NO_LOSS),
                 "grasp_perpendicular": (rng.normal(size=(N, 1)) * 5, rng.normal(size=(N, 1, 6)), np.eye(1),
                                         RobustLoss("huber", 1.345))}
        out = book.correct(terms, np.stack([_spd(rng, 6) for _ in range(N)]), k / 30)
        assert np.all(out == 0.0)


def test_book_rows_follow_their_hypotheses() -> None:
    """``rows`` copies, ``set_rows`` overwrites: what a window's subset, resampling and copies use."""
    rng = np.random.default_rng(5)
    book = BiasBook.start(BiasModel(5.0, 0.3))
    C = _spd(rng, 3) * 1e-6
    book.correct({"grasp_position": (rng.normal(size=(4, 3)) * 1e-3, np.zeros((4, 3, 6)), C, NO_LOSS)},
                 np.zeros((4, 6, 6)), 0.0)
    sub = book.rows([3, 1])
    np.testing.assert_array_equal(sub.means["grasp_position"], book.means["grasp_position"][[3, 1]])
    sub.means["grasp_position"][0] = 1.0
    assert not np.any(book.means["grasp_position"] == 1.0)
    book.set_rows([0], sub, [0])
    np.testing.assert_array_equal(book.means["grasp_position"][0], 1.0)
    np.testing.assert_array_equal(book.covs["grasp_position"][0], book.covs["grasp_position"][3])


def _simulated(tmp_path, n: int):
    from pinpoint_fg.io.recording import read_recording
    from pinpoint_fg.observe import observe_frame
    from pinpoint_fg.sim.scenarios import simulate

    rec = read_recording(simulate("drive", n, seed=2, out=tmp_path / "run"))
    return rec, [observe_frame(rec, f) for f in rec.frames]


def test_kinematic_correction_takes_the_kinematic_terms_out_of_the_information(tmp_path) -> None:
    """The cavity: a frame with only kinematic terms, its Gauss-Newton information less their shares is zero
    (``kinematic_terms``' shares are :meth:`FrameLikelihood.gauss_newton`'s, robust weights included)."""
    from dataclasses import replace

    from pinpoint_fg.likelihood import FrameLikelihood
    from pinpoint_fg.track import tracker_config

    rec, obs = _simulated(tmp_path, 3)
    o = replace(obs[1], tip_px=None, tail_px=None, backbone_px=None)
    lik = FrameLikelihood(o, tracker_config(rec, "svn").model)
    T = rec.frames[1].cam_T_needle_gt[None] @ np.stack([np.eye(4), np.eye(4)])
    T[1, :3, 3] += [1e-3, 0.0, 0.0]
    _, _, H = lik.gauss_newton(T)
    parts = lik.kinematic_terms(T, KINEMATIC_TERMS)
    assert set(parts) == set(KINEMATIC_TERMS)
    np.testing.assert_allclose(sum(p[4] for p in parts.values()), H, rtol=1e-12, atol=1e-9)
    book = BiasBook.start(BiasModel(5.0, 0.3))
    assert kinematic_correction(book, lik, T, H + np.eye(6)).shape == (2,)
    assert kinematic_correction(book, FrameLikelihood(replace(o, cam_T_grasper=None), lik.model), T, H) is None
    assert book.t_s == o.t_s  # the filters were brought to the frame's time all the same


def test_svn_with_an_all_white_bias_model_tracks_bit_for_bit_as_without(tmp_path) -> None:
    """The evidence correction is wired through the window (marginalisation, subsets, copies, shared books): with
    ``white_share = 1`` it adds exact zeros, and SVN's estimates equal the default's bit for bit; with a bias it
    changes the evidence, and every hypothesis keeps a filter row."""
    from pinpoint_fg.track import suggested_disable, tracker_config
    from pinpoint_fg.trackers.svn import SvnSettings, SvnTracker

    rec, obs = _simulated(tmp_path, 12)
    cfg = tracker_config(rec, "svn", disable=suggested_disable(tmp_path / "run"), seed=0)
    trackers = [SvnTracker(cfg), SvnTracker(cfg, SvnSettings(kinematic_bias=BiasModel(5.0, 1.0))),
                SvnTracker(cfg, SvnSettings(kinematic_bias=BiasModel(5.0, 0.3)))]
    for o in obs:
        plain, white, biased = (t.step(o) for t in trackers)
        np.testing.assert_array_equal(white.cam_T_needle, plain.cam_T_needle)
        np.testing.assert_array_equal(white.particles, plain.particles)
        np.testing.assert_array_equal(white.log_posterior, plain.log_posterior)
        assert [m.weight for m in white.modes] == [m.weight for m in plain.modes]
    np.testing.assert_array_equal(trackers[1].window.evidence, trackers[0].window.evidence)
    book = trackers[2].window.kin
    assert not np.array_equal(trackers[2].window.evidence, trackers[0].window.evidence)
    assert {k: m.shape for k, m in book.means.items()} == {"grasp_position": (cfg.particles, 3),
                                                           "grasp_perpendicular": (cfg.particles, 1)}
