"""The least-squares conic of image points and the points' distance to it (pinpoint_fg.conic_fit)."""

from __future__ import annotations

import numpy as np
import pytest

from pinpoint_fg.conic_fit import conic_misfit_px, fit_conic, sampson_distance_px


def _ellipse(rng: np.random.Generator, n: int, arc_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on an arc of a random ellipse, and that ellipse's conic (unit norm)."""
    a, b = rng.uniform(40, 300), rng.uniform(5, 300)
    c, th = rng.uniform(100, 900, 2), rng.uniform(0, np.pi)
    t = rng.uniform(0, 2 * np.pi) + np.linspace(0, arc_rad, n)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    pts = np.stack([a * np.cos(t), b * np.sin(t)], 1) @ R.T + c
    A = R @ np.diag([1 / a**2, 1 / b**2]) @ R.T
    C = np.block([[A, (-A @ c)[:, None]], [(-A @ c)[None, :], np.array([[c @ A @ c - 1]])]])
    return pts, C / np.linalg.norm(C)


@pytest.mark.parametrize("seed", range(20))
def test_points_on_an_arc_give_their_ellipse(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts, C = _ellipse(rng, 60, rng.uniform(np.pi / 2, 2 * np.pi))
    fit = fit_conic(pts)
    assert fit is not None
    np.testing.assert_allclose(fit * np.sign(fit[2, 2] * C[2, 2]), C, atol=1e-6)
    assert sampson_distance_px(fit, pts).max() < 1e-6
    assert conic_misfit_px(pts) < 1e-6


def test_sampson_distance_is_the_distance_to_first_order() -> None:
    """For the circle x^2 + y^2 = r^2 the distance of a point at radius d is |d^2 - r^2| / 2d, ~ |d - r|."""
    C = np.diag([1.0, 1.0, -100.0**2])
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, 50)
    d = 100.0 + rng.uniform(-0.5, 0.5, 50)
    p = np.stack([d * np.cos(ang), d * np.sin(ang)], 1)
    got = sampson_distance_px(C, p)
    np.testing.assert_allclose(got, np.abs(d**2 - 100.0**2) / (2 * d), rtol=1e-12)
    np.testing.assert_allclose(got, np.abs(d - 100.0), atol=2e-3)
    assert np.isinf(sampson_distance_px(C, np.zeros((1, 2))))[0]


def test_misfit_separates_a_noisy_arc_from_scattered_points() -> None:
    rng = np.random.default_rng(7)
    pts, _ = _ellipse(rng, 200, 2.0)
    noisy = pts + rng.normal(scale=0.5, size=pts.shape)
    assert conic_misfit_px(noisy) < 0.6
    scattered = rng.uniform(0, 400, size=(200, 2))
    assert conic_misfit_px(scattered) > 10.0
    line = np.stack([np.linspace(0, 300, 100), 0.2 * np.linspace(0, 300, 100) + 5], 1)
    assert conic_misfit_px(line) < 1e-6  # an edge-on needle's image: a degenerate conic fits it
    assert fit_conic(pts[:4]) is None and conic_misfit_px(pts[:4]) == 0.0


@pytest.mark.parametrize("direction", [(0.0, 1.0), (1.0, 0.0), (1.0, 1.0), (1.0, 0.2), (0.3, -1.0)])
def test_exactly_collinear_pixels_fit_their_line(direction: tuple[float, float]) -> None:
    """Collinear pixels (an edge-on needle's image) have many least-squares conics, among them double lines on
    which the Sampson distance is 0/0: the misfit is then the distance to their line, 0."""
    t = np.linspace(-200.0, 200.0, 200)
    pts = np.array([539.5, 539.5]) + t[:, None] * np.asarray(direction) / np.hypot(*direction)
    assert conic_misfit_px(pts) < 1e-9
    rng = np.random.default_rng(1)
    assert conic_misfit_px(pts + rng.normal(scale=0.5, size=pts.shape)) < 0.6
