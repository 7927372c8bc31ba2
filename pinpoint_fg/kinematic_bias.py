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
``S = C``, and every quantity is the white model's.

Not yet wired into the trackers (README, issue 9): this module scores trajectories for the diagnosis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BiasModel:
    """The slowly varying part of a kinematic residual's error (module docstring)."""

    tau_s: float = 5.0
    """Time constant of the Ornstein-Uhlenbeck bias, seconds (the simulator's ``kin_bias_tau_s``)."""
    white_share: float = 0.01
    """Share ``f`` of the residual's variance that is white (the simulator's ``kin_white_var_fraction``); 1: no bias."""

    def __post_init__(self) -> None:
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
    """The bias estimate of ``N`` hypotheses for one residual type: ``mean (N, d)`` and the shared ``cov (d, d)``.

    Both are the estimate *before* the next frame's residual (after :meth:`predict`). ``noise_cov`` (the residual's
    ``C``) and ``model`` are passed to each call rather than kept, so one filter can be scored under several.
    """

    mean: np.ndarray
    """Predicted bias of every hypothesis, ``(N, d)``, in the residual's units."""
    cov: np.ndarray
    """Covariance of the predicted bias, ``(d, d)``, the same for every hypothesis."""

    @classmethod
    def stationary(cls, n: int, noise_cov: np.ndarray, model: BiasModel) -> BiasFilter:
        """The filter before any frame: zero bias with its stationary covariance ``(1 - f) C``."""
        C = np.atleast_2d(np.asarray(noise_cov, dtype=float))
        return cls(np.zeros((n, C.shape[0])), (1.0 - model.white_share) * C)

    def innovation_cov(self, noise_cov: np.ndarray, model: BiasModel) -> np.ndarray:
        """``S = P^- + f C`` ``(d, d)``: the covariance of the next residual about :attr:`mean`."""
        return self.cov + model.white_share * np.atleast_2d(np.asarray(noise_cov, dtype=float))

    def update(self, residual: np.ndarray, noise_cov: np.ndarray, model: BiasModel) -> BiasFilter:
        """The estimate after each hypothesis's residual ``(N, d)`` of this frame (at its final pose)."""
        S = self.innovation_cov(noise_cov, model)
        gain = np.linalg.solve(S, self.cov).T  # P S^-1 (P and S symmetric)
        mean = self.mean + (np.asarray(residual, dtype=float) - self.mean) @ gain.T
        cov = self.cov - gain @ self.cov
        return BiasFilter(mean, 0.5 * (cov + cov.T))

    def predict(self, dt_s: float, noise_cov: np.ndarray, model: BiasModel) -> BiasFilter:
        """The estimate ``dt_s`` seconds later: ``a`` times the mean, ``a^2 P + (1 - a^2)(1 - f) C``."""
        a = model.decay(dt_s)
        C = np.atleast_2d(np.asarray(noise_cov, dtype=float))
        return BiasFilter(a * self.mean, a * a * self.cov + (1.0 - a * a) * (1.0 - model.white_share) * C)

    def rows(self, index: np.ndarray | list[int]) -> BiasFilter:
        """The filter of hypotheses ``index`` (copies; the covariance is shared)."""
        return BiasFilter(self.mean[np.asarray(index)].copy(), self.cov.copy())


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
