"""Is a particle posterior genuinely bimodal? (paper §V "Multimodal Evaluation Criterion").

Recipe (DESIGN.md §Evaluation):

1. Map every particle into the tangent space at the MAP pose, ``xi_i = Log(T_map^-1 T_i)``
   (GTSAM order ``[omega; v]``), and make it dimensionless: rotation components divided by
   5 degrees (in radians), translation components by 1 mm (:func:`tangent_at_map`).
2. Fit Gaussian mixtures with one and two components (full covariances) by EM
   (scikit-learn's ``GaussianMixture``).
3. Call the set *bimodal* only if all three hold: ``BIC(2) < BIC(1)``; Ashman's
   ``D = sqrt(2) |mu_1 - mu_2| / sqrt(s_1^2 + s_2^2) > 2``, with ``s_k^2 = u^T Sigma_k u`` the
   variance of component k along the unit axis ``u`` joining the two means; and the minor
   mixture weight ``>= 0.10``.
4. With a ground-truth pose, map it into the same scaled tangent coordinates and assign it to
   the nearer component mean (Euclidean distance in the scaled space, i.e. 1 mm ~ 5 degrees,
   the paper's "nearest component mean"); report whether that is the dominant (heavier)
   component.

Fitting choices, fixed here so verdicts are reproducible: ``reg_covar = 1e-4`` scaled units^2
is added to every covariance diagonal (a floor of 0.01 mm / 0.05 degrees standard deviation:
far below any real spread, but enough to keep EM finite on duplicated particles);
``init_params="k-means++"``, ``n_init = 3`` for two components, ``random_state = seed``; EM stops when the
mean log-likelihood per point changes by less than ``tol = 1e-2`` (:class:`EmSettings`).

Why ``tol = 1e-2`` and not scikit-learn's 1e-3: the verdict thresholds the fit (BIC(2) < BIC(1) needs the
second component to gain ``28/2 ln n`` nats, 55 at 50 particles), and on a unimodal cloud split in two EM crawls
at 1e-3 for tens of iterations that move none of the three tests. Against a converged reference (20 starts,
``tol = 1e-6``, ``max_iter = 2000``; ``scripts/verdict_em_tol.py``), 1e-2 disagreed on 17 of 1,080 SVN particle
sets (1e-3: 16), 2 of 180 PF sets (2) and 67 of 240 SVGD sets (63: SVGD's wide clouds split either way with the
starts), and cost 0.6 of the time (README, *Method notes* and *Latency*, thirty-third round). The one-component
fit stops after one EM step: its responsibilities are all ones, so that step's M-step is the sample mean and
covariance, the converged fit bit for bit (``max_iter = 1``).
scikit-learn's mixture has no sample weights, so a weighted set (particle filter) is first
turned into an equally weighted one by systematic resampling with a seeded generator; sets
larger than ``max_points`` (default 1000) are thinned the same way (uniform weights), which
keeps a 3000-particle filter well under 100 ms. Sets with fewer than 6 distinct points, or
(numerically) no spread, get a unimodal verdict without fitting.

Speed: the fits run with one BLAS / OpenMP thread (:func:`_one_thread`). The problems are tiny
(<= 1000 points in 6-D), so threads only add start-up; on a busy 2-core machine a threaded
``solve_triangular`` of a 6x6 waited milliseconds for its second thread, and a fit took
seconds instead of 20 ms. The verdict therefore does not depend on the caller's thread settings.
scikit-learn is imported on the first fit, not with this module (about 1 s), so a process that
leaves the verdicts to a worker (``pinpoint-fg track``) never loads it. The fits run with scikit-learn's input and
parameter validation off (``assume_finite``, ``skip_parameter_validation``): the points are checked finite here
and the parameters are the constants below, and the checks ran on every fit, every EM restart's k-means++ and every
``bic``. Same fits bit for bit (``tests/test_posterior_bimodality.py``); a verdict on the SVN particle sets of
normal-01 / symmetric-01 / snapshots-01 took 0.93 / 0.84 / 0.89 of the time (100 frames each, best of three).
"""

from __future__ import annotations

import warnings
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any

import numpy as np

from factors.lie import local
from pinpoint_fg.errors import InputError

ROT_UNIT_RAD = float(np.deg2rad(5.0))
"""Rotation unit of the scaled tangent space: 5 degrees, in radians."""
TRANS_UNIT_M = 1e-3
"""Translation unit of the scaled tangent space: 1 mm, in metres."""
REG_COVAR = 1e-4
"""Added to GMM covariance diagonals, in scaled units squared (std floor 0.01 mm / 0.05 deg)."""
N_INIT = 3
"""EM restarts for the two-component fit (the best log-likelihood is kept)."""
EM_TOL = 1e-2
"""EM stops when the mean log-likelihood per point changes by less than this (module docstring)."""
EM_MAX_ITER = 100
"""EM iterations per start at most (scikit-learn's default)."""
MAX_FIT_POINTS = 1000
"""Default cap on the number of (resampled) points the mixtures are fitted to."""
MIN_DISTINCT_POINTS = 6
"""Fewer distinct scaled tangent vectors than this -> unimodal without fitting."""
MIN_SPREAD = 1e-6
"""If every scaled coordinate's standard deviation is below this, the set has no spread -> unimodal."""
ASHMAN_D_MIN = 2.0
"""Ashman's D must exceed this for the two components to count as separate modes."""
MINOR_WEIGHT_MIN = 0.10
"""The lighter component must carry at least this share of the mixture weight."""


_CONTROLLER: Any = None


def _one_thread() -> AbstractContextManager:
    """Context limiting the loaded BLAS and OpenMP pools to one thread (threadpoolctl; one cached controller,
    created after scikit-learn is imported, so it sees every pool the fits use)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1)


def _scale() -> np.ndarray:
    """(6,) divisors turning ``[omega (rad); v (m)]`` into scaled units."""
    return np.array([ROT_UNIT_RAD] * 3 + [TRANS_UNIT_M] * 3)


def _pose(name: str, T: np.ndarray) -> np.ndarray:
    """A single finite (4, 4) pose."""
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric 4x4 pose", column=name) from None
    if T.shape != (4, 4):
        raise InputError(f"{name} must have shape (4, 4), got {T.shape}", column=name)
    if not np.all(np.isfinite(T)):
        raise InputError(f"{name} must be finite", column=name)
    return T


def tangent_at_map(T_map: np.ndarray, particles_T: np.ndarray) -> np.ndarray:
    """Scaled tangent vectors of particles (N, 4, 4) at ``T_map`` (4, 4) -> (N, 6), dimensionless.

    ``xi_i = Log(T_map^-1 T_i) = [omega_i; v_i]``; returns ``[omega_i / 5 deg; v_i / 1 mm]``.
    """
    T_map = _pose("T_map", T_map)
    try:
        P = np.asarray(particles_T, dtype=float)
    except (TypeError, ValueError):
        raise InputError("particles_T must be a numeric array of 4x4 poses", column="particles_T") from None
    if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] == 0:
        raise InputError(f"particles_T must have shape (N, 4, 4), got {P.shape}", column="particles_T")
    if not np.all(np.isfinite(P)):
        raise InputError("particles_T must be finite", column="particles_T")
    return local(T_map[None], P) / _scale()


def systematic_resample(weights: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (m,) drawn by systematic resampling of normalised ``weights`` (N,).

    One uniform offset ``u ~ U[0, 1)``; sample j takes the particle whose cumulative-weight bin
    contains ``(u + j) / m``. Each particle is drawn ``floor(m w_i)`` or ``ceil(m w_i)`` times.
    """
    w = np.asarray(weights, dtype=float)
    cum = np.cumsum(w / w.sum())
    pos = (rng.random() + np.arange(m)) / m
    return np.minimum(np.searchsorted(cum, pos, side="right"), w.shape[0] - 1)


@dataclass(frozen=True)
class BimodalityVerdict:
    """Outcome of the bimodality test on one particle set (all vectors in scaled tangent units)."""

    bimodal: bool
    """True only if BIC prefers two components, Ashman's D > 2 and the minor weight >= 0.10."""
    reason: str
    """``bimodal``, ``degenerate``, or the failed tests joined by ``+``: bic, ashman_d, minor_weight."""
    bic1: float
    """BIC of the one-component fit (NaN when degenerate)."""
    bic2: float
    """BIC of the two-component fit (NaN when degenerate)."""
    ashman_d: float
    """Ashman's D of the two-component fit along the axis joining its means (0 when degenerate)."""
    minor_weight: float
    """Smaller of the two mixture weights (0 when degenerate)."""
    means: np.ndarray
    """(2, 6) means of the two-component fit, ``[omega/5deg; v/1mm]`` (both the sample mean if degenerate)."""
    covariances: np.ndarray
    """(2, 6, 6) component covariances of the two-component fit, scaled units squared."""
    weights: np.ndarray
    """(2,) mixture weights of the two-component fit (``[1, 0]`` when degenerate)."""
    dominant: int
    """Index (0 or 1) of the heavier component."""
    n_fit_points: int
    """Number of (resampled) points the mixtures were fitted to."""
    gt_xi_scaled: np.ndarray | None = None
    """(6,) ground truth in the same scaled tangent coordinates, when ``T_gt`` was given."""
    gt_component: int | None = None
    """Component whose mean is nearer (Euclidean, scaled space) to the truth; only if bimodal and ``T_gt``."""
    truth_in_dominant: bool | None = None
    """Whether ``gt_component`` is the dominant one; ``None`` unless bimodal with ``T_gt``."""


@dataclass(frozen=True)
class EmSettings:
    """How the two-component mixture is fitted (the one-component fit is closed-form: one EM step)."""

    tol: float = EM_TOL
    """Stop a start when the mean log-likelihood per point changes by less than this."""
    n_init: int = N_INIT
    """k-means++ starts; the one with the highest log-likelihood is kept."""
    max_iter: int = EM_MAX_ITER
    """EM iterations per start at most."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.tol) and self.tol > 0):
            raise InputError(f"EM tol must be a positive number, got {self.tol}", column="tol")
        for name in ("n_init", "max_iter"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"EM {name} must be at least 1, got {getattr(self, name)}", column=name)


def ashman_d(means: np.ndarray, covariances: np.ndarray) -> float:
    """Ashman's D of two Gaussians (means (2, d), covariances (2, d, d)) along the axis joining the means.

    ``u = (mu_1 - mu_2) / |mu_1 - mu_2|``, ``s_k^2 = u^T Sigma_k u``,
    ``D = sqrt(2) |mu_1 - mu_2| / sqrt(s_1^2 + s_2^2)``; 0 when the means coincide.
    """
    diff = means[0] - means[1]
    dist = float(np.linalg.norm(diff))
    if dist == 0.0:
        return 0.0
    u = diff / dist
    s2 = np.einsum("i,kij,j->k", u, covariances, u)
    return float(np.sqrt(2.0) * dist / np.sqrt(max(float(s2.sum()), 1e-300)))


def assess_bimodality(
    particles_T: np.ndarray,
    T_map: np.ndarray,
    weights: np.ndarray | None = None,
    T_gt: np.ndarray | None = None,
    seed: int = 0,
    max_points: int = MAX_FIT_POINTS,
    em: EmSettings = EmSettings(),
) -> BimodalityVerdict:
    """Bimodality verdict for particles (N, 4, 4) around the MAP pose ``T_map`` (4, 4).

    ``weights`` (N,) (``None`` = equal) are honoured by systematic resampling to
    ``min(N, max_points)`` points; an unweighted set larger than ``max_points`` is thinned the
    same way. ``T_gt`` (4, 4), optional, is assigned to the nearer component mean when the verdict
    is bimodal. Deterministic for a given ``seed``. ``em``: how the two-component mixture is fitted (the
    default is the verdict's; other settings are for measuring it, ``scripts/verdict_em_tol.py``). See the module
    docstring for the rule.
    """
    X = tangent_at_map(T_map, particles_T)
    n = X.shape[0]
    if max_points < 1:
        raise InputError(f"max_points must be positive, got {max_points}", column="max_points")
    rng = np.random.default_rng(seed)
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,):
            raise InputError(f"weights has shape {w.shape}, expected ({n},)", column="weights")
        with np.errstate(over="ignore"):  # finite weights summing to inf (1e308 each) were an overflow warning
            total = w.sum()
        if not np.all(np.isfinite(w)) or np.any(w < 0) or not 0 < total < np.inf:
            raise InputError("weights must be finite, non-negative, not all zero and have a finite sum",
                             column="weights")
        X = X[systematic_resample(w, min(n, max_points), rng)]
    elif n > max_points:
        X = X[systematic_resample(np.ones(n), max_points, rng)]

    gt_xi = None if T_gt is None else local(_pose("T_map", T_map), _pose("T_gt", T_gt)) / _scale()

    m = X.shape[0]
    n_distinct = np.unique(X, axis=0).shape[0]
    if n_distinct < MIN_DISTINCT_POINTS or np.all(X.std(axis=0) < MIN_SPREAD):
        mu = X.mean(axis=0)
        cov = np.cov(X, rowvar=False, bias=True).reshape(6, 6) + REG_COVAR * np.eye(6)
        return BimodalityVerdict(
            bimodal=False,
            reason="degenerate",
            bic1=float("nan"),
            bic2=float("nan"),
            ashman_d=0.0,
            minor_weight=0.0,
            means=np.stack([mu, mu]),
            covariances=np.stack([cov, cov]),
            weights=np.array([1.0, 0.0]),
            dominant=0,
            n_fit_points=m,
            gt_xi_scaled=gt_xi,
        )

    from sklearn import config_context
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.mixture import GaussianMixture

    common = dict(covariance_type="full", reg_covar=REG_COVAR, random_state=seed, init_params="k-means++")
    # the points are finite (checked above) and the parameters fixed: scikit-learn's own checks of both, on every
    # fit and k-means++ call, are skipped (same fits, bit for bit; 7-16 % of a verdict: module docstring)
    with warnings.catch_warnings(), _one_thread(), config_context(assume_finite=True, skip_parameter_validation=True):
        warnings.simplefilter("ignore", ConvergenceWarning)
        # one EM step is the converged one-component fit, bit for bit (module docstring); it does not "converge"
        gm1 = GaussianMixture(n_components=1, n_init=1, max_iter=1, **common).fit(X)
        gm2 = GaussianMixture(n_components=2, n_init=em.n_init, tol=em.tol, max_iter=em.max_iter, **common).fit(X)
        bic1, bic2 = float(gm1.bic(X)), float(gm2.bic(X))
    means, covs, mix = gm2.means_, gm2.covariances_, gm2.weights_
    d = ashman_d(means, covs)
    minor = float(mix.min())
    dominant = int(np.argmax(mix))

    failed = [
        name
        for name, ok in (
            ("bic", bic2 < bic1),
            ("ashman_d", d > ASHMAN_D_MIN),
            ("minor_weight", minor >= MINOR_WEIGHT_MIN),
        )
        if not ok
    ]
    bimodal = not failed
    gt_component = truth_in_dominant = None
    if bimodal and gt_xi is not None:
        gt_component = int(np.argmin(np.linalg.norm(means - gt_xi, axis=1)))
        truth_in_dominant = gt_component == dominant
    return BimodalityVerdict(
        bimodal=bimodal,
        reason="bimodal" if bimodal else "+".join(failed),
        bic1=bic1,
        bic2=bic2,
        ashman_d=d,
        minor_weight=minor,
        means=np.array(means),
        covariances=np.array(covs),
        weights=np.array(mix),
        dominant=dominant,
        n_fit_points=m,
        gt_xi_scaled=gt_xi,
        gt_component=gt_component,
        truth_in_dominant=truth_in_dominant,
    )


def principal_plane(scaled_xi: np.ndarray) -> np.ndarray:
    """Top-2 principal directions (2, 6) of scaled tangent vectors (N, 6), for plotting.

    Eigenvectors of the (biased) sample covariance with the two largest eigenvalues, as
    orthonormal rows; each row's sign is fixed so its largest-magnitude entry is positive.
    Project with ``xi @ basis.T``; a Gaussian ``(mu, Sigma)`` projects to
    ``(basis @ mu, basis @ Sigma @ basis.T)``. Degenerate inputs (N = 1, zero spread) still give
    an orthonormal basis.
    """
    X = np.asarray(scaled_xi, dtype=float)
    if X.ndim != 2 or X.shape[1] != 6 or X.shape[0] == 0:
        raise InputError(f"scaled_xi must have shape (N, 6), N >= 1, got {X.shape}", column="scaled_xi")
    if not np.all(np.isfinite(X)):
        raise InputError("scaled_xi must be finite", column="scaled_xi")
    Xc = X - X.mean(axis=0)
    _, vecs = np.linalg.eigh(Xc.T @ Xc / X.shape[0])
    basis = vecs[:, ::-1][:, :2].T.copy()
    k = np.argmax(np.abs(basis), axis=1)
    basis *= np.sign(basis[np.arange(2), k])[:, None]
    return basis
