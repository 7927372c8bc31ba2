"""The restructured SE(3) exponential and logarithms equal their reference forms (tests/reference_lie.py) to 1e-9.

Random tangents with rotation angles spread over [0, pi], within 1e-12..1e-2 of 0 (the Taylor
branch and its boundary), within 1e-9..1e-2 of pi, and exactly 0.
"""

from __future__ import annotations

import numpy as np
import pytest

from factors import lie
from tests.poses import KINDS, sample_poses
from tests.reference_lie import (
    rotation_to_quat_wxyz_reference,
    se3_exp_reference,
    se3_log_reference,
    so3_log_reference,
)


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



_BRANCHED = {
    "so3_exp": lambda x: lie.so3_exp(x[..., :3]),
    "so3_right_jacobian": lambda x: lie.so3_right_jacobian(x[..., :3]),
    "so3_right_jacobian_inv": lambda x: lie.so3_right_jacobian_inv(x[..., :3]),
    "q_left": lambda x: lie._q_left(x[..., :3], x[..., 3:]),
    "se3_exp": lie.se3_exp,
    "se3_log": lambda x: lie.se3_log(se3_exp_reference(x)),
    "so3_log": lambda x: lie.so3_log(se3_exp_reference(x)[..., :3, :3]),
}


@pytest.mark.parametrize("name", sorted(_BRANCHED))
@pytest.mark.parametrize("kind", ("near_identity_all", "uniform", "near_pi", "zero"))
def test_series_branch_skipping_is_bitwise_np_where(name: str, kind: str) -> None:
    """A batch whose angles all take one branch (Taylor or closed form) skips the other: its rows are bitwise
    those of the same tangents inside a mixed batch (``np.where`` over both branches), single vectors too."""
    rng = np.random.default_rng(34)
    if kind == "near_identity_all":  # every angle below both Taylor thresholds (1e-4 and Q's 1e-3)
        axis = rng.normal(size=(60, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        xi = np.concatenate([axis * 10 ** rng.uniform(-12, -4.5, size=(60, 1)), rng.normal(size=(60, 3)) * 0.05], 1)
    else:
        xi = _tangents(kind, 60, rng)
        xi = xi[np.linalg.norm(xi[:, :3], axis=1) > 2e-3] if kind != "zero" else xi
    other = _tangents("uniform" if kind in ("near_identity_all", "zero") else "zero", 5, rng)
    other[:, :3] *= 1.0 if kind in ("near_identity_all", "zero") else 0.0
    f = _BRANCHED[name]
    alone = f(xi)
    mixed = f(np.concatenate([xi, other]))[: xi.shape[0]]
    assert np.array_equal(alone, mixed)
    for i in (0, 1):
        assert np.array_equal(f(xi[i]), alone[i])


@pytest.mark.parametrize("kind", ("uniform", "near_identity", "near_pi", "zero"))
def test_se3_log_right_jacobian_inv_is_bitwise_the_two_calls(kind: str) -> None:
    """The fused log + inverse right Jacobian (one shared series coefficient) equals the two separate calls."""
    rng = np.random.default_rng(34)
    T = lie.se3_exp(_tangents(kind, 300, rng))
    xi, Jinv = lie.se3_log_right_jacobian_inv(T)
    np.testing.assert_array_equal(xi, lie.se3_log(T))
    np.testing.assert_array_equal(Jinv, lie.se3_right_jacobian_inv(lie.se3_log(T)))
    for i in (0, 7):  # one pose at a time (N = 1 batches)
        xi1, J1 = lie.se3_log_right_jacobian_inv(T[i])
        np.testing.assert_array_equal(xi1, lie.se3_log(T[i]))
        np.testing.assert_array_equal(J1, lie.se3_right_jacobian_inv(lie.se3_log(T[i])))


def _cross_textbook(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` component by component (the formula :func:`factors.lie.cross` evaluates in fewer calls)."""
    a, b = np.broadcast_arrays(a, b)
    out = np.empty(a.shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


@pytest.mark.parametrize("kind", ("uniform", "near_identity", "near_pi", "zero"))
def test_cross_is_bitwise_the_textbook_formula(kind: str) -> None:
    """The doubled-vector cross product has the same bits (signed zeros included) as the component formula,
    for equal shapes, broadcast operands and single vectors."""
    rng = np.random.default_rng(35)
    x = _tangents(kind, 200, rng)
    a, b = x[:, :3], x[:, 3:]
    b[::7] = -0.0  # signed zeros take the same products
    for u, v in ((a, b), (a[0], b), (a, b[3]), (a[5], b[5]), (a.reshape(4, 50, 3), b.reshape(4, 50, 3))):
        assert lie.cross(u, v).tobytes() == _cross_textbook(u, v).tobytes()


@pytest.mark.parametrize("kind", ("uniform", "near_identity", "near_pi", "zero", "pi"))
def test_rotation_to_quat_is_bitwise_the_four_candidate_form(kind: str) -> None:
    """The table gather of Shepperd's method selects the same divisions as building all four candidates.

    Exactly pi puts the largest component on each of x, y and z in turn (the axes below), near identity on w.
    """
    rng = np.random.default_rng(33)
    if kind == "pi":
        axis = np.concatenate([np.eye(3), rng.normal(size=(397, 3))])
        w = axis / np.linalg.norm(axis, axis=1, keepdims=True) * np.pi
    else:
        w = _tangents(kind, 400, rng)[:, :3]
    R = lie.so3_exp(w)
    largest = np.argmax(np.abs(lie.rotation_to_quat_wxyz(R)), axis=1)
    if kind in ("uniform", "near_pi", "pi"):
        assert set(largest) == {0, 1, 2, 3} - ({0} if kind != "uniform" else set())
    for got, ref in ((lie.rotation_to_quat_wxyz(R), rotation_to_quat_wxyz_reference(R)),
                     (lie.rotation_to_quat_wxyz(R.reshape(4, 100, 3, 3)),
                      rotation_to_quat_wxyz_reference(R).reshape(4, 100, 4)),
                     (lie.rotation_to_quat_wxyz(R[7]), rotation_to_quat_wxyz_reference(R[7]))):
        assert got.shape == ref.shape
        assert got.tobytes() == ref.tobytes()
