"""modes.csv of a tracking result: round trip exact to the written precision, validation, crash safety."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.result.reader import read_modes, read_result
from pinpoint_fg.io.result.schema import MAX_MODES, MODE_COLUMNS, MODES_CSV
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.posterior.summary import K_MAX
from tests.test_io_result import make_estimates, open_writer, set_cell


def _modes(rng: np.random.Generator, k: int) -> tuple[Mode, ...]:
    w = rng.random(k) + 0.05
    w = w / w.sum()
    out = []
    for i in range(k):
        A = rng.normal(size=(6, 6)) * np.array([1e-2] * 3 + [1e-3] * 3)
        out.append(Mode(cam_T_needle=se3_exp(rng.normal(size=6) * 0.3), weight=float(w[i]), cov_xi=A @ A.T))
    return tuple(out)


def _with_modes(n_frames: int = 5, skip: tuple[int, ...] = ()):
    rng = np.random.default_rng(7)
    ests = make_estimates(n_frames)
    return [dataclasses.replace(e, modes=None if i in skip else _modes(rng, 1 + i % MAX_MODES))
            for i, e in enumerate(ests)]


def test_modes_round_trip_exactly(tmp_path: Path) -> None:
    ests = _with_modes(6, skip=(2,))
    with open_writer(tmp_path / "r") as w:
        for e in ests:
            w.write(e)
    assert K_MAX == MAX_MODES
    hist = read_modes(tmp_path / "r")
    got = hist.by_frame()
    assert list(got) == [e.frame for e in ests if e.modes is not None]
    for e in ests:
        if e.modes is None:
            continue
        want = sorted(e.modes, key=lambda m: -m.weight)
        assert [m.weight for m in got[e.frame]] == [m.weight for m in want]  # repr text: bit-exact
        for a, b in zip(got[e.frame], want, strict=True):
            np.testing.assert_array_equal(a.cov_xi, b.cov_xi)  # upper triangle written, symmetric back
            np.testing.assert_allclose(a.cam_T_needle, b.cam_T_needle, rtol=0, atol=2e-15)
    W = hist.weights_at(np.array([e.frame for e in ests]))
    assert W.shape == (6, MAX_MODES) and np.all(np.isnan(W[2]))
    assert W[3].tolist() == sorted([m.weight for m in ests[3].modes], reverse=True)  # 4 modes
    assert W[0].tolist() == [1.0, 0.0, 0.0, 0.0]  # 1 mode, zero-padded
    assert read_result(tmp_path / "r").frame.tolist() == [e.frame for e in ests]  # other files untouched
    with open(tmp_path / "r" / MODES_CSV) as f:
        assert next(csv.reader(f)) == list(MODE_COLUMNS)
    assert len(MODE_COLUMNS) == 3 + 7 + 21


def test_writer_rejects_bad_modes(tmp_path: Path) -> None:
    e = _with_modes(1)[0]
    m = e.modes[0]
    bad = {
        "sum to": (dataclasses.replace(m, weight=0.5),),
        "1 to 4 modes": tuple(dataclasses.replace(m, weight=0.2) for _ in range(5)),
        "symmetric": (dataclasses.replace(m, weight=1.0, cov_xi=np.triu(np.ones((6, 6)))),),
        "[0, 1]": (dataclasses.replace(m, weight=1.5), dataclasses.replace(m, weight=-0.5)),
    }
    for words, modes in bad.items():
        with open_writer(tmp_path / words.replace(" ", "_")) as w, pytest.raises(ValueError, match=words):
            w.write(dataclasses.replace(e, modes=modes))


@pytest.fixture
def modes_dir(tmp_path: Path) -> Path:
    out = tmp_path / "res"
    with open_writer(out) as w:
        for e in _with_modes(4):
            w.write(e)
    return out  # frames with 1, 2, 3, 4 modes: data rows 1 | 2-3 | 4-6 | 7-10


@pytest.mark.parametrize(
    ("row", "column", "value", "words"),
    [
        (2, "weight", "abc", "not a finite number"),
        (3, "weight", "1.5", "outside [0, 1]"),
        (4, "weight", "0.99", "sum to"),
        (4, "mode", "1", "expected 0"),
        (6, "frame", "3", "smaller than"),
        (7, "cov_23", "nan", "not a finite number"),
        (8, "cov_44", "-1.0", "negative"),
        (9, "cov_01", "1.0", "positive semi-definite"),
        (10, "qx", "2.0", "norm"),
    ],
)
def test_malformed_modes_name_row_and_column(modes_dir: Path, row: int, column: str, value: str, words: str) -> None:
    path = modes_dir / MODES_CSV
    set_cell(path, row, column, value)
    if words == "sum to":
        row = 6  # the check names the frame's last row
    with pytest.raises(InputError) as info:
        read_modes(modes_dir)
    err = info.value
    assert Path(err.file).name == MODES_CSV and err.row == row and err.column == (
        "cov_00" if words == "positive semi-definite" else "qw" if words == "norm" else column)
    assert words in str(err) and f"row {row}:" in str(err)


def test_missing_modes_file_and_torn_incomplete_frame(tmp_path: Path) -> None:
    out = tmp_path / "r"
    ests = _with_modes(4)
    w = open_writer(out)
    for e in ests:
        w.write(e)
    w._modes.flush()  # abandoned without close(): result.json says complete = false
    text = (out / MODES_CSV).read_text()
    lines = text.splitlines(keepends=True)
    (out / MODES_CSV).write_text("".join(lines[:-2]))  # the last frame lost two of its four rows
    hist = read_modes(out)
    assert hist.frames.tolist() == [e.frame for e in ests[:3]]
    (out / MODES_CSV).unlink()
    with pytest.raises(InputError, match="file not found"):
        read_modes(out)
