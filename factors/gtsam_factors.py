"""GTSAM factors wrapping the batched residuals of :mod:`factors.residuals`.

Each class is a ``gtsam.CustomFactor`` (hence a ``gtsam.NonlinearFactor`` usable in any
``NonlinearFactorGraph``) whose ``unwhitenedError(values)`` is exactly the residual of the
same-named function, evaluated for one pose, in the units stated there. GTSAM whitens with
the noise model you pass (any gtsam noise model of the right dimension, robust ones included).

Crash-proofing (GTSAM_NOTES.md §6): constructors check shapes, finiteness and the noise
dimension and raise ``ValueError`` naming the argument; the callbacks always assign a 2-D
float Jacobian of shape ``(rows, 6)`` for every key, never write into ``H`` in place, and
never return a Python float.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from factors import residuals as res
from factors.geometry import PinholeCamera, as_points_px, as_vector


def _check_noise(noise: object, dim: int) -> gtsam.noiseModel.Base:
    if not isinstance(noise, gtsam.noiseModel.Base):
        raise ValueError(f"noise must be a gtsam noise model, got {type(noise).__name__}")
    if noise.dim() != dim:
        raise ValueError(f"noise has dimension {noise.dim()}, this factor's residual has {dim}")
    return noise


def _check_key(name: str, key: object) -> int:
    if isinstance(key, bool) or not isinstance(key, (int, np.integer)):
        raise ValueError(f"{name} must be an integer gtsam key, got {key!r}")
    return int(key)


def _check_pose(name: str, pose: object) -> gtsam.Pose3:
    if isinstance(pose, gtsam.Pose3):
        m = pose.matrix()
    else:
        m = np.asarray(pose, dtype=float)
        if m.shape != (4, 4):
            raise ValueError(f"{name} must be a gtsam.Pose3 or a (4, 4) matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return gtsam.Pose3(gtsam.Rot3(m[:3, :3]), gtsam.Point3(*m[:3, 3]))


def _camera_K(camera: object) -> np.ndarray:
    if isinstance(camera, PinholeCamera):
        return camera.K
    K = np.asarray(camera, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError("camera must be a PinholeCamera or a finite (3, 3) intrinsic matrix")
    return K


def _reraise(exc: Exception) -> None:
    """Re-raise ``exc`` from a callback without GTSAM's temporaries in its traceback.

    ``this``, ``values`` and ``H`` are wrappers of C++ objects that die when the call unwinds;
    a traceback keeping them lets a later ``repr`` of its frames (pytest, IPython, a debugger)
    read freed memory and crash the interpreter. The callers clear those locals first; the
    traceback is reset so the frames below (which saw them too) are not kept either.
    """
    raise exc.with_traceback(None)


def _unary_residual(
    fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], dim: int, cam_T_needle: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    r, J = fn(np.asarray(cam_T_needle, dtype=float)[None])
    return r.reshape(dim), J.reshape(dim, 6)


def _unary_callback(fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], dim: int) -> Callable:
    """The GTSAM callback of a one-pose factor.

    It closes over ``fn`` and ``dim`` only, never over the factor object: the C++ factor owns the
    callback, so a callback holding the Python factor would make a reference cycle through C++
    that Python's garbage collector cannot see, and every factor ever built would stay alive
    (measured: the MAP tracker grew ~6 MB per 1000 frames, all of it dead factors).
    """

    def evaluate(this: gtsam.CustomFactor, values: gtsam.Values, H: object) -> np.ndarray:
        try:
            T = values.atPose3(this.keys()[0]).matrix()
            r, J = _unary_residual(fn, dim, T)
            if H is not None:
                H[0] = np.ascontiguousarray(J, dtype=float)
            return np.ascontiguousarray(r, dtype=float)
        except Exception as exc:
            this = values = H = None  # noqa: F841 - see _reraise
            _reraise(exc)

    return evaluate


class _UnaryPoseFactor(gtsam.CustomFactor):
    """A one-pose factor whose residual/Jacobian come from a batched function ``T (1,4,4) -> r, J``."""

    def __init__(
        self,
        noise: gtsam.noiseModel.Base,
        key: int,
        dim: int,
        fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    ) -> None:
        self._fn = fn
        self._dim = dim
        super().__init__(_check_noise(noise, dim), [_check_key("key", key)], _unary_callback(fn, dim))

    def residual(self, cam_T_needle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``(dim,)`` and Jacobian ``(dim, 6)`` at a ``(4, 4)`` pose (no GTSAM involved)."""
        return _unary_residual(self._fn, self._dim, cam_T_needle)


class KeypointFactor(_UnaryPoseFactor):
    """Keypoint reprojection ``pi(T X) - z`` (2 px) for a needle point ``X`` (metres, needle frame).

    ``measured_px`` must be undistorted (ideal pinhole) pixels.
    """

    def __init__(
        self,
        key: int,
        camera: PinholeCamera | np.ndarray,
        needle_point_m: np.ndarray,
        measured_px: np.ndarray,
        noise: gtsam.noiseModel.Base,
    ) -> None:
        K = _camera_K(camera)
        X = as_vector("needle_point_m", needle_point_m, 3)
        z = as_vector("measured_px", measured_px, 2)
        super().__init__(noise, key, 2, lambda T: res.keypoint_residual(T, K, X, z))


def _conic_inputs(camera: object, radius_m: float, points_px: np.ndarray, bias: float
                  ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Checked ``(K, points_px (M, 2), radius_m, bias)`` of a conic factor (ValueError on bad input)."""
    K = _camera_K(camera)
    pts = as_points_px("points_px", points_px)
    if pts.shape[0] == 0:
        raise ValueError("points_px must hold at least one backbone pixel")
    r_m = float(radius_m)
    if not np.isfinite(r_m) or r_m <= 0:
        raise ValueError(f"radius_m must be a positive finite number, got {radius_m!r}")
    b = float(bias)
    if not np.isfinite(b):
        raise ValueError("bias must be finite")
    return K, pts, r_m, b


class ConicFactor(_UnaryPoseFactor):
    """Sampson distances (M px) of M backbone pixels to the needle circle's image conic; one per frame.

    ``bias`` (px, default 0) is subtracted from every distance (a calibrated residual mean).
    """

    def __init__(
        self,
        key: int,
        camera: PinholeCamera | np.ndarray,
        radius_m: float,
        points_px: np.ndarray,
        noise: gtsam.noiseModel.Base,
        bias: float = 0.0,
    ) -> None:
        K, pts, r_m, b = _conic_inputs(camera, radius_m, points_px, bias)

        def fn(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            r, J = res.conic_residual(T, K, r_m, pts)
            return r - b, J

        super().__init__(noise, key, pts.shape[0], fn)


class _ConicCache:
    """All pixels' Sampson distances and Jacobians at the last pose asked for (one batched call per pose)."""

    def __init__(self, K: np.ndarray, radius_m: float, points_px: np.ndarray, bias: float) -> None:
        self._K, self._r, self._pts, self._b = K, radius_m, points_px, bias
        self._key: bytes | None = None
        self._rJ: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.ascontiguousarray(T, dtype=float).tobytes()
        if key != self._key or self._rJ is None:
            r, J = res.conic_residual(T, self._K, self._r, self._pts)
            self._rJ = (r[0] - self._b, J[0])
            self._key = key
        return self._rJ


class ConicPixelFactor(_UnaryPoseFactor):
    """The Sampson distance of ONE backbone pixel (1 px); see :func:`conic_pixel_factors`."""

    def __init__(self, key: int, cache: _ConicCache, index: int, noise: gtsam.noiseModel.Base) -> None:
        i = int(index)

        def fn(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            r, J = cache(T[0])
            return r[i : i + 1], J[i : i + 1]

        super().__init__(noise, key, 1, fn)


def conic_pixel_factors(
    key: int,
    camera: PinholeCamera | np.ndarray,
    radius_m: float,
    points_px: np.ndarray,
    noise: gtsam.noiseModel.Base,
    bias: float = 0.0,
) -> list[ConicPixelFactor]:
    """One 1-row factor per backbone pixel, each with the 1-D ``noise`` (typically a robust model).

    The per-pixel form of :class:`ConicFactor`: GTSAM weights a robust factor by the norm of its
    whole whitened vector, so a robust loss *per pixel* needs one factor per pixel. The sum of
    their errors and their stacked linearisations equal :class:`ConicFactor`'s when ``noise`` is
    the plain Gaussian. All the factors share one cache, so a graph linearised at one pose runs
    the batched :func:`factors.residuals.conic_residual` once, not once per pixel.
    """
    K, pts, r_m, b = _conic_inputs(camera, radius_m, points_px, bias)
    _check_noise(noise, 1)
    cache = _ConicCache(K, r_m, pts, b)
    return [ConicPixelFactor(key, cache, i, noise) for i in range(pts.shape[0])]


class GraspPositionFactor(_UnaryPoseFactor):
    """Grasp position ``T X_g - p_g`` (3 m, camera axes); ``p_g`` from kinematics."""

    def __init__(
        self, key: int, needle_point_m: np.ndarray, measured_cam_m: np.ndarray, noise: gtsam.noiseModel.Base
    ) -> None:
        X = as_vector("needle_point_m", needle_point_m, 3)
        p = as_vector("measured_cam_m", measured_cam_m, 3)
        super().__init__(noise, key, 3, lambda T: res.grasp_position_residual(T, X, p))


class GraspPerpendicularFactor(_UnaryPoseFactor):
    """Grasp perpendicularity ``z_g . (R t_g)`` (1, unitless); both directions normalised.

    ``bias`` (default 0) is subtracted (a calibrated residual mean).
    """

    def __init__(
        self,
        key: int,
        needle_tangent: np.ndarray,
        grasper_axis_cam: np.ndarray,
        noise: gtsam.noiseModel.Base,
        bias: float = 0.0,
    ) -> None:
        t = as_vector("needle_tangent", needle_tangent, 3)
        z = as_vector("grasper_axis_cam", grasper_axis_cam, 3)
        for name, v in (("needle_tangent", t), ("grasper_axis_cam", z)):
            if np.linalg.norm(v) < 1e-12:
                raise ValueError(f"{name} must be a non-zero direction")
        b = float(bias)
        if not np.isfinite(b):
            raise ValueError("bias must be finite")

        def fn(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            r, J = res.grasp_perpendicular_residual(T, t, z)
            return r - b, J

        super().__init__(noise, key, 1, fn)


class PosePriorFactor(_UnaryPoseFactor):
    """Gaussian pose prior ``Log(T_mean^-1 T)`` (6) with the exact Jacobian (unlike PriorFactorPose3)."""

    def __init__(self, key: int, cam_T_mean: gtsam.Pose3 | np.ndarray, noise: gtsam.noiseModel.Base) -> None:
        M = _check_pose("cam_T_mean", cam_T_mean).matrix()
        super().__init__(noise, key, 6, lambda T: res.pose_prior_residual(T, M))


class MotionFactor(gtsam.CustomFactor):
    """Motion between frames ``Log((D T_prev)^-1 T_cur)`` (6, ``[omega; v]``).

    ``cam_delta`` ``D = cam_T_grasper(k) cam_T_grasper(k-1)^-1`` is the grasper's motion in the
    camera frame (a ``gtsam.Pose3``); the needle moves with it, up to the process noise.
    """

    def __init__(
        self, key_prev: int, key_cur: int, cam_delta: gtsam.Pose3 | np.ndarray, noise: gtsam.noiseModel.Base
    ) -> None:
        kp, kc = _check_key("key_prev", key_prev), _check_key("key_cur", key_cur)
        if kp == kc:
            raise ValueError("key_prev and key_cur must differ")
        self._delta = delta = _check_pose("cam_delta", cam_delta).matrix()

        def evaluate(this: gtsam.CustomFactor, values: gtsam.Values, H: object) -> np.ndarray:
            # closes over ``delta`` only, not ``self`` (see _unary_callback: no cycle through C++)
            try:
                keys = this.keys()
                r, Jp, Jc = _motion_residual(delta, values.atPose3(keys[0]).matrix(), values.atPose3(keys[1]).matrix())
                if H is not None:
                    H[0] = np.ascontiguousarray(Jp, dtype=float)
                    H[1] = np.ascontiguousarray(Jc, dtype=float)
                return np.ascontiguousarray(r, dtype=float)
            except Exception as exc:
                this = values = H = keys = None  # noqa: F841 - see _reraise
                _reraise(exc)

        super().__init__(_check_noise(noise, 6), [kp, kc], evaluate)

    def residual(self, cam_T_prev: np.ndarray, cam_T_cur: np.ndarray) -> tuple[np.ndarray, ...]:
        """``r (6,)``, ``J_prev (6, 6)``, ``J_cur (6, 6)`` for two ``(4, 4)`` poses."""
        return _motion_residual(self._delta, cam_T_prev, cam_T_cur)


def _motion_residual(delta: np.ndarray, cam_T_prev: np.ndarray, cam_T_cur: np.ndarray) -> tuple[np.ndarray, ...]:
    r, Jp, Jc = res.motion_residual(cam_T_prev, cam_T_cur, delta)
    return r[0], Jp[0], Jc[0]
