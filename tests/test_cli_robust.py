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
