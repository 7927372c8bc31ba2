"""The conic through a set of image points, and how far the points lie from it.

A needle's backbone pixels are an arc of the circle's image, an ellipse (a line pair or a line when the needle is
seen edge-on). :func:`fit_conic` is the algebraic least-squares conic ``x^T C x = 0`` through them, used to seed
hypotheses (:mod:`pinpoint_fg.init`, :mod:`pinpoint_fg.proposals`) and to tell a needle's centre-line from a mask
that is no curve at all (:func:`conic_misfit_px`, :mod:`pinpoint_fg.observe`).
"""

from __future__ import annotations

import numpy as np


def fit_conic(points_px: np.ndarray) -> np.ndarray | None:
    """Least-squares conic ``x^T C x = 0`` through pixels ``(M, 2)`` (Hartley-normalised); None if M < 5.

    Returns a symmetric 3x3 ``C`` in pixel coordinates, scaled to unit Frobenius norm.
    """
    p = np.asarray(points_px, dtype=float)
    if p.shape[0] < 5:
        return None
    mu = p.mean(axis=0)
    s = np.sqrt(2.0) / max(np.mean(np.linalg.norm(p - mu, axis=1)), 1e-9)
    N = np.array([[s, 0, -s * mu[0]], [0, s, -s * mu[1]], [0, 0, 1.0]])
    x, y = s * (p[:, 0] - mu[0]), s * (p[:, 1] - mu[1])
    D = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    _, _, Vt = np.linalg.svd(D, full_matrices=False)
    a, b, c, d, e, f = Vt[-1]
    Cn = np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])
    C = N.T @ Cn @ N
    return C / np.linalg.norm(C)


def sampson_distance_px(C: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    """``(M,)`` first-order distance ``|f(p)| / |grad f(p)|`` of pixels ``(M, 2)`` to conic ``C`` (3, 3), pixels,
    ``f(p) = [p; 1]^T C [p; 1]``; ``inf`` where the gradient vanishes (the centre of a line pair, or anywhere on
    a double line, where ``f`` vanishes too: not a distance there)."""
    P = np.concatenate([np.asarray(points_px, dtype=float), np.ones((len(points_px), 1))], axis=1)
    CP = P @ C
    f = np.einsum("ni,ni->n", CP, P)
    g = 2.0 * np.hypot(CP[:, 0], CP[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(g > 0.0, np.abs(f) / g, np.inf)


def line_distance_px(points_px: np.ndarray) -> np.ndarray:
    """``(M,)`` distance of pixels ``(M, 2)`` to their total-least-squares line (through their mean, along their
    principal direction), pixels."""
    p = np.asarray(points_px, dtype=float)
    if p.shape[0] == 0:
        return np.zeros(0)
    q = p - p.mean(axis=0)
    _, _, Vt = np.linalg.svd(q, full_matrices=False)
    return np.abs(q @ Vt[-1])


def conic_misfit_px(points_px: np.ndarray) -> float:
    """How far pixels ``(M, 2)`` lie from one conic, pixels: the median :func:`sampson_distance_px` to their own
    :func:`fit_conic`, or the median :func:`line_distance_px` to their own line when that is smaller (0 if M < 5).

    A needle's centre-line (an arc, or the line an edge-on needle projects to) scores a fraction of a pixel to a
    pixel or two; pixels spread over an area (a mask of noise or texture), or two wires of different curves,
    score tens. The median ignores up to half the pixels: a spur or a short second blob does not move it. The
    line is a conic too (a degenerate one), fitted on its own because the algebraic fit is not unique for
    collinear pixels: any line pair through them fits, and the one the SVD returns can be a double line, on which
    the Sampson distance is 0/0.
    """
    if len(points_px) < 5:
        return 0.0
    C = fit_conic(points_px)
    line = float(np.median(line_distance_px(points_px)))
    return line if C is None else min(line, float(np.median(sampson_distance_px(C, points_px))))
