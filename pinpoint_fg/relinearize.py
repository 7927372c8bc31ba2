"""Relinearisation threshold for a window's older frames (iSAM2-style fluid relinearisation), batched over particles.

During SVN's transport the older poses of every window move only by back-substitution, by about
the newest pose's step and less as it converges, yet :meth:`pinpoint_fg.window.Window.linearize`
would re-evaluate their frames' measurement terms (residuals, Jacobians, robust weights: the
conic's 200 pixels per frame) on every iteration. :class:`FrameAnchors` keeps, per older frame
and per hypothesis, the exact Gauss-Newton terms ``(v0, g0, H0)`` at the pose ``T0`` they were
last evaluated at (the *anchor*). At a pose ``T = T0 Exp(d)``, ``d = Log(T0^-1 T)`` (right chart),
the frame's terms are taken from the anchor's quadratic model

    v = v0 + g0^T d + 1/2 d^T H0 d,    g = g0 + H0 d,    H = H0,

as long as every component of ``d`` is below ``threshold`` times :data:`RELIN_SCALE` (5 deg, 1 mm:
the kernel's and the random walk's scale); a hypothesis whose pose moved further is re-evaluated
exactly and re-anchored there. (iSAM2 does the same per variable, with the linear delta kept
instead of the value re-evaluated; GTSAM's default threshold is 0.1 in rad and m, far coarser.)

Decisions where the literature is silent:

* Only the older frames' **measurement** terms are reused. The newest frame (which the Stein
  step moves directly), the window prior and the motion terms (cheap: one batched call for the
  whole chain) are always evaluated exactly, and marginalisation evaluates the oldest frame
  exactly at its final pose, so the window's evidence is exact.
* The gradient is not transported between the two tangent spaces at ``T0`` and ``T`` (a
  relative change of order ``|d|``, below the threshold).
* ``threshold = 0`` disables the reuse: :meth:`pinpoint_fg.window.Window.linearize` then takes its
  exact path (tested equal to it).
"""

from __future__ import annotations

import numpy as np

from factors.lie import local
from pinpoint_fg.likelihood import FrameLikelihood, gauss_newton_frames

#: Scale of the relinearisation threshold: [omega x3 (rad), v x3 (m)] = 5 deg, 1 mm.
RELIN_SCALE = np.array([np.deg2rad(5.0)] * 3 + [1e-3] * 3)

Anchor = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # T0 (N, 4, 4), v0 (N,), g0 (N, 6), H0 (N, 6, 6)


class FrameAnchors:
    """Per frame (keyed by the frame object), per hypothesis: the pose and exact terms of its last evaluation."""

    def __init__(self) -> None:
        self.anchors: dict[FrameLikelihood, Anchor] = {}

    def clear(self) -> None:
        """Forget every anchor (new hypotheses)."""
        self.anchors = {}

    def keep_only(self, frames: list[FrameLikelihood]) -> None:
        """Drop the anchors of frames no longer in ``frames`` (marginalised)."""
        live = {id(f) for f in frames}
        self.anchors = {f: a for f, a in self.anchors.items() if id(f) in live}

    def subset(self, index: np.ndarray) -> FrameAnchors:
        """The anchors of hypotheses ``index`` (copies)."""
        out = FrameAnchors()
        out.anchors = {f: tuple(x[index] for x in a) for f, a in self.anchors.items()}
        return out

    def copy_rows(self, index: np.ndarray, source: FrameAnchors, source_index: np.ndarray) -> None:
        """Rows ``index`` become copies of ``source``'s rows ``source_index``; frames ``source`` lacks are dropped."""
        for f in list(self.anchors):
            src = source.anchors.get(f)
            if src is None:
                del self.anchors[f]
                continue
            for x, s in zip(self.anchors[f], src, strict=True):
                x[index] = s[source_index]

    def terms(self, frames: list[FrameLikelihood], poses: np.ndarray, threshold: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frames' Gauss-Newton terms at ``poses (K, N, 4, 4)``: values (K, N), gradients (K, N, 6), H (K, N, 6, 6).

        From each anchor's quadratic model where the pose moved less than ``threshold * RELIN_SCALE``
        per component since the anchor (module docstring), exact elsewhere (and re-anchored there).
        The exact evaluations of all frames are one :func:`~pinpoint_fg.likelihood.gauss_newton_frames` call.
        """
        K, N = poses.shape[:2]
        have = [j for j, f in enumerate(frames) if f in self.anchors and self.anchors[f][0].shape[0] == N]
        d = np.zeros((K, N, 6))
        stale = np.ones((K, N), dtype=bool)
        if have:
            T0 = np.stack([self.anchors[frames[j]][0] for j in have])
            d[have] = local(T0.reshape(-1, 4, 4), poses[have].reshape(-1, 4, 4)).reshape(len(have), N, 6)
            stale[have] = ~(np.max(np.abs(d[have]) / RELIN_SCALE, axis=2) < threshold)
        todo = [j for j in range(K) if stale[j].any()]
        if todo:
            rows = [np.flatnonzero(stale[j]) for j in todo]
            fresh = gauss_newton_frames([frames[j] for j in todo],
                                        [poses[j, r] for j, r in zip(todo, rows, strict=True)])
            for j, r, (v, g, H) in zip(todo, rows, fresh, strict=True):
                if r.size == N:
                    self.anchors[frames[j]] = (poses[j].copy(), v, g, H)
                else:
                    a = self.anchors[frames[j]]
                    for x, new in zip(a, (poses[j, r], v, g, H), strict=True):
                        x[r] = new
                d[j, r] = 0.0
        a = [self.anchors[f] for f in frames]
        v0, g0, H0 = np.stack([x[1] for x in a]), np.stack([x[2] for x in a]), np.stack([x[3] for x in a])
        Hd = (H0 @ d[..., None])[..., 0]
        return v0 + np.sum(d * (g0 + 0.5 * Hd), axis=-1), g0 + Hd, H0
