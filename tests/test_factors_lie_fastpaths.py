"""The restructured SE(3) exponential equals its reference form (tests/reference_lie.py) to 1e-9.

Random tangents with rotation angles spread over [0, pi], within 1e-12..1e-2 of 0 (the Taylor
branch and its boundary), within 1e-9..1e-2 of pi, and exactly 0.
"""

from __future__ import annotations

import numpy as np
import pytest

from factors import lie
from tests.reference_lie import se3_exp_reference


def _tangents(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 6) tangents whose rotation part has the angles of ``kind``; translations up to ~0.1 m."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    if kind == "near_identity":
        angle = 10 ** rng.uniform(-12, -2, size=(n, 1))
    elif kind == "near_pi":
        angle = np.pi - 10 ** rng.uniform(-9, -2, size=(n, 1))
    elif kind == "zero":
        angle = np.zeros((n, 1))
    else:
        angle = rng.uniform(0.0, np.pi, size=(n, 1))
    return np.concatenate([axis * angle, rng.normal(size=(n, 3)) * 0.05], axis=1)


@pytest.mark.parametrize("kind", ("uniform", "near_identity", "near_pi", "zero"))
def test_se3_exp_equals_reference(kind: str) -> None:
    xi = _tangents(kind, 400, np.random.default_rng(31))
    ref = se3_exp_reference(xi)
    for got in (lie.se3_exp(xi), lie.se3_exp(xi.reshape(4, 100, 6)).reshape(400, 4, 4),
                np.stack([lie.se3_exp(x) for x in xi[:20]] + list(lie.se3_exp(xi[20:])))):
        # rotation block to 1e-12 absolute; translation relative to |v| (at least 1 mm)
        np.testing.assert_allclose(got[:, :3, :3], ref[:, :3, :3], rtol=0, atol=1e-12)
        scale = np.maximum(np.linalg.norm(xi[:, 3:], axis=1), 1e-3)
        assert np.all(np.linalg.norm(got[:, :3, 3] - ref[:, :3, 3], axis=1) < 1e-9 * scale)
        np.testing.assert_array_equal(got[:, 3], ref[:, 3])
