"""Per-hypothesis sliding windows, batched over particles (DESIGN.md §Inference, steps 2, 3, 5).

Each of the ``N`` hypotheses owns a window of its last ``L`` poses ``x_0 .. x_{L-1}`` (oldest to
newest) with

* a Gaussian prior on ``x_0``, ``1/2 |W_p Log(mu^-1 x_0)|^2``, holding what was marginalised,
* the measurement terms of each window frame (:class:`pinpoint_fg.likelihood.FrameLikelihood`),
* motion terms ``1/2 |W_m Log((D_j x_j)^-1 x_{j+1})|^2`` between consecutive poses, with
  ``D_j`` the grasper's measured motion (identity plus a random-walk noise when the motion model
  is off or kinematics are missing).

The frames and motions are shared by all hypotheses; only poses and priors differ.

The elimination maths (Schur sweep, back-substitution, marginal prior) are pure functions in
:mod:`pinpoint_fg.elimination`; this module owns the windows' state.

**Per-particle linearisation** (:meth:`Window.linearize`): at each hypothesis's own poses the
window's Gauss-Newton model ``c + g^T d + 1/2 d^T H d`` (``d`` stacks the right-chart tangent
perturbations of the L poses) is block tridiagonal; a forward Schur sweep eliminates
``x_0 .. x_{L-2}`` and leaves the marginal model of the newest pose: value ``c``, gradient ``g``
and information ``H`` (6x6), all particles at once. The sweep's conditionals give the
back-substitution that moves the older poses with the newest (smoothing). This equals GTSAM's
``linearize`` + ``eliminatePartialMultifrontal`` on the same window (tested).

**Relinearisation threshold** (:attr:`Window.relin_threshold`, :mod:`pinpoint_fg.relinearize`): at
``L > 1`` the Gauss-Newton model of the terms among the older poses is reused, corrected to first and
second order, while those poses moved less than the threshold since it was last evaluated exactly
(0: every call exact, the path the GTSAM comparison pins).

**Sliding** (:meth:`Window.push`): a new frame appends the pose predicted by the grasper's motion;
when the window exceeds ``L`` poses the oldest is marginalised into a new prior on the next one
(Schur complement, re-expressed as a mean and information; eigenvalues floored so it stays
positive definite). ``L = 1`` is the paper's filter.

**Evidence**: marginalisation also leaves a constant per hypothesis — the cost of the history it
removed, at its optimum. Discarding it (as a prior factor does) would make every hypothesis look
equally supported by the past; it is kept in :attr:`Window.evidence` with a forgetting factor
``gamma`` per frame (``evidence <- gamma * evidence + c``; ``gamma = 1``: none), so hypotheses are
compared on their history rather than on the current frame alone. ``c`` is the negative log of
the Laplace integral over the removed pose: the Gauss-Newton optimum's cost plus
``1/2 log det A`` (``A`` the removed pose's conditional information; the common ``3 log 2 pi``
left out), so with ``gamma = 1`` the evidence is the hypothesis's marginal likelihood of its past.
"""

from __future__ import annotations

import numpy as np

from factors import residuals as res
from factors.lie import local, se3_exp
from pinpoint_fg import window_rows
from pinpoint_fg.elimination import (
    Linearization,
    add_chain_motion,
    chain_motion_terms,
    conditional_step,
    eliminate_onto_newest,
    marginal_prior,
    motion_value,
    older_value,
    whiten_motion,
    whiten_prior,
)
from pinpoint_fg.kinematic_bias import BiasBook, BiasModel, kinematic_correction
from pinpoint_fg.likelihood import FrameLikelihood, gauss_newton_frames, gauss_newton_rows
from pinpoint_fg.relinearize import ChainAnchor, anchored_linearization
from pinpoint_fg.window_memo import OldestTermsMemo

#: Random-walk noise per frame when the motion model is off or kinematics are missing:
#: [omega (rad) x3, v (m) x3] = 5 deg, 1 mm (the particle filter's random walk, DESIGN.md).
RANDOM_WALK_SIGMA = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)

#: Default relinearisation threshold of the older poses (:mod:`pinpoint_fg.relinearize`), in units of
#: (5 deg, 1 mm) per tangent component: 10 deg, 2 mm. Measured with ``scripts/svn_window_cost.py RUN --particles 50
#: --windows 5 --relin 0 1 2`` (lock-step thread CPU; 16 runs of 150 frames: every scenario but symmetric at seed 1,
#: all but rotation and symmetric at seed 2, snapshots at seed 3): 2 against 1 gave 5 % less CPU per frame at L = 5
#: (median; 2-11 % less on 15 runs, 3 % more on normal-02) and mean MAP errors that moved both ways -- better on
#: drive-01 (3.29 -> 3.14 deg) and rotation-01, worse on calibration-01 (0.440 -> 0.455 mm, 4.79 -> 4.87 deg) and
#: drive-02 (+2.3 % rotation), within 1 % elsewhere; the snapshots runs, chaotic at every threshold, averaged
#: 22.4 deg at 1 and 19.8 at 2 (exact path, 0: 16.0). 1 had been measured
#: against 0 at 0.58-0.66x the CPU and within 2 % of its errors on normal, rotation, suturing and kinfault.
#: (GTSAM's iSAM2 default, 0.1 rad / 0.1 m, is coarser in translation.) L = 1 has no older poses: unaffected.
DEFAULT_RELIN_THRESHOLD = 2.0

class Window:
    """The sliding windows of all hypotheses (see module docstring)."""

    def __init__(self, length: int, process_cov: np.ndarray, forgetting: float = 0.9,
                 relin_threshold: float = DEFAULT_RELIN_THRESHOLD, kinematic_bias: BiasModel | None = None) -> None:
        """``process_cov``: per-frame covariance ``Q`` (6x6, ``[omega; v]``) of the motion residual.

        ``relin_threshold``: the Gauss-Newton model of the terms among the older poses (their frames, the
        prior, their motion terms) is reused from its last exact evaluation while those poses moved less than
        this times (5 deg, 1 mm) per component (:mod:`pinpoint_fg.relinearize`); 0 re-linearises every term
        exactly on every call.
        """
        if int(length) < 1:
            raise ValueError(f"window length must be >= 1, got {length}")
        if not 0.0 <= forgetting <= 1.0:
            raise ValueError(f"forgetting must be in [0, 1], got {forgetting}")
        if not (np.isfinite(relin_threshold) and relin_threshold >= 0.0):
            raise ValueError(f"relin_threshold must be finite and >= 0, got {relin_threshold}")
        self.relin_threshold = float(relin_threshold)
        self.kinematic_bias = kinematic_bias
        self.kin: BiasBook | None = None  # per-hypothesis kinematic bias filters (evidence correction)
        self._anchor = ChainAnchor()
        self._memo = OldestTermsMemo()
        self.length = int(length)
        self.forgetting = float(forgetting)
        self.evidence: np.ndarray | None = None  # (N,) accumulated marginalised cost
        Q = np.asarray(process_cov, dtype=float)
        if Q.shape != (6, 6) or not np.all(np.isfinite(Q)) or np.min(np.linalg.eigvalsh(0.5 * (Q + Q.T))) <= 0:
            raise ValueError("process_cov must be a finite, positive-definite (6, 6) covariance")
        self.motion_W = np.linalg.inv(np.linalg.cholesky(0.5 * (Q + Q.T)))  # W^T W = Q^-1
        self.walk_W = np.diag(1.0 / RANDOM_WALK_SIGMA)
        self.poses: np.ndarray | None = None  # (L', N, 4, 4)
        self.frames: list[FrameLikelihood] = []
        self.deltas: list[np.ndarray] = []  # (4, 4) between consecutive poses
        self.delta_W: list[np.ndarray] = []  # (6, 6) whitening of each motion term
        self.prior_mean: np.ndarray | None = None  # (N, 4, 4)
        self.prior_W: np.ndarray | None = None  # (N, 6, 6)

    @property
    def size(self) -> int:
        """Number of poses currently in the window."""
        return 0 if self.poses is None else self.poses.shape[0]

    @property
    def newest(self) -> np.ndarray:
        """(N, 4, 4) the newest pose of every hypothesis."""
        assert self.poses is not None
        return self.poses[-1]

    @property
    def oldest(self) -> np.ndarray:
        """(N, 4, 4) the oldest pose of every hypothesis."""
        assert self.poses is not None
        return self.poses[0]

    def start(self, cam_T_needle: np.ndarray, frame: FrameLikelihood, prior_sigma: np.ndarray) -> None:
        """Begin with one pose per hypothesis and a weak prior centred on it (sigma per tangent axis)."""
        T = res.as_pose_batch(cam_T_needle)
        self.poses = T[None].copy()
        self.frames = [frame]
        self.deltas, self.delta_W = [], []
        self.prior_mean = T.copy()
        self.evidence = np.zeros(T.shape[0])
        W = np.diag(1.0 / np.asarray(prior_sigma, dtype=float))
        self.prior_W = np.broadcast_to(W, (T.shape[0], 6, 6)).copy()
        self.kin = None if self.kinematic_bias is None else BiasBook.start(self.kinematic_bias)
        self._anchor.clear()

    def reset_newest(self, cam_T_needle: np.ndarray, prior_sigma: np.ndarray) -> None:
        """Re-seed: keep only the newest frame, at new poses with a fresh weak prior."""
        frame = self.frames[-1]
        self.start(cam_T_needle, frame, prior_sigma)

    def push(self, frame: FrameLikelihood, cam_delta: np.ndarray | None, use_motion: bool,
             process_scale: float = 1.0) -> None:
        """Append a frame: predict the newest pose by ``cam_delta`` and slide (marginalise) if over length.

        ``cam_delta`` None (kinematics missing) or ``use_motion`` False gives an identity motion
        with the random-walk noise. ``process_scale`` multiplies the motion term's covariance
        (elapsed reference frames, :mod:`pinpoint_fg.kinematics_check`): ``W <- W / sqrt(scale)``.
        """
        assert self.poses is not None
        if not (np.isfinite(process_scale) and process_scale > 0):
            raise ValueError(f"process_scale must be positive, got {process_scale!r}")
        if cam_delta is None or not use_motion:
            D, W = np.eye(4), self.walk_W
        else:
            D, W = np.asarray(cam_delta, dtype=float), self.motion_W
        if process_scale != 1.0:
            W = W / np.sqrt(process_scale)
        pred = D @ self.poses[-1]
        self.poses = np.concatenate([self.poses, pred[None]], axis=0)
        self.frames.append(frame)
        self.deltas.append(D)
        self.delta_W.append(W)
        while self.size > self.length:
            self._marginalise_oldest()

    def _prior_terms(self, T: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The marginalisation prior on the oldest pose at poses T (of hypotheses ``rows``; None: all): value,
        gradient, information."""
        mean, W = (self.prior_mean, self.prior_W) if rows is None else (self.prior_mean[rows], self.prior_W[rows])
        r, J = res.pose_prior_residual(T, mean)
        return whiten_prior(r, J, W)

    def _prior_key(self, T: np.ndarray) -> tuple:
        """Memo key of the oldest frame's terms at poses T (:class:`~pinpoint_fg.window_memo.OldestTermsMemo`)."""
        return OldestTermsMemo.key(self.frames[0], T, self.prior_mean, self.prior_W)

    def _unary(self, j: int, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame j's terms (and, for j = 0, the prior) at poses T: value, gradient, information.

        Memoised on the exact values of T and of the prior (the last call only): the safeguard's
        trial evaluation of the newest pose is the next linearisation's, bitwise.
        """
        if j == 0:
            key = self._prior_key(T)
            hit = self._memo.get(key)
            if hit is not None:
                return hit
        nll, g, H = self.frames[j].gauss_newton(T)
        if j == 0:
            pv, pg, pH = self._prior_terms(T)
            return self._memo.put(key, (nll + pv, g + pg, H + pH))
        return nll, g, H

    def _unary_rows(self, T: np.ndarray, rows: np.ndarray, T_before: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_unary` of the oldest pose at poses ``T`` that equal ``T_before`` (the last evaluation's)
        outside ``rows``: those rows are evaluated, the others come from the memo, which then holds ``T``."""
        key = self._prior_key(T)
        hit = self._memo.get(key)
        if hit is not None:
            return hit
        if not self._memo.holds(self._prior_key(T_before)):
            return self._unary(0, T)
        nll, g, H = gauss_newton_rows(self.frames[0], T, rows, T_before)
        pv, pg, pH = self._prior_terms(T[rows], rows)
        self._memo.with_rows(key, (nll[rows] + pv, g[rows] + pg, H[rows] + pH), rows)
        return self._memo.get(key)

    def linearize(self) -> Linearization:
        """Gauss-Newton model of every window, eliminated onto the newest pose (see module docstring)."""
        assert self.poses is not None
        L = self.size
        if L > 1 and self.relin_threshold > 0:
            return self._linearize_anchored()
        vals, gs, Hs = self._exact_unaries()
        newest_own = vals[-1]
        Bs: list[np.ndarray] = []
        if L > 1:
            motion = chain_motion_terms(self.poses, self.deltas, self.delta_W)
            vals, gs, Hs, Bs = add_chain_motion(vals, gs, Hs, motion)
        window_value = np.sum(vals, axis=0)
        c, g_run, H_run, cond_inv, cond_g = eliminate_onto_newest(window_value, gs, Hs, Bs)
        return Linearization(c, g_run, H_run, cond_inv, cond_g, Bs, window_value, newest_own if L > 1 else None)

    def _linearize_anchored(self) -> Linearization:
        """:meth:`linearize` with the older part from its anchored model (:mod:`pinpoint_fg.relinearize`)."""
        assert self.poses is not None and self.prior_mean is not None
        return anchored_linearization(self._anchor, self.frames, self.poses, (self.prior_mean, self.prior_W),
                                      self.deltas, self.delta_W, self.relin_threshold,
                                      self._unary(self.size - 1, self.poses[-1]))

    def _exact_unaries(self) -> tuple[list, list, list]:
        """Every pose's own terms (:meth:`_unary`), the frames no memo holds in one batched evaluation."""
        assert self.poses is not None
        L = self.size
        if L > 1:
            # the frames no memo holds, in one batched evaluation (fewer, larger NumPy calls); fills their memos
            first = 1 if self._memo.holds(self._prior_key(self.poses[0])) else 0
            if L - first > 1:
                gauss_newton_frames(self.frames[first:], list(self.poses[first:]))
        vals, gs, Hs = [], [], []
        for j in range(L):
            v, g, H = self._unary(j, self.poses[j])
            vals.append(v)
            gs.append(g)
            Hs.append(H)
        return vals, gs, Hs

    def move_newest(self, step: np.ndarray, lin: Linearization, newest: np.ndarray | None = None) -> None:
        """Retract the newest poses by ``step (N, 6)`` and the older ones by back-substitution.

        ``d_j = -H_jj^-1 (g_j + H_{j,j+1} d_{j+1})`` for ``j = L-2 .. 0``: the older poses move to
        their Gauss-Newton conditional optimum given the newest (the smoothing step).

        ``newest``: the caller's ``newest @ se3_exp(step)`` when it has it already (a safeguard's accepted
        trial; the same product, bitwise): with ``L = 1`` it is taken as is instead of being recomputed.
        """
        assert self.poses is not None
        if newest is not None and self.size == 1:
            self.poses = np.asarray(newest, dtype=float)[None].copy()
            return
        d = np.empty(self.poses.shape[:2] + (6,))
        d[-1] = step
        for j in range(self.size - 2, -1, -1):
            d[j] = conditional_step(lin.cond_inv[j], lin.cond_g[j], lin.cond_B[j], d[j + 1])
        self.poses = self.poses @ se3_exp(d)  # all L retractions in one call

    def newest_value(self, cam_T_newest: np.ndarray, lin: Linearization,
                     changed: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Negative log-posterior (N,) if the newest poses were ``cam_T_newest`` (older at their conditional optimum).

        Exact for the newest pose's own terms; the older poses' contribution uses the GN model
        ``lin`` (constant + the coupling through the last motion term), which is what the
        backtracking safeguard and the MAP choice compare.

        Consistent with ``lin``: at the current newest poses it returns ``lin.value`` (to round-off;
        :func:`~pinpoint_fg.elimination.older_value` says why the last motion term needs care).

        ``changed = (rows, cam_T_before)``: ``cam_T_newest`` equals the poses of the last call (with the same
        ``lin``) outside ``rows``; the frame's terms are evaluated for those rows only and the memos merged
        (:func:`~pinpoint_fg.likelihood.gauss_newton_rows`): the safeguard's halvings re-evaluate the few
        particles whose step they shortened.
        """
        assert self.poses is not None
        if self.size == 1:
            if changed is not None:
                return self._unary_rows(cam_T_newest, *changed)[0]
            return self._unary(0, cam_T_newest)[0]
        # exact terms of the newest pose + exact last motion term with x_{L-2} at its conditional optimum
        j = self.size - 1
        # the older terms' share, once per linearisation (the current poses' evaluation is memoised)
        base = getattr(lin, "_newest_base", None)
        if base is None or base[0] is not self.poses:
            lin._newest_base = (self.poses, older_value(lin, self.poses[-2], self.poses[-1], self.deltas[-1],
                                                        self.delta_W[-1]))
        older = lin._newest_base[1]
        if changed is not None:  # memoised: the next linearisation reuses it
            v_new = gauss_newton_rows(self.frames[j], cam_T_newest, changed[0], changed[1])[0]
        else:
            v_new = self.frames[j].gauss_newton(cam_T_newest)[0]
        # conditional optimum of x_{L-2} given the move of the newest: linear in the newest's tangent change
        dL = local(self.poses[-1], cam_T_newest)
        dprev = conditional_step(lin.cond_inv[-1], lin.cond_g[-1], lin.cond_B[-1], dL)
        prev = self.poses[-2] @ se3_exp(dprev)
        r, _, _ = res.motion_residual(prev, cam_T_newest, self.deltas[-1], jacobian=False)
        return v_new + motion_value(r, self.delta_W[-1]) + older

    def _marginalise_oldest(self) -> None:
        """Schur-complement the oldest pose into a Gaussian prior on the next one."""
        assert self.poses is not None and self.size >= 2
        v0, g0, H0 = self._unary(0, self.poses[0])
        r, Jp, Jc = res.motion_residual(self.poses[0], self.poses[1], self.deltas[0])
        c, d_star, Hn = marginal_prior(v0, g0, H0, whiten_motion(r, Jp, Jc, self.delta_W[0]))
        if self.kin is not None:  # the kinematic terms' count under the bias model (kinematic_bias.BiasBook)
            corr = kinematic_correction(self.kin, self.frames[0], self.poses[0], H0)
            if corr is not None:
                c = c + corr
        self.evidence = self.forgetting * self.evidence + c
        self.prior_mean = self.poses[1] @ se3_exp(d_star)
        self.prior_W = np.swapaxes(np.linalg.cholesky(Hn), 1, 2)  # Hn is floored already: W^T W = Hn
        self.poses = self.poses[1:]
        self.frames = self.frames[1:]
        self.deltas = self.deltas[1:]
        self.delta_W = self.delta_W[1:]

    def subset(self, index: np.ndarray | list[int]) -> Window:
        """A window over hypotheses ``index`` only (:func:`pinpoint_fg.window_rows.subset`)."""
        return window_rows.subset(self, index)

    def adopt(self, sub: Window, index: np.ndarray | list[int]) -> None:
        """Write a :meth:`subset`'s poses back to hypotheses ``index`` (:func:`pinpoint_fg.window_rows.adopt`)."""
        window_rows.adopt(self, sub, index)

    def resample(self, index: np.ndarray) -> None:
        """Keep hypotheses ``index`` (N',) (:func:`pinpoint_fg.window_rows.resample`)."""
        window_rows.resample(self, index)
