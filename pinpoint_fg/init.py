"""Seeding hypotheses: every plausible mode, not one guess plus noise (DESIGN.md §Inference).

Candidates are generated from whatever the frame offers, then all are scored with the frame's
likelihood (:class:`pinpoint_fg.likelihood.FrameLikelihood`) and polished by a few batched
Gauss-Newton steps; distinct low-cost modes are kept and the particles are spread over them.

* **Ellipse** (backbone pixels): fit a conic to the pixels, back-project it to the cone
  ``Q = K^T C K`` and take the classic two-fold closed form: with ``Q``'s eigenvalues ordered
  ``l1 >= l2 > 0 > l3`` (eigenvectors e1, e2, e3), the planes cutting the cone in a circle have
  normals ``n = ±sqrt((l1-l2)/(l1-l3)) e1 + sqrt((l2-l3)/(l1-l3)) e3``; the circle's centre
  and distance follow from the radius. The in-plane angle (where the arc lies on the circle)
  is swept on a grid, and both normal orientations are kept.
* **Grasp** (kinematics): the needle passes through the grasp point ``p_g`` with its tangent
  there perpendicular to the grasper axis ``z_g``; the tangent's direction in the plane
  ``⟂ z_g`` and the needle plane's rotation about that tangent are swept on a grid.
* **Fallback** (no mask, no kinematics): keypoints alone, or nothing — a fronto-parallel needle
  at ``default_depth_m`` swept over in-plane angle and tilt, with a wide spread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.lie import cross, homogeneous, local, se3_exp
from factors.residuals import needle_image_conic
from pinpoint_fg.conic_fit import fit_conic
from pinpoint_fg.likelihood import FrameLikelihood, batched_gauss_newton, batched_nll
from pinpoint_fg.stein import floor_hessians


@dataclass(frozen=True)
class InitConfig:
    """Settings of the seeding."""

    angle_steps: int = 36
    """Grid resolution of each swept angle (36 -> 10 degrees)."""
    polish_iters: int = 6
    """Batched Gauss-Newton steps applied to every candidate before choosing modes."""
    max_modes: int = 8
    """At most this many distinct modes receive particles (the two circle poses, each possibly
    flipped about the grasp point when no keypoint tells tip from tail, plus near-ties)."""
    mode_nll_margin: float = 80.0
    """A mode is kept if its cost is within this of the best (nats of the frame's NLL after the polish).

    Wide on purpose: the window, not the seeding, rules modes out. The costs here come after ``polish_iters``
    Gauss-Newton steps from a 10 deg grid, not at the peaks (on held-out slow-02's first frame, candidates 318 and
    515 nats behind polish to 30 and 0 in 40 steps), and a mask's pixels are counted as independent, which
    overstates what one frame says (*Mask noise models* in the README). The tracker's transport and Laplace
    evidence then prune at ``SvnSettings.prune_nll`` (30 nats). Measured (thirty-second round,
    ``scripts/svn_settings_ab.py init.mode_nll_margin 25 80``, SVN on 88 runs: the nine scenarios at seeds 1-4,
    drive / kinfault / snapshots / symmetric at 5-8, and the held-out geometry at 1-4): 25 dropped held-out
    slow-02's true mode (30.2 nats behind a turn about the tip-tail chord at seeding; every tracker then stayed
    72 deg off for the whole run); 80 keeps it (2.7 deg). Held-out snapshots 65.2 -> 39.3 deg (mean of 4 seeds;
    one run lost, one rescued: ties between two equally weighted modes), every other scenario within 0.1 deg and
    0.01 mm on both geometries but paper snapshots (18.2 -> 18.4 deg over 8 seeds), CPU 1.00x. On the held-out
    geometry's seeds 5-8 (36 runs it was not chosen on) likewise: snapshots 117.1 -> 104.9 deg (one lost, one
    rescued), the rest within 0.1 deg, CPU 0.96x. 50 gave the same outcomes on the runs 80 changed; unbounded (only
    ``max_modes``) moved snapshots both ways."""
    mode_separation: tuple[float, float] = (np.deg2rad(15.0), 3e-3)
    """Two candidates closer than (rotation rad, translation m) belong to one mode."""
    spread_sigma: tuple[float, ...] = (np.deg2rad(3.0),) * 3 + (0.5e-3,) * 3
    """Per-axis Gaussian spread of the particles around their mode, [omega x3 (rad), v x3 (m)]."""
    default_depth_m: float = 0.05
    """Depth of the fallback fronto-parallel needle when there is no mask and no kinematics."""


def circle_poses_from_conic(C: np.ndarray, K: np.ndarray, radius_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The two 3-D circles of radius ``radius_m`` whose image is conic ``C``: ``[(centre (3,), normal (3,))]``.

    Normals point away from the camera's side of the plane flipped to ``n_z > 0``; empty when
    the conic is not an ellipse seen from the front.
    """
    Q = K.T @ C @ K
    Q = 0.5 * (Q + Q.T)
    w, V = np.linalg.eigh(Q)
    if np.sum(w > 0) == 1:
        Q, w = -Q, -w[::-1]
        V = V[:, ::-1]
    if not (np.sum(w > 0) == 2 and np.sum(w < 0) == 1):
        return []
    order = np.argsort(w)[::-1]  # l1 >= l2 > 0 > l3
    l1, l2, l3 = w[order]
    e1, e2, e3 = V[:, order[0]], V[:, order[1]], V[:, order[2]]
    a = np.sqrt(max(l1 - l2, 0.0) / (l1 - l3))
    c = np.sqrt(max(l2 - l3, 0.0) / (l1 - l3))
    out = []
    for sgn in (1.0, -1.0):
        n = sgn * a * e1 + c * e3
        n /= np.linalg.norm(n)
        # intersect the cone with the plane n.X = 1: X = n + u1 s + u2 t
        u1 = e2 - (e2 @ n) * n
        u1 /= np.linalg.norm(u1)
        u2 = cross(n, u1)  # np.cross's formula, bit for bit, at a fraction of its per-call cost
        B = np.stack([u1, u2, n], axis=1)  # (3, 3): X = B [s, t, 1]
        M = B.T @ Q @ B
        A2 = M[:2, :2]
        try:
            ctr = -np.linalg.solve(A2, M[:2, 2])
        except np.linalg.LinAlgError:
            continue
        rho2 = (ctr @ A2 @ ctr - M[2, 2]) / np.mean(np.diag(A2))
        if not np.isfinite(rho2) or rho2 <= 0:
            continue
        dist = radius_m / np.sqrt(rho2)
        centre = dist * (B @ np.r_[ctr, 1.0])
        if centre[2] < 0:
            centre = -centre
        nn = n if n[2] > 0 else -n
        out.append((centre, nn))
    return out


def _frame_from_normal(normal: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    n = normal / np.linalg.norm(normal)
    x = x_hint - (x_hint @ n) * n
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(n, [1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.cross(n, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1)




def ellipse_candidates(lik: FrameLikelihood, steps: int) -> np.ndarray:
    """Candidate poses ``(C, 4, 4)`` from the frame's backbone pixels (empty when unusable)."""
    obs = lik.observation
    if obs.backbone_px is None:
        return np.zeros((0, 4, 4))
    C = fit_conic(obs.backbone_px)
    if C is None:
        return np.zeros((0, 4, 4))
    out = []
    ang = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    for centre, normal in circle_poses_from_conic(C, lik.model.camera.K, lik.model.needle.radius_m):
        for nrm in (normal, -normal):
            R0 = _frame_from_normal(nrm, np.array([1.0, 0.0, 0.0]))
            Rz = np.zeros((steps, 3, 3))
            Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = np.cos(ang), -np.sin(ang), np.sin(ang), np.cos(ang)
            Rz[:, 2, 2] = 1.0
            out.append(homogeneous(R0 @ Rz, np.broadcast_to(centre, (steps, 3))))
    return np.concatenate(out, axis=0) if out else np.zeros((0, 4, 4))


def grasp_candidates(lik: FrameLikelihood, steps: int) -> np.ndarray:
    """Candidate poses from the grasp point and grasper axis (empty without kinematics)."""
    obs = lik.observation
    if obs.cam_T_grasper is None:
        return np.zeros((0, 4, 4))
    nd = lik.model.needle
    pg, zg = obs.cam_T_grasper[:3, 3], obs.cam_T_grasper[:3, 2]
    zg = zg / np.linalg.norm(zg)
    b1 = _frame_from_normal(zg, np.array([1.0, 0.0, 0.0]))[:, 0]
    b2 = np.cross(zg, b1)
    a = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    beta = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    A, Bt = np.meshgrid(a, beta, indexing="ij")
    A, Bt = A.ravel(), Bt.ravel()
    tang = np.cos(A)[:, None] * b1 + np.sin(A)[:, None] * b2  # camera-frame tangent at the grasp point
    # needle normal: rotate z_g about the tangent by beta (z_g is perpendicular to the tangent)
    w = np.cross(tang, zg)
    nrm = np.cos(Bt)[:, None] * zg + np.sin(Bt)[:, None] * w
    # needle frame: its tangent at theta_g is (-sin, cos, 0), the radial (cos, sin, 0)
    radial = np.cross(tang, nrm)  # tangent x normal = outward radial for a counter-clockwise arc
    th = nd.grasp_angle_rad
    ex = np.cos(th) * radial - np.sin(th) * tang
    ey = np.sin(th) * radial + np.cos(th) * tang
    R = np.stack([ex, ey, nrm], axis=2)
    t = pg - nd.radius_m * radial
    return homogeneous(R, t)


def fallback_candidates(lik: FrameLikelihood, steps: int, depth_m: float) -> np.ndarray:
    """Fronto-parallel-ish needles at ``depth_m`` swept over in-plane angle and two tilts."""
    obs = lik.observation
    K = lik.model.camera.K
    pts = [p for p in (obs.tip_px, obs.tail_px) if p is not None]
    centre_px = np.mean(pts, axis=0) if pts else K[:2, 2]
    ray = np.linalg.solve(K, np.r_[centre_px, 1.0])
    centre = depth_m * ray / ray[2]
    out = []
    ang = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    for tilt in (0.0, np.deg2rad(40.0), -np.deg2rad(40.0)):
        for axis in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)):
            R0 = se3_exp(np.r_[np.asarray(axis) * tilt, 0, 0, 0])[:3, :3]
            Rz = se3_exp(np.stack([np.zeros(steps), np.zeros(steps), ang, *np.zeros((3, steps))], axis=1))[:, :3, :3]
            out.append(homogeneous(R0 @ Rz, np.broadcast_to(centre, (steps, 3))))
    return np.concatenate(out, axis=0)


def polish(lik: FrameLikelihood, T: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """A few damped Gauss-Newton steps on every candidate (batched); returns poses and their nll.

    The candidates (1440 with a mask and kinematics) are evaluated in cache-sized batches
    (:func:`~pinpoint_fg.likelihood.batched_gauss_newton`, :func:`~pinpoint_fg.likelihood.batched_nll`): all at
    once, the conic's temporaries were tens of MB and an evaluation took ~1.5x as long. The last step's trial is
    scored by its nll alone: no step follows, so its gradient and information would go unused, and building them is
    ~85 % of an evaluation (1440 candidates x 200 px: 70 ms with, 11 ms without). ``lik.nll`` equals
    ``lik.gauss_newton``'s nll bit for bit (``tests/test_likelihood.py``); a non-finite nll, which ``batched_nll``
    reads as ``+inf``, is never an improvement either way.
    """
    lam = np.full(T.shape[0], 1e-3)
    nll, g, H = batched_gauss_newton(lik, T)
    for k in range(iters):
        Hf, _ = floor_hessians(H, eps=1e-6)
        diag = np.einsum("nii->ni", Hf)
        A = Hf + lam[:, None, None] * diag[:, :, None] * np.eye(6)
        step = -np.linalg.solve(A, g[..., None])[..., 0]
        Tn = T @ se3_exp(step)
        last = k == iters - 1
        if last:
            nll_n = batched_nll(lik, Tn)
        else:
            nll_n, g_n, H_n = batched_gauss_newton(lik, Tn)
        better = nll_n < nll
        T = np.where(better[:, None, None], Tn, T)
        nll = np.where(better, nll_n, nll)
        if last:
            break
        g = np.where(better[:, None], g_n, g)
        H = np.where(better[:, None, None], H_n, H)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return T, nll


def select_modes(T: np.ndarray, nll: np.ndarray, cfg: InitConfig) -> tuple[np.ndarray, np.ndarray]:
    """Greedy: best candidates first, skip those within ``mode_separation`` of a kept one."""
    order = np.argsort(nll)
    kept: list[int] = []
    for i in order:
        if nll[i] > nll[order[0]] + cfg.mode_nll_margin or len(kept) >= cfg.max_modes:
            break
        if kept:
            xi = local(T[kept], np.broadcast_to(T[i], (len(kept), 4, 4)))
            near = (np.linalg.norm(xi[:, :3], axis=1) < cfg.mode_separation[0]) & (
                np.linalg.norm(T[kept, :3, 3] - T[i, :3, 3], axis=1) < cfg.mode_separation[1]
            )
            if near.any():
                continue
        kept.append(int(i))
    return T[kept], nll[kept]


def seed_particles(
    lik: FrameLikelihood, n_particles: int, rng: np.random.Generator, cfg: InitConfig = InitConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Seed ``n_particles`` poses ``(N, 4, 4)`` over every plausible mode of one frame; also return the modes.

    Particles are split evenly between the kept modes (the first mode gets the remainder)
    and spread by ``cfg.spread_sigma`` in each mode's right tangent space.
    """
    steps = cfg.angle_steps
    cands = [ellipse_candidates(lik, steps), grasp_candidates(lik, steps)]
    C = np.concatenate(cands, axis=0)
    if C.shape[0] == 0:
        C = fallback_candidates(lik, steps, cfg.default_depth_m)
    C, nll = polish(lik, C, cfg.polish_iters)
    finite = np.isfinite(nll)
    C, nll = C[finite], nll[finite]
    if C.shape[0] == 0:
        C = fallback_candidates(lik, steps, cfg.default_depth_m)
        nll = lik.nll(C)
    modes, _ = select_modes(C, nll, cfg)
    modes = modes[: max(1, int(n_particles))]  # fewer particles than modes: keep the best ones
    m = modes.shape[0]
    counts = np.full(m, n_particles // m)
    counts[0] += n_particles - counts.sum()
    base = np.repeat(modes, counts, axis=0)
    noise = rng.normal(size=(n_particles, 6)) * np.asarray(cfg.spread_sigma)
    noise[np.cumsum(np.r_[0, counts[:-1]])] = 0.0  # one particle sits exactly on each mode
    return base @ se3_exp(noise), modes


def image_conic(cam_T_needle: np.ndarray, K: np.ndarray, radius_m: float) -> np.ndarray:
    """The needle circle's image conic at one pose, unit norm (:func:`factors.residuals.needle_image_conic`)."""
    return needle_image_conic(cam_T_needle, K, radius_m)[0]
