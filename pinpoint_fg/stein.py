"""Stein variational transport on plain tangent vectors: kernel, bandwidth, preconditioning.

This module knows nothing about needles or SE(3). It works on N particles in R^d (the
particle axis first), given each particle's gradient ``g_i`` of the log-posterior and a
curvature (information) matrix ``H_i`` (e.g. Gauss-Newton ``J^T J``). The tracker expresses
all particles in ONE chart per iteration (``xi_i = Log(T_ref^-1 T_i)``), calls
:func:`stein_step`, and retracts ``T_i <- T_i Exp(step_i)``.

Maths (paper Sec. IV; Liu & Wang 2016; Detommaso et al. 2018)
-------------------------------------------------------------
Whitened RBF kernel, ``S = diag(scale)``::

    k(xi_j, xi_i) = exp(-||S^-1 (xi_i - xi_j)||^2 / (2 h))
    grad_{xi_j} k(xi_j, xi_i) = k(xi_j, xi_i) S^-2 (xi_i - xi_j) / h

Bandwidth (median heuristic, floored)::

    h = max(median_{i<j} ||S^-1(xi_i - xi_j)||^2 / log N, h_floor)

Stein velocity (paper Eq. 11), with normaliser ``c_i``::

    phi_i = (1/c_i) sum_j [ k(xi_j, xi_i) g_j + grad_{xi_j} k(xi_j, xi_i) ]
    c_i = N                    (normalise="n": the paper / textbook form)
    c_i = sum_j k(xi_j, xi_i)  (normalise="kernel-sum")

Preconditioners (``H~`` = symmetrised, eigenvalue-floored, see :func:`floor_hessians`):

* ``"newton-eq14"`` (default, paper Eq. 14): ``step_i = step_size * Hbar_i^-1 phi_i`` with
  ``Hbar_i`` one of

  - ``"kernel-weighted"`` (default): the block-diagonal ("mass-lumped") Newton matrix of SVN
    (Detommaso et al. 2018; the same block as their reference code), including the
    curvature of the repulsion::

        Hbar_i = (1/c2_i) sum_j [ k(xi_j, xi_i)^2 H~_j + grad_j k_ji grad_j k_ji^T ]
        c2_i = N                       (normalise="n": exactly Detommaso et al.)
        c2_i = sum_j k(xi_j, xi_i)^2   (normalise="kernel-sum")

  - ``"kernel-average"``: ``Hbar_i = sum_j k_ji H~_j / sum_j k_ji`` (a smoothed metric);
  - ``"own"``: ``Hbar_i = H~_i`` (the literal reading of Eq. 14).

  The result is floored again, so cond(Hbar_i) <= 1/eps as well. With ``floor_each=False`` only ``Hbar_i``
  is floored (each ``H_j`` just symmetrised): one eigen-decomposition per step instead of two. A kernel-weighted
  sum of positive semi-definite blocks is one; the floor of the sum bounds the step's conditioning as the
  floor of each block did, differing only in how much weak directions are damped.

* ``"newton-alg1"`` (paper Algorithm 1): each particle's own ``H~_j^-1`` is applied to its
  gradient inside the kernel sum, the repulsion is not preconditioned::

      step_i = step_size * (1/c_i) sum_j [ k_ji H~_j^-1 g_j + grad_j k_ji ]

* ``"none"`` (SVGD, Liu & Wang): ``step_i = step_size * phi_i`` (H = I); with
  ``isotropic=True`` the kernel also uses ``S = I``. Use a small fixed ``step_size``.

All Eq.-14 variants share the fixed point ``phi_i = 0`` (the SVGD fixed point of the whitened
kernel); the preconditioner and the normaliser only change how fast and how stably it is
reached. Algorithm 1 has a different fixed point (below).

Scaling: the normaliser and the defaults
----------------------------------------
With the raw ``1/N`` sum a particle whose neighbours are far (``k_ji << 1``) sees
``phi_i ~ g_i / N``; preconditioned by its own ``H_i`` that is a Newton step shrunk N times,
so ``"own"``/``"kernel-average"``/``"newton-alg1"`` with ``normalise="n"`` crawl while the cloud
is spread (measured: ~180 iterations instead of 8-16 on the Gaussian test). Dividing by
``sum_j k_ji`` makes a lone particle take a full Newton step.

SVN's matrix is self-scaling for a lone particle (``N = 1``: ``H_i^-1 g_i``), but with
Detommaso's ``1/N`` on both sides the COLLECTIVE mode (the whole cloud offset by ``delta``
from the mode) gets ``-(sum_j k_ji / sum_j k_ji^2) delta``: an overshoot by ``sum k / sum k^2 > 1``
(their code tames it with a decaying step size). For a converged standard-normal cloud of 50
with the median bandwidth that ratio is 1.6-2.2 in 2-D (which still converges) and 2.3-2.9 in
6-D, where the cloud oscillates around the mode without converging (measured: mean error
5-60 posterior sigmas after 200 iterations). Normalising
``phi`` by ``sum k`` and the SVN matrix by ``sum k^2`` ("kernel-sum") makes the collective step
an exact Newton step and keeps SVN's repulsion curvature, which stabilises the relative
motion of close particles: ``"own"`` (no such term) is exact on the collective mode too but,
on a strongly correlated target, its relative modes are amplified by ``(I + Sigma S^-2 / h)``
per step and the cloud never settles (measured: whitened spread eigenvalues wandering in
0.06..1.2 after 200 iterations on a 2-D target with correlation 0.99).

Defaults, therefore: ``newton-eq14`` + ``kernel-weighted`` + ``normalise="kernel-sum"``.
Measured (``tests/test_stein.py`` harness, seeds 0-4): Gaussians with condition number 1e3,
N = 50, S = per-axis posterior std times a random factor in [0.5, 2], eps = 1e-4 (<= 1/cond),
start 5 (widest axis) to 160 (narrowest axis) sigmas away. The paper's early stop (5 % of the
per-axis std, best logp flat) fires after 8-10 (d = 2) and 15-16 (d = 6) iterations; mean
error <= 0.02 posterior sigmas; sqrt of the eigenvalues of the posterior-whitened particle
covariance 0.94-0.99 (d = 2) and 0.84-0.94 (d = 6): the finite-N Stein fixed point is
slightly under-dispersed, more so in 6-D. Same harness, other options: faithful SVN ("n")
8-15 iterations in 2-D but no convergence in 6-D (mean error 14-16 sigmas); ``"own"`` and
``"kernel-average"`` (kernel-sum) match the default in 6-D but fail to settle in 3 of 5 2-D
runs (spread wandering 0.8-1.1); any "n" normaliser without SVN's matrix needs ~180
iterations; SVGD (isotropic, step 1e-3) is still 5-16 sigmas off after 200.

On a correlated target (the diagonal S then mismatches the posterior's axes) the default gets
the mean and the per-axis stds right within 8-28 iterations, but the spread along the thin
principal direction relaxes slowly (up to 4-5x too wide at 30 iterations, 0.77-1.15 after
200). With the paper's ``eps = 1e-2`` on a 1e3-conditioned target the directions weaker than
1/100 of the strongest are slowed 10x (by design), so the same fixed point needs more
iterations (mean still > 1 sigma off after 10 iterations).

``"newton-alg1"`` converges to the WRONG covariance on a Gaussian: for ``g_j = -A (xi_j - mu)``
the attraction becomes ``-(xi_j - mu)``, a unit-precision pull, while the repulsion keeps its
kernel scale, so its fixed point is the SVGD fixed point of ``N(mu, I)`` (identity in the raw
tangent coordinates), not of ``N(mu, A^-1)`` (measured: narrow-axis std ~30x too large on the
1e3 target, i.e. std ~1). Kept as the paper's Algorithm 1, an option only.

Hessian floor
-------------
Each ``H_i`` is symmetrised, eigendecomposed and its eigenvalues floored at
``eps * w_max`` (``eps = eig_floor_rel``, paper: 1e-2), bounding the condition number at
``1/eps``. A particle whose ``H_i`` carries no usable information (``w_max <= 1e-12 *
max(fallback)``, or a non-finite entry) gets the fallback information ``diag(fallback)`` instead; the Stein step uses
``diag(scale)^-2`` (one scale unit of information per axis; ``scale`` even when the kernel is
isotropic) so that a missing Hessian turns the Newton step into a scale-metric gradient step
rather than an overflow. A non-finite gradient is treated as zero (the repulsion still acts).

Bandwidth floor
---------------
The paper floors h at ``sigma_Q^2 = tr(Q) / 6``, which adds rad^2 to m^2. Here the floor is in
the kernel's whitened units; :func:`whitened_noise_floor` gives ``tr(S^-1 Q S^-1) / d``, the
dimensionless version (= 1 when S = sqrt(diag Q)). A floor large relative to the cloud makes
the kernel broad. At convergence that is harmless for a Gaussian target (the broad-kernel
limit of Stein matches second moments: measured std ratio 0.98-1.01 with h floored at 1, vs
0.88 with the median bandwidth alone in 6-D), but it SLOWS CONTRACTION: with k ~ 1 for all
pairs every particle feels the same averaged gradient, so the cloud moves as a whole and
shrinks only through the small variation of k. Measured (d = 6, N = 50, cloud starting at
std = S, default options), std ratio after 15 iterations for posterior std / S = 0.3, 0.1,
0.03: floor 1 -> 1.00, 1.88, 5.8; floor 0.1 -> 0.88, 1.01, 2.15; floor 1e-3 -> 0.88, 0.88,
0.89. Keep the floor at or below the expected whitened posterior variance (or choose S near
the posterior scale) if the spread must settle within the iteration budget.

Particles are differences in whatever chart the caller chose; nothing here retracts.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pinpoint_fg.errors import InputError

PRECONDITIONERS = ("newton-eq14", "newton-alg1", "none")
HESSIAN_MODES = ("kernel-weighted", "kernel-average", "own")
NORMALISERS = ("kernel-sum", "n")


@dataclass(frozen=True)
class SteinConfig:
    """Settings of one Stein transport step (see the module docstring for the maths)."""

    scale: tuple[float, ...]
    """S diagonal (d,): per-axis kernel scale, e.g. [sigma_r x3, sigma_t x3] in GTSAM [omega; v]."""
    bandwidth_floor: float
    """Floor of the bandwidth h, in the kernel's (whitened) squared units; must be > 0."""
    eig_floor_rel: float = 1e-2
    """eps: each Hessian eigenvalue is floored at eps * (largest eigenvalue of that Hessian)."""
    preconditioner: str = "newton-eq14"
    """'newton-eq14' (H^-1 on the whole velocity), 'newton-alg1' (H_j^-1 g_j in the sum), 'none'."""
    hessian: str = "kernel-weighted"
    """Eq.-14 matrix: 'kernel-weighted' (SVN: k^2 H + grad k grad k^T), 'kernel-average', 'own'."""
    normalise: str = "kernel-sum"
    """Normaliser of the kernel sums: 'kernel-sum' (sum_j k_ji; sum_j k_ji^2 for SVN's matrix) or 'n' (N)."""
    step_size: float = 1.0
    """Multiplier of the step: 1.0 for the Newton forms; a small fixed value for SVGD."""
    isotropic: bool = False
    """Use S = I in the kernel (the SVGD baseline); bandwidth_floor is then in raw units."""
    floor_each: bool = True
    """Kernel-weighted / kernel-average matrix: floor every ``H_j`` before the kernel sum, as well as the sum (two
    eigen-decompositions per step); False: only the sum is floored (one; :func:`stein_step`)."""

    def __post_init__(self) -> None:
        scale = np.asarray(self.scale, dtype=float)
        if scale.ndim != 1 or scale.size == 0:
            raise InputError("scale must be a non-empty 1-D sequence", column="scale")
        if not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise InputError("scale entries must be finite and > 0", column="scale")
        object.__setattr__(self, "scale", tuple(float(s) for s in scale))
        if not (math.isfinite(self.bandwidth_floor) and self.bandwidth_floor > 0):
            raise InputError("bandwidth_floor must be finite and > 0", column="bandwidth_floor")
        if not (0.0 < self.eig_floor_rel <= 1.0):
            raise InputError("eig_floor_rel must be in (0, 1]", column="eig_floor_rel")
        if self.preconditioner not in PRECONDITIONERS:
            raise InputError(f"preconditioner must be one of {PRECONDITIONERS}", column="preconditioner")
        if self.hessian not in HESSIAN_MODES:
            raise InputError(f"hessian must be one of {HESSIAN_MODES}", column="hessian")
        if self.normalise not in NORMALISERS:
            raise InputError(f"normalise must be one of {NORMALISERS}", column="normalise")
        if not (math.isfinite(self.step_size) and self.step_size > 0):
            raise InputError("step_size must be finite and > 0", column="step_size")

    @property
    def kernel_scale(self) -> np.ndarray:
        """(d,) the S actually used by the kernel: ones when isotropic, else ``scale``."""
        s = np.asarray(self.scale, dtype=float)
        return np.ones_like(s) if self.isotropic else s


@dataclass(frozen=True)
class SteinStep:
    """Result of one Stein step."""

    step: np.ndarray
    """(N, d) tangent step of each particle (apply as xi_i + step_i, or T_i Exp(step_i))."""
    bandwidth: float
    """h used by the kernel (whitened squared units)."""
    kernel: np.ndarray
    """(N, N) K[j, i] = k(xi_j, xi_i) (symmetric)."""
    velocity: np.ndarray
    """(N, d) the un-preconditioned Stein velocity phi_i (with the configured normaliser)."""


def _check_particles(xi: np.ndarray, name: str = "xi") -> np.ndarray:
    xi = np.asarray(xi, dtype=float)
    if xi.ndim != 2 or xi.shape[0] == 0:
        raise InputError(f"{name} must have shape (N, d) with N >= 1, got {xi.shape}", column=name)
    if not np.isfinite(xi).all():
        raise InputError(f"{name} contains non-finite values", column=name)
    return xi


def median_bandwidth(xi_white: np.ndarray, floor: float) -> float:
    """Median-heuristic bandwidth ``h = max(median_{i<j} ||xi_i - xi_j||^2 / log N, floor)``.

    ``xi_white`` (N, d) are already whitened (divided by S). With N = 1 there are no pairs and
    ``log 1 = 0``: the floor is returned. ``floor`` must be > 0 so that h > 0 always.
    """
    xi_white = _check_particles(xi_white, "xi_white")
    if not (math.isfinite(floor) and floor > 0):
        raise InputError("bandwidth floor must be finite and > 0", column="bandwidth_floor")
    if xi_white.shape[0] < 2:
        return float(floor)
    diff = xi_white[:, None, :] - xi_white[None, :, :]
    return _bandwidth_from_d2(np.einsum("ijk,ijk->ij", diff, diff), floor)


@functools.lru_cache(maxsize=16)
def _ones(d: int) -> np.ndarray:
    """``np.ones(d)``, built once per ``d`` (read-only): :func:`floor_hessians`' default fallback."""
    out = np.ones(d)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=16)
def _eye(d: int) -> np.ndarray:
    """``np.eye(d)``, built once per ``d`` (read-only)."""
    out = np.eye(d)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=16)
def _upper_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, k=1)``, computed once per ``n`` (read-only)."""
    rows, cols = np.triu_indices(n, k=1)
    rows.flags.writeable = False
    cols.flags.writeable = False
    return rows, cols


def _bandwidth_from_d2(d2: np.ndarray, floor: float) -> float:
    """The median heuristic from the (N, N) whitened squared distances (see :func:`median_bandwidth`)."""
    n = d2.shape[0]
    if n < 2:
        return float(floor)
    m = _median(d2[_upper_pairs(n)])
    return max(m / math.log(n), float(floor))


def _median(v: np.ndarray) -> float:
    """``np.median`` of a 1-D float array, bitwise, without its generic machinery: the middle order statistic, or
    the mean ``(a + b) / 2`` of the two middle ones (NaN if any value is NaN)."""
    n = v.shape[0]
    k = n // 2
    part = np.partition(v, (k - 1, k, n - 1) if n % 2 == 0 else (k, n - 1))
    if np.isnan(part[-1]):
        return float("nan")
    return float(part[k]) if n % 2 else float((part[k - 1] + part[k]) / 2.0)


def whitened_noise_floor(Q: np.ndarray, scale: np.ndarray) -> float:
    """Bandwidth floor from a process-noise covariance: ``tr(S^-1 Q S^-1) / d``.

    ``Q`` (d, d) or its diagonal (d,), ``scale`` (d,) = diag(S). The paper's ``tr(Q) / 6``
    expressed in the kernel's whitened (dimensionless) units.
    """
    scale = np.asarray(scale, dtype=float)
    Q = np.asarray(Q, dtype=float)
    q_diag = np.diag(Q) if Q.ndim == 2 else Q
    if q_diag.shape != scale.shape:
        raise InputError(f"Q has dimension {q_diag.shape}, scale {scale.shape}", column="Q")
    return float(np.mean(q_diag / scale**2))


def kernel_matrix(xi: np.ndarray, scale: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Whitened RBF kernel and its gradient with respect to the first argument.

    ``xi`` (N, d), ``scale`` (d,) = diag(S), ``h`` > 0. Returns

    * ``K`` (N, N): ``K[j, i] = exp(-||S^-1 (xi_i - xi_j)||^2 / (2h))`` (symmetric);
    * ``gradK`` (N, N, d): ``gradK[j, i] = d k(xi_j, xi_i) / d xi_j
      = K[j, i] * S^-2 (xi_i - xi_j) / h`` in the UN-whitened coordinates of ``xi``.
    """
    xi = np.asarray(xi, dtype=float)
    scale = np.asarray(scale, dtype=float)
    diff = xi[None, :, :] - xi[:, None, :]  # diff[j, i] = xi_i - xi_j
    white = diff / scale
    d2 = np.einsum("jik,jik->ji", white, white)
    K = np.exp(-d2 / (2.0 * h))
    gradK = K[:, :, None] * diff / (scale**2 * h)
    return K, gradK


def floor_hessians(
    H: np.ndarray,
    eps: float = 1e-2,
    fallback: np.ndarray | None = None,
    min_info_rel: float = 1e-12,
) -> tuple[np.ndarray, np.ndarray]:
    """Symmetrise and eigenvalue-floor a batch of information matrices; also return the inverses.

    ``H`` (N, d, d). Each ``0.5 (H_i + H_i^T) = V diag(w) V^T`` gets
    ``w~ = max(w, eps * w_max)``, so ``H~_i`` is symmetric positive definite with condition
    number <= 1/eps; negative eigenvalues (an indefinite true Hessian) are raised to the floor.

    A particle with no usable information — ``w_max <= min_info_rel * max(fallback)`` (zero,
    negative semi-definite or vanishing H) or any non-finite entry — gets ``diag(fallback)``
    (``fallback`` (d,) > 0, default ones) instead, so the result is always finite and
    invertible. Returns ``(H~, H~^-1)``, both (N, d, d).
    """
    H = np.asarray(H, dtype=float)
    if H.ndim != 3 or H.shape[1] != H.shape[2]:
        raise InputError(f"Hessians must have shape (N, d, d), got {H.shape}", column="hess")
    n, d, _ = H.shape
    if fallback is None:  # the default ones: valid by construction, built once per d
        fb = _ones(d)
    else:
        fb = np.asarray(fallback, dtype=float)
        if fb.shape != (d,) or not np.all(np.isfinite(fb)) or np.any(fb <= 0):
            raise InputError("fallback must be (d,) finite and > 0", column="fallback")
    unfloored = _unfloored(H, eps, fb, min_info_rel)
    if unfloored is not None:
        return unfloored
    H_fl, H_inv, _ = _floor_eig(H, eps, fb, min_info_rel)
    return H_fl, H_inv


def _spectral_bound(Hs: np.ndarray, fro: np.ndarray) -> np.ndarray:
    """An upper bound ``(N,)`` of the largest absolute eigenvalue of each symmetric ``Hs (N, d, d)`` with Frobenius
    norms ``fro`` > 0: ``fro ||U^4||_F^(1/4)``, ``U = Hs / fro``, within a factor ``d^(1/8)`` of it (exact for rank
    one), since ``||U^4||_F^2 = sum_i (w_i / fro)^8``."""
    U = Hs / fro[:, None, None]
    U2 = U @ U
    U4 = U2 @ U2
    return fro * np.sqrt(np.sqrt(np.sqrt(np.einsum("nij,nij->n", U4, U4))))


def _unfloored(H: np.ndarray, eps: float, fb: np.ndarray, min_info_rel: float
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """``(H_s, H_s^-1)`` (``H_s`` the symmetrised ``H``) when provably no eigenvalue floor of :func:`_floor_eig` binds
    and no row needs the fallback; None otherwise (then the eigen-decomposition decides).

    ``b = ||H_s||_F ||(H_s / ||H_s||_F)^4||_F^(1/4) >= w_max`` (for symmetric ``H_s``, ``||H_s^k||_F^2 = sum_i w_i^2k
    >= w_max^2k``; the normalisation keeps the powers from overflowing), so a Cholesky factorisation of
    ``H_s - eps b I`` (it succeeds iff that matrix is positive definite) proves ``w_min > eps w_max`` for every row,
    and ``w_max >= ||H_s||_F / sqrt(d)`` above ``min_info_rel * max(fb)`` proves every row usable: the floored
    matrix is then ``H_s`` itself, and its inverse by LU the same to round-off. The fourth power matters: ``b``
    exceeds ``w_max`` by ``(sum_i (w_i / w_max)^8)^(1/8)`` (a few per mille on the tracker's matrices) where
    ``||H_s||_F`` itself exceeds it by ``(sum_i (w_i / w_max)^2)^(1/2)`` (10-50 %): the SVN block of the Stein step
    (eigenvalues just above its 1e-2 floor, which it almost never needs) passes the sharp test on most calls and
    failed the Frobenius one on 86 % (normal-01). The Laplace evidence and the polish's decrement (floors at 1e-6
    and 1e-9 of the largest eigenvalue) never bind on the tracker's Gauss-Newton information, and a batched
    Cholesky and inverse cost a third of a batched ``eigh`` of 6x6 blocks (measured ~55 vs ~195 us for 50). Where
    a floor binds (each particle's own block in the Stein step, on 98 % of rows) the test fails and costs one
    factorisation attempt.
    """
    d = H.shape[-1]
    Hs = 0.5 * (H + np.swapaxes(H, 1, 2))
    if not np.isfinite(Hs).all():
        return None
    fro = np.sqrt(np.einsum("nij,nij->n", Hs, Hs))
    if not (fro > math.sqrt(d) * min_info_rel * fb.max()).all():
        return None
    try:
        np.linalg.cholesky(Hs - (eps * _spectral_bound(Hs, fro))[:, None, None] * _eye(d))
    except np.linalg.LinAlgError:
        return None
    return Hs, np.linalg.inv(Hs)


def _floor_eig(H: np.ndarray, eps: float, fb: np.ndarray, min_info_rel: float, want: str = "both"
               ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
    """:func:`floor_hessians` without the argument checks; also returns the floored eigenvalues (N, d).

    ``want``: "both", "floored" or "inverse" — the other matrix is returned as None (not computed).
    """
    d = H.shape[-1]
    finite = np.isfinite(H).all(axis=(1, 2))
    all_finite = bool(finite.all())
    Hs = H if all_finite else np.where(finite[:, None, None], H, 0.0)  # (a no-op replacement is skipped)
    Hs = 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
    w, V = np.linalg.eigh(Hs)  # ascending eigenvalues
    w_max = w[:, -1]
    usable = finite & (w_max > min_info_rel * fb.max())
    w_fl = np.maximum(w, eps * w_max[:, None])
    # Unusable rows: replace by the fallback diagonal (eigenvectors = identity); skipped when there are none.
    if not (all_finite and usable.all()):
        w_fl = np.where(usable[:, None], w_fl, fb[None, :])
        V = np.where(usable[:, None, None], V, np.eye(d)[None, :, :])
    VT = np.swapaxes(V, 1, 2)
    H_fl = (V * w_fl[:, None, :]) @ VT if want != "inverse" else None
    H_inv = (V / w_fl[:, None, :]) @ VT if want != "floored" else None
    return H_fl, H_inv, w_fl


def _symmetrised(H: np.ndarray, fb: np.ndarray, min_info_rel: float) -> np.ndarray:
    """``0.5 (H + H^T)`` per row, ``diag(fb)`` for rows without usable information (:func:`_floor_eig`'s fallback)
    — a non-finite entry or ``tr H <= d * min_info_rel * max(fb)`` — without an eigen-decomposition.

    For positive semi-definite ``H`` the trace test implies :func:`_floor_eig`'s ``w_max > min_info_rel * max(fb)``
    and is implied by ``w_max > d * min_info_rel * max(fb)``: only rows with next to no information are classed
    differently, and they carry none either way.
    """
    d = H.shape[-1]
    finite = np.isfinite(H).all(axis=(1, 2))
    Hs = H if finite.all() else np.where(finite[:, None, None], H, 0.0)
    Hs = 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
    usable = finite & (np.einsum("nii->n", Hs) > d * min_info_rel * fb.max())
    if not usable.all():
        Hs = np.where(usable[:, None, None], Hs, np.diag(fb)[None])
    return Hs


def stein_step(
    xi: np.ndarray,
    grad_logp: np.ndarray,
    hess: np.ndarray | None,
    config: SteinConfig,
) -> SteinStep:
    """One (preconditioned) Stein variational step for all particles.

    ``xi`` (N, d) particles in one chart, ``grad_logp`` (N, d) gradient of the log-posterior at
    each particle, ``hess`` (N, d, d) information (e.g. Gauss-Newton ``J^T J`` of the NEGATIVE
    log-posterior; ignored and may be None when ``preconditioner == "none"``). See the module
    docstring for the update formulas, the normaliser and the Hessian floor.
    """
    xi = _check_particles(xi)
    n, d = xi.shape
    g = np.asarray(grad_logp, dtype=float)
    if g.shape != (n, d):
        raise InputError(f"grad_logp must have shape {(n, d)}, got {g.shape}", column="grad_logp")
    if len(config.scale) != d:
        raise InputError(f"config.scale has {len(config.scale)} entries, particles have d={d}",
                         column="scale")
    # A non-finite gradient carries no direction: zero it (the repulsion still acts).
    finite_g = np.isfinite(g)
    if not finite_g.all():
        g = np.where(finite_g, g, 0.0)

    S = config.kernel_scale
    # one pass over the pairs: differences, whitened squared distances, bandwidth, kernel, its gradient
    diff = xi[None, :, :] - xi[:, None, :]  # diff[j, i] = xi_i - xi_j
    white = diff / S
    d2 = np.einsum("jik,jik->ji", white, white)
    h = _bandwidth_from_d2(d2, config.bandwidth_floor)
    K = np.exp(-d2 / (2.0 * h))
    gradK = K[:, :, None] * diff  # (N, N, d): d k(xi_j, xi_i) / d xi_j, divided in place:
    gradK /= S**2 * h
    c = K.sum(axis=0) if config.normalise == "kernel-sum" else np.full(n, float(n))
    repulsion = gradK.sum(axis=0)  # (N, d): sum_j grad_{xi_j} k(xi_j, xi_i)
    phi = (K.T @ g + repulsion) / c[:, None]

    if config.preconditioner == "none":
        return SteinStep(step=config.step_size * phi, bandwidth=h, kernel=K, velocity=phi)

    if hess is None:
        raise InputError("hess is required for the Newton preconditioners", column="hess")
    hess = np.asarray(hess, dtype=float)
    if hess.shape != (n, d, d):
        raise InputError(f"hess must have shape {(n, d, d)}, got {hess.shape}", column="hess")
    eps = config.eig_floor_rel
    fallback = 1.0 / np.asarray(config.scale, dtype=float) ** 2
    # the kernel-weighted and kernel-average matrices need H~_j only, Algorithm 1 and "own" H~_j^-1 only
    need = "inverse" if config.preconditioner == "newton-alg1" or config.hessian == "own" else "floored"
    if need == "floored" and not config.floor_each:
        H_fl, H_inv = _symmetrised(hess, fallback, 1e-12), None
    else:
        H_fl, H_inv, _ = _floor_eig(hess, eps, fallback, 1e-12, want=need)

    if config.preconditioner == "newton-alg1":
        nat = np.einsum("jab,jb->ja", H_inv, g)  # H~_j^-1 g_j
        step = (K.T @ nat + repulsion) / c[:, None]
        return SteinStep(step=config.step_size * step, bandwidth=h, kernel=K, velocity=phi)

    if config.hessian == "own":
        step = np.einsum("iab,ib->ia", H_inv, phi)
        return SteinStep(step=config.step_size * step, bandwidth=h, kernel=K, velocity=phi)
    if config.hessian == "kernel-weighted":
        # SVN block: sum_j k_ji^2 H~_j + grad_j k_ji grad_j k_ji^T, normalised by N ("n":
        # Detommaso et al. exactly) or by sum_j k_ji^2 ("kernel-sum": exact collective step).
        Wk = K**2
        c2 = Wk.sum(axis=0) if config.normalise == "kernel-sum" else np.full(n, float(n))
        gk = np.swapaxes(gradK, 0, 1)  # (N_i, N_j, d)
        rep = np.swapaxes(gk, 1, 2) @ gk  # (N_i, d, d): sum_j grad_j k_ji grad_j k_ji^T
    else:  # kernel-average
        Wk, c2, rep = K, K.sum(axis=0), 0.0
    Hbar = ((Wk.T @ H_fl.reshape(n, d * d)).reshape(n, d, d) + rep) / c2[:, None, None]
    # Floored like every H~_j, where the floor binds: on the tracker's blocks it almost never does (their smallest
    # eigenvalues sit just above it), which a Cholesky test proves without an eigendecomposition (:func:`_unfloored`).
    unfloored = _unfloored(Hbar, eps, fallback, 1e-12)
    Hbar_inv = unfloored[1] if unfloored is not None else _floor_eig(Hbar, eps, fallback, 1e-12, want="inverse")[1]
    step = np.einsum("iab,ib->ia", Hbar_inv, phi)
    return SteinStep(step=config.step_size * step, bandwidth=h, kernel=K, velocity=phi)


def quantile_rows(x: np.ndarray, q: float) -> np.ndarray:
    """``np.quantile(x, q, axis=1)`` (method "linear") of a 2-D ``x (R, N)``, bitwise, in a few NumPy calls.

    The same order statistics (one sort instead of a partition: equal values) and numpy's own interpolation
    ``a + (b - a) g`` (``b - (b - a)(1 - g)`` for ``g >= 0.5``) at the virtual index ``(N - 1) q``; a row with a
    NaN gives NaN. ``np.quantile``'s generic machinery costs ~100 us per call, more than the Stein step's sums.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[1]
    s = np.sort(x, axis=1)  # NaN sorts last
    vi = (n - 1) * float(q)
    lo = math.floor(vi)
    if vi >= n - 1:  # numpy then reads the last value at both ends, with gamma measured from index -1
        lo, hi, g = -1, -1, vi + 1.0
    else:
        hi, g = lo + 1, vi - lo
    a, b = s[:, lo], s[:, hi]
    diff = b - a
    out = b - diff * (1.0 - g) if g >= 0.5 else a + diff * g
    return np.where(np.isnan(s[:, -1]), np.nan, out)


@dataclass(frozen=True)
class StopCriteria:
    """Early stop of the paper (Sec. V-B): small updates and a flat best log-posterior, twice."""

    groups: tuple[tuple[int, ...], ...] = ()
    """Index groups of the tangent whose Euclidean norms are the 'update sizes' (default: all axes)."""
    size_tol: tuple[float, ...] = (1e-6,)
    """Per-group threshold on the 95th percentile (over particles) of the group's update norm."""
    logp_tol: float = 0.02
    """Threshold on |change of the best log-posterior| between iterations."""
    patience: int = 2
    """Number of consecutive iterations satisfying both conditions before stopping."""
    quantile: float = 0.95
    """Quantile of the update sizes over particles."""

    @classmethod
    def paper_se3(cls) -> StopCriteria:
        """Paper Sec. V-B on GTSAM tangents [omega; v]: q95 below 0.5 deg and 0.1 mm, twice."""
        return cls(groups=((0, 1, 2), (3, 4, 5)), size_tol=(math.radians(0.5), 1e-4))

    def __post_init__(self) -> None:
        n_groups = max(len(self.groups), 1)
        if len(self.size_tol) != n_groups:
            raise InputError(f"size_tol needs {n_groups} entries", column="size_tol")
        if self.patience < 1:
            raise InputError("patience must be >= 1", column="patience")


@dataclass
class EarlyStop:
    """Stateful early-stop check; call :meth:`update` once per iteration with the applied steps."""

    criteria: StopCriteria = field(default_factory=StopCriteria)
    """The thresholds."""
    _streak: int = 0
    _best_prev: float | None = None

    def update(self, steps: np.ndarray, best_logp: float) -> bool:
        """Record one iteration's ``steps`` (N, d) and best log-posterior; True when to stop."""
        steps = np.asarray(steps, dtype=float)
        groups = self.criteria.groups or (tuple(range(steps.shape[1])),)
        small = True
        for idx, tol in zip(groups, self.criteria.size_tol, strict=True):
            sizes = np.linalg.norm(steps[:, list(idx)], axis=1)
            small &= bool(np.quantile(sizes, self.criteria.quantile) < tol)
        flat = self._best_prev is not None and abs(best_logp - self._best_prev) < self.criteria.logp_tol
        self._best_prev = float(best_logp)
        self._streak = self._streak + 1 if (small and flat) else 0
        return self._streak >= self.criteria.patience


LogpGradHess = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class TransportResult:
    """Outcome of :func:`transport`."""

    xi: np.ndarray
    """(N, d) final particles."""
    logp: np.ndarray
    """(N,) log-posterior at the final particles."""
    iterations: int
    """Number of Stein steps applied."""
    converged: bool
    """True if the early stop fired before max_iters."""
    step_norms: tuple[float, ...]
    """Per iteration, the largest particle step norm (diagnostic)."""


def transport(
    xi0: np.ndarray,
    logp_grad_hess: LogpGradHess,
    config: SteinConfig,
    max_iters: int = 30,
    stop: StopCriteria | None = None,
    backtrack_drop: float | None = None,
    max_halvings: int = 5,
) -> TransportResult:
    """Euclidean Stein transport driver (the SE(3) driver lives in the tracker).

    ``logp_grad_hess(xi (M, d)) -> (logp (M,), grad (M, d), hess (M, d, d))`` for any M.
    Each iteration: :func:`stein_step`, then ``xi <- xi + step``. Stops after ``max_iters``
    or when :class:`EarlyStop` fires (``stop``; default thresholds of :class:`StopCriteria`).

    Backtracking safeguard (off when ``backtrack_drop`` is None): a particle whose
    log-posterior would drop by more than ``backtrack_drop`` has its step halved, up to
    ``max_halvings`` times, then the step is dropped (the particle stays). Stein steps may
    legitimately lower a particle's log-posterior (repulsion), hence a tolerance rather than
    a strict descent test; the safeguard only stops a Newton step that overshoots into a
    collapse of the posterior.
    """
    xi = _check_particles(np.array(xi0, dtype=float), "xi0")
    if max_iters < 0:
        raise InputError("max_iters must be >= 0", column="max_iters")
    if backtrack_drop is not None and not backtrack_drop >= 0:
        raise InputError("backtrack_drop must be >= 0 (or None to disable)", column="backtrack_drop")
    early = EarlyStop(stop or StopCriteria())
    logp, grad, hess = logp_grad_hess(xi)
    norms: list[float] = []
    converged = False
    it = 0
    while it < max_iters:
        res = stein_step(xi, grad, hess, config)
        step = res.step
        cand = xi + step
        c_logp, c_grad, c_hess = (np.array(a, dtype=float) for a in logp_grad_hess(cand))
        if backtrack_drop is not None:
            for k in range(max_halvings + 1):
                bad = ~(c_logp >= logp - backtrack_drop)  # also catches NaN
                if not np.any(bad):
                    break
                factor = 0.5 if k < max_halvings else 0.0
                step[bad] *= factor
                cand[bad] = xi[bad] + step[bad]
                b_logp, b_grad, b_hess = logp_grad_hess(cand[bad])
                c_logp[bad], c_grad[bad], c_hess[bad] = b_logp, b_grad, b_hess
        xi, logp, grad, hess = cand, c_logp, c_grad, c_hess
        it += 1
        norms.append(float(np.max(np.linalg.norm(step, axis=1))))
        if early.update(step, float(np.max(logp))):
            converged = True
            break
    return TransportResult(xi=xi, logp=logp, iterations=it, converged=converged, step_norms=tuple(norms))
