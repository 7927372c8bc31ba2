"""Along-arc correlated pixel noise of the backbone residual: an Ornstein-Uhlenbeck model and its exact whitening.

A segmentation mask's boundary errors are smooth along the needle, so the Sampson distances of neighbouring
skeleton pixels (:func:`factors.residuals.conic_residual`) are strongly correlated; counting them as independent
pixels over-states how much one mask says about the pose. Model the residuals of one frame, ordered along the arc
with arc positions ``s_0 < s_1 < ...`` (pixels), as a stationary Ornstein-Uhlenbeck process::

    cov(r_i, r_j) = sigma^2 exp(-|s_i - s_j| / ell)

It is Markov along the arc, so its exact whitening is sequential (the Cholesky factor of that covariance is
bidiagonal): with ``a_i = exp(-(s_i - s_{i-1}) / ell)`` (``a_0 = 0``)::

    e_0 = r_0,   e_i = (r_i - a_i r_{i-1}) / sqrt(1 - a_i^2)

are independent with variance ``sigma^2`` each, so ``e`` replaces ``r`` under the same per-pixel noise model,
robust loss included (the loss then acts per innovation). The map is linear and fixed per frame (it depends on
the pixels, not on the pose), so the Jacobian of ``e`` is the same map applied to the rows of ``d r / d xi``:
analytic, in GTSAM's chart as the residual's own. ``ell -> 0`` gives ``e = r`` (independent pixels, the paper's
model).

The order comes from the pixels alone (:func:`arc_order`), and the arc position is the path length along it, so
every pose is scored against the same whitening. Gaps between visible pieces (occlusion) and branches get large
steps, hence ``a`` near 0: independent there.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Consecutive pixels closer than this (px) are taken this far apart: two pixels at one place would be perfectly
#: correlated (``a = 1``) and their innovation 0 / 0; at 0.25 px the pair still counts as nearly one pixel.
MIN_STEP_PX = 0.25


#: :func:`arc_order` tries nearest-neighbour chains only when its other candidates' shortest path exceeds this
#: multiple of the summed nearest-neighbour distances (a path that follows the arc is close to that sum; one that
#: zig-zags between an arc's folded branches is not); the chains cost a loop over the pixels.
ZIGZAG_RATIO = 1.15


def _path_length(points: np.ndarray, order: np.ndarray) -> float:
    q = points[order]
    return float(np.sqrt(((q[1:] - q[:-1]) ** 2).sum(axis=1)).sum())


def _nearest_neighbour_chain(d2: np.ndarray, start: int) -> np.ndarray:
    """The greedy path from ``start``: each step to the nearest pixel not yet visited (``d2``: squared distances)."""
    m = d2.shape[0]
    order = np.empty(m, dtype=int)
    visited = np.zeros(m, dtype=bool)
    i = start
    for k in range(m):
        order[k] = i
        visited[i] = True
        if k + 1 < m:
            i = int(np.argmin(np.where(visited, np.inf, d2[i])))
    return order


def arc_order(points_px: np.ndarray) -> np.ndarray:
    """An order ``(M,)`` of backbone pixels ``(M, 2)`` along the arc, from the pixels alone (no pose).

    Mask skeletons arrive in raster order, which runs back and forth across a curved arc. Three candidates, and
    the one with the shortest path through the pixels wins: the projection on the pixels' principal axis, which
    follows a nearly straight arc (an edge-on needle); the parametric angle on the ellipse OpenCV fits to the
    pixels (``cv2.fitEllipse``; each pixel mapped onto the fit's unit circle), cut at the largest angular gap (the
    arc's open end), which follows any elliptic arc; and, when both are much longer than the pixels' summed
    nearest-neighbour distances (:data:`ZIGZAG_RATIO`), the nearest-neighbour chains from either end of the
    principal axis, which follow an arc that folds back on itself in the image (a
    3/8 circle seen within a few degrees of edge-on), where both others zig-zag between its branches. Fewer than
    5 pixels: the principal axis alone. Ties keep the input order (stable sorts).
    """
    pts = np.asarray(points_px, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.isfinite(pts).all():
        raise ValueError(f"points_px must be finite (M, 2) pixels, got shape {pts.shape}")
    m = pts.shape[0]
    if m < 3:
        return np.arange(m)
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    candidates = [np.argsort(centred @ vt[0], kind="stable")]
    if m >= 5:
        try:
            (cx, cy), (w, h), angle_deg = cv2.fitEllipse(pts.astype(np.float32))
        except cv2.error:
            cx = cy = w = h = angle_deg = 0.0
        if np.isfinite([cx, cy, w, h, angle_deg]).all() and min(w, h) > 1e-6:
            t = np.deg2rad(angle_deg)
            c, s = np.cos(t), np.sin(t)
            d = pts - (cx, cy)
            u = (c * d[:, 0] + s * d[:, 1]) / (0.5 * w)
            v = (-s * d[:, 0] + c * d[:, 1]) / (0.5 * h)
            theta = np.arctan2(v, u)
            order = np.argsort(theta, kind="stable")
            ts = theta[order]
            gaps = np.diff(np.concatenate([ts, ts[:1] + 2.0 * np.pi]))
            candidates.append(np.roll(order, -(int(np.argmax(gaps)) + 1)))
    lengths = [_path_length(pts, o) for o in candidates]
    if m >= 5:
        # a path along the arc steps from each pixel to about its nearest neighbour; one much longer zig-zags
        dx, dy = pts[:, None, 0] - pts[None, :, 0], pts[:, None, 1] - pts[None, :, 1]
        d2 = dx * dx + dy * dy
        np.fill_diagonal(d2, np.inf)
        if min(lengths) > ZIGZAG_RATIO * float(np.sqrt(d2.min(axis=1)).sum()):
            for end in (candidates[0][0], candidates[0][-1]):
                candidates.append(_nearest_neighbour_chain(d2, int(end)))
                lengths.append(_path_length(pts, candidates[-1]))
    return candidates[int(np.argmin(lengths))]


@dataclass(frozen=True)
class ArcWhitening:
    """The whitening of one frame's backbone residuals under the Ornstein-Uhlenbeck model (module docstring)."""

    order: np.ndarray
    """(M,) the pixels' order along the arc; innovation ``i`` belongs to pixel ``order[i]``."""
    a: np.ndarray
    """(M,) ``exp(-step_i / ell)`` to the previous pixel in that order (``a[0] = 0``)."""
    length_px: float
    """The correlation length ``ell`` (px)."""

    @classmethod
    def from_points(cls, points_px: np.ndarray, length_px: float) -> ArcWhitening:
        """The whitening of pixels ``(M, 2)`` for correlation length ``length_px`` > 0 (steps floored at
        :data:`MIN_STEP_PX`)."""
        ell = float(length_px)
        if not (np.isfinite(ell) and ell > 0):
            raise ValueError(f"correlation length must be a positive number of pixels, got {length_px!r}")
        pts = np.asarray(points_px, dtype=float)
        order = arc_order(pts)
        q = pts[order]
        step = np.maximum(np.sqrt(((q[1:] - q[:-1]) ** 2).sum(axis=1)), MIN_STEP_PX)
        a = np.concatenate([[0.0], np.exp(-step / ell)])
        order.flags.writeable = False
        a.flags.writeable = False
        return cls(order, a, ell)

    @property
    def arc_length_px(self) -> np.ndarray:
        """(M,) each innovation's arc position ``s_i`` (from 0; the steps ``-ell log a_i`` summed, as floored)."""
        return np.concatenate([[0.0], np.cumsum(-self.length_px * np.log(self.a[1:]))])

    def apply(self, r: np.ndarray, J: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Innovations ``e (N, M)`` of residuals ``r (N, M)`` (bias removed) and ``J_e (N, M, 6)`` of ``J`` (or None).

        ``e_i = (r_o(i) - a_i r_o(i-1)) / sqrt(1 - a_i^2)`` with ``o = order``; the Jacobian rows by the same map.
        """
        a = self.a
        inv = 1.0 / np.sqrt(1.0 - a * a)
        x = r[:, self.order]
        e = x * inv
        e[:, 1:] -= (a[1:] * inv[1:]) * x[:, :-1]
        if J is None:
            return e, None
        Jx = J[:, self.order]
        Je = Jx * inv[:, None]
        Je[:, 1:] -= (a[1:] * inv[1:])[:, None] * Jx[:, :-1]
        return e, Je
