"""Reference implementations kept only to pin the library's fast paths (one implementation in the library).

``conic_residual_reference`` is the conic kernel as it was before it was restructured for speed
(one (N, 6, 3, M) product per derivative); ``stein_step_reference`` (with its helpers) is the
Stein step before it shared one pairwise-difference pass and replaced its einsums by matrix
products. ``tests/test_factors_fastpaths.py`` pins the library to them.
"""

from __future__ import annotations

import math

import numpy as np

from factors.lie import skew
from factors.residuals import SAMPSON_MAX_PX, as_pose_batch
from pinpoint_fg.errors import InputError
from pinpoint_fg.stein import SteinConfig, SteinStep, _check_particles


def conic_residual_reference(
    cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float, points_px: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`factors.residuals.conic_residual` as first written (the same Sampson distance, its docstring states
    the mathematics): every product formed in full, no coefficient tables. The production kernel is pinned to
    this one; kept apart so a restructuring of the fast path is checked against an independent copy.
    """
    T = as_pose_batch(cam_T_needle)
    K = np.asarray(K, dtype=float)
    pts = np.asarray(points_px, dtype=float)
    N, M = T.shape[0], pts.shape[0]
    R, t = T[:, :3, :3], T[:, :3, 3]
    h1 = R[:, :, 0] @ K.T
    h2 = R[:, :, 1] @ K.T
    h3 = t @ K.T
    # dh/dxi (N, 3, 6): d(R e_k) = -R [e_k]x omega, dt = R v
    KR = K @ R
    e = np.eye(3)
    Dh1 = np.concatenate([-KR @ skew(e[0]), np.zeros((N, 3, 3))], axis=2)
    Dh2 = np.concatenate([-KR @ skew(e[1]), np.zeros((N, 3, 3))], axis=2)
    Dh3 = np.concatenate([np.zeros((N, 3, 3)), KR], axis=2)
    # adjugate rows a1 = h2 x h3, a2 = h3 x h1, a3 = h1 x h2 and their Jacobians
    a1, a2, a3 = np.cross(h2, h3), np.cross(h3, h1), np.cross(h1, h2)
    S1, S2, S3 = skew(h1), skew(h2), skew(h3)
    Da1 = -S3 @ Dh2 + S2 @ Dh3
    Da2 = -S1 @ Dh3 + S3 @ Dh1
    Da3 = -S2 @ Dh1 + S1 @ Dh2
    A = np.stack([a1, a2, a3], axis=1)  # (N, 3, 3)
    DA = np.stack([Da1, Da2, Da3], axis=1)  # (N, 3, 3, 6): row i, component k, xi
    scale = 1.0 / np.maximum(np.linalg.norm(A, axis=(1, 2)), 1e-300)
    A = A * scale[:, None, None]
    DA = DA * scale[:, None, None, None]

    # Work in centred, scaled pixels x = P xh (P = [[s, 0, cu], [0, s, cv], [0, 0, 1]]) so every term
    # is O(1): f is unchanged, the image gradient scales by s, and s_px = s * f / |gh|.
    centre = pts.mean(axis=0) if M else np.zeros(2)
    sc = max(float(np.sqrt(np.mean(np.sum((pts - centre) ** 2, axis=1)))) if M else 1.0, 1.0)
    P = np.array([[sc, 0.0, centre[0]], [0.0, sc, centre[1]], [0.0, 0.0, 1.0]])
    xh = np.concatenate([(pts - centre) / sc, np.ones((M, 1))], axis=1)  # (M, 3)
    Q = np.diag([1.0, 1.0, -(float(radius_m) ** 2)])
    # Ch = P^T A^T Q A P and its derivative per tangent direction (N, 6, 3, 3)
    AP = A @ P
    QAP = Q @ AP
    C = np.swapaxes(AP, 1, 2) @ QAP
    DAd = np.moveaxis(DA, 3, 1) @ P  # (N, 6, 3, 3): [n, d, row i, component k]
    dC = np.swapaxes(DAd, 2, 3) @ QAP[:, None]
    dC = dC + np.swapaxes(dC, 2, 3)
    cn = 1.0 / np.maximum(np.linalg.norm(C, axis=(1, 2)), 1e-300)  # scale invariance again
    C = C * cn[:, None, None]
    dC = dC * cn[:, None, None, None]
    xT = xh.T  # (3, M)
    Cx = C @ xT  # (N, 3, M)
    f = np.sum(Cx * xT, axis=1)  # (N, M)
    g = 2.0 * np.swapaxes(Cx[:, :2, :], 1, 2)  # (N, M, 2)
    if not jacobian:
        g2 = np.sum(g * g, axis=2)
        f2d = (f * sc / SAMPSON_MAX_PX) ** 2
        den = g2 + f2d
        ok = den > 0
        return sc * f * np.sqrt(g2) * np.where(ok, 1.0 / np.where(ok, den, 1.0), 0.0), None
    dCx = dC @ xT  # (N, 6, 3, M)
    Df = np.swapaxes(np.sum(dCx * xT, axis=2), 1, 2)  # (N, M, 6)
    Dg = 2.0 * np.moveaxis(dCx[:, :, :2, :], (1, 2, 3), (3, 2, 1))  # (N, M, 2, 6)
    g2 = np.sum(g * g, axis=2)
    gn = np.sqrt(g2)
    f2d = (f * sc / SAMPSON_MAX_PX) ** 2
    den = g2 + f2d
    ok = den > 0
    iden = np.where(ok, 1.0 / np.where(ok, den, 1.0), 0.0)
    r = sc * f * gn * iden
    # s = sc f |g| / den:  ds = sc [df (|g| - 2 f2d |g| / den) / den + d|g| f (1 - 2 g^2 / den) / den]
    gdg = g[..., 0, None] * Dg[..., 0, :] + g[..., 1, None] * Dg[..., 1, :]
    safe_gn = np.where(gn > 0, gn, 1.0)
    dgn = np.where((gn > 0)[..., None], gdg / safe_gn[..., None], 0.0)
    c_f = sc * gn * (1.0 - 2.0 * f2d * iden) * iden
    c_g = sc * f * (1.0 - 2.0 * g2 * iden) * iden
    J = Df * c_f[..., None] + dgn * c_g[..., None]
    return r, J


def median_bandwidth_reference(xi_white: np.ndarray, floor: float) -> float:
    """Median-heuristic bandwidth ``h = max(median_{i<j} ||xi_i - xi_j||^2 / log N, floor)``.

    ``xi_white`` (N, d) are already whitened (divided by S). With N = 1 there are no pairs and
    ``log 1 = 0``: the floor is returned. ``floor`` must be > 0 so that h > 0 always.
    """
    xi_white = _check_particles(xi_white, "xi_white")
    if not (math.isfinite(floor) and floor > 0):
        raise InputError("bandwidth floor must be finite and > 0", column="bandwidth_floor")
    n = xi_white.shape[0]
    if n < 2:
        return float(floor)
    diff = xi_white[:, None, :] - xi_white[None, :, :]
    d2 = np.einsum("ijk,ijk->ij", diff, diff)
    iu = np.triu_indices(n, k=1)
    m = float(np.median(d2[iu]))
    return max(m / math.log(n), float(floor))


def kernel_matrix_reference(xi: np.ndarray, scale: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
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


def floor_hessians_reference(
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
    fb = np.ones(d) if fallback is None else np.asarray(fallback, dtype=float)
    if fb.shape != (d,) or not np.all(np.isfinite(fb)) or np.any(fb <= 0):
        raise InputError("fallback must be (d,) finite and > 0", column="fallback")
    finite = np.all(np.isfinite(H), axis=(1, 2))
    Hs = np.where(finite[:, None, None], H, 0.0)
    Hs = 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
    w, V = np.linalg.eigh(Hs)  # ascending eigenvalues
    w_max = w[:, -1]
    usable = finite & (w_max > min_info_rel * fb.max())
    w_fl = np.maximum(w, eps * w_max[:, None])
    # Unusable rows: replace by the fallback diagonal (eigenvectors = identity).
    w_fl = np.where(usable[:, None], w_fl, fb[None, :])
    V = np.where(usable[:, None, None], V, np.eye(d)[None, :, :])
    H_fl = np.einsum("nik,nk,njk->nij", V, w_fl, V)
    H_inv = np.einsum("nik,nk,njk->nij", V, 1.0 / w_fl, V)
    return H_fl, H_inv


def stein_step_reference(
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
    g = np.where(np.isfinite(g), g, 0.0)

    S = config.kernel_scale
    h = median_bandwidth_reference(xi / S, config.bandwidth_floor)
    K, gradK = kernel_matrix_reference(xi, S, h)
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
    H_fl, H_inv = floor_hessians_reference(hess, eps, fallback)
    if not config.floor_each:  # only the kernel sum is floored: each H_j symmetrised, the fallback where unusable
        finite = np.all(np.isfinite(hess), axis=(1, 2))
        Hs = np.where(finite[:, None, None], hess, 0.0)
        Hs = 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
        usable = finite & (np.trace(Hs, axis1=1, axis2=2) > d * 1e-12 * fallback.max())
        H_fl = np.where(usable[:, None, None], Hs, np.diag(fallback)[None])

    if config.preconditioner == "newton-alg1":
        nat = np.einsum("jab,jb->ja", H_inv, g)  # H~_j^-1 g_j
        step = (K.T @ nat + repulsion) / c[:, None]
        return SteinStep(step=config.step_size * step, bandwidth=h, kernel=K, velocity=phi)

    K2 = K**2
    if config.hessian == "own":
        Hbar_inv = H_inv
    else:
        if config.hessian == "kernel-weighted":
            # SVN block: sum_j k_ji^2 H~_j + grad_j k_ji grad_j k_ji^T, normalised by N ("n":
            # Detommaso et al. exactly) or by sum_j k_ji^2 ("kernel-sum": exact collective step).
            c2 = K2.sum(axis=0) if config.normalise == "kernel-sum" else np.full(n, float(n))
            Hbar = (np.einsum("ji,jab->iab", K2, H_fl)
                    + np.einsum("jia,jib->iab", gradK, gradK)) / c2[:, None, None]
        else:  # kernel-average
            Hbar = np.einsum("ji,jab->iab", K, H_fl) / K.sum(axis=0)[:, None, None]
        _, Hbar_inv = floor_hessians_reference(Hbar, eps, fallback)
    step = np.einsum("iab,ib->ia", Hbar_inv, phi)
    return SteinStep(step=config.step_size * step, bandwidth=h, kernel=K, velocity=phi)
