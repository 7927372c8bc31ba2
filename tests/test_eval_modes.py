"""Modes in the evaluation: both verdicts judged against a reference MHT result, truth kept, the figure."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.eval.modes import ResultModes, mode_weight_calibration, reference_rates
from pinpoint_fg.eval.report import evaluate_results
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.posterior.modes import Mode
from pinpoint_fg.sim.scenarios import simulate

F = 12
COV = np.diag([np.radians(1.0) ** 2] * 3 + [(0.2e-3) ** 2] * 3)


def _shift(T: np.ndarray, dx_m: float) -> np.ndarray:
    T = T.copy()
    T[:3, 3] += [dx_m, 0.0, 0.0]
    return T


def _write(out: Path, rec: Recording, method: str, multi: set[int], far: set[int] = frozenset(),
           clusters: set[int] | None = None) -> Path:
    """Result whose modes are 0.6 / 0.4 on the frame positions in ``multi`` (else one mode of weight 1).

    The dominant peak is 1 mm from the truth (5 mm on positions in ``far``); the second mode is 40 deg
    away. The 50 particles hold two clusters (35 / 15, 40 deg apart) on the positions in ``clusters``
    (default ``multi``), else one tight cluster; particle 0 is the dominant peak.
    """
    clusters = multi if clusters is None else clusters
    rng = np.random.default_rng(1)
    settings = {"method": method, "particles": 50, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
    with ResultWriter(out, method, settings, rec.info.name, str(rec.root.resolve())) as w:
        for i, r in enumerate(rec.frames[:F]):
            T = _shift(r.cam_T_needle_gt, 5e-3 if i in far else 1e-3)
            other = T @ se3_exp(np.array([0.7, 0, 0, 0, 0, 0]))
            xi = rng.normal(size=(50, 6)) * np.r_[[np.radians(1.0)] * 3, [0.2e-3] * 3]
            xi[0] = 0.0
            if i in clusters:
                xi[35:, 0] += 0.7
            if i in multi:
                modes = (Mode(T, 0.6, COV), Mode(other, 0.4, COV))
            else:
                modes = (Mode(T, 1.0, COV),)
            P = T[None] @ se3_exp(xi)
            w.write(Estimate(
                frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=2e-3, q95_rot_rad=0.1, bimodal=False,
                iterations=1, latency_ms=5.0, particles=P, log_posterior=np.zeros(50), modes=modes,
            ))
    return out


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Recording, Path, Path, Path]:
    base = tmp_path_factory.mktemp("modes")
    rec = read_recording(simulate("rotation", F, seed=3, out=base / "run"))
    mht = _write(base / "mht", rec, "mht", multi=set(range(6)))
    # the evaluated method: multimodal on 5 of the reference's 6 multimodal frames, and on 1 of its 6
    # single-mode frames; its GMM verdict sees two clusters on frames 0-5 only
    svn = _write(base / "svn", rec, "svn", multi={0, 1, 2, 3, 4, 11}, far={6, 7},
                 clusters=set(range(6)))
    return rec, mht, svn, base


def test_reference_rates_on_a_constructed_example() -> None:
    frames = np.arange(6)
    gmm = np.array([1, 1, 0, 0, 0, 1], bool)
    modes = np.array([1, 0, 0, 0, 1, 1], bool)
    ref_w = np.array([[0.5, 0.5], [0.8, 0.2], [0.95, 0.05], [1.0, 0.0], [0.9, 0.1], [np.nan, np.nan]])
    r = reference_rates(frames, gmm, np.ones(6, bool), modes, np.ones(6, bool), frames, ref_w)
    # reference multimodal: frames 0, 1, 4 (second >= 0.1); single: 2, 3; frame 5 has no reference modes
    assert (r["ref_multimodal_frames"], r["ref_single_frames"]) == (3, 2)
    assert r["bimodal_ref_multi_rate"] == pytest.approx(2 / 3)
    assert r["bimodal_modes_ref_multi_rate"] == pytest.approx(2 / 3)
    assert r["bimodal_ref_single_rate"] == 0.0 and r["bimodal_modes_ref_single_rate"] == 0.0


def test_mode_weights_against_the_truth_on_a_constructed_example() -> None:
    """Minor-mode weight vs how often the truth sits in a minor mode, over the frames some mode keeps the truth."""
    T = np.eye(4)
    T[2, 3] = 0.1
    away = T @ se3_exp(np.array([0.7, 0, 0, 0, 0, 0]))  # 40 deg: not the truth
    peaks = [np.stack([T, away]), np.stack([away, T]), np.stack([T]), np.stack([away]), np.zeros((0, 4, 4))]
    weights = np.array([[0.8, 0.2], [0.7, 0.3], [1.0, 0.0], [1.0, 0.0], [np.nan, np.nan]])
    modes = ResultModes(weights, peaks, "modes.csv")
    gt = np.broadcast_to(T, (5, 4, 4))
    r = mode_weight_calibration(modes, gt, np.ones(5, bool))
    # frames 0-2 keep the truth (frame 3's only mode is 40 deg off, frame 4 has none): minor weights 0.2, 0.3, 0;
    # the truth is in the minor mode on frame 1 (the dominant there is the 0.7 mode 40 deg away)
    assert r["truth_mode_frames"] == 3
    assert r["minor_weight_mean"] == pytest.approx(0.5 / 3)
    assert r["truth_minor_share"] == pytest.approx(1 / 3)
    none = mode_weight_calibration(modes, gt, np.zeros(5, bool))
    assert none["truth_mode_frames"] == 0 and np.isnan(none["minor_weight_mean"])


def test_mht_among_the_results_is_the_reference(setup) -> None:  # noqa: ANN001
    rec, mht, svn, base = setup
    rep = evaluate_results([mht, svn], out=base / "eval", ambiguity=False)
    ref_row, row = rep.evaluations[0].row, rep.evaluations[1].row
    assert row["reference"] == str(mht) and ref_row["reference"] == str(mht)
    assert (row["ref_multimodal_frames"], row["ref_single_frames"]) == (6, 6)
    assert row["bimodal_modes_ref_multi_rate"] == pytest.approx(5 / 6)
    assert row["bimodal_modes_ref_single_rate"] == pytest.approx(1 / 6)
    assert row["bimodal_ref_multi_rate"] == 1.0 and row["bimodal_ref_single_rate"] == 0.0
    assert ref_row["bimodal_modes_ref_multi_rate"] == 1.0 and ref_row["bimodal_modes_ref_single_rate"] == 0.0
    assert row["bimodal_modes_share"] == pytest.approx(6 / 12)
    assert row["truth_kept_modes_share"] == pytest.approx(10 / 12)  # frames 6, 7: 5 mm off
    assert row["truth_kept_particles_share"] == pytest.approx(10 / 12)
    assert ref_row["truth_kept_modes_share"] == 1.0
    # the truth is always in the dominant mode (1 mm off; frames 6, 7 keep it in no mode): minor weight 0.4 on
    # frames 0-4 and 11, 0 on the other four of the ten that keep it
    assert row["truth_mode_frames"] == 10 and row["truth_minor_share"] == 0.0
    assert row["minor_weight_mean"] == pytest.approx(0.4 * 6 / 10)
    names = {p.name for p in (base / "eval").glob("modes_time_*.png")}
    assert names == {f"modes_time_{rec.info.name}_mht.png", f"modes_time_{rec.info.name}_svn.png"}
    for p in (base / "eval").glob("modes_time_*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(base / "eval" / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert float(rows[1]["bimodal_modes_ref_single_rate"]) == pytest.approx(1 / 6)
    assert "## Posterior modes" in (base / "eval" / "tables.md").read_text()
    assert "vs reference" in rep.text


def test_reference_flag_and_a_reference_without_modes(setup, tmp_path: Path,  # noqa: ANN001
                                                      capsys: pytest.CaptureFixture) -> None:
    rec, mht, svn, base = setup
    assert main(["evaluate", str(svn), "--reference", str(mht), "--out", str(tmp_path / "e")]) == 0
    assert "vs reference: GMM 100% / 0%, modes 83% / 17% (6 / 6 frames)" in capsys.readouterr().out
    rep = evaluate_results([svn], out=tmp_path / "e2", ambiguity=False, figures=False)
    assert rep.evaluations[0].row["reference"] == "" and np.isnan(rep.evaluations[0].row["bimodal_ref_multi_rate"])
    old = shutil.copytree(svn, tmp_path / "old")
    (old / "modes.csv").unlink()  # an old result: modes recomputed from its particles (two clusters on 0-5)
    rep = evaluate_results([old], out=tmp_path / "e3", ambiguity=False, figures=False, reference=mht)
    assert rep.evaluations[0].modes.source == "particles"
    assert rep.evaluations[0].row["bimodal_modes_ref_multi_rate"] == 1.0
    assert rep.evaluations[0].row["bimodal_modes_ref_single_rate"] == 0.0
    with pytest.raises(InputError, match="no modes.csv"):
        evaluate_results([mht], out=tmp_path / "e4", ambiguity=False, figures=False, reference=old)


def test_a_single_mode_reference_is_refused_and_the_text_names_the_references_method(
        setup, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    """A MAP result as ``--reference`` (one mode per frame: every frame "single-mode") is refused at its
    result.json's ``method``; an SVN reference is accepted, and the rates line says SVN, not MHT."""
    rec, mht, svn, base = setup
    as_map = _write(tmp_path / "map", rec, "map", multi=set())
    with pytest.raises(InputError, match="single-mode MAP") as exc:
        evaluate_results([svn], out=tmp_path / "e", ambiguity=False, figures=False, reference=as_map)
    assert exc.value.column == "method" and not (tmp_path / "e").exists()
    capsys.readouterr()
    assert main(["evaluate", str(svn), "--reference", str(as_map), "--out", str(tmp_path / "e1")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "result.json" in err[0] and "Traceback" not in err[0]
    rep = evaluate_results([mht], out=tmp_path / "e2", ambiguity=False, figures=False, reference=svn)
    assert "rates on frames the reference SVN calls" in rep.text and "reference MHT" not in rep.text
    rep = evaluate_results([mht, svn], out=tmp_path / "e3", ambiguity=False, figures=False)
    assert "rates on frames the reference MHT calls" in rep.text
