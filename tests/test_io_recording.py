"""Recorded-run format v1: writer/reader round trip, every kind of malformation, the CLI's validate."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.columns import near_miss_columns
from pinpoint_fg.io.recording.png import png_size
from pinpoint_fg.io.recording.reader import read_recording, summarize_recording, unknown_columns_note
from pinpoint_fg.io.recording.schema import KNOWN_COLUMNS, QUAT_NORM_TOL, FrameRecord, Recording, RecordingInfo
from pinpoint_fg.io.recording.validator import validate_run
from pinpoint_fg.io.recording.writer import RecordingWriter, replace_ground_truth, write_recording

W, H = 40, 30  # a small camera keeps the PNGs tiny


def make_info() -> RecordingInfo:
    cam = PinholeCamera(60.0, 61.0, 19.5, 14.5, width=W, height=H, distortion=(0.1, -0.01, 0.001, 0.0, 0.0))
    needle = NeedleModel(radius_m=0.005, grasp_angle_rad=0.9)
    return RecordingInfo(name="unit-run", frame_rate_hz=30.0, camera=cam, needle=needle, extra={"site": "bench"})


def in_front(T: np.ndarray) -> np.ndarray:
    """``T`` moved in front of the camera (z = |z| + 5 cm): ground truth behind it is refused by the reader."""
    T = np.array(T, dtype=float)
    T[2, 3] = abs(T[2, 3]) + 0.05
    return T


def make_frames(n: int = 6, seed: int = 0):
    """Frames with every group present on some rows and missing on others, plus masks and images."""
    rng = np.random.default_rng(seed)
    frames, masks, images = [], {}, {}
    labels = ["none", "partial", "heavy", None]
    for i in range(n):
        k = 2 * i + 3  # non-contiguous frame indices
        frames.append(
            FrameRecord(
                frame=k,
                t_s=k / 30.0,
                tip_px=rng.normal(20.0, 5.0, size=2) if i % 2 == 0 else None,
                tail_px=rng.normal(20.0, 5.0, size=2) if i % 3 != 1 else None,
                cam_T_grasper=se3_exp(rng.normal(size=6) * 0.3) if i != 4 else None,
                cam_T_needle_gt=in_front(se3_exp(rng.normal(size=6) * 0.3)) if i < 4 else None,
                occlusion=labels[i % 4],
            )
        )
        if i % 3 == 0:
            masks[k] = rng.random((H, W)) > 0.8
        if i in (1, 2):
            images[k] = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    return frames, masks, images


@pytest.fixture()
def run(tmp_path: Path):
    frames, masks, images = make_frames()
    root = write_recording(tmp_path / "run", make_info(), frames, masks, images)
    return root, frames, masks, images


def rewrite_csv(root: Path, edit) -> None:
    """Apply ``edit(header, rows)`` (lists of str, mutated in place) to frames.csv."""
    path = root / "frames.csv"
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    edit(rows[0], rows[1:])
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def set_cell(root: Path, data_row: int, column: str, value: str) -> None:
    def edit(header, rows):
        rows[data_row - 1][header.index(column)] = value

    rewrite_csv(root, edit)


def edit_json(root: Path, edit) -> None:
    path = root / "recording.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def the_error(root: Path) -> InputError:
    recording, errors = validate_run(root)
    assert recording is None
    assert len(errors) == 1, [str(e) for e in errors]
    return errors[0]


def assert_located(err: InputError, file_name: str, row: int | None, column: str) -> None:
    """The error names the file, the row (or JSON key) and the column, both as attributes and in text."""
    text = str(err)
    assert Path(err.file).name == file_name and file_name in text
    assert err.row == row
    if row is not None:
        assert f"row {row}:" in text
    assert err.column == column and repr(column) in text


# ---------------------------------------------------------------------------------------------
# round trip
# ---------------------------------------------------------------------------------------------


def test_round_trip_with_masks_images_and_missing_groups(run) -> None:
    root, frames, masks, images = run
    rec = read_recording(root)
    assert isinstance(rec, Recording) and len(rec) == len(frames)
    info = make_info()
    assert rec.info.name == info.name and rec.info.frame_rate_hz == info.frame_rate_hz
    assert rec.info.camera == info.camera and rec.info.needle == info.needle
    assert rec.info.extra == {"site": "bench"}
    for want, got in zip(frames, rec.frames, strict=True):
        assert got.frame == want.frame and got.t_s == want.t_s  # repr floats: bit-exact
        assert got.occlusion == want.occlusion
        for name in ("tip_px", "tail_px"):
            a, b = getattr(want, name), getattr(got, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert np.array_equal(a, b)
        for name in ("cam_T_grasper", "cam_T_needle_gt"):
            a, b = getattr(want, name), getattr(got, name)
            assert (a is None) == (b is None)
            if a is not None:  # through a unit quaternion: equal up to a few ulp
                np.testing.assert_allclose(b, a, rtol=0, atol=2e-15)
        if want.frame in masks:
            assert got.mask == f"masks/{want.frame:06d}.png"
            m = rec.load_mask(got)
            assert m.dtype == bool and m.shape == (H, W)
            assert np.array_equal(m, masks[want.frame])
        else:
            assert got.mask is None and rec.mask_path(got) is None and rec.load_mask(got) is None
        if want.frame in images:
            assert rec.image_path(got) == root / f"images/{want.frame:06d}.png"
            assert np.array_equal(rec.load_image(got), images[want.frame])
        else:
            assert got.image is None and rec.load_image(got) is None
    assert rec.has_ground_truth


def test_writer_is_incremental_and_rejects_bad_frames(tmp_path: Path) -> None:
    frames, masks, _ = make_frames(3)
    with RecordingWriter(tmp_path / "r", make_info()) as w:
        out = w.add(frames[0], mask=masks[frames[0].frame])
        assert out.mask == f"masks/{frames[0].frame:06d}.png"
        # the row is on disk before close: the partial run is already valid
        assert len(read_recording(tmp_path / "r")) == 1
        with pytest.raises(ValueError, match="not greater"):
            w.add(frames[0])
        with pytest.raises(ValueError, match="mask must have shape"):
            w.add(frames[1], mask=np.zeros((W, H)))
        with pytest.raises(ValueError, match="occlusion"):
            w.add(FrameRecord(frame=100, t_s=1.0, occlusion="light"))
        with pytest.raises(ValueError, match="proper rotation"):
            w.add(FrameRecord(frame=100, t_s=1.0, cam_T_grasper=2.0 * np.eye(4)))
        with pytest.raises(ValueError, match=r"\.\."):
            w.add(FrameRecord(frame=100, t_s=1.0, mask="../x.png"))
        w.add(frames[1])
    assert w.closed
    assert [f.frame for f in read_recording(tmp_path / "r").frames] == [frames[0].frame, frames[1].frame]


def test_extra_columns_and_keys_are_ignored(run) -> None:
    root, frames, _, _ = run
    before = read_recording(root)

    def edit(header, rows):
        header.insert(3, "detector_score")
        header.append("notes")
        for i, r in enumerate(rows):
            r.insert(3, "not-a-number" if i == 0 else str(0.5 + i))
            r.append("free text, with a comma")

    rewrite_csv(root, edit)
    edit_json(root, lambda d: (d.update(operator="x", version=1), d["camera"].update(serial="A1")))
    after = read_recording(root)
    assert after.info.extra == {"site": "bench", "operator": "x"}
    assert after.info.camera == before.info.camera
    for a, b in zip(before.frames, after.frames, strict=True):
        assert a.frame == b.frame and a.t_s == b.t_s and a.mask == b.mask
        assert np.array_equal(a.tip_px, b.tip_px) if a.tip_px is not None else b.tip_px is None


def test_replace_ground_truth_keeps_every_other_cell(run) -> None:
    root, frames, _, _ = run

    def add_extra(header, rows):
        header.append("operator_note")
        for i, r in enumerate(rows):
            r.append(f"note {i}")

    rewrite_csv(root, add_extra)
    with open(root / "frames.csv", newline="") as f:
        old = list(csv.reader(f))
    rng = np.random.default_rng(5)
    new_gt = {frames[0].frame: in_front(se3_exp(rng.normal(size=6))), frames[1].frame: None,
              frames[5].frame: in_front(np.eye(4))}
    replace_ground_truth(root, new_gt)
    with open(root / "frames.csv", newline="") as f:
        new = list(csv.reader(f))
    assert new[0] == old[0]
    gt_idx = [i for i, c in enumerate(old[0]) if c.startswith("gt_")]
    for o, n in zip(old[1:], new[1:], strict=True):
        assert [c for i, c in enumerate(o) if i not in gt_idx] == [c for i, c in enumerate(n) if i not in gt_idx]
    rec = read_recording(root)
    np.testing.assert_allclose(rec.frames[0].cam_T_needle_gt, new_gt[frames[0].frame], atol=2e-15)
    assert rec.frames[1].cam_T_needle_gt is None
    np.testing.assert_array_equal(rec.frames[5].cam_T_needle_gt, in_front(np.eye(4)))
    # untouched frames keep their ground truth
    np.testing.assert_allclose(rec.frames[2].cam_T_needle_gt, frames[2].cam_T_needle_gt, atol=2e-15)
    assert not list(root.glob(".*tmp"))
    with pytest.raises(ValueError, match="not in"):
        replace_ground_truth(root, {999: np.eye(4)})


def test_replace_ground_truth_adds_missing_columns(tmp_path: Path) -> None:
    root = tmp_path / "r"
    write_recording(root, make_info(), [FrameRecord(0, 0.0), FrameRecord(1, 0.1)])

    def drop_gt(header, rows):
        keep = [i for i, c in enumerate(header) if not c.startswith("gt_")]
        header[:] = [header[i] for i in keep]
        for r in rows:
            r[:] = [r[i] for i in keep]

    rewrite_csv(root, drop_gt)
    assert read_recording(root).frames[1].cam_T_needle_gt is None
    replace_ground_truth(root, {1: in_front(np.eye(4))})
    rec = read_recording(root)
    assert rec.frames[0].cam_T_needle_gt is None
    np.testing.assert_array_equal(rec.frames[1].cam_T_needle_gt, in_front(np.eye(4)))
    with pytest.raises(InputError, match="not in front of the camera"):  # what the reader refuses is not written
        replace_ground_truth(root, {1: np.eye(4)})
    np.testing.assert_array_equal(read_recording(root).frames[1].cam_T_needle_gt, in_front(np.eye(4)))


def test_quaternion_close_to_unit_is_normalised(run) -> None:
    root, frames, _, _ = run
    scale = 1.0 + 0.5 * QUAT_NORM_TOL

    def edit(header, rows):
        for c in ("grasper_qw", "grasper_qx", "grasper_qy", "grasper_qz"):
            rows[0][header.index(c)] = repr(float(rows[0][header.index(c)]) * scale)

    rewrite_csv(root, edit)
    T = read_recording(root).frames[0].cam_T_grasper
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-14)
    np.testing.assert_allclose(T, frames[0].cam_T_grasper, atol=1e-14)


# ---------------------------------------------------------------------------------------------
# malformations: each names the file, the row (or JSON key) and the column
# ---------------------------------------------------------------------------------------------


def test_non_numeric_cell(run) -> None:
    root = run[0]
    set_cell(root, 3, "tip_u_px", "12,5x")
    err = the_error(root)
    assert_located(err, "frames.csv", 3, "tip_u_px")
    assert "not a number" in str(err) and f"frame {run[1][2].frame}" in str(err)


@pytest.mark.parametrize(("column", "value"), [("frame", "\u0664"), ("tip_u_px", "1\u0662.5"), ("gt_y_m", "\uff11")])
def test_digits_other_than_ascii_are_not_numbers(run, column: str, value: str) -> None:
    """Arabic-Indic and full-width digits: Python's int() and float() read them (the frame cell "\u0664" was
    taken as frame 4), but they are not the format's plain decimal numbers."""
    root = run[0]
    set_cell(root, 3, column, value)
    err = validate_run(root)[1][0]
    assert_located(err, "frames.csv", 3, column)


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-Infinity"])
def test_nan_or_inf_cell(run, value: str) -> None:
    root = run[0]
    set_cell(root, 2, "gt_y_m", value)
    err = the_error(root)
    assert_located(err, "frames.csv", 2, "gt_y_m")
    assert "NaN or infinite" in str(err)


def test_half_a_column_group(run) -> None:
    root = run[0]
    set_cell(root, 1, "tip_v_px", "")  # row 1 has a tip: now only tip_u_px is filled
    err = the_error(root)
    assert_located(err, "frames.csv", 1, "tip_v_px")
    assert "all present or all empty" in str(err)


def test_half_a_group_in_the_header(run) -> None:
    root = run[0]

    def edit(header, rows):
        i = header.index("grasper_qz")
        del header[i]
        for r in rows:
            del r[i]

    rewrite_csv(root, edit)
    err = the_error(root)
    assert_located(err, "frames.csv", None, "grasper_qz")
    assert "header" in str(err)


def test_frames_not_strictly_increasing(run) -> None:
    root, frames = run[0], run[1]
    set_cell(root, 4, "frame", str(frames[2].frame))
    err = the_error(root)
    assert_located(err, "frames.csv", 4, "frame")
    assert "strictly increasing" in str(err)


def test_frame_not_an_integer(run) -> None:
    root = run[0]
    set_cell(root, 2, "frame", "5.0")
    err = validate_run(root)[1][0]
    assert_located(err, "frames.csv", 2, "frame")


@pytest.mark.parametrize("kind", ["dotdot", "absolute", "symlink", "missing", "backslash", "directory", "fifo"])
def test_mask_path_must_stay_inside_the_run(run, tmp_path: Path, kind: str) -> None:
    root = run[0]
    outside = tmp_path / "outside.png"
    cv2.imwrite(str(outside), np.zeros((H, W), np.uint8))
    if kind == "dotdot":
        value = "../outside.png"
    elif kind == "absolute":
        value = str(outside)
    elif kind == "symlink":
        os.symlink(outside, root / "masks" / "link.png")
        value = "masks/link.png"
    elif kind == "missing":
        value = "masks/nope.png"
    elif kind == "directory":
        value = "masks"
    elif kind == "fifo":
        os.mkfifo(root / "masks" / "pipe.png")  # never opened: a reader would block on it
        value = "masks/pipe.png"
    else:
        value = "masks\\000003.png"
    set_cell(root, 1, "mask", value)
    err = the_error(root)
    assert_located(err, "frames.csv", 1, "mask")
    expected = {"dotdot": "'..'", "absolute": "absolute", "symlink": "outside the run",
                "missing": "no such file", "backslash": "backslash", "directory": "not a regular file",
                "fifo": "not a regular file"}[kind]
    assert expected in str(err)


def test_image_path_escaping_is_reported_on_the_image_column(run) -> None:
    root = run[0]
    set_cell(root, 2, "image", "images/../../x.png")
    assert_located(the_error(root), "frames.csv", 2, "image")


@pytest.mark.parametrize("damage", ["truncate", "bitflip", "not_png"])
def test_corrupt_mask_png(run, damage: str) -> None:
    root, frames = run[0], run[1]
    png = root / "masks" / f"{frames[3].frame:06d}.png"  # data row 4
    data = png.read_bytes()
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "bitflip":
        i = len(data) - 20  # inside the IDAT payload
        data = data[:i] + bytes([data[i] ^ 0x10]) + data[i + 1 :]
    else:
        data = b"GIF89a" + data[6:]
    png.write_bytes(data)
    err = the_error(root)
    assert_located(err, "frames.csv", 4, "mask")
    assert str(png) in str(err)


def test_wrong_size_png(run) -> None:
    root, frames = run[0], run[1]
    png = root / "masks" / f"{frames[0].frame:06d}.png"
    cv2.imwrite(str(png), np.zeros((H, W + 1), np.uint8))
    err = the_error(root)
    assert_located(err, "frames.csv", 1, "mask")
    assert str(png) in str(err) and f"{W + 1}x{H}" in str(err)


def test_wrong_size_image(run) -> None:
    root, frames = run[0], run[1]
    png = root / "images" / f"{frames[1].frame:06d}.png"
    cv2.imwrite(str(png), np.zeros((H + 2, W, 3), np.uint8))
    assert_located(the_error(root), "frames.csv", 2, "image")


def test_load_mask_reports_a_png_damaged_after_validation(run) -> None:
    root, frames = run[0], run[1]
    rec = read_recording(root)
    png = root / "masks" / f"{frames[3].frame:06d}.png"
    png.write_bytes(png.read_bytes()[:40])
    with pytest.raises(InputError) as info:
        rec.load_mask(rec.frames[3])
    assert_located(info.value, "frames.csv", 4, "mask")
    assert str(png) in str(info.value)


@pytest.mark.parametrize(
    ("key", "edit"),
    [
        ("camera.fx", lambda d: d["camera"].pop("fx")),
        ("needle.radius_m", lambda d: d["needle"].pop("radius_m")),
        ("frame_rate_hz", lambda d: d.pop("frame_rate_hz")),
        ("camera.distortion", lambda d: d["camera"].pop("distortion")),
    ],
)
def test_missing_json_key(run, key: str, edit) -> None:
    root = run[0]
    edit_json(root, edit)
    err = the_error(root)
    assert_located(err, "recording.json", None, key)
    assert "missing required key" in str(err)


@pytest.mark.parametrize(
    ("key", "edit", "words"),
    [
        ("camera.width", lambda d: d["camera"].update(width="40"), "integer"),
        ("camera.height", lambda d: d["camera"].update(height=30.5), "integer"),
        ("camera.fx", lambda d: d["camera"].update(fx=0.0), "> 0"),
        # a tiny positive focal length made every undistorted keypoint infinite: a traceback in track
        ("camera.fy", lambda d: d["camera"].update(fy=1e-300), "out of range"),
        # within every coefficient's bound, but OpenCV's inverse of this rational model is NaN on the image
        ("camera.distortion", lambda d: d["camera"].update(distortion=[0.0] * 7 + [1e6]), "cannot be inverted"),
        ("camera.cy", lambda d: d["camera"].update(cy=True), "number"),
        ("camera.distortion", lambda d: d["camera"].update(distortion=[0.1, 0.2, 0.3]), "coefficients"),
        ("camera", lambda d: d.update(camera=[1, 2]), "object"),
        ("needle.tip_angle_rad", lambda d: d["needle"].update(tip_angle_rad="3/4 pi"), "number"),
        ("needle", lambda d: d["needle"].update(tip_angle_rad=0.0), "differ"),
        ("needle", lambda d: d["needle"].update(grasp_angle_rad=-1.0), "not on the arc"),  # were accepted
        ("needle", lambda d: d["needle"].update(tip_angle_rad=6.5), "full circle"),
        ("needle", lambda d: d["needle"].update(wire_diameter_m=0.02), "twice radius_m"),
        # a unit mistake (um typed as m) put the tracked needle at a depth of nanometres
        ("needle.radius_m", lambda d: d["needle"].update(radius_m=1e-33), "out of range"),
        ("needle.wire_diameter_m", lambda d: d["needle"].update(wire_diameter_m=4e-10), "out of range"),
        ("format", lambda d: d.update(format="something-else"), "pinpoint-recording"),
        ("version", lambda d: d.update(version=2), "unsupported"),
        ("name", lambda d: d.update(name=""), "non-empty"),
    ],
)
def test_wrong_json_values(run, key: str, edit, words: str) -> None:
    root = run[0]
    edit_json(root, edit)
    err = the_error(root)
    assert_located(err, "recording.json", None, key)
    assert words in str(err)


def test_invalid_json_and_missing_files(run) -> None:
    root = run[0]
    (root / "recording.json").write_text('{"format": "pinpoint-recording",')
    errors = validate_run(root)[1]
    assert "not valid JSON" in str(errors[0]) and Path(errors[0].file).name == "recording.json"
    (root / "frames.csv").unlink()
    errors = validate_run(root)[1]
    assert any(Path(e.file).name == "frames.csv" and "not found" in str(e) for e in errors)
    assert validate_run(root / "nowhere")[1][0].reason.startswith("not a directory")


def test_unknown_occlusion_label(run) -> None:
    root = run[0]
    set_cell(root, 2, "occlusion", "Partial")
    err = the_error(root)
    assert_located(err, "frames.csv", 2, "occlusion")
    assert "none, partial, heavy" in str(err)


def test_quaternion_norm_far_from_one(run) -> None:
    root = run[0]

    def edit(header, rows):
        for c in ("gt_qw", "gt_qx", "gt_qy", "gt_qz"):
            rows[2][header.index(c)] = repr(float(rows[2][header.index(c)]) * 1.05)

    rewrite_csv(root, edit)
    err = the_error(root)
    assert_located(err, "frames.csv", 3, "gt_qw")
    assert "norm 1.05" in str(err)


def test_wrong_number_of_cells(run) -> None:
    root = run[0]
    rewrite_csv(root, lambda header, rows: rows[1].pop())
    err = the_error(root)
    assert Path(err.file).name == "frames.csv" and err.row == 2 and "cells" in str(err)


def test_every_error_is_collected_in_file_order(run) -> None:
    root = run[0]
    set_cell(root, 1, "t_s", "soon")
    set_cell(root, 3, "occlusion", "total")
    set_cell(root, 6, "tail_u_px", "nan")
    edit_json(root, lambda d: d["camera"].pop("cx"))
    _, errors = validate_run(root)
    located = [(Path(e.file).name, e.row, e.column) for e in errors]
    assert located == [
        ("recording.json", None, "camera.cx"),
        ("frames.csv", 1, "t_s"),
        ("frames.csv", 3, "occlusion"),
        ("frames.csv", 6, "tail_u_px"),
    ]
    with pytest.raises(InputError) as info:
        read_recording(root)
    assert str(info.value) == str(errors[0])


def test_blank_lines_do_not_count_as_rows(run) -> None:
    root = run[0]
    text = (root / "frames.csv").read_text().splitlines(keepends=True)
    (root / "frames.csv").write_text("".join(text[:2] + ["\n"] + text[2:] + ["\n"]))
    assert len(read_recording(root)) == len(run[1])
    text = (root / "frames.csv").read_text().splitlines(keepends=True)
    text[4] = text[4].replace(",", ",x", 1)  # file line 5 = data row 3 (frame 7): its t_s is now 'x0.2...'
    (root / "frames.csv").write_text("".join(text))
    err = the_error(root)
    assert err.row == 3 and err.column == "t_s" and "(frame 7, file line 5)" in str(err)


def test_png_size_reads_the_header() -> None:
    ok, buf = cv2.imencode(".png", np.zeros((7, 9), np.uint8))
    assert ok and png_size(buf.tobytes()) == (9, 7)


# ---------------------------------------------------------------------------------------------
# summary and the CLI
# ---------------------------------------------------------------------------------------------


def test_summary_lists_counts(run) -> None:
    root, frames, masks, images = run
    text = summarize_recording(read_recording(root))
    assert "unit-run" in text
    assert f"frames       {len(frames)}" in text
    assert f"duration {(frames[-1].t_s - frames[0].t_s):.3f} s" in text and "30 Hz declared" in text
    assert f"mask              {len(masks)}" in text
    assert f"image             {len(images)}" in text
    n_tip = sum(f.tip_px is not None for f in frames)
    assert f"tip               {n_tip}  ({100 * n_tip / len(frames):5.1f} %)" in text
    assert "none 2, partial 2, heavy 1, unlabelled 1" in text


def test_cli_validate_good_run(run, capsys) -> None:
    root = run[0]
    assert main(["validate", str(root)]) == 0
    out = capsys.readouterr().out
    assert "unit-run" in out and "ground truth" in out


def test_cli_validate_bad_run(run, capsys) -> None:
    root = run[0]
    set_cell(root, 3, "tip_u_px", "abc")
    set_cell(root, 2, "occlusion", "lots")
    code = main(["validate", str(root)])
    captured = capsys.readouterr()
    assert code != 0
    assert "Traceback" not in captured.err + captured.out
    assert "row 3: column 'tip_u_px'" in captured.err
    assert "row 2: column 'occlusion'" in captured.err
    assert "2 error(s)" in captured.err


def test_known_columns_cover_the_format() -> None:
    assert KNOWN_COLUMNS[:2] == ("frame", "t_s") and len(KNOWN_COLUMNS) == len(set(KNOWN_COLUMNS)) == 23


# ---------------------------------------------------------------------------------------------
# unknown columns that look like a known one (extra columns stay allowed)
# ---------------------------------------------------------------------------------------------


def rename_columns(root: Path, renames: dict[str, str], add: dict[str, str] | None = None,
                   drop: tuple[str, ...] = ()) -> None:
    """Rename header columns of frames.csv, drop some (with their cells), append ``add`` (column: cell)."""
    def edit(header, rows):
        for name in drop:
            i = header.index(name)
            del header[i]
            for r in rows:
                del r[i]
        for old, new in renames.items():
            header[header.index(old)] = new
        for name, value in (add or {}).items():
            header.append(name)
            for r in rows:
                r.append(value)

    rewrite_csv(root, edit)


def test_renamed_mask_column_is_named_on_a_note(run) -> None:
    """A run whose ``mask`` column was written as ``mask_path`` was valid and tracked without masks, silently."""
    root = run[0]
    rename_columns(root, {"mask": "mask_path"})
    rec = read_recording(root)
    assert all(f.mask is None for f in rec.frames)  # still ignored: the format allows extra columns
    note = unknown_columns_note(rec)
    assert note == (f"note: {root / 'frames.csv'}: column 'mask_path' is not in the format and is ignored "
                    "(did you mean 'mask'?)")


def test_case_mismatch_and_missing_unit_suffix_are_named_on_one_note(run) -> None:
    root = run[0]
    rename_columns(root, {"tip_u_px": "Tip_U_px", "tip_v_px": "TIP_V_PX", "gt_qw": "gt_wq"},
                   drop=("gt_x_m", "gt_y_m", "gt_z_m", "gt_qx", "gt_qy", "gt_qz"))
    rename_columns(root, {"tail_u_px": "tail_u", "tail_v_px": "tail_v"})
    rec = read_recording(root)
    assert all(f.tip_px is None and f.tail_px is None for f in rec.frames)
    note = unknown_columns_note(rec)
    assert note is not None and note.count("\n") == 0 and note.startswith(f"note: {root / 'frames.csv'}: ")
    assert note.endswith(": columns 'Tip_U_px', 'TIP_V_PX', 'tail_u' and 2 more are not in the format and are ignored "
                         "(did you mean 'tip_u_px', 'tip_v_px', 'tail_u_px' (pixels) and 2 more?)")


def test_the_note_names_a_few_columns_each_meant_column_once_and_the_unit_a_look_alike_lacks(run) -> None:
    """A generated header of many look-alikes gave a note of 600,000 characters naming 'mask' over and over."""
    root = run[0]
    rename_columns(root, {"mask": "Mask", "gt_x_m": "gt_x_mm"},
                   drop=tuple(c for c in KNOWN_COLUMNS if c.startswith("gt_") and c != "gt_x_m"),
                   add={f"{c}_{k}": "" for k in range(200) for c in ("mask",)}
                   | {"MASK": "", "mask_path": "", "mask_file": "", "Mask-Path": ""})
    note = unknown_columns_note(read_recording(root))
    assert note is not None and len(note) < 400, note
    assert "'Mask', 'gt_x_mm', 'MASK' and 3 more are not in the format" in note
    assert note.endswith("(did you mean 'mask', 'gt_x_m' (metres)?)")


def test_unrelated_extra_columns_get_no_note(run) -> None:
    """Forward-compatible extras are not near misses, even where a known column is absent (no image, no mask)."""
    root = run[0]
    rename_columns(root, {}, drop=("image", "mask"),
                   add={"surgeon_comment": "ok", "image_exposure_ms": "3.5", "detector_score": "0.9",
                        "masked_ratio": "0.1", "notes": ""})
    assert unknown_columns_note(read_recording(root)) is None


def test_plausible_extra_columns_of_a_missing_group_get_no_note(run) -> None:
    """Without kinematics, ground truth, image or occlusion columns, extras that only resemble them are the user's own
    (each was once suggested as a known column: grasper_id as grasper_qz, occlusion_s as occlusion), and a name
    that resembles several known columns equally (gt_q, grasper_qe) suggests none."""
    root = run[0]
    grasper = [c for c in KNOWN_COLUMNS if c.startswith("grasper_")]
    gt = [c for c in KNOWN_COLUMNS if c.startswith("gt_")]
    extras = ("grasper_id", "grasper_jaw", "grasper_qe", "image_w", "masked", "occlusion_px", "occlusion_s", "gt_q",
              "t_ms", "frame_id", "tip_u_px_std")
    rename_columns(root, {}, drop=(*grasper, *gt, "image", "mask", "occlusion"), add={c: "" for c in extras})
    assert unknown_columns_note(read_recording(root)) is None


def test_no_note_when_the_known_column_is_there_too(run) -> None:
    root = run[0]
    rename_columns(root, {}, add={"mask_path": "x", "Tip_U_px": "1", "occlusions": "none"})
    assert unknown_columns_note(read_recording(root)) is None


def test_near_miss_columns_rules() -> None:
    """Case and separators, a unit or path suffix too many or too few, a typo; the known column must be absent."""
    header = ("frame", "t_s", "MASK", "image_file", "tip_u", "Tip-V-px", "grasper_qww", "gt_wq", "surgeon_comment")
    assert near_miss_columns(header) == {"MASK": "mask", "image_file": "image", "tip_u": "tip_u_px",
                                         "Tip-V-px": "tip_v_px", "grasper_qww": "grasper_qw", "gt_wq": "gt_qw"}
    # a variant of a column the header has is no near miss of another, absent one (tip_v_px)
    assert near_miss_columns(("frame", "t_s", "tip_u_px", "Tip_U_px", "tip_u_pxx")) == {}


def test_missing_column_error_names_its_look_alike(run) -> None:
    """A typo inside a group the header otherwise has is an error; it names the look-alike column beside it."""
    root = run[0]
    rename_columns(root, {"grasper_qw": "grasper_wq"})
    recording, errors = validate_run(root)
    assert recording is None
    missing = [e for e in errors if e.column == "grasper_qw"]
    assert len(missing) == 1 and str(missing[0]).endswith("; the header's 'grasper_wq' looks like it")
    rename_columns(root, {}, add={"Grasper_QW": "1"})  # two look-alikes: both named
    _, errors = validate_run(root)
    assert [str(e).endswith("; the header's 'grasper_wq', 'Grasper_QW' look like it")
            for e in errors if e.column == "grasper_qw"] == [True]
    rename_columns(root, {}, drop=("Grasper_QW",))
    rename_columns(root, {"grasper_wq": "grasper_qw", "grasper_x_m": "grasper_x_mm"})  # another unit: said so
    _, errors = validate_run(root)
    assert [str(e).endswith("; the header's 'grasper_x_mm' looks like it (grasper_x_m is in metres)")
            for e in errors if e.column == "grasper_x_m"] == [True]
    rename_columns(root, {"grasper_x_mm": "grasper_x_m", "grasper_qw": "grasper_wq"})
    rename_columns(root, {}, drop=("grasper_wq",))  # a plain omission names nothing else
    _, errors = validate_run(root)
    assert [str(e).endswith(")") for e in errors if e.column == "grasper_qw"] == [True]


def test_cli_validate_prints_the_renamed_column_note(run, capsys) -> None:
    root = run[0]
    rename_columns(root, {"mask": "mask_path"})
    assert main(["validate", str(root)]) == 0
    err = capsys.readouterr().err
    notes = [line for line in err.splitlines() if "is not in the format" in line]
    assert notes == [f"note: {root / 'frames.csv'}: column 'mask_path' is not in the format and is ignored "
                     "(did you mean 'mask'?)"]
