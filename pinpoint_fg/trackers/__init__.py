"""Trackers: SVN (PinPoint), SVGD, particle filter and GTSAM fixed-lag MAP, one step(observation) interface."""
