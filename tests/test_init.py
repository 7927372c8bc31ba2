"""Seeding: closed-form circle poses, and every plausible mode gets particles."""

from __future__ import annotations

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.conic_fit import fit_conic
from pinpoint_fg.init import InitConfig, circle_poses_from_conic, seed_particles
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


def _polish_every_trial_in_full(lik: FrameLikelihood, T: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """The seeding's polish as it was before its last trial was scored by nll alone: every trial evaluated with its
    gradient and information (the reference the fast path is pinned to)."""
    from pinpoint_fg.stein import floor_hessians

    lam = np.full(T.shape[0], 1e-3)
    nll, g, H = lik.gauss_newton(T)
    for _ in range(iters):
        Hf, _ = floor_hessians(H, eps=1e-6)
        diag = np.einsum("nii->ni", Hf)
        step = -np.linalg.solve(Hf + lam[:, None, None] * diag[:, :, None] * np.eye(6), g[..., None])[..., 0]
        Tn = T @ se3_exp(step)
        nll_n, g_n, H_n = lik.gauss_newton(Tn)
        better = nll_n < nll
        T, nll = np.where(better[:, None, None], Tn, T), np.where(better, nll_n, nll)
        g, H = np.where(better[:, None], g_n, g), np.where(better[:, None, None], H_n, H)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return T, nll


def _frame(rng: np.random.Generator, arc_px: int) -> Observation:
    """A frame with a tip, ``arc_px`` backbone pixels and a grasper pose, each with noise."""
    T = se3_exp(np.r_[rng.normal(size=3) * 0.7, rng.uniform(-0.01, 0.01, 2), rng.uniform(0.03, 0.08)])
    R, t = T[:3, :3], T[:3, 3]
    G = np.eye(4)
    G[:3, :3] = R @ se3_exp(np.r_[rng.normal(size=3) * 0.05, 0, 0, 0])[:3, :3]
    G[:3, 3] = R @ NEEDLE.grasp_m + t + rng.normal(size=3) * 3e-4
    return Observation(0, 0.0, tip_px=CAM.project(R @ NEEDLE.tip_m + t) + rng.normal(size=2),
                       backbone_px=CAM.project(NEEDLE.arc_points(arc_px) @ R.T + t) + rng.normal(size=(arc_px, 2)),
                       cam_T_grasper=G)


@pytest.mark.parametrize("seed", range(4))
def test_polish_scores_its_last_trial_by_nll_alone_with_the_same_result(seed: int) -> None:
    from pinpoint_fg.init import ellipse_candidates, grasp_candidates, polish

    obs = _frame(np.random.default_rng(seed), 80)
    lik = FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE))
    C = np.concatenate([ellipse_candidates(lik, 12), grasp_candidates(lik, 12)])
    assert C.shape[0] > 100
    for iters in (1, 2, 6):
        fast = polish(lik, C, iters)
        ref = _polish_every_trial_in_full(FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE)), C, iters)
        assert np.array_equal(fast[0], ref[0]) and np.array_equal(fast[1], ref[1])


@pytest.mark.parametrize("seed", range(2))
def test_polish_in_batches_equals_one_batch_to_round_off(seed: int) -> None:
    """The seeding's 1440 candidates of a 200-pixel frame are evaluated in ~12 cache-sized batches; the polished
    poses and their nll are those of evaluating all at once, to round-off (a batch's BLAS blocking differs)."""
    from pinpoint_fg.init import InitConfig, ellipse_candidates, grasp_candidates, polish
    from pinpoint_fg.likelihood import GN_BATCH_ENTRIES

    obs = _frame(np.random.default_rng(100 + seed), 200)
    lik = FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE))
    steps = InitConfig().angle_steps
    C = np.concatenate([ellipse_candidates(lik, steps), grasp_candidates(lik, steps)])
    assert C.shape[0] == 1440 and C.shape[0] > 10 * (GN_BATCH_ENTRIES // lik.dim)
    T, nll = polish(lik, C, InitConfig().polish_iters)
    T_ref, nll_ref = _polish_every_trial_in_full(FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE)), C,
                                                 InitConfig().polish_iters)
    np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(nll, nll_ref, rtol=1e-9)


def test_seeding_keeps_a_true_mode_one_mask_disfavours(tmp_path) -> None:
    """Held-out geometry, slow, seed 2: on the first frame the mask prefers the pose turned ~74 deg about the needle's
    tip-tail chord (which moves neither keypoint) by ~30 nats of the seeding's cost. A margin of 25 (the default before
    the thirty-second round) gave that mode no particle and SVN never found the truth again (72 deg off for 150 frames);
    the default margin keeps it, and the window's evidence picks it within the first frames. The margin-25 run is the
    check that this run still shows the trap (the simulator's noise depends on the run's length: 150 frames)."""
    from pinpoint_fg.eval.modes import near_truth
    from pinpoint_fg.io.recording import read_recording
    from pinpoint_fg.observe import observe_frame
    from pinpoint_fg.sim.config import geometry_config
    from pinpoint_fg.sim.scenarios import simulate
    from pinpoint_fg.track import suggested_disable, tracker_config
    from pinpoint_fg.trackers.svn import SvnTracker

    rec = read_recording(simulate("slow", 150, seed=2, out=tmp_path / "run", config=geometry_config("held-out")))
    kept = {}
    for margin in (25.0, InitConfig().mode_nll_margin):
        tracker = SvnTracker(tracker_config(rec, "svn", disable=suggested_disable(rec), seed=0),
                             init=InitConfig(mode_nll_margin=margin))
        kept[margin] = [bool(np.any(near_truth(tracker.step(observe_frame(rec, f, max_points=200)).particles,
                                               f.cam_T_needle_gt))) for f in rec.frames[:4]]
    assert not any(kept[25.0])
    assert all(kept[InitConfig().mode_nll_margin])
