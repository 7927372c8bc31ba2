"""Mode proposals and their Laplace evidence: pure, batched building blocks (issue 9, item 1).

A circle seen by one camera is ambiguous in two ways, and every proposal below keeps the
projected ellipse *exactly* (only evidence beyond the ellipse — keypoints, kinematics, motion —
can tell them apart):

* **Twin** (the two-fold cone ambiguity): the other circle of radius ``r`` whose image is the
  same conic — from the mode's own projected ellipse (:func:`twin_poses`) or from the frame's
  fitted ellipse (:func:`frame_ellipse_poses`, both circles). The closed form of
  :func:`pinpoint_fg.init.circle_poses_from_conic` gives each circle's centre and normal; the
  in-plane angle (where the arc lies on the circle) is closed-form too: the mode's arc midpoint
  and ends are carried along their camera rays onto the twin's plane (the same image pixels),
  the normal's sign is chosen so the arc runs from the tail to the tip counter-clockwise like
  the model's, and the needle frame is turned so the arc midpoint sits at its model angle. From
  the frame's ellipse, the arc midpoint is the middle of the angular range the backbone pixels
  cover once back-projected onto the plane (the complement of the largest empty gap).
* **Flips** (:func:`arc_flips`): rigid rotations by ``pi`` about an in-plane axis through the
  circle's centre map the circle onto itself: about the arc midpoint's radius (the arc keeps
  its points, its direction reverses: tip and tail swap), about the tail's radius (the arc is
  mirrored beyond the tail) and about the tip's radius (mirrored beyond the tip). In the needle
  frame that is ``T' = T Rot(u, pi)``, ``u = (cos a, sin a, 0)``.

:func:`mode_proposals` gathers these for a mode and removes duplicates (within
``separation``, also of modes already held). Polishing and admission are the tracker's job:
:func:`polish_with_prior` is the batched Gauss-Newton polish of ``frame nll + Gaussian window
prior`` and :func:`laplace_log_evidence` scores the polished peak.

**Laplace evidence convention.** For an energy ``E(x) = -log p(z, x)`` (the frame's nll plus the
window prior's quadratic) with a peak ``x*`` and information ``H`` (the Hessian of ``E`` at the
peak in GTSAM's right chart, ``d x d``):

    log Z = -E(x*) - 1/2 log det H + d/2 log(2 pi)

(``d = 6`` for a pose: ``+3 log 2 pi``). The measurement noise normalisers are left out: they are
the same for every hypothesis of one frame, so weights stay comparable. A Gaussian prior
``N(mu, P)`` contributes its normaliser ``-1/2 log det(2 pi P)`` (:func:`gaussian_log_normaliser`),
which *does* differ between hypotheses whose priors differ. A non-positive-definite ``H`` has
no Laplace approximation and scores ``-inf``.
"""

from __future__ import annotations

import numpy as np

from factors.lie import cross, local, se3_exp, se3_inverse, se3_right_jacobian_inv
from factors.residuals import as_pose_batch, needle_image_conic
from pinpoint_fg.conic_fit import fit_conic
from pinpoint_fg.init import circle_poses_from_conic
from pinpoint_fg.likelihood import FrameLikelihood

#: Two poses closer than (rotation rad, centre translation m) are one proposal (or one mode).
DEFAULT_SEPARATION = (np.deg2rad(5.0), 1e-3)


# ----------------------------------------------------------------------------- evidence


def laplace_log_evidence(nll_at_peak: np.ndarray | float, information: np.ndarray) -> np.ndarray:
    """``log Z = -E - 1/2 log det H + d/2 log 2 pi`` per hypothesis (module docstring); ``(...)``.

    ``nll_at_peak (...)`` is the energy at the peak, ``information (..., d, d)`` its Hessian there
    (any ``d``; 6 for a pose, 1 for a slice). Non-positive-definite information gives ``-inf``.
    """
    H = np.asarray(information, dtype=float)
    E = np.asarray(nll_at_peak, dtype=float)
    d = H.shape[-1]
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    w = np.linalg.eigvalsh(Hs)
    pd = np.all(w > 0, axis=-1)
    logdet = np.sum(np.log(np.where(w > 0, w, 1.0)), axis=-1)
    out = -E - 0.5 * logdet + 0.5 * d * np.log(2.0 * np.pi)
    return np.where(pd & np.isfinite(out), out, -np.inf)


def gaussian_log_normaliser(cov: np.ndarray) -> np.ndarray:
    """``-1/2 log det(2 pi P)`` of a Gaussian with covariance ``cov (..., d, d)``; ``(...)``."""
    P = np.asarray(cov, dtype=float)
    d = P.shape[-1]
    sign, logdet = np.linalg.slogdet(0.5 * (P + np.swapaxes(P, -1, -2)))
    return np.where(sign > 0, -0.5 * (logdet + d * np.log(2.0 * np.pi)), -np.inf)


# ----------------------------------------------------------------------------- geometry


def _rot_pi(axis: np.ndarray) -> np.ndarray:
    """Rotation by pi about unit axes ``(..., 3)``: ``2 u u^T - I``."""
    u = np.asarray(axis, dtype=float)
    return 2.0 * u[..., :, None] * u[..., None, :] - np.eye(3)


def arc_flips(cam_T_needle: np.ndarray, tail_angle_rad: float, tip_angle_rad: float) -> np.ndarray:
    """The three flips of every pose, ``(N, 3, 4, 4)``: about the arc midpoint's, the tail's and the tip's radius.

    ``T' = T [Rot(u, pi), 0]`` with ``u = (cos a, sin a, 0)`` in the needle frame and ``a`` the
    midpoint ``(tail + tip) / 2``, the tail or the tip angle. Each maps the circle onto itself, so
    the image conic is unchanged.
    """
    T = as_pose_batch(cam_T_needle)
    angles = np.array([0.5 * (tail_angle_rad + tip_angle_rad), tail_angle_rad, tip_angle_rad])
    F = np.tile(np.eye(4), (3, 1, 1))
    F[:, :3, :3] = _rot_pi(np.stack([np.cos(angles), np.sin(angles), np.zeros(3)], axis=1))
    return T[:, None] @ F[None]


def pose_on_circle(centre_m: np.ndarray, normal: np.ndarray, cam_dir_mid: np.ndarray,
                   mid_angle_rad: float) -> np.ndarray:
    """Needle poses ``(N, 4, 4)``: circle centre, needle z = ``normal``, arc midpoint direction ``cam_dir_mid``.

    The needle frame's x axis is ``cos(a) m - sin(a) (n x m)`` (``a`` = the model's midpoint angle,
    ``m`` = ``cam_dir_mid`` projected into the plane), so ``R (cos a, sin a, 0) = m``.
    """
    c = np.atleast_2d(np.asarray(centre_m, dtype=float))
    n = np.atleast_2d(np.asarray(normal, dtype=float))
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    m = np.atleast_2d(np.asarray(cam_dir_mid, dtype=float))
    m = m - np.sum(m * n, axis=1, keepdims=True) * n
    m = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    nxm = cross(n, m)
    x = np.cos(mid_angle_rad) * m - np.sin(mid_angle_rad) * nxm
    T = np.tile(np.eye(4), (c.shape[0], 1, 1))
    T[:, :3, :3] = np.stack([x, cross(n, x), n], axis=2)
    T[:, :3, 3] = c
    return T


def _rays_to_plane(points_cam: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Carry camera-frame points ``(M, 3)`` along their rays onto the plane through ``centre`` with ``normal``."""
    den = points_cam @ normal
    den = np.where(np.abs(den) < 1e-300, 1e-300, den)
    return points_cam * ((centre @ normal) / den)[:, None]


def twin_poses(cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float, tail_angle_rad: float,
               tip_angle_rad: float, min_angle_rad: float = np.deg2rad(5.0)) -> np.ndarray:
    """Closed-form twin of each pose from its own projected ellipse, ``(N', 4, 4)`` (N' <= N).

    The other circle with the same image conic (its plane more than ``min_angle_rad`` from the
    pose's; face-on and edge-on views have none and are skipped). The arc's tail, midpoint and
    tip are carried along their rays onto the twin's plane; the normal's sign makes the arc run
    tail -> tip in the model's sense and the midpoint sits at the model's midpoint angle.
    """
    T = as_pose_batch(cam_T_needle)
    K = np.asarray(K, dtype=float)
    a_mid = 0.5 * (tail_angle_rad + tip_angle_rad)
    sense = 1.0 if tip_angle_rad > tail_angle_rad else -1.0
    needle_pts = radius_m * np.array([[np.cos(a), np.sin(a), 0.0] for a in (tail_angle_rad, a_mid, tip_angle_rad)])
    conics = needle_image_conic(T, K, radius_m)
    out = []
    for Ti, C in zip(T, conics, strict=True):
        sols = circle_poses_from_conic(C, K, radius_m)
        if len(sols) < 2:
            continue
        n_ref = Ti[:3, 2]
        cos_ang = [abs(float(n @ n_ref)) for _, n in sols]
        j = int(np.argmin(cos_ang))
        if cos_ang[j] > np.cos(min_angle_rad):
            continue
        c, n = sols[j]
        p = needle_pts @ Ti[:3, :3].T + Ti[:3, 3]
        q = _rays_to_plane(p, c, n) - c
        nn = n * np.sign(cross(q[0], q[2]) @ n) * sense
        out.append(pose_on_circle(c, nn, q[1], a_mid)[0])
    return np.stack(out) if out else np.zeros((0, 4, 4))


def frame_ellipse_poses(backbone_px: np.ndarray | None, K: np.ndarray, radius_m: float, tail_angle_rad: float,
                        tip_angle_rad: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Both circle poses of the ellipse fitted to a frame's backbone pixels, ``(P, 4, 4)``, and that conic.

    Per circle, the backbone pixels are carried along their rays onto its plane; the arc midpoint
    is the middle of the angular range they cover (the complement of the largest empty gap), and
    both normal signs are returned (they are each other's midpoint flip). Empty (and None) when
    there are fewer than 5 pixels or the fit is not an ellipse seen from the front.
    """
    if backbone_px is None or len(backbone_px) < 5:
        return np.zeros((0, 4, 4)), None
    C = fit_conic(np.asarray(backbone_px, dtype=float))
    if C is None:
        return np.zeros((0, 4, 4)), None
    K = np.asarray(K, dtype=float)
    rays = np.linalg.solve(K, np.concatenate([backbone_px, np.ones((len(backbone_px), 1))], axis=1).T).T
    a_mid = 0.5 * (tail_angle_rad + tip_angle_rad)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (centre, normal, midpoint direction) per pose
    for c, n in circle_poses_from_conic(C, K, radius_m):
        q = _rays_to_plane(rays, c, n) - c
        b1 = q[0] - (q[0] @ n) * n
        b1 = b1 / np.linalg.norm(b1)
        b2 = cross(n, b1)
        ang = np.sort(np.mod(np.arctan2(q @ b2, q @ b1), 2 * np.pi))
        gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
        g = int(np.argmax(gaps))
        start = ang[(g + 1) % len(ang)]  # the occupied range runs from the gap's end ...
        mid = start + 0.5 * (2 * np.pi - gaps[g])  # ... over 2 pi - gap
        m = np.cos(mid) * b1 + np.sin(mid) * b2
        rows += [(c, s * n, m) for s in (1.0, -1.0)]
    if not rows:
        return np.zeros((0, 4, 4)), C
    # all poses in one call: pose_on_circle works row by row (the same bits as one call per pose)
    centres, normals, mids = (np.stack(a) for a in zip(*rows, strict=True))
    return pose_on_circle(centres, normals, mids, a_mid), C


def near(T_a: np.ndarray, T_b: np.ndarray, separation: tuple[float, float] = DEFAULT_SEPARATION) -> np.ndarray:
    """``(A, B)`` True where pose ``a`` is within ``separation`` (rotation rad, centre m) of pose ``b``."""
    A, B = as_pose_batch(T_a), np.asarray(T_b, dtype=float).reshape(-1, 4, 4)
    if A.shape[0] == 0 or B.shape[0] == 0:
        return np.zeros((A.shape[0], B.shape[0]), dtype=bool)
    Rrel = np.swapaxes(A[:, None, :3, :3], -1, -2) @ B[None, :, :3, :3]
    cos = np.clip((np.trace(Rrel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    dist = np.linalg.norm(A[:, None, :3, 3] - B[None, :, :3, 3], axis=-1)
    return (np.arccos(cos) < separation[0]) & (dist < separation[1])


def dedupe(T: np.ndarray, existing: np.ndarray | None = None,
           separation: tuple[float, float] = DEFAULT_SEPARATION) -> np.ndarray:
    """Indices of the poses to keep, in order: the first of each cluster, none near an ``existing`` pose.

    Greedy in order: pose ``i`` is kept unless it is :func:`near` an ``existing`` pose or a pose kept before it.
    Every pair is tested in one :func:`near` call (the same per-pair products, bit for bit, as one call per pose;
    ``tests/test_proposals.py`` pins it to that loop): per-call overhead, not arithmetic, was the cost (~15 poses).
    """
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    E = np.zeros((0, 4, 4)) if existing is None else np.asarray(existing, dtype=float).reshape(-1, 4, 4)
    close = near(T, np.concatenate([E, T]), separation)  # (n, e + n)
    by_existing = close[:, :E.shape[0]].any(axis=1).tolist()
    among = close[:, E.shape[0]:].tolist()
    kept: list[int] = []
    for i in range(T.shape[0]):
        if not by_existing[i] and not any(among[i][k] for k in kept):
            kept.append(i)
    return np.asarray(kept, dtype=int)


def mode_proposals(cam_T_mode: np.ndarray, lik: FrameLikelihood, existing: np.ndarray | None = None,
                   separation: tuple[float, float] = DEFAULT_SEPARATION, frame_ellipse: bool = True) -> np.ndarray:
    """Distinct proposals ``(P, 4, 4)`` for one mode on one frame (unpolished; every one keeps its ellipse exactly).

    The mode's three flips, its twin and the twin's flips, and (``frame_ellipse``) both circles of
    the frame's fitted ellipse with their flips. Poses within ``separation`` of the mode, of one
    of ``existing`` (other modes already held, ``(M, 4, 4)``) or of an earlier proposal are dropped.
    """
    nd, K = lik.model.needle, lik.model.camera.K
    T = as_pose_batch(cam_T_mode)[:1]
    ta, pa = nd.tail_angle_rad, nd.tip_angle_rad
    base = [T, twin_poses(T, K, nd.radius_m, ta, pa)]
    if frame_ellipse:
        base.append(frame_ellipse_poses(lik.observation.backbone_px, K, nd.radius_m, ta, pa)[0])
    B = np.concatenate(base)
    cands = np.concatenate([B[1:], arc_flips(B, ta, pa).reshape(-1, 4, 4)])
    ref = T if existing is None else np.concatenate([T, np.asarray(existing, dtype=float).reshape(-1, 4, 4)])
    return cands[dedupe(cands, ref, separation)]


# ----------------------------------------------------------------------------- polishing


def prior_energy(cam_T_needle: np.ndarray, cam_T_mean: np.ndarray | None, info: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Window prior ``1/2 r^T Lambda r``, ``r = Log(mu^-1 T)``: value (N,), gradient (N, 6), GN Hessian (N, 6, 6).

    ``cam_T_mean`` is ``(4, 4)`` or ``(N, 4, 4)``, ``info`` = ``Lambda`` ``(6, 6)`` or ``(N, 6, 6)``;
    either None means no prior (zeros).
    """
    T = as_pose_batch(cam_T_needle)
    N = T.shape[0]
    if cam_T_mean is None or info is None:
        return np.zeros(N), np.zeros((N, 6)), np.zeros((N, 6, 6))
    r = local(np.broadcast_to(np.asarray(cam_T_mean, dtype=float), T.shape), T)
    J = se3_right_jacobian_inv(r)  # exact d r / d xi, as in factors.residuals.pose_prior_residual
    L = np.broadcast_to(np.asarray(info, dtype=float), (N, 6, 6))
    Lr = (L @ r[:, :, None])[:, :, 0]
    JT = np.swapaxes(J, 1, 2)
    return 0.5 * np.sum(r * Lr, axis=1), (JT @ Lr[:, :, None])[:, :, 0], JT @ L @ J


def polish_with_prior(lik: FrameLikelihood, cam_T_needle: np.ndarray, cam_T_mean: np.ndarray | None = None,
                      info: np.ndarray | None = None, iters: int = 10
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Damped Gauss-Newton (Levenberg-Marquardt) on ``frame nll + window prior``, batched over poses.

    Returns the polished poses ``(N, 4, 4)``, their energy ``E (N,)`` and the Gauss-Newton
    information ``H (N, 6, 6)`` at the result (the inputs of :func:`laplace_log_evidence`).
    """
    T = as_pose_batch(cam_T_needle).copy()
    N = T.shape[0]

    def energy(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nll, g, H = lik.gauss_newton(X)
        pe, pg, pH = prior_energy(X, cam_T_mean, info)
        return nll + pe, g + pg, H + pH

    E, g, H = energy(T)
    lam = np.full(N, 1e-3)
    for _ in range(iters):
        diag = np.einsum("nii->ni", H)
        A = H + lam[:, None, None] * (diag[:, :, None] * np.eye(6) + 1e-12 * np.eye(6))
        try:
            step = -np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        step = np.where(np.isfinite(step), step, 0.0)
        Tn = T @ se3_exp(step)
        En, gn, Hn = energy(Tn)
        better = En < E
        T = np.where(better[:, None, None], Tn, T)
        E, g, H = np.where(better, En, E), np.where(better[:, None], gn, g), np.where(better[:, None, None], Hn, H)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return T, E, H


def rigid_map(cam_T_from: np.ndarray, cam_T_to: np.ndarray) -> np.ndarray:
    """The camera-frame rigid map ``G = T_to T_from^-1`` that carries a mode (and its history) onto a proposal."""
    return np.asarray(cam_T_to, dtype=float) @ se3_inverse(np.asarray(cam_T_from, dtype=float))
