"""pinpoint_fg.noise: noise files hold only variances the trackers can use (floors per residual type)."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from factors.robust import RobustLoss
from pinpoint_fg.errors import InputError
from pinpoint_fg.noise import (
    NOISE_VARIANCE_FLOOR,
    RESIDUAL_DIMS,
    NoiseConfig,
    ResidualNoise,
    format_robust,
    parse_robust_spec,
)


def _doc_with(name: str, variance: float) -> dict:
    doc = copy.deepcopy(NoiseConfig().to_json())
    doc["residuals"][name]["cov"] = (variance * np.eye(RESIDUAL_DIMS[name])).tolist()
    return doc


@pytest.mark.parametrize("name", sorted(NOISE_VARIANCE_FLOOR))
def test_each_residual_type_has_its_floor(name: str, tmp_path: Path) -> None:
    floor = NOISE_VARIANCE_FLOOR[name]
    at, below = tmp_path / "at.json", tmp_path / "below.json"
    at.write_text(json.dumps(_doc_with(name, floor)))
    below.write_text(json.dumps(_doc_with(name, 0.5 * floor)))
    assert NoiseConfig.load(at).residuals[name].cov[0, 0] == floor
    with pytest.raises(InputError, match=f"residuals.{name}"):
        NoiseConfig.load(below)


def test_the_defaults_lie_above_the_floors() -> None:
    for name, noise in NoiseConfig().residuals.items():
        assert np.linalg.eigvalsh(noise.cov)[0] >= NOISE_VARIANCE_FLOOR[name], name


def test_save_refuses_what_load_would_refuse_and_writes_nothing(tmp_path: Path) -> None:
    cfg = NoiseConfig()
    residuals = dict(cfg.residuals)
    residuals["tip"] = ResidualNoise(mean=np.zeros(2), cov=1e-6 * np.eye(2), count=10)  # e.g. noise-free data
    path = tmp_path / "noise.json"
    with pytest.raises(InputError, match="'tip'"):
        NoiseConfig(residuals=residuals, robust=cfg.robust).save(path)
    assert not path.exists()


@pytest.mark.parametrize(("name", "variance"),
                         [("tip", 1e-8), ("grasp_position", 1e-14), ("grasp_perpendicular", 1e-14)])
def test_a_variance_that_broke_the_map_baseline_is_one_line_before_tracking(name: str, variance: float,
                                                                             tmp_path: Path) -> None:
    """These made GTSAM's MAP baseline raise an indeterminate linear system mid-run (simulator, normal scenario);
    now the noise file is refused, with exit code 2, before anything is written."""
    run, noise, out = tmp_path / "run", tmp_path / "noise.json", tmp_path / "out"
    noise.write_text(json.dumps(_doc_with(name, variance)))
    cli = [sys.executable, "-m", "pinpoint_fg.cli"]
    assert subprocess.run([*cli, "simulate", "--scenario", "normal", "--frames", "3", "--seed", "1", "--out",
                           str(run)], capture_output=True).returncode == 0
    done = subprocess.run([*cli, "track", str(run), "--method", "map", "--noise", str(noise), "--out", str(out)],
                          capture_output=True, text=True)
    assert done.returncode == 2
    lines = [s for s in done.stderr.splitlines() if s.strip()]
    assert len(lines) == 1 and str(noise) in lines[0] and f"residuals.{name}" in lines[0], done.stderr
    assert not out.exists() or not any(out.iterdir())


def test_the_conic_correlation_length_round_trips_and_bad_ones_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "noise.json"
    NoiseConfig(conic_correlation_px=23.5).save(path)
    assert NoiseConfig.load(path).conic_correlation_px == 23.5
    assert NoiseConfig(conic_correlation_px=23.5).with_robust({}).conic_correlation_px == 23.5
    doc = NoiseConfig().to_json()
    del doc["conic_correlation_px"]  # a file written before the key existed: independent pixels
    path.write_text(json.dumps(doc))
    assert NoiseConfig.load(path).conic_correlation_px == 0.0
    for bad in (-1.0, "20", True, 1e5, None):
        doc["conic_correlation_px"] = bad
        path.write_text(json.dumps(doc))
        with pytest.raises(InputError, match="conic_correlation_px"):
            NoiseConfig.load(path)
    for bad in (-1.0, float("nan"), float("inf"), 1e5, True):
        with pytest.raises(ValueError, match="conic_correlation_px"):
            NoiseConfig(conic_correlation_px=bad)


def test_the_calibrated_conic_distance_round_trips_and_bad_ones_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "noise.json"
    noise = NoiseConfig(conic_correlation_px=4.0).with_conic_distance("geometric")
    noise.save(path)
    back = NoiseConfig.load(path)
    assert back.conic_distance == "geometric" and back.conic_correlation_px == 4.0
    # the copies keep it
    assert back.with_robust({}).conic_distance == back.with_conic_correlation(0.0).conic_distance == "geometric"
    doc = NoiseConfig().to_json()
    assert "conic_distance" not in doc  # the defaults were calibrated for no distance in particular
    path.write_text(json.dumps(doc))
    assert NoiseConfig.load(path).conic_distance is None  # a file from before the key: any distance
    for bad in ("euclid", 3, True, ["sampson"]):
        doc["conic_distance"] = bad
        path.write_text(json.dumps(doc))
        with pytest.raises(InputError, match="conic_distance"):
            NoiseConfig.load(path)
    with pytest.raises(ValueError, match="conic_distance"):
        NoiseConfig(conic_distance="euclid")


def test_a_geman_mcclure_loss_round_trips_through_a_noise_file(tmp_path: Path) -> None:
    path = tmp_path / "noise.json"
    robust = parse_robust_spec("conic=gm:3,grasp-perpendicular=huber:1.345")
    NoiseConfig().with_robust(robust).save(path)
    assert json.loads(path.read_text())["robust"]["conic"] == {"loss": "gm", "k": 3.0}
    assert NoiseConfig.load(path).robust["conic"] == RobustLoss("gm", 3.0)
    assert format_robust(NoiseConfig.load(path).robust) == "conic=gm:3,grasp-perpendicular=huber:1.345"


@pytest.mark.parametrize(("name", "key", "value", "says"), [
    ("tip", "cov", [[float("inf"), 0.0], [0.0, 1.0]], "'cov': [0][0] must be finite"),  # JSON Infinity, 1e400
    ("tip", "cov", [[1.0, 0.0], [0.0]], "'cov': [1] must be a list of 2 numbers"),  # was NumPy's "inhomogeneous"
    ("tip", "cov", [[True, 0.0], [0.0, 1.0]], "'cov': [0][0] must be a number, got true"),
    ("motion", "mean", float("inf"), "'mean': must be a list of 6 numbers, got Infinity"),  # was a shape mismatch
    ("tip", "mean", [None, 0.0], "'mean': [0] must be a number, got null"),  # was "NaN or infinite"
    ("tip", "mean", ["x", 0.0], "'mean': [0] must be a number, got \"x\""),  # was float()'s message
])
def test_malformed_noise_arrays_name_the_element(name: str, key: str, value: object, says: str,
                                                 tmp_path: Path) -> None:
    doc = copy.deepcopy(NoiseConfig().to_json())
    doc["residuals"][name][key] = value
    path = tmp_path / "noise.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as exc:
        NoiseConfig.load(path)
    assert str(exc.value).startswith(f'{path}: key "residuals.{name}": {says}'), str(exc.value)


@pytest.mark.parametrize(("cov", "mean"), [(0.25, 0.1), ([0.25], [0.1]), ([[0.25]], [[0.1]]), ([[0.25]], 0.1)])
def test_a_one_dimensional_residual_takes_its_scalar_forms(cov: object, mean: object, tmp_path: Path) -> None:
    """Hand-written files with ``"cov": 0.25`` for the conic loaded before the element checks, and still do."""
    doc = copy.deepcopy(NoiseConfig().to_json())
    doc["residuals"]["conic"].update(cov=cov, mean=mean)
    path = tmp_path / "noise.json"
    path.write_text(json.dumps(doc))
    conic = NoiseConfig.load(path)["conic"]
    assert conic.cov.tolist() == [[0.25]] and conic.mean.tolist() == [0.1]
    doc["residuals"]["conic"].update(cov=[0.25, 0.5])
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"must be a list of 1 number, got \[0.25, 0.5\]"):
        NoiseConfig.load(path)
