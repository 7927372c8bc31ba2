"""SVN vs single-mode MAP vs MHT on every run of a directory: mean errors, truth kept, modes verdict (issue 9).

Usage: ``.venv/bin/python scripts/compare_svn_map_mht.py RUNS_DIR [--methods svn map mht] [--runs GLOB ...]
[--robust SPEC] [--noise FILE] [--disable SWITCH ...]``
(e.g. the runs of ``pinpoint-fg simulate`` for each scenario with another ``--seed`` than the benchmark's;
``--runs 'snapshots-0[1-8]'`` keeps the runs whose names match a glob; ``--methods svn`` scores one method (``pf``
and ``svgd`` are accepted too), e.g. to compare two trees by running this from each with ``PYTHONPATH`` set to it;
``--robust`` sets the robust losses as ``track --robust`` does, e.g. ``conic=cauchy:3,grasp-perpendicular=huber:1.345``,
the default before the twenty-third round, against today's; ``--noise`` tracks with a noise file, as ``track --noise``
does, the ``--robust`` given then replacing the file's; ``--disable`` adds switches to each run's suggested ones).
Each run is tracked as ``track`` would with the recording's
``suggested_disable`` given as ``--disable`` (seed 0), one method after the other, in this process; "kept" = some
particle within 2 mm / 10 deg of the truth, "bimodal" = the modes verdict (second mode >= 0.1). Last, per scenario (a
run's name without its ``-SEED`` suffix, as ``pinpoint-fg simulate`` names runs) and method, the means of those columns
over the scenario's runs.
"""

from __future__ import annotations

import argparse
import fnmatch
from pathlib import Path

from factors.robust import RobustLoss
from pinpoint_fg.experiments.compare import score_run
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.noise import NoiseConfig, parse_robust_spec
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

METHODS = ("svn", "map", "mht")


def main(root: Path, methods: tuple[str, ...] = METHODS, patterns: tuple[str, ...] = ("*",),
         robust: dict[str, RobustLoss] | None = None, noise_file: Path | None = None,
         disable: tuple[str, ...] = ()) -> None:
    noise = NoiseConfig.load(noise_file) if noise_file is not None else None
    if robust is not None:
        noise = (noise or NoiseConfig()).with_robust(robust)
    header = f"{'method':<6} {'trans mm':>8} {'rot deg':>8} {'kept':>6} {'bimodal':>8}"
    print(f"{'run':<16} {header}")
    scores: dict[str, dict[str, list]] = {}
    for run in sorted(p for p in root.iterdir() if (p / "recording.json").exists()
                      and any(fnmatch.fnmatch(p.name, g) for g in patterns)):
        rec = read_recording(run)
        scenario = run.name.rsplit("-", 1)[0] if run.name.rsplit("-", 1)[-1].isdigit() else run.name
        for method in methods:
            switches = tuple(dict.fromkeys((*suggested_disable(rec), *disable)))
            config = tracker_config(rec, method, noise=noise, disable=switches, seed=0)
            sc = score_run(rec, make_tracker(method, config))
            scores.setdefault(scenario, {}).setdefault(method, []).append(sc)
            print(f"{run.name:<16} {method:<6} {sc.trans_mm:8.2f} {sc.rot_deg:8.1f} {sc.kept:6.1%} {sc.bimodal:8.1%}",
                  flush=True)
    print(f"\nmeans per scenario\n{'scenario':<12} {'runs':>4} {header}")
    for scenario, by_method in scores.items():
        for method in methods:
            runs = by_method.get(method, [])
            mean = [sum(getattr(r, k) for r in runs) / len(runs) for k in ("trans_mm", "rot_deg", "kept", "bimodal")]
            print(f"{scenario:<12} {len(runs):4d} {method:<6} {mean[0]:8.2f} {mean[1]:8.1f} {mean[2]:6.1%} "
                  f"{mean[3]:8.1%}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=(*METHODS, "pf", "svgd"))
    ap.add_argument("--runs", nargs="+", default=["*"], help="globs of run names to keep")
    ap.add_argument("--robust", type=parse_robust_spec, default=None, help="robust losses, as track --robust")
    ap.add_argument("--noise", type=Path, default=None, help="a noise file, as track --noise")
    ap.add_argument("--disable", nargs="+", default=[], help="switches added to each run's suggested ones")
    args = ap.parse_args()
    main(args.root, tuple(args.methods), tuple(args.runs), args.robust, args.noise, tuple(args.disable))
