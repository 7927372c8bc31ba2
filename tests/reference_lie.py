"""The SE(3) exponential of :mod:`factors.lie` as it was before it was restructured for speed.

Kept only to pin the library's fast path (``tests/test_factors_lie_fastpaths.py``): the
reference builds the translation as ``R Jr(w) v`` from two separate SO(3) series.
"""

from __future__ import annotations

import numpy as np

from factors.lie import so3_exp, so3_right_jacobian


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
