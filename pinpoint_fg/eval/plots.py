"""Figures of the evaluation (paper Figs. 4-7), drawn with matplotlib's Agg canvas into PNG files.

Every function takes plain arrays (no result objects) and writes one PNG; nothing here touches
pyplot's global state, so figures can be drawn from any thread or process.

* :func:`error_distributions` — per recording, the translation and rotation error of every
  method as a half-violin with the frames scattered beside it and the median as a white dot;
  below each panel a stacked bar per method with the share of each camera axis (X, Y, Z) in
  the mean per-axis error (paper Fig. 4).
* :func:`error_over_time` — translation and rotation error of one result over time with the
  predicted q95 band, the accuracy floor, bimodal frames, and the occlusion level (Fig. 7).
* :func:`particle_cloud` — particle sets of one frame in the scaled tangent space at the MAP
  (1 mm, 5°), projected onto their two principal directions, with the two GMM components'
  2-sigma ellipses, the MAP and the truth (Fig. 6).
* :func:`mode_weights_over_time` — the sorted mode weights of one result per frame, stacked.
* :func:`ablation_bars` — relative change of mean translation and rotation error of every
  ablation against the full model (Fig. 5).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from pinpoint_fg.posterior.bimodality import BimodalityVerdict, principal_plane

AXIS_COLOURS = ("#1b9e77", "#d95f02", "#7570b3")
"""X (green), Y (orange), Z (purple), as in the paper."""
METHOD_COLOURS = (
    "#3b75af", "#e377c2", "#8c8c8c", "#2ca02c", "#ff7f0e", "#9467bd", "#17becf", "#bcbd22", "#d62728",
)
"""Colours cycled over methods."""
OCCLUSION_LEVEL = {"none": 0, "partial": 1, "heavy": 2}
"""Occlusion label -> plotted level."""


@dataclass(frozen=True)
class MethodErrors:
    """One method's per-frame errors on one recording (frames with ground truth)."""

    label: str
    """Legend / tick label."""
    trans_mm: np.ndarray
    """(F,) translation error, mm."""
    rot_deg: np.ndarray
    """(F,) rotation error, degrees."""
    trans_axes_mm: np.ndarray
    """(F, 3) per-axis translation error magnitudes, mm."""
    rot_axes_deg: np.ndarray
    """(F, 3) per-axis rotation error magnitudes, degrees."""


@dataclass(frozen=True)
class CloudPanel:
    """One particle set to draw in :func:`particle_cloud`."""

    label: str
    """Panel title (method)."""
    scaled_xi: np.ndarray
    """(N, 6) particles in the scaled tangent space at the MAP, ``[omega / 5 deg; v / 1 mm]``."""
    verdict: BimodalityVerdict
    """The bimodality verdict of the set (GMM means/covariances in the same space)."""


def _save(fig: Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def _half_violin(ax, values: np.ndarray, pos: float, colour: str, rng: np.random.Generator) -> None:  # noqa: ANN001
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return
    if v.size >= 2 and np.std(v) > 0:
        parts = ax.violinplot([v], positions=[pos], widths=0.8, showextrema=False)
        for body in parts["bodies"]:
            verts = body.get_paths()[0].vertices
            verts[:, 0] = np.clip(verts[:, 0], pos, np.inf)
            body.set_facecolor(colour)
            body.set_edgecolor("black")
            body.set_linewidth(0.5)
            body.set_alpha(0.6)
    x = pos - 0.06 - 0.22 * rng.random(v.size)
    ax.scatter(x, v, s=4, color=colour, alpha=0.5, linewidths=0)
    ax.scatter([pos], [np.median(v)], s=30, color="white", edgecolors="black", zorder=3)


def _axis_shares(axes_values: np.ndarray) -> np.ndarray:
    """(3,) share of each axis in the sum of the per-axis mean errors (NaN-safe; zeros if empty)."""
    a = np.asarray(axes_values, dtype=float).reshape(-1, 3)
    a = a[np.all(np.isfinite(a), axis=1)]
    if a.shape[0] == 0:
        return np.zeros(3)
    m = a.mean(axis=0)
    s = m.sum()
    return m / s if s > 0 else np.zeros(3)


def error_distributions(groups: Sequence[tuple[str, Sequence[MethodErrors]]], path: Path) -> Path:
    """Half-violins of translation / rotation errors per method, one column per recording (module doc).

    A method keeps its colour in every column.
    """
    ncol = max(len(groups), 1)
    most = max((len(m) for _, m in groups), default=1)
    fig = Figure(figsize=(max(4.2, 0.8 * most + 1.2) * ncol + 0.8, 9.0 if most > 3 else 8.0))
    gs = fig.add_gridspec(4, ncol, height_ratios=[3, 1, 3, 1], hspace=0.75 if most > 3 else 0.35, wspace=0.3)
    rng = np.random.default_rng(0)
    colour_of: dict[str, str] = {}
    for _, methods in groups:
        for m in methods:
            colour_of.setdefault(m.label, METHOD_COLOURS[len(colour_of) % len(METHOD_COLOURS)])
    for c, (title, methods) in enumerate(groups):
        pos = np.arange(len(methods), dtype=float)
        labels = [m.label for m in methods]
        panels = (
            ("trans_mm", "trans_axes_mm", "translation error (mm)"),
            ("rot_deg", "rot_axes_deg", "rotation error (deg)"),
        )
        for r, (key, axes_key, unit) in enumerate(panels):
            ax = fig.add_subplot(gs[2 * r, c])
            for i, m in enumerate(methods):
                _half_violin(ax, getattr(m, key), pos[i], colour_of[m.label], rng)
            ax.set_xticks(pos, [""] * len(methods))
            ax.set_xlim(-0.7, len(methods) - 0.2)
            ax.set_ylabel(unit, fontsize=8)
            ax.grid(axis="y", alpha=0.3)
            if r == 0:
                ax.set_title(title, fontsize=10)
            bx = fig.add_subplot(gs[2 * r + 1, c])
            bottom = np.zeros(len(methods))
            shares = np.array([_axis_shares(getattr(m, axes_key)) for m in methods]).reshape(-1, 3)
            for j, name in enumerate("XYZ"):
                bx.bar(pos, shares[:, j], bottom=bottom, color=AXIS_COLOURS[j], width=0.6, label=name)
                bottom += shares[:, j]
            if len(methods) > 3:
                bx.set_xticks(pos, labels, fontsize=7, rotation=30, ha="right", rotation_mode="anchor")
            else:
                bx.set_xticks(pos, labels, fontsize=8)
            bx.set_xlim(-0.7, len(methods) - 0.2)
            bx.set_ylim(0, 1)
            bx.set_ylabel("axis share", fontsize=7)
            bx.tick_params(labelsize=7)
            if c == ncol - 1 and r == 0:
                bx.legend(fontsize=6, ncol=3, loc="lower right", bbox_to_anchor=(1.0, 1.0), frameon=False)
    return _save(fig, path)


def error_over_time(
    t_s: np.ndarray,
    trans_mm: np.ndarray,
    rot_deg: np.ndarray,
    q95_trans_mm: np.ndarray,
    q95_rot_deg: np.ndarray,
    occlusion: Sequence[str | None],
    title: str,
    path: Path,
    bimodal: np.ndarray | None = None,
    floor_trans_mm: np.ndarray | None = None,
    floor_rot_deg: np.ndarray | None = None,
) -> Path:
    """Errors over time with the q95 band ``[0, q95]``, the floor, bimodal frames and occlusion (F,) each."""
    t = np.asarray(t_s, dtype=float)
    fig = Figure(figsize=(9.0, 6.0))
    gs = fig.add_gridspec(3, 1, height_ratios=[3, 3, 1], hspace=0.15)
    axes = [fig.add_subplot(gs[i]) for i in range(3)]
    for ax, err, q95, floor, colour, unit in (
        (axes[0], trans_mm, q95_trans_mm, floor_trans_mm, "#1f77b4", "translation (mm)"),
        (axes[1], rot_deg, q95_rot_deg, floor_rot_deg, "#ff7f0e", "rotation (deg)"),
    ):
        q = np.asarray(q95, dtype=float)
        ax.fill_between(t, 0.0, np.where(np.isfinite(q), q, np.nan), color=colour, alpha=0.18, step="mid",
                        label="predicted q95", linewidth=0)
        ax.plot(t, err, color=colour, linewidth=1.2, label="error")
        if floor is not None:
            ax.plot(t, floor, color="black", linewidth=0.8, linestyle=":", label="floor (MAP from truth)")
        if bimodal is not None and np.any(bimodal):
            b = np.asarray(bimodal, dtype=bool)
            e = np.asarray(err, dtype=float)
            ax.scatter(t[b], e[b], s=8, color="black", marker="|", label="bimodal", zorder=3)
        ax.set_ylabel(unit, fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelbottom=False)
        ax.set_ylim(bottom=0.0)
    axes[0].set_title(title, fontsize=10)
    axes[0].legend(fontsize=7, loc="upper right", ncol=4)
    levels = np.array([OCCLUSION_LEVEL.get(str(o), np.nan) if o is not None else np.nan for o in occlusion])
    ax = axes[2]
    if np.any(np.isfinite(levels)):
        ax.step(t, levels, where="mid", color="#7f7f7f")
        ax.fill_between(t, 0, np.nan_to_num(levels), step="mid", color="#7f7f7f", alpha=0.3, linewidth=0)
    else:
        ax.text(0.5, 0.5, "occlusion not labelled", transform=ax.transAxes, ha="center", va="center",
                fontsize=8)
    ax.set_yticks([0, 1, 2], ["none", "partial", "heavy"], fontsize=7)
    ax.set_ylim(-0.2, 2.3)
    ax.set_xlabel("time (s)", fontsize=9)
    ax.grid(alpha=0.3)
    lo, hi = (float(t.min()), float(t.max())) if t.size else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    for a in axes:
        a.set_xlim(lo, hi)
    return _save(fig, path)


def _ellipse(ax, mean2: np.ndarray, cov2: np.ndarray, colour: str, label: str | None) -> None:  # noqa: ANN001
    w, V = np.linalg.eigh(0.5 * (cov2 + cov2.T))
    w = np.maximum(w, 1e-12)
    angle = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))
    e = Ellipse(tuple(mean2), 2 * 2.0 * np.sqrt(w[1]), 2 * 2.0 * np.sqrt(w[0]), angle=angle, fill=False,
                edgecolor=colour, linewidth=1.5, label=label)
    ax.add_patch(e)


def particle_cloud(panels: Sequence[CloudPanel], title: str, path: Path) -> Path:
    """Particle sets of one frame in their principal tangent plane with GMM ellipses, MAP and truth."""
    n = max(len(panels), 1)
    fig = Figure(figsize=(4.4 * n, 4.4))
    for i, p in enumerate(panels):
        ax = fig.add_subplot(1, n, i + 1)
        X = np.asarray(p.scaled_xi, dtype=float)
        B = principal_plane(X)
        Y = X @ B.T
        ax.scatter(Y[:, 0], Y[:, 1], s=6, color="#555555", alpha=0.5, linewidths=0, label="particles")
        v = p.verdict
        for k in range(2):
            if v.weights[k] <= 0:
                continue
            colour = "#d62728" if k == v.dominant else "#1f77b4"
            _ellipse(ax, B @ v.means[k], B @ v.covariances[k] @ B.T, colour, f"GMM w={v.weights[k]:.2f}")
        ax.scatter([0.0], [0.0], marker="x", s=60, color="black", label="MAP", zorder=4)
        if v.gt_xi_scaled is not None:
            g = B @ v.gt_xi_scaled
            ax.scatter([g[0]], [g[1]], marker="*", s=120, color="#2ca02c", edgecolors="black", label="truth",
                       zorder=5)
        verdict = "bimodal" if v.bimodal else f"unimodal ({v.reason})"
        ax.set_title(f"{p.label}: {verdict}, D = {v.ashman_d:.1f}", fontsize=9)
        ax.set_xlabel("PC 1 (1 mm ~ 5 deg units)", fontsize=8)
        ax.set_ylabel("PC 2", fontsize=8)
        ax.grid(alpha=0.3)
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=6, loc="best")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def ablation_bars(
    names: Sequence[str], trans_mm: np.ndarray, rot_deg: np.ndarray, title: str, path: Path,
    reference: int | None = 0,
) -> Path:
    """Mean errors of ablations: change relative to ``names[reference]`` in %, or absolute when None."""
    t = np.asarray(trans_mm, dtype=float)
    r = np.asarray(rot_deg, dtype=float)
    x = np.arange(len(names), dtype=float)
    fig = Figure(figsize=(max(6.0, 0.9 * len(names) + 2.0), 4.2))
    ax = fig.add_subplot(1, 1, 1)
    if reference is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t_rel = 100.0 * (t / t[reference] - 1.0)
            r_rel = 100.0 * (r / r[reference] - 1.0)
        ax.bar(x - 0.2, t_rel, width=0.4, color="#1f77b4", label="translation")
        ax.bar(x + 0.2, r_rel, width=0.4, color="#ff7f0e", label="rotation")
        ax.axhline(0.0, color="black", linewidth=0.8)
        ax.set_ylabel(f"mean error change vs {names[reference]} (%)", fontsize=9)
    else:
        ax.bar(x - 0.2, t, width=0.4, color="#1f77b4", label="translation (mm)")
        ax2 = ax.twinx()
        ax2.bar(x + 0.2, r, width=0.4, color="#ff7f0e", label="rotation (deg)")
        ax.set_ylabel("mean translation error (mm)", fontsize=9)
        ax2.set_ylabel("mean rotation error (deg)", fontsize=9)
    ax.set_xticks(x, list(names), rotation=30, ha="right", fontsize=8)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(title, fontsize=10)
    fig.subplots_adjust(bottom=0.3)
    return _save(fig, path)


def mode_weights_over_time(t_s: np.ndarray, weights: np.ndarray, title: str, path: Path,
                           threshold: float = 0.1) -> Path:
    """Stacked per-frame sorted mode weights (F, K) over time (NaN rows: no modes, left blank).

    The bottom band is the dominant mode. The second mode's weight is also drawn as a black line,
    with the modes verdict's ``threshold`` dashed: frames where the line reaches it are bimodal.
    """
    t = np.asarray(t_s, dtype=float)
    W = np.asarray(weights, dtype=float)
    fig = Figure(figsize=(9.0, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    ok = np.isfinite(W[:, 0])
    Wm = np.where(ok[:, None], W, np.nan)
    bottom = np.zeros(len(t))
    colours = ("#3b75af", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")
    for k in range(W.shape[1]):
        top = bottom + np.nan_to_num(Wm[:, k])
        ax.fill_between(t, np.where(ok, bottom, np.nan), np.where(ok, top, np.nan), step="mid", linewidth=0,
                        color=colours[k % len(colours)], alpha=0.8, label=f"mode {k + 1}")
        bottom = top
    if W.shape[1] > 1:
        ax.step(t, np.where(ok, W[:, 1], np.nan), where="mid", color="black", linewidth=1.0,
                label="second mode's weight")
    ax.axhline(threshold, color="black", linestyle="--", linewidth=0.8, label=f"bimodal at >= {threshold:g}")
    ax.set_ylim(0.0, 1.0)
    ax.set_ylabel("mode weight", fontsize=9)
    ax.set_xlabel("time (s)", fontsize=9)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="center left", ncol=W.shape[1] + 2, framealpha=0.9)
    ax.grid(alpha=0.3)
    lo, hi = (float(t.min()), float(t.max())) if t.size else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    ax.set_xlim(lo, hi)
    fig.tight_layout()
    return _save(fig, path)
