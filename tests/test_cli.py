"""Smoke tests of every ``pinpoint-fg`` subcommand on short simulated runs, and of bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.experiments.benchmark import BENCH_SCENARIOS
from pinpoint_fg.experiments.coverage import CLEAR_SCENARIOS
from pinpoint_fg.io.result.reader import read_modes, read_result


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli")
    out = {}
    for sc in ("normal", "calibration"):
        out[sc] = root / sc
        assert main(["simulate", "--scenario", sc, "--frames", "12", "--seed", "2", "--out", str(out[sc])]) == 0
    return out


def test_validate_ok_and_bad(runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(runs["normal"])]) == 0
    assert "frames" in capsys.readouterr().out
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "recording.json").write_text("{}")
    (bad / "frames.csv").write_text("frame,t_s\n0,abc\n")
    assert main(["validate", str(bad)]) != 0
    err = capsys.readouterr().err
    assert "recording.json" in err and "Traceback" not in err


@pytest.mark.parametrize("method", ["svn", "svgd", "pf", "map"])
def test_track_every_method(runs: dict[str, Path], tmp_path: Path, method: str) -> None:
    out = tmp_path / method
    args = ["track", str(runs["normal"]), "--method", method, "--out", str(out), "--seed", "1"]
    if method == "pf":
        args += ["--particles", "300"]
    assert main(args) == 0
    res = read_result(out)
    assert len(res.frame) == 12 and np.all(np.isfinite(res.cam_T_needle))
    assert (out / "trajectory.tum").read_text().count("\n") == 12
    modes = read_modes(out)  # every method writes its posterior modes
    assert modes.frames.tolist() == res.frame.tolist()
    W = modes.weights_at(res.frame)
    assert np.allclose(W.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_array_equal(res.extra["bimodal_modes"], (W[:, 1] >= 0.1).astype(float))
    if method == "map":
        assert np.all(W[:, 0] == 1.0)
    u = np.stack([res.extra[c] for c in ("weak_wx", "weak_wy", "weak_wz", "weak_vx", "weak_vy", "weak_vz")], 1)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, rtol=1e-9)
    assert np.all(res.extra["weak_sigma"] > 0)


def test_track_with_window_disable_and_noise_file(runs: dict[str, Path], tmp_path: Path) -> None:
    noise = tmp_path / "noise.json"
    assert main(["calibrate", str(runs["calibration"]), "--out", str(noise)]) == 0
    assert json.loads(noise.read_text())["format"] == "pinpoint-noise"
    out = tmp_path / "w3"
    assert main(["track", str(runs["normal"]), "--window", "3", "--disable", "dense,tip", "--noise", str(noise),
                 "--particles", "20", "--out", str(out)]) == 0
    assert (out / "smoothed.csv").exists()
    assert read_result(out).smoothed is not None


def test_track_bad_arguments_give_clear_errors(runs: dict[str, Path], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["track", str(runs["normal"]), "--disable", "nonsense", "--out", str(tmp_path / "x")])
    assert main(["track", str(tmp_path / "missing"), "--out", str(tmp_path / "y")]) == 2
    assert main(["track", str(runs["normal"]), "--noise", str(tmp_path / "none.json"),
                 "--out", str(tmp_path / "z")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_evaluate_and_ablate(runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b = tmp_path / "svn", tmp_path / "map"
    assert main(["track", str(runs["normal"]), "--method", "svn", "--particles", "20", "--out", str(a)]) == 0
    assert main(["track", str(runs["normal"]), "--method", "map", "--out", str(b)]) == 0
    rep = tmp_path / "report"
    capsys.readouterr()
    assert main(["evaluate", str(a), str(b), "--out", str(rep)]) == 0
    printed = capsys.readouterr().out
    assert "partial:" not in printed  # both results cover the whole run
    assert "no modes.csv" not in printed  # every tracker writes its modes
    assert "; no reference\n" in printed
    assert "(no reference: neither an mht result of that recording among the inputs nor a --reference of it)" in printed
    assert "(0 / 0 frames)" not in printed  # rates against no reference are not printed as if measured
    assert (rep / "summary.csv").exists() and (rep / "tables.md").exists()
    assert list(rep.glob("*.png"))
    (a / "modes.csv").unlink()  # the modes are then the particles': said, not silent
    assert main(["evaluate", str(a), str(b), "--out", str(rep), "--overwrite"]) == 0
    notes = [ln for ln in capsys.readouterr().out.splitlines() if "no modes.csv" in ln]
    assert notes == [f"note: {a} has no modes.csv: its modes are recomputed from its particles"]
    abl = tmp_path / "ablation"
    assert main(["ablate", str(runs["normal"]), "--out", str(abl), "--jobs", "2", "--frames", "6"]) == 0
    tables = (abl / "tables.md").read_text()
    assert "Table III" in tables and "SVGD" in tables, tables[:400]


def test_groundtruth_command(tmp_path: Path) -> None:
    from pinpoint_fg.groundtruth import write_board_to_needle

    run = tmp_path / "img"
    assert main(["simulate", "--scenario", "slow", "--frames", "4", "--seed", "1", "--out", str(run), "--images"]) == 0
    b2n = tmp_path / "b2n.json"
    write_board_to_needle(b2n)
    assert main(["groundtruth", str(run), "--board-to-needle", str(b2n)]) == 0


@pytest.mark.slow
def test_demo_and_benchmark_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--frames", "8", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "accuracy floor" in out and "svn" in out and "map" in out
    assert (tmp_path / "demo" / "report" / "summary.csv").exists()
    assert main(["benchmark", "--frames", "6", "--out", str(tmp_path / "bench"), "--jobs", "2",
                 "--unseen-seeds", "3", "--held-out-geometry"]) == 0
    unseen = (tmp_path / "bench" / "unseen.txt").read_text()
    per_method, unseen_ratios = unseen.split("\n\n")
    assert per_method.count("\n") + 1 == 2 + len(BENCH_SCENARIOS) * 4 and " pf " in per_method
    assert "trans/mht" in unseen_ratios and unseen_ratios.strip().count("\n") == 1 + len(BENCH_SCENARIOS)
    assert (tmp_path / "bench" / "seed-3" / "results" / "snapshots" / "mht" / "estimates.csv").exists()
    # the held-out camera and needle, on the benchmark's seed and the unseen one, laid out as unseen.txt
    held = (tmp_path / "bench" / "held_out.txt").read_text()
    held_methods, held_ratios = held.split("\n\n")
    assert held.startswith("Held-out camera and needle, seeds 1, 3: means over the seeds")
    assert held_methods.count("\n") + 1 == 2 + len(BENCH_SCENARIOS) * 4
    assert held_ratios.strip().count("\n") == 1 + len(BENCH_SCENARIOS)
    held_rows = (tmp_path / "bench" / "held_out.csv").read_text().strip().splitlines()
    assert len(held_rows) == 1 + 2 * len(BENCH_SCENARIOS) * 4
    for k in (1, 3):
        doc = json.loads((tmp_path / "bench" / f"held-out-seed-{k}" / "runs" / f"drive-0{k}" / "recording.json")
                         .read_text())
        assert doc["camera"]["width"] == 1280 and doc["needle"]["tip_angle_rad"] == pytest.approx(np.pi)
    cover = (tmp_path / "bench" / "coverage.txt").read_text()  # fitted on seed 3, scored on seed 1
    cover_rows = (tmp_path / "bench" / "coverage.csv").read_text().strip().splitlines()[1:]
    assert cover.startswith("q95 coverage")
    assert len(cover_rows) == (15 if "factors (kappa" in cover else 0)
    assert all(r.split(",")[:2] in ([sc, "1"] for sc in CLEAR_SCENARIOS) for r in cover_rows)
    text = (tmp_path / "bench" / "benchmark.txt").read_text()
    table, ratios, weights = text.split("\n\n")
    assert "median vs pf" in table and "cover t/r" in table and " mht " in table
    assert table.count("\n") + 1 == 1 + len(BENCH_SCENARIOS) * 5
    assert "trans/map" in ratios and ratios.strip().count("\n") == 1 + len(BENCH_SCENARIOS)
    assert "minor w / truth" in weights and weights.strip().count("\n") == 2 + len(BENCH_SCENARIOS)
    assert "symmetric" in text and "snapshots" in text
    # the symmetric run asks to be tracked without the grasp factors; the benchmark honours it
    for method, expected in (("svn", ["grasp-position", "grasp-perpendicular"]), ("map", ["grasp-position",
                                                                                        "grasp-perpendicular"])):
        settings = json.loads((tmp_path / "bench" / "results" / "symmetric" / method / "result.json").read_text())
        assert sorted(settings["settings"]["disabled"]) == sorted(expected)
    settings = json.loads((tmp_path / "bench" / "results" / "normal" / "svn" / "result.json").read_text())
    assert settings["settings"]["disabled"] == []
    lat = json.loads((tmp_path / "bench" / "latency.json").read_text())
    assert set(lat["scenarios"]) == set(BENCH_SCENARIOS)
    # latency is measured on the model the accuracy table scores: symmetric without its grasp factors
    assert sorted(lat["scenarios"]["symmetric"]["disabled"]) == ["grasp-perpendicular", "grasp-position"]
    assert lat["scenarios"]["normal"]["disabled"] == []
    grid = {(r["particles"], r["window"]) for r in lat["grid"]}
    assert grid == {(n, w) for n in (10, 25, 50, 100) for w in (1, 3, 5)}
    normal = lat["scenarios"]["normal"]["methods"]
    assert normal["pf"]["ratio_median_vs_pf"] == 1.0 and normal["svn"]["ratio_median_vs_map"] > 0
    assert lat["track"]["ratio"] > 0 and (tmp_path / "bench" / "latency_vs_n_l.png").stat().st_size > 0
    # track's wall / steps is the median of three runs, each kept
    assert len(lat["track"]["ratios"]) == 3 and lat["track"]["ratio"] == sorted(lat["track"]["ratios"])[1]
    assert all((tmp_path / "bench" / "track-svn" / f"repeat-{k}" / "estimates.csv").is_file() for k in (1, 2, 3))
    # with the CPU of its two processes and the ratio that work bounds it to
    assert lat["track"]["cpu_worker_s"] > 0 and lat["track"]["cpu_bound"] > 0
    assert "spread perfectly over 2 cores" in (tmp_path / "bench" / "latency.txt").read_text()
    assert "SVN cost vs particles N and window L" in capsys.readouterr().out


def test_simulate_new_scenarios_and_suggested_disable(tmp_path: Path) -> None:
    from pinpoint_fg.errors import InputError
    from pinpoint_fg.io.recording import read_recording
    from pinpoint_fg.track import suggested_disable

    for scenario in ("symmetric", "drive", "kinfault", "snapshots"):
        assert main(["simulate", "--scenario", scenario, "--frames", "4", "--out", str(tmp_path / scenario)]) == 0
    assert suggested_disable(tmp_path / "symmetric") == ("grasp-position", "grasp-perpendicular")
    assert suggested_disable(tmp_path / "drive") == ()
    # a Recording already read gives the same answer without reading the run again
    assert suggested_disable(read_recording(tmp_path / "symmetric")) == ("grasp-position", "grasp-perpendicular")
    doc = json.loads((tmp_path / "drive" / "recording.json").read_text())
    doc["suggested_disable"] = ["grasp"]
    (tmp_path / "drive" / "recording.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="suggested_disable"):
        suggested_disable(tmp_path / "drive")


def test_simulate_held_out_geometry_and_track_it(tmp_path: Path) -> None:
    """`simulate --geometry held-out` writes a run with the other camera and 1/2-circle needle; `track` reads them
    from the recording and tracks it as well as a run of the paper's geometry."""
    from pinpoint_fg import cli
    from pinpoint_fg.eval.metrics import pose_errors
    from pinpoint_fg.io.recording import read_recording
    from pinpoint_fg.io.result.reader import read_result
    from pinpoint_fg.sim.config import GEOMETRIES, held_out_camera

    assert cli.GEOMETRIES == GEOMETRIES
    run = tmp_path / "held-out"
    assert main(["simulate", "--scenario", "normal", "--frames", "10", "--seed", "4", "--geometry", "held-out",
                 "--mask-spurs", "0.5", "--out", str(run)]) == 0
    rec = read_recording(run)
    assert rec.info.camera == held_out_camera()
    assert rec.info.extra["simulator"]["config"]["mask_spur_prob"] == 0.5  # both options apply
    assert main(["track", str(run), "--method", "svn", "--out", str(tmp_path / "svn")]) == 0
    res = read_result(tmp_path / "svn")
    err = pose_errors(res.cam_T_needle, np.stack([f.cam_T_needle_gt for f in rec.frames]))
    # the held-out runs' full-length SVN errors are ~0.2 mm / 2 deg (README, Results); 10 frames from a cold start
    assert np.mean(err.trans_m) < 1.5e-3 and np.degrees(np.mean(err.rot_rad)) < 10.0, (err.trans_m, err.rot_rad)
    with pytest.raises(SystemExit) as exc:  # an unknown geometry is a usage error (argparse: exit 2)
        main(["simulate", "--geometry", "fisheye", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2 and not (tmp_path / "x").exists()


def test_output_to_a_closed_pipe_is_not_a_traceback(runs: dict[str, Path]) -> None:
    """`pinpoint-fg validate RUN | head -0`: the reader is gone before we write; exit 0, nothing on stderr."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "pinpoint_fg.cli", "validate", str(runs["normal"])],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # like `head` exiting at once
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0
    assert "Traceback" not in err and "BrokenPipeError" not in err


def test_keypoints_outside_the_image_are_ignored_with_a_note(runs: dict[str, Path], tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Tip cells at u = -5000 (valid format: within 10 image sizes) give the poses of the same run with those
    cells empty, and `validate` / `track` say so in one note line each."""
    import csv
    import shutil

    def edited(name: str, value: str) -> Path:
        run = tmp_path / name
        shutil.copytree(runs["normal"], run)
        rows = list(csv.reader((run / "frames.csv").open()))
        u, v = rows[0].index("tip_u_px"), rows[0].index("tip_v_px")
        changed = 0
        for row in rows[1:]:
            if row[u] and changed < 4:
                row[u], row[v] = (value, row[v]) if value else ("", "")
                changed += 1
        assert changed == 4
        with (run / "frames.csv").open("w", newline="") as f:
            csv.writer(f).writerows(rows)
        return run

    far, empty = edited("far", "-5000"), edited("empty", "")
    capsys.readouterr()
    assert main(["validate", str(far)]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(notes) == 1 and notes[0].startswith("note: ") and "4 tip/tail keypoint(s)" in notes[0]
    poses = {}
    for run in (far, empty):
        out = tmp_path / f"out-{run.name}"
        assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 0
        err = capsys.readouterr().err
        assert ("outside the" in err) == (run is far)
        rows = list(csv.DictReader((out / "estimates.csv").open()))
        poses[run.name] = [[r[k] for k in ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")] for r in rows]
    assert poses["far"] == poses["empty"]


def test_the_command_lines_backbone_distances_are_the_libraries() -> None:
    from pinpoint_fg import cli
    from pinpoint_fg.noise import CONIC_DISTANCES

    assert cli._CONIC_DISTANCES == CONIC_DISTANCES
    for command in ("track", "batch", "calibrate"):
        with pytest.raises(SystemExit):
            main([command, "--conic-distance", "euclid", "x", "--out", "y"])


def test_simulate_overwrite_names_the_earlier_runs_leftover_pngs(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """--overwrite replaces what simulate writes and leaves other files, as everywhere; masks of a longer earlier
    run that no row names are said, not silently left (nor deleted)."""
    out = tmp_path / "run"
    assert main(["simulate", "--frames", "12", "--seed", "2", "--out", str(out)]) == 0
    before = sorted(p.name for p in (out / "masks").glob("*.png"))
    assert "note:" not in capsys.readouterr().err
    assert main(["simulate", "--frames", "12", "--seed", "2", "--out", str(out), "--overwrite"]) == 0
    assert "note:" not in capsys.readouterr().err  # the same run again: every PNG is named
    assert main(["simulate", "--frames", "4", "--seed", "2", "--out", str(out), "--overwrite"]) == 0
    err = capsys.readouterr().err
    with open(out / "frames.csv", newline="") as fh:
        named = {row["mask"] for row in csv.DictReader(fh) if row["mask"]}
    stale = len(before) - len(named)
    assert stale > 0 and sorted(p.name for p in (out / "masks").glob("*.png")) == before  # nothing deleted
    assert err.count("note:") == 1 and f"holds {stale} PNG file(s) of an earlier run" in err, err
