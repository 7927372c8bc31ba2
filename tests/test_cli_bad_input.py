"""A new user's bad input, end to end: every case here was a traceback, a wrong exit code or a silently wrong
number before its fix (the audit of this file's commit). Each must now give exit code 2 and one line naming
the file and the key (or a usage error naming the flag) before any work starts."""

from __future__ import annotations

import copy
import errno
import json
import os
import shutil
import warnings
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from factors.robust import RobustLoss
from pinpoint_fg import track as track_module
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.spread_calibration import scale_quantile
from pinpoint_fg.groundtruth import read_board_to_needle, write_board_to_needle
from pinpoint_fg.io.recording.png import decode_image
from pinpoint_fg.io.recording.validator import validate_run
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.io.spread_scale import SpreadScale, recorded_scale
from pinpoint_fg.noise import NoiseConfig


def _simulated(tmp_path_factory: pytest.TempPathFactory, where: str, scenario: str, frames: int, seed: int) -> Path:
    """A simulated run with images, made through the CLI (the module fixtures' runs)."""
    out = tmp_path_factory.mktemp(where) / "run"
    assert main(["simulate", "--scenario", scenario, "--frames", str(frames), "--seed", str(seed), "--images",
                 "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _simulated(tmp_path_factory, "bad-input", "normal", 8, 1)


def _one_error_line(err: str) -> str:
    lines = [s for s in err.splitlines() if s.strip()]
    assert "Traceback" not in err
    assert lines and lines[-1].startswith(("error:", "pinpoint-fg")), err
    return lines[-1]


# --- counts and seeds: refused by the parser (a usage error, exit 2), before any work --------------------

BAD_ARGS = [
    (["simulate", "--frames", "0"], "--frames"),          # was ValueError traceback from the simulator
    (["simulate", "--frames", "-3"], "--frames"),
    (["simulate", "--seed", "-1"], "--seed"),              # was ValueError traceback
    (["simulate", "--seed", str(2**63)], "--seed"),        # was accepted: recording.json then unreadable
    (["track", "RUN", "--particles", "0"], "--particles"),  # was ValueError traceback from tracker_config
    (["track", "RUN", "--window", "0"], "--window"),
    (["track", "RUN", "--seed", "-1"], "--seed"),          # was NumPy's "expected non-negative integer" traceback
    (["track", "RUN", "--seed", str(2**64)], "--seed"),    # was accepted: result.json then unreadable
    (["batch", "RUN", "--particles", "-1"], "--particles"),
    (["batch", "RUN", "--seed", "-1"], "--seed"),
    (["demo", "--frames", "0"], "--frames"),
    (["benchmark", "--frames", "0"], "--frames"),
    (["benchmark", "--unseen-seeds", "-1"], "--unseen-seeds"),  # was refused only after the main benchmark
    (["benchmark", "--grid-frames", "0"], "--grid-frames"),
    (["ablate", "RUN", "--frames", "0"], "--frames"),
    (["import-bop", "SCENE", "--model", "M.ply", "--obj-id", "1", "--seed", "-1"], "--seed"),
    (["track", "RUN", "--robust", "conic=cauchy:1e308"], "--robust"),  # was NaN poses -> ValueError traceback
    (["demo", "--jobs", "0"], "--jobs"),                   # was accepted (and run serially)
    (["ablate", "RUN", "--jobs", "-2"], "--jobs"),
    (["benchmark", "--jobs", "100000"], "--jobs"),         # was accepted: one process per job
]


@pytest.mark.parametrize(("argv", "flag"), BAD_ARGS, ids=[" ".join(a) for a, _ in BAD_ARGS])
def test_bad_counts_seeds_and_thresholds_are_usage_errors(argv: list[str], flag: str, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main([*(str(tmp_path / a) if a in ("RUN", "SCENE") else a for a in argv), "--out", str(out)])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert flag in line
    assert not out.exists()  # refused before any work


def test_robust_threshold_is_bounded() -> None:
    with pytest.raises(ValueError, match="<= 1e"):
        RobustLoss("cauchy", 1e308)
    assert RobustLoss("cauchy", 1e6).k == 1e6  # the largest accepted


# --- noise files -----------------------------------------------------------------------------------------

def _noise_doc() -> dict:
    return copy.deepcopy(NoiseConfig().to_json())


def _tip(doc: dict) -> dict:
    return doc["residuals"]["tip"]


NOISE_CASES = {
    # a traceback before (NaN poses / overflow in the maths)
    "variance 1e-300": lambda d: _tip(d).update(cov=[[1e-300, 0.0], [0.0, 1e-300]]),
    "mean 1e308": lambda d: _tip(d).update(mean=[1e308, 0.0]),
    "robust k 1e308": lambda d: d["robust"].update(conic={"loss": "cauchy", "k": 1e308}),
    # silently accepted before
    "variance 1e308": lambda d: _tip(d).update(cov=[[1e308, 0.0], [0.0, 1e308]]),
    "asymmetric cov": lambda d: _tip(d).update(cov=[[1.0, 0.9], [-0.9, 1.0]]),  # was symmetrised to I
    "boolean in cov": lambda d: _tip(d).update(cov=[[True, 0.0], [0.0, 1.0]]),
    "fractional count": lambda d: _tip(d).update(count=2.5),
    "negative count": lambda d: _tip(d).update(count=-5),
    "string k": lambda d: d["robust"].update(conic={"loss": "cauchy", "k": "3"}),
}


@pytest.mark.parametrize("case", list(NOISE_CASES))
def test_noise_file_refuses_values_it_used_to_take(case: str, tmp_path: Path) -> None:
    doc = _noise_doc()
    NOISE_CASES[case](doc)
    path = tmp_path / "noise.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as exc:
        NoiseConfig.load(path)
    assert str(exc.value).startswith(str(path)) and ("residuals.tip" in str(exc.value) or "robust.conic" in
                                                      str(exc.value))
    assert str(exc.value).count(str(path)) == 1


def test_noise_file_keeps_accepting_what_calibrate_writes(tmp_path: Path) -> None:
    path = tmp_path / "noise.json"
    NoiseConfig().save(path)
    assert NoiseConfig.load(path).residuals["tip"].count == 0
    doc = _noise_doc()
    _tip(doc).update(cov=[[1.0, 0.3], [0.3 + 1e-17, 2.0]], count=12)  # rounding asymmetry is fine
    path.write_text(json.dumps(doc))
    assert NoiseConfig.load(path).residuals["tip"].count == 12


def test_track_with_a_bad_noise_file_is_one_line(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = _noise_doc()
    _tip(doc).update(cov=[[1e-300, 0.0], [0.0, 1e-300]])
    path = tmp_path / "noise.json"
    path.write_text(json.dumps(doc))
    assert main(["track", str(run), "--method", "map", "--noise", str(path), "--out", str(tmp_path / "r")]) == 2
    assert "residuals.tip" in _one_error_line(capsys.readouterr().err)


# --- spread-scale files ---------------------------------------------------------------------------------

def _scale_doc(kappa: float) -> dict:
    return {"format": "pinpoint-spread-scale", "version": 1, "level": 0.95, "mode_gate_rad": 0.5,
            "methods": {"map": {"kappa_trans": kappa, "kappa_rot": 1.0}}}


@pytest.mark.parametrize("kappa", [1e308, 1e-308])
def test_spread_scale_factor_is_bounded(kappa: float, run: Path, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "scale.json"
    path.write_text(json.dumps(_scale_doc(kappa)))
    with pytest.raises(InputError, match="methods.map.kappa_trans"):
        SpreadScale.load(path)
    with pytest.raises(InputError, match="settings.spread_scale.kappa_trans"):
        recorded_scale({"spread_scale": {"kappa_trans": kappa, "kappa_rot": 1.0}}, tmp_path / "result.json")
    # 1e308 was numpy's "Eigenvalues did not converge" traceback in track
    assert main(["track", str(run), "--method", "map", "--spread-scale", str(path), "--out", str(tmp_path / "r")]) == 2
    assert "kappa_trans" in _one_error_line(capsys.readouterr().err)


def test_spread_fit_refuses_a_factor_its_file_could_not_hold() -> None:
    # q95 of ~1e-18 with millimetre errors (a one-particle set) made kappa ~1e15, written and then unreadable
    with pytest.raises(InputError, match="outside"):
        scale_quantile(np.full(10, 1e-3), np.full(10, 3.5e-18))
    assert scale_quantile(np.full(10, 1e-3), np.full(10, 1e-3)) == pytest.approx(1.0)


# --- images --------------------------------------------------------------------------------------------

def test_zero_byte_camera_image_is_a_located_error(run: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "run"
    shutil.copytree(run, bad)
    (bad / "images" / "000003.png").write_bytes(b"")  # cv2.imdecode raised cv2.error on the empty buffer
    _, errors = validate_run(bad)
    assert len(errors) == 1 and "000003.png" in str(errors[0]) and "empty" in str(errors[0])
    with pytest.raises(ValueError, match="empty"):
        decode_image(bad / "images" / "000003.png", None, None, png_only=False)
    assert main(["track", str(bad), "--method", "map", "--out", str(tmp_path / "r")]) == 2
    assert "column 'image'" in _one_error_line(capsys.readouterr().err)


def _corrupt_under_valid_crcs(png: Path) -> None:
    """Replace the PNG's image data by a sound zlib stream of the wrong length, with valid CRCs: only inflating
    the data finds it."""
    data = png.read_bytes()
    i = data.index(b"IDAT") - 4
    n = int.from_bytes(data[i : i + 4], "big")
    payload = zlib.compress(b"\x00" * 10)
    chunk = b"IDAT" + payload
    png.write_bytes(data[:i] + len(payload).to_bytes(4, "big") + chunk + zlib.crc32(chunk).to_bytes(4, "big")
                    + data[i + 12 + n :])


def test_track_reports_mask_data_corrupt_under_valid_crcs_at_its_frame(run: Path, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """``track`` reads without inflating masks (every decode inflates first): the corrupt data is still one located
    line, exit 2, raised at its frame with the frames before it on disk; ``validate`` finds it before any work."""
    bad = tmp_path / "run"
    shutil.copytree(run, bad)
    png = bad / "masks" / "000006.png"
    _corrupt_under_valid_crcs(png)
    _, errors = validate_run(bad)
    assert len(errors) == 1 and "000006.png" in str(errors[0]) and "image data" in str(errors[0])
    assert not validate_run(bad, inflate=False)[1]
    out = tmp_path / "r"
    assert main(["track", str(bad), "--method", "map", "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "frames.csv" in line and "row 7" in line and "column 'mask'" in line and "000006.png" in line
    assert read_result(out).frame.tolist() == [0, 1, 2, 3, 4, 5]


# --- groundtruth ------------------------------------------------------------------------------------------

def test_groundtruth_refuses_a_mount_that_would_break_the_run(run: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    board = tmp_path / "b2n.json"
    write_board_to_needle(board)
    doc = json.loads(board.read_text())
    doc["board_T_needle"][0][3] = 1e300
    board.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="board_T_needle"):
        read_board_to_needle(board)
    copy_run = tmp_path / "run"
    shutil.copytree(run, copy_run)
    before = (copy_run / "frames.csv").read_bytes()
    # before: exit 0, and every gt_* cell rewritten to ~1e300, so the run no longer validated
    assert main(["groundtruth", str(copy_run), "--board-to-needle", str(board)]) == 2
    assert "board_T_needle" in _one_error_line(capsys.readouterr().err)
    assert (copy_run / "frames.csv").read_bytes() == before
    assert not validate_run(copy_run)[1]


# --- a tracker's numerical breakdown -----------------------------------------------------------------------

class _Breaks:
    """The real map tracker until frame 3, then a failure of the kind seen on degenerate input."""

    def __init__(self, inner, how: str) -> None:
        self.inner, self.how = inner, how

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def step(self, obs):
        est = self.inner.step(obs)
        if obs.frame < 3:
            return est
        if self.how == "gtsam":  # what GTSAM raised with a principal point 10 images off (cx = -10000)
            raise RuntimeError("\nIndeterminate linear system detected while working near variable\n9 (Symbol: 9).")
        if self.how == "diverged":  # a pose 10 000 km away: written, it made a result its own reader refuses
            far = np.array(est.cam_T_needle, dtype=float)
            far[0, 3] = 1e7
            return replace(est, cam_T_needle=far)
        return replace(est, log_posterior=np.full_like(np.asarray(est.log_posterior, dtype=float), np.inf))


@pytest.mark.parametrize("how", ["gtsam", "nonfinite", "diverged"])
def test_tracker_breakdown_is_one_line_and_keeps_finished_frames(how: str, run: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    real = track_module.make_tracker
    monkeypatch.setattr(track_module, "make_tracker", lambda method, config: _Breaks(real(method, config), how))
    out = tmp_path / "r"
    assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "frames.csv" in line and "map failed" in line
    assert read_result(out).frame.tolist() == [0, 1, 2]
    # evaluating the frames that were kept says the result is partial (was: figures as if complete)
    assert main(["evaluate", str(out), "--out", str(tmp_path / "ev")]) == 0
    printed = capsys.readouterr().out
    assert "partial: map on" in printed and "3 of 8 frames, stopped early" in printed


def test_a_programming_error_in_a_tracker_is_not_hidden(run: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    class Buggy(_Breaks):
        def step(self, obs):
            raise ValueError("shapes (3,) and (4,) not aligned")

    real = track_module.make_tracker
    monkeypatch.setattr(track_module, "make_tracker", lambda method, config: Buggy(real(method, config), ""))
    with pytest.raises(ValueError, match="not aligned"):
        main(["track", str(run), "--method", "map", "--out", str(tmp_path / "r")])


# --- importers and the recording writer: never write a run the reader refuses -------------------------------

@pytest.fixture(scope="module")
def bop_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tests.bop_scene import write_bop_scene

    root = tmp_path_factory.mktemp("bop")
    write_bop_scene(root)
    return root


@pytest.mark.parametrize(("fps", "key"), [("1e308", "frame_rate_hz"), ("1e-300", "t_s")])
def test_import_bop_refuses_an_fps_the_reader_would_refuse(fps: str, key: str, bop_scene: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    # before: exit 0 and a run whose recording.json / frames.csv did not validate
    assert main(["import-bop", str(bop_scene / "000001"), "--model", str(bop_scene / "models" / "obj_000007.ply"),
                 "--obj-id", "7", "--fps", fps, "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert key in line and str(out) in line


def test_import_bag_refuses_a_needle_or_tolerance_out_of_range(run: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "normal.bag"
    assert main(["export-bag", str(run), "--out", str(bag), "--format", "ros1"]) == 0
    needle = json.loads((run / "recording.json").read_text())["needle"]
    needle["radius_m"] = 1e308
    needle_file = tmp_path / "needle.json"
    needle_file.write_text(json.dumps(needle))
    out = tmp_path / "imported"
    assert main(["import-bag", str(bag), "--out", str(out), "--needle", str(needle_file)]) == 2  # was 0
    line = _one_error_line(capsys.readouterr().err)
    assert "radius_m" in line and str(needle_file) in line  # (the fourth audit: was the run's recording.json)
    # was OverflowError: cannot convert float infinity to integer
    assert main(["import-bag", str(bag), "--out", str(tmp_path / "b"), "--needle", str(run / "recording.json"),
                 "--stamp-tolerance-s", "1e308"]) == 2
    assert "--stamp-tolerance-s" in _one_error_line(capsys.readouterr().err)
    assert main(["import-bag", str(bag), "--out", str(tmp_path / "c"), "--needle", str(run / "recording.json"),
                 "--frame-rate-hz", "1e308"]) == 2  # was 0 and a run that did not validate
    assert "frame_rate_hz" in _one_error_line(capsys.readouterr().err)


def test_writer_refuses_poses_the_reader_would_refuse(run: Path, tmp_path: Path) -> None:
    from pinpoint_fg.io.recording.reader import read_recording
    from pinpoint_fg.io.recording.writer import RecordingWriter, replace_ground_truth

    rec = read_recording(run)
    far = np.eye(4)
    far[0, 3] = 11.0
    with RecordingWriter(tmp_path / "w", rec.info) as w, pytest.raises(InputError, match="10 m"):
        w.add(replace(rec.frames[0], cam_T_grasper=far))
    copy_run = tmp_path / "run"
    shutil.copytree(run, copy_run)
    with pytest.raises(InputError, match="gt_x_m"):
        replace_ground_truth(copy_run, {0: far})
    assert not validate_run(copy_run)[1]


# --- second audit: results read back, a reference of another recording, Ctrl-C in worker pools ---------------

@pytest.fixture(scope="module")
def map_result(run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("audit2") / "map"
    assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 0
    return out


def _edit_estimate(result: Path, dest: Path, row: int, column: str, cell: str) -> Path:
    shutil.copytree(result, dest)
    lines = (dest / "estimates.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(column)] = cell
    lines[row] = ",".join(cells)
    (dest / "estimates.csv").write_text("\n".join(lines) + "\n")
    return dest


@pytest.mark.parametrize("column", ["q95_trans_m", "q95_rot_rad", "latency_ms"])
def test_hand_edited_negative_q95_or_latency_is_located(column: str, map_result: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Before: evaluate said only "column 'q95_trans': q95_trans must be non-negative" (no file, no row),
    calibrate-spread "method 'map': a result reports a negative q95", and a negative latency was averaged in."""
    bad = _edit_estimate(map_result, tmp_path / "r", 3, column, "-0.5")
    with pytest.raises(InputError) as exc:
        read_result(bad)
    assert (exc.value.file, exc.value.row, exc.value.column) == (str(bad / "estimates.csv"), 3, column)
    assert main(["evaluate", str(bad), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "estimates.csv" in line and "row 3" in line and column in line
    assert not (tmp_path / "ev" / "summary.csv").exists()
    if column != "latency_ms":
        assert main(["calibrate-spread", str(bad), "--out", str(tmp_path / "s.json")]) == 2
        assert "row 3" in _one_error_line(capsys.readouterr().err)
        assert not (tmp_path / "s.json").exists()


@pytest.mark.parametrize("gate", ["nan", "0", "-5", "181", "1e400"])
def test_calibrate_spread_names_its_mode_gate_option(gate: str, map_result: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Before: "column 'mode_gate'", a column of no file."""
    assert main(["calibrate-spread", str(map_result), "--mode-gate-deg", gate, "--out", str(tmp_path / "s.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: option '--mode-gate-deg': must lie in (0, 180]"), err
    assert not (tmp_path / "s.json").exists()


def test_result_writer_refuses_a_negative_q95(map_result: Path, tmp_path: Path) -> None:
    from pinpoint_fg.estimate import Estimate
    from pinpoint_fg.io.result.writer import ResultWriter

    res = read_result(map_result)

    def estimate(k: int, q95_rot_rad: float) -> Estimate:
        return Estimate(frame=int(res.frame[k]), t_s=float(res.t_s[k]), cam_T_needle=res.cam_T_needle[k],
                        q95_trans_m=1e-3, q95_rot_rad=q95_rot_rad, iterations=1, latency_ms=1.0,
                        particles=res.cam_T_needle[k][None], log_posterior=np.zeros(1))

    with ResultWriter(tmp_path / "w", method="map", settings={}, recording_name="x") as w:
        w.write(estimate(0, 0.01))
        with pytest.raises(ValueError, match="q95_rot_rad must not be negative"):  # was written, then unreadable
            w.write(estimate(1, -1e-3))
    assert read_result(tmp_path / "w").frame.tolist() == [0]


def test_reference_of_another_recording_is_refused_before_any_work(map_result: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Before: exit 0 and "vs reference: – / – (0 / 0 frames)": a reference nobody was compared with."""
    other_run = tmp_path / "other"
    assert main(["simulate", "--scenario", "rotation", "--frames", "4", "--seed", "2", "--out", str(other_run)]) == 0
    other = tmp_path / "other-result"
    assert main(["track", str(other_run), "--method", "mht", "--out", str(other)]) == 0  # a multi-hypothesis one
    capsys.readouterr()
    ev = tmp_path / "ev"
    assert main(["evaluate", str(map_result), "--reference", str(other), "--out", str(ev)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(other / "result.json") in line and "recording_name" in line and "rotation-02" in line
    assert not ev.exists()  # refused before --out is made: nothing left behind
    # a reference of one of the evaluated recordings is still taken
    both = [str(map_result), str(other)]
    assert main(["evaluate", *both, "--reference", str(other), "--out", str(tmp_path / "ok")]) == 0
    assert "(0 / 4 frames)" in capsys.readouterr().out  # the other recording's result, judged on its 4 frames


def _interrupt_or_mark(job) -> tuple[str, float]:
    """A stand-in for a tracking job: the first one is hit by Ctrl-C (the terminal sends SIGINT to the caller and
    to its worker); every other one takes a moment and leaves a marker file."""
    import os
    import signal
    import time

    if job.method == "interrupt":
        os.kill(os.getppid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(30)
    time.sleep(0.3)
    Path(job.out).touch()
    return job.out, 0.3


def test_ctrl_c_stops_the_pending_jobs_of_a_worker_pool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: an interrupted ``demo`` (or benchmark, ablate) kept running every pending job to its end
    (ProcessPoolExecutor's shutdown waits for them; each worker took the next job after its KeyboardInterrupt):
    42 s after Ctrl-C on a 150-frame demo, instead of 0.6 s."""
    import signal

    from pinpoint_fg.experiments import jobs as jobs_module

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # the test process must see Ctrl-C
    try:
        monkeypatch.setattr(jobs_module, "_track", _interrupt_or_mark)
        job_list = [jobs_module.TrackJob("run", "interrupt", str(tmp_path / "interrupt"))]
        job_list += [jobs_module.TrackJob("run", "mark", str(tmp_path / f"m{i}")) for i in range(10)]
        with pytest.raises(KeyboardInterrupt):
            jobs_module.run_tracking(job_list, workers=2)
    finally:
        signal.signal(signal.SIGINT, previous)
    ran = sorted(p.name for p in tmp_path.glob("m*"))
    # at most the job the other worker was running and the ones already handed to it; before: all 10
    assert len(ran) <= 3, ran


def _edit_settings(result: Path, dest: Path, **settings: object) -> Path:
    shutil.copytree(result, dest)
    doc = json.loads((dest / "result.json").read_text())
    doc["settings"].update(settings)
    (dest / "result.json").write_text(json.dumps(doc))
    return dest


@pytest.mark.parametrize(("settings", "says"), [
    ({"disabled": 5}, "must be a list"),                          # was TypeError: 'int' object is not iterable
    ({"noise_file": 5}, "must be a path or null"),                # was "RESULT/5: not found"
    ({"noise_file": "/nonexistent/noise.json"}, "is not found"),  # was the noise file alone, not who needs it
])
def test_hand_edited_result_settings_are_located(settings: dict, says: str, map_result: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    bad = _edit_settings(map_result, tmp_path / "r", **settings)
    assert main(["evaluate", str(bad), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(bad / "result.json") in line and "settings." + next(iter(settings)) in line and says in line


def test_noise_file_given_relative_is_found_from_another_directory(run: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """track recorded ``--noise`` as given: evaluated from another directory, a relative name found that
    directory's noise.json (another file: silently other numbers) or none at all."""
    (tmp_path / "a").mkdir()
    NoiseConfig().save(tmp_path / "a" / "noise.json")
    monkeypatch.chdir(tmp_path / "a")
    assert main(["track", str(run), "--method", "map", "--noise", "noise.json", "--out", str(tmp_path / "r")]) == 0
    recorded = json.loads((tmp_path / "r" / "result.json").read_text())["settings"]["noise_file"]
    assert recorded == str(tmp_path / "a" / "noise.json")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "noise.json").write_text("{}")  # another directory's noise.json, not the one tracked with
    monkeypatch.chdir(tmp_path / "b")
    assert main(["evaluate", str(tmp_path / "r"), "--out", str(tmp_path / "ev")]) == 0  # was 2, naming b/noise.json


@pytest.mark.parametrize("command", ["calibrate", "ablate"])
def test_a_run_given_twice_is_refused_not_pooled_twice(command: str, run: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Before: calibrate counted the run twice (8 frames -> 16 samples: a motion covariance replaced its default,
    exit 0), ablate tracked it twice and weighed it double in Table III. ``batch`` already refused it."""
    link = tmp_path / "same-run"
    link.symlink_to(run)
    out = tmp_path / ("noise.json" if command == "calibrate" else "ablation")
    assert main([command, str(run), str(link), "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(link) in line and "given twice" in line and str(run) in line
    assert not out.exists()


def test_calibrate_refuses_ground_truth_behind_the_camera(run: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Before: exit 0, and the keypoint residuals of the needle's mirror image pooled into the noise file
    (tip std 0.6 -> 42 px from one such frame of eight). A needle centre behind the camera is now the reader's
    refusal (``test_ground_truth_behind_the_camera_is_refused_by_the_reader``); a centre 0.5 µm in front of it
    passes the reader, but the frame's mask shows the centre within MIN_DEPTH_M: calibrate's own check."""
    bad = tmp_path / "run"
    shutil.copytree(run, bad)
    lines = (bad / "frames.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[4].split(",")
    assert cells[header.index("mask")]  # data row 4 (frame 3) has a mask: the centre is seen
    cells[header.index("gt_z_m")] = "5e-07"
    lines[4] = ",".join(cells)
    (bad / "frames.csv").write_text("\n".join(lines) + "\n")
    assert not validate_run(bad)[1]  # a valid recording: its content is what is wrong
    out = tmp_path / "noise.json"
    assert main(["calibrate", str(bad), "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "frames.csv" in line and "row 4" in line and "gt_z_m" in line and "not in front" in line
    assert not out.exists()
    assert main(["calibrate", str(run), "--out", str(out)]) == 0  # the run as simulated still calibrates


def test_an_idle_pool_worker_remembers_ctrl_c_without_a_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker waiting for its next job printed a KeyboardInterrupt traceback of its queue; it now only remembers
    the interrupt and refuses the next job."""
    from pinpoint_fg.experiments import jobs as jobs_module

    monkeypatch.setattr(jobs_module, "_interrupted", False)
    jobs_module._on_sigint(2, None)  # idle: no exception
    assert jobs_module._interrupted
    with pytest.raises(KeyboardInterrupt):
        jobs_module._guarded(print, "never printed")
    monkeypatch.setattr(jobs_module, "_interrupted", False)
    assert jobs_module._guarded(int, "7") == 7


def test_track_workers_leave_ctrl_c_to_the_tracking_process() -> None:
    """Ctrl-C during ``track`` printed the verdict/observer workers' KeyboardInterrupt tracebacks beside the
    command's one line; the workers now ignore SIGINT (the tracking process stops them)."""
    import signal
    import subprocess
    import sys

    code = ("import os, signal, time\nfrom pinpoint_fg.offload import _worker_init\n_worker_init(os.getppid())\n"
            "os.kill(os.getpid(), signal.SIGINT)\ntime.sleep(0.2)\nprint('alive')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert done.returncode == 0 and done.stdout.strip() == "alive" and "Traceback" not in done.stderr


@pytest.mark.parametrize(("command", "says"), [("evaluate", "--recording"), ("calibrate-spread", "correct")])
def test_a_result_whose_recording_moved_names_the_result(command: str, says: str, map_result: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Before: "MOVED: not a directory (a run is ...)", not saying which result needs it or what to do."""
    moved = tmp_path / "r"
    shutil.copytree(map_result, moved)
    doc = json.loads((moved / "result.json").read_text())
    doc["recording_path"] = str(tmp_path / "moved-away")
    (moved / "result.json").write_text(json.dumps(doc))
    assert main([command, str(moved), "--out", str(tmp_path / "out")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(moved / "result.json") in line and "recording_path" in line and "moved-away" in line and says in line


@pytest.mark.parametrize("command", ["evaluate", "calibrate-spread", "calibrate", "ablate"])
def test_a_symlink_loop_given_as_input_is_one_line(command: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Before: evaluate and calibrate-spread gave pathlib's "RuntimeError: Symlink loop from ..." traceback
    (Path.resolve while dropping duplicate results); calibrate and ablate, whose duplicate check is new, must not."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    out = tmp_path / ("out.json" if command.startswith("calibrate") else "out")
    assert main([command, str(tmp_path / "a"), "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(tmp_path / "a") in line and "not a directory" in line


@pytest.mark.parametrize("target", ["loop", "missing"])
def test_out_as_a_symlink_that_cannot_be_followed_is_refused_before_any_work(target: str, run: Path, tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Before, with --overwrite: a loop was an OSError traceback when the noise file was saved (after the work);
    a link to a missing file wrote the noise file there, outside --out's directory."""
    out = tmp_path / "noise.json"
    if target == "loop":
        (tmp_path / "other").symlink_to(out)
        out.symlink_to(tmp_path / "other")
    else:
        out.symlink_to(tmp_path / "elsewhere" / "noise.json")
        (tmp_path / "elsewhere").mkdir()
    assert main(["calibrate", str(run), "--out", str(out), "--overwrite"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(out) in line and "symbolic link that cannot be followed" in line
    assert not (tmp_path / "elsewhere" / "noise.json").exists()
    assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 2  # a directory output, too
    assert "symbolic link" in _one_error_line(capsys.readouterr().err)


def _renamed(run: Path, dest: Path, name: str) -> Path:
    shutil.copytree(run, dest)
    doc = json.loads((dest / "recording.json").read_text())
    doc["name"] = name
    (dest / "recording.json").write_text(json.dumps(doc))
    return dest


def test_ablate_keeps_every_result_inside_out_whatever_the_recording_names(run: Path, tmp_path: Path) -> None:
    """The directory came from recording.json's free-text name, and ablate tracks with overwrite: ``..`` and
    ``/abs/path`` put (and overwrote) results outside --out; runs named x, x, x-2 shared a directory."""
    from pinpoint_fg.experiments.ablate import ablation_jobs

    names = ["..", str(tmp_path / "elsewhere"), "x", "x", "x-2", "a/b"]
    runs = [_renamed(run, tmp_path / f"run{i}", n) for i, n in enumerate(names)]
    out = tmp_path / "ablation"
    jobs = ablation_jobs(runs, out)
    dirs = [Path(j.out).parent for j in jobs]
    assert all(d.parent == out for d in dirs), sorted({str(d) for d in dirs})
    assert len({d.name for d in dirs}) == len(names)  # one directory per run
    assert [d.name for d in dirs[:: len(jobs) // len(names)]][2:] == ["x", "x-2", "x-2-2", "a_b"]


def test_batch_names_a_run_given_as_dotdot_inside_out(run: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``batch ..`` wrote the result to ``OUT/..``, the directory holding OUT."""
    from pinpoint_fg.experiments.batch import result_dir_names

    monkeypatch.chdir(run / "masks")
    assert result_dir_names([Path("..").absolute(), Path(run).absolute()]) == [run.name, f"{run.name}-2"]


@pytest.mark.parametrize("command", [["track", "RUN", "--method", "svn"], ["batch", "RUN"]])
@pytest.mark.parametrize("off", ["dense,sparse,grasp-position,grasp-perpendicular",
                                 "dense,tip,tail,grasp-position,grasp-perpendicular,motion"])
def test_disabling_every_measurement_is_a_usage_error(command: list[str], off: str, run: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Before: exit 0, the initial guess written with q95_trans_m = 1.9e-16 m (svn, no term left to inform it)."""
    out = tmp_path / "r"
    with pytest.raises(SystemExit) as exc:
        main([str(run) if a == "RUN" else a for a in command] + ["--disable", off, "--out", str(out)])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--disable" in line and "nothing is left to track" in line
    assert not out.exists()
    # one measurement left is still a (Table III) variant
    assert main(["track", str(run), "--method", "map", "--disable", "dense,sparse,grasp-position",
                 "--out", str(out)]) == 0


# --- the machine refuses a file operation ------------------------------------------------------------------

def test_a_full_disk_while_writing_is_one_line_and_keeps_the_finished_frames(
        run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """An OSError other than "not found" (here ENOSPC from the result writer at frame 3) was a traceback."""
    from pinpoint_fg.io.result.writer import ResultWriter

    out = tmp_path / "r"
    real = ResultWriter.write

    def write(self, est):
        if int(est.frame) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out / "estimates.csv"))
        return real(self, est)

    monkeypatch.setattr(ResultWriter, "write", write)
    assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"error: {out / 'estimates.csv'}: {os.strerror(errno.ENOSPC)}"
    assert read_result(out).frame.tolist() == [0, 1, 2]


# --- third audit: empty paths and topics ----------------------------------------------------------------------

@pytest.mark.parametrize(("argv", "flag"), [
    (["validate", ""], "run"),                                    # validated the current directory
    (["track", "RUN", "--out", "", "--overwrite"], "--out"),      # wrote the result into the current directory
    (["export-bag", "RUN", "--out", "OUT", "--topic-tip", ""], "--topic-tip"),  # dropped the tips, exit 0
])
def test_an_empty_path_or_topic_is_a_usage_error(argv: list[str], flag: str, run: Path, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """An unset shell variable (``pinpoint-fg track "$RUN" --out "$OUT"``) is an empty argument."""
    here = tmp_path / "here"
    shutil.copytree(run, here)
    monkeypatch.chdir(here)
    before = sorted(p.name for p in here.iterdir())
    with pytest.raises(SystemExit) as exc:
        main([str(run) if a == "RUN" else str(tmp_path / "x.bag") if a == "OUT" else a for a in argv])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert flag in line and "empty" in line
    assert sorted(p.name for p in here.iterdir()) == before and not (tmp_path / "x.bag").exists()


@pytest.mark.parametrize(("command", "name"), [("calibrate-spread", "result.json"), ("calibrate-spread", "modes.csv"),
                                               ("calibrate", "frames.csv"), ("calibrate", "masks/000001.png")])
def test_out_naming_a_file_of_the_input_is_refused(command: str, name: str, run: Path, map_result: Path,
                                                   tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Before, with --overwrite: exit 0 and the input's own file replaced by the JSON written (the result or run
    unreadable afterwards); without it, the refusal advised --overwrite."""
    source = tmp_path / "in"
    shutil.copytree(map_result if command == "calibrate-spread" else run, source)
    target = source / name
    before = target.read_bytes() if target.exists() else None
    for overwrite in ([], ["--overwrite"]):
        assert main([command, str(source), "--out", str(target), *overwrite]) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert str(target) in line and "file of the input" in line
    assert (target.read_bytes() if target.exists() else None) == before
    # a file of another name beside the input's files is still fine
    assert main([command, str(source), "--out", str(source / "fitted.json")]) == 0


def test_export_bag_refuses_a_ros2_storage_for_a_ros1_bag(run: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """``--storage mcap`` with ``--format ros1`` was ignored without a word (exit 0, a ROS 1 bag written)."""
    bag = tmp_path / "normal.bag"
    assert main(["export-bag", str(run), "--out", str(bag), "--format", "ros1", "--storage", "mcap"]) == 2
    assert "--storage" in _one_error_line(capsys.readouterr().err)
    assert not bag.exists()


@pytest.mark.parametrize("command", ["track", "evaluate-result", "evaluate-recording"])
def test_out_that_is_the_input_directory_is_refused(command: str, run: Path, map_result: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Before, ``track RUN --out RUN --overwrite`` wrote result.json, estimates.csv, ... into the recording (exit 0)
    and ``evaluate RES --out RES --overwrite`` its tables into the result: two directories' files mixed. Refused
    with or without --overwrite, given through a symlink too, and the input is left as it was."""
    source = tmp_path / "in"
    shutil.copytree(map_result if command == "evaluate-result" else run, source)
    link = tmp_path / "link"
    link.symlink_to(source, target_is_directory=True)
    before = sorted(str(p.relative_to(source)) for p in source.rglob("*"))
    argv = {"track": ["track", str(source), "--method", "map"],
            "evaluate-result": ["evaluate", str(source)],
            "evaluate-recording": ["evaluate", str(map_result), "--recording", str(source)]}[command]
    for out in (source, link):
        for overwrite in ([], ["--overwrite"]):
            assert main([*argv, "--out", str(out), *overwrite]) == 2
            line = _one_error_line(capsys.readouterr().err)
            assert str(out) in line and "also an input" in line
    assert sorted(str(p.relative_to(source)) for p in source.rglob("*")) == before


# --- fourth audit: groundtruth, damaged results read back, huge counts, --out inside an importer's input -------

@pytest.fixture(scope="module")
def board_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated run whose images show the ground-truth checkerboard (and which has ground truth)."""
    return _simulated(tmp_path_factory, "audit4", "calibration", 3, 2)


def test_groundtruth_that_finds_no_board_keeps_the_runs_ground_truth(board_run: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Before, a board-to-needle file with the wrong board size (7 x 4 instead of 5 x 4) found the board in none of
    the images and emptied every gt cell of the run, exit 0 ("no previous ground truth to compare with")."""
    run = tmp_path / "run"
    shutil.copytree(board_run, run)
    before = (run / "frames.csv").read_bytes()
    b2n = write_board_to_needle(tmp_path / "b2n.json")
    doc = json.loads(b2n.read_text())
    doc["board"]["squares_x"] = 7
    b2n.write_text(json.dumps(doc))
    assert main(["groundtruth", str(run), "--board-to-needle", str(b2n)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(b2n) in line and "'board'" in line and "none of the run's 3 images" in line
    assert (run / "frames.csv").read_bytes() == before
    # the right board still rewrites the gt columns
    assert main(["groundtruth", str(run), "--board-to-needle", str(write_board_to_needle(tmp_path / "ok.json"))]) == 0
    assert "board detected in 3" in capsys.readouterr().out


def _edit_cell(path: Path, row: int, column: str, cell: str) -> None:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(column)] = cell
    lines[row] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


DAMAGED_RESULTS = [  # file, row, column, cell: each was a traceback of `evaluate` before
    ("estimates.csv", 2, "x_m", "1e300"),          # LinAlgError "Eigenvalues did not converge" (after warnings)
    ("smoothed.csv", 2, "z_m", "-1e300"),
    ("modes.csv", 1, "frame", str(2**63)),         # OverflowError: Python int too large to convert to C long
    ("modes.csv", 1, "y_m", "1e300"),              # NumPy overflow warnings, then exit 0
    ("modes.csv", 1, "qw", "1e200"),               # "norm inf" after NumPy's overflow warning
    ("particles.npz", 2, "xyz_m", "1e300"),
]


@pytest.fixture(scope="module")
def svn_result(run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An SVN result with every file: estimates, smoothed (L = 2), modes, particles."""
    out = tmp_path_factory.mktemp("audit4") / "svn"
    assert main(["track", str(run), "--method", "svn", "--particles", "8", "--window", "2", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize(("name", "row", "column", "cell"), DAMAGED_RESULTS,
                         ids=[f"{n}:{c}={v}" for n, _, c, v in DAMAGED_RESULTS])
def test_a_damaged_result_is_located_not_a_traceback(name: str, row: int, column: str, cell: str, svn_result: Path,
                                                      tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = tmp_path / "res"
    shutil.copytree(svn_result, result)
    if name == "particles.npz":
        with np.load(result / name) as z:
            arrays = {k: z[k] for k in z.files}
        arrays[column][row - 1, 0, 0] = float(cell)
        np.savez(result / name, **arrays)
    else:
        _edit_cell(result / name, row, column, cell)
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # on the command line, NumPy's warning was a second line
        assert main(["evaluate", str(result), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(result / name) in line and f"row {row}" in line and repr(column) in line


@pytest.mark.parametrize("command", ["track", "batch"])
def test_a_particle_count_no_result_can_hold_is_a_usage_error(command: str, run: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``--particles 100000000000`` was accepted, the run read, then NumPy's "Unable to allocate 11.6 TiB" traceback;
    a result's reader takes at most 10 million particles (its journal check)."""
    with pytest.raises(SystemExit) as exc:
        main([command, str(run), "--method", "pf", "--particles", "100000000000", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "--particles" in _one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "o").exists()


def test_running_out_of_memory_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``simulate --frames 100000000000`` was NumPy's "Unable to allocate 745. GiB" traceback (exit 1)."""
    assert main(["simulate", "--scenario", "normal", "--frames", "100000000000", "--out", str(tmp_path / "s")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith("error: out of memory") and "fewer frames" in line


@pytest.mark.parametrize("command", ["import-bag", "import-bop", "batch", "ablate"])
def test_out_that_is_an_importers_or_pools_input_is_refused(command: str, run: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Before, ``import-bag BAG --out BAG --overwrite`` wrote recording.json, frames.csv and masks/ into the ROS 2 bag
    directory, ``import-bop SCENE --out SCENE --overwrite`` the run into the BOP scene, ``batch RUN --out RUN
    --overwrite`` (and ``ablate``) results into the recording (exit 0): two directories' files mixed. As for
    ``track`` and ``evaluate``: refused with or without --overwrite, before any work, the input left as it was."""
    from tests.bop_scene import NEEDLE_OBJ_ID, write_bop_scene

    if command == "import-bag":
        source = tmp_path / "bag"
        assert main(["export-bag", str(run), "--out", str(source)]) == 0
        argv = ["import-bag", str(source), "--needle", str(run / "recording.json")]
    elif command == "import-bop":
        info = write_bop_scene(tmp_path / "dataset", n_images=2)
        source = Path(info["scene"])
        argv = ["import-bop", str(source), "--model", str(info["model"]), "--obj-id", str(NEEDLE_OBJ_ID)]
    else:
        source = tmp_path / "run"
        shutil.copytree(run, source)
        argv = [command, str(source), *(["--method", "pf", "--workers", "1"] if command == "batch" else [])]
    capsys.readouterr()
    before = sorted(str(p.relative_to(source)) for p in source.rglob("*"))
    for overwrite in ([], ["--overwrite"]):
        assert main([*argv, "--out", str(source), *overwrite]) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert str(source) in line and "also an input" in line
    assert sorted(str(p.relative_to(source)) for p in source.rglob("*")) == before


@pytest.mark.parametrize(("key", "value"), [("radius_m", 1e308), ("wire_diameter_m", 2.0), ("tip_angle_rad", -1e9),
                                            ("radius_m", 1e-33)])
def test_import_bag_names_the_needle_file_for_a_needle_out_of_range(key: str, value: float, run: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A NEEDLE.json with ``radius_m: 1e308`` was blamed on the run being written ("OUT/recording.json: column
    'needle.radius_m'"), after the whole bag had been read; now the needle file and its key are named first."""
    bag = tmp_path / "bag"
    assert main(["export-bag", str(run), "--out", str(bag)]) == 0
    doc = json.loads((run / "recording.json").read_text())["needle"]
    doc[key] = value
    needle = tmp_path / "needle.json"
    needle.write_text(json.dumps(doc))
    capsys.readouterr()
    out = tmp_path / "imported"
    assert main(["import-bag", str(bag), "--out", str(out), "--needle", str(needle)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith(f"error: {needle}: column {key!r}: out of range")
    assert not out.exists()


def test_import_bop_corrupt_png_mask_is_one_line(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A BOP mask PNG cut after its signature: OpenCV printed "[ERROR:0@...] global grfmt_png.cpp ... readHeader IHDR
    chunk shall be first" on stderr before our line. The PNG's structure is now checked before OpenCV sees it, as a
    recording's PNGs are (pinpoint_fg.io.recording.png)."""
    from tests.bop_scene import NEEDLE_OBJ_ID, write_bop_scene

    info = write_bop_scene(tmp_path / "dataset", n_images=2)
    mask = Path(info["scene"]) / "mask_visib" / "000001_000001.png"
    mask.write_bytes(mask.read_bytes()[:12])
    capfd.readouterr()
    assert main(["import-bop", str(info["scene"]), "--model", str(info["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(tmp_path / "run")]) == 2
    err = capfd.readouterr().err  # the file descriptor: OpenCV writes past sys.stderr
    assert len([s for s in err.splitlines() if s.strip()]) == 1, err
    line = _one_error_line(err)
    assert str(mask) in line and "not a readable image" in line


@pytest.mark.parametrize(("index", "key"), [(0, "camera.fx"), (2, "camera.cx")])
def test_import_bop_names_scene_camera_for_intrinsics_out_of_range(index: int, key: str, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """``cam_K`` with fx = 1e300 (or cx = 1e12) was blamed on the run being written ("OUT/recording.json: column
    'camera.fx'") and left OUT behind; now scene_camera.json and its key are named before anything is written."""
    from tests.bop_scene import NEEDLE_OBJ_ID, write_bop_scene

    info = write_bop_scene(tmp_path / "dataset", n_images=2)
    cameras = Path(info["scene"]) / "scene_camera.json"
    doc = json.loads(cameras.read_text())
    for entry in doc.values():
        entry["cam_K"][index] = 1e300 if index == 0 else 1e12
    cameras.write_text(json.dumps(doc))
    out = tmp_path / "run"
    assert main(["import-bop", str(info["scene"]), "--model", str(info["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(cameras) in line and "'0.cam_K'" in line and key in line and "out of range" in line
    assert not out.exists()


@pytest.mark.parametrize(("index", "key"), [(0, "camera.fx"), (2, "camera.cx")])
def test_import_bag_names_camera_info_for_intrinsics_out_of_range(index: int, key: str, run: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A camera_info whose K has fx = 1e300 (or cx = 1e12) was blamed on OUT/recording.json and left a half-written
    run behind; now the bag and its camera_info topic are named, before anything is written."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    good = tmp_path / "good.bag"
    assert main(["export-bag", str(run), "--out", str(good), "--format", "ros1"]) == 0
    bag = tmp_path / "bad.bag"
    with AnyReader([good]) as reader, Writer(bag) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore)
                 for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            if conn.topic == "/camera/camera_info":
                msg = reader.deserialize(raw, conn.msgtype)
                msg.K = msg.K.copy()  # ROS 1 spells it K; deserialised read-only
                msg.K[index] = 1e300 if index == 0 else 1e12
                raw = reader.typestore.serialize_ros1(msg, conn.msgtype)
            writer.write(conns[conn.id], stamp, raw)
    capsys.readouterr()
    out = tmp_path / "imported"
    assert main(["import-bag", str(bag), "--out", str(out), "--needle", str(run / "recording.json")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(bag) in line and "'/camera/camera_info'" in line and key in line and "out of range" in line
    assert not out.exists()


@pytest.mark.parametrize("method", ["", "svn"])
@pytest.mark.parametrize("command", ["evaluate", "calibrate-spread"])
def test_a_hand_edited_result_method_is_located(method: str, command: str, map_result: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """``"method": ""`` or ``"svn"`` in a map result's result.json was evaluated (and given svn's spread factors) as
    that method, exit 0 ("no method could be fitted (: q95_trans_m ..." from calibrate-spread)."""
    result = tmp_path / "res"
    shutil.copytree(map_result, result)
    doc = json.loads((result / "result.json").read_text())
    doc["method"] = method
    (result / "result.json").write_text(json.dumps(doc))
    out = tmp_path / ("ev" if command == "evaluate" else "scale.json")
    assert main([command, str(result), "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(result / "result.json") in line and "'method'" in line


# --- fifth audit: modes.csv that lacks frames, gt behind the camera, half-written runs, huge q95 ---------------

def _drop_modes_rows(modes_csv: Path, frames: set[int]) -> None:
    lines = modes_csv.read_text().splitlines(keepends=True)
    modes_csv.write_text("".join([lines[0], *(s for s in lines[1:] if int(s.split(",")[0]) not in frames)]))


@pytest.mark.parametrize(("dropped", "row", "says"), [
    ({3, 4, 5, 6, 7}, "row ", "frame 3 of estimates.csv has no modes"),  # modes.csv stops early
    ({1}, "row ", "frame 1 of estimates.csv has no modes"),               # a frame in the middle
    ({0, 1, 2, 3, 4, 5, 6, 7}, "", "frame 0 of estimates.csv has no modes"),  # the header only
])
def test_evaluate_refuses_a_modes_csv_that_lacks_frames(dropped: set[int], row: str, says: str, svn_result: Path,
                                                        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A modes.csv missing frames of estimates.csv was evaluated on the frames it had (the truth kept by the modes
    and the modes' bimodal share of a subset, exit 0); the format has one row per frame and mode."""
    result = tmp_path / "res"
    shutil.copytree(svn_result, result)
    _drop_modes_rows(result / "modes.csv", dropped)
    capsys.readouterr()
    assert main(["evaluate", str(result), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(result / "modes.csv") in line and row in line and "'frame'" in line and says in line
    assert not (tmp_path / "ev").exists()  # refused before --out is made: nothing left behind


def test_evaluate_refuses_a_modes_frame_the_estimates_lack(svn_result: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """A modes.csv row of a frame estimates.csv does not have was ignored without a word."""
    result = tmp_path / "res"
    shutil.copytree(svn_result, result)
    lines = (result / "modes.csv").read_text().splitlines()
    cells = lines[-1].split(",")
    cells[:3] = ["99", "0", "1.0"]
    (result / "modes.csv").write_text("\n".join([*lines, ",".join(cells)]) + "\n")
    capsys.readouterr()
    assert main(["evaluate", str(result), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"row {len(lines)}:" in line and "'frame'" in line and "frame 99 is not a frame of estimates.csv" in line


def test_an_unfinished_result_may_lack_the_modes_of_its_last_frame_only(svn_result: Path, tmp_path: Path) -> None:
    """The writer appends a frame's modes after its estimates row: a result stopped between the two is evaluated
    (its last frame without modes); a gap anywhere else is refused as for a finished result."""
    from pinpoint_fg.eval.modes import modes_of_result

    result = tmp_path / "res"
    shutil.copytree(svn_result, result)
    doc = json.loads((result / "result.json").read_text())
    doc["complete"] = False
    (result / "result.json").write_text(json.dumps(doc))
    _drop_modes_rows(result / "modes.csv", {7})
    modes = modes_of_result(read_result(result))
    assert modes.has_modes.tolist() == [True] * 7 + [False]
    _drop_modes_rows(result / "modes.csv", {6})
    with pytest.raises(InputError, match="frame 6 of estimates.csv has no modes"):
        modes_of_result(read_result(result))


def _gt_behind(run: Path, dest: Path, row: int = 3) -> Path:
    """A copy of ``run`` whose ground truth of data row ``row`` is mirrored through the image plane (z -> -z)."""
    shutil.copytree(run, dest)
    lines = (dest / "frames.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index("gt_z_m")] = str(-float(cells[header.index("gt_z_m")]))
    lines[row] = ",".join(cells)
    (dest / "frames.csv").write_text("\n".join(lines) + "\n")
    return dest


def test_ground_truth_behind_the_camera_is_refused_by_the_reader(run: Path, map_result: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A gt pose mirrored behind the camera validated, and ``evaluate`` scored the estimates against it: one such
    frame of eight turned a 0.2 mm mean error into 10.7 mm, exit 0."""
    bad = _gt_behind(run, tmp_path / "run")
    errors = validate_run(bad)[1]
    assert len(errors) == 1 and errors[0].row == 3 and errors[0].column == "gt_z_m"
    assert "not in front of the camera" in str(errors[0])
    capsys.readouterr()
    assert main(["evaluate", str(map_result), "--recording", str(bad), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(bad / "frames.csv") in line and "row 3" in line and "'gt_z_m'" in line


def test_the_recording_writer_refuses_ground_truth_behind_the_camera(run: Path, tmp_path: Path) -> None:
    """What the reader refuses is not written (``groundtruth``, the importers and ``simulate`` write through it)."""
    from pinpoint_fg.io.recording.reader import read_recording
    from pinpoint_fg.io.recording.writer import RecordingWriter

    rec = read_recording(run)
    T = rec.frames[0].cam_T_needle_gt.copy()
    T[2, 3] = 0.0  # in the image plane: not in front either
    with RecordingWriter(tmp_path / "w", rec.info) as w, pytest.raises(InputError) as exc:
        w.add(replace(rec.frames[0], cam_T_needle_gt=T, mask=None, image=None))
    assert exc.value.column == "gt_z_m" and "not in front of the camera" in str(exc.value)


def test_import_bop_refuses_ground_truth_behind_the_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A scene_gt.json entry with the needle behind the camera was imported (exit 0) into a run whose own reader
    then refused it; now scene_gt.json and the entry's cam_t_m2c are named before anything is written."""
    path, idx, out = _import_bop_with_needle_depth(tmp_path, lambda z: -abs(z))
    line = _one_error_line(capsys.readouterr().err)
    assert str(path) in line and f"'1[{idx}].cam_t_m2c'" in line and "not in front of the camera" in line
    assert not out.exists()


def _import_bop_with_needle_depth(tmp_path: Path, depth: object) -> tuple[Path, int, Path]:
    """``import-bop`` of a scene whose needle entry's ``cam_t_m2c`` z is ``depth(z)``; asserts exit code 2 and returns
    (scene_gt.json, the entry's index, the --out that must not exist)."""
    from tests.bop_scene import NEEDLE_OBJ_ID, write_bop_scene

    info = write_bop_scene(tmp_path / "dataset", n_images=3)
    path = Path(info["scene"]) / "scene_gt.json"
    doc = json.loads(path.read_text())
    idx = next(i for i, e in enumerate(doc["1"]) if e["obj_id"] == NEEDLE_OBJ_ID)
    doc["1"][idx]["cam_t_m2c"][2] = depth(doc["1"][idx]["cam_t_m2c"][2])
    path.write_text(json.dumps(doc))
    out = tmp_path / "run"
    assert main(["import-bop", str(info["scene"]), "--model", str(info["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(out)]) == 2
    return path, idx, out


def test_import_bag_refuses_ground_truth_behind_the_camera(run: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """A bag whose gt topic puts the needle behind the camera was imported, exit 0, into a run its reader refused."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    good = tmp_path / "good.bag"
    assert main(["export-bag", str(run), "--out", str(good), "--format", "ros1"]) == 0
    bag = tmp_path / "bad.bag"
    topic = None
    with AnyReader([good]) as reader, Writer(bag) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore)
                 for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            if conn.topic.endswith("gt_pose") and topic is None:
                topic = conn.topic
                msg = reader.deserialize(raw, conn.msgtype)
                msg.pose.position.z = -msg.pose.position.z
                raw = reader.typestore.serialize_ros1(msg, conn.msgtype)
            writer.write(conns[conn.id], stamp, raw)
    assert topic is not None
    capsys.readouterr()
    out = tmp_path / "imported"
    assert main(["import-bag", str(bag), "--out", str(out), "--needle", str(run / "recording.json")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(bag) in line and repr(topic) in line and "not in front of the camera" in line
    assert not out.exists()


def test_groundtruth_refuses_a_mount_that_puts_the_needle_behind_the_camera(board_run: Path, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """A board-to-needle mount 1 m behind the board rewrote every gt cell behind the camera (exit 0), a run its
    reader now refuses; the mount is named and frames.csv left as it was."""
    run = tmp_path / "run"
    shutil.copytree(board_run, run)
    before = (run / "frames.csv").read_bytes()
    b2n = write_board_to_needle(tmp_path / "b2n.json")
    doc = json.loads(b2n.read_text())
    from pinpoint_fg.io.recording.reader import read_recording

    gt0 = read_recording(run).frames[0].cam_T_needle_gt  # = cam_T_board @ board_T_needle in frame 0
    back = np.eye(4)
    back[2, 3] = -0.5  # the needle moved 0.5 m along the camera's axis towards it: behind the camera
    doc["board_T_needle"] = (np.array(doc["board_T_needle"]) @ np.linalg.inv(gt0) @ back @ gt0).tolist()
    b2n.write_text(json.dumps(doc))
    assert main(["groundtruth", str(run), "--board-to-needle", str(b2n)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(b2n) in line and "'board_T_needle'" in line and "not in front of the camera" in line
    assert (run / "frames.csv").read_bytes() == before


def test_import_bop_that_fails_half_way_leaves_no_run_behind(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A mask PNG of the third image cut short: the import stopped there (one line, exit 2) but left OUT as a valid
    run of the first two frames, which every later command read as the scene. Now OUT is not created; with
    --overwrite over an earlier run, that run is left as it was."""
    from tests.bop_scene import NEEDLE_OBJ_ID, write_bop_scene

    info = write_bop_scene(tmp_path / "dataset", n_images=3)
    argv = ["import-bop", str(info["scene"]), "--model", str(info["model"]), "--obj-id", str(NEEDLE_OBJ_ID)]
    earlier = tmp_path / "earlier"
    assert main([*argv, "--out", str(earlier)]) == 0
    before = {str(p.relative_to(earlier)): p.read_bytes() for p in earlier.rglob("*") if p.is_file()}
    mask = Path(info["scene"]) / "mask_visib" / "000002_000001.png"
    mask.write_bytes(mask.read_bytes()[:12])
    capsys.readouterr()
    out = tmp_path / "new" / "run"
    assert main([*argv, "--out", str(out)]) == 2
    assert str(mask) in _one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "new").exists()  # nor the parent it would have created
    assert main([*argv, "--out", str(earlier), "--overwrite"]) == 2
    assert {str(p.relative_to(earlier)): p.read_bytes() for p in earlier.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset", "earlier"]  # no staging directory left


def test_simulate_that_fails_leaves_no_directory_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """``simulate --frames 100000000000`` (out of memory) left an empty --out; a failure while writing left a
    shorter run. Neither leaves anything now, and a successful run with --overwrite keeps other files."""
    from pinpoint_fg.io.recording.writer import RecordingWriter
    from pinpoint_fg.sim import scenarios

    out = tmp_path / "s"
    assert main(["simulate", "--scenario", "normal", "--frames", "100000000000", "--out", str(out)]) == 2
    assert _one_error_line(capsys.readouterr().err).startswith("error: out of memory")
    assert not out.exists()

    add = RecordingWriter.add

    def fails_at_frame_3(self, frame, mask=None, image=None):  # noqa: ANN001, ANN202
        if frame.frame == 3:
            raise MemoryError("Unable to allocate the image of frame 3")
        return add(self, frame, mask=mask, image=image)

    monkeypatch.setattr(RecordingWriter, "add", fails_at_frame_3)
    assert main(["simulate", "--scenario", "normal", "--frames", "6", "--out", str(out)]) == 2
    assert "frame 3" in _one_error_line(capsys.readouterr().err)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == []
    monkeypatch.setattr(RecordingWriter, "add", add)
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["simulate", "--scenario", "normal", "--frames", "4", "--out", str(out), "--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine" and len(validate_run(out)[0].frames) == 4
    assert scenarios.simulate("normal", 4, out=tmp_path / "api") == tmp_path / "api"
    assert (tmp_path / "api" / "frames.csv").read_bytes() == (out / "frames.csv").read_bytes()


@pytest.mark.parametrize("column", ["q95_trans_m", "q95_rot_rad"])
def test_a_huge_q95_is_located_and_a_large_one_scores_finitely(column: str, svn_result: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A hand-edited q95 of 1e300 (finite) printed NumPy's "overflow encountered in square" on stderr and wrote
    NLL-S = inf to summary.csv, exit 0. Beyond MAX_RESULT_Q95 it is now refused at its row; up to it, evaluate's
    numbers stay finite and quiet."""
    import csv

    from pinpoint_fg.io.result.schema import MAX_RESULT_Q95

    for cell, code in (("1e300", 2), (repr(MAX_RESULT_Q95), 0)):
        result = tmp_path / f"res{code}"
        shutil.copytree(svn_result, result)
        _edit_cell(result / "estimates.csv", 3, column, cell)
        capsys.readouterr()
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            assert main(["evaluate", str(result), "--out", str(tmp_path / f"ev{code}")]) == code
        err = capsys.readouterr().err
        if code:
            line = _one_error_line(err)
            assert str(result / "estimates.csv") in line and "row 3" in line and repr(column) in line
        else:
            assert not err.strip()
            with open(tmp_path / "ev0" / "summary.csv") as f:
                row = next(csv.DictReader(f))
            kind = "trans" if "trans" in column else "rot"
            assert all(np.isfinite(float(row[k])) for k in (f"nlls_{kind}", f"is_{kind}", f"{kind}_q95_"
                                                            + ("mm" if kind == "trans" else "deg")))


def test_the_result_writer_refuses_a_q95_the_reader_refuses(tmp_path: Path) -> None:
    """What the reader refuses is not written (``track`` stops at that frame, its finished frames kept)."""
    from pinpoint_fg.io.result.schema import MAX_RESULT_Q95
    from tests.test_io_result import make_estimates, open_writer

    est = make_estimates(1)[0]
    with open_writer(tmp_path / "r") as w, pytest.raises(ValueError, match="beyond the result format"):
        w.write(replace(est, q95_rot_rad=2 * MAX_RESULT_Q95))


@pytest.fixture(scope="module")
def namesake(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run named 'normal-01' like ``run`` (same scenario, seed and frames) but of other content (spurs in its masks,
    no images): every frame of a result of ``run`` is one of its frames."""
    out = tmp_path_factory.mktemp("audit5") / "other" / "normal-01"
    assert main(["simulate", "--scenario", "normal", "--frames", "8", "--seed", "1", "--mask-spurs", "0.5",
                 "--out", str(out)]) == 0
    return out


def test_evaluate_refuses_two_recordings_of_one_name(run: Path, namesake: Path, map_result: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Results of two different recordings named alike were evaluated together, exit 0: tables, figure files and
    the MHT reference are keyed by the name, so one recording's reference judged the other's frames and one figure
    overwrote the other. Refused; results of two copies of one recording are still evaluated together."""
    other = tmp_path / "res-other"
    assert main(["track", str(namesake), "--method", "map", "--out", str(other)]) == 0
    copy = tmp_path / "copy" / run.name
    shutil.copytree(run, copy)
    on_copy = tmp_path / "res-copy"
    assert main(["track", str(copy), "--method", "map", "--out", str(on_copy)]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(map_result), str(other), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(other / "result.json") in line and "'recording_name'" in line and "both named 'normal-01'" in line
    assert main(["evaluate", str(map_result), str(on_copy), "--out", str(tmp_path / "ev2")]) == 0


def test_evaluate_refuses_a_recording_of_the_same_name_and_other_content(run: Path, namesake: Path, map_result: Path,
                                                                        tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """``evaluate RES --recording OTHER`` with OTHER named like RES's recording was scored against OTHER's ground
    truth, exit 0 (only the names were compared). track now records the recording's fingerprint; a result written
    before it is compared with the recording at its recording_path when that still exists."""
    capsys.readouterr()
    assert main(["evaluate", str(map_result), "--recording", str(namesake), "--out", str(tmp_path / "ev")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(map_result / "result.json") in line and "'recording_fingerprint'" in line and "differs" in line
    legacy = tmp_path / "legacy"
    shutil.copytree(map_result, legacy)
    doc = json.loads((legacy / "result.json").read_text())
    del doc["recording_fingerprint"]
    (legacy / "result.json").write_text(json.dumps(doc))
    assert main(["evaluate", str(legacy), "--recording", str(namesake), "--out", str(tmp_path / "ev")]) == 2
    assert "'recording_path'" in _one_error_line(capsys.readouterr().err)
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)  # the same recording elsewhere (moved, copied) is fine, with or without the key
    for res in (map_result, legacy):
        assert main(["evaluate", str(res), "--recording", str(copy), "--out", str(tmp_path / f"ok-{res.name}")]) == 0


# --- sixth audit --------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("board", "says"), [
    ({"square_m": 1e300}, "square_m"),   # was ValueError "points_px contains NaN or infinite values" (a traceback)
    ({"squares_x": 5.0}, None),          # a whole float: was OpenCV's "Can't parse 'patternSize'" traceback
    ({"squares_x": 2**31 + 1}, "squares_x"),  # the same traceback: OpenCV's pattern size is a C int
    ({"square_m": 1.0}, "10 m"),         # was "error: column 'gt_x_m': ...", naming no file
])
def test_groundtruth_board_sizes_are_located_or_work(board: dict, says: str | None, board_run: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    shutil.copytree(board_run, run)
    before = (run / "frames.csv").read_bytes()
    b2n = write_board_to_needle(tmp_path / "b2n.json")
    doc = json.loads(b2n.read_text())
    doc["board"].update(board)
    b2n.write_text(json.dumps(doc))
    capsys.readouterr()
    code = main(["groundtruth", str(run), "--board-to-needle", str(b2n)])
    if says is None:  # 5.0 squares are 5 squares
        assert code == 0 and "board detected in 3" in capsys.readouterr().out
        return
    assert code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(b2n) in line and "'board" in line and says in line
    assert (run / "frames.csv").read_bytes() == before


def test_import_bop_names_scene_gt_for_a_needle_beyond_the_format(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A scene_gt.json entry 20 m from the camera (cam_t_m2c 2e4 mm) was refused naming the run's frames.csv, a file
    that does not exist (the run is never written); now scene_gt.json and the entry's cam_t_m2c are named."""
    path, idx, out = _import_bop_with_needle_depth(tmp_path, lambda z: 2e4)
    line = _one_error_line(capsys.readouterr().err)
    assert str(path) in line and f"'1[{idx}].cam_t_m2c'" in line and "10 m" in line
    assert not out.exists()


HUGE = "99999999999999999999999"  # beyond int64
HUGE_COUNTS = [  # each was a traceback (exit 1)
    (["simulate", "--frames", HUGE], "--frames"),          # NumPy's "Maximum allowed size exceeded"
    (["track", "RUN", "--window", HUGE], "--window"),      # track_recording's "window must be a whole number >= 1"
    (["batch", "RUN", "--window", HUGE], "--window"),
    (["ablate", "RUN", "--frames", HUGE], "--frames"),     # "max_frames must be a whole number", from a worker
    (["demo", "--frames", HUGE], "--frames"),
    (["benchmark", "--grid-frames", HUGE], "--grid-frames"),
]


@pytest.mark.parametrize(("argv", "flag"), HUGE_COUNTS, ids=[" ".join(a[:3]) for a, _ in HUGE_COUNTS])
def test_a_count_beyond_any_run_is_a_usage_error(argv: list[str], flag: str, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main([*(str(tmp_path / a) if a == "RUN" else a for a in argv), "--out", str(out)])
    assert exc.value.code == 2
    assert flag in _one_error_line(capsys.readouterr().err)
    assert not out.exists()


@pytest.mark.parametrize("method", ["map", "mht"])
def test_a_window_longer_than_the_run_tracks_as_the_whole_run(method: str, run: Path, tmp_path: Path) -> None:
    """``track --method map --window 1000000000`` on an 8-frame run never finished (the smoother walked every key of
    the window, most before the run's first, on every frame); now it tracks as a window of the whole run would."""
    import subprocess
    import sys

    argv = ["track", str(run), "--method", method, "--particles", "2"]
    whole = tmp_path / "whole"
    assert main([*argv, "--window", "8", "--out", str(whole)]) == 0
    long = tmp_path / "long"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "pinpoint_fg.cli", *argv, "--window", "1000000000", "--out",
                           str(long)], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    for name in ("smoothed.csv", "trajectory.tum"):
        assert (long / name).read_text() == (whole / name).read_text()


def test_out_that_is_the_reference_result_is_refused(map_result: Path, svn_result: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``evaluate RES --reference REF --out REF --overwrite`` wrote summary.csv, tables.md and the figures into the
    reference result (exit 0), while the same --out for RES or --recording was refused."""
    ref = tmp_path / "ref"
    shutil.copytree(map_result, ref)
    before = sorted(str(p.relative_to(ref)) for p in ref.rglob("*"))
    assert main(["evaluate", str(svn_result), "--reference", str(ref), "--out", str(ref), "--overwrite"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(ref) in line and "also an input" in line
    assert sorted(str(p.relative_to(ref)) for p in ref.rglob("*")) == before


def test_a_recording_name_with_a_pipe_or_newline_keeps_the_tables_in_shape(run: Path, tmp_path: Path) -> None:
    """A recording named ``a|b`` (any JSON string is a valid name) shifted every value of its tables.md rows one
    column right, under the wrong header, exit 0; a newline in the name cut the row in two."""
    import re

    named = tmp_path / "named"
    shutil.copytree(run, named)
    doc = json.loads((named / "recording.json").read_text())
    doc["name"] = "a|b\nc"
    (named / "recording.json").write_text(json.dumps(doc))
    assert main(["track", str(named), "--method", "map", "--out", str(tmp_path / "res")]) == 0
    assert main(["evaluate", str(tmp_path / "res"), "--out", str(tmp_path / "ev")]) == 0
    lines = (tmp_path / "ev" / "tables.md").read_text().splitlines()
    cells = lambda line: len(re.split(r"(?<!\\)\|", line))  # noqa: E731 (the cells of a row, escaped pipes kept)
    n = 0
    for i, line in enumerate(lines):
        if line.startswith("|---"):  # a table's separator: its header above, its rows below
            width = cells(lines[i - 1])
            for row in lines[i + 1:]:
                if not row.startswith("|"):
                    break
                assert cells(row) == width, row
                n += 1
        else:
            assert not line.startswith("c |") and not line.startswith("c\\|"), line  # a row cut by the newline
    assert n > 0


@pytest.mark.parametrize("spec", ["", "  "])
def test_an_empty_robust_spec_is_a_usage_error(spec: str, run: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """``--robust "$ROBUST"`` with the variable unset switched every robust loss off (as ``none``), exit 0: the
    default conic=cauchy:3 and grasp-perpendicular=huber:1.345 were silently dropped."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main(["track", str(run), "--method", "map", "--robust", spec, "--out", str(out)])
    assert exc.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--robust" in line and "empty" in line and "'none'" in line
    assert not out.exists()


def test_validate_refuses_a_run_without_frames_as_track_does(run: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "run"
    shutil.copytree(run, bad)
    lines = (bad / "frames.csv").read_text().splitlines()
    (bad / "frames.csv").write_text(lines[0] + "\n")  # the header alone: validate said OK, track "no frames"
    assert main(["validate", str(bad)]) == 2
    assert "no frames" in capsys.readouterr().err
    assert main(["track", str(bad), "--method", "map", "--out", str(tmp_path / "r")]) == 2
    assert "no frames" in _one_error_line(capsys.readouterr().err)


def test_time_stamps_out_of_order_are_tracked_with_a_note(run: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The format orders frames by `frame` only: a t_s that goes back is valid and tracked, but the user is told
    (trajectory.tum is then not in time order)."""
    bad = tmp_path / "run"
    shutil.copytree(run, bad)
    lines = (bad / "frames.csv").read_text().splitlines()
    cols = lines[0].split(",")
    i = cols.index("t_s")
    row = lines[5].split(",")  # frame 4 gets the time stamp of frame 1
    row[i] = lines[2].split(",")[i]
    lines[5] = ",".join(row)
    (bad / "frames.csv").write_text("\n".join(lines) + "\n")
    assert main(["validate", str(bad)]) == 0
    err = capsys.readouterr().err
    assert "t_s does not increase at 1 frame(s) (first: frame 4" in err
    assert main(["track", str(bad), "--method", "map", "--out", str(tmp_path / "r")]) == 0
    assert "t_s does not increase" in capsys.readouterr().err
    times = [float(s.split()[0]) for s in (tmp_path / "r" / "trajectory.tum").read_text().splitlines()]
    assert len(times) == 8 and times[4] < times[3]


def test_a_run_without_any_image_evidence_is_tracked_with_a_note(run: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    bare = tmp_path / "run"
    shutil.copytree(run, bare)
    lines = (bare / "frames.csv").read_text().splitlines()
    cols = lines[0].split(",")
    gone = [cols.index(c) for c in ("tip_u_px", "tip_v_px", "tail_u_px", "tail_v_px", "mask")]
    rows = [line.split(",") for line in lines[1:]]
    for r in rows:
        for i in gone:
            r[i] = ""
    (bare / "frames.csv").write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    assert main(["validate", str(bare)]) == 0
    assert "none of the 8 frames has a tip, a tail or a mask" in capsys.readouterr().err
    assert main(["track", str(bare), "--method", "map", "--out", str(tmp_path / "r")]) == 0
    assert "none of the 8 frames" in capsys.readouterr().err
    assert main(["validate", str(run)]) == 0
    assert "none of the" not in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "starts"), [
    (["track", "RUN", "--particles", "0", "--out", "O"], "error: pinpoint-fg track: argument --particles: "),
    (["track", "RUN", "--disable", "bogus", "--out", "O"], "error: pinpoint-fg track: argument --disable: "),
    (["simulate", "--frames", "0", "--out", "O"], "error: pinpoint-fg simulate: argument --frames: "),
    (["bogus"], "error: pinpoint-fg: argument command: invalid choice: 'bogus'"),
    ([], "error: pinpoint-fg: the following arguments are required: command"),
])
def test_usage_errors_are_one_line(argv: list[str], starts: str, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Before: argparse's usage block (6-8 lines) above the error."""
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / a) if a in ("RUN", "O") else a for a in argv])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and err.startswith(starts) and err.rstrip().endswith(
        "--help`)"), err
