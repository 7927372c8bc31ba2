"""One frame's measurement likelihood, batched over pose hypotheses.

``FrameLikelihood(observation, model)`` stacks the whitened residuals of every enabled
measurement of that frame — tip/tail keypoints, dense backbone (conic), grasp position,
grasp perpendicularity — for ``N`` poses at once:

    e_k(T) = W_k (r_k(T) - mu_k),    nll(T) = sum_b rho_b(|e_b(T)|)

with ``r_k`` from :mod:`factors.residuals` (the only copy of the maths), ``mu_k`` the
calibrated bias and ``W_k^T W_k = Sigma_k^-1`` (:mod:`pinpoint_fg.noise`). ``b`` runs over the
blocks one GTSAM factor measures — each keypoint (2), the grasp position (3), perpendicularity
(1) and every backbone pixel (1) — and ``rho_b`` is the residual type's robust loss
(:mod:`factors.robust`; ``rho = d^2 / 2`` without one, giving ``1/2 sum |e|^2``). Its Gauss-Newton
form is iteratively reweighted least squares exactly as GTSAM linearises a robust factor: with
``w_b = rho_b'(d_b) / d_b``, ``e_b -> sqrt(w_b) e_b`` and ``J_b -> sqrt(w_b) J_b``, so per pose the
gradient is ``sum_b w_b J_b^T e_b`` (the exact gradient of ``nll``) and ``H = sum_b w_b J_b^T J_b``,
in GTSAM's right chart.
``gtsam_factors(key)`` returns the same terms as GTSAM factors (used by the MAP baseline and
by the tests that prove the two paths equal).

Cheirality: the conic cannot tell a circle behind the camera from one in front; poses whose
needle centre is closer than ``min_depth_m`` (or behind) get an additional quadratic penalty
``1/2 ((min_depth_m - z) / 1 mm)^2`` so no hypothesis settles there.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors import residuals as res
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import (
    ConicFactor,
    GraspPerpendicularFactor,
    GraspPositionFactor,
    KeypointFactor,
    conic_pixel_factors,
)
from factors.robust import RobustLoss
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.observation import Observation

#: Names accepted by ``--disable`` and what they switch off.
SWITCH_NAMES = ("dense", "sparse", "tip", "tail", "grasp-position", "grasp-perpendicular", "motion")


@dataclass(frozen=True)
class Switches:
    """Which likelihood terms are used (paper Table III ablations)."""

    dense: bool = True
    """Backbone pixels vs the projected conic."""
    tip: bool = True
    """Tip keypoint."""
    tail: bool = True
    """Tail keypoint."""
    grasp_position: bool = True
    """Grasp position from kinematics."""
    grasp_perpendicular: bool = True
    """Grasper axis perpendicular to the needle tangent at the grasp point."""
    motion: bool = True
    """Motion model: the grasper's measured motion moves the needle (else a random walk)."""

    @classmethod
    def from_disabled(cls, disabled: tuple[str, ...] | list[str] = ()) -> Switches:
        """Build from ``--disable`` names; ``sparse`` turns off both keypoints."""
        off = set(disabled)
        unknown = off - set(SWITCH_NAMES)
        if unknown:
            raise ValueError(f"unknown likelihood switch(es) {sorted(unknown)}; choose from {SWITCH_NAMES}")
        return cls(
            dense="dense" not in off,
            tip=not ({"sparse", "tip"} & off),
            tail=not ({"sparse", "tail"} & off),
            grasp_position="grasp-position" not in off,
            grasp_perpendicular="grasp-perpendicular" not in off,
            motion="motion" not in off,
        )

    def disabled(self) -> tuple[str, ...]:
        """The ``--disable`` names equivalent to these switches."""
        out = []
        if not self.dense:
            out.append("dense")
        if not self.tip and not self.tail:
            out.append("sparse")
        elif not self.tip:
            out.append("tip")
        elif not self.tail:
            out.append("tail")
        if not self.grasp_position:
            out.append("grasp-position")
        if not self.grasp_perpendicular:
            out.append("grasp-perpendicular")
        if not self.motion:
            out.append("motion")
        return tuple(out)


@dataclass(frozen=True)
class MeasurementModel:
    """Everything a frame's likelihood needs besides the observation."""

    camera: PinholeCamera
    """Camera (ideal pinhole K is used; observations are undistorted)."""
    needle: NeedleModel
    """Needle geometry."""
    noise: NoiseConfig = NoiseConfig()
    """Bias and covariance of every residual."""
    switches: Switches = Switches()
    """Enabled terms."""
    min_depth_m: float = 0.003
    """Needle centres closer than this (or behind the camera) are penalised."""


@dataclass(frozen=True)
class _Term:
    name: str
    W: np.ndarray  # (d, d) whitening
    mean: np.ndarray  # (d,)


class FrameLikelihood:
    """Whitened residual stack of one frame for ``N`` poses (see module docstring)."""

    def __init__(self, observation: Observation, model: MeasurementModel) -> None:
        self.observation = observation
        self.model = model
        sw = model.switches
        nd = model.needle
        self._K = model.camera.K
        self._terms: list[tuple[str, object]] = []
        o = observation
        if sw.tip and o.tip_px is not None:
            self._terms.append(("tip", o.tip_px))
        if sw.tail and o.tail_px is not None:
            self._terms.append(("tail", o.tail_px))
        if sw.dense and o.backbone_px is not None and len(o.backbone_px) > 0:
            self._terms.append(("conic", o.backbone_px))
        if o.cam_T_grasper is not None:
            if sw.grasp_position:
                self._terms.append(("grasp_position", o.cam_T_grasper[:3, 3].copy()))
            if sw.grasp_perpendicular:
                self._terms.append(("grasp_perpendicular", o.cam_T_grasper[:3, 2].copy()))
        self._noise = {name: model.noise[name] for name, _ in self._terms}
        self._W = {name: n.sqrt_information for name, n in self._noise.items()}
        self._loss: dict[str, RobustLoss] = {name: model.noise.loss(name) for name, _ in self._terms}
        self._tip, self._tail, self._grasp, self._tgrasp = nd.tip_m, nd.tail_m, nd.grasp_m, nd.grasp_tangent
        self.dim = sum(self._term_dim(name, data) for name, data in self._terms)
        self._gn_memo: tuple[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    @staticmethod
    def _term_dim(name: str, data: object) -> int:
        dims = {"tip": 2, "tail": 2, "grasp_position": 3, "grasp_perpendicular": 1}
        return len(data) if name == "conic" else dims[name]

    @property
    def term_names(self) -> tuple[str, ...]:
        """Names of the terms present this frame (a subset of tip, tail, conic, grasp_position, grasp_perpendicular)."""
        return tuple(name for name, _ in self._terms)

    @property
    def has_image_evidence(self) -> bool:
        """True when a keypoint or backbone term is present."""
        return any(n in ("tip", "tail", "conic") for n in self.term_names)

    def _raw(self, name: str, data: object, T: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray]:
        if name == "tip":
            return res.keypoint_residual(T, self._K, self._tip, data)
        if name == "tail":
            return res.keypoint_residual(T, self._K, self._tail, data)
        if name == "conic":
            return res.conic_residual(T, self._K, self.model.needle.radius_m, data, jacobian=jacobian)
        if name == "grasp_position":
            return res.grasp_position_residual(T, self._grasp, data)
        return res.grasp_perpendicular_residual(T, self._tgrasp, data)

    def _blocks(self, T: np.ndarray, jacobian: bool) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
        """Per term: name, whitened residual ``(N, d)`` and Jacobian ``(N, d, 6)`` (None without jacobian)."""
        out = []
        for name, data in self._terms:
            r, J = self._raw(name, data, T, jacobian)
            n = self._noise[name]
            W = self._W[name]
            if name == "conic":
                # one scalar noise per pixel: W and mean are 1x1
                out.append((name, (r - n.mean[0]) * W[0, 0], J * W[0, 0] if jacobian else None))
            else:
                out.append((name, (r - n.mean) @ W.T, W @ J if jacobian else None))
        return out

    def whitened(self, cam_T_needle: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals ``e (N, m)`` and Jacobians ``(N, m, 6)`` (None with ``jacobian=False``).

        Plain (not robustly reweighted); :meth:`irls` gives the weighted ones.
        """
        T = res.as_pose_batch(cam_T_needle)
        N = T.shape[0]
        blocks = self._blocks(T, jacobian)
        if not blocks:
            return np.zeros((N, 0)), (np.zeros((N, 0, 6)) if jacobian else None)
        e = np.concatenate([b[1] for b in blocks], axis=1)
        return e, (np.concatenate([b[2] for b in blocks], axis=1) if jacobian else None)

    def irls(self, cam_T_needle: np.ndarray, jacobian: bool = True
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Robust loss ``sum_b rho_b(|e_b|)`` ``(N,)``, and ``sqrt(w) e`` ``(N, m)``, ``sqrt(w) J`` ``(N, m, 6)``.

        The rows of the last two are those of :meth:`whitened`, each block scaled by the square root
        of its IRLS weight (module docstring) — what GTSAM's ``linearize`` of the same factor with
        :meth:`factors.robust.RobustLoss.gtsam_model` returns as ``A`` and ``-b``. Terms without a
        robust loss are left as they are and cost ``1/2 |e|^2``.
        """
        T = res.as_pose_batch(cam_T_needle)
        N = T.shape[0]
        loss = np.zeros(N)
        es, Js = [], []
        for name, e, J in self._blocks(T, jacobian):
            rl = self._loss[name]
            if rl.active:
                # a conic block is one pixel; the others are the whole term
                d = np.abs(e) if name == "conic" else np.linalg.norm(e, axis=1, keepdims=True)
                loss += np.sum(rl.loss(d), axis=1)
                sw = np.sqrt(rl.weight(d))
                if name != "conic":
                    sw = np.broadcast_to(sw, e.shape)
                e = e * sw
                if jacobian:
                    J = J * sw[:, :, None]
            else:
                loss += 0.5 * np.sum(e * e, axis=1)
            es.append(e)
            Js.append(J)
        if not es:
            return loss, np.zeros((N, 0)), (np.zeros((N, 0, 6)) if jacobian else None)
        return loss, np.concatenate(es, axis=1), (np.concatenate(Js, axis=1) if jacobian else None)

    def loss_at_rms(self, rms_sigma: float) -> float:
        """``nll`` of residuals whose blocks are all ``rms_sigma`` standard deviations per dimension off.

        ``sum_b rho_b(rms_sigma sqrt(dim_b))``; without robust losses ``1/2 rms_sigma^2 dim``. The
        implausibility test (:func:`pinpoint_fg.trackers.base.implausible`) compares against it so a
        robust loss does not make every frame look plausible.
        """
        total = 0.0
        for name, data in self._terms:
            dim = self._term_dim(name, data)
            rl = self._loss[name]
            if name == "conic":
                total += dim * float(rl.loss(rms_sigma))
            else:
                total += float(rl.loss(rms_sigma * np.sqrt(dim)))
        return total

    def cheirality(self, cam_T_needle: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Penalty ``1/2 s^2``, ``s = max(0, z_min - z) / 1 mm``: value (N,), gradient (N, 6), Hessian (N, 6, 6)."""
        T = res.as_pose_batch(cam_T_needle)
        s = np.maximum(0.0, self.model.min_depth_m - T[:, 2, 3]) / 1e-3
        # dz/dxi = [0, R_row2] (translation moves along R v)
        Jz = np.zeros((T.shape[0], 6))
        Jz[:, 3:] = T[:, 2, :3]
        Js = -(s > 0).astype(float)[:, None] * Jz / 1e-3
        return 0.5 * s * s, s[:, None] * Js, Js[:, :, None] * Js[:, None, :]

    def nll(self, cam_T_needle: np.ndarray) -> np.ndarray:
        """Negative log-likelihood ``sum_b rho_b(|e_b|)`` plus the cheirality penalty, shape (N,)."""
        loss, _, _ = self.irls(cam_T_needle, jacobian=False)
        return loss + self.cheirality(cam_T_needle)[0]

    def gauss_newton(self, cam_T_needle: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``nll (N,)``, its gradient ``J^T w e`` ``(N, 6)`` and ``H = J^T w J`` ``(N, 6, 6)`` (right chart, IRLS).

        The last result is memoised on the exact pose values (their bytes): a tracker that
        evaluates trial poses (a safeguard) and then linearises at the accepted ones gets the
        second call free, bitwise identical. The memo is kept read-only; callers get copies.
        """
        T = res.as_pose_batch(cam_T_needle)
        key = T.tobytes()
        if self._gn_memo is not None and self._gn_memo[0] == key:
            return tuple(a.copy() for a in self._gn_memo[1])
        loss, e, J = self.irls(T)
        c, cg, cH = self.cheirality(T)
        nll = loss + c
        JT = np.swapaxes(J, 1, 2)
        grad = (JT @ e[:, :, None])[:, :, 0] + cg
        H = JT @ J + cH
        for a in (nll, grad, H):
            a.flags.writeable = False
        self._gn_memo = (key, (nll, grad, H))
        return nll.copy(), grad.copy(), H.copy()

    def gtsam_factors(self, key: int) -> list[gtsam.NonlinearFactor]:
        """The same terms as GTSAM factors on ``key``, biases included.

        The biases of keypoint and grasp-position residuals shift the measurement
        (``r - mu = pi(TX) - (z + mu)``); conic and perpendicularity factors take theirs as
        ``bias``. The cheirality penalty has no factor: it is zero for every pose in front of
        the camera. A residual type with a robust loss gets ``gtsam.noiseModel.Robust`` around its
        Gaussian (:meth:`factors.robust.RobustLoss.gtsam_model`); the conic then becomes one factor
        per pixel (:func:`factors.gtsam_factors.conic_pixel_factors`), since GTSAM weights a
        factor's whole whitened vector.
        """
        cam, nd = self.model.camera, self.model.needle
        out: list[gtsam.NonlinearFactor] = []
        for name, data in self._terms:
            n: ResidualNoise = self._noise[name]
            rl = self._loss[name]
            if name in ("tip", "tail"):
                X = nd.tip_m if name == "tip" else nd.tail_m
                out.append(KeypointFactor(key, cam, X, np.asarray(data) + n.mean, rl.gtsam_model(n.gtsam_model())))
            elif name == "conic":
                pts = np.asarray(data)
                if rl.active:
                    pixel = rl.gtsam_model(gtsam.noiseModel.Isotropic.Sigma(1, float(n.sigma[0])))
                    out.extend(conic_pixel_factors(key, cam, nd.radius_m, pts, pixel, bias=float(n.mean[0])))
                else:
                    out.append(ConicFactor(key, cam, nd.radius_m, pts,
                                           gtsam.noiseModel.Isotropic.Sigma(len(pts), float(n.sigma[0])),
                                           bias=float(n.mean[0])))
            elif name == "grasp_position":
                out.append(GraspPositionFactor(key, nd.grasp_m, np.asarray(data) + n.mean,
                                               rl.gtsam_model(n.gtsam_model())))
            else:
                out.append(GraspPerpendicularFactor(key, nd.grasp_tangent, data, rl.gtsam_model(n.gtsam_model()),
                                                    bias=float(n.mean[0])))
        return out
