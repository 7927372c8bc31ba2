"""Segmentation masks -> needle backbone pixels, and recorded frames -> tracker observations.

:func:`mask_backbone` (and :func:`backbone_from_mask`, its pixels alone) turns a binary needle mask (distorted
camera image) into at most ``max_points`` undistorted pixels on the needle's centre-line:

1. **Binarise**: nonzero = needle.
2. **Drop blobs that cannot be needle**: 8-connected components are kept when their area
   is at least ``max(min_blob_px, min_blob_fraction · largest area)`` and — after
   thinning — when they are elongated: ``L² / A >= min_elongation`` with ``L`` the
   component's skeleton length (pixels) and ``A`` its area, i.e. roughly length/width >= 2
   (the largest component is always kept). Segmentation false positives are specks or
   small ellipses (a few to ~150 pixels); the needle, even when occlusion cuts it into
   pieces, is a wire ~5-10 px thick and tens to hundreds of pixels long. A visible needle
   piece smaller than a tenth of the largest piece, or shorter than about three wire
   widths, is sacrificed with them.
3. **Thin** the kept blobs to a one-pixel centre-line: Zhang-Suen thinning, each
   sub-iteration one whole-array step over the blobs' bounding box (the 8 neighbours are
   packed into a byte and a 256-entry table says whether the pixel is deleted). A long, thin
   blob whose skeleton thinning leaves far shorter than the blob (Zhang-Suen erodes a wire two
   pixels wide on a diagonal, a staircase, to a pixel or two: a far needle's whole mask) is
   thinned again at three times the resolution, where it is a solid band, and its centre-line
   mapped back (:data:`THIN_AGAIN_ELONGATION` tells it from a speck, :data:`THIN_AGAIN_SHORT`
   from a wire that thinning kept). On 6,349 simulated mask frames no blob qualified: every
   centre-line pixel is as before. Such a staircase also loses a pixel at each end per
   iteration, so thinning stops after ``ceil(d) +`` :data:`ZS_SPARE_ITERATIONS` iterations
   (``d``: the crop's largest distance to the background) and a long, thin blob still thinning
   then takes the finer pass at once.
4. **Subsample** deterministically to at most ``max_points``: the skeleton pixels in raster
   order, taken at evenly spaced indices. A one-pixel 8-connected curve has about one pixel
   per row or per column along its dominant direction, so equal steps in raster order are
   equal steps along the curve to within a factor √2 (diagonal vs. axis-aligned runs).
5. **Refine across the wire** (sub-pixel): Zhang-Suen's centre-line is up to half a pixel
   off for even wire widths and jagged edges. At each kept point the wire's normal comes
   from the mask's structure tensor (Gaussian window ~ half the wire width); the mask is
   sampled along the normal and the point moves to the midpoint of the two 0.5-crossings
   of the wire's cross-section (unchanged when either edge is not found within one wire
   width, or when the move exceeds ``0.25 ·`` wire width + 1 px, e.g. at a junction).
6. **Undistort** with :meth:`PinholeCamera.undistort_px`.

:func:`observe_frame` then checks that the pixels can be one needle's centre-line at all: they must lie on
their own best-fitting conic to within the wire's width or 3 px, whichever is larger
(:func:`centre_line_misfit`); a mask of noise or texture is ignored, with the reason in the observation,
instead of being fitted.

The wire width ``w`` used in step 5 is estimated as blob area / skeleton length. Skeleton
pixels within ``w`` of the image border are dropped before step 4: where the image frame
cuts the wire obliquely, the thinned line bends towards the middle of the cut.

A centre-line is only meaningful where the wire's image curves more gently than its own
width: for a needle seen nearly edge-on (apparent ellipse with minor axis comparable to the
wire width) the mask merges the near and far branches and its centre-line lies between them.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from factors.geometry import PinholeCamera
from pinpoint_fg.conic_fit import conic_misfit_px
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.reader import no_image_evidence_note, time_order_note, unknown_columns_note
from pinpoint_fg.observation import Observation

if TYPE_CHECKING:
    from pinpoint_fg.io.recording.schema import FrameRecord, Recording


def _zhang_suen_tables() -> tuple[np.ndarray, np.ndarray]:
    """Deletion tables of the two Zhang-Suen sub-iterations, indexed by the neighbour byte.

    Bit ``k`` of the byte is neighbour ``P(k+2)``: P2 = N, P3 = NE, P4 = E, P5 = SE, P6 = S,
    P7 = SW, P8 = W, P9 = NW. A pixel is deleted when 2 <= B <= 6 (B: foreground
    neighbours), A = 1 (A: 0->1 transitions around P2..P9,P2) and, in the first
    sub-iteration, P2·P4·P6 = P4·P6·P8 = 0; in the second, P2·P4·P8 = P2·P6·P8 = 0.
    """
    codes = np.arange(256)
    p = (codes[:, None] >> np.arange(8)[None, :]) & 1  # (256, 8): P2..P9
    B = p.sum(axis=1)
    A = ((p == 0) & (np.roll(p, -1, axis=1) == 1)).sum(axis=1)
    P2, P4, P6, P8 = p[:, 0], p[:, 2], p[:, 4], p[:, 6]
    base = (B >= 2) & (B <= 6) & (A == 1)
    first = base & (P2 * P4 * P6 == 0) & (P4 * P6 * P8 == 0)
    second = base & (P2 * P4 * P8 == 0) & (P2 * P6 * P8 == 0)
    return first.astype(np.uint8), second.astype(np.uint8)


_ZS_FIRST, _ZS_SECOND = _zhang_suen_tables()


#: Correlation kernel packing the 8 neighbours into a byte: bit k <-> neighbour P(k+2) (N, NE, E, ... NW).
_ZS_KERNEL = np.array([[128.0, 1.0, 2.0], [64.0, 0.0, 4.0], [32.0, 16.0, 8.0]], dtype=np.float32)


def zhang_suen_thin(binary: np.ndarray) -> np.ndarray:
    """Zhang-Suen thinning of a 0/1 image ``(H, W)`` -> 0/1 uint8 skeleton ``(H, W)``.

    Vectorised: each sub-iteration packs the 8 neighbours of every pixel into a byte with
    one 3x3 correlation (weights 1, 2, ..., 128; exact in 8 bits), looks the deletion
    decision up in a 256-entry table and deletes in one step. Iterations stop when neither
    sub-iteration deletes anything (about half the stroke width of them). Pixels outside
    the image count as background.
    """
    b = np.asarray(binary)
    if b.ndim != 2:
        raise ValueError(f"binary must be 2-D, got shape {b.shape}")
    return _zhang_suen((b != 0).astype(np.uint8), None)[0]


def _zhang_suen(C: np.ndarray, max_iterations: int | None) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`zhang_suen_thin` of the 0/1 uint8 image ``C`` (thinned in place), stopped after ``max_iterations``
    (None: none). Returns the image and, when stopped with pixels still being deleted, the 0/1 image of the last
    iteration's deletions (else None). The state is the image alone: thinning the returned image goes on
    exactly where this stopped."""
    iteration = 0
    while max_iterations is None or iteration < max_iterations:
        iteration += 1
        deleted = None
        for table in (_ZS_FIRST, _ZS_SECOND):
            code = cv2.filter2D(C, cv2.CV_8U, _ZS_KERNEL, borderType=cv2.BORDER_CONSTANT)
            delete = cv2.bitwise_and(cv2.LUT(code, table), C)
            if cv2.countNonZero(delete):
                cv2.subtract(C, delete, dst=C)
                deleted = delete if deleted is None else cv2.bitwise_or(deleted, delete)
        if deleted is None:
            return C, None
    return C, deleted


def _refine_across(
    crop: np.ndarray, pts_rc: np.ndarray, width_px: float
) -> np.ndarray:
    """Move crop points ``(M, 2)`` as (row, col) to the middle of the wire across its local normal.

    ``crop`` is the 0/1 blob image; returns refined (row, col) ``(M, 2)``, float.
    """
    f = crop.astype(np.float32)
    sigma = max(1.0, 0.5 * width_px)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), sigma)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), sigma)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), sigma)
    r = pts_rc[:, 0].astype(int)
    c = pts_rc[:, 1].astype(int)
    angle = 0.5 * np.arctan2(2.0 * jxy[r, c], jxx[r, c] - jyy[r, c])  # normal direction (x=col, y=row)
    n_col, n_row = np.cos(angle), np.sin(angle)
    reach = max(2.0, width_px)
    step = 0.25
    offsets = np.arange(-reach, reach + step / 2, step)  # (S,)
    mid = int(np.argmin(np.abs(offsets)))
    map_x = (c[:, None] + offsets[None, :] * n_col[:, None]).astype(np.float32)
    map_y = (r[:, None] + offsets[None, :] * n_row[:, None]).astype(np.float32)
    prof = cv2.remap(f, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    inside = prof >= 0.5
    right_part = ~inside[:, mid:]
    left_part = ~inside[:, mid::-1]
    has_r = right_part.any(axis=1)
    has_l = left_part.any(axis=1)
    jr = mid + np.argmax(right_part, axis=1)  # first sample outside, going right
    jl = mid - np.argmax(left_part, axis=1)  # first sample outside, going left

    def crossing(j_out: np.ndarray, j_in: np.ndarray) -> np.ndarray:
        rows = np.arange(prof.shape[0])
        a, b = prof[rows, j_in], prof[rows, j_out]
        t = np.clip((a - 0.5) / np.where(a - b > 1e-6, a - b, 1.0), 0.0, 1.0)
        return offsets[j_in] + t * (offsets[j_out] - offsets[j_in])

    j_in_r = np.maximum(jr - 1, 0)
    j_in_l = np.minimum(jl + 1, len(offsets) - 1)
    edge_r = crossing(jr, j_in_r)
    edge_l = crossing(jl, j_in_l)
    shift = 0.5 * (edge_r + edge_l)
    ok = has_r & has_l & inside[:, mid] & (np.abs(shift) <= 0.25 * width_px + 1.0)
    shift = np.where(ok, shift, 0.0)
    return np.stack([r + shift * n_row, c + shift * n_col], axis=1)


#: A mask with more of its pixels nonzero than this share holds no needle (:func:`mask_backbone` does not read it;
#: :func:`centre_line_misfit` says why): a needle's wire covers at most a few per cent of the image (a 32 px wire
#: 700 px long: 2 % of 1080 x 1080), an inverted mask (the needle zero) or one of noise most of it.
MAX_FOREGROUND_SHARE = 0.25

#: :attr:`MaskBackbone.thickness_px` reads this quantile of the skeleton's distances to the background: the
#: centre-line's, above its side branches' (which run out to the boundary).
THICKNESS_QUANTILE = 0.9


#: :func:`_thin_finer`'s magnification (nearest neighbour). Zhang-Suen erodes a staircase two pixels wide to two
#: pixels on one diagonal at 1x and 2x and on both at 1x; at 3x it thins it along its middle on both.
THIN_AGAIN_SCALE = 3


#: A blob is thinned again when its bounding box's diagonal squared is at least this many times its area (a
#: staircase two pixels wide and ``n`` rows long scores about ``n``; an upright elliptic speck of axes ratio ``r``
#: ``(4 / pi) (r + 1 / r)``, 2.5 when round) ...
THIN_AGAIN_ELONGATION = 16.0
#: ... and its skeleton is shorter than this share of that diagonal: thinning eroded it (to a pixel or two, or to a
#: few around a knob or a corner that broke the staircase), where a wire's skeleton runs its whole length.
THIN_AGAIN_SHORT = 0.25


#: Zhang-Suen gets ``ceil(d) +`` this many iterations at full resolution, ``d`` the crop's largest distance to the
#: background (a band ``2 d`` wide thins in about ``d``). On 6,349 simulated mask frames it needed at most
#: ``ceil(d) + 20``; a staircase two pixels wide loses a pixel at each end per iteration instead, so it takes half
#: its length (0.83 s for 800 rows). A long, thin blob still thinning then is thinned at :data:`THIN_AGAIN_SCALE`
#: times the resolution, where a staircase's erosion would have sent it anyway (a blob that thinning would not have
#: eroded is thinned at 3x too, its centre-line mapped back); any other blob still thinning is thinned on.
ZS_SPARE_ITERATIONS = 32


def _thin_finer(skeleton: np.ndarray, blobs: np.ndarray) -> np.ndarray:
    """``skeleton`` (0/1, ``(H, W)``) with the pixels of ``blobs`` (0/1, same shape; blobs its thinning eroded)
    replaced by their thinning at :data:`THIN_AGAIN_SCALE` times the resolution, mapped back: a staircase two
    pixels wide, which Zhang-Suen erodes to a pixel or two, is a solid band there."""
    k = THIN_AGAIN_SCALE
    x, y, w, h = cv2.boundingRect(blobs)  # only the erased blobs' box: the crop may hold a far wire too
    finer = cv2.resize(blobs[y : y + h, x : x + w], None, fx=float(k), fy=float(k), interpolation=cv2.INTER_NEAREST)
    rk, ck = np.nonzero(zhang_suen_thin(finer))
    out = skeleton.copy()
    out[blobs != 0] = 0
    out[y + rk // k, x + ck // k] = 1
    return out


@dataclass(frozen=True)
class MaskBackbone:
    """What :func:`mask_backbone` reads from a mask."""

    points_px: np.ndarray
    """Undistorted centre-line pixels ``(M, 2)`` as (u, v); ``(0, 2)`` when the mask holds no wire."""
    width_px: float
    """The wire's mean width in the mask, pixels: the kept blobs' area over their skeleton length (0 if none)."""
    thickness_px: float
    """The wire's width across its centre-line, pixels: ``2 d - 1`` with ``d`` the :data:`THICKNESS_QUANTILE` of
    the skeleton pixels' distance to the background (0 if none). Unlike ``width_px`` it does not shrink when a
    rough boundary or holes give the skeleton side branches and loops (a 32 px wire with a boundary jagged by
    ±4 px: ``width_px`` 6-8, ``thickness_px`` 22-23)."""
    foreground_share: float = 0.0
    """The share of the image's pixels that are nonzero; above :data:`MAX_FOREGROUND_SHARE` the mask is not read
    (no points)."""

    @property
    def wire_px(self) -> float:
        """The wire's width the gate of :func:`centre_line_misfit` scales with: the larger of ``width_px`` and
        ``thickness_px``."""
        return max(self.width_px, self.thickness_px)


def mask_backbone(
    mask: np.ndarray,
    camera: PinholeCamera,
    max_points: int = 200,
    min_blob_px: int = 40,
    min_blob_fraction: float = 0.1,
    min_elongation: float = 2.0,
    refine: bool = True,
    file: str | Path | None = None,
) -> MaskBackbone:
    """Undistorted centre-line pixels ``(M, 2)`` as (u, v), ``M <= max_points``, of a needle mask, and the
    wire's width (:class:`MaskBackbone`).

    ``mask`` is ``(camera.height, camera.width)``, nonzero = needle (distorted image), any
    dtype. The steps are in the module docstring: ``min_blob_px``, ``min_blob_fraction`` and
    ``min_elongation`` are step 2's thresholds, ``refine`` switches step 5 off (the raw
    Zhang-Suen pixels, up to half a pixel off). An empty mask (or one with only dropped
    blobs) gives a ``(0, 2)`` array — "no dense observation"; so does one more than
    :data:`MAX_FOREGROUND_SHARE` nonzero, which is not thinned (:attr:`MaskBackbone.foreground_share`). A mask
    that is not 2-D or not the camera's size raises :class:`InputError` naming ``file``. Deterministic; ~3 ms for a
    1080x1080 mask with a 100 px-radius arc.
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"mask must be a single-channel 2-D image, got shape {m.shape}", file=file)
    if camera.width is not None and camera.height is not None and m.shape != (camera.height, camera.width):
        raise InputError(
            f"mask is {m.shape[1]}x{m.shape[0]} px but the camera image is {camera.width}x{camera.height}",
            file=file,
        )
    if int(max_points) < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    if m.dtype == np.uint8:
        binary = cv2.threshold(m, 0, 1, cv2.THRESH_BINARY)[1]
    elif m.dtype == bool:
        binary = np.ascontiguousarray(m).view(np.uint8)
    else:
        binary = (m != 0).astype(np.uint8)
    fg = cv2.findNonZero(binary)
    if fg is None:
        return MaskBackbone(np.zeros((0, 2)), 0.0, 0.0, 0.0)
    share = fg.shape[0] / float(binary.size)
    nothing = MaskBackbone(np.zeros((0, 2)), 0.0, 0.0, share)
    if share > MAX_FOREGROUND_SHARE:  # not thinned: ~1.4 s for an inverted 1080 x 1080 mask, and no wire in it
        return nothing
    fg = fg.reshape(-1, 2)  # (N, 2) as (u, v)
    u_lo, v_lo = fg.min(axis=0)
    u_hi, v_hi = fg.max(axis=0)
    box = binary[v_lo : v_hi + 1, u_lo : u_hi + 1]
    _, labels, stats, _ = cv2.connectedComponentsWithStats(box, connectivity=8, ltype=cv2.CV_32S)
    fg_label = labels[fg[:, 1] - v_lo, fg[:, 0] - u_lo]
    areas = np.bincount(fg_label)
    areas[0] = 0
    largest = int(np.argmax(areas))
    keep = areas >= max(float(min_blob_px), float(min_blob_fraction) * float(areas[largest]))
    keep[0] = False
    kept = fg[keep[fg_label]]
    if kept.shape[0] == 0:
        return nothing
    c0, r0 = kept.min(axis=0)
    c1, r1 = kept.max(axis=0) + 1
    crop = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
    crop[kept[:, 1] - r0, kept[:, 0] - c0] = 1
    padded = cv2.copyMakeBorder(crop, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)  # outside the crop is background
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    crop_labels = labels[r0 - v_lo : r1 - v_lo, c0 - u_lo : c1 - u_lo]
    diag2 = stats[:, cv2.CC_STAT_WIDTH].astype(float) ** 2 + stats[:, cv2.CC_STAT_HEIGHT].astype(float) ** 2
    thin_blob = keep & (diag2 >= THIN_AGAIN_ELONGATION * areas)
    skeleton, thinning = _zhang_suen(crop.copy(), int(np.ceil(float(dist.max()))) + ZS_SPARE_ITERATIONS)
    unsettled = np.zeros(areas.size, dtype=bool)
    if thinning is not None:
        unsettled[crop_labels[thinning != 0]] = True
        if (unsettled & ~thin_blob).any():  # not the staircase's erosion: thinned to the end, as always
            skeleton, _ = _zhang_suen(skeleton, None)
            unsettled[:] = False
    rows, cols = np.nonzero(skeleton)
    length = np.bincount(crop_labels[rows, cols], minlength=areas.size)
    # Zhang-Suen erodes a wire two pixels wide on a diagonal (a staircase) to a pixel or two; a speck erodes so
    # too, and must stay a speck: only long, thin blobs whose skeleton is much shorter are thinned again
    vanished = thin_blob & ((length * length < THIN_AGAIN_SHORT**2 * diag2) | unsettled)
    if vanished.any():
        skeleton = _thin_finer(skeleton, crop & vanished[crop_labels])
        rows, cols = np.nonzero(skeleton)
    if rows.size == 0:
        return nothing
    # compact blobs (skeleton length^2 / area < min_elongation) are specks, not wire; the largest stays
    sk_label = crop_labels[rows, cols]
    length = np.bincount(sk_label, minlength=areas.size).astype(float)
    wire = keep & (length * length >= float(min_elongation) * areas)
    wire[largest] = True
    on_wire = wire[sk_label]
    rows, cols = rows[on_wire], cols[on_wire]
    width_px = float(areas[wire].sum()) / float(rows.size)
    # the skeleton's side branches into a rough boundary lengthen it and shrink width_px; the distance to the
    # background on the centre-line does not shrink: 2 d - 1 is the width of a band whose middle pixel is d away
    thickness_px = max(2.0 * float(np.quantile(dist[rows + 1, cols + 1], THICKNESS_QUANTILE)) - 1.0, 0.0)
    # where the image frame cuts the wire the centre-line bends towards the cut: drop that stretch
    border = int(np.ceil(width_px))
    h, w = m.shape
    inner = (
        (rows + r0 >= border) & (rows + r0 <= h - 1 - border) & (cols + c0 >= border) & (cols + c0 <= w - 1 - border)
    )
    rows, cols = rows[inner], cols[inner]
    if rows.size == 0:
        return nothing
    count = min(int(max_points), rows.size)
    idx = (np.arange(count) * rows.size) // count
    pts_rc = np.stack([rows[idx], cols[idx]], axis=1).astype(float)
    if refine:
        pts_rc = _refine_across(crop, pts_rc, width_px)
    pts_px = np.stack([pts_rc[:, 1] + c0, pts_rc[:, 0] + r0], axis=1)
    return MaskBackbone(camera.undistort_px(pts_px), width_px, thickness_px, share)


def backbone_from_mask(mask: np.ndarray, camera: PinholeCamera, *args: Any, **options: Any) -> np.ndarray:
    """:func:`mask_backbone`'s centre-line pixels ``(M, 2)`` alone (``args``, ``options``: its other arguments)."""
    return mask_backbone(mask, camera, *args, **options).points_px


#: A mask's centre-line is no needle's when its median distance to its own best-fitting conic exceeds this many
#: wire widths (:func:`centre_line_misfit`) ...
MISFIT_WIDTHS = 1.0
#: ... and this many pixels.
MISFIT_MIN_PX = 3.0


def centre_line_misfit(backbone: MaskBackbone) -> str | None:
    """Why ``backbone``'s pixels cannot be a needle's centre-line, or None (also when it has fewer than five: five
    pixels fix a conic, so they cannot be tested). First, a mask more than :data:`MAX_FOREGROUND_SHARE` nonzero
    is no needle's.

    A needle's centre-line is an arc of the circle's image conic (a line when seen edge-on), so its pixels lie
    on their own least-squares conic to within the mask's noise: :func:`pinpoint_fg.conic_fit.conic_misfit_px`
    (median Sampson distance, or distance to a line). The gate is that median above :data:`MISFIT_WIDTHS` wire
    widths (the larger of :attr:`MaskBackbone.width_px` and :attr:`~MaskBackbone.thickness_px`) and
    :data:`MISFIT_MIN_PX` pixels. On 6,349 simulated mask frames (every scenario, seeds 1-8, drive 9-14,
    snapshots 9-20; ``scripts/mask_gate.py measure``) the median was at most 2.1 px and 0.26 widths;
    masks of random noise (20 or 50 % of the pixels), stripes, or an arc beside a second wire scored 2-107
    widths and 3.0-127 px. Such a frame's mask is ignored (the frame keeps its keypoints and kinematics):
    fitted, 16 noise masks among normal-01's 49 (``scripts/mask_gate.py corrupt``) took SVN's mean error to
    2.61 mm / 31.8 deg and MAP's to 3.12 mm / 39.5 deg; with 14 ignored, 0.55 / 7.5 and 0.59 / 7.6. Not caught:
    noise sparse enough to leave a few specks (the other two, 1.5 and 2.3 px: a conic passes near five specks),
    and a mask holding one straight line or one clean arc that is not the needle (an edge-on needle looks alike),
    or an arc beside an object thicker than their misfit (the thickest wire blob sets the width: an instrument's
    shaft 20 px wide beside a 6 px needle passes).
    Ignored although a needle: a wire split lengthwise into two rims (a missed specular line: two curves about a
    quarter of the wire apart) and a needle whose mask includes a long, wavy suture thread. A thread in every mask
    passes the gate (the least-squares conic runs between needle and thread, within the wire's width of most
    pixels) and defeats Huber and Cauchy conic losses; the default Geman-McClure conic
    (:data:`pinpoint_fg.noise.DEFAULT_ROBUST`) tracks it (README, *Robust losses*).
    """
    if backbone.foreground_share > MAX_FOREGROUND_SHARE:
        return (f"{backbone.foreground_share:.0%} of its pixels are nonzero, more than any needle covers: an inverted "
                "mask (nonzero must be the needle) or noise?")
    if backbone.points_px.shape[0] < 5:
        return None
    misfit = conic_misfit_px(backbone.points_px)
    wire_px = backbone.wire_px
    gate = max(MISFIT_WIDTHS * wire_px, MISFIT_MIN_PX)
    if misfit <= gate:
        return None
    return (f"its centre-line lies a median {misfit:.2f} px off its best-fitting conic, more than the wire's width "
            f"({wire_px:.2f} px) and {MISFIT_MIN_PX:g} px: no single thin curve (noise, texture, a second object?)")


def ignored_masks(recording: Recording) -> list[tuple[int, str]]:
    """``(frame, why)`` of every frame whose mask :func:`observe_frame` ignores (:func:`centre_line_misfit`)."""
    out = []
    for rec in recording.frames:
        if rec.mask is not None:
            why = observe_frame(recording, rec).mask_ignored
            if why is not None:
                out.append((int(rec.frame), why))
    return out


def ignored_masks_note(run: Path, ignored: list[tuple[int, str]], fate: str = "tracked") -> str:
    """One ``note:`` line for the frames ``(frame, Observation.mask_ignored)`` whose masks were ignored, which are
    ``fate`` without them."""
    frame, why = ignored[0]
    return (f"note: {run}: the masks of {len(ignored)} frame(s) are ignored, those frames {fate} without them "
            f"(first: frame {frame}, {why})")


#: A keypoint cell more than this many pixels outside the image is not a detection (:func:`observe_frame`).
KEYPOINT_OUTSIDE_PX = 10.0


def detected_in_image(camera: PinholeCamera, px: np.ndarray | None) -> bool:
    """Whether a recorded keypoint ``px (2,)`` (distorted pixels) can be a detection: inside the image, give or
    take :data:`KEYPOINT_OUTSIDE_PX` (a detector's sub-pixel output at the border); False for None."""
    if px is None:
        return False
    return bool(camera.in_image(np.asarray(px, dtype=float), margin_px=-KEYPOINT_OUTSIDE_PX))


def keypoints_outside_image(recording: Recording, frames: list[FrameRecord] | None = None) -> list[tuple[int, str]]:
    """``(frame, "tip" | "tail")`` of every keypoint :func:`observe_frame` ignores as outside the image."""
    camera = recording.info.camera
    return [(int(rec.frame), name) for rec in (recording.frames if frames is None else frames)
            for name, px in (("tip", rec.tip_px), ("tail", rec.tail_px))
            if px is not None and not detected_in_image(camera, px)]


def outside_image_note(recording: Recording, frames: list[FrameRecord] | None = None) -> str | None:
    """One line for the user when :func:`keypoints_outside_image` finds any (None otherwise)."""
    outside = keypoints_outside_image(recording, frames)
    if not outside:
        return None
    camera = recording.info.camera
    frame, name = outside[0]
    rec = next(r for r in recording.frames if r.frame == frame)
    u, v = (rec.tip_px if name == "tip" else rec.tail_px)  # type: ignore[misc]
    return (f"note: {Path(recording.root) / 'frames.csv'}: {len(outside)} tip/tail keypoint(s) more than "
            f"{KEYPOINT_OUTSIDE_PX:g} px outside the {camera.width} x {camera.height} image are ignored as not "
            f"detected (first: frame {frame}, {name} at ({u:g}, {v:g}) px; wrong image size or pixel scale?)")


def recording_notes(recording: Recording, frames: list[FrameRecord] | None = None) -> list[str]:
    """The ``note:`` lines a valid run (or its ``frames``) still deserves, for ``validate`` and ``track``: keypoints
    outside the image (:func:`outside_image_note`), ``t_s`` out of order, no image evidence at all and unknown
    columns that look like a misspelt known one (:mod:`pinpoint_fg.io.recording.reader`)."""
    notes = (unknown_columns_note(recording), outside_image_note(recording, frames),
             time_order_note(recording, frames), no_image_evidence_note(recording, frames))
    return [n for n in notes if n is not None]


def observe_frame(recording: Recording, rec: FrameRecord, max_points: int = 200) -> Observation:
    """The tracker's input for one recorded frame ``rec`` of ``recording``.

    Tip/tail keypoints are undistorted; one that lies outside the image (by more than
    :data:`KEYPOINT_OUTSIDE_PX`) is taken as not detected: no detector reports a point it cannot
    see, the distortion model means nothing there, and such cells (a keypoint in another image's
    pixel scale, a sentinel like -5000) on ten frames had turned both SVN's and MAP's pose by
    140 deg on those frames. :func:`outside_image_note` tells the user. The backbone comes from the frame's mask via
    :func:`mask_backbone` (None when the frame has no mask or the mask holds no
    needle); a mask whose centre-line fits no conic (:func:`centre_line_misfit`) is ignored, and the
    observation says why in ``mask_ignored``. ``cam_T_grasper`` is passed through.
    """
    camera: PinholeCamera = recording.info.camera
    tip, tail = (camera.undistort_px(np.asarray(px, float)[None, :])[0] if detected_in_image(camera, px) else None
                 for px in (rec.tip_px, rec.tail_px))
    for name, px, raw in (("tip", tip, rec.tip_px), ("tail", tail, rec.tail_px)):
        if px is not None and not np.isfinite(px).all():  # the reader's grid check makes this rare; never silent
            raise InputError(f"frame {rec.frame}: the {name} at ({raw[0]:g}, {raw[1]:g}) px cannot be undistorted "
                             "with recording.json's camera.distortion (NaN or inf)",
                             file=Path(recording.root) / "frames.csv", row=recording.row_of(rec),
                             column=f"{name}_u_px")
    backbone = ignored = None
    if rec.mask is not None:
        mask = recording.load_mask(rec)
        mb = mask_backbone(mask, camera, max_points=max_points, file=Path(recording.root) / rec.mask)
        pts = mb.points_px
        if not np.isfinite(pts).all():
            raise InputError(f"frame {rec.frame}: {int((~np.isfinite(pts).all(axis=1)).sum())} backbone pixel(s) "
                             "cannot be undistorted with recording.json's camera.distortion (NaN or inf)",
                             file=Path(recording.root) / rec.mask)
        ignored = centre_line_misfit(mb)
        if ignored is not None:
            ignored = f"{rec.mask}: {ignored}"
        backbone = pts if pts.shape[0] > 0 and ignored is None else None
    return Observation(
        frame=int(rec.frame),
        t_s=float(rec.t_s),
        tip_px=tip,
        tail_px=tail,
        backbone_px=backbone,
        cam_T_grasper=rec.cam_T_grasper,
        mask_ignored=ignored,
    )


def iter_observations(recording: Recording, max_points: int = 200) -> Iterator[Observation]:
    """:func:`observe_frame` for every frame of ``recording``, in order."""
    for rec in recording.frames:
        yield observe_frame(recording, rec, max_points=max_points)
