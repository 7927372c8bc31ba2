"""GTSAM factors for monocular needle pose: geometry, batched residuals and their factor wrappers.

Depends on gtsam and numpy (and OpenCV for undistortion) only; knows nothing of particles,
files or the command line. Everything a user needs to put the needle into their own GTSAM graph
is importable from here (README, "Using the factors in your own GTSAM graph")::

    from factors import KeypointFactor, ConicFactor, GraspPositionFactor, GraspPerpendicularFactor, MotionFactor

The factor classes are loaded with :mod:`factors.gtsam_factors` on first use (PEP 562), so code that needs only the
geometry or the batched residuals (:mod:`factors.residuals`, :mod:`factors.lie`) does not import gtsam: ``track``'s
worker process, which observes frames and fits the bimodality mixtures, started ~0.15 s sooner without it.
"""

from __future__ import annotations

from typing import Any

from factors.geometry import NeedleModel, PinholeCamera

__all__ = [
    "ConicFactor",
    "GraspPerpendicularFactor",
    "GraspPositionFactor",
    "KeypointFactor",
    "MotionFactor",
    "NeedleModel",
    "PinholeCamera",
    "PosePriorFactor",
]
_GTSAM_FACTORS = frozenset(__all__) - {"NeedleModel", "PinholeCamera"}


def __getattr__(name: str) -> Any:
    if name in _GTSAM_FACTORS:
        from factors import gtsam_factors

        return getattr(gtsam_factors, name)
    raise AttributeError(f"module 'factors' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_GTSAM_FACTORS})
