"""Rendering for the simulator: segmentation masks, false positives, camera images.

Masks (what a segmentation network would output, 10 Hz)
    The visible part of the needle arc is sampled every 0.5° (``ARC_SAMPLES`` over the 3/8
    circle), projected *with* lens distortion, and drawn as a band around the projected
    centre line whose half width is the wire's projected radius ``0.2 mm · f / depth`` at each
    sample (so it narrows with depth along the needle), never below
    ``mask_min_half_width_px``. The boundary is perturbed by smooth noise along the arc
    length ``s`` (pixels): a sideways displacement of the whole band ``δc(s)`` (std
    ``mask_centreline_sigma_px``) and an independent jitter of each edge ``δl(s)``, ``δr(s)``
    (std ``mask_edge_sigma_px``), all stationary Gaussian processes with the squared-
    exponential correlation ``exp(−Δs² / 2ℓ²)``, ``ℓ = mask_noise_length_px`` (drawn as
    random Fourier features, 24 per process). The band is filled segment by segment
    (convex quadrilaterals, 1/16-pixel precision), giving a uint8 0/255 image the size of
    the camera image. With probability ``fp_blob_prob`` (and again for a second one) a
    false-positive ellipse (semi-axes uniform in ``fp_blob_axes_px``) is added at least
    ``fp_blob_min_distance_px`` away from the needle's projection; the blobs are returned so
    tests can tell them apart. Self-intersecting bands (a nearly edge-on arc folds back on
    itself in the image) are filled correctly because the quadrilaterals are drawn one by one.
    Optionally (``spur_prob`` > 0; off by default, and then no random numbers are drawn for it)
    a mask gets up to two *spurs*: wire-wide straight branches (length uniform in
    ``spur_length_px``, 20-35 px) leaving the band at a random visible point, within ±60° of
    its normal — a segmenter bleeding into a thread or a tissue fold; after thinning they
    become skeleton branches whose pixels lie up to the spur length off the needle's conic.

Images
    A static tissue-like background (pink-red colour noise at three scales, deterministic per
    seed), then the checkerboard of :mod:`pinpoint_fg.checkerboard` at
    ``cam_T_needle · DEFAULT_NEEDLE_T_BOARD`` (:func:`render_board`), then the visible needle
    as a grey metallic band (anti-aliased, a brighter specular line along its centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from factors.geometry import NeedleModel, PinholeCamera

#: Arc samples per needle (0.5° apart on the default 3/8 circle).
ARC_SAMPLES = 271

_SHIFT = 4  # fixed-point bits for OpenCV drawing (1/16 px)
_SCALE = float(1 << _SHIFT)
_FOURIER_FEATURES = 24


@dataclass(frozen=True)
class Blob:
    """A false-positive ellipse drawn into a mask."""

    centre_px: tuple[float, float]
    """Centre (u, v), pixels."""
    axes_px: tuple[float, float]
    """Semi-axes, pixels."""
    angle_deg: float
    """Rotation of the first axis, degrees (OpenCV convention)."""

    def contains(self, points_px: np.ndarray, pad_px: float = 1.0) -> np.ndarray:
        """Boolean ``(M,)``: points ``(M, 2)`` inside the ellipse grown by ``pad_px``."""
        p = np.asarray(points_px, dtype=float) - np.asarray(self.centre_px)
        a = math.radians(self.angle_deg)
        c, s = math.cos(a), math.sin(a)
        x = c * p[:, 0] + s * p[:, 1]
        y = -s * p[:, 0] + c * p[:, 1]
        ax, ay = self.axes_px[0] + pad_px, self.axes_px[1] + pad_px
        return (x / ax) ** 2 + (y / ay) ** 2 <= 1.0


def smooth_noise(rng: np.random.Generator, s: np.ndarray, sigma: float, length: float, count: int = 1) -> np.ndarray:
    """``count`` stationary Gaussian processes at positions ``s`` ``(M,)`` -> ``(count, M)``.

    Random Fourier features of the squared-exponential kernel ``σ² exp(−Δs²/2ℓ²)``:
    ``σ √(2/J) Σ_j cos(ω_j s + φ_j)``, ``ω_j ~ N(0, 1/ℓ²)``, ``φ_j ~ U(0, 2π)``.
    """
    s = np.asarray(s, dtype=float)
    omega = rng.standard_normal((count, _FOURIER_FEATURES)) / length
    phase = rng.uniform(0.0, 2.0 * math.pi, (count, _FOURIER_FEATURES))
    if sigma == 0.0:
        return np.zeros((count, s.shape[0]))
    arg = omega[:, :, None] * s[None, None, :] + phase[:, :, None]
    return sigma * math.sqrt(2.0 / _FOURIER_FEATURES) * np.cos(arg).sum(axis=1)


def visible_runs(visible: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs ``[start, stop)`` of True in a boolean ``(A,)`` array."""
    v = np.concatenate([[False], np.asarray(visible, dtype=bool), [False]])
    d = np.diff(v.astype(np.int8))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def project_arc(
    camera: PinholeCamera, cam_T_needle: np.ndarray, needle: NeedleModel, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels ``(A, 2)`` and depths ``(A,)`` of the arc points at angles ``theta``."""
    p = needle.point(theta) @ cam_T_needle[:3, :3].T + cam_T_needle[:3, 3]
    return camera.distort_px(camera.project(p)), p[:, 2]


def _band_edges(px: np.ndarray, half_width: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left/right edges ``(A, 2)`` of a band of half widths ``(A,)`` around a polyline ``(A, 2)``."""
    tan = np.gradient(px, axis=0) if px.shape[0] > 1 else np.array([[1.0, 0.0]])
    n = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-9, n / np.maximum(norm, 1e-12), np.array([[1.0, 0.0]]))
    return px + half_width[:, None] * n, px - half_width[:, None] * n


def fill_band(
    image: np.ndarray, left: np.ndarray, right: np.ndarray, color: int | tuple, line_type: int = cv2.LINE_8
) -> None:
    """Fill the band between two edge polylines ``(A, 2)`` quad by quad (in place)."""
    L = np.rint(left * _SCALE).astype(np.int32)
    R = np.rint(right * _SCALE).astype(np.int32)
    for i in range(L.shape[0] - 1):
        quad = np.stack([L[i], L[i + 1], R[i + 1], R[i]])
        cv2.fillConvexPoly(image, quad, color, lineType=line_type, shift=_SHIFT)


def render_mask(
    camera: PinholeCamera,
    cam_T_needle: np.ndarray,
    needle: NeedleModel,
    theta: np.ndarray,
    visible: np.ndarray,
    rng: np.random.Generator,
    centreline_sigma_px: float,
    edge_sigma_px: float,
    noise_length_px: float,
    min_half_width_px: float,
    fp_blob_prob: float,
    fp_blob_axes_px: tuple[float, float],
    fp_blob_min_distance_px: float,
    spur_prob: float = 0.0,
    spur_length_px: tuple[float, float] = (20.0, 35.0),
) -> tuple[np.ndarray, list[Blob]]:
    """A noisy segmentation mask (module docstring): uint8 ``(H, W)`` 0/255 and the false-positive blobs.

    ``theta`` ``(A,)`` are arc angles, ``visible`` ``(A,)`` which of them are visible. The
    random draws are made in a fixed order whatever is visible, so a frame's noise does not
    depend on the previous frames' geometry.
    """
    H, W = int(camera.height), int(camera.width)
    mask = np.zeros((H, W), np.uint8)
    px, depth = project_arc(camera, cam_T_needle, needle, theta)
    hw = 0.5 * needle.wire_diameter_m * camera.fx / np.maximum(depth, 1e-6)
    # arc length along the projected curve (pixels) parametrises the boundary noise
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(px, axis=0), axis=1))])
    dc, = smooth_noise(rng, s, centreline_sigma_px, noise_length_px, 1)
    dl, dr = smooth_noise(rng, s, edge_sigma_px, noise_length_px, 2)
    blob_u = rng.uniform(0.0, 1.0, (2, 8, 6))  # up to 2 blobs, 8 placement tries, 6 numbers each
    for start, stop in visible_runs(visible):
        if stop - start < 2:
            continue
        sl = slice(start, stop)
        centre = px[sl]
        left0, right0 = _band_edges(centre, np.ones(stop - start))
        normal = left0 - centre
        shifted = centre + dc[sl, None] * normal
        left = shifted + np.maximum(hw[sl] + dl[sl], min_half_width_px)[:, None] * normal
        right = shifted - np.maximum(hw[sl] + dr[sl], min_half_width_px)[:, None] * normal
        fill_band(mask, left, right, 255)
    if spur_prob > 0:
        _draw_spurs(mask, px, hw, visible, rng.uniform(0.0, 1.0, (2, 4)), spur_prob, spur_length_px,
                    min_half_width_px)
    blobs: list[Blob] = []
    if fp_blob_prob > 0:
        vis_px = px[np.asarray(visible, bool)]
        all_px = px  # keep blobs away from the whole projected needle, hidden parts included
        ref = all_px if all_px.shape[0] else vis_px
        for b in range(2):
            if blob_u[b, 0, 5] >= fp_blob_prob or (b == 1 and not blobs):
                break
            for k in range(blob_u.shape[1]):
                u = blob_u[b, k]
                cu, cv = u[0] * (W - 1), u[1] * (H - 1)
                a0, a1 = fp_blob_axes_px
                ax = (a0 + (a1 - a0) * u[2], a0 + (a1 - a0) * u[3])
                d = np.min(np.hypot(ref[:, 0] - cu, ref[:, 1] - cv)) if ref.shape[0] else np.inf
                if d < fp_blob_min_distance_px + max(ax):
                    continue
                blob = Blob(centre_px=(float(cu), float(cv)), axes_px=(float(ax[0]), float(ax[1])),
                            angle_deg=float(180.0 * u[4]))
                cv2.ellipse(
                    mask,
                    (int(round(cu * _SCALE)), int(round(cv * _SCALE))),
                    (int(round(ax[0] * _SCALE)), int(round(ax[1] * _SCALE))),
                    blob.angle_deg, 0.0, 360.0, 255, -1, cv2.LINE_8, _SHIFT,
                )
                blobs.append(blob)
                break
    return mask, blobs


def _draw_spurs(mask: np.ndarray, px: np.ndarray, hw: np.ndarray, visible: np.ndarray, u: np.ndarray,
                prob: float, length_px: tuple[float, float], min_half_width_px: float) -> None:
    """Up to two spurs (``u`` (2, 4) uniforms: go, where, angle, length) off the visible band, in place."""
    idx = np.flatnonzero(np.asarray(visible, bool))
    if idx.shape[0] < 3:
        return
    tan = np.gradient(px, axis=0)
    for b in range(2):
        if u[b, 0] >= prob or (b == 1 and u[0, 0] >= prob):
            break
        i = int(idx[min(int(u[b, 1] * idx.shape[0]), idx.shape[0] - 1)])
        t = tan[i] / max(float(np.linalg.norm(tan[i])), 1e-12)
        a = (u[b, 2] - 0.5) * (2.0 * math.pi / 3.0) + (0.0 if u[b, 2] < 0.5 else math.pi)  # ±60° of ±normal
        n = np.array([-t[1], t[0]])
        d = math.cos(a) * n + math.sin(a) * t
        end = px[i] + (length_px[0] + (length_px[1] - length_px[0]) * u[b, 3]) * d
        w = max(2.0 * max(float(hw[i]), min_half_width_px), 1.0)
        p0 = np.rint(px[i] * _SCALE).astype(np.int32)
        p1 = np.rint(end * _SCALE).astype(np.int32)
        cv2.line(mask, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), 255, int(round(w)), cv2.LINE_8, _SHIFT)


def tissue_background(width: int, height: int, seed: int) -> np.ndarray:
    """A deterministic tissue-like BGR uint8 image ``(H, W, 3)``: smooth pink-red colour noise."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7155]))
    base = np.array([105.0, 115.0, 185.0])  # BGR: pink-red
    img = np.zeros((height, width, 3), np.float32)
    for cells, amp in ((6, 30.0), (24, 14.0), (96, 6.0)):
        low = rng.standard_normal((cells, cells, 3)).astype(np.float32)
        low[..., 0] = 0.6 * low[..., 0] + 0.4 * low[..., 2]  # correlated channels: tissue, not confetti
        low[..., 1] = 0.6 * low[..., 1] + 0.4 * low[..., 2]
        img += amp * cv2.resize(low, (width, height), interpolation=cv2.INTER_CUBIC)
    lum = cv2.resize(rng.standard_normal((12, 12)).astype(np.float32), (width, height),
                     interpolation=cv2.INTER_CUBIC)
    img += base[None, None, :].astype(np.float32) * (1.0 + 0.12 * lum[..., None])
    img = cv2.GaussianBlur(img, (0, 0), 4.0)  # no blocky texture that could pass for board corners
    return np.clip(img, 0, 255).astype(np.uint8)


def draw_needle(
    image: np.ndarray,
    camera: PinholeCamera,
    cam_T_needle: np.ndarray,
    needle: NeedleModel,
    theta: np.ndarray,
    visible: np.ndarray,
) -> None:
    """Draw the visible needle (grey metallic band with a specular centre line) into ``image`` in place."""
    px, depth = project_arc(camera, cam_T_needle, needle, theta)
    hw = np.maximum(0.5 * needle.wire_diameter_m * camera.fx / np.maximum(depth, 1e-6), 0.5)
    for start, stop in visible_runs(visible):
        if stop - start < 2:
            continue
        c = px[start:stop]
        left, right = _band_edges(c, hw[start:stop])
        fill_band(image, left, right, (120, 125, 128), cv2.LINE_AA)
        l2, r2 = _band_edges(c, 0.45 * hw[start:stop])
        fill_band(image, l2, r2, (175, 180, 182), cv2.LINE_AA)
        l3, r3 = _band_edges(c, 0.15 * hw[start:stop])
        fill_band(image, l3, r3, (235, 238, 240), cv2.LINE_AA)
