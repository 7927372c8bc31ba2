"""ROS bag import/export (pinpoint_fg.io.bag): round trips through ROS 1 and ROS 2 bags, stamp matching,
and malformed bags. Every bag is written by the tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from factors.geometry import PinholeCamera
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.bag import BagTopics, _BagWriter, export_bag, import_bag, read_needle_json
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.sim.scenarios import simulate

NS = 1_000_000_000
T0 = 1_700_000_000 * NS + 123_456_789  # an absolute epoch stamp, as real bags have


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("normal", 10, seed=4, out=tmp_path_factory.mktemp("bag") / "sim")


def _assert_same_run(a_path: Path, b_path: Path) -> None:
    """Every value of two runs: camera, needle, rate, frames, ns times, keypoints, poses, masks."""
    a, b = read_recording(a_path), read_recording(b_path)
    assert b.info.camera == a.info.camera
    assert b.info.needle == a.info.needle
    assert b.info.frame_rate_hz == a.info.frame_rate_hz
    assert len(b) == len(a)
    n_mask = n_gt = 0
    for x, y in zip(a.frames, b.frames, strict=True):
        assert y.frame == x.frame
        assert round(y.t_s * NS) == round(x.t_s * NS)
        for name in ("tip_px", "tail_px"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None) == (v is None)
            if u is not None:
                assert np.array_equal(u, v), name  # float64 through the bag: bit-identical
        for name in ("cam_T_grasper", "cam_T_needle_gt"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None) == (v is None)
            if u is not None:
                # matrix -> quaternion -> matrix: rounding only
                np.testing.assert_allclose(v, u, rtol=0, atol=2e-16 * 8)
                n_gt += name == "cam_T_needle_gt"
        ma, mb = a.load_mask(x), b.load_mask(y)
        assert (ma is None) == (mb is None)
        if ma is not None:
            assert np.array_equal(ma, mb)
            n_mask += 1
    assert n_mask > 0 and n_gt == len(a)


@pytest.mark.parametrize(("fmt", "storage", "name"), [("ros2", "sqlite3", "b2"), ("ros1", "sqlite3", "b1.bag"),
                                                      ("ros2", "mcap", "b2m")])
def test_round_trip_is_identical(sim_run: Path, tmp_path: Path, fmt: str, storage: str, name: str) -> None:
    bag = export_bag(sim_run, tmp_path / name, fmt=fmt, storage=storage)
    summary = import_bag(bag, tmp_path / "back", needle=sim_run / "recording.json")
    src = read_recording(sim_run)
    assert summary.frames == 10 and summary.unmatched["tip"] == 0
    assert summary.matched["tip"] == sum(f.tip_px is not None for f in src.frames)
    assert summary.matched["mask"] == sum(f.mask is not None for f in src.frames)
    _assert_same_run(sim_run, tmp_path / "back")
    # and once more: the imported run exports and imports to itself
    export_bag(tmp_path / "back", tmp_path / ("again" + (".bag" if fmt == "ros1" else "")), fmt=fmt)
    import_bag(tmp_path / ("again" + (".bag" if fmt == "ros1" else "")), tmp_path / "back2",
               needle=tmp_path / "back" / "recording.json")
    _assert_same_run(tmp_path / "back", tmp_path / "back2")
    assert json.loads((tmp_path / "back2" / "recording.json").read_text())["ros_bag"]["time_origin_ns"] == 0


CAM = PinholeCamera(fx=500.0, fy=510.0, cx=31.5, cy=23.5, width=64, height=48, distortion=(-0.1, 0.01, 1e-3, 0, 0))


def _write_bag(path: Path, fmt: str, build) -> Path:
    """A bag written message by message: ``build(w)`` yields (topic, msg, stamp_ns)."""
    with _BagWriter(path, fmt, "sqlite3") as w:
        for topic, msg, ns in build(w):
            w.write(topic, msg, ns)
    return path


def _camera_frames(w: _BagWriter, n: int = 4, period_ns: int = 40_000_000, model: str = "plumb_bob",
                   d: tuple = CAM.distortion):
    for k in range(n):
        yield "/camera/camera_info", w.camera_info(w.header(T0 + k * period_ns, "cam", k), CAM, model, list(d)), \
            T0 + k * period_ns


def _observations(w: _BagWriter, offsets_ns: dict[int, int], **skip: bool):
    """Tip/tail/grasper on every frame k in offsets_ns, stamped T0 + 40 ms * k + offset."""
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.1]
    for k, off in offsets_ns.items():
        ns = T0 + k * 40_000_000 + off
        h = w.header(ns, "cam", k)
        yield "/needle/tip_px", w.point(h, np.array([10.25 + k, 20.5])), ns
        yield "/needle/tail_px", w.point(h, np.array([30.0, 40.0 - k])), ns
        if not skip.get("grasper"):
            yield "/grasper/pose", w.pose(h, T), ns
        if k == 0 and not skip.get("mask"):
            yield "/needle/mask", _padded_mask(w, ns), ns


def _padded_mask(w: _BagWriter, ns: int, encoding: str = "mono8", step: int = 70, frame_id: str = "cam"):
    img = np.zeros((CAM.height, step), dtype=np.uint8)
    img[5:9, 10:20] = 7
    img[:, CAM.width:] = 255  # padding bytes beyond the width: must be ignored
    return w.T["sensor_msgs/msg/Image"](header=w.header(ns, frame_id, 0), height=CAM.height, width=CAM.width,
                                        encoding=encoding, is_bigendian=0, step=step, data=img.reshape(-1))


@pytest.mark.parametrize("fmt", ["ros2", "ros1"])
def test_stamp_matching_relative_times_and_step_padding(tmp_path: Path, fmt: str) -> None:
    def build(w: _BagWriter):
        yield from _camera_frames(w)
        # frame 0 exact, frame 1 +0.4 ms, frame 2 -0.9 ms, frame 3 +5 ms (beyond 1 ms: not observed)
        yield from _observations(w, {0: 0, 1: 400_000, 2: -900_000, 3: 5_000_000}, mask=True)
        yield "/needle/mask", _padded_mask(w, T0 + 40_000_000, "8UC1"), T0 + 40_000_000

    bag = _write_bag(tmp_path / ("h.bag" if fmt == "ros1" else "h"), fmt, build)
    needle = tmp_path / "needle.json"
    needle.write_text(json.dumps({"radius_m": 0.005, "tail_angle_rad": 0.0, "tip_angle_rad": 2.0,
                                  "grasp_angle_rad": 1.0, "wire_diameter_m": 0.0003}))
    s = import_bag(bag, tmp_path / "run", needle)
    assert s.matched == {"mask": 1, "tip": 3, "tail": 3, "grasper": 3, "gt": 0}
    assert s.unmatched["tip"] == 1
    rec = read_recording(tmp_path / "run")
    assert rec.info.camera == CAM and rec.info.frame_rate_hz == 25.0 and rec.info.name == "h"
    assert rec.info.needle.radius_m == 0.005
    assert rec.info.extra["ros_bag"] == {"time_origin_ns": T0, "camera_frame_id": "cam"}
    assert [f.t_s for f in rec.frames] == [0.0, 0.04, 0.08, 0.12]
    assert np.array_equal(rec.frames[1].tip_px, [11.25, 20.5]) and rec.frames[3].tip_px is None
    assert rec.frames[2].cam_T_grasper[2, 3] == 0.1 and rec.frames[3].cam_T_grasper is None
    mask = rec.load_mask(rec.frames[1])
    assert mask.shape == (48, 64) and mask.sum() == 40 and mask[5:9, 10:20].all()
    assert rec.frames[0].mask is None

    # exact matching: only frame 0's messages are stamped exactly
    s0 = import_bag(bag, tmp_path / "exact", needle, stamp_tolerance_s=0.0)
    assert s0.matched["tip"] == 1 and s0.unmatched["tip"] == 3
    # the export of the import writes the absolute stamps back
    out = export_bag(tmp_path / "run", tmp_path / ("e.bag" if fmt == "ros1" else "e"), fmt=fmt)
    import_bag(out, tmp_path / "run2", tmp_path / "run" / "recording.json")
    assert read_recording(tmp_path / "run2").info.extra["ros_bag"]["time_origin_ns"] == T0
    _assert_frames_equal_without_gt(tmp_path / "run", tmp_path / "run2")


def _assert_frames_equal_without_gt(a_path: Path, b_path: Path) -> None:
    a, b = read_recording(a_path), read_recording(b_path)
    assert a.info.camera == b.info.camera and len(a) == len(b)
    for x, y in zip(a.frames, b.frames, strict=True):
        assert x.t_s == y.t_s
        for name in ("tip_px", "tail_px"):
            u, v = getattr(x, name), getattr(y, name)
            assert (u is None and v is None) or np.array_equal(u, v)


def _needle(tmp_path: Path) -> Path:
    p = tmp_path / "needle.json"
    p.write_text(json.dumps({"radius_m": 0.005, "tail_angle_rad": 0.0, "tip_angle_rad": 2.0,
                             "grasp_angle_rad": 1.0, "wire_diameter_m": 0.0003}))
    return p


def _bad_bag_cases():
    def missing_topic(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, grasper=True)

    def fisheye(w):
        yield from _camera_frames(w, model="equidistant", d=(0.1, 0.0, 0.0, 0.0))
        yield from _observations(w, {0: 0})

    def rgb_mask(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, mask=True)
        yield "/needle/mask", _padded_mask(w, T0, "rgb8"), T0

    def bad_quaternion(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, grasper=True)
        m = w.pose(w.header(T0, "cam", 0), np.eye(4))
        m.pose.orientation.w = 1.2
        yield "/grasper/pose", m, T0

    def other_frame(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, grasper=True)
        yield "/grasper/pose", w.pose(w.header(T0, "world", 0), np.eye(4)), T0

    def duplicate(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0, 1: 0})
        yield "/needle/tip_px", w.point(w.header(T0, "cam", 0), np.array([1.0, 2.0])), T0 + 1

    def camera_changes(w):
        frames = list(_camera_frames(w))
        m = frames[2][1]
        m.width = 65
        yield from frames
        yield from _observations(w, {0: 0})

    def wrong_type(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, grasper=True)
        yield "/grasper/pose", w.point(w.header(T0, "cam", 0), np.array([1.0, 2.0])), T0

    return [
        (missing_topic, "/grasper/pose", "not in the bag"),
        (fisheye, "/camera/camera_info", "distortion_model 'equidistant' is not supported"),
        (rgb_mask, "/needle/mask", "encoding 'rgb8' is not supported"),
        (bad_quaternion, "/grasper/pose", "quaternion has norm"),
        (other_frame, "/grasper/pose", "in frame 'world' but the camera frame is 'cam'"),
        (duplicate, "/needle/tip_px", "same stamp"),
        (camera_changes, "/camera/camera_info", "camera changed within the bag (width)"),
        (wrong_type, "/grasper/pose", "expected geometry_msgs/msg/PoseStamped"),
    ]


@pytest.mark.parametrize(("build", "column", "text"), _bad_bag_cases(), ids=lambda v: getattr(v, "__name__", None))
def test_malformed_bags_name_the_topic_and_write_nothing(tmp_path: Path, build, column: str, text: str) -> None:
    bag = _write_bag(tmp_path / "bad", "ros2", build)
    with pytest.raises(InputError) as ei:
        import_bag(bag, tmp_path / "run", _needle(tmp_path))
    assert ei.value.column == column and text in str(ei.value) and ei.value.file == str(bag)
    assert "\n" not in str(ei.value)
    assert not (tmp_path / "run").exists()


def test_skipping_a_topic_and_bad_files(tmp_path: Path) -> None:
    def build(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0}, grasper=True)

    bag = _write_bag(tmp_path / "b", "ros2", build)
    s = import_bag(bag, tmp_path / "run", _needle(tmp_path), topics=BagTopics(grasper=None, mask=None))
    assert "grasper" not in s.matched and s.matched["tip"] == 1
    with pytest.raises(InputError, match="--out is not empty"):
        import_bag(bag, tmp_path / "run", _needle(tmp_path), topics=BagTopics(grasper=None))
    with pytest.raises(InputError, match="half the frame period"):
        import_bag(bag, tmp_path / "r2", _needle(tmp_path), topics=BagTopics(grasper=None), stamp_tolerance_s=0.02)
    data = (bag / "b.db3").read_bytes()
    (bag / "b.db3").write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="cannot read the bag") as ei:
        import_bag(bag, tmp_path / "r3", _needle(tmp_path))
    assert "\n" not in str(ei.value)
    (tmp_path / "trunc.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 50)
    with pytest.raises(InputError, match="cannot read the bag"):
        import_bag(tmp_path / "trunc.bag", tmp_path / "r4", _needle(tmp_path))


def test_needle_json(tmp_path: Path, sim_run: Path) -> None:
    assert read_needle_json(sim_run / "recording.json") == read_recording(sim_run).info.needle
    p = tmp_path / "n.json"
    p.write_text(json.dumps({"radius_m": 0.005, "tail_angle_rad": 0.0, "tip_angle_rad": 2.0,
                             "grasp_angle_rad": 1.0}))
    with pytest.raises(InputError) as ei:
        read_needle_json(p)
    assert ei.value.column == "wire_diameter_m"
    p.write_text(json.dumps({"needle": {"radius_m": "big"}}))
    with pytest.raises(InputError) as ei:
        read_needle_json(p)
    assert ei.value.column == "needle.radius_m"


def test_export_refuses_what_a_bag_cannot_hold(sim_run: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="must end in .bag"):
        export_bag(sim_run, tmp_path / "x", fmt="ros1")
    with pytest.raises(InputError, match="must not end in .bag"):
        export_bag(sim_run, tmp_path / "x.bag", fmt="ros2")
    (tmp_path / "exists").mkdir()  # an empty directory is written into, as a new one (as every --out)
    assert (export_bag(sim_run, tmp_path / "exists") / "metadata.yaml").is_file()


def test_cli_export_import_and_bad_bag(sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "cli.bag"
    assert main(["export-bag", str(sim_run), "--out", str(bag), "--format", "ros1"]) == 0
    assert main(["import-bag", str(bag), "--out", str(tmp_path / "run"), "--needle",
                 str(sim_run / "recording.json"), "--topic-gt", "none"]) == 0
    assert "10 frames" in capsys.readouterr().out
    assert not read_recording(tmp_path / "run").has_ground_truth
    # a missing topic, a malformed bag: exit 2 and one line naming the bag
    assert main(["import-bag", str(bag), "--out", str(tmp_path / "r2"), "--needle", str(sim_run / "recording.json"),
                 "--topic-mask", "/seg"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/seg" in err and str(bag) in err and "Traceback" not in err
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    assert main(["import-bag", str(tmp_path / "junk.bag"), "--out", str(tmp_path / "r3"), "--needle",
                 str(sim_run / "recording.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "junk.bag" in err and "Traceback" not in err


# --- export-bag over an existing --out ----------------------------------------------------------


def _tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (or ``root`` itself) with its bytes, and the hidden siblings' names."""
    files = {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()} if root.is_dir() \
        else {".": root.read_bytes()}
    return {**files, "siblings": repr(sorted(p.name for p in root.parent.iterdir() if p.name.startswith(".")))}


def _topics(bag: Path) -> set[str]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return {c.topic for c in reader.connections}


@pytest.mark.parametrize(("fmt", "name"), [("ros2", "b2"), ("ros1", "b1.bag")])
def test_export_refuses_an_existing_bag_without_overwrite(sim_run: Path, tmp_path: Path, fmt: str, name: str) -> None:
    bag = export_bag(sim_run, tmp_path / name, fmt=fmt)
    before = _tree(bag)
    with pytest.raises(InputError, match="pass --overwrite to replace it") as ei:
        export_bag(sim_run, bag, fmt=fmt, topics=BagTopics(gt=None))
    assert str(bag) in str(ei.value) and "\n" not in str(ei.value)
    assert _tree(bag) == before


def test_export_overwrite_replaces_a_ros2_bag_whole(sim_run: Path, tmp_path: Path) -> None:
    """The old bag's storage file goes with it (sqlite3 -> mcap: no .db3 left beside the .mcap), and no staging
    directory is left beside it."""
    bag = export_bag(sim_run, tmp_path / "b2")
    assert "/needle/gt_pose" in _topics(bag)
    assert export_bag(sim_run, bag, storage="mcap", topics=BagTopics(gt=None), overwrite=True) == bag
    assert sorted(p.name for p in bag.iterdir()) == ["b2.mcap", "metadata.yaml"]
    assert "/needle/gt_pose" not in _topics(bag) and "/needle/tip_px" in _topics(bag)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b2"]


def test_export_overwrite_replaces_a_ros1_bag(sim_run: Path, tmp_path: Path) -> None:
    bag = export_bag(sim_run, tmp_path / "b1.bag", fmt="ros1")
    assert export_bag(sim_run, bag, fmt="ros1", topics=BagTopics(gt=None), overwrite=True) == bag
    assert "/needle/gt_pose" not in _topics(bag) and "/needle/tip_px" in _topics(bag)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b1.bag"]


def test_export_overwrite_refuses_what_is_not_a_bag(sim_run: Path, tmp_path: Path) -> None:
    """--overwrite replaces a bag, nothing else: a directory holding other files (a bag plus the user's notes, a run
    directory), a file that is no ROS 1 bag, the other format's bag, and a symbolic link are left as they were."""
    bag = export_bag(sim_run, tmp_path / "b2")
    (bag / "notes.txt").write_text("mine")
    other = tmp_path / "other.bag"
    other.write_text("not a bag")
    export_bag(sim_run, tmp_path / "r1.bag", fmt="ros1")
    (tmp_path / "dir.bag").mkdir()
    (tmp_path / "dir.bag" / "x").write_text("x")
    (tmp_path / "link").symlink_to(bag)
    cases = [(bag, "ros2", "notes.txt"), (sim_run, "ros2", "also an input"), (other, "ros1", "not a ROS 1 bag"),
             (tmp_path / "dir.bag", "ros1", "a directory"), (tmp_path / "link", "ros2", "symbolic link")]
    before = {p: _tree(p) for p, _, _ in cases}
    for path, fmt, why in cases:
        for overwrite in (False, True):
            with pytest.raises(InputError, match=why) as ei:
                export_bag(sim_run, path, fmt=fmt, overwrite=overwrite)
            assert str(path) in str(ei.value) and "\n" not in str(ei.value)
    assert {p: _tree(p) for p, _, _ in cases} == before
    run_before = _tree(sim_run)
    for path, fmt in ((sim_run / "masks", "ros2"), (sim_run / "bags" / "new", "ros2"), (sim_run / "x.bag", "ros1")):
        with pytest.raises(InputError, match="inside the input"):  # as every other command's output
            export_bag(sim_run, path, fmt=fmt)
    assert _tree(sim_run) == run_before


@pytest.mark.parametrize("error", ["os", "sqlite"])
@pytest.mark.parametrize(("fmt", "name"), [("ros2", "b2"), ("ros1", "b1.bag")])
def test_export_overwrite_keeps_the_old_bag_when_writing_fails(sim_run: Path, tmp_path: Path, fmt: str, name: str,
                                                                error: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk half-way through the new bag: OSError, or sqlite3's own error under the default ROS 2 storage
    (``sqlite3.OperationalError: disk I/O error`` under ``ulimit -f``, a traceback before)."""
    import sqlite3

    bag = export_bag(sim_run, tmp_path / name, fmt=fmt)
    before = _tree(bag)
    calls = []

    def failing_write(self, topic, msg, ns):
        calls.append(topic)
        if len(calls) == 7:
            if error == "sqlite":
                raise sqlite3.OperationalError("No space left on device (disk I/O error)")
            raise OSError(28, "No space left on device", str(self.writer.path))
        original(self, topic, msg, ns)

    original = _BagWriter.write
    monkeypatch.setattr(_BagWriter, "write", failing_write)
    with pytest.raises(InputError, match="No space left on device") as ei:
        export_bag(sim_run, bag, fmt=fmt, overwrite=True)
    assert str(bag) in str(ei.value) and ".partial" not in str(ei.value)
    assert _tree(bag) == before


def test_cli_export_bag_overwrite(sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from pinpoint_fg.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert "--overwrite" in sub.choices["export-bag"].format_help()
    bag = tmp_path / "b2"
    assert main(["export-bag", str(sim_run), "--out", str(bag)]) == 0
    capsys.readouterr()
    assert main(["export-bag", str(sim_run), "--out", str(bag)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bag) in err and "--overwrite" in err and "Traceback" not in err
    assert main(["export-bag", str(sim_run), "--out", str(bag), "--overwrite", "--topic-gt", "none"]) == 0
    assert "/needle/gt_pose" not in _topics(bag)


def test_cli_export_bag_interrupted_says_what_is_at_out(sim_run: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C printed "finished frames are on disk", which export-bag never writes; the old bag stays whole."""
    bag = export_bag(sim_run, tmp_path / "b2")
    before = _tree(bag)

    def interrupted(self, topic, msg, ns):
        raise KeyboardInterrupt

    monkeypatch.setattr(_BagWriter, "write", interrupted)
    assert main(["export-bag", str(sim_run), "--out", str(bag), "--overwrite"]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "old bag" in err and "frames" not in err
    assert _tree(bag) == before and sorted(p.name for p in tmp_path.iterdir()) == ["b2"]
