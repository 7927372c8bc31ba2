"""Tracking-result format v1: round trip, crash safety (every finished frame readable), validation."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import pinpoint_fg
from factors.lie import se3_exp
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.result.particles import JOURNAL_HEADER_BYTES, journal_dtype
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.io.result.schema import ESTIMATE_COLUMNS, PARTICLES_JOURNAL
from pinpoint_fg.io.result.writer import ResultWriter

N = 7  # particles


def make_estimates(n_frames: int = 5, weighted: bool = True, smoothed: bool = True, seed: int = 0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_frames):
        k = 10 + 3 * i
        P = se3_exp(rng.normal(size=(N, 6)) * 0.2)
        logp = rng.normal(size=N) * 3.0
        logp[0] = -np.inf if i == 1 else logp[0]  # a particle of zero posterior is representable
        w = rng.random(N)
        out.append(
            Estimate(
                frame=k,
                t_s=k / 30.0,
                cam_T_needle=P[1],
                q95_trans_m=float(rng.random() * 1e-3),
                q95_rot_rad=float(rng.random() * 0.1) if i != 2 else float("nan"),
                bimodal=bool(i % 2),
                iterations=int(rng.integers(1, 30)),
                latency_ms=float(rng.random() * 40),
                particles=P,
                log_posterior=logp,
                weights=w / w.sum() if weighted else None,
                smoothed=(k - 3, (k - 3) / 30.0, se3_exp(rng.normal(size=6))) if smoothed and i > 0 else None,
                extra={"reseeded": float(i == 3), "ess": float(rng.random() * N)},
            )
        )
    return out


def open_writer(out: Path, weighted: bool = True, smoothed: bool = True, **kw) -> ResultWriter:
    settings = {"particles": N, "window": 2, "disable": ("dense",), "sigma": np.float64(0.5), "path": out}
    return ResultWriter(out, "svn", settings, "unit-run", "/data/unit-run", weighted, smoothed, **kw)


def assert_matches(res, ests, weighted: bool = True) -> None:
    F = len(ests)
    assert len(res) == F
    assert res.frame.tolist() == [e.frame for e in ests]
    assert res.t_s.tolist() == [e.t_s for e in ests]  # repr text: bit-exact
    np.testing.assert_allclose(res.cam_T_needle, np.stack([e.cam_T_needle for e in ests]), rtol=0, atol=2e-15)
    np.testing.assert_array_equal(res.q95_trans_m, [e.q95_trans_m for e in ests])
    np.testing.assert_array_equal(res.q95_rot_rad, [e.q95_rot_rad for e in ests])  # NaN == NaN here
    assert res.bimodal.tolist() == [e.bimodal for e in ests]
    assert res.iterations.tolist() == [e.iterations for e in ests]
    assert res.latency_ms.tolist() == [e.latency_ms for e in ests]
    assert res.extra["reseeded"].tolist() == [e.extra["reseeded"] for e in ests]
    p = res.particles
    assert p is not None and p.frame.tolist() == res.frame.tolist()
    assert p.cam_T_needle.shape == (F, N, 4, 4) and p.T is p.cam_T_needle
    np.testing.assert_allclose(p.cam_T_needle, np.stack([e.particles for e in ests]), rtol=0, atol=2e-15)
    np.testing.assert_array_equal(p.log_posterior, np.stack([e.log_posterior for e in ests]))
    if weighted:
        np.testing.assert_array_equal(p.weight, np.stack([e.weights for e in ests]))
    else:
        assert p.weight is None


def test_round_trip(tmp_path: Path) -> None:
    ests = make_estimates()
    out = tmp_path / "res"
    with open_writer(out) as w:
        for e in ests:
            w.write(e)
        w.write_smoothed(ests[-1].frame - 1, (ests[-1].frame - 1) / 30.0, np.eye(4))  # end of the window
    res = read_result(out)
    assert_matches(res, ests)
    assert res.complete and res.method == "svn"
    info = res.info
    assert info["format"] == "pinpoint-result" and info["version"] == 1
    assert info["recording_name"] == "unit-run" and info["recording_path"] == "/data/unit-run"
    assert info["library_version"] == pinpoint_fg.__version__
    assert info["settings"] == {"particles": N, "window": 2, "disable": ["dense"], "sigma": 0.5, "path": str(out)}
    assert info["frames"] == len(ests) and info["particles"] == N
    sm_frames, sm_T = res.smoothed
    assert sm_frames.tolist() == [e.smoothed[0] for e in ests[1:]] + [ests[-1].frame - 1]
    np.testing.assert_allclose(sm_T[:-1], np.stack([e.smoothed[2] for e in ests[1:]]), atol=2e-15)
    assert not (out / PARTICLES_JOURNAL).exists()

    # the files as an outside tool sees them
    with open(out / "estimates.csv", newline="") as f:
        header = next(csv.reader(f))
    assert tuple(header) == (*ESTIMATE_COLUMNS, "reseeded", "ess")
    with np.load(out / "particles.npz", allow_pickle=False) as z:
        assert sorted(z.files) == ["frame", "log_posterior", "quat_wxyz", "weight", "xyz_m"]
        assert z["xyz_m"].shape == (5, N, 3) and z["quat_wxyz"].shape == (5, N, 4)
        np.testing.assert_allclose(np.linalg.norm(z["quat_wxyz"], axis=-1), 1.0, atol=1e-15)
    lines = (out / "trajectory.tum").read_text().splitlines()
    assert len(lines) == len(ests)
    t, x, y, z, qx, qy, qz, qw = map(float, lines[3].split(" "))
    T = ests[3].cam_T_needle
    assert t == ests[3].t_s and [x, y, z] == pytest.approx(T[:3, 3].tolist(), abs=0)
    assert qw >= 0 and qw**2 + qx**2 + qy**2 + qz**2 == pytest.approx(1.0, abs=1e-15)
    assert 2 * np.arccos(min(qw, 1.0)) == pytest.approx(np.arccos((np.trace(T[:3, :3]) - 1) / 2), abs=1e-7)


def test_unweighted_unsmoothed_and_empty(tmp_path: Path) -> None:
    ests = make_estimates(3, weighted=False, smoothed=False)
    with open_writer(tmp_path / "a", weighted=False, smoothed=False) as w:
        for e in ests:
            w.write(e)
    res = read_result(tmp_path / "a")
    assert_matches(res, ests, weighted=False)
    assert res.smoothed is None and not (tmp_path / "a" / "smoothed.csv").exists()
    with np.load(tmp_path / "a" / "particles.npz", allow_pickle=False) as z:
        assert "weight" not in z.files

    open_writer(tmp_path / "b").close()
    empty = read_result(tmp_path / "b")
    assert len(empty) == 0 and empty.particles is None and empty.complete


def test_abandoned_writer_keeps_every_written_frame(tmp_path: Path) -> None:
    ests = make_estimates(4)
    out = tmp_path / "res"
    w = open_writer(out)
    for e in ests:
        w.write(e)
    # no close(): the process could die here
    res = read_result(out)
    assert not res.complete
    assert_matches(res, ests)
    with np.load(out / "particles.npz", allow_pickle=False) as z:  # small arrays: rewritten every frame
        assert z["frame"].tolist() == [e.frame for e in ests]
    w.close()
    assert read_result(out).complete


def test_throttled_npz_lags_but_the_journal_has_every_frame(tmp_path: Path) -> None:
    ests = make_estimates(5)
    out = tmp_path / "res"
    w = open_writer(out, npz_large_bytes=0, npz_min_interval_s=1e9)  # "large": rewrite only on close
    for e in ests:
        w.write(e)
    with np.load(out / "particles.npz", allow_pickle=False) as z:
        assert z["frame"].tolist() == [ests[0].frame]  # readable, but behind
    assert_matches(read_result(out), ests)
    w.close()
    with np.load(out / "particles.npz", allow_pickle=False) as z:
        assert z["frame"].tolist() == [e.frame for e in ests]


def test_process_killed_mid_run(tmp_path: Path) -> None:
    out = tmp_path / "res"
    script = textwrap.dedent(
        f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from pathlib import Path
        from test_io_result import make_estimates, open_writer
        w = open_writer(Path({str(out)!r}), npz_large_bytes=0, npz_min_interval_s=1e9)
        for e in make_estimates(6):
            w.write(e)
        os._exit(0)  # no close, no interpreter clean-up
        """
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    res = read_result(out)
    assert not res.complete
    assert_matches(res, make_estimates(6))


def test_torn_last_row_is_dropped_when_incomplete(tmp_path: Path) -> None:
    ests = make_estimates(3)
    out = tmp_path / "res"
    w = open_writer(out)
    for e in ests:
        w.write(e)
    with open(out / "estimates.csv", "a") as f:
        f.write("99,3.3,0.1")  # a row cut off by a crash
    res = read_result(out)
    assert res.frame.tolist() == [e.frame for e in ests]


def test_writer_rejects_inconsistent_frames(tmp_path: Path) -> None:
    ests = make_estimates(3)
    with open_writer(tmp_path / "r") as w:
        w.write(ests[0])
        with pytest.raises(ValueError, match="N is fixed"):
            w.write(Estimate(**{**ests[1].__dict__, "particles": ests[1].particles[:3],
                                     "log_posterior": ests[1].log_posterior[:3], "weights": ests[1].weights[:3]}))
        with pytest.raises(ValueError, match="not greater"):
            w.write(ests[0])
        with pytest.raises(ValueError, match="no weight"):
            w.write(Estimate(**{**ests[1].__dict__, "weights": None}))
        with pytest.raises(ValueError, match="extra keys"):
            w.write(Estimate(**{**ests[1].__dict__, "extra": {"new": 1.0}}))
        with pytest.raises(ValueError, match="proper rotation"):
            w.write(Estimate(**{**ests[1].__dict__, "cam_T_needle": 2 * np.eye(4)}))
        w.write(ests[1])
    with pytest.raises(ValueError, match="closed"):
        w.write(ests[2])
    assert len(read_result(tmp_path / "r")) == 2


def test_exception_inside_the_with_block_leaves_an_incomplete_result(tmp_path: Path) -> None:
    ests = make_estimates(3)
    with pytest.raises(KeyboardInterrupt), open_writer(tmp_path / "r") as w:
        w.write(ests[0])
        w.write(ests[1])
        raise KeyboardInterrupt
    res = read_result(tmp_path / "r")
    assert not res.complete and res.info["stopped"] == "KeyboardInterrupt"
    assert_matches(res, ests[:2])


# ---------------------------------------------------------------------------------------------
# malformed results
# ---------------------------------------------------------------------------------------------


@pytest.fixture()
def result_dir(tmp_path: Path) -> Path:
    out = tmp_path / "res"
    with open_writer(out) as w:
        for e in make_estimates(4):
            w.write(e)
    return out


def set_cell(path: Path, data_row: int, column: str, value: str) -> None:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    rows[data_row][rows[0].index(column)] = value
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


@pytest.mark.parametrize(
    ("file", "row", "column", "value", "words"),
    [
        ("estimates.csv", 2, "x_m", "abc", "not a finite number"),
        ("estimates.csv", 3, "t_s", "nan", "not a finite number"),
        ("estimates.csv", 1, "bimodal", "yes", "0 or 1"),
        ("estimates.csv", 4, "iterations", "2.5", "integer"),
        ("estimates.csv", 4, "iterations", "\u0662", "integer"),  # int() reads Arabic-Indic digits; not the format's
        ("estimates.csv", 2, "x_m", "0.\uff10\uff11", "not a finite number"),  # full-width digits: float() reads them
        ("estimates.csv", 3, "frame", "10", "not greater"),
        ("estimates.csv", 2, "qw", "3.0", "norm"),
        ("smoothed.csv", 2, "qz", "x", "not a finite number"),
    ],
)
def test_malformed_cell(result_dir: Path, file: str, row: int, column: str, value: str, words: str) -> None:
    set_cell(result_dir / file, row, column, value)
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    err = info.value
    assert Path(err.file).name == file and err.row == row and err.column == column
    assert file in str(err) and f"row {row}:" in str(err) and repr(column) in str(err) and words in str(err)


def test_nan_allowed_in_uncertainty_columns(result_dir: Path) -> None:
    set_cell(result_dir / "estimates.csv", 1, "latency_ms", "nan")
    assert np.isnan(read_result(result_dir).latency_ms[0])


@pytest.mark.parametrize("key", ["method", "complete", "weighted", "library_version"])
def test_missing_result_json_key(result_dir: Path, key: str) -> None:
    path = result_dir / "result.json"
    doc = json.loads(path.read_text())
    del doc[key]
    doc["future_key"] = {"ignored": True}
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    assert info.value.column == key and "result.json" in str(info.value) and "missing" in str(info.value)


def test_extra_keys_and_columns_are_ignored(result_dir: Path) -> None:
    path = result_dir / "result.json"
    doc = json.loads(path.read_text())
    doc["future_key"] = [1, 2]
    path.write_text(json.dumps(doc))
    with open(result_dir / "estimates.csv", newline="") as f:
        rows = list(csv.reader(f))
    for i, r in enumerate(rows):
        r.append("comment" if i == 0 else f"text {i}")
    with open(result_dir / "estimates.csv", "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    res = read_result(result_dir)
    assert len(res) == 4 and "comment" not in res.extra and set(res.extra) == {"reseeded", "ess"}


def test_particles_npz_is_validated(result_dir: Path) -> None:
    path = result_dir / "particles.npz"
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    bad = dict(arrays, log_posterior=arrays["log_posterior"].copy())
    bad["log_posterior"][2, 3] = np.nan
    np.savez(path, **bad)
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    assert info.value.column == "log_posterior" and info.value.row == 3 and "particles.npz" in str(info.value)

    np.savez(path, **dict(arrays, xyz_m=np.array([object()] * 3, dtype=object)))  # needs pickle
    with pytest.raises(InputError, match="allow_pickle=False"):
        read_result(result_dir)

    np.savez(path, **{k: v for k, v in arrays.items() if k != "weight"})  # result.json says weighted
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    assert info.value.column == "weighted" and "particles.npz holds no per-particle weights" in str(info.value)

    np.savez(path, **dict(arrays, frame=arrays["frame"][::-1].copy()))
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    assert info.value.column == "frame" and info.value.row == 2

    path.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="particles.npz"):
        read_result(result_dir)


@pytest.mark.parametrize(("value", "words"), [(0.0, "are all zero"), (1e308, "sum to infinity")])
def test_particles_npz_frame_weights_must_have_a_positive_finite_sum(result_dir: Path, value: float,
                                                                    words: str) -> None:
    # all zero was "column 'weights'" from the bimodality test with no file or row; every weight 1e308 (each one
    # finite, the sum inf) was NumPy's overflow warning there and a bimodal rate computed from NaNs, exit 0
    path = result_dir / "particles.npz"
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["weight"] = arrays["weight"].copy()
    arrays["weight"][2] = value
    np.savez(path, **arrays)
    with pytest.raises(InputError) as info:
        read_result(result_dir)
    err = info.value
    assert Path(err.file).name == "particles.npz" and err.row == 3 and err.column == "weight"
    assert words in str(err) and f"frame {int(arrays['frame'][2])}" in str(err)


@pytest.mark.parametrize("value", [0.0, 1e308])
def test_particles_journal_frame_weights_must_have_a_positive_finite_sum(tmp_path: Path, value: float) -> None:
    out = tmp_path / "res"
    w = open_writer(out, npz_large_bytes=0, npz_min_interval_s=1e9)  # the npz lags: frames 2.. come from the journal
    for e in make_estimates(4):
        w.write(e)
    # no close(): the process could die here
    path = out / PARTICLES_JOURNAL
    data = bytearray(path.read_bytes())
    dt = journal_dtype(N, True)
    rec = np.frombuffer(data, dtype=dt, count=4, offset=JOURNAL_HEADER_BYTES).copy()
    rec["weight"][2] = value
    data[JOURNAL_HEADER_BYTES:JOURNAL_HEADER_BYTES + rec.nbytes] = rec.tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as info:
        read_result(out)
    err = info.value
    assert Path(err.file).name == PARTICLES_JOURNAL and err.row == 3 and err.column == "weight"
    w.close()


def _refused_with_weighted(out: Path, flag: bool) -> InputError:
    """Set result.json's "weighted" to ``flag``; the reader's refusal, which must name result.json's ``weighted``."""
    path = out / "result.json"
    doc = json.loads(path.read_text())
    doc["weighted"] = flag
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        read_result(out)
    assert Path(info.value.file).name == "result.json" and info.value.column == "weighted"
    return info.value


@pytest.mark.parametrize("flag", [False, True])
def test_result_json_weighted_must_agree_with_the_particles(tmp_path: Path, flag: bool) -> None:
    # "weighted": false over a particle filter's weights was evaluated with the weights ignored (bimodal rate
    # 17 % -> 8 %, exit 0); true over unweighted particles was "missing required array" blaming particles.npz
    out = tmp_path / "res"
    with open_writer(out, weighted=not flag) as w:
        for e in make_estimates(3, weighted=not flag):
            w.write(e)
    err = _refused_with_weighted(out, flag)
    assert err.row is None and f"is {str(flag).lower()} but particles.npz holds" in str(err)


def test_result_json_weighted_must_agree_with_the_journal(tmp_path: Path) -> None:
    out = tmp_path / "res"
    w = open_writer(out, npz_large_bytes=0, npz_min_interval_s=1e9)
    for e in make_estimates(3):
        w.write(e)
    # no close(): a crashed run; its result.json is then edited to "weighted": false
    (out / "particles.npz").unlink()
    err = _refused_with_weighted(out, False)
    assert "particles.journal holds per-particle weights" in str(err)
    w.close()


def test_expand_result_dirs_reports_the_sub_directories_it_skips(result_dir: Path, tmp_path: Path) -> None:
    from pinpoint_fg.io.result.reader import expand_result_dirs, skipped_dir_note

    batch = tmp_path / "batch"
    batch.mkdir()
    result_dir.rename(batch / "a")
    for name in ("b-failed", ".hidden", "c\nnewline"):
        (batch / name).mkdir()
    (batch / "summary.txt").write_text("a file, not a sub-directory")
    assert expand_result_dirs([batch]) == [batch / "a"]  # the signature other callers use is unchanged
    skipped: list[Path] = []
    assert expand_result_dirs([batch, batch / "a"], skipped) == [batch / "a"]
    assert skipped == [batch / "b-failed", batch / "c\nnewline"]
    note = skipped_dir_note(skipped[1])
    assert "\n" not in note and note.startswith("note: skipped ") and "empty, not a result" in note
    # a directory without any result is passed through for read_result to refuse, not "skipped"
    skipped.clear()
    assert expand_result_dirs([batch / "b-failed"], skipped) == [batch / "b-failed"] and skipped == []
