"""Noise calibration, metrics, reports and ablations."""
