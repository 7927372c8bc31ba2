"""Held-out q95 coverage for the benchmark: spread factors fitted on one seed, scored on the others (issue 9).

Every tracker's raw q95 is too tight on the simulator's runs (README, "Calibrated q95"): its kinematic errors are a
slowly varying bias and its mask noise is correlated along the arc, which a per-frame independent noise model
cannot know. ``calibrate-spread`` fixes the bound's size after the fact. The benchmark already tracks every
scenario on the unseen seeds, so it can measure that fix without tracking anything more:

* **fit** (:func:`pinpoint_fg.eval.spread_calibration.fit_spread_scale`, its 30 deg mode gate) on the
  :data:`CLEAR_SCENARIOS` of the *first* unseen seed, per method;
* **score** the raw and the scaled coverage (share of frames whose MAP error is within q95, every frame with truth
  counted, no gate) of the same scenarios on the benchmark's own seed and the other unseen seeds — runs the fit
  has never seen.

Only the clear scenarios: on rotation (the needle turns in the grasp), kinfault (faults), symmetric and snapshots
(ambiguous) the MAP sits in another mode on some frames, where no factor of a bound can cover the error (the
README's limits); issue 9's 90-98 % band is asked of the clear scenarios.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.spread_scale import SpreadScale

#: The scenarios whose coverage is fitted and scored (module docstring).
CLEAR_SCENARIOS = ("slow", "normal", "suturing", "calibration", "drive")
#: The methods whose bounds are calibrated: PinPoint and the two MAP baselines (PF reports q95 = 0 on a
#: collapsed particle set, which no factor can scale: ``calibrate-spread`` lists it as unfitted).
COVERAGE_METHODS = ("svn", "map", "mht")


@dataclass(frozen=True)
class CoverageRow:
    """One held-out result's coverage, raw and with the fitted factors."""

    scenario: str
    """Scenario name."""
    seed: int
    """The run's seed."""
    method: str
    """Tracker."""
    raw_trans: float
    """Share of frames whose translation error is within the raw q95 (NaN: no frame with truth)."""
    raw_rot: float
    """The same for rotation."""
    scaled_trans: float
    """With ``kappa_trans`` times q95 (NaN: the method has no factor)."""
    scaled_rot: float
    """With ``kappa_rot`` times q95."""


def held_out_coverage(train: list[Path], held_out: dict[tuple[str, int, str], Path]
                      ) -> tuple[SpreadScale, list[CoverageRow]]:
    """Fit the factors on ``train`` (result directories) and score every ``held_out`` result.

    ``held_out``: ``(scenario, seed, method) -> result directory``. Returns the fitted
    :class:`~pinpoint_fg.io.spread_scale.SpreadScale` and one row per held-out result (scaled columns NaN where the
    fit has no factor for the method). :class:`InputError` when no method could be fitted.
    """
    from pinpoint_fg.eval.spread_calibration import coverage, fit_spread_scale, frame_errors
    from pinpoint_fg.io.recording import Recording
    from pinpoint_fg.io.result.reader import read_result, recording_of

    scale = fit_spread_scale(train)
    cache: dict[Path, Recording] = {}
    rows = []
    for (scenario, seed, method), path in held_out.items():
        res = read_result(path)
        e = frame_errors(res, recording_of(res, cache))
        k = scale.methods.get(method)
        kt, kr = (k.kappa_trans, k.kappa_rot) if k is not None else (float("nan"), float("nan"))
        rows.append(CoverageRow(scenario, seed, method, coverage(e.err_trans_m, e.q95_trans_m),
                                coverage(e.err_rot_rad, e.q95_rot_rad), coverage(e.err_trans_m, kt * e.q95_trans_m),
                                coverage(e.err_rot_rad, kr * e.q95_rot_rad)))
    return scale, rows


def _pct(x: float) -> str:
    return "  -" if not np.isfinite(x) else f"{100 * x:3.0f}"


def coverage_table(scale: SpreadScale, rows: list[CoverageRow], fit_seed: int) -> str:
    """``rows`` as text: per scenario and seed, each method's coverage raw -> scaled (t/r, %), then the factors."""
    methods = [m for m in COVERAGE_METHODS if any(r.method == m for r in rows)]
    lines = [f"q95 coverage on runs the spread fit has not seen (factors fitted on seed {fit_seed}'s "
             f"{', '.join(CLEAR_SCENARIOS)}; raw -> scaled, translation/rotation, %)",
             "run            " + "".join(f"{m:<22}" for m in methods)]
    by = {(r.scenario, r.seed, r.method): r for r in rows}
    for sc, seed in dict.fromkeys((r.scenario, r.seed) for r in rows):
        cells = []
        for m in methods:
            r = by.get((sc, seed, m))
            cell = "-" if r is None else \
                f"{_pct(r.raw_trans)}/{_pct(r.raw_rot)} -> {_pct(r.scaled_trans)}/{_pct(r.scaled_rot)}"
            cells.append(cell.ljust(22))
        lines.append(f"{sc}-{seed:02d}".ljust(15) + "".join(cells))
    for m in methods:
        got = [r for r in rows if r.method == m and np.isfinite(r.scaled_trans) and np.isfinite(r.scaled_rot)]
        if not got:
            continue
        parts = [x for r in got for x in (r.scaled_trans, r.scaled_rot)]
        band = sum(0.90 <= r.scaled_trans <= 0.98 and 0.90 <= r.scaled_rot <= 0.98 for r in got)
        below = sum(min(r.scaled_trans, r.scaled_rot) < 0.90 for r in got)
        lines.append(f"{m} scaled: {100 * min(parts):.0f}-{100 * max(parts):.0f} %; inside 90-98 % on both parts "
                     f"{band} of {len(got)} runs, below 90 % on a part {below}")
    lines.append("factors (kappa trans/rot, training frames): " + "; ".join(
        f"{m} {s.kappa_trans:.2f}/{s.kappa_rot:.2f} ({s.frames})" for m, s in sorted(scale.methods.items()))
        + "".join(f"; {m} not fitted ({why})" for m, why in sorted(scale.unfitted.items())))
    return "\n".join(lines)


def benchmark_coverage(out: Path, seed: int, unseen_seeds: tuple[int, ...]) -> tuple[str, list[CoverageRow]]:
    """The benchmark's held-out coverage: fit on ``unseen_seeds[0]``'s results under ``out/seed-K``, score the
    benchmark's own seed (``out/results``) and the other unseen seeds. Returns the text (a one-line reason when
    nothing could be fitted, e.g. too few frames) and the rows."""
    fit_seed = unseen_seeds[0]
    train = [out / f"seed-{fit_seed}" / "results" / sc / m for sc in CLEAR_SCENARIOS for m in COVERAGE_METHODS]
    held_out = {(sc, seed, m): out / "results" / sc / m for sc in CLEAR_SCENARIOS for m in COVERAGE_METHODS}
    for k in unseen_seeds[1:]:
        held_out.update({(sc, k, m): out / f"seed-{k}" / "results" / sc / m
                         for sc in CLEAR_SCENARIOS for m in COVERAGE_METHODS})
    train = [p for p in train if p.is_dir()]  # a scenario or method not tracked is not there
    held_out = {k: p for k, p in held_out.items() if p.is_dir()}
    try:
        scale, rows = held_out_coverage(train, held_out)
    except InputError as exc:
        return f"q95 coverage: no spread factor could be fitted on seed {fit_seed} ({exc})", []
    return coverage_table(scale, rows, fit_seed), rows


def write_coverage_csv(rows: list[CoverageRow], path: Path) -> None:
    """``rows`` as CSV (one line per held-out result; coverage as shares in [0, 1], empty when undefined)."""
    import csv
    from dataclasses import asdict

    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(CoverageRow.__dataclass_fields__))
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(r).items()})
