"""The benchmark's unseen-seed table: means over seeds, each seed's rotation error, SVN's ratios; bad seeds."""

from __future__ import annotations

from pathlib import Path

import pytest

from pinpoint_fg.cli import main
from pinpoint_fg.experiments.benchmark import BENCH_SCENARIOS, UNSEEN_METHODS, unseen_table


def _row(scenario: str, method: str, seed: int, trans_mm: float, rot_deg: float, kept: float, bim: float) -> dict:
    return {"scenario": scenario, "method": method, "seed": seed, "trans_mean_mm": trans_mm, "rot_mean_deg": rot_deg,
            "truth_kept_particles_share": kept, "bimodal_modes_share": bim}


def test_unseen_table_averages_over_seeds_and_lists_each_seed_in_order() -> None:
    rows = []
    for seed, svn_rot in ((4, 30.0), (2, 10.0)):  # given out of order: listed by seed
        rows += [_row("snapshots", "svn", seed, 1.0 + seed, svn_rot, 0.9, 0.5),
                 _row("snapshots", "pf", seed, 4.0, 40.0, 0.5, 0.0),
                 _row("snapshots", "map", seed, 6.0, 80.0, 0.1, 0.0),
                 _row("snapshots", "mht", seed, 1.5, 25.0, 0.7, 0.1)]
    text = unseen_table(rows, (2, 4))
    per_method, ratios = text.split("\n\n")
    svn = next(line for line in per_method.splitlines() if line.startswith("snapshots    svn"))
    assert svn.split()[2:6] == ["4.00", "20.0", "90%", "50%"]  # means over the two seeds
    assert svn.endswith("10.0 / 30.0")  # seed 2, then seed 4
    assert "Unseen seeds 2, 4" in per_method
    snap = next(line for line in ratios.splitlines() if line.startswith("snapshots"))
    assert [float(x) for x in snap.split()[1:]] == pytest.approx([4.0 / 6.0, 20.0 / 80.0, 4.0 / 1.5, 20.0 / 25.0],
                                                                 abs=0.005)
    # scenarios without rows are left out of both parts
    assert not any(line.startswith("normal") for line in text.splitlines())
    assert set(UNSEEN_METHODS) == {"svn", "pf", "map", "mht"} and "snapshots" in BENCH_SCENARIOS


def test_unseen_seeds_that_repeat_or_include_the_benchmark_seed_are_refused_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for seeds in (["1"], ["2", "2"]):
        out = tmp_path / f"bench-{'-'.join(seeds)}"
        assert main(["benchmark", "--frames", "4", "--seed", "1", "--unseen-seeds", *seeds, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "--unseen-seeds" in err and len(err.strip().splitlines()) == 1
        assert not out.exists()
