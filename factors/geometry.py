"""Camera and needle models (DESIGN.md §Conventions).

* :class:`PinholeCamera` — intrinsics ``K`` plus OpenCV's (k1, k2, p1, p2, k3) distortion.
  Pixels are ``(u, v)`` = (column, row) with pixel centres at integer coordinates. Residuals
  use the ideal pinhole ``K``; observed pixels are undistorted first (:meth:`undistort_px`).
* :class:`NeedleModel` — an arc of the circle of radius ``r`` centred at the needle-frame
  origin in its x-y plane: ``P(theta) = r (cos theta, sin theta, 0)``, unit tangent
  ``t(theta) = (-sin theta, cos theta, 0)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


def _finite_float(name: str, value: object, positive: bool = False) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x!r}")
    if positive and x <= 0:
        raise ValueError(f"{name} must be > 0, got {x!r}")
    return x


def _float_array(name: str, value: object) -> np.ndarray:
    """``np.asarray(value, dtype=float)``, or ValueError naming ``name`` (NumPy's says only "could not convert")."""
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers, got {value!r:.80}") from exc


def as_points_px(name: str, points: object, dims: int = 2) -> np.ndarray:
    """Validate an ``(M, dims)`` finite float array (a single point ``(dims,)`` becomes ``(1, dims)``)."""
    arr = _float_array(name, points)
    if arr.ndim == 1 and arr.shape[0] == dims:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dims:
        raise ValueError(f"{name} must have shape (M, {dims}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def as_vector(name: str, value: object, dims: int) -> np.ndarray:
    """Validate a finite float vector of shape ``(dims,)``."""
    arr = _float_array(name, value)
    arr = arr.reshape(-1) if arr.ndim <= 1 else arr
    if arr.shape != (dims,):
        raise ValueError(f"{name} must have shape ({dims},), got {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics with optional OpenCV distortion."""

    fx: float
    """Focal length along u, pixels."""
    fy: float
    """Focal length along v, pixels."""
    cx: float
    """Principal point u, pixels."""
    cy: float
    """Principal point v, pixels."""
    width: int | None = None
    """Image width in pixels (None: unknown)."""
    height: int | None = None
    """Image height in pixels (None: unknown)."""
    distortion: tuple[float, ...] | None = None
    """OpenCV (k1, k2, p1, p2, k3); None or all zeros means no distortion."""

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            object.__setattr__(self, name, _finite_float(name, getattr(self, name), positive=True))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _finite_float(name, getattr(self, name)))
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None:
                iv = int(_finite_float(name, v, positive=True))
                if iv != float(v):
                    raise ValueError(f"{name} must be a whole number of pixels, got {v!r}")
                object.__setattr__(self, name, iv)
        if self.distortion is not None:
            d = np.asarray(self.distortion, dtype=float).reshape(-1)
            if d.shape[0] not in (4, 5, 8, 12, 14):
                raise ValueError(f"distortion must have 4, 5, 8, 12 or 14 OpenCV coefficients, got {d.shape[0]}")
            if not np.all(np.isfinite(d)):
                raise ValueError("distortion contains NaN or infinite values")
            object.__setattr__(self, "distortion", tuple(float(x) for x in d))

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return self.distortion is not None and any(abs(c) > 0 for c in self.distortion)

    def dist_coeffs(self) -> np.ndarray:
        """Distortion coefficients as OpenCV expects them (zeros when there is none)."""
        if self.distortion is None:
            return np.zeros(5)
        return np.asarray(self.distortion, dtype=float)

    def undistort_px(self, points_px: np.ndarray) -> np.ndarray:
        """Remove lens distortion from observed pixels ``(M, 2)`` -> ideal-pinhole pixels ``(M, 2)``.

        OpenCV's iterative inverse of its own model (``cv2.undistortPoints`` with ``P = K``);
        without distortion the input is returned unchanged (copied).
        """
        pts = as_points_px("points_px", points_px)
        if not self.has_distortion or pts.shape[0] == 0:
            return pts.copy()
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        src = pts.reshape(-1, 1, 2)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            out = cv2.undistortPointsIter(src, self.K, self.dist_coeffs(), None, self.K, criteria)
        else:  # OpenCV 5.x folded the iterative variant into undistortPoints
            out = cv2.undistortPoints(src, self.K, self.dist_coeffs(), R=None, P=self.K, criteria=criteria)
        return out.reshape(-1, 2).astype(float)

    def distort_px(self, points_px: np.ndarray) -> np.ndarray:
        """Apply lens distortion to ideal-pinhole pixels ``(M, 2)`` (the forward OpenCV model)."""
        pts = as_points_px("points_px", points_px)
        if not self.has_distortion or pts.shape[0] == 0:
            return pts.copy()
        x = (pts[:, 0] - self.cx) / self.fx
        y = (pts[:, 1] - self.cy) / self.fy
        rays = np.stack([x, y, np.ones_like(x)], axis=1)
        out, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist_coeffs())
        return out.reshape(-1, 2).astype(float)

    def project(self, points_cam_m: np.ndarray) -> np.ndarray:
        """Ideal pinhole projection of camera-frame points ``(..., 3)`` -> pixels ``(..., 2)``."""
        p = np.asarray(points_cam_m, dtype=float)
        z = p[..., 2]
        return np.stack([self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy], axis=-1)

    def in_image(self, points_px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (True everywhere when the size is unknown)."""
        p = np.asarray(points_px, dtype=float)
        if self.width is None or self.height is None:
            return np.ones(p.shape[:-1], dtype=bool)
        u, v = p[..., 0], p[..., 1]
        return (
            (u >= -0.5 + margin_px)
            & (u <= self.width - 0.5 - margin_px)
            & (v >= -0.5 + margin_px)
            & (v <= self.height - 0.5 - margin_px)
        )


#: Smallest needle radius accepted, metres. Surgical needles run from ~1 mm (ophthalmic) up; a radius below
#: 0.1 mm is a unit mistake (mm or um typed as m), and tracking it puts the needle at a depth of nanometres.
MIN_NEEDLE_RADIUS_M = 1e-4
#: Thinnest wire accepted, metres (the finest suture needles' wire is ~30 um).
MIN_WIRE_DIAMETER_M = 1e-6


@dataclass(frozen=True)
class NeedleModel:
    """A circular suture needle: an arc of the needle-frame circle of radius ``radius_m``.

    Physically possible only (``ValueError`` otherwise): finite numbers, a radius of at least
    :data:`MIN_NEEDLE_RADIUS_M` and a wire of at least :data:`MIN_WIRE_DIAMETER_M`, an arc of
    non-zero length shorter than a full circle, the grasp angle on the arc (from the tail towards the tip,
    mod 2 pi; its ends included) and a wire thinner than twice the radius.
    """

    radius_m: float = 0.0045
    """Radius of curvature, metres (4-0 P-3: 4.5 mm)."""
    tail_angle_rad: float = 0.0
    """Arc angle of the tail (swaged end), radians."""
    tip_angle_rad: float = 3.0 * math.pi / 4.0
    """Arc angle of the tip, radians (3/8 circle from the tail)."""
    grasp_angle_rad: float = math.pi / 4.0
    """Arc angle of the grasp point held by the C-Lock, radians."""
    wire_diameter_m: float = 0.0004
    """Wire diameter, metres (only used to render masks)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius_m", _finite_float("radius_m", self.radius_m, positive=True))
        object.__setattr__(
            self, "wire_diameter_m", _finite_float("wire_diameter_m", self.wire_diameter_m, positive=True)
        )
        for name in ("tail_angle_rad", "tip_angle_rad", "grasp_angle_rad"):
            object.__setattr__(self, name, _finite_float(name, getattr(self, name)))
        for name, least in (("radius_m", MIN_NEEDLE_RADIUS_M), ("wire_diameter_m", MIN_WIRE_DIAMETER_M)):
            if getattr(self, name) < least:
                raise ValueError(f"{name} {getattr(self, name):.6g} is below {least:g} m (a unit mistake?)")
        arc = abs(self.tip_angle_rad - self.tail_angle_rad)
        if arc < 1e-9:
            raise ValueError("tip_angle_rad and tail_angle_rad must differ (the arc has zero length)")
        if arc >= 2.0 * math.pi:
            raise ValueError(f"the arc from tail_angle_rad to tip_angle_rad spans {arc:.6g} rad, a full circle or more "
                             "(the wire would overlap itself)")
        # the grasper holds the wire: the grasp angle lies on the arc, taken from the tail towards the tip mod 2 pi
        towards_tip = math.copysign(1.0, self.tip_angle_rad - self.tail_angle_rad)
        along = (towards_tip * (self.grasp_angle_rad - self.tail_angle_rad)) % (2.0 * math.pi)
        if arc + 1e-9 < along < 2.0 * math.pi - 1e-9:  # (a hair before the tail is the tail, round-off)
            raise ValueError(f"grasp_angle_rad {self.grasp_angle_rad:.6g} is not on the arc from tail_angle_rad "
                             f"{self.tail_angle_rad:.6g} to tip_angle_rad {self.tip_angle_rad:.6g} (mod 2 pi)")
        if self.wire_diameter_m >= 2.0 * self.radius_m:
            raise ValueError(f"wire_diameter_m {self.wire_diameter_m:.6g} is at least twice radius_m "
                             f"{self.radius_m:.6g} (no wire bends that tightly)")

    def point(self, theta: float | np.ndarray) -> np.ndarray:
        """Needle-frame point(s) at arc angle ``theta``: ``r (cos, sin, 0)``, shape ``(..., 3)``."""
        th = np.asarray(theta, dtype=float)
        return self.radius_m * np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=-1)

    def tangent(self, theta: float | np.ndarray) -> np.ndarray:
        """Unit needle-frame tangent(s) at ``theta``: ``(-sin, cos, 0)``, shape ``(..., 3)``."""
        th = np.asarray(theta, dtype=float)
        return np.stack([-np.sin(th), np.cos(th), np.zeros_like(th)], axis=-1)

    @property
    def tip_m(self) -> np.ndarray:
        """Tip point in the needle frame, metres."""
        return self.point(self.tip_angle_rad)

    @property
    def tail_m(self) -> np.ndarray:
        """Tail point in the needle frame, metres."""
        return self.point(self.tail_angle_rad)

    @property
    def grasp_m(self) -> np.ndarray:
        """Grasp point in the needle frame, metres."""
        return self.point(self.grasp_angle_rad)

    @property
    def grasp_tangent(self) -> np.ndarray:
        """Unit tangent at the grasp point in the needle frame."""
        return self.tangent(self.grasp_angle_rad)

    def arc_angles(self, count: int) -> np.ndarray:
        """``count`` angles evenly spaced from the tail to the tip (inclusive)."""
        return np.linspace(self.tail_angle_rad, self.tip_angle_rad, int(count))

    def arc_points(self, count: int) -> np.ndarray:
        """``count`` needle-frame points evenly spaced along the arc, ``(count, 3)``."""
        return self.point(self.arc_angles(count))


def pose_from_xyz_quat(xyz_m: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """Homogeneous ``(..., 4, 4)`` from translations ``(..., 3)`` and Hamilton quaternions ``(..., 4)``."""
    from factors.lie import quat_wxyz_to_rotation

    xyz = np.asarray(xyz_m, dtype=float)
    R = quat_wxyz_to_rotation(quat_wxyz)
    T = np.zeros(xyz.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = xyz
    T[..., 3, 3] = 1.0
    return T


def xyz_quat_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pose_from_xyz_quat`: ``(..., 4, 4)`` -> ``(..., 3)``, ``(..., 4)`` (w >= 0)."""
    from factors.lie import rotation_to_quat_wxyz

    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), rotation_to_quat_wxyz(T[..., :3, :3])
