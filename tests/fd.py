"""Finite differences through ``gtsam.Pose3.retract`` with an error estimate (Richardson-style)."""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

STEPS = (1e-3, 3e-4, 1e-4, 3e-5, 1e-5, 3e-6, 1e-6, 3e-7, 1e-7, 3e-8, 1e-8, 3e-9, 1e-9, 3e-10)


def numerical_jacobian(f: Callable[[gtsam.Pose3], np.ndarray], T: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of ``f(T.retract(d))`` w.r.t. ``d`` at 0, shape ``(m, 6)``, and an error estimate.

    Central differences are taken at several step sizes; the estimate is the one from the pair
    of neighbouring steps that agree best, and their disagreement (per row) is the error
    estimate. A smooth function gives ~1e-10 relative; a strongly curved one (edge-on conic)
    reports a larger estimate honestly instead of a false failure.
    """
    ests = []
    for h in STEPS:
        cols = []
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            cols.append((np.atleast_1d(f(T.retract(d))) - np.atleast_1d(f(T.retract(-d)))) / (2 * h))
        ests.append(np.stack(cols, axis=-1))
    ests = np.array(ests)  # (S, m, 6)
    diffs = np.abs(ests[1:] - ests[:-1]).max(axis=2)  # (S-1, m) per row
    best = np.argmin(diffs, axis=0)  # per row
    rows = np.arange(ests.shape[1])
    J = ests[best + 1, rows, :]
    err = diffs[best, rows]
    return J, err
