"""Per-frame judgement of the kinematics: elapsed time, drop-outs and re-registration jumps.

Every tracker asks :class:`KinematicsMonitor` once per frame what motion input to use; all of
them (SVN, SVGD, PF, MAP) therefore take the same decisions with the same widened noise.

**Motion model.** Between consecutive frames the needle moves with the grasper's measured motion
``D = G_k G_{k-1}^-1`` (``G`` = ``cam_T_grasper``) plus a random walk, or — when ``D`` is not
available — stays where it was plus a random walk (constant pose + random walk). The per-frame
covariances of the noise config (``Q``, :data:`pinpoint_fg.noise.DEFAULT_MOTION_SIGMA`) and the
walk (:data:`pinpoint_fg.window.RANDOM_WALK_SIGMA`, 5 deg and 1 mm) are stated for one frame at
30 Hz (``reference_dt_s``). A random walk's covariance grows linearly with elapsed time, so a
frame ``dt`` after its predecessor uses ``scale * Q`` (or ``scale * walk``) with
``scale = dt / reference_dt_s``. Without kinematics that is the walk's per-second covariance:
``5 deg * sqrt(30) = 27 deg`` and ``5.5 mm`` per ``sqrt(s)`` (a still every 0.5 s: 19 deg,
3.9 mm per axis). Decisions where the text above is silent:

* ``scale`` is never below 1: the per-frame ``Q`` also holds the noise of the measured motion,
  which does not shrink with a faster camera; time-stamp jitter of 0.1 % counts as one frame.
* ``scale`` is capped at ``max_scale`` (64: ~2 s at 30 Hz, a walk of 40 deg and 8 mm), beyond
  which the prior is uninformative anyway; a non-increasing or missing time step counts as one
  frame.
* ``D`` needs the kinematics of *both* frames. The first frame with kinematics after a drop-out
  has no motion input (the hypotheses of frame ``k-1`` already absorbed the drop-out's images,
  so the grasper's motion over the whole gap cannot be applied to them); the grasper is simply
  re-referenced there and the next frame's ``D`` is used normally.

**Jump test** (a re-registration of camera and robot, a glitch of the robot's reported pose).
The grasper's own motion is tested, not a tracker's hypotheses, so the decision is the same for
every method: from the last two frames with kinematics a constant-velocity prediction
``G_pred = G_{k-1} Exp(V dt_k)``, ``V = Log(G_{k-2}^-1 G_{k-1}) / dt_{k-1}`` (body frame; a
constant pose when only one previous frame is known), and the residual
``r = Log(G_pred^-1 G_k)`` (``[omega; v]``, grasper body frame) gives
``chi2 = r^T (c scale Q)^-1 r`` with ``c = 3`` for the constant-velocity prediction (a second
difference of white measurement noise has 3x the variance of the first difference, which is
what Q bounds) and ``c = 1`` for a constant pose. A fault is declared when ``chi2`` exceeds the chi-square(6)
quantile ``jump_quantile`` (0.999: 22.46). ``Q`` is the needle's process covariance used as the
grasper's: the rotation part is frame independent, the translation part differs by the lever
arm between grasp point and needle centre (``|omega| r`` ~ 0.1 mm at 0.02 rad, below Q's
0.3 mm). The test only runs when the previous frame had kinematics and is at most
``max_test_gap_s`` old: a jump inside a drop-out cannot be told from motion and is not tested
(limitation).

**On a fault** the frame gets no motion input (``delta`` None: constant pose + the widened walk,
so the hypotheses re-anchor on the image instead of being dragged 4 mm by a jump the needle did
not make), the jump is taken as a change of registration and removed from this and every later
absolute grasper pose (``G <- J^-1 G``; ``correct_registration``), so the grasp-position factor
stays unbiased, and the grasper is re-referenced at the corrected pose so the following frames'
relative motions are used normally. ``J`` is the *translation* ``p_k - p_pred`` only: one
frame's rotation residual is dominated by the recorded orientation's noise (the simulator's
perpendicularity angle alone has 0.8 deg of white noise per frame), and a rotation about the
camera origin estimated from it would move every later grasp point by ``angle x 45 mm`` ~ 1 mm
(measured: 1.5 mm), while the translation of the jump is recovered to ~0.3 mm (6 seeds: at most
0.4 mm per axis). A rotational re-registration is therefore only re-referenced, not corrected,
and biases the perpendicularity factor (limitation). Without ``correct_registration`` the
velocity history restarts at the raw pose and the absolute grasp factors see the offset. A false
alarm costs one frame without motion input and a registration "correction" of the size of that
frame's unexplained motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import gammaincinv

from factors.lie import se3_exp, se3_inverse, se3_log
from pinpoint_fg.observation import Observation

#: Covariance of the constant-velocity residual in units of Q: it differences two measured motions,
#: and for white measurement noise ``w_k - 2 w_{k-1} + w_{k-2}`` has 3x the variance of one motion
#: ``w_k - w_{k-1}`` (Q). Measured false-alarm rate at 3 Q: 1 of 8372 clean frames (module docstring).
CONSTANT_VELOCITY_COV_FACTOR = 3.0


@dataclass(frozen=True)
class KinematicsCheckConfig:
    """How elapsed time, drop-outs and jumps of the kinematics are handled (module docstring)."""

    reference_dt_s: float = 1.0 / 30.0
    """Frame interval the per-frame process covariance Q and the random walk refer to, seconds (30 Hz)."""
    jump_quantile: float = 0.999
    """A frame is a kinematic fault when its motion residual's chi2 exceeds this chi-square(6) quantile."""
    max_test_gap_s: float = 0.2
    """The jump test needs the previous frame's kinematics at most this old, seconds."""
    max_scale: float = 64.0
    """Largest multiplier of the per-frame covariance (elapsed reference frames)."""
    correct_registration: bool = True
    """Remove a detected jump from the later absolute grasper poses (a re-registration), else only re-reference."""
    detect_jumps: bool = True
    """Run the jump test (False: every measured motion is applied, as before fault handling; for comparisons)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.reference_dt_s) and self.reference_dt_s > 0):
            raise ValueError(f"reference_dt_s must be positive, got {self.reference_dt_s!r}")
        if not 0.0 < self.jump_quantile < 1.0:
            raise ValueError(f"jump_quantile must lie in (0, 1), got {self.jump_quantile!r}")
        if not self.max_test_gap_s > 0 or not self.max_scale >= 1.0:
            raise ValueError("max_test_gap_s must be positive and max_scale at least 1")

    @property
    def threshold(self) -> float:
        """The chi-square(6) threshold of the jump test (22.46 at 0.999).

        ``2 P^-1(3, q)``, the regularised lower incomplete gamma function's inverse: the formula of
        ``scipy.stats.chi2.ppf(q, 6)``, bit for bit (``tests/test_trackers_kinematics.py``), without importing
        ``scipy.stats`` (~0.6 s of every command's start-up, and of each worker process ``track`` spawns).
        """
        return float(2.0 * gammaincinv(3.0, self.jump_quantile))


@dataclass(frozen=True)
class MotionInput:
    """What a tracker uses to predict frame k from frame k-1."""

    observation: Observation
    """The frame, with the registration offset removed from its grasper pose."""
    delta: np.ndarray | None
    """``D`` (4, 4) to apply to the hypotheses, or None: constant pose + random walk."""
    scale: float
    """Multiplier of the per-frame covariance (Q with ``delta``, the random walk without)."""
    dt_s: float
    """Time since the previous frame, seconds (nan on the first frame)."""
    fault: bool
    """A kinematic jump was detected on this frame."""
    chi2: float
    """The jump test's statistic (nan when not tested)."""


def elapsed_scale(dt_s: float, config: KinematicsCheckConfig) -> float:
    """``clip(dt / reference_dt, 1, max_scale)``; 1 for a non-finite or non-positive ``dt`` (module docstring)."""
    if not math.isfinite(dt_s) or dt_s <= 0:
        return 1.0
    n = dt_s / config.reference_dt_s
    return 1.0 if n <= 1.0 + 1e-3 else float(min(n, config.max_scale))


class KinematicsMonitor:
    """Feeds one observation per frame to :meth:`update`; keeps the grasper history and registration."""

    def __init__(self, process_cov: np.ndarray, config: KinematicsCheckConfig | None = None) -> None:
        """``process_cov``: the per-frame motion covariance Q (6, 6), ``[omega; v]``."""
        self.config = config or KinematicsCheckConfig()
        Q = 0.5 * (np.asarray(process_cov, dtype=float) + np.asarray(process_cov, dtype=float).T)
        if Q.shape != (6, 6):
            raise ValueError(f"process_cov must be (6, 6), got {Q.shape}")
        self._Q_inv = np.linalg.inv(Q)
        self._threshold = self.config.threshold
        self._t_prev: float | None = None
        self._hist: list[tuple[float, np.ndarray]] = []  # (t_s, corrected G) of consecutive frames with kinematics
        self.registration = np.eye(4)
        """Current registration correction ``C``: corrected pose = ``C^-1 G``."""
        self._C_inv = np.eye(4)
        self.faults: list[int] = []
        """Frame indices flagged so far."""

    def update(self, observation: Observation) -> MotionInput:
        """Decide frame k's motion input (module docstring)."""
        cfg = self.config
        t = float(observation.t_s)
        dt = float("nan") if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        scale = elapsed_scale(dt, cfg)
        raw = observation.cam_T_grasper
        if raw is None:
            self._hist = []
            return MotionInput(observation, None, scale, dt, False, float("nan"))
        G = self._C_inv @ np.asarray(raw, dtype=float)
        hist = self._hist
        delta: np.ndarray | None = None
        fault = False
        chi2 = float("nan")
        if hist:
            t1, G1 = hist[-1]
            if cfg.detect_jumps and 0.0 < t - t1 <= cfg.max_test_gap_s:
                pred, c = G1, 1.0
                if len(hist) >= 2 and t1 > hist[-2][0]:
                    t0, G0 = hist[-2]
                    V = se3_log(se3_inverse(G0) @ G1) / (t1 - t0)
                    pred, c = G1 @ se3_exp(V * (t - t1)), CONSTANT_VELOCITY_COV_FACTOR
                r = se3_log(se3_inverse(pred) @ G)
                chi2 = float(r @ self._Q_inv @ r) / (c * scale)
                fault = chi2 > self._threshold
            if fault:
                self.faults.append(int(observation.frame))
                if cfg.correct_registration:
                    J = np.eye(4)
                    J[:3, 3] = G[:3, 3] - pred[:3, 3]  # translation only (module docstring)
                    self._C_inv = se3_inverse(J) @ self._C_inv
                    self.registration = se3_inverse(self._C_inv)
                    G = se3_inverse(J) @ G
                    hist = [*hist[-1:], (t, G)]
                else:
                    hist = [(t, G)]
            else:
                delta = G @ se3_inverse(G1)
                hist = [*hist[-1:], (t, G)]
        else:
            hist = [(t, G)]
        self._hist = hist
        obs = observation if np.array_equal(G, raw) else replace(observation, cam_T_grasper=G)
        return MotionInput(obs, delta, scale, dt, fault, chi2)
