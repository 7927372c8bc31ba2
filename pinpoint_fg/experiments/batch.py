"""Track many recorded runs on a Dask distributed cluster (``pinpoint-fg batch``).

``batch_track(runs, method, OUT)`` runs :func:`pinpoint_fg.track.track_recording` once per run,
each as one Dask task, and writes the result of run ``RUN`` to ``OUT/<RUN's directory name>``:
the same files a single ``pinpoint-fg track RUN --method M --out OUT/<name>`` writes, identical
except the ``latency_ms`` column (timing). This is how many runs scale past one machine: point
``scheduler`` at a running ``dask scheduler`` whose workers share the file system.

Decisions:

* **Cluster.** Without ``scheduler`` a :class:`distributed.LocalCluster` is started for the call
  (``workers`` processes, one thread each: one tracker per process, NumPy/GTSAM not sharing a
  process; bound to 127.0.0.1, its HTTP endpoint on a free port) and closed afterwards. With ``scheduler`` (an address
  such as ``tcp://host:8786``) the call connects to that cluster (``workers`` is then ignored) and
  leaves it running. Dask's workers run with one BLAS thread (its default environment).
* **Tasks build their own tracker.** GTSAM objects cannot be pickled, so a task receives only
  paths and plain options and calls ``track_recording``, which reads the recording and builds the
  tracker inside the worker. Paths (runs, ``OUT``, noise file) are made absolute before they are
  sent, so workers need the same file system view (a shared or the local disk).
* **Result names.** ``OUT/<name>`` with ``name`` the run directory's name; when two runs share a
  name, the later ones get ``-2``, ``-3``, ... in the order given. The same run twice is an error.
* **Failures.** A run whose recording is malformed (:class:`InputError`) or whose file is missing
  does not stop the others: its error is kept as one line and the remaining runs finish;
  :func:`run_batch` reports every outcome, :func:`batch_track` raises :class:`BatchError` after
  all runs finished when any failed (the CLI prints one line per failed run and exits 2). Any
  other exception in a task is a bug: it is re-raised, also only after the other runs finished.
* **Output directory.** ``OUT`` must be new or empty (nothing is overwritten).
"""

from __future__ import annotations

import inspect
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pinpoint_fg.errors import InputError, path_argument, path_list, refuse_repeated
from pinpoint_fg.io.outdir import missing_dirs, prepare_output_dir, remove_empty_dirs
from pinpoint_fg.io.spread_scale import SpreadScale, settings_entry
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.track import METHODS, resolve_conic_distance, track_recording

#: track_recording keywords a batch passes through (everything but run, method, out, progress).
TRACK_OPTIONS = tuple(p for p in inspect.signature(track_recording).parameters
                      if p not in ("run", "method", "out", "progress"))


class BatchError(InputError):
    """Some runs of a batch failed; ``failures`` maps each failed run to its one-line error."""

    def __init__(self, failures: dict[Path, str], results: dict[Path, Path], total: int) -> None:
        self.failures = dict(failures)
        self.results = dict(results)
        first = next(iter(self.failures.values()))
        super().__init__(f"{len(self.failures)} of {total} runs failed (first: {first})")


@dataclass(frozen=True)
class BatchOutcome:
    """Every run's outcome, in the order the runs were given."""

    out_dirs: dict[Path, Path]
    """Run -> its result directory (planned, also for failed runs)."""
    results: dict[Path, Path] = field(default_factory=dict)
    """Run -> result directory, for the runs tracked successfully."""
    failures: dict[Path, str] = field(default_factory=dict)
    """Run -> one-line error, for the runs that failed."""


def result_dir_names(runs: Sequence[Path]) -> list[str]:
    """``OUT`` sub-directory names of ``runs``: the run directory's name, ``-2``, ``-3``... on collisions."""
    used: set[str] = set()
    names = []
    for run in runs:
        base = run.name if run.name not in ("", "..") else Path(os.path.realpath(run)).name  # `..` left OUT
        base = base or "run"
        name, k = base, 1
        while name in used:
            k += 1
            name = f"{base}-{k}"
        used.add(name)
        names.append(name)
    return names


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, FileNotFoundError) and exc.filename:
        return f"{exc.filename}: not found"
    return " ".join(str(exc).split())


def _track_task(run: str, out: str, method: str, options: dict[str, Any]) -> tuple[str, str]:
    """One Dask task: track ``run`` into ``out``; ``("ok", out)`` or ``("error", one line)`` for bad input."""
    try:
        track_recording(run, method=method, out=out, progress=False, **options)
    except (InputError, FileNotFoundError) as exc:
        return "error", _one_line(exc)
    return "ok", out


def _prepare(runs: Sequence[str | Path], method: str, out_dir: Path, workers: int,
             options: dict[str, Any]) -> tuple[list[Path], dict[str, Any]]:
    """Validate everything that can be checked before a cluster starts; absolute paths for the workers."""
    runs = path_list("runs", runs)
    if not runs:
        raise InputError("no runs given")
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose from {', '.join(METHODS)}", column="--method")
    unknown = sorted(set(options) - set(TRACK_OPTIONS))
    if unknown:
        raise TypeError(f"unknown track options {unknown}; known: {', '.join(TRACK_OPTIONS)}")
    if int(workers) < 1:
        raise InputError(f"must be >= 1, got {workers}", column="--workers")
    refuse_repeated(runs, "run")
    paths = [Path(r).absolute() for r in runs]
    options = dict(options)
    if options.get("noise_file") is not None:
        noise = Path(options["noise_file"]).absolute()
        # a bad noise file, or one calibrated for another backbone distance, fails every run: say so once, before
        resolve_conic_distance(options.get("conic_distance"), NoiseConfig.load(noise), noise)
        options["noise_file"] = str(noise)
    if options.get("spread_scale") is not None:
        scale = Path(options["spread_scale"]).absolute()
        settings_entry(SpreadScale.load(scale), method)  # a bad file or a method without factors: say so once
        options["spread_scale"] = str(scale)
    prepare_output_dir(out_dir, bool(options.get("overwrite", False)), "batch output", inputs=paths)
    return paths, options


def run_batch(
    runs: Sequence[str | Path],
    method: str,
    out_dir: str | Path,
    scheduler: str | None = None,
    workers: int = 2,
    on_done: Callable[[Path, Path, str | None], None] | None = None,
    **track_options: Any,
) -> BatchOutcome:
    """Track every run on Dask (module docstring); returns each run's outcome, failures included.

    ``track_options`` are :func:`track_recording`'s (:data:`TRACK_OPTIONS`: ``particles``, ``window``, ``noise_file``,
    ``disable``, ``seed``, ``max_frames``, ``max_points``, ``robust``, ``spread_scale``, ``conic_correlation_px``,
    ``conic_distance``, ...). ``on_done(run, out, error)`` is called as each run finishes (``error`` None on success).
    An ``out_dir`` this call created is removed again while it is still empty when the batch fails.
    """
    from distributed import Client, LocalCluster, as_completed

    out_dir = path_argument("out_dir", out_dir).absolute()  # "" was the current directory
    created = missing_dirs(out_dir)  # removed again (while still empty) when no task could start
    paths, options = _prepare(runs, method, out_dir, workers, track_options)
    out_dirs = {p: out_dir / name for p, name in zip(paths, result_dir_names(paths), strict=True)}
    out_dir.mkdir(parents=True, exist_ok=True)

    cluster = None
    try:
        if scheduler is None:
            # the scheduler's HTTP endpoint on a free loopback port (None would still try port 8787)
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise InputError(f"cannot connect to the Dask scheduler {scheduler!r}: {_one_line(exc)}",
                                 column="--scheduler") from None
        with client:
            futures = {
                client.submit(_track_task, str(p), str(out_dirs[p]), method, options, pure=False): p
                for p in paths
            }
            done: dict[Path, tuple[str, str]] = {}
            bug: BaseException | None = None
            for fut in as_completed(futures):
                run = futures[fut]
                if fut.status == "error":
                    bug = bug or fut.exception()
                    done[run] = ("error", f"{type(fut.exception()).__name__}: {_one_line(fut.exception())}")
                else:
                    done[run] = fut.result()
                if on_done is not None:
                    status, text = done[run]
                    on_done(run, out_dirs[run], None if status == "ok" else text)
    except BaseException:
        remove_empty_dirs(created)  # e.g. no scheduler at --scheduler: nothing was written
        raise
    finally:
        if cluster is not None:
            cluster.close()
    if bug is not None:
        remove_empty_dirs(created)
        raise bug
    results = {p: out_dirs[p] for p in paths if done[p][0] == "ok"}
    failures = {p: done[p][1] for p in paths if done[p][0] != "ok"}
    return BatchOutcome(out_dirs=out_dirs, results=results, failures=failures)


def batch_track(
    runs: Sequence[str | Path],
    method: str,
    out_dir: str | Path,
    scheduler: str | None = None,
    workers: int = 2,
    **track_options: Any,
) -> list[Path]:
    """Track every run on Dask; the result directories in run order. Raises :class:`BatchError`
    (after every run finished) when any run failed; the successful results are on disk then too."""
    outcome = run_batch(runs, method, out_dir, scheduler=scheduler, workers=workers, **track_options)
    if outcome.failures:
        raise BatchError(outcome.failures, outcome.results, len(outcome.out_dirs))
    return list(outcome.results.values())
