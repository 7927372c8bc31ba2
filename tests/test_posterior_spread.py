"""Hand-checked cases for pinpoint_fg.posterior.spread (weighted quantile, tangent spread)."""

from __future__ import annotations

import numpy as np
import pytest

from factors.lie import retract, se3_exp
from pinpoint_fg.errors import InputError
from pinpoint_fg.posterior.spread import tangent_covariance, tangent_spread, weighted_quantile

# ----------------------------------------------------------------------------- weighted quantile


def test_weighted_quantile_equal_weights_is_numpy_inverted_cdf() -> None:
    rng = np.random.default_rng(0)
    for n in (1, 2, 4, 7, 20, 50, 3000):
        v = rng.normal(size=(3, n))
        for q in (0.0, 0.05, 0.25, 0.5, 0.75, 0.9, 0.95, 1.0):
            ref = np.quantile(v, q, axis=-1, method="inverted_cdf")
            np.testing.assert_array_equal(weighted_quantile(v, None, q), ref)
            np.testing.assert_array_equal(weighted_quantile(v, np.full((3, n), 0.3), q), ref)
    # ties and exact k/N boundaries: q*N = 19 for N = 20
    v = np.arange(1.0, 21.0)
    assert weighted_quantile(v, None, 0.95) == np.quantile(v, 0.95, method="inverted_cdf") == 19.0


def test_weighted_quantile_hand_case_unequal_weights() -> None:
    v = np.array([3.0, 1.0, 4.0, 2.0])  # unsorted on purpose
    w = np.array([0.3, 0.1, 0.4, 0.2])  # sorted: 1 (.1), 2 (.2), 3 (.3), 4 (.4); CDF .1 .3 .6 1.0
    assert weighted_quantile(v, w, 0.0) == 1.0
    assert weighted_quantile(v, w, 0.05) == 1.0
    assert weighted_quantile(v, w, 0.25) == 2.0
    assert weighted_quantile(v, w, 0.59) == 3.0
    assert weighted_quantile(v, w, 0.61) == 4.0
    assert weighted_quantile(v, w, 0.95) == 4.0
    # zero-weight values never come out
    assert weighted_quantile(np.array([10.0, 1.0, 2.0]), np.array([0.0, 1.0, 1.0]), 1.0) == 2.0
    assert weighted_quantile(np.array([-5.0, 1.0, 2.0]), np.array([0.0, 1.0, 1.0]), 0.0) == 1.0


def test_weighted_quantile_bad_input() -> None:
    with pytest.raises(InputError):
        weighted_quantile(np.ones(3), None, 1.5)
    with pytest.raises(InputError):
        weighted_quantile(np.ones(3), np.array([1.0, -1.0, 1.0]), 0.5)
    with pytest.raises(InputError):
        weighted_quantile(np.ones(3), np.zeros(3), 0.5)
    with pytest.raises(InputError):
        weighted_quantile(np.array([1.0, np.nan]), None, 0.5)


# ----------------------------------------------------------------------------- tangent spread


def test_tangent_spread_q95_hand_case() -> None:
    T_ref = se3_exp(np.array([0.3, -0.1, 0.2, 0.01, -0.02, 0.05]))
    k = np.arange(1, 21)
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(20, 2, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    xi = np.concatenate([dirs[:, 0] * np.deg2rad(k)[:, None], dirs[:, 1] * 1e-3 * k[:, None]], axis=1)
    P = retract(T_ref[None], xi[rng.permutation(20)])
    s = tangent_spread(T_ref, P)
    # inverted CDF with 20 equal weights: the 19th smallest of 1..20
    assert s.q95_trans_m == pytest.approx(19e-3, rel=1e-9)
    assert s.q95_rot_rad == pytest.approx(np.deg2rad(19.0), rel=1e-9)
    # all weight on particle with index 4 of the original order
    w = np.zeros(20)
    P2 = retract(T_ref[None], xi)
    w[4] = 1.0
    s2 = tangent_spread(T_ref, P2, w)
    assert s2.q95_trans_m == pytest.approx(5e-3, rel=1e-9)
    np.testing.assert_allclose(s2.mean_xi, xi[4], atol=1e-12)
    np.testing.assert_allclose(s2.cov_xi, 0.0, atol=1e-20)


def test_tangent_spread_weighted_mean_and_cov_hand_case() -> None:
    T_ref = se3_exp(np.array([0.0, 0.2, 0.0, 0.0, 0.0, 0.08]))
    a = np.array([0.01, 0.0, 0.0, 0.001, 0.0, 0.0])
    b = np.array([0.0, -0.02, 0.0, 0.0, 0.0, 0.002])
    P = retract(T_ref[None], np.stack([a, b]))
    s = tangent_spread(T_ref, P, np.array([1.0, 3.0]))  # normalised to 0.25, 0.75
    np.testing.assert_allclose(s.mean_xi, 0.25 * a + 0.75 * b, atol=1e-14)
    np.testing.assert_allclose(s.cov_xi, 0.25 * 0.75 * np.outer(a - b, a - b), atol=1e-16)
    # batched over frames with one shared reference pose
    PF = np.stack([P, P[::-1]])
    sF = tangent_spread(T_ref, PF, np.array([[1.0, 3.0], [3.0, 1.0]]))
    np.testing.assert_allclose(sF.mean_xi, np.stack([s.mean_xi, s.mean_xi]), atol=1e-14)
    assert sF.q95_trans_m.shape == (2,)
    with pytest.raises(InputError):
        tangent_spread(np.tile(T_ref, (3, 1, 1)), PF)


@pytest.mark.parametrize("weighted", [False, True])
def test_tangent_covariance_is_tangent_spreads_cov_bit_for_bit(weighted: bool) -> None:
    """The covariance alone (SVN's modes) is the very same numbers as the full spread's, and checks alike."""
    rng = np.random.default_rng(3)
    T_ref = se3_exp(rng.normal(size=6) * [1, 1, 1, 0.01, 0.01, 0.01])
    P = retract(T_ref[None], rng.normal(size=(40, 6)) * [0.2, 0.2, 0.2, 2e-3, 2e-3, 2e-3])
    w = rng.uniform(0.1, 1.0, size=40) if weighted else None
    assert tangent_covariance(T_ref, P, w).tobytes() == tangent_spread(T_ref, P, w).cov_xi.tobytes()
    with pytest.raises(InputError):
        tangent_covariance(T_ref, P[:, :3])
