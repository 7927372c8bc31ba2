"""Two SVN settings side by side on the same frames: CPU per frame and the MAP pose's mean errors (issue 10).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/svn_settings_ab.py FIELD VALUE_A VALUE_B
RUN [RUN ...] [--reference RESULT ...]`` (e.g. ``floor_each true false /tmp/runs/normal-01``; FIELD is an
:class:`~pinpoint_fg.trackers.svn.SvnSettings` field, or ``modes.NAME`` for a
:class:`~pinpoint_fg.trackers.svn_modes.ModeSettings` one, or ``init.NAME`` for an
:class:`~pinpoint_fg.init.InitConfig` one (the seeding's); the values are parsed as JSON: ``true``, ``2``, ``0.5``;
several fields comma-separated with JSON lists of values: ``modes.polish_iters,modes.max_candidates [8,6] [30,19]``;
``kinematic_bias`` takes ``null`` or a :class:`~pinpoint_fg.kinematic_bias.BiasModel` as a JSON object,
``'{"tau_s": 5, "white_share": 0.3}'``). ``--window L``: both trackers smooth over L frames (default 1).

Both trackers are stepped in turn on every frame (lock-step, one thread: load on the machine hits both alike), with the
run's suggested switches (``demo``'s and ``benchmark``'s; ``track`` notes them). Prints per run the median thread-CPU
milliseconds per frame over all, no-mask and mask frames (from frame 10 on: the first frames run more iterations), the
MAP pose's mean translation (mm) and rotation (deg) errors, the share of frames where a particle is within 2 mm / 10 deg
of the truth (``kept``) and the modes verdict (second mode >= 0.1, ``bim``), all over the frames with ground truth, and
the ratio B / A of the CPU medians; last, the ratio of the summed per-run medians. The ambiguous scenarios (symmetric,
snapshots, drive) are chaotic: a change of round-off alone moves their errors, so judge accuracy over several seeds.

``--reference RESULT ...``: MHT results of the same runs (matched by ``result.json``'s ``recording_name``, e.g.
``/tmp/bench29/results/snapshots/mht``): each run with one then also prints, per setting, the modes verdict's rate
on the frames that result calls multimodal (its second mode >= 0.1) and on those it calls single-mode, as
``evaluate --reference`` and the benchmark's ``bim. MHT multi/single`` column judge it (issue 9).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.eval.modes import near_truth, reference_rates
from pinpoint_fg.init import InitConfig
from pinpoint_fg.io.jsonfile import load_json
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.io.result import read_modes
from pinpoint_fg.kinematic_bias import BiasModel
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.posterior.summary import bimodal_from_modes, modes_of_estimate
from pinpoint_fg.track import suggested_disable, tracker_config
from pinpoint_fg.trackers.svn import SvnSettings, SvnTracker
from pinpoint_fg.trackers.svn_modes import ModeSettings


def _with(field: str, value: object) -> tuple[SvnSettings, InitConfig]:
    """The default settings with ``field`` set to ``value``; ``modes.NAME`` sets a :class:`ModeSettings` field,
    ``init.NAME`` an :class:`~pinpoint_fg.init.InitConfig` one (the seeding's).

    Several fields at once: ``field`` comma-separated and ``value`` a JSON list of as many values.
    """
    names = field.split(",")
    values = value if len(names) > 1 else [value]
    if not isinstance(values, list) or len(values) != len(names):
        raise SystemExit(f"{field}: give a JSON list of {len(names)} values, got {value!r}")
    top = {n: v for n, v in zip(names, values, strict=True) if not n.startswith(("modes.", "init."))}
    if isinstance(top.get("kinematic_bias"), dict):  # {"tau_s": 5, "white_share": 0.3}
        top["kinematic_bias"] = BiasModel(**top["kinematic_bias"])
    modes = {n.removeprefix("modes."): v for n, v in zip(names, values, strict=True) if n.startswith("modes.")}
    init = {n.removeprefix("init."): v for n, v in zip(names, values, strict=True) if n.startswith("init.")}
    return (dataclasses.replace(SvnSettings(), modes=dataclasses.replace(ModeSettings(), **modes), **top),
            dataclasses.replace(InitConfig(), **init))


def _references(results: list[Path]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per recording name, the reference result's mode frames and sorted weights (``ModeHistory.weights_at``)."""
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for res in results:
        modes = read_modes(res)
        out[str(load_json(res / "result.json")["recording_name"])] = (modes.frames, modes.weights_at(modes.frames))
    return out


def _verdict_rates(frames: np.ndarray, bimodal: np.ndarray, ref: tuple[np.ndarray, np.ndarray]) -> str:
    """The modes verdict's bimodal rate on the reference's multimodal / single-mode frames, with their counts, as
    ``evaluate --reference`` computes them (:func:`pinpoint_fg.eval.modes.reference_rates`)."""
    every = np.ones(frames.shape[0], dtype=bool)
    r = reference_rates(frames, bimodal, every, bimodal, every, *ref)
    return " / ".join(f"{r['bimodal_modes_ref_' + part + '_rate']:4.0%} of {r['ref_' + label + '_frames']}"
                      for part, label in (("multi", "multimodal"), ("single", "single")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("field")
    ap.add_argument("value_a")
    ap.add_argument("value_b")
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--reference", type=Path, nargs="+", default=[])
    ap.add_argument("--window", type=int, default=1, help="window length L of both trackers (default 1)")
    args = ap.parse_args()
    references = _references(args.reference)
    values = [json.loads(args.value_a), json.loads(args.value_b)]
    settings = [_with(args.field, v) for v in values]
    totals = np.zeros(2)
    print(f"{'run':16s} " + " | ".join(f"{args.field}={v!s:6s} med  no-mask  mask   mm    deg  kept  bim"
                                        for v in values) + " | B/A")
    for run in args.runs:
        rec = read_recording(run)
        config = tracker_config(rec, "svn", window=args.window, disable=suggested_disable(run), seed=0)
        trackers = [SvnTracker(config, s, init) for s, init in settings]
        cpu = np.zeros((2, len(rec.frames)))
        err: list[list[tuple[float, float, bool, bool]]] = [[], []]
        verdicts = np.zeros((2, len(rec.frames)), dtype=bool)
        mask = np.zeros(len(rec.frames), dtype=bool)
        for k, frame in enumerate(rec.frames):
            obs = observe_frame(rec, frame)
            mask[k] = obs.backbone_px is not None
            for i, tracker in enumerate(trackers):
                t0 = time.thread_time()
                est = tracker.step(obs)
                cpu[i, k] = 1e3 * (time.thread_time() - t0)
                verdicts[i, k] = bimodal_from_modes(modes_of_estimate(est))
                if frame.cam_T_needle_gt is not None:
                    e = pose_errors(est.cam_T_needle[None], frame.cam_T_needle_gt[None])
                    err[i].append((1e3 * float(e.trans_m[0]), float(np.degrees(e.rot_rad[0])),
                                   bool(np.any(near_truth(est.particles, frame.cam_T_needle_gt))),
                                   bool(bimodal_from_modes(modes_of_estimate(est)))))
        sel = np.arange(len(rec.frames)) >= 10
        cols = []
        for i in range(2):
            med = float(np.median(cpu[i, sel]))
            totals[i] += med
            mm, deg, kept, bim = np.mean(err[i], axis=0) if err[i] else (float("nan"),) * 4
            cols.append(f"{'':{len(args.field) + 7}s}{med:5.1f} {np.median(cpu[i, sel & ~mask]):7.1f} "
                        f"{np.median(cpu[i, sel & mask]):5.1f} {mm:6.3f} {deg:6.2f} {kept:5.0%} {bim:4.0%}")
        ratio = np.median(cpu[1, sel]) / np.median(cpu[0, sel])
        print(f"{run.name:16s} " + " | ".join(cols) + f" | {ratio:.3f}", flush=True)
        if rec.info.name in references:
            ref, frames = references[rec.info.name], np.array([f.frame for f in rec.frames])
            print(f"{'':16s} bimodal on the reference's multimodal / single-mode frames: "
                  + " | ".join(f"{args.field}={v!s}: {_verdict_rates(frames, verdicts[i], ref)}"
                               for i, v in enumerate(values)), flush=True)
    print(f"sum of the per-run medians, B / A: {totals[1] / totals[0]:.3f}")


if __name__ == "__main__":
    main()
