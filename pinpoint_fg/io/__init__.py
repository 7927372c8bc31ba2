"""Recorded runs and tracking results: the v1 on-disk formats."""
