"""Summaries of a frame's pose posterior: its modes, the modes' bimodality verdict, the least-observable direction.

**Modes of a particle set** (:func:`modes_from_particles`). SVN / SVGD particles are samples of
the posterior and PF particles are weighted samples, so a mode is a cluster of particles: its
weight is its share of the particle weight (equal weights for SVN/SVGD, the PF weights for the
PF), its peak the cluster's highest-log-posterior particle, its covariance the weighted tangent
covariance of its members in GTSAM's chart at the peak
(:func:`pinpoint_fg.posterior.spread.tangent_spread`; about the members' weighted mean, [omega; v],
rad / m). Clustering, all in the scaled tangent chart at the MAP particle
(:func:`pinpoint_fg.posterior.bimodality.tangent_at_map`: omega / 5 deg, v / 1 mm, the S of svn.py and
of the GMM verdict):

1. Identical particles (the PF's resampling copies) become one point (weights summed).
2. *Persistence clustering* (ToMATo, Chazal, Guibas, Oudot & Skraba 2013) on the symmetric
   ``NEIGHBOURS``-nearest-neighbour graph (k = 8) with the particles' own log-posterior as the
   height: points are added from the highest log-posterior down; a point with no higher graph
   neighbour starts a cluster (a peak), otherwise it joins its highest neighbour's cluster, and two
   clusters that meet at a point less than ``PERSISTENCE_NATS`` = 2 nats below the lower peak are
   merged. So a mode must rise 2 nats above the pass joining it to a higher one (for two equal
   Gaussians of std s that is a separation of about 4 s; 0.7 / 0.3 needs ~5.5 s). The log-posterior
   is exact at every particle, so no density estimate is needed, and neither the graph nor the
   threshold has a length scale: a single Gaussian cloud of any width gives one mode (tested on
   20-3000 particles, std 0.3-10 units, 20 seeds each: no second mode, even with 1 nat).
   Groups the graph does not connect at all stay separate modes (far-away hypotheses).
   *Resolution*: peaks closer than ``MIN_SEPARATION`` = 2 scaled units (2 mm, or 10 deg, or a
   mix: the norm of the scaled 6-vector) are one mode, both when clusters meet in step 2 and in a
   final pass over all peaks (lightest merged into the nearest). Without this, tracker particle
   sets — which are not converged i.i.d. samples: their log-posterior spans 10-50 nats over a cloud
   of 0.2 scaled units — show "modes" 0.5 mm / 1 deg apart on most frames (measured on a simulated
   suturing run: 60 % of SVN frames "bimodal" without it); 2 units is also the evaluation's
   truth-kept tolerance, so a second mode always is a pose the evaluation tells apart from the first.
3. At most ``k_max`` modes: the lightest cluster is merged into the one with the nearest peak until
   ``k_max`` remain (mass is kept; the merged covariance then includes the stray particles).

Sets with more than ``MAX_CLUSTER_POINTS`` (500; the 3000-particle PF) distinct points are
clustered on a systematically resampled subset (seeded, so verdicts are reproducible; the MAP
particle always included), and then every particle joins the cluster of its nearest subset point;
weights, peaks and covariances use all particles. Cost: a k-d tree and a union-find over <= 500
points, milliseconds; no scikit-learn.

**Bimodal verdict from modes** (:func:`bimodal_from_modes`): the second-heaviest mode carries at
least ``BIMODAL_MODE_WEIGHT`` = 0.1 of the weight (the GMM verdict's minor-weight threshold).

**Least-observable direction** (:func:`weak_direction`): of the MAP pose's information
``Lambda`` (the inverse of the MAP mode's covariance), expressed in mixed units ``xi_s = D xi`` with
``D = diag(180/pi, 180/pi, 180/pi, 1e3, 1e3, 1e3)`` (deg, mm): the unit eigenvector ``u`` of the
smallest eigenvalue ``lambda_min`` of ``D^-1 Lambda D^-1``, sign-normalised so that its
largest-magnitude component is positive, and ``sigma = 1 / sqrt(lambda_min)``, the standard
deviation along ``u`` in that mixed deg/mm unit. Computed from the covariance as the eigenvector of
the LARGEST eigenvalue of ``D Sigma D`` (same vector, ``sigma = sqrt(lambda_max)``), which needs no
inversion and stays defined for a singular (e.g. two-particle) covariance.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

from pinpoint_fg.posterior.bimodality import systematic_resample, tangent_at_map
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.posterior.spread import tangent_covariance

K_MAX = 4
"""Most modes reported per frame."""
NEIGHBOURS = 8
"""k of the symmetric k-nearest-neighbour graph the clusters are built on."""
PERSISTENCE_NATS = 2.0
"""A peak is a separate mode only if it rises at least this many nats above where it meets a higher one."""
MIN_SEPARATION = 2.0
"""... and lies at least this far from every other mode's peak, in scaled units (2 mm, 10 deg: the truth-kept
tolerance of the evaluation; nearer peaks are one mode)."""
MAX_CLUSTER_POINTS = 500
"""Larger particle sets are clustered on a systematically resampled subset of this size."""
BIMODAL_MODE_WEIGHT = 0.1
"""The modes verdict is bimodal when the second mode's weight is at least this."""
WEAK_UNITS = np.array([180.0 / np.pi] * 3 + [1e3] * 3)
"""``diag(D)``: multiplies ``[omega (rad); v (m)]`` into ``[deg; mm]`` for the weak direction."""
WEAK_COLUMNS = ("weak_wx", "weak_wy", "weak_wz", "weak_vx", "weak_vy", "weak_vz", "weak_sigma")
"""estimates.csv columns of the weak direction (unit vector in deg/mm units, then its std)."""


def _knn_graph(X: np.ndarray, k: int) -> list[np.ndarray]:
    """Neighbours of every point of X (M, d) in the symmetric k-nearest-neighbour graph."""
    M = X.shape[0]
    k = min(k, M - 1)
    if k < 1:
        return [np.zeros(0, dtype=int) for _ in range(M)]
    _, nn = cKDTree(X).query(X, k=k + 1)  # the point itself (or a duplicate of it) is among them
    i = np.repeat(np.arange(M), k + 1)
    j = nn.ravel()
    keep = i != j
    A = coo_matrix((np.ones(int(keep.sum()), dtype=bool), (i[keep], j[keep])), shape=(M, M)).tocsr()
    A = (A + A.T).tocsr()
    return [A.indices[A.indptr[r]:A.indptr[r + 1]] for r in range(M)]


def _persistence_clusters(X: np.ndarray, score: np.ndarray, k: int, tau: float, min_sep: float) -> np.ndarray:
    """ToMATo (Chazal et al. 2013): cluster label (M,) = index of the peak each point's cluster keeps.

    Points are added by decreasing ``score`` (log-posterior; ties by index). A point without an
    already-added graph neighbour starts a cluster (a peak); otherwise it joins the cluster of its
    highest neighbour, and every other neighbouring cluster whose peak is less than ``tau`` above
    this point (persistence < tau), or whose peak is closer than ``min_sep`` to the other peak, is
    merged into the one with the higher peak.
    """
    M = X.shape[0]
    nbrs = _knn_graph(X, k)
    order = np.lexsort((np.arange(M), -score))
    pos = np.empty(M, dtype=int)
    pos[order] = np.arange(M)
    parent = np.full(M, -1)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in order:
        up = [j for j in nbrs[i] if pos[j] < pos[i]]
        if not up:
            parent[i] = i
            continue
        best = root(min(up, key=lambda j: pos[j]))
        parent[i] = best
        for j in up:
            rj, rb = root(j), root(i)
            if rj == rb:
                continue
            low, high = (rj, rb) if pos[rj] > pos[rb] else (rb, rj)
            if score[low] - score[i] < tau or np.linalg.norm(X[low] - X[high]) < min_sep:
                parent[low] = high
    return np.array([root(i) for i in range(M)])


def modes_from_particles(
    particles: np.ndarray, log_posterior: np.ndarray, weights: np.ndarray | None = None, k_max: int = K_MAX
) -> tuple[Mode, ...]:
    """The modes (dominant first, at most ``k_max``) of a particle set (module docstring for the recipe).

    ``particles`` (N, 4, 4) ``cam_T_needle``; ``log_posterior`` (N,) up to a constant; ``weights``
    (N,) for weighted sets (PF), None for equal weights (SVN, SVGD). Weights sum to 1 exactly
    (up to rounding); each mode's ``cov_xi`` is in GTSAM's chart at its peak, [omega; v], rad / m.
    """
    P = np.asarray(particles, dtype=float)
    logp = np.asarray(log_posterior, dtype=float)
    N = P.shape[0]
    if P.ndim != 3 or P.shape[1:] != (4, 4) or N == 0 or logp.shape != (N,):
        raise ValueError(f"particles must be (N, 4, 4) and log_posterior (N,), got {P.shape}, {logp.shape}")
    if int(k_max) < 1:
        raise ValueError(f"k_max must be >= 1, got {k_max}")
    w = np.full(N, 1.0 / N) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (N,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be a finite, non-negative (N,) array with a positive sum")
    w = w / w.sum()
    score = np.nan_to_num(logp, nan=-1e300, neginf=-1e300)
    order = np.lexsort((np.arange(N), -score))  # highest log-posterior first, ties by index
    rank = np.empty(N, dtype=int)
    rank[order] = np.arange(N)
    Z = tangent_at_map(P[order[0]], P)

    # identical particles (PF resampling copies) are one graph node: else copies only see each other
    U, inv = np.unique(Z, axis=0, return_inverse=True)
    inv = inv.ravel()
    u_score = np.full(U.shape[0], -np.inf)
    np.maximum.at(u_score, inv, score)
    u_w = np.zeros(U.shape[0])
    np.add.at(u_w, inv, w)
    if U.shape[0] > MAX_CLUSTER_POINTS:
        sub = np.unique(systematic_resample(u_w / u_w.sum(), MAX_CLUSTER_POINTS, np.random.default_rng(0)))
        sub = np.union1d(sub, [int(np.argmax(u_score))])  # the MAP particle is always a subset point
        sub_label = sub[_persistence_clusters(U[sub], u_score[sub], NEIGHBOURS, PERSISTENCE_NATS, MIN_SEPARATION)]
        u_label = sub_label[cKDTree(U[sub]).query(U)[1]]
    else:
        u_label = _persistence_clusters(U, u_score, NEIGHBOURS, PERSISTENCE_NATS, MIN_SEPARATION)
    label = u_label[inv]
    clusters = [np.nonzero(label == lab)[0] for lab in np.unique(label)]

    def mass(c: np.ndarray) -> float:
        return min(1.0, float(w[c].sum()))  # rounding can push a whole set's sum to 1 + 2e-16

    def peak(c: np.ndarray) -> int:
        return int(c[np.argmin(rank[c])])

    # a cluster of zero-weight particles (PF weights underflowed to 0) carries no mass: it is not a mode
    empty = [c for c in clusters if not w[c].sum() > 0]
    if empty:
        clusters = [c for c in clusters if w[c].sum() > 0]
        for c in empty:
            d = [float(np.linalg.norm(Z[peak(k)] - Z[peak(c)])) for k in clusters]
            j = int(np.argmin(d))
            clusters[j] = np.concatenate([clusters[j], c])

    merged = True
    while merged and len(clusters) > 1:  # peaks closer than MIN_SEPARATION are one mode (lightest first)
        merged = False
        clusters.sort(key=mass)
        for a in range(len(clusters) - 1):
            d = [float(np.linalg.norm(Z[peak(c)] - Z[peak(clusters[a])])) for c in clusters[a + 1:]]
            b = a + 1 + int(np.argmin(d))
            if d[b - a - 1] < MIN_SEPARATION:
                clusters[b] = np.concatenate([clusters[b], clusters[a]])
                del clusters[a]
                merged = True
                break

    while len(clusters) > int(k_max):  # step 3: at most k_max modes
        clusters.sort(key=mass)
        light = clusters.pop(0)
        dist = [float(np.linalg.norm(Z[peak(c)] - Z[peak(light)])) for c in clusters]
        j = int(np.argmin(dist))
        clusters[j] = np.concatenate([clusters[j], light])

    modes = []
    for c in sorted(clusters, key=lambda c: (-mass(c), rank[peak(c)])):
        i = peak(c)
        cov = tangent_covariance(P[i], P[c], w[c])
        modes.append(Mode(cam_T_needle=P[i].copy(), weight=mass(c), cov_xi=0.5 * (cov + cov.T)))
    return tuple(modes)


def modes_of_estimate(est: object) -> tuple[Mode, ...]:
    """The modes of a tracker's :class:`~pinpoint_fg.estimate.Estimate`, dominant first.

    The tracker's own ``modes`` when it reports them (SVN, MHT): the ``K_MAX`` heaviest (the result format's
    limit; an MHT bank of more branches, ``--particles 8``, had more and its writer refused the frame), weights
    renormalised over them to sum to 1 (as SVN reports its best modes) and covariances symmetrised, against
    rounding in the tracker; a single particle (the MAP method) is one mode of weight 1 with the estimate's
    covariance (the MAP tracker's GTSAM marginal); otherwise :func:`modes_from_particles` of the particle set.
    """
    own = getattr(est, "modes", None)
    if own is not None:
        kept = sorted(own, key=lambda m: -float(m.weight))[:K_MAX]
        total = float(sum(float(m.weight) for m in kept))
        return tuple(Mode(np.asarray(m.cam_T_needle, dtype=float), min(1.0, float(m.weight) / total), _sym(m.cov_xi))
                     for m in kept)
    P = np.asarray(est.particles, dtype=float)  # type: ignore[attr-defined]
    if P.shape[0] == 1:
        return (Mode(cam_T_needle=np.asarray(est.cam_T_needle, dtype=float),  # type: ignore[attr-defined]
                     weight=1.0, cov_xi=_sym(est.cov_xi)),)  # type: ignore[attr-defined]
    return modes_from_particles(P, est.log_posterior, est.weights)  # type: ignore[attr-defined]


def _sym(C: np.ndarray) -> np.ndarray:
    C = np.asarray(C, dtype=float)
    return 0.5 * (C + C.T)


def second_mode_weight(weights: np.ndarray) -> float:
    """Weight of the second-heaviest mode (0 with a single mode)."""
    w = np.sort(np.asarray(weights, dtype=float).ravel())[::-1]
    return float(w[1]) if w.size > 1 else 0.0


def bimodal_from_modes(modes: tuple[Mode, ...]) -> bool:
    """The modes verdict: the second-heaviest mode weighs at least :data:`BIMODAL_MODE_WEIGHT`."""
    return second_mode_weight(np.array([m.weight for m in modes])) >= BIMODAL_MODE_WEIGHT


def map_mode(modes: tuple[Mode, ...], T_map: np.ndarray) -> Mode:
    """The mode whose peak is nearest the MAP pose ``T_map`` (scaled tangent distance)."""
    peaks = np.stack([m.cam_T_needle for m in modes])
    return modes[int(np.argmin(np.linalg.norm(tangent_at_map(T_map, peaks), axis=1)))]


def weak_direction(cov_xi: np.ndarray | None = None, information: np.ndarray | None = None
                   ) -> tuple[np.ndarray, float]:
    """Least-observable direction (6,) in deg/mm units and its std ``sigma`` (module docstring).

    Give the (6, 6) covariance ``cov_xi`` ([omega; v], rad / m) or the information (its inverse,
    e.g. a Gauss-Newton Hessian); the information wins when both are given. ``sigma`` is
    ``inf`` when the information is singular (lambda_min <= 0).
    """
    if information is not None:
        L = np.asarray(information, dtype=float)
        Ls = L / np.outer(WEAK_UNITS, WEAK_UNITS)
        vals, vecs = np.linalg.eigh(0.5 * (Ls + Ls.T))
        u, lam = vecs[:, 0], float(vals[0])
        sigma = 1.0 / np.sqrt(lam) if lam > 0 else float("inf")
    elif cov_xi is not None:
        C = np.asarray(cov_xi, dtype=float)
        Cs = C * np.outer(WEAK_UNITS, WEAK_UNITS)
        vals, vecs = np.linalg.eigh(0.5 * (Cs + Cs.T))
        u, lam = vecs[:, -1], float(vals[-1])
        sigma = float(np.sqrt(max(lam, 0.0)))
    else:
        raise ValueError("weak_direction needs cov_xi or information")
    u = u / np.linalg.norm(u)
    if u[int(np.argmax(np.abs(u)))] < 0:
        u = -u
    return u, float(sigma)


def posterior_columns(modes: tuple[Mode, ...], T_map: np.ndarray) -> dict[str, float]:
    """estimates.csv columns of a frame: ``bimodal_modes`` (0/1) and the weak direction of the MAP mode."""
    u, sigma = weak_direction(map_mode(modes, T_map).cov_xi)
    cols = {"bimodal_modes": float(bimodal_from_modes(modes))}
    cols.update({k: float(v) for k, v in zip(WEAK_COLUMNS, [*u, sigma], strict=True)})
    return cols
