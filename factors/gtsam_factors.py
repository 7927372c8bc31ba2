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
from factors.conic_correlation import ArcWhitening
from factors.geometry import PinholeCamera, _finite_float, as_points_px, as_vector

#: Largest accepted |pixel coordinate| of a measurement or an intrinsic (``K``'s entries), pixels: beyond it the
#: residuals' squares overflow (a backbone pixel at 1e200 made every error NaN, a keypoint at 1e308 inf).
MAX_ABS_PX = 1e7
#: Largest accepted |length| (needle points, radius, measured positions, pose translations), metres. An overflow
#: guard, not a physical limit: a noise file's bias may reach 1e6 (``pinpoint_fg.noise.MAX_NOISE_ABS_MEAN``).
MAX_ABS_M = 1e7
#: Largest accepted deviation of a pose's rotation block from a rotation (``max |R^T R - I|``).
ROTATION_TOL = 1e-6


def _whitening_problem(noise: gtsam.noiseModel.Base) -> str | None:
    """Why GTSAM would whiten with inf/NaN (a zero or NaN sigma of a non-constrained model), or None.

    ``Isotropic.Sigma(d, 0)`` and ``Gaussian.Covariance(zeros)`` are accepted by GTSAM with an infinite square-root
    information: the factor's ``error()`` is then inf and its Jacobian inf/NaN, silently. A robust model is judged
    by its base; ``Constrained`` models (GTSAM's hard constraints, zero sigmas by design) are left to GTSAM.
    """
    base = noise
    while isinstance(base, gtsam.noiseModel.Robust):
        base = base.noise()
    if isinstance(base, gtsam.noiseModel.Gaussian) and not base.isConstrained() and not np.all(np.isfinite(base.R())):
        return ("noise has a zero or NaN sigma (its square-root information is not finite); "
                "use gtsam.noiseModel.Constrained for a hard constraint")
    return None


def _check_noise(noise: object, dim: int, sigmas: bool = True) -> gtsam.noiseModel.Base:
    if not isinstance(noise, gtsam.noiseModel.Base):
        raise ValueError(f"noise must be a gtsam noise model, got {type(noise).__name__}")
    if noise.dim() != dim:
        raise ValueError(f"noise has dimension {noise.dim()}, this factor's residual has {dim}")
    problem = _whitening_problem(noise) if sigmas else None
    if problem is not None:
        raise ValueError(problem)
    return noise


def _whole_index(name: str, value: object, count: int) -> int:
    """``value`` as an index in ``[0, count)``, else ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= int(value) < count:
        raise ValueError(f"{name} must be a whole number in [0, {count}), got {value!r}")
    return int(value)


def _check_key(name: str, key: object) -> int:
    """A gtsam key: a whole number in ``[0, 2^64)`` (pybind's own refusal dumped its constructor signatures)."""
    return _whole_index(name, key, 2**64)


def _number(name: str, value: object, bound: float, positive: bool = False) -> float:
    """``value`` as a finite float, ``|value| <= bound`` (``> 0`` when ``positive``), else ValueError naming it."""
    x = _finite_float(name, value, positive=positive)
    if abs(x) > bound:
        raise ValueError(f"{name} must be at most {bound:g} in magnitude, got {x!r}")
    return x


def _bounded(name: str, arr: np.ndarray, bound: float, unit: str) -> np.ndarray:
    """``arr`` itself when every |entry| is at most ``bound`` (the unit named in the message), else ValueError."""
    if arr.size and float(np.max(np.abs(arr))) > bound:
        raise ValueError(f"{name} has an entry of magnitude {float(np.max(np.abs(arr))):.3g} {unit}, "
                         f"more than the {bound:g} {unit} accepted")
    return arr


def _direction(name: str, value: object) -> np.ndarray:
    """A finite non-zero 3-vector whose norm is finite too (``[1e200, 0, 0]`` normalised to 0, silently)."""
    v = as_vector(name, value, 3)
    with np.errstate(over="ignore"):
        n = float(np.linalg.norm(v))
    if not (1e-12 <= n < np.inf):
        raise ValueError(f"{name} must be a non-zero direction of finite length, got norm {n:.3g}")
    return v


def _check_pose(name: str, pose: object) -> gtsam.Pose3:
    if isinstance(pose, gtsam.Pose3):
        m = pose.matrix()
    else:
        try:
            m = np.asarray(pose, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a gtsam.Pose3 or a (4, 4) matrix, got {pose!r}") from exc
        if m.shape != (4, 4):
            raise ValueError(f"{name} must be a gtsam.Pose3 or a (4, 4) matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} contains NaN or infinite values")
    R = m[:3, :3]
    # gtsam.Rot3 keeps any 3x3 as given: a scaled, sheared or zero block was a silently wrong error value
    if (not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]) or float(np.max(np.abs(R.T @ R - np.eye(3)))) > ROTATION_TOL
            or np.linalg.det(R) <= 0):
        raise ValueError(f"{name} is not a rigid transform (rotation block not a rotation within {ROTATION_TOL:g}, "
                         "or last row not [0, 0, 0, 1])")
    _bounded(f"{name}'s translation", m[:3, 3], MAX_ABS_M, "m")
    return gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(*m[:3, 3]))


def _camera_K(camera: object) -> np.ndarray:
    """The checked ``K`` of a camera: ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` with ``0 < fx, fy`` and every entry
    within :data:`MAX_ABS_PX`. The keypoint residual reads ``fx, fy, cx, cy`` only: a skew, a ``K[2, 2] != 1`` or a
    singular ``K`` (all zeros) gave a silently wrong error, and the conic factor a different one."""
    if isinstance(camera, PinholeCamera):
        K = camera.K
    else:
        try:
            K = np.asarray(camera, dtype=float)
        except (TypeError, ValueError):
            K = np.zeros(0)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError("camera must be a PinholeCamera or a finite (3, 3) intrinsic matrix")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[0, 1] == 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])):
        raise ValueError("camera K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 "
                         f"(no skew; the keypoint residual assumes it), got {K.tolist()}")
    return _bounded("camera K", K, MAX_ABS_PX, "px")


def _reraise(exc: Exception) -> None:
    """Re-raise ``exc`` from a callback without GTSAM's temporaries in its traceback.

    ``this``, ``values`` and ``H`` are wrappers of C++ objects that die when the call unwinds;
    a traceback keeping them lets a later ``repr`` of its frames (pytest, IPython, a debugger)
    read freed memory and crash the interpreter. The callers clear those locals first; the
    traceback is reset so the frames below (which saw them too) are not kept either.
    """
    raise exc.with_traceback(None)


#: A one-pose factor's batched function: ``(T (1, 4, 4), jacobian) -> (r (1, dim), J (1, dim, 6) or None)``; with
#: ``jacobian=False`` it may skip the Jacobian (GTSAM asks for ``error()`` alone, e.g. on every trial step).
UnaryFn = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]


def _unary_residual(fn: UnaryFn, dim: int, cam_T_needle: np.ndarray, jacobian: bool = True
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    r, J = fn(np.asarray(cam_T_needle, dtype=float)[None], jacobian)
    return r.reshape(dim), (J.reshape(dim, 6) if jacobian else None)


def _unary_callback(fn: UnaryFn, dim: int) -> Callable:
    """The GTSAM callback of a one-pose factor (the Jacobian only built when GTSAM asks for it).

    It closes over ``fn`` and ``dim`` only, never over the factor object: the C++ factor owns the
    callback, so a callback holding the Python factor would make a reference cycle through C++
    that Python's garbage collector cannot see, and every factor ever built would stay alive
    (measured: the MAP tracker grew ~6 MB per 1000 frames, all of it dead factors).
    """

    def evaluate(this: gtsam.CustomFactor, values: gtsam.Values, H: object) -> np.ndarray:
        try:
            T = values.atPose3(this.keys()[0]).matrix()
            r, J = _unary_residual(fn, dim, T, H is not None)
            if H is not None:
                H[0] = np.ascontiguousarray(J, dtype=float)
            return np.ascontiguousarray(r, dtype=float)
        except Exception as exc:
            this = values = H = None  # noqa: F841 - see _reraise
            _reraise(exc)

    return evaluate


class _UnaryPoseFactor(gtsam.CustomFactor):
    """A one-pose factor whose residual/Jacobian come from a batched function ``(T (1,4,4), jacobian) -> r, J``."""

    def __init__(
        self,
        noise: gtsam.noiseModel.Base,
        key: int,
        dim: int,
        fn: UnaryFn,
        sigmas: bool = True,
    ) -> None:
        self._fn = fn
        self._dim = dim
        super().__init__(_check_noise(noise, dim, sigmas), [_check_key("key", key)], _unary_callback(fn, dim))

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
        X = _bounded("needle_point_m", as_vector("needle_point_m", needle_point_m, 3), MAX_ABS_M, "m")
        z = _bounded("measured_px", as_vector("measured_px", measured_px, 2), MAX_ABS_PX, "px")
        super().__init__(noise, key, 2, lambda T, jacobian: res.keypoint_residual(T, K, X, z, jacobian=jacobian))


def _conic_inputs(camera: object, radius_m: float, points_px: np.ndarray, bias: float
                  ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Checked ``(K, points_px (M, 2), radius_m, bias)`` of a conic factor (ValueError on bad input)."""
    K = _camera_K(camera)
    pts = _bounded("points_px", as_points_px("points_px", points_px), MAX_ABS_PX, "px")
    if pts.shape[0] == 0:
        raise ValueError("points_px must hold at least one backbone pixel")
    r_m = _number("radius_m", radius_m, MAX_ABS_M, positive=True)
    b = _number("bias", bias, MAX_ABS_PX)
    return K, pts, r_m, b


class ConicFactor(_UnaryPoseFactor):
    """Sampson distances (M px) of M backbone pixels to the needle circle's image conic; one per frame.

    ``bias`` (px, default 0) is subtracted from every distance (a calibrated residual mean). ``whitening``
    (optional, :class:`factors.conic_correlation.ArcWhitening` of these pixels): the distances' along-arc
    innovations instead, in arc order, for noise correlated along the arc. ``distance``: "sampson"
    (:func:`factors.residuals.conic_residual`, the default) or "geometric"
    (:func:`factors.residuals.conic_geometric_residual`).
    """

    def __init__(
        self,
        key: int,
        camera: PinholeCamera | np.ndarray,
        radius_m: float,
        points_px: np.ndarray,
        noise: gtsam.noiseModel.Base,
        bias: float = 0.0,
        whitening: ArcWhitening | None = None,
        distance: str = "sampson",
    ) -> None:
        K, pts, r_m, b = _conic_inputs(camera, radius_m, points_px, bias)
        _check_whitening(whitening, pts.shape[0])
        residual = _conic_distance(distance)

        def fn(T: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
            r, J = residual(T, K, r_m, pts, jacobian=jacobian)
            if whitening is None:
                return r - b, J
            return whitening.apply(r - b, J)

        super().__init__(noise, key, pts.shape[0], fn)


def _conic_distance(distance: object) -> Callable:
    """The residual function of a conic factor's ``distance`` ("sampson" or "geometric"; ValueError otherwise)."""
    if distance == "sampson":
        return res.conic_residual
    if distance == "geometric":
        return res.conic_geometric_residual
    raise ValueError(f"distance must be 'sampson' or 'geometric', got {distance!r}")


def _check_whitening(whitening: object, count: int) -> None:
    """ValueError unless ``whitening`` is None or an :class:`ArcWhitening` of ``count`` pixels."""
    if whitening is None:
        return
    if not isinstance(whitening, ArcWhitening):
        raise ValueError(f"whitening must be an ArcWhitening or None, got {type(whitening).__name__}")
    if whitening.order.shape != (count,):
        raise ValueError(f"whitening is for {whitening.order.shape[0]} pixels, the factor has {count}")


class _ConicCache:
    """All pixels' Sampson distances (or their along-arc innovations) and Jacobians at the last pose asked for
    (one batched call per pose)."""

    def __init__(self, K: np.ndarray, radius_m: float, points_px: np.ndarray, bias: float,
                 whitening: ArcWhitening | None = None, distance: str = "sampson") -> None:
        self._K, self._r, self._pts, self._b = K, radius_m, points_px, bias
        self._whitening = whitening
        self._residual = _conic_distance(distance)
        self.count = int(points_px.shape[0])
        self._key: bytes | None = None
        self._rJ: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.ascontiguousarray(T, dtype=float).tobytes()
        if key != self._key or self._rJ is None:
            r, J = self._residual(T, self._K, self._r, self._pts)
            if self._whitening is not None:
                r, J = self._whitening.apply(r - self._b, J)
                self._rJ = (r[0], J[0])
            else:
                self._rJ = (r[0] - self._b, J[0])
            self._key = key
        return self._rJ


class ConicPixelFactor(_UnaryPoseFactor):
    """The Sampson distance of ONE backbone pixel (1 px); see :func:`conic_pixel_factors`."""

    def __init__(self, key: int, cache: _ConicCache, index: int, noise: gtsam.noiseModel.Base) -> None:
        if not isinstance(cache, _ConicCache):
            raise ValueError(f"cache must come from conic_pixel_factors, got {type(cache).__name__}")
        i = _whole_index("index", index, cache.count)  # -1 or past the end read no row: "cannot reshape" per error()

        def fn(T: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
            # always with the Jacobian: the cache serves all pixels of a pose, and GTSAM's linearisation
            # usually follows its error() at the same pose
            r, J = cache(T[0])
            return r[i : i + 1], J[i : i + 1]

        # the sigmas were checked once by conic_pixel_factors (one noise model shared by every pixel)
        super().__init__(noise, key, 1, fn, sigmas=False)


def conic_pixel_factors(
    key: int,
    camera: PinholeCamera | np.ndarray,
    radius_m: float,
    points_px: np.ndarray,
    noise: gtsam.noiseModel.Base,
    bias: float = 0.0,
    whitening: ArcWhitening | None = None,
    distance: str = "sampson",
) -> list[ConicPixelFactor]:
    """One 1-row factor per backbone pixel, each with the 1-D ``noise`` (typically a robust model).

    With ``whitening`` (:class:`factors.conic_correlation.ArcWhitening` of these pixels) factor ``i`` holds the
    ``i``-th along-arc innovation instead of pixel ``i``'s distance (the robust loss then acts per innovation).
    ``distance``: as :class:`ConicFactor`'s.

    The per-pixel form of :class:`ConicFactor`: GTSAM weights a robust factor by the norm of its
    whole whitened vector, so a robust loss *per pixel* needs one factor per pixel. The sum of
    their errors and their stacked linearisations equal :class:`ConicFactor`'s when ``noise`` is
    the plain Gaussian. All the factors share one cache, so a graph linearised at one pose runs
    the batched :func:`factors.residuals.conic_residual` once, not once per pixel.
    """
    K, pts, r_m, b = _conic_inputs(camera, radius_m, points_px, bias)
    _check_noise(noise, 1)
    _check_whitening(whitening, pts.shape[0])
    cache = _ConicCache(K, r_m, pts, b, whitening, distance)
    return [ConicPixelFactor(key, cache, i, noise) for i in range(pts.shape[0])]


class GraspPositionFactor(_UnaryPoseFactor):
    """Grasp position ``T X_g - p_g`` (3 m, camera axes); ``p_g`` from kinematics."""

    def __init__(
        self, key: int, needle_point_m: np.ndarray, measured_cam_m: np.ndarray, noise: gtsam.noiseModel.Base
    ) -> None:
        X = _bounded("needle_point_m", as_vector("needle_point_m", needle_point_m, 3), MAX_ABS_M, "m")
        p = _bounded("measured_cam_m", as_vector("measured_cam_m", measured_cam_m, 3), MAX_ABS_M, "m")
        super().__init__(noise, key, 3, lambda T, jacobian: res.grasp_position_residual(T, X, p, jacobian=jacobian))


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
        t = _direction("needle_tangent", needle_tangent)
        z = _direction("grasper_axis_cam", grasper_axis_cam)
        b = _number("bias", bias, MAX_ABS_PX)

        def fn(T: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
            r, J = res.grasp_perpendicular_residual(T, t, z, jacobian=jacobian)
            return r - b, J

        super().__init__(noise, key, 1, fn)


class PosePriorFactor(_UnaryPoseFactor):
    """Gaussian pose prior ``Log(T_mean^-1 T)`` (6) with the exact Jacobian (unlike PriorFactorPose3)."""

    def __init__(self, key: int, cam_T_mean: gtsam.Pose3 | np.ndarray, noise: gtsam.noiseModel.Base) -> None:
        M = _check_pose("cam_T_mean", cam_T_mean).matrix()
        super().__init__(noise, key, 6, lambda T, jacobian: res.pose_prior_residual(T, M, jacobian=jacobian))


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
                r, Jp, Jc = _motion_residual(delta, values.atPose3(keys[0]).matrix(), values.atPose3(keys[1]).matrix(),
                                             H is not None)
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


def _motion_residual(delta: np.ndarray, cam_T_prev: np.ndarray, cam_T_cur: np.ndarray, jacobian: bool = True
                     ) -> tuple[np.ndarray, ...]:
    r, Jp, Jc = res.motion_residual(cam_T_prev, cam_T_cur, delta, jacobian=jacobian)
    return (r[0], Jp[0], Jc[0]) if jacobian else (r[0], None, None)
