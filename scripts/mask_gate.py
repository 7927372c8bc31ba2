"""The mask gate of :func:`pinpoint_fg.observe.centre_line_misfit`: its margin on valid masks, and what it saves.

Usage::

    .venv/bin/python scripts/mask_gate.py measure RUN [RUN ...]
    .venv/bin/python scripts/mask_gate.py corrupt RUN OUT [--seed 5] [--kind noise|thread]

``measure`` reads every mask of the runs (e.g. ``/tmp/runs/*-0[1-8]``: ``pinpoint-fg simulate --scenario S
--frames 150 --seed K``) and prints percentiles of the wire's width (the larger of ``width_px`` and
``thickness_px``), of the centre-line's median distance to its own conic (pixels) and of that distance in wire
widths, the worst frame, and how many masks the gate ignores (0 on valid runs). ``corrupt`` copies RUN to OUT with
masks changed: ``--kind noise`` replaces the first five by 50 % noise and every fourth after by 20 % noise;
``--kind thread`` draws into every mask a suture thread leaving the needle's tail (ground truth), 2-5 px wide,
100-400 px long, waving by 5-40 px. Then ``pinpoint-fg track OUT`` (it prints the ignored masks' note) and
``pinpoint-fg evaluate`` show what the gate does (README, *Bad input*; compare a tree before it).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np

from pinpoint_fg.conic_fit import conic_misfit_px
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.observe import centre_line_misfit, mask_backbone


def measure(runs: list[Path]) -> None:
    rows = []
    for run in runs:
        rec = read_recording(run)
        for f in rec.frames:
            if f.mask is None:
                continue
            mb = mask_backbone(rec.load_mask(f), rec.info.camera)
            if mb.points_px.shape[0] == 0:
                continue
            wire = mb.wire_px
            rows.append((run.name, f.frame, wire, conic_misfit_px(mb.points_px), centre_line_misfit(mb)))
    w, mis = np.array([r[2] for r in rows]), np.array([r[3] for r in rows])
    q = [0, 1, 50, 99, 99.9, 100]
    print(f"{len(rows)} mask frames of {len(runs)} runs; percentiles {q}")
    for name, a in (("wire width px", w), ("misfit px", mis), ("misfit / width", mis / w)):
        print(f"  {name:15s}", " ".join(f"{v:7.3f}" for v in np.percentile(a, q)))
    worst = rows[int(np.argmax(mis / w))]
    print(f"  worst: {worst[0]} frame {worst[1]}: {worst[3]:.2f} px, width {worst[2]:.2f} px")
    print(f"  ignored by the gate: {sum(r[4] is not None for r in rows)}")


def corrupt(run: Path, out: Path, seed: int, kind: str) -> None:
    if out.exists():
        raise SystemExit(f"{out} exists")
    shutil.copytree(run, out)
    rec = read_recording(out)
    rng = np.random.default_rng(seed)
    masked = [f for f in rec.frames if f.mask is not None]
    for i, f in enumerate(masked):
        path = out / f.mask
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if kind == "noise" and (i < 5 or i % 4 == 0):
            cv2.imwrite(str(path), ((rng.random(mask.shape) < (0.5 if i < 5 else 0.2)) * 255).astype(np.uint8))
            print(f"frame {f.frame}: {f.mask} is noise")
        elif kind == "thread" and f.cam_T_needle_gt is not None:
            T, needle, camera = f.cam_T_needle_gt, rec.info.needle, rec.info.camera
            tail = camera.distort_px(camera.project(needle.point(np.array([0.0])) @ T[:3, :3].T + T[:3, 3]))[0]
            s = np.linspace(0.0, 1.0, 200)[:, None]
            d = rng.normal(size=2)
            d /= np.linalg.norm(d)
            length = rng.uniform(100, 400)
            wave = np.sin(s[:, 0] * rng.uniform(3, 12)) * rng.uniform(5, 40)
            pts = tail + s * length * d + np.outer(wave, [-d[1], d[0]])
            cv2.polylines(mask, [np.round(pts).astype(np.int32)], False, 255, int(rng.integers(2, 6)))
            cv2.imwrite(str(path), mask)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("measure")
    m.add_argument("runs", nargs="+", type=Path)
    c = sub.add_parser("corrupt")
    c.add_argument("run", type=Path)
    c.add_argument("out", type=Path)
    c.add_argument("--seed", type=int, default=5)
    c.add_argument("--kind", choices=("noise", "thread"), default="noise")
    args = ap.parse_args()
    if args.cmd == "measure":
        measure(args.runs)
    else:
        corrupt(args.run, args.out, args.seed, args.kind)


if __name__ == "__main__":
    main()
