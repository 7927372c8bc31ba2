"""The truth about ambiguity, and the accuracy floor (DESIGN.md §Evaluation).

A bimodality verdict is only meaningful against what the frame's data actually allow, so for
every frame with a ground-truth pose ``T_gt`` this module measures

**ΔNLL: how much worse the second circle pose explains the frame.** The needle circle at
``T_gt`` projects to the image conic ``C ∝ adj(H)^T diag(1, 1, -r^2) adj(H)``, ``H = K [r1 r2 t]``
(as in :func:`factors.residuals.conic_residual`). A circle of known radius seen as an ellipse
has two closed-form poses (:func:`pinpoint_fg.init.circle_poses_from_conic`): one reproduces the
truth's plane, the other is the *alternative* (its normal differs). The alternative fixes the
needle's plane and centre but not where the arc lies on the circle, so:

1. sweep the in-plane angle on a grid (``angle_steps``, both normal orientations) and score
   every candidate with the frame's :class:`~pinpoint_fg.likelihood.FrameLikelihood` — the same
   terms, switches and noise the tracker used;
2. polish the ``candidates`` best grid poses, and ``T_gt`` itself, by batched Levenberg-Marquardt
   on all six degrees of freedom (:func:`polish_to_convergence`: a step is kept only if it lowers
   the NLL, until the Gauss-Newton decrement ``1/2 g^T H^-1 g`` of every pose is below
   ``decrement_tol`` nats);
3. keep a polished alternative only if it stayed in its mode: its plane normal must remain
   closer (as a line, ``arccos |n . n'|``) to the alternative's than to the truth's. If every
   polished candidate drifted back to the truth, the best *unpolished* grid pose is used (its
   ΔNLL is then an upper bound). Likewise, if the solve started at ``T_gt`` ends nearer the
   alternative's plane (a frame that does not pin the pose down, e.g. one keypoint and the grasp
   terms), the truth side of ΔNLL is ``nll(T_gt)`` instead;
4. ``ΔNLL = nll(alternative mode) - nll(truth mode)``.

Decision (refines the wording "nll(alternative) - nll(truth)"): both sides are *mode minima*.
``T_gt`` itself is not the minimum of a noisy frame's NLL: it sits about ½·χ²₆ ≈ 3 nats above
it, as much as the 2.3-nat threshold, while the alternative is polished to its minimum; comparing
minimum with minimum removes that bias. ``exp(-ΔNLL)`` is then the alternative mode's peak
density relative to the truth's (Laplace mass ratio up to the two modes' volume factors), so
``ΔNLL < 2.3`` (:data:`AMBIGUOUS_BELOW`) means the alternative holds ≳ 10 % of the mass — the
frame is genuinely ambiguous — and ``ΔNLL > 10`` (:data:`CLEAR_ABOVE`) means it holds
< 5·10⁻⁵: the frame is clear. When the two closed-form planes are closer than
``min_mode_separation_deg`` (a needle seen face-on: one mode) there is no alternative mode and
ΔNLL is ``+inf`` (clear); when the conic is not an ellipse (edge-on) ΔNLL is NaN (unknown).

**The accuracy floor.** The polished truth of step 2 is the frame's MAP solved from the truth:
same factors and noise, a single frame, no motion model and no prior (a per-frame estimator's
best case started at the right mode). Its error against ``T_gt`` is the error no per-frame
estimator beats on average; a tracker's mean error divided by the floor's says how close it
gets (:func:`pinpoint_fg.eval.metrics.accuracy_multiple`). The floor pose is wherever that solve
converges, even when it leaves the truth's basin (a frame with too few terms to fix all six
degrees of freedom can slide far): that is what a per-frame estimator would get. Directions
with no information at all (e.g. no image evidence) do not move, so there the floor is
optimistic (it inherits the truth).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from factors.lie import se3_exp
from factors.residuals import needle_image_conic
from pinpoint_fg.eval.metrics import PoseErrors, pose_errors
from pinpoint_fg.init import circle_poses_from_conic
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.stein import floor_hessians

AMBIGUOUS_BELOW = 2.3
"""ΔNLL below this: the alternative circle pose holds >= ~10 % of the mass (exp(-2.3) = 0.10)."""
CLEAR_ABOVE = 10.0
"""ΔNLL above this: the alternative holds < ~5e-5 of the mass."""

LABELS = ("ambiguous", "between", "clear", "unknown")
"""Frame labels: by ΔNLL, and ``unknown`` (no ground truth, or no closed-form alternative)."""


@dataclass(frozen=True)
class AmbiguityConfig:
    """Settings of the ΔNLL measurement and the accuracy floor."""

    angle_steps: int = 72
    """In-plane angles swept for the alternative pose (per normal orientation; 72 -> 5 degrees)."""
    candidates: int = 3
    """Best grid poses polished by Gauss-Newton."""
    polish_iters: int = 60
    """At most this many Levenberg-Marquardt iterations per polish (truth and alternatives)."""
    decrement_tol: float = 1e-2
    """A polish stops when every pose's Gauss-Newton decrement is below this, nats."""
    min_mode_separation_deg: float = 5.0
    """Closed-form planes closer than this (angle between normals) are one mode: ΔNLL = +inf."""


@dataclass(frozen=True)
class FrameAmbiguity:
    """ΔNLL analysis of one frame."""

    delta_nll: float
    """``nll(alternative mode) - nll(truth mode)``; +inf without a distinct alternative, NaN if unknown."""
    nll_truth: float
    """NLL of the truth mode: the polished truth, or ``nll(T_gt)`` if that solve crossed planes."""
    nll_alternative: float
    """NLL of the alternative mode (NaN / inf when there is none)."""
    cam_T_truth_mode: np.ndarray
    """(4, 4) the frame's MAP solved from the truth (the accuracy-floor pose)."""
    cam_T_alternative: np.ndarray | None
    """(4, 4) the alternative mode's pose, None when there is none."""
    normal_separation_deg: float
    """Angle between the truth's plane and the alternative plane, degrees (NaN when unknown)."""
    truth_solve_crossed: bool = False
    """The solve from the truth ended nearer the alternative's plane than the truth's."""


def image_conic(cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float) -> np.ndarray:
    """Image conic ``C`` (3, 3) of the needle circle at one pose: ``adj(H)^T diag(1, 1, -r^2) adj(H)``.

    ``H = K [r1 r2 t]``; scaled to unit Frobenius norm (a conic is defined up to scale). The one
    implementation is :func:`factors.residuals.needle_image_conic`.
    """
    return needle_image_conic(cam_T_needle, K, radius_m)[0]


def _line_angle_deg(n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """Angle between lines along unit vectors (..., 3), degrees, in [0, 90]."""
    c = np.abs(np.sum(n1 * n2, axis=-1)) / (np.linalg.norm(n1, axis=-1) * np.linalg.norm(n2, axis=-1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def alternative_circle(
    cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The truth's image ellipse's other closed-form circle: ``(centre (3,), normal (3,), separation_deg)``.

    Of the two solutions of :func:`~pinpoint_fg.init.circle_poses_from_conic`, the one whose plane
    is farther from the truth's (angle between the normals as lines) is returned, with that
    angle. None when the conic is not an ellipse seen from the front (edge-on needle).
    """
    T = np.asarray(cam_T_needle, dtype=float)
    sols = circle_poses_from_conic(image_conic(T, K, radius_m), np.asarray(K, dtype=float), radius_m)
    if len(sols) < 2:
        return None
    n_gt = T[:3, 2]
    ang = [float(_line_angle_deg(n, n_gt)) for _, n in sols]
    i = int(np.argmax(ang))
    centre, normal = sols[i]
    return np.asarray(centre, float), np.asarray(normal, float) / np.linalg.norm(normal), ang[i]


def _in_plane_poses(centre: np.ndarray, normal: np.ndarray, steps: int) -> np.ndarray:
    """Poses (2 steps, 4, 4): needle frames with z = ±normal at ``centre``, in-plane angle on a grid."""
    out = []
    ang = np.linspace(0.0, 2.0 * np.pi, int(steps), endpoint=False)
    c, s = np.cos(ang), np.sin(ang)
    for n in (normal, -normal):
        helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x0 = helper - (helper @ n) * n
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(n, x0)
        ex = c[:, None] * x0 + s[:, None] * y0
        ey = -s[:, None] * x0 + c[:, None] * y0
        T = np.zeros((ang.shape[0], 4, 4))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = ex, ey, n
        T[:, :3, 3] = centre
        T[:, 3, 3] = 1.0
        out.append(T)
    return np.concatenate(out, axis=0)


def _jacobi_scaled(g: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit-free form of gradients (N, 6) and information (N, 6, 6): ``d = sqrt(diag H)``,
    ``g_s = g / d``, ``H_s = H / (d d^T)`` with eigenvalues floored at 1e-9 of the largest.

    Returns ``g_s``, floored ``H_s``, its inverse and ``d`` (N, 6). A direction without
    information (``diag H = 0``) gets a tiny ``d`` and zero gradient, so it does not move.
    """
    diag = np.einsum("nii->ni", H)
    d = np.sqrt(np.maximum(diag, 1e-18 * np.max(diag, axis=1, keepdims=True) + 1e-300))
    Hs = H / (d[:, :, None] * d[:, None, :])
    Hs_f, Hs_inv = floor_hessians(Hs, eps=1e-9)
    return g / d, Hs_f, Hs_inv, d


def polish_to_convergence(
    lik: FrameLikelihood, cam_T_needle: np.ndarray, max_iters: int = 60, decrement_tol: float = 1e-2
) -> tuple[np.ndarray, np.ndarray]:
    """Batched Levenberg-Marquardt on poses (N, 4, 4) -> polished poses (N, 4, 4) and their NLL (N,).

    Per pose, in Jacobi-scaled (unit-free) coordinates ``d = sqrt(diag H)`` so that rotation
    (rad) and translation (m) are comparable: ``H_s = H / (d d^T)`` with eigenvalues floored at
    1e-9 of the largest (:func:`pinpoint_fg.stein.floor_hessians`), the Marquardt step
    ``-(H_s + lam I)^-1 (g / d) / d`` in the right chart, kept only if the NLL decreases (then
    ``lam /= 3``, else ``lam *= 10``; ``lam`` starts at 1e-3). A pose stops once its Gauss-Newton
    decrement ``1/2 g^T H^-1 g`` is below ``decrement_tol`` (only the others are iterated on); all
    stop after ``max_iters``. Directions the frame does not observe get no information and do not
    move.
    """
    T = np.array(cam_T_needle, dtype=float)
    lam = np.full(T.shape[0], 1e-3)
    nll, g, H = lik.gauss_newton(T)
    eye = np.eye(6)
    for _ in range(int(max_iters)):
        gs, Hs_f, Hs_inv, d = _jacobi_scaled(g, H)
        active = np.nonzero(0.5 * np.einsum("ni,nij,nj->n", gs, Hs_inv, gs) >= decrement_tol)[0]
        if active.size == 0:
            break
        A = Hs_f[active] + lam[active, None, None] * eye
        step = -np.linalg.solve(A, gs[active][..., None])[..., 0] / d[active]
        Tn = T[active] @ se3_exp(step)
        nll_n, g_n, H_n = lik.gauss_newton(Tn)
        better = nll_n < nll[active]
        acc = active[better]
        T[acc], nll[acc], g[acc], H[acc] = Tn[better], nll_n[better], g_n[better], H_n[better]
        lam[active] = np.where(better, lam[active] / 3.0, lam[active] * 10.0)
    return T, nll


def analyse_frame(
    lik: FrameLikelihood,
    cam_T_gt: np.ndarray,
    config: AmbiguityConfig = AmbiguityConfig(),
    alternatives: bool = True,
) -> FrameAmbiguity:
    """ΔNLL and the accuracy-floor pose of one frame (module docstring); ``alternatives=False`` skips ΔNLL."""
    T_gt = np.asarray(cam_T_gt, dtype=float)
    K = lik.model.camera.K
    r = lik.model.needle.radius_m
    n_gt = T_gt[:3, 2]
    alt = alternative_circle(T_gt, K, r)  # closed form; also needed for the truth polish's drift check

    grid = np.zeros((0, 4, 4))
    grid_nll = np.zeros(0)
    if alternatives and alt is not None and alt[2] >= config.min_mode_separation_deg:
        grid = _in_plane_poses(alt[0], alt[1], config.angle_steps)
        grid_nll = lik.nll(grid)
        order = np.argsort(grid_nll)[: max(int(config.candidates), 1)]
        start = np.concatenate([T_gt[None], grid[order]], axis=0)
    else:
        start = T_gt[None]
    polished, nll = polish_to_convergence(lik, start, config.polish_iters, config.decrement_tol)

    # the floor is wherever the solve from the truth went; the truth *mode's* NLL falls back to
    # nll(T_gt) when that solve left the truth's plane for one nearer the alternative's
    T_truth, nll_truth = polished[0], float(nll[0])
    crossed = alt is not None and bool(
        _line_angle_deg(T_truth[:3, 2], alt[1]) < _line_angle_deg(T_truth[:3, 2], n_gt)
    )
    if crossed:
        nll_truth = float(lik.nll(T_gt)[0])

    if not alternatives or alt is None:
        return FrameAmbiguity(
            delta_nll=float("nan"), nll_truth=nll_truth, nll_alternative=float("nan"),
            cam_T_truth_mode=T_truth, cam_T_alternative=None,
            normal_separation_deg=float("nan") if alt is None else alt[2], truth_solve_crossed=crossed,
        )
    if grid.shape[0] == 0:
        return FrameAmbiguity(
            delta_nll=float("inf"), nll_truth=nll_truth, nll_alternative=float("inf"),
            cam_T_truth_mode=T_truth, cam_T_alternative=None, normal_separation_deg=alt[2],
            truth_solve_crossed=crossed,
        )
    P, pn = polished[1:], nll[1:]
    stayed = _line_angle_deg(P[:, :3, 2], alt[1][None]) < _line_angle_deg(P[:, :3, 2], n_gt[None])
    if np.any(stayed):
        j = int(np.argmin(np.where(stayed, pn, np.inf)))
        T_alt, nll_alt = P[j], float(pn[j])
    else:
        j = int(np.argmin(grid_nll))
        T_alt, nll_alt = grid[j], float(grid_nll[j])
    return FrameAmbiguity(
        delta_nll=nll_alt - nll_truth, nll_truth=nll_truth, nll_alternative=nll_alt, cam_T_truth_mode=T_truth,
        cam_T_alternative=T_alt, normal_separation_deg=alt[2], truth_solve_crossed=crossed,
    )


def ambiguity_delta_nll(
    lik: FrameLikelihood, T_gt: np.ndarray, config: AmbiguityConfig = AmbiguityConfig()
) -> float:
    """``nll(alternative mode) - nll(truth mode)`` of one frame with the tracker's likelihood (see module)."""
    return analyse_frame(lik, T_gt, config).delta_nll


def label_delta_nll(delta_nll: np.ndarray) -> np.ndarray:
    """Labels (F,) of ΔNLL: ``ambiguous`` (< 2.3), ``clear`` (> 10, +inf), ``between``, ``unknown`` (NaN)."""
    d = np.asarray(delta_nll, dtype=float)
    out = np.full(d.shape, "between", dtype=object)
    out[d < AMBIGUOUS_BELOW] = "ambiguous"
    out[d > CLEAR_ABOVE] = "clear"
    out[np.isnan(d)] = "unknown"
    return out


@dataclass(frozen=True)
class RecordingAmbiguity:
    """Per-frame ΔNLL, labels and accuracy floor of a recording under one measurement model."""

    frame: np.ndarray
    """Frame indices (F,) of the recording."""
    delta_nll: np.ndarray
    """(F,) ΔNLL; NaN without ground truth (or when not computed)."""
    labels: np.ndarray
    """(F,) object array of :data:`LABELS`."""
    floor_T: np.ndarray
    """(F, 4, 4) the per-frame MAP solved from the truth; NaN without ground truth."""
    floor_errors: PoseErrors
    """Errors of ``floor_T`` against the truth (NaN without ground truth)."""
    normal_separation_deg: np.ndarray
    """(F,) angle between the two closed-form planes, degrees (NaN when unknown)."""

    def index_of(self, frames: np.ndarray) -> np.ndarray:
        """Row indices (K,) of the given frame numbers (-1 where a frame is not in the recording)."""
        pos = {int(f): i for i, f in enumerate(self.frame)}
        return np.array([pos.get(int(f), -1) for f in np.asarray(frames).reshape(-1)], dtype=int)


def analyse_recording(
    recording: Recording,
    model: MeasurementModel,
    config: AmbiguityConfig = AmbiguityConfig(),
    alternatives: bool = True,
    frames: Iterable[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RecordingAmbiguity:
    """:func:`analyse_frame` on every frame of the recording that has ground truth.

    The result has one row per recording frame; with ``frames`` (frame numbers) only those are
    analysed and the others stay NaN / ``unknown``. ``progress(done, total)`` is called after
    each analysed frame when given.
    """
    wanted = None if frames is None else {int(f) for f in frames}
    all_frames = recording.frames
    F = len(all_frames)
    todo = [i for i, r in enumerate(all_frames)
            if r.cam_T_needle_gt is not None and (wanted is None or int(r.frame) in wanted)]
    delta = np.full(F, np.nan)
    sep = np.full(F, np.nan)
    floor_T = np.full((F, 4, 4), np.nan)
    T_gt = np.full((F, 4, 4), np.nan)
    for done, i in enumerate(todo, start=1):
        rec = all_frames[i]
        T_gt[i] = rec.cam_T_needle_gt
        lik = FrameLikelihood(observe_frame(recording, rec), model)
        fa = analyse_frame(lik, rec.cam_T_needle_gt, config, alternatives=alternatives)
        delta[i], sep[i], floor_T[i] = fa.delta_nll, fa.normal_separation_deg, fa.cam_T_truth_mode
        if progress is not None:
            progress(done, len(todo))
    labels = label_delta_nll(delta) if alternatives else np.full(F, "unknown", dtype=object)
    return RecordingAmbiguity(
        frame=np.array([r.frame for r in all_frames], dtype=np.int64),
        delta_nll=delta,
        labels=labels,
        floor_T=floor_T,
        floor_errors=pose_errors(floor_T, T_gt),
        normal_separation_deg=sep,
    )


def label_frames(
    recording: Recording, model: MeasurementModel, config: AmbiguityConfig = AmbiguityConfig()
) -> np.ndarray:
    """Per-frame labels (F,) of a recording: ``ambiguous``, ``between``, ``clear``, ``unknown`` (no truth)."""
    return analyse_recording(recording, model, config).labels


def accuracy_floor(
    recording: Recording, model: MeasurementModel, config: AmbiguityConfig = AmbiguityConfig()
) -> np.ndarray:
    """Per-frame MAP poses (F, 4, 4) solved from the truth (NaN where a frame has no ground truth).

    Single frame, the model's likelihood terms only (no motion model, no prior), batched damped
    Gauss-Newton started at ``T_gt`` (module docstring). Compare with
    :func:`pinpoint_fg.eval.metrics.pose_errors`.
    """
    return analyse_recording(recording, model, config, alternatives=False).floor_T

