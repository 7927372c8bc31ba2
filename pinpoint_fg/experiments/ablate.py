"""The ablation matrix of the paper's Table III (``pinpoint-fg ablate``).

For every run and every variant of :data:`pinpoint_fg.eval.report.ABLATION_VARIANTS` — the full
model; without the dense image term; with one keypoint (the tip disabled); without keypoints;
without any image term; without the grasp position; without the grasp perpendicularity;
without both grasp terms and the motion model; and SVGD instead of SVN — the run is tracked
(:func:`pinpoint_fg.track.track_recording`) into ``out/<run name>/<variant>``, then all results
are evaluated together (:func:`pinpoint_fg.eval.report.evaluate_results`, into ``out``), which
writes Table III (``tables.md``) and the ablation bar figure.

Jobs run in ``jobs`` worker processes (``spawn`` start method: GTSAM objects are not picklable
and a forked GTSAM/TBB runtime is not safe, so a worker receives only paths and strings and
builds everything itself); each worker limits BLAS/OpenMP to one thread so ``jobs`` processes
share the cores instead of oversubscribing them. ``jobs <= 1`` runs everything in this process.
A job that fails is reported (its exception) and left out of the tables; if every job fails the
first failure is raised.
"""

from __future__ import annotations

import multiprocessing
import re
import sys
from collections.abc import Sequence
from concurrent.futures import Future, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pinpoint_fg.errors import InputError, path_argument, path_list, refuse_repeated
from pinpoint_fg.eval.report import ABLATION_VARIANTS, evaluate_results
from pinpoint_fg.experiments.jobs import interruptible_pool
from pinpoint_fg.io.outdir import prepare_output_dir
from pinpoint_fg.io.recording.reader import read_recording


@dataclass(frozen=True)
class AblationJob:
    """One (run, variant) tracking job; only plain values, so it pickles across processes."""

    run: str
    """Recorded run directory."""
    variant: str
    """Variant name (first column of ABLATION_VARIANTS)."""
    method: str
    """Tracking method."""
    disable: tuple[str, ...]
    """Disabled likelihood switches."""
    out: str
    """Result directory."""
    max_frames: int | None
    """Only the first N frames (None: all)."""


def _run_job(job: AblationJob) -> str:
    """Worker: track one job with single-threaded BLAS; returns the result directory."""
    from threadpoolctl import threadpool_limits

    from pinpoint_fg.track import track_recording

    with threadpool_limits(1):
        # job.out lies under the ablation's OUT, which ablate() checked (empty, new or --overwrite)
        track_recording(job.run, method=job.method, out=job.out, disable=job.disable, progress=False,
                        max_frames=job.max_frames, overwrite=True)
    return job.out


def _dir_name(name: str) -> str:
    """A recording's name as one directory name inside ``out``: every run of characters other than letters,
    digits, ``.``, ``_`` and ``-`` becomes ``_``; a name of dots only becomes ``run``. (The name is free text in
    recording.json: ``..`` or ``/data/x`` put the results, tracked with overwrite, outside ``out``.)"""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_")
    return safe if safe.strip(".") else "run"


def ablation_jobs(
    runs: Sequence[Path | str], out: Path | str, frames: int | None = None
) -> list[AblationJob]:
    """Every (run, variant) job with its result directory ``out/<run name>/<variant>``.

    The run name is the recording's name (as a directory name, :func:`_dir_name`); runs that share a name get
    ``-2``, ``-3``, ... appended.
    Raises :class:`InputError` when a run cannot be read or is given twice.
    """
    runs = path_list("runs", runs)
    if not runs:
        raise InputError("ablate needs at least one recorded run")
    refuse_repeated(runs, "run")  # was tracked twice and weighed double in Table III
    # int() truncated 2.5 to 2 frames and took "3" or True as counts, silently
    if frames is not None and (isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1):
        raise InputError(f"--frames must be a whole number >= 1, got {frames!r}")
    out = path_argument("out", out)  # None was pathlib's TypeError, naming no argument
    jobs: list[AblationJob] = []
    used: set[str] = set()
    for run in runs:
        base = _dir_name(read_recording(run).info.name)
        name, k = base, 1
        while name in used:  # (a count per name gave x, x-2, x-2 for runs named x, x, x-2: one overwrote another)
            k += 1
            name = f"{base}-{k}"
        used.add(name)
        for variant, method, disable, _ in ABLATION_VARIANTS:
            jobs.append(AblationJob(
                run=str(Path(run)), variant=variant, method=method, disable=tuple(disable),
                out=str(out / name / variant), max_frames=None if frames is None else int(frames),
            ))
    return jobs


def run_jobs(
    jobs: Sequence[AblationJob], workers: int = 2, show_progress: bool | None = None
) -> tuple[list[str], list[str]]:
    """Run tracking jobs (in ``workers`` processes when > 1); returns (result dirs, failure messages).

    ``show_progress`` None: a bar only when stderr is a terminal (as ``track``), not in a redirected log."""
    done: list[str] = []
    failures: list[str] = []
    errors: list[BaseException] = []
    if show_progress is None:
        show_progress = sys.stderr.isatty()
    bar = tqdm(total=len(jobs), desc="ablate", unit="run", disable=not show_progress)
    try:
        if workers <= 1:
            for job in jobs:
                try:
                    done.append(_run_job(job))
                except Exception as exc:  # noqa: BLE001 - reported, the other jobs go on
                    errors.append(exc)
                    failures.append(f"{job.run} [{job.variant}]: {type(exc).__name__}: {exc}")
                bar.update(1)
        else:
            ctx = multiprocessing.get_context("spawn")
            with interruptible_pool(int(workers), mp_context=ctx) as submit:  # Ctrl-C stops every job
                futures: dict[Future, AblationJob] = {submit(_run_job, job): job for job in jobs}
                for fut in as_completed(futures):
                    job = futures[fut]
                    try:
                        done.append(fut.result())
                    except Exception as exc:  # noqa: BLE001 - reported, the other jobs go on
                        errors.append(exc)
                        failures.append(f"{job.run} [{job.variant}]: {type(exc).__name__}: {exc}")
                    bar.update(1)
    finally:
        bar.close()
    if errors and not done:
        raise errors[0]
    order = {job.out: i for i, job in enumerate(jobs)}
    return sorted(done, key=lambda p: order[p]), failures


def ablate(runs: list[Path], out: Path, jobs: int = 2, frames: int | None = None, overwrite: bool = False) -> str:
    """Track every run with every ablation variant, evaluate, and return Table III (markdown).

    Result directories go to ``out/<run name>/<variant>``; the evaluation (summary.csv,
    tables.md with Table III, figures including the ablation bars) to ``out``, which must be new
    or empty unless ``overwrite`` (:func:`pinpoint_fg.io.outdir.prepare_output_dir`).
    """
    job_list = ablation_jobs(runs, out, frames)  # reads every run first: bad input costs nothing
    out = prepare_output_dir(out, overwrite, "ablation", inputs=runs)
    done, failures = run_jobs(job_list, workers=int(jobs))
    report = evaluate_results([Path(p) for p in done], out=out)
    text = report.table_iii or report.table_ii
    if failures:
        text += "\n\nfailed runs:\n" + "\n".join(f"  {f}" for f in failures)
    return text
