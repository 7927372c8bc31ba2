"""The ground-truth checkerboard: model, rendering, detection, orientation (pinpoint_fg.checkerboard)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import so3_exp, so3_log
from pinpoint_fg.checkerboard import (
    BLACK_LEVEL,
    DEFAULT_NEEDLE_T_BOARD,
    WHITE_LEVEL,
    BoardSpec,
    board_visible,
    detect_board,
    detect_board_corners,
    render_board,
)

CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080, (-0.05, 0.01, 0.0, 0.0, 0.0))
SPEC = BoardSpec()


def _rot_z(a: float) -> np.ndarray:
    return so3_exp(np.array([0.0, 0.0, a]))


def _board_pose(rng: np.random.Generator, max_tilt_deg: float = 60.0) -> np.ndarray:
    """A visible board pose: face tilted up to max_tilt_deg from the optical axis, any in-plane angle."""
    while True:
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= np.linalg.norm(axis)
        T = np.eye(4)
        tilt = so3_exp(axis * math.radians(rng.uniform(0.0, max_tilt_deg)))
        T[:3, :3] = tilt @ _rot_z(rng.uniform(-math.pi, math.pi))
        T[:3, 3] = [rng.uniform(-0.012, 0.012), rng.uniform(-0.012, 0.012), rng.uniform(0.030, 0.060)]
        if board_visible(CAM, T):
            return T


def _background(rng: np.random.Generator) -> np.ndarray:
    low = rng.normal(0.0, 1.0, (12, 12, 3)).astype(np.float32)
    smooth = cv2.resize(low, (1080, 1080), interpolation=cv2.INTER_CUBIC)
    img = np.array([105.0, 115.0, 185.0], np.float32) + 20.0 * smooth
    return np.clip(img, 0, 255).astype(np.uint8)


def _photo(rng: np.random.Generator, T: np.ndarray, background: np.ndarray) -> np.ndarray:
    img = render_board(background, CAM, T)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    t_mm = 1e3 * float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    r_deg = math.degrees(float(np.linalg.norm(so3_log(T_true[:3, :3].T @ T_est[:3, :3]))))
    return t_mm, r_deg


def test_board_spec_geometry() -> None:
    assert SPEC.pattern_size == (4, 3)
    c = SPEC.inner_corners_board_m()
    assert c.shape == (12, 3)
    np.testing.assert_allclose(c.mean(axis=0), 0.0, atol=1e-15)
    np.testing.assert_allclose(c[1] - c[0], [0.001, 0.0, 0.0])  # row-major, x fastest
    np.testing.assert_allclose(c[4] - c[0], [0.0, 0.001, 0.0])
    centres, black = SPEC.square_centres_board_m()
    assert centres.shape == (20, 3) and black.sum() == 10 and black[0]
    with pytest.raises(ValueError, match="odd"):
        BoardSpec(squares_x=4, squares_y=4)
    with pytest.raises(ValueError, match=">= 4"):
        BoardSpec(squares_x=4, squares_y=3)


def test_render_is_antialiased_and_local() -> None:
    T = np.eye(4)
    T[:3, :3] = _rot_z(0.3)
    T[:3, 3] = [0.0, 0.0, 0.04]
    bg = np.full((1080, 1080, 3), 100, np.uint8)
    img = render_board(bg, CAM, T)
    assert img is not bg and np.all(bg == 100)  # a new image, the input untouched
    changed = np.any(img != 100, axis=2)
    rows, cols = np.nonzero(changed)
    # the printed area (7 x 6 mm at 40 mm ~ 160 x 135 px) around the principal point, nothing elsewhere
    assert 400 < cols.min() and cols.max() < 680 and 400 < rows.min() and rows.max() < 680
    grey = img[..., 0].astype(float)[changed]
    assert np.any(np.abs(grey - BLACK_LEVEL) < 1) and np.any(np.abs(grey - WHITE_LEVEL) < 1)
    mixed = (grey > BLACK_LEVEL + 20) & (grey < WHITE_LEVEL - 20) & (np.abs(grey - 100) > 5)
    assert mixed.sum() > 100  # partially covered pixels along the square edges (anti-aliasing)
    # grey input works too, and a board seen from behind draws nothing
    assert render_board(bg[..., 0], CAM, T).shape == (1080, 1080)
    back = T.copy()
    back[:3, :3] = T[:3, :3] @ so3_exp(np.array([math.pi, 0.0, 0.0]))
    np.testing.assert_array_equal(render_board(bg, CAM, back), bg)


def test_detect_recovers_known_poses() -> None:
    rng = np.random.default_rng(7)
    bg = _background(rng)
    t_err, r_err = [], []
    for _ in range(12):
        T = _board_pose(rng)
        est = detect_board(_photo(rng, T, bg), CAM, SPEC)
        assert est is not None
        t_mm, r_deg = _errors(est, T)
        t_err.append(t_mm)
        r_err.append(r_deg)
    t_err, r_err = np.array(t_err), np.array(r_err)
    print(f"checkerboard PnP error: translation mean {t_err.mean():.4f} max {t_err.max():.4f} mm, "
          f"rotation mean {r_err.mean():.3f} max {r_err.max():.3f} deg")
    assert t_err.max() < 0.15 and r_err.max() < 1.5  # no flipped/mirrored solution (those are mm and 180 deg off)
    assert t_err.mean() < 0.05 and r_err.mean() < 0.4


def test_orientation_is_resolved_for_every_in_plane_angle() -> None:
    rng = np.random.default_rng(11)
    bg = _background(rng)
    base = np.eye(4)
    base[:3, :3] = so3_exp(np.array([0.5, -0.2, 0.0]))
    base[:3, 3] = [0.002, -0.003, 0.042]
    truth_px = None
    for deg in range(0, 360, 45):
        T = base.copy()
        T[:3, :3] = base[:3, :3] @ _rot_z(math.radians(deg))
        img = _photo(rng, T, bg)
        corners = detect_board_corners(img, CAM, SPEC)
        truth_px = CAM.distort_px(CAM.project(SPEC.inner_corners_board_m() @ T[:3, :3].T + T[:3, 3]))
        assert corners is not None
        assert np.abs(corners - truth_px).max() < 0.5, f"in-plane angle {deg}: corners in the wrong order"
        est = detect_board(img, CAM, SPEC)
        assert est is not None and _errors(est, T)[1] < 1.5
    # the same board turned by 180 degrees (same corner positions as a set) is told apart by its colours
    flipped = base.copy()
    flipped[:3, :3] = base[:3, :3] @ _rot_z(math.pi)
    a = detect_board(_photo(rng, base, bg), CAM, SPEC)
    b = detect_board(_photo(rng, flipped, bg), CAM, SPEC)
    assert a is not None and b is not None
    assert _errors(a, base)[1] < 1.5 and _errors(b, flipped)[1] < 1.5
    assert _errors(a, b)[1] > 170.0


def test_board_not_visible_gives_none() -> None:
    rng = np.random.default_rng(5)
    bg = _background(rng)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.04]
    assert board_visible(CAM, T)
    cases = {
        "behind the camera": np.diag([1.0, 1.0, 1.0, 1.0]) @ np.array(
            [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -0.04], [0, 0, 0, 1.0]]
        ),
        "back side": np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0.04], [0, 0, 0, 1.0]]),
        "outside the image": np.array([[1, 0, 0, 0.05], [0, 1, 0, 0], [0, 0, 1, 0.04], [0, 0, 0, 1.0]]),
        "edge-on": np.block([[so3_exp(np.array([math.radians(88.0), 0, 0])), np.array([[0], [0], [0.04]])],
                             [np.zeros((1, 3)), np.ones((1, 1))]]),
    }
    for name, Tc in cases.items():
        assert not board_visible(CAM, Tc), name
        assert detect_board(_photo(rng, Tc, bg), CAM, SPEC) is None, name
    assert detect_board(bg, CAM, SPEC) is None
    # too small (far away) is not visible either
    far = T.copy()
    far[2, 3] = 0.5
    assert not board_visible(CAM, far)


def test_default_mount_is_a_sensible_rigid_transform() -> None:
    T = np.asarray(DEFAULT_NEEDLE_T_BOARD)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    assert 0.004 < np.linalg.norm(T[:3, 3]) < 0.010  # a few mm beside the needle circle
    needle = NeedleModel()
    # a typical view: needle 40 mm away, its normal 40 deg off the optical axis (+z away from the camera)
    rng = np.random.default_rng(2)
    for _ in range(10):
        cam_T_needle = np.eye(4)
        cam_T_needle[:3, :3] = _rot_z(rng.uniform(-math.pi, math.pi)) @ so3_exp(
            np.array([math.radians(40.0), 0, 0])
        ) @ _rot_z(rng.uniform(-math.pi, math.pi))
        cam_T_needle[:3, 3] = [0.0, 0.0, 0.04]
        cam_T_board = cam_T_needle @ T
        if not board_visible(CAM, cam_T_board, max_obliquity_deg=75.0):
            continue
        # the board's printed area does not cover the needle arc in the image
        poly = CAM.project(SPEC.outline_board_m(1) @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]).astype(np.float32)
        arc = CAM.project(needle.arc_points(50) @ cam_T_needle[:3, :3].T + cam_T_needle[:3, 3])
        inside = [cv2.pointPolygonTest(poly, (float(u), float(v)), False) for u, v in arc]
        assert max(inside) < 0
    # face-on needle: the board is seen 15 deg off face-on
    cam_T_needle = np.eye(4)
    cam_T_needle[:3, 3] = [0.0, 0.0, 0.04]
    assert board_visible(CAM, cam_T_needle @ T, max_obliquity_deg=20.0)
