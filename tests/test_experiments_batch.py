"""pinpoint_fg.experiments.batch: many runs on Dask give the results of single ``track`` runs; failures stay per run."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.experiments.batch import BatchError, batch_track, result_dir_names, run_batch
from pinpoint_fg.io.result.reader import expand_result_dirs
from pinpoint_fg.io.spread_scale import MethodScale, SpreadScale
from pinpoint_fg.sim.scenarios import simulate
from pinpoint_fg.track import track_recording

FRAMES = 12


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two short runs whose directories share the name ``run`` (a/run, b/run)."""
    root = tmp_path_factory.mktemp("batch")
    return [simulate("normal", FRAMES, seed=1, out=root / "a" / "run"),
            simulate("rotation", FRAMES, seed=2, out=root / "b" / "run")]


@pytest.fixture(scope="module")
def scheduler() -> str:
    """One explicitly started local cluster for the module (its address is passed as ``scheduler``)."""
    import logging

    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) as cluster:
        yield cluster.scheduler_address


def _estimates_without_latency(path: Path) -> list[dict[str, str]]:
    with open(path / "estimates.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and "latency_ms" in rows[0]
    for r in rows:
        del r["latency_ms"]
    return rows


def _assert_same_result(batch: Path, single: Path) -> None:
    assert _estimates_without_latency(batch) == _estimates_without_latency(single)
    with np.load(batch / "particles.npz", allow_pickle=False) as a, \
            np.load(single / "particles.npz", allow_pickle=False) as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            assert np.array_equal(a[k], b[k]), k
    ia, ib = (json.loads((p / "result.json").read_text()) for p in (batch, single))
    assert ia == ib
    assert (batch / "trajectory.tum").read_text() == (single / "trajectory.tum").read_text()


@pytest.mark.parametrize(("method", "n_runs", "options"),
                         [("map", 2, {}), ("svn", 1, {"particles": 10, "max_frames": 5}),
                          ("map", 1, {"max_frames": 4, "spread_scale": "SCALE"})])
def test_batch_equals_single_track_runs(runs: list[Path], scheduler: str, tmp_path: Path, method: str, n_runs: int,
                                        options: dict) -> None:
    if options.get("spread_scale") == "SCALE":  # a calibrate-spread file: batch passes it on like track
        options = {**options, "spread_scale": SpreadScale({"map": MethodScale(2.0, 3.0)}).save(tmp_path / "s.json")}
    out = batch_track(runs[:n_runs], method, tmp_path / "batch", scheduler=scheduler, seed=3, **options)
    assert out == [tmp_path / "batch" / "run", tmp_path / "batch" / "run-2"][:n_runs]
    for run, res in zip(runs, out, strict=False):
        single = track_recording(run, method=method, out=tmp_path / f"single-{res.name}", seed=3, progress=False,
                                 **options)
        _assert_same_result(res, single)
    assert expand_result_dirs([tmp_path / "batch"]) == out


def test_a_malformed_run_does_not_lose_the_others(runs: list[Path], scheduler: str, tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "recording.json").write_text("{}")
    (bad / "frames.csv").write_text("frame,t_s\n0,0.0\n")
    with pytest.raises(BatchError) as ei:
        batch_track([bad, runs[0]], "map", tmp_path / "out", scheduler=scheduler)
    err = ei.value
    assert list(err.failures) == [bad.absolute()] and "recording.json" in err.failures[bad.absolute()]
    assert "\n" not in err.failures[bad.absolute()] and "1 of 2 runs failed" in str(err)
    assert list(err.results.values()) == [tmp_path / "out" / "run"]
    assert (tmp_path / "out" / "run" / "estimates.csv").exists()
    # a non-empty output directory is refused before anything runs
    with pytest.raises(InputError, match="--out is not empty"):
        run_batch(runs, "map", tmp_path / "out", scheduler=scheduler)
    # ... unless the user asks for it: the results are replaced, the same as a fresh run
    before = (tmp_path / "out" / "run" / "trajectory.tum").read_bytes()
    again = run_batch([runs[0]], "map", tmp_path / "out", scheduler=scheduler, overwrite=True)
    assert not again.failures and (tmp_path / "out" / "run" / "trajectory.tum").read_bytes() == before


def test_bad_arguments_fail_before_a_cluster_starts(runs: list[Path], tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown method"):
        batch_track(runs, "nope", tmp_path / "o")
    with pytest.raises(InputError, match="given twice"):
        batch_track([runs[0], runs[0]], "map", tmp_path / "o")
    with pytest.raises(InputError, match="file not found"):
        batch_track(runs, "map", tmp_path / "o", noise_file=tmp_path / "missing.json")
    scale = SpreadScale({"svn": MethodScale(2.0, 3.0)}).save(tmp_path / "svn-only.json")
    with pytest.raises(InputError, match="no scale for method 'map'"):
        batch_track(runs, "map", tmp_path / "o", spread_scale=scale)
    assert not (tmp_path / "o").exists()
    assert result_dir_names([Path("x/run"), Path("y/run"), Path("run-2"), Path("z/run")]) == \
        ["run", "run-2", "run-2-2", "run-3"]


def test_cli_batch_on_a_local_cluster_then_evaluate(runs: list[Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing-run"
    out = tmp_path / "cli"
    code = main(["batch", str(runs[0]), str(missing), "--method", "map", "--workers", "1", "--out", str(out)])
    assert code == 2
    captured = capsys.readouterr()
    err_lines = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert len(err_lines) == 1 and "missing-run" in err_lines[0] and "Traceback" not in captured.err
    assert "1 of 2 runs tracked" in captured.out
    report = tmp_path / "report"
    assert main(["evaluate", str(out), "--out", str(report)]) == 0
    with open(report / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["method"] for r in rows] == ["map"] and rows[0]["frames"] == str(FRAMES)


def test_a_run_failing_before_it_writes_leaves_no_directory_and_evaluate_names_a_skipped_one(
        runs: list[Path], scheduler: str, tmp_path: Path) -> None:
    from pinpoint_fg.eval.report import evaluate_results

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "recording.json").write_text("{}")
    (bad / "frames.csv").write_text("frame,t_s\n0,0.0\n")
    out = tmp_path / "out"
    outcome = run_batch([bad, runs[0]], "map", out, scheduler=scheduler)
    assert list(outcome.failures) == [bad.absolute()]
    # was: an empty out/bad, which evaluate then skipped without a word
    assert sorted(p.name for p in out.iterdir()) == ["run"]
    (out / "bad").mkdir()  # what an older batch left, or anything a user put beside the results
    (out / "notes").mkdir()
    (out / "notes" / "todo.txt").write_text("re-run bad")
    (out / ".cache").mkdir()  # hidden: not named
    report = evaluate_results([out], out=tmp_path / "ev", ambiguity=False, figures=False)
    assert [ev.result.root for ev in report.evaluations] == [out / "run"]
    notes = [ln for ln in report.text.splitlines() if ln.startswith("note: skipped")]
    assert notes == [f"note: skipped {out / 'bad'}: empty, not a result (what a batch run that failed before "
                     f"writing anything left), beside the results in {out}",
                     f"note: skipped {out / 'notes'}: not a result (no result.json), beside the results in {out}"]


def test_an_unreachable_scheduler_is_one_line_and_leaves_no_out_directory(
        runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "new" / "results"
    assert main(["batch", str(runs[0]), "--method", "map", "--scheduler", "tcp://127.0.0.1:1",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "option '--scheduler'" in err[0] and "cannot connect" in err[0]
    assert not (tmp_path / "new").exists()  # the directories batch created are removed again


def test_batch_takes_tracks_robust_losses_and_checks_the_noise_files_distance_once(
        runs: list[Path], scheduler: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "robust"
    assert main(["batch", str(runs[0]), "--method", "map", "--robust", "conic=huber:2", "--scheduler", scheduler,
                 "--out", str(out)]) == 0
    settings = json.loads((out / "run" / "result.json").read_text())["settings"]
    assert settings["robust"] == "conic=huber:2"
    from pinpoint_fg.noise import NoiseConfig

    noise = tmp_path / "geometric.json"
    NoiseConfig().with_conic_distance("geometric").save(noise)
    capsys.readouterr()
    assert main(["batch", str(runs[0]), "--method", "map", "--noise", str(noise), "--conic-distance", "sampson",
                 "--scheduler", scheduler, "--out", str(tmp_path / "refused")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "geometric.json" in err[0] and "conic_distance" in err[0], err
    assert not (tmp_path / "refused").exists()
