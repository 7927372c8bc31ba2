"""The batched per-particle window linearisation equals GTSAM's own elimination (GTSAM_NOTES §4)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.conventions import matrix_to_pose3
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import MotionFactor, PosePriorFactor
from factors.lie import se3_exp, se3_inverse
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observation import Observation
from pinpoint_fg.window import RANDOM_WALK_SIGMA, Window

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
NEEDLE = NeedleModel()
MODEL = MeasurementModel(CAM, NEEDLE, NoiseConfig())


def _truth(k: int) -> np.ndarray:
    T = se3_exp(np.r_[0.4 + 0.02 * k, -0.3, 0.2 + 0.01 * k, 0.002 + 2e-4 * k, -0.001, 0.045])
    return T


def _observation(k: int, rng: np.random.Generator, image: bool = True) -> Observation:
    T = _truth(k)
    R, t = T[:3, :3], T[:3, 3]
    G = np.eye(4)
    G[:3, 3] = R @ NEEDLE.grasp_m + t + rng.normal(size=3) * 3e-4
    z = np.cross(R @ NEEDLE.grasp_tangent, R[:, 2])  # radial direction: perpendicular to the tangent
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    G[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    if not image:
        return Observation(k, k / 30.0, cam_T_grasper=G)
    return Observation(
        k, k / 30.0,
        tip_px=CAM.project(R @ NEEDLE.tip_m + t) + rng.normal(size=2),
        tail_px=CAM.project(R @ NEEDLE.tail_m + t) + rng.normal(size=2),
        backbone_px=CAM.project(NEEDLE.arc_points(40) @ R.T + t) + rng.normal(size=(40, 2)),
        cam_T_grasper=G,
    )


def _window(L: int, N: int, rng: np.random.Generator, frames: int, image_every: int = 2) -> tuple[Window, list]:
    noise = NoiseConfig()
    w = Window(L, noise.process_cov, relin_threshold=0.0)  # the exact path (test_relinearize.py: the anchored one)
    obs = [_observation(k, rng, image=(k % image_every == 0)) for k in range(frames)]
    start = _truth(0) @ se3_exp(rng.normal(size=(N, 6)) * np.r_[[0.05] * 3, [1e-3] * 3])
    w.start(start, FrameLikelihood(obs[0], MODEL), np.r_[[0.3] * 3, [0.01] * 3])
    for k in range(1, frames):
        D = obs[k].cam_T_grasper @ se3_inverse(obs[k - 1].cam_T_grasper)
        w.push(FrameLikelihood(obs[k], MODEL), D, use_motion=True)
    # move every pose of every particle off its prediction so the test is not at a special point
    w.poses = w.poses @ se3_exp(rng.normal(size=w.poses.shape[:2] + (6,)) * np.r_[[0.02] * 3, [5e-4] * 3])
    return w, obs


def _gtsam_graph(w: Window, i: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
    keys = list(range(w.size))
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    cov = np.linalg.inv(w.prior_W[i].T @ w.prior_W[i])
    g.add(PosePriorFactor(keys[0], w.prior_mean[i], gtsam.noiseModel.Gaussian.Covariance(cov)))
    for j, k in enumerate(keys):
        for f in w.frames[j].gtsam_factors(k):
            g.add(f)
        v.insert(k, matrix_to_pose3(w.poses[j, i]))
    for j in range(w.size - 1):
        Wm = w.delta_W[j]
        g.add(MotionFactor(keys[j], keys[j + 1], w.deltas[j],
                           gtsam.noiseModel.Gaussian.Covariance(np.linalg.inv(Wm.T @ Wm))))
    return g, v, keys


@pytest.mark.parametrize("L", [1, 2, 4])
def test_fast_linearisation_equals_gtsam_elimination(L: int) -> None:
    rng = np.random.default_rng(L)
    w, _ = _window(L, 8, rng, frames=7)
    assert w.size == L
    lin = w.linearize()
    for i in range(8):
        g, v, keys = _gtsam_graph(w, i)
        gfg = g.linearize(v)
        if L > 1:
            _, rem = gfg.eliminatePartialMultifrontal(gtsam.Ordering(keys[:-1]))
            Lam, eta = rem.hessian()
        else:
            Lam, eta = gfg.hessian()
        Lam, eta = np.asarray(Lam)[:6, :6], np.asarray(eta)[:6]
        scale = np.abs(Lam).max()
        np.testing.assert_allclose(lin.hess[i], Lam, rtol=1e-8, atol=1e-9 * scale)
        np.testing.assert_allclose(lin.grad[i], -eta, rtol=1e-8, atol=1e-9 * np.abs(eta).max())
        np.testing.assert_allclose(lin.window_value[i], g.error(v), rtol=1e-10)


def test_back_substitution_is_gauss_newton_step_of_the_whole_window() -> None:
    """Moving the newest pose by its marginal GN step and back-substituting = GTSAM's full GN step."""
    rng = np.random.default_rng(9)
    w, _ = _window(3, 4, rng, frames=6, image_every=1)
    lin = w.linearize()
    step = -np.linalg.solve(lin.hess, lin.grad[..., None])[..., 0]
    before = w.poses.copy()
    w.move_newest(step, lin)
    for i in range(4):
        g, v, keys = _gtsam_graph_from(before, w, i)
        delta = g.linearize(v).optimize()
        for j, k in enumerate(keys):
            expected = matrix_to_pose3(before[j, i]).retract(delta.at(k)).matrix()
            np.testing.assert_allclose(w.poses[j, i], expected, atol=1e-9)


def _gtsam_graph_from(poses: np.ndarray, w: Window, i: int):
    saved = w.poses
    w.poses = poses
    try:
        return _gtsam_graph(w, i)
    finally:
        w.poses = saved


def test_marginalisation_keeps_information_and_evidence_finite() -> None:
    rng = np.random.default_rng(3)
    w, _ = _window(1, 5, rng, frames=12)
    eig = np.linalg.eigvalsh(np.swapaxes(w.prior_W, 1, 2) @ w.prior_W)
    assert np.all(eig > 0) and np.all(np.isfinite(w.evidence))
    # the prior of a frame with only kinematics still constrains all six directions
    assert np.all(np.isfinite(w.prior_mean))


def test_motion_term_is_whitened_by_the_process_noise() -> None:
    """Two poses off the grasper's motion by a known tangent d: the window cost is 1/2 |d / sigma_Q|^2."""
    noise = NoiseConfig()
    sigma = np.sqrt(np.diag(noise.process_cov))
    w = Window(2, noise.process_cov)
    T0 = _truth(0)
    empty = FrameLikelihood(Observation(0, 0.0), MODEL)
    w.start(T0[None], empty, np.full(6, 1e6))  # a negligible prior
    D = se3_exp(np.r_[0.01, -0.02, 0.03, 1e-3, 0.0, -2e-3])
    w.push(FrameLikelihood(Observation(1, 0.033), MODEL), D, use_motion=True)
    d = np.r_[0.02, 0.0, -0.01, 2e-4, 1e-4, 0.0]
    w.poses[1] = D @ T0[None] @ se3_exp(d)
    lin = w.linearize()
    np.testing.assert_allclose(lin.window_value[0], 0.5 * np.sum((d / sigma) ** 2), rtol=1e-6)
    # without kinematics: the random walk's sigma
    w2 = Window(2, noise.process_cov)
    w2.start(T0[None], empty, np.full(6, 1e6))
    w2.push(FrameLikelihood(Observation(1, 0.033), MODEL), None, use_motion=True)
    w2.poses[1] = T0[None] @ se3_exp(d)
    np.testing.assert_allclose(w2.linearize().window_value[0], 0.5 * np.sum((d / RANDOM_WALK_SIGMA) ** 2), rtol=1e-6)


def _fresh_copy(w: Window) -> Window:
    """The same window with new likelihood objects (no memo anywhere)."""
    c = w.subset(np.arange(w.poses.shape[1]))
    c.frames = [FrameLikelihood(f.observation, f.model) for f in w.frames]
    return c


@pytest.mark.parametrize("L", [1, 3])
def test_memoised_trial_evaluation_equals_the_fresh_linearisation(L: int) -> None:
    # The memo returns the very arrays computed for the (bitwise equal) trial poses; a fresh
    # evaluation on another buffer may differ in the last bit (NumPy's SIMD reductions depend on
    # memory alignment), hence 1e-14 rather than bitwise.
    rng = np.random.default_rng(21)
    w, _ = _window(L, 8, rng, frames=4)
    lin = w.linearize()
    step = rng.normal(size=(8, 6)) * np.r_[[0.01] * 3, [2e-4] * 3]
    trial = w.newest @ se3_exp(step)
    w.newest_value(trial, lin)  # the safeguard's trial: memoised
    w.move_newest(step, lin)
    assert np.array_equal(w.newest, trial)  # the accepted poses are bitwise the trial: the memo hits

    def no_evaluation(*args: object, **kwargs: object) -> None:
        raise AssertionError("the newest frame was re-evaluated")

    w.frames[-1].whitened = no_evaluation
    cached = w.linearize()  # reuses the trial evaluation of the newest frame
    fresh = _fresh_copy(w).linearize()
    for name in ("value", "grad", "hess", "window_value"):
        # round-off of a sum scales with its largest terms, not with a cancelling entry: bound it by the array's scale
        b = getattr(fresh, name)
        np.testing.assert_allclose(getattr(cached, name), b, rtol=1e-14, atol=1e-14 * np.abs(b).max(), err_msg=name)


@pytest.mark.parametrize("L", [1, 3])
def test_adopt_keeps_the_oldest_frame_memo_equal_to_a_fresh_evaluation(L: int) -> None:
    rng = np.random.default_rng(22)
    w, _ = _window(L, 8, rng, frames=4)
    lin = w.linearize()
    sub = w.subset([5])
    sub_lin = lin.subset([5])
    sub.move_newest(np.r_[0.01, 0.0, -0.01, 1e-4, 0.0, 0.0][None], sub_lin)
    sub.linearize()
    w.adopt(sub, [5])
    assert np.array_equal(w.poses[:, 5], sub.poses[:, 0])
    assert w._memo.entry is not None  # merged, not dropped
    memo = w._unary(0, w.poses[0])
    fresh = _fresh_copy(w)._unary(0, w.poses[0])
    for a, b in zip(memo, fresh, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("L", [1, 3, 5])
def test_newest_value_at_the_current_poses_is_the_linearisation_value(L: int) -> None:
    # The safeguard and the MAP polish compare newest_value(trial) with lin.value: at the current
    # poses they must agree (else an inconsistency of ~1e-3 nats rejects every small improving step).
    rng = np.random.default_rng(23)
    w, _ = _window(L, 8, rng, frames=6)
    lin = w.linearize()
    np.testing.assert_allclose(w.newest_value(w.newest.copy(), lin), lin.value, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("L", [1, 3])
def test_resample_keeps_the_oldest_frame_memo_equal_to_a_fresh_evaluation(L: int) -> None:
    rng = np.random.default_rng(24)
    w, _ = _window(L, 8, rng, frames=4)
    w.linearize()
    index = np.array([0, 0, 3, 5, 5, 5, 7, 2])
    w.resample(index)
    assert w._memo.entry is not None  # reindexed, not dropped
    memo = w._unary(0, w.poses[0])
    fresh = _fresh_copy(w)._unary(0, w.poses[0])
    for a, b in zip(memo, fresh, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    w.poses[0, 1] = w.poses[0, 1] @ se3_exp(np.full(6, 1e-3))  # a moved pose misses the memo
    assert not w._memo.holds(w._prior_key(w.poses[0]))


@pytest.mark.parametrize("L", [1, 3])
def test_share_books_copies_prior_and_evidence_and_keeps_the_memo_equal_to_a_fresh_evaluation(L: int) -> None:
    from pinpoint_fg.window_rows import share_books

    rng = np.random.default_rng(25)
    w, _ = _window(L, 8, rng, frames=4)
    w.evidence = rng.normal(size=8) * 10.0
    w.linearize()
    poses = w.poses.copy()
    share_books(w, [1, 2, 6], [0, 0, 5])
    assert np.array_equal(w.poses, poses)  # own poses kept
    for dst, src in ((1, 0), (2, 0), (6, 5)):
        assert np.array_equal(w.prior_mean[dst], w.prior_mean[src])
        assert np.array_equal(w.prior_W[dst], w.prior_W[src])
        assert w.evidence[dst] == w.evidence[src]
    assert w._memo.holds(w._prior_key(w.poses[0]))  # patched, not dropped
    memo = w._unary(0, w.poses[0])
    fresh = _fresh_copy(w)._unary(0, w.poses[0])
    for a, b in zip(memo, fresh, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


def test_move_newest_with_the_accepted_trial_is_bitwise_the_retraction() -> None:
    """L = 1: handing ``move_newest`` the safeguard's ``T @ Exp(step)`` gives the poses it would compute itself."""
    rng = np.random.default_rng(41)
    w, _ = _window(1, 12, rng, 1)
    step = rng.normal(size=(12, 6)) * np.r_[[0.02] * 3, [5e-4] * 3]
    lin = w.linearize()
    trial = w.newest @ se3_exp(step)
    ref = w.poses @ se3_exp(step[None])
    w.move_newest(step, lin, newest=trial)
    assert np.array_equal(w.poses, ref) and w.poses.shape == (1, 12, 4, 4)
    trial[:] = 0.0  # the window holds its own copy
    assert np.array_equal(w.poses, ref)


def test_kinematic_bias_books_follow_the_hypotheses_through_every_row_operation() -> None:
    """With a bias model the window keeps one filter row per hypothesis (:class:`~pinpoint_fg.kinematic_bias.BiasBook`,
    updated at each marginalisation), and subsets, resampling, copies and shared books move those rows with the
    evidence they belong to."""
    from pinpoint_fg.kinematic_bias import BiasModel
    from pinpoint_fg.window_rows import copy_hypotheses, share_books

    rng = np.random.default_rng(11)
    noise = NoiseConfig()
    N = 6
    w = Window(1, noise.process_cov, forgetting=1.0, kinematic_bias=BiasModel(5.0, 0.3))
    obs = [_observation(k, rng) for k in range(5)]
    w.start(_truth(0) @ se3_exp(rng.normal(size=(N, 6)) * np.r_[[0.05] * 3, [1e-3] * 3]),
            FrameLikelihood(obs[0], MODEL), np.r_[[0.3] * 3, [0.01] * 3])
    for k in range(1, 5):
        w.push(FrameLikelihood(obs[k], MODEL), obs[k].cam_T_grasper @ se3_inverse(obs[k - 1].cam_T_grasper), True)
    means = {k: m.copy() for k, m in w.kin.means.items()}
    assert set(means) == {"grasp_position", "grasp_perpendicular"} and w.kin.t_s == obs[3].t_s
    assert all(len(np.unique(m, axis=0)) == N for m in means.values())  # every hypothesis its own bias

    def rows_of(book, index):
        return {k: m[index] for k, m in book.means.items()}

    sub = w.subset([4, 1])
    for k, m in rows_of(sub.kin, slice(None)).items():
        np.testing.assert_array_equal(m, means[k][[4, 1]])
    copy_hypotheses(w, [0], sub, [0])  # hypothesis 0 becomes a copy of 4
    share_books(w, np.array([2]), np.array([5]))  # 2 takes 5's books
    for k, m in w.kin.means.items():
        np.testing.assert_array_equal(m[[0, 2]], means[k][[4, 5]])
    np.testing.assert_array_equal(w.evidence[[0, 2]], w.evidence[[4, 5]])
    w.resample(np.array([3, 3, 1, 0, 2, 5]))
    for k, m in w.kin.means.items():
        np.testing.assert_array_equal(m, means[k][[3, 3, 1, 4, 5, 5]])


@pytest.mark.parametrize("L", [1, 3])
def test_a_halving_re_evaluates_only_its_rows_and_the_accepted_trial_needs_no_evaluation(L: int) -> None:
    # The SVN safeguard: a full trial, then the rows whose step was halved only (newest_value's ``changed``).
    rng = np.random.default_rng(25)
    w, _ = _window(L, 8, rng, frames=5)  # the newest frame has a backbone
    lin = w.linearize()
    step = rng.normal(size=(8, 6)) * np.r_[[0.01] * 3, [2e-4] * 3]
    trial = w.newest @ se3_exp(step)
    full = w.newest_value(trial, lin)
    rows = np.array([1, 6])
    halved = step.copy()
    halved[rows] *= 0.5
    trial2 = trial.copy()
    trial2[rows] = w.newest[rows] @ se3_exp(halved[rows])
    sizes = []
    irls = w.frames[-1].irls
    w.frames[-1].irls = lambda T, jacobian=True: (sizes.append(T.shape[0]), irls(T, jacobian))[1]
    partial = w.newest_value(trial2, lin, changed=(rows, trial))
    assert sizes == [2]
    others = np.setdiff1d(np.arange(8), rows)
    assert np.array_equal(partial[others], full[others])
    reference = _fresh_copy(w).newest_value(trial2, lin)
    np.testing.assert_allclose(partial, reference, rtol=1e-12, atol=1e-9)
    # accepting the merged trial: the next linearisation finds the newest frame's terms in the memo
    w.move_newest(halved, lin, newest=trial2)
    assert np.array_equal(w.newest, trial2)

    def no_evaluation(*args: object, **kwargs: object) -> None:
        raise AssertionError("the newest frame was re-evaluated")

    w.frames[-1].irls = no_evaluation
    cached = w.linearize()
    fresh = _fresh_copy(w).linearize()
    for name in ("value", "grad", "hess", "window_value"):
        b = getattr(fresh, name)
        np.testing.assert_allclose(getattr(cached, name), b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=name)
