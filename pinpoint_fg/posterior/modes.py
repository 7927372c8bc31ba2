"""The modes of a pose posterior: one peak pose, its weight and its covariance per mode."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mode:
    """One mode of a frame's pose posterior."""

    cam_T_needle: np.ndarray
    """(4, 4) peak pose."""
    weight: float
    """Weight of the mode; the modes of a frame sum to 1."""
    cov_xi: np.ndarray
    """(6, 6) covariance in GTSAM's chart at the peak, [omega; v], rad / m."""
