"""Multi-hypothesis MAP bank: holds the truth when the twin is ambiguous, equals map on clear runs, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.trackers.base import TrackerConfig
from pinpoint_fg.trackers.map import MapTracker
from pinpoint_fg.trackers.mht import MhtConfig, MhtTracker
from tests.test_trackers_pf import CAMERA, NEEDLE, pose_error, synthetic_sequence


def _config(k: int = 4) -> TrackerConfig:
    return TrackerConfig(camera=CAMERA, needle=NEEDLE, particles=k)


def _close(T: np.ndarray, T_gt: np.ndarray) -> bool:
    e_t, e_r = pose_error(T, T_gt)
    return e_t < 2e-3 and e_r < np.deg2rad(10.0)


def _check_weights(est) -> None:  # noqa: ANN001
    w = est.weights
    assert w.shape == (4,) and np.all(w >= 0) and np.isclose(w.sum(), 1.0, atol=1e-12)
    assert est.particles.shape == (4, 4, 4) and est.log_posterior.shape == (4,)
    live = len(est.modes)
    assert live == est.extra["branches"] and 1 <= live <= 4
    assert np.allclose(np.exp(est.log_posterior[:live]), w[:live]) and np.all(w[live:] == 0.0)
    assert np.isclose(sum(m.weight for m in est.modes), 1.0, atol=1e-12)
    assert np.allclose(est.cam_T_needle, est.modes[0].cam_T_needle) and w[0] == w.max()
    for m in est.modes:
        assert m.cov_xi.shape == (6, 6) and np.all(np.linalg.eigvalsh(m.cov_xi) > 0)


@pytest.mark.parametrize("transport", [False, True])
def test_ambiguous_run_keeps_a_branch_at_the_truth(transport: bool) -> None:
    """Tail keypoint and backbone only: twin and tail flip explain the frame as well as the truth."""
    seq = synthetic_sequence(16, seed=3, tip=False, kinematics=False)
    mht = MhtTracker(_config(), MhtConfig(transport_prior=transport))
    held, several = [], []
    for obs, T in zip(seq.observations, seq.cam_T_needle, strict=True):
        est = mht.step(obs)
        _check_weights(est)
        held.append(any(_close(m.cam_T_needle, T) for m in est.modes))
        several.append(len(est.modes) >= 2 and est.weights[1] > 0.05)
    assert np.mean(held) >= 0.9  # measured 1.0
    assert np.mean(several) >= 0.9  # the posterior is really multi-modal here (measured 1.0)
    # (Which of the equally good modes a single-mode MAP settles in is a tie-break of round-off, so
    # nothing is asserted about it here.)


def test_exactly_equivalent_modes_get_equal_evidence() -> None:
    """Backbone (full-circle conic) + tail only: the tail flip leaves every residual unchanged."""
    obs = synthetic_sequence(1, seed=5, tip=False, kinematics=False).observations[0]
    est = MhtTracker(_config()).step(obs)
    from pinpoint_fg.proposals import arc_flips

    modes = [m.cam_T_needle for m in est.modes]
    pairs = 0
    for i, Ti in enumerate(modes):
        flip = arc_flips(Ti, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0, 1]
        for j in range(i + 1, len(modes)):
            if _close(flip, modes[j]) and pose_error(flip, modes[j])[1] < np.deg2rad(2.0):
                pairs += 1
                assert np.isclose(np.log(est.weights[i]), np.log(est.weights[j]), atol=0.05)
    assert pairs >= 1


def test_clear_run_has_one_dominant_branch_and_equals_map() -> None:
    seq = synthetic_sequence(16, seed=4)
    mht, mp = MhtTracker(_config()), MapTracker(_config())
    dominant, e_mht, e_map = [], [], []
    for obs, T in zip(seq.observations, seq.cam_T_needle, strict=True):
        est = mht.step(obs)
        _check_weights(est)
        dominant.append(est.weights[0] > 0.9)
        e_mht.append(pose_error(est.cam_T_needle, T))
        e_map.append(pose_error(mp.step(obs).cam_T_needle, T))
    assert np.mean(dominant) >= 0.9  # measured 1.0
    a, b = np.mean(e_mht, axis=0), np.mean(e_map, axis=0)
    assert np.all(np.abs(a - b) <= 0.03 * b)  # measured identical


def test_redetects_when_every_branch_is_implausible(monkeypatch: pytest.MonkeyPatch) -> None:
    import pinpoint_fg.trackers.mht as mht_module

    seq = synthetic_sequence(2, seed=17)
    tr = MhtTracker(_config())
    assert not tr.step(seq.observations[0]).reseeded
    monkeypatch.setattr(mht_module, "implausible", lambda *args: True)
    est = tr.step(seq.observations[1])
    assert est.reseeded and est.extra["branches"] >= 1
    _check_weights(est)
    assert _close(est.cam_T_needle, seq.cam_T_needle[1])


def test_branches_whose_smoother_raises_end_and_the_bank_redetects(monkeypatch: pytest.MonkeyPatch) -> None:
    from pinpoint_fg.trackers.map import MapSmoother

    seq = synthetic_sequence(2, seed=18)
    tr = MhtTracker(_config())
    tr.step(seq.observations[0])

    def fail(*args: object) -> None:
        raise RuntimeError("Indeterminate linear system detected while working near variable")

    monkeypatch.setattr(MapSmoother, "advance", fail)
    est = tr.step(seq.observations[1])
    assert est.reseeded and est.extra["recovered"] >= 1
    _check_weights(est)
    assert _close(est.cam_T_needle, seq.cam_T_needle[1])


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        MhtConfig(max_branches=0)
    with pytest.raises(ValueError):
        MhtConfig(admit_nats=30.0, prune_nats=20.0)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="reroute_nats"):
            MhtConfig(reroute_nats=bad)


def test_cli_track_mht(tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "8", "--seed", "2", "--out", str(run)]) == 0
    out = tmp_path / "mht"
    assert main(["track", str(run), "--method", "mht", "--out", str(out), "--seed", "1"]) == 0
    res = read_result(out)
    assert res.method == "mht" and len(res.frame) == 8 and np.all(np.isfinite(res.cam_T_needle))
    w = res.particles.weight
    assert w is not None and w.shape == (8, 4) and np.allclose(w.sum(axis=1), 1.0)
    assert np.all(res.extra["branches"] >= 1) and np.all(res.extra["best_weight"] > 0)


@pytest.mark.parametrize("transport", [False, True])
def test_smoothed_poses_cover_every_frame_when_a_branch_started_inside_the_window_becomes_best(
        tmp_path: Path, transport: bool) -> None:
    """Snapshots seed 1 (frames 0.5 s apart, no kinematics), L = 3: a proposal admitted at a frame becomes the best
    branch (frame 5; transported prior: frame 9) and the bank re-detects (frame 6), so the best smoother holds none
    of the frames it must report next. Each frame still gets exactly one smoothed pose, in order; with the parent's
    own prior the frames the best smoother started after are reported at the pose the bank held for them before
    the switch, bitwise (a transported proposal carries them rigidly onto its mode: not compared here).

    The Cauchy conic (the default until the twenty-third round) is pinned: with it the bank re-detects early in this
    run; with today's Geman-McClure conic it does not, and the re-detection path would go untested."""
    from pinpoint_fg.io.recording import read_recording
    from pinpoint_fg.noise import NoiseConfig, parse_robust_spec
    from pinpoint_fg.observe import observe_frame
    from pinpoint_fg.track import tracker_config

    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "snapshots", "--frames", "40", "--seed", "1", "--out", str(run)]) == 0
    rec = read_recording(run)
    L, n = 3, (12 if transport else 8)
    cauchy = NoiseConfig().with_robust(parse_robust_spec("conic=cauchy:3,grasp-perpendicular=huber:1.345"))
    tr = MhtTracker(tracker_config(rec, "mht", noise=cauchy, window=L, seed=1), MhtConfig(transport_prior=transport))
    frames, switched = [], {"admitted": 0, "reseeded": 0}
    for fr in rec.frames[:n]:
        held = [b.smoother.pending() for b in tr.branches]  # the bank's poses of the frames still to report
        est = tr.step(observe_frame(rec, fr))
        top = tr.branches[0].smoother
        inherited = top.first_key > fr.frame - (L - 1) >= 0
        if inherited:  # the best branch started inside the window (the case this test is about)
            switched["reseeded" if est.reseeded else "admitted"] += int(top.first_key == fr.frame)
        if est.smoothed is not None:
            f, _, T = est.smoothed
            frames.append(f)
            if inherited and not transport:
                assert any(np.array_equal(T, h[f][2]) for h in held if f in h)
    frames += [f for f, _, _ in tr.final_smoothed()]
    assert switched["admitted"] >= 1 and switched["reseeded"] >= 1, switched  # both ways a branch starts late
    assert frames == list(range(n))


def test_a_proposal_that_is_a_better_route_into_another_branchs_mode_replaces_that_branch() -> None:
    """The better route into a mode wins: both circles of an ambiguous frame are branches; the twin's is set 8 nats
    behind. Frames 1 s apart without kinematics (a wide random walk), the best branch's twin proposal lands on the
    twin's branch and beats its own history by more than ``reroute_nats`` (here 1): it replaces the branch, whose
    weight rises to the route's. With ``reroute_nats = inf`` (the default) the branch keeps its own history and its
    handicap."""
    from pinpoint_fg.likelihood import Switches
    from pinpoint_fg.noise import NoiseConfig
    from pinpoint_fg.observation import Observation
    from pinpoint_fg.proposals import twin_poses
    from tests.test_trackers_svn import CAM, _ambiguous_scene
    from tests.test_trackers_svn import NEEDLE as NEEDLE_SVN

    T, _, arc = _ambiguous_scene()
    twin = twin_poses(T[None], CAM.K, NEEDLE_SVN.radius_m, NEEDLE_SVN.tail_angle_rad, NEEDLE_SVN.tip_angle_rad)[0]
    sw = Switches(grasp_perpendicular=False, grasp_position=False, tip=False, tail=False)
    cfg = TrackerConfig(CAM, NEEDLE_SVN, NoiseConfig(), sw, particles=4)
    rng = np.random.default_rng(5)
    obs = [Observation(k, float(k), backbone_px=arc + rng.normal(size=arc.shape) * 0.5) for k in range(2)]

    def is_twin(P: np.ndarray) -> bool:
        return pose_error(P, twin)[1] < np.deg2rad(15.0)  # the other modes are 130-180 deg from it

    def twin_log_odds(reroute: float) -> float:
        mht = MhtTracker(cfg, MhtConfig(reroute_nats=reroute))
        mht.step(obs[0])
        held = [b for b in mht.branches if is_twin(b.smoother.newest)]
        assert len(held) == 1 and held[0] is not mht.branches[0]
        held[0].log_w -= 8.0
        est = mht.step(obs[1])
        w = [m.weight for m in est.modes if is_twin(m.cam_T_needle)]
        assert len(w) == 1
        return float(np.log(w[0] / est.modes[0].weight))

    own, routed = twin_log_odds(np.inf), twin_log_odds(1.0)
    assert own < -6.0  # the handicap stays (its own history); measured -9.6
    assert routed > own + 1.0  # replaced by the better route; measured -1.9
