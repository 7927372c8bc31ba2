"""The ground-truth checkerboard (paper §V-A): its model, a renderer for the simulator, a detector.

The paper fixes a small checkerboard with 1 mm squares rigidly to the needle mount; OpenCV
finds it in each image, PnP gives ``cam_T_board`` and a measured, fixed ``board_T_needle``
gives the needle pose ``cam_T_needle = cam_T_board · board_T_needle``.

Board model and frame (:class:`BoardSpec`)
    ``squares_x × squares_y`` squares of side ``square_m`` surrounded by a white margin.
    The paper's "3×4 checkerboard" is read as OpenCV's *pattern size* (inner corners)
    3×4, i.e. 4×5 squares: OpenCV refuses patterns with 2 inner corners along a side
    (``findChessboardCorners`` needs > 2 each way), so 4×3 squares (3×2 inner corners)
    could not be detected at all. The default is therefore 5×4 squares, 4×3 inner corners.
    The board frame has its origin at the board centre, ``x`` along the ``squares_x``
    direction, ``y`` along ``squares_y``, ``z = x × y`` pointing *into* the board (away from
    a viewer of the printed face) — OpenCV's convention, so a camera that sees the printed
    face has the board's ``+z`` pointing away from it. Square ``(a, b)`` (column ``a`` along
    x, row ``b`` along y, both from 0 at the ``-x, -y`` corner) is black when ``a + b`` is even.
    Inner corner ``k = j · nx + i`` (``nx = squares_x - 1``) sits at
    ``((i - (nx-1)/2) s, (j - (ny-1)/2) s, 0)``: the row-major order OpenCV reports.

Orientation (the 180° ambiguity)
    A grid of inner corners can be reported starting from any of its four corners. Two of
    the four orderings are mirror images (they would put the printed face on the far side
    of the board) and are rejected by handedness; one of the remaining two is the 180°
    rotation of the other. With one side an odd and the other an even number of squares the
    180° rotation swaps black and white, so the colour of the squares decides it: the
    ordering whose predicted black squares are darker than its predicted white squares is
    kept. :class:`BoardSpec` therefore requires ``squares_x + squares_y`` to be odd.

Rendering (:func:`render_board`)
    Exact inverse mapping with anti-aliasing: every image pixel in the board's bounding box
    is undistorted (:meth:`PinholeCamera.undistort_px`) and carried to the board plane by the
    inverse plane homography ``H⁻¹``, ``H = K [r₁ r₂ t]``; the board-plane coordinates are
    bilinearly upsampled to ``supersample²`` sub-pixels per pixel, each sub-pixel takes the
    board's colour (black/white square, white margin) or keeps the background, and the
    sub-pixels are averaged. Lens distortion, perspective and partial-pixel coverage are all
    rendered; the board is one-sided (nothing is drawn when its back faces the camera).

Detection (:func:`detect_board`)
    ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` (``findChessboardCornersSB`` was
    tried: 6-10x slower here and no more accurate after ``cornerSubPix``); orientation as
    above; then ``cv2.solvePnPGeneric`` with IPPE (the two planar solutions), the one with
    the lower reprojection error refined by Levenberg-Marquardt (``cv2.solvePnPRefineLM``),
    with the camera's ``K`` and distortion. Near face-on views the out-of-plane tilt of so
    small a board is weakly observed (the two IPPE solutions nearly coincide): rotation
    errors there reach ~1° while translation stays at hundredths of a millimetre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from factors.geometry import PinholeCamera

#: Grey level of the black squares (0..255).
BLACK_LEVEL = 25.0
#: Grey level of the white squares and the margin (0..255).
WHITE_LEVEL = 235.0
#: Largest accepted square side and margin of the board, metres.
MAX_BOARD_M = 1.0
#: Most squares along a side of the board (OpenCV's pattern size is a C int; a 4 px square needs 4000 px for 1000).
MAX_BOARD_SQUARES = 1000


@dataclass(frozen=True)
class BoardSpec:
    """Geometry of the ground-truth checkerboard (see the module docstring for its frame)."""

    squares_x: int = 5
    """Number of squares along the board's x axis (inner corners: ``squares_x - 1``)."""
    squares_y: int = 4
    """Number of squares along the board's y axis (inner corners: ``squares_y - 1``)."""
    square_m: float = 0.001
    """Side of one square, metres (paper: 1 mm)."""
    margin_m: float = 0.001
    """Width of the white border around the squares, metres (``findChessboardCornersSB`` wants ~1 square)."""

    def __post_init__(self) -> None:
        for name in ("squares_x", "squares_y"):
            v = getattr(self, name)
            if int(v) != v or v < 4:
                raise ValueError(f"BoardSpec.{name} must be a whole number >= 4 (OpenCV needs > 2 inner corners)")
            if v > MAX_BOARD_SQUARES:  # 2**31 + 1 was OpenCV's "Can't parse 'patternSize'" traceback
                raise ValueError(f"BoardSpec.{name} must be at most {MAX_BOARD_SQUARES}, got {v!r}")
            object.__setattr__(self, name, int(v))  # a JSON 5.0 was OpenCV's "Can't parse 'patternSize'" traceback
        if (self.squares_x + self.squares_y) % 2 != 1:
            raise ValueError(
                "BoardSpec needs one odd and one even side (squares_x + squares_y odd) so that its colours "
                f"fix the 180-degree orientation; got {self.squares_x} x {self.squares_y}"
            )
        # a printed board of metre-sized squares is a unit mistake; 1e300 m overflowed the detector's homography
        if not (math.isfinite(self.square_m) and 0 < self.square_m <= MAX_BOARD_M):
            raise ValueError(f"BoardSpec.square_m must be > 0 and <= {MAX_BOARD_M:g} m, got {self.square_m!r}")
        if not (math.isfinite(self.margin_m) and 0 <= self.margin_m <= MAX_BOARD_M):
            raise ValueError(f"BoardSpec.margin_m must be >= 0 and <= {MAX_BOARD_M:g} m, got {self.margin_m!r}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's pattern size: inner corners ``(nx, ny)`` = ``(squares_x - 1, squares_y - 1)``."""
        return (self.squares_x - 1, self.squares_y - 1)

    @property
    def half_extent_m(self) -> tuple[float, float]:
        """Half width and half height of the printed area including the margin, metres."""
        return (
            0.5 * self.squares_x * self.square_m + self.margin_m,
            0.5 * self.squares_y * self.square_m + self.margin_m,
        )

    def inner_corners_board_m(self) -> np.ndarray:
        """Inner corners in the board frame ``(K, 3)``, ``K = nx · ny``, row-major (x fastest), z = 0."""
        nx, ny = self.pattern_size
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        x = (i.ravel() - 0.5 * (nx - 1)) * self.square_m
        y = (j.ravel() - 0.5 * (ny - 1)) * self.square_m
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    def square_centres_board_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres of all squares ``(S, 3)`` (z = 0) and whether each is black ``(S,)``."""
        a, b = np.meshgrid(np.arange(self.squares_x), np.arange(self.squares_y))
        a, b = a.ravel(), b.ravel()
        x = (a + 0.5 - 0.5 * self.squares_x) * self.square_m
        y = (b + 0.5 - 0.5 * self.squares_y) * self.square_m
        return np.stack([x, y, np.zeros_like(x)], axis=1), (a + b) % 2 == 0

    def outline_board_m(self, samples_per_edge: int = 1) -> np.ndarray:
        """Points on the outer boundary (margin included), board frame ``(4 · samples_per_edge, 3)``."""
        hx, hy = self.half_extent_m
        corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        f = np.arange(samples_per_edge)[:, None] / samples_per_edge
        pts = np.concatenate([corners[k] + f * (corners[(k + 1) % 4] - corners[k]) for k in range(4)])
        return np.concatenate([pts, np.zeros((pts.shape[0], 1))], axis=1)


def _default_needle_T_board() -> np.ndarray:
    """Build :data:`DEFAULT_NEEDLE_T_BOARD` (see its description)."""
    tilt = math.radians(15.0)
    toward = math.radians(-60.0)
    w = np.array([math.cos(toward), math.sin(toward), 0.0])
    z_b = math.cos(tilt) * np.array([0.0, 0.0, 1.0]) + math.sin(tilt) * w
    x_b = np.cross(np.array([0.0, 0.0, 1.0]), w)  # the tilt axis, in the needle plane
    y_b = np.cross(z_b, x_b)
    centre_angle = math.radians(-112.5)  # opposite the middle of the default 0..135 deg arc
    T = np.eye(4)
    T[:3, :3] = np.stack([x_b, y_b, z_b], axis=1)
    T[:3, 3] = 0.0065 * np.array([math.cos(centre_angle), math.sin(centre_angle), 0.0])
    return T


#: Where the board sits in the needle frame in the simulator, ``needle_T_board`` (4, 4).
#:
#: * Centre 6.5 mm from the needle-circle centre in the needle plane, at the angle -112.5°,
#:   i.e. opposite the middle of the default arc (tail 0°, tip 135°): the arc stays ~4 mm
#:   or more from the board's outline, so in typical views the two do not overlap.
#: * Printed face towards the needle's ``−z`` half-space (board ``+z`` ≈ needle ``+z``): a
#:   camera that sees the needle with its ``+z`` axis pointing away — the simulator's
#:   convention — sees the board.
#: * Tilted 15° out of the needle plane, board ``z = cos 15° ẑ + sin 15° ŵ`` with ``ŵ`` the
#:   in-plane direction at -60° (close to ``−t̂(θ_g)``, the direction a camera looks along
#:   when the needle, turned in the grasp about the grasper's radial axis, is seen edge-on);
#:   board ``x = ẑ × ŵ``. A larger tilt keeps edge-on views detectable but makes ordinary
#:   views (needle normal 35-50° off the viewing ray) too oblique; 15° towards -60° was chosen
#:   on the simulator's five scenarios (board within 65° of face-on, inside the image and
#:   clear of the arc in 100 % of the slow/normal/suturing frames, ~90 % of calibration and
#:   ~75 % of rotation frames, where the remaining ones are the edge-on stretches).
DEFAULT_NEEDLE_T_BOARD: np.ndarray = _default_needle_T_board()
DEFAULT_NEEDLE_T_BOARD.setflags(write=False)


def _check_pose(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite (4, 4) pose, got shape {T.shape}")
    return T


def _board_to_camera(cam_T_board: np.ndarray, points_board_m: np.ndarray) -> np.ndarray:
    return points_board_m @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]


def board_visible(
    camera: PinholeCamera,
    cam_T_board: np.ndarray,
    spec: BoardSpec | None = None,
    max_obliquity_deg: float = 60.0,
    min_square_px: float = 6.0,
    margin_px: float = 2.0,
) -> bool:
    """Whether the board can be expected to be detected in an image of this camera.

    True when the printed face looks at the camera at most ``max_obliquity_deg`` off its
    normal (angle between the board's ``+z`` and the ray to its centre; :func:`detect_board`
    is reliable to ~60° and finds most boards to ~68°), the whole outline
    (margin included, distorted) lies in front of the camera and inside the image by
    ``margin_px``, and the squares are not smaller than ``min_square_px`` (the shortest
    projected distance between neighbouring inner corners).
    """
    spec = spec or BoardSpec()
    T = _check_pose("cam_T_board", cam_T_board)
    centre = T[:3, 3]
    dist = float(np.linalg.norm(centre))
    if dist <= 0:
        return False
    cos_obl = float(T[:3, 2] @ centre) / dist
    if cos_obl < math.cos(math.radians(max_obliquity_deg)):
        return False
    outline = _board_to_camera(T, spec.outline_board_m(8))
    if np.any(outline[:, 2] <= 1e-4):
        return False
    outline_px = camera.distort_px(camera.project(outline))
    if not np.all(camera.in_image(outline_px, margin_px=margin_px)):
        return False
    nx, ny = spec.pattern_size
    grid = camera.project(_board_to_camera(T, spec.inner_corners_board_m())).reshape(ny, nx, 2)
    step_x = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    step_y = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
    return bool(min(step_x.min(), step_y.min()) >= min_square_px)


def render_board(
    image_bgr: np.ndarray,
    camera: PinholeCamera,
    cam_T_board: np.ndarray,
    spec: BoardSpec | None = None,
    supersample: int = 4,
) -> np.ndarray:
    """Draw the board into a copy of ``image_bgr`` ``(H, W, 3)`` or ``(H, W)`` uint8, anti-aliased.

    Per pixel ``p`` of the board's bounding box: ``X_b = H⁻¹ undistort(p)`` (homogeneous,
    valid when its last entry — the inverse depth — is positive), then for each of the
    ``supersample²`` sub-pixels the board colour (square ``(⌊x/s + n_x/2⌋, ⌊y/s + n_y/2⌋)``,
    black when the indices sum to an even number; white margin) or the background; the
    pixel is the mean of its sub-pixels. Returns the image unchanged (copied) when the board
    is behind the camera, shows its back, or falls outside the image.
    """
    spec = spec or BoardSpec()
    T = _check_pose("cam_T_board", cam_T_board)
    img = np.asarray(image_bgr)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"image_bgr must be an (H, W, 3) or (H, W) uint8 image, got {img.dtype} {img.shape}")
    if camera.width is not None and camera.height is not None and img.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} but the camera is {camera.width}x{camera.height}")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    out = img.copy()
    outline = _board_to_camera(T, spec.outline_board_m(16))
    if np.any(outline[:, 2] <= 1e-4) or float(T[:3, 2] @ T[:3, 3]) <= 0.0:
        return out  # behind the camera, or its back faces the camera
    outline_px = camera.distort_px(camera.project(outline))
    h, w = img.shape[:2]
    u0 = max(int(math.floor(outline_px[:, 0].min())) - 2, 0)
    u1 = min(int(math.ceil(outline_px[:, 0].max())) + 2, w - 1)
    v0 = max(int(math.floor(outline_px[:, 1].min())) - 2, 0)
    v1 = min(int(math.ceil(outline_px[:, 1].max())) + 2, h - 1)
    if u1 < u0 or v1 < v0:
        return out
    # board-plane coordinates at the pixel centres of the box, with a one-pixel apron for interpolation
    uu, vv = np.meshgrid(np.arange(u0 - 1, u1 + 2, dtype=float), np.arange(v0 - 1, v1 + 2, dtype=float))
    und = camera.undistort_px(np.stack([uu.ravel(), vv.ravel()], axis=1))
    H = camera.K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
    q = np.column_stack([und, np.ones(und.shape[0])]) @ np.linalg.inv(H).T
    inv_depth = q[:, 2]
    ok = inv_depth > 1e-9
    far = 1e3  # metres: a sentinel far outside any board
    xb = np.where(ok, q[:, 0] / np.where(ok, inv_depth, 1.0), far).reshape(uu.shape).astype(np.float32)
    yb = np.where(ok, q[:, 1] / np.where(ok, inv_depth, 1.0), far).reshape(uu.shape).astype(np.float32)
    # cv2.resize(INTER_LINEAR) by s samples the input at ((k + 0.5) / s - 0.5): the sub-pixel centres
    big = (xb.shape[1] * s, xb.shape[0] * s)
    xs = cv2.resize(xb, big, interpolation=cv2.INTER_LINEAR)[s:-s, s:-s].astype(float)
    ys = cv2.resize(yb, big, interpolation=cv2.INTER_LINEAR)[s:-s, s:-s].astype(float)
    hx, hy = spec.half_extent_m
    inside = (np.abs(xs) <= hx) & (np.abs(ys) <= hy)
    a = np.floor(xs / spec.square_m + 0.5 * spec.squares_x)
    b = np.floor(ys / spec.square_m + 0.5 * spec.squares_y)
    in_squares = (a >= 0) & (a < spec.squares_x) & (b >= 0) & (b < spec.squares_y)
    black = in_squares & (np.mod(a + b, 2) == 0)
    level = np.where(black, BLACK_LEVEL, WHITE_LEVEL)
    bh, bw = v1 - v0 + 1, u1 - u0 + 1
    cover = inside.reshape(bh, s, bw, s).mean(axis=(1, 3))
    board_sum = np.where(inside, level, 0.0).reshape(bh, s, bw, s).mean(axis=(1, 3))
    patch = out[v0 : v1 + 1, u0 : u1 + 1].astype(float)
    if patch.ndim == 3:
        blended = patch * (1.0 - cover)[..., None] + board_sum[..., None]
    else:
        blended = patch * (1.0 - cover) + board_sum
    out[v0 : v1 + 1, u0 : u1 + 1] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
    return out


def _gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image from ``(H, W)``, ``(H, W, 1)``, BGR ``(H, W, 3)`` or BGRA ``(H, W, 4)``, uint8/uint16/float."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise ValueError(f"image must be (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}")
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(np.rint(img.astype(float)), 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(img)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def _orient_corners(
    gray: np.ndarray, camera: PinholeCamera, corners_px: np.ndarray, spec: BoardSpec, min_contrast: float
) -> np.ndarray | None:
    """Reorder detected corners ``(K, 2)`` to the board's own row-major order, or None if undecidable.

    Of the four orderings of the grid (as found, 180° turned, mirrored in x, mirrored in y)
    the mirrored ones are rejected by handedness (the printed face must look at the camera:
    the image cross product of the grid's x and y directions is positive, image axes being
    x right, y down), and of the other two the one whose predicted black squares are darker
    (by at least ``min_contrast`` grey levels) than its white squares is kept.
    """
    nx, ny = spec.pattern_size
    grid = corners_px.reshape(ny, nx, 2)
    board_xy = spec.inner_corners_board_m()[:, :2]
    centres_m, is_black = spec.square_centres_board_m()
    h, w = gray.shape
    best, best_score = None, -np.inf
    for cand in (grid, grid[::-1, ::-1], grid[:, ::-1], grid[::-1, :]):
        pts = cand.reshape(-1, 2)
        und = camera.undistort_px(pts)
        g = und.reshape(ny, nx, 2)
        ex, ey = g[0, -1] - g[0, 0], g[-1, 0] - g[0, 0]
        if ex[0] * ey[1] - ex[1] * ey[0] <= 0:
            continue
        Hb, _ = cv2.findHomography(board_xy, und, 0)
        if Hb is None:
            continue
        c = np.column_stack([centres_m[:, :2], np.ones(len(centres_m))]) @ Hb.T
        c_px = camera.distort_px(c[:, :2] / c[:, 2:3])
        if not np.all(camera.in_image(c_px)):
            continue
        u = np.clip(c_px[:, 0], 0, w - 1).astype(np.float32)
        v = np.clip(c_px[:, 1], 0, h - 1).astype(np.float32)
        vals = cv2.remap(gray, u[None, :], v[None, :], cv2.INTER_LINEAR)[0].astype(float)
        score = vals[~is_black].mean() - vals[is_black].mean()
        if score > best_score:
            best, best_score = pts, score
    if best is None or best_score < min_contrast:
        return None
    return best


#: findChessboardCorners flag sets tried in turn. CALIB_CB_FAST_CHECK is not used: it rejects
#: valid boards seen 65-70° off face-on.
_DETECT_FLAGS = (0, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
#: Fewest pixels per square (plus one square of margin on each side) an image side must offer for a detection to be
#: tried: a smaller image cannot show the board, and below 15 px OpenCV's adaptive threshold failed an assertion
#: (``blockSize % 2 == 1 && blockSize > 1``: a cv2.error traceback from ``groundtruth`` on a run of tiny images).
MIN_PX_PER_SQUARE = 4


def detect_board_corners(
    image: np.ndarray, camera: PinholeCamera, spec: BoardSpec | None = None, min_contrast: float = 20.0
) -> np.ndarray | None:
    """Inner corners of the board ``(K, 2)`` in (distorted) image pixels, in the board's order, or None.

    ``cv2.findChessboardCorners`` (first with a global threshold, ~15 ms on a 1080² image
    with or without a board; then, if that fails, with adaptive thresholding and
    normalisation, ~100 ms, which copes with uneven lighting), refined by
    ``cv2.cornerSubPix`` with a window of about a third of the projected square, then
    oriented (see :func:`_orient_corners`). An image whose shorter side is under :data:`MIN_PX_PER_SQUARE` px per
    square of the board's shorter side plus two squares is not searched (None).
    """
    spec = spec or BoardSpec()
    gray = _gray(image)
    if min(gray.shape[:2]) < MIN_PX_PER_SQUARE * (min(spec.squares_x, spec.squares_y) + 2):
        return None  # too small to show the board (MIN_PX_PER_SQUARE)
    found, corners = False, None
    for flags in _DETECT_FLAGS:
        found, corners = cv2.findChessboardCorners(gray, spec.pattern_size, flags=flags)
        if found and corners is not None:
            break
    if not found or corners is None:
        return None
    nx, ny = spec.pattern_size
    grid = corners.reshape(ny, nx, 2).astype(float)
    step = min(
        np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(), np.linalg.norm(np.diff(grid, axis=0), axis=-1).min()
    )
    half = int(np.clip(round(0.33 * step), 2, 10))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    refined = cv2.cornerSubPix(gray, corners.astype(np.float32), (half, half), (-1, -1), criteria)
    return _orient_corners(gray, camera, refined.reshape(-1, 2).astype(float), spec, min_contrast)


def detect_board(
    image: np.ndarray, camera: PinholeCamera, spec: BoardSpec | None = None, max_rms_px: float = 1.0
) -> np.ndarray | None:
    """``cam_T_board`` (4, 4) from one image, or None when the board is not found reliably.

    Corners from :func:`detect_board_corners`; ``cv2.solvePnPGeneric`` with IPPE gives the
    two planar solutions, the one with the lower reprojection error is refined by
    ``cv2.solvePnPRefineLM`` (camera ``K`` and distortion). None when no corners, when the
    refined RMS reprojection error exceeds ``max_rms_px``, or when the pose would show the
    board's back.
    """
    spec = spec or BoardSpec()
    corners = detect_board_corners(image, camera, spec)
    if corners is None:
        return None
    obj = spec.inner_corners_board_m()
    K, dist = camera.K, camera.dist_coeffs()
    img_pts = corners.reshape(-1, 1, 2)
    n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img_pts, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        return None
    k = int(np.argmin(np.asarray(errs).ravel()))
    rvec, tvec = cv2.solvePnPRefineLM(obj, img_pts, K, dist, rvecs[k].copy(), tvecs[k].copy())
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - corners) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    if rms > max_rms_px or float(T[:3, 2] @ T[:3, 3]) <= 0.0:
        return None
    return T
