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
With a correlation length ``ell > 0`` (``NoiseConfig.conic_correlation_px``) the backbone's residuals are
first decorrelated along the arc (:mod:`factors.conic_correlation`: ``r -> L (r - mu)``, ``J -> L J``, one
innovation per pixel, each then whitened and robustly weighted as a pixel was).
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
from factors.conic_correlation import ArcWhitening
from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import (
    ConicFactor,
    GraspPerpendicularFactor,
    GraspPositionFactor,
    KeypointFactor,
    conic_pixel_factors,
)
from factors.robust import RobustLoss
from pinpoint_fg.noise import CONIC_DISTANCES, NoiseConfig, ResidualNoise
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
    conic_distance: str = "sampson"
    """Backbone pixel to image conic: "sampson" (first-order distance, the paper's) or "geometric" (exact;
    :func:`factors.residuals.conic_geometric_residual`)."""

    def __post_init__(self) -> None:
        if self.conic_distance not in CONIC_DISTANCES:
            raise ValueError(f"conic_distance must be one of {', '.join(CONIC_DISTANCES)}, got {self.conic_distance!r}")


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
        self._data = dict(self._terms)
        self._noise = {name: model.noise[name] for name, _ in self._terms}
        self._W = {name: n.sqrt_information for name, n in self._noise.items()}
        self._loss: dict[str, RobustLoss] = {name: model.noise.loss(name) for name, _ in self._terms}
        self._tip, self._tail, self._grasp, self._tgrasp = nd.tip_m, nd.tail_m, nd.grasp_m, nd.grasp_tangent
        self.dim = sum(self._term_dim(name, data) for name, data in self._terms)
        self._gn_memo: tuple[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        ell = model.noise.conic_correlation_px
        #: the backbone's along-arc decorrelation (None: independent pixels)
        self.arc_whitening = (ArcWhitening.from_points(self._data["conic"], ell)
                              if ell > 0 and "conic" in self._data else None)
        # frames with equal keys evaluate their stacked terms in one call (:func:`gauss_newton_frames`):
        # everything those terms read besides the measurement (models are rebuilt per frame, equal by value)
        noise = model.noise
        self._stack_key = (
            np.asarray(self._K, dtype=float).tobytes(), float(model.min_depth_m),
            *(np.asarray(a, dtype=float).tobytes() for a in (self._tip, self._tail, self._grasp, self._tgrasp)),
            *((name, np.asarray(noise[name].mean, dtype=float).tobytes(),
               np.asarray(noise[name].sqrt_information, dtype=float).tobytes(), noise.loss(name))
              for name in _STACKED_TERMS),
        )

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

    def _raw(self, name: str, data: object, T: np.ndarray, jacobian: bool = True
             ) -> tuple[np.ndarray, np.ndarray | None]:
        if name == "tip":
            return res.keypoint_residual(T, self._K, self._tip, data, jacobian=jacobian)
        if name == "tail":
            return res.keypoint_residual(T, self._K, self._tail, data, jacobian=jacobian)
        if name == "conic":
            fn = res.conic_geometric_residual if self.model.conic_distance == "geometric" else res.conic_residual
            return fn(T, self._K, self.model.needle.radius_m, data, jacobian=jacobian)
        if name == "grasp_position":
            return res.grasp_position_residual(T, self._grasp, data, jacobian=jacobian)
        return res.grasp_perpendicular_residual(T, self._tgrasp, data, jacobian=jacobian)

    def _whiten(self, name: str, r: np.ndarray, J: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residual ``W (r - mean)`` and Jacobian ``W J`` of term ``name`` (J None: skipped).

        ``J`` is the caller's fresh array from :meth:`_raw`, consumed: the conic's (N, M, 6), the largest array
        of a frame, is scaled in place (the same products as a new array; one allocation fewer).
        """
        n = self._noise[name]
        W = self._W[name]
        if name == "conic" and self.arc_whitening is not None:
            e, J = self.arc_whitening.apply(r - n.mean[0], J)  # fresh arrays: scaled in place
            e *= W[0, 0]
            if J is not None:
                J *= W[0, 0]
            return e, J
        if name == "conic":
            # one scalar noise per pixel: W and mean are 1x1
            if J is not None:
                J *= W[0, 0]
            return (r - n.mean[0]) * W[0, 0], J
        return (r - n.mean) @ W.T, (None if J is None else W @ J)

    def _blocks(self, T: np.ndarray, jacobian: bool) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
        """Per term: name, whitened residual ``(N, d)`` and Jacobian ``(N, d, 6)`` (None without jacobian)."""
        out = []
        for name, data in self._terms:
            r, J = self._raw(name, data, T, jacobian)
            out.append((name, *self._whiten(name, r, J if jacobian else None)))
        return out

    def _robust(self, name: str, e: np.ndarray, J: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Loss ``(N,)`` of one whitened block and its IRLS-weighted ``sqrt(w) e``, ``sqrt(w) J`` (see :meth:`irls`).

        ``J`` is :meth:`_whiten`'s fresh array, consumed: the conic's is reweighted in place.
        """
        rl = self._loss[name]
        if not rl.active:
            return 0.5 * (e * e).sum(axis=1), e, J
        # a conic block is one pixel; the others are the whole term
        d = np.abs(e) if name == "conic" else np.sqrt(np.add.reduce(e * e, axis=1, keepdims=True))  # = norm
        loss = rl.loss(d).sum(axis=1)
        sw = np.sqrt(rl.weight(d))  # (N, M) per conic pixel, else (N, 1): one weight for the term's d rows
        if name == "conic" and J is not None:
            J *= sw[:, :, None]
            return loss, e * sw, J
        return loss, e * sw, (None if J is None else J * sw[:, :, None])

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
            b_loss, e, J = self._robust(name, e, J)
            loss += b_loss
            es.append(e)
            Js.append(J)
        if not es:
            return loss, np.zeros((N, 0)), (np.zeros((N, 0, 6)) if jacobian else None)
        return loss, np.concatenate(es, axis=1), (np.concatenate(Js, axis=1) if jacobian else None)

    def term_losses(self, cam_T_needle: np.ndarray) -> dict[str, np.ndarray]:
        """Each term's robust loss ``rho_b(|e_b|)`` ``(N,)``, by term name (:attr:`term_names` order).

        The parts of :meth:`irls`'s loss: summed in this order from zero they give it exactly. For
        diagnosis: which measurement makes one pose cheaper than another (``scripts/frame_terms.py``).
        """
        T = res.as_pose_batch(cam_T_needle)
        return {name: self._robust(name, e, None)[0] for name, e, _ in self._blocks(T, False)}

    def residuals(self, cam_T_needle: np.ndarray) -> dict[str, np.ndarray]:
        """Each term's residual less its noise mean, unwhitened, ``(N, d)`` by term name (:attr:`term_names` order):
        ``r - mean`` in the term's units (``noise.RESIDUAL_UNITS``), what :meth:`whitened` multiplies by ``W``
        (the backbone's after its along-arc decorrelation, when :attr:`arc_whitening` is set)."""
        T = res.as_pose_batch(cam_T_needle)
        return {name: self._raw(name, data, T, False)[0] - self._noise[name].mean
                for name, data in self._terms}

    def kinematic_terms(self, cam_T_needle: np.ndarray, names: tuple[str, ...]) -> dict[str, tuple]:
        """Per term of ``names`` present this frame: ``r - mean (N, d)``, its Jacobian ``(N, d, 6)`` (right chart),
        the noise covariance ``C (d, d)``, the robust loss, and the term's share ``J^T W^T w W J (N, 6, 6)`` of
        :meth:`gauss_newton`'s information (``w`` its IRLS weight at these poses). For
        :func:`pinpoint_fg.kinematic_bias.kinematic_correction`."""
        T = res.as_pose_batch(cam_T_needle)
        out = {}
        for name, data in self._terms:
            if name not in names:
                continue
            r, J = self._raw(name, data, T)
            _, _, Jw = self._robust(name, *self._whiten(name, r, J))  # W @ J: a new array, J is kept
            out[name] = (r - self._noise[name].mean, J, self._noise[name].cov, self._loss[name],
                         np.swapaxes(Jw, 1, 2) @ Jw)
        return out

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
        return gauss_newton_frames([self], [cam_T_needle])[0]

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
                    out.extend(conic_pixel_factors(key, cam, nd.radius_m, pts, pixel, bias=float(n.mean[0]),
                                                   whitening=self.arc_whitening,
                                                   distance=self.model.conic_distance))
                else:
                    out.append(ConicFactor(key, cam, nd.radius_m, pts,
                                           gtsam.noiseModel.Isotropic.Sigma(len(pts), float(n.sigma[0])),
                                           bias=float(n.mean[0]), whitening=self.arc_whitening,
                                           distance=self.model.conic_distance))
            elif name == "grasp_position":
                out.append(GraspPositionFactor(key, nd.grasp_m, np.asarray(data) + n.mean,
                                               rl.gtsam_model(n.gtsam_model())))
            else:
                out.append(GraspPerpendicularFactor(key, nd.grasp_tangent, data, rl.gtsam_model(n.gtsam_model()),
                                                    bias=float(n.mean[0])))
        return out


#: Terms whose data is one small vector per frame: several frames' poses are evaluated in one call.
_STACKED_TERMS = ("tip", "tail", "grasp_position", "grasp_perpendicular")


def gauss_newton_frames(frames: list[FrameLikelihood], cam_T_needle: list[np.ndarray]
                        ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``[f.gauss_newton(T) for f, T in zip(frames, cam_T_needle)]``, with fewer, larger NumPy calls.

    :meth:`FrameLikelihood.gauss_newton` is this function for one frame (its blocks concatenated,
    ``J^T J`` in one product: the fewest calls for one frame). Frames that share a
    measurement model (equal by value: a window's frames) have each keypoint / grasp term evaluated for
    all their poses in ONE residual call (each pose with its own frame's measurement), since at
    ~50 poses per frame per-call overhead, not arithmetic, is the cost; the conic (a different
    pixel set per frame) is evaluated per frame. Per pose, ``nll = sum_b rho_b + cheirality``,
    ``grad = sum_b J_b^T w_b e_b`` and ``H = sum_b J_b^T w_b J_b`` (the same sums as the
    concatenated ``J^T e`` / ``J^T J``, in another order). Each frame's memo is used and updated.
    """
    out: list = [None] * len(frames)
    todo: dict[int, list] = {}
    for k, (f, T) in enumerate(zip(frames, cam_T_needle, strict=True)):
        T = res.as_pose_batch(T)
        key = T.tobytes()
        if f._gn_memo is not None and f._gn_memo[0] == key:
            out[k] = tuple(a.copy() for a in f._gn_memo[1])
        else:
            todo.setdefault(f._stack_key, []).append((k, f, T, key))
    for items in todo.values():
        if len(items) == 1:  # one frame: its blocks concatenated, one J^T J (fewest calls for one frame)
            k, f, T, key = items[0]
            loss, e, J = f.irls(T)
            c, cg, cH = f.cheirality(T)
            JT = np.swapaxes(J, 1, 2)
            _store(f, key, (loss + c, (JT @ e[:, :, None])[:, :, 0] + cg, JT @ J + cH))
            out[k] = tuple(a.copy() for a in f._gn_memo[1])
            continue
        Ts = [it[2] for it in items]
        offs = np.cumsum([0] + [T.shape[0] for T in Ts])
        T_all = Ts[0] if len(Ts) == 1 else np.concatenate(Ts)
        f0 = items[0][1]
        acc = (np.zeros(T_all.shape[0]), np.zeros((T_all.shape[0], 6)), np.zeros((T_all.shape[0], 6, 6)))
        loss, grad, H = acc
        whole: list[tuple[np.ndarray, np.ndarray]] = []  # small blocks on every row: one J^T J for all of them

        def add(name: str, f: FrameLikelihood, data: object, T: np.ndarray, rows: slice | np.ndarray,
                acc: tuple[np.ndarray, np.ndarray, np.ndarray] = acc, whole: list = whole) -> None:
            r, J = f._raw(name, data, T)
            b_loss, e, J = f._robust(name, *f._whiten(name, r, J))
            acc[0][rows] += b_loss
            if isinstance(rows, slice) and rows == slice(None) and name != "conic":
                whole.append((e, J))
                return
            JT = np.swapaxes(J, 1, 2)
            acc[1][rows] += (JT @ e[:, :, None])[:, :, 0]
            acc[2][rows] += JT @ J

        for name in _STACKED_TERMS:
            members = [i for i, it in enumerate(items) if name in it[1]._data]
            if not members:
                continue
            if len(members) == 1:
                i = members[0]
                add(name, items[i][1], items[i][1]._data[name], Ts[i], slice(offs[i], offs[i + 1]))
                continue
            data = np.concatenate([np.broadcast_to(np.asarray(items[i][1]._data[name], dtype=float),
                                                   (Ts[i].shape[0], len(items[i][1]._data[name])))
                                   for i in members])
            fm = items[members[0]][1]  # the term's noise and loss come from the shared model
            if len(members) == len(items):
                add(name, fm, data, T_all, slice(None))
            else:
                rows = np.concatenate([np.arange(offs[i], offs[i + 1]) for i in members])
                add(name, fm, data, T_all[rows], rows)
        for i, (_, f, T, _) in enumerate(items):
            if "conic" in f._data:
                add("conic", f, f._data["conic"], T, slice(offs[i], offs[i + 1]))
        if whole:
            e = whole[0][0] if len(whole) == 1 else np.concatenate([b[0] for b in whole], axis=1)
            J = whole[0][1] if len(whole) == 1 else np.concatenate([b[1] for b in whole], axis=1)
            JT = np.swapaxes(J, 1, 2)
            grad += (JT @ e[:, :, None])[:, :, 0]
            H += JT @ J
        c, cg, cH = f0.cheirality(T_all)
        loss += c
        grad += cg
        H += cH
        for i, (k, f, _, key) in enumerate(items):
            sl = slice(offs[i], offs[i + 1])
            _store(f, key, (loss[sl].copy(), grad[sl].copy(), H[sl].copy()))
            out[k] = tuple(a.copy() for a in f._gn_memo[1])
    return out


def gauss_newton_rows(f: FrameLikelihood, cam_T_needle: np.ndarray, rows: np.ndarray, cam_T_before: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``f.gauss_newton(cam_T_needle)`` evaluating rows ``rows`` only, the others taken from ``f``'s memo.

    For poses ``cam_T_needle (N, 4, 4)`` that equal ``cam_T_before`` (the poses of ``f``'s last evaluation)
    outside ``rows``: a safeguard that halves a few particles' steps re-evaluates those few, not all ``N``. The
    memo then holds the merged result for ``cam_T_needle``, as a full evaluation would leave it. The evaluated
    rows equal a full evaluation's to round-off, not bit for bit: the conic's pixel terms are one BLAS matrix
    product whose blocking depends on the row count (measured: 1 call in 112 on a normal run differed, by 1e-14
    px; ``tests/test_likelihood.py``). Without the memo of ``cam_T_before`` (or when the poses differ
    elsewhere) this is a full evaluation.
    """
    T = res.as_pose_batch(cam_T_needle)
    before = res.as_pose_batch(cam_T_before)
    rows = np.asarray(rows, dtype=int)
    memo = f._gn_memo
    others = np.ones(T.shape[0], dtype=bool)
    others[rows] = False
    if (rows.size == 0 or memo is None or memo[0] != before.tobytes() or before.shape != T.shape
            or not np.array_equal(T[others], before[others])):
        return f.gauss_newton(T)  # nothing changed (the memo answers), or a full evaluation
    old = memo[1]
    part = gauss_newton_frames([f], [T[rows]])[0]
    merged = tuple(a.copy() for a in old)
    for a, p in zip(merged, part, strict=True):
        a[rows] = p
    _store(f, T.tobytes(), merged)
    return tuple(a.copy() for a in merged)


def _store(f: FrameLikelihood, key: bytes, result: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Keep ``result`` (own arrays, made read-only) as frame ``f``'s memo for the poses whose bytes are ``key``."""
    for a in result:
        a.flags.writeable = False
    f._gn_memo = (key, result)


def _batches(lik: FrameLikelihood, T: np.ndarray, entries: int, chunk: int | None) -> list[np.ndarray]:
    """``T (N, 4, 4)`` cut into consecutive batches of ``chunk`` poses (default: ``entries`` residual entries of
    ``lik``'s frame); one batch (``T`` itself) when it fits."""
    rows = max(1, entries // max(lik.dim, 1)) if chunk is None else chunk
    return [T] if T.shape[0] <= rows else [T[i : i + rows] for i in range(0, T.shape[0], rows)]


#: Residual entries per batch when evaluating the likelihood of many poses (poses x the frame's residual dimension):
#: the likelihood-only path builds no Jacobian, and its largest temporaries are a few times this size; batches that
#: stay in the cache beat one pass over arrays of tens of MB. Measured on normal-01 (3000 particles, thread CPU,
#: ``batched_nll`` alone): 128 rows per batch cost 4.4 ms on a frame without a mask and 20.8 ms with ~200 backbone
#: pixels; the whole batch 1.8 / 33.6 ms; ~500 rows 2.3 / 18.8 ms.
NLL_BATCH_ENTRIES = 100_000


def batched_nll(lik: FrameLikelihood, cam_T_needle: np.ndarray, chunk: int | None = None) -> np.ndarray:
    """``lik.nll`` of ``(N, 4, 4)`` poses in batches of ``chunk`` (default: ``NLL_BATCH_ENTRIES`` residual entries,
    all the particles on a frame without a mask, ~500 with ~200 backbone pixels); non-finite values become
    ``+inf``. Shape (N,). Rows are evaluated independently: the batch size changes round-off only (BLAS may block
    a larger product differently; 5e-13 nats on 91 of 3000 rows of one frame of normal-01, the rest bitwise)."""
    T = np.asarray(cam_T_needle, dtype=float)
    parts = [lik.nll(b) for b in _batches(lik, T, NLL_BATCH_ENTRIES, chunk)]
    out = parts[0] if len(parts) == 1 else np.concatenate(parts)
    return np.where(np.isfinite(out), out, np.inf)


#: Residual entries per batch of :func:`batched_gauss_newton`: with the Jacobian each entry carries six more numbers,
#: so its batches are smaller than :data:`NLL_BATCH_ENTRIES`'. Measured on the seeding's 1440 candidates of a mask
#: frame (thread CPU per evaluation, best of 5; normal-01 208 residual entries per pose, drive-02 140,
#: calibration-01 208): all at once 75 / 71 / 82 ms, batches of 20 000 entries 48 / 43 / 61, 40 000 52 / 44 / 47,
#: 100 000 96 / 50 / 55.
GN_BATCH_ENTRIES = 25_000


def batched_gauss_newton(lik: FrameLikelihood, cam_T_needle: np.ndarray, chunk: int | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``lik.gauss_newton`` of ``(N, 4, 4)`` poses in batches of ``chunk`` rows (default: ``GN_BATCH_ENTRIES``
    residual entries, ~120 poses with ~200 backbone pixels): ``nll (N,)``, ``grad (N, 6)``, ``H (N, 6, 6)``.

    For the many candidate poses of a seeding (:func:`pinpoint_fg.init.polish`). Rows are evaluated independently, so
    the batch size changes round-off only, as in :func:`batched_nll` (``tests/test_likelihood_robust.py``). ``lik``'s
    memo then holds the last batch, not the whole set: the seeding evaluates each candidate set once.
    """
    parts = [lik.gauss_newton(b) for b in _batches(lik, res.as_pose_batch(cam_T_needle), GN_BATCH_ENTRIES, chunk)]
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))  # type: ignore[return-value]
