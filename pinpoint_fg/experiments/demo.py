"""``pinpoint-fg demo`` (the README's main job): simulate, track, evaluate, compare.

Simulates the normal-speed, rotation and suturing runs, tracks each with svn, pf and map (in parallel
processes, :mod:`pinpoint_fg.experiments.jobs`), evaluates them against the simulator's ground truth
and prints the comparison table; figures and tables land in ``OUT``.
"""

from __future__ import annotations

import time
from pathlib import Path

from pinpoint_fg.experiments.jobs import TrackJob, run_tracking, simulate_runs

DEMO_SCENARIOS = ("normal", "rotation", "suturing")
DEMO_METHODS = ("svn", "pf", "map")


def run_demo(out: Path = Path("demo-output"), frames: int = 240, jobs: int = 2, seed: int = 1,
             overwrite: bool = False) -> Path:
    """Simulate, track with svn/pf/map, evaluate, print the comparison; returns the report directory.

    ``out`` must be new or empty unless ``overwrite`` (:func:`pinpoint_fg.io.outdir.prepare_output_dir`).
    """
    from pinpoint_fg.eval.report import evaluate_results
    from pinpoint_fg.io.outdir import prepare_output_dir
    from pinpoint_fg.sim.scenarios import _check_args
    from pinpoint_fg.track import suggested_disable

    _check_args(DEMO_SCENARIOS[0], frames, seed)  # before out exists: the simulator's refusal left an empty out
    out = prepare_output_dir(out, overwrite, "demo output")
    t0 = time.perf_counter()
    print(f"[demo] simulating {', '.join(DEMO_SCENARIOS)} ({frames} frames each, seed {seed}) -> {out / 'runs'}")
    runs = simulate_runs(DEMO_SCENARIOS, frames, seed, out)
    disable = {sc: suggested_disable(runs[sc]) for sc in DEMO_SCENARIOS}  # one read per run, not per method
    jobs_list = [TrackJob(str(runs[sc]), m, str(out / "results" / sc / m), disable=disable[sc])
                 for sc in DEMO_SCENARIOS for m in DEMO_METHODS]
    print(f"[demo] tracking {len(jobs_list)} runs on {jobs} process(es)")
    run_tracking(jobs_list, jobs, "demo tracking")
    print("[demo] evaluating (metrics, bimodality vs. ambiguity truth, accuracy floor, figures)")
    report = evaluate_results([j.out for j in jobs_list], out=out / "report")
    print()
    print(report.text)
    print()
    print(f"[demo] done in {time.perf_counter() - t0:.0f} s. Tables: {out / 'report' / 'tables.md'}; "
          f"summary: {out / 'report' / 'summary.csv'}; figures: {out / 'report'}/*.png")
    return out / "report"
