"""``pinpoint-fg``: the command line. The only module that parses arguments.

Each subcommand is a thin shell over a library function; bad input is reported as one
line naming the file/row/column (exit code 2), never as a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pinpoint_fg.errors import InputError

METHODS = ("svn", "svgd", "pf", "map")
SWITCHES = ("dense", "sparse", "tip", "tail", "grasp-position", "grasp-perpendicular", "motion")
SCENARIOS = ("slow", "normal", "rotation", "suturing", "calibration", "symmetric", "drive", "kinfault", "snapshots")


def _disable_list(text: str) -> tuple[str, ...]:
    items = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in items if s not in SWITCHES]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown switch(es) {bad}; choose from {', '.join(SWITCHES)}")
    return items


def _cmd_validate(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.recording import summarize_recording, validate_run

    recording, errors = validate_run(args.run)
    if errors:
        for e in errors:
            print(f"error: {e}", file=sys.stderr)
        print(f"{args.run}: INVALID ({len(errors)} error(s))", file=sys.stderr)
        return 1
    print(summarize_recording(recording))
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from pinpoint_fg.sim.scenarios import simulate

    out = simulate(args.scenario, n_frames=args.frames, seed=args.seed, out=args.out, images=args.images)
    print(f"wrote {out}")
    return 0


def _cmd_groundtruth(args: argparse.Namespace) -> int:
    from pinpoint_fg.groundtruth import groundtruth_run

    stats = groundtruth_run(args.run, args.board_to_needle)
    print(stats.describe() if hasattr(stats, "describe") else stats)
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    from pinpoint_fg.track import track_recording

    out = track_recording(
        args.run,
        method=args.method,
        out=args.out,
        particles=args.particles,
        window=args.window,
        noise_file=args.noise,
        disable=args.disable,
        seed=args.seed,
        progress=None,
    )
    print(f"wrote {out}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from pinpoint_fg.eval.calibrate import calibrate_runs, format_table

    noise = calibrate_runs(args.runs)
    noise.save(args.out)
    print(format_table(noise))
    print(f"wrote {args.out}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pinpoint_fg.eval.report import evaluate

    summary = evaluate(args.results, recording=args.recording, out=args.out)
    print(summary)
    return 0


def _cmd_ablate(args: argparse.Namespace) -> int:
    from pinpoint_fg.eval.ablate import ablate

    table = ablate(args.runs, out=args.out, jobs=args.jobs, frames=args.frames)
    print(table)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from pinpoint_fg.demo import run_demo

    run_demo(out=args.out, frames=args.frames, jobs=args.jobs)
    return 0


def _cmd_benchmark(args: argparse.Namespace) -> int:
    from pinpoint_fg.demo import run_benchmark

    run_benchmark(out=args.out, frames=args.frames, seed=args.seed, jobs=args.jobs)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    p = argparse.ArgumentParser(prog="pinpoint-fg", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("validate", help="check a recorded run against the v1 format")
    s.add_argument("run", type=Path)
    s.set_defaults(func=_cmd_validate)

    s = sub.add_parser("simulate", help="write a simulated recorded run")
    s.add_argument("--scenario", choices=SCENARIOS, default="normal")
    s.add_argument("--frames", type=int, default=300)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--images", action="store_true", help="also render camera images with the checkerboard")
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser("groundtruth", help="gt_* columns from the checkerboard in the run's images")
    s.add_argument("run", type=Path)
    s.add_argument("--board-to-needle", type=Path, required=True, help="JSON with the fixed board_T_needle")
    s.set_defaults(func=_cmd_groundtruth)

    s = sub.add_parser("track", help="track the needle through a recorded run")
    s.add_argument("run", type=Path)
    s.add_argument("--method", choices=METHODS, default="svn")
    s.add_argument("--particles", type=int, default=None, help="default: 50 (svn, svgd), 3000 (pf)")
    s.add_argument("--window", type=int, default=1, help="window length L (1 = filter)")
    s.add_argument("--noise", type=Path, default=None, help="noise file from `calibrate`")
    s.add_argument("--disable", type=_disable_list, default=(), help="comma list: " + ",".join(SWITCHES))
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", type=Path, required=True)
    s.set_defaults(func=_cmd_track)

    s = sub.add_parser("calibrate", help="noise statistics of every residual at ground truth")
    s.add_argument("runs", type=Path, nargs="+")
    s.add_argument("--out", type=Path, required=True)
    s.set_defaults(func=_cmd_calibrate)

    s = sub.add_parser("evaluate", help="metrics, tables and figures of tracking results")
    s.add_argument("results", type=Path, nargs="+")
    s.add_argument("--recording", type=Path, default=None)
    s.add_argument("--out", type=Path, required=True)
    s.set_defaults(func=_cmd_evaluate)

    s = sub.add_parser("ablate", help="the ablation matrix of the paper's Table III")
    s.add_argument("runs", type=Path, nargs="+")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--jobs", type=int, default=2)
    s.add_argument("--frames", type=int, default=None, help="only the first N frames of each run")
    s.set_defaults(func=_cmd_ablate)

    s = sub.add_parser("demo", help="simulate, track with svn/pf/map, evaluate, print the comparison")
    s.add_argument("--out", type=Path, default=Path("demo-output"))
    s.add_argument("--frames", type=int, default=240)
    s.add_argument("--jobs", type=int, default=2)
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser("benchmark", help="accuracy and latency of every method on every scenario")
    s.add_argument("--out", type=Path, default=Path("benchmark-output"))
    s.add_argument("--frames", type=int, default=300)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--jobs", type=int, default=1, help="parallel processes (1 keeps latencies clean)")
    s.set_defaults(func=_cmd_benchmark)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``pinpoint-fg`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"error: {exc.filename or exc}: not found", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished frames are on disk", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
