"""Seeded pose samplers for the tests: uniform, near-identity, near-pi and near edge-on needles."""

from __future__ import annotations

import numpy as np

from factors.lie import so3_exp

KINDS = ("uniform", "near_identity", "near_pi", "edge_on")


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sample_rotations(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3, 3)`` rotations of the given kind."""
    if kind == "uniform":
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        from factors.lie import quat_wxyz_to_rotation

        return quat_wxyz_to_rotation(q)
    if kind == "near_identity":
        return so3_exp(_unit(rng, n) * 10 ** rng.uniform(-9, -2, size=(n, 1)))
    if kind == "near_pi":
        return so3_exp(_unit(rng, n) * (np.pi - 10 ** rng.uniform(-9, -2, size=(n, 1))))
    raise ValueError(kind)


def sample_poses(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 4, 4)`` needle poses 10-100 mm in front of the camera.

    ``edge_on``: the needle normal is tilted only 1e-7..1e-2 rad out of perpendicular to the
    viewing ray through the needle centre, so the circle projects to an almost-degenerate conic.
    """
    z = rng.uniform(0.01, 0.1, size=n)
    t = np.stack([rng.uniform(-0.3, 0.3, n) * z, rng.uniform(-0.3, 0.3, n) * z, z], axis=1)
    if kind == "edge_on":
        ray = t / np.linalg.norm(t, axis=1, keepdims=True)
        a = _unit(rng, n)
        a -= np.sum(a * ray, axis=1, keepdims=True) * ray
        a /= np.linalg.norm(a, axis=1, keepdims=True)  # a ⟂ ray
        tilt = 10 ** rng.uniform(-7, -2, size=(n, 1)) * rng.choice([-1, 1], size=(n, 1))
        normal = np.cos(tilt) * a + np.sin(tilt) * ray
        x = np.cross(normal, _unit(rng, n))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(normal, x)
        R = np.stack([x, y, normal], axis=2)
    else:
        R = sample_rotations(kind, n, rng)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T
