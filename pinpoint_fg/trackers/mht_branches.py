"""The branches of the MHT bank (:mod:`pinpoint_fg.trackers.mht`): evidence, duplicates, selection, spread.

A branch is one single-mode GTSAM smoother with its log-weight and window prior. These functions score a
branch (its Laplace evidence increment), tell two branches apart (absolute separation or Mahalanobis
distance under the better one's marginal), select the bank (merge duplicates, prune, keep K), charge a
transported proposal the parent's history, and spread the weighted mixture around the best branch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from factors.lie import local, se3_exp
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.posterior.spread import tangent_spread
from pinpoint_fg.proposals import gaussian_log_normaliser, laplace_log_evidence, near, polish_with_prior
from pinpoint_fg.trackers.map import MapSmoother


@dataclass
class Branch:
    """One single-mode hypothesis of the bank: its smoother, log-weight and window prior."""

    smoother: MapSmoother
    log_w: float
    prior_mean: np.ndarray  # window prior of the newest key (mean, covariance)
    prior_cov: np.ndarray
    inc: float = 0.0  # this frame's evidence increment
    iterations: int = 1
    history: list = field(default_factory=list)  # [(FrameLikelihood, (4, 4) pose)] of the previous frames


def _sqrt_psd(C: np.ndarray) -> np.ndarray:
    """``S`` with ``S S^T = C`` for a symmetric PSD (6, 6) ``C`` (eigen-decomposition; negative eigenvalues clipped)."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.maximum(w, 0.0))


def _mahalanobis2(T: np.ndarray, centres: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """``xi^T Sigma^-1 xi`` of pose ``T`` around each centre ``(B, 4, 4)`` with covariances ``(B, 6, 6)``."""
    xi = local(centres, np.broadcast_to(T, centres.shape))
    return np.einsum("bi,bi->b", xi, np.linalg.solve(covs, xi[..., None])[..., 0])


def branch_evidence(lik: FrameLikelihood, T: np.ndarray, cov: np.ndarray, mean: np.ndarray,
                    prior_cov: np.ndarray) -> float:
    """Laplace log-evidence increment of a smoother's estimate ``T`` with marginal ``cov`` (mht step 1).

    ``mean``, ``prior_cov``: the branch's window prior on the newest pose; ``-inf`` when ``cov`` is singular.
    """
    r = local(mean, T[None])[0]
    E = float(lik.nll(T)[0]) + 0.5 * float(r @ np.linalg.solve(prior_cov, r))
    try:
        H = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        return -np.inf
    return float(laplace_log_evidence(E, H) + gaussian_log_normaliser(prior_cov))


def is_duplicate(T: np.ndarray, kept: list[Branch], separation: tuple[float, float], merge_mahalanobis2: float) -> bool:
    """True when ``T`` is the same mode as one of ``kept`` (absolute separation or Mahalanobis distance)."""
    return bool(duplicated(T, kept, separation, merge_mahalanobis2).any())


def duplicated(T: np.ndarray, kept: list[Branch], separation: tuple[float, float], merge_mahalanobis2: float
               ) -> np.ndarray:
    """(B,) bool: which of ``kept`` ``T`` is the same mode as (:func:`is_duplicate`'s rule, per branch)."""
    if not kept:
        return np.zeros(0, dtype=bool)
    centres = np.stack([k.smoother.newest for k in kept])
    covs = np.stack([k.smoother.cov for k in kept])
    return near(T, centres, separation)[0] | (_mahalanobis2(T, centres, covs) < merge_mahalanobis2)


def select_branches(branches: list[Branch], prune_nats: float, max_branches: int, separation: tuple[float, float],
                    merge_mahalanobis2: float) -> list[Branch]:
    """Best first; merge duplicates (keep the better); prune; keep K; shift log-weights so the best is 0."""
    live = sorted([b for b in branches if np.isfinite(b.log_w)], key=lambda b: -b.log_w)
    if not live:  # nothing finite: keep the first as is
        live = branches[:1]
        live[0].log_w = 0.0
    best = live[0].log_w
    kept: list[Branch] = []
    for b in live:
        if b.log_w < best - prune_nats or len(kept) >= max_branches:
            continue
        if is_duplicate(b.smoother.newest, kept, separation, merge_mahalanobis2):
            continue
        kept.append(b)
    for b in kept:
        b.log_w -= best
    return kept


def history_cost(parent: Branch, G: np.ndarray) -> tuple[float, list]:
    """What the parent's past frames say against the proposal's history ``G x_j``, and that history.

    Each past pose carried by ``G`` is polished on its own frame (a few Gauss-Newton steps);
    the cost is ``sum_j nll_j(polished) - nll_j(x_j polished alike)`` (the evidence of the mode history "this
    proposal all along" relative to the parent's, per frame, motion consistency assumed equal).
    """
    cost, hist = 0.0, []
    for lik_j, T_j in parent.history:
        if lik_j.dim == 0:
            hist.append((lik_j, G @ T_j))
            continue
        # both polished alike on the frame alone: the parent's pose is a filtered estimate, not the
        # frame's own optimum, and comparing against it unpolished would favour every proposal
        Tq, E, _ = polish_with_prior(lik_j, np.stack([T_j, G @ T_j]), iters=3)
        cost += float(E[1] - E[0])
        hist.append((lik_j, Tq[1]))
    return cost, hist


def mixture_spread(branches: list[Branch], w: np.ndarray, z: np.ndarray) -> tuple[float, float, np.ndarray]:
    """q95 translation, q95 rotation and covariance of the branch mixture around the best branch.

    ``w`` the normalised branch weights, ``z`` (M, 6) fixed standard-normal draws split among the branches by weight.
    """
    M = z.shape[0]
    counts = np.floor(w * M).astype(int)
    counts[np.argsort(-(w * M - counts))[: M - counts.sum()]] += 1
    samples, start = [], 0
    for b, c in zip(branches, counts, strict=True):
        if c == 0:
            continue
        xi = z[start:start + c] @ _sqrt_psd(b.smoother.cov).T
        samples.append(b.smoother.newest @ se3_exp(xi))
        start += c
    sp = tangent_spread(branches[0].smoother.newest, np.concatenate(samples), None)
    return float(sp.q95_trans_m), float(sp.q95_rot_rad), np.asarray(sp.cov_xi)
