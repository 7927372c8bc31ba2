"""The elimination's information floor: the eigen-decomposition is skipped only where no floor binds."""

from __future__ import annotations

import numpy as np
import pytest

from pinpoint_fg.elimination import floor_information


def _reference(H: np.ndarray, rel: float = 1e-9, abs_floor: float = 1e-6) -> np.ndarray:
    """The floor by eigen-decomposition, always (the definition)."""
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    w, V = np.linalg.eigh(Hs)
    w = np.maximum(w, np.maximum(rel * w[..., -1:], abs_floor))
    return (V * w[..., None, :]) @ np.swapaxes(V, -1, -2)


@pytest.mark.parametrize("scale", [1e-2, 1.0, 1e8])
def test_floor_information_is_the_eigen_floor_with_or_without_binding_rows(scale: float) -> None:
    rng = np.random.default_rng(31)
    Q = np.linalg.qr(rng.normal(size=(40, 6, 6)))[0]
    w = scale * np.exp(rng.uniform(np.log(1e-6), 0.0, size=(40, 6)))  # well above both floors
    H = (Q * w[:, None, :]) @ np.swapaxes(Q, 1, 2)
    H[:, 2, 4] += 1e-12 * scale  # asymmetric by round-off: symmetrised
    np.testing.assert_allclose(floor_information(H), _reference(H), rtol=0, atol=1e-14 * np.abs(H).max())
    singular = H.copy()
    singular[5] = scale * np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])  # the floor binds: eigen path for the batch
    singular[6] = -scale * np.eye(6)  # negative definite: every eigenvalue raised to the absolute floor
    out = floor_information(singular)
    np.testing.assert_allclose(out, _reference(singular), rtol=0, atol=1e-14 * np.abs(singular).max())
    assert np.all(np.linalg.eigvalsh(out)[:, 0] > 0)
    assert np.allclose(out[6], 1e-6 * np.eye(6))
