"""Noise models of the residuals: bias (sample mean) and covariance per residual type.

Defaults are the paper's Table I (standard deviations, diagonal); ``pinpoint-fg calibrate``
writes a file of the same shape from residuals at ground-truth poses, and
``pinpoint-fg track --noise FILE`` reads it.

File format (JSON)::

    {"format": "pinpoint-noise", "version": 1,
     "residuals": {"tip": {"mean": [du, dv], "cov": [[...], [...]], "count": n}, ...}}

with one entry per residual type in :data:`RESIDUAL_DIMS`. Units are those of the residual:
pixels (tip, tail, conic), metres (grasp_position, camera axes), unitless
(grasp_perpendicular), and the tangent ``[omega (rad); v (m)]`` of the motion residual
(per camera frame, in the needle frame: it is GTSAM's right-perturbation chart).

Decision (not in the paper): the calibrated mean is treated as a measurement bias and
subtracted from the residual before whitening, so ``whitened = L^-1 (r - mean)`` with
``cov = L L^T``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import load_json

#: Residual types and their dimensions.
RESIDUAL_DIMS: dict[str, int] = {
    "tip": 2,
    "tail": 2,
    "conic": 1,
    "grasp_position": 3,
    "grasp_perpendicular": 1,
    "motion": 6,
}

#: Paper Table I standard deviations; motion is this project's choice (see DEFAULT_MOTION_SIGMA).
TABLE_I_SIGMA: dict[str, tuple[float, ...]] = {
    "tip": (1.006, 1.012),
    "tail": (0.921, 0.680),
    "conic": (1.235,),
    "grasp_position": (0.41e-3, 0.44e-3, 1.00e-3),
    "grasp_perpendicular": (0.138,),
}

#: Per-frame (30 Hz) process noise of the motion residual, [omega (rad) x3, v (m) x3].
#: The paper gives no value. The grasper's measured motion is accurate frame to frame, but the
#: needle can turn inside the grasp (external forces) and the robot can slip in tissue; 0.02 rad
#: (~1.1 deg) and 0.3 mm per frame admit ~35 deg/s and ~9 mm/s of unmodelled motion at 1 sigma.
DEFAULT_MOTION_SIGMA: tuple[float, ...] = (0.02, 0.02, 0.02, 0.3e-3, 0.3e-3, 0.3e-3)


@dataclass(frozen=True)
class ResidualNoise:
    """Bias and covariance of one residual type."""

    mean: np.ndarray
    """Sample mean (bias), shape (d,); subtracted before whitening."""
    cov: np.ndarray
    """Covariance, shape (d, d), symmetric positive definite."""
    count: int = 0
    """Number of residual samples it was estimated from (0: a default)."""

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=float).reshape(-1)
        cov = np.atleast_2d(np.asarray(self.cov, dtype=float))
        d = mean.shape[0]
        if cov.shape != (d, d):
            raise ValueError(f"cov must have shape ({d}, {d}) to match mean, got {cov.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError("noise mean/cov contain NaN or infinite values")
        cov = 0.5 * (cov + cov.T)
        if np.min(np.linalg.eigvalsh(cov)) <= 0:
            raise ValueError("noise covariance must be positive definite")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)

    @classmethod
    def from_sigma(cls, sigma: tuple[float, ...] | np.ndarray) -> ResidualNoise:
        """Zero-mean, diagonal noise with the given standard deviations."""
        s = np.asarray(sigma, dtype=float)
        return cls(mean=np.zeros_like(s), cov=np.diag(s**2))

    @property
    def dim(self) -> int:
        """Residual dimension."""
        return int(self.mean.shape[0])

    @property
    def sigma(self) -> np.ndarray:
        """Marginal standard deviations, shape (d,)."""
        return np.sqrt(np.diag(self.cov))

    @property
    def sqrt_information(self) -> np.ndarray:
        """``W`` with ``W^T W = cov^-1`` (upper triangular), so the whitened residual is ``W (r - mean)``."""
        L = np.linalg.cholesky(self.cov)
        return np.linalg.inv(L)

    def gtsam_model(self):  # noqa: ANN201 - gtsam type
        """The matching zero-mean gtsam noise model (Diagonal when the covariance is diagonal)."""
        import gtsam

        off = self.cov - np.diag(np.diag(self.cov))
        if np.allclose(off, 0.0):
            return gtsam.noiseModel.Diagonal.Sigmas(self.sigma)
        return gtsam.noiseModel.Gaussian.Covariance(self.cov)


def _default_residuals() -> dict[str, ResidualNoise]:
    out = {k: ResidualNoise.from_sigma(v) for k, v in TABLE_I_SIGMA.items()}
    out["motion"] = ResidualNoise.from_sigma(DEFAULT_MOTION_SIGMA)
    return out


@dataclass(frozen=True)
class NoiseConfig:
    """Noise of every residual type (defaults: the paper's Table I plus DEFAULT_MOTION_SIGMA)."""

    residuals: dict[str, ResidualNoise] = field(default_factory=_default_residuals)
    """Residual type -> its noise; keys are those of RESIDUAL_DIMS."""

    def __post_init__(self) -> None:
        merged = _default_residuals()
        merged.update(self.residuals)
        for k, v in merged.items():
            if k not in RESIDUAL_DIMS:
                raise ValueError(f"unknown residual type {k!r}; expected one of {sorted(RESIDUAL_DIMS)}")
            if v.dim != RESIDUAL_DIMS[k]:
                raise ValueError(f"noise for {k!r} has dimension {v.dim}, expected {RESIDUAL_DIMS[k]}")
        object.__setattr__(self, "residuals", merged)

    def __getitem__(self, key: str) -> ResidualNoise:
        return self.residuals[key]

    @property
    def process_cov(self) -> np.ndarray:
        """Per-frame process noise ``Q`` (6x6, ``[omega; v]``) of the motion residual."""
        return self.residuals["motion"].cov

    def to_json(self) -> dict:
        """The JSON object written by ``calibrate``."""
        return {
            "format": "pinpoint-noise",
            "version": 1,
            "residuals": {
                k: {"mean": v.mean.tolist(), "cov": v.cov.tolist(), "count": int(v.count)}
                for k, v in self.residuals.items()
            },
        }

    def save(self, path: str | Path) -> None:
        """Write the JSON file."""
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> NoiseConfig:
        """Read and validate a noise file; residual types it omits keep their defaults."""
        path = Path(path)
        doc = load_json(path)  # bounded nesting and integer size; InputError naming the file
        if not isinstance(doc, dict) or doc.get("format") != "pinpoint-noise":
            raise InputError('key "format" must be "pinpoint-noise"', file=path)
        if doc.get("version") != 1:
            raise InputError(f'key "version": unsupported version {doc.get("version")!r}', file=path)
        res = doc.get("residuals")
        if not isinstance(res, dict):
            raise InputError('key "residuals" must be an object', file=path)
        parsed: dict[str, ResidualNoise] = {}
        for k, entry in res.items():
            if k not in RESIDUAL_DIMS:
                continue  # forward compatibility: unknown residual types are ignored
            where = f'key "residuals.{k}"'
            if not isinstance(entry, dict) or "cov" not in entry:
                raise InputError(f'{where} must be an object with "cov" (and optionally "mean")', file=path)
            d = RESIDUAL_DIMS[k]
            try:
                mean = np.asarray(entry.get("mean", [0.0] * d), dtype=float).reshape(-1)
                cov = np.atleast_2d(np.asarray(entry["cov"], dtype=float))
                parsed[k] = ResidualNoise(mean=mean, cov=cov, count=int(entry.get("count", 0)))
            except (TypeError, ValueError) as exc:
                raise InputError(f"{where}: {exc}", file=path) from exc
            if parsed[k].dim != d:
                raise InputError(f"{where}: dimension {parsed[k].dim}, expected {d}", file=path)
        return cls(residuals=parsed)

    def process_variance_whitened(self, scale: np.ndarray) -> float:
        """``tr(S^-1 Q S^-1) / 6``: the mean per-axis process variance in the kernel's whitened units."""
        s = np.asarray(scale, dtype=float)
        return float(np.trace(self.process_cov / np.outer(s, s)) / 6.0)


def degrees(rad: float) -> float:
    """Radians to degrees (small helper for reports)."""
    return rad * 180.0 / math.pi
