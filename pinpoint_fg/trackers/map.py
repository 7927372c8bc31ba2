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
error ``1/2 sum |whitened residual|^2`` (``rho(|e|)`` for the factors with a robust loss, see
:mod:`factors.robust`) at the optimum (before the expired pose is marginalised,
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
is restarted from a fresh seeding of the frame (``Estimate.reseeded``). Graph keys are
never iterated as temporary ``KeySet`` objects (GTSAM_NOTES §6).

**Smoothed poses across a restart.** Every frame gets exactly one smoothed pose, when it leaves the
window (the last ``L - 1`` at the end, :meth:`MapSmoother.remaining_smoothed`). A smoother rebuilt or
restarted at frame ``k`` no longer holds the earlier frames still in the window; they keep the smoothed
poses they had before frame ``k`` was added (:meth:`MapSmoother.pending`, conditioned on the frames up
to ``k - 1``) and are reported at those, frozen (``MapSmoother.inherited``): the rebuilt smoother
summarises them by a prior on one pose and cannot re-smooth them. The ``mht`` bank hands its branches'
poses on the same way (its module docstring).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from factors.gtsam_factors import MotionFactor, PosePriorFactor
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.init import InitConfig, seed_particles
from pinpoint_fg.kinematics_check import MotionInput
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observation import Observation
from pinpoint_fg.posterior.spread import weighted_quantile
from pinpoint_fg.trackers.base import Tracker, TrackerConfig, implausible
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


def motion_model(config: TrackerConfig, motion: MotionInput) -> tuple[np.ndarray, gtsam.noiseModel.Base, np.ndarray]:
    """``(D, noise model, covariance)`` of the motion factor into a frame, shared by ``map`` and ``mht``.

    The grasper's motion ``D`` with ``scale * Q`` (the process covariance), or the identity with
    ``scale *`` the random walk when there is no motion input (no kinematics, a kinematic fault, the
    motion switch off); ``scale`` is the elapsed-time factor of :class:`pinpoint_fg.kinematics_check.MotionInput`.
    """
    scale = float(motion.scale)
    if motion.delta is None or not config.switches.motion:
        cov = np.diag(RANDOM_WALK_SIGMA**2) * scale
        return np.eye(4), gtsam.noiseModel.Diagonal.Sigmas(RANDOM_WALK_SIGMA * np.sqrt(scale)), cov
    noise = config.noise["motion"]
    if scale == 1.0:
        return motion.delta, noise.gtsam_model(), noise.cov
    cov = scale * config.noise.process_cov
    return motion.delta, gtsam.noiseModel.Gaussian.Covariance(cov), cov


class MapSmoother:
    """One single-mode GTSAM fixed-lag smoother and its bookkeeping (shared by ``map`` and the ``mht`` bank).

    Builds the graph exactly as the module docstring says: :meth:`restart` (a fresh smoother on
    one key: its frame factors and a prior), :meth:`advance` (motion + frame factors, with the
    recovery after GTSAM raises), :meth:`finish` (estimate, marginal covariance, smoothed pose).
    """

    def __init__(self, map_config: MapConfig, window: int) -> None:
        self.map = map_config
        self.window = int(window)
        self.lag = float(window - 1)
        self.prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(map_config.prior_sigma))
        self.smoother: gtsam.BatchFixedLagSmoother | None = None
        self.key = -1  # newest key
        self.first_key = 0  # oldest key the current smoother has held
        self.stamps: dict[int, tuple[int, float]] = {}  # key -> (frame, t_s)
        self.newest: np.ndarray | None = None
        self.cov: np.ndarray | None = None
        self.last_update: tuple[gtsam.NonlinearFactorGraph, gtsam.Values] | None = None
        self.inherited: dict[int, tuple[int, float, np.ndarray]] = {}  # key -> smoothed pose, keys < first_key
        self.before: dict[int, tuple[int, float, np.ndarray]] = {}  # pending() as of before the latest key

    def _new_smoother(self) -> gtsam.BatchFixedLagSmoother:
        return gtsam.BatchFixedLagSmoother(self.lag, self.map.lm_params())

    def restart(self, frame_factors: list, key: int, cam_T_init: np.ndarray,
                prior: tuple[np.ndarray, gtsam.noiseModel.Base] | None = None,
                inherit: dict[int, tuple[int, float, np.ndarray]] | None = None) -> gtsam.FixedLagSmootherResult:
        """A fresh smoother holding only ``key``: its frame factors and a prior (default: weak, at ``cam_T_init``).

        ``inherit``: the smoothed poses of the frames before ``key`` not yet reported (a :meth:`pending` taken
        before this frame), which the fresh smoother cannot hold; :meth:`smoothed_at` reports them as they are.
        """
        self._hand_over(key, inherit)
        self.before = dict(self.inherited)  # a branch started here: what it inherited is its pending before `key`
        self.smoother = self._new_smoother()
        self.first_key = key
        mean, noise = (cam_T_init, self.prior_noise) if prior is None else prior
        g = _graph([*frame_factors, PosePriorFactor(key, mean, noise)])
        v = gtsam.Values()
        v.insert(key, _pose3(cam_T_init))
        self.last_update = (g, v)
        return self.smoother.update(g, v, {key: float(key)})

    def _rebuild(self, new_factors: list, key: int, cam_T_init: np.ndarray) -> gtsam.FixedLagSmootherResult:
        """Recovery after GTSAM raised: previous pose as a Gaussian prior, this frame's factors, weak prior."""
        assert self.newest is not None and self.cov is not None
        self._hand_over(key - 1, self.before)
        self.smoother = self._new_smoother()
        self.first_key = key - 1
        prev_noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (self.cov + self.cov.T))
        g = _graph([PosePriorFactor(key - 1, self.newest, prev_noise), *new_factors,
                    PosePriorFactor(key, cam_T_init, self.prior_noise)])
        v = gtsam.Values()
        v.insert(key - 1, _pose3(self.newest))
        v.insert(key, _pose3(cam_T_init))
        return self.smoother.update(g, v, {key - 1: float(key - 1), key: float(key)})

    def advance(self, frame_factors: list, key: int, D: np.ndarray, motion_noise: gtsam.noiseModel.Base
                ) -> tuple[gtsam.FixedLagSmootherResult, int]:
        """Add ``key`` with its frame factors and the motion factor from ``key - 1``; returns (result, recoveries)."""
        assert self.smoother is not None and self.newest is not None
        self.before = self.pending()
        new_factors = [*frame_factors, MotionFactor(key - 1, key, D, motion_noise)]
        cam_T_init = D @ self.newest
        g = _graph(new_factors)
        v = gtsam.Values()
        v.insert(key, _pose3(cam_T_init))
        self.last_update = (g, v)
        try:
            return self.smoother.update(g, v, {key: float(key)}), 0
        except RuntimeError:
            try:
                return self._rebuild(new_factors, key, cam_T_init), 1
            except RuntimeError:  # the previous pose's prior is the problem: start over from here
                return self.restart(frame_factors, key, cam_T_init, inherit=self.before), 1

    def estimate(self, key: int) -> np.ndarray:
        """(4, 4) the smoother's current estimate of ``key``."""
        assert self.smoother is not None
        return self.smoother.calculateEstimatePose3(key).matrix()

    def marginal_cov(self, key: int) -> tuple[np.ndarray, bool]:
        """Marginal covariance (6, 6) of ``key``; True when the weak-prior fallback was needed."""
        assert self.smoother is not None
        factors = self.smoother.getFactors()
        est = self.smoother.calculateEstimate()
        try:
            C = gtsam.Marginals(factors, est).marginalCovariance(key)
            used_fallback = False
        except RuntimeError:
            used_fallback = True
            keys = list(est.keys())
            g = _graph(live_factors(factors)
                       + [PosePriorFactor(k, est.atPose3(k), self.prior_noise) for k in keys])
            try:
                C = gtsam.Marginals(g, est).marginalCovariance(key)
            except RuntimeError:  # last resort: the weak prior's covariance
                C = np.diag(np.square(self.map.prior_sigma))
        C = np.asarray(C, dtype=float)
        return 0.5 * (C + C.T), used_fallback

    def finish(self, key: int, frame: int, t_s: float, est: np.ndarray
               ) -> tuple[np.ndarray, bool, tuple[int, float, np.ndarray] | None]:
        """Record ``key`` as the newest; returns its marginal covariance, whether it fell back, the smoothed pose."""
        self.key = key
        self.stamps[key] = (frame, t_s)
        self.newest = est
        cov, fell_back = self.marginal_cov(key)
        self.cov = cov
        old = key - (self.window - 1)
        smoothed = self.smoothed_at(old) if self.window > 1 else None
        for k in [k for k in self.stamps if k < old]:
            del self.stamps[k]
        for k in [k for k in self.inherited if k < old]:
            del self.inherited[k]
        return cov, fell_back, smoothed

    def smoothed_at(self, key: int) -> tuple[int, float, np.ndarray] | None:
        """``(frame, t_s, pose)`` of ``key`` at its current smoothed value: the smoother's estimate while it holds
        the key, else the inherited pose (a restart or a branch started after it); None when neither has it."""
        if key >= self.first_key and key in self.stamps:
            return (*self.stamps[key], self.estimate(key))
        return self.inherited.get(key)

    def pending(self) -> dict[int, tuple[int, float, np.ndarray]]:
        """The window's poses :meth:`finish` has not reported as smoothed yet (its last ``L - 1`` keys, each at its
        current smoothed value, inherited ones included), by key; empty with ``L = 1`` or before the first key."""
        if self.window <= 1 or self.smoother is None or self.key < 0:
            return {}
        out = {}
        # keys start at 0: a window longer than the run (L = 1e9) walked a billion keys before it on every frame
        for k in range(max(0, self.key - (self.window - 1) + 1), self.key + 1):
            s = self.smoothed_at(k)
            if s is not None:
                out[k] = s
        return out

    def _hand_over(self, first_key: int, inherit: dict[int, tuple[int, float, np.ndarray]] | None) -> None:
        """Keep the poses of ``inherit`` older than ``first_key`` (copied) as this smoother's inherited ones."""
        self.inherited = {k: (f, t, T.copy()) for k, (f, t, T) in (inherit or {}).items() if k < first_key}

    def remaining_smoothed(self) -> list[tuple[int, float, np.ndarray]]:
        """At the end of a run: the window's poses :meth:`finish` has not reported as smoothed (its last
        ``L - 1`` frames, inherited ones included), each at its smoothed value, oldest first."""
        return [v for _, v in sorted(self.pending().items())]


class MapTracker(Tracker):
    """GTSAM batch fixed-lag smoother over a window of ``config.window`` frames (module docstring)."""

    method = "map"

    def __init__(self, config: TrackerConfig, map_config: MapConfig = MapConfig()) -> None:
        super().__init__(config)
        if config.window < 1:
            raise ValueError(f"window must be at least 1, got {config.window}")
        self.map = map_config
        self._model = config.model
        self._branch = MapSmoother(map_config, config.window)
        self._z = np.random.default_rng([config.seed, 95]).standard_normal((map_config.q95_samples, 6))

    @property
    def smoother(self) -> gtsam.BatchFixedLagSmoother | None:
        """The GTSAM smoother (None before the first frame)."""
        return self._branch.smoother

    @property
    def _smoother(self) -> gtsam.BatchFixedLagSmoother | None:
        return self._branch.smoother

    @_smoother.setter
    def _smoother(self, value: gtsam.BatchFixedLagSmoother | None) -> None:  # tests inject failures here
        self._branch.smoother = value

    @property
    def last_update(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values] | None:
        """The factors and initial values added by the latest step (for inspection and tests)."""
        return self._branch.last_update

    @property
    def newest_key(self) -> int:
        """GTSAM key of the newest pose (-1 before the first frame)."""
        return self._branch.key

    def final_smoothed(self) -> list[tuple[int, float, np.ndarray]]:
        """``(frame, t_s, cam_T_needle)`` of the window's last ``L - 1`` frames at the end of a run (their smoothed
        poses are not reported by :meth:`step`); ``track`` writes them to smoothed.csv."""
        return self._branch.remaining_smoothed()

    @property
    def particles(self) -> np.ndarray:
        """(1, 4, 4) the newest estimate; (0, 4, 4) before the first frame."""
        b = self._branch
        return np.zeros((0, 4, 4)) if b.newest is None else b.newest[None].copy()

    def settings(self) -> dict:
        """Common settings plus the smoother's."""
        out = super().settings()
        out.update(smoother="BatchFixedLagSmoother", lag=self._branch.lag, prior_sigma=list(self.map.prior_sigma),
                   max_iterations=self.map.max_iterations, reseed=self.map.reseed)
        return out

    def _seed_pose(self, lik: FrameLikelihood) -> np.ndarray:
        _, modes = seed_particles(lik, max(self.config.particles, InitConfig().max_modes), self.rng)
        return modes[0]

    # ------------------------------------------------------------------ step
    def step(self, observation: Observation) -> Estimate:
        """Add the frame to the smoother, optimise, report the newest pose and its marginal (module docstring)."""
        t0 = time.perf_counter()
        motion = self.motion_input(observation)
        lik = FrameLikelihood(motion.observation, self._model)
        b = self._branch
        key = b.key + 1
        frame_factors = lik.gtsam_factors(key)
        recovered = 0
        reseeded = False
        if b.smoother is None:
            result = b.restart(frame_factors, key, self._seed_pose(lik))
        else:
            D, motion_noise, _ = motion_model(self.config, motion)
            try:
                result, recovered = b.advance(frame_factors, key, D, motion_noise)
            except RuntimeError:  # even a restart at the prediction raised (e.g. a far snapshot): re-seed
                result, recovered = b.restart(frame_factors, key, self._seed_pose(lik), inherit=b.before), 1
                reseeded = True
        est = b.estimate(key)
        if self.map.reseed and key > b.first_key and implausible(float(lik.nll(est)[0]), lik):
            result = b.restart(frame_factors, key, self._seed_pose(lik), inherit=b.before)
            est = b.estimate(key)
            reseeded = True
        cov, fell_back, smoothed = b.finish(key, observation.frame, observation.t_s, est)
        recovered += int(fell_back)
        q_t, q_r = gaussian_q95(cov, self._z)
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
