"""Spread recalibration: the fitted q95 factor on constructed results, applying it, the file and its reader, the CLI."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.eval.spread_calibration import coverage, fit_spread_scale, frame_errors, scale_quantile, scaled_result
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.reader import read_modes, read_result
from pinpoint_fg.io.result.schema import Result
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.io.spread_scale import MethodScale, SpreadScale, recorded_scale
from pinpoint_fg.posterior.summary import WEAK_COLUMNS, map_mode, weak_direction
from pinpoint_fg.sim.scenarios import simulate
from pinpoint_fg.track import track_recording

F = 40
Q95_TRANS_M = 1e-3
Q95_ROT_RAD = math.radians(2.0)
WRONG_MODE_FRAME = 7  # this frame's MAP is 40 deg off: another mode, left out of the fit
NAN_FRAME = 11  # this frame reports no q95: no claim, skipped


def _trans_err_m(f: int) -> float:
    """Translation error of frame ``f``: 0.1, 0.2, ... mm (ratio to q95 = (f + 1) / 10)."""
    return 1e-4 * (f + 1)


def _rot_err_rad(f: int) -> float:
    """Rotation error of frame ``f``: 0.25, 0.5, ... deg (ratio to q95 = (f + 1) / 8)."""
    return math.radians(0.25 * (f + 1))


def _write(out: Path, rec: Recording, method: str, factor: float = 1.0) -> Path:
    """A result whose MAP errors are known exactly: translation along camera x, rotation about needle z.

    ``factor`` multiplies every error (another method with other ratios).
    """
    settings_ = {"method": method, "particles": 1, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
    with ResultWriter(out, method, settings_, rec.info.name, str(rec.root.resolve())) as w:
        for f, r in enumerate(rec.frames[:F]):
            angle = math.radians(40.0) if f == WRONG_MODE_FRAME else factor * _rot_err_rad(f)
            T = r.cam_T_needle_gt @ se3_exp(np.array([0.0, 0.0, angle, 0.0, 0.0, 0.0]))
            T[:3, 3] += [factor * _trans_err_m(f), 0.0, 0.0]
            q_t, q_r = (math.nan, math.nan) if f == NAN_FRAME else (Q95_TRANS_M, Q95_ROT_RAD)
            w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=q_t, q95_rot_rad=q_r,
                             bimodal=False, iterations=1, latency_ms=1.0, particles=T[None],
                             log_posterior=np.zeros(1)))
    return out


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> tuple[Recording, dict[str, Path], Path]:
    base = tmp_path_factory.mktemp("spreadcal")
    rec = read_recording(simulate("normal", F, seed=5, out=base / "run"))
    results = {"svn": _write(base / "svn", rec, "svn"), "map": _write(base / "map", rec, "map", factor=0.5)}
    return rec, results, base


def _expected_kappa(ratios: np.ndarray) -> float:
    """Smallest ratio with at least 95 % of the ratios at or below it (sorted order statistic)."""
    r = np.sort(ratios)
    return float(r[math.ceil(0.95 * r.size) - 1])


# ----------------------------------------------------------------------------- the quantile


def test_scale_quantile_is_the_smallest_factor_covering_95_percent() -> None:
    rng = np.random.default_rng(0)
    q = rng.uniform(0.5, 2.0, 200)
    ratio = rng.permutation(np.arange(1, 201)) / 10.0  # 0.1 ... 20.0
    err = ratio * q
    k = scale_quantile(err, q)
    assert k == pytest.approx(19.0, rel=1e-9)  # the 190th of 200 sorted ratios
    assert coverage(err, k * q) == pytest.approx(0.95)  # exactly 95 %: the boundary frame is covered
    assert coverage(err, k * (1 - 1e-6) * q) < 0.95  # any smaller factor misses it


def test_scale_quantile_zero_spread_frames_count_as_misses() -> None:
    err = np.r_[np.full(95, 1.0), np.full(5, 2.0)]
    q = np.r_[np.full(95, 1.0), np.zeros(5)]  # five collapsed frames, all wrong: 95 % still reachable
    assert scale_quantile(err, q) == pytest.approx(1.0)
    q[0] = 0.0  # a sixth: no finite factor covers 95 %
    with pytest.raises(InputError, match="q95 = 0 with a nonzero error"):
        scale_quantile(err, q, what="q95_trans_m")
    assert scale_quantile(np.r_[0.0, np.ones(99)], np.r_[0.0, np.ones(99)]) == pytest.approx(1.0)  # 0/0: covered


@pytest.mark.parametrize(("err", "q", "match"), [
    ([], [], "no frame"),
    ([1.0, np.nan], [1.0, 1.0], "finite"),
    ([1.0, -1.0], [1.0, 1.0], "non-negative"),
    ([1.0, 1.0], [1.0, -1.0], "non-negative"),
    ([1.0], [1.0, 2.0], "errors but"),
    ([0.0] * 20, [1.0] * 20, "scale is 0"),
])
def test_scale_quantile_refuses_bad_input(err: list, q: list, match: str) -> None:
    with pytest.raises(InputError, match=match):
        scale_quantile(np.array(err), np.array(q))


# ----------------------------------------------------------------------------- the fit on results


def test_fit_on_constructed_results_gives_the_known_quantiles(data) -> None:  # noqa: ANN001
    _, results, _ = data
    scale = fit_spread_scale([results["svn"], results["map"]])
    used = np.array([f for f in range(F) if f not in (WRONG_MODE_FRAME, NAN_FRAME)])
    for method, factor in (("svn", 1.0), ("map", 0.5)):
        s = scale.methods[method]
        t_ratio = factor * np.array([_trans_err_m(f) for f in used]) / Q95_TRANS_M
        r_ratio = factor * np.array([_rot_err_rad(f) for f in used]) / Q95_ROT_RAD
        assert s.kappa_trans == pytest.approx(_expected_kappa(t_ratio), rel=1e-6)
        assert s.kappa_rot == pytest.approx(_expected_kappa(r_ratio), rel=1e-6)
        assert (s.frames, s.skipped_frames, s.wrong_mode_frames) == (F - 2, 1, 1)
        assert s.coverage_raw_trans == pytest.approx(np.mean(t_ratio <= 1.0))
        assert s.coverage_raw_rot == pytest.approx(np.mean(r_ratio <= 1.0))
    assert scale.methods["svn"].kappa_trans == pytest.approx(3.9, rel=1e-6)  # 37th of 38 ratios 0.1..4.0 (no 0.8, 1.2)
    assert scale.unfitted == {}
    assert set(scale.results) == {str(results["svn"].resolve()), str(results["map"].resolve())}


def test_without_the_gate_the_wrong_mode_frame_is_fitted_too(data) -> None:  # noqa: ANN001
    _, results, _ = data
    gated = fit_spread_scale([results["svn"]]).methods["svn"]
    all_frames = fit_spread_scale([results["svn"]], mode_gate_rad=math.pi).methods["svn"]
    assert (all_frames.frames, all_frames.wrong_mode_frames) == (gated.frames + 1, 0)
    assert all_frames.kappa_rot > gated.kappa_rot  # one more large ratio (40 deg / 2 deg = 20)
    with pytest.raises(InputError, match="mode gate"):
        fit_spread_scale([results["svn"]], mode_gate_rad=0.0)


def test_applying_the_scale_covers_95_percent_of_the_training_frames(data) -> None:  # noqa: ANN001
    rec, results, _ = data
    scale = fit_spread_scale([results["svn"]])
    res = read_result(results["svn"])
    scaled = scaled_result(res, scale)
    s = scale.methods["svn"]
    np.testing.assert_array_equal(scaled.q95_trans_m, s.kappa_trans * res.q95_trans_m)
    np.testing.assert_array_equal(scaled.cam_T_needle, res.cam_T_needle)  # the estimates do not move
    fe = frame_errors(res, rec)
    in_mode = fe.err_rot_rad <= math.radians(30.0)
    et, er = np.where(in_mode, fe.err_trans_m, np.nan), np.where(in_mode, fe.err_rot_rad, np.nan)
    assert coverage(et, scaled.q95_trans_m) >= 0.95 and coverage(er, scaled.q95_rot_rad) >= 0.95
    assert coverage(et, res.q95_trans_m) < 0.5  # raw: overconfident by construction
    assert np.isnan(scaled.q95_trans_m[NAN_FRAME])  # no claim stays no claim
    assert read_result(results["svn"]).q95_trans_m[0] == Q95_TRANS_M  # nothing on disk changed


def test_a_method_without_a_scale_is_refused(data) -> None:  # noqa: ANN001
    _, results, _ = data
    only_map = SpreadScale(methods={"map": MethodScale(1.5, 2.0)}, source="x.json")
    with pytest.raises(InputError, match="no scale for method 'svn'") as exc:
        scaled_result(read_result(results["svn"]), only_map)
    assert exc.value.column == "methods.svn"
    unfit = SpreadScale(methods={"map": MethodScale(1.5, 2.0)}, unfitted={"svn": "collapsed"})
    with pytest.raises(InputError, match="could not be fitted \\(collapsed\\)"):
        scaled_result(read_result(results["svn"]), unfit)


def test_a_method_that_cannot_be_fitted_is_listed_not_dropped(data) -> None:  # noqa: ANN001
    rec, results, base = data
    out = base / "pf"
    if not out.exists():
        settings_ = {"method": "pf", "particles": 1, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
        with ResultWriter(out, "pf", settings_, rec.info.name, str(rec.root.resolve())) as w:
            for r in rec.frames[:F]:  # a collapsed filter: zero spread, 1 mm off
                T = r.cam_T_needle_gt.copy()
                T[:3, 3] += [1e-3, 0.0, 0.0]
                w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=0.0, q95_rot_rad=0.0,
                                 bimodal=False, iterations=1, latency_ms=1.0, particles=T[None],
                                 log_posterior=np.zeros(1)))
    scale = fit_spread_scale([results["svn"], out])
    assert set(scale.methods) == {"svn"}
    assert "pf" in scale.unfitted and "q95 = 0" in scale.unfitted["pf"]
    with pytest.raises(InputError, match="no method could be fitted"):
        fit_spread_scale([out])


# ----------------------------------------------------------------------------- the file


def test_file_round_trip(data, tmp_path: Path) -> None:  # noqa: ANN001
    _, results, _ = data
    scale = fit_spread_scale([results["svn"], results["map"]])
    path = scale.save(tmp_path / "scale.json")
    doc = json.loads(path.read_text())
    assert (doc["format"], doc["version"]) == ("pinpoint-spread-scale", 1)
    back = SpreadScale.load(path)
    assert back.methods == scale.methods
    assert (back.level, back.mode_gate_rad, back.results, back.unfitted) == (
        scale.level, scale.mode_gate_rad, scale.results, scale.unfitted)
    assert back.source == str(path)


# ----------------------------------------------------------------------------- the command line


def test_cli_calibrate_spread_and_evaluate_with_it(data, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    _, results, _ = data
    out = tmp_path / "scale.json"
    assert main(["calibrate-spread", str(results["svn"]), str(results["map"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "kappa t/r" in printed and f"wrote {out}" in printed
    scale = SpreadScale.load(out)
    assert set(scale.methods) == {"svn", "map"}
    assert main(["calibrate-spread", str(results["svn"]), "--out", str(out)]) == 2  # exists, no --overwrite
    assert "--overwrite" in capsys.readouterr().err

    rep = tmp_path / "eval"
    assert main(["evaluate", str(results["svn"]), "--out", str(rep), "--spread-scale", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    head = next(i for i, ln in enumerate(printed) if "raw -> scaled" in ln)
    table = printed[head + 1: head + 3]  # header and the one result's row, each value under its head
    last = table[1].split()[-1]  # the scaled coverage, e.g. 97%/95%
    assert table[0].startswith("recording") and table[0].index("scaled cover t/r") == len(table[1]) - len(last)
    with open(rep / "summary.csv", newline="") as fh:
        row = next(csv.DictReader(fh))
    s = scale.methods["svn"]
    assert float(row["spread_kappa_trans"]) == pytest.approx(s.kappa_trans)
    assert float(row["trans_q95_mm"]) == pytest.approx(s.kappa_trans * Q95_TRANS_M * 1e3)
    # every frame counts in evaluate, the wrong-mode one included: 38 of 39 frames with a q95 in the fit
    assert float(row["coverage_raw_trans"]) == pytest.approx(np.mean([_trans_err_m(f) <= Q95_TRANS_M
                                                                      for f in range(F) if f != NAN_FRAME]))
    assert float(row["coverage_trans"]) >= 0.95 * (F - 2) / (F - 1)

    bad = tmp_path / "bad.json"
    doc = json.loads(out.read_text())
    doc["methods"]["svn"]["kappa_rot"] = -2.0
    bad.write_text(json.dumps(doc))
    assert main(["evaluate", str(results["svn"]), "--out", str(tmp_path / "e2"), "--spread-scale", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "methods.svn.kappa_rot" in err and "must be positive" in err
    assert main(["calibrate-spread", str(tmp_path / "missing"), "--out", str(tmp_path / "s2.json")]) == 2


def _assert_modes_scaled(raw: Result, scaled: Result, kt: float, kr: float) -> None:
    """modes.csv of ``scaled`` is that of ``raw`` with the covariances scaled like q95 (rotation block kr^2,
    translation kt^2, cross kr kt; 1e-12 relative), and its weak_* columns are those of the scaled MAP mode."""
    a, b = read_modes(raw.root), read_modes(scaled.root)
    np.testing.assert_array_equal(b.frame, a.frame)
    np.testing.assert_array_equal(b.weight, a.weight)
    np.testing.assert_array_equal(b.cam_T_needle, a.cam_T_needle)
    k = np.array([kr] * 3 + [kt] * 3)
    np.testing.assert_allclose(b.cov_xi, a.cov_xi * np.outer(k, k), rtol=1e-12, atol=0)
    assert not np.allclose(b.cov_xi, a.cov_xi, rtol=0.5)  # the factors are far from 1: the check can fail
    modes = b.by_frame()
    for i, f in enumerate(scaled.frame):
        u, sigma = weak_direction(map_mode(modes[int(f)], scaled.cam_T_needle[i]).cov_xi)
        assert scaled.extra["weak_sigma"][i] == pytest.approx(sigma, rel=1e-12)
        np.testing.assert_allclose([scaled.extra[c][i] for c in WEAK_COLUMNS[:6]], u, atol=1e-12)
    assert not np.allclose(scaled.extra["weak_sigma"], raw.extra["weak_sigma"])


def test_cli_track_with_a_spread_scale_writes_scaled_q95_and_records_it(data, tmp_path: Path,  # noqa: ANN001
                                                                        capsys: pytest.CaptureFixture) -> None:
    rec, _, _ = data
    scale = tmp_path / "scale.json"
    SpreadScale(methods={"map": MethodScale(2.5, 3.5)}).save(scale)
    raw, scaled = tmp_path / "raw", tmp_path / "scaled"
    args = ["track", str(rec.root), "--method", "map"]
    assert main([*args, "--out", str(raw)]) == 0
    assert main([*args, "--spread-scale", str(scale), "--out", str(scaled)]) == 0
    a, b = read_result(raw), read_result(scaled)
    np.testing.assert_array_equal(b.cam_T_needle, a.cam_T_needle)  # the estimates do not move
    np.testing.assert_array_equal(b.q95_trans_m, 2.5 * a.q95_trans_m)
    np.testing.assert_array_equal(b.q95_rot_rad, 3.5 * a.q95_rot_rad)
    assert b.info["settings"]["spread_scale"] == {"file": str(scale.resolve()), "kappa_trans": 2.5, "kappa_rot": 3.5}
    assert "spread_scale" not in a.info["settings"]
    assert recorded_scale(b.info["settings"], b.root / "result.json") == (2.5, 3.5)
    _assert_modes_scaled(a, b, 2.5, 3.5)
    capsys.readouterr()

    # no double scaling, no fit on scaled bounds, no method without a factor
    assert main(["evaluate", str(scaled), "--spread-scale", str(scale), "--out", str(tmp_path / "e1")]) == 2
    assert "already scaled" in capsys.readouterr().err
    assert main(["calibrate-spread", str(scaled), "--out", str(tmp_path / "s.json")]) == 2
    assert "settings.spread_scale" in capsys.readouterr().err
    assert main(["track", str(rec.root), "--method", "svn", "--spread-scale", str(scale),
                 "--out", str(tmp_path / "svn")]) == 2
    assert "no scale for method 'svn'" in capsys.readouterr().err

    # evaluated as tracked: the recorded factors and the raw coverage (of q95 / kappa) in the row
    assert main(["evaluate", str(raw), str(scaled), "--out", str(tmp_path / "e2")]) == 0
    assert "the factors recorded when tracked" in capsys.readouterr().out
    with open(tmp_path / "e2" / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["spread_kappa_trans"]) for r in rows] == [1.0, 2.5]
    assert rows[1]["coverage_raw_trans"] == rows[0]["coverage_trans"] == rows[0]["coverage_raw_trans"]
    assert rows[1]["coverage_raw_rot"] == rows[0]["coverage_rot"]




def test_track_with_a_spread_scale_scales_every_mode_of_a_bank(data, tmp_path: Path) -> None:  # noqa: ANN001
    """MHT: several modes per frame, each a GTSAM marginal; every one is scaled, weights and poses untouched."""
    rec, _, _ = data
    scale = tmp_path / "scale.json"
    SpreadScale(methods={"mht": MethodScale(2.25, 2.9)}).save(scale)
    kw = dict(method="mht", max_frames=10, progress=False)
    a = read_result(track_recording(rec.root, out=tmp_path / "raw", **kw))
    b = read_result(track_recording(rec.root, out=tmp_path / "scaled", spread_scale=scale, **kw))
    assert np.any(np.bincount(read_modes(a.root).frame) >= 2)  # a frame with several modes is among them
    _assert_modes_scaled(a, b, 2.25, 2.9)


def test_cli_calibrate_spread_names_the_sub_directories_of_a_batch_it_skips(data, tmp_path: Path,  # noqa: ANN001
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    _, results, _ = data
    batch = tmp_path / "batch"
    batch.mkdir()
    shutil.copytree(results["svn"], batch / "svn")
    (batch / "failed").mkdir()  # the empty directory a failed batch run left: was skipped without a word
    capsys.readouterr()
    assert main(["calibrate-spread", str(batch), "--out", str(tmp_path / "s.json")]) == 0
    err = capsys.readouterr().err
    assert f"note: skipped {batch / 'failed'}: empty, not a result" in err and len(err.splitlines()) == 1
    notes: list[str] = []
    scale = fit_spread_scale([batch], notes=notes)
    assert scale.results == (str((batch / "svn").resolve()),) and notes == [err.strip()]
