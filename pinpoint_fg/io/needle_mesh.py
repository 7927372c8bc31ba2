"""A needle's circle from its 3D mesh: centre, normal, radius, the arc's two ends, which end is the tip.

Real needle models (e.g. a BOP dataset's ``models/obj_NNNNNN.ply``) are a wire — a tube around an
arc of a circle — in the model's own frame: the circle need not be centred at the model origin,
its plane need not be a coordinate plane, and its arc need not start at angle 0. This module
recovers the circle from the mesh vertices and the transform ``model_T_needle`` from the needle
frame of DESIGN.md (circle of radius ``r`` centred at the origin in the x-y plane, normal +z,
tail at θ = 0, tip at θ = arc angle, counter-clockwise about +z) to the model frame, so that
``cam_T_needle = cam_T_model @ model_T_needle``.

The fit (vertices ``V`` in metres, model frame):

1. **Plane**: SVD of the centred vertices; the right singular vector of the smallest singular
   value is the normal ``n``. The plane passes through the centroid. For a tube whose
   cross-section is symmetric about the centre line the vertex cloud is symmetric about the
   centre-line plane, so this is the centre-line plane (no further refinement is done).
2. **Circle in the plane**: the algebraic (Kåsa) fit of the in-plane coordinates, then
   Levenberg-Marquardt on the geometric distances ``|p_i - c| - r`` (``scipy.optimize.least_squares``).
   The vertices lie on a torus (the wire's surface), spread ``±w`` around the centre line in the
   plane; for a symmetric cross-section the geometric fit's radius is the centre line's.
3. **Cross-section**: each vertex's distance ``d_i = hypot(ρ_i − r, h_i)`` from the centre line
   (``ρ`` in-plane distance to the centre, ``h`` height above the plane). The mesh is accepted as
   a needle only when the 95th percentile of ``d`` is below :data:`MAX_TUBE_TO_RADIUS` × r (a thin
   tube around a circle); a cube, a sphere or a flat plate fail here. Wire diameter = 2 × median ``d``.
4. **Arc ends**: the vertices' angles about the centre; the largest circular gap between sorted
   angles is where there is no wire. It must be clearly the largest (≥ :data:`MIN_GAP_RATIO` ×
   the second largest, and ≥ 5°), otherwise the mesh is a closed ring with no ends. The ends are
   the extreme vertex angles (exact for flat end faces and for a tip that ends in a point).
5. **Tip**: the median cross-section radius of the vertices within
   ``max(4 × median d, 8 % of the arc length)`` of each end, relative to the median over the
   whole wire. The tip is the end that tapers: ratio below :data:`TAPER_RATIO` while the other end's
   is at least :data:`BLUNT_RATIO` (a rounded end cap shrinks only over one wire radius, which
   the zone's median ignores). When neither (or both) ends taper the mesh cannot tell, and the
   caller must name the tip end: ``tip_end = "+x"`` means "the end with the larger model x"
   (any of ``±x, ±y, ±z``). A ``tip_end`` contradicting a clear taper is an error, not a
   silent override.

Units: PLY vertices are in ``units`` (``"mm"``, the BOP convention, or ``"m"``) and are converted
to metres on reading. Malformed files and meshes that are not a needle raise
:class:`pinpoint_fg.errors.InputError` naming the file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from factors.geometry import NeedleModel
from factors.lie import homogeneous
from pinpoint_fg.errors import InputError, path_argument

#: Length units a PLY model may use, and their size in metres.
MODEL_UNITS: dict[str, float] = {"mm": 1e-3, "m": 1.0}

#: Tip-end names: the tip is the arc end with the larger coordinate along this model axis.
TIP_END_AXES: dict[str, np.ndarray] = {
    f"{sign}{axis}": (1.0 if sign == "+" else -1.0) * np.eye(3)[i]
    for i, axis in enumerate("xyz") for sign in "+-"
}

#: Largest accepted 95th percentile of the vertices' distance from the centre line, relative to r.
MAX_TUBE_TO_RADIUS = 0.25
#: The gap without wire must be at least this many times the second-largest angular gap.
MIN_GAP_RATIO = 3.0
#: Smallest accepted gap without wire, radians.
MIN_GAP_RAD = math.radians(5.0)
#: An end tapers when its zone's median cross-section is below this fraction of the wire's median.
TAPER_RATIO = 0.7
#: The other end must keep at least this fraction for the taper to be a clear verdict.
BLUNT_RATIO = 0.85
#: Fewest vertices accepted as a needle mesh.
MIN_VERTICES = 20


@dataclass(frozen=True)
class NeedleMeshFit:
    """The needle circle fitted to a mesh, in the model frame (metres)."""

    centre_m: np.ndarray
    """Circle centre ``(3,)``, model frame, metres."""
    normal: np.ndarray
    """Unit normal ``(3,)`` oriented so that going from the tail to the tip is counter-clockwise about it."""
    radius_m: float
    """Radius of the wire's centre line, metres."""
    wire_diameter_m: float
    """Wire diameter: twice the median distance of the vertices from the centre line, metres."""
    arc_angle_rad: float
    """Angle from the tail to the tip about ``normal``, radians, in (0, 2π)."""
    tail_m: np.ndarray
    """Centre-line point at the tail end ``(3,)``, model frame, metres."""
    tip_m: np.ndarray
    """Centre-line point at the tip end ``(3,)``, model frame, metres."""
    tip_from: str
    """How the tip was told from the tail: ``"taper"`` (the mesh) or ``"tip_end"`` (the caller)."""
    end_taper: tuple[float, float]
    """Median cross-section near (tail, tip) relative to the wire's median cross-section."""
    tube_p95_m: float
    """95th percentile of the vertices' distance from the fitted centre line, metres."""
    model_T_needle: np.ndarray
    """``(4, 4)``: needle frame of DESIGN.md -> model frame (origin = centre, x towards the tail, z = normal)."""

    def needle_model(self, grasp_angle_rad: float | None = None) -> NeedleModel:
        """The :class:`NeedleModel` (tail at 0, tip at the arc angle); grasp default: a third of the arc.

        The default grasp angle keeps the proportion of the project's default needle (grasp at
        π/4 of a 3π/4 arc); it only matters with grasper kinematics.
        """
        grasp = self.arc_angle_rad / 3.0 if grasp_angle_rad is None else float(grasp_angle_rad)
        return NeedleModel(radius_m=self.radius_m, tail_angle_rad=0.0, tip_angle_rad=self.arc_angle_rad,
                           grasp_angle_rad=grasp, wire_diameter_m=self.wire_diameter_m)

    def describe(self) -> str:
        """One line: radius, arc, wire, how the tip was chosen."""
        return (f"needle circle: radius {self.radius_m * 1e3:.4g} mm, arc {math.degrees(self.arc_angle_rad):.2f} deg, "
                f"wire {self.wire_diameter_m * 1e3:.3g} mm, centre {np.round(self.centre_m * 1e3, 4).tolist()} mm "
                f"(model frame), tip by {self.tip_from} (end taper tail/tip {self.end_taper[0]:.2f}/"
                f"{self.end_taper[1]:.2f})")


def read_ply_vertices(path: str | Path, units: str = "mm") -> np.ndarray:
    """Vertex positions ``(V, 3)`` in metres of an ascii or binary PLY file (``plyfile``).

    Raises :class:`InputError` naming the file for an unreadable or malformed file, a missing
    ``vertex`` element or ``x``/``y``/``z`` property, or non-finite coordinates.
    """
    from plyfile import PlyData

    path = path_argument("path", path)  # None was pathlib's TypeError; "" read the current directory
    if units not in MODEL_UNITS:
        raise InputError(f"unknown model units {units!r}; choose from {', '.join(MODEL_UNITS)}", file=path)
    if not path.is_file():
        raise InputError("file not found (the needle's PLY model)", file=path)
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # noqa: BLE001 - plyfile raises many types for malformed files
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"not a readable PLY file: {reason}", file=path) from None
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise InputError(f"no 'vertex' element (elements: {names})", file=path)
    vertex = ply["vertex"]
    props = [p.name for p in vertex.properties]
    missing = [c for c in "xyz" if c not in props]
    if missing:
        raise InputError(f"vertex element has no {'/'.join(missing)} property (properties: {props})", file=path)
    data = vertex.data
    V = np.stack([np.asarray(data[c], dtype=float) for c in "xyz"], axis=1)
    if not np.all(np.isfinite(V)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(V), axis=1))[0])
        raise InputError(f"vertex {bad} has a NaN or infinite coordinate", file=path)
    return V * MODEL_UNITS[units]


def _kasa(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Algebraic circle fit ``a² + b² + D a + E b + F = 0`` -> (cx, cy, r) (NaN r when degenerate)."""
    A = np.stack([a, b, np.ones_like(a)], axis=1)
    sol, *_ = np.linalg.lstsq(A, -(a * a + b * b), rcond=None)
    cx, cy = -0.5 * sol[0], -0.5 * sol[1]
    r2 = cx * cx + cy * cy - sol[2]
    return float(cx), float(cy), float(math.sqrt(r2)) if r2 > 0 else float("nan")


def _geometric_circle(a: np.ndarray, b: np.ndarray, start: tuple[float, float, float]) -> np.ndarray:
    """Levenberg-Marquardt on ``hypot(a - cx, b - cy) - r`` from ``start``; returns (cx, cy, r)."""

    def residual(p: np.ndarray) -> np.ndarray:
        return np.hypot(a - p[0], b - p[1]) - p[2]

    def jacobian(p: np.ndarray) -> np.ndarray:
        rho = np.maximum(np.hypot(a - p[0], b - p[1]), 1e-300)
        return np.stack([-(a - p[0]) / rho, -(b - p[1]) / rho, -np.ones_like(a)], axis=1)

    return least_squares(residual, np.asarray(start, dtype=float), jac=jacobian, method="lm",
                         xtol=1e-15, ftol=1e-15, gtol=1e-15).x


def fit_needle_mesh(vertices_m: np.ndarray, tip_end: str | None = None,
                    source: str | Path | None = None) -> NeedleMeshFit:
    """Fit the needle circle to mesh vertices ``(V, 3)`` in metres (module docstring for the method).

    ``tip_end`` (``"+x"``, ``"-y"``, …) names the tip when the mesh does not show a taper;
    ``source`` is the file named in errors. Raises :class:`InputError` when the vertices are not a
    thin tube around an open arc, when the tip cannot be told, or when ``tip_end`` is unusable.
    """
    V = np.asarray(vertices_m, dtype=float)
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"vertices must have shape (V, 3), got {V.shape}", file=source)
    if tip_end is not None and tip_end not in TIP_END_AXES:
        raise InputError(f"tip end {tip_end!r} is not one of {', '.join(TIP_END_AXES)}", file=source)
    V = np.unique(V, axis=0)  # duplicated vertices (split normals/UVs) must not weigh twice
    if V.shape[0] < MIN_VERTICES:
        raise InputError(f"not a needle mesh: only {V.shape[0]} distinct vertices (at least {MIN_VERTICES})",
                         file=source)
    centroid = V.mean(axis=0)
    X = V - centroid
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    n = Vt[2] / np.linalg.norm(Vt[2])
    e1 = Vt[0] / np.linalg.norm(Vt[0])
    e2 = np.cross(n, e1)
    a, b, h = X @ e1, X @ e2, X @ n
    start = _kasa(a, b)
    if not all(math.isfinite(v) for v in start):
        raise InputError("not a needle mesh: the vertices do not lie around a circle (degenerate circle fit)",
                         file=source)
    cx, cy, r = _geometric_circle(a, b, start)
    r = abs(float(r))
    extent = float(np.max(np.linalg.norm(X, axis=1)))
    if not (math.isfinite(r) and 0 < r < 1e3 * max(extent, 1e-300)):
        raise InputError("not a needle mesh: the vertices do not lie around a circle (degenerate circle fit)",
                         file=source)
    rho = np.hypot(a - cx, b - cy)
    d = np.hypot(rho - r, h)
    tube = float(np.percentile(d, 95))
    if tube > MAX_TUBE_TO_RADIUS * r:
        raise InputError(
            f"not a needle mesh: the vertices are not a thin wire around a circle (95 % of them within "
            f"{tube / r:.2f} x radius of the fitted circle, at most {MAX_TUBE_TO_RADIUS} expected)", file=source)
    psi = np.arctan2(b - cy, a - cx)
    order = np.sort(psi)
    gaps = np.diff(np.concatenate([order, [order[0] + 2 * math.pi]]))
    j = int(np.argmax(gaps))
    gap = float(gaps[j])
    second = float(np.partition(gaps, -2)[-2]) if gaps.size > 1 else 0.0
    if gap < MIN_GAP_RAD or gap < MIN_GAP_RATIO * second:
        raise InputError(
            f"not a needle mesh: the wire goes all around the circle (largest angular gap {math.degrees(gap):.1f} "
            f"deg, next {math.degrees(second):.1f} deg), so it has no ends", file=source)
    psi_s = float(order[(j + 1) % order.size])  # counter-clockwise (about n) start of the arc
    span = 2 * math.pi - gap
    u = np.mod(psi - psi_s, 2 * math.pi)  # position along the arc from the start, radians
    u = np.where(u > span + 0.5 * gap, u - 2 * math.pi, u)  # a vertex just before the start due to rounding
    w_med = float(np.median(d))
    if w_med <= 0:
        raise InputError("not a needle mesh: the wire has no thickness (vertices on the centre line)", file=source)
    zone = max(4.0 * w_med / r, 0.08 * span)
    ratio_s = float(np.median(d[u <= zone])) / w_med
    ratio_e = float(np.median(d[u >= span - zone])) / w_med
    centre = centroid + cx * e1 + cy * e2
    end_s = centre + r * (math.cos(psi_s) * e1 + math.sin(psi_s) * e2)
    psi_e = psi_s + span
    end_e = centre + r * (math.cos(psi_e) * e1 + math.sin(psi_e) * e2)
    tapered = None
    if ratio_s < TAPER_RATIO and ratio_e >= BLUNT_RATIO:
        tapered = "start"
    elif ratio_e < TAPER_RATIO and ratio_s >= BLUNT_RATIO:
        tapered = "end"
    if tip_end is not None:
        axis = TIP_END_AXES[tip_end]
        diff = float(axis @ (end_e - end_s))
        if abs(diff) < 0.05 * r:
            raise InputError(
                f"tip end {tip_end}: the arc's two ends are nearly level along that axis "
                f"({abs(diff) * 1e3:.3g} mm apart); name another axis", file=source)
        chosen = "end" if diff > 0 else "start"
        if tapered is not None and chosen != tapered:
            raise InputError(
                f"tip end {tip_end} names the blunt end, but the mesh tapers at the other end "
                f"(cross-section near the ends {ratio_s:.2f} and {ratio_e:.2f} of the median)", file=source)
        tip_at, tip_from = chosen, "tip_end"
    elif tapered is None:
        raise InputError(
            f"cannot tell the tip from the tail: neither end of the wire clearly tapers (cross-section near the "
            f"ends {ratio_s:.2f} and {ratio_e:.2f} of the median); name the tip end (--tip-end "
            f"{'|'.join(TIP_END_AXES)}: the end with the larger coordinate along that model axis)", file=source)
    else:
        tip_at, tip_from = tapered, "taper"
    if tip_at == "end":  # tail at the start, tip counter-clockwise about n
        z, tail, tip, taper = n, end_s, end_e, (ratio_s, ratio_e)
    else:  # tail at the end: counter-clockwise about -n from it reaches the start
        z, tail, tip, taper = -n, end_e, end_s, (ratio_e, ratio_s)
    x = (tail - centre) / np.linalg.norm(tail - centre)
    y = np.cross(z, x)
    model_T_needle = homogeneous(np.stack([x, y, z], axis=1), centre)
    return NeedleMeshFit(
        centre_m=centre, normal=z.copy(), radius_m=r, wire_diameter_m=2.0 * w_med, arc_angle_rad=span,
        tail_m=tail, tip_m=tip, tip_from=tip_from, end_taper=(float(taper[0]), float(taper[1])), tube_p95_m=tube,
        model_T_needle=model_T_needle,
    )
