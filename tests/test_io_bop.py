"""BOP import: a small BOP scene written by the tests, converted, checked against its construction."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from factors.lie import local
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.bop import BopImportConfig, import_bop
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.validator import validate_run
from pinpoint_fg.io.result.reader import read_result
from tests.bop_scene import CAMERA, NEEDLE_OBJ_ID, NEEDLE_RGB, write_bop_scene

N_IMAGES = 8


@pytest.fixture(scope="module")
def bop(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("bop")
    info = write_bop_scene(root / "dataset", n_images=N_IMAGES)
    run = root / "run"
    summary = import_bop(info["scene"], info["model"], run, BopImportConfig(obj_id=NEEDLE_OBJ_ID))
    return {**info, "root": root, "run": run, "summary": summary}


def _import(bop: dict, out: Path, **kwargs) -> Path:
    import_bop(bop["scene"], bop["model"], out, BopImportConfig(obj_id=NEEDLE_OBJ_ID, **kwargs))
    return out


def test_imported_run_is_valid_and_matches_the_construction(bop: dict) -> None:
    recording, errors = validate_run(bop["run"])
    assert errors == [] and recording is not None
    info = recording.info
    assert (info.camera.width, info.camera.height) == (640, 480)
    np.testing.assert_array_equal(info.camera.K, CAMERA.K)
    assert not info.camera.has_distortion and info.frame_rate_hz == 30.0
    truth = bop["truth"]
    assert info.needle.radius_m == pytest.approx(truth.radius_m, abs=2e-9)
    assert info.needle.tail_angle_rad == 0.0
    assert info.needle.tip_angle_rad == pytest.approx(truth.arc_rad, abs=2e-7)
    assert info.needle.wire_diameter_m == pytest.approx(2 * truth.wire_m, rel=1e-6)
    extra = info.extra["bop_import"]
    assert extra["obj_id"] == NEEDLE_OBJ_ID and extra["tip_from"] == "taper"
    assert extra["keypoints"] == {"source": "none"}
    np.testing.assert_allclose(extra["model_T_needle"], truth.model_T_needle, atol=2e-7)
    assert [f.frame for f in recording.frames] == list(range(N_IMAGES))
    assert [f.t_s for f in recording.frames] == pytest.approx([k / 30.0 for k in range(N_IMAGES)])
    for f in recording.frames:
        assert f.tip_px is None and f.tail_px is None and f.cam_T_grasper is None
        assert f.image is not None
        if f.frame in bop["without_needle"]:
            assert f.cam_T_needle_gt is None and f.mask is None
            continue
        xi = local(bop["poses"][f.frame], f.cam_T_needle_gt)
        assert np.linalg.norm(xi[:3]) < 1e-6 and np.linalg.norm(xi[3:]) < 1e-8
        src = cv2.imread(str(bop["scene"] / "mask_visib" / f"{f.frame:06d}_000001.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(recording.load_mask(f) != 0, src != 0)
    img = recording.load_image(recording.frames[0])
    np.testing.assert_array_equal(img, cv2.imread(str(bop["scene"] / "rgb" / "000000.png"), cv2.IMREAD_UNCHANGED))
    s = bop["summary"]
    assert (s.frames, s.with_gt, s.with_mask, s.with_keypoints) == (N_IMAGES, N_IMAGES - 1, N_IMAGES - 1, 0)


def _on_mask_share(recording, frame, T: np.ndarray) -> float:
    needle = recording.info.needle
    p = needle.arc_points(300) @ T[:3, :3].T + T[:3, 3]
    px = np.rint(recording.info.camera.project(p)).astype(int)
    mask = recording.load_mask(frame)
    inside = (px[:, 0] >= 0) & (px[:, 0] < mask.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < mask.shape[0])
    hit = np.zeros(len(px), bool)
    hit[inside] = mask[px[inside, 1], px[inside, 0]] != 0
    return float(hit.mean())


def test_converted_poses_project_the_needle_onto_its_mask(bop: dict) -> None:
    recording = read_recording(bop["run"])
    gt_frames = [f for f in recording.frames if f.cam_T_needle_gt is not None]
    assert len(gt_frames) == N_IMAGES - 1
    for f in gt_frames:
        assert _on_mask_share(recording, f, f.cam_T_needle_gt) == 1.0
        # the model pose itself (without model_T_needle) misses: the conversion is what makes it fit
        model_T_needle = np.asarray(recording.info.extra["bop_import"]["model_T_needle"])
        cam_T_model = f.cam_T_needle_gt @ np.linalg.inv(model_T_needle)
        assert _on_mask_share(recording, f, cam_T_model) < 0.5


def test_synthetic_keypoints_from_ground_truth(bop: dict, tmp_path: Path) -> None:
    exact = read_recording(_import(bop, tmp_path / "k0", keypoints_sigma_px=0.0, images=False))
    for f in exact.frames:
        if f.cam_T_needle_gt is None:
            assert f.tip_px is None and f.tail_px is None
            continue
        T, needle = bop["poses"][f.frame], bop["truth"].needle
        np.testing.assert_allclose(f.tip_px, CAMERA.project(T[:3, :3] @ needle.point(needle.tip_angle_rad) + T[:3, 3]),
                                   atol=1e-5)
        np.testing.assert_allclose(f.tail_px, CAMERA.project(T[:3, 3] + T[:3, :3] @ needle.tail_m), atol=1e-5)
        assert f.image is None
    assert exact.info.extra["bop_import"]["keypoints"]["source"].startswith("synthetic")
    a = read_recording(_import(bop, tmp_path / "k1", keypoints_sigma_px=2.0, seed=4, images=False))
    b = read_recording(_import(bop, tmp_path / "k2", keypoints_sigma_px=2.0, seed=4, images=False))
    c = read_recording(_import(bop, tmp_path / "k3", keypoints_sigma_px=2.0, seed=5, images=False))
    dev = np.array([fa.tip_px - fe.tip_px for fa, fe in zip(a.frames, exact.frames, strict=True)
                    if fe.tip_px is not None])
    assert 0.0 < np.abs(dev).max() < 10.0
    assert all(np.array_equal(fa.tip_px, fb.tip_px) for fa, fb in zip(a.frames, b.frames, strict=True)
               if fa.tip_px is not None)
    assert not np.array_equal(a.frames[0].tip_px, c.frames[0].tip_px)
    assert a.info.extra["bop_import"]["keypoints"] == {
        "source": a.info.extra["bop_import"]["keypoints"]["source"], "sigma_px": 2.0, "seed": 4}


def test_colour_label_masks(bop: dict, tmp_path: Path) -> None:
    rec = read_recording(_import(bop, tmp_path / "c", mask_dir="labels", mask_color=NEEDLE_RGB, images=False))
    ref = read_recording(bop["run"])
    for f, g in zip(rec.frames, ref.frames, strict=True):
        assert (f.mask is None) == (g.mask is None)
        if f.mask is not None:
            np.testing.assert_array_equal(rec.load_mask(f), ref.load_mask(g))


def test_several_instances_need_a_choice(bop: dict, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(bop["scene"], scene)
    gt = json.loads((scene / "scene_gt.json").read_text())
    moved = dict(gt["2"][1])
    moved["cam_t_m2c"] = [v + 1.0 for v in moved["cam_t_m2c"]]
    gt["2"].append(moved)
    shutil.copy(scene / "mask_visib" / "000002_000001.png", scene / "mask_visib" / "000002_000002.png")
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    cfg = BopImportConfig(obj_id=NEEDLE_OBJ_ID, images=False)
    with pytest.raises(InputError, match=r"2 entries of obj_id 7 in one image; choose one with --instance") as e:
        import_bop(scene, bop["model"], tmp_path / "a", cfg)
    assert "scene_gt.json" in str(e.value) and "'2'" in str(e.value)
    import_bop(scene, bop["model"], tmp_path / "b", BopImportConfig(obj_id=NEEDLE_OBJ_ID, images=False, instance=1))
    frames = read_recording(tmp_path / "b").frames
    assert [f.frame for f in frames if f.cam_T_needle_gt is not None] == [2]
    np.testing.assert_allclose(frames[2].cam_T_needle_gt[:3, 3] - bop["poses"][2][:3, 3], [1e-3] * 3, atol=1e-9)


@pytest.mark.slow
def test_map_tracker_runs_on_the_imported_run(bop: dict, tmp_path: Path) -> None:
    run = _import(bop, tmp_path / "kp", keypoints_sigma_px=1.0, seed=1)
    out = tmp_path / "map"
    assert main(["track", str(run), "--method", "map", "--out", str(out)]) == 0
    res = read_result(out)
    rec = read_recording(run)
    errs = [local(f.cam_T_needle_gt, T) for f, T in zip(rec.frames, res.cam_T_needle, strict=True)
            if f.cam_T_needle_gt is not None]
    e_t = np.array([np.linalg.norm(xi[3:]) for xi in errs])
    e_r = np.array([np.linalg.norm(xi[:3]) for xi in errs])
    assert len(errs) == N_IMAGES - 1
    assert e_t.mean() < 0.75e-3 and np.degrees(e_r.mean()) < 3.0


# ----------------------------------------------------------------------------------------- errors


def _broken_copy(bop: dict, tmp_path: Path, edit) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(bop["scene"], scene)
    edit(scene)
    return scene


def _edit_json(name: str, change):
    def edit(scene: Path) -> None:
        doc = json.loads((scene / name).read_text())
        change(doc)
        (scene / name).write_text(json.dumps(doc))
    return edit


def _set(doc: dict, keys: tuple, value) -> None:
    for k in keys[:-1]:
        doc = doc[k]
    doc[keys[-1]] = value


SCALED_R = [1, 0, 0, 0, 1, 0, 0, 0, 2]

ERROR_CASES = {
    "missing scene_gt": (lambda s: (s / "scene_gt.json").unlink(), [], r"scene_gt\.json: file not found"),
    "malformed json": (lambda s: (s / "scene_camera.json").write_text('{"0": {"cam_K": [1, 2,}'), [],
                       r"scene_camera\.json: not valid JSON: .* at line 1, column"),
    "wrong obj id": (lambda s: None, ["--obj-id", "99"],
                     r"scene_gt\.json: no entry has obj_id 99 \(obj_ids present: 3, 7\)"),
    "not a rotation": (_edit_json("scene_gt.json", lambda d: _set(d, ("3", 1, "cam_R_m2c"), SCALED_R)),
                       [], r"scene_gt\.json: column '3\[1\]\.cam_R_m2c': not a rotation matrix"),
    "short translation": (_edit_json("scene_gt.json", lambda d: _set(d, ("4", 1, "cam_t_m2c"), [1, 2])), [],
                          r"column '4\[1\]\.cam_t_m2c': must be a list of 3 numbers"),
    "bad im_id": (_edit_json("scene_gt.json", lambda d: _set(d, ("frame9",), [])), [],
                  r"column 'frame9': image ids"),
    "two cameras": (_edit_json("scene_camera.json", lambda d: _set(d, ("6", "cam_K", 0), 700.0)), [],
                    r"column '6\.cam_K': differs from image 0's"),
    "missing mask": (lambda s: (s / "mask_visib" / "000004_000001.png").unlink(), [],
                     r"mask_visib/000004_000001\.png: file not found"),
    "missing image": (lambda s: (s / "rgb" / "000003.png").unlink(), [], r"no image for im_id 3"),
    "colour not found": (lambda s: None, ["--mask-dir", "labels", "--mask-color", "1,2,3"],
                         r"labels: no pixel has the needle's colour \(R,G,B\) = \(1, 2, 3\)"),
    "unknown mask dir": (lambda s: None, ["--mask-dir", "nope"], r"nope: mask directory not found"),
    "mis-sized image": (lambda s: cv2.imwrite(str(s / "rgb" / "000002.png"), np.zeros((10, 10), np.uint8)), [],
                        r"000002\.png: image is 10x10 px but the scene's images are 640x480 px"),
}


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_malformed_scene_gives_one_line_and_exit_2(bop: dict, tmp_path: Path, case: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    edit, extra_args, pattern = ERROR_CASES[case]
    scene = _broken_copy(bop, tmp_path, edit)
    args = ["import-bop", str(scene), "--model", str(bop["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
            "--out", str(tmp_path / "out"), *extra_args]
    assert main(args) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err
    import re

    assert re.search(pattern, lines[0]), lines[0]


def test_cube_model_and_existing_output_are_rejected(bop: dict, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from tests.bop_scene import write_ply
    from tests.test_io_needle_mesh import _cube

    cube = write_ply(tmp_path / "cube.ply", _cube())
    base = ["import-bop", str(bop["scene"]), "--obj-id", str(NEEDLE_OBJ_ID)]
    assert main([*base, "--model", str(cube), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cube.ply: not a needle mesh" in err[0]
    assert main([*base, "--model", str(bop["model"]), "--out", str(bop["run"])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out is not empty" in err[0]
    with pytest.raises(SystemExit) as exit_info:  # argparse's own one-line usage error
        main([*base, "--model", str(bop["model"]), "--out", str(tmp_path / "o2"), "--mask-color", "1,2"])
    assert exit_info.value.code == 2 and "expected R,G,B" in capsys.readouterr().err


def test_cli_import_then_validate(bop: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    assert main(["import-bop", str(bop["scene"]), "--model", str(bop["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(out), "--keypoints-from-gt", "1.0", "--fps", "10", "--no-images"]) == 0
    text = capsys.readouterr().out
    assert "8 frames, ground truth in 7, masks in 7, synthetic keypoints in 7" in text
    assert "tip by taper" in text
    assert main(["validate", str(out)]) == 0
    rec = read_recording(out)
    assert rec.info.frame_rate_hz == 10.0 and rec.frames[3].t_s == pytest.approx(0.3)


@pytest.mark.parametrize("sigma", ["1e308", "-1", "nan"])
def test_cli_refuses_keypoint_noise_off_any_image(bop: dict, tmp_path: Path, sigma: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "kp"
    assert main(["import-bop", str(bop["scene"]), "--model", str(bop["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(out), "--keypoints-from-gt", sigma, "--no-images"]) == 2  # 1e308: exit 0, no keypoints
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--keypoints-from-gt" in err
    assert not out.exists() or not any(out.iterdir())


def test_cli_refuses_a_grasp_off_the_needle(bop: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "off"
    assert main(["import-bop", str(bop["scene"]), "--model", str(bop["model"]), "--obj-id", str(NEEDLE_OBJ_ID),
                 "--out", str(out), "--grasp-angle-rad", "5.0", "--no-images"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "not on the arc" in err and "--grasp-angle-rad 5.0" in err
    assert not out.exists() or not any(out.iterdir())


def test_gray_jpeg_images_and_no_camera_extras(bop: dict, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(bop["scene"], scene)
    (scene / "gray").mkdir()
    for p in sorted((scene / "rgb").glob("*.png")):
        grey = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(scene / "gray" / (p.stem + ".jpg")), grey)
    shutil.rmtree(scene / "rgb")
    cams = json.loads((scene / "scene_camera.json").read_text())
    for entry in cams.values():  # world-to-camera extrinsics are allowed and ignored
        entry.update({"cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_w2c": [0, 0, 0]})
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    import_bop(scene, bop["model"], tmp_path / "g", BopImportConfig(obj_id=NEEDLE_OBJ_ID))
    rec = read_recording(tmp_path / "g")
    img = rec.load_image(rec.frames[1])
    assert img.shape == (480, 640)
    np.testing.assert_array_equal(img, cv2.imread(str(scene / "gray" / "000001.jpg"), cv2.IMREAD_UNCHANGED))
