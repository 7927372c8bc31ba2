"""``pinpoint-fg``: the command line. The only module that parses arguments.

Each subcommand is a thin shell over a library function; bad input is reported as one
line naming the file/row/column (exit code 2), never as a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import NoReturn

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import INT64_MAX

METHODS = ("svn", "svgd", "pf", "map", "mht")
SWITCHES = ("dense", "sparse", "tip", "tail", "grasp-position", "grasp-perpendicular", "motion")
SCENARIOS = ("slow", "normal", "rotation", "suturing", "calibration", "symmetric", "drive", "kinfault", "snapshots")
#: ``simulate --geometry`` choices (:data:`pinpoint_fg.sim.config.GEOMETRIES`; named here so ``--help`` imports no
#: simulator).
GEOMETRIES = ("paper", "held-out")
OVERWRITE_HELP = "write into a non-empty --out (replacing what this command writes there)"


def _disable_list(text: str) -> tuple[str, ...]:
    items = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in items if s not in SWITCHES]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown switch(es) {bad}; choose from {', '.join(SWITCHES)}")
    off = set(items)
    if {"dense", "grasp-position", "grasp-perpendicular"} <= off and ("sparse" in off or {"tip", "tail"} <= off):
        # no term left that sees the needle: the trackers wrote their initial guess with a q95 of ~1e-16 m
        raise argparse.ArgumentTypeError("switches off every measurement (dense, tip, tail, grasp-position, "
                                         "grasp-perpendicular): nothing is left to track the needle with")
    return items


def _robust_spec(text: str) -> dict:
    from pinpoint_fg.noise import parse_robust_spec

    if not text.strip():  # was read as 'none': an unset shell variable switched the default robust losses off, exit 0
        raise argparse.ArgumentTypeError("an empty spec (an unset shell variable?); write 'none' to switch every "
                                         "robust loss off")
    try:
        return parse_robust_spec(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _path(text: str) -> Path:
    """An argparse type: a non-empty path. ``Path("")`` is the current directory, so an unset shell variable
    (``pinpoint-fg validate "$RUN"``) validated, tracked or overwrote whatever directory the user stood in."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?)")
    return Path(text)


#: Largest accepted seed: the seed is recorded in the output's JSON, whose readers accept int64 integers only.
MAX_SEED = INT64_MAX


def _int_at_least(low: int, high: int | None = None):
    """An argparse type: a decimal integer in ``[low, high]`` (a clear usage error, exit 2, otherwise).

    Checked at parse time so a bad count or seed fails before any work (a negative seed used to
    surface as NumPy's traceback, a seed beyond int64 as a result its own reader refuses).
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low or (high is not None and value > high):
            bound = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {text!r}")
        return value

    parse.__name__ = "integer"  # argparse names the type in its own messages
    return parse


#: Most frames (or window length) a count accepts: more than any run holds (the format's time stamps end at 1e10 s,
#: 3e11 frames at 30 Hz). Beyond int64 was a traceback (``simulate --frames 1e23``: NumPy's "Maximum allowed size
#: exceeded"; ``track --window 1e23``: track_recording's ValueError; ``ablate --frames 1e23``: a worker's).
MAX_FRAMES = 10**12
_count = _int_at_least(1, MAX_FRAMES)


def _correlation_px(text: str) -> float:
    from pinpoint_fg.noise import MAX_CORRELATION_PX

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of pixels") from None
    if not 0.0 <= value <= MAX_CORRELATION_PX:  # NaN fails too
        raise argparse.ArgumentTypeError(f"{text!r}: a correlation length in [0, {MAX_CORRELATION_PX:g}] px")
    return value


def _particles(text: str) -> int:
    """An argparse type: a particle count in [1, MAX_PARTICLES], the most a result holds (``--particles 1e11`` was
    NumPy's 11.6 TiB MemoryError traceback after the run had been read)."""
    from pinpoint_fg.io.result.particles import MAX_PARTICLES

    return _int_at_least(1, MAX_PARTICLES)(text)


_seed = _int_at_least(0, MAX_SEED)
#: Most worker processes ``--jobs`` accepts (each holds a tracker and its own interpreter: ~150 MB).
MAX_JOBS = 64
_jobs = _int_at_least(1, MAX_JOBS)


def _probability(text: str) -> float:
    try:
        p = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from exc
    if not 0.0 <= p <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a probability in [0, 1]")
    return p


def _cmd_validate(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.recording.reader import summarize_recording
    from pinpoint_fg.io.recording.validator import validate_run
    from pinpoint_fg.observe import ignored_masks, ignored_masks_note, recording_notes

    recording, errors = validate_run(args.run)
    if not errors and not recording.frames:  # valid as a format, but `track` has nothing to track: say so here too
        errors = [InputError("the recording has no frames", file=Path(args.run) / "frames.csv")]
    if errors:
        for e in errors:
            print(f"error: {e}", file=sys.stderr)
        print(f"{args.run}: INVALID ({len(errors)} error(s))", file=sys.stderr)
        return 2
    print(summarize_recording(recording))
    for note in recording_notes(recording):  # valid, but the user should know
        print(note, file=sys.stderr)
    ignored = ignored_masks(recording)  # every mask's centre-line, read as `track` reads it
    if ignored:
        print(ignored_masks_note(Path(args.run), ignored), file=sys.stderr)
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.outdir import check_output_dir
    from pinpoint_fg.sim.scenarios import simulate

    check_output_dir(args.out, args.overwrite, "simulated run")  # created by simulate, whole or not at all
    config = None
    if args.mask_spurs or args.geometry != "paper":
        from dataclasses import replace

        from pinpoint_fg.sim.config import geometry_config

        config = replace(geometry_config(args.geometry), mask_spur_prob=args.mask_spurs)
    out = simulate(args.scenario, n_frames=args.frames, seed=args.seed, out=args.out, images=args.images,
                   config=config)
    if args.overwrite:
        note = _unnamed_pngs_note(Path(out))
        if note is not None:
            print(note, file=sys.stderr)
    print(f"wrote {out}")
    return 0


def _unnamed_pngs_note(run: Path) -> str | None:
    """A ``note:`` line when ``run``'s masks/ or images/ hold PNGs that no row of its frames.csv names: files of a
    longer run written there before, which ``--overwrite`` leaves in place as it leaves every file it does not
    write (said, not deleted)."""
    import csv

    with open(run / "frames.csv", newline="", encoding="utf-8") as fh:
        named = {cell for row in csv.DictReader(fh) for key in ("mask", "image") if (cell := row.get(key))}
    stale = sorted(str(p.relative_to(run)) for d in ("masks", "images") if (run / d).is_dir()
                   for p in (run / d).glob("*.png") if str(p.relative_to(run)) not in named)
    if not stale:
        return None
    return (f"note: {run} holds {len(stale)} PNG file(s) of an earlier run that no row of frames.csv names "
            f"(e.g. {stale[0]}); left in place")


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
        overwrite=args.overwrite,
        verdict_workers=1,  # bimodality verdicts in a worker process, alongside the tracker
        robust=args.robust,
        spread_scale=args.spread_scale,
        conic_correlation_px=args.conic_correlation_px,
        conic_distance=args.conic_distance,
    )
    print(f"wrote {out}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from pinpoint_fg.eval.calibrate import calibrate_runs, format_table
    from pinpoint_fg.io.outdir import prepare_output_file

    prepare_output_file(args.out, args.overwrite, "noise file", inputs=args.runs)
    notes: list[str] = []
    noise = calibrate_runs(args.runs, fit_correlation=args.conic_correlation, conic_distance=args.conic_distance,
                           notes=notes)
    for note in notes:
        print(note, file=sys.stderr)
    noise.save(args.out)
    print(format_table(noise))
    print(f"wrote {args.out}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pinpoint_fg.eval.report import evaluate
    from pinpoint_fg.io.outdir import check_output_dir

    # checked here, created by evaluate once its inputs are read: a refused input leaves no empty --out behind
    check_output_dir(args.out, args.overwrite, "evaluation",  # the reference too: its files were mixed with ours
                     inputs=[*args.results, *(p for p in (args.recording, args.reference) if p is not None)])
    summary = evaluate(args.results, recording=args.recording, out=args.out, reference=args.reference,
                       spread_scale=args.spread_scale)
    print(summary)
    return 0


def _cmd_calibrate_spread(args: argparse.Namespace) -> int:
    import math

    from pinpoint_fg.eval.spread_calibration import fit_spread_scale
    from pinpoint_fg.io.outdir import prepare_output_file
    from pinpoint_fg.io.spread_scale import format_scale

    if not 0.0 < args.mode_gate_deg <= 180.0:  # named as the option here (the library names its argument)
        raise InputError(f"must lie in (0, 180] degrees, got {args.mode_gate_deg:g}", column="--mode-gate-deg")
    prepare_output_file(args.out, args.overwrite, "spread scale", inputs=args.results)
    notes: list[str] = []
    scale = fit_spread_scale(args.results, mode_gate_rad=math.radians(args.mode_gate_deg), notes=notes)
    for note in notes:
        print(note, file=sys.stderr)
    scale.save(args.out)
    print(format_scale(scale))
    print(f"wrote {args.out}")
    return 0


def _cmd_ablate(args: argparse.Namespace) -> int:
    from pinpoint_fg.experiments.ablate import ablate

    table = ablate(args.runs, out=args.out, jobs=args.jobs, frames=args.frames, overwrite=args.overwrite)
    print(table)
    return 0


def _rgb(text: str) -> tuple[int, int, int]:
    try:
        rgb = tuple(int(s) for s in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or any(not 0 <= c <= 255 for c in rgb):
        raise argparse.ArgumentTypeError(f"expected R,G,B with integers 0..255, got {text!r}")
    return rgb  # type: ignore[return-value]


def _cmd_import_bop(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.bop import BopImportConfig, import_bop

    config = BopImportConfig(
        obj_id=args.obj_id, mask_dir=args.mask_dir, mask_color=args.mask_color, model_units=args.model_units,
        instance=args.instance, fps=args.fps, tip_end=args.tip_end, grasp_angle_rad=args.grasp_angle_rad,
        keypoints_sigma_px=args.keypoints_from_gt, seed=args.seed, images=not args.no_images, name=args.name,
    )
    print(import_bop(args.scene, args.model, args.out, config, overwrite=args.overwrite).describe())
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from pinpoint_fg.experiments.demo import run_demo

    run_demo(out=args.out, frames=args.frames, jobs=args.jobs, overwrite=args.overwrite)
    return 0


def _cmd_benchmark(args: argparse.Namespace) -> int:
    from pinpoint_fg.experiments.benchmark import run_benchmark

    frames, grid = (args.frames, args.grid_frames)
    if args.quick:
        frames, grid = min(frames, 150), min(grid or frames, 100)
    run_benchmark(out=args.out, frames=frames, seed=args.seed, jobs=args.jobs, grid_frames=grid,
                  overwrite=args.overwrite, unseen_seeds=tuple(args.unseen_seeds),
                  held_out_geometry=args.held_out_geometry)
    return 0


# --- ROS bags (import-bag, export-bag) -----------------------------------------------------

BAG_ROLES = ("camera-info", "mask", "tip", "tail", "grasper", "gt")


def _bag_topic(text: str) -> str | None:
    if not text.strip():  # was read as 'none': an unset shell variable dropped the role's data, exit 0
        raise argparse.ArgumentTypeError("an empty topic name; write 'none' to skip this role")
    return None if text.strip().lower() == "none" else text.strip()


def _bag_topics(args: argparse.Namespace):
    from pinpoint_fg.io.bag import BagTopics

    given = {r.replace("-", "_"): vars(args).get("topic_" + r.replace("-", "_"), "") for r in BAG_ROLES}
    try:
        return BagTopics(**{k: v for k, v in given.items() if v != ""})  # "" = option not given
    except ValueError as exc:
        raise InputError(str(exc), column="--topic-*") from None


def _add_bag_topic_options(s: argparse.ArgumentParser) -> None:
    from pinpoint_fg.io.bag import BagTopics

    for role in BAG_ROLES:
        default = getattr(BagTopics(), role.replace("-", "_"))
        s.add_argument(f"--topic-{role}", type=_bag_topic, default=argparse.SUPPRESS, metavar="TOPIC",
                       help=f"default {default}" + ("" if role == "camera-info" else "; 'none' skips it"))


def _cmd_import_bag(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.bag import import_bag

    summary = import_bag(args.bag, args.out, args.needle, topics=_bag_topics(args),
                         stamp_tolerance_s=args.stamp_tolerance_s, name=args.name, frame_rate_hz=args.frame_rate_hz,
                         overwrite=args.overwrite)
    print(summary.describe())
    return 0


def _cmd_export_bag(args: argparse.Namespace) -> int:
    from pinpoint_fg.io.bag import export_bag

    if args.format == "ros1" and args.storage is not None:  # was ignored: a ROS 1 bag has one storage format
        raise InputError("--storage is a ROS 2 option (sqlite3 or mcap); a ROS 1 bag has one format",
                         column="--storage")
    out = export_bag(args.run, args.out, fmt=args.format, storage=args.storage or "sqlite3",
                     topics=_bag_topics(args), overwrite=args.overwrite)
    print(f"wrote {out}")
    return 0


def _add_bag_parsers(sub: argparse._SubParsersAction) -> None:
    from pinpoint_fg.io.bag import DEFAULT_STAMP_TOLERANCE_S

    s = sub.add_parser("import-bag", help="convert a ROS 1/2 bag into a recorded run")
    s.add_argument("bag", type=Path, help="a ROS 1 .bag file or a ROS 2 bag directory")
    s.add_argument("--out", type=Path, required=True, help="the run directory to write (new or empty)")
    s.add_argument("--needle", type=Path, required=True,
                   help="NEEDLE.json: the 'needle' object of recording.json (a whole recording.json works too)")
    s.add_argument("--stamp-tolerance-s", type=float, default=DEFAULT_STAMP_TOLERANCE_S,
                   help="match messages to frames whose header stamps differ by at most this (0 = exact)")
    s.add_argument("--name", default=None, help="run name (default: the bag's name)")
    s.add_argument("--frame-rate-hz", type=float, default=None, help="default: from the camera_info stamps")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    _add_bag_topic_options(s)
    s.set_defaults(func=_cmd_import_bag)

    s = sub.add_parser("export-bag", help="write a recorded run as a ROS 2 (default) or ROS 1 bag")
    s.add_argument("run", type=Path)
    s.add_argument("--out", type=Path, required=True, help="ROS 2: a new (or empty) directory; ROS 1: a new FILE.bag")
    s.add_argument("--format", choices=("ros2", "ros1"), default="ros2")
    s.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                   help="ROS 2 storage plugin (default sqlite3; refused with --format ros1)")
    s.add_argument("--overwrite", action="store_true",
                   help="replace an existing bag at --out, whole, once the new one is written (only a bag: a "
                        "directory holding other files is refused)")
    _add_bag_topic_options(s)
    s.set_defaults(func=_cmd_export_bag)


# --- batch -----------------------------------------------------------------------------------


def _cmd_batch(args: argparse.Namespace) -> int:
    from pinpoint_fg.experiments.batch import run_batch

    def done(run: Path, out: Path, error: str | None) -> None:
        print(f"wrote {out}" if error is None else f"failed {run}", flush=True)

    outcome = run_batch(
        args.runs, args.method, args.out, scheduler=args.scheduler, workers=args.workers, on_done=done,
        particles=args.particles, window=args.window, noise_file=args.noise, disable=args.disable, seed=args.seed,
        overwrite=args.overwrite, spread_scale=args.spread_scale, conic_correlation_px=args.conic_correlation_px,
        conic_distance=args.conic_distance, robust=args.robust,
    )
    for run, error in outcome.failures.items():
        print(f"error: {run}: {error}" if str(run) not in error else f"error: {error}", file=sys.stderr)
    print(f"{len(outcome.results)} of {len(outcome.out_dirs)} runs tracked into {args.out}")
    return 2 if outcome.failures else 0


def _add_batch_parser(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("batch", help="track many runs on a Dask cluster (local by default)")
    s.add_argument("runs", type=Path, nargs="+")
    s.add_argument("--method", choices=METHODS, default="svn")
    s.add_argument("--out", type=Path, required=True, help="new or empty directory; one result per run inside")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://host:8786 (default: a local cluster)")
    s.add_argument("--workers", type=_jobs, default=2, help="worker processes of the local cluster")
    s.add_argument("--particles", type=_particles, default=None, help="default: 50 (svn, svgd), 3000 (pf)")
    s.add_argument("--window", type=_count, default=1, help="window length L (1 = filter)")
    s.add_argument("--noise", type=Path, default=None, help="noise file from `calibrate`")
    s.add_argument("--disable", type=_disable_list, default=(), help="comma list: " + ",".join(SWITCHES))
    _add_robust_option(s)
    _add_conic_model_options(s)
    s.add_argument("--seed", type=_seed, default=0)
    s.add_argument("--spread-scale", type=Path, default=None, metavar="FILE",
                   help="write q95 times the method's factors from `calibrate-spread` (recorded in result.json)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.set_defaults(func=_cmd_batch)


#: ``noise.CONIC_DISTANCES``, spelled out: importing ``pinpoint_fg.noise`` here would cost every command's start
#: (and ``--help``) ~0.8 s of NumPy and factors; ``tests/test_cli.py`` pins the two equal.
_CONIC_DISTANCES = ("sampson", "geometric")


def _add_robust_option(s: argparse.ArgumentParser) -> None:
    """``--robust`` (track and batch)."""
    s.add_argument("--robust", type=_robust_spec, default=None, metavar="SPEC",
                   help="robust losses, e.g. conic=huber:1.345,grasp-perpendicular=cauchy:1 (unlisted: none; "
                        "losses none, huber, cauchy, gm); 'none' switches all off; default: the noise file's or the "
                        "built-in conic=gm:3,grasp-perpendicular=huber:1.345")


def _add_conic_model_options(s: argparse.ArgumentParser) -> None:
    """``--conic-correlation-px`` and ``--conic-distance`` (track and batch)."""
    s.add_argument("--conic-correlation-px", type=_correlation_px, default=None, metavar="PX",
                   help="correlation length of the backbone residuals along the arc (0: independent pixels); "
                        "default: the noise file's, else 0")
    s.add_argument("--conic-distance", choices=_CONIC_DISTANCES, default=None,
                   help="backbone pixel to the image conic: first-order Sampson distance (the paper's) or the exact "
                        "geometric distance (better for a needle seen nearly edge-on); default: the noise file's, "
                        "else sampson")


class _OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose usage errors are one line (exit 2), like every other refusal of bad input: the
    usage block argparse prints first is 6-8 lines, and ``--help`` shows it."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {self.prog}: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand (subparsers inherit the one-line errors)."""
    p = _OneLineParser(
        prog="pinpoint-fg",
        description="Track the 6-DoF pose of a grasped suture needle through recorded runs (PinPoint on GTSAM): "
                    "simulate or import runs, track them (svn, svgd, pf, map, mht), evaluate and benchmark. "
                    "`pinpoint-fg COMMAND --help` for each command; bad input exits with code 2 and one line.")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("validate", help="check a recorded run against the v1 format")
    s.add_argument("run", type=Path)
    s.set_defaults(func=_cmd_validate)

    s = sub.add_parser("simulate", help="write a simulated recorded run")
    s.add_argument("--scenario", choices=SCENARIOS, default="normal", help="default: normal")
    s.add_argument("--frames", type=_count, default=300, help="default: 300 (10 s at 30 fps)")
    s.add_argument("--seed", type=_seed, default=0, help="default: 0 (a run is deterministic per seed)")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--images", action="store_true", help="also render camera images with the checkerboard")
    s.add_argument("--mask-spurs", type=_probability, default=0.0, metavar="P",
                   help="probability of a 20-35 px spur (skeleton outlier) per mask (default 0)")
    s.add_argument("--geometry", choices=GEOMETRIES, default="paper",
                   help="camera and needle: the paper's (1080x1080 px, 3/8 circle, r 4.5 mm; default) or a held-out "
                        "pair no default was tuned on (1280x1024 px, stronger distortion, 1/2 circle, r 5.5 mm)")
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser("groundtruth", help="gt_* columns from the checkerboard in the run's images")
    s.add_argument("run", type=Path)
    s.add_argument("--board-to-needle", type=Path, required=True, help="JSON with the fixed board_T_needle")
    s.set_defaults(func=_cmd_groundtruth)

    s = sub.add_parser("track", help="track the needle through a recorded run")
    s.add_argument("run", type=Path)
    s.add_argument("--method", choices=METHODS, default="svn")
    s.add_argument("--particles", type=_particles, default=None,
                   help="default: 50 (svn, svgd), 3000 (pf); mht: the bank size K (4)")
    s.add_argument("--window", type=_count, default=1, help="window length L (1 = filter)")
    s.add_argument("--noise", type=Path, default=None, help="noise file from `calibrate`")
    s.add_argument("--disable", type=_disable_list, default=(), help="comma list: " + ",".join(SWITCHES))
    _add_robust_option(s)
    _add_conic_model_options(s)
    s.add_argument("--seed", type=_seed, default=0)
    s.add_argument("--spread-scale", type=Path, default=None, metavar="FILE",
                   help="write q95 times the method's factors from `calibrate-spread` (recorded in result.json)")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.set_defaults(func=_cmd_track)

    s = sub.add_parser("calibrate", help="noise statistics of every residual at ground truth")
    s.add_argument("runs", type=Path, nargs="+")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--conic-correlation", action="store_true",
                   help="also fit the backbone residuals' correlation length along the arc (default: independent "
                        "pixels, the paper's model)")
    s.add_argument("--conic-distance", choices=_CONIC_DISTANCES, default="sampson",
                   help="the backbone residual to calibrate: the one you track with (default: sampson); recorded in "
                        "the noise file, whose distance `track --noise` then uses and enforces")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.set_defaults(func=_cmd_calibrate)

    s = sub.add_parser("evaluate", help="metrics, tables and figures of tracking results")
    s.add_argument("results", type=Path, nargs="+", help="result directories, or a `batch` output directory")
    s.add_argument("--recording", type=Path, default=None)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--reference", type=Path, default=None,
                   help="a multi-hypothesis (MHT) result of the same recording whose modes judge the bimodal verdicts")
    s.add_argument("--spread-scale", type=Path, default=None, metavar="FILE",
                   help="scale each result's q95 by its method's factors from `calibrate-spread` (files unchanged)")
    s.set_defaults(func=_cmd_evaluate)

    s = sub.add_parser("calibrate-spread",
                       help="fit per-method q95 scale factors (95 %% coverage) on results with ground truth")
    s.add_argument("results", type=Path, nargs="+", help="result directories, or a `batch` output directory")
    s.add_argument("--out", type=Path, required=True, help="the spread-scale JSON file to write")
    s.add_argument("--mode-gate-deg", type=float, default=30.0,
                   help="leave out training frames whose MAP rotation error exceeds this (another mode); "
                        "180 keeps every frame (default 30)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.set_defaults(func=_cmd_calibrate_spread)

    s = sub.add_parser("ablate", help="the ablation matrix of the paper's Table III")
    s.add_argument("runs", type=Path, nargs="+")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--jobs", type=_jobs, default=2, help="parallel processes")
    s.add_argument("--frames", type=_count, default=None, help="only the first N frames of each run")
    s.set_defaults(func=_cmd_ablate)

    s = sub.add_parser("import-bop", help="convert a BOP-format scene of a needle into a recorded run")
    s.add_argument("scene", type=Path, help="BOP scene directory (scene_camera.json, scene_gt.json, rgb/, mask_visib/)")
    s.add_argument("--model", type=Path, required=True, help="the needle's PLY model (its circle is fitted)")
    s.add_argument("--obj-id", type=int, required=True, help="BOP obj_id of the needle")
    s.add_argument("--out", type=Path, required=True, help="run directory to create (new or empty)")
    s.add_argument("--mask-dir", default="mask_visib", help="mask directory in the scene (default mask_visib)")
    s.add_argument("--mask-color", type=_rgb, default=None, metavar="R,G,B",
                   help="masks are colour labels ({im_id:06d}.png) and the needle has this colour")
    s.add_argument("--model-units", choices=("mm", "m"), default="mm", help="unit of the PLY vertices (BOP: mm)")
    s.add_argument("--instance", type=int, default=None, help="which entry of the object when an image has several")
    s.add_argument("--fps", type=float, default=30.0, help="frame rate: t_s = im_id / fps (default 30)")
    s.add_argument("--tip-end", choices=("+x", "-x", "+y", "-y", "+z", "-z"), default=None,
                   help="the tip is the arc end with the larger model coordinate along this axis "
                        "(needed when the mesh shows no tapered tip)")
    s.add_argument("--grasp-angle-rad", type=float, default=None,
                   help="grasp angle in the needle frame (default: a third of the arc from the tail)")
    s.add_argument("--keypoints-from-gt", type=float, default=None, metavar="SIGMA_PX",
                   help="SYNTHETIC keypoints: project tip/tail from the ground truth plus N(0, SIGMA_PX^2) noise")
    s.add_argument("--seed", type=_seed, default=0, help="seed of the synthetic keypoint noise")
    s.add_argument("--no-images", action="store_true", help="do not copy the images into the run")
    s.add_argument("--name", default=None, help="run name (default: the scene directory's name)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.set_defaults(func=_cmd_import_bop)

    s = sub.add_parser("demo", help="simulate, track with svn/pf/map, evaluate, print the comparison")
    s.add_argument("--out", type=Path, default=Path("demo-output"))
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--frames", type=_count, default=240)
    s.add_argument("--jobs", type=_jobs, default=2, help="parallel processes")
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser("benchmark", help="accuracy and latency of every method on every scenario")
    s.add_argument("--out", type=Path, default=Path("benchmark-output"))
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--frames", type=_count, default=300)
    s.add_argument("--seed", type=_seed, default=1)
    s.add_argument("--jobs", type=_jobs, default=1, help="parallel processes (1 keeps latencies clean)")
    s.add_argument("--grid-frames", type=_count, default=150, help="frames of the N x L latency grid")
    s.add_argument("--quick", action="store_true", help="150 frames per scenario, 100 in the N x L grid")
    s.add_argument("--unseen-seeds", type=_seed, nargs="+", default=[], metavar="SEED",
                   help="also track every scenario on these seeds with svn, pf, map and mht; means over them")
    s.add_argument("--held-out-geometry", action="store_true",
                   help="also track every scenario simulated with the held-out camera and needle (`simulate "
                        "--geometry held-out`) on the benchmark's seed and the unseen seeds, with svn, pf, map and mht")
    s.set_defaults(func=_cmd_benchmark)

    _add_bag_parsers(sub)
    _add_batch_parser(sub)
    for command in sub.choices.values():  # every ``type=Path`` argument parses through _path
        command.register("type", Path, _path)
    return p


#: What a Ctrl-C leaves, for the commands whose output is not written frame by frame.
_INTERRUPTED = {
    "export-bag": "interrupted; --out holds the old bag (or nothing) or the new one whole, never half of either",
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``pinpoint-fg`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"error: {exc.filename or exc}: not found", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(_INTERRUPTED.get(args.command, "interrupted; finished frames are on disk"), file=sys.stderr)
        return 130
    except MemoryError as exc:
        # more frames, particles or a longer window than the machine holds (`simulate --frames 1e11` was NumPy's
        # "Unable to allocate 745. GiB" traceback): one line; what was written before it stays on disk
        print(f"error: out of memory: {exc or 'MemoryError'} (ask for fewer frames or particles)", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader of our output went away (e.g. `| head`): not an error of the command. Point
        # stdout at /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        # the machine refused a file operation (disk full, permission, read-only file system): one line naming the
        # file; whatever was written before it (e.g. a result's finished frames) stays on disk
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    """The chosen subcommand; the worker pools it stopped have shut down when it returns (a race at interpreter
    exit otherwise: :func:`pinpoint_fg.offload.join_stopped_workers`)."""
    try:
        return int(args.func(args) or 0)
    finally:
        offload = sys.modules.get("pinpoint_fg.offload")  # imported only by the commands that start workers
        if offload is not None:
            offload.join_stopped_workers()


if __name__ == "__main__":
    sys.exit(main())
