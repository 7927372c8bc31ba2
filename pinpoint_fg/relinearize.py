"""Relinearisation threshold for a window's older poses (iSAM2-style fluid relinearisation), batched over particles.

During SVN's transport the older poses of every window move only by back-substitution, by about
the newest pose's step and less as it converges, yet :meth:`pinpoint_fg.window.Window.linearize`
would re-evaluate every term that touches them — their frames' measurements (the conic's 200
pixels per frame), the window prior, the motion terms between them — on every call, and sweep
the whole chain again. At ~50 particles the per-call overhead of those evaluations, not their
arithmetic, is what a window of L poses costs over one of a single pose.

:class:`ChainAnchor` keeps, per hypothesis, the Gauss-Newton model of the window's **older part**
— the terms that involve only ``x_0 .. x_{L-2}``: their frames, the prior on ``x_0`` and the
motion terms among them — exactly evaluated at the poses ``A_j`` where it was last linearised
(the *anchor*): a value ``V``, gradient ``G`` and block-tridiagonal information (diagonal blocks
``Hd_j``, couplings ``Bo_j``). At the current poses ``x_j = A_j Exp(d_j)`` the older part is
that quadratic model,

    value = V + G^T d + 1/2 d^T H d,    gradient = G + H d,    information = H,

as long as every component of every ``d_j`` of that hypothesis is below ``threshold`` times
:data:`RELIN_SCALE` (5 deg, 1 mm: the kernel's and the random walk's scale); a hypothesis whose
older poses moved further is re-linearised exactly and re-anchored there. The newest frame and
the last motion term (which the Stein step moves directly) are always exact. (iSAM2 does the
same per variable, keeping the linear system of the variables it does not relinearise; GTSAM's
default threshold is 0.1 rad / 0.1 m, far coarser.)

Decisions where the literature is silent:

* Marginalisation evaluates the oldest frame, prior and motion term exactly at the final poses
  (:meth:`pinpoint_fg.window.Window.push`), so the window's evidence is exact.
* The gradient is not transported between the tangent spaces at ``A_j`` and ``x_j`` (a relative
  change of order ``|d|``, below the threshold). Being the Gauss-Newton model, the reused
  gradient also omits the residuals' curvature, so its error is first order in ``|d|`` and the
  value's second order (tested).
* ``threshold = 0`` disables the reuse: :meth:`pinpoint_fg.window.Window.linearize` then takes its
  exact path (tested equal to it).
"""

from __future__ import annotations

import numpy as np

from factors import residuals as res
from factors.lie import local
from pinpoint_fg.elimination import (
    Linearization,
    chain_motion_terms,
    eliminate_onto_newest,
    inv_psd,
    whiten_motion,
    whiten_prior,
)
from pinpoint_fg.likelihood import FrameLikelihood, gauss_newton_frames

#: Scale of the relinearisation threshold: [omega x3 (rad), v x3 (m)] = 5 deg, 1 mm.
RELIN_SCALE = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)

#: Axis of the hypotheses in each anchored array: A (L-1, N, 4, 4), the frames' own terms Fv (L-1, N), Fg (L-1, N, 6),
#: FH (L-1, N, 6, 6), the older part's V (N,), G (L-1, N, 6), Hd (L-1, N, 6, 6), Bo (L-2, N, 6, 6), the sweep's
#: Hinv (L-2, N, 6, 6) and H_last (N, 6, 6) (see :meth:`ChainAnchor.model`), valid (N,).
_ROW_AXIS = {"A": 1, "Fv": 1, "Fg": 1, "FH": 1, "V": 0, "G": 1, "Hd": 1, "Bo": 1, "Hinv": 1, "H_last": 0, "valid": 0}


class ChainAnchor:
    """The older part's Gauss-Newton model per hypothesis, at its anchor poses (module docstring)."""

    def __init__(self) -> None:
        self.key: tuple | None = None  # identities of the older frames the model belongs to
        self.arrays: dict[str, np.ndarray] = {}

    def clear(self) -> None:
        """Forget the model (new hypotheses or a new window)."""
        self.key, self.arrays = None, {}

    def subset(self, index: np.ndarray) -> ChainAnchor:
        """The anchors of hypotheses ``index`` (copies)."""
        out = ChainAnchor()
        out.key = self.key
        out.arrays = {k: np.take(a, index, axis=_ROW_AXIS[k]) for k, a in self.arrays.items()}
        return out

    def copy_rows(self, index: np.ndarray, source: ChainAnchor, source_index: np.ndarray) -> None:
        """Rows ``index`` become copies of ``source``'s rows ``source_index`` (invalid where it has no model)."""
        if self.key is None:
            return
        same = source.key == self.key and source.arrays["A"].shape[0] == self.arrays["A"].shape[0]
        if not same:
            self.arrays["valid"][index] = False
            return
        for k, a in self.arrays.items():
            src = np.take(source.arrays[k], source_index, axis=_ROW_AXIS[k])
            if _ROW_AXIS[k] == 0:
                a[index] = src
            else:
                a[:, index] = src

    def invalidate(self, index: np.ndarray) -> None:
        """Rows ``index`` are re-linearised exactly at the next :meth:`model` (e.g. their prior changed)."""
        if self.key is not None:
            self.arrays["valid"][index] = False

    @staticmethod
    def _assemble(A: np.ndarray, Fv: np.ndarray, Fg: np.ndarray, FH: np.ndarray, prior: tuple[np.ndarray, np.ndarray],
                  deltas: list[np.ndarray], delta_W: list[np.ndarray]) -> dict[str, np.ndarray]:
        """The older part's model at anchor poses ``A (L-1, n, 4, 4)`` from its frames' terms there (``Fv``, ``Fg``,
        ``FH``): the prior and the motion terms added (evaluated at ``A``), and the sweep's informations."""
        K, n = A.shape[:2]
        r, J = res.pose_prior_residual(A[0], prior[0])
        pv, pg, pH = whiten_prior(r, J, prior[1])
        V, G, Hd = np.sum(Fv, axis=0) + pv, Fg.copy(), FH.copy()
        G[0] += pg
        Hd[0] += pH
        Bo = np.zeros((0, n, 6, 6))
        if K > 1:
            m_val, m_gp, m_gc, m_Hpp, Bo, m_Hcc = chain_motion_terms(A, deltas, delta_W)
            V = V + np.sum(m_val, axis=0)
            G[:-1] += m_gp
            G[1:] += m_gc
            Hd[:-1] += m_Hpp
            Hd[1:] += m_Hcc
        Hinv, H_last = ChainAnchor._sweep(Hd, Bo)
        return {"A": A, "Fv": Fv, "Fg": Fg, "FH": FH, "V": V, "G": G, "Hd": Hd, "Bo": np.array(Bo),
                "Hinv": Hinv, "H_last": H_last, "valid": np.ones(n, dtype=bool)}

    @staticmethod
    def _sweep(Hd: np.ndarray, Bo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Schur sweep's informations, which depend on the anchored blocks alone (kept with them):
        ``H_jj^-1`` of poses ``0 .. K-2`` (K-1, n, 6, 6) and pose K-1's information after their elimination."""
        K, n = Hd.shape[:2]
        Hinv, H_run = [], Hd[0]
        for j in range(K - 1):
            Hinv.append(inv_psd(H_run))
            H_run = Hd[j + 1] - np.swapaxes(Bo[j], -1, -2) @ Hinv[-1] @ Bo[j]
        return np.array(Hinv).reshape(K - 1, n, 6, 6), H_run

    def replace_prior(self, frames: list[FrameLikelihood], index: np.ndarray, old: tuple[np.ndarray, np.ndarray],
                      new: tuple[np.ndarray, np.ndarray]) -> None:
        """Rows ``index`` change their window prior from ``old`` to ``new`` (each (mean (n, 4, 4), whitening
        (n, 6, 6))): the prior's terms are swapped in the model at the rows' anchors and their sweep redone.

        ``frames`` are the window's older frames. The model is then the one :meth:`model` would evaluate
        afresh at the same anchors, to round-off (tested): the older frames' and motion terms do not depend
        on the prior, so their costly re-evaluation (an :meth:`invalidate`) is not needed. A model of other
        frames (the window was pushed since it was last used) is left alone: sliding it assembles the prior
        afresh.
        """
        if self.key is None or self.key != tuple(id(f) for f in frames) or index.size == 0:
            return
        a = self.arrays
        A0 = a["A"][0, index]
        v_o, g_o, H_o = whiten_prior(*res.pose_prior_residual(A0, old[0]), old[1])
        v_n, g_n, H_n = whiten_prior(*res.pose_prior_residual(A0, new[0]), new[1])
        a["V"][index] += v_n - v_o
        a["G"][0, index] += g_n - g_o
        a["Hd"][0, index] += H_n - H_o
        Hinv, H_last = self._sweep(a["Hd"][:, index], a["Bo"][:, index])
        a["Hinv"][:, index] = Hinv
        a["H_last"][index] = H_last

    def _evaluate(self, frames: list[FrameLikelihood], poses: np.ndarray, prior: tuple[np.ndarray, np.ndarray],
                  deltas: list[np.ndarray], delta_W: list[np.ndarray]) -> dict[str, np.ndarray]:
        """The older part's exact model at ``poses (L-1, n, 4, 4)`` (rows of the hypotheses to re-anchor)."""
        terms = gauss_newton_frames(frames, list(poses))
        return self._assemble(poses.copy(), np.stack([t[0] for t in terms]), np.stack([t[1] for t in terms]),
                              np.stack([t[2] for t in terms]), prior, deltas, delta_W)

    def _slid(self, key: tuple, frames: list[FrameLikelihood], poses: np.ndarray,
              prior: tuple[np.ndarray, np.ndarray], deltas: list[np.ndarray], delta_W: list[np.ndarray]
              ) -> dict[str, np.ndarray] | None:
        """After a push: the model of the new older part from the old one's frames (still at their anchors),
        the frame that joined (evaluated at its current poses: memoised as the newest) and the prior and motion
        terms evaluated anew; None when the old model does not cover the new older part."""
        old, a = self.key, self.arrays
        if old is None or not old or a["V"].shape[0] != poses.shape[1]:
            return None
        if key[:-1] == old:  # the window grew: a frame joined the older part
            keep = slice(0, len(old))
        elif key[:-1] == old[1:]:  # it slid: the oldest frame was marginalised, a frame joined
            keep = slice(1, len(old))
        else:
            return None
        v, g, H = gauss_newton_frames([frames[-1]], [poses[-1]])[0]
        A = np.concatenate([a["A"][keep], poses[-1:]])
        out = self._assemble(A, np.concatenate([a["Fv"][keep], v[None]]), np.concatenate([a["Fg"][keep], g[None]]),
                             np.concatenate([a["FH"][keep], H[None]]), prior, deltas, delta_W)
        out["valid"] = a["valid"].copy()
        return out

    def model(self, frames: list[FrameLikelihood], poses: np.ndarray, prior: tuple[np.ndarray, np.ndarray],
              deltas: list[np.ndarray], delta_W: list[np.ndarray], threshold: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The older part at its current ``poses (L-1, N, 4, 4)``: value (N,), gradients (L-1, N, 6), diagonal
        blocks (L-1, N, 6, 6), couplings (L-2, N, 6, 6), and its Schur sweep: ``H_jj^-1`` of poses
        ``0 .. L-3`` (L-2, N, 6, 6) and pose L-2's information after their elimination (N, 6, 6) (the
        ``head_inv`` and ``Hs[L-2]`` of :func:`~pinpoint_fg.elimination.eliminate_onto_newest`, before the last
        motion term is added).

        ``frames`` the older frames, ``prior`` the window prior's (mean, whitening), ``deltas`` / ``delta_W``
        the motions among the older poses. Hypotheses whose poses moved ``threshold * RELIN_SCALE`` or more
        (in any component of any pose) since their anchor are re-linearised exactly, in one batched
        evaluation, and re-anchored.
        """
        K, N = poses.shape[:2]
        key = tuple(id(f) for f in frames)
        if self.key == key and self.arrays["V"].shape[0] != N:
            self.key = None
        exact = False
        if self.key != key:
            slid = self._slid(key, frames, poses, prior, deltas, delta_W)
            exact = slid is None
            self.key, self.arrays = key, (self._evaluate(frames, poses, prior, deltas, delta_W) if exact else slid)
        a = self.arrays
        if exact:
            d = np.zeros((K, N, 6))
        else:
            d = local(a["A"].reshape(-1, 4, 4), poses.reshape(-1, 4, 4)).reshape(K, N, 6)
            stale = ~a["valid"] | ~(np.max(np.abs(d) / RELIN_SCALE, axis=(0, 2)) < threshold)
            if stale.any():
                rows = np.flatnonzero(stale)
                fresh = self._evaluate(frames, poses[:, rows], (prior[0][rows], prior[1][rows]), deltas, delta_W)
                for k, x in fresh.items():
                    if _ROW_AXIS[k] == 0:
                        a[k][rows] = x
                    else:
                        a[k][:, rows] = x
                d[:, rows] = 0.0
        Hd_d = (a["Hd"] @ d[..., None])[..., 0]
        if K > 1:
            Hd_d[:-1] += (a["Bo"] @ d[1:, ..., None])[..., 0]
            Hd_d[1:] += (np.swapaxes(a["Bo"], -1, -2) @ d[:-1, ..., None])[..., 0]
        value = a["V"] + np.sum(d * (a["G"] + 0.5 * Hd_d), axis=(0, 2))
        return value, a["G"] + Hd_d, a["Hd"], a["Bo"], a["Hinv"], a["H_last"]


def anchored_linearization(anchor: ChainAnchor, frames: list[FrameLikelihood], poses: np.ndarray,
                           prior: tuple[np.ndarray, np.ndarray], deltas: list[np.ndarray], delta_W: list[np.ndarray],
                           threshold: float, newest_terms: tuple[np.ndarray, np.ndarray, np.ndarray]
                           ) -> Linearization:
    """A window's :class:`~pinpoint_fg.elimination.Linearization` with its older part from ``anchor``'s model.

    ``poses (L, N, 4, 4)``, ``frames``, ``deltas``, ``delta_W`` the window's; ``newest_terms`` the newest
    frame's exact (value, gradient, information); the last motion term is evaluated exactly here.
    """
    v_old, g_old, H_old, B_old, head_inv, H_last = anchor.model(frames[:-1], poses[:-1], prior, deltas[:-1],
                                                                delta_W[:-1], threshold)
    v_new, g_new, H_new = newest_terms
    r, Jp, Jc = res.motion_residual(poses[-2], poses[-1], deltas[-1])
    m_val, m_gp, m_gc, m_Hpp, m_Hpc, m_Hcc = whiten_motion(r, Jp, Jc, delta_W[-1])
    gs, Hs = list(g_old), list(H_old)
    gs[-1] = gs[-1] + m_gp
    Hs[-1] = (H_last if len(head_inv) else Hs[-1]) + m_Hpp  # pose L-2 after the (known) older eliminations
    gs.append(g_new + m_gc)
    Hs.append(H_new + m_Hcc)
    Bs = list(B_old) + [m_Hpc]
    window_value = v_old + m_val + v_new
    c, g_run, H_run, cond_inv, cond_g = eliminate_onto_newest(window_value, gs, Hs, Bs, list(head_inv))
    return Linearization(c, g_run, H_run, cond_inv, cond_g, Bs, window_value, v_new)
