"""pinpoint-fg: multi-hypothesis monocular needle pose tracking on GTSAM factors."""

__version__ = "0.1.0"
