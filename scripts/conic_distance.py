"""Sampson vs geometric backbone distance at the true pose, per masked frame (README "Mask noise models").

Usage: ``.venv/bin/python scripts/conic_distance.py RUN FIRST LAST``

For masked frames FIRST..LAST-1 of a run with ground truth, prints how far the needle's plane is from containing
the viewing ray (0 deg: edge-on), the largest and median |distance| of the frame's backbone pixels to the true
pose's image conic under each distance, and the conic term's robust loss (nats) at the truth under each (the
default noise): where the Sampson distance over-states a thin ellipse's distance, the truth pays for it.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from factors import residuals as res
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import suggested_disable, tracker_config


def main(run: Path, first: int, last: int) -> None:
    rec = read_recording(run)
    model = tracker_config(rec, "svn", disable=suggested_disable(run)).model
    K, radius = rec.info.camera.K, rec.info.needle.radius_m
    for frame in rec.frames[first:last]:
        obs = observe_frame(rec, frame)
        T = frame.cam_T_needle_gt
        if obs.backbone_px is None or T is None:
            continue
        view = np.degrees(np.arcsin(abs(T[:3, 2] @ T[:3, 3]) / np.linalg.norm(T[:3, 3])))
        cells = []
        for name, fn in (("sampson", res.conic_residual), ("geometric", res.conic_geometric_residual)):
            r = np.abs(fn(T[None], K, radius, obs.backbone_px, jacobian=False)[0][0])
            loss = FrameLikelihood(obs, replace(model, conic_distance=name)).term_losses(T[None])["conic"][0]
            cells.append(f"{name} max {r.max():5.1f} median {np.median(r):4.2f} px, loss {loss:6.1f}")
        print(f"frame {frame.frame:4d}  view {view:4.1f} deg  {len(obs.backbone_px):3d} px | " + " | ".join(cells))


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]))
