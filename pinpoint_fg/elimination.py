"""Batched Gauss-Newton elimination on a chain of poses: Schur sweeps, back-substitution, marginalisation.

The pure maths of :class:`pinpoint_fg.window.Window`, all particles at once (leading axis ``N``). A chain
``x_0 .. x_{L-1}`` has per-pose terms (value, gradient, 6x6 information) and motion terms coupling
consecutive poses; its Gauss-Newton model is block tridiagonal, so a forward Schur sweep
(:func:`eliminate_onto_newest`) leaves the marginal model of the newest pose, and its conditionals give
the back-substitution (:func:`conditional_step`) that moves the older poses with the newest.
:func:`marginal_prior` Schur-complements the oldest pose into a Gaussian prior on the next one and
returns the constant the elimination leaves (the window's evidence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors import residuals as res
from factors.lie import se3_exp

_RIDGE = 1e-12  # relative ridge added before inverting 6x6 blocks


def inv_psd(H: np.ndarray) -> np.ndarray:
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
    """Symmetrise and floor eigenvalues at ``max(rel * w_max, abs_floor)`` so a prior stays PD.

    When a Cholesky factorisation of ``H_s - max(rel ||H_s||_F, abs_floor) I`` succeeds (``||H_s||_F >= w_max``)
    no floor binds and ``H_s`` is returned as it is, without the eigen-decomposition (the usual case: a third of
    its cost; :func:`pinpoint_fg.stein.floor_hessians` does the same).
    """
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    if np.isfinite(Hs).all():
        fro = np.sqrt(np.einsum("...ij,...ij->...", Hs, Hs))
        try:
            np.linalg.cholesky(Hs - np.maximum(rel * fro, abs_floor)[..., None, None] * np.eye(H.shape[-1]))
            return Hs
        except np.linalg.LinAlgError:
            pass
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
    newest_own: np.ndarray | None = None
    """(N,) the newest pose's own terms (its frame's) at the current poses (L > 1)."""


    def append(self, other: Linearization) -> Linearization:
        """This model's hypotheses followed by ``other``'s (same window length)."""
        def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return np.concatenate([a, b], axis=0)
        return Linearization(cat(self.value, other.value), cat(self.grad, other.grad), cat(self.hess, other.hess),
                             [cat(a, b) for a, b in zip(self.cond_inv, other.cond_inv, strict=True)],
                             [cat(a, b) for a, b in zip(self.cond_g, other.cond_g, strict=True)],
                             [cat(a, b) for a, b in zip(self.cond_B, other.cond_B, strict=True)],
                             cat(self.window_value, other.window_value),
                             None if self.newest_own is None or other.newest_own is None
                             else cat(self.newest_own, other.newest_own))

    def subset(self, index: np.ndarray | list[int]) -> Linearization:
        """The same model for hypotheses ``index`` only (matches :meth:`pinpoint_fg.window.Window.subset`)."""
        index = np.asarray(index)
        return Linearization(self.value[index], self.grad[index], self.hess[index],
                             [a[index] for a in self.cond_inv], [a[index] for a in self.cond_g],
                             [a[index] for a in self.cond_B], self.window_value[index],
                             None if self.newest_own is None else self.newest_own[index])


def whiten_prior(r: np.ndarray, J: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian prior ``1/2 |W r|^2`` per particle: value (N,), gradient (N, 6), information (N, 6, 6).

    ``r`` (N, 6) the prior residual, ``J`` (N, 6, 6) its Jacobian, ``W`` (N, 6, 6) the per-particle whitening.
    """
    e = np.einsum("nij,nj->ni", W, r)
    Jw = W @ J
    return 0.5 * (e * e).sum(axis=1), np.einsum("nmi,nm->ni", Jw, e), np.swapaxes(Jw, 1, 2) @ Jw


def motion_value(r: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Value (N,) of the motion term ``1/2 |W r|^2`` alone (no Jacobians)."""
    e = r @ W.T
    return 0.5 * (e * e).sum(axis=1)


def whiten_motion(r: np.ndarray, Jp: np.ndarray, Jc: np.ndarray, W: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Motion term ``1/2 |W r|^2`` between poses j and j+1: value, g_prev, g_cur, H_pp, H_pc, H_cc.

    ``r`` (N, 6) and its Jacobians ``Jp``, ``Jc`` (N, 6, 6) w.r.t. the previous and current pose; ``W``
    (6, 6) the whitening (``W^T W`` = the information of the motion residual).
    """
    e = r @ W.T
    Jp, Jc = W @ Jp, W @ Jc
    JpT, JcT = np.swapaxes(Jp, 1, 2), np.swapaxes(Jc, 1, 2)
    return (0.5 * (e * e).sum(axis=1), np.einsum("nij,nj->ni", JpT, e), np.einsum("nij,nj->ni", JcT, e),
            JpT @ Jp, JpT @ Jc, JcT @ Jc)


def chain_motion_terms(poses: np.ndarray, deltas: list[np.ndarray], delta_W: list[np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All L-1 motion terms of a chain ``poses (L, N, 4, 4)`` in one batched evaluation: :func:`whiten_motion`'s
    value, g_prev, g_cur, H_pp, H_pc, H_cc, each with a leading (L-1) axis (per-call overhead dominates at N ~ 50).
    """
    L, N = poses.shape[:2]
    D = np.broadcast_to(np.stack(deltas)[:, None], (L - 1, N, 4, 4)).reshape(-1, 4, 4)
    r, Jp, Jc = res.motion_residual(poses[:-1].reshape(-1, 4, 4), poses[1:].reshape(-1, 4, 4), D)
    Wm = np.stack(delta_W)[:, None]  # (L-1, 1, 6, 6)
    e = (Wm @ r.reshape(L - 1, N, 6, 1))[..., 0]
    Jp, Jc = Wm @ Jp.reshape(L - 1, N, 6, 6), Wm @ Jc.reshape(L - 1, N, 6, 6)
    JpT, JcT = np.swapaxes(Jp, -1, -2), np.swapaxes(Jc, -1, -2)
    return (0.5 * (e * e).sum(axis=-1), (JpT @ e[..., None])[..., 0], (JcT @ e[..., None])[..., 0],
            JpT @ Jp, JpT @ Jc, JcT @ Jc)


def add_chain_motion(vals: list[np.ndarray], gs: list[np.ndarray], Hs: list[np.ndarray],
                     motion: tuple[np.ndarray, ...]) -> tuple[list, list, list, list]:
    """Add :func:`chain_motion_terms` to the poses' own terms: values, gradients, informations and the
    coupling blocks ``H_{j,j+1}`` of the block-tridiagonal chain (the inputs of :func:`eliminate_onto_newest`)."""
    m_val, m_gp, m_gc, m_Hpp, m_Hpc, m_Hcc = motion
    vals, gs, Hs = list(vals), list(gs), list(Hs)
    for j in range(len(vals) - 1):
        vals[j] = vals[j] + m_val[j]
        gs[j] = gs[j] + m_gp[j]
        gs[j + 1] = gs[j + 1] + m_gc[j]
        Hs[j] = Hs[j] + m_Hpp[j]
        Hs[j + 1] = Hs[j + 1] + m_Hcc[j]
    return vals, gs, Hs, [m_Hpc[j] for j in range(len(vals) - 1)]


def eliminate_onto_newest(window_value: np.ndarray, gs: list[np.ndarray], Hs: list[np.ndarray],
                          Bs: list[np.ndarray], head_inv: tuple | list = ()
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list, list]:
    """Forward Schur sweep over a chain: eliminate ``x_0 .. x_{L-2}`` onto the newest pose.

    ``gs[j]`` (N, 6) and ``Hs[j]`` (N, 6, 6) are pose j's gradient and information (motion terms
    included), ``Bs[j]`` the coupling block ``H_{j,j+1}``, ``window_value`` (N,) the chain's value. Returns
    the eliminated value ``c``, the newest pose's gradient and (symmetrised) information, and per older
    pose the conditionals ``H_jj^-1`` and ``g_j`` after the sweep.

    ``head_inv``: the sweep's ``H_jj^-1`` of the first ``k`` poses when they are already known (the
    informations do not depend on the gradients: :mod:`pinpoint_fg.relinearize` keeps them); ``Hs[k]`` is
    then pose k's information after those eliminations, and only the gradients are swept through them.
    """
    c = window_value.copy()
    cond_inv, cond_g = [], []
    k = len(head_inv)
    g_run, H_run = gs[0], (Hs[0] if k == 0 else None)
    for j in range(len(Hs) - 1):
        Hinv = head_inv[j] if j < k else inv_psd(H_run)
        BT = np.swapaxes(Bs[j], 1, 2)
        Hig = np.einsum("nij,nj->ni", Hinv, g_run)
        c = c - 0.5 * (g_run * Hig).sum(axis=1)
        cond_inv.append(Hinv)
        cond_g.append(g_run)
        g_run = gs[j + 1] - np.einsum("nij,nj->ni", BT, Hig)
        if j + 1 == k:
            H_run = Hs[k]
        elif j + 1 > k:
            H_run = Hs[j + 1] - BT @ Hinv @ Bs[j]
    H_run = 0.5 * (H_run + np.swapaxes(H_run, 1, 2))
    return c, g_run, H_run, cond_inv, cond_g


def conditional_step(cond_inv: np.ndarray, cond_g: np.ndarray, cond_B: np.ndarray, d_next: np.ndarray
                     ) -> np.ndarray:
    """Back-substitution ``d_j = -H_jj^-1 (g_j + H_{j,j+1} d_{j+1})`` (N, 6): pose j's Gauss-Newton
    conditional optimum given the step ``d_next`` of pose j+1."""
    rhs = cond_g + np.einsum("nij,nj->ni", cond_B, d_next)
    return -np.einsum("nij,nj->ni", cond_inv, rhs)


def older_value(lin: Linearization, prev_T: np.ndarray, newest_T: np.ndarray, delta: np.ndarray,
                W: np.ndarray) -> np.ndarray:
    """The older poses' share ``(N,)`` of ``lin.value``: everything but the newest pose's own terms and the last
    motion term, that term taken with ``x_{L-2}`` at its conditional optimum given the current newest pose.

    ``lin.value`` already holds the Gauss-Newton gain of moving ``x_{L-2}`` to that optimum, including the last
    motion term's share; counting the exact last term from the unmoved ``x_{L-2}`` would count that gain twice
    (measured 1e-3 nats: the size of the MAP polish's convergence test, which then rejected every step up to
    its iteration cap on a quarter of the frames at L = 5). ``prev_T``, ``newest_T`` (N, 4, 4) the current
    poses ``x_{L-2}``, ``x_{L-1}``; ``delta``, ``W`` the last motion and its whitening.
    """
    dprev0 = -np.einsum("nij,nj->ni", lin.cond_inv[-1], lin.cond_g[-1])
    r = res.motion_residual(prev_T @ se3_exp(dprev0), newest_T, delta, False)[0]
    return lin.value - lin.newest_own - motion_value(r, W)


def marginal_prior(v0: np.ndarray, g0: np.ndarray, H0: np.ndarray,
                   motion: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Schur-complement the oldest pose into a Gaussian prior on the next one.

    ``v0, g0, H0``: the oldest pose's own terms (prior included); ``motion``: :func:`whiten_motion` of the
    term joining it to the next pose. Returns the constant ``c`` (N,) left by the elimination (the value
    at the optimum of the removed pose and of the new prior), the prior's mean as a step ``d_star``
    (N, 6) from the next pose, and its information ``Hn`` (N, 6, 6), eigenvalue-floored. ``c`` includes
    ``1/2 log det A`` of the removed pose's conditional information (the Laplace integral over it; the common
    ``3 log 2 pi`` left out).
    """
    mv, gp, gc, Hpp, Hpc, Hcc = motion
    A = H0 + Hpp
    gA = g0 + gp
    B = Hpc
    C = Hcc
    g1 = gc
    Ainv = inv_psd(A)
    BT = np.swapaxes(B, 1, 2)
    Hn = floor_information(C - BT @ Ainv @ B)
    gn = g1 - np.einsum("nij,nj->ni", BT @ Ainv, gA)
    d_star = -np.linalg.solve(Hn, gn[..., None])[..., 0]
    c = v0 + mv - 0.5 * (gA * np.einsum("nij,nj->ni", Ainv, gA)).sum(axis=1)
    c = c - 0.5 * (gn * -d_star).sum(axis=1)
    # Laplace: integrating the removed pose out multiplies by det(A)^-1/2 (A its conditional information), so
    # the cost gains 1/2 log det A: the evidence is then each hypothesis's marginal likelihood, not its best path
    c = c + 0.5 * np.linalg.slogdet(A)[1]
    return c, d_star, Hn
