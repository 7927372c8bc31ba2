"""What every tracker shares: the per-frame estimate, the ``step(observation)`` interface, reporting.

A tracker is fed one :class:`pinpoint_fg.observation.Observation` at a time and returns an
:class:`pinpoint_fg.estimate.Estimate`. The MAP pose, the q95 spread and the tangent covariance are computed the
same way for every method (paper §IV "Uncertainty Estimation"): tangent vectors
``xi_i = Log(T_map^-1 T_i)`` of all particles around the MAP particle, the (weighted) 95th
percentile of ``|v|`` and ``|omega|``, and their weighted covariance.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from pinpoint_fg.estimate import Estimate
from pinpoint_fg.kinematics_check import KinematicsCheckConfig, KinematicsMonitor, MotionInput
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.noise import format_robust
from pinpoint_fg.observation import Observation
from pinpoint_fg.posterior.spread import tangent_spread

#: :func:`implausible` fires when the best hypothesis's root-mean-square whitened residual exceeds this.
IMPLAUSIBLE_RMS_SIGMA = 5.0


def implausible(best_nll: float, lik: FrameLikelihood, rms_sigma: float = IMPLAUSIBLE_RMS_SIGMA) -> bool:
    """True when even the best hypothesis cannot explain this frame, so the hypotheses should be re-seeded.

    With ``m = lik.dim`` whitened residuals, ``2 nll`` at the true pose is about chi-square(m)
    (mean ``m``). The criterion is ``nll > 1/2 rms_sigma^2 m``: the best pose's residuals are
    ``rms_sigma`` (5) standard deviations off on average, far outside chi-square's range for every
    ``m`` (for m = 2 the chance is e^-25, for m = 200 it is nil) but still tolerant of a moderately
    mis-calibrated noise model. The cheirality penalty is part of ``nll`` and counts against it.
    With robust losses the threshold is the same statement in their units:
    :meth:`~pinpoint_fg.likelihood.FrameLikelihood.loss_at_rms` (every block ``rms_sigma`` off).
    A frame without residuals (``m = 0``: no image evidence, no kinematics) can judge nothing and
    returns False; a non-finite ``best_nll`` returns True.
    """
    if not np.isfinite(best_nll):
        return True
    if lik.dim == 0:
        return False
    return bool(best_nll > lik.loss_at_rms(rms_sigma))



def summarize(particles: np.ndarray, log_posterior: np.ndarray, weights: np.ndarray | None = None,
              map_index: int | None = None) -> tuple[int, float, float, np.ndarray]:
    """MAP index (highest log-posterior unless given), q95 translation (m), q95 rotation (rad), covariance (6, 6)."""
    i = int(np.argmax(log_posterior)) if map_index is None else int(map_index)
    sp = tangent_spread(particles[i], particles, weights)
    return i, float(sp.q95_trans_m), float(sp.q95_rot_rad), np.asarray(sp.cov_xi)


@dataclass(frozen=True)
class TrackerConfig(MeasurementModel):
    """Settings common to every tracker: a :class:`~pinpoint_fg.likelihood.MeasurementModel` (camera, needle,
    noise, switches, depth penalty: declared once, there) extended by the inference settings below."""

    particles: int = 50
    """Number of hypotheses."""
    window: int = 1
    """Window length L (1 = filter)."""
    seed: int = 0
    """Random seed (initial spread, PF noise)."""
    kinematics: KinematicsCheckConfig = KinematicsCheckConfig()
    """Elapsed-time scaling of the process noise and the kinematic jump test (:mod:`pinpoint_fg.kinematics_check`)."""

    @property
    def model(self) -> MeasurementModel:
        """The measurement model every frame's likelihood uses (the measurement fields alone)."""
        return MeasurementModel(self.camera, self.needle, self.noise, self.switches, self.min_depth_m,
                                self.conic_distance)


class Tracker(abc.ABC):
    """Feed observations one at a time with :meth:`step`; read :attr:`particles` at any time."""

    method: str = "base"

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        self.kinematics = KinematicsMonitor(config.noise.process_cov, config.kinematics)
        self.frames_seen = 0

    @abc.abstractmethod
    def step(self, observation: Observation) -> Estimate:
        """Process one frame and return its estimate."""

    @property
    @abc.abstractmethod
    def particles(self) -> np.ndarray:
        """(N, 4, 4) current hypotheses (newest frame)."""

    def settings(self) -> dict:
        """JSON-serialisable settings written to result.json."""
        c = self.config
        k = c.kinematics
        return {"method": self.method, "particles": c.particles, "window": c.window, "seed": c.seed,
                "disabled": list(c.switches.disabled()), "robust": format_robust(c.noise.robust),
                "conic_correlation_px": c.noise.conic_correlation_px, "conic_distance": c.conic_distance,
                "kinematics_check": {"reference_dt_s": k.reference_dt_s, "jump_quantile": k.jump_quantile,
                                     "max_test_gap_s": k.max_test_gap_s, "max_scale": k.max_scale,
                                     "correct_registration": k.correct_registration,
                                     "detect_jumps": k.detect_jumps}}

    def motion_input(self, observation: Observation) -> MotionInput:
        """Frame k's motion input, the same decision for every method (:mod:`pinpoint_fg.kinematics_check`).

        ``delta`` is ``D = cam_T_grasper(k) cam_T_grasper(k-1)^-1`` when both frames have
        kinematics and no jump was detected, else None; ``scale`` multiplies the per-frame process
        (or random-walk) covariance by the elapsed time; ``observation`` has the estimated
        registration offset removed from its grasper pose and is what the likelihood must use.
        """
        return self.kinematics.update(observation)

    @staticmethod
    def kinematics_extra(motion: MotionInput) -> dict:
        """Result columns of the kinematics decision: ``kinematics_fault`` (0/1) and ``process_scale``."""
        return {"kinematics_fault": float(motion.fault), "process_scale": float(motion.scale)}
