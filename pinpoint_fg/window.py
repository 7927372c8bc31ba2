"""Per-hypothesis sliding windows, batched over particles (DESIGN.md §Inference, steps 2, 3, 5).

Each of the ``N`` hypotheses owns a window of its last ``L`` poses ``x_0 .. x_{L-1}`` (oldest to
newest) with

* a Gaussian prior on ``x_0``, ``1/2 |W_p Log(mu^-1 x_0)|^2``, holding what was marginalised,
* the measurement terms of each window frame (:class:`pinpoint_fg.likelihood.FrameLikelihood`),
* motion terms ``1/2 |W_m Log((D_j x_j)^-1 x_{j+1})|^2`` between consecutive poses, with
  ``D_j`` the grasper's measured motion (identity plus a random-walk noise when the motion model
  is off or kinematics are missing).

The frames and motions are shared by all hypotheses; only poses and priors differ.

**Per-particle linearisation** (:meth:`Window.linearize`): at each hypothesis's own poses the
window's Gauss-Newton model ``c + g^T d + 1/2 d^T H d`` (``d`` stacks the right-chart tangent
perturbations of the L poses) is block tridiagonal; a forward Schur sweep eliminates
``x_0 .. x_{L-2}`` and leaves the marginal model of the newest pose: value ``c``, gradient ``g``
and information ``H`` (6x6), all particles at once. The sweep's conditionals give the
back-substitution that moves the older poses with the newest (smoothing). This equals GTSAM's
``linearize`` + ``eliminatePartialMultifrontal`` on the same window (tested).

**Sliding** (:meth:`Window.push`): a new frame appends the pose predicted by the grasper's motion;
when the window exceeds ``L`` poses the oldest is marginalised into a new prior on the next one
(Schur complement, re-expressed as a mean and information; eigenvalues floored so it stays
positive definite). ``L = 1`` is the paper's filter.

**Evidence**: marginalisation also leaves a constant per hypothesis — the cost of the history it
removed, at its optimum. Discarding it (as a prior factor does) would make every hypothesis look
equally supported by the past; it is kept in :attr:`Window.evidence` with a forgetting factor
``gamma`` per frame (``evidence <- gamma * evidence + c``), so hypotheses are compared on their
recent history (about ``1 / (1 - gamma)`` frames) rather than on the current frame alone.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from factors import residuals as res
from factors.lie import local, se3_exp
from pinpoint_fg.likelihood import FrameLikelihood

#: Random-walk noise per frame when the motion model is off or kinematics are missing:
#: [omega (rad) x3, v (m) x3] = 5 deg, 1 mm (the particle filter's random walk, DESIGN.md).
RANDOM_WALK_SIGMA = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)

_RIDGE = 1e-12  # relative ridge added before inverting 6x6 blocks


def _inv_psd(H: np.ndarray) -> np.ndarray:
    """Inverse of symmetric PSD blocks ``(..., 6, 6)``, finite even for singular H.

    Jacobi-scaled first (``D^-1 H D^-1`` with ``D = sqrt(diag H)``) so the tiny ridge ``_RIDGE``
    is unit-free: the blocks mix rad^-2 and m^-2 entries that differ by orders of magnitude.
    """
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    d = np.sqrt(np.maximum(np.einsum("...ii->...i", Hs), 1e-300))
    Hn = Hs / (d[..., :, None] * d[..., None, :])
    inv = np.linalg.inv(Hn + _RIDGE * np.eye(H.shape[-1]))
    return inv / (d[..., :, None] * d[..., None, :])


def floor_information(H: np.ndarray, rel: float = 1e-9, abs_floor: float = 1e-6) -> np.ndarray:
    """Symmetrise and floor eigenvalues at ``max(rel * w_max, abs_floor)`` so a prior stays PD."""
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    w, V = np.linalg.eigh(Hs)
    w = np.maximum(w, np.maximum(rel * w[..., -1:], abs_floor))
    return (V * w[..., None, :]) @ np.swapaxes(V, -1, -2)


def sqrt_information(H: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T W = H`` (upper Cholesky factor), batched; H is floored first."""
    L = np.linalg.cholesky(floor_information(H))
    return np.swapaxes(L, -1, -2)


@dataclass
class Linearization:
    """The window's Gauss-Newton model eliminated onto the newest pose, per particle."""

    value: np.ndarray
    """(N,) negative log-posterior with the older poses at their conditional optimum (GN estimate)."""
    grad: np.ndarray
    """(N, 6) gradient of the negative log-posterior w.r.t. the newest pose (right chart)."""
    hess: np.ndarray
    """(N, 6, 6) Gauss-Newton information of the newest pose, older poses eliminated."""
    cond_inv: list[np.ndarray]
    """Per older pose j: H_jj^-1 after the sweep, (N, 6, 6)."""
    cond_g: list[np.ndarray]
    """Per older pose j: the eliminated gradient g_j, (N, 6)."""
    cond_B: list[np.ndarray]
    """Per older pose j: the coupling block H_{j,j+1}, (N, 6, 6)."""
    window_value: np.ndarray
    """(N,) the window's negative log-posterior at the current poses (no elimination)."""
    newest_part: np.ndarray | None = None
    """(N,) the newest pose's own terms plus the last motion term at the current poses (L > 1)."""


    def subset(self, index: np.ndarray | list[int]) -> Linearization:
        """The same model for hypotheses ``index`` only (matches :meth:`Window.subset`)."""
        index = np.asarray(index)
        return Linearization(self.value[index], self.grad[index], self.hess[index],
                             [a[index] for a in self.cond_inv], [a[index] for a in self.cond_g],
                             [a[index] for a in self.cond_B], self.window_value[index],
                             None if self.newest_part is None else self.newest_part[index])


class Window:
    """The sliding windows of all hypotheses (see module docstring)."""

    def __init__(self, length: int, process_cov: np.ndarray, forgetting: float = 0.9) -> None:
        """``process_cov``: per-frame covariance ``Q`` (6x6, ``[omega; v]``) of the motion residual."""
        if int(length) < 1:
            raise ValueError(f"window length must be >= 1, got {length}")
        if not 0.0 <= forgetting <= 1.0:
            raise ValueError(f"forgetting must be in [0, 1], got {forgetting}")
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

    def _prior_terms(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The marginalisation prior on the oldest pose at poses T: value, gradient, information."""
        r, J = res.pose_prior_residual(T, self.prior_mean)
        e = np.einsum("nij,nj->ni", self.prior_W, r)
        Jw = self.prior_W @ J
        return 0.5 * np.sum(e * e, axis=1), np.einsum("nmi,nm->ni", Jw, e), np.swapaxes(Jw, 1, 2) @ Jw

    def _prior_key(self, T: np.ndarray) -> tuple:
        """Memo key of the oldest frame's terms at poses T: the frame object and the exact values."""
        return (self.frames[0], np.ascontiguousarray(T).tobytes(), self.prior_mean.tobytes(), self.prior_W.tobytes())

    def _unary(self, j: int, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame j's terms (and, for j = 0, the prior) at poses T: value, gradient, information.

        Memoised on the exact values of T and of the prior (the last call only): the safeguard's
        trial evaluation of the newest pose is the next linearisation's, bitwise.
        """
        key = None
        if j == 0:
            key = self._prior_key(T)
            memo = getattr(self, "_prior_memo", None)
            if memo is not None and memo[0] == key:
                return memo[1]
        nll, g, H = self.frames[j].gauss_newton(T)
        if j == 0:
            pv, pg, pH = self._prior_terms(T)
            nll, g, H = nll + pv, g + pg, H + pH
            for a in (nll, g, H):
                a.flags.writeable = False
            self._prior_memo = (key, (nll, g, H))
        return nll, g, H

    def _motion(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Motion term between poses j and j+1: value, g_prev, g_cur, H_pp, H_pc, H_cc."""
        assert self.poses is not None
        r, Jp, Jc = res.motion_residual(self.poses[j], self.poses[j + 1], self.deltas[j])
        W = self.delta_W[j]
        e = r @ W.T
        Jp, Jc = W @ Jp, W @ Jc
        JpT, JcT = np.swapaxes(Jp, 1, 2), np.swapaxes(Jc, 1, 2)
        return (0.5 * np.sum(e * e, axis=1), np.einsum("nij,nj->ni", JpT, e), np.einsum("nij,nj->ni", JcT, e),
                JpT @ Jp, JpT @ Jc, JcT @ Jc)

    def linearize(self) -> Linearization:
        """Gauss-Newton model of every window, eliminated onto the newest pose (see module docstring)."""
        assert self.poses is not None
        L = self.size
        if L > 1:
            from pinpoint_fg.likelihood import gauss_newton_frames

            # the frames no memo holds, in one batched evaluation (fewer, larger NumPy calls); fills their memos
            memo = getattr(self, "_prior_memo", None)
            first = 1 if memo is not None and memo[0] == self._prior_key(self.poses[0]) else 0
            if L - first > 1:
                gauss_newton_frames(self.frames[first:], list(self.poses[first:]))
        vals, gs, Hs = [], [], []
        for j in range(L):
            v, g, H = self._unary(j, self.poses[j])
            vals.append(v)
            gs.append(g)
            Hs.append(H)
        Bs = []
        newest_part = vals[-1]
        if L > 1:
            # all L-1 motion terms in one batched evaluation ((L-1) N poses; per-call overhead dominates at N ~ 50)
            N = self.poses.shape[1]
            D = np.broadcast_to(np.stack(self.deltas)[:, None], (L - 1, N, 4, 4)).reshape(-1, 4, 4)
            r, Jp, Jc = res.motion_residual(self.poses[:-1].reshape(-1, 4, 4), self.poses[1:].reshape(-1, 4, 4), D)
            Wm = np.stack(self.delta_W)[:, None]  # (L-1, 1, 6, 6)
            e = (Wm @ r.reshape(L - 1, N, 6, 1))[..., 0]
            Jp, Jc = Wm @ Jp.reshape(L - 1, N, 6, 6), Wm @ Jc.reshape(L - 1, N, 6, 6)
            JpT, JcT = np.swapaxes(Jp, -1, -2), np.swapaxes(Jc, -1, -2)
            m_val = 0.5 * np.sum(e * e, axis=-1)
            m_gp, m_gc = (JpT @ e[..., None])[..., 0], (JcT @ e[..., None])[..., 0]
            m_Hpp, m_Hpc, m_Hcc = JpT @ Jp, JpT @ Jc, JcT @ Jc
        for j in range(L - 1):
            v, gp, gc, Hpp, Hpc, Hcc = m_val[j], m_gp[j], m_gc[j], m_Hpp[j], m_Hpc[j], m_Hcc[j]
            if j == L - 2:
                newest_part = newest_part + v
            vals[j] = vals[j] + v
            gs[j] = gs[j] + gp
            gs[j + 1] = gs[j + 1] + gc
            Hs[j] = Hs[j] + Hpp
            Hs[j + 1] = Hs[j + 1] + Hcc
            Bs.append(Hpc)
        window_value = np.sum(vals, axis=0)
        c = window_value.copy()
        cond_inv, cond_g = [], []
        g_run, H_run = gs[0], Hs[0]
        for j in range(L - 1):
            Hinv = _inv_psd(H_run)
            BT = np.swapaxes(Bs[j], 1, 2)
            Hig = np.einsum("nij,nj->ni", Hinv, g_run)
            c = c - 0.5 * np.sum(g_run * Hig, axis=1)
            cond_inv.append(Hinv)
            cond_g.append(g_run)
            g_run = gs[j + 1] - np.einsum("nij,nj->ni", BT, Hig)
            H_run = Hs[j + 1] - BT @ Hinv @ Bs[j]
        H_run = 0.5 * (H_run + np.swapaxes(H_run, 1, 2))
        return Linearization(c, g_run, H_run, cond_inv, cond_g, Bs, window_value, newest_part if L > 1 else None)

    def move_newest(self, step: np.ndarray, lin: Linearization) -> None:
        """Retract the newest poses by ``step (N, 6)`` and the older ones by back-substitution.

        ``d_j = -H_jj^-1 (g_j + H_{j,j+1} d_{j+1})`` for ``j = L-2 .. 0``: the older poses move to
        their Gauss-Newton conditional optimum given the newest (the smoothing step).
        """
        assert self.poses is not None
        d = np.asarray(step, dtype=float)
        new = [None] * self.size
        new[-1] = self.poses[-1] @ se3_exp(d)
        for j in range(self.size - 2, -1, -1):
            rhs = lin.cond_g[j] + np.einsum("nij,nj->ni", lin.cond_B[j], d)
            d = -np.einsum("nij,nj->ni", lin.cond_inv[j], rhs)
            new[j] = self.poses[j] @ se3_exp(d)
        self.poses = np.stack(new, axis=0)

    def newest_value(self, cam_T_newest: np.ndarray, lin: Linearization) -> np.ndarray:
        """Negative log-posterior (N,) if the newest poses were ``cam_T_newest`` (older at their conditional optimum).

        Exact for the newest pose's own terms; the older poses' contribution uses the GN model
        ``lin`` (constant + the coupling through the last motion term), which is what the
        backtracking safeguard and the MAP choice compare.

        Consistent with ``lin``: at the current newest poses it returns ``lin.value`` (to round-off).
        ``lin.value`` already holds the GN-predicted gain of moving ``x_{L-2}`` to its conditional
        optimum, including the last motion term's share, so the exact last motion term is counted
        relative to its value at that optimum with the newest poses unmoved (else that gain is counted
        twice: measured 1e-3 nats, the size of the MAP polish's convergence test, which then rejected
        every step up to its iteration cap on a quarter of the frames at L = 5).
        """
        assert self.poses is not None
        if self.size == 1:
            return self._unary(0, cam_T_newest)[0]
        # exact terms of the newest pose + exact last motion term with x_{L-2} at its conditional optimum
        j = self.size - 1
        # the remaining older terms: GN value of the eliminated part at d_prev (evaluated first: the
        # current poses' evaluation is memoised by the linearisation and must not evict the trial's)
        base = getattr(lin, "_newest_base", None)
        if base is None or base[0] is not self.poses:
            part = self._newest_part_value(lin) if lin.newest_part is None else lin.newest_part
            # the last motion term at x_{L-2}'s conditional optimum given the current newest, minus at x_{L-2}
            dprev0 = -np.einsum("nij,nj->ni", lin.cond_inv[-1], lin.cond_g[-1])
            r0, _, _ = res.motion_residual(self.poses[-2] @ se3_exp(dprev0), self.poses[-1], self.deltas[-1], False)
            r1, _, _ = res.motion_residual(self.poses[-2], self.poses[-1], self.deltas[-1], False)
            e0, e1 = r0 @ self.delta_W[-1].T, r1 @ self.delta_W[-1].T
            older = lin.value - part - 0.5 * np.sum(e0 * e0, axis=1) + 0.5 * np.sum(e1 * e1, axis=1)
            lin._newest_base = (self.poses, older)
        older = lin._newest_base[1]
        v_new = self.frames[j].gauss_newton(cam_T_newest)[0]  # memoised: the next linearisation reuses it
        # conditional optimum of x_{L-2} given the move of the newest: linear in the newest's tangent change
        dL = local(self.poses[-1], cam_T_newest)
        rhs = lin.cond_g[-1] + np.einsum("nij,nj->ni", lin.cond_B[-1], dL)
        dprev = -np.einsum("nij,nj->ni", lin.cond_inv[-1], rhs)
        prev = self.poses[-2] @ se3_exp(dprev)
        r, _, _ = res.motion_residual(prev, cam_T_newest, self.deltas[-1], jacobian=False)
        e = r @ self.delta_W[-1].T
        return v_new + 0.5 * np.sum(e * e, axis=1) + older

    def _newest_part_value(self, lin: Linearization) -> np.ndarray:
        """Current value of the newest pose's own terms plus the last motion term."""
        assert self.poses is not None
        j = self.size - 1
        v = self.frames[j].gauss_newton(self.poses[j])[0]  # memoised by the linearisation at these poses
        r, _, _ = res.motion_residual(self.poses[j - 1], self.poses[j], self.deltas[j - 1], jacobian=False)
        e = r @ self.delta_W[j - 1].T
        return v + 0.5 * np.sum(e * e, axis=1)

    def _marginalise_oldest(self) -> None:
        """Schur-complement the oldest pose into a Gaussian prior on the next one."""
        assert self.poses is not None and self.size >= 2
        v0, g0, H0 = self._unary(0, self.poses[0])
        r, Jp, Jc = res.motion_residual(self.poses[0], self.poses[1], self.deltas[0])
        W = self.delta_W[0]
        e = r @ W.T
        Jp, Jc = W @ Jp, W @ Jc
        JpT, JcT = np.swapaxes(Jp, 1, 2), np.swapaxes(Jc, 1, 2)
        A = H0 + JpT @ Jp
        gA = g0 + np.einsum("nij,nj->ni", JpT, e)
        B = JpT @ Jc
        C = JcT @ Jc
        g1 = np.einsum("nij,nj->ni", JcT, e)
        Ainv = _inv_psd(A)
        BT = np.swapaxes(B, 1, 2)
        Hn = floor_information(C - BT @ Ainv @ B)
        gn = g1 - np.einsum("nij,nj->ni", BT @ Ainv, gA)
        d_star = -np.linalg.solve(Hn, gn[..., None])[..., 0]
        # constant left by the elimination: value at the optimum of the removed pose and of the new prior
        c = v0 + 0.5 * np.sum(e * e, axis=1) - 0.5 * np.sum(gA * np.einsum("nij,nj->ni", Ainv, gA), axis=1)
        c = c - 0.5 * np.sum(gn * -d_star, axis=1)
        self.evidence = self.forgetting * self.evidence + c
        self.prior_mean = self.poses[1] @ se3_exp(d_star)
        self.prior_W = np.swapaxes(np.linalg.cholesky(Hn), 1, 2)  # Hn is floored already: W^T W = Hn
        self.poses = self.poses[1:]
        self.frames = self.frames[1:]
        self.deltas = self.deltas[1:]
        self.delta_W = self.delta_W[1:]

    def subset(self, index: np.ndarray | list[int]) -> Window:
        """A window over hypotheses ``index`` only: copies of their poses, priors and evidence, the same frames.

        Work on a few hypotheses (polishing the MAP, trial poses) then costs what those few cost,
        not what all N cost; write the result back with ``poses[:, index] = sub.poses``.
        """
        assert self.poses is not None and self.prior_mean is not None and self.prior_W is not None
        index = np.asarray(index)
        sub = copy.copy(self)
        sub.poses = self.poses[:, index].copy()
        sub.prior_mean = self.prior_mean[index].copy()
        sub.prior_W = self.prior_W[index].copy()
        sub.evidence = None if self.evidence is None else self.evidence[index].copy()
        sub.frames, sub.deltas, sub.delta_W = list(self.frames), list(self.deltas), list(self.delta_W)
        sub._prior_memo = None
        return sub

    def adopt(self, sub: Window, index: np.ndarray | list[int]) -> None:
        """Write a :meth:`subset`'s poses back to hypotheses ``index``, keeping the prior-term memo valid.

        The memo of the oldest frame's terms (all hypotheses) gets the subset's rows where the
        subset holds them for its current poses, so the next marginalisation need not
        re-evaluate the hypotheses that did not move (equal to a fresh evaluation to round-off:
        the subset's rows were computed in a smaller batch).
        """
        assert self.poses is not None and sub.poses is not None
        index = np.asarray(index)
        memo, sub_memo = getattr(self, "_prior_memo", None), getattr(sub, "_prior_memo", None)
        valid = (memo is not None and sub_memo is not None and memo[0] == self._prior_key(self.poses[0])
                 and sub_memo[0] == sub._prior_key(sub.poses[0]))
        self.poses[:, index] = sub.poses
        if not valid:
            self._prior_memo = None
            return
        merged = []
        for full, part in zip(memo[1], sub_memo[1], strict=True):
            a = full.copy()
            a[index] = part
            a.flags.writeable = False
            merged.append(a)
        self._prior_memo = (self._prior_key(self.poses[0]), tuple(merged))

    def resample(self, index: np.ndarray) -> None:
        """Keep hypotheses ``index`` (N',): poses and priors follow (used by re-seeding and the PF).

        The memo of the oldest frame's terms follows too (its rows are reindexed, as :meth:`adopt`
        merges rows), so the next marginalisation need not re-evaluate the kept hypotheses.
        """
        assert self.poses is not None and self.prior_mean is not None and self.prior_W is not None
        memo = getattr(self, "_prior_memo", None)
        valid = memo is not None and memo[0] == self._prior_key(self.poses[0])
        self.poses = self.poses[:, index]
        self.prior_mean = self.prior_mean[index]
        self.prior_W = self.prior_W[index]
        if self.evidence is not None:
            self.evidence = self.evidence[index]
        self._prior_memo = None
        if valid:
            rows = tuple(a[index] for a in memo[1])
            for a in rows:
                a.flags.writeable = False
            self._prior_memo = (self._prior_key(self.poses[0]), rows)
