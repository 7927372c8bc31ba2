"""Evaluation reports: summary.csv, Tables II/III, figures, on synthetic results of a simulated run."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.cli import main
from pinpoint_fg.errors import InputError
from pinpoint_fg.estimate import Estimate
from pinpoint_fg.eval.ambiguity import label_frames
from pinpoint_fg.eval.metrics import nll_score
from pinpoint_fg.eval.report import (
    ABLATION_VARIANTS,
    comparison_text,
    evaluate,
    evaluate_results,
    table_ii,
    variant_name,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.io.result.writer import ResultWriter
from pinpoint_fg.likelihood import MeasurementModel
from pinpoint_fg.sim.scenarios import simulate

F = 12
OFFSET_M = np.array([1e-3, 0.0, 0.0])
REQUIRED = (
    "method", "recording", "frames", "trans_mean_mm", "trans_std_mm", "rot_mean_deg", "rot_std_deg",
    "trans_q95_mm", "rot_q95_deg", "nlls_trans", "nlls_rot", "is_trans", "is_rot", "bimodal_share",
    "truth_in_dominant_share", "floor_trans_mm", "trans_floor_multiple", "bimodal_ambiguous_rate",
    "bimodal_clear_rate", "latency_median_ms", "latency_p95_ms",
)


def _particles(
    kind: str, T_map: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray | None]:
    """Synthetic particle sets around the MAP: two well separated clusters, one pose, or a weighted blob."""
    if kind == "single":
        return T_map[None], None
    if kind == "bimodal":
        xi = rng.normal(size=(50, 6)) * np.r_[[np.radians(1.0)] * 3, [0.2e-3] * 3]
        xi[35:, 0] += 0.7  # 15 particles in a second mode, 40 deg away
        xi[0] = 0.0  # the MAP itself
        return T_map[None] @ se3_exp(xi), None
    xi = rng.normal(size=(200, 6)) * np.r_[[np.radians(2.0)] * 3, [0.3e-3] * 3]
    xi[0] = 0.0
    w = rng.uniform(0.5, 1.5, 200)
    return T_map[None] @ se3_exp(xi), w / w.sum()


def _write_result(out: Path, rec: Recording, method: str, kind: str, disabled: tuple[str, ...] = (),
                  recording_path: str | None = "auto", name: str | None = None, frames: int = F) -> Path:
    rng = np.random.default_rng(len(method) + 7 * len(disabled))
    weighted = kind == "weighted"
    path = str(rec.root.resolve()) if recording_path == "auto" else recording_path
    settings = {"method": method, "particles": 1, "window": 1, "seed": 0, "disabled": list(disabled),
                "noise_file": None}
    with ResultWriter(out, method, settings, name or rec.info.name, path, weighted=weighted) as w:
        for r in rec.frames[:frames]:
            T = r.cam_T_needle_gt.copy()
            T[:3, 3] += OFFSET_M
            P, wt = _particles(kind, T, rng)
            w.write(Estimate(
                frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=2e-3,
                q95_rot_rad=float(np.radians(5.0)), bimodal=False, iterations=3, latency_ms=10.0 + r.frame,
                particles=P, log_posterior=np.zeros(P.shape[0]), weights=wt,
            ))
    return out


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Recording, dict[str, Path], Path]:
    base = tmp_path_factory.mktemp("report")
    rec = read_recording(simulate("rotation", F, seed=3, out=base / "run"))
    results = {
        "svn": _write_result(base / "svn", rec, "svn", "bimodal"),
        "pf": _write_result(base / "pf", rec, "pf", "weighted"),
        "map": _write_result(base / "map", rec, "map", "single"),
    }
    return rec, results, base


@pytest.fixture(scope="module")
def report(setup: tuple[Recording, dict[str, Path], Path]):  # noqa: ANN201
    rec, results, base = setup
    return evaluate_results([results[m] for m in ("svn", "pf", "map")], out=base / "eval"), base / "eval"


def _rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames or []), list(reader)


def test_summary_csv_has_the_required_columns_and_values(report, setup) -> None:  # noqa: ANN001
    _, out = report
    rec = setup[0]
    header, rows = _rows(out / "summary.csv")
    assert set(REQUIRED) <= set(header)
    by = {r["method"]: r for r in rows}
    assert list(by) == ["svn", "pf", "map"]
    for r in rows:
        assert int(r["frames"]) == F and r["recording"] == rec.info.name
        assert float(r["trans_mean_mm"]) == pytest.approx(1.0, abs=1e-9)  # the 1 mm offset in x
        assert float(r["trans_x_mean_mm"]) == pytest.approx(1.0, abs=1e-9)
        assert float(r["trans_z_mean_mm"]) == pytest.approx(0.0, abs=1e-9)
        assert float(r["rot_mean_deg"]) == pytest.approx(0.0, abs=1e-6)
        assert float(r["trans_q95_mm"]) == pytest.approx(2.0)
        assert float(r["nlls_trans"]) == pytest.approx(float(nll_score(1.0, 2.0 / 1.959963984540054)))
        assert float(r["is_trans"]) == pytest.approx(2.0)  # inside [0, q95]: the width only
        assert float(r["latency_median_ms"]) == pytest.approx(10.0 + (F - 1) / 2)
        floor = float(r["floor_trans_mm"])
        assert np.isfinite(floor) and float(r["trans_floor_multiple"]) == pytest.approx(1.0 / floor, rel=1e-9)
        assert float(r["trans_mm_none"]) == pytest.approx(1.0)  # rotation scenario: never occluded
        assert r["trans_mm_heavy"] == "nan"
    assert float(by["svn"]["bimodal_share"]) == 1.0
    assert float(by["svn"]["truth_in_dominant_share"]) == 1.0
    assert float(by["pf"]["bimodal_share"]) == 0.0
    assert float(by["map"]["bimodal_share"]) == 0.0
    assert by["map"]["truth_in_dominant_share"] == "nan"
    labels = label_frames(rec, MeasurementModel(rec.info.camera, rec.info.needle))
    n_amb, n_clear = int(np.sum(labels == "ambiguous")), int(np.sum(labels == "clear"))
    assert int(by["svn"]["ambiguous_frames"]) == n_amb and int(by["svn"]["clear_frames"]) == n_clear
    assert by["svn"]["bimodal_clear_rate"] == ("1.0" if n_clear else "nan")
    assert by["map"]["bimodal_ambiguous_rate"] == ("0.0" if n_amb else "nan")


def test_tables_are_shaped_like_the_paper(report) -> None:  # noqa: ANN001
    rep, out = report
    text = (out / "tables.md").read_text()
    assert "## Tracking comparison (Table II)" in text and "Table III" not in text
    lines = rep.table_ii.splitlines()
    header = "| Method | Recording | Metric | X | Y | Z | Total | Unc (p95) | NLL-S | IS | × floor |"
    assert lines[0] == header
    assert len(lines) == 2 + 2 * 3
    assert [ln.split("|")[3].strip() for ln in lines[2:4]] == ["Trans (mm)", "Rot (deg)"]
    assert lines[2].split("|")[7].strip() == "1.00±0.00"
    assert rep.table_iii == ""
    methods = [ln.split()[1] for ln in rep.text.splitlines()[2:5]]
    assert methods == ["svn", "pf", "map"]


def test_figures_are_written(report) -> None:  # noqa: ANN001
    _, out = report
    names = {p.name for p in out.glob("*.png")}
    assert "errors.png" in names
    assert sum(n.startswith("error_time_") for n in names) == 3
    assert any(n.startswith("particle_cloud_") for n in names)
    for p in out.glob("*.png"):
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_ablation_results_give_table_iii_and_bars(setup, tmp_path: Path) -> None:  # noqa: ANN001
    rec, results, _ = setup
    paths = [
        _write_result(tmp_path / "svgd", rec, "svgd", "bimodal", frames=4),
        _write_result(tmp_path / "nodense", rec, "svn", "bimodal", ("dense",), frames=4),
        _write_result(tmp_path / "full", rec, "svn", "bimodal", frames=4),
    ]
    rep = evaluate_results(paths, out=tmp_path / "eval")
    lines = rep.table_iii.splitlines()
    assert lines[0] == f"### {rec.info.name}"
    titles = [ln.split("|")[1].strip() for ln in lines[4:]]
    assert titles == ["All (full model)", "No dense image", "SVGD (no Hessian)"]
    assert "## Ablations (Table III)" in (tmp_path / "eval" / "tables.md").read_text()
    assert (tmp_path / "eval" / f"ablation_{rec.info.name}.png").exists()
    assert [ev.variant for ev in rep.evaluations] == ["svgd", "no-dense", "full"]


def test_variant_names_cover_the_ablation_matrix() -> None:
    for name, method, disabled, _ in ABLATION_VARIANTS:
        assert variant_name(method, disabled) == name
    assert variant_name("svn", ("tail", "tip")) == "no-keypoints"
    assert variant_name("pf", ()) == "full"
    assert variant_name("svn", ("motion",)) == "disable-motion"


def test_cli_evaluate_prints_the_comparison(setup, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    _, results, _ = setup
    assert main(["evaluate", str(results["map"]), "--out", str(tmp_path / "e")]) == 0
    assert "map" in capsys.readouterr().out
    assert (tmp_path / "e" / "summary.csv").exists()
    assert evaluate([results["map"]], out=tmp_path / "e2").splitlines()[0].startswith("recording")


def test_the_accuracy_floor_is_printed_once_per_likelihood_not_per_method(setup, tmp_path: Path) -> None:  # noqa: ANN001
    rec, results, _ = setup
    svgd = _write_result(tmp_path / "svgd", rec, "svgd", "bimodal")
    text = evaluate_results([results["svn"], svgd], out=tmp_path / "e", figures=False).text
    floor = [ln for ln in text.splitlines() if ln.startswith("accuracy floor")]
    assert len(floor) == 1 and floor[0].count(" mm / ") == 1, floor  # svgd's model is svn's full one
    # another likelihood (the dense term off) has its own floor, named as SVN's variant of it, whatever the method
    off = _write_result(tmp_path / "svgd-nodense", rec, "svgd", "bimodal", disabled=("dense",))
    text = evaluate_results([results["svn"], svgd, off], out=tmp_path / "e2", figures=False).text
    floor = next(ln for ln in text.splitlines() if ln.startswith("accuracy floor"))
    assert floor.count(" mm / ") == 2 and f"{rec.info.name} {variant_name('svn', ('dense',))}: " in floor, floor


def test_recording_given_explicitly_or_missing(setup, tmp_path: Path) -> None:  # noqa: ANN001
    rec, _, _ = setup
    r = _write_result(tmp_path / "nopath", rec, "map", "single", recording_path=None, frames=3)
    with pytest.raises(InputError, match="recording_path"):
        evaluate_results([r], out=tmp_path / "e", figures=False)
    rep = evaluate_results([r], recording=rec.root, out=tmp_path / "e", figures=False, ambiguity=False)
    assert rep.evaluations[0].row["frames"] == 3
    assert np.isnan(rep.evaluations[0].row["bimodal_ambiguous_rate"])
    assert np.isfinite(rep.evaluations[0].row["floor_trans_mm"])


def test_mismatched_recording_and_unknown_frames_are_input_errors(setup, tmp_path: Path) -> None:  # noqa: ANN001
    rec, _, _ = setup
    r = _write_result(tmp_path / "other", rec, "map", "single", name="another-run", frames=2)
    with pytest.raises(InputError, match="another-run"):
        evaluate_results([r], out=tmp_path / "e", figures=False)
    r2 = _write_result(tmp_path / "late", rec, "map", "single", frames=2)
    info = json.loads((r2 / "result.json").read_text())
    est = (r2 / "estimates.csv").read_text().splitlines()
    est[2] = "999" + est[2][est[2].index(","):]  # frame 999 is not in the recording
    (r2 / "estimates.csv").write_text("\n".join(est) + "\n")
    assert info["complete"]
    with pytest.raises(InputError) as exc:
        evaluate_results([r2], out=tmp_path / "e", figures=False)
    assert "999" in str(exc.value) and "estimates.csv" in str(exc.value)


def test_smoothed_poses_are_scored_against_the_filtered_ones_of_the_same_frames(setup, tmp_path: Path) -> None:  # noqa: ANN001
    """A window L = 3 result: filtered poses 1 mm off the truth, smoothed ones 0.25 mm off, none for the last two
    frames. The smoothed columns score the smoothed poses and the filtered ones on the same F - 2 frames; a
    result without smoothing has 0 frames and NaN; a smoothed frame missing from estimates.csv is an InputError."""
    rec, results, _ = setup
    settings = {"method": "map", "particles": 1, "window": 3, "seed": 0, "disabled": [], "noise_file": None}
    out = tmp_path / "smoothed"
    with ResultWriter(out, "map", settings, rec.info.name, str(rec.root.resolve()), smoothed=True) as w:
        for r in rec.frames[:F]:
            T = r.cam_T_needle_gt.copy()
            T[:3, 3] += OFFSET_M
            w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=2e-3, q95_rot_rad=0.1,
                             bimodal=False, iterations=3, latency_ms=10.0, particles=T[None],
                             log_posterior=np.zeros(1)))
        for r in rec.frames[: F - 2]:
            T = r.cam_T_needle_gt.copy()
            T[:3, 3] += 0.25 * OFFSET_M
            w.write_smoothed(r.frame, r.t_s, T)
    rep = evaluate_results([out, results["map"]], out=tmp_path / "eval", figures=False)
    row = rep.evaluations[0].row
    assert row["smoothed_frames"] == F - 2
    assert row["smoothed_trans_mean_mm"] == pytest.approx(0.25, abs=1e-9)
    assert row["filtered_trans_mean_mm_same"] == pytest.approx(1.0, abs=1e-9)
    assert row["smoothed_rot_mean_deg"] == pytest.approx(0.0, abs=1e-6)
    plain = rep.evaluations[1].row
    assert plain["smoothed_frames"] == 0 and np.isnan(plain["smoothed_trans_mean_mm"])
    assert "fixed-lag smoothed poses" in rep.text and "0.25 mm" in rep.text
    assert "## Fixed-lag smoothing" in (tmp_path / "eval" / "tables.md").read_text()
    header, rows = _rows(tmp_path / "eval" / "summary.csv")
    assert "smoothed_trans_mean_mm" in header and float(rows[0]["smoothed_trans_mean_mm"]) == pytest.approx(0.25)

    # a smoothed row for a frame estimates.csv does not have
    with open(out / "smoothed.csv", "a", encoding="utf-8") as fh:
        last = open(out / "smoothed.csv", encoding="utf-8").read().splitlines()[-1].split(",")
        last[0] = "9999"
        fh.write(",".join(last) + "\n")
    with pytest.raises(InputError, match="smoothed frame 9999 has no row in estimates.csv") as err:
        evaluate_results([out], out=tmp_path / "eval2", figures=False)
    assert "smoothed.csv" in str(err.value)


def test_spreads_over_part_of_the_frames_are_marked(setup, tmp_path: Path) -> None:  # noqa: ANN001
    """A result with NaN (unknown) q95 on some frames: q95, NLL-S and IS are over the frames that report one,
    and the comparison and Table II say over which share."""
    rec = setup[0]
    out = tmp_path / "pf"
    settings = {"method": "pf", "particles": 1, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
    with ResultWriter(out, "pf", settings, rec.info.name, str(rec.root.resolve()), weighted=True) as w:
        for k, r in enumerate(rec.frames[:F]):
            T = r.cam_T_needle_gt.copy()
            T[:3, 3] += OFFSET_M
            q = 2e-3 if k < 3 else float("nan")  # 3 of 12 frames with a spread
            w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=q,
                             q95_rot_rad=q, bimodal=False, iterations=1, latency_ms=1.0,
                             particles=T[None], log_posterior=np.zeros(1), weights=np.ones(1)))
    rep = evaluate_results([out, setup[1]["map"]], out=tmp_path / "eval")
    row = rep.evaluations[0].row
    assert (row["uncertainty_frames_trans"], row["uncertainty_frames_rot"], row["frames"]) == (3, 3, F)
    assert np.isclose(row["trans_q95_mm"], 2.0)
    _, rows = _rows(tmp_path / "eval" / "summary.csv")
    assert [r["uncertainty_frames_rot"] for r in rows] == ["3", str(F)]
    text = comparison_text(rep.evaluations)
    pf_line = next(line for line in text.splitlines() if " pf " in f" {line} ")
    assert "@25%" in pf_line and "q95 @k%" in text
    map_line = next(line for line in text.splitlines() if " map " in f" {line} ")
    assert "@" not in map_line
    assert "2.00 @25%" in table_ii(rep.evaluations)


def _result_on(rec: Recording, poses_from: Recording, out: Path) -> Path:
    """A MAP result on ``rec`` whose poses are ``poses_from``'s ground truth plus the 1 mm offset."""
    settings = {"method": "map", "particles": 1, "window": 1, "seed": 0, "disabled": [], "noise_file": None}
    with ResultWriter(out, "map", settings, rec.info.name, str(rec.root.resolve())) as w:
        for r, src in zip(rec.frames[:F], poses_from.frames[:F], strict=True):
            T = src.cam_T_needle_gt.copy()
            T[:3, 3] += OFFSET_M
            w.write(Estimate(frame=r.frame, t_s=r.t_s, cam_T_needle=T, q95_trans_m=2e-3, q95_rot_rad=0.1,
                             bimodal=False, iterations=1, latency_ms=1.0, particles=T[None],
                             log_posterior=np.zeros(1)))
    return out


def _run_with_gt(src: Path, dest: Path, change: dict) -> Recording:
    import shutil

    from pinpoint_fg.io.recording import replace_ground_truth

    shutil.copytree(src, dest)
    replace_ground_truth(dest, change)
    return read_recording(dest)


def test_ground_truth_that_does_not_describe_its_frame_is_left_out_of_the_scores(
        setup, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    """Two gt depths of 9.9 m (a unit slip in two cells; without the gate the mean translation error was 1642
    instead of 1.0 mm): the scores equal those with the two cells cleared, summary.csv counts them, and one
    note names their rows."""
    rec = setup[0]
    far = {}
    for f in rec.frames[4:6]:
        T = f.cam_T_needle_gt.copy()
        T[2, 3] = 9.9
        far[f.frame] = T
    bad = _run_with_gt(rec.root, tmp_path / "far", far)
    cleared = _run_with_gt(rec.root, tmp_path / "cleared", dict.fromkeys(far))
    rep_bad = evaluate_results([_result_on(bad, rec, tmp_path / "r_bad")], out=tmp_path / "e_bad", figures=False)
    rep_ok = evaluate_results([_result_on(cleared, rec, tmp_path / "r_ok")], out=tmp_path / "e_ok", figures=False)
    row_bad, row_ok = rep_bad.evaluations[0].row, rep_ok.evaluations[0].row
    for k in ("trans_mean_mm", "rot_mean_deg", "coverage_trans", "floor_trans_mm", "nlls_trans"):
        assert row_bad[k] == row_ok[k], k
    assert row_bad["trans_mean_mm"] == pytest.approx(1.0, abs=1e-9)
    assert (row_bad["gt_left_out_frames"], row_ok["gt_left_out_frames"]) == (2, 0)
    def gt_notes(text: str) -> list[str]:  # these hand-written results carry no modes: that note is not counted
        return [ln for ln in text.splitlines() if ln.startswith("note:") and "no modes.csv" not in ln]

    notes = gt_notes(rep_bad.text)
    rows = [bad.row_of(f) for f in bad.frames[4:6]]
    assert len(notes) == 1 and "2 ground-truth frame(s) left out of the scores" in notes[0]
    assert all(f"{r} (x" in notes[0] for r in rows)
    assert not gt_notes(rep_ok.text)
    _, csv_rows = _rows(tmp_path / "e_bad" / "summary.csv")
    assert csv_rows[0]["gt_left_out_frames"] == "2"
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "r_bad"), "--out", str(tmp_path / "e_cli")]) == 0
    assert len(gt_notes(capsys.readouterr().out)) == 1


def test_a_run_without_ground_truth_is_said_to_be_so(setup, tmp_path: Path) -> None:  # noqa: ANN001
    """Its row reads 0 frames and dashes; one line says why (a run without truth is valid: tracked, not scored)."""
    rec = setup[0]
    bare = _run_with_gt(rec.root, tmp_path / "bare", {f.frame: None for f in rec.frames})
    rep = evaluate_results([_result_on(bare, rec, tmp_path / "r")], out=tmp_path / "e", figures=False)
    assert rep.evaluations[0].row["frames"] == 0
    lines = [line for line in rep.text.splitlines() if line.startswith("no ground truth:")]
    assert len(lines) == 1 and f"none of its {F} frames has a ground-truth pose" in lines[0]
    scored = evaluate_results([_result_on(rec, rec, tmp_path / "r2")], out=tmp_path / "e2", figures=False)
    assert "no ground truth" not in scored.text


def test_ground_truth_in_the_wrong_unit_throughout_is_refused_before_the_output_exists(
        setup, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    """Every gt translation 100x too large: the first row is named, exit 2, and no --out directory is left."""
    rec = setup[0]
    cm = {}
    for f in rec.frames:
        T = f.cam_T_needle_gt.copy()
        T[:3, 3] *= 100.0
        cm[f.frame] = T
    bad = _run_with_gt(rec.root, tmp_path / "cm", cm)
    result = _result_on(bad, rec, tmp_path / "r")
    with pytest.raises(InputError) as exc:
        evaluate_results([result], out=tmp_path / "e", figures=False)
    assert exc.value.column == "gt_z_m" and exc.value.row == bad.row_of(bad.frames[0])
    assert not (tmp_path / "e").exists()
    capsys.readouterr()
    assert main(["evaluate", str(result), "--out", str(tmp_path / "e2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gt_z_m" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "e2").exists()


def _renamed(src: Path, dest: Path, name: str) -> Recording:
    import shutil

    shutil.copytree(src, dest)
    info = json.loads((dest / "recording.json").read_text())
    info["name"] = name
    (dest / "recording.json").write_text(json.dumps(info))
    return read_recording(dest)


def test_recordings_whose_names_give_one_file_name_keep_their_own_figures(setup, tmp_path: Path) -> None:  # noqa: ANN001
    """``x y`` and ``x_y`` (one slug) and two all-non-ASCII names (both ``result``) each get their own figures; a
    240-character name gives a bounded file name (it failed after half the files were written)."""
    rec = setup[0]
    names = ["x y", "x_y", "naïve: ü", "ü ö", "n" * 240]
    recs = [_renamed(rec.root, tmp_path / f"run{i}", n) for i, n in enumerate(names)]
    results = [_result_on(r, rec, tmp_path / f"r{i}") for i, r in enumerate(recs)]
    rep = evaluate_results(results, out=tmp_path / "e", ambiguity=False)
    error_time = sorted(p.name for p in (tmp_path / "e").iterdir() if p.name.startswith("error_time_"))
    assert len(error_time) == len(names) == len(set(error_time))
    assert all(len(n) <= 120 for n in error_time)
    assert len([p for p in rep.files if p.name.startswith("error_time_")]) == len(names)


def test_file_stems_are_distinct_bounded_and_stable() -> None:
    from pinpoint_fg.eval.report import SLUG_MAX, _slug, _Stems

    stems = _Stems()
    assert [stems(t) for t in ("x y", "x_y", "x y", "ü", "ö")] == ["x_y", "x_y-2", "x_y", "result", "result-2"]
    a, b = "a" * 200 + "1", "a" * 200 + "2"
    assert len(_slug(a)) == SLUG_MAX and _slug(a) != _slug(b) and _slug(a) == _slug(a)
    assert stems("p_q", key=("p", "q")) != stems("p_q", key=("p_q", ""))


def test_ground_truth_placed_beside_its_needle_is_left_out_of_the_scores(setup, tmp_path: Path) -> None:  # noqa: ANN001
    """0.5 m typed for 0.5 mm in one gt_x_m cell (the needle ~10,000 px beside where its image shows it: the mean
    translation error read 41.9 mm instead of 1.0) and one depth of 1e-9 m (a seen point behind the camera): both
    frames are scored as without truth, and the note names their rows and why."""
    rec = setup[0]
    bad = {}
    T = rec.frames[4].cam_T_needle_gt.copy()
    T[0, 3] = 0.5
    bad[rec.frames[4].frame] = T
    T = rec.frames[7].cam_T_needle_gt.copy()
    T[2, 3] = 1e-9  # the circle through the camera centre: a point the image shows lies behind it
    bad[rec.frames[7].frame] = T
    run = _run_with_gt(rec.root, tmp_path / "beside", bad)
    cleared = _run_with_gt(rec.root, tmp_path / "cleared", dict.fromkeys(bad))
    rep_bad = evaluate_results([_result_on(run, rec, tmp_path / "r_bad")], out=tmp_path / "e_bad", figures=False)
    rep_ok = evaluate_results([_result_on(cleared, rec, tmp_path / "r_ok")], out=tmp_path / "e_ok", figures=False)
    for k in ("trans_mean_mm", "rot_mean_deg", "coverage_trans", "nlls_trans"):
        assert rep_bad.evaluations[0].row[k] == rep_ok.evaluations[0].row[k], k
    assert rep_bad.evaluations[0].row["trans_mean_mm"] == pytest.approx(1.0, abs=1e-9)
    assert rep_bad.evaluations[0].row["gt_left_out_frames"] == 2
    note = next(line for line in rep_bad.text.splitlines() if line.startswith("note:"))
    assert f"{run.row_of(run.frames[4])} (" in note and "sizes away" in note
    assert f"{run.row_of(run.frames[7])} (" in note and "behind the camera" in note
