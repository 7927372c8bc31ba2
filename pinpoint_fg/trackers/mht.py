"""Multi-hypothesis MAP baseline (``--method mht``): a bank of single-mode GTSAM smoothers (issue 9, item 6).

The discrete-mode MAP a GTSAM user would build for the circle's ambiguities: up to ``K``
(:attr:`MhtConfig.max_branches`, 4) *branches*, each a :class:`pinpoint_fg.trackers.map.MapSmoother`
— the ``map`` baseline's fixed-lag smoother, the same factors, built by the same code — that
branch on the proposals of :mod:`pinpoint_fg.proposals` and are weighted and pruned by their
Laplace evidence.

**Why not ``gtsam.HybridSmoother``.** A hybrid factor graph selects among alternative *factors*
with a discrete key, and the hybrid smoother keeps one continuous linearisation point
(``HybridSmoother.linearizationPoint()`` is a single ``Values``) for every discrete assignment.
The circle's twin and the arc flips are not alternative factors: they are other local minima of
the *same* factors, 20-180 degrees away from each other. Expressing them would need a discrete
variable choosing among invented priors, and one shared linearisation point cannot represent
minima that far apart (Gauss-Newton from the mode's point never reaches its twin). A bank of
ordinary smoothers, one per discrete mode history, is the faithful formulation; the discrete
part (which branches live, their weights) is ~50 lines below.

**Per frame** ``k`` (motion ``D`` and process covariance ``Q`` as in ``map``; the random walk
:data:`pinpoint_fg.window.RANDOM_WALK_SIGMA` without kinematics):

1. *Update.* Each branch ``b`` adds the frame to its smoother (:meth:`MapSmoother.advance`).
   Its window prior on ``x_k`` is the prediction ``N(mu_b = D x_{k-1}^b, P_b = Sigma_{k-1}^b + Q)``
   (the previous marginal carried by the motion factor, in the right chart). Its evidence
   increment is the Laplace approximation of ``log int p(z_k | x) N(x; mu_b, P_b) dx``:
   ``laplace_log_evidence(E, H) + gaussian_log_normaliser(P_b)`` with
   ``E = nll_k(x*) + 1/2 |Log(mu_b^-1 x*)|^2_{P_b}`` at the smoother's estimate ``x*`` and ``H`` the
   information of GTSAM's marginal of ``x_k`` (its inverse covariance). With a window ``L = 1``
   that information is exactly ``frame + window prior``; with ``L > 1`` the smoother also
   re-weighs older frames and the increment is an approximation (documented, not hidden).
   The branch's log-weight accumulates the increments.
2. *Propose.* Only on frames with backbone pixels (every proposal keeps the ellipse, which is
   what makes it an ambiguity; without a backbone a flipped arc is simply a worse fit and the
   broad posterior of tip/tail/kinematics-only frames would be cut into spurious "modes").
   For each branch, :func:`pinpoint_fg.proposals.mode_proposals` (twin from the mode's ellipse
   and from the frame's fitted ellipse, the three arc flips of each). The frame's ellipse is
   the same for every branch; its poses are proposed once per frame, with the best branch as
   their parent. (Copying the parent's factor graph onto a proposal is not possible — the
   factors are measurements — so a new branch is a new smoother holding a prior and the frame.)
   Which prior (:attr:`MhtConfig.transport_prior`):

   * *Default (False): the parent's own window prior* ``N(mu_b, P_b)``. Switching to another mode
     within a branch's history is a jump the motion model prices, so mid-run a proposal is
     admitted only when the frame outweighs that price; the modes that were ambiguous from the
     start (seeding, re-detection) keep their own branches with their own histories.
   * *Transported (True):* the prior moved rigidly onto the proposal, mean ``G mu_b`` with
     ``G = p' x*^-1`` (``p'`` the proposal polished on the frame alone, so ``G`` carries the
     parent's posterior onto the proposal's), covariance ``P_b``: parent and proposal pay the same
     prior cost and only the frames decide. On its own that lets a twin inherit the parent's
     history for free, and one frame favouring the twin outweighs ten that ruled it out
     (measured on the normal run: the MAP jumped to the twin on 13 % of the frames), so the
     proposal is also charged what the parent's last :attr:`MhtConfig.history_frames` frames
     say against it: those poses carried by ``G`` and the parent's, both polished on their own
     frame (3 Gauss-Newton steps), cost ``sum_j nll_j(G x_j) - nll_j(x_j)`` (motion consistency
     assumed equal; frames that cannot tell them apart cost nothing).

   Measured on 300-frame runs (seed 1): with the transported prior the bank follows the frames
   into wrong modes on the rotation run (65 deg mean error vs 15 deg for ``map``: the needle
   turns in the grasp, the grasp factors then favour a flipped pose and the tail-only frames
   before cannot rule it out); with the default it equals ``map`` there and on the normal run.
3. *Screen and admit.* Every proposal is polished on the frame alone, then on its window
   (frame + prior, batched Gauss-Newton, :func:`pinpoint_fg.proposals.polish_with_prior`) and
   scored with its parent's previous log-weight plus its Laplace increment (minus the history
   cost when transported). Proposals within :attr:`MhtConfig.admit_nats` of the best branch
   that are not duplicates of a branch compete with the branches for the ``K`` slots; the ones
   that get a slot become GTSAM smoothers (prior + frame factors, LM) and are rescored with
   GTSAM's marginal exactly like step 1. With a finite :attr:`MhtConfig.reroute_nats` (off by
   default), a proposal that duplicates *another* branch than its parent is a second route into
   that branch's mode (the parent's history, then a jump): it competes too when it beats that
   branch by more than ``reroute_nats``, and the merge of step 4 keeps the better, so a mode's
   weight is its best route's, as in SVN (:mod:`pinpoint_fg.trackers.svn_modes`, *Routes*, with
   the measurement and why it is not the default).
4. *Prune.* Branches more than :attr:`MhtConfig.prune_nats` behind the best are dropped;
   duplicates (within :attr:`MhtConfig.separation`, or within Mahalanobis distance
   :attr:`MhtConfig.merge_mahalanobis2` under the better branch's marginal: one broad mode is
   not several) are merged keeping the better (a MAP over mode histories: the better route to a
   mode wins, weights are not summed, since a proposal's prior is borrowed from its parent).
   Log-weights are then shifted so the best is 0.

**Seeding and re-detection.** The first frame, and any frame where every branch is implausible
(:func:`pinpoint_fg.trackers.base.implausible`), start the bank from the frame alone: the modes of
:func:`pinpoint_fg.init.seed_particles` (the best ``K``), each a smoother with the weak prior
``MapConfig.prior_sigma`` at the mode, weighted by their Laplace evidence under that prior
(``Estimate.reseeded`` on re-detection).

**Robustness.** Each branch's smoother recovers as ``map``'s does; a branch whose recovery raises
too ends, and a candidate whose smoother raises is not admitted (both count in ``recovered``).
When no branch is left the bank re-detects from the frame; if GTSAM cannot solve any seed with
the frame, the best seed is held by its weak prior alone for this frame.

**Smoothed poses** (``L > 1``). Frame ``k - L + 1`` leaves the window at frame ``k`` and is reported at the pose
the branch that is best at frame ``k`` holds for it (each frame exactly once; the last ``L - 1`` frames from the
best branch at the end, :meth:`MhtTracker.final_smoothed`). A branch started at frame ``k`` — a proposal
admitted, or a re-detection — has a smoother holding ``x_k`` only, so it *inherits* the frames still to be
reported: a proposal its parent's smoothed poses as they were before frame ``k`` was added, a re-detected bank
those of the branch that was best before frame ``k``, and reports them unchanged when they leave the window
(:meth:`pinpoint_fg.trackers.map.MapSmoother.pending`, ``inherited``). Why: the new branch's mode history *is*
its parent's up to ``k - 1`` (its prior is the parent's prediction from ``x_{k-1}``, its ``history`` the
parent's), so the parent's estimates of those frames, conditioned on the frames up to ``k - 1`` exactly as that
prior is, are the branch's best estimates of them; its smoother cannot re-smooth them (their factors stayed in
the parent's graph). With the transported prior the history is the parent's carried by ``G``, and so are the
inherited poses (``G x_j``). A re-detection starts from the frame alone and knows nothing of earlier frames, so the
bank's estimates from before are the best there are. Filtered estimates are untouched by this bookkeeping.

**Report.** The MAP is the best branch's pose; ``particles`` are the branch poses padded to ``K``
rows (``particles.npz`` needs a fixed ``N``) with copies of the best pose at weight 0 and
log-posterior ``-inf``; ``weights`` are the normalised branch weights, ``log_posterior`` their
logarithms; ``modes`` lists every branch (pose, weight, GTSAM marginal covariance). q95 and
``cov_xi`` describe the whole mixture: fixed standard-normal draws split among the branches by
weight, ``x = x_b Exp(S_b z)`` (``S_b S_b^T`` the branch's marginal), spread around the MAP exactly
as the particle methods do (:func:`pinpoint_fg.posterior.spread.tangent_spread`); with one branch this
equals ``map``'s numbers. ``extra``: ``branches`` (live count), ``best_weight``, ``proposals``
(screened this frame), ``admitted`` (new branches), ``recovered`` (GTSAM recoveries).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from pinpoint_fg.estimate import Estimate
from pinpoint_fg.init import InitConfig, seed_particles
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observation import Observation
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.proposals import (
    DEFAULT_SEPARATION,
    gaussian_log_normaliser,
    laplace_log_evidence,
    mode_proposals,
    polish_with_prior,
    rigid_map,
)
from pinpoint_fg.trackers.base import Tracker, TrackerConfig, implausible
from pinpoint_fg.trackers.map import MapConfig, MapSmoother, motion_model
from pinpoint_fg.trackers.mht_branches import (
    Branch,
    branch_evidence,
    duplicated,
    history_cost,
    is_duplicate,
    mixture_spread,
    select_branches,
)


@dataclass(frozen=True)
class MhtConfig:
    """Settings of the multi-hypothesis bank beyond :class:`TrackerConfig`."""

    max_branches: int = 4
    """K: at most this many single-mode smoothers."""
    admit_nats: float = 10.0
    """A proposal may become a branch when its log-weight is within this of the best (1 : e^10)."""
    prune_nats: float = 20.0
    """A branch is dropped when its log-weight falls this far behind the best (1 : e^20)."""
    separation: tuple[float, float] = DEFAULT_SEPARATION
    """Two branches closer than (rotation rad, centre m) are one mode and are merged."""
    merge_mahalanobis2: float = 22.5
    """Also one mode when ``xi^T Sigma^-1 xi`` below this under the better branch's marginal (chi-square(6) 99.9 %)."""
    transport_prior: bool = False
    """A proposal inherits its parent's window prior moved rigidly onto it (and pays the history cost);
    False: it keeps the parent's prior as is, so switching mode pays the motion model's price (a jump)."""
    history_frames: int = 10
    """A proposal is charged what the parent's last this-many frames say against it (module docstring)."""
    polish_iters: int = 6
    """Batched Gauss-Newton steps that polish each proposal on the frame, and again on its window."""
    frame_ellipse: bool = True
    """Also propose both circles of the frame's fitted ellipse (and their flips)."""
    reroute_nats: float = float("inf")
    """A proposal landing on another branch's mode replaces that branch (the better route into the mode) when its
    log-weight beats the branch's by more than this; inf (the default): branches keep their own history and such
    proposals are not generated (SVN's ``ModeSettings.reroute_nats`` alike; 1 was measured and not kept)."""
    map: MapConfig = field(default_factory=MapConfig)
    """The settings of every branch's smoother (the ``map`` baseline's)."""

    def __post_init__(self) -> None:
        if self.max_branches < 1:
            raise ValueError(f"max_branches must be at least 1, got {self.max_branches}")
        if not (0 <= self.admit_nats <= self.prune_nats):
            raise ValueError("need 0 <= admit_nats <= prune_nats")
        if not self.reroute_nats >= 0:
            raise ValueError(f"reroute_nats must be >= 0 (inf: no rerouting), got {self.reroute_nats}")


class MhtTracker(Tracker):
    """A bank of up to K single-mode GTSAM fixed-lag smoothers weighted by Laplace evidence (module docstring)."""

    method = "mht"

    def __init__(self, config: TrackerConfig, mht_config: MhtConfig = MhtConfig()) -> None:
        super().__init__(config)
        if config.window < 1:
            raise ValueError(f"window must be at least 1, got {config.window}")
        self.mht = mht_config
        self._model = config.model
        self._weak_cov = np.diag(np.square(mht_config.map.prior_sigma))
        self._z = np.random.default_rng([config.seed, 95]).standard_normal((mht_config.map.q95_samples, 6))
        self.branches: list[Branch] = []
        self._key = -1

    @property
    def particles(self) -> np.ndarray:
        """(B, 4, 4) the live branches' newest poses, best first."""
        if not self.branches:
            return np.zeros((0, 4, 4))
        return np.stack([b.smoother.newest for b in self.branches])

    def settings(self) -> dict:
        """Common settings plus the bank's."""
        out = super().settings()
        m = self.mht
        out.update(smoother="BatchFixedLagSmoother bank", lag=float(self.config.window - 1),
                   max_branches=m.max_branches, admit_nats=m.admit_nats, prune_nats=m.prune_nats,
                   separation=list(m.separation), prior_sigma=list(m.map.prior_sigma), reseed=m.map.reseed)
        return out

    # ------------------------------------------------------------------ pieces
    def _new_branch(self, lik: FrameLikelihood, key: int, obs: Observation, T_init: np.ndarray,
                    mean: np.ndarray, prior_cov: np.ndarray, log_w0: float, inherit: dict,
                    frame_factors: bool = True) -> tuple[Branch | None, int]:
        """A new smoother at ``key``: the frame's factors and the prior ``N(mean, prior_cov)``; None if GTSAM raises.

        ``inherit``: the smoothed poses of the earlier frames still to be reported (module docstring, *Smoothed poses*).
        """
        sm = MapSmoother(self.mht.map, self.config.window)
        noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (prior_cov + prior_cov.T))
        factors = lik.gtsam_factors(key) if frame_factors else []
        try:
            result = sm.restart(factors, key, T_init, prior=(mean, noise), inherit=inherit)
        except RuntimeError:
            return None, 1
        T = sm.estimate(key)
        cov, fell_back, _ = sm.finish(key, obs.frame, obs.t_s, T)
        inc = branch_evidence(lik, T, cov, mean, prior_cov)
        return Branch(sm, log_w0 + inc, mean, prior_cov, inc, max(int(result.getIterations()), 1)), int(fell_back)

    def _seed(self, lik: FrameLikelihood, key: int, obs: Observation, inherit: dict) -> tuple[list[Branch], int]:
        """Branches from the frame alone (first frame, re-detection): the best K seeding modes, weak prior."""
        _, modes = seed_particles(lik, max(self.config.particles, InitConfig().max_modes), self.rng)
        out, rec = [], 0
        for T in modes[: self.mht.max_branches]:
            b, r = self._new_branch(lik, key, obs, T, T, self._weak_cov, 0.0, inherit)
            rec += r
            if b is not None:
                out.append(b)
        if not out:  # GTSAM could not solve any seed with this frame: hold the best seed by its weak prior alone
            b, r = self._new_branch(lik, key, obs, modes[0], modes[0], self._weak_cov, 0.0, inherit,
                                    frame_factors=False)
            assert b is not None
            out.append(b)
            rec += r
        return out, rec

    def _select(self, branches: list[Branch]) -> list[Branch]:
        """:func:`~pinpoint_fg.trackers.mht_branches.select_branches` with this bank's settings."""
        m = self.mht
        return select_branches(branches, m.prune_nats, m.max_branches, m.separation, m.merge_mahalanobis2)

    def _propose(self, lik: FrameLikelihood, key: int, obs: Observation, branches: list[Branch],
                 prev_w: list[float]) -> tuple[list[Branch], int, int, int]:
        """Proposals of every branch: screen, let the best compete for the K slots, build their smoothers."""
        held = np.stack([b.smoother.newest for b in branches])
        best = max(b.log_w for b in branches)
        cands: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, float, list, dict]] = []
        n_prop = 0
        for j, (b, w0) in enumerate(zip(branches, prev_w, strict=True)):
            T_b = b.smoother.newest
            # the frame's ellipse is the same for every branch: proposed once, from the best branch's history
            # with routes on, proposals landing on another branch are kept: other routes into its mode
            P = mode_proposals(T_b, lik, existing=None if np.isfinite(self.mht.reroute_nats) else held,
                               separation=self.mht.separation, frame_ellipse=self.mht.frame_ellipse and j == 0)
            if P.shape[0] == 0:
                continue
            n_prop += P.shape[0]
            # polish on the frame alone, then carry the parent's window prior onto the polished pose and
            # polish on the window (frame + that prior): the proposal inherits its parent's prior cost
            P, _, _ = polish_with_prior(lik, P, iters=self.mht.polish_iters)
            if self.mht.transport_prior:
                means = rigid_map(T_b, P) @ b.prior_mean
            else:
                means = np.broadcast_to(b.prior_mean, P.shape).copy()
            info = np.linalg.inv(b.prior_cov)
            Tp, E, H = polish_with_prior(lik, P, means, info, self.mht.polish_iters)
            score = w0 + laplace_log_evidence(E, H) + gaussian_log_normaliser(b.prior_cov)
            for i in np.flatnonzero(np.isfinite(score) & (score >= best - self.mht.admit_nats)):
                dup = duplicated(Tp[i], branches, self.mht.separation, self.mht.merge_mahalanobis2)
                if dup[j] or (dup.any() and score[i] <= max(branches[d].log_w for d in np.flatnonzero(dup))
                                                        + self.mht.reroute_nats):
                    continue  # the parent's own mode, or a route into a branch no better than the branch's own
                before = b.smoother.before  # the parent's smoothed poses of the frames still to be reported
                if self.mht.transport_prior:
                    G = rigid_map(T_b, Tp[i])
                    hist_cost, hist = history_cost(b, G)
                    before = {k: (f, t, G @ T) for k, (f, t, T) in before.items()}
                else:  # the parent's own history, unchanged: nothing to charge
                    hist_cost, hist = 0.0, list(b.history)
                if score[i] - hist_cost >= best - self.mht.admit_nats:
                    cands.append((float(score[i] - hist_cost), Tp[i], means[i], b.prior_cov, w0 - hist_cost, hist,
                                  before))
        cands.sort(key=lambda c: -c[0])
        # compete for slots: a candidate needs a slot among the K best and must not duplicate a better pose
        slots = sorted([b.log_w for b in branches], reverse=True)
        out, admitted, rec = [], 0, 0
        for score, T, mean, pc, w0, hist, before in cands:
            rank = sum(s > score for s in slots)
            if rank >= self.mht.max_branches:
                break
            if is_duplicate(T, out, self.mht.separation, self.mht.merge_mahalanobis2):
                continue
            nb, r = self._new_branch(lik, key, obs, T, mean, pc, w0, before)
            rec += r
            if nb is None:
                continue
            nb.history = hist
            out.append(nb)
            slots.append(nb.log_w)
            slots.sort(reverse=True)
            admitted += 1
        return out, n_prop, admitted, rec

    # ------------------------------------------------------------------ step
    def final_smoothed(self) -> list[tuple[int, float, np.ndarray]]:
        """``(frame, t_s, cam_T_needle)`` of the last ``L - 1`` frames at the end of a run, from the best branch
        (the one whose smoothed poses :meth:`step` reports, inherited ones included); ``track`` writes them to
        smoothed.csv."""
        if not self.branches:
            return []
        return self.branches[0].smoother.remaining_smoothed()

    def step(self, observation: Observation) -> Estimate:
        """Update every branch, branch on the proposals, weigh by Laplace evidence, prune (module docstring)."""
        t0 = time.perf_counter()
        motion = self.motion_input(observation)
        observation = motion.observation  # the grasper pose with a detected re-registration removed
        lik = FrameLikelihood(observation, self._model)
        D, motion_noise, Q = motion_model(self.config, motion)
        key = self._key + 1
        recovered, reseeded = 0, False
        if not self.branches:
            branches, recovered = self._seed(lik, key, observation, {})
        else:
            branches = []
            for b in self.branches:
                mean, pc = D @ b.smoother.newest, b.smoother.cov + Q
                try:
                    result, r = b.smoother.advance(lik.gtsam_factors(key), key, D, motion_noise)
                except RuntimeError:  # even map's recovery raised: this branch ends here
                    recovered += 1
                    continue
                T = b.smoother.estimate(key)
                cov, fell_back, _ = b.smoother.finish(key, observation.frame, observation.t_s, T)
                recovered += r + int(fell_back)
                b.inc = branch_evidence(lik, T, cov, mean, pc)
                b.log_w += b.inc
                b.prior_mean, b.prior_cov = mean, pc
                b.iterations = max(int(result.getIterations()), 1)
                branches.append(b)
            if not branches or (self.mht.map.reseed and
                                all(implausible(float(lik.nll(b.smoother.newest)[0]), lik) for b in branches)):
                # the re-detected branches inherit the frames still to be reported from the best branch before
                branches, r = self._seed(lik, key, observation, self.branches[0].smoother.before)
                recovered += r
                reseeded = True
        branches = self._select(branches)
        prev_w = [b.log_w - b.inc for b in branches]  # proposals inherit the parent's weight before this frame
        n_prop = admitted = 0
        if "conic" in lik.term_names:  # the proposals are the ellipse's ambiguities: only with a backbone
            new, n_prop, admitted, r = self._propose(lik, key, observation, branches, prev_w)
            recovered += r
            branches = self._select(branches + new)
        for b in branches:  # remember this frame for the proposals of the coming frames
            b.history = [*b.history, (lik, b.smoother.newest.copy())][-self.mht.history_frames:]
        self.branches = branches
        self._key = key
        lw = np.array([b.log_w for b in branches])
        w = np.exp(lw - lw.max())
        w /= w.sum()
        q_t, q_r, cov_mix = mixture_spread(branches, w, self._z)
        K = self.mht.max_branches
        top = branches[0].smoother
        best = top.newest
        smoothed = top.smoothed_at(key - (self.config.window - 1)) if self.config.window > 1 else None
        pad = K - len(branches)
        particles = np.concatenate([np.stack([b.smoother.newest for b in branches]), np.repeat(best[None], pad, 0)])
        weights = np.r_[w, np.zeros(pad)]
        with np.errstate(divide="ignore"):
            log_post = np.log(weights)
        self.frames_seen += 1
        return Estimate(
            frame=observation.frame,
            t_s=observation.t_s,
            cam_T_needle=best.copy(),
            q95_trans_m=q_t,
            q95_rot_rad=q_r,
            cov_xi=cov_mix,
            iterations=branches[0].iterations,
            latency_ms=(time.perf_counter() - t0) * 1e3,
            particles=particles,
            log_posterior=log_post,
            weights=weights,
            smoothed=smoothed,
            reseeded=reseeded,
            extra={"branches": len(branches), "best_weight": float(w[0]), "proposals": n_prop,
                   "admitted": admitted, "recovered": recovered, **self.kinematics_extra(motion)},
            modes=tuple(Mode(b.smoother.newest.copy(), float(wi), b.smoother.cov.copy())
                        for b, wi in zip(branches, w, strict=True)),
        )
