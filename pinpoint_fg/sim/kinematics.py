"""The simulated robot: the C-Lock grasp geometry and the kinematic noise model.

Grasp geometry (rigid while the needle is held)
    ``needle_T_grasper`` has its origin at the grasp point ``X_g = P(θ_g)`` and axes

    * ``x_g = t(θ_g)``, the needle tangent at the grasp point;
    * ``z_g = cos α · ẑ_n − sin α · r̂(θ_g)``, the grasper (tube) axis: the needle-plane normal
      tilted by ``α`` (``SimConfig.grasper_tilt_rad``, default 20°) towards the needle centre.
      A needle driver holds a curved needle with its plane roughly perpendicular to the
      instrument shaft (rolling the shaft then drives the needle along its curve); the tilt
      keeps the geometry generic (tool roll then also changes the needle plane's obliquity).
    * ``y_g = z_g × x_g``.

    So ``ẑ_g · t_g = 0`` exactly: the perpendicularity residual vanishes at the truth unless the
    needle turns inside the grasp. A turn by ``φ`` about ``y_g`` through the grasp point (an
    external force; scenario ``rotation``) tilts the tangent towards ``z_g``:
    ``ẑ_g · (R t_g) = −sin φ``, leaves the grasp point where it is, and tips the needle plane
    out of its plane (``y_g`` lies mostly along the radial line of the grasp point).

Kinematic noise (what the robot reports vs. where the grasper is)
    ``cam_T_grasper_recorded = [R · R_err,  p + e]`` with ``(R, p)`` the commanded grasper pose.

    * ``e`` (3,), camera axes: per axis ``e = b + w``. ``b`` is a stationary Ornstein-Uhlenbeck
      process (time constant ``τ = kin_bias_tau_s``, default 5 s; exact discretisation
      ``b_k = a b_{k−1} + σ_b √(1−a²) ε_k``, ``a = exp(−Δt/τ)``, ``b_0 ~ N(0, σ_b²)``) and ``w`` is
      white; ``σ_w² = f σ²``, ``σ_b² = (1−f) σ²`` with ``f = kin_white_var_fraction`` (default
      1 %) and ``σ`` Table I's (0.41, 0.44, 1.00) mm. Every frame's error is exactly
      ``N(0, σ²)`` (stationary from frame 0); consecutive frames differ by
      ``σ √(2(1−f)(1−a) + 2f)`` ≈ 0.18 σ at 30 Hz — a concentric-tube robot's kinematic error
      is mostly a slowly varying, configuration-dependent bias, so the measured *motion*
      between frames is far more accurate than the absolute position.
    * ``R_err = R_x(α_k) · R_y(β_k) · R_z(γ_k)``, grasper axes, each angle the same OU + white
      mixture. With ``t_g`` the true grasper x axis, ``ẑ_rec · t_g = e_xᵀ R_err e_z = sin β``
      exactly, so ``β`` alone sets the perpendicularity residual; its std ``s`` solves
      ``E[sin² β] = (1 − exp(−2 s²)) / 2 = σ⊥²`` (σ⊥ = 0.138, Table I → s = 0.1393 rad).
      ``α`` and ``γ`` (std ``grasper_rot_sigma_rad``, default 2°) tilt the recorded grasper in
      the directions no residual but the motion model sees.

Calibrating from simulated runs
    The bias decorrelates over ``τ``: a 10 s run holds only ~2.7 effective samples of it, so
    one run's sample std is ~0.67 σ and its sample mean is that run's bias, not zero. Pool
    several seeds or use long runs (100 s: ~21 effective samples, within-run std ~0.95 σ)
    when estimating the kinematic noise (``pinpoint-fg calibrate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from factors.geometry import NeedleModel


def needle_T_grasper(needle: NeedleModel, tilt_rad: float) -> np.ndarray:
    """The fixed grasp transform ``(4, 4)``: grasper frame in the needle frame (module docstring)."""
    th = needle.grasp_angle_rad
    radial = np.array([math.cos(th), math.sin(th), 0.0])
    x = needle.grasp_tangent
    z = math.cos(tilt_rad) * np.array([0.0, 0.0, 1.0]) - math.sin(tilt_rad) * radial
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = needle.grasp_m
    return T


def rot_x(a: np.ndarray) -> np.ndarray:
    """Rotations about x by angles ``(...)`` -> ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a: np.ndarray) -> np.ndarray:
    """Rotations about y by angles ``(...)`` -> ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a: np.ndarray) -> np.ndarray:
    """Rotations about z by angles ``(...)`` -> ``(..., 3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def ou_white_process(
    rng: np.random.Generator, n: int, sigma: np.ndarray, dt_s: float, tau_s: float, white_var_fraction: float
) -> np.ndarray:
    """Stationary OU bias plus white noise, ``(n, d)`` for per-column total stds ``sigma`` ``(d,)``.

    ``x_k = b_k + w_k``; ``b`` is OU with ``a = exp(−Δt/τ)`` started from its stationary law,
    ``var(b) = (1−f) σ²``, ``var(w) = f σ²``: every ``x_k ~ N(0, σ²)`` exactly.
    """
    sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
    d = sigma.shape[0]
    a = math.exp(-dt_s / tau_s)
    sb = sigma * math.sqrt(1.0 - white_var_fraction)
    sw = sigma * math.sqrt(white_var_fraction)
    eps = rng.standard_normal((max(n, 1), d))
    white = rng.standard_normal((max(n, 1), d))
    drive = eps * (sb * math.sqrt(1.0 - a * a))
    drive[0] = eps[0] * sb
    b = lfilter([1.0], [1.0, -a], drive, axis=0)
    return (b + white * sw)[:n]


def frame_difference_std(sigma: float, dt_s: float, tau_s: float, white_var_fraction: float) -> float:
    """Std of ``x_k − x_{k−1}`` for :func:`ou_white_process`: ``σ √(2(1−f)(1−a) + 2f)``."""
    a = math.exp(-dt_s / tau_s)
    f = white_var_fraction
    return sigma * math.sqrt(2.0 * (1.0 - f) * (1.0 - a) + 2.0 * f)


def ou_white_autocorrelation(lags: np.ndarray, dt_s: float, tau_s: float, white_var_fraction: float) -> np.ndarray:
    """Autocorrelation ``ρ(k)`` of :func:`ou_white_process` at integer lags: ``(1−f) a^|k|`` (+ f at 0)."""
    k = np.abs(np.asarray(lags))
    a = math.exp(-dt_s / tau_s)
    return (1.0 - white_var_fraction) * a**k + white_var_fraction * (k == 0)


def perpendicular_angle_sigma(perpendicular_sigma: float) -> float:
    """Std ``s`` of a Gaussian angle β with ``std(sin β) = perpendicular_sigma``: ``E sin²β = (1−e^{−2s²})/2``."""
    v = 2.0 * perpendicular_sigma**2
    if v >= 1.0:
        raise ValueError("perpendicular_sigma must be below 1/sqrt(2)")
    return math.sqrt(-0.5 * math.log(1.0 - v))


@dataclass(frozen=True)
class KinematicErrors:
    """The errors the simulated kinematics add to the commanded grasper pose."""

    position_m: np.ndarray
    """Grasp position error ``e`` ``(F, 3)``, camera axes, metres (recorded − commanded)."""
    angles_rad: np.ndarray
    """``(α, β, γ)`` ``(F, 3)`` of ``R_err = R_x(α) R_y(β) R_z(γ)``, grasper axes, radians."""

    @property
    def rotation(self) -> np.ndarray:
        """``R_err`` ``(F, 3, 3)``."""
        a = self.angles_rad
        return rot_x(a[:, 0]) @ rot_y(a[:, 1]) @ rot_z(a[:, 2])


def draw_kinematic_errors(
    rng: np.random.Generator,
    n: int,
    position_sigma_m: tuple[float, float, float],
    perpendicular_sigma: float,
    rot_sigma_rad: float,
    dt_s: float,
    tau_s: float,
    white_var_fraction: float,
) -> KinematicErrors:
    """Draw ``n`` frames of kinematic error (module docstring): position, then the three angles."""
    pos = ou_white_process(rng, n, np.asarray(position_sigma_m), dt_s, tau_s, white_var_fraction)
    s_beta = perpendicular_angle_sigma(perpendicular_sigma)
    ang = ou_white_process(rng, n, np.array([rot_sigma_rad, s_beta, rot_sigma_rad]), dt_s, tau_s, white_var_fraction)
    return KinematicErrors(position_m=pos, angles_rad=ang)


def apply_kinematic_errors(cam_T_grasper: np.ndarray, errors: KinematicErrors) -> np.ndarray:
    """``[R R_err, p + e]`` for commanded poses ``(F, 4, 4)`` -> recorded poses ``(F, 4, 4)``."""
    T = np.array(cam_T_grasper, dtype=float, copy=True)
    T[:, :3, :3] = T[:, :3, :3] @ errors.rotation
    T[:, :3, 3] = T[:, :3, 3] + errors.position_m
    return T
