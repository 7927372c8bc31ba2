"""One frame's estimate: what a tracker reports and what a result file holds, one type for both.

A tracker's :meth:`~pinpoint_fg.trackers.base.Tracker.step` returns it with what the step itself
knows; ``pinpoint_fg.track.to_frame_estimate`` completes it (``dataclasses.replace``) with what is
judged after the step — the GMM verdict ``bimodal``, the modes, the summary columns in ``extra`` — and
:class:`pinpoint_fg.io.result.ResultWriter` writes it; ``cov_xi`` and ``reseeded`` are the tracker's
(``reseeded`` goes to disk as an extra column, ``cov_xi`` does not go to disk).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pinpoint_fg.posterior.modes import Mode


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """One frame's estimate (module docstring); every field is passed by keyword."""

    frame: int
    """Frame index in the recording."""
    t_s: float
    """Time stamp, seconds."""
    cam_T_needle: np.ndarray
    """(4, 4) MAP pose."""
    q95_trans_m: float
    """Weighted 95th percentile of the particles' translation distance to the MAP, metres (NaN: unknown)."""
    q95_rot_rad: float
    """Weighted 95th percentile of the particles' rotation angle to the MAP, radians (NaN: unknown)."""
    iterations: int
    """Transport iterations (SVN/SVGD), optimiser iterations (MAP) or 1 (PF)."""
    latency_ms: float
    """Wall time of this frame's inference, milliseconds."""
    particles: np.ndarray
    """(N, 4, 4) the particle set ``cam_T_needle`` (N = 1 for MAP; fixed for a run)."""
    log_posterior: np.ndarray
    """(N,) log-posterior of each particle (up to a constant)."""
    weights: np.ndarray | None = None
    """(N,) normalised weights for weighted methods (PF), else None (equal weights)."""
    cov_xi: np.ndarray | None = None
    """(6, 6) weighted covariance of the particles' tangent vectors at the MAP, [omega; v] (not written to disk)."""
    smoothed: tuple[int, float, np.ndarray] | None = None
    """With a window L > 1: (frame, t_s, (4, 4) pose) of the fixed-lag smoothed frame k - L + 1."""
    reseeded: bool = False
    """True when every hypothesis was implausible and the particles were re-seeded this frame."""
    bimodal: bool = False
    """The GMM bimodality verdict of the particle set (set after the step, by ``to_frame_estimate``)."""
    extra: dict[str, float] = field(default_factory=dict)
    """More numeric per-frame columns for estimates.csv (method-specific, then the summaries)."""
    modes: tuple[Mode, ...] | None = None
    """Posterior modes of the frame (written to modes.csv, dominant first); None: none (yet)."""
