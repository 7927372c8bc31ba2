"""The restructured SE(3) exponential and logarithms equal their reference forms (tests/reference_lie.py) to 1e-9.

Random tangents with rotation angles spread over [0, pi], within 1e-12..1e-2 of 0 (the Taylor
branch and its boundary), within 1e-9..1e-2 of pi, and exactly 0.
"""

from __future__ import annotations

import numpy as np
import pytest

from factors import lie
from tests.poses import KINDS, sample_poses
from tests.reference_lie import se3_exp_reference, se3_log_reference, so3_log_reference


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


@pytest.mark.parametrize("kind", ("uniform", "near_identity", "near_pi", "zero", "switch"))
def test_so3_log_equals_reference(kind: str) -> None:
    """The trace/skew path (and its quaternion branch near pi) against the quaternion path on every angle."""
    rng = np.random.default_rng(32)
    if kind == "switch":  # angles around the branch switch, cos(theta) = -0.8
        axis = rng.normal(size=(400, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        w = axis * (np.arccos(-0.8) + rng.uniform(-1e-3, 1e-3, size=(400, 1)))
    else:
        w = _tangents(kind, 400, rng)[:, :3]
    R = lie.so3_exp(w)
    ref = so3_log_reference(R)
    angle = np.linalg.norm(ref, axis=1)
    for got in (lie.so3_log(R), lie.so3_log(R.reshape(4, 100, 3, 3)).reshape(400, 3),
                np.stack([lie.so3_log(r) for r in R[:20]] + list(lie.so3_log(R[20:])))):
        err = np.linalg.norm(got - ref, axis=1)
        assert np.all(err <= 1e-9 * np.maximum(angle, 1e-6)), float(np.max(err))
    np.testing.assert_allclose(lie.so3_log(R), w, rtol=0, atol=1e-6)  # and it is the inverse of so3_exp


@pytest.mark.parametrize("kind", KINDS)
def test_se3_log_equals_reference(kind: str) -> None:
    """Poses of every kind (uniform, near-identity, near-pi, near edge-on needles) and relative poses between them."""
    rng = np.random.default_rng(33)
    T = sample_poses(kind, 300, rng)
    rel = lie.se3_inverse(T[:150]) @ T[150:]
    for X in (T, rel):
        ref = se3_log_reference(X)
        got = lie.se3_log(X)
        scale = np.maximum(np.linalg.norm(ref, axis=1), 1e-6)
        assert np.all(np.linalg.norm(got - ref, axis=1) <= 1e-9 * scale)
    xi = _tangents("uniform", 300, rng)
    np.testing.assert_allclose(lie.se3_log(lie.se3_exp(xi)), xi, rtol=0, atol=1e-9)

