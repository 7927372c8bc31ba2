"""GTSAM factors for monocular needle pose: geometry, batched residuals and their factor wrappers.

Depends on gtsam and numpy (and OpenCV for undistortion) only; knows nothing of particles,
files or the command line.
"""

from factors.geometry import NeedleModel, PinholeCamera

__all__ = ["NeedleModel", "PinholeCamera"]
