"""A frame likelihood's batched Gauss-Newton terms against the GTSAM factors it builds (shared by tests)."""

from __future__ import annotations

import gtsam
import numpy as np

from factors.conventions import matrix_to_pose3
from pinpoint_fg.likelihood import FrameLikelihood


def assert_equals_its_gtsam_factors(lik: FrameLikelihood, poses: np.ndarray) -> list:
    """Per pose: the factors' summed error is ``nll`` (1e-10), their ``A^T A`` and ``-A^T b`` are the batched
    information and gradient (1e-9). Returns the factors."""
    nll, grad, H = lik.gauss_newton(poses)
    factors = lik.gtsam_factors(0)
    for i in range(poses.shape[0]):
        v = gtsam.Values()
        v.insert(0, matrix_to_pose3(poses[i]))
        np.testing.assert_allclose(sum(f.error(v) for f in factors), nll[i], rtol=1e-10)
        A_b = [f.linearize(v).jacobian() for f in factors]
        np.testing.assert_allclose(sum(A.T @ A for A, _ in A_b), H[i], rtol=1e-9, atol=1e-9 * np.abs(H[i]).max())
        np.testing.assert_allclose(-sum(A.T @ b for A, b in A_b), grad[i], rtol=1e-9,
                                   atol=1e-9 * np.abs(grad[i]).max())
    return factors
