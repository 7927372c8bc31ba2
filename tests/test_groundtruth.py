"""Ground truth from the checkerboard in a run's images (pinpoint_fg.groundtruth)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera, pose_from_xyz_quat, xyz_quat_from_pose
from factors.lie import se3_inverse, so3_exp, so3_log
from pinpoint_fg.checkerboard import DEFAULT_NEEDLE_T_BOARD, BoardSpec, render_board
from pinpoint_fg.errors import InputError
from pinpoint_fg.groundtruth import (
    DEFAULT_BOARD_T_NEEDLE,
    groundtruth_run,
    read_board_to_needle,
    write_board_to_needle,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import FrameRecord, RecordingInfo
from pinpoint_fg.io.recording.writer import write_recording

CAM = PinholeCamera(700.0, 700.0, 359.5, 359.5, 720, 720, (-0.05, 0.01, 0.0, 0.0, 0.0))
NEEDLE = NeedleModel()


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    t_mm = 1e3 * float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    r_deg = math.degrees(float(np.linalg.norm(so3_log(T_true[:3, :3].T @ T_est[:3, :3]))))
    return t_mm, r_deg


def test_board_to_needle_file_round_trip(tmp_path) -> None:
    p = write_board_to_needle(tmp_path / "b2n.json")
    T, spec = read_board_to_needle(p)
    np.testing.assert_allclose(T, DEFAULT_BOARD_T_NEEDLE, atol=1e-15)
    np.testing.assert_allclose(T @ DEFAULT_NEEDLE_T_BOARD, np.eye(4), atol=1e-12)
    assert spec == BoardSpec()
    # the xyz + quaternion form, with a board of another size
    xyz, q = xyz_quat_from_pose(DEFAULT_BOARD_T_NEEDLE)
    doc = {"xyz_m": xyz.tolist(), "quat_wxyz": (1.001 * q).tolist(), "board": {"squares_x": 7, "squares_y": 6}}
    (tmp_path / "q.json").write_text(json.dumps(doc))
    T2, spec2 = read_board_to_needle(tmp_path / "q.json")
    np.testing.assert_allclose(T2, pose_from_xyz_quat(xyz, q), atol=1e-12)
    assert spec2.pattern_size == (6, 5)
    # rounded hand-typed rotations are projected onto SO(3)
    rounded = np.round(DEFAULT_BOARD_T_NEEDLE, 4)
    (tmp_path / "r.json").write_text(json.dumps({"board_T_needle": rounded.tolist()}))
    T3, _ = read_board_to_needle(tmp_path / "r.json")
    np.testing.assert_allclose(T3[:3, :3].T @ T3[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T3, DEFAULT_BOARD_T_NEEDLE, atol=1e-4)


@pytest.mark.parametrize(
    ("doc", "where"),
    [
        ("{not json", "not valid JSON"),
        ([1, 2], "JSON object"),
        ({"board_T_needle": np.eye(3).tolist()}, "'board_T_needle': must have shape (4, 4)"),
        ({"board_T_needle": (2 * np.eye(4)).tolist()}, "'board_T_needle'"),
        ({"board_T_needle": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}, "last row"),
        ({"board_T_needle": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, "proper rotation"),
        ({"board_T_needle": [[1, 0, 0, "x"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "'board_T_needle'"),
        ({"xyz_m": [0, 0, 0]}, "'quat_wxyz': missing"),
        ({"xyz_m": [0, 0, 0], "quat_wxyz": [2, 0, 0, 0]}, "'quat_wxyz': quaternion norm"),
        ({"xyz_m": [0, 0], "quat_wxyz": [1, 0, 0, 0]}, "'xyz_m': must have shape (3,)"),
        ({"board_T_needle": np.eye(4).tolist(), "xyz_m": [0, 0, 0], "quat_wxyz": [1, 0, 0, 0]}, "exactly one"),
        ({}, "exactly one"),
        ({"format": "something-else", "board_T_needle": np.eye(4).tolist()}, "'format'"),
        ({"version": 2, "board_T_needle": np.eye(4).tolist()}, "'version'"),
        ({"board_T_needle": np.eye(4).tolist(), "board": {"squares_x": 4, "squares_y": 4}}, "'board'"),
        ({"board_T_needle": np.eye(4).tolist(), "board": {"square_m": "1mm"}}, "'board.square_m'"),
    ],
)
def test_bad_board_to_needle_files_raise_input_error(tmp_path, doc, where) -> None:
    p = tmp_path / "bad.json"
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(InputError) as exc:
        read_board_to_needle(p)
    assert str(p) in str(exc.value)
    assert where in str(exc.value)
    with pytest.raises(InputError, match="not found"):
        read_board_to_needle(tmp_path / "missing.json")


def _synthetic_run(tmp_path, rng: np.random.Generator):
    """Six frames: four with the board visible, one with it turned away, one without an image."""
    info = RecordingInfo(name="gt", frame_rate_hz=30.0, camera=CAM, needle=NEEDLE)
    low = rng.normal(0.0, 1.0, (10, 10, 3)).astype(np.float32)
    bg = np.clip(np.array([105.0, 115.0, 185.0], np.float32) + 20.0 * cv2.resize(low, (720, 720)), 0, 255)
    bg = bg.astype(np.uint8)
    frames, images, truth = [], {}, {}
    for k in range(6):
        T = np.eye(4)
        T[:3, :3] = so3_exp(np.array([math.radians(35.0), 0.0, 0.0]) + rng.normal(0.0, 0.15, 3))
        T[:3, 3] = [rng.uniform(-0.004, 0.004), rng.uniform(-0.004, 0.004), rng.uniform(0.032, 0.040)]
        if k == 3:  # the needle (and its board) turned over: the board shows its back
            T[:3, :3] = T[:3, :3] @ so3_exp(np.array([math.pi, 0.0, 0.0]))
        truth[k] = T
        if k != 5:
            img = render_board(bg, CAM, T @ DEFAULT_NEEDLE_T_BOARD)
            images[k] = np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)
        frames.append(FrameRecord(frame=k, t_s=k / 30.0, cam_T_needle_gt=T))
    run = write_recording(tmp_path / "run", info, frames, images=images)
    return run, truth


def test_groundtruth_run_rewrites_gt_from_the_board(tmp_path) -> None:
    rng = np.random.default_rng(4)
    run, truth = _synthetic_run(tmp_path, rng)
    b2n = write_board_to_needle(tmp_path / "b2n.json", se3_inverse(np.asarray(DEFAULT_NEEDLE_T_BOARD)))
    stats = groundtruth_run(run, b2n)
    assert (stats.frames, stats.with_image, stats.detected) == (6, 5, 4)
    assert list(stats.compared_frames) == [0, 1, 2, 4]
    rec = read_recording(run)
    for f in rec.frames:
        if f.frame in (3, 5):
            assert f.cam_T_needle_gt is None  # no detection -> empty gt cells
            continue
        t_mm, r_deg = _errors(f.cam_T_needle_gt, truth[f.frame])
        assert t_mm < 0.1 and r_deg < 1.0
    # the comparison with the previous (true) gt is what the rewritten columns say
    recomputed = [_errors(f.cam_T_needle_gt, truth[f.frame]) for f in rec.frames if f.frame in (0, 1, 2, 4)]
    np.testing.assert_allclose(stats.trans_err_mm, [e[0] for e in recomputed], atol=1e-6)
    np.testing.assert_allclose(stats.rot_err_deg, [e[1] for e in recomputed], atol=1e-5)
    assert stats.trans_summary_mm["max"] == pytest.approx(max(e[0] for e in recomputed), abs=1e-6)
    text = stats.describe()
    assert "detected in 4" in text and "translation [mm]" in text and "p95" in text
    # running it again compares against the checkerboard gt just written: identical poses
    again = groundtruth_run(run, b2n)
    assert again.detected == 4 and again.trans_err_mm.max() < 1e-6 and again.rot_err_deg.max() < 1e-4


def test_groundtruth_run_without_images_is_an_input_error(tmp_path) -> None:
    info = RecordingInfo(name="noimg", frame_rate_hz=30.0, camera=CAM, needle=NEEDLE)
    run = write_recording(tmp_path / "noimg", info, [FrameRecord(frame=0, t_s=0.0)])
    b2n = write_board_to_needle(tmp_path / "b2n.json")
    with pytest.raises(InputError, match="no camera images") as exc:
        groundtruth_run(run, b2n)
    assert str(run) in str(exc.value)


def test_groundtruth_on_a_simulated_run(tmp_path) -> None:
    from pinpoint_fg.sim.scenarios import simulate

    run = simulate("normal", n_frames=6, seed=1, out=tmp_path / "sim", images=True)
    truth = {f.frame: f.cam_T_needle_gt for f in read_recording(run).frames}
    stats = groundtruth_run(run, write_board_to_needle(tmp_path / "b2n.json"))
    assert stats.with_image == 6 and stats.detected >= 5
    assert stats.trans_err_mm.max() < 0.1 and stats.rot_err_deg.max() < 0.5
    for f in read_recording(run).frames:
        if f.cam_T_needle_gt is not None:
            t_mm, r_deg = _errors(f.cam_T_needle_gt, truth[f.frame])
            assert t_mm < 0.1 and r_deg < 0.5
