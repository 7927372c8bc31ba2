"""One mode of a tracker's posterior: its pose, weight and Gaussian spread (reported per frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mode:
    """A posterior mode: a pose, its share of the posterior mass and its tangent covariance."""

    cam_T_needle: np.ndarray
    """(4, 4) the mode's pose."""
    weight: float
    """Normalised weight of the mode (the modes of one frame sum to 1)."""
    cov_xi: np.ndarray
    """(6, 6) covariance of the tangent ``[omega; v]`` at the mode (GTSAM right chart)."""
