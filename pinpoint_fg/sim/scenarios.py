"""The simulator's scenarios (paper §V-B) and the recorded runs it writes.

:func:`simulate` writes a recorded run (``shared/RECORDING_FORMAT.md``, with ``gt_*`` and
``occlusion`` columns) frame by frame; :func:`simulate_frames` returns the same run in
memory together with everything noise-free (:class:`SimRun`). Both are deterministic for a
given ``(scenario, n_frames, seed, config)``: independent random streams (trajectory,
kinematics, keypoints, masks) are spawned from ``SeedSequence([seed, scenario])``, and the
image background is seeded from the same pair, so ``images=True`` changes no other value.

What is simulated per frame (30 Hz), see also :mod:`pinpoint_fg.sim.kinematics` and
:mod:`pinpoint_fg.sim.render`:

* the true needle pose ``cam_T_needle`` and the true (physical) grasper pose; the needle is
  held rigidly by the C-Lock unless a scenario turns it inside the grasp;
* recorded kinematics: the grasper pose the robot *believes* (commanded; differs from the
  physical pose only while the robot slips in tissue) plus the kinematic noise model;
* tip and tail keypoints: the true point projected with lens distortion plus Gaussian noise
  (Table I, in the distorted image), missed with ``keypoint_miss_prob``, absent when the
  point is hidden in tissue, outside the image (by ``keypoint_margin_px``) or in a scenario's
  detector drop-out;
* a segmentation mask on every third frame (10 Hz), missing with ``mask_miss_prob``;
* the ``occlusion`` label: ``none`` (the whole arc visible), ``heavy`` (tip inside the tissue
  and at least ``HEAVY_HIDDEN_FRACTION`` of the arc hidden: only the tail part shows), else
  ``partial`` (part of the arc hidden: the tip entering, or the middle of the needle still in
  the tissue after the tip has re-emerged).

Scenarios (base poses put the needle centre 40-55 mm in front of the camera; the needle
normal is 35-50° off the viewing ray so the arc projects as an open ellipse):

``slow``
    ~1 mm/s, one axis at a time in 4 s segments: left/right (camera x), up/down (y),
    in/out (z), then tool roll about the grasper axis; each segment is one sine period of
    amplitude 1 mm (mean speed 1 mm/s; the roll's amplitude moves the needle centre at the
    same mean speed). Depth 40 mm.
``normal``
    ~2 mm/s free smooth motion: every translation and rotation axis of the grasper is a sum
    of three sinusoids (0.05-0.3 Hz, random phases; rotations about the grasp point reach
    5-18° per axis in 10 s); the translation is scaled so the needle centre's mean speed is
    2 mm/s (a few mm of travel per axis). Depth 42 mm.
``rotation``
    Depth 55 mm, slow free robot motion (1 mm/s, ±2° rotations) while an external force turns
    the needle *inside the grasp* about the grasper's ``y`` axis through the grasp point,
    ``φ(t) = Φ sin(2π t / 6 s)``; the kinematics do not see it, so the perpendicularity
    residual at the truth is ``−sin φ`` and the motion model is broken. ``Φ`` is chosen from
    the base pose as the in-grasp angle at which the needle is seen exactly edge-on plus 15°,
    so every positive swing passes through edge-on views. The tip detector fails while the
    needle is more than ``ROTATION_TIP_DROPOUT_DEG`` = 60° from face-on (angle between its
    normal and the viewing ray): stretches with a single keypoint at oblique, distant views,
    where the two circle poses are hardest to tell apart. Measured (seed 0, masked frames,
    ΔNLL of the best alternative circle pose minus the truth's, both polished): without the
    perpendicularity term ~90 % of frames have ΔNLL < 2.3; with it the truth is often *worse*
    than the alternative (ΔNLL down to −30), because the constraint is exactly what the force
    broke. The other scenarios: 10-20 % of masked frames ambiguous, most clear (ΔNLL > 10).
``suturing``
    A bite into a tissue half-space (depth 40 mm, needle plane 50° off the viewing ray and
    perpendicular to the tissue surface, the camera on the outside). Phases, as fractions of
    the run: approach (0-15 %: the needle comes down 3 mm onto the entry point); drive
    (15-55 %: the robot turns the needle about its own centre axis, the tip enters, the backbone
    disappears progressively from the tip until only the tail part shows, then the tip
    re-emerges 70° further on and protrudes 10°); lift (55-75 %: the needle is lifted out
    along the surface normal, the hidden middle shrinks to nothing — a simplification of
    pulling through that keeps what the camera sees: both ends visible, a shrinking hidden
    middle); free motion (75-100 %). The tissue surface is a plane; an arc point is hidden
    when it lies inside. Slip: from 55 % to 67 % of the drive the robot keeps turning while the
    embedded needle stays put; the lag stays until the needle is free and relaxes over 1 s
    afterwards (recorded kinematics are off by up to ~1.3 mm in that time).
``calibration``
    A random smooth tour (waypoints every 2 s, monotone cubic interpolation) over depth
    30-60 mm, obliquity 0-65°, any in-plane rotation and position (±15 % of the depth off the
    optical axis), rigid grasp, no occlusion: ground truth for noise calibration.

Scenarios of issue 9 (hard cases; none is tuned to make a method fail, the values are the ones above
or the paper's working range):

``symmetric``
    Far and shallow: depth ``SYMMETRIC_DEPTH_M`` = 60 mm (the far end of the 30-60 mm range the
    calibration tour covers), needle normal ``SYMMETRIC_OBLIQUITY_DEG`` = 65° off the viewing ray
    (a grazing view of the needle plane), slow free motion (1 mm/s, ±3°, rigid grasp), and the tip
    detector never fires: the tail and the backbone alone, where the circle's two poses are hardest
    to tell apart. Meant to be tracked with the grasp factors off (they would settle the circle):
    recording.json says so in ``suggested_disable`` (:data:`SUGGESTED_DISABLE`).
``drive``
    A bite into a tissue half-space (``suturing``'s geometry, depth 45 mm): approach (0-10 %: 3 mm
    onto the entry point), then the driver rolls about its shaft — the grasper axis, tilted 20° from
    the needle normal (``SimConfig.grasper_tilt_rad``), through the needle centre — by 84° (10-80 %,
    eased), then holds. The tilt makes the needle plane wobble while the tip advances; the base tilt
    is searched on a 0.25° grid so the needle is exactly edge-on half-way through the drive (76° →
    90° → 76°). Arc points inside the tissue are hidden, so the tip keypoint is missing once the tip
    has entered (from ~20 % of the run): the tip enters tissue while the needle turns through
    edge-on. Rigid grasp, complete kinematics.
``kinfault``
    ``normal``'s motion with faulty kinematics (:func:`kinfault_events`): two drop-outs of 0.5-1 s
    (empty grasper columns) and one re-registration jump of ``KINFAULT_JUMP_M`` = 4 mm (a random
    direction, the recorded ``cam_T_grasper`` only: the needle does not jump) that persists to the
    end. recording.json lists them under ``simulator.kinematics_missing`` / ``registration_jump``.
``snapshots``
    Stills ``SNAPSHOT_DT_S`` = 0.5 s apart (2 Hz, a mask on every frame: :func:`scenario_config`),
    free motion at 5 mm/s with ±20° rotations (~2.5 mm and 9° between frames, depth 42-56 mm),
    rigid grasp, no kinematics at all.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from factors.lie import homogeneous, se3_inverse, so3_exp
from pinpoint_fg.io.recording.schema import FrameRecord, RecordingInfo
from pinpoint_fg.sim.config import SimConfig
from pinpoint_fg.sim.kinematics import (
    KinematicErrors,
    apply_kinematic_errors,
    draw_kinematic_errors,
    needle_T_grasper,
    rot_x,
    rot_y,
    rot_z,
)
from pinpoint_fg.sim.render import ARC_SAMPLES, Blob, draw_needle, render_mask, tissue_background

SCENARIOS: tuple[str, ...] = (
    "slow", "normal", "rotation", "suturing", "calibration", "symmetric", "drive", "kinfault", "snapshots",
)
#: Likelihood switches each scenario is meant to be tracked without (written to recording.json as
#: ``suggested_disable``; ``demo``/``benchmark`` honour it, ``track`` keeps its explicit ``--disable``).
SUGGESTED_DISABLE: dict[str, tuple[str, ...]] = {"symmetric": ("grasp-position", "grasp-perpendicular")}

#: In ``rotation``, the tip detector fails beyond this angle between needle normal and viewing ray, degrees.
ROTATION_TIP_DROPOUT_DEG = 60.0
#: ``heavy`` occlusion: the tip is hidden and at least this share of the arc is inside tissue.
HEAVY_HIDDEN_FRACTION = 0.3


@dataclass(frozen=True)
class Trajectory:
    """A scenario's noise-free motion and visibility, ``F`` frames."""

    cam_T_needle: np.ndarray
    """True needle poses ``(F, 4, 4)``."""
    cam_T_grasper: np.ndarray
    """True (physical) grasper poses ``(F, 4, 4)``."""
    cam_T_grasper_cmd: np.ndarray
    """Grasper poses the robot believes (before kinematic noise) ``(F, 4, 4)``."""
    visible: np.ndarray
    """Which arc samples are not hidden by tissue ``(F, A)`` bool."""
    tip_dropout: np.ndarray
    """Frames where the tip detector fails regardless of visibility ``(F,)`` bool."""
    in_grasp_rad: np.ndarray
    """Needle rotation inside the grasp about grasper y ``(F,)``, radians (0 = rigid grasp)."""
    slipping: np.ndarray
    """Frames where the recorded kinematics differ from the physical grasper by a slip ``(F,)`` bool."""
    tissue_plane: tuple[np.ndarray, float] | None = None
    """Suturing only: ``(m, d)`` with a camera point x inside the tissue when ``m·x > d``."""
    kinematics_missing: np.ndarray | None = None
    """Frames whose kinematics are not recorded ``(F,)`` bool (None: none missing)."""
    registration_offset: np.ndarray | None = None
    """``(F, 4, 4)`` camera-frame transform left-multiplied onto the recorded kinematics (a
    camera-robot re-registration); None: identity."""


@dataclass
class SimRun:
    """A simulated run in memory: what is recorded plus the noise-free truth behind it."""

    scenario: str
    """Scenario name."""
    seed: int
    """Seed the run was drawn with."""
    config: SimConfig
    """Simulator settings."""
    info: RecordingInfo
    """The recording.json contents."""
    frames: list[FrameRecord]
    """One record per frame, as written to frames.csv (mask paths as the writer names them; image None)."""
    masks: dict[int, np.ndarray]
    """Frame index -> uint8 0/255 mask ``(H, W)``."""
    cam_T_needle: np.ndarray
    """True needle poses ``(F, 4, 4)``."""
    cam_T_grasper: np.ndarray
    """True (physical) grasper poses ``(F, 4, 4)``: origin = grasp point, z = grasper axis."""
    cam_T_grasper_recorded: np.ndarray
    """Recorded kinematics ``(F, 4, 4)`` (commanded pose plus kinematic noise)."""
    kinematic_errors: KinematicErrors
    """The drawn kinematic errors (recorded = commanded ⊕ errors)."""
    arc_theta: np.ndarray
    """Arc angles of the visibility samples ``(A,)``, radians."""
    visible: np.ndarray
    """Arc samples not hidden in tissue ``(F, A)`` bool."""
    tip_px_true: np.ndarray
    """Noise-free tip pixel ``(F, 2)``, distorted image."""
    tail_px_true: np.ndarray
    """Noise-free tail pixel ``(F, 2)``, distorted image."""
    tip_detectable: np.ndarray
    """Tip visible, in the image and not in a detector drop-out ``(F,)`` (before random misses)."""
    tail_detectable: np.ndarray
    """Tail visible and in the image ``(F,)`` (before random misses)."""
    occlusion: list[str]
    """Occlusion label per frame."""
    in_grasp_rad: np.ndarray
    """Needle rotation inside the grasp ``(F,)``, radians."""
    slipping: np.ndarray
    """Recorded kinematics offset by a slip ``(F,)`` bool."""
    edge_on_deg: np.ndarray
    """Angle between needle normal and the viewing ray to the needle centre ``(F,)``, degrees (90 = edge-on)."""
    fp_blobs: dict[int, list[Blob]] = field(default_factory=dict)
    """False-positive blobs drawn into each mask."""
    tissue_plane: tuple[np.ndarray, float] | None = None
    """Suturing: tissue half-space ``m·x > d`` (camera frame, metres)."""
    kinematics_missing: np.ndarray | None = None
    """Frames recorded without kinematics ``(F,)`` bool (empty grasper columns)."""
    registration_offset: np.ndarray | None = None
    """``(F, 4, 4)`` re-registration offset included in :attr:`cam_T_grasper_recorded` (identity if none)."""

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return len(self.frames)


# ---------------------------------------------------------------------------------------------
# helpers




def _base_rotation(az_deg: float, tilt_deg: float, spin_deg: float) -> np.ndarray:
    """``Rz(az) Rx(tilt) Rz(spin)``: tilt 0 puts the needle normal along the optical axis."""
    return rot_z(math.radians(az_deg)) @ rot_x(math.radians(tilt_deg)) @ rot_z(math.radians(spin_deg))


def _edge_on_deg(cam_T_needle: np.ndarray) -> np.ndarray:
    n = cam_T_needle[..., :3, 2]
    c = cam_T_needle[..., :3, 3]
    cosang = np.abs(np.sum(n * c, axis=-1)) / np.maximum(np.linalg.norm(c, axis=-1), 1e-12)
    return np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _ease(x: np.ndarray) -> np.ndarray:
    """Cosine easing 0 -> 1 on [0, 1] (zero velocity at both ends)."""
    return 0.5 * (1.0 - np.cos(math.pi * np.clip(x, 0.0, 1.0)))


def _sinusoids(rng: np.random.Generator, t: np.ndarray, dims: int, f_lo: float, f_hi: float) -> np.ndarray:
    """``(F, dims)`` sums of three sinusoids per column, unit-ish amplitude, zero at t = 0."""
    f = rng.uniform(f_lo, f_hi, (3, dims))
    amp = rng.uniform(0.5, 1.0, (3, dims))
    ph = rng.uniform(0.0, 2.0 * math.pi, (3, dims))
    arg = 2.0 * math.pi * f[None] * t[:, None, None] + ph[None]
    return np.sum(amp[None] * (np.sin(arg) - np.sin(ph)[None]), axis=1) / math.sqrt(3.0)


def _free_motion(
    rng: np.random.Generator,
    t: np.ndarray,
    G0: np.ndarray,
    grasper_p_centre: np.ndarray,
    speed_m_s: float,
    rot_amp_rad: float,
) -> np.ndarray:
    """Grasper poses ``(F, 4, 4)``: ``G0`` moved by smooth random translations and rotations.

    Rotations (grasper axes, about the grasp point) are sums of sinusoids of amplitude
    ``rot_amp_rad``; translations (camera axes) are sums of sinusoids scaled (bisection) so the
    needle centre's mean speed is ``speed_m_s``.
    """
    w = rot_amp_rad * _sinusoids(rng, t, 3, 0.05, 0.25)
    d = _sinusoids(rng, t, 3, 0.05, 0.3)
    R = G0[:3, :3] @ so3_exp(w)
    centre_rot = np.einsum("fij,j->fi", R, grasper_p_centre) + G0[:3, 3]
    if t.shape[0] < 2:
        return homogeneous(R, G0[:3, 3] + 0.0 * d)
    dt = t[1] - t[0]

    def speed(scale: float) -> float:
        c = centre_rot + scale * d
        return float(np.mean(np.linalg.norm(np.diff(c, axis=0), axis=1)) / dt)

    lo, hi = 0.0, 1.0e-3
    while speed(hi) < speed_m_s and hi < 1.0:
        hi *= 2.0
    if speed(lo) >= speed_m_s:
        scale = 0.0
    else:
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if speed(mid) < speed_m_s else (lo, mid)
        scale = 0.5 * (lo + hi)
    return homogeneous(R, G0[:3, 3] + scale * d)


# ---------------------------------------------------------------------------------------------
# scenarios


def _rigid(cfg: SimConfig, grasper: np.ndarray, n_arc: int) -> Trajectory:
    gTn = se3_inverse(needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad))
    F = grasper.shape[0]
    return Trajectory(
        cam_T_needle=grasper @ gTn,
        cam_T_grasper=grasper,
        cam_T_grasper_cmd=grasper.copy(),
        visible=np.ones((F, n_arc), bool),
        tip_dropout=np.zeros(F, bool),
        in_grasp_rad=np.zeros(F),
        slipping=np.zeros(F, bool),
    )


def _base_grasper(cfg: SimConfig, R_needle: np.ndarray, centre_m: np.ndarray) -> np.ndarray:
    T = homogeneous(R_needle, np.asarray(centre_m, float))
    return T @ needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad)


def _scenario_slow(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    G0 = _base_grasper(cfg, _base_rotation(25.0, 35.0, -20.0), np.array([1.0e-3, -1.0e-3, 0.040]))
    seg_s, speed = 4.0, 1.0e-3
    amp = speed * seg_s / 4.0  # one sine period of amplitude A covers 4 A
    roll_amp = amp / cfg.needle.radius_m  # the centre is r away from the grasp point
    seg = np.floor(t / seg_s).astype(int) % 4
    prof = np.sin(2.0 * math.pi * np.mod(t, seg_s) / seg_s)
    d = np.zeros((t.shape[0], 3))
    for axis in range(3):
        d[seg == axis, axis] = amp * prof[seg == axis]
    roll = np.where(seg == 3, roll_amp * prof, 0.0)
    G = homogeneous(G0[:3, :3] @ rot_z(roll), G0[:3, 3] + d)
    return _rigid(cfg, G, n_arc)


def _scenario_normal(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    G0 = _base_grasper(cfg, _base_rotation(-30.0, 40.0, 10.0), np.array([0.0, 0.5e-3, 0.042]))
    centre_g = se3_inverse(needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad))[:3, 3]
    G = _free_motion(rng, t, G0, centre_g, 2.0e-3, math.radians(8.0))
    return _rigid(cfg, G, n_arc)


def _in_grasp_pose(G: np.ndarray, phi: np.ndarray, gTn: np.ndarray) -> np.ndarray:
    Ry = homogeneous(rot_y(phi), np.zeros(phi.shape + (3,)))
    return G @ Ry @ gTn


def _scenario_rotation(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    G0 = _base_grasper(cfg, _base_rotation(0.0, 40.0, 150.0), np.array([0.0, 0.0, 0.055]))
    gTn = se3_inverse(needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad))
    # the in-grasp angle at which the base pose is seen edge-on, searched on a 0.25 deg grid
    grid = np.radians(np.arange(0.0, 120.0 + 1e-9, 0.25))
    ang = _edge_on_deg(_in_grasp_pose(np.broadcast_to(G0, (grid.shape[0], 4, 4)), grid, gTn))
    amp = min(float(grid[int(np.argmax(ang))]) + math.radians(15.0), math.radians(120.0))
    G = _free_motion(rng, t, G0, gTn[:3, 3], 1.0e-3, math.radians(2.0))
    phi = amp * np.sin(2.0 * math.pi * t / 6.0)
    T = _in_grasp_pose(G, phi, gTn)
    F = t.shape[0]
    return Trajectory(
        cam_T_needle=T,
        cam_T_grasper=G,
        cam_T_grasper_cmd=G.copy(),
        visible=np.ones((F, n_arc), bool),
        tip_dropout=_edge_on_deg(T) > ROTATION_TIP_DROPOUT_DEG,
        in_grasp_rad=phi,
        slipping=np.zeros(F, bool),
    )


def _scenario_suturing(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    nd = cfg.needle
    F = t.shape[0]
    T_total = max(float(t[-1]), 1e-9) if F > 1 else 1.0
    u = t / T_total
    nTg = needle_T_grasper(nd, cfg.grasper_tilt_rad)
    # tissue geometry in the needle frame at the start of the drive: the hidden window of half
    # width beta starts just beyond the tip, the needle is turned by psi about its centre axis
    beta, eps, protrude = math.radians(35.0), math.radians(4.0), math.radians(10.0)
    sgn = 1.0 if nd.tip_angle_rad >= nd.tail_angle_rad else -1.0
    theta_d0 = nd.tip_angle_rad + sgn * (beta + eps)
    psi_end = eps + 2.0 * beta + protrude
    h = nd.radius_m * math.cos(beta)
    spin = math.degrees(math.pi / 2.0 - theta_d0)  # puts the tissue's inward normal away from the camera
    T0 = homogeneous(_base_rotation(20.0, 50.0, spin), np.array([0.5e-3, 0.0, 0.040]))
    m = T0[:3, :3] @ np.array([math.cos(theta_d0), math.sin(theta_d0), 0.0])  # inward surface normal
    d_plane = float(m @ T0[:3, 3]) + h
    # phases
    u_app, u_drv, u_lift = 0.15, 0.55, 0.75
    w_app = np.clip(u / u_app, 0, 1)
    w_drv = np.clip((u - u_app) / (u_drv - u_app), 0, 1)
    w_lift = np.clip((u - u_drv) / (u_lift - u_drv), 0, 1)
    # slip within the drive: the needle stalls from 55 % to 67 % of the drive (time warp)
    s0, ds = 0.55, 0.12
    warped = (w_drv - np.clip(w_drv - s0, 0.0, ds)) / (1.0 - ds)
    psi_true = sgn * psi_end * _ease(warped)
    rate0 = psi_end * 0.5 * math.pi * math.sin(math.pi * s0 / (1.0 - ds)) / (1.0 - ds)  # d psi / d w at the stall
    lag_max = rate0 * ds
    dt_after = 1.0 / T_total  # the lag relaxes over 1 s once the needle is free
    lag = sgn * lag_max * _smoothstep((w_drv - s0) / ds) * (1.0 - _smoothstep((u - u_lift) / dt_after))
    slipping = np.abs(lag) > 1e-9
    # translations: approach from 3 mm outside, lift out along -m until the circle clears the plane
    approach = 3.0e-3 * (1.0 - _ease(w_app))
    lift = (nd.radius_m - h + 1.0e-3) * _ease(w_lift)
    offset = -(approach + lift)[:, None] * m[None, :]
    after = np.clip((u - u_lift) / (1.0 - u_lift), 0, 1)
    G_tmp = T0 @ nTg
    free = _free_motion(rng, t, G_tmp, se3_inverse(nTg)[:3, 3], 1.0e-3, math.radians(3.0))
    free_d = (free[:, :3, 3] - G_tmp[:3, 3]) * _smoothstep(after / 0.2)[:, None]
    free_d -= 2.0 * np.maximum(free_d @ m, 0.0)[:, None] * m[None, :]  # never back into the tissue

    def needle_pose(psi: np.ndarray) -> np.ndarray:
        Rz = homogeneous(rot_z(psi), np.zeros((F, 3)))
        T = T0[None] @ Rz
        T[:, :3, 3] += offset + free_d
        return T

    T_true = needle_pose(psi_true)
    T_cmd = needle_pose(psi_true + lag)
    theta = nd.arc_angles(n_arc)
    pts = np.einsum("fij,aj->fai", T_true[:, :3, :3], nd.point(theta)) + T_true[:, None, :3, 3]
    inside = pts @ m > d_plane
    return Trajectory(
        cam_T_needle=T_true,
        cam_T_grasper=T_true @ nTg,
        cam_T_grasper_cmd=T_cmd @ nTg,
        visible=~inside,
        tip_dropout=np.zeros(F, bool),
        in_grasp_rad=np.zeros(F),
        slipping=slipping,
        tissue_plane=(m, d_plane),
    )


def _scenario_calibration(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    span = float(t[-1]) if t.shape[0] > 1 else 0.0
    n_way = max(int(math.ceil(span / 2.0)) + 1, 2)
    tw = np.linspace(0.0, max(span, 1e-6), n_way)
    depth = np.empty(n_way)
    depth[0] = rng.uniform(0.035, 0.050)
    for i in range(1, n_way):
        depth[i] = np.clip(depth[i - 1] + rng.uniform(-0.008, 0.008), 0.030, 0.060)
    xy = rng.uniform(-0.15, 0.15, (n_way, 2)) * depth[:, None]
    tilt = rng.uniform(0.0, 65.0, n_way)
    az = np.cumsum(rng.uniform(-60.0, 60.0, n_way)) + rng.uniform(0.0, 360.0)
    spin = np.cumsum(rng.uniform(-60.0, 60.0, n_way)) + rng.uniform(0.0, 360.0)
    way = np.column_stack([xy, depth, az, tilt, spin])
    path = PchipInterpolator(tw, way, axis=0)(np.clip(t, 0.0, tw[-1]))
    R = rot_z(np.radians(path[:, 3])) @ rot_x(np.radians(path[:, 4])) @ rot_z(np.radians(path[:, 5]))
    T = homogeneous(R, path[:, :3])
    return _rigid(cfg, T @ needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad), n_arc)


#: ``symmetric``: needle centre depth (the far end of the 30-60 mm working range), metres.
SYMMETRIC_DEPTH_M = 0.060
#: ``symmetric``: angle between the needle normal and the viewing ray (a shallow, grazing view), degrees.
SYMMETRIC_OBLIQUITY_DEG = 65.0
#: ``kinfault``: size of the re-registration jump of the recorded grasper pose, metres.
KINFAULT_JUMP_M = 4.0e-3
#: ``kinfault``: range of the length of each kinematics drop-out, seconds.
KINFAULT_GAP_S = (0.5, 1.0)
#: ``snapshots``: time between frames, seconds (2 Hz: a still every half second).
SNAPSHOT_DT_S = 0.5


def _scenario_symmetric(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    G0 = _base_grasper(cfg, _base_rotation(35.0, SYMMETRIC_OBLIQUITY_DEG, 60.0),
                       np.array([1.0e-3, -1.0e-3, SYMMETRIC_DEPTH_M]))
    centre_g = se3_inverse(needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad))[:3, 3]
    G = _free_motion(rng, t, G0, centre_g, 1.0e-3, math.radians(3.0))
    traj = _rigid(cfg, G, n_arc)
    return Trajectory(**{**traj.__dict__, "tip_dropout": np.ones(t.shape[0], bool)})


def _scenario_drive(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    nd = cfg.needle
    F = t.shape[0]
    T_total = max(float(t[-1]), 1e-9) if F > 1 else 1.0
    u = t / T_total
    nTg = needle_T_grasper(nd, cfg.grasper_tilt_rad)
    sgn = 1.0 if nd.tip_angle_rad >= nd.tail_angle_rad else -1.0
    # the drive turns the needle about the driver's shaft (the grasper axis z_g, needle frame),
    # through the needle centre: the needle plane wobbles by the grasper tilt while the tip advances
    axis_n = nTg[:3, 2]
    beta, eps, protrude = math.radians(35.0), math.radians(4.0), math.radians(10.0)
    theta_d0 = nd.tip_angle_rad + sgn * (beta + eps)
    psi_end = eps + 2.0 * beta + protrude
    h = nd.radius_m * math.cos(beta)
    spin = math.degrees(math.pi / 2.0 - theta_d0)
    u_app, u_drv = 0.1, 0.8
    w_app = np.clip(u / u_app, 0, 1)
    w_drv = np.clip((u - u_app) / (u_drv - u_app), 0, 1)
    psi = sgn * psi_end * _ease(w_drv)

    def turn(angle: np.ndarray) -> np.ndarray:
        a = np.asarray(angle, float)[..., None] * axis_n
        return homogeneous(so3_exp(a), np.zeros(a.shape))

    # base tilt: searched (0.25 deg grid) so the needle is seen exactly edge-on half-way through the drive
    mid = turn(np.array(sgn * psi_end * 0.5))
    tilts = np.arange(90.0, 140.0 + 1e-9, 0.25)  # past edge-on: the drive turns the plane back through it
    ang = np.array([_edge_on_deg(homogeneous(_base_rotation(20.0, a, spin), np.array([0.5e-3, 0.0, 0.045])) @ mid)
                    for a in tilts])
    tilt = float(tilts[int(np.argmin(np.abs(ang - 90.0)))])
    T0 = homogeneous(_base_rotation(20.0, tilt, spin), np.array([0.5e-3, 0.0, 0.045]))
    m = T0[:3, :3] @ np.array([math.cos(theta_d0), math.sin(theta_d0), 0.0])  # inward tissue normal
    d_plane = float(m @ T0[:3, 3]) + h
    approach = 3.0e-3 * (1.0 - _ease(w_app))
    T = T0[None] @ turn(psi)
    T[:, :3, 3] -= approach[:, None] * m[None, :]
    theta = nd.arc_angles(n_arc)
    pts = np.einsum("fij,aj->fai", T[:, :3, :3], nd.point(theta)) + T[:, None, :3, 3]
    G = T @ nTg
    return Trajectory(
        cam_T_needle=T,
        cam_T_grasper=G,
        cam_T_grasper_cmd=G.copy(),
        visible=~(pts @ m > d_plane),
        tip_dropout=np.zeros(F, bool),
        in_grasp_rad=np.zeros(F),
        slipping=np.zeros(F, bool),
        tissue_plane=(m, d_plane),
    )


def kinfault_events(t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, int, np.ndarray]:
    """``kinfault``'s faults: missing-kinematics frames ``(F,)``, the jump frame, the jump vector (3,) m.

    Two drop-outs of ``KINFAULT_GAP_S`` (uniform, at most 10 % of the run each) starting at a
    uniform point of 15-25 % and 60-70 % of the run; the jump at 45 %, in a uniform random
    direction, of ``KINFAULT_JUMP_M``. Runs shorter than 10 frames get no faults.
    """
    F = t.shape[0]
    missing = np.zeros(F, bool)
    span = float(t[-1] - t[0]) if F > 1 else 0.0
    starts = (rng.uniform(0.15, 0.25), rng.uniform(0.60, 0.70))
    lengths = rng.uniform(*KINFAULT_GAP_S, size=2)
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    if F < 10:
        return missing, F, KINFAULT_JUMP_M * direction
    for s0, ln in zip(starts, lengths, strict=True):
        a = t[0] + s0 * span
        missing |= (t >= a) & (t < a + min(float(ln), 0.1 * span))
    return missing, int(round(0.45 * (F - 1))), KINFAULT_JUMP_M * direction


def _scenario_kinfault(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    traj = _scenario_normal(cfg, t, rng, n_arc)
    missing, jump_frame, jump = kinfault_events(t, rng)
    offset = np.broadcast_to(np.eye(4), (t.shape[0], 4, 4)).copy()
    offset[jump_frame:, :3, 3] = jump
    return Trajectory(**{**traj.__dict__, "kinematics_missing": missing, "registration_offset": offset})


def _scenario_snapshots(cfg: SimConfig, t: np.ndarray, rng: np.random.Generator, n_arc: int) -> Trajectory:
    G0 = _base_grasper(cfg, _base_rotation(-20.0, 40.0, 30.0), np.array([0.0, 0.0, 0.045]))
    centre_g = se3_inverse(needle_T_grasper(cfg.needle, cfg.grasper_tilt_rad))[:3, 3]
    G = _free_motion(rng, t, G0, centre_g, 5.0e-3, math.radians(20.0))
    traj = _rigid(cfg, G, n_arc)
    return Trajectory(**{**traj.__dict__, "kinematics_missing": np.ones(t.shape[0], bool)})


def scenario_config(scenario: str, config: SimConfig | None = None) -> SimConfig:
    """The settings a scenario runs with: ``config`` (default :class:`SimConfig`), with ``snapshots``'
    frame interval (``SNAPSHOT_DT_S``) and a mask on every frame (a segmenter runs on every still)."""
    cfg = config or SimConfig()
    if scenario == "snapshots":
        cfg = replace(cfg, frame_rate_hz=1.0 / SNAPSHOT_DT_S, mask_every=1)
    return cfg


_BUILDERS: dict[str, Callable[[SimConfig, np.ndarray, np.random.Generator, int], Trajectory]] = {
    "slow": _scenario_slow,
    "normal": _scenario_normal,
    "rotation": _scenario_rotation,
    "suturing": _scenario_suturing,
    "calibration": _scenario_calibration,
    "symmetric": _scenario_symmetric,
    "drive": _scenario_drive,
    "kinfault": _scenario_kinfault,
    "snapshots": _scenario_snapshots,
}


# ---------------------------------------------------------------------------------------------
# observations


def _check_args(scenario: str, n_frames: int, seed: int) -> None:
    if scenario not in _BUILDERS:
        raise ValueError(f"unknown scenario {scenario!r}; valid scenarios: {', '.join(SCENARIOS)}")
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")


def _streams(scenario: str, seed: int) -> list[np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), SCENARIOS.index(scenario)])
    return [np.random.default_rng(s) for s in ss.spawn(4)]


def _occlusion_labels(visible: np.ndarray) -> list[str]:
    hidden = 1.0 - visible.mean(axis=1)
    tip_hidden = ~visible[:, -1]
    out = []
    for hf, th in zip(hidden, tip_hidden, strict=True):
        if hf <= 0.0:
            out.append("none")
        elif th and hf >= HEAVY_HIDDEN_FRACTION:
            out.append("heavy")
        else:
            out.append("partial")
    return out


def mask_path(frame: int) -> str:
    """Relative path of a frame's mask in a run directory."""
    return f"masks/{frame:06d}.png"


def image_path(frame: int) -> str:
    """Relative path of a frame's camera image in a run directory."""
    return f"images/{frame:06d}.png"


def _recording_extra(scenario: str, seed: int, F: int, cfg: SimConfig, traj: Trajectory,
                     kin_missing: np.ndarray) -> dict:
    """recording.json's extra keys: the simulator's settings, the kinematic faults, suggested switches."""
    sim: dict = {"scenario": scenario, "seed": seed, "n_frames": F, "config": cfg.to_json()}
    if kin_missing.any():
        edges = np.flatnonzero(np.diff(np.concatenate([[0], kin_missing.astype(int), [0]])))
        sim["kinematics_missing"] = [[int(a), int(b) - 1] for a, b in zip(edges[::2], edges[1::2], strict=True)]
    if traj.registration_offset is not None:
        moved = np.flatnonzero(np.any(np.abs(traj.registration_offset - np.eye(4)) > 0, axis=(1, 2)))
        if moved.size:
            k = int(moved[0])
            sim["registration_jump"] = {"frame": k, "offset_m": traj.registration_offset[k, :3, 3].tolist()}
    out: dict = {"simulator": sim}
    if scenario in SUGGESTED_DISABLE:
        out["suggested_disable"] = list(SUGGESTED_DISABLE[scenario])
    return out


@dataclass
class _Pending:
    """Per-frame recorded values decided before any mask is rendered."""

    t_s: np.ndarray
    tip_meas: np.ndarray
    tip_seen: np.ndarray
    tail_meas: np.ndarray
    tail_seen: np.ndarray
    rng_mask: np.random.Generator


def _prepare(scenario: str, n_frames: int, seed: int, config: SimConfig | None) -> tuple[SimRun, _Pending]:
    """Everything but the masks and frame records: trajectory, kinematics, keypoints, labels."""
    _check_args(scenario, n_frames, seed)
    cfg = scenario_config(scenario, config)
    cam, nd = cfg.camera, cfg.needle
    F = int(n_frames)
    t = np.arange(F) * cfg.dt_s
    rng_traj, rng_kin, rng_kp, rng_mask = _streams(scenario, seed)
    theta = nd.arc_angles(ARC_SAMPLES)
    traj = _BUILDERS[scenario](cfg, t, rng_traj, ARC_SAMPLES)
    T = traj.cam_T_needle

    errors = draw_kinematic_errors(
        rng_kin, F, cfg.grasp_position_sigma_m, cfg.perpendicular_sigma, cfg.grasper_rot_sigma_rad,
        cfg.dt_s, cfg.kin_bias_tau_s, cfg.kin_white_var_fraction,
    )
    recorded = apply_kinematic_errors(traj.cam_T_grasper_cmd, errors)
    if traj.registration_offset is not None:
        recorded = traj.registration_offset @ recorded
    kin_missing = np.zeros(F, bool) if traj.kinematics_missing is None else np.asarray(traj.kinematics_missing, bool)

    # keypoints: fixed draws per frame whatever is visible (determinism, independence)
    def keypoint(point_m: np.ndarray, sigma: tuple[float, float], arc_index: int, dropout: np.ndarray):
        p = T[:, :3, :3] @ point_m + T[:, :3, 3]
        px = cam.distort_px(cam.project(p))
        noise = rng_kp.standard_normal((F, 2)) * np.asarray(sigma)
        miss = rng_kp.uniform(size=F) < cfg.keypoint_miss_prob
        ok = (p[:, 2] > 1e-4) & cam.in_image(px, cfg.keypoint_margin_px) & traj.visible[:, arc_index] & ~dropout
        return px, ok, ok & ~miss, px + noise

    tip_true, tip_ok, tip_seen, tip_meas = keypoint(nd.tip_m, cfg.tip_sigma_px, -1, traj.tip_dropout)
    tail_true, tail_ok, tail_seen, tail_meas = keypoint(nd.tail_m, cfg.tail_sigma_px, 0, np.zeros(F, bool))
    info = RecordingInfo(
        name=f"{scenario}-{seed:02d}",
        frame_rate_hz=cfg.frame_rate_hz,
        camera=cam,
        needle=nd,
        extra=_recording_extra(scenario, int(seed), F, cfg, traj, kin_missing),
    )
    run = SimRun(
        scenario=scenario,
        seed=int(seed),
        config=cfg,
        info=info,
        frames=[],
        masks={},
        cam_T_needle=T,
        cam_T_grasper=traj.cam_T_grasper,
        cam_T_grasper_recorded=recorded,
        kinematic_errors=errors,
        arc_theta=theta,
        visible=traj.visible,
        tip_px_true=tip_true,
        tail_px_true=tail_true,
        tip_detectable=tip_ok,
        tail_detectable=tail_ok,
        occlusion=_occlusion_labels(traj.visible),
        in_grasp_rad=traj.in_grasp_rad,
        slipping=traj.slipping,
        edge_on_deg=_edge_on_deg(T),
        tissue_plane=traj.tissue_plane,
        kinematics_missing=kin_missing,
        registration_offset=traj.registration_offset,
    )
    return run, _Pending(t, tip_meas, tip_seen, tail_meas, tail_seen, rng_mask)


def _iter_frames(run: SimRun, pend: _Pending) -> Iterator[tuple[FrameRecord, np.ndarray | None, list[Blob]]]:
    """Frame records in order, with the frame's mask (rendered now, None if none) and its false positives."""
    cfg = run.config
    for k in range(run.cam_T_needle.shape[0]):
        mask, fp = None, []
        if k % cfg.mask_every == 0:
            missed = pend.rng_mask.uniform() < cfg.mask_miss_prob
            m, fp = render_mask(
                cfg.camera, run.cam_T_needle[k], cfg.needle, run.arc_theta, run.visible[k], pend.rng_mask,
                cfg.mask_centreline_sigma_px, cfg.mask_edge_sigma_px, cfg.mask_noise_length_px,
                cfg.mask_min_half_width_px, cfg.fp_blob_prob, cfg.fp_blob_axes_px, cfg.fp_blob_min_distance_px,
                spur_prob=cfg.mask_spur_prob, spur_length_px=cfg.mask_spur_length_px,
            )
            if not missed and np.any(m):
                mask = m
        rec = FrameRecord(
            frame=k,
            t_s=float(pend.t_s[k]),
            tip_px=pend.tip_meas[k].copy() if pend.tip_seen[k] else None,
            tail_px=pend.tail_meas[k].copy() if pend.tail_seen[k] else None,
            mask=mask_path(k) if mask is not None else None,
            cam_T_grasper=None if run.kinematics_missing[k] else run.cam_T_grasper_recorded[k].copy(),
            cam_T_needle_gt=run.cam_T_needle[k].copy(),
            image=None,
            occlusion=run.occlusion[k],
        )
        yield rec, mask, (fp if mask is not None else [])


def simulate_frames(
    scenario: str, n_frames: int = 300, seed: int = 0, config: SimConfig | None = None
) -> SimRun:
    """Simulate a run in memory (module docstring): recorded frames, masks and the noise-free truth.

    Identical to what :func:`simulate` writes for the same arguments. Raises ValueError for an
    unknown scenario (listing the valid ones) or bad sizes. Masks are kept in memory
    (1.2 MB each at 1080x1080): for long runs prefer :func:`simulate`, which streams them.
    """
    run, pend = _prepare(scenario, n_frames, seed, config)
    for rec, mask, fp in _iter_frames(run, pend):
        run.frames.append(rec)
        if mask is not None:
            run.masks[rec.frame] = mask
            run.fp_blobs[rec.frame] = fp
    return run


def render_image(run: SimRun, frame: int, background: np.ndarray | None = None) -> np.ndarray:
    """The camera image ``(H, W, 3)`` BGR uint8 of one frame: tissue, checkerboard, needle (render.py)."""
    from pinpoint_fg.checkerboard import DEFAULT_NEEDLE_T_BOARD, render_board

    cam = run.config.camera
    if background is None:
        background = run_background(run)
    img = render_board(background, cam, run.cam_T_needle[frame] @ DEFAULT_NEEDLE_T_BOARD)
    draw_needle(img, cam, run.cam_T_needle[frame], run.config.needle, run.arc_theta, run.visible[frame])
    return img


def run_background(run: SimRun) -> np.ndarray:
    """The run's static tissue background (deterministic per scenario and seed)."""
    cam = run.config.camera
    return tissue_background(int(cam.width), int(cam.height), SCENARIOS.index(run.scenario) * 100003 + run.seed)


def simulate(
    scenario: str,
    n_frames: int = 300,
    seed: int = 0,
    *,
    out: Path | str,
    images: bool = False,
    config: SimConfig | None = None,
) -> Path:
    """Simulate a run and write it to the directory ``out`` (recording format v1); returns ``out``.

    Frames are written one by one through :class:`pinpoint_fg.io.recording.RecordingWriter`;
    with ``images`` every frame also gets a rendered camera image (:func:`render_image`).
    Same arguments, same bytes. The run is written into a hidden sibling of ``out`` and moved into place at the
    end (:func:`pinpoint_fg.io.outdir.staged_output_dir`; files already in ``out`` are replaced by their
    namesakes, others left alone): a failure half-way (out of memory, Ctrl-C) leaves neither an empty ``out`` nor
    a shorter run that a later command would read as this one.
    """
    from pinpoint_fg.errors import path_argument
    from pinpoint_fg.io.outdir import staged_output_dir
    from pinpoint_fg.io.recording.writer import RecordingWriter

    out = path_argument("out", out)  # "" was the current directory: the run replaced the files there
    run, pend = _prepare(scenario, n_frames, seed, config)
    background = run_background(run) if images else None
    with staged_output_dir(out, True, "simulated run") as stage, RecordingWriter(stage, run.info) as writer:
        for rec, mask, _ in _iter_frames(run, pend):
            img = render_image(run, rec.frame, background) if images else None
            writer.add(rec, mask=mask, image=img)
    return out
