"""Lock-step latency measurement: several trackers stepped in turn on the same frames of one run.

Machines are noisy and shared, so absolute milliseconds do not transfer; ratios measured in the
same run do. :func:`lockstep` observes every frame once (mask processing is not part of any
tracker's step), then feeds each frame to every tracker in turn (one thread: load hits all
alike) and records each step's own ``latency_ms``, its iterations, whether the frame had a mask
(backbone pixels) and, where the run has ground truth, the MAP pose's errors.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import observe_frame


@dataclass(frozen=True)
class TrackerSpec:
    """One tracker of a lock-step run."""

    label: str
    """Name in the tables, e.g. ``svn`` or ``svn N=25 L=3``."""
    method: str
    """svn, svgd, pf or map."""
    particles: int | None = None
    """Hypotheses (None: the method's default)."""
    window: int = 1
    """Window length L."""


@dataclass
class LockstepResult:
    """Per-frame numbers of every tracker of one lock-step run."""

    mask: np.ndarray
    """(F,) True where the frame had backbone pixels."""
    latency_ms: dict[str, np.ndarray] = field(default_factory=dict)
    """Per label, (F,) step latency, milliseconds."""
    cpu_ms: dict[str, np.ndarray] = field(default_factory=dict)
    """Per label, (F,) CPU time of this thread during the step, milliseconds (less sensitive to other load)."""
    iterations: dict[str, np.ndarray] = field(default_factory=dict)
    """Per label, (F,) iterations."""
    trans_err_m: dict[str, np.ndarray] = field(default_factory=dict)
    """Per label, (F,) translation error of the MAP pose (NaN without ground truth), metres."""
    rot_err_rad: dict[str, np.ndarray] = field(default_factory=dict)
    """Per label, (F,) rotation error of the MAP pose (NaN without ground truth), radians."""

    def summary(self, label: str) -> dict[str, float]:
        """Median / p95 latency over all, mask and no-mask frames; mean iterations; mean errors."""
        lat = self.latency_ms[label]
        out: dict[str, float] = {}
        for name, sel in (("all", np.ones_like(self.mask)), ("mask", self.mask), ("nomask", ~self.mask)):
            x = lat[sel]
            out[f"median_ms_{name}"] = float(np.median(x)) if x.size else float("nan")
            out[f"p95_ms_{name}"] = float(np.percentile(x, 95)) if x.size else float("nan")
        cpu = self.cpu_ms[label]
        for name, sel in (("all", np.ones_like(self.mask)), ("mask", self.mask), ("nomask", ~self.mask)):
            out[f"cpu_median_ms_{name}"] = float(np.median(cpu[sel])) if sel.any() else float("nan")
        out["iterations_mean"] = float(np.mean(self.iterations[label]))
        out["iterations_mean_mask"] = float(np.mean(self.iterations[label][self.mask])) if self.mask.any() else 0.0
        for name, sel in (("", np.ones_like(self.mask)), ("_mask", self.mask), ("_nomask", ~self.mask)):
            t, r = self.trans_err_m[label][sel], self.rot_err_rad[label][sel]
            out[f"trans_mean_mm{name}"] = float(np.nanmean(t) * 1e3) if np.isfinite(t).any() else float("nan")
            out[f"rot_mean_deg{name}"] = float(np.degrees(np.nanmean(r))) if np.isfinite(r).any() else float("nan")
        return out


def _errors(T: np.ndarray, T_gt: np.ndarray | None) -> tuple[float, float]:
    if T_gt is None:
        return float("nan"), float("nan")
    dt = float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))
    c = 0.5 * (np.trace(T_gt[:3, :3].T @ T[:3, :3]) - 1.0)
    return dt, float(np.arccos(np.clip(c, -1.0, 1.0)))


def lockstep(run: str | Path, specs: list[TrackerSpec], max_frames: int | None = None, seed: int = 0,
             max_points: int = 200) -> LockstepResult:
    """Step every tracker of ``specs`` in turn on each frame of ``run`` (see module docstring)."""
    from pinpoint_fg.track import make_tracker, tracker_config

    recording = read_recording(run)
    frames = recording.frames if max_frames is None else recording.frames[: int(max_frames)]
    observations = [observe_frame(recording, rec, max_points=max_points) for rec in frames]
    trackers = {s.label: make_tracker(s.method, tracker_config(recording, s.method, s.particles, s.window,
                                                               seed=seed)) for s in specs}
    n = len(frames)
    out = LockstepResult(mask=np.array([o.backbone_px is not None for o in observations], dtype=bool))
    for s in specs:
        out.latency_ms[s.label] = np.zeros(n)
        out.iterations[s.label] = np.zeros(n)
        out.cpu_ms[s.label] = np.zeros(n)
        out.trans_err_m[s.label] = np.full(n, np.nan)
        out.rot_err_rad[s.label] = np.full(n, np.nan)
    for k, (rec, obs) in enumerate(zip(frames, observations, strict=True)):
        for s in specs:
            c0 = time.thread_time()
            est = trackers[s.label].step(obs)
            out.cpu_ms[s.label][k] = 1e3 * (time.thread_time() - c0)
            out.latency_ms[s.label][k] = est.latency_ms
            out.iterations[s.label][k] = est.iterations
            out.trans_err_m[s.label][k], out.rot_err_rad[s.label][k] = _errors(est.cam_T_needle, rec.cam_T_needle_gt)
    return out
