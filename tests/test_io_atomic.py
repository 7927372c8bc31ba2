"""Atomic replacement keeps the permissions of an ordinary file (pinpoint_fg/io/atomic.py).

Before, mkstemp's 0600 made recording.json, result.json, particles.npz and a rewritten frames.csv unreadable to
other users whatever the umask (the umask test and the last test fail on that code).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from pinpoint_fg.io.atomic import atomic_write
from pinpoint_fg.io.recording.writer import replace_ground_truth, write_recording
from tests.test_io_recording import make_frames, make_info
from tests.test_io_result import make_estimates, open_writer


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@contextmanager
def _umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_a_new_file_gets_what_open_gives_under_the_umask(umask: int, mode: int, tmp_path: Path) -> None:
    with _umask(umask):
        (tmp_path / "plain.txt").write_text("x", encoding="utf-8")
        with atomic_write(tmp_path / "atomic.txt") as fh:
            fh.write("a\nb\n")
    assert (tmp_path / "atomic.txt").read_text(encoding="utf-8") == "a\nb\n"
    assert _mode(tmp_path / "atomic.txt") == _mode(tmp_path / "plain.txt") == mode


def test_a_rewritten_file_keeps_its_mode(tmp_path: Path) -> None:
    target = tmp_path / "frames.csv"
    target.write_text("old\n", encoding="utf-8")
    target.chmod(0o640)
    with _umask(0o022), atomic_write(target) as fh:  # open(target, "w") would keep 0640 too
        fh.write("new\n")
    assert target.read_text(encoding="utf-8") == "new\n" and _mode(target) == 0o640


def test_a_failed_write_leaves_the_target_and_no_temporary_file(tmp_path: Path) -> None:
    target = tmp_path / "data.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_write(target, binary=True) as fh:
        fh.write(b"new, half")
        raise RuntimeError("stopped")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.bin"]


def test_recordings_and_results_are_readable_like_their_csv_files(tmp_path: Path) -> None:
    with _umask(0o022):
        frames, masks, images = make_frames()
        root = write_recording(tmp_path / "run", make_info(), frames, masks, images)
        assert _mode(root / "recording.json") == _mode(root / "frames.csv") == 0o644
        replace_ground_truth(root, {})
        assert _mode(root / "frames.csv") == 0o644
        out = tmp_path / "res"
        with open_writer(out) as w:
            for e in make_estimates():
                w.write(e)
    for name in ("result.json", "particles.npz", "estimates.csv"):
        assert _mode(out / name) == 0o644, name
