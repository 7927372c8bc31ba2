"""Kinematic faults (issue 9, item 4): elapsed-time widening, the jump test, re-anchoring, snapshots."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.kinematics_check import KinematicsCheckConfig, KinematicsMonitor, elapsed_scale
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.noise import NoiseConfig
from pinpoint_fg.observation import Observation
from pinpoint_fg.sim.scenarios import SimRun, simulate, simulate_frames
from pinpoint_fg.track import track_recording
from pinpoint_fg.window import RANDOM_WALK_SIGMA, Window

Q = NoiseConfig().process_cov


@cache
def _sim(scenario: str, n: int, seed: int) -> SimRun:
    return simulate_frames(scenario, n, seed)


def _monitor_run(run: SimRun, config: KinematicsCheckConfig | None = None) -> tuple[KinematicsMonitor, list]:
    mon = KinematicsMonitor(Q, config)
    out = [mon.update(Observation(f.frame, f.t_s, cam_T_grasper=f.cam_T_grasper)) for f in run.frames]
    return mon, out


# ---------------------------------------------------------------------------------------------
# the monitor


def test_elapsed_scale() -> None:
    cfg = KinematicsCheckConfig()
    assert elapsed_scale(1 / 30, cfg) == 1.0 and elapsed_scale(1 / 30 * 1.0005, cfg) == 1.0
    assert elapsed_scale(0.5, cfg) == pytest.approx(15.0)
    assert elapsed_scale(1 / 60, cfg) == 1.0  # never narrower than one reference frame
    assert elapsed_scale(10.0, cfg) == cfg.max_scale
    assert elapsed_scale(float("nan"), cfg) == 1.0 and elapsed_scale(-1.0, cfg) == 1.0
    assert cfg.threshold == pytest.approx(22.458, abs=1e-3)
    with pytest.raises(ValueError):
        KinematicsCheckConfig(jump_quantile=1.0)


@pytest.mark.parametrize("q", [0.5, 0.9, 0.99, 0.999, 0.9999, 1.0 - 1e-9])
def test_threshold_is_scipy_stats_chi2_ppf_bit_for_bit(q: float) -> None:
    from scipy import stats

    assert KinematicsCheckConfig(jump_quantile=q).threshold == float(stats.chi2.ppf(q, 6))


def test_tracking_does_not_import_scipy_stats() -> None:
    # scipy.stats costs ~0.6 s of every command's start-up and of each worker process track spawns
    import subprocess
    import sys

    code = "import sys, pinpoint_fg.track, pinpoint_fg.cli; print('scipy.stats' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"


def test_jump_is_flagged_on_its_frame_and_removed_from_later_poses() -> None:
    run = _sim("kinfault", 300, 1)
    k = run.info.extra["simulator"]["registration_jump"]["frame"]
    mon, out = _monitor_run(run)
    assert mon.faults == [k]
    assert [i for i, m in enumerate(out) if m.fault] == [k]
    assert out[k].chi2 > KinematicsCheckConfig().threshold and out[k].delta is None
    # the registration estimated from the jump is the simulated offset, to within a frame's motion noise
    np.testing.assert_allclose(mon.registration[:3, 3], run.registration_offset[k, :3, 3], atol=0.3e-3)
    # later absolute poses are corrected: as close to the un-jumped recording as before the jump
    for j in range(k, 300):
        if out[j].observation.cam_T_grasper is not None:
            err = out[j].observation.cam_T_grasper[:3, 3] - run.cam_T_grasper_recorded[j, :3, 3]
            np.testing.assert_allclose(err, -run.registration_offset[j, :3, 3], atol=0.3e-3)
    # the following frame's relative motion is used normally
    assert out[k + 1].delta is not None and not out[k + 1].fault
    # without the correction only the velocity history restarts: later poses keep the offset
    mon2, out2 = _monitor_run(run, KinematicsCheckConfig(correct_registration=False))
    assert mon2.faults == [k] and out2[k + 1].delta is not None
    np.testing.assert_array_equal(out2[k + 5].observation.cam_T_grasper, run.frames[k + 5].cam_T_grasper)


def test_no_motion_input_across_a_dropout() -> None:
    run = _sim("kinfault", 300, 1)
    _, out = _monitor_run(run)
    for a, b in run.info.extra["simulator"]["kinematics_missing"]:
        assert all(m.delta is None and not m.fault and np.isnan(m.chi2) for m in out[a : b + 2])
        assert out[b + 2].delta is not None  # re-referenced on the first frame back
    assert out[0].delta is None and np.isnan(out[0].dt_s)


def test_false_alarm_rate_on_clean_runs() -> None:
    """Clean runs of every scenario without faults: at most 0.2 % flagged (chi-square(6) 0.999 quantile)."""
    tested = flagged = 0
    for scenario in ("slow", "normal", "rotation", "suturing", "calibration", "drive"):
        for seed in (0, 1):
            _, out = _monitor_run(_sim(scenario, 300, seed))
            tested += sum(np.isfinite(m.chi2) for m in out)
            flagged += sum(m.fault for m in out)
    assert tested > 3500
    assert flagged <= 0.002 * tested, f"{flagged} false alarms in {tested} tested frames"


# ---------------------------------------------------------------------------------------------
# the window: a drop-out widens the prior by the elapsed time


CAM = PinholeCamera(900.0, 900.0, 539.5, 539.5, 1080, 1080)
MODEL = MeasurementModel(CAM, NeedleModel(), NoiseConfig())


def _prior_cov_after_push(delta: np.ndarray | None, scale: float) -> np.ndarray:
    T0 = se3_exp(np.r_[0.3, -0.2, 0.1, 0.001, 0.002, 0.045])[None]
    w = Window(1, Q)
    w.start(T0, FrameLikelihood(Observation(0, 0.0), MODEL), np.r_[[0.1] * 3, [2e-3] * 3])
    w.push(FrameLikelihood(Observation(1, 0.5), MODEL), delta, use_motion=True, process_scale=scale)
    W = w.prior_W[0]
    return np.linalg.inv(W.T @ W)


def test_dropout_widens_the_window_prior_with_elapsed_time() -> None:
    P0 = np.diag(np.r_[[0.1] * 3, [2e-3] * 3] ** 2)
    walk = np.diag(RANDOM_WALK_SIGMA**2)
    # no evidence in the new frame, identity motion: the prior is exactly P0 + scale * walk
    for scale in (1.0, 15.0):
        np.testing.assert_allclose(_prior_cov_after_push(None, scale), P0 + scale * walk, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(_prior_cov_after_push(np.eye(4), 4.0), P0 + 4.0 * Q, rtol=1e-6, atol=1e-12)
    # a frame without kinematics (walk) widens more than one with (Q); a longer drop-out more still
    with_kin = np.trace(_prior_cov_after_push(np.eye(4), 1.0))
    without = np.trace(_prior_cov_after_push(None, 1.0))
    longer = np.trace(_prior_cov_after_push(None, 15.0))
    assert with_kin < without < longer
    with pytest.raises(ValueError):
        _prior_cov_after_push(None, 0.0)


# ---------------------------------------------------------------------------------------------
# every tracker: the same decision, reported per frame


@pytest.fixture(scope="module")
def kinfault_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("kinfault", 60, 1, out=tmp_path_factory.mktemp("kin") / "run")


@pytest.mark.parametrize(("method", "particles"), [("svn", 20), ("pf", 500), ("map", None)])
def test_trackers_report_the_jump_and_track_through_it(kinfault_run: Path, tmp_path: Path, method: str,
                                                      particles: int | None) -> None:
    import json

    sim = json.loads((kinfault_run / "recording.json").read_text())["simulator"]
    k = sim["registration_jump"]["frame"]
    out = track_recording(kinfault_run, method, tmp_path / method, particles=particles, progress=False)
    res = read_result(out)
    fault = res.extra["kinematics_fault"]
    assert list(np.flatnonzero(fault)) == [k]
    scale = res.extra["process_scale"]
    np.testing.assert_allclose(scale, 1.0)  # a 30 Hz run: one reference frame per step
    truth = simulate_frames("kinfault", 60, 1).cam_T_needle
    err = pose_errors(res.cam_T_needle, truth).trans_m
    # re-anchored, not dragged by the 4 mm jump: the estimate moves with the needle at the jump frame,
    # and tracking continues after it as accurately as before it (whatever mode the tracker holds)
    moved = np.linalg.norm(res.cam_T_needle[k, :3, 3] - res.cam_T_needle[k - 1, :3, 3])
    assert moved < np.linalg.norm(truth[k, :3, 3] - truth[k - 1, :3, 3]) + 1e-3
    assert np.mean(err[k:]) < np.mean(err[:k]) + 0.5e-3


_CAUCHY_STUCK = ("known weakness: with a Cauchy conic (the default until the twenty-third round) a wrong mode costs "
                 "less, the MAP tracker's re-seed test does not fire on snapshots, and it stays in the flipped mode "
                 "from frame 10 on (measured, seed 1: median 59 deg)")


@pytest.mark.parametrize(("method", "particles", "robust"), [
    ("svn", 20, None), ("pf", 1000, None), ("map", None, "none"),
    ("map", None, None),  # today's default conic, Geman-McClure, re-seeds here as the Gaussian one does
    pytest.param("map", None, "conic=cauchy:3,grasp-perpendicular=huber:1.345",
                 marks=pytest.mark.xfail(strict=True, reason=_CAUCHY_STUCK)),
])
def test_snapshots_are_tracked_frame_to_frame(tmp_path: Path, method: str, particles: int | None,
                                              robust: str | None) -> None:
    from pinpoint_fg.noise import parse_robust_spec

    run = simulate("snapshots", 16, 1, out=tmp_path / "run")
    out = track_recording(run, method, tmp_path / method, particles=particles, progress=False,
                          robust=None if robust is None else parse_robust_spec(robust))
    res = read_result(out)
    np.testing.assert_allclose(res.extra["process_scale"][1:], 15.0)  # 0.5 s = 15 reference frames
    assert not np.any(res.extra["kinematics_fault"])
    truth = simulate_frames("snapshots", 16, 1).cam_T_needle
    err = pose_errors(res.cam_T_needle, truth)
    assert np.all(np.isfinite(err.trans_m))
    assert np.median(err.trans_m) < 3e-3
    if method == "svn":
        # SVN reports its modes: with frames 0.5 s apart and no kinematics the circle and its twin (~70 deg
        # away) are within ~2 nats on several frames (measured, seed 1, frame 4: 293.5 vs 295.8), so which
        # one is the MAP is a coin toss that round-off decides; what must hold is that the truth stays
        # among the reported modes (within the needle radius and 15 deg) on most frames
        from pinpoint_fg.io.result import read_modes

        modes = read_modes(out).by_frame()
        kept = []
        for k, T in enumerate(truth):
            peaks = np.stack([m.cam_T_needle for m in modes[k]])
            e = pose_errors(peaks, np.broadcast_to(T, peaks.shape))
            kept.append(bool(np.any((e.trans_m < 4.5e-3) & (np.degrees(e.rot_rad) < 15.0))))
        assert np.mean(kept) >= 0.8, kept
    else:
        # sensible, not an accuracy claim: within the needle radius (4.5 mm) and 30 deg on most frames
        # (measured, seed 1: map well inside 2 mm / 15 deg; pf ~2 mm / 20 deg)
        assert np.median(np.degrees(err.rot_rad)) < 30.0
