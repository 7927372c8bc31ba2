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

