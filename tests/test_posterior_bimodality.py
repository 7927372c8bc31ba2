"""The bimodality rule of pinpoint_fg.posterior.bimodality on constructed particle sets."""

from __future__ import annotations

import numpy as np
import pytest

from factors.lie import retract, se3_exp
from pinpoint_fg.errors import InputError
from pinpoint_fg.posterior.bimodality import (
    ROT_UNIT_RAD,
    TRANS_UNIT_M,
    ashman_d,
    assess_bimodality,
    principal_plane,
    systematic_resample,
    tangent_at_map,
)

T_MAP = se3_exp(np.array([0.4, -0.3, 0.2, 0.002, -0.001, 0.03]))
SCALE = np.array([ROT_UNIT_RAD] * 3 + [TRANS_UNIT_M] * 3)


def cloud(rng: np.random.Generator, n: int, centre_scaled, std_scaled: float) -> np.ndarray:
    """n poses T_MAP * Exp(xi), xi ~ N(centre, std^2 I) in scaled units (5 deg, 1 mm)."""
    xi = (np.asarray(centre_scaled, dtype=float) + std_scaled * rng.normal(size=(n, 6))) * SCALE
    return retract(T_MAP[None], xi)


FAR = np.array([6.0, 0.0, 0.0, 0.0, 0.0, 8.0])  # 30 deg about x and 8 mm along z: |FAR| = 10 units


def shaped_set(case: str, rng: np.random.Generator) -> np.ndarray:
    """A particle set of a named shape: ``one`` Gaussian (50), ``two`` separated clusters (25 + 25), ``overlap``
    (30 + 20, a fifth of FAR apart), ``weighted`` (200 + 100, for random weights), ``thinned`` (1500 + 600, above
    the fit's point cap), ``duplicates`` (10 poses, each 5 times)."""
    if case == "one":
        return cloud(rng, 50, np.zeros(6), 1.0)
    if case == "two":
        return np.concatenate([cloud(rng, 25, np.zeros(6), 0.7), cloud(rng, 25, FAR, 0.7)])
    if case == "overlap":
        return np.concatenate([cloud(rng, 30, np.zeros(6), 1.0), cloud(rng, 20, FAR / 5, 1.0)])
    if case == "weighted":
        return np.concatenate([cloud(rng, 200, np.zeros(6), 1.0), cloud(rng, 100, FAR, 1.0)])
    if case == "thinned":
        return np.concatenate([cloud(rng, 1500, np.zeros(6), 1.0), cloud(rng, 600, FAR, 1.0)])
    if case == "duplicates":
        return np.repeat(cloud(rng, 10, np.zeros(6), 1.0), 5, axis=0)
    raise ValueError(case)


def test_tangent_at_map_scaling() -> None:
    xi = np.array([[1.0, 0, 0, 1, 0, 0], [0, -2, 0, 0, 0, 3]]) * SCALE
    np.testing.assert_allclose(
        tangent_at_map(T_MAP, retract(T_MAP[None], xi)), [[1, 0, 0, 1, 0, 0], [0, -2, 0, 0, 0, 3]], atol=1e-9
    )
    with pytest.raises(InputError):
        tangent_at_map(T_MAP, np.eye(4))


def test_ashman_d_hand_values() -> None:
    means = np.array([[0.0] * 6, [4.0] + [0.0] * 5])
    assert ashman_d(means, np.stack([np.eye(6), np.eye(6)])) == pytest.approx(4.0)
    wide = np.eye(6)
    wide[0, 0] = 9.0
    wide[1, 1] = 100.0  # variance off the joining axis does not count
    assert ashman_d(means, np.stack([wide, np.eye(6)])) == pytest.approx(np.sqrt(2) * 4 / np.sqrt(10))
    assert ashman_d(np.zeros((2, 6)), np.stack([np.eye(6), np.eye(6)])) == 0.0


def test_systematic_resample_counts() -> None:
    w = np.array([0.05, 0.5, 0.0, 0.3, 0.15])
    idx = systematic_resample(w, 40, np.random.default_rng(7))
    counts = np.bincount(idx, minlength=5)
    assert counts.sum() == 40
    assert np.all(counts >= np.floor(40 * w)) and np.all(counts <= np.ceil(40 * w))
    assert counts[2] == 0


def test_two_separated_equal_clusters_are_bimodal() -> None:
    rng = np.random.default_rng(0)
    P = np.concatenate([cloud(rng, 100, np.zeros(6), 1.0), cloud(rng, 100, FAR, 1.0)])
    v = assess_bimodality(P, T_MAP)
    assert v.bimodal and v.reason == "bimodal"
    assert v.bic2 < v.bic1 and v.ashman_d > 7.0 and v.minor_weight == pytest.approx(0.5, abs=0.02)
    order = np.argsort(np.linalg.norm(v.means, axis=1))
    np.testing.assert_allclose(v.means[order], [np.zeros(6), FAR], atol=0.4)
    assert v.means.shape == (2, 6) and v.covariances.shape == (2, 6, 6) and v.n_fit_points == 200
    assert v.gt_component is None and v.truth_in_dominant is None  # no truth given
    # deterministic for a seed
    assert assess_bimodality(P, T_MAP).ashman_d == v.ashman_d


def test_one_gaussian_is_unimodal() -> None:
    rng = np.random.default_rng(1)
    P = cloud(rng, 200, np.zeros(6), 1.0)
    v = assess_bimodality(P, T_MAP, T_gt=T_MAP)
    assert not v.bimodal
    assert v.bic1 < v.bic2 and "bic" in v.reason
    assert v.gt_component is None and v.truth_in_dominant is None
    np.testing.assert_allclose(v.gt_xi_scaled, 0.0, atol=1e-9)


def test_95_5_split_is_unimodal_by_minor_weight() -> None:
    rng = np.random.default_rng(2)
    P = np.concatenate([cloud(rng, 380, np.zeros(6), 1.0), cloud(rng, 20, FAR, 1.0)])
    v = assess_bimodality(P, T_MAP)
    assert v.bic2 < v.bic1 and v.ashman_d > 2.0
    assert v.minor_weight == pytest.approx(0.05, abs=0.01)
    assert not v.bimodal and v.reason == "minor_weight"


def test_overlapping_clusters_are_unimodal_even_when_bic_prefers_two() -> None:
    # a narrow spike inside a broad cloud: BIC strongly prefers two components, but they overlap
    rng = np.random.default_rng(3)
    P = np.concatenate([cloud(rng, 300, np.zeros(6), 0.05), cloud(rng, 300, [0.5, 0, 0, 0, 0, 0], 1.0)])
    v = assess_bimodality(P, T_MAP)
    assert v.bic2 < v.bic1 - 1000.0
    assert v.minor_weight >= 0.1
    assert v.ashman_d < 2.0
    assert not v.bimodal and v.reason == "ashman_d"


def test_truth_is_assigned_to_the_nearer_mean() -> None:
    rng = np.random.default_rng(4)
    P = np.concatenate([cloud(rng, 140, np.zeros(6), 1.0), cloud(rng, 60, FAR, 1.0)])
    near_minor = retract(T_MAP, (FAR + np.array([0.5, -0.5, 0, 0, 0.5, 0])) * SCALE)
    near_major = retract(T_MAP, np.array([0.0, 0.5, 0, 0.5, 0, -0.5]) * SCALE)
    v_minor = assess_bimodality(P, T_MAP, T_gt=near_minor)
    v_major = assess_bimodality(P, T_MAP, T_gt=near_major)
    for v in (v_minor, v_major):
        assert v.bimodal
        assert v.weights[v.dominant] == pytest.approx(0.7, abs=0.02)
    far_idx = int(np.argmax(np.linalg.norm(v_minor.means, axis=1)))
    assert far_idx != v_minor.dominant
    assert v_minor.gt_component == far_idx and v_minor.truth_in_dominant is False
    assert v_major.gt_component == v_major.dominant and v_major.truth_in_dominant is True
    np.testing.assert_allclose(v_minor.gt_xi_scaled, FAR + np.array([0.5, -0.5, 0, 0, 0.5, 0]), atol=1e-6)


def test_weights_are_honoured() -> None:
    rng = np.random.default_rng(5)
    P = np.concatenate([cloud(rng, 150, np.zeros(6), 1.0), cloud(rng, 150, FAR, 1.0)])
    assert assess_bimodality(P, T_MAP).bimodal
    w = np.r_[np.full(150, 0.97 / 150), np.full(150, 0.03 / 150)]
    v = assess_bimodality(P, T_MAP, weights=w)
    assert not v.bimodal and v.minor_weight < 0.1
    w2 = rng.uniform(0.5, 1.5, size=300)
    assert assess_bimodality(P, T_MAP, weights=w2).bimodal
    with pytest.raises(InputError):
        assess_bimodality(P, T_MAP, weights=np.ones(10))
    with pytest.raises(InputError):
        assess_bimodality(P, T_MAP, weights=np.zeros(300))
    with pytest.raises(InputError, match="finite sum"):  # each finite, the sum inf: was an overflow warning
        assess_bimodality(P, T_MAP, weights=np.full(300, 1e308))


def test_degenerate_sets_are_unimodal() -> None:
    same = np.repeat(T_MAP[None], 50, axis=0)
    v = assess_bimodality(same, T_MAP, T_gt=T_MAP)
    assert not v.bimodal and v.reason == "degenerate" and np.isnan(v.bic1)
    np.testing.assert_array_equal(v.weights, [1.0, 0.0])
    rng = np.random.default_rng(6)
    five = np.repeat(cloud(rng, 5, np.zeros(6), 3.0), 10, axis=0)
    assert assess_bimodality(five, T_MAP).reason == "degenerate"
    # a weighted set collapsed onto three particles
    P = cloud(rng, 100, np.zeros(6), 3.0)
    w = np.zeros(100)
    w[[3, 50, 70]] = 1.0
    assert assess_bimodality(P, T_MAP, weights=w).reason == "degenerate"


def test_small_and_large_weighted_sets() -> None:
    """Timings live in the benchmark, not here (tests never assert wall-clock times)."""
    rng = np.random.default_rng(8)
    small = np.concatenate([cloud(rng, 25, np.zeros(6), 0.3), cloud(rng, 25, FAR, 0.3)])
    big = np.concatenate([cloud(rng, 1500, np.zeros(6), 1.0), cloud(rng, 1500, FAR, 1.0)])
    w = rng.uniform(size=3000)
    v_small = assess_bimodality(small, T_MAP)
    v_big = assess_bimodality(big, T_MAP, weights=w)
    assert v_small.bimodal and v_big.bimodal and v_big.n_fit_points == 1000


def test_principal_plane() -> None:
    rng = np.random.default_rng(9)
    X = rng.normal(size=(500, 6)) * np.array([5.0, 0.1, 0.1, 0.1, 2.0, 0.1])
    B = principal_plane(X)
    np.testing.assert_allclose(B @ B.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(np.abs(B[0]), np.eye(6)[0], atol=0.02)
    np.testing.assert_allclose(np.abs(B[1]), np.eye(6)[4], atol=0.02)
    assert B[0, 0] > 0 and B[1, 4] > 0
    D = principal_plane(np.zeros((1, 6)))
    np.testing.assert_allclose(D @ D.T, np.eye(2), atol=1e-12)
    with pytest.raises(InputError):
        principal_plane(np.zeros((3, 5)))


def test_fits_run_with_one_blas_thread_whatever_the_callers_pools(monkeypatch: pytest.MonkeyPatch) -> None:
    """Both EM fits see one BLAS / OpenMP thread; the caller's pools are restored; the verdict is the same
    bit for bit whether the caller limits its pools or not."""
    from sklearn.mixture import GaussianMixture
    from threadpoolctl import threadpool_info, threadpool_limits

    seen: list[int] = []
    fit = GaussianMixture.fit

    def spy(self, X, y=None):  # scikit-learn's signature
        seen.append(max(p["num_threads"] for p in threadpool_info()))
        return fit(self, X, y)

    monkeypatch.setattr(GaussianMixture, "fit", spy)
    rng = np.random.default_rng(11)
    P = np.concatenate([cloud(rng, 30, np.zeros(6), 0.5), cloud(rng, 30, FAR, 0.5)])
    before = [(p["filepath"], p["num_threads"]) for p in threadpool_info()]
    free = assess_bimodality(P, T_MAP)
    assert seen == [1, 1]
    assert [(p["filepath"], p["num_threads"]) for p in threadpool_info()] == before
    with threadpool_limits(limits=1):
        limited = assess_bimodality(P, T_MAP)
    assert free.bimodal and limited.bimodal
    assert (free.bic1, free.bic2, free.ashman_d) == (limited.bic1, limited.bic2, limited.ashman_d)
    assert np.array_equal(free.means, limited.means) and np.array_equal(free.covariances, limited.covariances)


@pytest.mark.parametrize("case", ["one", "two", "overlap", "weighted", "thinned"])
def test_fits_without_scikit_learns_checks_are_those_with_them_bit_for_bit(
        case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The verdict's fits skip scikit-learn's input and parameter checks (``config_context``); with the checks on
    (the context made a no-op) every fitted number is the same."""
    import contextlib

    import sklearn

    rng = np.random.default_rng(["one", "two", "overlap", "weighted", "thinned"].index(case))
    P = shaped_set(case, rng)
    weights = rng.random(300) if case == "weighted" else None
    from sklearn.mixture import GaussianMixture

    skipped: list[bool] = []
    fit = GaussianMixture.fit

    def spy(self, X, y=None):  # scikit-learn's signature
        skipped.append(sklearn.get_config()["skip_parameter_validation"])
        return fit(self, X, y)

    monkeypatch.setattr(GaussianMixture, "fit", spy)
    fast = assess_bimodality(P, T_MAP, weights=weights, seed=3)
    monkeypatch.setattr(sklearn, "config_context", lambda **_: contextlib.nullcontext())
    checked = assess_bimodality(P, T_MAP, weights=weights, seed=3)
    assert skipped == [True, True, False, False]  # the two paths differ in the checks, as meant
    assert (fast.bimodal, fast.reason, fast.dominant, fast.n_fit_points) == (
        checked.bimodal, checked.reason, checked.dominant, checked.n_fit_points)
    assert (fast.bic1, fast.bic2, fast.ashman_d, fast.minor_weight) == (
        checked.bic1, checked.bic2, checked.ashman_d, checked.minor_weight)
    for a, b in ((fast.means, checked.means), (fast.covariances, checked.covariances), (fast.weights, checked.weights)):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("case", ["one", "two", "overlap", "duplicates"])
def test_one_component_fit_of_one_em_step_is_the_converged_fit(case: str) -> None:
    """The verdict fits one component with a single EM step (``max_iter = 1``): with every responsibility one,
    that step's M-step is the converged fit, so BIC(1) equals scikit-learn's fit run to convergence bit for bit."""
    from sklearn.mixture import GaussianMixture

    from pinpoint_fg.posterior.bimodality import REG_COVAR

    P = shaped_set(case, np.random.default_rng(["one", "two", "overlap", "duplicates"].index(case)))
    X = tangent_at_map(T_MAP, P)
    converged = GaussianMixture(n_components=1, covariance_type="full", reg_covar=REG_COVAR, random_state=0,
                                init_params="k-means++", max_iter=100, tol=1e-12).fit(X)
    assert converged.converged_ and converged.n_iter_ >= 2
    assert assess_bimodality(P, T_MAP).bic1 == converged.bic(X)


def test_em_settings_are_checked() -> None:
    from pinpoint_fg.posterior.bimodality import EmSettings

    for bad in ({"tol": 0.0}, {"tol": float("nan")}, {"n_init": 0}, {"max_iter": 0}):
        with pytest.raises(InputError):
            EmSettings(**bad)


def test_the_fits_use_the_verdicts_em_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    """One component in one EM step; two from ``N_INIT`` k-means++ starts stopped at ``EM_TOL`` (the module docstring
    says why 1e-2 and not scikit-learn's 1e-3); ``em`` overrides the two-component fit only."""
    from sklearn.mixture import GaussianMixture

    from pinpoint_fg.posterior.bimodality import EM_MAX_ITER, EM_TOL, N_INIT, EmSettings

    seen: list[tuple] = []
    fit = GaussianMixture.fit

    def spy(self, X, y=None):  # scikit-learn's signature
        seen.append((self.n_components, self.n_init, self.max_iter, self.tol if self.n_components == 2 else None))
        return fit(self, X, y)

    monkeypatch.setattr(GaussianMixture, "fit", spy)
    P = np.concatenate([cloud(np.random.default_rng(0), 25, np.zeros(6), 0.7),
                        cloud(np.random.default_rng(1), 25, FAR, 0.7)])
    default = assess_bimodality(P, T_MAP)
    converged = assess_bimodality(P, T_MAP, em=EmSettings(tol=1e-9, n_init=5, max_iter=5000))
    assert EM_TOL == 1e-2 and N_INIT == 3
    assert seen == [(1, 1, 1, None), (2, N_INIT, EM_MAX_ITER, EM_TOL), (1, 1, 1, None), (2, 5, 5000, 1e-9)]
    assert default.bimodal and converged.bimodal and default.bic1 == converged.bic1
