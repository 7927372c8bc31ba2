"""GTSAM factors for monocular needle pose: geometry, batched residuals and their factor wrappers.

Depends on gtsam and numpy (and OpenCV for undistortion) only; knows nothing of particles,
files or the command line. Everything a user needs to put the needle into their own GTSAM graph
is importable from here (README, "Using the factors in your own GTSAM graph")::

    from factors import KeypointFactor, ConicFactor, GraspPositionFactor, GraspPerpendicularFactor, MotionFactor
"""

from factors.geometry import NeedleModel, PinholeCamera
from factors.gtsam_factors import (
    ConicFactor,
    GraspPerpendicularFactor,
    GraspPositionFactor,
    KeypointFactor,
    MotionFactor,
    PosePriorFactor,
)

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
