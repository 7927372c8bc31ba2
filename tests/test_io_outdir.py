"""The one output check: --out never silently replaces a user's results; bad --out is one line, exit 2."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.outdir import prepare_output_dir, prepare_output_file, staged_replacement


def test_new_and_empty_directories_are_accepted(tmp_path: Path) -> None:
    assert prepare_output_dir(tmp_path / "a" / "b", False, "result") == tmp_path / "a" / "b"
    assert (tmp_path / "a" / "b").is_dir()
    assert prepare_output_dir(tmp_path / "a" / "b", False, "result") == tmp_path / "a" / "b"  # still empty


def test_non_empty_directory_needs_overwrite(tmp_path: Path) -> None:
    (tmp_path / "old.csv").write_text("my results")
    with pytest.raises(InputError, match="--overwrite") as info:
        prepare_output_dir(tmp_path, False, "result")
    assert info.value.file == str(tmp_path) and "old.csv" in str(info.value)
    assert prepare_output_dir(tmp_path, True, "result") == tmp_path
    assert (tmp_path / "old.csv").read_text() == "my results"  # nothing is deleted wholesale


@pytest.mark.parametrize("sub", ["", "x", "x/y"])
def test_a_file_in_the_way_is_refused(tmp_path: Path, sub: str) -> None:
    f = tmp_path / "file"
    f.write_text("data")
    target = f / sub if sub else f
    for overwrite in (False, True):
        with pytest.raises(InputError, match="file"):
            prepare_output_dir(target, overwrite, "result")
    assert f.read_text() == "data"


@pytest.mark.parametrize("name", ["a" * 300, "a\x00b"])
def test_paths_the_os_refuses_are_input_errors(tmp_path: Path, name: str) -> None:
    with pytest.raises(InputError) as info:
        prepare_output_dir(tmp_path / name, False, "result")
    assert "\n" not in str(info.value) and "\x00" not in str(info.value)
    with pytest.raises(InputError):
        prepare_output_file(tmp_path / name, False, "noise file")


def test_output_file_rules(tmp_path: Path) -> None:
    f = tmp_path / "sub" / "noise.json"
    assert prepare_output_file(f, False, "noise file") == f and f.parent.is_dir() and not f.exists()
    f.write_text("{}")
    with pytest.raises(InputError, match="--overwrite"):
        prepare_output_file(f, False, "noise file")
    assert prepare_output_file(f, True, "noise file") == f
    with pytest.raises(InputError, match="directory"):
        prepare_output_file(tmp_path, True, "noise file")
    with pytest.raises(InputError, match="is a file"):
        prepare_output_file(f / "x.json", True, "noise file")


@pytest.fixture(scope="module")
def run12(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("outdir") / "run"
    assert main(["simulate", "--scenario", "slow", "--frames", "4", "--seed", "3", "--out", str(run)]) == 0
    return run


def _one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def test_cli_track_refuses_to_replace_a_result(run12: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "res"
    assert main(["track", str(run12), "--method", "map", "--out", str(out)]) == 0
    before = (out / "estimates.csv").read_bytes()
    capsys.readouterr()
    assert main(["track", str(run12), "--method", "map", "--out", str(out)]) == 2
    assert "--overwrite" in _one_error_line(capsys)
    assert (out / "estimates.csv").read_bytes() == before
    assert main(["track", str(run12), "--method", "map", "--out", str(out), "--overwrite"]) == 0


def test_cli_out_naming_a_file_or_a_path_under_one(run12: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "f.txt"
    f.write_text("keep")
    for out in (f, f / "res"):
        for cmd in (["track", str(run12), "--method", "map"], ["simulate", "--frames", "2"],
                    ["evaluate", str(tmp_path)], ["demo", "--frames", "2"], ["ablate", str(run12)]):
            capsys.readouterr()
            assert main([*cmd, "--out", str(out)]) == 2, cmd
            assert str(f) in _one_error_line(capsys)
    assert f.read_text() == "keep"


def test_cli_simulate_and_calibrate_refuse_without_overwrite(run12: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["simulate", "--frames", "2", "--out", str(run12)]) == 2
    _one_error_line(capsys)
    noise = tmp_path / "noise.json"
    noise.write_text("{}")
    assert main(["calibrate", str(run12), "--out", str(noise)]) == 2
    _one_error_line(capsys)
    assert noise.read_text() == "{}"


def test_validate_exits_2_on_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "recording.json").write_text("[" * 100000)
    (bad / "frames.csv").write_text("frame,t_s\n0,1e400\n")
    assert main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "nested" in err and "t_s" in err
    assert main(["validate", str(tmp_path / ("x" * 300))]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_an_output_directory_inside_an_input_is_refused(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "masks").mkdir(parents=True)
    (run / "masks" / "result.json").write_text("a mask's namesake")
    link = tmp_path / "link"
    link.symlink_to(run / "masks")
    for out in (run / "masks", run / "masks" / "new" / "deeper", run / "sub", link, link / "x"):
        for overwrite in (False, True):
            with pytest.raises(InputError, match="--out is inside the input") as info:
                prepare_output_dir(out, overwrite, "result", inputs=[run])
            assert info.value.file == str(out)
    assert (run / "masks" / "result.json").read_text() == "a mask's namesake"
    assert sorted(p.name for p in run.iterdir()) == ["masks"]  # nothing created
    # beside the input, or an input inside the output (a batch of runs under the output's parent), is fine
    assert prepare_output_dir(tmp_path / "runx", False, "result", inputs=[run]) == tmp_path / "runx"
    assert prepare_output_dir(tmp_path / "b", False, "batch output", inputs=[run]) == tmp_path / "b"


@pytest.mark.parametrize(("command", "sub"), [
    (["track", "--method", "map", "--overwrite"], "masks"),  # was: result files written among the masks
    (["track", "--method", "map"], "masks/new"),
    (["track", "--method", "map"], "results"),
    (["batch", "--method", "map", "--workers", "1"], "results"),
])
def test_cli_refuses_an_out_inside_the_input_recording(command: list[str], sub: str, run12: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    shutil.copytree(run12, run)
    before = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    capsys.readouterr()
    assert main([command[0], str(run), *command[1:], "--out", str(run / sub)]) == 2
    line = _one_error_line(capsys)
    assert "--out is inside the input" in line and str(run / sub) in line
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == before


def _renames_failing(monkeypatch: pytest.MonkeyPatch, fails: Callable[[int], bool], error: OSError) -> list:
    """Patch ``os.rename`` to raise ``error`` (naming the source) on the calls whose 1-based number ``fails``; the
    list it returns collects every call's destination."""
    real_rename = os.rename
    calls: list = []

    def rename(src, dst):
        calls.append(dst)
        if fails(len(calls)):
            raise OSError(error.errno, error.strerror, str(src))
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    return calls


def test_staged_replacement_swaps_a_directory_whole_or_not_at_all(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The new output replaces the old whole once written; when writing, or moving it into place, fails, the old
    output is where it was; no hidden sibling is left either way."""
    out = tmp_path / "bag"
    out.mkdir()
    (out / "old.db3").write_text("old")
    with pytest.raises(RuntimeError), staged_replacement(out, "bag") as new:
        new.mkdir()
        (new / "new.db3").write_text("half")
        raise RuntimeError("disk full")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bag", "old.db3"]
    real_rename = os.rename
    # the second move (the new output into place) fails
    calls = _renames_failing(monkeypatch, lambda n: n == 2, OSError(13, "Permission denied"))
    with pytest.raises(InputError, match="the old bag is as it was") as ei, staged_replacement(out, "bag") as new:
        new.mkdir()
        (new / "new.db3").write_text("new")
    assert ei.value.file == str(out) and len(calls) == 3  # named as the user knows it; moved back
    assert "\n" not in str(ei.value) and "Permission denied" in str(ei.value)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bag", "old.db3"]
    monkeypatch.setattr(os, "rename", real_rename)
    with staged_replacement(out, "bag") as new:
        new.mkdir()
        (new / "new.db3").write_text("new")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bag", "new.db3"]


def test_staged_replacement_never_deletes_the_old_output_when_it_cannot_be_moved_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Both the move of the new output into place and the move of the old one back fail: the old output is kept in
    the hidden sibling (not removed with it), and the one-line error says where."""
    out = tmp_path / "bag"
    out.mkdir()
    (out / "old.db3").write_text("old")
    # the first move (the old output aside) works, every later one fails
    _renames_failing(monkeypatch, lambda n: n > 1, OSError(5, "Input/output error"))
    with pytest.raises(InputError, match="nor the old one back") as ei, staged_replacement(out, "bag") as new:
        new.mkdir()
        (new / "new.db3").write_text("new")
    kept = [p for p in tmp_path.rglob("old.db3")]
    assert len(kept) == 1 and kept[0].read_text() == "old" and str(kept[0].parent) in str(ei.value)
    assert "\n" not in str(ei.value)


def test_staged_replacement_holds_back_ctrl_c_between_the_two_moves(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A SIGINT raised between moving the old output aside and the new one into place takes effect after both: the new
    output is in place, the old one and the hidden sibling are gone, and the KeyboardInterrupt still reaches the
    caller."""
    import signal

    out = tmp_path / "bag"
    out.mkdir()
    (out / "old.db3").write_text("old")
    real_rename = os.rename
    calls = []

    def rename(src, dst):
        calls.append(dst)
        real_rename(src, dst)
        if len(calls) == 1:  # right after the old output was moved aside
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(os, "rename", rename)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # a pytest-xdist worker ignores SIGINT
    try:
        with pytest.raises(KeyboardInterrupt), staged_replacement(out, "bag") as new:
            new.mkdir()
            (new / "new.db3").write_text("new")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(calls) == 2
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bag", "new.db3"]


def test_staged_replacement_of_the_current_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``.`` has no name to stage under: the path is made absolute first, so an empty current directory is replaced
    by the new output like any other."""
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    with staged_replacement(".", "bag") as new:
        new.mkdir()
        (new / "new.db3").write_text("new")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["here", "new.db3"]
