"""Atomic replacement keeps the permissions of an ordinary file (pinpoint_fg/io/atomic.py).

Before, mkstemp's 0600 made recording.json, result.json, particles.npz and a rewritten frames.csv unreadable to
other users whatever the umask (the last test fails on that code).
"""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from pinpoint_fg.io.atomic import FILE_MODE, atomic_write
from pinpoint_fg.io.recording.writer import replace_ground_truth, write_recording
from tests.test_io_recording import make_frames, make_info
from tests.test_io_result import make_estimates, open_writer


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_file_mode_is_what_open_gives(tmp_path: Path) -> None:
    (tmp_path / "plain.txt").write_text("x", encoding="utf-8")
    assert FILE_MODE == _mode(tmp_path / "plain.txt")
    with atomic_write(tmp_path / "atomic.txt") as fh:
        fh.write("a\nb\n")
    assert (tmp_path / "atomic.txt").read_text(encoding="utf-8") == "a\nb\n"
    assert _mode(tmp_path / "atomic.txt") == FILE_MODE


def test_a_failed_write_leaves_the_target_and_no_temporary_file(tmp_path: Path) -> None:
    target = tmp_path / "data.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_write(target, binary=True) as fh:
        fh.write(b"new, half")
        raise RuntimeError("stopped")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.bin"]


def test_recordings_and_results_are_readable_like_their_csv_files(tmp_path: Path) -> None:
    frames, masks, images = make_frames()
    root = write_recording(tmp_path / "run", make_info(), frames, masks, images)
    assert _mode(root / "recording.json") == _mode(root / "frames.csv") == FILE_MODE
    replace_ground_truth(root, {})
    assert _mode(root / "frames.csv") == FILE_MODE
    out = tmp_path / "res"
    with open_writer(out) as w:
        for e in make_estimates():
            w.write(e)
    for name in ("result.json", "particles.npz", "estimates.csv"):
        assert _mode(out / name) == FILE_MODE, name
