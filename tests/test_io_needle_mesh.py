"""The needle circle fitted to a PLY mesh against the mesh's known construction."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from factors.lie import homogeneous, local, so3_exp
from pinpoint_fg.errors import InputError
from pinpoint_fg.io.needle_mesh import fit_needle_mesh, read_ply_vertices
from tests.bop_scene import tube_mesh, write_ply

# float32 PLY coordinates of ~8 mm carry ~5e-10 m of rounding: the fit must be that good.
TOL_M = 2e-9
TOL_RAD = 2e-7


def assert_fit_matches(fit, truth, model_T_needle: np.ndarray) -> None:
    """``fit`` is the circle of ``truth`` with the needle frame ``model_T_needle`` (tail at 0, tip at the arc)."""
    T = model_T_needle
    assert fit.radius_m == pytest.approx(truth.radius_m, abs=TOL_M)
    assert fit.arc_angle_rad == pytest.approx(truth.arc_rad, abs=TOL_RAD)
    np.testing.assert_allclose(fit.centre_m, T[:3, 3], atol=TOL_M)
    np.testing.assert_allclose(fit.normal, T[:3, 2], atol=TOL_RAD)
    tail = T[:3, :3] @ truth.needle.tail_m + T[:3, 3]
    tip = T[:3, :3] @ truth.needle.point(truth.arc_rad) + T[:3, 3]
    np.testing.assert_allclose(fit.tail_m, tail, atol=TOL_M)
    np.testing.assert_allclose(fit.tip_m, tip, atol=TOL_M)
    xi = local(T, fit.model_T_needle)
    assert np.linalg.norm(xi[:3]) < TOL_RAD and np.linalg.norm(xi[3:]) < TOL_M


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_fit_recovers_the_construction(tmp_path: Path, text: bool) -> None:
    verts, faces, truth = tube_mesh()
    path = write_ply(tmp_path / "needle.ply", verts, faces, text=text)
    fit = fit_needle_mesh(read_ply_vertices(path, "mm"), source=path)
    assert_fit_matches(fit, truth, truth.model_T_needle)
    assert fit.tip_from == "taper"
    assert fit.wire_diameter_m == pytest.approx(2 * truth.wire_m, rel=1e-6)
    assert fit.end_taper[0] > 0.95 and fit.end_taper[1] < 0.5
    needle = fit.needle_model()
    assert needle.tail_angle_rad == 0.0 and needle.tip_angle_rad == fit.arc_angle_rad
    assert needle.grasp_angle_rad == pytest.approx(fit.arc_angle_rad / 3)
    # the needle frame's tip, mapped into the model, is the mesh's tip
    np.testing.assert_allclose(fit.model_T_needle[:3, :3] @ needle.tip_m + fit.model_T_needle[:3, 3], fit.tip_m,
                               atol=TOL_M)


@pytest.mark.parametrize("seed", range(5))
def test_fit_any_plane_offset_and_arc(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = homogeneous(so3_exp(rng.normal(size=3) * 2.0), rng.uniform(-20e-3, 20e-3, 3))
    arc = float(rng.uniform(0.4, 1.6) * math.pi)  # up to 288 degrees: the gap can be smaller than the wire
    verts, _, truth = tube_mesh(radius_mm=float(rng.uniform(2.0, 12.0)), arc_rad=arc, rings=200,
                                model_T_needle=T)
    fit = fit_needle_mesh(verts * 1e-3)
    assert_fit_matches(fit, truth, truth.model_T_needle)


def test_units_metres(tmp_path: Path) -> None:
    verts, faces, truth = tube_mesh()
    path = write_ply(tmp_path / "m.ply", verts * 1e-3, faces)
    fit = fit_needle_mesh(read_ply_vertices(path, "m"))
    assert fit.radius_m == pytest.approx(truth.radius_m, rel=1e-6)
    with pytest.raises(InputError, match="unknown model units"):
        read_ply_vertices(path, "inch")


def test_tip_end_names_the_tip_of_an_untapered_wire() -> None:
    verts, _, truth = tube_mesh(taper=0.0)
    V = verts * 1e-3
    with pytest.raises(InputError, match="cannot tell the tip from the tail.*--tip-end"):
        fit_needle_mesh(V)
    T = truth.model_T_needle
    tail = T[:3, :3] @ truth.needle.tail_m + T[:3, 3]
    tip = T[:3, :3] @ truth.needle.point(truth.arc_rad) + T[:3, 3]
    i = int(np.argmax(np.abs(tip - tail)))
    toward_tip = ("+" if tip[i] > tail[i] else "-") + "xyz"[i]
    toward_tail = ("-" if toward_tip[0] == "+" else "+") + "xyz"[i]
    fit = fit_needle_mesh(V, tip_end=toward_tip)
    assert fit.tip_from == "tip_end"
    assert_fit_matches(fit, truth, T)
    # the other end as the tip: the needle frame turned by pi about the in-plane axis at arc/2
    half = truth.arc_rad / 2
    flip = homogeneous(so3_exp(math.pi * np.array([math.cos(half), math.sin(half), 0.0])), np.zeros(3))
    T_rev = T @ flip
    fit_rev = fit_needle_mesh(V, tip_end=toward_tail)
    assert_fit_matches(fit_rev, truth, T_rev)


def test_tip_end_contradicting_the_taper_is_an_error() -> None:
    verts, _, truth = tube_mesh()
    T = truth.model_T_needle
    tail = T[:3, :3] @ truth.needle.tail_m + T[:3, 3]
    tip = T[:3, :3] @ truth.needle.point(truth.arc_rad) + T[:3, 3]
    i = int(np.argmax(np.abs(tip - tail)))
    toward_tail = ("-" if tip[i] > tail[i] else "+") + "xyz"[i]
    with pytest.raises(InputError, match="names the blunt end"):
        fit_needle_mesh(verts * 1e-3, tip_end=toward_tail)
    with pytest.raises(InputError, match="not one of"):
        fit_needle_mesh(verts * 1e-3, tip_end="up")


def _cube(n: int = 6) -> np.ndarray:
    g = np.linspace(-5.0, 5.0, n)
    pts = set()
    for a in g:
        for b in g:
            for c in (-5.0, 5.0):
                pts |= {(a, b, c), (a, c, b), (c, a, b)}
    return np.array(sorted(pts))


def _torus() -> np.ndarray:
    theta = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    phi = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    th, ph = np.meshgrid(theta, phi)
    r, w = 4.5, 0.2
    return np.stack([(r + w * np.cos(ph)) * np.cos(th), (r + w * np.cos(ph)) * np.sin(th), w * np.sin(ph)],
                    axis=-1).reshape(-1, 3)


def _plate() -> np.ndarray:
    g = np.linspace(-5.0, 5.0, 20)
    a, b = np.meshgrid(g, g)
    return np.stack([a.ravel(), b.ravel(), np.zeros(a.size)], axis=1)


@pytest.mark.parametrize(("shape", "message"), [
    (_cube, "not a thin wire around a circle"),
    (_plate, "not a thin wire around a circle"),
    (_torus, "all around the circle"),
    (lambda: _cube(2), "only 8 distinct vertices"),
])
def test_not_a_needle_is_rejected(tmp_path: Path, shape, message: str) -> None:
    path = write_ply(tmp_path / "shape.ply", shape())
    with pytest.raises(InputError, match=message) as info:
        fit_needle_mesh(read_ply_vertices(path), source=path)
    assert str(path) in str(info.value)


def test_malformed_ply_files(tmp_path: Path) -> None:
    verts, faces, _ = tube_mesh()
    good = write_ply(tmp_path / "good.ply", verts, faces).read_bytes()
    cases = {
        "garbage.ply": (b"hello world\n", "not a readable PLY file"),
        "truncated.ply": (good[: len(good) // 2], "not a readable PLY file"),
        "novertex.ply": (b"ply\nformat ascii 1.0\nelement point 1\nproperty float x\nend_header\n1\n",
                         "no 'vertex' element"),
        "noz.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
                    "no z property"),
        "nan.ply": (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n1 2 3\nnan 2 3\n", "vertex 1 has a NaN"),
    }
    for name, (data, message) in cases.items():
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(InputError, match=message) as info:
            read_ply_vertices(p)
        assert str(p) in str(info.value)
    with pytest.raises(InputError, match="file not found"):
        read_ply_vertices(tmp_path / "missing.ply")
