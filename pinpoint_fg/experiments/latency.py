"""Lock-step latency measurement: several trackers stepped in turn on the same frames of one run.

Machines are noisy and shared, so absolute milliseconds do not transfer; ratios measured in the
same run do. :func:`lockstep` observes every frame once (mask processing is not part of any
tracker's step), then feeds each frame to every tracker in turn (one thread: load hits all
alike; the BLAS / OpenMP pools are limited to one thread too, as ``pinpoint-fg track`` runs
them) and records each step's own ``latency_ms``, its iterations, whether the frame had a mask
(backbone pixels) and, where the run has ground truth, the MAP pose's errors. Every method's ``latency_ms`` spans
its whole step, its uncertainty summary included (``tests/test_trackers_latency.py``; SVN's excluded its q95 spread
before commit 7595a6d, about 0.3 ms a frame in its favour).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.reader import read_recording
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
    disabled: tuple[str, ...] = ()
    """The likelihood switches every tracker ran without (``--disable`` names)."""
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
             max_points: int = 200, disable: tuple[str, ...] | None = None) -> LockstepResult:
    """Step every tracker of ``specs`` in turn on each frame of ``run`` (see module docstring).

    ``disable``: likelihood switches turned off; None (default) takes the recording's ``suggested_disable``, as
    ``demo`` and ``benchmark`` track it, so latency is measured on the model whose errors those tables report
    (before the eighteenth round the symmetric run's latency was measured with its grasp factors on).
    """
    from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

    recording = read_recording(run)
    if disable is None:
        disable = suggested_disable(recording)
    frames = recording.frames if max_frames is None else recording.frames[: int(max_frames)]
    observations = [observe_frame(recording, rec, max_points=max_points) for rec in frames]
    trackers = {s.label: make_tracker(s.method, tracker_config(recording, s.method, s.particles, s.window,
                                                               disable=disable, seed=seed)) for s in specs}
    from threadpoolctl import threadpool_limits

    n = len(frames)
    out = LockstepResult(mask=np.array([o.backbone_px is not None for o in observations], dtype=bool),
                         disabled=tuple(disable))
    for s in specs:
        out.latency_ms[s.label] = np.zeros(n)
        out.iterations[s.label] = np.zeros(n)
        out.cpu_ms[s.label] = np.zeros(n)
        out.trans_err_m[s.label] = np.full(n, np.nan)
        out.rot_err_rad[s.label] = np.full(n, np.nan)
    with threadpool_limits(limits=1):
        for k, (rec, obs) in enumerate(zip(frames, observations, strict=True)):
            for s in specs:
                c0 = time.thread_time()
                est = trackers[s.label].step(obs)
                out.cpu_ms[s.label][k] = 1e3 * (time.thread_time() - c0)
                out.latency_ms[s.label][k] = est.latency_ms
                out.iterations[s.label][k] = est.iterations
                out.trans_err_m[s.label][k], out.rot_err_rad[s.label][k] = _errors(est.cam_T_needle,
                                                                                   rec.cam_T_needle_gt)
    return out


#: Lock-step methods of the latency benchmark (svgd is an ablation with its own iteration count, left out).
LATENCY_METHODS = ("svn", "pf", "map")
GRID_PARTICLES = (10, 25, 50, 100)
GRID_WINDOWS = (1, 3, 5)
TRACK_REPEATS = 3
"""How many times ``track``'s wall time is measured; the median ratio is reported (one 150-frame run moved from
1.12 to 1.44 between runs of the same code on an idle machine: a worker process starts beside it)."""


def _timed_track(run: Path, dest: Path, frames: int | None) -> tuple[float, float, float, float]:
    """One :func:`~pinpoint_fg.track.track_recording` of svn as ``pinpoint-fg track`` runs it (one verdict worker):
    ``(wall seconds, sum of its step latencies, CPU seconds of this process during the call, CPU seconds of the
    worker process)``. Run in a fresh process by :func:`track_wall`; the worker's CPU is read once its pool has shut
    down and joined it (after the wall time is taken), from this process's reaped children."""
    import resource

    from pinpoint_fg.io.result.reader import read_result
    from pinpoint_fg.offload import join_stopped_workers
    from pinpoint_fg.track import track_recording

    c0 = time.process_time()
    t0 = time.perf_counter()
    track_recording(run, "svn", dest, progress=False, max_frames=frames, verdict_workers=1)
    wall = time.perf_counter() - t0
    cpu_tracker = time.process_time() - c0
    join_stopped_workers()  # the pool's manager thread joins the worker process: its CPU is counted below
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (wall, float(np.sum(read_result(dest).latency_ms)) / 1e3, cpu_tracker,
            children.ru_utime + children.ru_stime)


def track_wall(run: Path, out: Path, frames: int | None, repeats: int = TRACK_REPEATS) -> dict:
    """``pinpoint-fg track``'s wall time over the sum of its step latencies, ``repeats`` times (under ``out/repeat-K``).

    The ratio says what ``track`` costs beyond the steps it reports: reading and observing frames, the
    bimodality verdicts (a worker process), the mode summary and writing. Each run is timed in a fresh (spawned)
    process, as a command-line run is: timed in this process, every run after the first found scikit-learn loaded
    here (the first run's end, or the accuracy part before, had imported it), so the end of the run made the
    workers' backlog here at no import cost, which a command-line run never can (*Twenty-ninth round* in
    docs/measurement-log.md). The process's own start-up, before ``track_recording`` is called, is not timed.

    Each run also reports the CPU seconds of the tracking process (``cpu_tracker_s``) and of its worker
    (``cpu_worker_s``: start-up, scikit-learn's import, verdicts, observations) and ``cpu_bound``, the wall / steps
    that work would take spread perfectly over two cores, ``max(cpu_tracker, (cpu_tracker + cpu_worker) / 2) /
    steps``. A ratio near the bound is limited by the work, one far above it by the schedule. (The worker's figure
    includes its exit after the last row, outside the wall, ~0.1 s: the bound can sit a little above a run.)
    Returns the median run's ``wall_s``, ``step_sum_s``, ``ratio``, ``cpu_tracker_s``, ``cpu_worker_s`` and
    ``cpu_bound``, every run's ``ratios`` and every run's ``runs`` (the same keys), in run order.
    """
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    if repeats < 1:
        raise InputError(f"must be >= 1, got {repeats}", column="track_repeats")
    runs = []
    for k in range(1, repeats + 1):
        with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
            wall, step_sum, cpu_tracker, cpu_worker = pool.submit(_timed_track, Path(run), out / f"repeat-{k}",
                                                                  frames).result()
        bound = max(cpu_tracker, (cpu_tracker + cpu_worker) / 2) / step_sum
        runs.append({"wall_s": wall, "step_sum_s": step_sum, "ratio": wall / step_sum, "cpu_tracker_s": cpu_tracker,
                     "cpu_worker_s": cpu_worker, "cpu_bound": bound})
    median = sorted(runs, key=lambda r: r["ratio"])[(len(runs) - 1) // 2]
    return {**median, "ratios": [r["ratio"] for r in runs], "runs": runs}


def latency_tables(runs: dict[str, Path], frames: int | None, grid_run: Path | None, grid_frames: int | None,
                   track_out: Path | None = None, track_repeats: int = TRACK_REPEATS) -> tuple[dict, str]:
    """The latency benchmark: per scenario, SVN / PF / MAP in lock-step; SVN's cost over N and L; track wall.

    Returns ``(data, text)``: ``data`` is JSON-ready, ``text`` the printed tables. Ratios are
    always between trackers of the same lock-step run. ``cpu`` columns are this thread's CPU time
    per step, a cross-check that is less sensitive to other processes sharing the cores.
    """
    data: dict = {"scenarios": {}, "grid": [], "track": None}
    lines = ["latency (lock-step: svn, pf, map stepped in turn on the same frames, one thread)",
             f"{'scenario':<12} {'method':<6} {'median':>7} {'p95':>7} {'mask med':>8} {'mask p95':>8} "
             f"{'no-mask':>7} {'cpu med':>7} {'iters':>5} {'mask it':>7} {'vs pf':>6} {'vs map':>6} "
             f"{'mask p95 vs map':>15} {'trans mm':>8} {'rot deg':>7} {'rot mask':>8}"]
    for sc, run in runs.items():
        res = lockstep(run, [TrackerSpec(m, m) for m in LATENCY_METHODS], max_frames=frames)
        summ = {m: res.summary(m) for m in LATENCY_METHODS}
        for m, s in summ.items():
            s["ratio_median_vs_pf"] = s["median_ms_all"] / summ["pf"]["median_ms_all"]
            s["ratio_median_vs_map"] = s["median_ms_all"] / summ["map"]["median_ms_all"]
            s["ratio_cpu_median_vs_pf"] = s["cpu_median_ms_all"] / summ["pf"]["cpu_median_ms_all"]
            s["ratio_cpu_median_vs_map"] = s["cpu_median_ms_all"] / summ["map"]["cpu_median_ms_all"]
            s["ratio_mask_p95_vs_map"] = s["p95_ms_mask"] / summ["map"]["p95_ms_mask"]
            lines.append(
                f"{sc:<12} {m:<6} {s['median_ms_all']:7.1f} {s['p95_ms_all']:7.1f} {s['median_ms_mask']:8.1f} "
                f"{s['p95_ms_mask']:8.1f} {s['median_ms_nomask']:7.1f} {s['cpu_median_ms_all']:7.1f} "
                f"{s['iterations_mean']:5.1f} {s['iterations_mean_mask']:7.1f} {s['ratio_median_vs_pf']:6.2f} "
                f"{s['ratio_median_vs_map']:6.2f} {s['ratio_mask_p95_vs_map']:15.2f} {s['trans_mean_mm']:8.3f} "
                f"{s['rot_mean_deg']:7.2f} {s['rot_mean_deg_mask']:8.2f}")
        data["scenarios"][sc] = {"frames": int(res.mask.size), "mask_frames": int(res.mask.sum()),
                                 "disabled": list(res.disabled), "methods": summ}
    if grid_run is not None:
        lines += ["", "SVN cost vs particles N and window L (lock-step, same frames; ms per frame)",
                  f"{'N':>4} {'L':>2} {'median':>7} {'p95':>7} {'mask med':>8} {'cpu med':>7} {'vs L=1':>6}"]
        specs = [TrackerSpec(f"svn N={n} L={L}", "svn", n, L) for n in GRID_PARTICLES for L in GRID_WINDOWS]
        res = lockstep(grid_run, specs, max_frames=grid_frames)
        for n in GRID_PARTICLES:
            base = res.summary(f"svn N={n} L=1")["median_ms_all"]
            for L in GRID_WINDOWS:
                s = res.summary(f"svn N={n} L={L}")
                row = {"particles": n, "window": L, **s, "ratio_vs_L1": s["median_ms_all"] / base}
                data["grid"].append(row)
                lines.append(f"{n:4d} {L:2d} {s['median_ms_all']:7.1f} {s['p95_ms_all']:7.1f} "
                             f"{s['median_ms_mask']:8.1f} {s['cpu_median_ms_all']:7.1f} {row['ratio_vs_L1']:6.2f}")
    if track_out is not None and grid_run is not None:
        data["track"] = track_wall(grid_run, track_out, grid_frames, track_repeats)
        t = data["track"]
        each = " / ".join(f"{r:.2f}" for r in t["ratios"])
        lines += ["", f"pinpoint-fg track (svn, {Path(grid_run).name}, {len(t['ratios'])} runs): wall / steps = "
                      f"{t['ratio']:.2f} (median; each run {each}; reading, verdicts, writing included); "
                      f"median run: wall {t['wall_s']:.2f} s, sum of step latencies {t['step_sum_s']:.2f} s; CPU: "
                      f"tracking process {t['cpu_tracker_s']:.2f} s, worker {t['cpu_worker_s']:.2f} s: spread "
                      f"perfectly over 2 cores, wall / steps {t['cpu_bound']:.2f}"]
    return data, "\n".join(lines)


def plot_grid(grid: list[dict], path: Path) -> None:
    """Median SVN latency vs N, one line per window length L."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for L in sorted({r["window"] for r in grid}):
        rows = sorted((r for r in grid if r["window"] == L), key=lambda r: r["particles"])
        ax.plot([r["particles"] for r in rows], [r["median_ms_all"] for r in rows], "o-", label=f"L = {L}")
    ax.set_xlabel("particles N")
    ax.set_ylabel("median ms per frame")
    ax.set_title("SVN latency vs N and window L")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
