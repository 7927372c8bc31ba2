"""SVN's mode bookkeeping: basins by predicted peaks, Laplace evidence, proposals admitted only when earned."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from factors.lie import local, se3_exp
from pinpoint_fg.likelihood import FrameLikelihood, Switches
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observation import Observation
from pinpoint_fg.posterior.summary import bimodal_from_modes
from pinpoint_fg.trackers.base import TrackerConfig
from pinpoint_fg.trackers.svn import FIRST_PRIOR_SIGMA, SvnTracker
from pinpoint_fg.trackers.svn_modes import (
    SCALE,
    ModeSettings,
    _greedy_groups,
    basins,
    laplace_terms,
    rotation_beyond,
    scaled_distance,
)
from pinpoint_fg.window import Linearization, Window
from tests.test_trackers_svn import CAM, NEEDLE, _ambiguous_scene, _grasper, _mode_shares


def _quadratic_lin(T: np.ndarray, peak: np.ndarray, H: np.ndarray, offset: float) -> Linearization:
    """The exact right-chart model of ``offset + 1/2 Log(peak^-1 x)^T H Log(peak^-1 x)`` at poses T (to 1st order)."""
    xi = local(np.broadcast_to(peak, T.shape), T)  # T = peak Exp(xi); the peak is at d = -xi from T
    g = xi @ H
    value = offset + 0.5 * np.einsum("ni,ni->n", xi, g)
    N = T.shape[0]
    return Linearization(value, g, np.broadcast_to(H, (N, 6, 6)).copy(), [], [], [], value.copy())


def test_basins_group_hypotheses_by_predicted_peak_and_weigh_them_by_evidence() -> None:
    rng = np.random.default_rng(3)
    H = np.diag(1.0 / np.r_[[np.deg2rad(3.0)] * 3, [0.5e-3] * 3] ** 2)
    peak_a = se3_exp(np.r_[0.3, -0.2, 0.1, 0.0, 0.0, 0.05])
    peak_b = peak_a @ se3_exp(np.r_[np.pi / 3, 0, 0, 0, 0, 0])  # 60 deg away
    # particles spread by about the kernel scale (repulsion) around each peak: 30 and 20 of them
    Ta = peak_a @ se3_exp(rng.normal(size=(30, 6)) * SCALE)
    Tb = peak_b @ se3_exp(rng.normal(size=(20, 6)) * SCALE)
    T = np.concatenate([Ta, Tb])
    lin_a, lin_b = _quadratic_lin(Ta, peak_a, H, 5.0), _quadratic_lin(Tb, peak_b, H, 6.0)
    lin = Linearization(np.r_[lin_a.value, lin_b.value], np.concatenate([lin_a.grad, lin_b.grad]),
                        np.concatenate([lin_a.hess, lin_b.hess]), [], [], [], np.r_[lin_a.value, lin_b.value])
    found = basins(T, lin, np.zeros(50))
    assert found.reps.shape == (2,)
    assert np.array_equal(found.labels, np.r_[np.zeros(30, int), np.ones(20, int)])
    # every hypothesis predicts its own mode's peak, to the quadratic model's precision
    err_a = np.linalg.norm(local(np.broadcast_to(peak_a, (30, 4, 4)), found.peaks[:30]) / SCALE, axis=1)
    assert err_a.max() < 0.02, err_a.max()
    # equal curvature: the weights are the e^-1 ratio of the offsets, whatever the particle counts
    assert np.allclose(found.weights, [1.0 / (1.0 + np.e ** -1), np.e ** -1 / (1.0 + np.e ** -1)], atol=1e-6)
    # converged exactly where the peak is within max_step scaled units
    dist = np.r_[np.linalg.norm(local(np.broadcast_to(peak_a, (30, 4, 4)), Ta) / SCALE, axis=1),
                 np.linalg.norm(local(np.broadcast_to(peak_b, (20, 4, 4)), Tb) / SCALE, axis=1)]
    assert np.array_equal(found.converged, dist < ModeSettings().max_step)
    # a hypothesis far from its peak (step beyond max_step) is flagged: its evidence is only a guess
    far = _quadratic_lin(peak_a @ se3_exp(np.r_[0.6, 0, 0, 0, 0, 0])[None], peak_a, H, 5.0)
    assert not basins(peak_a[None] @ se3_exp(np.r_[0.6, 0, 0, 0, 0, 0])[None], far, np.zeros(1)).converged[0]


def test_laplace_evidence_prefers_the_broader_of_two_equally_high_peaks() -> None:
    """Equal peak cost, one mode twice as wide on every axis: log Z differs by 6 log 2 (= -1/2 log det ratio)."""
    peak = se3_exp(np.r_[0.1, 0.2, 0.3, 0.0, 0.0, 0.05])
    H = np.diag(1.0 / np.r_[[np.deg2rad(3.0)] * 3, [0.5e-3] * 3] ** 2)
    T = peak[None] @ se3_exp(np.r_[0.01, 0, 0, 1e-4, 0, 0])[None]
    _, m1, z1 = laplace_terms(_quadratic_lin(T, peak, H, 2.0), np.zeros(1))
    _, m2, z2 = laplace_terms(_quadratic_lin(T, peak, H / 4.0, 2.0), np.zeros(1))
    assert np.allclose([m1[0], m2[0]], 2.0, atol=1e-9)
    assert abs((z2[0] - z1[0]) - 6.0 * np.log(2.0)) < 1e-9


def test_the_map_is_the_heaviest_modes_best_hypothesis_not_the_highest_peak() -> None:
    """A narrow mode with the higher peak (cost 2) and a broad one 4x wider on every axis (cost 3): the broad mode
    holds e^(6 log 4 - 1) ~ 1500x the mass, so the MAP is its best hypothesis although the narrow mode's is the
    lowest-cost one (the choice that put calibration-01's first frame on the twin circle, 143 deg off). A mode
    whose evidence is NaN never wins."""
    rng = np.random.default_rng(5)
    H = np.diag(1.0 / np.r_[[np.deg2rad(3.0)] * 3, [0.5e-3] * 3] ** 2)
    peak_a = se3_exp(np.r_[0.3, -0.2, 0.1, 0.0, 0.0, 0.05])
    peak_b = peak_a @ se3_exp(np.r_[np.pi / 3, 0, 0, 0, 0, 0])
    Ta = peak_a @ se3_exp(rng.normal(size=(10, 6)) * SCALE * 0.01)
    Tb = peak_b @ se3_exp(rng.normal(size=(10, 6)) * SCALE * 0.01)
    lin_a, lin_b = _quadratic_lin(Ta, peak_a, 16.0 * H, 2.0), _quadratic_lin(Tb, peak_b, H, 3.0)
    value = np.r_[lin_a.value, lin_b.value]
    lin = Linearization(value, np.concatenate([lin_a.grad, lin_b.grad]), np.concatenate([lin_a.hess, lin_b.hess]),
                        [], [], [], value.copy())
    found = basins(np.concatenate([Ta, Tb]), lin, np.zeros(20))
    assert found.reps.shape == (2,)
    i = found.heaviest_rep()
    assert i >= 10 and i in found.reps, i  # mode b's representative
    assert int(np.argmin(value)) < 10  # the highest density is mode a's
    assert np.max(found.weights) > 0.999
    z = found.log_evidence.copy()
    z[found.labels == found.labels[i]] = np.nan
    assert dataclasses.replace(found, log_evidence=z).heaviest_rep() < 10


def test_the_trackers_map_lies_in_its_heaviest_reported_mode() -> None:
    """Both circle poses kept (no perpendicularity, no keypoints): on every frame the reported pose is the peak of
    the mode ``modes.csv`` would rank first."""
    T, _, arc = _ambiguous_scene()
    rng = np.random.default_rng(1)
    tracker = SvnTracker(TrackerConfig(CAM, NEEDLE, NoiseConfig(), Switches(grasp_perpendicular=False, tip=False,
                                                                           tail=False), particles=50))
    two_modes = 0
    for k in range(8):
        est = tracker.step(Observation(k, k / 30, backbone_px=arc + rng.normal(size=arc.shape) * 0.5,
                                       cam_T_grasper=_grasper(T)))
        at_map = [m for m in est.modes if np.array_equal(m.cam_T_needle, est.cam_T_needle)]
        assert len(at_map) == 1, k
        assert at_map[0].weight == max(m.weight for m in est.modes), (k, [m.weight for m in est.modes])
        two_modes += sum(m.weight >= 0.1 for m in est.modes) >= 2
    assert two_modes >= 4, two_modes  # not vacuous: the choice was made between two weighty modes


def test_window_evidence_is_the_laplace_marginal_likelihood_of_the_marginalised_pose() -> None:
    """Prior + motion only (no measurements): the joint is Gaussian at the optimum, so evidence + 1/2 log det of the
    newest pose's information is 1/2 log det of the whole information: it differs between priors of width s and 2s
    by exactly 6 log 2 (the motion term's determinant is the same for both)."""
    T0 = se3_exp(np.r_[0.2, -0.1, 0.3, 0.001, 0.002, 0.05])
    empty = FrameLikelihood(Observation(0, 0.0), TrackerConfig(CAM, NEEDLE).model)
    assert empty.dim == 0
    Q = np.diag(np.r_[[0.02 ** 2] * 3, [0.3e-3 ** 2] * 3])
    w = Window(1, Q, forgetting=1.0)
    sigma = np.r_[[np.deg2rad(10.0)] * 3, [2e-3] * 3]
    w.start(np.stack([T0, T0]), empty, sigma)
    w.prior_W[1] = w.prior_W[1] / 2.0  # hypothesis 1: prior twice as wide
    delta = se3_exp(np.r_[0.01, 0.0, 0.0, 1e-4, 0.0, 0.0])
    w.push(FrameLikelihood(Observation(1, 1 / 30), TrackerConfig(CAM, NEEDLE).model), delta, use_motion=True)
    lin = w.linearize()
    total = w.evidence + 0.5 * np.linalg.slogdet(lin.hess)[1]
    assert abs((total[0] - total[1]) - 6.0 * np.log(2.0)) < 1e-6, total[0] - total[1]


def _snapshots(T: np.ndarray, arc: np.ndarray, n: int, dt_s: float, kinematics: bool) -> list[Observation]:
    rng = np.random.default_rng(5)
    return [Observation(k, k * dt_s, backbone_px=arc + rng.normal(size=arc.shape) * 0.5,
                        cam_T_grasper=_grasper(T) if kinematics else None) for k in range(n)]


def _start_in_the_true_mode(tr: SvnTracker, T: np.ndarray, first: Observation) -> None:
    """Frame 0 processed with every hypothesis near the truth (as if the other circle had been lost)."""
    motion = tr.motion_input(first)
    near = T @ se3_exp(np.random.default_rng(0).normal(size=(tr.config.particles, 6)) * np.r_[[1e-2] * 3, [1e-4] * 3])
    tr.window.start(near, FrameLikelihood(motion.observation, tr.config.model), FIRST_PRIOR_SIGMA)
    tr._transport(30)
    tr.frames_seen = 1


def test_a_mode_the_particles_lost_is_proposed_and_admitted_when_the_frames_are_far_apart() -> None:
    """Every particle in the true circle; frames 1 s apart without kinematics (the random walk scaled by the elapsed
    time): the frame's ellipse proposes the other circle, which explains the frame as well and costs little under
    the wide prior — it is admitted, holds at least the floor of hypotheses, and the modes call the frame bimodal."""
    T, alt_normal, arc = _ambiguous_scene()
    sw = Switches(grasp_perpendicular=False, grasp_position=False, tip=False, tail=False)
    tr = SvnTracker(TrackerConfig(CAM, NEEDLE, NoiseConfig(), sw, particles=40))
    obs = _snapshots(T, arc, 3, 1.0, kinematics=False)
    _start_in_the_true_mode(tr, T, obs[0])
    assert _mode_shares(tr.particles, T, alt_normal)[1] == 0.0
    est = tr.step(obs[1])
    assert est.extra["proposals"] > 0 and est.extra["allotted"] >= ModeSettings().floor
    share_true, share_alt = _mode_shares(est.particles, T, alt_normal)
    assert min(share_true, share_alt) * 40 >= ModeSettings().floor, (share_true, share_alt)
    assert abs(sum(m.weight for m in est.modes) - 1.0) < 1e-12
    assert bimodal_from_modes(est.modes)


def test_no_mode_is_admitted_against_tight_kinematics() -> None:
    """The same ambiguous frames at 30 Hz with the grasper's pose: switching circles would be a 50 deg jump the
    motion model rules out (hundreds of nats), so nothing is polished or allotted and one mode of weight 1 remains."""
    T, alt_normal, arc = _ambiguous_scene()
    sw = Switches(grasp_perpendicular=False, tip=False, tail=False)
    tr = SvnTracker(TrackerConfig(CAM, NEEDLE, NoiseConfig(), sw, particles=40))
    obs = _snapshots(T, arc, 4, 1 / 30, kinematics=True)
    _start_in_the_true_mode(tr, T, obs[0])
    for o in obs[1:]:
        est = tr.step(o)
        assert est.extra["proposals"] > 0 and est.extra["allotted"] == 0
    assert _mode_shares(est.particles, T, alt_normal) == (1.0, 0.0)
    assert len(est.modes) == 1 and est.modes[0].weight == 1.0
    assert not bimodal_from_modes(est.modes)


def test_allotment_gives_every_admitted_mode_its_floor_from_outside_modes_first_then_the_largest() -> None:
    from pinpoint_fg.trackers.svn_modes import Admitted, Basins, allot

    model = TrackerConfig(CAM, NEEDLE).model
    Q = np.diag(np.r_[[0.02 ** 2] * 3, [0.3e-3 ** 2] * 3])
    base = [se3_exp(np.r_[0.1 * k, 0.2, 0.3, 0.0, 0.0, 0.05 + 0.01 * k]) for k in range(4)]
    labels = np.r_[np.zeros(7, int), np.ones(2, int), np.full(3, 2)]  # 7 in mode 0, 2 in mode 1, 3 in mode 2
    T = np.stack([base[m] for m in labels])
    w = Window(1, Q, forgetting=1.0)
    w.start(T, FrameLikelihood(Observation(0, 0.0), model), FIRST_PRIOR_SIGMA)
    w.evidence[:] = np.arange(12.0)
    reps = np.array([0, 7, 9])
    z_modes = np.array([0.0, -2.0, -20.0])  # mode 2 falls outside the K = 3 best once a candidate is admitted
    found = Basins(z_modes[labels], T.copy(), labels, reps, np.ones(12, bool))
    cand = w.subset([0])
    cand.poses[-1] = base[3][None]
    cand.evidence[:] = 100.0
    settings = ModeSettings(max_modes=3, floor=3)
    moved = allot(w, found, Admitted(cand, np.array([-1.0]), 5), settings, np.random.default_rng(0),
                  np.r_[[1e-3] * 3, [1e-5] * 3])
    assert moved == 4  # one copy tops mode 1 up to 3, three copies populate the new mode
    near = lambda P, Q: np.linalg.norm(local(np.broadcast_to(Q, P.shape), P) / SCALE, axis=1) < 0.1  # noqa: E731
    in_mode = [near(w.newest, base[m]) for m in range(4)]
    assert [int(x.sum()) for x in in_mode] == [6, 3, 0, 3]
    assert np.array_equal(w.newest[reps[:2]], T[reps[:2]])  # the modes' best hypotheses are never donors
    new = np.flatnonzero(in_mode[3])
    assert np.all(w.evidence[new] == 100.0)  # the copies carry the candidate's window: prior and evidence
    assert np.any(np.all(w.newest[new] == base[3], axis=(1, 2)))  # the first copy is exact, the others jittered


def _two_circle_window(rng: np.random.Generator) -> tuple[Window, np.random.Generator]:
    """A one-frame window of 12 hypotheses: 6 within 3 deg / 0.3 mm of the true circle, 6 of its twin, each
    half's prior centred on its own circle (the ambiguous scene, dense term only)."""
    from pinpoint_fg.proposals import twin_poses

    T, _, arc = _ambiguous_scene()
    cfg = TrackerConfig(CAM, NEEDLE, NoiseConfig(), Switches(grasp_perpendicular=False, tip=False, tail=False))
    lik = FrameLikelihood(Observation(0, 0.0, backbone_px=arc, cam_T_grasper=_grasper(T)), cfg.model)
    twin = twin_poses(T[None], CAM.K, NEEDLE.radius_m, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0]
    off = np.r_[[np.deg2rad(3.0)] * 3, [0.3e-3] * 3]
    poses = np.concatenate([T @ se3_exp(rng.normal(size=(6, 6)) * off), twin @ se3_exp(rng.normal(size=(6, 6)) * off)])
    w = Window(1, np.diag(np.r_[[0.02 ** 2] * 3, [0.3e-3 ** 2] * 3]), forgetting=1.0)
    w.start(poses, lik, FIRST_PRIOR_SIGMA)
    w.prior_mean[:6], w.prior_mean[6:] = T, twin
    return w, rng


def test_settle_moves_each_compared_modes_best_hypothesis_to_its_peak_and_rescores_the_mode() -> None:
    """Two modes (the true circle and its twin), each best hypothesis started 3 deg / 0.3 mm off its peak: after
    settle both sit at their peaks (Gauss-Newton decrement below 1e-3 nats), every member carries its mode's
    polished evidence: the Laplace evidence at its peak."""
    from pinpoint_fg.trackers.svn_modes import settle

    w, _ = _two_circle_window(np.random.default_rng(2))
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    assert found.reps.shape == (2,)
    settled, polished, lin_r = settle(w, lin, found, iters=30)
    assert set(polished.tolist()) == set(found.reps.tolist())
    fresh = w.subset(polished).linearize()
    Hinv = np.linalg.inv(fresh.hess)
    decrement = 0.5 * np.einsum("ni,nij,nj->n", fresh.grad, Hinv, fresh.grad)
    assert np.all(decrement < 1e-3), decrement
    for m, r in enumerate(found.reps):
        assert np.all(settled.log_evidence[found.labels == m] == settled.log_evidence[r])
    # the modes' evidence is the Laplace evidence at the peaks: a fresh linearisation there agrees (the remaining
    # Gauss-Newton decrement is below 1e-3 nats); the one-step prediction from 3 deg away was off by up to 10 nats
    z_fresh = laplace_terms(fresh, w.evidence[polished])[2]
    assert np.allclose(settled.log_evidence[polished], z_fresh, atol=2e-3)


def test_modes_whose_polished_peaks_coincide_are_reported_as_one_with_the_better_evidence() -> None:
    """The true circle's six hypotheses handed to settle as two modes (as clipped Gauss-Newton predictions split them
    after a large motion): both representatives polish to one optimum. settle keeps the tracker's three groups;
    join_coincident reports one mode there, with all six members and the better of the two polished evidences, and
    the twin as a mode of its own. Basins without such a pair are returned as they are."""
    from pinpoint_fg.trackers.svn_modes import Basins, join_coincident, scaled_distance, settle

    w, _ = _two_circle_window(np.random.default_rng(2))
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    assert found.reps.shape == (2,)
    assert join_coincident(found) is found
    true_mode = int(found.labels[0])
    rows = np.flatnonzero(found.labels == true_mode)
    assert rows.tolist() == [0, 1, 2, 3, 4, 5]
    labels = found.labels.copy()
    labels[rows[3:]] = 2  # a third mode: the true circle's last three hypotheses
    best = lambda r: int(r[np.argmax(found.log_evidence[r])])  # noqa: E731
    reps = found.reps.copy()
    reps[true_mode] = best(rows[:3])
    split = Basins(found.log_evidence, found.peaks, labels, np.r_[reps, best(rows[3:])], found.converged)

    settled, _, _ = settle(w, lin, split, iters=30)
    assert settled.reps.shape == (3,)
    copies = settled.reps[[true_mode, 2]]
    assert scaled_distance(w.newest[copies[0]], w.newest[copies[1]]) < 0.05  # one optimum, reached twice

    joined = join_coincident(settled)
    assert joined.reps.shape == (2,)
    assert np.unique(joined.labels[rows]).size == 1 and joined.labels[6] != joined.labels[0]
    m = int(joined.labels[0])
    z_copies = settled.mode_log_evidence[[true_mode, 2]]
    assert joined.mode_log_evidence[m] == np.max(z_copies)
    assert joined.reps[m] == copies[int(np.argmax(z_copies))]
    assert np.all(joined.log_evidence[rows] == joined.mode_log_evidence[m])
    assert joined.mode_log_evidence[1 - m] == settled.mode_log_evidence[1 - true_mode]
    assert np.all(joined.counts() == [6, 6])
    assert joined.weights[m] == pytest.approx(1.0 / (1.0 + np.exp(joined.mode_log_evidence[1 - m] - np.max(z_copies))))
    # a tighter separation keeps modes apart that the default joins
    assert join_coincident(settled, separation=0.0).reps.shape == (3,)
    # the worse copy kept first (the tracker's MAP mode): it stays, with its own rep, and takes the better evidence
    worse = [true_mode, 2][int(np.argmin(z_copies))]
    kept_first = join_coincident(settled, first=worse)
    mk = int(kept_first.labels[0])
    assert kept_first.reps.shape == (2,) and kept_first.reps[mk] == settled.reps[worse]
    assert kept_first.mode_log_evidence[mk] == np.max(z_copies)
    # compared at the poses given: the copy reported 30 deg away is a mode of its own
    peaks = settled.peaks[settled.reps].copy()
    peaks[2] = peaks[2] @ se3_exp(np.r_[np.deg2rad(30.0), 0, 0, 0, 0, 0])
    assert join_coincident(settled, peaks=peaks).reps.shape == (3,)


def test_every_member_of_a_settled_mode_takes_its_peaks_books_after_the_next_marginalisation() -> None:
    """Evidence is kept per mode: after the next frame's push, members carry the prior and evidence their
    polished rep's own marginalisation gave — the prior marginalised at the peak, not at the member's pose."""
    from pinpoint_fg.trackers.svn_modes import book_sources, settle
    from pinpoint_fg.window_rows import share_books

    w, rng = _two_circle_window(np.random.default_rng(4))
    w.evidence = rng.normal(size=12) * 50.0  # drifted books
    found = basins(w.newest, w.linearize(), w.evidence)
    found, polished, _ = settle(w, w.linearize(), found, iters=30)
    index = np.arange(12)
    index[3] = 0  # a pruned hypothesis now copies hypothesis 0
    members, source = book_sources(found, polished, index)
    assert members.size == 10 and not np.isin(polished, members).any()
    assert np.all(found.labels[index[members]] == found.labels[source])
    alone = w.subset(polished)  # each rep's window on its own, pushed the same way
    D = se3_exp(np.r_[0.01, -0.02, 0.01, 1e-4, 0.0, -1e-4])
    frame = w.frames[-1]
    w.push(frame, D, True)
    alone.push(frame, D, True)
    before = w.newest.copy()
    share_books(w, members, source)
    assert np.array_equal(w.newest, before)  # poses are not touched
    for k, r in enumerate(polished):
        rows = np.r_[r, members[source == r]]
        assert np.allclose(w.prior_mean[rows], alone.prior_mean[k], rtol=0, atol=1e-12)
        assert np.allclose(w.prior_W[rows], alone.prior_W[k], rtol=0, atol=1e-9)
        assert np.allclose(w.evidence[rows], alone.evidence[k], rtol=0, atol=1e-9)
    # a rep that was pruned gives no books
    index2 = np.arange(12)
    index2[int(polished[0])] = int(polished[1])
    members2, source2 = book_sources(found, polished[:1], index2)
    assert members2.size == 0 and source2.size == 0


def test_settle_also_starts_from_the_predicted_previous_map_and_keeps_the_better_start_per_row(monkeypatch) -> None:
    """``predicted=(row, pose)``: a start whose Gauss-Newton-predicted peak is one a start of its mode already seeks
    (8 deg off in the same basin) is not polished; one that predicts another peak (the twin circle, given to the true
    circle's best row) is polished beside the others, the row appears once in the result and holds whichever of its
    two starts has the higher evidence."""
    from pinpoint_fg.proposals import twin_poses
    from pinpoint_fg.trackers import svn_modes

    seen: list[np.ndarray] = []
    real_polish = svn_modes.polish

    def spy(sub: Window, lin: Linearization, iters: int, decrement: float = 1e-3) -> Linearization:
        seen.append(sub.newest.copy())
        return real_polish(sub, lin, iters, decrement)

    monkeypatch.setattr(svn_modes, "polish", spy)
    w, _ = _two_circle_window(np.random.default_rng(2))
    found = basins(w.newest, w.linearize(), w.evidence)
    ref = w.subset(np.arange(12))
    _, polished0, lin0 = svn_modes.settle(ref, ref.linearize(), found, iters=30)
    n_plain = seen[-1].shape[0]
    r = int(found.reps[0])
    assert found.labels[r] == found.labels[0]  # the true circle's mode (rows 0-5) is the best
    peak = ref.newest[r].copy()
    z0 = laplace_terms(lin0, ref.evidence[polished0])[2]

    w1 = w.subset(np.arange(12))
    near = peak @ se3_exp(np.r_[np.deg2rad(8.0), 0, 0, 0, 0, 0])
    svn_modes.settle(w1, w1.linearize(), found, iters=30, predicted=(r, near))
    assert seen[-1].shape[0] == n_plain  # same peak: not polished again

    T, _, _ = _ambiguous_scene()
    twin = twin_poses(T[None], CAM.K, NEEDLE.radius_m, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0]
    w2 = w.subset(np.arange(12))
    settled, polished, lin_r = svn_modes.settle(w2, w2.linearize(), found, iters=30, predicted=(r, twin))
    assert seen[-1].shape[0] == n_plain + 1 and np.allclose(seen[-1][-1], twin)
    assert sorted(polished.tolist()) == sorted(polished0.tolist())  # the row appears once
    # the twin start, polished on the row's window alone (its prior is centred on the true circle)
    alone = w.subset([r])
    alone.poses[-1, 0] = twin
    z_twin = laplace_terms(real_polish(alone, alone.linearize(), 30), alone.evidence)[2][0]
    k, k0 = int(np.flatnonzero(polished == r)[0]), int(np.flatnonzero(polished0 == r)[0])
    z = laplace_terms(lin_r, w2.evidence[polished])[2]
    assert z[k] == pytest.approx(max(z0[k0], z_twin), abs=1e-6)
    assert np.allclose(w2.newest[r], peak if z0[k0] >= z_twin else alone.newest[0], atol=1e-9)
    # the start's model given (the tracker's row of its batched pre-transport model, one pose per window): the
    # same polish, to round-off, without linearising that window again
    batch = w.subset(np.arange(12))
    batch.poses[-1, r] = twin
    given = batch.linearize().subset([r])
    w3 = w.subset(np.arange(12))
    settled3, polished3, lin3 = svn_modes.settle(w3, w3.linearize(), found, iters=30, predicted=(r, twin, given))
    assert polished3.tolist() == polished.tolist() and seen[-1].shape[0] == n_plain + 1
    np.testing.assert_allclose(lin3.value, lin_r.value, rtol=1e-9)
    np.testing.assert_allclose(w3.newest, w2.newest, rtol=0, atol=1e-9)
    np.testing.assert_allclose(settled3.log_evidence, settled.log_evidence, rtol=1e-9)


def test_a_proposal_whose_predicted_peak_is_a_held_mode_is_not_polished(monkeypatch) -> None:
    """A candidate 12 deg from the mode, inside its basin (one Gauss-Newton step lands on the mode's peak), is the
    mode itself: dropped after the batched linearisation, never polished, nothing admitted. One 50 deg away (the other
    circle) is not dropped by that test."""
    from pinpoint_fg.proposals import twin_poses
    from pinpoint_fg.trackers import svn_modes

    T, _, arc = _ambiguous_scene()
    cfg = TrackerConfig(CAM, NEEDLE, NoiseConfig(), Switches(grasp_perpendicular=False, tip=False, tail=False))
    lik = FrameLikelihood(Observation(0, 0.0, backbone_px=arc, cam_T_grasper=_grasper(T)), cfg.model)
    w = Window(1, np.diag(np.r_[[0.02 ** 2] * 3, [0.3e-3 ** 2] * 3]), forgetting=1.0)
    w.start(T @ se3_exp(np.random.default_rng(5).normal(size=(8, 6)) * 0.2 * SCALE), lik, FIRST_PRIOR_SIGMA)
    w.prior_mean[:] = T
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    assert found.reps.shape == (1,)
    polished: list[int] = []
    real_polish = svn_modes.polish
    monkeypatch.setattr(svn_modes, "polish", lambda sub, lin, iters, *a: polished.append(sub.newest.shape[0])
                        or real_polish(sub, lin, iters, *a))
    near_pose = T @ se3_exp(np.r_[np.deg2rad(12.0) / np.sqrt(2), np.deg2rad(12.0) / np.sqrt(2), 0, 0, 0, 0])
    monkeypatch.setattr(svn_modes, "mode_proposals", lambda *a, **k: near_pose[None])
    out = svn_modes.propose(w, lin, found, lik, ModeSettings(screen_nats=1e9))
    assert out.screened == 1 and out.windows is None and polished == []
    twin = twin_poses(T[None], CAM.K, NEEDLE.radius_m, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0]
    monkeypatch.setattr(svn_modes, "mode_proposals", lambda *a, **k: twin[None])
    svn_modes.propose(w, lin, found, lik, ModeSettings(screen_nats=1e9))
    assert polished and polished[0] == 1  # the other circle is polished


def test_settle_polishes_the_best_mode_from_several_starts_and_keeps_the_best_as_its_representative() -> None:
    """starts=3: the best mode is also polished from two more of its members (here every member qualifies:
    ``spacing=0``); the mode's representative (and evidence) is the polished start with the highest evidence."""
    from pinpoint_fg.trackers.svn_modes import settle

    T, _, arc = _ambiguous_scene()
    cfg = TrackerConfig(CAM, NEEDLE, NoiseConfig(), Switches(grasp_perpendicular=False, tip=False, tail=False))
    lik = FrameLikelihood(Observation(0, 0.0, backbone_px=arc, cam_T_grasper=_grasper(T)), cfg.model)
    rng = np.random.default_rng(6)
    w = Window(1, np.diag(np.r_[[0.02 ** 2] * 3, [0.3e-3 ** 2] * 3]), forgetting=1.0)
    w.start(T @ se3_exp(rng.normal(size=(10, 6)) * np.r_[[np.deg2rad(3.0)] * 3, [0.3e-3] * 3]), lik,
            FIRST_PRIOR_SIGMA)
    w.prior_mean[:] = T
    w.evidence = rng.normal(size=10)  # each start carries its own books
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    assert found.reps.shape == (1,)
    one, polished1, _ = settle(w.subset(np.arange(10)), lin, found, iters=30, starts=1)
    many, polished, lin_r = settle(w, lin, found, iters=30, starts=3, spacing=0.0)
    assert polished1.tolist() == [int(found.reps[0])]
    assert polished.shape == (3,) and polished[0] == found.reps[0]
    assert np.all(found.labels[polished] == 0)
    z = laplace_terms(lin_r, w.evidence[polished])[2]
    assert many.reps[0] == polished[int(np.argmax(z))]
    assert many.mode_log_evidence[0] == pytest.approx(np.max(z), abs=1e-9)
    assert many.mode_log_evidence[0] >= one.mode_log_evidence[0] - 1e-9


def test_extra_starts_are_the_lowest_cost_members_whose_predicted_peaks_lie_a_kernel_scale_from_every_start() -> None:
    """Members predicting (nearly) the rep's peak, or one already chosen, are skipped however cheap they are."""
    from pinpoint_fg.trackers.svn_modes import Basins, _extra_starts

    tangent = {  # predicted peak of each member, in scaled units from the rep's (row 0)
        0: [0, 0, 0, 0, 0, 0], 1: [0.6, 0, 0, 0, 0, 0], 2: [0, 0.7, 0, 0, 0, 0], 3: [1.5, 0, 0, 0, 0, 0],
        4: [1.6, 0, 0, 0, 0, 0], 5: [0, 0, 0, 0, 1.5, 0], 6: [0, 0, 0, 3.0, 0, 0],
    }
    peaks = se3_exp(np.array([tangent[k] for k in range(7)], dtype=float) * SCALE)
    labels = np.array([0, 0, 0, 0, 0, 0, 1])  # row 6 is another mode
    found = Basins(np.zeros(7), peaks, labels, np.array([0, 6]), np.ones(7, bool))
    cost = np.array([0.0, 1.0, 2.0, 3.0, 2.5, 4.0, 0.5])
    # 1 and 2 are cheapest but within one unit of the rep; 4 is cheaper than 3 and both lie together: 4, then 5
    assert _extra_starts(found, 0, 0, cost, 2, spacing=1.0) == [4, 5]
    assert _extra_starts(found, 0, 0, cost, 1, spacing=1.0) == [4]
    assert _extra_starts(found, 0, 0, cost, 3, spacing=1.0) == [4, 5]  # no third distinct peak
    assert _extra_starts(found, 0, 0, cost, 2, spacing=0.5) == [1, 2]  # 0.5 unit: the near members qualify
    assert _extra_starts(found, 0, 0, cost, 2, spacing=10.0) == []


def test_scaled_distance_is_bitwise_the_norm_of_the_scaled_tangent() -> None:
    """:func:`scaled_distance` (its inlined norm, equal-shape operands not broadcast) has the bits of
    ``np.linalg.norm(local(A, B) / SCALE, axis=1)`` over the broadcast operands."""
    rng = np.random.default_rng(36)
    P = se3_exp(rng.normal(size=(12, 6)) * np.array([0.3] * 3 + [0.01] * 3))
    for a, b in ((P[0], P), (P, P[::-1]), (P[3], P[3:4]), (P[:, None], P[None, :4])):
        A, B = np.broadcast_arrays(a, b)
        ref = np.linalg.norm(local(A.reshape(-1, 4, 4), B.reshape(-1, 4, 4)) / SCALE, axis=1).reshape(A.shape[:-2])
        assert scaled_distance(a, b).tobytes() == ref.tobytes()


def _poses_about_the_grouping_radius(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 4) poses in clusters about a few centres, half of them turned half a turn (the twin), with rotations
    drawn at 0.5-1.5x the 10 deg grouping radius and some exactly on it to round-off."""
    centres = se3_exp(rng.normal(size=(3, 6)) * np.array([1.0] * 3 + [0.02] * 3))
    twin = se3_exp(np.array([np.pi - 1e-4, 0.0, 0.0, 0.0, 0.0, 0.0]))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.deg2rad(10.0) * rng.choice([rng.uniform(0.5, 1.5), 1.0 + 1e-12, 1.0 - 1e-12], size=n)[:, None]
    xi = np.concatenate([axis * angle, rng.normal(size=(n, 3)) * 2e-4], axis=1)
    base = centres[rng.integers(0, 3, size=n)]
    base = np.where(rng.random(n)[:, None, None] < 0.5, base @ twin, base)
    return base @ se3_exp(xi)


def test_rotation_beyond_rules_out_only_poses_beyond_the_angle() -> None:
    """Never true for a rotation within the angle (by :func:`local`'s own logarithm), true past it by 1e-5;
    rotations drawn about each reference at 0-2x the angle, on it to 1e-12 and 1e-6, and near a half turn."""
    rng = np.random.default_rng(37)
    angle = np.deg2rad(10.0)
    for T_a in se3_exp(rng.normal(size=(5, 6)) * np.array([1.0] * 3 + [0.02] * 3)):
        axis = rng.normal(size=(400, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        factor = rng.choice([1.0 - 1e-12, 1.0 + 1e-12, 1.0 - 1e-6, 1.0 + 1e-6, np.pi / angle - 1e-3], size=400)
        factor = np.where(rng.random(400) < 0.5, rng.uniform(0.0, 2.0, size=400), factor)
        xi = np.concatenate([axis * (angle * factor)[:, None], rng.normal(size=(400, 3)) * 1e-3], axis=1)
        T_b = T_a @ se3_exp(xi)
        theta = np.linalg.norm(local(np.broadcast_to(T_a, T_b.shape), T_b)[:, :3], axis=1)
        beyond = rotation_beyond(T_a[:3, :3], T_b[:, :3, :3], angle)
        assert not np.any(beyond & (theta <= angle * (1 + 1e-7)))
        assert np.all(beyond[theta > angle * (1 + 1e-5)])
        assert beyond.sum() > 100 and (~beyond).sum() > 100
        assert not rotation_beyond(T_a[:3, :3], T_b[:, :3, :3], np.pi).any()


@pytest.mark.parametrize("seed", range(6))
def test_greedy_groups_equal_the_plain_loop_over_every_free_pose(seed: int) -> None:
    """Skipping the logarithms :func:`rotation_beyond` rules out leaves the groups as the plain loop forms them."""
    rng = np.random.default_rng(40 + seed)
    P = _poses_about_the_grouping_radius(rng, 50)
    order = rng.permutation(50)
    labels_ref, reps_ref = np.full(50, -1), []
    for i in order:
        if labels_ref[i] >= 0:
            continue
        free = np.flatnonzero(labels_ref < 0)
        labels_ref[free[scaled_distance(P[i], P[free]) < 2.0]] = len(reps_ref)
        labels_ref[i] = len(reps_ref)
        reps_ref.append(int(i))
    labels, reps = _greedy_groups(P, order, 2.0)
    assert labels.tolist() == labels_ref.tolist() and reps.tolist() == reps_ref
    assert len(reps) > 3


def _rerouting_setup(monkeypatch, advantage_nats: float):  # noqa: ANN001, ANN202
    """Two modes, the true circle (rows 0-5, a broad prior: a jump costs little) and its twin (rows 6-11, a tight
    prior on the twin), whose own history is shifted so that the route from the true mode into the twin's basin (its
    proposal, the twin pose, polished on the true mode's window) beats the twin's own by ``advantage_nats``."""
    from pinpoint_fg.proposals import twin_poses
    from pinpoint_fg.trackers import svn_modes

    w, _ = _two_circle_window(np.random.default_rng(6))
    w.prior_W[:6] *= 0.02  # the true mode's prior: 50x the standard deviation
    T, _, _ = _ambiguous_scene()
    twin = twin_poses(T[None], CAM.K, NEEDLE.radius_m, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0]
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    assert found.reps.shape == (2,)
    settled, _, _ = svn_modes.settle(w.subset(np.arange(12)), lin, found, iters=30)
    twin_mode = int(found.labels[6])
    assert np.all(found.labels[6:] == twin_mode) and np.all(found.labels[:6] != twin_mode)
    # the route: the true mode's best hypothesis's window with the twin pose, polished
    route = w.subset([int(found.reps[1 - twin_mode])])
    route.poses[-1] = twin[None]
    _, _, z_route = laplace_terms(svn_modes.polish(route, route.linearize(), ModeSettings().polish_iters),
                                  route.evidence)
    w.evidence[6:] += float(settled.mode_log_evidence[twin_mode] - z_route[0]) + advantage_nats
    monkeypatch.setattr(svn_modes, "mode_proposals", lambda T_mode, *a, **k: twin[None])
    lin = w.linearize()
    return w, lin, basins(w.newest, lin, w.evidence), twin_mode, float(z_route[0])


def test_a_proposal_that_is_a_better_route_into_a_held_mode_takes_over_its_books(monkeypatch) -> None:
    """With routes on (``reroute_nats`` finite; module docstring, *Routes*) the better route into a mode wins: a
    proposal landing in another held mode's basin whose Laplace evidence beats that mode's by more than
    ``reroute_nats`` replaces the mode's windows (prior, evidence, newest pose: the first copy exact, the others
    jittered), and the mode's weight becomes the route's. One that beats it by less leaves the mode's own history
    alone, and so does the default (off)."""
    from pinpoint_fg.trackers.svn_modes import Admitted, allot, propose

    w, lin, found, twin_mode, z_route = _rerouting_setup(monkeypatch, advantage_nats=3.0)
    # off by default (inf): the held mode keeps its own history, nothing is polished or admitted
    assert propose(w.subset(np.arange(12)), lin, found, w.frames[-1], ModeSettings(screen_nats=1e9)).windows is None
    settings = ModeSettings(screen_nats=1e9, reroute_nats=1.0)
    out = propose(w, lin, found, w.frames[-1], settings)
    assert out.windows is not None and out.replaced().tolist() == [twin_mode]
    assert out.log_evidence[0] == pytest.approx(z_route, rel=0, abs=1e-9)  # propose polishes it alike
    rescored = out.basins
    assert out.log_evidence[0] > rescored.mode_log_evidence[twin_mode] + 2.9  # the 3 nats, to the polish
    before = w.newest.copy(), w.evidence.copy()
    moved = allot(w, rescored, out, settings, np.random.default_rng(0), np.r_[[1e-3] * 3, [1e-5] * 3])
    members = np.flatnonzero(rescored.labels == twin_mode)
    others = np.flatnonzero(rescored.labels != twin_mode)
    assert moved == members.size == 6
    assert np.all(w.evidence[members] == out.windows.evidence[0])  # the route's books: the true mode's history
    assert np.all(w.prior_mean[members] == out.windows.prior_mean[0])
    assert np.array_equal(w.newest[members[0]], out.windows.newest[0])  # the first copy exact
    assert not np.any(np.all(w.newest[members[1:]] == out.windows.newest[0], axis=(1, 2)))  # the others jittered
    assert np.array_equal(w.newest[others], before[0][others]) and np.array_equal(w.evidence[others],
                                                                                   before[1][others])
    # beaten by less than the margin: the held mode keeps its own history (nothing admitted, nothing polished)
    w2, lin2, found2, _, _ = _rerouting_setup(monkeypatch, advantage_nats=0.5)
    out2 = propose(w2, lin2, found2, w2.frames[-1], settings)
    assert out2.windows is None
    assert isinstance(out2, Admitted)


def test_reroute_margin_is_checked() -> None:
    for bad in (-0.5, float("nan")):
        with pytest.raises(ValueError, match="reroute_nats"):
            ModeSettings(reroute_nats=bad)
    assert ModeSettings(reroute_nats=float("inf")).reroute_nats == float("inf")


def test_frame_polish_iters_is_checked() -> None:
    """A negative count meant 0 silently; 2.5 or '6' failed inside tracking."""
    for bad in (-3, 2.5, "6", float("nan"), True):
        with pytest.raises(ValueError, match="frame_polish_iters"):
            ModeSettings(frame_polish_iters=bad)
    assert ModeSettings(frame_polish_iters=np.int64(6)).frame_polish_iters == 6


def test_frame_polish_admits_a_proposal_whose_raw_pose_is_off_the_frames_optimum(monkeypatch) -> None:
    """``frame_polish_iters``: a proposal 15 deg off the other circle is screened out as proposed (its one-step
    prediction is far from the peak), but polished on the frame first, as MHT's proposals are, it reaches the other
    circle and is admitted. The exact twin is admitted either way."""
    from pinpoint_fg.proposals import twin_poses
    from pinpoint_fg.trackers import svn_modes

    T, _, arc = _ambiguous_scene()
    sw = Switches(grasp_perpendicular=False, grasp_position=False, tip=False, tail=False)
    lik = FrameLikelihood(Observation(0, 0.0, backbone_px=arc), TrackerConfig(CAM, NEEDLE, NoiseConfig(), sw).model)
    w = Window(1, np.diag(np.r_[[0.3 ** 2] * 3, [3e-3 ** 2] * 3]), forgetting=1.0)  # frames far apart: a wide prior
    w.start(T @ se3_exp(np.random.default_rng(5).normal(size=(8, 6)) * 0.2 * SCALE), lik, FIRST_PRIOR_SIGMA)
    w.prior_mean[:] = T
    lin = w.linearize()
    found = basins(w.newest, lin, w.evidence)
    twin = twin_poses(T[None], CAM.K, NEEDLE.radius_m, NEEDLE.tail_angle_rad, NEEDLE.tip_angle_rad)[0]
    for deg, admitted_raw in ((0.0, True), (15.0, False)):
        proposal = twin @ se3_exp(np.r_[np.deg2rad(deg), 0, 0, 0, 0, 0])
        monkeypatch.setattr(svn_modes, "mode_proposals", lambda *a, proposal=proposal, **k: proposal[None])
        raw = svn_modes.propose(w, lin, found, lik, ModeSettings())
        polished = svn_modes.propose(w, lin, found, lik, ModeSettings(frame_polish_iters=6))
        assert (raw.windows is not None) == admitted_raw, deg
        assert polished.windows is not None and polished.windows.newest.shape == (1, 4, 4), deg
        n_twin = twin[:3, 2] * np.sign(twin[2, 2])
        n_new = polished.windows.newest[0, :3, 2]
        assert np.degrees(np.arccos(min(1.0, abs(n_new @ n_twin)))) < 3.0, deg  # the other circle, not a third pose
