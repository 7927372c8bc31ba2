"""``pinpoint-fg track``'s wall time against the sum of its step latencies, each run in a fresh process (issue 10).

Usage: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/track_wall.py RUN --out DIR [--frames 100]
[--repeats 3]``. Prints every run's wall seconds, step sum and ratio, and the CPU seconds of the tracking process and
of its worker with the ratio they would give spread perfectly over two cores: the benchmark's ``track`` line
(:func:`pinpoint_fg.experiments.latency.track_wall`: svn, one worker process). To compare two trees, run it from
each in turn with ``PYTHONPATH`` set to the tree, one repeat at a time, alternating: the machine's load moves the
wall time by more than most changes do.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from pinpoint_fg.experiments.latency import track_wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, required=True, help="scratch directory (emptied first)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    result = track_wall(args.run, args.out, args.frames, args.repeats)
    for k, r in enumerate(result["runs"], start=1):
        print(f"{args.run.name} run {k}: wall {r['wall_s']:.3f} s, steps {r['step_sum_s']:.3f} s, "
              f"wall / steps {r['ratio']:.3f}; CPU tracker {r['cpu_tracker_s']:.3f} s, "
              f"worker {r['cpu_worker_s']:.3f} s, bound {r['cpu_bound']:.3f}")


if __name__ == "__main__":
    main()
