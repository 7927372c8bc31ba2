"""Robust losses (M-estimators) of whitened residual blocks: GTSAM's noise model and the batched IRLS maths.

A residual block ``e`` (already whitened, ``e = W (r - mu)``) of Euclidean norm ``d = |e|`` costs
``rho(d)`` instead of ``d^2 / 2``:

=========  ====================================================  =============================
loss       ``rho(d)``                                            IRLS weight ``w(d) = rho'(d)/d``
=========  ====================================================  =============================
none       ``d^2 / 2``                                           ``1``
huber      ``d^2 / 2`` if ``d <= k`` else ``k d - k^2 / 2``       ``min(1, k / d)``
cauchy     ``k^2 / 2 log(1 + d^2 / k^2)``                        ``k^2 / (k^2 + d^2)``
gm         ``k^2 d^2 / (2 (k^2 + d^2))`` (Geman-McClure)          ``k^4 / (k^2 + d^2)^2``
=========  ====================================================  =============================

Geman-McClure redescends: its cost is bounded by ``k^2 / 2``, so a far outlier costs a constant and pulls
nothing, where Huber's and Cauchy's cost keeps growing (linearly, logarithmically) and a crowd of outliers (a
suture thread's pixels in the backbone) can outweigh the wire.

These are GTSAM's ``noiseModel.mEstimator.Huber`` / ``Cauchy`` / ``GemanMcClure`` definitions (GTSAM 4.3; pinned by
``tests/test_factors_robust.py`` against the mEstimator objects' ``loss``/``weight`` to 1e-12).
:meth:`RobustLoss.gtsam_model` wraps a base noise model in ``gtsam.noiseModel.Robust`` so a factor's
``error()`` is ``rho(|e|)`` and its ``linearize()`` scales the whitened ``A`` and ``b`` by ``sqrt(w)``
(iteratively reweighted least squares). The batched path (:mod:`pinpoint_fg.likelihood`) calls
:meth:`RobustLoss.loss` and :meth:`RobustLoss.weight` on block norms of ``N`` poses at once and scales
``e`` and ``J`` by ``sqrt(w)`` the same way, so both give the same value, gradient ``J^T w e`` and
Gauss-Newton Hessian ``J^T w J``.

GTSAM applies one weight to the whole whitened vector of a factor, so the *block* is what one
factor measures: a keypoint (2), the grasp position (3), perpendicularity (1) — and one backbone
pixel (1) for the conic, whose robust GTSAM form is one factor per pixel
(:func:`factors.gtsam_factors.conic_pixel_factors`).

The thresholds ``k`` are in whitened units (standard deviations). Calling GTSAM's mEstimator per
element would cost a Python call per pixel per particle, hence the NumPy copy of these three
one-line formulas, held equal to GTSAM's by the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

#: Loss names accepted by :class:`RobustLoss`.
LOSS_KINDS = ("none", "huber", "cauchy", "gm")
#: Largest accepted threshold ``k`` (standard deviations). Beyond it every loss is the Gaussian for any residual
#: a frame can hold, and ``k^2`` in the formulas would overflow to inf (``1e308`` gave NaN poses).
MAX_K = 1e6


@dataclass(frozen=True)
class RobustLoss:
    """One residual block's loss: ``kind`` in :data:`LOSS_KINDS` and its threshold ``k``."""

    kind: str = "none"
    """``none`` (Gaussian), ``huber``, ``cauchy`` or ``gm`` (Geman-McClure)."""
    k: float = 1.0
    """Threshold in whitened units (standard deviations); unused by ``none``."""

    def __post_init__(self) -> None:
        if self.kind not in LOSS_KINDS:
            raise ValueError(f"unknown robust loss {self.kind!r}; choose from {', '.join(LOSS_KINDS)}")
        try:
            k = float(self.k)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"robust threshold k must be a number, got {self.k!r}") from exc
        if not (np.isfinite(k) and 0 < k <= MAX_K):
            raise ValueError(f"robust threshold k must be a positive finite number <= {MAX_K:g}, got {self.k!r}")
        object.__setattr__(self, "k", k)

    @classmethod
    def parse(cls, text: str) -> RobustLoss:
        """``none``, ``huber``, ``huber:1.345``, ``cauchy:2``, ``gm:3`` (default k: 1.345 Huber, 1.0 the others)."""
        if not isinstance(text, str):  # None or a number was an AttributeError naming nothing
            raise ValueError(f"a robust loss is a string such as 'huber:1.345' or 'none', got {text!r}")
        kind, _, k = text.strip().partition(":")
        kind = kind.strip().lower()
        if not k.strip():
            return cls(kind, 1.345 if kind == "huber" else 1.0)
        try:
            kv = float(k)
        except ValueError as exc:
            raise ValueError(f"robust threshold {k!r} is not a number") from exc
        return cls(kind, kv)

    @property
    def active(self) -> bool:
        """True unless the loss is the plain Gaussian."""
        return self.kind != "none"

    def __str__(self) -> str:
        return "none" if not self.active else f"{self.kind}:{self.k:g}"

    def loss(self, d: np.ndarray) -> np.ndarray:
        """``rho(d)`` elementwise for block norms ``d >= 0`` (any shape)."""
        d = np.abs(np.asarray(d, dtype=float))
        k = self.k
        if self.kind == "huber":
            return np.where(d <= k, 0.5 * d * d, k * d - 0.5 * k * k)
        if self.kind == "cauchy":
            return 0.5 * k * k * np.log1p((d / k) ** 2)
        if self.kind == "gm":
            return 0.5 * k * k * d * d / (k * k + d * d)
        return 0.5 * d * d

    def weight(self, d: np.ndarray) -> np.ndarray:
        """IRLS weight ``w(d) = rho'(d) / d`` elementwise (1 at ``d = 0``)."""
        d = np.abs(np.asarray(d, dtype=float))
        k = self.k
        if self.kind == "huber":
            return np.where(d <= k, 1.0, k / np.where(d <= k, 1.0, d))
        if self.kind == "cauchy":
            return k * k / (k * k + d * d)
        if self.kind == "gm":
            return (k * k / (k * k + d * d)) ** 2
        return np.ones_like(d)

    def gtsam_estimator(self) -> gtsam.noiseModel.mEstimator.Base | None:
        """GTSAM's mEstimator of this loss (None for ``none``)."""
        if self.kind == "huber":
            return gtsam.noiseModel.mEstimator.Huber.Create(self.k)
        if self.kind == "cauchy":
            return gtsam.noiseModel.mEstimator.Cauchy.Create(self.k)
        if self.kind == "gm":
            return gtsam.noiseModel.mEstimator.GemanMcClure.Create(self.k)
        return None

    def gtsam_model(self, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        """``gtsam.noiseModel.Robust(estimator, base)``, or ``base`` itself for ``none``."""
        est = self.gtsam_estimator()
        return base if est is None else gtsam.noiseModel.Robust.Create(est, base)


#: The plain Gaussian loss.
NO_LOSS = RobustLoss()
