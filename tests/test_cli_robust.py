"""CLI smoke tests of ``track --robust`` and ``simulate --mask-spurs``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.io.result.reader import read_result


def test_track_robust_flag_and_mask_spurs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "9", "--seed", "2", "--mask-spurs", "0.5",
                 "--out", str(run)]) == 0
    for method in ("map", "svn"):
        out = tmp_path / method
        assert main(["track", str(run), "--method", method, "--particles", "12" if method == "svn" else "1",
                     "--robust", "conic=huber:2,grasp-perpendicular=cauchy", "--out", str(out)]) == 0
        res = read_result(out)
        assert len(res.frame) == 9 and np.all(np.isfinite(res.cam_T_needle))
        settings = json.loads((out / "result.json").read_text())["settings"]
        assert settings["robust"] == "conic=huber:2,grasp-perpendicular=cauchy:1"
    out = tmp_path / "gm"
    assert main(["track", str(run), "--method", "mht", "--robust", "conic=GM:3", "--out", str(out)]) == 0
    assert json.loads((out / "result.json").read_text())["settings"]["robust"] == "conic=gm:3"
    assert np.all(np.isfinite(read_result(out).cam_T_needle))
    out = tmp_path / "off"
    assert main(["track", str(run), "--method", "map", "--robust", "none", "--out", str(out)]) == 0
    assert json.loads((out / "result.json").read_text())["settings"]["robust"] == "none"
    capsys.readouterr()
    for bad in (["--robust", "conic=tukey"], ["--robust", "motion=huber"]):
        with pytest.raises(SystemExit) as exc:
            main(["track", str(run), *bad, "--out", str(tmp_path / "x")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "robust" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--mask-spurs", "2", "--out", str(tmp_path / "y")])
    assert exc.value.code == 2


def test_track_conic_distance_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "6", "--seed", "3", "--out", str(run)]) == 0
    for method, particles in (("map", "1"), ("svn", "12")):
        out = tmp_path / method
        assert main(["track", str(run), "--method", method, "--particles", particles, "--conic-distance", "geometric",
                     "--out", str(out)]) == 0
        assert json.loads((out / "result.json").read_text())["settings"]["conic_distance"] == "geometric"
        assert np.all(np.isfinite(read_result(out).cam_T_needle))
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["track", str(run), "--conic-distance", "euclid", "--out", str(tmp_path / "x")])
    assert exc.value.code == 2 and "conic-distance" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    # evaluate scores it with the model it was tracked with; a hand-edited value is one line, exit 2
    assert main(["evaluate", str(tmp_path / "map"), "--recording", str(run), "--out", str(tmp_path / "ev")]) == 0
    info = tmp_path / "map" / "result.json"
    doc = json.loads(info.read_text())
    for key, bad in (("conic_distance", "euclid"), ("conic_correlation_px", -3)):
        edited = json.loads(json.dumps(doc))
        edited["settings"][key] = bad
        info.write_text(json.dumps(edited))
        capsys.readouterr()
        assert main(["evaluate", str(tmp_path / "map"), "--recording", str(run), "--out", str(tmp_path / "ev2")]) == 2
        err = capsys.readouterr().err
        assert f"settings.{key}" in err and "Traceback" not in err


def test_track_conic_correlation_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--conic-correlation-px`` reaches every tracker's likelihood (recorded in result.json; it changes the
    poses, the batched path's SVN and the GTSAM path's MAP alike); bad lengths exit 2 with one line."""
    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "9", "--seed", "2", "--out", str(run)]) == 0
    for method, particles in (("map", "1"), ("svn", "12")):
        poses = {}
        for ell in ("0", "20"):
            out = tmp_path / f"{method}-{ell}"
            assert main(["track", str(run), "--method", method, "--particles", particles, "--conic-correlation-px",
                         ell, "--out", str(out)]) == 0
            settings = json.loads((out / "result.json").read_text())["settings"]
            assert settings["conic_correlation_px"] == float(ell)
            poses[ell] = read_result(out).cam_T_needle
        assert np.all(np.isfinite(poses["20"])) and not np.array_equal(poses["0"], poses["20"])
    capsys.readouterr()
    for bad in ("-1", "nan", "1e9", "x"):
        with pytest.raises(SystemExit) as exc:
            main(["track", str(run), "--conic-correlation-px", bad, "--out", str(tmp_path / "x")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "conic-correlation-px" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()
