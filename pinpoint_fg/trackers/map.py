"""Single-mode MAP baseline: GTSAM's own fixed-lag smoother over the same factors (DESIGN.md, Baselines).

One ``Pose3`` key per frame, in a ``gtsam.BatchFixedLagSmoother`` (GTSAM_NOTES §3: the
incremental smoother has known marginalisation bugs). Per frame ``k`` the update adds

* the frame's measurement factors, :meth:`pinpoint_fg.likelihood.FrameLikelihood.gtsam_factors`
  (the same residuals and noise as every other method; the cheirality penalty has no factor);
* a :class:`factors.gtsam_factors.MotionFactor` ``Log((D x_{k-1})^-1 x_k)`` with the grasper's
  measured motion ``D`` and the process noise ``Q`` (``config.noise["motion"]``), or ``D = I``
  and the random walk :data:`pinpoint_fg.window.RANDOM_WALK_SIGMA` when the kinematics of either
  frame are missing, on a kinematic fault, or when the motion switch is off; either covariance is
  multiplied by the elapsed-time ``scale`` of :meth:`pinpoint_fg.trackers.base.Tracker.motion_input`
  (:mod:`pinpoint_fg.kinematics_check`, the decision every tracker shares);
* the initial value ``D x_{k-1}`` (the previous estimate moved by the grasper).

The first frame's initial value is the best mode of :func:`pinpoint_fg.init.seed_particles`
(the seeding every tracker shares), held by a weak :class:`PosePriorFactor` of standard
deviations :attr:`MapConfig.prior_sigma` (0.5 rad, 20 mm): enough to fix what one frame cannot
see (e.g. the rotation of a full circle about its normal when only the backbone is observed),
negligible against any real measurement.

**Window.** Time stamps are the step count; the smoother lag is ``L - 1`` for a window of ``L``
frames, so after each update exactly the ``L`` newest poses remain (GTSAM marginalises keys
older than ``t_now - lag`` *after* optimising; the marginal becomes a ``LinearContainerFactor``).
GTSAM's batch smoother keeps the linearisation point of the poses touched by such marginal
factors fixed (first-estimate Jacobians, its ``enforceConsistency`` default, not exposed to
Python), so once marginalisation has started its optimum differs from a plain
Levenberg-Marquardt solve of the same factors by terms of second order in how far those poses
move: identical (1e-11) before, afterwards measured up to 1e-4 rad / 1e-6 m with L = 1 and
5e-6 rad with L = 3 — under 1 % of the posterior standard deviation (tests/test_trackers_map.py).

**Uncertainty.** ``Sigma = gtsam.Marginals(smoother.getFactors(), estimate).marginalCovariance(x_k)``
(the 4.3 wheel's batch smoother has no ``marginalCovariance``), in GTSAM's ``[omega; v]`` right
chart. The q95 spreads come from fixed standard-normal draws ``z_j`` (``MapConfig.q95_samples``
of them, drawn once from the tracker's seed): ``xi_j = S z_j`` with ``S S^T = Sigma``, and
``q95_trans_m`` / ``q95_rot_rad`` are the 95th percentiles of ``|v_j|`` / ``|omega_j|`` — the
same statistic the particle methods report, applied to the Gaussian. Fixed draws keep it
deterministic and smooth from frame to frame (Monte-Carlo error ~2 % at 2000 draws).

**Report.** The newest pose as the single particle; ``log_posterior`` is minus GTSAM's window
error ``1/2 sum |whitened residual|^2`` at the optimum (before the expired pose is marginalised,
up to a constant); ``iterations`` are the smoother's Levenberg-Marquardt iterations; with
``L > 1`` also the smoothed pose of frame ``k - L + 1`` (the oldest still in the window).

**Robustness.** A frame with no factors of its own still gets the motion factor. If GTSAM raises
(an indeterminate system while optimising or marginalising), the smoother is rebuilt from the
last estimate: a Gaussian prior at the previous pose with its last marginal covariance, this
frame's motion and measurement factors, and a weak prior on the new pose (if that raises too, a
fresh start at the predicted pose, and if even that raises — a prediction far from the frame, as
between snapshots 0.5 s apart — a fresh seeding of the frame, ``Estimate.reseeded``). If
``Marginals`` raises, it is retried with weak priors (``prior_sigma``) on every pose of the
window, and failing that the weak prior's covariance is reported. Both count in
``Estimate.extra["recovered"]``. When the estimate explains the frame implausibly badly
(:func:`pinpoint_fg.trackers.base.implausible`, the criterion every tracker shares) the smoother
is restarted from a fresh seeding of the frame (``Estimate.reseeded``); the smoothed output then
pauses until the new window holds ``L`` frames again. Graph keys are
never iterated as temporary ``KeySet`` objects (GTSAM_NOTES §6).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.gtsam_factors import MotionFactor, PosePriorFactor
from pinpoint_fg.eval.metrics import weighted_quantile
from pinpoint_fg.init import InitConfig, seed_particles
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observation import Observation
from pinpoint_fg.trackers.base import Estimate, Tracker, TrackerConfig, implausible
from pinpoint_fg.window import RANDOM_WALK_SIGMA


@dataclass(frozen=True)
class MapConfig:
    """Settings of the fixed-lag MAP smoother beyond :class:`TrackerConfig`."""

    prior_sigma: tuple[float, ...] = (0.5, 0.5, 0.5, 0.02, 0.02, 0.02)
    """Weak prior on the first pose (and on recovery), ``[omega (rad) x3, v (m) x3]``."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per update (at most)."""
    relative_error_tol: float = 1e-6
    """Levenberg-Marquardt stops when the error decreases by less than this fraction."""
    absolute_error_tol: float = 1e-6
    """Levenberg-Marquardt stops when the error decreases by less than this."""
    q95_samples: int = 2000
    """Fixed Gaussian draws used to turn the marginal covariance into q95 spreads."""
    reseed: bool = True
    """Restart from a fresh seeding when the estimate is implausible for the frame."""

    def __post_init__(self) -> None:
        s = np.asarray(self.prior_sigma, dtype=float).reshape(-1)
        if s.shape != (6,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError("prior_sigma must be 6 positive finite numbers [omega x3, v x3]")
        object.__setattr__(self, "prior_sigma", tuple(float(x) for x in s))
        if self.max_iterations < 1 or self.q95_samples < 1:
            raise ValueError("max_iterations and q95_samples must be at least 1")

    def lm_params(self) -> gtsam.LevenbergMarquardtParams:
        """The Levenberg-Marquardt parameters the smoother uses (GTSAM defaults otherwise)."""
        p = gtsam.LevenbergMarquardtParams()
        p.setMaxIterations(int(self.max_iterations))
        p.setRelativeErrorTol(float(self.relative_error_tol))
        p.setAbsoluteErrorTol(float(self.absolute_error_tol))
        return p


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    T = np.asarray(T, dtype=float)
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), gtsam.Point3(*T[:3, 3]))


def _graph(factors: list) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    for f in factors:
        g.add(f)
    return g


def live_factors(graph: gtsam.NonlinearFactorGraph) -> list:
    """The non-empty factors of a graph (the batch smoother leaves ``None`` slots after marginalising)."""
    out = []
    for i in range(graph.size()):
        f = graph.at(i)
        if f is not None:
            out.append(f)
    return out


def gaussian_q95(cov_xi: np.ndarray, z: np.ndarray) -> tuple[float, float]:
    """q95 of ``|v|`` (m) and ``|omega|`` (rad) over ``xi_j = S z_j``, ``S S^T = cov_xi`` (6, 6); z (M, 6)."""
    C = 0.5 * (cov_xi + cov_xi.T)
    w, V = np.linalg.eigh(C)
    S = V * np.sqrt(np.maximum(w, 0.0))
    xi = z @ S.T
    return (float(weighted_quantile(np.linalg.norm(xi[:, 3:], axis=1), None, 0.95)),
            float(weighted_quantile(np.linalg.norm(xi[:, :3], axis=1), None, 0.95)))


class MapTracker(Tracker):
    """GTSAM batch fixed-lag smoother over a window of ``config.window`` frames (module docstring)."""

    method = "map"

    def __init__(self, config: TrackerConfig, map_config: MapConfig = MapConfig()) -> None:
        super().__init__(config)
        if config.window < 1:
            raise ValueError(f"window must be at least 1, got {config.window}")
        self.map = map_config
        self._model = config.model
        self._lag = float(config.window - 1)
        self._prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(map_config.prior_sigma))
        self._walk_noise = gtsam.noiseModel.Diagonal.Sigmas(RANDOM_WALK_SIGMA)
        self._z = np.random.default_rng([config.seed, 95]).standard_normal((map_config.q95_samples, 6))
        self._smoother: gtsam.BatchFixedLagSmoother | None = None
        self._key = -1  # newest key (= step count - 1)
        self._first_key = 0  # oldest key the current smoother has held
        self._stamps: dict[int, tuple[int, float]] = {}  # key -> (frame, t_s)
        self._newest: np.ndarray | None = None
        self._cov: np.ndarray | None = None
        self.last_update: tuple[gtsam.NonlinearFactorGraph, gtsam.Values] | None = None
        """The factors and initial values added by the latest step (for inspection and tests)."""

    @property
    def smoother(self) -> gtsam.BatchFixedLagSmoother | None:
        """The GTSAM smoother (None before the first frame)."""
        return self._smoother

    @property
    def newest_key(self) -> int:
        """GTSAM key of the newest pose (-1 before the first frame)."""
        return self._key

    @property
    def particles(self) -> np.ndarray:
        """(1, 4, 4) the newest estimate; (0, 4, 4) before the first frame."""
        return np.zeros((0, 4, 4)) if self._newest is None else self._newest[None].copy()

    def settings(self) -> dict:
        """Common settings plus the smoother's."""
        out = super().settings()
        out.update(smoother="BatchFixedLagSmoother", lag=self._lag, prior_sigma=list(self.map.prior_sigma),
                   max_iterations=self.map.max_iterations, reseed=self.map.reseed)
        return out

    # ------------------------------------------------------------------ helpers
    def _new_smoother(self) -> gtsam.BatchFixedLagSmoother:
        return gtsam.BatchFixedLagSmoother(self._lag, self.map.lm_params())

    def _seed_pose(self, lik: FrameLikelihood) -> np.ndarray:
        _, modes = seed_particles(lik, max(self.config.particles, InitConfig().max_modes), self.rng)
        return modes[0]

    def _restart(self, frame_factors: list, key: int, cam_T_init: np.ndarray) -> gtsam.FixedLagSmootherResult:
        """A fresh smoother holding only ``key``: its frame factors and a weak prior at ``cam_T_init``."""
        self._smoother = self._new_smoother()
        self._first_key = key
        g = _graph([*frame_factors, PosePriorFactor(key, cam_T_init, self._prior_noise)])
        v = gtsam.Values()
        v.insert(key, _pose3(cam_T_init))
        self.last_update = (g, v)
        return self._smoother.update(g, v, {key: float(key)})

    def _rebuild(self, new_factors: list, key: int, cam_T_init: np.ndarray) -> gtsam.FixedLagSmootherResult:
        """Recovery after GTSAM raised: previous pose as a Gaussian prior, this frame's factors, weak prior."""
        assert self._newest is not None and self._cov is not None
        self._smoother = self._new_smoother()
        self._first_key = key - 1
        prev_noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (self._cov + self._cov.T))
        g = _graph([PosePriorFactor(key - 1, self._newest, prev_noise), *new_factors,
                    PosePriorFactor(key, cam_T_init, self._prior_noise)])
        v = gtsam.Values()
        v.insert(key - 1, _pose3(self._newest))
        v.insert(key, _pose3(cam_T_init))
        return self._smoother.update(g, v, {key - 1: float(key - 1), key: float(key)})

    def _marginal_cov(self, key: int) -> tuple[np.ndarray, bool]:
        """Marginal covariance (6, 6) of ``key``; True when the weak-prior fallback was needed."""
        assert self._smoother is not None
        factors = self._smoother.getFactors()
        est = self._smoother.calculateEstimate()
        try:
            C = gtsam.Marginals(factors, est).marginalCovariance(key)
            used_fallback = False
        except RuntimeError:
            used_fallback = True
            keys = list(est.keys())
            g = _graph(live_factors(factors)
                       + [PosePriorFactor(k, est.atPose3(k), self._prior_noise) for k in keys])
            try:
                C = gtsam.Marginals(g, est).marginalCovariance(key)
            except RuntimeError:  # last resort: the weak prior's covariance
                C = np.diag(np.square(self.map.prior_sigma))
        C = np.asarray(C, dtype=float)
        return 0.5 * (C + C.T), used_fallback

    def _motion_model(self, delta: np.ndarray | None, scale: float) -> tuple[np.ndarray, gtsam.noiseModel.Base]:
        """``(D, noise)`` of the motion factor: the grasper's motion with ``scale * Q``, or the identity
        with ``scale *`` the random walk (no kinematics, a kinematic fault, or the motion switch off)."""
        if delta is None or not self.config.switches.motion:
            if scale == 1.0:
                return np.eye(4), self._walk_noise
            return np.eye(4), gtsam.noiseModel.Diagonal.Sigmas(RANDOM_WALK_SIGMA * np.sqrt(scale))
        if scale == 1.0:
            return delta, self.config.noise["motion"].gtsam_model()
        return delta, gtsam.noiseModel.Gaussian.Covariance(scale * self.config.noise.process_cov)

    # ------------------------------------------------------------------ step
    def step(self, observation: Observation) -> Estimate:
        """Add the frame to the smoother, optimise, report the newest pose and its marginal (module docstring)."""
        t0 = time.perf_counter()
        motion = self.motion_input(observation)
        lik = FrameLikelihood(motion.observation, self._model)
        delta = motion.delta
        key = self._key + 1
        frame_factors = lik.gtsam_factors(key)
        recovered = 0
        reseeded = False
        if self._smoother is None:
            result = self._restart(frame_factors, key, self._seed_pose(lik))
        else:
            assert self._newest is not None
            D, noise = self._motion_model(delta, motion.scale)
            new_factors = [*frame_factors, MotionFactor(key - 1, key, D, noise)]
            cam_T_init = D @ self._newest
            g = _graph(new_factors)
            v = gtsam.Values()
            v.insert(key, _pose3(cam_T_init))
            self.last_update = (g, v)
            try:
                result = self._smoother.update(g, v, {key: float(key)})
            except RuntimeError:
                recovered += 1
                try:
                    result = self._rebuild(new_factors, key, cam_T_init)
                except RuntimeError:  # the previous pose's prior is the problem: start over from here
                    try:
                        result = self._restart(frame_factors, key, cam_T_init)
                    except RuntimeError:  # the prediction itself is unusable (e.g. a far snapshot): re-seed
                        result = self._restart(frame_factors, key, self._seed_pose(lik))
                        reseeded = True
        assert self._smoother is not None
        est = self._smoother.calculateEstimatePose3(key).matrix()
        if self.map.reseed and key > self._first_key and implausible(float(lik.nll(est)[0]), lik):
            result = self._restart(frame_factors, key, self._seed_pose(lik))
            est = self._smoother.calculateEstimatePose3(key).matrix()
            reseeded = True
        self._key = key
        self._stamps[key] = (observation.frame, observation.t_s)
        self._newest = est
        cov, fell_back = self._marginal_cov(key)
        recovered += int(fell_back)
        self._cov = cov
        q_t, q_r = gaussian_q95(cov, self._z)
        smoothed = None
        old = key - (self.config.window - 1)
        if self.config.window > 1 and old >= self._first_key:
            frame, t_s = self._stamps[old]
            smoothed = (frame, t_s, self._smoother.calculateEstimatePose3(old).matrix())
        for k in [k for k in self._stamps if k < old]:
            del self._stamps[k]
        error = float(result.getError())
        self.frames_seen += 1
        return Estimate(
            frame=observation.frame,
            t_s=observation.t_s,
            cam_T_needle=est.copy(),
            q95_trans_m=q_t,
            q95_rot_rad=q_r,
            cov_xi=cov,
            iterations=max(int(result.getIterations()), 1),
            latency_ms=(time.perf_counter() - t0) * 1e3,
            particles=est[None].copy(),
            log_posterior=np.array([-error]),
            weights=None,
            smoothed=smoothed,
            reseeded=reseeded,
            extra={"recovered": recovered, "window_error": error, **self.kinematics_extra(motion)},
        )
