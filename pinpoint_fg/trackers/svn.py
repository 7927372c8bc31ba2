"""PinPoint: Stein Variational Newton transport of per-hypothesis windows (paper §IV, Algorithm 1).

Per frame (DESIGN.md §Inference):

1. **Predict / slide** — every hypothesis's window gets the new frame, its newest pose predicted
   by the grasper's motion ``D`` (:class:`pinpoint_fg.window.Window`).
2. **Transport** — up to 30 iterations on the first 10 frames, 15 afterwards. Each iteration
   linearises every window at its own poses and eliminates the older poses, giving the
   negative log-posterior ``c_i``, gradient ``g_i`` and GN information ``H_i`` of each newest pose
   (right chart). The particles are expressed in **one chart, at the best particle**
   ``T_ref`` (highest log-posterior): ``xi_i = Log(T_ref^-1 T_i)``; with ``T_ref Exp(xi_i + d) ≈
   T_i Exp(Jr(xi_i) d)`` the gradient and information become ``Jr^T (-g_i)`` and
   ``Jr^T H_i Jr``, the Stein step ``s_i`` (:func:`pinpoint_fg.stein.stein_step`, Eq. 14 with
   the kernel-weighted SVN Hessian by default) maps back to ``T_i <- T_i Exp(Jr(xi_i) s_i)``,
   and the older window poses follow by back-substitution (smoothing).
   The step is computed in **S-whitened coordinates** (``xi / S``, ``S = diag(5 deg x3, 1 mm x3)``,
   the kernel's scale): the Hessian's entries are in rad^-2 and m^-2, which differ by ~1e4, so
   flooring its eigenvalues at ``eps * w_max`` in raw units would inflate every rotational
   eigenvalue to the translational scale and freeze rotation. In whitened units the floor
   bounds the condition number of a dimensionless matrix, as intended. (SVGD keeps raw units.)
3. **Safeguard** — a moved particle whose negative log-posterior rises by more than
   ``collapse_nll`` has its step halved (up to 5 times) and otherwise stays put: repulsion may
   cost a little posterior, never a collapse.
4. **Early stop** — when the 95th percentile of step sizes is below 0.1 mm and 0.5 deg two
   iterations in a row (paper §V-B without its flat-log-posterior test, which measured nothing
   useful here: ``SvnSettings.stop_logp``), or one small step after a step that the Gauss-Newton model
   predicted: every particle's cost changed by what ``g^T d + 1/2 d^T H d`` said, to 5 % (at the 95th
   percentile; ``SvnSettings.stop_model_tol``). Where the model holds, a small next step is the converged
   one and a second small step adds nothing. The cost after the step is the window's, from the next
   linearisation (at L = 1 the accepted trial's own; at L > 1 the safeguard's trial cost keeps the older
   poses' share constant, which the eliminated model does not). The last of those small steps is computed,
   found small, and not taken (``SvnSettings.skip_last_step``): the same decision, one evaluation fewer.
5. **Modes** (:mod:`pinpoint_fg.trackers.svn_modes`, before the transport) — Stein transport
   cannot move particles between basins, and an ambiguity can *emerge* while tracking (the
   needle turns through an edge-on view) far from every hypothesis. The hypotheses are grouped
   into modes by their Gauss-Newton-predicted peaks, each scored by its Laplace evidence (the
   accumulated marginal likelihood of its window, ``-1/2 log det`` of the information included).
   On frames with a backbone, each of the ``K`` best modes proposes its closed-form twin and
   arc flips, and the frame's own ellipse proposes both circles (re-detection from the frame
   alone, every frame); a proposal keeps its parent's window prior (a mode switch pays the
   motion model's price), is polished on its window and admitted when its evidence is within
   ``admit_nats`` of the best mode's. Every admitted mode holds at least a floor of
   hypotheses (copies of its window); then the transport proceeds as above.
6. **Prune** — a mode the evidence has ruled out would otherwise linger. After transport,
   hypotheses whose basin's log-evidence is more than ``prune_nll`` below the best (relative
   mass e^-30) are replaced by copies of surviving ones (jittered at the next frame's
   prediction so the transport spreads them again). Basins, not particles, are compared: every
   particle of one mode predicts the same peak, however far repulsion has spread them, so
   genuinely ambiguous modes (a few nats apart) are untouched. The evidence is never forgotten
   (``SvnSettings.forgetting``).
7. **Report** — first the best hypothesis of each of the ``2K`` best modes is polished to
   convergence by damped Gauss-Newton on its own window
   (:func:`~pinpoint_fg.trackers.svn_modes.settle`: batched one-hypothesis
   windows of :meth:`~pinpoint_fg.window.Window.subset`, steps accepted only when the cost drops, at most
   ``map_polish_iters``): repulsion keeps every particle off its mode's peak by about the kernel
   scale, the reported estimate should be the peak, and modes are compared at their peaks. The
   MAP is then the best hypothesis of the heaviest mode, as MHT reports its heaviest branch
   (``map_by_evidence``; False: the lowest-cost hypothesis, the highest density). The
   modes (``Estimate.modes``, at most ``K``): each mode's weight is ``softmax`` of the modes'
   log-evidence (particle counts are not weights: transport cannot move mass between basins),
   its peak its polished best hypothesis, its covariance its members' tangent covariance (or
   the inverse information when it has fewer than 7 members). Then q95 spread and covariance
   around the MAP; with L > 1 the smoothed pose of frame k - L + 1. Last, the books are kept per mode,
   as MHT keeps them per branch (:func:`~pinpoint_fg.trackers.svn_modes.book_sources`): right after
   the next frame's marginalisation every member of a settled mode takes its polished peak's window
   prior and evidence (per particle they drift apart by hundreds of nats over a run because each
   member's marginalisations are made where repulsion put it). The previous MAP hypothesis at its
   motion prediction, where single-mode MAP starts its search, is one more start of its mode's
   polish (``ModeSettings.map_from_prediction``). When every hypothesis is
   implausible (the best one's cost far above what the frame's residual count allows) the
   particles are re-seeded from this frame.

SVGD (ablation baseline) is the same loop with ``H = I``, ``S = I`` and a fixed step size.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from factors.lie import local, se3_exp, se3_right_jacobian
from pinpoint_fg.elimination import Linearization
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.init import InitConfig, seed_particles
from pinpoint_fg.kinematic_bias import BiasModel
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observation import Observation
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.posterior.spread import TangentSpread, tangent_covariance, tangent_spread
from pinpoint_fg.stein import SteinConfig, floor_hessians, quantile_rows, stein_step
from pinpoint_fg.trackers.base import Tracker, TrackerConfig, implausible
from pinpoint_fg.trackers.svn_modes import (
    SCALE,
    Basins,
    ModeSettings,
    allot,
    basins,
    book_sources,
    join_coincident,
    propose,
    settle,
)
from pinpoint_fg.window import DEFAULT_RELIN_THRESHOLD, Window
from pinpoint_fg.window_rows import share_books

#: Weak prior on the very first pose of each hypothesis: [omega x3 (rad), v x3 (m)].
FIRST_PRIOR_SIGMA = np.array([np.deg2rad(30.0)] * 3 + [10e-3] * 3)


@dataclass(frozen=True)
class SvnSettings:
    """Transport settings (paper §IV-V defaults)."""

    sigma_r_rad: float = np.deg2rad(5.0)
    """Kernel scale of rotation (S), radians."""
    sigma_t_m: float = 1e-3
    """Kernel scale of translation (S), metres."""
    eig_floor_rel: float = 1e-2
    """Hessian eigenvalue floor relative to the largest (epsilon)."""
    floor_each: bool = True
    """Also floor every particle's information before the Stein step's kernel sum, not only the sum
    (:attr:`pinpoint_fg.stein.SteinConfig.floor_each`; a second eigen-decomposition per iteration). Without it
    (``scripts/svn_settings_ab.py floor_each true false RUN...``, lock-step) the clear runs cost 4-7 % less CPU
    per frame at the same errors (to three digits), but snapshots, seeds 1-10, lost accuracy on 8 of 10 runs
    (mean rotation error 18.1 -> 20.2 deg, truth kept 94.5 -> 93.2 %) at no saving there (0.98x): the
    per-particle floor damps each particle's weak directions, which matter where posteriors are broad."""
    preconditioner: str = "newton-eq14"
    """'newton-eq14' (default), 'newton-alg1' or 'none' (SVGD)."""
    hessian: str = "kernel-weighted"
    """Eq.-14 matrix: 'kernel-weighted' (SVN), 'kernel-average' or 'own'."""
    isotropic: bool = False
    """S = I in the kernel (SVGD)."""
    step_size: float = 1.0
    """Step multiplier (1 for Newton; a small fixed value for SVGD)."""
    iters_first: int = 30
    """Iterations on the first ``first_frames`` frames."""
    iters_later: int = 15
    """Iterations afterwards."""
    first_frames: int = 10
    """How many frames count as 'first'."""
    stop_trans_m: float = 1e-4
    """Early stop: 95th percentile of translation steps below this (0.1 mm)."""
    stop_rot_rad: float = np.deg2rad(0.5)
    """Early stop: 95th percentile of rotation steps below this (0.5 deg)."""
    stop_quiet: int = 2
    """Early stop after this many consecutive iterations with small steps. One measured 14 % faster per frame
    (normal-01, drive-01) but moved drive-01's mean rotation error 3.18 -> 3.27 deg (+2.7 %) and flipped the
    ambiguous runs' outcomes (symmetric-01 bimodal frames 100 % -> 19 %), so two stay the default. Measured again
    on 24 runs, seeds 1-4 (``scripts/svn_settings_ab.py stop_quiet 2 1 RUN...``, lock-step, ``floor_each`` off):
    6-16 % less CPU per frame, the same errors on the clear runs (to 0.4 %), but drive-01 3.06 -> 3.53 deg:
    through its edge-on turn (frames 57-86) the MAP settles in a local optimum 1-9 deg worse, while drive-04
    went 3.31 -> 2.89 and the snapshots runs moved both ways. Not adopted: one scenario's MAP is worse, the rest
    is noise-level."""
    stop_logp: float = float("inf")
    """Early stop: also require the best log-posterior to change by less than this (inf: steps alone).
    The paper's 0.02 kept 80-90 % of mask frames at the iteration cap although the steps had fallen
    below 0.1 mm / 0.5 deg after 3-4 iterations: the best particle's value keeps moving by a few
    hundredths of a nat as repulsion reshuffles the cloud, which says nothing about convergence of
    the poses. Stopping on the step sizes alone measured 2.4x faster on mask frames at unchanged accuracy."""
    skip_last_step: bool = True
    """The early stop's last small step is computed but not taken: when the previous ``stop_quiet - 1`` steps
    were small and the step just computed is small too (before its safeguard, which can only shorten it), the
    transport stops where it is. The stop decision is the same as taking that step and then testing it; only
    the step (below 0.1 mm / 0.5 deg at the 95th percentile) and its trial evaluation are saved, and the
    transport's last linearisation is then the one already made at the current poses. Measured lock-step
    (``scripts/svn_settings_ab.py skip_last_step false true``, the nine scenarios, seeds 1 and 2): 5.5 % less
    CPU per frame in sum (0.89-1.02 per run), errors of the clear runs within 0.4 %, the ambiguous runs as
    chaotic as ever (snapshots-02 14.1 -> 10.3 deg, symmetric-01 160.6 -> 16.7 deg: a coin toss)."""
    stop_model_tol: float = 0.05
    """Early stop after one small step (instead of ``stop_quiet``) when the step before it changed the cost as the
    Gauss-Newton model predicted: :func:`model_disagreement` of that step below this (0 disables). The quiet test's
    second small step guards against a step that was small only because the model was poor (a ridge, an
    edge-on turn); a step whose actual change of cost matched the quadratic model's to 5 % shows the model good
    where the particles are, so the small step computed after it is the converged one. Measured lock-step
    (``scripts/svn_settings_ab.py stop_model_tol 0 0.05 RUN...``, 52 runs: the nine scenarios at seeds 1-4, drive,
    kinfault, snapshots and symmetric at 5-8 too): CPU per frame 0.85-0.95x on the 32 runs of the clear
    scenarios (no-mask frames ~5.8 -> ~4.8 ms), their mean errors within 2.5 % (drive-04 2.90 -> 2.97 deg,
    drive-06 2.97 -> 2.86), snapshots 0.94-1.05x (its mask frames run to the iteration cap either way) at mean
    rotation error 18.2 deg over seeds 1-8 both, symmetric's coin tosses 74.1 -> 75.9 deg over seeds 1-8 (truth
    kept 53 -> 48 %, symmetric-01 36 -> 6 %). A looser 0.2 saved a little more (normal-01 0.87x) but moved drive-01
    3.00 -> 3.18 deg and snapshots-01 18.2 -> 26.2 deg. The cost after a step is read from the next
    linearisation: at L > 1 the safeguard's trial cost (:meth:`~pinpoint_fg.window.Window.newest_value`) holds the
    older poses' share constant, which the eliminated model does not (judged by it, the median disagreement on
    normal-01's no-mask frames was 0.46 at L = 5 against 0.02 at L = 1, and the test rarely fired). At L = 5
    (``--window 5``, 17 runs of seeds 1-2): CPU 0.84-0.95x on the clear runs, filtered errors within 2 % but
    drive-01 3.00 -> 3.12 deg."""
    collapse_nll: float = 10.0
    """Safeguard: largest accepted rise of a particle's negative log-posterior per step."""
    prune_nll: float = 30.0
    """Hypotheses whose basin's log-evidence is this far below the best are replaced (inf disables pruning)."""
    forgetting: float = 1.0
    """Per-frame forgetting factor of each hypothesis's accumulated evidence (1 = none: the evidence is the
    hypothesis's whole marginal likelihood). Measured against 0.9 (the earlier default) on the nine benchmark
    scenarios (``scripts/compare_forgetting.py`` on ``./run benchmark --quick``'s runs: 150 frames, seed 1;
    a particle within 2 mm / 10 deg of the truth): equal on seven, better on
    snapshots (96.7 % vs 94.0 %) and symmetric (16 % vs 0 %); MAP rotation error better on calibration
    (3.8 vs 4.8 deg), snapshots (8.3 vs 11.4) and symmetric (31 vs 77), worse on kinfault (6.0 vs 5.5)."""
    map_polish_iters: int = 20
    """At most this many damped Gauss-Newton steps polish the MAP particle after transport (0 disables);
    it stops earlier at convergence (``polish_decrement``)."""
    polish_decrement: float = 1e-3
    """Polish converged when the Gauss-Newton decrement ``1/2 g^T H^-1 g`` (the cost still to gain) is below
    this many nats: the pose is then within ~0.05 posterior standard deviations of the peak."""
    jitter_sigma: tuple[float, ...] = (np.deg2rad(1.0),) * 3 + (0.2e-3,) * 3
    """Spread of the copies that replace pruned hypotheses, [omega x3 (rad), v x3 (m)]."""
    map_by_evidence: bool = True
    """The MAP is the best hypothesis of the mode with the highest Laplace evidence (the most posterior mass;
    default since the twenty-third round) instead of the lowest-cost hypothesis (the highest posterior density).
    They differ only when a broad mode outweighs a higher, narrower peak. The heavier mode is the likelier to hold
    the truth, the reported pose then lies in the mode ``modes.csv`` ranks first, and MHT chooses its branch the
    same way. Measured (``scripts/svn_settings_ab.py map_by_evidence false true`` on the nine scenarios at seeds
    1-8, 72 runs): snapshots' mean rotation error 20.3 -> 18.0 deg, calibration-01 4.8 -> 3.8 deg (its first frame,
    the twin circle, 143 -> 2 deg), slow-02 4.0 -> 4.5 deg, symmetric's coin tosses 90.0 -> 92.5 deg, every
    other run within 0.2 deg but drive-08 (the twin throughout, 159.1 -> 157.1 deg); cost unchanged (summed
    medians 0.99 and 1.00 of before)."""
    relin_threshold: float = DEFAULT_RELIN_THRESHOLD
    """L > 1: the older poses' Gauss-Newton model is reused while they moved less than this times (5 deg, 1 mm)
    per component (:mod:`pinpoint_fg.relinearize`; 0: exact on every iteration)."""
    kinematic_bias: BiasModel | None = None
    """Count the kinematic terms in the evidence under a slowly varying bias model: each marginalised frame's
    grasp terms are re-scored by per-hypothesis bias filters, the pose's own uncertainty folded in
    (:class:`~pinpoint_fg.kinematic_bias.BiasBook`); the pose fit is unchanged. None (default): as independent per
    frame, the white model. Measured (README, *Kinematic bias in the evidence*; ``scripts/svn_settings_ab.py
    kinematic_bias null '{"tau_s": 5, "white_share": 0.3}' RUN...``): on the drive runs mean rotation error
    31.3 -> 10.4 deg over seeds 1-10 and 41.6 -> 13.7 deg over unseen seeds 11-14 (the twin circle no longer wins
    drive-02, -08, -09, -10, -14), the other scenarios of seeds 1-4 unchanged but normal and kinfault (3.9 -> 4.7,
    4.9 -> 5.6 deg); on unseen seeds 5-8 normal 3.9 -> 22.6 deg and kinfault 6.2 -> 31.7 deg (normal-05 and
    kinfault-07 keep a flipped arc early in the run, which the white count of the kinematic terms had ruled out
    within a few frames): not a default. ``white_share`` 0.1 lost rotation (14.3 -> 31.0 deg): the smaller it is,
    the more the evidence punishes a pose estimate's frame-to-frame jitter."""
    modes: ModeSettings = field(default_factory=ModeSettings)
    """Mode proposals, Laplace admission and the per-mode floor of hypotheses (:mod:`.svn_modes`)."""


@dataclass(frozen=True)
class _Prediction:
    """The previous MAP hypothesis at its motion prediction: one more start of its mode's polish (module
    docstring, step 7; :func:`~pinpoint_fg.trackers.svn_modes.settle`'s ``predicted``)."""

    row: int
    """The hypothesis."""
    cam_T_newest: np.ndarray
    """(4, 4) its newest pose as predicted, before any transport."""
    prior_mean: np.ndarray
    """(4, 4) its window prior's mean then: a copy made since replaces it, and the start is dropped."""
    evidence: float
    """Its accumulated evidence then (the same check)."""
    model: Linearization | None = None
    """Its one-pose window's model at the prediction, from the transport's first linearisation (L = 1 only)."""

    def start(self) -> tuple:
        """``settle``'s ``predicted``: (row, pose[, model])."""
        return (self.row, self.cam_T_newest) + (() if self.model is None else (self.model,))


def model_disagreement(lin: Linearization, delta: np.ndarray, value: np.ndarray, new_value: np.ndarray) -> float:
    """How far a step's actual change of cost departs from the Gauss-Newton model's prediction, relatively.

    ``delta (N, 6)`` the step taken (right chart of each newest pose, as ``lin.grad`` and ``lin.hess``),
    ``value (N,)`` the cost before it (``lin.value``) and ``new_value (N,)`` after it (nats). Per particle
    ``|(new - value) - m| / (|m| + 0.1)`` with ``m = g^T d + 1/2 d^T H d``; the 0.1 nat keeps a step that barely
    moves the cost from being judged by its round-off. Returns the 95th percentile over particles (the early
    stop's quantile; NaN where a cost is not finite).
    """
    m = np.einsum("ni,ni->n", lin.grad, delta) + 0.5 * np.einsum("ni,nij,nj->n", delta, lin.hess, delta)
    rel = np.abs((new_value - value) - m) / (np.abs(m) + 0.1)
    return float(quantile_rows(rel[None], 0.95)[0])


def _step_lengths(delta: np.ndarray) -> np.ndarray:
    """(2, N): each step's translation (m) and rotation (rad) length, of ``delta (N, 6)`` = [omega; v]."""
    d_rot, d_tra = delta[:, :3], delta[:, 3:]
    # np.linalg.norm(., axis=1)'s own sums, without its argument handling
    return np.stack([np.sqrt(np.add.reduce(d_tra * d_tra, axis=1)), np.sqrt(np.add.reduce(d_rot * d_rot, axis=1))])


class SvnTracker(Tracker):
    """PinPoint's tracker (and, with ``settings`` of SVGD, its gradient-only ablation)."""

    method = "svn"

    def __init__(self, config: TrackerConfig, settings: SvnSettings | None = None,
                 init: InitConfig | None = None) -> None:
        super().__init__(config)
        self.svn = settings or SvnSettings()
        self.init = init or InitConfig()
        noise = config.noise
        scale = np.array([self.svn.sigma_r_rad] * 3 + [self.svn.sigma_t_m] * 3)
        floor_scale = np.ones(6) if self.svn.isotropic else scale
        self._S = np.ones(6) if self.svn.isotropic else scale
        self.stein = SteinConfig(
            scale=(1.0,) * 6,
            bandwidth_floor=noise.process_variance_whitened(floor_scale),
            eig_floor_rel=self.svn.eig_floor_rel,
            preconditioner=self.svn.preconditioner,
            hessian=self.svn.hessian,
            step_size=self.svn.step_size,
            isotropic=self.svn.isotropic,
            floor_each=self.svn.floor_each,
        )
        self.window = Window(config.window, noise.process_cov, self.svn.forgetting, self.svn.relin_threshold,
                             self.svn.kinematic_bias)
        self._times: list[tuple[int, float]] = []
        self._lin = None  # the transport's final linearisation (reused by the MAP polish)
        self._books: tuple[np.ndarray, np.ndarray] | None = None  # (members, their rep) to share after the push
        self._prev_map: int | None = None  # the last MAP hypothesis, if it survived the pruning
        self._predicted: _Prediction | None = None  # _prev_map at its motion prediction (settle's extra start)
        self._last_map: int | None = None  # the MAP hypothesis of the last step (its window: final_smoothed)

    @property
    def particles(self) -> np.ndarray:
        """(N, 4, 4) newest poses of all hypotheses."""
        return np.empty((0, 4, 4)) if self.window.poses is None else self.window.newest.copy()

    def settings(self) -> dict:
        """Settings for result.json."""
        out = super().settings()
        out.update({k: (float(v) if isinstance(v, float) else v) for k, v in asdict(self.svn).items()})
        return out

    def _seed(self, lik: FrameLikelihood) -> None:
        particles, _ = seed_particles(lik, self.config.particles, self.rng, self.init)
        if self.window.poses is None:
            self.window.start(particles, lik, FIRST_PRIOR_SIGMA)
        else:
            self.window.reset_newest(particles, FIRST_PRIOR_SIGMA)

    def _small(self, delta: np.ndarray) -> bool:
        """The early stop's test of steps ``delta (N, 6)``: 95th percentiles below 0.1 mm and 0.5 deg (the settings)."""
        q_tra, q_rot = quantile_rows(_step_lengths(delta), 0.95)  # = np.quantile(., 0.95, axis=1), cheaper
        return bool(q_tra < self.svn.stop_trans_m and q_rot < self.svn.stop_rot_rad)

    def _transport(self, max_iters: int) -> tuple[int, np.ndarray]:
        """Run the Stein iterations; returns (iterations, negative log-posterior (N,))."""
        s = self.svn
        quiet = 0
        taken = None  # (model, step) of the last step taken, for the model test (stop_model_tol)
        agreed = False  # that step changed the cost as its model predicted
        best_prev = None
        value = None
        iterations = 0
        for iterations in range(1, max_iters + 1):  # noqa: B007 - the count is returned
            lin = self.window.linearize()
            # the window's cost after the last step against its model's prediction (module docstring, step 4)
            agreed = taken is not None and (
                model_disagreement(taken[0], taken[1], taken[0].value, lin.value) < s.stop_model_tol)
            value = lin.value
            ref = int(np.argmin(value + self.window.evidence))
            T = self.window.newest
            xi = local(np.broadcast_to(T[ref], T.shape), T)
            Jr = se3_right_jacobian(xi)
            JrT = np.swapaxes(Jr, 1, 2)
            grad_logp = -np.einsum("nij,nj->ni", JrT, lin.grad)
            hess = JrT @ lin.hess @ Jr
            S = self._S
            step = S * stein_step(xi / S, grad_logp * S, hess * np.outer(S, S), self.stein).step
            delta = np.einsum("nij,nj->ni", Jr, step)
            if s.skip_last_step and (quiet + 1 >= s.stop_quiet or agreed) and s.stop_logp == float("inf"):
                if self._small(delta):
                    self._lin = lin
                    return iterations, value + self.window.evidence
            # safeguard: halve steps whose particle's cost would collapse; a halving re-evaluates only the
            # particles it shortened (the others' trial poses, and so their values, are unchanged)
            scale = np.ones(T.shape[0])
            trial = T @ se3_exp(delta)
            new_val = self.window.newest_value(trial, lin)
            bad = ~np.isfinite(new_val) | (new_val > value + s.collapse_nll)
            for _ in range(5):  # up to 6 evaluations in all
                if not bad.any():
                    break
                scale = np.where(bad, scale * 0.5, scale)
                rows = np.flatnonzero(bad)
                before, trial = trial, trial.copy()
                trial[rows] = T[rows] @ se3_exp(delta[rows] * scale[rows, None])
                new_val = self.window.newest_value(trial, lin, changed=(rows, before))
                bad = ~np.isfinite(new_val) | (new_val > value + s.collapse_nll)
            if bad.any():  # still collapsing after five halvings: those particles stay put
                scale = np.where(bad, 0.0, scale)
                trial = None  # the last trial is not the accepted step
            delta = delta * scale[:, None]
            # a particle whose step the safeguard cut to nothing (trial None) is one the model did not predict
            taken = (lin, delta) if s.stop_model_tol > 0 and trial is not None else None
            self.window.move_newest(delta, lin, newest=trial)
            best = -float(np.min(value + self.window.evidence))
            small = self._small(delta)
            steady = s.stop_logp == float("inf") or (best_prev is not None and abs(best - best_prev) < s.stop_logp)
            quiet = quiet + 1 if (small and steady) else 0
            best_prev = best
            if quiet >= s.stop_quiet or (quiet and agreed):
                break
        lin = self.window.linearize()
        self._lin = lin
        final = lin.value + self.window.evidence
        return iterations, final

    def _prune(self, log_evidence: np.ndarray, total: np.ndarray) -> np.ndarray:
        """Replace hypotheses whose basin's ``log_evidence (N,)`` is ruled out with copies of survivors (+inf: keep).

        Returns the index (N,) each hypothesis now copies (identity where alive); ``total`` follows.
        """
        best = np.max(log_evidence[np.isfinite(log_evidence)], initial=-np.inf)
        dead = np.isnan(log_evidence) | (log_evidence == -np.inf) | (log_evidence < best - self.svn.prune_nll)
        if dead.all():
            return np.arange(log_evidence.shape[0])
        n_dead = int(dead.sum())
        self._pending_jitter = dead
        index = np.arange(log_evidence.shape[0])
        if n_dead == 0:
            return index
        index[dead] = self.rng.choice(np.flatnonzero(~dead), size=n_dead)
        self.window.resample(index)
        total[dead] = total[index[dead]]
        return index

    def _modes(self, found: Basins, index: np.ndarray, i_map: int, spread: TangentSpread) -> tuple[Mode, ...]:
        """The reported modes (module docstring, step 7): evidence weights, best K, dominant first.

        ``spread``: every hypothesis's spread about the MAP ``i_map`` (the estimate's summary), which is the MAP's
        mode's own when that mode holds every hypothesis (the usual single-mode frame): not computed twice.
        """
        labels = found.labels[index]
        P = self.window.newest
        weights = found.weights
        out = []
        for m in np.argsort(-weights, kind="stable")[: self.svn.modes.max_modes]:
            members = labels == m
            if not members.any():
                continue
            peak = P[i_map] if m == labels[i_map] else found.peaks[found.reps[m]]
            if m == labels[i_map] and members.all():
                cov = spread.cov_xi
            elif members.sum() >= 7:
                cov = tangent_covariance(peak, P[members])
            else:
                H = self._lin.hess[found.reps[m]] if self._lin is not None else np.eye(6)
                cov = floor_hessians((H * np.outer(SCALE, SCALE))[None], eps=1e-6)[1][0] * np.outer(SCALE, SCALE)
            out.append(Mode(cam_T_needle=peak.copy(), weight=float(weights[m]), cov_xi=0.5 * (cov + cov.T)))
        total = sum(m.weight for m in out)
        return tuple(Mode(m.cam_T_needle, m.weight / total, m.cov_xi) for m in out)

    def _propose(self, lik: FrameLikelihood) -> tuple[int, int]:
        """Mode proposals, admission and allotment before the transport (module docstring, step 5)."""
        lin = self.window.linearize()
        if self._predicted is not None and self.window.size == 1:
            # the previous MAP hypothesis is still at its prediction: its model there is the settle's start
            # (with one pose per window no transport can move an older pose of that row in between)
            self._predicted = replace(self._predicted, model=lin.subset([self._predicted.row]))
        found = basins(self.window.newest, lin, self.window.evidence, self.svn.modes)
        admitted = propose(self.window, lin, found, lik, self.svn.modes)
        moved = allot(self.window, found, admitted, self.svn.modes, self.rng, np.asarray(self.svn.jitter_sigma))
        return admitted.screened, moved

    def _jitter_copies(self) -> None:
        """Spread last frame's copies (:meth:`_prune`) so the transport can separate them."""
        dead = getattr(self, "_pending_jitter", None)
        if dead is None or not dead.any() or self.window.poses is None or dead.shape[0] != self.window.poses.shape[1]:
            return
        jitter = self.rng.normal(size=(int(dead.sum()), 6)) * np.asarray(self.svn.jitter_sigma)
        self.window.poses[-1, dead] = self.window.poses[-1, dead] @ se3_exp(jitter)

    def final_smoothed(self) -> list[tuple[int, float, np.ndarray]]:
        """``(frame, t_s, cam_T_needle)`` of the window's poses :meth:`step` has not reported as smoothed (the last
        ``L - 1`` frames at the end of a run), from the last MAP hypothesis's window; ``track`` writes them."""
        i = self._last_map
        if self.config.window <= 1 or self.window.poses is None or i is None:
            return []
        n = self.window.size
        start = 1 if n == self.config.window else 0  # the oldest pose was reported by the last step
        if n <= start:
            return []
        return [(f, t, self.window.poses[j, i].copy())
                for j, (f, t) in zip(range(start, n), self._times[-(n - start):], strict=True)]

    def step(self, observation: Observation) -> Estimate:
        """Process one frame (see the module docstring)."""
        t0 = time.perf_counter()
        motion = self.motion_input(observation)
        lik = FrameLikelihood(motion.observation, self.config.model)
        reseeded, proposed, moved = False, 0, 0
        if self.window.poses is None:
            self._seed(lik)
        else:
            self.window.push(lik, motion.delta, self.config.switches.motion, process_scale=motion.scale)
            if self._books is not None:
                share_books(self.window, *self._books)
            self._books = None
            prev = self._prev_map
            if self.svn.modes.map_from_prediction and prev is not None:
                self._predicted = _Prediction(prev, self.window.newest[prev].copy(),
                                              self.window.prior_mean[prev].copy(), float(self.window.evidence[prev]))
            self._jitter_copies()
            proposed, moved = self._propose(lik)
        first = self.frames_seen < self.svn.first_frames
        iters, value = self._transport(self.svn.iters_first if first else self.svn.iters_later)
        # the frame's terms at the current poses: memoised by the transport's last evaluation
        if implausible(float(lik.gauss_newton(self.window.newest)[0][int(np.argmin(value))]), lik):
            kept = (self.window.poses.copy(), self.window.prior_mean.copy(), self.window.prior_W.copy(),
                    self.window.evidence.copy(), self.window.kin)
            kept_frames = (list(self.window.frames), list(self.window.deltas), list(self.window.delta_W))
            old_best = float(np.min(lik.nll(self.window.newest)))
            self._seed(lik)
            it2, value2 = self._transport(self.svn.iters_first)
            if float(np.min(lik.nll(self.window.newest))) < old_best:
                reseeded, iters, value = True, iters + it2, value2
            else:  # seeding did not explain the frame better: keep the tracked hypotheses
                (self.window.poses, self.window.prior_mean, self.window.prior_W, self.window.evidence,
                 self.window.kin) = kept
                self.window.frames, self.window.deltas, self.window.delta_W = kept_frames
                self._lin = None  # the transport's last linearisation belongs to the discarded seeding
        if self._lin is None:
            self._lin = self.window.linearize()
        found = basins(self.window.newest, self._lin, self.window.evidence, self.svn.modes)
        polished = np.zeros(0, dtype=int)
        predicted, self._predicted = self._predicted, None
        if predicted is not None and (reseeded or not (
                np.array_equal(self.window.prior_mean[predicted.row], predicted.prior_mean)
                and self.window.evidence[predicted.row] == predicted.evidence)):
            predicted = None  # the hypothesis was replaced since its prediction
        if self.svn.map_polish_iters > 0:  # every compared mode's best hypothesis moved to its peak
            found, polished, lin_r = settle(self.window, self._lin, found, self.svn.map_polish_iters,
                                            self.svn.polish_decrement, 2 * self.svn.modes.max_modes,
                                            self.svn.modes.map_starts,
                                            None if predicted is None else predicted.start(),
                                            self.svn.modes.start_spacing)
            value[polished] = lin_r.value + self.window.evidence[polished]
        if self.svn.map_by_evidence:  # best hypothesis of the heaviest mode
            i = found.heaviest_rep()
        else:  # the highest posterior density: every compared mode's best hypothesis is at its peak
            i = int(np.argmin(value))
        index = self._prune(np.where(found.converged, found.log_evidence, np.inf), value)
        particles = self.window.newest.copy()
        logp = -value
        spread = tangent_spread(particles[i], particles)  # :func:`~pinpoint_fg.trackers.base.summarize`'s, once
        # one mode per reported peak; the MAP's mode is reported at the MAP hypothesis, so it is compared there
        m_map = int(found.labels[index[i]])
        reported = found.peaks[found.reps].copy()
        reported[m_map] = particles[i]
        joined = join_coincident(found, self.svn.modes.separation, first=m_map, peaks=reported)
        modes = self._modes(joined, index, i, spread)
        self._prev_map = i if index[i] == i else None
        if self.svn.modes.shared_books:  # applied after the next marginalisation (module docstring, step 7)
            self._books = book_sources(found, found.reps[np.isin(found.reps, polished)], index)
        q_t, q_r, cov = float(spread.q95_trans_m), float(spread.q95_rot_rad), np.asarray(spread.cov_xi)
        # the uncertainty summary included, as in every other tracker's latency
        latency_ms = 1e3 * (time.perf_counter() - t0)
        self.frames_seen += 1
        self._times.append((observation.frame, observation.t_s))
        smoothed = None
        self._last_map = i
        if self.config.window > 1 and self.window.size == self.config.window:
            f, t = self._times[-self.config.window]
            smoothed = (f, t, self.window.oldest[i].copy())
        return Estimate(
            frame=observation.frame, t_s=observation.t_s, cam_T_needle=particles[i].copy(),
            q95_trans_m=q_t, q95_rot_rad=q_r, cov_xi=cov, iterations=iters, latency_ms=latency_ms,
            particles=particles, log_posterior=logp, smoothed=smoothed, reseeded=reseeded,
            modes=modes,
            extra={"pruned": float(np.sum(index != np.arange(index.shape[0]))), "proposals": float(proposed),
                   "allotted": float(moved), **self.kinematics_extra(motion)},
        )


class SvgdTracker(SvnTracker):
    """SVGD ablation: the same loop with H = I, an isotropic kernel and a fixed step (paper §V-D)."""

    method = "svgd"

    def __init__(self, config: TrackerConfig, step_size: float = 1e-9) -> None:
        super().__init__(config, SvnSettings(preconditioner="none", isotropic=True, step_size=step_size))
