"""Fuzzing the readers: whatever bytes a recording or a result holds, only InputError escapes.

``hypothesis`` mutates a small valid recorded run (recording.json, frames.csv, a mask PNG) and a
small valid result (result.json, estimates.csv, smoothed.csv, particles.npz, the journal) with
byte edits and with values known to have broken readers (huge or long numbers, ``1e400``, NUL,
4000-character paths, deep JSON nesting, corrupt PNG data behind valid CRCs). The readers must
either accept the input or raise :class:`InputError`; the recording reader must also never let
libpng print to stderr. Examples are derandomised, so the suite is deterministic. Cases:
RECORDING_CASES + RESULT_CASES (>= 2000 in total).
"""

from __future__ import annotations

import functools
import shutil
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.validator import validate_run
from pinpoint_fg.io.recording.writer import write_recording
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.io.result.writer import ResultWriter
from tests.test_io_recording import make_frames, make_info
from tests.test_io_result import make_estimates

RECORDING_CASES = 1400
RESULT_CASES = 700

FUZZ = settings(deadline=None, derandomize=True, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])

#: Values that broke (or could break) a reader: overflow, huge integers, long/NUL paths, nesting.
NASTY = [
    "1e400", "-1e400", "1e300", "-1e300", "1e-400", "9" * 5000, "1" * 4000, "-" + "9" * 25, "18446744073709551616",
    "100000000000000000000", "nan", "inf", "", " ", "\x00", "a\x00b", "a" * 300, "masks/" + "x" * 4000,
    "../x", "/etc/passwd", "C:\\x", "masks/../../x", "\u202e", "\ufeff", '"', "'", ",", "\n", "\r\n",
    "[" * 5000, "{" * 3000, '{"a":' * 3000, "0x10", "1_000", "١٢", "true", "null", "[]", "{}", "1e", ".", "-0",
]

nasty_text = st.one_of(st.sampled_from(NASTY), st.text(max_size=12), st.from_regex(r"-?\d{1,30}(\.\d*)?(e-?\d{1,4})?",
                                                                                   fullmatch=True))


def _mutate_bytes(data: bytes, draw_ops: list[tuple[int, int, bytes]]) -> bytes:
    """Apply (position, delete count, inserted bytes) edits, positions taken modulo the length."""
    b = bytearray(data)
    for pos, n_del, ins in draw_ops:
        p = pos % (len(b) + 1)
        b[p : p + n_del] = ins
    return bytes(b)


byte_ops = st.lists(
    st.tuples(st.integers(0, 1 << 20), st.integers(0, 8),
              st.one_of(st.binary(max_size=6), st.sampled_from([s.encode("utf-8") for s in NASTY]))),
    min_size=1, max_size=4,
)


def _decode(data: bytes) -> str:
    return data.decode("utf-8", "surrogateescape")


def _encode(text: str) -> bytes:
    return text.encode("utf-8", "surrogateescape")


def _mutate_csv(text: str, edits: list[tuple[int, int, str]]) -> str:
    """Replace cells (row, column taken modulo the table's size) with the given texts."""
    lines = text.split("\n")
    body = [ln for ln in lines if ln]
    for r, c, value in edits:
        row = r % len(body)
        cells = body[row].split(",")
        cells[c % len(cells)] = value
        body[row] = ",".join(cells)
    return "\n".join(body) + "\n"


cell_edits = st.lists(st.tuples(st.integers(0, 50), st.integers(0, 50), nasty_text), min_size=1, max_size=3)


def _json_mutations() -> st.SearchStrategy[str]:
    values = st.one_of(st.sampled_from(NASTY), st.integers(-(10**30), 10**30), st.floats(), st.booleans(), st.none())
    return values.map(str)


# --------------------------------------------------------------------------------------------
# Recording reader
# --------------------------------------------------------------------------------------------


@functools.cache
def _base_run() -> dict[str, bytes]:
    """The files of a small valid run (built once; a module-level cache keeps hypothesis' reports short)."""
    frames, masks, images = make_frames()
    with tempfile.TemporaryDirectory() as tmp:
        root = write_recording(Path(tmp) / "run", make_info(), frames, masks, images)
        files = {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert "masks/000003.png" in files and "recording.json" in files
    return files


@pytest.fixture(scope="module")
def scratch() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="ppfg-fuzz-"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _write_tree(root: Path, files: dict[str, bytes]) -> Path:
    if root.exists():
        shutil.rmtree(root)
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root


def _corrupt_png_keep_crcs(png: bytes, pos: int, value: int) -> bytes:
    """Change one byte inside the first IDAT payload and recompute that chunk's CRC."""
    i = png.find(b"IDAT") - 4
    n = int.from_bytes(png[i : i + 4], "big") if i >= 0 else 0
    payload = bytearray(png[i + 8 : i + 8 + n])
    if i < 0 or n == 0 or len(payload) != n:  # an earlier mutation already broke the chunk: leave it
        return png
    payload[pos % n] = value
    chunk = b"IDAT" + bytes(payload)
    return png[: i + 8] + bytes(payload) + zlib.crc32(chunk).to_bytes(4, "big") + png[i + 12 + n :]


recording_mutation = st.one_of(
    st.tuples(st.just("json-bytes"), byte_ops),
    st.tuples(st.just("json-value"), st.tuples(st.sampled_from(
        ["fx", "cx", "width", "height", "radius_m", "tip_angle_rad", "frame_rate_hz", "30.0", "version", "0.1"]),
        _json_mutations())),
    st.tuples(st.just("csv-bytes"), byte_ops),
    st.tuples(st.just("csv-cells"), cell_edits),
    st.tuples(st.just("png-bytes"), byte_ops),
    st.tuples(st.just("png-data"), st.tuples(st.integers(0, 1 << 16), st.integers(0, 255))),
)


def _apply_recording_mutation(files: dict[str, bytes], kind: str, arg) -> dict[str, bytes]:
    files = dict(files)
    if kind == "json-bytes":
        files["recording.json"] = _mutate_bytes(files["recording.json"], arg)
    elif kind == "json-value":
        key, value = arg
        text = files["recording.json"].decode("utf-8", "surrogateescape")
        anchor = f'"{key}": ' if not key[0].isdigit() else key
        at = text.find(anchor)
        if at >= 0:
            start = at + len(anchor) if not key[0].isdigit() else at
            end = start
            while end < len(text) and text[end] not in ",\n}]":
                end += 1
            text = text[:start] + value + text[end:]
        files["recording.json"] = text.encode("utf-8", "surrogateescape")
    elif kind == "csv-bytes":
        files["frames.csv"] = _mutate_bytes(files["frames.csv"], arg)
    elif kind == "csv-cells":
        files["frames.csv"] = _encode(_mutate_csv(_decode(files["frames.csv"]), arg))
    elif kind == "png-bytes":
        files["masks/000003.png"] = _mutate_bytes(files["masks/000003.png"], arg)
    elif kind == "png-data":
        files["masks/000003.png"] = _corrupt_png_keep_crcs(files["masks/000003.png"], *arg)
    return files


@settings(FUZZ, max_examples=RECORDING_CASES)
@given(mutations=st.lists(recording_mutation, min_size=1, max_size=3))
def test_recording_reader_raises_only_input_error(scratch, capfd, mutations) -> None:
    files = _base_run()
    for kind, arg in mutations:
        files = _apply_recording_mutation(files, kind, arg)
    root = _write_tree(scratch / "run", files)
    capfd.readouterr()
    recording, errors = validate_run(root)
    assert all(isinstance(e, InputError) for e in errors)
    assert (recording is None) == bool(errors)
    for e in errors:  # one line each, and not an echo of a 4000-character cell
        assert "\n" not in str(e) and len(str(e)) < 1200, str(e)[:300]
    if recording is not None:
        again = read_recording(root)
        for rec in again.frames:  # what validated must decode
            again.load_mask(rec)
            again.load_image(rec)
        for rec in again.frames:
            for v in (rec.tip_px, rec.tail_px):
                assert v is None or np.all(np.isfinite(v))
    err = capfd.readouterr().err
    assert err == "", f"a decoder printed to stderr: {err[:300]}"


def test_fuzz_covers_known_bad_inputs(scratch) -> None:
    """The mutations above reach the issue's examples: each is refused with the right location."""
    cases = [
        ("csv-cells", [(1, 2, "1e400")], "tip_u_px"),
        ("csv-cells", [(1, 2, "1e300")], "tip_u_px"),
        ("csv-cells", [(1, 0, "100000000000000000000")], "frame"),
        ("csv-cells", [(1, 6, "a" * 300)], "mask"),
        ("csv-cells", [(1, 6, "masks/a\x00b.png")], "mask"),
        ("csv-cells", [(1, 7, "1e300")], "grasper_x_m"),
        ("json-value", ("fx", "9" * 5000), None),
        ("json-value", ("fx", "[" * 5000 + "]" * 5000), None),
        ("png-data", (40, 0xFF), "mask"),
    ]
    for kind, arg, column in cases:
        root = _write_tree(scratch / "known", _apply_recording_mutation(_base_run(), kind, arg))
        with pytest.raises(InputError) as info:
            read_recording(root)
        assert info.value.column == column, (kind, str(info.value)[:200])
        assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------------
# Result reader
# --------------------------------------------------------------------------------------------


@functools.cache
def _base_result() -> dict[str, dict[str, bytes]]:
    """The files of a small valid result, closed ("complete") and abandoned mid-run ("crashed")."""
    out: dict[str, dict[str, bytes]] = {}
    for complete in (True, False):
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "res"
            w = ResultWriter(root, "pf", {"particles": 7, "window": 2}, "unit-run", None, weighted=True,
                             smoothed=True)
            for e in make_estimates(4):
                w.write(e)
            if complete:
                w.close()
            out["complete" if complete else "crashed"] = {
                p.name: p.read_bytes() for p in root.iterdir() if p.is_file()
            }
            if not complete:
                w.close()
    assert "particles.journal" in out["crashed"]
    return out


result_file = st.sampled_from(["result.json", "estimates.csv", "smoothed.csv", "particles.npz", "particles.journal",
                               "trajectory.tum"])
result_mutation = st.one_of(
    st.tuples(st.just("bytes"), st.tuples(result_file, byte_ops)),
    st.tuples(st.just("cells"), st.tuples(st.sampled_from(["estimates.csv", "smoothed.csv"]), cell_edits)),
    st.tuples(st.just("json"), st.tuples(st.sampled_from(['"version": ', '"weighted": ', '"complete": ',
                                                          '"method": ', '"particles": 7']), _json_mutations())),
    st.tuples(st.just("delete"), result_file),
)


def _apply_result_mutation(files: dict[str, bytes], kind: str, arg) -> dict[str, bytes]:
    files = dict(files)
    if kind == "bytes":
        name, ops = arg
        if name in files:
            files[name] = _mutate_bytes(files[name], ops)
    elif kind == "cells":
        name, edits = arg
        if name in files:
            files[name] = _encode(_mutate_csv(_decode(files[name]), edits))
    elif kind == "json" and "result.json" in files:
        anchor, value = arg
        text = files["result.json"].decode("utf-8", "surrogateescape")
        at = text.find(anchor)
        if at >= 0:
            start = at + len(anchor)
            end = start
            while end < len(text) and text[end] not in ",\n}":
                end += 1
            text = text[:start] + value + text[end:]
        files["result.json"] = text.encode("utf-8", "surrogateescape")
    elif kind == "delete":
        files.pop(arg, None)
    return files


@settings(FUZZ, max_examples=RESULT_CASES)
@given(which=st.sampled_from(["complete", "crashed"]), mutations=st.lists(result_mutation, min_size=1, max_size=3))
def test_result_reader_raises_only_input_error(scratch, which, mutations) -> None:
    files = _base_result()[which]
    for kind, arg in mutations:
        files = _apply_result_mutation(files, kind, arg)
    root = _write_tree(scratch / "res", files)
    try:
        res = read_result(root)
    except InputError as exc:
        assert "\n" not in str(exc) and len(str(exc)) < 1200, str(exc)[:300]
        return
    assert np.all(np.isfinite(res.cam_T_needle)) and np.all(np.isfinite(res.t_s))
    assert res.frame.dtype == np.int64 and np.all(res.frame >= 0)
    if res.particles is not None:
        assert np.all(np.isfinite(res.particles.cam_T_needle))
