"""Experiments that run tracking: demo, benchmark, ablation, batch (Dask), lock-step latency (above track)."""
