"""Reference implementations kept only to pin the library's fast paths (one implementation in the library).

``conic_residual_reference`` is the conic kernel as it was before it was restructured for speed
(one (N, 6, 3, M) product per derivative); ``tests/test_factors_fastpaths.py`` pins
:func:`factors.residuals.conic_residual` to it.
"""

from __future__ import annotations

import numpy as np

from factors.lie import skew
from factors.residuals import SAMPSON_MAX_PX, as_pose_batch


def conic_residual_reference(
    cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float, points_px: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Sampson distance (pixels) of each backbone pixel to the image conic of the needle circle.

    ``H = K [r1 r2 t]`` maps the needle plane to the image; with ``A = adj(H)`` (the adjugate,
    ``H^-1 ∝ A``) the conic is ``C = A^T Q A``, ``Q = diag(1, 1, -r^2)`` (paper Eq. for C(T)).
    For a pixel ``x = (u, v, 1)``: ``y = A x``, ``f = x^T C x = y1^2 + y2^2 - r^2 y3^2``,
    ``g = grad_(u,v) f = 2 (A^T Q y)_{1:2}`` (image coordinates only — the paper's 3-vector norm
    is a slip, DESIGN.md), and the residual is ``s = f / |g|``.

    The Sampson distance is invariant to the scale of ``C``, so ``A`` is normalised per pose to
    unit Frobenius norm (its derivative then drops out of ``ds``). The denominator is
    regularised without a scale: ``s = f |g| / (|g|^2 + (f / D)^2)`` with
    ``D = SAMPSON_MAX_PX``. It differs from ``f / |g|`` by a relative ``(s / D)^2`` (< 1e-12 for
    any pixel within 100 px of the conic) and stays finite where ``g = 0`` — at the conic's
    centre, and on the double line an edge-on needle projects to (``H`` singular, ``A`` rank 1,
    ``C = l l^T``) — where such pixels read 0 (0/0 is defined as 0). ``|s|`` never exceeds
    ``D / 2``. The circle is the full circle, not the arc (the paper's model). A circle behind
    the camera projects to the same conic: this residual cannot see cheirality.

    Internally the pixels are centred and scaled (``x = P xh``) so every product is O(1); ``f``
    is unchanged by that and the image gradient scales exactly, so the result is the same
    Sampson distance in pixels.

    ``points_px`` ``(M, 2)`` are undistorted pixels. Returns ``r (N, M)``, ``J (N, M, 6)``
    (``J`` is None with ``jacobian=False``, which skips its computation; ``r`` is identical).
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
