"""Summaries of a frame's pose posterior: spread, modes, bimodality verdict (below trackers and evaluation)."""
