"""The backbone's weight against accuracy: SVN and MAP with every conic pixel counting ``1 / c^2`` of an
independent pixel, and the along-arc correlation of the conic residuals at the truth (issue 9, coverage).

The likelihood treats a mask skeleton's pixels as independent. Measured at the true pose of the simulator's
runs, neighbouring skeleton pixels' residuals are strongly correlated (``correlation``), so the conic term is
over-weighted. ``sweep`` tracks with the conic's sigma times ``c`` and its Cauchy knee over ``c`` (the knee
stays at the same pixel distance, so each pixel's loss is exactly divided by ``c^2``) and prints, per run and
method, the MAP's mean errors, the share of frames with a particle within 2 mm / 10 deg of the truth and the
q95 coverage. ``terms`` prints, for frames of a tracked run, each measurement term's loss (nats, robust) at
the truth and at the result's MAP pose: where the truth costs more in every term, no tracker of this model can
keep it.

Usage (one thread)::

    .venv/bin/python scripts/conic_weight.py correlation RUN [RUN ...]
    .venv/bin/python scripts/conic_weight.py sweep C svn,map RUN [RUN ...]
    .venv/bin/python scripts/conic_weight.py correlated ELL svn,map RUN [RUN ...]
    .venv/bin/python scripts/conic_weight.py distance {sampson,geometric} svn,map RUN [RUN ...]
    .venv/bin/python scripts/conic_weight.py combined ELL svn,map RUN [RUN ...]
    .venv/bin/python scripts/conic_weight.py terms RUN RESULT_DIR FIRST LAST STEP
    .venv/bin/python scripts/conic_weight.py trail C RUN FIRST LAST

``correlated`` is ``sweep`` with the default noise but the backbone residuals correlated along the arc with length
``ELL`` px (``NoiseConfig.conic_correlation_px``, :mod:`factors.conic_correlation`; 0 = independent pixels).

``distance`` is ``sweep`` with the default noise and the backbone distance given (``--conic-distance``).

``combined`` is both at once: the geometric distance, correlated along the arc with length ``ELL``
(``track --conic-distance geometric --conic-correlation-px ELL``).

``trail`` tracks RUN with SVN at weight ``1 / c^2`` and prints, for frames FIRST..LAST-1, how far (nats of
log-posterior) the best particle within 2 mm / 10 deg of the truth trails the best particle overall, and
how many particles were pruned (a trailing mode is pruned once its evidence is 30 nats behind).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from factors import residuals as res
from factors.robust import RobustLoss
from pinpoint_fg.eval.metrics import pose_errors
from pinpoint_fg.eval.modes import near_truth
from pinpoint_fg.io.recording import read_recording
from pinpoint_fg.noise import NoiseConfig, ResidualNoise
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.track import make_tracker, suggested_disable, tracker_config

LAGS = 20  # autocorrelation lags (skeleton pixels are ~1 px apart)


def conic_scaled(c: float) -> NoiseConfig:
    """The default noise with each conic pixel's loss divided by ``c^2`` (sigma times c, knee over c)."""
    base = NoiseConfig()
    residuals = dict(base.residuals)
    residuals["conic"] = ResidualNoise(base["conic"].mean, base["conic"].cov * c * c)
    robust = dict(base.robust)
    if robust["conic"].active:
        robust["conic"] = RobustLoss(robust["conic"].kind, robust["conic"].k / c)
    return NoiseConfig(residuals=residuals, robust=robust)


def correlation(run: Path) -> None:
    """Mean autocorrelation of the conic residuals at the truth along the skeleton, and its integrated length."""
    rec = read_recording(run)
    rho = []
    for frame in rec.frames:
        obs = observe_frame(rec, frame)
        if obs.backbone_px is None or len(obs.backbone_px) < 3 * LAGS or frame.cam_T_needle_gt is None:
            continue
        r = res.conic_residual(frame.cam_T_needle_gt[None], rec.info.camera.K, rec.info.needle.radius_m,
                               obs.backbone_px, jacobian=False)[0][0]
        r = r - r.mean()
        n, v = r.shape[0], float(r @ r)
        rho.append([float(r[:-k] @ r[k:]) / v * n / (n - k) for k in range(1, LAGS + 1)])
    if not rho:
        print(f"{run.name}: no frame with a skeleton of {3 * LAGS}+ pixels")
        return
    mean = np.mean(rho, axis=0)
    cut = int(np.argmax(mean < 0)) if (mean < 0).any() else LAGS
    tau = 1.0 + 2.0 * float(np.sum(mean[:cut]))
    print(f"{run.name:<16} frames {len(rho):3d}  rho(1..5) {np.round(mean[:5], 2)}  rho(10) {mean[9]:.2f}  "
          f"integrated length (lags <= {LAGS}) {tau:.1f} px")


def sweep(c: float, methods: list[str], run: Path, noise: NoiseConfig | None = None, label: str = "c",
          distance: str = "sampson") -> None:
    """``noise``: instead of :func:`conic_scaled`, this noise (``c`` is then only printed, as ``label=c``);
    ``distance``: the backbone residual's (``MeasurementModel.conic_distance``)."""
    rec = read_recording(run)
    for method in methods:
        tracker = make_tracker(method, tracker_config(rec, method, noise=conic_scaled(c) if noise is None else noise,
                                                      disable=suggested_disable(run), seed=0,
                                                      conic_distance=distance))
        et, er, kept, cov_t, cov_r = [], [], [], [], []
        for frame in rec.frames:
            est = tracker.step(observe_frame(rec, frame))
            T = frame.cam_T_needle_gt
            if T is None:
                continue
            e = pose_errors(est.cam_T_needle[None], T[None])
            et.append(e.trans_m[0] * 1e3)
            er.append(np.degrees(e.rot_rad[0]))
            cov_t.append(e.trans_m[0] <= est.q95_trans_m)
            cov_r.append(e.rot_rad[0] <= est.q95_rot_rad)
            kept.append(bool(np.any(near_truth(est.particles, T))))
        print(f"{label}={c:<4} {run.name:<16} {method:<4} {np.mean(et):6.3f} mm {np.mean(er):7.2f} deg  "
              f"kept {np.mean(kept):5.0%}  q95 coverage {np.mean(cov_t):4.0%} / {np.mean(cov_r):4.0%}", flush=True)


def terms(run: Path, result: Path, frames: range) -> None:
    from pinpoint_fg.io.result.reader import read_result
    from pinpoint_fg.likelihood import FrameLikelihood

    rec, out = read_recording(run), read_result(result)
    model = tracker_config(rec, "svn", disable=suggested_disable(run)).model
    for k in frames:
        frame = rec.frames[k]
        lik = FrameLikelihood(observe_frame(rec, frame), model)
        T = np.stack([frame.cam_T_needle_gt, out.cam_T_needle[k]])
        cells = [f"{name} {loss[0]:6.1f} / {loss[1]:6.1f}" for name, loss in lik.term_losses(T).items()]
        print(f"frame {k:3d} (truth / MAP, nats): " + " | ".join(cells))


def trail(c: float, run: Path, first: int, last: int) -> None:
    rec = read_recording(run)
    tracker = make_tracker("svn", tracker_config(rec, "svn", noise=conic_scaled(c), disable=suggested_disable(run),
                                                 seed=0))
    for k, frame in enumerate(rec.frames[:last]):
        est = tracker.step(observe_frame(rec, frame))
        if k < first or frame.cam_T_needle_gt is None:
            continue
        near = near_truth(est.particles, frame.cam_T_needle_gt)
        gap = float(np.max(est.log_posterior) - np.max(est.log_posterior[near])) if near.any() else float("nan")
        print(f"c={c:<4} {run.name} frame {k:3d}: particles near the truth {int(near.sum()):2d}, best of them "
              f"{gap:6.1f} nats behind the best; pruned {int(est.extra.get('pruned', 0))}")


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "trail":
        trail(float(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]))
        sys.exit(0)
    if len(sys.argv) == 7 and sys.argv[1] == "terms":
        terms(Path(sys.argv[2]), Path(sys.argv[3]), range(int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])))
        sys.exit(0)
    if len(sys.argv) >= 3 and sys.argv[1] == "correlation":
        for path in sys.argv[2:]:
            correlation(Path(path))
    elif len(sys.argv) >= 5 and sys.argv[1] == "distance":
        for path in sys.argv[4:]:
            sweep(0.0, sys.argv[3].split(","), Path(path), NoiseConfig(), sys.argv[2], distance=sys.argv[2])
    elif len(sys.argv) >= 5 and sys.argv[1] == "correlated":
        for path in sys.argv[4:]:
            ell = float(sys.argv[2])
            sweep(ell, sys.argv[3].split(","), Path(path), NoiseConfig(conic_correlation_px=ell), "ell")
    elif len(sys.argv) >= 5 and sys.argv[1] == "combined":
        for path in sys.argv[4:]:
            ell = float(sys.argv[2])
            sweep(ell, sys.argv[3].split(","), Path(path), NoiseConfig(conic_correlation_px=ell), "ell+geometric",
                  distance="geometric")
    elif len(sys.argv) >= 5 and sys.argv[1] == "sweep":
        for path in sys.argv[4:]:
            sweep(float(sys.argv[2]), sys.argv[3].split(","), Path(path))
    else:
        sys.exit(__doc__)
