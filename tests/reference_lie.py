"""The SE(3) exponential and logarithms of :mod:`factors.lie` as they were before they were restructured for speed.

Kept only to pin the library's fast path (``tests/test_factors_lie_fastpaths.py``): the
reference builds the translation as ``R Jr(w) v`` from two separate SO(3) series.
"""

from __future__ import annotations

import numpy as np

from factors.lie import _so3_log_quat, so3_exp, so3_right_jacobian, so3_right_jacobian_inv


def se3_exp_reference(xi: np.ndarray) -> np.ndarray:
    """``Exp`` of tangent vectors ``(..., 6)`` = ``[omega; v]`` -> poses ``(..., 4, 4)`` (GTSAM's Expmap)."""
    xi = np.asarray(xi, dtype=float)
    w, v = xi[..., :3], xi[..., 3:]
    R = so3_exp(w)
    # translation = J_l(w) v = R J_r(w) v
    t = np.einsum("...ij,...j->...i", R @ so3_right_jacobian(w), v)
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def rotation_to_quat_wxyz_reference(R: np.ndarray) -> np.ndarray:
    """Shepperd's method as it was before the table gather: all four candidate quaternions built, one selected."""
    R = np.asarray(R, dtype=float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([1.0 + tr, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1)
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))
    q = np.empty(R.shape[:-2] + (4,))
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    c0 = np.stack([0.25 * s, d21 / s, d02 / s, d10 / s], -1)
    c1 = np.stack([d21 / s, 0.25 * s, s10 / s, s02 / s], -1)
    c2 = np.stack([d02 / s, s10 / s, 0.25 * s, s21 / s], -1)
    c3 = np.stack([d10 / s, s02 / s, s21 / s, 0.25 * s], -1)
    for j, c in enumerate((c0, c1, c2, c3)):
        q = np.where((k == j)[..., None], c, q)
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def so3_log_reference(R: np.ndarray) -> np.ndarray:
    """``Log`` of rotations through the quaternion for every angle (the form before the trace/skew fast path;
    ``so3_log`` itself uses it only beyond 143 deg)."""
    return _so3_log_quat(R)


def se3_log_reference(T: np.ndarray) -> np.ndarray:
    """``Log`` of poses with ``v = Jr^-1(w) R^T t`` from the 3x3 matrix (the form before the cross-product path)."""
    T = np.asarray(T, dtype=float)
    w = so3_log_reference(T[..., :3, :3])
    Rt = np.einsum("...ji,...j->...i", T[..., :3, :3], T[..., :3, 3])
    v = np.einsum("...ij,...j->...i", so3_right_jacobian_inv(w), Rt)
    return np.concatenate([w, v], axis=-1)

