"""The ablation runner: job matrix, parallel tracking, Table III."""

from __future__ import annotations

from pathlib import Path

import pytest

import pinpoint_fg.experiments.ablate as ablate_mod
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.report import ABLATION_VARIANTS
from pinpoint_fg.experiments.ablate import AblationJob, ablate, ablation_jobs, run_jobs
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.sim.scenarios import simulate

SMALL = tuple(v for v in ABLATION_VARIANTS if v[0] in ("full", "no-dense", "svgd"))


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("normal", 4, seed=2, out=tmp_path_factory.mktemp("abl") / "run")


def test_job_matrix_is_table_iii(run: Path, tmp_path: Path) -> None:
    twin = simulate("normal", 2, seed=2, out=tmp_path / "twin")  # same recording name as `run`
    jobs = ablation_jobs([run, twin], tmp_path / "out", frames=3)
    assert len(jobs) == 2 * len(ABLATION_VARIANTS) == 18
    first = jobs[: len(ABLATION_VARIANTS)]
    assert [j.variant for j in first] == [v[0] for v in ABLATION_VARIANTS]
    assert {j.out for j in first} == {str(tmp_path / "out" / "normal-02" / v[0]) for v in ABLATION_VARIANTS}
    assert {Path(j.out).parent.name for j in jobs[len(ABLATION_VARIANTS):]} == {"normal-02-2"}
    by = {j.variant: j for j in first}
    assert by["no-image"].disable == ("dense", "sparse") and by["no-image"].method == "svn"
    assert by["one-keypoint"].disable == ("tip",)
    assert by["no-robot-no-motion"].disable == ("grasp-position", "grasp-perpendicular", "motion")
    assert by["svgd"].method == "svgd" and by["svgd"].disable == ()
    assert all(j.max_frames == 3 for j in jobs)
    with pytest.raises(InputError):
        ablation_jobs([run], tmp_path / "out", frames=0)
    with pytest.raises(InputError):
        ablation_jobs([tmp_path / "missing"], tmp_path / "out")


def test_failed_jobs_are_reported_and_all_failing_raises(run: Path, tmp_path: Path) -> None:
    good = AblationJob(str(run), "full", "map", (), str(tmp_path / "good"), 2)
    bad = AblationJob(str(tmp_path / "missing"), "full", "map", (), str(tmp_path / "bad"), 2)
    done, failures = run_jobs([good, bad], workers=1, show_progress=False)
    assert done == [str(tmp_path / "good")] and len(failures) == 1 and "missing" in failures[0]
    assert len(read_result(tmp_path / "good")) == 2
    with pytest.raises(InputError):
        run_jobs([bad], workers=1, show_progress=False)


def test_ablate_in_worker_processes(run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ablate_mod, "ABLATION_VARIANTS", SMALL)
    table = ablate([run], tmp_path / "out", jobs=2, frames=2)
    lines = table.splitlines()
    assert lines[0] == "### normal-02"
    titles = [ln.split("|")[1].strip() for ln in lines[4:]]
    assert titles == ["All (full model)", "No dense image", "SVGD (no Hessian)"]
    for variant in ("full", "no-dense", "svgd"):
        res = read_result(tmp_path / "out" / "normal-02" / variant)
        assert len(res) == 2 and res.complete
    assert read_result(tmp_path / "out" / "normal-02" / "no-dense").info["settings"]["disabled"] == ["dense"]
    assert (tmp_path / "out" / "summary.csv").exists()
    assert (tmp_path / "out" / "ablation_normal-02.png").exists()


def test_cli_ablate_in_process(run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                               capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setattr(ablate_mod, "ABLATION_VARIANTS", SMALL[:2])
    code = main(["ablate", str(run), "--out", str(tmp_path / "o"), "--jobs", "1", "--frames", "1"])
    assert code == 0
    assert "No dense image" in capsys.readouterr().out
