"""The benchmark's held-out q95 coverage: factors fitted on one seed's results, coverage scored on others."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.experiments.coverage import (
    CLEAR_SCENARIOS,
    benchmark_coverage,
    held_out_coverage,
    write_coverage_csv,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.sim.scenarios import simulate

F = 30
Q_T, Q_R = 1e-3, math.radians(2.0)


def _result(out: Path, rec: Recording, method: str, err_t: np.ndarray, err_r: np.ndarray,
            q95: tuple[float, float] = (Q_T, Q_R)) -> Path:
    """A result whose frame ``f`` is ``err_t[f]`` (m) along camera x and ``err_r[f]`` (rad) about the needle's z
    off the truth, with constant bounds ``q95``."""
    settings_ = {"method": method, "particles": 1, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
    with ResultWriter(out, method, settings_, rec.info.name, str(rec.root.resolve())) as w:
        for f, r in enumerate(rec.frames[:F]):
            T = r.cam_T_needle_gt @ se3_exp(np.array([0.0, 0.0, err_r[f], 0.0, 0.0, 0.0]))
            T[:3, 3] += [err_t[f], 0.0, 0.0]
            w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=q95[0], q95_rot_rad=q95[1],
                             bimodal=False, iterations=1, latency_ms=1.0, particles=T[None],
                             log_posterior=np.zeros(1)))
    return out


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    return read_recording(simulate("normal", F, seed=7, out=tmp_path_factory.mktemp("cover") / "run"))


def test_coverage_raw_and_scaled_on_held_out_results_are_the_counted_shares(rec: Recording, tmp_path: Path) -> None:
    ratios = np.arange(1, F + 1) / 10.0  # error / q95: 0.1 ... 3.0
    train = _result(tmp_path / "train", rec, "svn", ratios * Q_T, ratios * Q_R)
    # kappa = the smallest ratio covering 95 % of the 30 training frames: the 29th of 30, 2.9 (both parts)
    held = _result(tmp_path / "held", rec, "svn", 0.5 * ratios * Q_T, 1.5 * ratios * Q_R)
    scale, rows = held_out_coverage([train], {("normal", 3, "svn"): held})
    k = scale.methods["svn"]
    assert k.kappa_trans == pytest.approx(2.9, rel=1e-6) and k.kappa_rot == pytest.approx(2.9, rel=1e-6)
    (row,) = rows
    assert (row.scenario, row.seed, row.method) == ("normal", 3, "svn")
    assert row.raw_trans == pytest.approx(np.mean(0.5 * ratios <= 1.0))  # 20 of 30
    assert row.raw_rot == pytest.approx(np.mean(1.5 * ratios <= 1.0))  # 6 of 30
    assert row.scaled_trans == pytest.approx(np.mean(0.5 * ratios <= k.kappa_trans))  # all
    assert row.scaled_rot == pytest.approx(np.mean(1.5 * ratios <= k.kappa_rot))  # 19 of 30
    assert (row.raw_trans, row.raw_rot, row.scaled_trans) == pytest.approx((20 / 30, 6 / 30, 1.0))
    assert row.scaled_rot == pytest.approx(19 / 30)


def test_a_method_without_factors_is_scored_raw_only(rec: Recording, tmp_path: Path) -> None:
    ratios = np.linspace(0.1, 2.0, F)
    train = _result(tmp_path / "train", rec, "svn", ratios * Q_T, ratios * Q_R)
    held = _result(tmp_path / "held", rec, "map", ratios * Q_T, ratios * Q_R)
    _, (row,) = held_out_coverage([train], {("normal", 3, "map"): held})
    assert np.isfinite(row.raw_trans) and math.isnan(row.scaled_trans) and math.isnan(row.scaled_rot)


def test_benchmark_layout_fits_on_the_first_unseen_seed_and_scores_the_others(rec: Recording, tmp_path: Path
                                                                               ) -> None:
    ratios = np.arange(1, F + 1) / 10.0
    for sc in CLEAR_SCENARIOS[:2]:  # the others were "not tracked": skipped, not an error
        _result(tmp_path / "seed-2" / "results" / sc / "svn", rec, "svn", ratios * Q_T, ratios * Q_R)
        _result(tmp_path / "results" / sc / "svn", rec, "svn", 0.5 * ratios * Q_T, 0.5 * ratios * Q_R)
        _result(tmp_path / "seed-4" / "results" / sc / "svn", rec, "svn", ratios * Q_T, ratios * Q_R)
    text, rows = benchmark_coverage(tmp_path, 1, (2, 4))
    assert sorted((r.scenario, r.seed) for r in rows) == sorted((sc, s) for sc in CLEAR_SCENARIOS[:2] for s in (1, 4))
    assert all(r.scaled_trans == pytest.approx(29 / 30) for r in rows if r.seed == 4)  # the training errors again
    assert f"{CLEAR_SCENARIOS[0]}-04" in text and "seed-2" not in text and "svn 2.90/2.90 (60)" in text
    write_coverage_csv(rows, tmp_path / "coverage.csv")
    with open(tmp_path / "coverage.csv", newline="", encoding="utf-8") as fh:
        got = list(csv.DictReader(fh))
    assert len(got) == len(rows) and float(got[0]["scaled_trans"]) == pytest.approx(rows[0].scaled_trans)


def test_nothing_fitted_gives_one_line_and_no_rows(rec: Recording, tmp_path: Path) -> None:
    zero = np.zeros(F)
    _result(tmp_path / "seed-2" / "results" / "normal" / "svn", rec, "svn", zero, zero, q95=(math.nan, math.nan))
    _result(tmp_path / "results" / "normal" / "svn", rec, "svn", zero, zero)
    text, rows = benchmark_coverage(tmp_path, 1, (2,))
    assert rows == [] and text.startswith("q95 coverage: no spread factor could be fitted on seed 2")
    assert "\n" not in text
