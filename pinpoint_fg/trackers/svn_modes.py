"""SVN's modes: which hypotheses share a basin, each basin's Laplace evidence, new modes from proposals (issue 9).

Stein transport moves particles *within* a basin of the posterior, never between basins, so
:class:`~pinpoint_fg.trackers.svn.SvnTracker` keeps its modes' books explicitly, with these
pure functions of the windows (:mod:`pinpoint_fg.window`).

**Basins** (:func:`basins`). Each hypothesis's window linearisation (value ``c``, gradient
``g``, information ``H`` of the newest pose, older poses eliminated; right chart) predicts the
peak of its basin by one Gauss-Newton step, ``P_i = T_i Exp(d_i)``, ``d_i = -H_i^-1 g_i`` (in
the kernel's scaled units ``S`` = 5 deg, 1 mm, eigenvalues floored at ``1e-6`` of the largest;
the step clipped to ``max_step`` scaled units), and the cost there,
``m_i = e_i + c_i - 1/2 g_i^T H_i^-1 g_i`` (the quadratic model's drop along the clipped step,
at most ``c_i``; ``e_i`` the accumulated evidence :attr:`pinpoint_fg.window.Window.evidence`).
A hypothesis whose step was clipped is not yet near its peak: its evidence is a guess, and it
is never pruned on it (:attr:`Basins.converged`). Repulsion spreads one mode's
particles by about the kernel scale, but they all predict the same peak; hypotheses whose
predicted peaks lie within ``separation`` scaled units (2: 10 deg or 2 mm, the evaluation's
truth-kept tolerance) of a better one's are one mode (greedy, best first). The report applies the same
rule again to the polished peaks (:func:`join_coincident`): two groups whose representatives polish to
one optimum are reported as one mode, with the better evidence.

**Laplace evidence** of a hypothesis's basin (:func:`pinpoint_fg.proposals.laplace_log_evidence`
applied to the window):

    log Z_i = -m_i - 1/2 log det H_i - 1/2 sum_j log det H_jj    (+ constants common to all)

``H_jj`` are the older poses' conditional informations of the elimination sweep (``L > 1``);
the evidence ``e_i`` holds ``+1/2 log det`` of every pose marginalised so far (window.py), so
``log Z`` is the hypothesis's whole marginal likelihood, frame by frame under Laplace
approximations. Measurement and motion normalisers and the whitening units are the same for
every hypothesis and left out. A mode's evidence is its best member's; mode weights are
``softmax(log Z)`` over modes. The books are kept per mode (:func:`book_sources`): right after the
next frame's marginalisation the members of a settled mode take its polished peak's window prior
and evidence, so a mode's evidence is the marginal likelihood along its peak, not the luckiest member's.

**Proposals** (:func:`propose`). Only on frames with a backbone (>= 5 px) and the conic term:
every proposal keeps the projected ellipse, which is what makes it an ambiguity; without a
backbone a flipped arc is simply a worse fit. For the ``max_modes`` best modes,
:func:`pinpoint_fg.proposals.mode_proposals` gives the twin circle (from the mode's own
ellipse), the three arc flips, and — for the best mode only, since it is the same for all —
both circles of the frame's fitted ellipse with their flips (re-detection from the frame alone,
every frame). A candidate is its parent's window with the newest pose replaced: older poses,
window prior and evidence stay the parent's, so switching mode pays the motion model's price
for the jump (a proposal does not inherit the parent's history for free; no handicap is
needed). Candidates whose Gauss-Newton-predicted cost ``m`` exceeds the best mode's by more
than ``screen_nats``, or whose predicted peak (step not clipped) is a held mode's (the frame's
own circles usually are: they fall just outside ``separation`` of the mode's pose but inside its
basin; with routes on, below, only their parent's own mode), are dropped after one batched
linearisation (under the per-frame process noise a 180 deg flip costs thousands of nats, so on
clear frames nothing is polished); the rest (at most ``max_candidates``, the most promising first)
are polished by Levenberg-Marquardt on their windows (:func:`polish`), deduplicated against every
mode (with routes on, a better route into one replaces it) and each other, and **admitted** when
their ``log Z`` is within ``admit_nats`` of the best mode's and among the ``max_modes`` best.

**Routes** (``reroute_nats``; off by default). A candidate whose peak is *another* held mode's is a
second route into that mode: the parent's history, then a jump the motion model prices. With a finite
``reroute_nats`` such candidates are generated, screened on their predicted ``log Z`` and polished only
when that beats the mode's by more than ``reroute_nats``; if one still does once polished, every member
of the mode takes its window (prior, evidence, older poses; the first copy exact, the others jittered),
so the mode's evidence is its best route's (MHT: ``MhtConfig.reroute_nats``). The mass of a basin sums
over every history that ends in it, and the best route is nearer that sum than the mode's own history.
Measured with 1 nat in both trackers (the thirty-fourth round, ``scripts/mode_agreement.py``,
``scripts/compare_svn_map_mht.py``, bench42): SVN's and MHT's weights agree (median log-odds offset of
the same two modes over snapshots seeds 1-8, 3.7 -> 0.006 nats; SVN's modes verdict on the frames MHT
calls multimodal / single-mode 51 / 9.0 % -> 80 / 5.8 %), but a minor mode then weighs what one frame
says against the jump, not its whole history, the MAP (the heaviest mode) follows single frames, and
SVN's snapshots accuracy fell: mean rotation 18.3 -> 19.9 deg (seeds 1-8), 17.7 -> 19.2 (9-16), held-out
geometry 39.3 -> 75.0 (truth kept 98 -> 86 %). Not the default.

**Allotment** (:func:`allot`). Every admitted mode — new, or existing and within
``admit_nats`` of the best — holds at least ``floor`` hypotheses: copies of its window (the
first exact, the others jittered at the newest pose, so the transport spreads them) replace the
worst hypotheses of modes outside the ``max_modes`` best, then of the most populous mode (which
keeps at least ``floor``). Particle counts are not mode weights (transport cannot move mass
between basins); the weights are the evidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.lie import local, se3_exp
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.proposals import mode_proposals, polish_with_prior
from pinpoint_fg.stein import floor_hessians
from pinpoint_fg.window import Linearization, Window
from pinpoint_fg.window_rows import copy_hypotheses

#: Kernel scale S of the scaled tangent units: [omega x3 (rad), v x3 (m)] (svn.py's default).
SCALE = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)

#: ``np.outer(SCALE, SCALE)``, built once (read-only): scales an information matrix to the scaled units.
_SCALE_OUTER = np.outer(SCALE, SCALE)
_SCALE_OUTER.flags.writeable = False


@dataclass(frozen=True)
class ModeSettings:
    """How SVN finds, admits and populates modes (module docstring)."""

    proposals: bool = True
    """Propose twins, flips and the frame's circles every backbone frame (False: only transport and pruning)."""
    max_modes: int = 4
    """K: at most this many modes are populated and reported."""
    admit_nats: float = 10.0
    """A proposal (or an existing mode) is admitted when its log-evidence is within this of the best (1 : e^10)."""
    screen_nats: float = 30.0
    """Candidates whose predicted cost exceeds the best mode's by more than this are not polished."""
    floor: int = 4
    """Each admitted mode holds at least this many hypotheses (capped at N / max_modes)."""
    separation: float = 2.0
    """Predicted peaks closer than this (scaled units: 10 deg, 2 mm) are one mode."""
    max_step: float = 4.0
    """The Gauss-Newton prediction of a basin's peak moves at most this far (scaled units)."""
    polish_iters: int = 8
    """Levenberg-Marquardt steps that polish each proposal on its window."""
    max_candidates: int = 6
    """At most this many screened proposals (the lowest predicted cost first) are polished per frame."""
    map_starts: int = 3
    """The best mode is polished from this many of its members (:func:`settle`; 1: its best hypothesis only)."""
    start_spacing: float = 1.0
    """The best mode's extra starts have predicted peaks at least this far apart (scaled units: one kernel scale,
    5 deg / 1 mm; :func:`_extra_starts`)."""
    shared_books: bool = True
    """Every member of a settled mode takes its polished peak's window prior and evidence, right after the next
    frame's marginalisation (:func:`book_sources`; False: each hypothesis keeps its own)."""
    reroute_nats: float = float("inf")
    """A proposal landing in another held mode's basin replaces that mode's books (the better route into it) when its
    log-evidence beats the mode's by more than this; inf (the default): held modes keep their own history and such
    proposals are not generated (module docstring, *Routes*: 1 was measured and not kept)."""
    map_from_prediction: bool = True
    """The previous MAP hypothesis at its motion prediction is one more start of its mode's polish (:func:`settle`)."""
    frame_polish_iters: int = 0
    """Levenberg-Marquardt steps that polish every proposal on the frame alone before it is screened, as MHT's
    proposals are (:func:`pinpoint_fg.proposals.polish_with_prior` without a prior); 0 (the default): screened as
    proposed, by the one-step prediction of its window's peak. Where a raw proposal lies far from the frame's optimum
    that prediction can screen out a branch MHT keeps: on calibration-03 (unseen seed 3) MHT holds from frame 135 a
    branch 4 deg nearer the truth (weight 0.004) that wins at frame 138, while SVN's best proposal there was predicted
    46 nats above its mode (the screen is 30) and SVN stays 10-21 deg off to the last frame. Measured lock-step, 0
    against 6 (``scripts/svn_settings_ab.py modes.frame_polish_iters 0 6 RUN...``, nine scenarios, seeds 1-4): equals
    MHT on calibration-03 (6.13 -> 5.31 deg, truth kept 92 -> 100 %) and symmetric-01 keeps the truth on 35 % of frames
    instead of 1 %, but calibration-01 3.84 -> 4.31 deg, drive-01 2.98 -> 3.19, drive-03 2.52 -> 2.91, snapshots 16.9
    -> 18.4 deg over seeds 1-4, every other run within 0.06 deg; mask frames cost 11-51 % more (snapshots 1.01-1.18x per
    frame). Not the default."""

    def __post_init__(self) -> None:
        if isinstance(self.frame_polish_iters, bool) or not isinstance(self.frame_polish_iters, int | np.integer) \
                or self.frame_polish_iters < 0:
            raise ValueError(f"frame_polish_iters must be an integer >= 0, got {self.frame_polish_iters!r}")
        if not self.reroute_nats >= 0:
            raise ValueError(f"reroute_nats must be >= 0 (inf: no rerouting), got {self.reroute_nats}")


@dataclass(frozen=True)
class Basins:
    """The modes of a set of hypotheses (module docstring), for one linearisation."""

    log_evidence: np.ndarray
    """(N,) Laplace log-evidence of each hypothesis's basin (up to a common constant)."""
    peaks: np.ndarray
    """(N, 4, 4) each hypothesis's predicted basin peak."""
    labels: np.ndarray
    """(N,) mode index of each hypothesis (modes ordered by evidence, best first)."""
    reps: np.ndarray
    """(M,) the best hypothesis of each mode."""
    converged: np.ndarray
    """(N,) the predicted peak is within ``max_step`` (else its evidence is a guess: never pruned on it)."""

    @property
    def mode_log_evidence(self) -> np.ndarray:
        """(M,) each mode's log-evidence (its best member's)."""
        return self.log_evidence[self.reps]

    def heaviest_rep(self) -> int:
        """The best hypothesis of the mode with the most posterior mass (the highest log-evidence; NaN never wins)."""
        z = self.mode_log_evidence
        return int(self.reps[int(np.argmax(np.where(np.isnan(z), -np.inf, z)))])

    @property
    def weights(self) -> np.ndarray:
        """(M,) normalised mode weights ``softmax(log Z)``."""
        z = self.mode_log_evidence
        w = np.exp(z - np.max(z)) if np.isfinite(np.max(z)) else np.ones_like(z)
        return w / w.sum()

    def counts(self) -> np.ndarray:
        """(M,) hypotheses per mode."""
        return np.bincount(self.labels, minlength=self.reps.shape[0])


def scaled_distance(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """``|Log(T_a^-1 T_b) / S|``: distance in scaled units, broadcast over leading axes.

    The norm is ``np.linalg.norm(x, axis=1)``'s own formula, ``sqrt(add.reduce(x * x, axis=1))`` (the same bits),
    without its generic dispatch; operands of equal shape skip the broadcast (the usual call compares one pose
    with a few: per-call overhead is the cost).
    """
    A, B = np.asarray(T_a, dtype=float), np.asarray(T_b, dtype=float)
    if A.shape != B.shape:
        A, B = np.broadcast_arrays(A, B)
    x = local(A.reshape(-1, 4, 4), B.reshape(-1, 4, 4)) / SCALE
    return np.sqrt(np.add.reduce(x * x, axis=1)).reshape(A.shape[:-2])


def rotation_beyond(R_a: np.ndarray, R_b: np.ndarray, angle_rad: float) -> np.ndarray:
    """Which rotations ``R_b (K, 3, 3)`` lie certainly more than ``angle_rad`` from ``R_a (3, 3)``: ``(K,)`` bool.

    ``cos theta = (tr(R_a^T R_b) - 1) / 2`` from one product; the test keeps a relative margin of 1e-6 on the
    angle, far above that cosine's round-off. The rotation part of a tangent bounds its scaled norm from below
    (``|Log(T_a^-1 T_b) / S| >= theta / max(S_rot)``), so
    :func:`_greedy_groups` skips the logarithms of poses this rules out: the same groups, and no near-pi
    logarithm (the costliest kind) for a twin mode's poses half a turn away.
    """
    bound = angle_rad * (1.0 + 1e-6)
    if bound >= np.pi:
        return np.zeros(R_b.shape[0], dtype=bool)
    return 0.5 * (np.einsum("ij,kij->k", R_a, R_b) - 1.0) < np.cos(bound)


def laplace_terms(lin: Linearization, evidence: np.ndarray, max_step: float = 4.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted peak step ``d (N, 6)``, peak cost ``m (N,)`` and log-evidence ``log Z (N,)`` (module docstring)."""
    S = SCALE
    H_fl, Hinv = floor_hessians(lin.hess * _SCALE_OUTER, eps=1e-6)
    gw = lin.grad * S
    step_w = -np.einsum("nij,nj->ni", Hinv, gw)
    norm = np.sqrt(np.add.reduce(step_w * step_w, axis=1))  # = np.linalg.norm(step_w, axis=1), its formula
    step_w = step_w * np.minimum(1.0, max_step / np.maximum(norm, 1e-300))[:, None]
    # the quadratic model's decrease along the (clipped) step: exact GN prediction when not clipped
    drop = -np.einsum("ni,ni->n", gw, step_w) - 0.5 * np.einsum("ni,nij,nj->n", step_w, H_fl, step_w)
    drop = np.clip(drop, 0.0, np.maximum(lin.value, 0.0))
    m = evidence + lin.value - drop
    logdet = np.linalg.slogdet(H_fl)[1]
    for cond_inv in lin.cond_inv:  # -1/2 log det H_jj = +1/2 log det H_jj^-1
        logdet = logdet - np.linalg.slogdet(cond_inv)[1]
    log_z = -m - 0.5 * logdet
    return step_w * S, m, np.where(np.isfinite(log_z), log_z, -np.inf)


def basins(newest: np.ndarray, lin: Linearization, evidence: np.ndarray, settings: ModeSettings = ModeSettings()
           ) -> Basins:
    """Group hypotheses ``newest (N, 4, 4)`` into modes by their predicted peaks (module docstring)."""
    step, _, log_z = laplace_terms(lin, evidence, settings.max_step)
    converged = np.linalg.norm(step / SCALE, axis=1) < settings.max_step
    P = newest @ se3_exp(step)
    N = P.shape[0]
    order = np.lexsort((np.arange(N), -np.nan_to_num(log_z, neginf=-1e300)))
    labels, reps = _greedy_groups(P, order, settings.separation)
    return Basins(log_z, P, labels, reps, converged)


def _greedy_groups(P: np.ndarray, order: np.ndarray | list[int], separation: float) -> tuple[np.ndarray, np.ndarray]:
    """Group poses ``P (K, 4, 4)``, best first: ``(labels (K,), reps (G,))``.

    In ``order``, each pose not yet grouped becomes a group's representative and takes every ungrouped pose within
    ``separation`` scaled units of it; ``labels`` number the groups as ``reps`` lists them. :func:`basins` groups
    hypotheses by their predicted peaks with it, :func:`join_coincident` the reported modes by their peaks.
    """
    labels = np.full(P.shape[0], -1)
    reps: list[int] = []
    radius_rad = separation * SCALE[:3].max()  # the rotation angle no pose of a group can exceed
    for i in order:
        if labels[i] >= 0:
            continue
        free = np.flatnonzero(labels < 0)
        free = free[~rotation_beyond(P[i, :3, :3], P[free, :3, :3], radius_rad)]
        close = free[scaled_distance(P[i], P[free]) < separation]
        labels[close] = len(reps)
        labels[i] = len(reps)
        reps.append(int(i))
    return labels, np.asarray(reps, dtype=int)


def polish(sub: Window, lin: Linearization, iters: int, decrement: float = 1e-3) -> Linearization:
    """Levenberg-Marquardt on every hypothesis of ``sub`` (each on its own window, batched); returns the final model.

    A step ``-(H + lambda diag H)^-1 g`` of the newest pose (older poses follow by back-substitution)
    is kept only where the window's cost drops; ``lambda`` shrinks by 0.3 on success and grows by 10
    otherwise. A hypothesis stops when its Gauss-Newton decrement ``1/2 g^T H^-1 g`` is below
    ``decrement`` nats or after two rejected steps in a row (at L > 1 the trial's exact last motion term
    and the model's slope can disagree near the peak: measured, every step up to the cap was rejected on a
    quarter of the frames at L = 5); all stop after ``iters`` steps.
    """
    N = sub.newest.shape[0]
    lam = np.full(N, 1e-3)
    rejected = np.zeros(N, dtype=int)
    for _ in range(iters):
        _, Hinv = floor_hessians(lin.hess, eps=1e-9)
        active = (0.5 * np.einsum("ni,nij,nj->n", lin.grad, Hinv, lin.grad) >= decrement) & (rejected < 2)
        if not active.any():
            break
        diag = np.maximum(np.einsum("nii->ni", lin.hess), 1e-12)
        A = lin.hess + lam[:, None, None] * (diag[:, :, None] * np.eye(6))
        step = -np.linalg.solve(A, lin.grad[..., None])[..., 0]
        step = np.where(active[:, None] & np.isfinite(step), step, 0.0)
        T_trial = sub.newest @ se3_exp(step)
        trial = sub.newest_value(T_trial, lin)
        better = active & np.isfinite(trial) & (trial < lin.value)
        if better.any():
            move = np.where(better[:, None], step, 0.0)
            # every step kept (the usual case): the moved newest poses are the trial's, bit for bit
            sub.move_newest(move, lin, newest=T_trial if move.tobytes() == step.tobytes() else None)
            lin = sub.linearize()
        lam = np.where(better, lam * 0.3, lam * 10.0)
        rejected = np.where(better, 0, rejected + active)
    return lin


def _extra_starts(found: Basins, mode: int, rep: int, cost: np.ndarray, count: int, spacing: float) -> list[int]:
    """Up to ``count`` members of ``mode`` to polish besides ``rep``, the lowest ``cost (N,)`` first, each one's
    predicted peak at least ``spacing`` scaled units from every start chosen before it (``rep``'s first).

    The starts should reach distinct local optima, and members whose predicted peaks lie within one kernel scale
    of a start already chosen mostly end at its optimum. Measured on drive-01, frame 57 (``scripts/polish_starts.py
    RUN 57``: every member of the best mode polished for 30 steps): of the 27 members 0.5-1.0 unit from the
    representative's predicted peak, 25 ended at its optimum (10.9 deg off the truth) and none at the optimum 5.3
    nats lower (7.6 deg off, MHT's pose), which 4 of the 11 members 1.0-1.7 units away reached. The rule before
    (the two lowest-cost members more than 0.5 unit from the representative's peak) took members 0.56 and 0.60
    unit away; this one takes one 1.70 units away, which reaches the better optimum.
    """
    members = np.flatnonzero(found.labels == mode)
    members = members[members != rep]
    far = members[scaled_distance(found.peaks[rep], found.peaks[members]) >= spacing]
    out: list[int] = []
    for j in far[np.argsort(cost[far], kind="stable")]:
        if len(out) >= count:
            break
        if not out or np.min(scaled_distance(found.peaks[j], found.peaks[out])) >= spacing:
            out.append(int(j))
    return out


def settle(window: Window, lin: Linearization, found: Basins, iters: int, decrement: float = 1e-3,
           max_modes: int = 8, starts: int = 1, predicted: tuple | None = None, spacing: float = 1.0
           ) -> tuple[Basins, np.ndarray, Linearization]:
    """Polish the best hypothesis of each of the ``max_modes`` best modes on its window and re-score the modes.

    A mode's evidence from the Gauss-Newton prediction is only as good as its best particle's
    convergence (the transport stops on step size with the whole cloud in view; after a large
    motion a mode's particles may still be many nats from its peak): comparing a polished
    mode with an unpolished one favours the polished. So every compared mode's best hypothesis
    is moved to its peak (:func:`polish`, batched; written back to the window) and every member
    of a mode carries its mode's polished log-evidence (modes beyond ``max_modes`` keep their
    prediction).

    ``starts > 1``: the best mode is also polished from up to ``starts - 1`` more of its members, chosen by
    :func:`_extra_starts` (the lowest-cost ones whose predicted peaks lie at least ``spacing`` scaled units from
    every other start's). A mode groups peaks within ``separation`` (10 deg, 2 mm); through an edge-on turn
    it can hold two local optima a few degrees apart, and the best hypothesis's polish finds only the one it
    started in. The mode's representative is then the polished start with the highest evidence.

    ``predicted`` ``(row, cam_T_newest (4, 4))``: one more start for the mode of hypothesis ``row``, at
    ``cam_T_newest`` — the previous MAP hypothesis at its motion prediction, where single-mode MAP starts
    its local search (a third element, optional: that one-hypothesis window's model at ``cam_T_newest``, when the
    caller holds it already; the tracker does with one pose per window, where it equals a fresh linearisation
    to round-off) — unless its Gauss-Newton-predicted peak lies within half a unit of one of that
    mode's starts' already. Transport moves that hypothesis before the polish, and repulsion can carry it
    over a ridge into a worse local optimum of the same mode (measured on drive-01, frame 60: 6.8 nats
    worse than the MAP baseline's optimum, 3.4 deg away). Where a row is polished from two starts, the
    one with the higher evidence is kept. A polished start may leave its mode's basin and still represent the
    mode; excluding starts that end more than ``separation`` from the mode's predicted peak was measured
    worse (snapshots seeds 1-4 mean rotation error 19.3 / 11.9 / 14.2 / 26.1 -> 22.0 / 14.4 / 16.0 / 29.0 deg;
    symmetric-01 bimodal frames 100 -> 14 %), so it is not done.

    Returns the re-scored basins (``reps`` updated), the polished hypotheses' indices (unique) and their
    final model.
    """
    z = found.mode_log_evidence
    chosen = np.argsort(-np.nan_to_num(z, neginf=-1e300), kind="stable")[:max_modes]
    reps = found.reps[chosen]
    cand, cand_mode = list(reps), list(chosen)
    if starts > 1 and chosen.size:
        extra = _extra_starts(found, int(chosen[0]), int(reps[0]), lin.value + window.evidence, starts - 1, spacing)
        cand += extra
        cand_mode += [int(chosen[0])] * len(extra)
    lin_sub = lin.subset(cand)
    from_prediction = False
    if predicted is not None and np.isin(found.labels[predicted[0]], chosen):
        row, m = int(predicted[0]), int(found.labels[predicted[0]])
        if len(predicted) > 2:  # the model is given: the one-hypothesis window itself is not needed
            lin_one, start = predicted[2], np.asarray(predicted[1], dtype=float)[None]
        else:
            one = window.subset([row])
            one.poses[-1, 0] = predicted[1]
            lin_one, start = one.linearize(), one.newest
        peak = start @ se3_exp(laplace_terms(lin_one, window.evidence[[row]])[0])
        starts_m = np.asarray(cand)[np.asarray(cand_mode) == m]
        if np.min(scaled_distance(peak[0], found.peaks[starts_m]), initial=np.inf) > 0.5:  # a peak not yet sought
            cand.append(row)
            cand_mode.append(m)
            lin_sub = lin_sub.append(lin_one)
            from_prediction = True
    cand_a, cand_mode_a = np.asarray(cand, dtype=int), np.asarray(cand_mode, dtype=int)
    sub = window.subset(cand_a)
    if from_prediction:
        sub.poses[-1, -1] = predicted[1]
    lin_r = polish(sub, lin_sub, iters, decrement)
    _, _, z_r = laplace_terms(lin_r, sub.evidence)
    keep = _best_per_row(cand_a, z_r)
    if keep.size < cand_a.size:  # a row polished from two starts: keep the better
        sub, lin_r, z_r = sub.subset(keep), lin_r.subset(keep), z_r[keep]
        cand_a, cand_mode_a = cand_a[keep], cand_mode_a[keep]
    window.adopt(sub, cand_a)
    mode_z = z.copy()
    new_reps = found.reps.copy()
    peaks = found.peaks.copy()
    peaks[cand_a] = sub.newest
    for m in chosen:
        rows = np.flatnonzero(cand_mode_a == m)
        best = rows[int(np.argmax(np.nan_to_num(z_r[rows], nan=-np.inf)))] if np.isfinite(z_r[rows]).any() else rows[0]
        mode_z[m] = z_r[best]
        new_reps[m] = cand_a[best]
    converged = found.converged[found.reps].copy()
    converged[chosen] = True
    settled = Basins(mode_z[found.labels], peaks, found.labels, new_reps, converged[found.labels])
    return settled, cand_a, lin_r


def join_coincident(found: Basins, separation: float = 2.0, first: int | None = None,
                    peaks: np.ndarray | None = None) -> Basins:
    """The reported modes of ``found``: modes whose peaks lie within ``separation`` of a better one's are that mode.

    :func:`basins` groups hypotheses by their Gauss-Newton-predicted peaks, a guess where the step was clipped (after
    a large motion, at the first frame), and :func:`settle` then often polishes two groups' representatives to one
    optimum. What is reported (``modes.csv``, the modes verdict) is one mode per peak, by the rule that made the
    groups: greedy over the modes by evidence, best first, a mode whose peak (``found.peaks[found.reps]``: polished
    for the settled modes) lies within ``separation`` scaled units of a kept mode's joins it, and the better evidence
    stands (a MAP over mode histories, as :mod:`pinpoint_fg.trackers.mht` merges its branches; not a sum: at the
    first frame, where no history differs, the groups are one Laplace component counted several times). The
    surviving modes keep their order; labels are renumbered.

    ``peaks`` (M, 4, 4): the poses the report gives the modes, when they are not ``found.peaks[found.reps]`` (the
    tracker reports the MAP's mode at the MAP hypothesis, which need not be that mode's representative). ``first``:
    a mode kept whatever its evidence (the MAP's), so that the pose it is reported at is the one the others are
    compared with; modes joining it lend it their evidence when better (its representative stays its own).

    Only the report is joined: the tracker prunes, shares books and allots on ``found``. Joining those too was
    measured (svn on snapshots seeds 1-20, ``scripts/compare_svn_map_mht.py DIR --methods svn``): mean rotation error
    21.0 -> 22.4 deg, truth kept 92.0 -> 92.0 %, ten runs better and ten worse by up to 20 deg; clear runs unchanged.
    Measured before the join on the benchmark's seed-1 runs (bench22): a second reported mode within 2 scaled units
    of the first on 101 of 150 snapshots frames, 17 symmetric and 1-5 elsewhere, mostly 0.001-0.01 units apart; 74
    of snapshots' 89 frames the modes verdict called bimodal were so only through such a copy.
    """
    z = found.mode_log_evidence
    M = z.shape[0]
    if M < 2:
        return found
    P = found.peaks[found.reps] if peaks is None else np.asarray(peaks, dtype=float)
    order = [int(m) for m in np.argsort(-np.nan_to_num(z, nan=-np.inf, neginf=-1e300), kind="stable")]
    if first is not None:
        order = [int(first)] + [m for m in order if m != first]
    group, leaders = _greedy_groups(P, order, separation)
    into = leaders[group]  # each mode's kept mode (itself when kept)
    keep = np.flatnonzero(into == np.arange(M))
    if keep.size == M:
        return found
    z_joined = np.full(M, -np.inf)
    np.maximum.at(z_joined, into, np.nan_to_num(z, nan=-np.inf))
    number = np.full(M, -1)
    number[keep] = np.arange(keep.size)
    labels = number[into[found.labels]]
    z_kept, conv = z_joined[keep], found.converged[found.reps][keep]
    return Basins(z_kept[labels], found.peaks, labels, found.reps[keep], conv[labels])


def book_sources(found: Basins, reps: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Books per mode: ``(members, their rep)``, the hypotheses that take a settled mode's books and whose.

    ``reps``: the settled hypotheses (:func:`settle`); ``index`` (N,): the copy map of a pruning since
    ``found`` was computed. A rep that was pruned gives no books. The tracker applies the map with
    :func:`pinpoint_fg.window_rows.share_books` right after the next frame's marginalisation, so every
    member's prior is the one marginalised at its mode's polished peak — where single-mode MAP
    marginalises — not at the member's own pose, off the peak by about the kernel scale. Sharing the
    prior before that marginalisation instead left each member's next prior linearised at its own pose;
    the member with the luckiest linearisation then became the MAP: on calibration-01, frames 67-91,
    3-9 deg from the MAP baseline whose pose cost 3-15 nats more in that member's window; shared after
    the marginalisation, the two agree to within 0.4 deg on those frames (0.0-0.1 deg on 25 of 26).
    """
    N = index.shape[0]
    labels = found.labels[index]
    source = np.full(N, -1)
    for r in np.asarray(reps, dtype=int):
        if index[r] == r:  # the rep survived the pruning
            source[labels == found.labels[r]] = r
    members = np.flatnonzero((source >= 0) & (source != np.arange(N)))
    return members, source[members]


def _best_per_row(rows: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Indices into ``rows`` keeping, for each distinct row, the entry with the highest ``z`` (order kept)."""
    order = np.lexsort((np.arange(rows.size), -np.nan_to_num(z, nan=-np.inf)))  # best first, ties: earliest
    _, first = np.unique(rows[order], return_index=True)
    return np.sort(order[first])


@dataclass(frozen=True)
class Admitted:
    """Proposals admitted as new modes: their polished windows and log-evidence."""

    windows: Window | None
    """The polished candidate windows (one hypothesis each), or None."""
    log_evidence: np.ndarray
    """(A,) their log-evidence."""
    screened: int
    """How many proposals were generated this frame."""
    basins: Basins | None = None
    """The modes as re-scored for the admission (:func:`settle`), when they were."""
    replaces: np.ndarray | None = None
    """(A,) the mode of ``basins`` each admitted window is a better route into (its members take the window), or
    -1 for a new mode; None: every one is new."""

    def replaced(self) -> np.ndarray:
        """(A,) :attr:`replaces`, all -1 when None."""
        n = self.log_evidence.shape[0]
        return np.full(n, -1) if self.replaces is None else np.asarray(self.replaces, dtype=int)


def propose(window: Window, lin: Linearization, found: Basins, lik: FrameLikelihood,
            settings: ModeSettings = ModeSettings()) -> Admitted:
    """Proposals of the best modes, screened, polished, deduplicated and admitted (module docstring)."""
    none = Admitted(None, np.zeros(0), 0)
    backbone = lik.observation.backbone_px
    if not settings.proposals or "conic" not in lik.term_names or backbone is None or len(backbone) < 5:
        return none
    mode_z = found.mode_log_evidence
    top = np.argsort(-mode_z, kind="stable")[: settings.max_modes]
    all_peaks = found.peaks[found.reps]
    poses, parents = [], []
    reroute = bool(np.isfinite(settings.reroute_nats))
    for k, m in enumerate(top):
        # with routes on, proposals landing in another held mode are kept: other routes into it (screened below)
        others = None if reroute else np.delete(all_peaks, m, axis=0)
        p = mode_proposals(all_peaks[m], lik, existing=others, frame_ellipse=(k == 0))
        poses.append(p)
        parents += [int(found.reps[m])] * p.shape[0]
    n_prop = len(parents)
    if n_prop == 0:
        return none
    cand = window.subset(parents)
    cand.poses[-1] = np.concatenate(poses)
    if settings.frame_polish_iters > 0:
        cand.poses[-1] = polish_with_prior(lik, cand.poses[-1], iters=settings.frame_polish_iters)[0]
    lin_c = cand.linearize()
    step_p, m_c, z_p = laplace_terms(lin_c, cand.evidence, settings.max_step)
    _, m_modes, _ = laplace_terms(lin.subset(found.reps), window.evidence[found.reps], settings.max_step)
    # a candidate whose (unclipped) predicted peak is a held mode's is that mode's basin: another route into it,
    # polished only when its predicted evidence beats the mode's (the better route wins, module docstring)
    unclipped = np.linalg.norm(step_p / SCALE, axis=1) < settings.max_step
    d_held = scaled_distance((cand.newest @ se3_exp(step_p))[:, None], all_peaks[None])
    nearest = np.argmin(d_held, axis=1)
    known = unclipped & (d_held[np.arange(nearest.shape[0]), nearest] < settings.separation)
    same_route = nearest == found.labels[np.asarray(parents)]  # the parent's own basin: its own history
    worse_route = known & (same_route | ~(z_p > mode_z[nearest] + settings.reroute_nats))
    keep = np.flatnonzero(np.isfinite(m_c) & (m_c <= np.min(m_modes) + settings.screen_nats) & ~worse_route)
    keep = keep[np.argsort(m_c[keep], kind="stable")[: settings.max_candidates]]
    if keep.size == 0:
        return Admitted(None, np.zeros(0), n_prop)
    cand = cand.subset(keep)
    lin_c = polish(cand, lin_c.subset(keep), settings.polish_iters)
    step_c, _, z_c = laplace_terms(lin_c, cand.evidence, settings.max_step)
    peaks_c = cand.newest @ se3_exp(step_c)
    # the modes are compared polished, as the candidates are (:func:`settle`)
    found, _, _ = settle(window, lin, found, settings.polish_iters, max_modes=settings.max_modes)
    mode_z = found.mode_log_evidence
    all_peaks = found.peaks[found.reps]
    best = float(np.max(mode_z))
    accepted: list[int] = []
    rerouted: dict[int, int] = {}  # held mode -> the candidate that is a better route into it
    parent_mode = found.labels[np.asarray(parents)[keep]]
    for i in np.argsort(-z_c, kind="stable"):
        if not z_c[i] >= best - settings.admit_nats:
            break
        if accepted and np.any(scaled_distance(peaks_c[i], peaks_c[accepted]) < settings.separation):
            continue
        d_modes = scaled_distance(peaks_c[i], all_peaks)
        near = np.flatnonzero(d_modes < settings.separation)
        if near.size == 0:
            accepted.append(int(i))
            continue
        m = int(near[np.argmin(d_modes[near])])
        if m not in rerouted and m != parent_mode[i] and z_c[i] > np.max(mode_z[near]) + settings.reroute_nats:
            rerouted[m] = int(i)
    # the max_modes best of modes (each at its better route's evidence) and new candidates
    z_eff = mode_z.copy()
    for m, i in rerouted.items():
        z_eff[m] = z_c[i]
    M = mode_z.shape[0]
    union = np.concatenate([z_eff, z_c[accepted]])
    slots = np.argsort(-union, kind="stable")[: settings.max_modes]
    fresh = [accepted[j - M] for j in slots if j >= M]
    routed_modes = [int(j) for j in slots if int(j) in rerouted]
    chosen = fresh + [rerouted[m] for m in routed_modes]
    replaces = [-1] * len(fresh) + routed_modes
    if not chosen:
        return Admitted(None, np.zeros(0), n_prop, found)
    return Admitted(cand.subset(chosen), z_c[chosen], n_prop, found, np.asarray(replaces, dtype=int))


def allot(window: Window, found: Basins, admitted: Admitted, settings: ModeSettings,
          rng: np.random.Generator, jitter_sigma: np.ndarray) -> int:
    """Give every admitted mode at least ``floor`` hypotheses (module docstring); returns how many were moved."""
    if admitted.basins is not None:
        found = admitted.basins
    N = window.newest.shape[0]
    n_adm = 0 if admitted.windows is None else admitted.log_evidence.shape[0]
    replaces = admitted.replaced() if n_adm else np.zeros(0, dtype=int)
    floor = max(1, min(settings.floor, N // max(1, settings.max_modes)))
    mode_z = found.mode_log_evidence.copy()
    mode_z[replaces[replaces >= 0]] = admitted.log_evidence[replaces >= 0]
    new_rows = np.flatnonzero(replaces < 0)
    union = np.concatenate([mode_z, admitted.log_evidence[new_rows]])
    slots = np.argsort(-union, kind="stable")[: settings.max_modes]
    best = float(np.max(union))
    kept_modes = [int(j) for j in slots if j < mode_z.shape[0]]
    counts = found.counts()
    moved = 0
    # a better route into a held mode: every member takes its window (the first exactly, the others jittered)
    source_row = found.reps.copy()
    for a in np.flatnonzero(replaces >= 0):
        members = np.flatnonzero(found.labels == replaces[a])
        copy_hypotheses(window, members, admitted.windows, np.full(members.shape[0], a))
        window.poses[-1, members[1:]] = window.poses[-1, members[1:]] @ se3_exp(
            rng.normal(size=(members.shape[0] - 1, 6)) * jitter_sigma)
        source_row[replaces[a]] = members[0]
        moved += members.shape[0]
    # sources: (window, row, how many copies) for under-populated admitted modes
    needs: list[tuple[Window, int, int, bool]] = []
    for m in kept_modes:
        if counts[m] < floor and mode_z[m] >= best - settings.admit_nats:
            needs.append((window, int(source_row[m]), floor - int(counts[m]), False))
    for a in new_rows:
        needs.append((admitted.windows, int(a), floor, True))
    if not needs:
        return moved
    # donors, in order: modes outside the K best (worst first), then the most populous mode's worst members
    cost = -found.log_evidence
    outside = [m for m in np.argsort(mode_z, kind="stable") if m not in kept_modes]
    donors = [int(i) for m in outside for i in np.flatnonzero(found.labels == m)[np.argsort(-cost[found.labels == m])]]
    protected = set(int(r) for r in source_row[kept_modes])
    remaining = counts.copy()
    for src, row, n, new in needs:
        for c in range(n):
            if not donors:
                big = int(np.argmax(np.where(np.isin(np.arange(len(remaining)), kept_modes), remaining, -1)))
                if remaining[big] <= floor:
                    return moved
                members = [int(i) for i in np.flatnonzero(found.labels == big) if int(i) not in protected]
                members.sort(key=lambda i: -cost[i])
                donors = members[: int(remaining[big]) - floor]
                remaining[big] = floor
                if not donors:
                    return moved
            dst = donors.pop(0)
            copy_hypotheses(window, [dst], src, [row])
            if c > 0 or not new:
                window.poses[-1, dst] = window.poses[-1, dst] @ se3_exp(rng.normal(size=6) * jitter_sigma)
            moved += 1
    return moved
