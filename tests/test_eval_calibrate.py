"""Noise calibration: residuals at the truth, recovery of the simulator's noise, the noise file, Table I."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from factors.geometry import PinholeCamera
from factors.lie import se3_inverse, se3_log
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.calibrate import (
    calibrate_runs,
    fit_conic_correlation,
    format_table,
    residuals_at_truth,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.writer import RecordingWriter, replace_ground_truth
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.sim.config import SimConfig
from pinpoint_fg.sim.kinematics import needle_T_grasper
from pinpoint_fg.sim.scenarios import SimRun, simulate, simulate_frames
from pinpoint_fg.track import track_recording

N_FRAMES = 500
#: An undistorted camera, so keypoint noise added in the image is exactly the residual's noise.
PINHOLE = PinholeCamera(fx=900.0, fy=900.0, cx=539.5, cy=539.5, width=1080, height=1080)
#: White kinematic noise: every frame an independent sample (the default bias would need hours of data).
WHITE = SimConfig(camera=PINHOLE, kin_white_var_fraction=1.0)


def _write(run: SimRun, out: Path) -> Path:
    """Write an in-memory simulated run exactly as ``simulate`` does."""
    with RecordingWriter(out, run.info) as writer:
        for rec in run.frames:
            writer.add(rec, mask=run.masks.get(rec.frame))
    return out


@pytest.fixture(scope="module")
def calib(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimRun, Path]:
    run = simulate_frames("calibration", N_FRAMES, seed=5, config=WHITE)
    return run, _write(run, tmp_path_factory.mktemp("calib") / "run")


def _within_sampling_error(estimate: np.ndarray, sigma: np.ndarray, n: int, k: float = 4.0) -> None:
    """Sample std within k standard errors (sigma / sqrt(2 (n - 1))) of the configured sigma."""
    se = np.asarray(sigma) / math.sqrt(2.0 * (n - 1))
    assert np.all(np.abs(np.asarray(estimate) - sigma) < k * se), (estimate, sigma, k * se)


def test_residuals_at_truth_are_exactly_the_simulated_errors(calib: tuple[SimRun, Path]) -> None:
    run, path = calib
    r = residuals_at_truth(read_recording(path))
    # grasp position: recorded = true + e, so T_gt X_g - p_rec = -e
    np.testing.assert_allclose(r["grasp_position"], -run.kinematic_errors.position_m, atol=1e-15)
    # perpendicularity: z_rec . t_g = sin(beta) exactly
    np.testing.assert_allclose(r["grasp_perpendicular"][:, 0], np.sin(run.kinematic_errors.angles_rad[:, 1]),
                               atol=1e-12)
    # keypoints (no distortion): pi(T X) - z = true pixel - measured pixel
    seen = [k for k, f in enumerate(run.frames) if f.tip_px is not None]
    expect = np.array([run.tip_px_true[k] - run.frames[k].tip_px for k in seen])
    np.testing.assert_allclose(r["tip"], expect, atol=1e-9)
    # motion: with N_k = G_k^-1 G_rec_k (grasper-frame error), E = nTg N_{k-1} N_k^-1 gTn
    G, Grec = run.cam_T_grasper, run.cam_T_grasper_recorded
    N = se3_inverse(G) @ Grec
    nTg = needle_T_grasper(run.config.needle, run.config.grasper_tilt_rad)
    E = nTg[None] @ N[:-1] @ se3_inverse(N[1:]) @ se3_inverse(nTg)[None]
    np.testing.assert_allclose(r["motion"], se3_log(E), atol=1e-10)
    # conic: one sample per extracted backbone pixel, every mask frame
    assert r["conic"].shape[1] == 1 and r["conic"].shape[0] > 50 * len(run.masks)


def test_calibration_recovers_the_configured_noise(calib: tuple[SimRun, Path]) -> None:
    run, path = calib
    noise = calibrate_runs([path])
    cfg = run.config
    n_gp = noise["grasp_position"].count
    assert n_gp == N_FRAMES
    _within_sampling_error(noise["grasp_position"].sigma, np.array(cfg.grasp_position_sigma_m), n_gp)
    _within_sampling_error(noise["grasp_perpendicular"].sigma, np.array([cfg.perpendicular_sigma]), n_gp)
    for name, sigma in (("tip", cfg.tip_sigma_px), ("tail", cfg.tail_sigma_px)):
        nz = noise[name]
        assert nz.count == sum(getattr(f, f"{name}_px") is not None for f in run.frames)
        _within_sampling_error(nz.sigma, np.array(sigma), nz.count)
        assert np.all(np.abs(nz.mean) < 4.0 * np.array(sigma) / math.sqrt(nz.count))
    assert noise["motion"].count == N_FRAMES - 1
    # the mask band's centre line moves by delta_c + (delta_l + delta_r) / 2 (render.py)
    band = math.sqrt(cfg.mask_centreline_sigma_px**2 + cfg.mask_edge_sigma_px**2 / 2.0)
    assert abs(noise["conic"].sigma[0] / band - 1.0) < 0.10
    assert abs(noise["conic"].mean[0]) < 0.2


def test_exact_kinematics_give_a_vanishing_motion_residual(tmp_path: Path) -> None:
    cfg = SimConfig(camera=PINHOLE, grasp_position_sigma_m=(1e-9, 1e-9, 1e-9), perpendicular_sigma=0.0,
                    grasper_rot_sigma_rad=0.0, mask_every=1000)
    path = simulate("calibration", 40, seed=2, out=tmp_path / "run", config=cfg)
    noise = calibrate_runs([path])
    assert noise["motion"].count == 39
    assert np.all(noise["motion"].sigma[:3] < 1e-8) and np.all(noise["motion"].sigma[3:] < 1e-9)
    assert noise["grasp_perpendicular"].sigma[0] < 1e-6  # floored, still positive definite


def test_noise_file_round_trips(calib: tuple[SimRun, Path], tmp_path: Path) -> None:
    noise = calibrate_runs([calib[1]])
    noise.save(tmp_path / "noise.json")
    back = NoiseConfig.load(tmp_path / "noise.json")
    for k, v in noise.residuals.items():
        np.testing.assert_array_equal(back[k].mean, v.mean)
        np.testing.assert_array_equal(back[k].cov, v.cov)
        assert back[k].count == v.count


def test_cli_calibrate_writes_a_loadable_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = simulate("calibration", 20, seed=1, out=tmp_path / "run", config=WHITE)
    assert main(["calibrate", str(path), "--out", str(tmp_path / "n.json")]) == 0
    out = capsys.readouterr().out
    assert "Anchor (x, y, z)" in out and "wrote" in out
    assert NoiseConfig.load(tmp_path / "n.json")["tip"].count > 0


def test_run_without_ground_truth_is_an_input_error_naming_it(tmp_path: Path) -> None:
    path = simulate("calibration", 6, seed=1, out=tmp_path / "nogt", config=WHITE)
    replace_ground_truth(path, {k: None for k in range(6)})
    with pytest.raises(InputError) as exc:
        calibrate_runs([path])
    assert "nogt" in str(exc.value) and "ground truth" in str(exc.value)
    assert main(["calibrate", str(path), "--out", str(tmp_path / "n.json")]) == 2


def test_format_table_is_shaped_like_table_i() -> None:
    text = format_table(NoiseConfig())
    lines = text.splitlines()
    assert lines[0].split()[:2] == ["Likelihood", "type"]
    rows = {ln.split("  ")[0].strip(): ln for ln in lines[2:]}
    assert set(rows) == {
        "Anchor (x, y, z)", "Perpendicular", "Conic", "Keypoints (tip u, v; tail u, v)",
        "Motion rotation (x, y, z) per frame", "Motion translation (x, y, z) per frame",
    }
    assert "(0.41, 0.44, 1.00) mm" in rows["Anchor (x, y, z)"]
    assert "1.235 px" in rows["Conic"]
    assert "(1.006, 1.012; 0.921, 0.680) px" in rows["Keypoints (tip u, v; tail u, v)"]
    assert all(ln.rstrip().endswith("default") for ln in lines[2:])


def _arc_frames(rng: np.random.Generator, ell: float, count: int = 60) -> list[tuple[np.ndarray, np.ndarray]]:
    """Masked frames of 150 pixels ~1 px apart along circular arcs, residuals an OU process of length ``ell`` px
    (``ell = 0``: independent), pixels given in a shuffled order (as raster order is not the arc's)."""
    frames = []
    for _ in range(count):
        angles = np.linspace(0.0, 1.5, 150) + rng.uniform(0, 2 * np.pi)
        radius = 150.0 / 1.5
        pts = np.c_[np.cos(angles), np.sin(angles)] * radius + 500.0
        s = radius * (angles - angles[0])
        cov = np.exp(-np.abs(s[:, None] - s[None, :]) / ell) if ell > 0 else np.eye(150)
        r = 0.1 + 1.3 * rng.multivariate_normal(np.zeros(150), cov)
        perm = rng.permutation(150)
        frames.append((pts[perm], r[perm]))
    return frames


@pytest.mark.parametrize("ell", [5.0, 15.0, 40.0])
def test_fit_conic_correlation_recovers_the_length_of_an_ou_process(ell: float) -> None:
    """The integrated autocorrelation of an OU process is its length: recovered within 15 % (seeded, 60 frames of
    150 px; the estimate's sampling error grows with ell / arc length)."""
    noise = ResidualNoise(np.r_[0.1], np.array([[1.69]]))
    got = fit_conic_correlation(_arc_frames(np.random.default_rng(int(ell)), ell), noise)
    assert abs(got / ell - 1.0) < 0.15, got


def test_fit_conic_correlation_of_independent_pixels_is_about_zero() -> None:
    noise = ResidualNoise(np.r_[0.1], np.array([[1.69]]))
    assert fit_conic_correlation(_arc_frames(np.random.default_rng(1), 0.0), noise) < 0.6
    assert fit_conic_correlation([], noise) == 0.0
    assert fit_conic_correlation([(np.zeros((1, 2)), np.zeros(1))], noise) == 0.0


def test_cli_calibrate_conic_correlation_writes_the_fitted_length(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    """The simulator's mask boundary noise is smooth along the arc (squared-exponential, 20 px): the fitted
    length is that process's integrated correlation, ~25 px (sqrt(pi / 2) * 20), and lands in the noise file
    and its table; without the flag the file keeps independent pixels."""
    path = simulate("calibration", 30, seed=1, out=tmp_path / "run", config=WHITE)
    assert main(["calibrate", str(path), "--conic-correlation", "--out", str(tmp_path / "c.json")]) == 0
    assert "Conic correlation length" in capsys.readouterr().out
    ell = NoiseConfig.load(tmp_path / "c.json").conic_correlation_px
    assert 10.0 < ell < 60.0, ell
    assert main(["calibrate", str(path), "--out", str(tmp_path / "n.json")]) == 0
    assert NoiseConfig.load(tmp_path / "n.json").conic_correlation_px == 0.0
    assert "Conic correlation length" not in capsys.readouterr().out


def test_calibrate_with_the_geometric_distance(calib: tuple[SimRun, Path], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """``--conic-distance geometric`` calibrates the backbone residual the tracker will use: the samples are the
    exact distances at the truth, frame by frame; the other residual types are unchanged."""
    from factors.residuals import conic_geometric_residual
    from pinpoint_fg.observe import observe_frame

    _, path = calib
    rec = read_recording(path)
    frames: list = []
    r = residuals_at_truth(rec, frames, conic_distance="geometric")
    plain = residuals_at_truth(rec)
    assert frames and r["conic"].shape == plain["conic"].shape
    for k in ("tip", "tail", "grasp_position", "grasp_perpendicular", "motion"):
        np.testing.assert_array_equal(r[k], plain[k])
    masked = [f for f in rec.frames if observe_frame(rec, f).backbone_px is not None]
    points, got = frames[0]
    want = conic_geometric_residual(masked[0].cam_T_needle_gt, rec.info.camera.K, rec.info.needle.radius_m,
                                    points, jacobian=False)[0][0]
    np.testing.assert_array_equal(got, want)
    assert main(["calibrate", str(path), "--conic-distance", "geometric", "--out", str(tmp_path / "g.json")]) == 0
    assert NoiseConfig.load(tmp_path / "g.json")["conic"].sigma[0] != calibrate_runs([path])["conic"].sigma[0]
    # the file records its distance; track takes it, and refuses the other one (exit 2, one line)
    assert NoiseConfig.load(tmp_path / "g.json").conic_distance == "geometric"
    assert calibrate_runs([path]).conic_distance == "sampson"
    out = track_recording(path, "map", tmp_path / "t", noise_file=tmp_path / "g.json", max_frames=2, progress=False)
    assert json.loads((out / "result.json").read_text())["settings"]["conic_distance"] == "geometric"
    capsys.readouterr()
    assert main(["track", str(path), "--method", "map", "--noise", str(tmp_path / "g.json"), "--conic-distance",
                 "sampson", "--out", str(tmp_path / "t2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "g.json" in err[0] and "conic_distance" in err[0] and "geometric" in err[0], err
    assert not (tmp_path / "t2").exists()
    with pytest.raises(ValueError, match="conic_distance"):
        residuals_at_truth(rec, conic_distance="euclid")


def _with_gt(src: Path, dest: Path, change: dict) -> Path:
    """A copy of run ``src`` whose ground truth of the frames in ``change`` is replaced (None: cleared)."""
    import shutil

    shutil.copytree(src, dest)
    replace_ground_truth(dest, change)
    return dest


def test_ground_truth_that_does_not_describe_its_frame_is_left_out(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    """Three gt depths of 9.9 m among forty frames gave an anchor std of 2.6 m and a conic std of 11 px: such
    frames are left out (the calibration equals that with their gt cleared) and named in a note."""
    src = simulate("calibration", 40, seed=1, out=tmp_path / "run", config=WHITE)
    rec = read_recording(src)
    far = {}
    for f in rec.frames[5:8]:
        T = f.cam_T_needle_gt.copy()
        T[2, 3] = 9.9
        far[f.frame] = T
    bad = _with_gt(src, tmp_path / "far", far)
    cleared = _with_gt(src, tmp_path / "cleared", dict.fromkeys(far))
    notes: list[str] = []
    noise = calibrate_runs([bad], notes=notes)
    assert noise.to_json() == calibrate_runs([cleared]).to_json()
    assert noise["grasp_position"].sigma.max() < 1e-3  # was 2.6 m
    rows = [read_recording(bad).row_of(f) for f in rec.frames[5:8]]
    assert len(notes) == 1 and "3 ground-truth frame(s) left out" in notes[0]
    assert all(f"{r} (x" in notes[0] for r in rows)
    capsys.readouterr()
    assert main(["calibrate", str(bad), "--out", str(tmp_path / "n.json")]) == 0
    assert "left out" in capsys.readouterr().err


def test_ground_truth_placed_beside_its_needle_is_left_out(tmp_path: Path) -> None:
    """0.5 m typed for 0.5 mm in one gt_x_m cell and a depth five times too small in another (anchor std 144 mm and
    a motion std of 16 mm before): both frames are left out, the calibration equals that with their gt cleared."""
    src = simulate("calibration", 40, seed=1, out=tmp_path / "run", config=WHITE)
    rec = read_recording(src)
    bad = {}
    T = rec.frames[6].cam_T_needle_gt.copy()
    T[0, 3] = 0.5
    bad[rec.frames[6].frame] = T
    T = rec.frames[20].cam_T_needle_gt.copy()
    T[2, 3] *= 0.2
    bad[rec.frames[20].frame] = T
    run = _with_gt(src, tmp_path / "beside", bad)
    notes: list[str] = []
    noise = calibrate_runs([run], notes=notes)
    assert noise.to_json() == calibrate_runs([_with_gt(src, tmp_path / "cleared", dict.fromkeys(bad))]).to_json()
    assert len(notes) == 1 and "2 ground-truth frame(s) left out" in notes[0] and "sizes away" in notes[0]


def test_ground_truth_in_the_wrong_unit_throughout_is_refused(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """Every gt translation 100x too large (centimetres typed as metres): nothing is left to calibrate from, and
    the first row is named (exit 2), not a noise file of metre-sized sigmas."""
    src = simulate("calibration", 12, seed=2, out=tmp_path / "run", config=WHITE)
    rec = read_recording(src)
    cm = {}
    for f in rec.frames:
        if f.cam_T_needle_gt is not None:
            T = f.cam_T_needle_gt.copy()
            T[:3, 3] *= 100.0
            cm[f.frame] = T
    bad = _with_gt(src, tmp_path / "cm", cm)
    with pytest.raises(InputError) as exc:
        calibrate_runs([bad])
    first = next(f for f in read_recording(bad).frames if f.cam_T_needle_gt is not None)
    assert exc.value.column == "gt_z_m" and exc.value.row == read_recording(bad).row_of(first)
    assert "metres expected" in str(exc.value)
    assert main(["calibrate", str(bad), "--out", str(tmp_path / "n.json")]) == 2
    assert not (tmp_path / "n.json").exists()


def test_a_mask_of_noise_is_calibrated_without_and_named(tmp_path: Path) -> None:
    """A mask that is no needle's (here half noise) adds nothing to the conic's samples (the calibration equals
    that of the run without it), and one note names it."""
    import shutil

    import cv2

    src = simulate("calibration", 30, seed=2, out=tmp_path / "run", config=WHITE)
    rec = read_recording(src)
    f = next(r for r in rec.frames if r.mask is not None)
    noisy = tmp_path / "noisy"
    shutil.copytree(src, noisy)
    shape = cv2.imread(str(src / f.mask), cv2.IMREAD_UNCHANGED).shape
    cv2.imwrite(str(noisy / f.mask), ((np.random.default_rng(0).random(shape) < 0.5) * 255).astype(np.uint8))
    bare = tmp_path / "bare"
    shutil.copytree(src, bare)
    cv2.imwrite(str(bare / f.mask), np.zeros(shape, np.uint8))  # an empty mask: no backbone
    notes: list[str] = []
    noise = calibrate_runs([noisy], notes=notes)
    assert noise.to_json() == calibrate_runs([bare]).to_json() != calibrate_runs([src]).to_json()
    assert len(notes) == 1
    assert notes[0].startswith(f"note: {noisy}: the masks of 1 frame(s) are ignored, those frames calibrated")
    assert f"frame {f.frame}, {f.mask}: " in notes[0]
