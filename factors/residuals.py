"""The five residuals of PinPoint, batched over poses, with analytic Jacobians.

This module is the only implementation of the measurement maths: the GTSAM factors in
:mod:`factors.gtsam_factors` call these functions for one pose, and the trackers call them
for all particles at once.

Every function takes poses ``cam_T_needle`` of shape ``(N, 4, 4)`` (a single ``(4, 4)`` is
promoted to ``N = 1``) and returns the *unwhitened* residual and its Jacobian
``d r(T ⊕ xi) / d xi`` in GTSAM's chart ``T ⊕ xi = T · Exp(xi)``, ``xi = [omega; v]``
(:mod:`factors.conventions`). With ``T ⊕ xi``: ``R -> R (I + [omega]x)``, ``t -> t + R v``, so a
needle-frame point ``X`` moves by ``d(R X + t) = -R [X]x omega + R v``.

Degenerate geometry (documented per function) gives finite values, never NaN or inf.
"""

from __future__ import annotations

import numpy as np

from factors.lie import cross, se3_adjoint, se3_inverse, se3_log, se3_log_right_jacobian_inv, skew

#: Depths with |z| below this (metres) are clamped (keeping the sign) before dividing.
MIN_DEPTH_M = 1e-6

#: Scale-free regulariser of the Sampson denominator, pixels (see :func:`conic_residual`).
SAMPSON_MAX_PX = 1e8


#: Gather of a flattened 3x3 conic (index 9 = 0) into its coefficients on phi = [u^2, 2uv, v^2, 2u, 2v, 1]
#: for f = x^T C x, g1 = 2 (C x)_1, g2 = 2 (C x)_2 (see :func:`conic_residual`).
_CONIC_COEF_INDEX = np.array([[0, 1, 4, 2, 5, 8], [9, 9, 9, 0, 1, 2], [9, 9, 9, 1, 4, 5]])
_CONIC_COEF_MULT = np.array([[1.0] * 6, [1.0] * 5 + [2.0], [1.0] * 5 + [2.0]])


def _frozen(cache: dict, key: object, make, bound: int = 256) -> np.ndarray:
    """``cache[key]``, built by ``make()`` on a miss and kept read-only (constants derived once per value).

    The memos below hold a handful of entries per run (needle points, unit axes, the needle radius); the
    bound only guards against a caller that feeds a new value every time.
    """
    out = cache.get(key)
    if out is None:
        if len(cache) > bound:
            cache.clear()
        out = make()
        out.flags.writeable = False
        cache[key] = out
    return out


#: :func:`_skew_const`'s, :func:`_unit_const`'s and :func:`_conic_q`'s results.
_SKEW_CONST: dict[bytes, np.ndarray] = {}
_UNIT_CONST: dict[bytes, np.ndarray] = {}
_CONIC_Q: dict[float, np.ndarray] = {}


def _skew_const(x: np.ndarray) -> np.ndarray:
    """``skew(x)`` of one constant 3-vector (a needle point, an axis), computed once per value (read-only)."""
    x = np.asarray(x, dtype=float)
    return _frozen(_SKEW_CONST, x.tobytes() + bytes(str(x.shape), "ascii"), lambda: skew(x))


def _unit_const(x: np.ndarray, last_axis: bool = False) -> np.ndarray:
    """``x / np.linalg.norm(x)`` of one 3-vector, computed once per value (read-only; bounded memo).

    ``last_axis``: ``x / np.linalg.norm(x, axis=-1, keepdims=True)`` instead (NumPy sums that norm
    differently from the whole-array one: each form is kept where it was used, bit for bit).
    """
    x = np.asarray(x, dtype=float)

    def make() -> np.ndarray:
        n = np.linalg.norm(x, axis=-1, keepdims=True) if last_axis else np.linalg.norm(x)
        if not (np.all(np.isfinite(n)) and np.all(n > 0)):  # checked once per value (memo): was NaN residuals
            raise ValueError(f"a direction must be non-zero and finite, got {x.tolist()}")
        return x / n

    return _frozen(_UNIT_CONST, x.tobytes() + (b"a" if last_axis else b""), make)


def _conic_q(radius_m: float) -> np.ndarray:
    """``Q = diag(1, 1, -r^2)`` of :func:`conic_residual`, built once per radius (read-only; bounded memo)."""
    r = float(radius_m)
    if not 0.0 < r < 1e150:  # NaN read NaN residuals, 0 a degenerate conic, 1e200 an OverflowError of r ** 2
        raise ValueError(f"radius_m must be a positive finite number, got {radius_m!r}")
    return _frozen(_CONIC_Q, r, lambda: np.diag([1.0, 1.0, -(r ** 2)]), bound=64)


def as_pose_batch(cam_T_needle: np.ndarray) -> np.ndarray:
    """Promote ``(4, 4)`` to ``(1, 4, 4)``; check the shape and finiteness of a pose batch."""
    T = np.asarray(cam_T_needle, dtype=float)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"cam_T_needle must have shape (N, 4, 4) or (4, 4), got {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError("cam_T_needle contains NaN or infinite values")
    return T


def point_jacobian(cam_T_needle: np.ndarray, needle_p: np.ndarray, jacobian: bool = True
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """Camera-frame point ``p = R X + t`` ``(N, 3)`` and ``dp/dxi = [-R [X]x, R]`` ``(N, 3, 6)``.

    ``jacobian=False`` returns None for the Jacobian and skips building it; ``p`` is the same bit for bit.
    """
    T = as_pose_batch(cam_T_needle)
    R, t = T[:, :3, :3], T[:, :3, 3]
    X = np.asarray(needle_p, dtype=float)
    p = R @ X + t
    if not jacobian:
        return p, None
    J = np.empty((T.shape[0], 3, 6))  # [-R [X]x, R] filled in place (np.concatenate's result, without its overhead)
    J[:, :, :3] = -R @ _skew_const(X)
    J[:, :, 3:] = R
    return p, J


def keypoint_residual(
    cam_T_needle: np.ndarray, K: np.ndarray, needle_p: np.ndarray, measured_px: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Reprojection residual ``pi(T X) - z`` in pixels (paper Eq. for r_key, appendix A).

    ``pi(p) = (fx x/z + cx, fy y/z + cy)`` with the ideal pinhole ``K`` (``measured_px`` must be
    undistorted). Returns ``r (N, 2)``, ``J (N, 2, 6)`` (None with ``jacobian=False``, which skips building
    it: what a likelihood-only caller, the particle filter, needs; ``r`` is identical).

    Behind the camera (z < 0) the projection is the central mirror image and stays finite; a
    point in the camera plane has its depth clamped to ``±MIN_DEPTH_M``. Trackers reject
    poses with the needle behind the camera separately (they are not image-consistent).
    """
    K = np.asarray(K, dtype=float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p, Jp = point_jacobian(cam_T_needle, needle_p, jacobian)
    z = p[:, 2]
    clamp = np.abs(z) < MIN_DEPTH_M
    if clamp.any():
        z = np.where(clamp, np.where(z < 0, -MIN_DEPTH_M, MIN_DEPTH_M), z)
    iz = 1.0 / z
    u = fx * p[:, 0] * iz + cx
    v = fy * p[:, 1] * iz + cy
    uv = np.empty((p.shape[0], 2))  # np.stack([u, v], axis=1), filled in place
    uv[:, 0] = u
    uv[:, 1] = v
    r = uv - np.asarray(measured_px, dtype=float)
    if Jp is None:
        return r, None
    Jpi = np.zeros((p.shape[0], 2, 3))
    Jpi[:, 0, 0] = fx * iz
    Jpi[:, 0, 2] = -fx * p[:, 0] * iz * iz
    Jpi[:, 1, 1] = fy * iz
    Jpi[:, 1, 2] = -fy * p[:, 1] * iz * iz
    return r, Jpi @ Jp


def needle_image_conic(cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float) -> np.ndarray:
    """Image conic ``C = A^T diag(1, 1, -r^2) A`` of the needle circle, ``A = adj(K [r1 r2 t])``; ``(N, 3, 3)``.

    The same construction :func:`conic_residual` differentiates (adjugate rows ``h2 x h3``,
    ``h3 x h1``, ``h1 x h2``), without its Jacobian, scaled to unit Frobenius norm and to a
    non-negative ``C[0, 0] + C[1, 1]`` so that two poses' conics can be compared entrywise.
    """
    T = as_pose_batch(cam_T_needle)
    K = np.asarray(K, dtype=float)
    h1, h2, h3 = T[:, :3, 0] @ K.T, T[:, :3, 1] @ K.T, T[:, :3, 3] @ K.T
    A = cross(np.stack([h2, h3, h1], axis=1), np.stack([h3, h1, h2], axis=1))  # rows h2 x h3, h3 x h1, h1 x h2
    C = np.swapaxes(A, 1, 2) @ np.diag([1.0, 1.0, -(float(radius_m) ** 2)]) @ A
    C = C / np.maximum(np.linalg.norm(C, axis=(1, 2)), 1e-300)[:, None, None]
    sign = np.where(C[:, 0, 0] + C[:, 1, 1] < 0, -1.0, 1.0)
    return C * sign[:, None, None]


def _conic_setup(cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float, points_px: np.ndarray, jacobian: bool
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """``(T, pts, sc, phi, Ch, coef)`` of a conic residual's arguments: the checked poses and pixels, then
    :func:`_pixel_basis`'s scale and basis and :func:`_conic_coefficients` in it. The pixels are centred and
    scaled (``x = P xh``, ``P = [[s, 0, cu], [0, s, cv], [0, 0, 1]]``) so every term is O(1): ``f`` is unchanged
    and the image gradient scales by ``s`` (distances in pixels are ``s`` times those in the basis)."""
    T = as_pose_batch(cam_T_needle)
    pts = np.asarray(points_px, dtype=float)
    _, sc, P, phi = _pixel_basis(pts)
    C, coef = _conic_coefficients(T, K, radius_m, P, jacobian)
    return T, pts, sc, phi, C, coef


def _conic_coefficients(T: np.ndarray, K: np.ndarray, radius_m: float, P: np.ndarray, jacobian: bool
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The needle circle's image conic in the pixel basis ``x = P xh`` (:func:`_pixel_basis`), per pose, and the
    coefficients of ``f``, ``g1``, ``g2`` (value and, with ``jacobian``, the six derivatives) on
    ``phi = [u^2, 2uv, v^2, 2u, 2v, 1]``: ``Ch (N, 3, 3)`` (unit Frobenius norm) and ``coef (N, n7, 3, 6)``
    (``n7`` = 7, or 1 without ``jacobian``). :func:`conic_residual` and :func:`conic_geometric_residual` share it.
    """
    N = T.shape[0]
    K = np.asarray(K, dtype=float)
    R, t = T[:, :3, :3], T[:, :3, 3]
    KR = K @ R
    h1, h2, h3 = KR[:, :, 0], KR[:, :, 1], t @ K.T
    # adjugate rows a1 = h2 x h3, a2 = h3 x h1, a3 = h1 x h2
    # the three cross products in one (np.cross's own elementwise formula, in fewer calls)
    A = cross(np.stack([h2, h3, h1], axis=1), np.stack([h3, h1, h2], axis=1))  # (N, 3, 3), C order
    scale = 1.0 / np.maximum(np.sqrt(np.add.reduce(A * A, axis=(1, 2))), 1e-300)  # = 1 / Frobenius norm
    A = A * scale[:, None, None]
    Q = _conic_q(radius_m)
    # Ch = P^T A^T Q A P (N, 3, 3), normalised (scale invariance again)
    AP = A @ P
    QAP = Q @ AP
    C = np.swapaxes(AP, 1, 2) @ QAP
    cn = 1.0 / np.maximum(np.sqrt(np.add.reduce(C * C, axis=(1, 2))), 1e-300)
    C = C * cn[:, None, None]
    if jacobian:
        # dh/dxi (N, 3, 6): d(R e_k) = -R [e_k]x omega, dt = R v
        Dh1 = np.zeros((N, 3, 6))  # [-KR [e_k]x, 0] and [0, KR], filled in place
        Dh1[:, :, :3] = -KR @ _SKEW_E[0]
        Dh2 = np.zeros((N, 3, 6))
        Dh2[:, :, :3] = -KR @ _SKEW_E[1]
        Dh3 = np.zeros((N, 3, 6))
        Dh3[:, :, 3:] = KR
        S1, S2, S3 = skew(h1), skew(h2), skew(h3)
        DA = np.stack([-S3 @ Dh2 + S2 @ Dh3, -S1 @ Dh3 + S3 @ Dh1, -S2 @ Dh1 + S1 @ Dh2], axis=1)  # (N, 3, 3, 6)
        DAd = np.moveaxis(DA * scale[:, None, None, None], 3, 1) @ P  # (N, 6, 3, 3): [n, d, row i, component k]
        dC = np.swapaxes(DAd, 2, 3) @ QAP[:, None]
        dC = (dC + np.swapaxes(dC, 2, 3)) * cn[:, None, None, None]
        Call = np.concatenate([C[:, None], dC], axis=1)  # (N, 7, 3, 3): value and six derivatives
    else:
        Call = C[:, None]
    # x^T C x and the image gradient 2 (C x)_{1:2} are linear in C's six distinct entries: with the
    # pixel basis phi(x) = [u^2, 2uv, v^2, 2u, 2v, 1], f = c . phi, g1 = (c11, c12, 2 c13) . phi[3:],
    # g2 = (c12, c22, 2 c23) . phi[3:]. The value and the six derivatives of C become ONE
    # (N * 7 * 3, 6) @ (6, M) product: f, g1, g2 and their derivatives for every pixel at once.
    n7 = Call.shape[1]
    flat = np.concatenate([Call.reshape(N, n7, 9), np.zeros((N, n7, 1))], axis=2)  # index 9 reads 0
    return C, flat[:, :, _CONIC_COEF_INDEX] * _CONIC_COEF_MULT  # (N, n7, 3, 6)


def conic_residual(
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
    T, pts, sc, phi, _, coef = _conic_setup(cam_T_needle, K, radius_m, points_px, jacobian)
    N, M, n7 = T.shape[0], pts.shape[0], coef.shape[1]
    out = (coef.reshape(-1, 6) @ phi).reshape(N, n7, 3, M)
    f, g1, g2 = out[:, 0, 0], out[:, 0, 1], out[:, 0, 2]  # (N, M)
    g2s = g1 * g1 + g2 * g2
    gn = np.sqrt(g2s)
    f2d = (f * sc / SAMPSON_MAX_PX) ** 2
    den = g2s + f2d
    ok = den > 0
    # 0/0 := 0 where the denominator vanishes; a batch without such pixels (the usual case) skips the two selects
    iden = 1.0 / den if ok.all() else np.where(ok, 1.0 / np.where(ok, den, 1.0), 0.0)
    r = sc * f * gn * iden
    if not jacobian:
        return r, None
    # s = sc f |g| / den:  ds = sc [df (|g| - 2 f2d |g| / den) / den + d|g| f (1 - 2 g^2 / den) / den],
    # d|g| = (g1 dg1 + g2 dg2) / |g| (0 where g = 0)
    c_f = sc * gn * (1.0 - 2.0 * f2d * iden) * iden
    c_g = sc * f * (1.0 - 2.0 * g2s * iden) * iden
    pos = gn > 0
    q = c_g / gn if pos.all() else np.where(pos, c_g / np.where(pos, gn, 1.0), 0.0)
    # J = out_f c_f + out_g1 (g1 q) + out_g2 (g2 q), summed in that order into one buffer (N, 6, M)
    J = out[:, 1:, 0] * c_f[:, None]
    tmp = out[:, 1:, 1] * (g1 * q)[:, None]
    J += tmp
    J += np.multiply(out[:, 1:, 2], (g2 * q)[:, None], out=tmp)
    return r, np.swapaxes(J, 1, 2)


#: :func:`conic_geometric_residual` treats an ellipse with ``b / a`` below this (a needle within 0.06 deg of
#: edge-on) as the double line an exactly edge-on circle projects to, and takes the Sampson distance there: the
#: closest point then sits at an end whose radius of curvature ``b^2 / a`` is below 1e-6 of the ellipse, and the
#: distance's derivative there is no longer resolved (measured against finite differences: 1e-5 failed).
THIN_ELLIPSE_RATIO = 1e-3

#: Bracketed Newton iterations at most of :func:`conic_geometric_residual`'s foot-point search (it stops earlier
#: once every step is below round-off; each iteration narrows the bracket at least by half where Newton leaves it).
FOOT_POINT_ITERATIONS = 60


def _ellipse_frames(C: np.ndarray) -> tuple[np.ndarray, ...]:
    """Centre ``m (N, 2)``, semi-axes ``a >= b (N,)``, unit major and minor axes ``e1, e2 (N, 2)`` of conics
    ``C (N, 3, 3)`` (``x^T C x = 0``, ``x = (u, v, 1)``), and ``ok (N,)``: which are real, proper ellipses.

    ``(x - m)^T A2 (x - m) = k`` with ``A2 = C[:2, :2]``, ``m = -A2^-1 C[:2, 2]``, ``k = -C[:2, 2] . m - C[2, 2]``;
    ``A2 / k`` has eigenvalues ``1 / a^2 <= 1 / b^2``, the smaller from the determinant (no cancellation for a thin
    ellipse). Rows that are not ellipses (hyperbola, parabola, a line pair or double line, imaginary) get
    harmless placeholders and ``ok`` False.
    """
    p, q, r = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    det = p * r - q * q
    ok = det > 0
    idet = 1.0 / np.where(ok, det, 1.0)
    bu, bv = C[:, 0, 2], C[:, 1, 2]
    mu = -(r * bu - q * bv) * idet
    mv = -(p * bv - q * bu) * idet
    k = -(bu * mu + bv * mv) - C[:, 2, 2]
    ok &= (k * p > 0) & np.isfinite(k)
    ik = 1.0 / np.where(ok, k, 1.0)
    p, q, r = p * ik, q * ik, r * ik
    half = 0.5 * (p - r)
    big = 0.5 * (p + r) + np.hypot(half, q)  # 1 / b^2
    small = (p * r - q * q) / np.where(ok, big, 1.0)  # 1 / a^2 = det / (1 / b^2)
    ok &= (small > 0) & np.isfinite(big) & (small > THIN_ELLIPSE_RATIO**2 * big)
    a = 1.0 / np.sqrt(np.where(ok, small, 1.0))
    b = 1.0 / np.sqrt(np.where(ok, big, 1.0))
    psi = 0.5 * np.arctan2(2.0 * q, p - r)  # direction of the larger eigenvalue: the minor axis
    e2 = np.stack([np.cos(psi), np.sin(psi)], axis=1)
    e1 = np.stack([-e2[:, 1], e2[:, 0]], axis=1)
    return np.stack([mu, mv], axis=1), a, b, e1, e2, ok


def _foot_point(U: np.ndarray, V: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point ``(x, y)`` on the ellipse ``x^2 / a^2 + y^2 / b^2 = 1`` to points ``(U, V)``, ``U, V >= 0``.

    The foot point is ``(a^2 U / (t + a^2), b^2 V / (t + b^2))`` with ``t`` the root in ``(-b^2, inf)`` of
    ``F(t) = (a U / (t + a^2))^2 + (b V / (t + b^2))^2 - 1``, which is convex and decreasing there (Eberly,
    "Distance from a point to an ellipse"). It lies in ``[b V - b^2, sqrt(a^2 U^2 + b^2 V^2) - b^2]``; solved in
    ``w = log(t + b^2)``, where the near-pole behaviour of a point on a thin ellipse's major axis is nearly linear,
    by Newton steps kept inside the bracket (bisection otherwise). ``V`` is floored at ``1e-12 b``: on the major
    axis itself the root is the pole, and the floor moves the distance by ~1e-12 relative.
    """
    V = np.maximum(V, 1e-12 * b)
    aU, bV = a * U, b * V
    gap = a * a - b * b
    lo = np.log(bV)
    hi = np.log(np.maximum(np.sqrt(aU * aU + bV * bV), bV))
    w = np.clip(np.log(b * b), lo, hi)  # t = 0: a point on the ellipse
    for _ in range(FOOT_POINT_ITERATIONS):
        s = np.exp(w)
        x1, x2 = aU / (s + gap), bV / s
        F = x1 * x1 + x2 * x2 - 1.0
        dF = -2.0 * s * (x1 * x1 / (s + gap) + x2 * x2 / s)  # dF/dw = s dF/ds
        lo = np.where(F > 0, w, lo)
        hi = np.where(F > 0, hi, w)
        step = np.where(dF < 0, -F / np.where(dF < 0, dF, -1.0), 0.0)
        w_new = w + step
        inside = (w_new >= lo) & (w_new <= hi)
        w_new = np.where(inside, w_new, 0.5 * (lo + hi))
        done = np.abs(w_new - w) <= 1e-14 * np.maximum(1.0, np.abs(w))
        w = w_new
        if done.all():
            break
    s = np.exp(w)
    return a * aU / (s + gap), b * bV / s


def conic_geometric_residual(
    cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float, points_px: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed geometric distance (pixels) of each backbone pixel to the needle circle's image ellipse.

    :func:`conic_residual`'s Sampson distance ``f / |grad f|`` is the distance to first order, which fails where
    the ellipse is thin (a needle within a few degrees of edge-on): measured at the true pose through drive-02's
    edge-on turn it read up to 35 px for pixels within 1 px of the ellipse. Here the distance is exact: the
    closest point ``q`` (:func:`_foot_point`, in the ellipse's own axes), ``r = sign(f(p)) |p - q|`` (the Sampson
    distance's sign, so the two agree to first order near the curve). Its Jacobian follows from moving the curve
    along its normal: ``dr / dxi = (df / dxi)(q) / |grad f(q)|`` (``f = x^T C x`` with the same ``C`` and ``dC``
    as :func:`conic_residual`; the closest point's own motion is tangential and drops out). Poses whose conic is
    not a real ellipse (the circle crossing the camera's principal plane, or exactly edge-on: a double line) fall
    back to the Sampson distance, row by row. The circle is the full circle, as for the Sampson distance.

    ``points_px`` ``(M, 2)`` undistorted pixels. Returns ``r (N, M)``, ``J (N, M, 6)`` (None with
    ``jacobian=False``; ``r`` identical).
    """
    T, pts, sc, phi, C, coef = _conic_setup(cam_T_needle, K, radius_m, points_px, jacobian)
    N, M, n7 = T.shape[0], pts.shape[0], coef.shape[1]
    m, a, b, e1, e2, ok = _ellipse_frames(C)
    x = phi[3:5] * 0.5  # (2, M): the centred, scaled pixels
    d = x[None, :, :] - m[:, :, None]  # (N, 2, M)
    u = np.einsum("nk,nkm->nm", e1, d)
    v = np.einsum("nk,nkm->nm", e2, d)
    fx, fy = _foot_point(np.abs(u), np.abs(v), a[:, None], b[:, None])
    fx, fy = np.copysign(fx, u), np.copysign(fy, v)
    qu = m[:, 0:1] + e1[:, 0:1] * fx + e2[:, 0:1] * fy  # (N, M) foot points in the scaled basis
    qv = m[:, 1:2] + e1[:, 1:2] * fx + e2[:, 1:2] * fy
    f_p = (coef[:, 0, 0] @ phi)  # (N, M): f at the pixels, for the sign
    dist = np.sqrt((u - fx) ** 2 + (v - fy) ** 2)
    r = sc * np.where(f_p < 0, -dist, dist)
    phi_q = np.stack([qu * qu, 2.0 * qu * qv, qv * qv, 2.0 * qu, 2.0 * qv, np.ones_like(qu)], axis=1)  # (N, 6, M)
    out = coef.reshape(N, n7 * 3, 6) @ phi_q  # (N, n7 * 3, M): f, g1, g2 (and derivatives) at the foot points
    out = out.reshape(N, n7, 3, M)
    fallback = ~ok
    J = None
    if jacobian:
        gn = np.sqrt(out[:, 0, 1] ** 2 + out[:, 0, 2] ** 2)
        J = np.swapaxes(out[:, 1:, 0] * (sc / np.maximum(gn, 1e-300))[:, None], 1, 2)  # (N, M, 6)
    if fallback.any():
        rs, Js = _sampson_residual(T[fallback], K, radius_m, pts, jacobian)
        r[fallback] = rs
        if jacobian:
            J[fallback] = Js
    return r, J


#: :func:`conic_residual` itself, for :func:`conic_geometric_residual`'s fallback rows.
_sampson_residual = conic_residual

#: ``skew(e_0)``, ``skew(e_1)`` of the unit axes (:func:`conic_residual`'s dh/dxi), read-only.
_SKEW_E = skew(np.eye(3)[:2])
_SKEW_E.flags.writeable = False

#: The last backbone's pixel basis (:func:`_pixel_basis`): its pixels' bytes and the derived arrays (read-only).
_PIXEL_BASIS: list = [None]


def _pixel_basis(pts: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Centre ``(2,)``, scale ``sc``, ``P (3, 3)`` and ``phi (6, M)`` of :func:`conic_residual`'s pixels ``pts (M, 2)``.

    ``x = P xh`` centres and scales the pixels; ``phi = [u^2, 2uv, v^2, 2u, 2v, 1]`` of the centred, scaled
    ones. A frame's pixels are evaluated many times per frame (every transport iteration, trial and polish):
    the last set's result is kept, keyed on the pixels' exact bytes (so it is the same arrays, bitwise).
    """
    key = pts.tobytes() + bytes(str(pts.shape), "ascii")
    hit = _PIXEL_BASIS[0]
    if hit is not None and hit[0] == key:
        return hit[1]
    M = pts.shape[0]
    centre = pts.mean(axis=0) if M else np.zeros(2)
    sc = max(float(np.sqrt(np.mean(np.sum((pts - centre) ** 2, axis=1)))) if M else 1.0, 1.0)
    P = np.array([[sc, 0.0, centre[0]], [0.0, sc, centre[1]], [0.0, 0.0, 1.0]])
    u, v = (pts[:, 0] - centre[0]) / sc, (pts[:, 1] - centre[1]) / sc
    phi = np.stack([u * u, 2.0 * u * v, v * v, 2.0 * u, 2.0 * v, np.ones(M)], axis=0)  # (6, M)
    for a in (centre, P, phi):
        a.flags.writeable = False
    _PIXEL_BASIS[0] = (key, (centre, sc, P, phi))
    return centre, sc, P, phi


def grasp_position_residual(
    cam_T_needle: np.ndarray, needle_p_grasp: np.ndarray, cam_p_grasp: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Grasp position ``T X_g - p_g`` in metres, camera axes (paper Eq. for r_p). ``(N, 3), (N, 3, 6)``
    (the Jacobian None with ``jacobian=False``)."""
    p, J = point_jacobian(cam_T_needle, needle_p_grasp, jacobian)
    return p - np.asarray(cam_p_grasp, dtype=float), J


def grasp_perpendicular_residual(
    cam_T_needle: np.ndarray, needle_t_grasp: np.ndarray, cam_z_grasper: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Grasp perpendicularity ``z_g . (R t_g)`` (unitless; paper Eq. for r_perp). ``(N, 1), (N, 1, 6)``
    (the Jacobian None with ``jacobian=False``).

    ``t_g`` and ``z_g`` are normalised here, so ``R t_g`` is already unit length and the
    paper's normalisation has zero derivative. ``d(z^T R t) = -z^T R [t]x omega``; translation
    does not enter. ``cam_z_grasper`` is ``(3,)`` or one axis per pose ``(N, 3)`` (several frames'
    poses evaluated in one batch).
    """
    T = as_pose_batch(cam_T_needle)
    tg = _unit_const(needle_t_grasp)
    zg = np.asarray(cam_z_grasper, dtype=float)
    zg = _unit_const(zg, last_axis=True) if zg.ndim == 1 else zg / np.linalg.norm(zg, axis=-1, keepdims=True)
    R = T[:, :3, :3]
    r = ((R @ tg) * zg).sum(axis=-1)
    if not jacobian:
        return r[:, None], None
    J = np.zeros((T.shape[0], 1, 6))  # [Jw, 0] filled in place
    J[:, 0, :3] = -np.einsum("i,nij->nj" if zg.ndim == 1 else "ni,nij->nj", zg, R @ _skew_const(tg))
    return r[:, None], J


def motion_residual(
    cam_T_prev: np.ndarray, cam_T_cur: np.ndarray, cam_delta: np.ndarray, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Motion residual ``Log((D T_prev)^-1 T_cur)`` (6, tangent ``[omega; v]``), D = grasper motion.

    ``D = cam_T_grasper(k) cam_T_grasper(k-1)^-1`` moves camera-frame points with the grasper.
    With ``E = (D T_prev)^-1 T_cur`` and ``r = Log(E)``:
    ``dr/dxi_cur = Jr^-1(r)`` and ``dr/dxi_prev = -Jr^-1(r) Ad_{E^-1}`` (right Jacobians of SE(3)).
    Finite for every pose, including rotation angles at pi. ``cam_delta`` is ``(4, 4)`` or ``(N, 4, 4)``.
    Returns ``r (N, 6)``, ``J_prev (N, 6, 6)``, ``J_cur (N, 6, 6)`` (both None with ``jacobian=False``,
    which skips their computation; ``r`` is identical).
    """
    Tp = as_pose_batch(cam_T_prev)
    Tc = as_pose_batch(cam_T_cur)
    D = np.asarray(cam_delta, dtype=float)
    E = se3_inverse(D @ Tp) @ Tc
    if not jacobian:
        return se3_log(E), None, None
    r, Jinv = se3_log_right_jacobian_inv(E)
    J_cur = Jinv
    J_prev = -Jinv @ se3_adjoint(se3_inverse(E))
    return r, J_prev, J_cur


def pose_prior_residual(cam_T_needle: np.ndarray, cam_T_mean: np.ndarray, jacobian: bool = True
                        ) -> tuple[np.ndarray, np.ndarray | None]:
    """Gaussian pose prior residual ``Log(T_mean^-1 T)`` with exact Jacobian ``Jr^-1(r)``. ``(N, 6), (N, 6, 6)``
    (the Jacobian None with ``jacobian=False``; ``r`` the same bits).

    Used for the prior that holds what a sliding window marginalised. (GTSAM's
    ``PriorFactorPose3`` uses an identity Jacobian instead; this one is exact.)
    """
    T = as_pose_batch(cam_T_needle)
    E = se3_inverse(np.asarray(cam_T_mean, dtype=float)) @ T
    return se3_log_right_jacobian_inv(E) if jacobian else (se3_log(E), None)
