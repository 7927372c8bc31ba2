"""A noise file whose motion covariance lets the needle pivot in the grasp (issue 9, rotation; measured, not kept).

Usage: ``.venv/bin/python scripts/grasp_pivot_noise.py RUN SIGMA_RAD TILT_DEG OUT.json``, then
``scripts/compare_svn_map_mht.py RUNS_DIR --noise OUT.json [...]``.

The motion residual ``Log((D T_prev)^-1 T_cur)`` is a twist in the needle frame (``factors.conventions``). A needle
that turns in the jaws by ``dphi`` about the grasper's y axis (the simulator's ``rotation`` scenario:
``T = G Ry(phi) gTn``) leaves exactly ``Ad(nTg) [e_y; 0] dphi`` in it, ``nTg`` the grasper frame in the needle frame
(:func:`pinpoint_fg.sim.kinematics.needle_T_grasper` of the run's needle and a grasper tilt). The file holds the
default noise with ``Q + SIGMA^2 a a^T`` as the motion covariance, ``a`` that twist per radian: the process noise of
a grasp that may pivot about that one axis. ``TILT_DEG`` 20 is the simulator's axis; 0 the axis a tracker can know
from the needle model alone (the radial direction at the grasp point, through the centre).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.sim.kinematics import needle_T_grasper


def pivot_noise(run: Path, sigma_rad: float, tilt_deg: float) -> tuple[NoiseConfig, np.ndarray]:
    """The default noise with the pivot variance added to the motion covariance, and the pivot twist ``(6,)``."""
    needle = read_recording(run, inflate=False).info.needle
    nTg = needle_T_grasper(needle, math.radians(tilt_deg))
    w = nTg[:3, :3] @ np.array([0.0, 1.0, 0.0])
    twist = np.concatenate([w, np.cross(nTg[:3, 3], w)])  # Ad(nTg) [e_y; 0], GTSAM's [omega; v]
    base = NoiseConfig()
    residuals = dict(base.residuals)
    residuals["motion"] = ResidualNoise(mean=np.zeros(6), cov=base.process_cov + sigma_rad**2 * np.outer(twist, twist))
    return replace(base, residuals=residuals), twist


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("sigma_rad", type=float)
    ap.add_argument("tilt_deg", type=float)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    noise, twist = pivot_noise(args.run, args.sigma_rad, args.tilt_deg)
    noise.save(args.out)
    print("pivot twist [omega; v]:", np.round(twist, 5))
