"""Summaries of a frame's pose posterior: spread, modes, the bimodality verdict (below the trackers, above the core)."""
