"""A slowly varying bias of the kinematic residuals, tracked by a Kalman filter per hypothesis (issue 9).

The trackers' likelihood counts each frame's grasp-position and grasp-perpendicularity residuals as independent
noise. The robot's kinematic error is mostly a slow drift (hand-eye calibration, cable stretch), and the
simulator's error is too: :func:`pinpoint_fg.sim.kinematics.ou_white_process`. Counted once per frame, one
persistent offset becomes fresh evidence on every frame, and the evidence for whichever pose absorbs it
grows without bound (``scripts/kinematic_bias_evidence.py``, README *Why SVN and MHT take the twin circle*).

The model here, for one residual type of dimension ``d`` with covariance ``C`` (the noise file's):

* ``r_k = b_k + w_k``, with ``w_k ~ N(0, f C)`` white (``f = BiasModel.white_share``);
* ``b_k = a b_{k-1} + q_k``, with ``a = exp(-dt_k / tau)`` and ``q_k ~ N(0, (1 - a^2) (1 - f) C)``. This is
  Ornstein-Uhlenbeck, started from its stationary law ``N(0, (1 - f) C)``, so every ``r_k ~ N(0, C)`` as before.

A hypothesis's bias is estimated from its own residual sequence. :class:`BiasFilter` holds one mean per
hypothesis ``(N, d)`` and one covariance ``(d, d)``, which every hypothesis shares: the covariance recursion does
not depend on the residuals, only on the frame times. The frame's kinematic term is then the filter's innovation
``r_k - a b_hat`` with covariance ``S = P^- + f C``. The sum of the innovations' NLLs is the exact log-likelihood of
the residual sequence (the prediction-error decomposition, :func:`sequence_nll`). With ``f = 1`` the bias is zero,
``S = C``, and every quantity is the white model's. ``scripts/kinematic_bias_evidence.py`` scores trajectories
with it.

:class:`BiasBook` turns a tracker's evidence (the white count of the kinematic terms) into this model's, frame by
frame, with each hypothesis's pose uncertainty folded in. SVN takes it as an option
(:attr:`pinpoint_fg.trackers.svn.SvnSettings.kinematic_bias`, off by default: measured in the README, *Kinematic
bias in the evidence*); the pose fit of every tracker stays the white model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from factors.robust import RobustLoss
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.stein import floor_hessians

#: The kinematic residual types a bias can be tracked for.
KINEMATIC_TERMS = ("grasp_position", "grasp_perpendicular")


@dataclass(frozen=True)
class BiasModel:
    """The slowly varying part of a kinematic residual's error (module docstring)."""

    tau_s: float = 5.0
    """Time constant of the Ornstein-Uhlenbeck bias, seconds (the simulator's ``kin_bias_tau_s``)."""
    white_share: float = 0.01
    """Share ``f`` of the residual's variance that is white (the simulator's ``kin_white_var_fraction``); 1: no bias."""
    terms: tuple[str, ...] = KINEMATIC_TERMS
    """The kinematic residual types the bias is modelled for (:class:`BiasBook`; the others stay white)."""

    def __post_init__(self) -> None:
        terms = tuple(self.terms)
        unknown = [t for t in terms if t not in KINEMATIC_TERMS]
        if unknown or len(set(terms)) != len(terms):
            raise ValueError(f"terms must be distinct names among {KINEMATIC_TERMS}, got {self.terms!r}")
        object.__setattr__(self, "terms", terms)
        if not (math.isfinite(self.tau_s) and self.tau_s > 0.0):
            raise ValueError(f"tau_s must be finite and > 0, got {self.tau_s!r}")
        if not (0.0 < self.white_share <= 1.0):
            raise ValueError(f"white_share must be in (0, 1], got {self.white_share!r}")

    def decay(self, dt_s: float) -> float:
        """``a = exp(-dt / tau)``: how much of the bias survives ``dt_s`` seconds (``dt_s >= 0``)."""
        if not (math.isfinite(dt_s) and dt_s >= 0.0):
            raise ValueError(f"dt_s must be finite and >= 0, got {dt_s!r}")
        return math.exp(-dt_s / self.tau_s)


@dataclass(frozen=True)
class BiasFilter:
    """The bias estimate of ``N`` hypotheses for one residual type: ``mean (N, d)`` and its covariance, ``(d, d)``
    shared by every hypothesis or ``(N, d, d)`` one each.

    Both are the estimate *before* the next frame's residual (after :meth:`predict`). ``noise_cov`` (the residual's
    ``C``) and ``model`` are passed to each call rather than kept, so one filter can be scored under several.
    ``extra`` (``(d, d)`` or ``(N, d, d)``, default none) is measurement noise beyond the white ``f C``: the residual's
    spread from the pose's own uncertainty (:class:`BiasBook`); with it the covariance becomes one per hypothesis.
    """

    mean: np.ndarray
    """Predicted bias of every hypothesis, ``(N, d)``, in the residual's units."""
    cov: np.ndarray
    """Covariance of the predicted bias, ``(d, d)`` (shared) or ``(N, d, d)``."""

    @classmethod
    def stationary(cls, n: int, noise_cov: np.ndarray, model: BiasModel) -> BiasFilter:
        """The filter before any frame: zero bias with its stationary covariance ``(1 - f) C``."""
        C = np.atleast_2d(np.asarray(noise_cov, dtype=float))
        return cls(np.zeros((n, C.shape[0])), (1.0 - model.white_share) * C)

    def innovation_cov(self, noise_cov: np.ndarray, model: BiasModel, extra: np.ndarray | float = 0.0) -> np.ndarray:
        """``S = P^- + f C (+ extra)``: the covariance of the next residual about :attr:`mean`."""
        return self.cov + model.white_share * np.atleast_2d(np.asarray(noise_cov, dtype=float)) + extra

    def update(self, residual: np.ndarray, noise_cov: np.ndarray, model: BiasModel,
               extra: np.ndarray | float = 0.0) -> BiasFilter:
        """The estimate after each hypothesis's residual ``(N, d)`` of this frame (at its final pose)."""
        S = self.innovation_cov(noise_cov, model, extra)
        P = self.cov
        gain = np.swapaxes(np.linalg.solve(S, np.swapaxes(P, -1, -2)), -1, -2)  # P S^-1
        nu = np.asarray(residual, dtype=float) - self.mean
        cov = P - gain @ P
        return BiasFilter(self.mean + np.einsum("...ij,...j->...i", gain, nu), 0.5 * (cov + np.swapaxes(cov, -1, -2)))

    def predict(self, dt_s: float, noise_cov: np.ndarray, model: BiasModel) -> BiasFilter:
        """The estimate ``dt_s`` seconds later: ``a`` times the mean, ``a^2 P + (1 - a^2)(1 - f) C``."""
        a = model.decay(dt_s)
        C = np.atleast_2d(np.asarray(noise_cov, dtype=float))
        return BiasFilter(a * self.mean, a * a * self.cov + (1.0 - a * a) * (1.0 - model.white_share) * C)

    def rows(self, index: np.ndarray | list[int]) -> BiasFilter:
        """The filter of hypotheses ``index`` (copies; a shared covariance stays shared)."""
        index = np.asarray(index)
        return BiasFilter(self.mean[index].copy(), self.cov[index].copy() if self.cov.ndim == 3 else self.cov.copy())


def gaussian_nll(nu: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``1/2 nu^T S^-1 nu + 1/2 log det(2 pi S)`` per row of ``nu (N, d)``, shape ``(N,)``."""
    S = np.atleast_2d(S)
    quad = np.einsum("ni,ni->n", nu, np.linalg.solve(S, nu.T).T)
    return 0.5 * quad + 0.5 * float(np.linalg.slogdet(2.0 * math.pi * S)[1])


def sequence_nll(residuals: np.ndarray, times_s: np.ndarray, noise_cov: np.ndarray,
                 model: BiasModel | None) -> np.ndarray:
    """Negative log-likelihood of residual sequences ``(K, N, d)`` at times ``(K,)``, per sequence ``(N,)``.

    ``model`` None: the white model, ``sum_k`` of each frame's ``N(0, C)`` NLL. Otherwise the bias model's exact
    sequence likelihood, by :class:`BiasFilter`'s prediction errors. A ``(K, d)`` array is one sequence.
    """
    r = np.asarray(residuals, dtype=float)
    if r.ndim == 2:
        r = r[:, None, :]
    C = np.atleast_2d(np.asarray(noise_cov, dtype=float))
    if model is None:
        return np.sum([gaussian_nll(rk, C) for rk in r], axis=0)
    t = np.asarray(times_s, dtype=float)
    filt = BiasFilter.stationary(r.shape[1], C, model)
    total = np.zeros(r.shape[1])
    for k, rk in enumerate(r):
        if k > 0:
            filt = filt.predict(float(t[k] - t[k - 1]), C, model)
        total += gaussian_nll(rk - filt.mean, filt.innovation_cov(C, model))
        filt = filt.update(rk, C, model)
    return total


@dataclass
class BiasBook:
    """Per-hypothesis bias filters of the kinematic terms, and the evidence correction they give (issue 9).

    The trackers' evidence (a hypothesis's accumulated marginal likelihood) counts each frame's kinematic terms as
    independent, ``r_k ~ N(0, C)`` per frame. Under :class:`BiasModel` the same residual sequence is scored by the
    bias filter's prediction errors instead, so one persistent offset is paid about once per ``tau``, not once per
    frame. A hypothesis's pose at frame ``k`` is itself uncertain (covariance ``Sigma``, what the frame's other terms
    and the window prior say: the *cavity* of the kinematic terms), so both scores are predictive, of
    ``r_k`` linearised as ``r + J d``, ``d ~ N(0, Sigma)``:

    * white: ``rho(|r|_{C + J Sigma J^T}) + 1/2 log det(C + J Sigma J^T)``;
    * bias: ``rho(|r - b|_{S + J Sigma J^T}) + 1/2 log det(S + J Sigma J^T)``, ``S = P^- + f C`` the filter's
      innovation covariance (``|x|_M = sqrt(x^T M^-1 x)``, ``rho`` the term's robust loss).

    :meth:`correct` returns the second minus the first, per hypothesis: added to the evidence it turns the white
    model's count into the bias model's. ``J Sigma J^T`` is what makes the scores predictive; in practice the white
    share ``f`` matters more, since ``S >= f C`` bounds how much a pose estimate's frame-to-frame jitter (a few
    degrees) is scored as a kinematic surprise (README, *Kinematic bias in the evidence*). The filters
    (:class:`BiasFilter`) are then updated with ``r`` as a measurement of ``b`` with noise ``f C + J Sigma J^T``, so
    each hypothesis has its own covariance. The pose fit is not changed.
    """

    model: BiasModel
    """The bias model of every kinematic term."""
    filters: dict[str, BiasFilter]
    """Per term its filters, from the term's first frame on."""
    noise: dict[str, np.ndarray]
    """Per term its noise covariance ``C`` ``(d, d)`` (as first seen)."""
    t_s: float | None = None
    """Time of the last frame the filters were brought to (None: none yet)."""

    @classmethod
    def start(cls, model: BiasModel) -> BiasBook:
        """An empty book: every term's filter starts stationary, ``N(0, (1 - f) C)``, at its first frame."""
        return cls(model, {}, {})

    @property
    def means(self) -> dict[str, np.ndarray]:
        """Per term the predicted bias of every hypothesis ``(N, d)`` (the filters' own arrays)."""
        return {k: f.mean for k, f in self.filters.items()}

    @property
    def covs(self) -> dict[str, np.ndarray]:
        """Per term the covariance of that prediction ``(N, d, d)`` (the filters' own arrays)."""
        return {k: f.cov for k, f in self.filters.items()}

    def rows(self, index: np.ndarray | list[int]) -> BiasBook:
        """The book of hypotheses ``index`` (copies)."""
        return BiasBook(self.model, {k: f.rows(index) for k, f in self.filters.items()}, dict(self.noise), self.t_s)

    def set_rows(self, index: np.ndarray | list[int], source: BiasBook, source_index: np.ndarray | list[int]) -> None:
        """Hypotheses ``index`` take ``source``'s filters of ``source_index`` (``source`` may be this book)."""
        index, source_index = np.asarray(index), np.asarray(source_index)
        for k, f in self.filters.items():
            if k in source.filters:
                f.mean[index] = source.filters[k].mean[source_index]
                f.cov[index] = source.filters[k].cov[source_index]

    def correct(self, terms: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, RobustLoss]], pose_cov: np.ndarray,
                t_s: float) -> np.ndarray | None:
        """Evidence correction ``(N,)`` of one frame (class docstring), the filters updated; None without terms.

        ``terms``: per present kinematic term ``(r - mean (N, d), its Jacobian (N, d, 6), C (d, d), RobustLoss)`` at
        each hypothesis's pose; ``pose_cov`` ``(N, 6, 6)``: each pose's covariance without the kinematic terms.
        """
        if self.t_s is not None:
            dt = max(0.0, float(t_s) - self.t_s)
            self.filters = {k: f.predict(dt, self.noise[k], self.model) for k, f in self.filters.items()}
        self.t_s = float(t_s)
        total = None
        for k, (r, J, C, loss) in terms.items():
            r = np.asarray(r, dtype=float)
            C = self.noise.setdefault(k, np.atleast_2d(np.asarray(C, dtype=float)))
            f = self.filters.get(k)
            if f is None:  # the term's first frame: the stationary law, one covariance per hypothesis
                f = BiasFilter.stationary(r.shape[0], C, self.model)
                f = BiasFilter(f.mean, np.broadcast_to(f.cov, (r.shape[0],) + C.shape).copy())
            A = J @ pose_cov @ np.swapaxes(J, 1, 2)
            S = f.innovation_cov(C, self.model, A)
            W = C + A
            term = ((loss.loss(_mahalanobis(r - f.mean, S)) + 0.5 * np.linalg.slogdet(S)[1])
                    - (loss.loss(_mahalanobis(r, W)) + 0.5 * np.linalg.slogdet(W)[1]))
            total = term if total is None else total + term
            self.filters[k] = f.update(r, C, self.model, A)
        return total


def _mahalanobis(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``sqrt(x^T M^-1 x)`` per row of ``x (N, d)`` with ``M (N, d, d)``."""
    return np.sqrt(np.maximum(np.einsum("ni,ni->n", x, np.linalg.solve(M, x[:, :, None])[:, :, 0]), 0.0))


def kinematic_correction(book: BiasBook, frame: FrameLikelihood, cam_T_needle: np.ndarray,
                         information: np.ndarray) -> np.ndarray | None:
    """:meth:`BiasBook.correct` of one frame at poses ``(N, 4, 4)`` whose Gauss-Newton information of everything
    counted so far (the frame's terms, the window prior) is ``information (N, 6, 6)``; the kinematic terms' own share
    is taken out of it for the cavity. None when the frame has no kinematic term the model covers."""
    names = tuple(k for k in KINEMATIC_TERMS if k in frame.term_names and k in book.model.terms)
    if not names:
        book.correct({}, np.zeros((0, 6, 6)), frame.observation.t_s)
        return None
    parts = frame.kinematic_terms(cam_T_needle, names)
    H = np.asarray(information, dtype=float) - sum(p[4] for p in parts.values())
    _, pose_cov = floor_hessians(H, eps=1e-9)
    return book.correct({k: p[:4] for k, p in parts.items()}, pose_cov, frame.observation.t_s)
