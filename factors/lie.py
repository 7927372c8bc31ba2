"""Batched SO(3)/SE(3) maths in GTSAM's tangent convention.

Poses are homogeneous matrices ``(N, 4, 4)``; tangent vectors are ``(N, 6)`` ordered
``xi = [omega; v]`` (rotation first), and a perturbation acts on the right:
``T ⊕ xi = T @ Exp(xi)`` (see :mod:`factors.conventions`, which states this as code).

Everything here is vectorised over the leading axis and finite for every input:
small angles use Taylor series, and angles near pi use the quaternion form of the
logarithm and the ``cot(theta/2)`` form of the inverse right Jacobian, both of which stay
well conditioned there.
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-4  # below this angle the closed forms lose digits; Taylor series take over

_NONE, _ALL, _MIXED = 0, 1, 2  # which entries of a batch take the Taylor branch (:func:`_branch`)

#: ``np.eye(3)``, built once (read-only): the same values, without a Python-level call per use.
_I3 = np.eye(3)
_I3.flags.writeable = False


def _branch(small: np.ndarray) -> int:
    """``_NONE`` / ``_ALL`` when no / every entry of ``small`` is set, else ``_MIXED`` (also for a single, 0-d one)."""
    if small.ndim == 0:
        return _MIXED
    n = np.count_nonzero(small)  # one call instead of any() and all(): a third of their cost at ~50 entries
    if n == 0:
        return _NONE
    return _ALL if n == small.size else _MIXED


def _pick(branch: int, small: np.ndarray, taylor, closed) -> np.ndarray:
    """``np.where(small, taylor(), closed())``, evaluating only the branch every entry takes when they agree.

    The same values bit for bit (``np.where`` selects elementwise; the skipped branch is never selected):
    at ~50 poses per call NumPy's per-call overhead, not arithmetic, is the cost, and most batches are all
    above the Taylor threshold.
    """
    if branch == _NONE:
        return closed()
    if branch == _ALL:
        return taylor()
    return np.where(small, taylor(), closed())


def _safe_angle(branch: int, small: np.ndarray, th: np.ndarray) -> np.ndarray:
    """``np.where(small, 1.0, th)``: the angle the closed forms divide by (1 where the series is used)."""
    if branch == _NONE:
        return th
    return np.where(small, 1.0, th)


def skew(w: np.ndarray) -> np.ndarray:
    """``[w]x`` for ``w`` of shape ``(..., 3)`` -> ``(..., 3, 3)``, so ``[w]x @ p = w x p``."""
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (3, 3))
    nw = -w  # one negation for the three negative entries
    out[..., 0, 1] = nw[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = nw[..., 0]
    out[..., 2, 0] = nw[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector ``(..., 3)`` -> rotation matrix ``(..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    th2 = (w * w).sum(axis=-1)
    th = np.sqrt(th2)
    small = th < _SMALL
    br = _branch(small)
    ths = _safe_angle(br, small, th)
    a = _pick(br, small, lambda: 1.0 - th2 / 6.0 + th2 * th2 / 120.0, lambda: np.sin(ths) / ths)
    b = _pick(br, small, lambda: 0.5 - th2 / 24.0 + th2 * th2 / 720.0, lambda: (1.0 - np.cos(ths)) / (ths * ths))
    W = skew(w)
    eye = np.broadcast_to(_I3, W.shape)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


#: Shepperd's method divides row ``k`` of this table (``k``: the largest of the four squared components) by ``s``;
#: its entries index ``[d21, d02, d10, s21, s02, s10, s]`` (``dij = R_ij - R_ji``, ``sij = R_ij + R_ji``), and the
#: diagonal entry (index 6) is replaced by ``s / 4``.
_SHEPPERD_ROWS = np.array([[6, 0, 1, 2], [0, 6, 5, 4], [1, 5, 6, 3], [2, 4, 3, 6]])
_OFF_UPPER = np.array([7, 2, 3])  # R21, R02, R10 in a row-major 3x3 ...
_OFF_LOWER = np.array([5, 6, 1])  # ... and their transposes R12, R20, R01


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> unit Hamilton quaternions ``(..., 4)`` as w, x, y, z, w >= 0.

    Shepperd's method: pick the largest of the four squared components to divide by, so
    the result is accurate for every rotation, including angles near pi. The four candidate quaternions
    are one table (``_SHEPPERD_ROWS``) gathered per rotation: the same divisions as building all four and
    selecting one, bit for bit, in a quarter of the NumPy calls (``so3_log`` takes this path near pi).
    """
    R = np.asarray(R, dtype=float)
    Rf = R.reshape(-1, 9)
    m00, m11, m22 = Rf[:, 0], Rf[:, 4], Rf[:, 8]
    tr = m00 + m11 + m22
    cand = np.stack([1.0 + tr, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)
    k = np.argmax(cand, axis=-1)
    n = np.arange(Rf.shape[0])
    s = 2.0 * np.sqrt(np.maximum(cand[n, k], 1e-300))
    upper, lower = Rf[:, _OFF_UPPER], Rf[:, _OFF_LOWER]
    off = np.concatenate((upper - lower, upper + lower, s[:, None]), axis=-1)
    q = off[n[:, None], _SHEPPERD_ROWS[k]] / s[:, None]
    q[n, k] = 0.25 * s
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).reshape(R.shape[:-2] + (4,))


def quat_wxyz_to_rotation(q: np.ndarray) -> np.ndarray:
    """Hamilton quaternions ``(..., 4)`` (w, x, y, z; normalised here) -> rotations ``(..., 3, 3)``."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def _so3_log_quat(R: np.ndarray) -> np.ndarray:
    """:func:`so3_log` through the quaternion: ``theta = 2 atan2(|q_v|, q_w)``, accurate near 0 and near pi."""
    q = rotation_to_quat_wxyz(R)
    qv = q[..., 1:]
    n = np.linalg.norm(qv, axis=-1)
    th = 2.0 * np.arctan2(n, q[..., 0])
    small = n < 1e-12
    scale = np.where(small, 2.0 / np.maximum(q[..., 0], 1e-300), th / np.where(small, 1.0, n))
    return qv * scale[..., None]


#: :func:`so3_log` takes the quaternion path where ``cos(theta)`` is below this (theta above ~143 deg).
_LOG_NEAR_PI_COS = -0.8


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> rotation vectors ``(..., 3)`` with angle in [0, pi].

    ``d = vee(R - R^T) = 2 sin(theta) u``, ``theta = atan2(|d| / 2, (tr R - 1) / 2)`` (accurate at every
    angle) and ``w = theta / (2 sin theta) d``: a few elementwise operations. Near pi, where ``d``
    vanishes and the axis must come from the symmetric part, those rotations take the quaternion
    path (Shepperd's method; ``theta = 2 atan2(|q_v|, q_w)``). The two agree to round-off (tested
    against the quaternion path on every angle).
    """
    R = np.asarray(R, dtype=float)
    d = np.empty(R.shape[:-1])  # vee(R - R^T), filled in place (np.stack's result, without its overhead)
    np.subtract(R[..., 2, 1], R[..., 1, 2], out=d[..., 0])
    np.subtract(R[..., 0, 2], R[..., 2, 0], out=d[..., 1])
    np.subtract(R[..., 1, 0], R[..., 0, 1], out=d[..., 2])
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    s = 0.5 * np.sqrt((d * d).sum(axis=-1))
    th = np.arctan2(s, c)
    tiny = s < 1e-8  # theta / (2 sin theta) = 1/2 + theta^2 / 12 + O(theta^4)
    tb = _branch(tiny)
    w = d * _pick(tb, tiny, lambda: 0.5 + th * th / 12.0, lambda: th / (2.0 * _safe_angle(tb, tiny, s)))[..., None]
    near = c < _LOG_NEAR_PI_COS
    if near.any():
        w[near] = _so3_log_quat(R[near])
    return w


def _jr_inv_coefficient(w: np.ndarray) -> np.ndarray:
    """``1/theta^2 - cot(theta/2) / (2 theta)`` of :func:`so3_right_jacobian_inv` (Taylor series near 0)."""
    th2 = (w * w).sum(axis=-1)
    th = np.sqrt(th2)
    small = th < _SMALL
    br = _branch(small)
    ths = _safe_angle(br, small, th)
    return _pick(br, small, lambda: 1.0 / 12.0 + th2 / 720.0,
                 lambda: 1.0 / (ths * ths) - 1.0 / (2.0 * ths * np.tan(ths / 2.0)))


def so3_right_jacobian_inv(w: np.ndarray, coefficient: np.ndarray | None = None) -> np.ndarray:
    """Inverse right Jacobian of SO(3): ``d Log(R Exp(d)) / d d`` at ``d = 0`` for ``R = Exp(w)``.

    ``Jr^-1(w) = I + 1/2 [w]x + (1/theta^2 - cot(theta/2) / (2 theta)) [w]x^2``; the coefficient
    is finite at theta = pi (where cot(pi/2) = 0). ``coefficient``: :func:`_jr_inv_coefficient` of this
    ``w`` when the caller has it already (:func:`se3_log_right_jacobian_inv`).
    """
    w = np.asarray(w, dtype=float)
    c = _jr_inv_coefficient(w) if coefficient is None else coefficient
    W = skew(w)
    return _I3 + 0.5 * W + c[..., None, None] * (W @ W)


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): ``Exp(w + d) ≈ Exp(w) Exp(Jr(w) d)``."""
    w = np.asarray(w, dtype=float)
    th2 = (w * w).sum(axis=-1)
    th = np.sqrt(th2)
    small = th < _SMALL
    br = _branch(small)
    ths = _safe_angle(br, small, th)
    a = _pick(br, small, lambda: 0.5 - th2 / 24.0, lambda: (1.0 - np.cos(ths)) / (ths * ths))
    b = _pick(br, small, lambda: 1.0 / 6.0 - th2 / 120.0, lambda: (ths - np.sin(ths)) / (ths * ths * ths))
    W = skew(w)
    return _I3 - a[..., None, None] * W + b[..., None, None] * (W @ W)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (elementwise: cheaper than ``np.cross`` for small batches).

    Component ``k`` is ``a[k+1] b[k+2] - a[k+2] b[k+1]`` (indices mod 3): the same products and difference per
    component as the textbook formula, bit for bit, computed on the cyclic doublings ``[a, a]`` and ``[b, b]``
    (:func:`_cross_doubled`) in three array operations instead of nine (per-call overhead, not arithmetic, is
    the cost at ~50 vectors). Operands of different shapes are broadcast first.
    """
    if a.shape != b.shape:
        a, b = np.broadcast_arrays(a, b)
    return _cross_doubled(np.concatenate((a, a), axis=-1), b)


def _cross_doubled(a2: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`cross` of ``a`` and ``b`` (same shape) given ``a2 = [a, a]`` along the last axis (an ``a`` crossed
    with several vectors is doubled once)."""
    b2 = np.concatenate((b, b), axis=-1)
    return a2[..., 1:4] * b2[..., 2:5] - a2[..., 2:5] * b2[..., 1:4]


def _q_left(phi: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Barfoot's ``Q(rho, phi)`` block of the SE(3) left Jacobian (batched)."""
    th2 = (phi * phi).sum(axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-3
    br = _branch(small)
    ths = _safe_angle(br, small, th)
    s, c = np.sin(ths), np.cos(ths)
    c1 = _pick(br, small, lambda: 1.0 / 6.0 - th2 / 120.0, lambda: (ths - s) / ths**3)
    c2 = _pick(br, small, lambda: 1.0 / 24.0 - th2 / 720.0, lambda: (th2 + 2.0 * c - 2.0) / (2.0 * ths**4))
    c3 = _pick(br, small, lambda: 1.0 / 120.0 - th2 / 2520.0,
               lambda: (2.0 * ths - 3.0 * s + ths * c) / (2.0 * ths**5))
    P, Rh = skew(phi), skew(rho)
    PR, RP = P @ Rh, Rh @ P
    PRP = PR @ P
    return (
        0.5 * Rh
        + c1[..., None, None] * (PR + RP + PRP)
        + c2[..., None, None] * (P @ PR + RP @ P - 3.0 * PRP)
        + c3[..., None, None] * (PRP @ P + P @ PRP)
    )


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """``Exp`` of tangent vectors ``(..., 6)`` = ``[omega; v]`` -> poses ``(..., 4, 4)`` (GTSAM's Expmap)."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[..., :3], xi[..., 3:]
    th2 = (w * w).sum(axis=-1)
    th = np.sqrt(th2)
    small = th < _SMALL
    br = _branch(small)
    ths = _safe_angle(br, small, th)
    sn = np.sin(ths)
    a = _pick(br, small, lambda: 1.0 - th2 / 6.0 + th2 * th2 / 120.0, lambda: sn / ths)
    b = _pick(br, small, lambda: 0.5 - th2 / 24.0 + th2 * th2 / 720.0, lambda: (1.0 - np.cos(ths)) / (ths * ths))
    c = _pick(br, small, lambda: 1.0 / 6.0 - th2 / 120.0, lambda: (ths - sn) / (ths * ths * ths))
    W = skew(w)
    WW = W @ W
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = _I3 + a[..., None, None] * W + b[..., None, None] * WW
    # translation = J_l(w) v = (I + b [w]x + c [w]x^2) v (the same coefficients as R's series)
    T[..., :3, 3] = v + np.einsum("...ij,...j->...i", b[..., None, None] * W + c[..., None, None] * WW, v)
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """``Log`` of poses ``(..., 4, 4)`` -> tangent vectors ``(..., 6)`` = ``[omega; v]`` (GTSAM's Logmap).

    ``v = J_l(w)^-1 t = J_r(w)^-1 R^T t`` with :func:`so3_right_jacobian_inv`'s series applied as cross
    products, ``u + 1/2 w x u + c w x (w x u)`` (no 3x3 matrices built).
    """
    return _se3_log_coefficient(T)[0]


def _se3_log_coefficient(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`se3_log` and the :func:`_jr_inv_coefficient` of its rotation part (computed on the way)."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    w = so3_log(R)
    c = _jr_inv_coefficient(w)
    u = (T[..., None, :3, 3] @ R)[..., 0, :]  # R^T t
    w2 = np.concatenate((w, w), axis=-1)  # w doubled once for both cross products
    wu = _cross_doubled(w2, u)
    v = u + 0.5 * wu + c[..., None] * _cross_doubled(w2, wu)
    return np.concatenate([w, v], axis=-1), c


def se3_log_right_jacobian_inv(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``xi = se3_log(T)`` and ``se3_right_jacobian_inv(xi)``, bitwise, with their shared coefficient computed once.

    ``Jr^-1`` of SO(3) needs ``1/theta^2 - cot(theta/2) / (2 theta)`` of ``xi``'s rotation part, which the
    logarithm has just computed from the same values (the prior and motion residuals take both).
    """
    xi, c = _se3_log_coefficient(T)
    return xi, se3_right_jacobian_inv(xi, coefficient=c)


def se3_right_jacobian(xi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SE(3) in ``[omega; v]`` order (GTSAM's ``Pose3.ExpmapDerivative``), ``(..., 6, 6)``."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[..., :3], xi[..., 3:]
    Jr = so3_right_jacobian(w)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Jr
    out[..., 3:, 3:] = Jr
    out[..., 3:, :3] = _q_left(-w, -v)
    return out


def se3_right_jacobian_inv(xi: np.ndarray, coefficient: np.ndarray | None = None) -> np.ndarray:
    """Inverse right Jacobian of SE(3) (GTSAM's ``Pose3.LogmapDerivative`` at ``Exp(xi)``), ``(..., 6, 6)``.

    ``Log(Exp(xi) Exp(d)) ≈ xi + Jr^-1(xi) d``. Block form ``[[Ji, 0], [-Ji Q Ji, Ji]]`` with
    ``Ji = Jr^-1`` of SO(3) and ``Q = Q_left(-omega, -v)``. ``coefficient``: see :func:`so3_right_jacobian_inv`.
    """
    xi = np.asarray(xi, dtype=float)
    w, v = xi[..., :3], xi[..., 3:]
    Ji = so3_right_jacobian_inv(w, coefficient)
    Q = _q_left(-w, -v)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ji
    out[..., 3:, 3:] = Ji
    out[..., 3:, :3] = -Ji @ Q @ Ji
    return out


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of poses ``(..., 4, 4)``."""
    T = np.asarray(T, dtype=float)
    Rt = T[..., :3, :3].swapaxes(-1, -2)
    out = np.zeros(T.shape)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint ``(..., 6, 6)`` in ``[omega; v]`` order: ``[[R, 0], [[t]x R, R]]``; ``T Exp(xi) T^-1 = Exp(Ad_T xi)``."""
    T = np.asarray(T, dtype=float)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(t) @ R
    return out


def homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)`` (broadcast)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T ⊕ xi = T @ Exp(xi)``, batched (GTSAM's ``Pose3.retract`` with the full exponential chart)."""
    return np.asarray(T, dtype=float) @ se3_exp(xi)


def local(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """``T_a ⊖ T_b``-style tangent from ``T_a`` to ``T_b``: ``Log(T_a^-1 T_b)`` (GTSAM's ``localCoordinates``)."""
    return se3_log(se3_inverse(T_a) @ np.asarray(T_b, dtype=float))
