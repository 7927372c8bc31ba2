"""Modes of particle sets (persistence clustering), the modes verdict and the least-observable direction."""

from __future__ import annotations

import numpy as np
import pytest

from factors.lie import retract, se3_exp
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.posterior.spread import tangent_spread
from pinpoint_fg.posterior.summary import (
    BIMODAL_MODE_WEIGHT,
    K_MAX,
    WEAK_UNITS,
    bimodal_from_modes,
    modes_from_particles,
    modes_of_estimate,
    posterior_columns,
    weak_direction,
)

S = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)
T0 = np.eye(4)
T0[:3, 3] = [0.01, -0.005, 0.08]


def _cloud(rng: np.random.Generator, n: int, centre: np.ndarray, sig: float) -> tuple[np.ndarray, np.ndarray]:
    """n poses T0 Exp(S (centre + sig z)), and their Gaussian log-density about the centre (scaled units)."""
    z = rng.normal(size=(n, 6)) * sig
    P = retract(np.broadcast_to(T0, (n, 4, 4)), (centre + z) * S)
    return P, -0.5 * np.sum((z / sig) ** 2, axis=1)


def _two_clusters(n1: int, n2: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    far = np.array([4.0, -3.0, 2.0, 10.0, 6.0, -8.0])  # 20 deg-ish rotation and ~14 mm away
    P1, l1 = _cloud(rng, n1, np.zeros(6), 1.0)
    P2, l2 = _cloud(rng, n2, far, 1.0)
    P = np.concatenate([P1, P2])
    lp = np.concatenate([l1, l2 - 0.5])  # the lighter mode's peak is also lower
    perm = rng.permutation(n1 + n2)
    inv = np.argsort(perm)
    return P[perm], lp[perm], [inv[:n1], inv[n1:]]


def test_two_clusters_recover_weights_peaks_and_covariances() -> None:
    P, lp, members = _two_clusters(42, 18)
    modes = modes_from_particles(P, lp)
    assert len(modes) == 2
    assert [m.weight for m in modes] == pytest.approx([0.7, 0.3], abs=1e-12)
    for mode, idx in zip(modes, members, strict=True):
        peak = idx[np.argmax(lp[idx])]
        np.testing.assert_array_equal(mode.cam_T_needle, P[peak])
        expected = tangent_spread(P[peak], P[idx]).cov_xi
        np.testing.assert_allclose(mode.cov_xi, expected, rtol=1e-12, atol=1e-20)
    assert bimodal_from_modes(modes)


def test_weighted_large_set_with_copies_uses_the_pf_weights() -> None:
    P, lp, members = _two_clusters(30, 30, seed=3)
    rng = np.random.default_rng(1)
    idx = rng.integers(0, 60, size=3000)  # resampling copies, as in a particle filter
    w = rng.uniform(0.5, 1.5, size=3000)
    w[np.isin(idx, members[1])] *= 0.25
    w /= w.sum()
    modes = modes_from_particles(P[idx], lp[idx], w)
    assert len(modes) == 2
    second = float(w[np.isin(idx, members[1])].sum())
    assert [m.weight for m in modes] == pytest.approx([1.0 - second, second], abs=1e-12)
    assert sum(m.weight for m in modes) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("n", [20, 50, 400, 3000])
@pytest.mark.parametrize("sig", [0.3, 1.0, 5.0])
def test_single_gaussian_cloud_is_one_mode(n: int, sig: float) -> None:
    for seed in range(3):
        P, lp = _cloud(np.random.default_rng(seed), n, np.zeros(6), sig)
        modes = modes_from_particles(P, lp)
        assert len(modes) == 1
        assert modes[0].weight == pytest.approx(1.0)
        assert not bimodal_from_modes(modes)
        np.testing.assert_array_equal(modes[0].cam_T_needle, P[np.argmax(lp)])


def test_at_most_k_max_modes_and_mass_is_kept() -> None:
    rng = np.random.default_rng(0)
    parts, lps = [], []
    for c in range(6):
        P, lp = _cloud(rng, 10 + 2 * c, np.array([0, 0, 0, 30.0 * c, 0, 0]), 1.0)
        parts.append(P)
        lps.append(lp)
    P, lp = np.concatenate(parts), np.concatenate(lps)
    modes = modes_from_particles(P, lp, k_max=4)
    assert len(modes) == 4
    assert sum(m.weight for m in modes) == pytest.approx(1.0)
    assert [m.weight for m in modes] == sorted((m.weight for m in modes), reverse=True)
    assert len(modes_from_particles(P, lp, k_max=6)) == 6


def test_modes_verdict_threshold() -> None:
    def modes(*w: float) -> tuple[Mode, ...]:
        return tuple(Mode(np.eye(4), x, np.eye(6)) for x in w)

    assert bimodal_from_modes(modes(1.0 - BIMODAL_MODE_WEIGHT, BIMODAL_MODE_WEIGHT))
    assert not bimodal_from_modes(modes(0.91, 0.09))
    assert not bimodal_from_modes(modes(1.0))
    assert bimodal_from_modes(modes(0.5, 0.3, 0.2))


def test_weak_direction_of_a_known_information_matrix() -> None:
    # information in deg/mm units with eigenvalues 1..6 along a rotated basis; the weakest is 0.25
    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    lam = np.array([0.25, 1.0, 2.0, 3.0, 5.0, 9.0])
    info_s = Q @ np.diag(lam) @ Q.T
    info = info_s * np.outer(WEAK_UNITS, WEAK_UNITS)  # back to rad / m units
    u, sigma = weak_direction(information=info)
    assert sigma == pytest.approx(2.0, rel=1e-9)
    assert abs(float(u @ Q[:, 0])) == pytest.approx(1.0, abs=1e-9)
    assert u[np.argmax(np.abs(u))] > 0
    u2, sigma2 = weak_direction(cov_xi=np.linalg.inv(info))
    np.testing.assert_allclose(u2, u, atol=1e-7)
    assert sigma2 == pytest.approx(sigma, rel=1e-7)


def test_weak_direction_picks_depth_when_depth_is_worst() -> None:
    cov = np.diag([np.deg2rad(1.0) ** 2] * 3 + [(0.2e-3) ** 2, (0.2e-3) ** 2, (3e-3) ** 2])
    u, sigma = weak_direction(cov)
    np.testing.assert_allclose(u, [0, 0, 0, 0, 0, 1], atol=1e-12)
    assert sigma == pytest.approx(3.0)  # mm


def _estimate(particles: np.ndarray, lp: np.ndarray, modes: tuple[Mode, ...] | None = None) -> Estimate:
    return Estimate(frame=0, t_s=0.0, cam_T_needle=particles[np.argmax(lp)], q95_trans_m=0.0, q95_rot_rad=0.0,
                    cov_xi=np.diag([1e-4] * 3 + [1e-6, 1e-6, 4e-6]), iterations=1, latency_ms=1.0, particles=particles,
                    log_posterior=lp, modes=modes)


def test_modes_of_estimate_prefers_the_trackers_modes_and_handles_map() -> None:
    P, lp, _ = _two_clusters(30, 20)
    own = (Mode(se3_exp(np.full(6, 0.01)), 0.2, np.eye(6)), Mode(np.eye(4), 0.8, 2 * np.eye(6)))
    got = modes_of_estimate(_estimate(P, lp, own))
    assert [m.weight for m in got] == [0.8, 0.2]
    assert [m.weight for m in modes_of_estimate(_estimate(P, lp))] == pytest.approx([0.6, 0.4])
    est = _estimate(P[:1], lp[:1])
    (single,) = modes_of_estimate(est)
    assert single.weight == 1.0
    np.testing.assert_array_equal(single.cov_xi, est.cov_xi)
    cols = posterior_columns((single,), est.cam_T_needle)
    assert cols["bimodal_modes"] == 0.0
    assert cols["weak_sigma"] == pytest.approx(2.0)  # 2 mm along z beats 0.57 deg and 1 mm
    assert cols["weak_vz"] == 1.0


def test_modes_of_estimate_reports_at_most_k_max_modes_renormalised() -> None:
    """An MHT bank of six branches: the four heaviest, their weights renormalised over them (the result format
    holds 1 to 4 modes per frame summing to 1; six modes were a ValueError traceback in track's writer)."""
    P, lp, _ = _two_clusters(30, 20)
    w = [0.05, 0.4, 0.02, 0.3, 0.03, 0.2]
    own = tuple(Mode(se3_exp(np.full(6, 0.01 * k)), wk, np.eye(6) * (k + 1)) for k, wk in enumerate(w))
    got = modes_of_estimate(_estimate(P, lp, own))
    assert len(got) == K_MAX == 4
    assert [m.weight for m in got] == pytest.approx([0.4 / 0.95, 0.3 / 0.95, 0.2 / 0.95, 0.05 / 0.95], rel=1e-15)
    assert [m.cov_xi[0, 0] for m in got] == [2.0, 4.0, 6.0, 1.0]
    assert sum(m.weight for m in got) == pytest.approx(1.0, abs=1e-15)


def test_bad_inputs_are_rejected() -> None:
    P, lp, _ = _two_clusters(5, 5)
    with pytest.raises(ValueError):
        modes_from_particles(P, lp[:3])
    with pytest.raises(ValueError):
        modes_from_particles(P, lp, -np.ones(10))
    with pytest.raises(ValueError):
        weak_direction()


@pytest.mark.parametrize(("sep", "n_modes"), [(1.0, 1), (1.9, 1), (3.0, 2)])
def test_peaks_nearer_than_the_resolution_are_one_mode(sep: float, n_modes: int) -> None:
    # two sharp clusters (std 0.1 units, 50 nats deep valley between them): persistence alone would split
    rng = np.random.default_rng(5)
    c2 = np.array([sep, 0, 0, 0, 0, 0])
    P1, l1 = _cloud(rng, 30, np.zeros(6), 0.1)
    P2, l2 = _cloud(rng, 20, c2, 0.1)
    modes = modes_from_particles(np.concatenate([P1, P2]), np.concatenate([l1, l2]))
    assert len(modes) == n_modes
    assert [m.weight for m in modes] == pytest.approx([1.0] if n_modes == 1 else [0.6, 0.4])


def test_zero_weight_particles_form_no_mode() -> None:
    """PF weights can underflow to exactly 0: a cluster of such particles holds no mass and is no mode."""
    rng = np.random.default_rng(5)
    base = np.eye(4)
    base[2, 3] = 0.05
    near = base @ se3_exp(rng.normal(size=(30, 6)) * np.r_[[0.01] * 3, [1e-4] * 3])
    far_xi = rng.normal(size=(30, 6)) * np.r_[[0.01] * 3, [1e-4] * 3] + np.r_[0, 0, 2.0, 0, 0, 0]
    far = base @ se3_exp(far_xi)
    P = np.concatenate([near, far])
    w = np.r_[np.full(30, 1 / 30), np.zeros(30)]
    logp = np.r_[np.zeros(30), np.full(30, -50.0)]
    modes = modes_from_particles(P, logp, w)
    assert len(modes) == 1 and np.isclose(modes[0].weight, 1.0)
